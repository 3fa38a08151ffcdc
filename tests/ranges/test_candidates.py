"""The candidate stage (sonarmap.ranges.candidates): component rule and band pooling."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.geometry import preset
from sonarmap.ranges.candidates import candidate_mask, pooled_band_mask
from sonarmap.ranges.config import CandidateConfig


def test_candidate_mask_keeps_surfaces_and_drops_fish():
    g = preset("didson-hf")
    lab = np.zeros(g.shape, dtype=np.uint8)
    lab[100:102, 10:60] = 1          # a surface: 50 beams x 2 bins
    lab[300:304, 70:76] = 2          # a fish: 6 beams x 4 bins = 24 pixels (any object class)
    m = candidate_mask(lab, g)
    assert m[100:102, 10:60].all() and not m[300:304, 70:76].any()
    # the same 24-pixel blob passes a looser rule; normalised images need larger components
    assert candidate_mask(lab, g, CandidateConfig(min_component_pixels=20))[300:304, 70:76].all()
    lab2 = np.zeros(g.shape, dtype=np.uint8)
    lab2[200:202, 10:30] = 1         # 20 beams: a surface for 8-bit images, not for normalised ones
    assert candidate_mask(lab2, g).any() and not candidate_mask(lab2, g, normalised=True).any()
    with pytest.raises(InputError, match="config: expected a CandidateConfig"):
        candidate_mask(lab, g, {"link_beams": 1})  # type: ignore[arg-type]


def test_pooled_band_mask_finds_a_wide_faint_band_only():
    img = np.zeros((64, 60), np.float32)
    img[30, :] = 0.5
    img[10, 5:15] = 0.5              # too narrow
    band = pooled_band_mask(img, 0.1, min_beams=40)
    assert band is not None and band[29:32].any(axis=0)[2:-2].all() and not band[:20].any()
    assert pooled_band_mask(np.zeros((64, 60), np.float32), 0.1) is None


def _box_cases(rng: np.random.Generator, n: int = 150):
    """``(t, image, box rows, box columns)`` of ``n`` random images (every third one 60 % zeros),
    drawn lazily from ``rng`` (a test may draw from it between cases)."""
    for t in range(n):
        h, w = int(rng.integers(1, 70)), int(rng.integers(1, 70))
        img = (rng.random((h, w)) ** rng.uniform(1, 8)).astype(np.float32)
        if t % 3 == 0:
            img[rng.random((h, w)) < 0.6] = 0
        yield t, img, int(rng.integers(1, 6)), int(rng.integers(1, 12))


def test_box_mean_kernel_is_scipy_uniform_filter_bit_for_bit():
    """The band-pooling box mean (numba) reproduces scipy.ndimage.uniform_filter exactly."""
    from scipy.ndimage import uniform_filter

    from sonarmap.ranges._kernels import box_mean_f32

    for _, img, s0, s1 in _box_cases(np.random.default_rng(0)):
        ref = uniform_filter(img, size=(s0, s1), mode="constant")
        assert np.array_equal(ref.view(np.uint32), box_mean_f32(img, s0, s1).view(np.uint32))


def test_box_band_kernel_is_box_mean_threshold():
    """The row-by-row band kernel equals the box mean's threshold, with its row span and column count."""
    from sonarmap.ranges._kernels import box_band, box_mean_f32

    rng = np.random.default_rng(1)
    for t, img, s0, s1 in _box_cases(rng):
        pooled = box_mean_f32(img, s0, s1)
        level = np.float32(np.quantile(pooled, rng.uniform(0.3, 1.0))) if t % 5 else np.float32(2.0)
        want = pooled >= level
        band, r0, r1, n_cols = box_band(img, s0, s1, level)
        rows = np.flatnonzero(want.any(axis=1))
        assert np.array_equal(band, want)
        assert (r0, r1) == ((int(rows[0]), int(rows[-1]) + 1) if rows.size else (img.shape[0], 0))
        assert n_cols == int(want.any(axis=0).sum())


def test_band_peak_kernel_matches_numpy_formulation():
    from sonarmap.ranges._kernels import band_peak_pixels

    rng = np.random.default_rng(5)
    for _ in range(100):
        h, w = int(rng.integers(1, 40)), int(rng.integers(1, 30))
        band = rng.random((h, w)) < rng.uniform(0.05, 0.9)
        img = np.floor(rng.random((h, w)) * 6).astype(np.float32)  # ties are common
        cols = band.any(axis=0) & (rng.random(w) < 0.8)
        first = band.argmax(axis=0)
        rows = np.arange(h)[:, None]
        below = rows >= first[None, :]
        run = np.logical_and.accumulate(band | ~below, axis=0) & below & cols[None, :]
        pick = np.where(run, img, -np.inf).argmax(axis=0)
        ref = np.zeros((h, w), bool)
        j = np.flatnonzero(cols)
        ref[pick[j], j] = True
        assert np.array_equal(band_peak_pixels(band, img, cols), ref)


def test_the_range_stages_alone_give_the_pipeline_ranges(test_pings, aris_pings, oculus_pings):
    """candidate_mask then surface_ranges on the classifier's image, labels and fit give exactly the
    returns process_ping reports, on every real DIDSON, ARIS and Oculus ping."""
    from sonarmap.pipeline import PipelineConfig, process_ping
    from sonarmap.ranges.measure import background_mean, surface_ranges
    from sonarmap.stats.mixture import quantize

    cfg = PipelineConfig()
    n = 0
    for p in [*test_pings, *aris_pings, *oculus_pings]:
        pr = process_ping(p, cfg, keep_labels=True)
        if pr.fit is None or pr.gates:
            continue
        normalised = bool(pr.background is not None and pr.background.applied)
        mask = candidate_mask(pr.labels, p.geometry, cfg.candidates, normalised=normalised)
        bg_mean, _ = background_mean(pr.fit, cfg.ranges)
        r, _ = surface_ranges(p, pr.image, quantize(pr.image), mask, pr.fit, cfg.ranges, cfg.candidates,
                              normalised=normalised, bg_mean=bg_mean, background=pr.background)
        np.testing.assert_array_equal(r.bin, pr.ranges.bin)
        np.testing.assert_array_equal(r.range_m, pr.ranges.range_m)
        np.testing.assert_array_equal(r.sigma_m, pr.ranges.sigma_m)
        n += 1
    assert n == 10 + 6 + 3  # every real ping passes the gates
