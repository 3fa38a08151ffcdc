"""One default configuration on every real recording, and fit gates that refuse garbage.

Real ARIS, Oculus and DIDSON pings go through the default :func:`process_ping`; degenerate pings
(pure noise, binary, constant) must give no returns and a flag.
"""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.ping import Ping
from sonarmap.pipeline import PipelineConfig, process_ping
from sonarmap.preprocess.normalise import BACKGROUND_MEAN, estimate_background
from sonarmap.stats.gates import GATE_DESCRIPTIONS, IMPLAUSIBLE, REFUSING, class_separation, fit_gates
from sonarmap.stats.mixture import fit_mixture

#: The per-ping fit as it was before it was converged: plain EM stopped at a 1e-6 relative gain.
_STOPPED_EARLY = {"fit_accelerate": False, "fit_tol": 1e-6}





# --------------------------------------------------------------------------- normalisation


def test_normalisation_applies_to_aris_and_not_to_thresholded_didson(aris_pings, test_pings):
    bg, u = estimate_background(aris_pings[0].image)
    assert bg.applied and bg.reason == "estimated" and u is not None
    assert u.dtype == np.float32 and u.shape == aris_pings[0].image.shape
    assert 0.0 <= float(u.min()) and float(u.max()) <= 1.0
    # the lower-quartile level falls with range (~3x over the window: 3.8-3.9 dB between deciles)
    assert 3.0 < bg.range_dependence_db < 5.0
    assert bg.level_by_bin[:100].mean() > 1.5 * bg.level_by_bin[-100:].mean()
    # most pixels under the emulated receiver threshold (the background's 0.9 quantile for an
    # exponential tail; ARIS's log-compressed background has a lighter tail): a zero spike
    assert 0.75 <= np.mean(u == 0) <= 0.92
    assert float(u[u > 0].mean()) == pytest.approx(BACKGROUND_MEAN, rel=0.4)
    for p in test_pings:
        bg, u = estimate_background(p.image)
        assert not bg.applied and bg.reason == "thresholded" and u is None
        assert bg.zero_fraction > 0.4


def test_normalisation_bad_input():
    from sonarmap.errors import InputError

    with pytest.raises(InputError, match="NaN"):
        estimate_background(np.full((8, 8), np.nan, np.float32))
    with pytest.raises(InputError, match="shape"):
        estimate_background(np.zeros(5, np.float32))
    with pytest.raises(InputError, match="floor_quantile"):
        estimate_background(np.ones((8, 8), np.float32), floor_quantile=1.0)
    # a binary 0/1 image is "thresholded" (half zeros), a sparse one degenerate
    img = np.zeros((64, 16), np.float32)
    img[::2, ::2] = 1.0
    assert estimate_background(img)[0].reason == "thresholded"
    sparse = np.full((64, 16), 0.5, np.float32)
    sparse[:, :12] = 0.0
    bg, u = estimate_background(sparse, thresholded_fraction=0.9)
    assert bg.reason == "degenerate" and u is None


# --------------------------------------------------------------------------- real recordings


def test_real_aris_returns_on_the_target_and_none_in_the_water_column(aris_pings):
    """The slanted line at ~15.7-17.3 m: every frame has returns on it and none in front of it
    (before this normalisation every beam of every frame reported the first range bin)."""
    for p in aris_pings:
        prod = process_ping(p)
        assert not prod.gates and prod.background.applied
        r = prod.ranges
        rm = r.range_m[r.valid]
        assert r.n_returns >= 20, p.source
        # nothing in the water column (3.3-15.4 m): the target's nearest leading edge lies at
        # ~15.4 m (frame 0 beams 37-39; 15.40 m combined along the surface), so more than 5 bins
        assert rm.min() > 15.35, p.source
        on_target = (rm >= 15.4) & (rm <= 17.6)
        assert on_target.sum() >= 28, p.source  # measured 39-42 of 48
        # the target runs from beam 0 (17.2 m) to beam ~42 (15.5 m)
        assert np.all(np.nonzero(r.valid)[0][on_target] <= 44)


