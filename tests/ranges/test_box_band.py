"""Band pooling's box-mean threshold kernel: the same pixels as the box mean compared with the level."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.ranges import _kernels


@pytest.mark.parametrize("seed", range(4))
def test_box_band_is_the_box_mean_compared_with_the_level(seed: int) -> None:
    # random sizes (boxes wider than the image too), scales, quantised values (means exactly at
    # the level) and levels one float32 step either side of a pooled value
    rng = np.random.default_rng(seed)
    for t in range(300):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        s0, s1 = int(rng.integers(1, 8)), int(rng.integers(1, 50))
        img = (rng.random((h, w)) ** 3 * rng.choice([1.0, 100.0, 1e-3, 1e30])).astype(np.float32)
        if t % 5 == 0:
            img = np.round(img * 8) / 8
        pooled = _kernels.box_mean_f32(img, s0, s1)
        level = np.float32(rng.choice(pooled.ravel())) if t % 2 else np.float32(np.quantile(pooled, rng.random()))
        if t % 7 == 0:
            level = np.nextafter(level, np.float32(rng.choice([-np.inf, np.inf])))
        if t % 11 == 0:
            level = np.float32(rng.choice([0.0, -1.0, np.inf]))
        band, r0, r1, n_cols = _kernels.box_band(img, s0, s1, level)
        ref = pooled >= level
        np.testing.assert_array_equal(band, ref)
        rows = np.flatnonzero(ref.any(axis=1))
        assert (r0, r1) == ((int(rows[0]), int(rows[-1]) + 1) if rows.size else (h, 0))
        assert n_cols == int(ref.any(axis=0).sum())


def test_mean_threshold_is_the_least_sum_that_reaches_the_level() -> None:
    rng = np.random.default_rng(0)
    for level in np.concatenate([rng.random(200) * 10.0 ** rng.integers(-30, 30, 200), [1e-45, 3e38]]).astype(
            np.float32):
        for size in (1, 3, 9, 17):
            x = _kernels._mean_threshold(level, size)
            assert np.float32(x / size) >= level
            assert not np.float32(np.nextafter(x, -np.inf) / size) >= level


def test_union_extent_is_the_union_and_its_rows() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        h, w = (int(v) for v in rng.integers(1, 30, 2))
        a = rng.random((h, w)) < rng.random() * 0.1
        b = rng.random((h, w)) < rng.random() * 0.1
        out, r0, r1 = _kernels.union_extent(a, b)
        np.testing.assert_array_equal(out, a | b)
        rows = np.flatnonzero((a | b).any(axis=1))
        assert (r0, r1) == ((int(rows[0]), int(rows[-1]) + 1) if rows.size else (h, 0))
