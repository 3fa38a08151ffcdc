"""A surface's echo against the water column in front of it (sonarmap.ranges.significance)."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.pipeline import PipelineConfig, process_ping
from sonarmap.ranges.echoes import find_echoes
from sonarmap.ranges.significance import surface_significance


def _geom(n_bins: int = 400, n_beams: int = 24) -> SonarGeometry:
    return SonarGeometry(range_m=2.0 + 0.02 * np.arange(n_bins), azimuth_rad=np.linspace(-0.3, 0.3, n_beams))


# (the images are float32, as every ping's raw image: the tests run the kernels' pipeline specialisation)


def _surface(img: np.ndarray, rows: np.ndarray, depth: int = 4) -> tuple[object, np.ndarray]:
    """The echoes of a surface ``depth`` bins deep from ``rows`` (per beam; -1: none) and its first
    returns."""
    mask = np.zeros(img.shape, bool)
    for j, r in enumerate(rows):
        if r >= 0:
            mask[r:r + depth, j] = True
    e = find_echoes(mask, img, _geom(*img.shape))
    first, count = e.per_beam()
    return e, np.where(count > 0, first, -1)


def test_a_bright_surface_stands_far_above_its_water_column_and_speckle_does_not():
    rng = np.random.default_rng(0)
    img = rng.exponential(0.1, (400, 24)).astype(np.float32)
    rows = 300 + np.arange(24) // 4  # a gently sloped surface
    bright = img.copy()
    for j, r in enumerate(rows):
        bright[r:r + 4, j] += 0.3  # +5 dB over the background
    e, first = _surface(bright, rows)
    z, n = surface_significance(e, first, bright)
    assert np.all(n == 200) and np.all(z > 10)
    # the same path through the background alone: within a few MADs of its water column
    e, first = _surface(img, rows)
    z, _ = surface_significance(e, first, img)
    assert np.all(np.abs(z) < 3)


def test_the_null_holds_on_correlated_speckle_whose_spread_grows_with_range():
    """Random surfaces over multi-looked speckle of a log-compressed-like background (the spread
    after the division by the level doubles over the window, as on ARIS): the test's false alarms
    at z >= 3.5 stay rare (measured 0 of 300) - a null taken far from the surface would not."""
    from scipy.ndimage import uniform_filter

    rng = np.random.default_rng(1)
    hits = 0
    total = 0
    for _ in range(30):
        n = 600
        grow = np.linspace(1.0, 2.0, n)[:, None]
        img = (1.0 + 0.05 * grow * (uniform_filter(rng.standard_normal((n, 24)), (5, 3)) * 4.0)).astype(np.float32)
        for _ in range(10):
            r0 = int(rng.integers(250, 580))
            rows = np.clip(r0 + np.cumsum(rng.integers(-2, 3, 24)), 215, n - 5)
            e, first = _surface(img, rows)
            z, _ = surface_significance(e, first, img)
            hits += int(z[0] >= 3.5)
            total += 1
    assert hits / total < 0.02


def test_short_surfaces_and_those_without_water_column_are_not_tested():
    rng = np.random.default_rng(2)
    img = rng.exponential(0.1, (400, 24)).astype(np.float32)
    rows = np.full(24, -1)
    rows[3:5] = 300  # two beams: too few
    rows[10:20] = 15  # 15 bins from the first bin: a few offsets in front of the gap, too few
    e, first = _surface(img, rows)
    z, n = surface_significance(e, first, img)
    assert np.all(np.isnan(z))
    assert 0 < n[12] < 20 and n[3] == 0
    # a surface cut by the end of the window is tested on the bins it has
    rows = np.full(24, -1)
    rows[4:16] = 398
    e, first = _surface(img, rows, depth=2)
    z, n = surface_significance(e, first, img)
    assert np.all(np.isfinite(z[4:16])) and n[4] == 200


def test_a_surface_the_contiguity_rule_breaks_is_tested_whole_with_the_jump_rule():
    """A bright surface whose echo steps 6 bins between beams 15 and 16 (its bin intervals 3 bins
    apart: two touch-runs; its leading edges 3.6 bins apart) is one surface under the tracker's
    neighbour rule (edges within ``jump_bins``): its short piece is tested with the rest (the same
    z), not alone; with a jump rule tighter than the step the pieces stay apart."""
    rng = np.random.default_rng(5)
    img = rng.exponential(0.1, (400, 24)).astype(np.float32)
    rows = np.where(np.arange(24) < 16, 300, 294)
    for j, r in enumerate(rows):
        img[r:r + 4, j] += 0.3
    e, first = _surface(img, rows)
    z_touch, _ = surface_significance(e, first, img)
    z_jump, _ = surface_significance(e, first, img, jump_bins=20.0)
    assert z_touch[0] != z_touch[20]  # two runs
    assert np.all(z_jump == z_jump[0]) and z_jump[0] > 10
    z_far, _ = surface_significance(e, first, img, jump_bins=1.0)
    np.testing.assert_array_equal(z_far, z_touch)


def test_bad_arguments_name_what_is_wrong():
    img = np.ones((50, 6), np.float32)
    e, first = _surface(img, np.full(6, 30))
    with pytest.raises(InputError, match="first"):
        surface_significance(e, first[:5], img)
    with pytest.raises(InputError, match="window_bins"):
        surface_significance(e, first, img, window_bins=1)
    with pytest.raises(InputError, match="raw"):
        surface_significance(e, first, img[0])
    with pytest.raises(Exception, match="surface_min_z"):
        PipelineConfig().replace(surface_min_z=-1.0)


@pytest.mark.parametrize("seed", [9, 19, 24])
def test_the_false_surfaces_at_the_far_end_of_empty_aris_pings_are_dropped(seed):
    """Simulated empty telephoto pings whose far-end speckle the tracker joined into a surface
    (bins 900-990 of 1000; 28, 16 and 32 beams): without the test they report it, with it nothing
    (on seed 24 a surface tracked behind the dropped one is not moved up)."""
    from sonarmap import preset
    from sonarmap.evaluate.segmentation import _simulate, preset_sim_configs

    g = preset("aris-telephoto-48")
    sim, _ = _simulate("empty", g, preset_sim_configs(g)[0], seed, -3.0, True)
    off = process_ping(sim.ping, PipelineConfig().replace(surface_min_z=0.0)).ranges
    assert np.isfinite(off.range_m).sum() >= 15
    assert np.all(off.bin[np.isfinite(off.range_m)] > 850)
    on = process_ping(sim.ping, PipelineConfig()).ranges
    assert not np.isfinite(on.range_m).any()


def test_the_real_aris_target_keeps_every_return(aris_pings):
    """On the 6 real ARIS frames the test keeps every return on the target (15.3-17.6 m) and the
    faint pieces at 21.8-22.1 m at the fan's edge that stand 3.6-6.8 MADs above their water
    column; it drops frame 5's weakest far piece (beams 42-47, z 2.1).  Frame 1's far piece
    (beams 44-47) stands at z 3.6 and is kept (2.8 with the pooled peak's height taken from its
    largest sample, ``edge_pool_peak_bins = 0``: its edges, and so its window, move).
    (These pieces sit in speckle at the window's far end: their z moves with the background
    estimate - before the level was bridged by a quadratic across surfaces and the beam factor's
    block rows median filtered, frame 2's piece had z 2.5 and frame 1's 3.6.)"""
    off_cfg = PipelineConfig().replace(surface_min_z=0.0)
    dropped = []
    for k, p in enumerate(aris_pings):
        off = process_ping(p, off_cfg).ranges.range_m
        on = process_ping(p, PipelineConfig()).ranges.range_m
        target = (off >= 15.3) & (off <= 17.6)
        np.testing.assert_array_equal(on[target], off[target])
        kept = np.isfinite(on)
        assert np.all(np.isnan(on[~np.isfinite(off)]))
        np.testing.assert_array_equal(on[kept], off[kept])
        dropped += [(k, int(j)) for j in np.flatnonzero(np.isfinite(off) & ~kept)]
        assert np.all(off[~kept & np.isfinite(off)] > 21.7)
    assert dropped == [(5, j) for j in range(42, 48)]


def test_the_real_oculus_seabed_and_didson_pings_keep_every_return(oculus_pings, test_pings):
    """The Oculus seabed stands 7.8-18 MADs above its water column (every return kept); DIDSON
    pings are pre-processed, not normalised, and are not tested."""
    off_cfg = PipelineConfig().replace(surface_min_z=0.0)
    for p in [*oculus_pings, *test_pings]:
        off = process_ping(p, off_cfg).ranges.range_m
        on = process_ping(p, PipelineConfig()).ranges.range_m
        np.testing.assert_array_equal(on, off)
