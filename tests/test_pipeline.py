"""The fused per-ping pipeline, its configuration, and the `ranges` / `segment` commands."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.pipeline import PipelineConfig, process_ping



@pytest.fixture(scope="module")
def products(test_pings):
    return [process_ping(p, keep_labels=True) for p in test_pings]


def test_config_validation_names_key(tmp_path):
    with pytest.raises(InputError, match="unknown key 'betta'"):
        PipelineConfig.from_dict({"betta": 1.0})
    with pytest.raises(InputError, match="beta"):
        PipelineConfig().replace(beta=-1.0)
    with pytest.raises(InputError, match="method"):
        PipelineConfig().replace(method="magic")
    with pytest.raises(InputError, match="neighbourhood"):
        PipelineConfig().replace(neighbourhood=6)
    with pytest.raises(InputError, match="cfar_train"):
        PipelineConfig().replace(cfar_train=41)
    cfg = PipelineConfig().replace(method="cfar-os", beta=0.5, families=["exponential", "rayleigh", "rayleigh"])
    assert PipelineConfig.from_dict(cfg.to_dict()) == cfg
    toml = tmp_path / "p.toml"
    toml.write_text('[pipeline]\nmethod = "map"\nmin_run = 3\n')
    assert PipelineConfig.from_toml(toml) == PipelineConfig().replace(method="map", min_run=3)
    toml.write_text('[pipeline]\nmin_run = "x"\n')
    with pytest.raises(InputError, match="min_run"):
        PipelineConfig.from_toml(toml)


def test_fish_only_pings_report_nothing(products):
    # paper images 1-3 contain fish schools only
    for prod in products[1:4]:
        assert prod.ranges.n_returns == 0, prod.source


def test_hull_pings_report_the_hull(products):
    # image 8: flat hull at rows ~183-200 across the whole fan
    r8 = products[8].ranges
    assert r8.n_returns >= 80
    assert np.all((r8.bin[r8.valid] >= 175) & (r8.bin[r8.valid] <= 205))
    # image 4: a curved hull from row ~277 (beam 0) to ~350 (beam 88); range grows with beam
    r4 = products[4].ranges
    assert r4.n_returns >= 80
    b = r4.bin[r4.valid]
    assert 270 <= b[0] <= 285 and 335 <= b[-1] <= 360
    assert np.all(np.diff(b) >= -3)
    # ranges in metres from the geometry's bins
    g = products[4].ranges
    # range_m is the sub-bin leading edge; bin is the bin whose centre is nearest to it
    assert np.all(np.abs(g.range_m[g.valid] - (2.25 + g.bin[g.valid] * 9.0 / 512)) <= 0.5 * 9.0 / 512 + 1e-9)


def test_pipeline_is_pure(test_pings):
    a = process_ping(test_pings[7], keep_labels=True)
    b = process_ping(test_pings[7], keep_labels=True)
    np.testing.assert_array_equal(a.ranges.bin, b.ranges.bin)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert a.flags == b.flags and a.kld == b.kld


@pytest.mark.parametrize("value", [0.0, 0.5])
def test_constant_pings_give_no_returns(test_pings, value):
    p = test_pings[0].replace(image=np.full(test_pings[0].shape, value, np.float32))
    for method in ("mrf", "map", "threshold", "cfar-so"):
        prod = process_ping(p, PipelineConfig().replace(method=method))
        assert prod.ranges.n_returns == 0
        assert "no_returns" in prod.flags


def test_other_methods_and_solvers_run(test_pings):
    """Ping 8 by ICM: the returns of the graph cut's beams, but the band lit across the fan at rows
    181-189 stays in the image the edges are measured on (ICM's stray labels leave too few
    water-column beams for the crosstalk estimate), and on the curved hull's beams beyond its flat
    part the pooled edges slide onto it (up to 7 bins): 72 % within 3 bins of the graph cut's
    returns; with ``edge_pool_lead_bins = 2`` they stay on the hull's front (all within 3 bins)."""
    p = test_pings[8]
    ref = process_ping(p, PipelineConfig()).ranges
    for lead, share in ((12, 0.65), (2, 0.95)):  # measured 0.719, 1.000
        icm = process_ping(p, PipelineConfig().replace(solver="icm", edge_pool_lead_bins=lead)).ranges
        both = ref.valid & icm.valid
        assert both.sum() >= 90
        assert np.mean(np.abs(icm.bin[both] - ref.bin[both]) <= 3) > share
    for m in ("map", "threshold", "cfar-ca", "cfar-go", "cfar-os"):
        prod = process_ping(p, PipelineConfig().replace(method=m))
        assert prod.ranges.n_beams == 96


