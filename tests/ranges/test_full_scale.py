"""The receiver's full scale per ping (``full_scale_level``) and clipped echoes that are not the
first peak of their echo."""

from __future__ import annotations

import numpy as np
import pytest

import sonarmap.ranges.measure as measure
from sonarmap.geometry import SonarGeometry
from sonarmap.pipeline import PipelineConfig, process_ping
from sonarmap.ranges.echoes import find_echoes, pooled_edges
from sonarmap.ranges.measure import CLIP_LEVEL, PILEUP_MIN_SAMPLES, full_scale_level

CODE_254 = float(np.float32(254 / 255))


def _speckle(seed: int = 0, shape: tuple[int, int] = (400, 64)) -> np.ndarray:
    """Rayleigh speckle on the 8-bit grid, far below full scale."""
    rng = np.random.default_rng(seed)
    return (np.floor(np.minimum(rng.rayleigh(0.1, shape), 0.9) * 255) / 255).astype(np.float32)


def test_without_a_pileup_the_level_is_the_top_code() -> None:
    img = _speckle()
    assert full_scale_level(img) == CLIP_LEVEL
    # a few samples at the maximum are the tail of the histogram, not a saturated receiver
    few = img.copy()
    few.flat[:PILEUP_MIN_SAMPLES - 1] = CODE_254
    assert full_scale_level(few) == CLIP_LEVEL
    # as many at the maximum as on the codes below it: no pile-up
    flat = np.repeat((np.arange(246, 255) / 255).astype(np.float32), 100).reshape(9, 100)
    assert full_scale_level(flat) == CLIP_LEVEL
    for bad in (np.zeros((0, 4), np.float32), np.full((8, 8), np.nan, np.float32), np.zeros((8, 8), np.float32)):
        assert full_scale_level(bad) == CLIP_LEVEL


def test_a_pileup_below_the_top_code_is_the_full_scale() -> None:
    img = _speckle()
    img[200:203] = CODE_254  # a saturated band of 192 samples at code 254
    assert full_scale_level(img) == CODE_254
    assert measure.full_scale_mask(img, full_scale_level(img)).sum() == 192
    # at code 255 the nominal level holds
    img[200:203] = 1.0
    assert full_scale_level(img) == CLIP_LEVEL


def test_the_real_recordings_full_scale(test_pings: list, aris_pings: list, oculus_pings: list) -> None:
    """The real Oculus M-series pings saturate at code 254 (1364-1514 samples per ping there, none
    at 255); the DIDSON and ARIS pings never reach full scale."""
    for p in oculus_pings:
        level = full_scale_level(p.image)
        assert level == float(p.image.max()) and abs(255 * level - 254) < 1e-3
        assert 1300 < np.sum(p.image >= level) < 1600
    assert all(full_scale_level(p.image) == CLIP_LEVEL for p in [*test_pings, *aris_pings])


def test_the_real_oculus_seabed_measured_with_its_own_full_scale(
        oculus_pings: list, monkeypatch: pytest.MonkeyPatch) -> None:
    """With the pings' own full scale (254) the seabed's saturated samples count as clipped.  Most
    sit inside the seabed's echo, behind its front, and move nothing: the clipped-echo fit applies
    only to an echo's first peak.  Where the front itself saturates (ping 0, beams 173-203) the fit
    moves the edge along the rise by at most a few bins; the sigmas of the clipped returns change.
    (Without the first-peak test the fit through deep clipped peaks moved edges 20-75 bins into
    the seabed on pings 1 and 2.)"""
    moved, changed = [], 0
    for p in oculus_pings:
        own = process_ping(p, PipelineConfig()).ranges
        with monkeypatch.context() as m:
            m.setattr(measure, "full_scale_level", lambda raw, top=None: CLIP_LEVEL)
            nominal = process_ping(p, PipelineConfig()).ranges
        assert np.isfinite(own.range_m).sum() == np.isfinite(nominal.range_m).sum() == 256
        moved.append(np.abs(own.range_m - nominal.range_m) / p.geometry.range_resolution_m)
        changed += int(np.sum(own.sigma_m != nominal.sigma_m))
    d = np.concatenate(moved)
    assert d.max() < 5.0 and np.mean(d <= 1.0) > 0.95  # measured 3.65, 0.977
    assert 20 <= changed <= 250  # measured 112 of 768


def test_a_deep_clipped_peak_is_not_fitted_as_the_echos_first() -> None:
    """A long echo (a seabed) on a pooled profile: its front rises to 0.7 of full scale and
    crosses half the clipped maximum at bin 51.75, one sample at full scale at bin 57, a floor,
    and far behind an echo three times full scale, clipped over bins 90-100.  The Gaussian
    through the deep clipped run's flanks - its rising flank reaches back only to bin 58, behind
    the front's crossing - is not the first peak's: the fit is refused (the pooled edge stays
    the front's crossing), while without that test it would put the edge at bin 90.3."""
    from sonarmap.ranges._kernels import _clipped_box_edge

    n = 200
    r = np.arange(n, dtype=float)
    prof = np.zeros(n)
    prof[50:54] = [0.15, 0.35, 0.55, 0.7]
    prof[54:62] = 0.7
    prof[62:80] = 0.3
    prof = np.maximum(prof, np.minimum(3.0 * np.exp(-0.5 * ((r - 95.0) / 4.0) ** 2), 1.0))
    prof[110:] = 0.0
    clipped = prof >= 1.0
    clipped[57] = True
    peak = int(np.argmax(prof))
    assert not _clipped_box_edge(prof, clipped, 0, 0, n, peak, 0.5, 110, 51.75)[0]
    ok, x, *_ = _clipped_box_edge(prof, clipped, 0, 0, n, peak, 0.5, 110, 1e9)
    assert ok and 89.0 < x < 92.0
    # a clipped first peak whose rising flank reaches the crossing is still fitted
    first = np.zeros(n)
    first[50:120] = np.minimum(3.0 * np.exp(-0.5 * ((r[50:120] - 70.0) / 4.0) ** 2), 1.0)
    ok, x, *_ = _clipped_box_edge(first, first >= 1.0, 0, 0, n, int(np.argmax(first)), 0.5, 120, 62.4)
    assert ok and abs(x - (70.0 - 4.0 * np.sqrt(2.0 * np.log(2.0)))) < 0.1
