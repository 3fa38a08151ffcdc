"""Tests of the simulator (sonarmap.simulate) and ``sonarmap simulate``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.geometry import preset
from sonarmap.simulate import (
    SCENE_NAMES,
    Scene,
    SimulationConfig,
    expected_background_image,
    expected_background_level,
    channel_gain,
    point_target,
    read_truth,
    scene_from_name,
    iter_simulated_pings,
    simulate_ping,
    simulate_pings,
    write_simulation,
)
from sonarmap.simulate.compare import background_stats, histogram_kld

GEOM = preset("didson-hf")
QUIET = SimulationConfig(speckle=False)


def test_same_seed_identical_bytes_and_different_seed_differs() -> None:
    scene = scene_from_name("fish_over_hull", 3)
    a = simulate_ping(scene, GEOM, seed=7)
    b = simulate_ping(scene_from_name("fish_over_hull", 3), GEOM, seed=7)
    c = simulate_ping(scene, GEOM, seed=8)
    assert a.ping.image.tobytes() == b.ping.image.tobytes()
    assert a.class_mask.tobytes() == b.class_mask.tobytes()
    assert not np.array_equal(a.ping.image, c.ping.image)
    img = a.ping.image
    assert img.dtype == np.float32 and img.shape == GEOM.shape
    assert np.allclose(img * 255, np.rint(img * 255), atol=1e-4)  # 8-bit levels k/255


FIELDS = ("clean", "class_mask", "first_return_bin", "first_return_range_m", "unblurred", "structure_peak_snr_db",
          "surface_range_m", "surface_ranges_m")


@pytest.mark.parametrize("name, scene_name", [("didson-hf", "fish_over_hull"), ("aris-telephoto-48", "hull_slope4")])
def test_several_seeds_rendered_once_give_each_seeds_own_bytes(name: str, scene_name: str) -> None:
    """simulate_pings reuses the scene's expected echo and surface truth across seeds: every ping
    equals simulate_ping of its seed (nothing shared is modified by one seed's ping), a Generator
    seed included."""
    g = preset(name)
    scene = scene_from_name(scene_name, geometry=g)
    seeds = [3, 0, np.random.default_rng(5), 3]
    batch = simulate_pings(scene, g, seeds=seeds, recording_meta=True)
    assert len(batch) == 4
    for seed, got in zip([3, 0, np.random.default_rng(5), 3], batch, strict=True):
        want = simulate_ping(scene, g, seed=seed, recording_meta=True)
        assert got.ping.image.tobytes() == want.ping.image.tobytes()
        assert got.ping.meta == want.ping.meta and got.config == want.config and got.seed == want.seed
        for f in FIELDS:
            a, b = getattr(got, f), getattr(want, f)
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), f
    assert not np.array_equal(batch[0].ping.image, batch[1].ping.image)
    assert simulate_pings(scene, g, seeds=[]) == []
    with pytest.raises(InputError, match="seed"):
        simulate_pings(scene, g, seeds=[0, 1.5])
    # one time stamp per seed, or one for all
    timed = simulate_pings(scene, g, seeds=[3, 0], time_ns=[5, 7])
    assert [r.ping.time_ns for r in timed] == [5, 7]
    assert timed[1].ping.image.tobytes() == batch[1].ping.image.tobytes()
    with pytest.raises(InputError, match="time_ns"):
        simulate_pings(scene, g, seeds=[3, 0], time_ns=[5])
    with pytest.raises(InputError, match="time_ns"):
        simulate_pings(scene, g, seeds=[3, 0], time_ns=1.5)
    for bad in (3, np.random.default_rng(0), None):
        with pytest.raises(InputError, match="seeds"):
            simulate_pings(scene, g, seeds=bad)
    # in batches: the same pings, one at a time; its arguments checked on the call
    lazy = list(iter_simulated_pings(scene, g, seeds=[3, 0, 3], recording_meta=True, batch=2))
    assert [r.ping.image.tobytes() for r in lazy] == [batch[k].ping.image.tobytes() for k in (0, 1, 3)]
    with pytest.raises(InputError, match="batch"):
        iter_simulated_pings(scene, g, seeds=[0], batch=0)
    with pytest.raises(InputError, match="seeds"):
        iter_simulated_pings(scene, g, seeds=5)


@pytest.mark.parametrize("beam, range_m", [(7, 3.1), (30, 6.02), (50, 8.5), (90, 10.9)])
def test_point_target_lands_on_nearest_bin_and_beam(beam: int, range_m: float) -> None:
    # Non-uniform azimuth table: aim a little off the beam centre, still nearest to `beam`.
    az = GEOM.azimuth_rad[beam] + 0.3 * (GEOM.azimuth_rad[beam + 1] - GEOM.azimuth_rad[beam])
    res = simulate_ping(point_target(range_m, az, ts_db=-45.0), GEOM, config=QUIET, seed=0)
    exp_bin = int(GEOM.bin_of_range(range_m))
    # Compare after removing the taper: a ghost at +-16 beams in a high-gain beam can outshine a
    # target in a low-gain edge beam (taper 0.32 vs 0.78), exactly as in real DIDSON images.
    # The causal pulse (5 mm) starts in the target's nearest bin and may end in the next one.
    for img in (res.clean, res.ping.image):
        i, j = np.unravel_index(np.argmax(img / GEOM.taper), GEOM.shape)
        assert j == beam and i in (exp_bin, exp_bin + 1)
    assert np.flatnonzero(res.clean[:, beam])[0] == exp_bin
    assert res.first_return_bin[beam] == exp_bin
    assert res.first_return_range_m[beam] == pytest.approx(GEOM.range_m[exp_bin])
    assert (res.class_mask == 1).sum() == 1


def test_psf_ghosts_at_plus_minus_8_beams_with_pattern_ratio() -> None:
    beam = 48
    res = simulate_ping(point_target(6.0, GEOM.azimuth_rad[beam], ts_db=-45.0), GEOM, config=QUIET, seed=0)
    row = res.clean[int(GEOM.bin_of_range(6.0))].astype(np.float64) / GEOM.taper
    c = GEOM.n_beams // 2
    for d in (-16, -8, 8, 16):
        assert row[beam + d] / row[beam] == pytest.approx(GEOM.psf[c + d] / GEOM.psf[c], rel=1e-4)
    # The main lobe (0.9 of the gap to the nearer beam wide) reaches the neighbours at ~2^-4.9 ...
    assert 0.02 < row[beam + 1] / row[beam] < 0.05 and 0.02 < row[beam - 1] / row[beam] < 0.05
    # ... and no further: the other non-tap beams are empty (ghosts only every 8th beam).
    assert np.all(row[[beam - 3, beam + 5]] == 0)
    no_lobe = simulate_ping(point_target(6.0, GEOM.azimuth_rad[beam], ts_db=-45.0), GEOM,
                            config=QUIET.replace(beam_width_rad=0.0), seed=0)
    row0 = no_lobe.clean[int(GEOM.bin_of_range(6.0))].astype(np.float64)
    assert np.all(row0[[beam + 1, beam - 3, beam + 5]] == 0)
    # Linear (not circular) convolution: a target at beam 2 puts nothing at beam 2 - 8 + 96 = 90.
    res2 = simulate_ping(point_target(6.0, GEOM.azimuth_rad[2], ts_db=-45.0), GEOM, config=QUIET, seed=0)
    row2 = res2.clean[int(GEOM.bin_of_range(6.0))]
    assert row2[90] == 0 and row2[10] > 0


def test_hull_ghost_energy_measurable_and_truth_has_no_ghosts() -> None:
    # A narrow rudder plate: ghost copies at +-8 beams carry psf[c+-8]/psf[c] of its energy.
    from sonarmap.simulate import rudder

    cfg = SimulationConfig(speckle=False, full_scale_db=200.0)  # no clipping at 1
    res = simulate_ping(rudder(width_m=0.25, yaw_deg=0.0), GEOM, config=cfg, seed=0)
    assert res.clean.max() < 1.0
    cols = np.flatnonzero((res.class_mask == 1).any(axis=0))
    assert 2 <= cols.size <= 7
    e = (res.clean.astype(np.float64) / GEOM.taper).sum(axis=0)
    main_e = e[cols].sum()
    ghost = e[np.clip(cols + 8, 0, 95)].sum() + e[np.clip(cols - 8, 0, 95)].sum()
    ratio_db = 10 * math.log10(ghost / main_e)
    c = GEOM.n_beams // 2
    expected_db = 10 * math.log10((GEOM.psf[c + 8] + GEOM.psf[c - 8]) / GEOM.psf[c])
    assert ratio_db == pytest.approx(expected_db, abs=1.0)
    # Truth mask only covers the real plate (ghost columns are background).
    assert not (res.class_mask[:, np.setdiff1d(cols + 8, cols)[:1]] == 1).any()


@pytest.mark.slow  # over a second in the fast subset
def test_taper_multiplies_echo_and_background() -> None:
    g = GEOM.replace(psf=None)
    r0 = simulate_ping(point_target(5.0, g.azimuth_rad[5], ts_db=-55.0), g, config=QUIET, seed=0)
    r1 = simulate_ping(point_target(5.0, g.azimuth_rad[42], ts_db=-55.0), g, config=QUIET, seed=0)
    assert r1.clean.max() < 1.0
    ratio = r0.clean.max() / r1.clean.max()
    assert ratio == pytest.approx(g.taper[5] / g.taper[42], rel=1e-4)
    # Open-water pings: mean per beam follows the exact expectation (taper + threshold + quantiser).
    imgs = np.stack([simulate_ping(scene_from_name("empty"), g, seed=s).ping.image for s in range(24)])
    exp_mean, exp_zero = expected_background_image(g)
    np.testing.assert_allclose(imgs.mean(axis=(0, 1)), exp_mean.mean(axis=0), rtol=0.08)
    assert (imgs == 0).mean() == pytest.approx(exp_zero.mean(), abs=0.005)


def test_background_level_follows_channel_loss() -> None:
    cfg = SimulationConfig()
    lvl = expected_background_level(GEOM, cfg)
    gain = channel_gain(GEOM, cfg)
    flat = lvl / gain
    assert flat.std() / flat.mean() < 1e-3  # noise term negligible; reverb goes through the channel
    r = GEOM.range_m
    tl = -10 * np.log10(gain / gain[0])
    k1, k2 = 20 * cfg.spreading_beta, 2 * cfg.alpha_db_per_m
    np.testing.assert_allclose(tl, k1 * np.log10(r / r[0]) + k2 * (r - r[0]), atol=1e-9)


@pytest.mark.parametrize("name", ["hull", "curved_hull", "fish_over_hull", "seafloor", "propeller"])
def test_first_return_matches_class_mask(name: str) -> None:
    res = simulate_ping(scene_from_name(name, 1), GEOM, seed=0)
    s = res.class_mask == 1
    assert s.any()
    for j in range(GEOM.n_beams):
        rows = np.flatnonzero(s[:, j])
        if rows.size:
            assert res.first_return_bin[j] == rows[0]
            assert res.first_return_range_m[j] == GEOM.range_m[rows[0]]
        else:
            assert res.first_return_bin[j] == -1 and math.isnan(res.first_return_range_m[j])


@pytest.mark.parametrize("name, changes", [("fish_over_hull", False), ("seafloor", True), ("propeller", True)])
@pytest.mark.slow
def test_structure_peak_snr_gives_the_class_mask_at_any_threshold(name: str, changes: bool) -> None:
    """A beam holds structure at truth threshold t exactly when its structure_peak_snr_db >= t:
    the same answer as rendering again with truth_snr_db = t (the evaluator relies on it)."""
    sc = scene_from_name(name, 1)
    res = simulate_ping(sc, GEOM, seed=0)
    assert np.array_equal(res.structure_peak_snr_db >= res.config.truth_snr_db, (res.class_mask == 1).any(axis=0))
    differ = 0
    for t in (-9.0, -6.0, 0.0, 6.0, 12.0):
        again = simulate_ping(sc, GEOM, config=res.config.replace(truth_snr_db=t), seed=0)
        has = (again.class_mask == 1).any(axis=0)
        assert np.array_equal(res.structure_peak_snr_db >= t, has), t
        differ += int((has != (res.class_mask == 1).any(axis=0)).sum())
    assert (differ > 0) == changes  # whether the thresholds change which beams hold structure
    empty = simulate_ping(scene_from_name("empty"), GEOM, seed=0)
    assert np.isneginf(empty.structure_peak_snr_db).all()


def test_hull_band_is_continuous_and_fish_are_clutter() -> None:
    res = simulate_ping(scene_from_name("hull"), GEOM, seed=0)
    assert (res.first_return_bin >= 0).all()  # every beam sees the hull
    assert np.abs(np.diff(res.first_return_bin)).max() <= 3  # continuous band
    fish = simulate_ping(scene_from_name("fish", 0), GEOM, seed=0)
    assert (fish.class_mask == 2).sum() >= 10 and not (fish.class_mask == 1).any()
    empty = simulate_ping(scene_from_name("empty"), GEOM, seed=0)
    assert not empty.class_mask.any() and (empty.first_return_bin == -1).all()


@pytest.mark.slow
def test_all_named_scenes_render() -> None:
    assert {"hull", "curved_hull", "propeller", "rudder", "seafloor", "fish", "fish_over_hull",
            "empty"} <= set(SCENE_NAMES)
    for name in SCENE_NAMES:
        res = simulate_ping(scene_from_name(name, 0), GEOM, seed=0)
        assert (res.class_mask > 0).any() == (name != "empty"), name


def test_background_histogram_close_to_real(background_paths: list[Path]) -> None:
    from sonarmap.io.pngjson import read_image_file

    real = background_stats(read_image_file(p) for p in background_paths)
    sim = background_stats(
        simulate_ping(scene_from_name("empty"), GEOM, seed=s).ping.image for s in range(40)
    )
    assert sim.zero_fraction == pytest.approx(real.zero_fraction, abs=0.05)
    assert histogram_kld(real.histogram, sim.histogram) < 0.03
    assert sim.mean == pytest.approx(real.mean, rel=0.15)


def test_write_and_read_back(tmp_path: Path) -> None:
    from sonarmap.io.pngjson import read_png_ping

    res = simulate_ping(scene_from_name("fish_over_hull", 0), GEOM, seed=5, time_ns=1_700_000_000_123_456_000)
    files = write_simulation(res, tmp_path, "1700000000123456")
    back = read_png_ping(files.image)
    assert np.array_equal(back.image, res.ping.image)
    assert back.geometry == GEOM and back.time_ns == res.ping.time_ns
    mask, info = read_truth(tmp_path, "1700000000123456")
    assert np.array_equal(mask, res.class_mask)
    assert info["first_return_bin"] == res.first_return_bin.tolist()
    assert info["scene"] == "fish_over_hull" and info["seed"] == 5


def test_bad_input_names_argument() -> None:
    pts = np.array([[5.0, 0.0, 0.0], [6.0, 0.1, 0.0]])
    ok = dict(normals=np.zeros((2, 3)), reflectivity=np.ones(2), labels=np.ones(2, np.uint8),
              patch_area_m2=np.ones(2))
    with pytest.raises(InputError, match="normals"):
        Scene(points_m=pts, **{**ok, "normals": np.zeros((2, 2))})
    with pytest.raises(InputError, match="points_m"):
        Scene(points_m=np.array([[5.0, np.nan, 0.0], [6.0, 0.0, 0.0]]), **ok)
    with pytest.raises(InputError, match="normals"):
        Scene(points_m=pts, **{**ok, "normals": np.full((2, 3), 0.3)})
    with pytest.raises(InputError, match="labels"):
        Scene(points_m=pts, **{**ok, "labels": np.array([1, 7])})
    with pytest.raises(InputError, match="scene"):
        scene_from_name("submarine")
    with pytest.raises(InputError, match="seed"):
        simulate_ping(Scene(points_m=pts, **ok), GEOM, seed=1.5)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="threshold"):
        SimulationConfig(threshold=2.0)


def test_transformed_and_concat() -> None:
    hull = scene_from_name("hull")
    a = 0.3
    rot = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    t = np.array([1.0, -2.0, 0.5])
    moved = hull.transformed(rot, t)
    back = moved.transformed(rot.T, -rot.T @ t)
    np.testing.assert_allclose(back.points_m, hull.points_m, atol=1e-12)
    np.testing.assert_allclose(back.normals, hull.normals, atol=1e-12)
    both = Scene.concat(hull, point_target(3.0, 0.0))
    assert len(both) == len(hull) + 1 and both.labels[-1] == 1
    with pytest.raises(InputError, match="rotation_matrix"):
        hull.transformed(2 * np.eye(3), t)


def test_cli_simulate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from sonarmap.cli import main

    assert main(["simulate", "--list-scenes"]) == 0
    assert "curved_hull" in capsys.readouterr().out
    out = tmp_path / "sim"
    assert main(["simulate", "--scene", "hull", "--seed", "0", "--count", "2", "--sonar", "didson-hf",
                 "-o", str(out)]) == 0
    assert str(out) in capsys.readouterr().err
    assert len(list(out.glob("*_raw.png"))) == 2 and len(list(out.glob("*_truth.json"))) == 2
    assert main(["simulate", "--scene", "nope", "-o", str(out)]) == 2  # usage error
    assert "nope" in capsys.readouterr().err


def test_cli_simulate_renders_in_batches_the_pings_of_one_seed_each(tmp_path: Path) -> None:
    """Past the first ping the CLI renders batches of SEEDS_PER_RENDER seeds (simulate_pings): ping i
    is still simulate_ping's ping of seed + i, 100 ms after ping i - 1."""
    from sonarmap.cli import main
    from sonarmap.simulate.render import SEEDS_PER_RENDER
    from sonarmap.io import read_pings

    n = SEEDS_PER_RENDER + 2  # the first ping, one full batch and one of 1
    out = tmp_path / "sim"
    assert main(["simulate", "--scene", "propeller", "--seed", "4", "--count", str(n), "--sonar", "didson-hf",
                 "--quiet", "-o", str(out)]) == 0
    pings = list(read_pings(sorted(str(p) for p in out.glob("*_raw.png"))))
    assert len(pings) == n
    assert np.all(np.diff([p.time_ns for p in pings]) == 100_000_000)
    scene = scene_from_name("propeller", 4, geometry=GEOM)
    for i in (0, 1, n - 1):
        assert np.array_equal(pings[i].image, simulate_ping(scene, GEOM, seed=4 + i).ping.image), i


def _ghost_pair(ghosts: str, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Recorded intensity of a point target's main beam and of its +8-beam ghost over n pings."""
    beam = 40
    r = 6.0
    cfg = SimulationConfig(ghosts=ghosts, noise_level_db=60.0, reverb_db=-120.0, threshold=0.0,
                           full_scale_db=175.0)  # main beam mean ~0.1: no clipping, negligible background
    b = int(GEOM.bin_of_range(r))
    scene = point_target(r, GEOM.azimuth_rad[beam], ts_db=-45.0)
    main = np.empty(n)
    ghost = np.empty(n)
    for s, res in enumerate(iter_simulated_pings(scene, GEOM, config=cfg, seeds=range(n), batch=50)):
        img = res.ping.image.astype(np.float64) / GEOM.taper  # (the target's echo rendered once per 50 seeds)
        main[s], ghost[s] = img[b, beam], img[b, beam + 8]
    return main, ghost


@pytest.mark.slow
def test_coherent_ghosts_copy_their_source_and_keep_the_expected_image() -> None:
    """Coherent model: a lone target's ghost is a scaled copy of its own speckled echo (the same
    scatterers through the +-8-beam taps), so per ping ghost/main = psf ratio; the incoherent
    model fades them independently.  Both have the expected ratio on average."""
    c = GEOM.n_beams // 2
    ratio = GEOM.psf[c + 8] / GEOM.psf[c]
    m_c, g_c = _ghost_pair("coherent")
    m_i, g_i = _ghost_pair("incoherent")
    ok = m_c > 0.5 * m_c.mean()  # ghost >= ~5 quanta: 8-bit rounding below 10 %
    assert np.corrcoef(m_c, g_c)[0, 1] > 0.95
    assert np.median(np.abs(g_c[ok] / m_c[ok] - ratio)) < 0.1 * ratio
    assert abs(np.corrcoef(m_i, g_i)[0, 1]) < 0.2
    for m, g in ((m_c, g_c), (m_i, g_i)):
        assert g.mean() / m.mean() == pytest.approx(ratio, rel=0.15)


def test_measured_beam_pattern_has_the_real_ghost_ratios() -> None:
    from sonarmap.simulate.render import MEASURED_DIDSON_GHOSTS, ghost_psf, main_lobe_taps, render_psf

    assert ghost_psf(GEOM, SimulationConfig()) is GEOM.psf
    assert render_psf(GEOM, SimulationConfig(beam_width_rad=0.0)) is GEOM.psf
    # the rendered pattern is the ghost taps through the main lobe
    both = np.convolve(GEOM.psf, main_lobe_taps(GEOM, SimulationConfig()))[48:144]
    np.testing.assert_allclose(render_psf(GEOM, SimulationConfig()), both / both.sum(), atol=1e-12)
    p = ghost_psf(GEOM, SimulationConfig(beam_pattern="measured"))
    c = GEOM.n_beams // 2
    assert p.sum() == pytest.approx(1.0)
    for k, ratio in enumerate(MEASURED_DIDSON_GHOSTS, start=1):
        assert p[c + 8 * k] / p[c] == pytest.approx(ratio) and p[c - 8 * k] / p[c] == pytest.approx(ratio)
    assert np.count_nonzero(p) == 1 + 2 * len(MEASURED_DIDSON_GHOSTS)
    # rendered: a target's ghost at +8 beams is ~3 % of it, not the stated PSF's 57 %
    res = simulate_ping(point_target(6.0, GEOM.azimuth_rad[40], ts_db=-45.0), GEOM,
                        config=SimulationConfig(speckle=False, beam_pattern="measured", full_scale_db=200.0), seed=0)
    row = res.clean[int(GEOM.bin_of_range(6.0))].astype(np.float64) / GEOM.taper
    assert row[48] / row[40] == pytest.approx(MEASURED_DIDSON_GHOSTS[0], rel=1e-4)
    with pytest.raises(InputError, match="beam_pattern"):
        SimulationConfig(beam_pattern="nope")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="ghosts"):
        SimulationConfig(ghosts="nope")  # type: ignore[arg-type]


def test_measured_ghost_ratios_reproduce_from_real_ping_5(test_ping_paths: list[Path]) -> None:
    """The constants come from the real DIDSON ping 5 (see MEASURED_DIDSON_GHOSTS)."""
    from sonarmap.io.pngjson import read_png_ping
    from sonarmap.simulate.compare import ghost_ratios
    from sonarmap.simulate.render import MEASURED_DIDSON_GHOSTS

    got = ghost_ratios(read_png_ping(test_ping_paths[5]))
    assert got == pytest.approx(MEASURED_DIDSON_GHOSTS, abs=0.002)