def _rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as fh:
        return list(csv.reader(fh))


def test_ranges_cli_960_rows(tmp_path, test_ping_paths):
    from sonarmap.cli import main

    out = tmp_path / "ranges.csv"
    assert main(["ranges", str(test_ping_paths[0].parent), "-o", str(out)]) == 0
    rows = _rows(out)
    assert rows[0] == ["ping", "beam", "azimuth_rad", "bin", "range_m", "intensity", "flags", "sigma_m", "p_detect",
                       "time", "time_ns"]
    # every return has a finite sigma; beams without one have empty cells
    ret = [r for r in rows[1:] if r[4]]
    assert ret and all(float(r[7]) > 0 for r in ret)
    assert all(r[7] == "" for r in rows[1:] if not r[4])
    assert len(rows) == 961
    pings = {r[0] for r in rows[1:]}
    assert pings == {str(p) for p in test_ping_paths}
    for r in rows[1:]:
        assert (r[3] == "") == (r[4] == "")
        if r[3]:
            # the sub-bin leading edge lies within half a bin of its bin's centre
            assert abs(float(r[4]) - (2.25 + int(r[3]) * 9.0 / 512)) <= 0.5 * 9.0 / 512 + 1e-5
    fish = [r for r in rows[1:] if r[0] == str(test_ping_paths[1])]
    assert len(fish) == 96 and all(r[3] == "" for r in fish)


def test_ranges_cli_zero_and_constant_pings(tmp_path, test_pings):
    from sonarmap.cli import main
    from sonarmap.io.pngjson import write_png_ping

    p = test_pings[0]
    write_png_ping(p.replace(image=np.zeros(p.shape, np.float32)), tmp_path, stem="1468966347175925")
    write_png_ping(p.replace(image=np.full(p.shape, 0.4, np.float32)), tmp_path, stem="1468966347175926")
    out = tmp_path / "r.csv"
    for method in (None, "cfar-os", "threshold"):
        args = ["ranges", str(tmp_path), "-o", str(out)] + ([] if method is None else ["--method", method])
        assert main(args) == 0
        rows = _rows(out)[1:]
        assert len(rows) == 192 and all(r[3] == "" and r[4] == "" for r in rows)
    assert main(["ranges", str(tmp_path), "-o", str(out), "--method", "nope"]) == 2  # usage error


@pytest.mark.slow  # over a second in the fast subset
def test_segment_cli_writes_labels_and_figure(tmp_path, test_ping_paths):
    from PIL import Image

    from sonarmap.cli import main

    assert main(["segment", str(test_ping_paths[8]), "-o", str(tmp_path)]) == 0
    stem = test_ping_paths[8].name.replace("_raw.png", "")
    lab = np.asarray(Image.open(tmp_path / f"{stem}_labels.png"))
    assert lab.shape == (512, 96) and set(np.unique(lab)) <= {0, 127, 254}
    assert (lab[175:205] > 0).sum() > 100
    assert (tmp_path / f"{stem}_segment.png").stat().st_size > 10_000


def test_band_pooling_recovers_speckled_survey_band():
    """A thin single-look-speckle band that the per-pixel route leaves in fragments (0-5 labelled
    pixels per beam, every component dropped) is found by band pooling, near the true range."""
    from sonarmap.simulate.survey import simulate_survey
    from sonarmap.pipeline import PipelineConfig, pooled_band_pixels, process_ping

    from sonarmap.simulate import SimulationConfig

    # the stated DIDSON PSF with independent speckle per beam: a diffuse, fragmented band
    s = simulate_survey(n_pings=3, seed=1, kind="hull", sim_config=SimulationConfig(ghosts="incoherent"))
    p = s.pings[2]
    assert process_ping(p, PipelineConfig().replace(pool_factor=0.0)).ranges.n_returns == 0
    r = process_ping(p, PipelineConfig().replace(pool_factor=6.0, pool_beams=4, pool_mode="fallback")).ranges
    assert r.n_returns >= 40
    truth = s.sim_truth[2].first_return_bin
    err = np.abs(r.bin[r.valid] - truth[r.valid])
    assert np.median(err) <= 3
    # one pixel per beam of each wide band; nothing on pure background
    acc = pooled_band_pixels(np.zeros((64, 48), np.float32), 0.1)
    assert acc is None
    img = np.zeros((64, 48), np.float32)
    img[30, :] = 1.0
    acc = pooled_band_pixels(img, 0.05, min_beams=40)
    assert acc is not None and (acc.sum(axis=0) == 1).all() and acc[30].all()


