"""Crosstalk rows: lit across the fan at a bright echo's range (``sonarmap.preprocess.crosstalk``)."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.pipeline import PipelineConfig, process_ping
from sonarmap.preprocess.crosstalk import crosstalk_by_row, remove_crosstalk

N_BINS, N_BEAMS = 300, 96


def _hull(seed: int, band: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A curved hull (apex at row 100 on the middle beams, flanks down to row ~160 at the fan's
    edges) over exponential speckle, its echo 4 bins deep; ``band`` added to rows 100-102 of every
    beam (crosstalk at the apex's range).  Image, labels and the surface row per beam."""
    rng = np.random.default_rng(seed)
    beams = np.arange(N_BEAMS)
    surface = (100 + 60 * ((beams - 47.5) / 47.5) ** 2).astype(int)
    img = rng.exponential(0.02, (N_BINS, N_BEAMS))
    labels = np.zeros((N_BINS, N_BEAMS), np.uint8)
    for j, s in enumerate(surface):
        img[s:s + 4, j] += 0.8 * rng.exponential(1.0, 4)
        labels[s:s + 4, j] = 1
    img[100:103] += band
    return img.astype(np.float32), labels, surface


def test_a_band_across_the_fan_is_found_at_its_rows_and_removed() -> None:
    for seed in range(5):
        img, labels, surface = _hull(seed, band=0.25)
        level = crosstalk_by_row(img, labels)
        assert np.all(np.abs(level[100:103] - 0.25) < 0.05)
        assert not np.any(np.delete(level, [100, 101, 102]))
        out = remove_crosstalk(img, labels)
        flanks = surface > 110  # beams whose own echo lies behind the band
        assert out[100:103][:, flanks].mean() < 0.05 < img[100:103][:, flanks].mean()
        # the apex's echo, at the band's rows, loses only the band
        apex = surface == 100
        assert np.allclose(out[100:103][:, apex], np.maximum(img[100:103][:, apex] - level[100:103, None], 0),
                           atol=1e-6)


def test_a_deep_band_is_followed_into_rows_that_fewer_beams_see() -> None:
    """A band lit over rows 100-140: towards its far end the hull's own echo fills more of the
    fan, and beyond row ~130 fewer than a quarter of the beams are water column there.  The band
    found on the rows with enough of them grows into those rows (down to 8 water-column beams)."""
    for seed in range(5):
        img, labels, surface = _hull(seed)
        img[100:141] += np.float32(0.25)
        level = crosstalk_by_row(img, labels)
        water = np.array([(surface > r + 4).sum() for r in range(N_BINS)])
        few = np.flatnonzero((water < N_BEAMS // 4) & (water >= 8) & (np.arange(N_BINS) <= 140))
        assert few.size >= 5 and few.min() > 120  # the rows only the growth reaches
        assert np.all(np.abs(level[100:141] - 0.25) < 0.06)
        assert not np.any(level[141:])


def test_without_a_band_nothing_changes() -> None:
    for seed in range(10):
        img, labels, _ = _hull(seed)
        assert not crosstalk_by_row(img, labels).any()
        assert remove_crosstalk(img, labels) is img


def test_a_flat_surface_across_the_fan_is_not_crosstalk() -> None:
    """A surface seen head on lights whole rows; no beam is water column there: no estimate."""
    rng = np.random.default_rng(3)
    img = rng.exponential(0.02, (N_BINS, N_BEAMS)).astype(np.float32)
    img[150:154] += 0.8
    labels = np.zeros(img.shape, np.uint8)
    labels[150:154] = 1
    assert not crosstalk_by_row(img, labels).any()


def test_a_bright_point_and_its_ghosts_are_not_crosstalk() -> None:
    """Ghosts light a few beams at +-8 / 16 / 24 from a bright point, not most of the fan."""
    img, labels, _ = _hull(7)
    img[200:203, 48] += 5.0
    labels[200:203, 48] = 1
    for d in (8, 16, 24):
        img[200:203, 48 - d] += 0.3
        img[200:203, 48 + d] += 0.3
    assert not crosstalk_by_row(img, labels).any()


def test_bad_arguments_are_refused() -> None:
    img, labels, _ = _hull(0)
    with pytest.raises(InputError, match="labels"):
        crosstalk_by_row(img, labels[:-1])
    with pytest.raises(InputError, match="margin_bins"):
        crosstalk_by_row(img, labels, margin_bins=-1)
    with pytest.raises(InputError, match="z"):
        crosstalk_by_row(img, labels, z=float("nan"))


def test_the_real_didson_flanks_beside_ping_9s_band(test_pings: list) -> None:
    """Ping 9's band (rows 193-207 lit across the fan behind the hull's apex): without the removal
    19 edges on the steep flanks (beams 30 on) lie more than 3 bins in front of the deconvolved
    image's (the deconvolution removes the band); with it 4 (beams 42-44 and 75, 3.1-3.8 bins,
    drawn towards their neighbours' line by the smoothing along the surface).  (Beams 10-13, at
    the hull's faint end far from the band, lie 3.4-4.2 bins in front of the deconvolved image's
    edges with or without the removal: the pooled edges reach the front of the faint band there.)
    Fish-only pings keep no return."""
    default = PipelineConfig()
    off = default.replace(edge_crosstalk=False)
    ref = default.replace(edge_image="classified")
    p = test_pings[9]
    res = p.geometry.range_resolution_m
    c = process_ping(p, ref).ranges.range_m
    a = process_ping(p, off).ranges.range_m
    b = process_ping(p, default).ranges.range_m
    assert np.isfinite(a).sum() == np.isfinite(b).sum() == 87
    flanks = slice(30, None)
    assert np.sum((a - c)[flanks] / res < -3) >= 8  # measured 19
    assert np.sum((b - c)[flanks] / res < -3) <= 4  # measured 4
    for k in (1, 2, 3):
        assert not np.isfinite(process_ping(test_pings[k], default).ranges.range_m).any()
