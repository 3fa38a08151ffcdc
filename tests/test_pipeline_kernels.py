"""The pipeline's kernels (:mod:`sonarmap._pipeline_kernels`) equal the numpy they replace."""

from __future__ import annotations

import numpy as np

from sonarmap._pipeline_kernels import any_columns
from sonarmap.pipeline import _labelled_columns


def test_any_columns_is_numpys_any_along_range() -> None:
    rng = np.random.default_rng(11)
    for shape in [(512, 96), (64, 16), (7, 3), (1, 1), (0, 4), (5, 0)]:
        for p in (0.0, 0.002, 0.4):
            for dtype in (np.uint8, np.uint16):
                labels = ((rng.random(shape) < p) * rng.integers(1, 300, shape)).astype(dtype)
                want = labels.any(axis=0)
                got = any_columns(labels)
                assert got.dtype == np.bool_ and np.array_equal(got, want)
                assert np.array_equal(_labelled_columns(labels), want)
                assert np.array_equal(_labelled_columns(np.asfortranarray(labels)), want)


def _p_detect_numpy(pd: float, pd_range: float, bins: np.ndarray, thickness: np.ndarray) -> np.ndarray:
    """``_p_detect``'s numpy form (before its kernels), NaN thicknesses included."""
    t = np.asarray(thickness, dtype=np.float64)
    valid = bins >= 0
    tv = t[valid]
    fill = float(np.median(tv)) if tv.size else 1.0
    t = np.where(valid, np.maximum(t, 1.0), max(fill, 1.0))
    f = 1.0 - (1.0 - min(pd, 1.0)) ** t
    fv = f[valid] if tv.size else f
    return (pd_range * f / max(float(fv.mean()), 1e-12)).clip(0.0, 1.0).astype(np.float32)


def test_p_detect_kernels_are_its_numpy_form() -> None:
    from sonarmap.pipeline import _p_detect
    from sonarmap.ranges import BeamRanges

    rng = np.random.default_rng(5)
    for n in (1, 2, 7, 16, 96, 257):
        for p_valid in (0.0, 0.3, 1.0):
            bins = np.where(rng.random(n) < p_valid, rng.integers(0, 500, n), -1).astype(np.int64)
            thick = [rng.integers(0, 12, n), rng.integers(0, 12, n).astype(np.float64)]
            thick[1][rng.random(n) < 0.1] = np.nan
            r = BeamRanges(range_m=np.where(bins >= 0, 1.0, np.nan), bin=bins, intensity=np.zeros(n, np.float32),
                           confidence=np.zeros(n, np.float32), azimuth_rad=np.zeros(n))
            for t in thick:
                for pd, pd_range in ((0.7, 0.5), (1.0, 0.9), (0.05, 2.0)):
                    with np.errstate(invalid="ignore"):
                        want = _p_detect_numpy(pd, pd_range, bins, t)
                    got = _p_detect(pd, pd_range, r, t)
                    assert got.dtype == np.float32
                    np.testing.assert_array_equal(got, want)


def test_return_counts_count_returns_and_labelled_columns_or_returns() -> None:
    from sonarmap._pipeline_kernels import return_counts

    rng = np.random.default_rng(3)
    for shape in [(512, 96), (64, 16), (3, 1), (0, 4)]:
        for p in (0.0, 0.002, 0.4):
            labels = (rng.random(shape) < p).astype(np.uint8)
            bins = np.where(rng.random(shape[1]) < 0.3, rng.integers(0, 50, shape[1]), -1).astype(np.int64)
            assert return_counts(labels, bins) == (np.count_nonzero(bins >= 0),
                                                   np.count_nonzero(labels.any(axis=0) | (bins >= 0)))
