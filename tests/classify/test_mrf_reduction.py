"""The table-driven first reduction pass against the pixel test it replaces, and the level-table
graph cut (uint8 levels, the pipeline's path) against the unreduced solution - also with ties."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarmap.classify import mrf
from sonarmap.classify._kernels import free_graph, free_graph4, reduce_binary, reduce_chains, reduce_uniform4
from sonarmap.classify._ladders import reduce_ladders


def _problem(seed: int, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """uint8 levels and a 256-level margin table: quarter-integer margins (exact ties), normal
    ones, or bright stripes along the beams (long runs, as in sonar images)."""
    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(3, 48, 2))
    if kind == "ties":
        margin = rng.integers(-24, 25, 256) * 0.25
    else:
        margin = rng.normal(0, 3, 256)
    levels = rng.integers(0, 256, (h, w))
    if kind == "stripes":
        margin = np.sort(margin)
        levels = np.where(np.arange(h)[:, None] % 9 < 2, rng.integers(180, 256, (h, w)), rng.integers(0, 200, (h, w)))
    # read-only, as the pipeline passes levels to the kernels (one compiled signature each)
    return mrf._read_only(levels.astype(np.uint8)), margin


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.5, 1.0, 2.0, 1.37]), st.sampled_from([1.0, 0.25, 0.3]),
       st.sampled_from(["ties", "normal", "stripes"]))
def test_table_pass_equals_the_pixel_test(seed, beta, range_weight, kind):
    """:func:`reduce_uniform4` fixes the same pixels to the same labels and lists the same free
    pixels, in the same order, as the first pass of :func:`reduce_binary`; the chain reduction
    after either is the same too."""
    levels, margin = _problem(seed, kind)
    h, w = levels.shape
    wt, wtot = mrf._uniform(h, w, 4, beta, range_weight)
    pair = mrf._uniform_pair(wt)
    ref_fixed, ref_stack = np.empty((h, w), np.int8), np.empty(h * w + 1, np.int64)
    fixed, stack = np.empty((h, w), np.int8), np.empty(h * w + 1, np.int64)
    n_ref = reduce_binary(levels, margin, wt, wtot, ref_fixed, ref_stack, pair, 0)
    n = reduce_uniform4(levels, margin, wt, wtot, fixed, stack, pair[0], pair[1])
    assert n == n_ref
    np.testing.assert_array_equal(fixed, ref_fixed)
    np.testing.assert_array_equal(stack[:n], ref_stack[:n_ref])
    if n:
        n_ref = reduce_chains(levels, margin, ref_fixed, ref_stack, n_ref, pair[0], pair[1], 6)
        n = reduce_chains(levels, margin, fixed, stack, n, pair[0], pair[1], 6)
        assert n == n_ref
        np.testing.assert_array_equal(fixed, ref_fixed)
        np.testing.assert_array_equal(stack[:n], ref_stack[:n_ref])


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.5, 1.0, 2.0]), st.sampled_from([1.0, 0.25]),
       st.sampled_from(["ties", "normal", "stripes"]), st.sampled_from([None, 0]))
def test_level_table_cut_keeps_the_least_minimiser(seed, beta, range_weight, kind, rounds_min):
    """The pipeline's path (uint8 levels, a 256-level table, :func:`mrf.graphcut_levels_labels`)
    gives the labels of the single-pixel reduction with full sweeps and no chains, with exact ties
    too, and the full-lattice cut's energy (also with the rounds of ladders and chains of large
    images, ``rounds_min`` 0); the labels are a fresh array each call."""
    levels, margin = _problem(seed, kind)
    h, w = levels.shape
    lut = np.stack([np.maximum(margin, 0), np.maximum(-margin, 0)])
    with pytest.MonkeyPatch.context() as mp:
        if rounds_min is not None:
            mp.setattr(mrf, "_LADDER_ROUNDS_MIN", rounds_min)
        labels = mrf.graphcut_levels_labels(levels, lut, beta=beta, range_weight=range_weight)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mrf, "_CHAIN_PASSES", 0)
        mp.setattr(mrf, "_REDUCTION_SWEEPS", 256)
        ref = mrf.solve_graphcut_levels(levels, lut, beta=beta, range_weight=range_weight)
    assert labels.dtype == np.uint8
    np.testing.assert_array_equal(labels, ref.labels)
    wt = mrf.pairwise_weights((h, w), beta=beta, range_weight=range_weight)
    full = mrf.solve_graphcut(lut[:, levels], weights=wt, reduce=False)
    assert mrf.energy(labels, lut[:, levels], weights=wt) == pytest.approx(full.energy, abs=1e-9)
    again = mrf.graphcut_levels_labels(levels, lut, beta=beta, range_weight=range_weight)
    assert not np.shares_memory(again, labels)
    np.testing.assert_array_equal(again, labels)


def _chained(levels: np.ndarray, margin: np.ndarray, beta: float, range_weight: float, chain_passes: int
             ) -> tuple[np.ndarray, float, float, np.ndarray, np.ndarray, int]:
    """``(wt, wr, wb, fixed, stack, n_free)`` after the first reduction pass and ``chain_passes``
    chain passes (uniform 4-neighbourhood weights)."""
    h, w = levels.shape
    wt, wtot = mrf._uniform(h, w, 4, beta, range_weight)
    wr, wb = float(wt[0, 1, 1]), float(wt[1, 1, 1])
    fixed, stack = np.empty((h, w), np.int8), np.empty(h * w + 1, np.int64)
    n = reduce_uniform4(levels, margin, wt, wtot, fixed, stack, wr, wb)
    if n and chain_passes:
        n = reduce_chains(levels, margin, fixed, stack, n, wr, wb, chain_passes)
    return wt, wr, wb, fixed, stack, n


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.0, 0.5, 2.0, 1.37]), st.sampled_from([1.0, 0.25, 0.3]),
       st.sampled_from(["ties", "normal", "stripes"]), st.sampled_from([0, 1, 6]))
def test_uniform_free_graph_equals_the_general_one(seed, beta, range_weight, kind, chain_passes):
    """:func:`free_graph4` (scalar weights, no node map) gives the arrays of :func:`free_graph`
    with the uniform weight array, bit for bit, after the first pass and after chain passes."""
    levels, margin = _problem(seed, kind)
    h, w = levels.shape
    wt, wr, wb, fixed, stack, n = _chained(levels, margin, beta, range_weight, chain_passes)
    ref = free_graph(levels, margin, wt, fixed, np.empty((h, w), np.int64), stack, n)
    got = free_graph4(levels, margin, fixed, stack, n, wr, wb)
    for a, b in zip(got, ref, strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.5, 1.0, 2.0, 1.37]), st.sampled_from([1.0, 0.25, 0.3]),
       st.sampled_from(["ties", "normal", "stripes"]), st.sampled_from([1, 3]))
def test_ladders_fix_only_persistent_labels(seed, beta, range_weight, kind, passes):
    """Every pixel :func:`reduce_ladders` fixes has that label in the least and in the greatest
    minimiser of the unreduced problem (so in every one), also with exact ties; the free list
    stays the free pixels in ascending raster order."""
    levels, margin = _problem(seed, kind)
    wt, wr, wb, fixed, stack, n = _chained(levels, margin, beta, range_weight, 6)
    before = fixed.copy()
    if n:
        n = reduce_ladders(levels, margin, fixed, stack, n, wr, wb, passes)
    np.testing.assert_array_equal(stack[:n], np.flatnonzero(fixed.ravel() < 0))
    lut = np.stack([np.maximum(margin, 0), np.maximum(-margin, 0)])
    least = mrf.solve_graphcut(lut[:, levels], weights=wt, reduce=False).labels
    # the greatest minimiser: the least one of the problem with the labels swapped
    greatest = 1 - mrf.solve_graphcut(lut[::-1][:, levels], weights=wt, reduce=False).labels
    new = (before < 0) & (fixed >= 0)
    np.testing.assert_array_equal(fixed[new], least[new])
    np.testing.assert_array_equal(fixed[new], greatest[new])