def test_real_aris_faint_end_of_the_target_is_followed(aris_pings):
    """In frame 0 the target's near end (beams 28-39, 15.4-16.0 m) is too faint for the
    classifier's components, and the returns there lie on the lines behind it (21.8-21.9 m); the
    surface continuation and the front pass follow the target there (measured 9 of those 12 beams:
    on beams 37-39 its echo steps 20 bins towards the sonar, and beam 39 has none; 0 without
    either, with the plain-EM fit stopped at a 1e-6 relative gain, the default until the fit was
    converged); frames 1-5: 12 of 12."""
    for k, p in enumerate(aris_pings):
        near_end = process_ping(p).ranges.range_m[28:40]
        assert np.count_nonzero((near_end > 15.3) & (near_end < 16.0)) >= (9 if k == 0 else 11), (k, near_end)
    neither = PipelineConfig().replace(continue_evidence=0, track={"front_pass": False}, fit=_STOPPED_EARLY)
    near_end = process_ping(aris_pings[0], neither).ranges.range_m[28:40]
    assert np.count_nonzero((near_end > 15.3) & (near_end < 16.0)) <= 1


def test_real_aris_target_does_not_depend_on_where_the_fit_stopped(aris_pings):
    """With SQUAREM-accelerated fits stopped at a 1e-6 relative gain (higher likelihood than plain
    EM stopped there, slightly different posteriors) the tracker's passes gave the target's near
    end (beams 28-39) of frame 5 to a line behind it (4 of 12 beams on the target; no longer, see
    the end of this test); the front pass
    reports the target there with plain EM, SQUAREM and the converged default fit alike (measured
    12 of 12 in frames 1-5, 9 of 12 in frame 0, whose faint end the previous test describes -
    with plain EM stopped early 6 of 12 there: beams 34-39 go to the line behind, since the beam
    factor's block rows are median filtered along range)."""
    accel = PipelineConfig().replace(fit={"fit_accelerate": True, "fit_tol": 1e-6})
    plain = PipelineConfig().replace(fit=_STOPPED_EARLY)
    for k, p in enumerate(aris_pings):
        for cfg in (PipelineConfig(), accel, plain):
            near_end = process_ping(p, cfg).ranges.range_m[28:40]
            least = 10 if k else (6 if cfg is plain else 9)
            assert np.count_nonzero((near_end > 15.3) & (near_end < 16.0)) >= least, (k, cfg.fit)
    # without the front pass the SQUAREM fit's frame 5 gave 4 of 12 before the beam factor's block
    # rows were median filtered; now the passes alone keep the target there (12 of 12)
    off = accel.replace(track={"front_pass": False})
    near_end = process_ping(aris_pings[5], off).ranges.range_m[28:40]
    assert np.count_nonzero((near_end > 15.3) & (near_end < 16.0)) >= 10


def test_real_aris_target_is_bridged_where_a_line_behind_took_beams(aris_pings):
    """In frame 3 the line behind the target (21.8 m) wins beams 31-33 in the tracker's first
    pass; the target's echoes there (15.67-15.70 m) are left over until the bridge gives them back
    (TrackConfig.bridge_beams); without it those beams report the line."""
    p = aris_pings[3]
    bridged = process_ping(p).ranges.range_m[31:34]
    assert np.all((bridged > 15.5) & (bridged < 15.9)), bridged
    # (the front pass, which pays a surface's costs, recovers them too: both off here, and the
    # surface significance test, which drops the line there - its water column holds the target)
    neither = PipelineConfig().replace(track={"bridge_beams": 0, "front_pass": False}, surface_min_z=0.0)
    plain = process_ping(p, neither).ranges.range_m[31:34]
    assert np.all(plain > 17.0), plain
    tested = process_ping(p, neither.replace(surface_min_z=3.5)).ranges.range_m[31:34]
    assert np.all(np.isnan(tested)), tested


