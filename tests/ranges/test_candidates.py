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


def _rippled_band_image() -> tuple[np.ndarray, np.ndarray]:
    """A thin rippled surface over 96 beams and its first row per beam: an echo 3 bins thick,
    flat on beams 0-45, then sand ripples of +-6 bins and 24 beams (flanks up to 1.6 bins per
    beam), faded on every sixth beam.  Pooled over 3 bins x 5 beams at level 0.3, its band is a
    58-beam piece and pieces of 13, 13, 13 and 3 beams."""
    j = np.arange(96)
    rows = 100 + np.where(j >= 46, np.round(6 * np.sin(2 * np.pi * (j - 46) / 24)), 0).astype(int)
    img = np.zeros((200, 96), np.float32)
    for t in range(3):
        img[rows + t, j] = 1.0
    for f in range(50, 96, 6):  # faded beams
        img[rows[f]:rows[f] + 3, f] = 0.0
    return img, rows


def test_pooled_band_mask_continues_a_rippled_surface_across_its_gaps():
    """Short pooled pieces that continue a kept band across beams are kept (link_beams), on every
    beam of the surface; without the link only the piece wider than min_beams survives."""
    img, rows = _rippled_band_image()
    depth = np.arange(200)[:, None] - rows[None, :]
    on_surface = (depth >= -2) & (depth <= 4)
    alone = pooled_band_mask(img, 0.3, pool_beams=2, pool_bins=3, min_beams=40)
    assert alone is not None and alone.any(axis=0).sum() == 58
    band = pooled_band_mask(img, 0.3, pool_beams=2, pool_bins=3, min_beams=40, link_beams=4)
    assert band is not None and band.any(axis=0).all() and not (band & ~on_surface).any()
    assert (band >= alone).all()
    assert np.array_equal(pooled_band_mask(img, 0.3, pool_beams=2, pool_bins=3, min_beams=40, link_beams=1), alone)
    # the numpy route (a level that is not a Python number) gives the same mask
    assert np.array_equal(pooled_band_mask(img, np.float64(0.3), pool_beams=2, pool_bins=3, min_beams=40,
                                           link_beams=4), band)
    # the pieces alone (no band wide enough to anchor them) are not a surface
    img[:, :46] = 0
    assert pooled_band_mask(img, 0.3, pool_beams=2, pool_bins=3, min_beams=40, link_beams=4) is None


def test_continued_bands_drops_a_school_beside_and_over_a_surface():
    """Fish streaks (flat, 3-7 beams) are not linked: not those that no kept band reaches, nor
    those within reach over beams the surface already holds (in front of or behind it)."""
    from sonarmap.ranges.candidates import continued_bands

    band = np.zeros((200, 96), dtype=bool)
    band[100:102, 0:50] = True                      # a surface on beams 0-49
    kept = band.copy()
    school = np.zeros_like(band)
    rng = np.random.default_rng(3)
    for _ in range(25):                             # a school over beams 56-95, 10+ bins off the surface
        r, j, n = int(rng.integers(20, 160)), int(rng.integers(56, 90)), int(rng.integers(3, 8))
        r += 30 if r >= 90 else 0
        school[r:r + 2, j:j + n] = True
    school[95:97, 30:46] = True                     # streaks within reach, in front of the surface
    school[104:106, 44:52] = True                   # and behind it (beams 44-49 held)
    out = continued_bands(band | school, kept, 4)
    assert np.array_equal(out, kept)
    # a piece continuing the surface beyond its end, three beams on and two bins deeper, is kept
    # (and the streak behind the surface, now within reach of it too, still is not)
    band[103:105, 53:61] = True
    out = continued_bands(band | school, kept, 4)
    assert out[103:105, 53:61].all() and not (out & ~band).any()
    assert not continued_bands(band, kept, 3)[103:105, 53:61].any()  # farther than link_beams
    with pytest.raises(InputError, match="kept: expected"):
        continued_bands(band, kept[:10], 4)


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
    from sonarmap.pipeline import PipelineConfig, measurement_image, process_ping
    from sonarmap.preprocess.normalise import condition_image
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
        # a pre-processed ping's echoes are measured on its pre-processing without the deconvolution
        edge = None if normalised else measurement_image(condition_image(p.image)[0], p.geometry, cfg, pr.labels,
                                                         pr.image, bg_mean)
        assert normalised or edge is not None
        r, _ = surface_ranges(p, pr.image, quantize(pr.image), mask, pr.fit, cfg.ranges, cfg.candidates,
                              normalised=normalised, bg_mean=bg_mean, background=pr.background,
                              edge_image=lambda: edge)
        np.testing.assert_array_equal(r.bin, pr.ranges.bin)
        np.testing.assert_array_equal(r.range_m, pr.ranges.range_m)
        np.testing.assert_array_equal(r.sigma_m, pr.ranges.sigma_m)
        n += 1
    assert n == 10 + 6 + 3  # every real ping passes the gates