def test_pool_config_validation():
    from sonarmap.errors import InputError
    from sonarmap.pipeline import PipelineConfig

    for bad in (dict(pool_factor=-1.0), dict(pool_beams=-1), dict(pool_bins=0), dict(pool_min_beams=0),
                dict(pool_link_beams=-1)):
        with pytest.raises(InputError):
            PipelineConfig().replace(**bad)
    assert PipelineConfig.from_dict(PipelineConfig().to_dict()) == PipelineConfig()


@pytest.mark.slow
def test_pool_fill_only_adds_returns_on_empty_beams():
    """pool_mode="fill": pooled band pixels are added only on beams the per-pixel route left
    empty; its own returns are unchanged."""
    from sonarmap.simulate.survey import simulate_survey
    from sonarmap.pipeline import PipelineConfig, process_ping

    s = simulate_survey(n_pings=6, seed=3, kind="seafloor")
    added = 0
    for p in s.pings:
        a = process_ping(p, PipelineConfig().replace(pool_factor=0.0, tracker="rules")).ranges
        b = process_ping(p, PipelineConfig().replace(tracker="rules")).ranges
        assert np.array_equal(b.bin[a.valid], a.bin[a.valid])
        added += int(b.n_returns - a.n_returns)
    assert added > 0
    with pytest.raises(Exception, match="pool_mode"):
        PipelineConfig().replace(pool_mode="always")


def test_component_pixel_rule_keeps_compact_targets_drops_fish_sized_blobs():
    from sonarmap.geometry import preset
    from sonarmap.ranges import extract_ranges

    g = preset("didson-hf")
    lab = np.zeros(g.shape, dtype=bool)
    lab[100:105, 10:22] = True       # a blade seen edge-on: 12 beams x 5 bins = 60 pixels
    lab[300:304, 60:66] = True       # a fish: 6 beams x 4 bins = 24 pixels
    img = lab.astype(np.float32)
    kw = dict(min_component_beams=16, min_component_bins=16, reject_isolated=False)
    r0 = extract_ranges(lab, img, g, **kw)
    assert r0.n_returns == 0
    r = extract_ranges(lab, img, g, min_component_pixels=40, **kw)
    assert r.n_returns == 12 and (r.bin[10:22] == 100).all() and (r.bin[60:66] == -1).all()


@pytest.mark.slow  # ~4.5 s: the simulator samples the hull over the Oculus fan
def test_a_small_window_is_modelled_not_refused_by_the_kld_gate():
    """A 64 x 16 ping of a hull: a correct model's KLD there is ~0.14 (sampling), which a fixed
    0.05 limit refused (no returns, flag ``kld``); the gate allows for the sample size."""
    from sonarmap import preset
    from sonarmap.simulate import scene_from_name, simulate_ping

    g = preset("oculus-m750d-like")
    g = g.replace(range_m=np.linspace(float(g.range_m[0]), float(g.range_m[-1]), 64),
                  azimuth_rad=np.linspace(float(g.azimuth_rad[0]), float(g.azimuth_rad[-1]), 16),
                  psf=None, taper=None, psf_raw=None)
    sim = simulate_ping(scene_from_name("hull", geometry=g), g, seed=0)
    prod = process_ping(sim.ping, PipelineConfig())
    assert prod.kld > 0.05 and "kld" not in prod.flags
    err = (prod.ranges.range_m - sim.surface_range_m) / abs(g.range_resolution_m)
    assert np.all(np.abs(err[np.isfinite(sim.surface_range_m)]) <= 3)
