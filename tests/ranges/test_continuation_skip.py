"""``measure._continuation`` returns None without calling ``continuation_extra`` when the
continuation mask holds no pixel: that kernel keeps none of an empty mask.  The kernel reads
only the rows of each column that the continuation mask filled."""

from __future__ import annotations

import numpy as np

from sonarmap.ranges._kernels import continuation_extra


def test_an_empty_continuation_mask_keeps_nothing() -> None:
    rng = np.random.default_rng(8)
    for _ in range(200):
        n, m = int(rng.integers(1, 80)), int(rng.integers(1, 40))
        extra = np.zeros((n, m), dtype=bool)
        cand = rng.random((n, m)) < rng.random()
        edge_bin = rng.random(5) * n
        first = rng.integers(-1, 5, m)
        col_lo = rng.integers(-2, n + 3, m)
        col_hi = rng.integers(-2, n + 3, m)
        out, hit, cols, e0, e1 = continuation_extra(extra, cand, first, edge_bin, col_lo, col_hi)
        assert not hit and cols.size == 0 and (e0, e1) == (n, 0) and not out.any()


def _reference(extra: np.ndarray, cand: np.ndarray, first: np.ndarray, edge_bin: np.ndarray, r0: int,
               r1: int) -> tuple[np.ndarray, bool, np.ndarray, int, int]:
    """The kernel's result from a walk over whole rows ``r0 .. r1 - 1`` of both masks."""
    n, m = extra.shape
    out = extra.copy()
    top = np.full(m, n)
    for i in range(r0, r1):
        for j in range(m):
            if out[i, j]:
                if cand[i, j]:
                    out[i, j] = False
                elif top[j] == n:
                    top[j] = i
    keep = (top < n) & ((first < 0) | (top < edge_bin[np.maximum(first, 0)]))
    e0, e1 = n, 0
    if keep.any():
        for i in range(r0, r1):
            for j in range(m):
                if out[i, j]:
                    if not keep[j]:
                        out[i, j] = False
                    else:
                        e0, e1 = min(e0, i), i + 1
    return out, bool(keep.any()), np.flatnonzero(keep), e0, e1


def test_the_kept_pixels_are_those_of_the_whole_mask() -> None:
    rng = np.random.default_rng(9)
    for _ in range(300):
        n, m = int(rng.integers(1, 60)), int(rng.integers(1, 30))
        col_lo = rng.integers(0, n, m)
        col_hi = np.minimum(col_lo + rng.integers(0, 12, m), n)
        extra = np.zeros((n, m), dtype=bool)
        for j in range(m):
            extra[col_lo[j]:col_hi[j], j] = rng.random(col_hi[j] - col_lo[j]) < 0.7
        cand = rng.random((n, m)) < 0.3 * rng.random()
        edge_bin = rng.random(5) * n
        first = rng.integers(-1, 5, m)
        ref = _reference(extra, cand, first, edge_bin, int(col_lo.min()), int(col_hi.max()))
        out, hit, cols, e0, e1 = continuation_extra(extra.copy(), cand, first, edge_bin, col_lo, col_hi)
        np.testing.assert_array_equal(out, ref[0])
        np.testing.assert_array_equal(cols, ref[2])
        assert (hit, e0, e1) == (ref[1], ref[3], ref[4])


def test_the_continuation_masks_column_rows_are_those_it_marked() -> None:
    """``continuation_mask``'s per-column rows (what ``continuation_extra`` reads) are the first and
    one-past-last row it marked in the column, the beams searched again between two found ones
    included; ``(n, 0)`` in a column it did not mark."""
    from sonarmap.ranges._kernels import continuation_mask

    n, m = 120, 40
    marked = 0
    for seed in range(30):
        rng = np.random.default_rng(seed)
        levels = rng.integers(0, 256, (n, m)).astype(np.uint8)
        lut = rng.uniform(-1.0, 2.0, 256)
        beams = np.arange(m)
        edge = np.where((beams >= 12) & (beams < 26), 50.0 + 1.5 * (beams - 12) + rng.normal(0, 0.3, m), np.nan)
        stop = edge + 5.0
        run = np.where(np.isfinite(edge), 0, -1).astype(np.int64)
        out, r_lo, r_hi, col_lo, col_hi = continuation_mask(levels, lut, edge, stop, run, 5, 16, 3.0, 6.0, 2)
        for j in range(m):
            rows = np.flatnonzero(out[:, j])
            assert (col_lo[j], col_hi[j]) == ((rows[0], rows[-1] + 1) if rows.size else (n, 0))
        rows = np.flatnonzero(out.any(axis=1))
        assert (r_lo, r_hi) == ((rows[0], rows[-1] + 1) if rows.size else (n, 0))
        marked += int(out.any())
    assert marked > 0