def test_real_aris_split_band_reports_the_nearer_band(aris_pings):
    """Where the target's band splits in two (frame 1 beams 26-27, frame 5 beams 27-29) the lines
    behind take the passes, the upper band's faint tail (15.91-15.99 m) is tracked and the lower
    band's start in front of it (15.70-15.82 m) is left over: too short to pay for a piece in
    the front pass, and not a bridge (the lower band does not come back on the other side).  The
    end extension (TrackConfig.extend_beams) continues the lower band from where its surface ends
    over those beams; without it they report the upper band's tail."""
    for k, beams in ((1, slice(26, 28)), (5, slice(27, 30))):
        r = process_ping(aris_pings[k]).ranges.range_m[beams]
        assert np.all((r > 15.6) & (r < 15.81)), (k, r)
        off = process_ping(aris_pings[k], PipelineConfig().replace(track={"extend_beams": 0})).ranges.range_m[beams]
        assert np.all(off > 15.88), (k, off)


def test_real_oculus_seabed_and_nothing_in_front(oculus_pings):
    """The returns lie on the seabed's front on every beam, nothing in front of it (before: ring-down
    returns at bin 0 on every beam; then faint arcs 5-19 cm in front of the seabed on ~170 of the
    256 beams, where the beam-factor grid halved the water column's background).  The front is
    found here without the pipeline: per beam, the first range where the 21-bin x 5-beam mean
    reaches half the beam's median level in the bright band at 0.85-1.15 m (a smoothed front, so
    it lies a few bins in front of the leading edge)."""
    from scipy.ndimage import uniform_filter

    for p in oculus_pings:
        prod = process_ping(p)
        r = prod.ranges
        assert not prod.gates
        assert r.n_returns >= 0.9 * r.n_beams, p.source  # measured 256 of 256
        img = uniform_filter(p.image.astype(np.float64), (21, 5), mode="nearest")
        rm = p.geometry.range_m
        band = (rm >= 0.85) & (rm <= 1.15)
        level = np.median(img[band], axis=0)
        front = rm[np.argmax(img >= 0.5 * level[None, :], axis=0)]
        ahead = (front - r.range_m[r.valid]) / p.geometry.range_resolution_m
        # measured: 8-10 of 256 more than 10 bins (2.8 cm) in front, none before 0.68 m
        assert np.sum(ahead > 10) <= 0.05 * r.n_beams, (p.source, np.sum(ahead > 10))
        assert r.range_m[r.valid].min() >= 0.68, p.source
        assert r.range_m[r.valid].max() <= 1.05, p.source


def test_real_didson_fish_only_pings_keep_no_returns(test_pings):
    counts = [process_ping(p).ranges.n_returns for p in test_pings]
    assert counts[1:4] == [0, 0, 0]
    assert counts[4] == 96 and counts[8] == 96  # hull pings: every beam
    for p in test_pings:
        assert not process_ping(p).gates


def test_real_didson_extra_images(didson_dir):
    """The two extra DIDSON images (no sidecar JSON: geometry given).  ``tuna_can.png`` (1 % zeros:
    normalised like ARIS) looks at a tank floor: a flat floor below the sonar is first seen through
    the lower edge of the vertical beam at the same range on every beam, so its leading edge is a
    row across the fan (rows 325-327, about 7.95 m; the brighter arc behind it, 330-350, curves with
    azimuth).  Every beam but 60-63 reports a return, on the floor's edge or, on the beams right of
    65, on a fainter echo in front of it at rows 178-189 (5.4-5.5 m, 0.4-1.3 m to starboard; 2-3.6x
    the rows in front of it there, 1.1-1.9x on the beams left of it) - nothing in the water column
    elsewhere.  On beams 60-63 the first surface is a piece of that echo (row 183) that does not
    stand out from its water column: the significance test drops it and the beams report none
    (before the beam factor's block rows were median filtered, beams 60-61 reported the floor at
    rows 330-332 and 62-63 the piece).  ``frame_2014.bmp`` (an older palettised
    frame, range window unknown) has 19 % zeros and row lower quartiles of 1-2 of 255 levels: too
    coarse to normalise ("quantised"), and on the deconvolved image the object class collapses
    onto the background's - no returns, and the ping says why (never silent)."""
    from sonarmap.io import read_ping

    tuna = read_ping(didson_dir / "extra" / "tuna_can.png", geometry=didson_dir / "didson.json")
    prod = process_ping(tuna)
    r = prod.ranges
    assert not prod.gates and prod.background.applied
    assert r.n_returns >= r.n_beams - 4  # measured 92 of 96
    rows = (r.range_m - tuna.geometry.range_m[0]) / tuna.geometry.range_resolution_m
    on_floor = (rows >= 322) & (rows <= 334)
    on_line = (rows >= 176) & (rows <= 192)
    assert np.all((on_floor | on_line)[r.valid]), np.round(rows[r.valid & ~(on_floor | on_line)])
    assert on_floor[:56].all()  # measured: beams 0-59, 64 and 65 on the floor
    assert np.flatnonzero(on_line).min() >= 56
    old = read_ping(didson_dir / "extra" / "frame_2014.bmp", geometry="didson-hf")
    prod = process_ping(old)
    assert prod.background.reason == "quantised"
    assert prod.ranges.n_returns == 0 and "collapsed" in prod.gates


