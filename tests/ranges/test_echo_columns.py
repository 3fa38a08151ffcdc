"""Echoes of some beams only (``find_echoes(columns=...)``) spliced into a ping's echoes
(:func:`sonarmap.ranges.echoes.spliced_echoes`) are the echoes of the whole ping, bit for bit - the
second measuring pass of :func:`sonarmap.ranges.measure.surface_ranges` relies on it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sonarmap.geometry import SonarGeometry
from sonarmap.ranges.echoes import find_echoes, spliced_echoes


@pytest.mark.parametrize("seed", range(16))
def test_spliced_columns_equal_whole_ping(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(8, 120)), int(rng.integers(1, 30))
    geom = SonarGeometry(range_m=1.0 + 0.01 * np.arange(n), azimuth_rad=np.linspace(-0.3, 0.3, m),
                         azimuth_beamwidth_rad=0.02)
    img = rng.exponential(1.0, (n, m)).astype(np.float32)
    levels = rng.integers(0, 16, (n, m)).astype(np.uint8)
    lut = rng.normal(0.5, 1.0, 16)
    boost = rng.random((n, m)) < 0.05 if seed % 3 == 0 else None
    before = rng.random((n, m)) < rng.uniform(0.02, 0.4)
    cols = np.flatnonzero(rng.random(m) < 0.3).astype(np.int64)
    after = before.copy()
    after[:, cols] |= rng.random((n, cols.size)) < 0.1
    kw = dict(levels=levels, level_evidence=lut, boost=boost, pulse_bins=int(rng.integers(1, 4)),
              background=0.3, scan="forward" if seed % 2 else "back")
    full = np.flatnonzero(after.any(axis=1))
    span = (int(full[0]), int(full[-1]) + 1) if full.size and seed % 4 == 1 else None
    whole = find_echoes(after, img, geom, rows=span, **kw)
    assert whole.size == find_echoes(after, img, geom, **kw).size
    hit = np.flatnonzero(after[:, cols].any(axis=1))
    rows = (int(hit[0]), int(hit[-1]) + 1) if hit.size and seed % 2 else None
    part = find_echoes(after, img, geom, columns=cols, rows=rows, **kw)
    assert set(part.beam.tolist()) <= set(cols.tolist())
    got = spliced_echoes(find_echoes(before, img, geom, **kw), part, cols)
    for f in dataclasses.fields(whole):
        a, b = getattr(whole, f.name), getattr(got, f.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), f.name
        else:
            assert a == b, f.name


@pytest.mark.parametrize("seed", range(4))
def test_column_counts_are_numpys_cumulative_column_sums(seed: int) -> None:
    """``_column_counts`` (find_echoes' first pass) against numpy: the running total of each
    column's true pixels on rows ``r0 .. r1 - 1``."""
    from sonarmap.ranges._kernels import _column_counts

    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(1, 300)), int(rng.integers(1, 70))
    mask = rng.random((n, m)) < rng.uniform(0.0, 0.8)
    for r0, r1 in ((0, n), (n // 3, n - n // 4), (n // 2, n // 2)):
        ref = np.concatenate([[0], np.cumsum(mask[r0:r1].sum(axis=0))])
        assert np.array_equal(_column_counts(mask, r0, r1), ref)


@pytest.mark.parametrize("seed", range(8))
def test_spliced_fields_kernel_is_numpys_stable_gather(seed: int) -> None:
    """With ``clipped`` and ``clip_row`` set (the range stage's echoes) the splice runs in one kernel
    (``_kernels.spliced_fields``): numpy's stable argsort by beam of the old echoes off ``columns``
    and the new ones, every field gathered from the two concatenated."""
    rng = np.random.default_rng(100 + seed)
    n, m = 60, int(rng.integers(2, 30))
    geom = SonarGeometry(range_m=1.0 + 0.01 * np.arange(n), azimuth_rad=np.linspace(-0.3, 0.3, m),
                         azimuth_beamwidth_rad=0.02)
    img = rng.exponential(1.0, (n, m)).astype(np.float32)
    cols = np.flatnonzero(rng.random(m) < 0.4).astype(np.int64)

    def echoes(mask: np.ndarray, columns: np.ndarray | None = None) -> object:
        e = find_echoes(mask, img, geom, columns=columns)
        return e.replaced(clipped=rng.random(e.size) < 0.3, clip_row=rng.integers(-1, n, e.size))

    old = echoes(rng.random((n, m)) < 0.2)
    new = echoes(rng.random((n, m)) < 0.2, cols)
    got = spliced_echoes(old, new, cols)
    kept = np.flatnonzero(~np.isin(old.beam, cols))
    take = np.concatenate([kept, old.size + np.arange(new.size)])[
        np.argsort(np.concatenate([old.beam[kept], new.beam]), kind="stable")]
    for f in dataclasses.fields(old):
        a = getattr(old, f.name)
        if isinstance(a, np.ndarray) and f.name != "beamwidth_beams":
            want = np.concatenate([a, getattr(new, f.name)])[take]
            assert getattr(got, f.name).dtype == want.dtype and np.array_equal(getattr(got, f.name), want), f.name