# --------------------------------------------------------------------------- degenerate pings


def _degenerate(rng: np.random.Generator) -> dict[str, np.ndarray]:
    shape = (512, 96)
    return {
        "rayleigh": rng.rayleigh(0.05, shape),
        "exponential": rng.exponential(0.05, shape),
        "gamma": rng.gamma(3.0, 0.03, shape),
        "uniform": rng.uniform(0.0, 1.0, shape),
        "checkerboard": (np.indices(shape).sum(0) % 2).astype(float),
        "constant100": np.full(shape, 100 / 255),
        "constant100_noisy": np.full(shape, 100 / 255) + rng.normal(0, 0.5 / 255, shape),
        "zero": np.zeros(shape),
    }


@pytest.mark.parametrize("preprocess", ["paper-table1", "none"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_degenerate_pings_give_no_returns_and_a_flag(test_pings, preprocess, seed):
    geom = test_pings[0].geometry
    cfg = PipelineConfig(preprocess=preprocess)
    for name, img in _degenerate(np.random.default_rng(seed)).items():
        prod = process_ping(Ping(image=np.clip(img, 0, 1).astype(np.float32), geometry=geom), cfg)
        assert prod.ranges.n_returns == 0, name
        assert "no_returns" in prod.flags, name
    # the binary image is refused by name, not just empty
    chk = _degenerate(np.random.default_rng(seed))["checkerboard"].astype(np.float32)
    prod = process_ping(Ping(image=chk, geometry=geom), cfg)
    assert prod.gates or {"degenerate", "constant_image"} & set(prod.flags)


def test_default_gates_on_an_unnormalised_aris_frame_refuse_it(aris_pings):
    """Without normalisation the ARIS frames are the old failure (object weight 1.0, a bin-0
    return on every beam); the gates now refuse them by name."""
    prod = process_ping(aris_pings[0], PipelineConfig(normalise="off"))
    assert prod.ranges.n_returns == 0
    assert prod.gates and set(prod.gates) <= REFUSING and {"kld", "object_weight"} <= set(prod.gates)
    assert prod.flagged


# --------------------------------------------------------------------------- gates


def test_fit_gates_named_reasons():
    rng = np.random.default_rng(0)
    # spike + exponential + a clearly separate Rayleigh object: plausible
    y = np.concatenate([np.zeros(6000), rng.exponential(0.02, 3500), rng.rayleigh(0.2, 500)])
    fit = fit_mixture(np.clip(y, 0, 1).reshape(100, 100).astype(np.float32), method="em")
    assert fit_gates(fit) == frozenset()
    assert class_separation(fit) > 5
    # an object component no brighter than 1.9x the background is a reshaped background
    assert "collapsed" in fit_gates(fit, min_separation=class_separation(fit) + 0.1)
    # most pixels "object": the background model does not hold
    y = np.concatenate([np.zeros(1000), rng.exponential(0.02, 1000), rng.rayleigh(0.3, 8000)])
    fit = fit_mixture(np.clip(y, 0, 1).reshape(100, 100).astype(np.float32), method="em")
    assert "object_weight" in fit_gates(fit)
    assert "kld" in fit_gates(fit, max_kld=0.0)
    assert set(GATE_DESCRIPTIONS) == REFUSING and IMPLAUSIBLE == REFUSING - {"collapsed"}
    from sonarmap.errors import InputError

    with pytest.raises(InputError, match="MixtureFit"):
        fit_gates("nope")  # type: ignore[arg-type]


def test_ranges_cli_flags_column_summary_and_strict(tmp_path, test_pings, capsys):
    from sonarmap.cli import main
    from sonarmap.io.pngjson import write_png_ping

    p = test_pings[0]
    chk = (np.indices(p.shape).sum(0) % 2).astype(np.float32)
    write_png_ping(p.replace(image=chk), tmp_path, stem="1468966347175925")
    write_png_ping(test_pings[4], tmp_path, stem="1468966347175926")
    out = tmp_path / "r.csv"
    assert main(["ranges", str(tmp_path), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "1 of 2 pings flagged:" in err
    import csv

    rows = list(csv.DictReader(open(out, newline="")))
    flagged = {r["ping"]: r["flags"] for r in rows}
    assert sum(1 for v in flagged.values() if v) == 1
    assert main(["ranges", str(tmp_path), "-o", str(tmp_path / "s.csv"), "--strict"]) == 1


def test_drop_small_components_matches_a_per_component_reference(test_pings):
    """The metric extent rule: a component survives iff its far-edge arc length (one beam spacing
    included) or its range extent reaches the limit (random masks against a per-component loop)."""
    from extent_reference import extent_reference

    from sonarmap.ranges import drop_small_components

    g = test_pings[0].geometry
    rng = np.random.default_rng(0)
    for _ in range(20):
        m = rng.random(g.shape) < rng.uniform(0.001, 0.05)
        for e in (0.02, 0.1, 0.3):
            np.testing.assert_array_equal(drop_small_components(m, g, e), extent_reference(m, g, e))
    assert not drop_small_components(np.zeros(g.shape, bool), g, 0.1).any()


@pytest.mark.parametrize("shape,pool", [((2000, 48), (5, 3)), ((7, 2), (5, 3)), ((703, 256), (5, 3)),
                                        ((10, 10), (1, 1)), ((6, 4), (4, 2))])
def test_pooled_ratio_kernel_is_scipys_uniform_filter(shape, pool):
    from scipy.ndimage import uniform_filter

    from sonarmap.preprocess._kernels import pooled_ratio

    rng = np.random.default_rng(0)
    img = rng.random(shape).astype(np.float32) + 0.1
    level = (rng.random(shape[0]) + 0.5).astype(np.float32)
    factor = (rng.random(shape) + 0.5).astype(np.float32)
    np.testing.assert_allclose(pooled_ratio(img, level, factor, *pool),
                               uniform_filter(img / level[:, None] / factor, pool, mode="nearest"), atol=1e-6)


@pytest.mark.slow
def test_process_strict_and_flag_summary(tmp_path, test_pings, capsys):
    from sonarmap.cli import main
    from sonarmap.io.pngjson import write_png_ping

    src = tmp_path / "in"
    chk = (np.indices(test_pings[0].shape).sum(0) % 2).astype(np.float32)
    write_png_ping(test_pings[0].replace(image=chk), src, stem="1468966347175925")
    write_png_ping(test_pings[4], src, stem="1468966347175926")
    assert main(["process", str(src), "-o", str(tmp_path / "s.zarr"), "--workers", "1"]) == 0
    cap = capsys.readouterr()
    assert "1 of 2 pings flagged: " in cap.out + cap.err
    assert main(["process", str(src), "-o", str(tmp_path / "s.zarr"), "--workers", "1", "--strict"]) == 1
    import zarr

    flags = [str(f) for f in zarr.open_group(str(tmp_path / "s.zarr"), mode="r")["flags"][:]]
    assert sum("kld" in f.split() or "collapsed" in f.split() for f in flags) == 1


def test_half_peak_edges_on_a_synthetic_echo(test_pings):
    """A beam whose echo rises linearly from bin 100 to a peak of 1.0 at bin 110: the leading
    edge at half the peak is bin 105 (range interpolated), whatever labelled bin it starts from."""
    from sonarmap.ranges import BeamRanges, half_peak_edges

    g = test_pings[0].geometry
    img = np.zeros(g.shape, np.float32)
    img[100:111, 3] = np.linspace(0.0, 1.0, 11)
    img[111:130, 3] = 0.8
    mask = img > 0
    n = g.shape[1]
    b = np.full(n, -1)
    b[3] = 101
    r = np.full(n, np.nan)
    r[3] = g.range_m[101]
    rr = BeamRanges(range_m=r, bin=b, intensity=np.zeros(n, np.float32), confidence=np.zeros(n, np.float32),
                    azimuth_rad=g.azimuth_rad)
    out = half_peak_edges(rr, img, mask, g)
    assert out.bin[3] == 105
    assert out.range_m[3] == pytest.approx(g.range_m[105], abs=1e-9)
    assert np.all(out.bin[np.arange(n) != 3] == -1)
    img[105, 3] = 0.45  # the crossing falls between bins 105 and 106 -> interpolated range
    out = half_peak_edges(rr, img, mask, g)
    assert out.bin[3] == 106 and g.range_m[105] < out.range_m[3] < g.range_m[106]


@pytest.mark.slow
def test_every_preset_same_default_no_false_returns_and_surfaces_found():
    """The every-sonar table (docs/segmentation.md), on a subset that runs in ~20 s: no preset
    reports returns on empty beams above 5 %, the propeller is found on the ARIS presets (recall
    against its first 6 dB bin 1.00) and the hull is measured there within 3 bins of its surface
    (headers declared, as every .aris file has them: 0.98-1.00).  The hull's clipped echo is
    measured by the Gaussian fit to its flanks, 3-4 bins behind its first 6 dB bin: that view
    scores it 0.71 / 0.17."""
    from sonarmap.evaluate import evaluate_presets, evaluate_ranges

    rows = {r.method: r for r in evaluate_presets(presets=("didson-hf", "aris3000-128", "aris-telephoto-48"),
                                                  scenes=("propeller", "fish", "empty"), seeds=(0, 1))}
    for name in ("didson-hf", "aris3000-128", "aris-telephoto-48"):
        assert rows[name].false_return_rate <= 0.05, name
    hull = {r.method: r for r in evaluate_ranges(presets=("aris3000-128", "aris-telephoto-48"), scenes=("hull",),
                                                 seeds=(0, 1)).rows}
    for name in ("aris3000-128", "aris-telephoto-48"):
        assert rows[f"{name} | propeller"].recall >= 0.9, name
        assert hull[f"{name} | hull"].recall >= 0.9, name
        assert abs(hull[f"{name} | hull"].median_signed_error_bins) <= 1.0, name
    oc = {r.method: r for r in evaluate_presets(presets=("oculus-m750d-like",), scenes=("propeller", "empty"),
                                                seeds=(0,))}
    assert oc["oculus-m750d-like"].false_return_rate <= 0.05
    assert oc["oculus-m750d-like | propeller"].recall >= 0.7


def test_capped_persistency_reduction_gives_the_same_minimiser(monkeypatch, aris_pings, oculus_pings, test_pings):
    """The MRF's reductions (single-pixel test, then 6 passes of chains along the beams) leave the
    rest to the exact cut: the labels equal those of the single-pixel reduction alone run to its
    fixed point, and of it capped at 2 sweeps, on real pings of 3 sonars."""
    import sonarmap.classify.mrf as mrf

    pings = [aris_pings[0], oculus_pings[0], test_pings[4], test_pings[7]]
    default = [process_ping(p, keep_labels=True).labels for p in pings]
    monkeypatch.setattr(mrf, "_CHAIN_PASSES", 0)
    for sweeps in (2, 256):
        monkeypatch.setattr(mrf, "_REDUCTION_SWEEPS", sweeps)
        for a, p in zip(default, pings):
            np.testing.assert_array_equal(a, process_ping(p, keep_labels=True).labels)


def test_normalisation_keeps_a_bright_target_from_filling_the_top_level():
    """A target ~100x a weak background over a third of the image would put ~30 % of the
    normalised pixels at 1.0 (a clipped histogram no mixture describes); the gain is lowered until
    1 % reach it, and a ping without such a target keeps the background's own gain."""
    from sonarmap.preprocess.normalise import MAX_SATURATED

    rng = np.random.default_rng(3)
    img = rng.exponential(0.01, (600, 128)).astype(np.float32)
    plain_bg, plain_u = estimate_background(img)
    img[250:450] = rng.exponential(1.0, (200, 128)).astype(np.float32)
    bg, u = estimate_background(img)
    assert bg.applied and u is not None and plain_u is not None
    assert float((u >= 1.0).mean()) <= MAX_SATURATED + 1e-3
    assert float((u >= 1.0).mean()) > 0.5 * MAX_SATURATED  # lowered just enough, not to nothing
    assert bg.gain < 0.5 * plain_bg.gain
    assert float((plain_u >= 1.0).mean()) < MAX_SATURATED


@pytest.mark.parametrize("seed", range(5))
def test_sidelobe_suppression_and_input_gain_leave_8bit_images_alone(seed):
    """Any 8-bit image (every DIDSON, ARIS and Oculus recording) passes both unchanged: its
    smallest positive level lies 24.1 dB under full scale, inside the 25 dB sidelobe level, and
    its levels are the sonar's own."""
    from sonarmap.preprocess.normalise import input_gain, suppress_sidelobes

    rng = np.random.default_rng(seed)
    img = (rng.integers(0, 256, (300, 64)) * (rng.random((300, 64)) < 0.4)).astype(np.float32) / np.float32(255)
    img[0, 0] = 1.0
    assert np.array_equal(suppress_sidelobes(img), img)
    dark = (rng.integers(0, 3, (300, 64)) / 255).astype(np.float32)  # 99.9th percentile below 4 levels
    out, g = input_gain(dark)
    assert g == 0.0 and np.array_equal(out, dark)


def test_sidelobe_suppression_removes_a_nadir_arc_and_keeps_the_seabed():
    """Water column in linear units: a nadir echo 50 dB over the noise leaks into every beam at its
    range (-35 dB); the off-nadir seabed, at other ranges, is the strongest echo of its own rows."""
    from sonarmap.preprocess.normalise import input_gain, suppress_sidelobes

    rng = np.random.default_rng(1)
    n, m = 400, 128
    img = (rng.exponential(1e-7, (n, m)) + 1e-9).astype(np.float32)  # noise, ~-70 dB re full scale
    nadir = 150
    img[nadir, 60:68] = 1e-2  # the specular nadir echo
    img[nadir, :60] = img[nadir, 68:] = 1e-2 * 10 ** -3.5  # its sidelobe arc, 35 dB under it
    seabed = (nadir / np.cos(np.linspace(-1.0, 1.0, m))).astype(int).clip(0, n - 1)
    img[seabed, np.arange(m)] = np.maximum(img[seabed, np.arange(m)], 3e-5)  # the off-nadir seabed
    out = suppress_sidelobes(img)
    assert np.all(out[nadir, :50] < 1e-6) and np.all(out[nadir, 60:68] == img[nadir, 60:68])
    off = np.abs(np.arange(m) - 64) > 20
    assert np.array_equal(out[seabed[off], np.arange(m)[off]], img[seabed[off], np.arange(m)[off]])
    gained, g = input_gain(out)
    assert g > 20 and gained.max() == 1.0
    assert np.quantile(gained[gained > 0], 0.999) == pytest.approx(1.0, abs=0.05)
