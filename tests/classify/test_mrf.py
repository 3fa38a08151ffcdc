"""MRF model and solvers: energies, brute force, graph cut vs ICM/annealing, reductions."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarmap.classify import mrf
from sonarmap.errors import InputError


def _brute(u: np.ndarray, wt: np.ndarray) -> float:
    n_labels, h, w = u.shape
    best = np.inf
    for combo in itertools.product(range(n_labels), repeat=h * w):
        best = min(best, mrf.energy(np.array(combo).reshape(h, w), u, weights=wt))
    return best


problem = st.tuples(
    st.integers(0, 2**31 - 1),            # seed
    st.floats(0.0, 2.0),                  # beta
    st.sampled_from([4, 8]),              # neighbourhood
)


@settings(max_examples=25, deadline=None)
@given(problem)
def test_graphcut_matches_brute_force_3x3_binary(p):
    seed, beta, nb = p
    rng = np.random.default_rng(seed)
    u = rng.normal(0, 1, (2, 3, 3))
    wt = mrf.pairwise_weights((3, 3), beta=beta, neighbourhood=nb)
    best = _brute(u, wt)
    for reduce in (True, False):
        res = mrf.solve_graphcut(u, weights=wt, reduce=reduce)
        assert res.exact
        assert res.energy == pytest.approx(best, abs=1e-9)
        assert res.energy == pytest.approx(mrf.energy(res.labels, u, weights=wt))


@settings(max_examples=25, deadline=None)
@given(problem)
def test_expansion_three_labels_2x3_vs_brute_force(p):
    seed, beta, nb = p
    rng = np.random.default_rng(seed)
    u = rng.uniform(0, 2, (3, 2, 3))  # non-negative unaries: the Potts 2-approximation applies
    wt = mrf.pairwise_weights((2, 3), beta=beta, neighbourhood=nb)
    best = _brute(u, wt)
    res = mrf.solve(u, weights=wt)  # graphcut with 3 labels -> alpha-expansion
    assert res.solver == "expansion"
    assert best - 1e-9 <= res.energy <= 2 * best + 1e-9
    # no single expansion move can improve the result (it is a local minimum w.r.t. expansions)
    for alpha in range(3):
        x = mrf.solve_expansion(u, weights=wt, init=res.labels, max_cycles=1)
        assert x.energy >= res.energy - 1e-9


def test_expansion_exact_when_unaries_dominate():
    rng = np.random.default_rng(3)
    truth = rng.integers(0, 3, (2, 3))
    u = np.full((3, 2, 3), 5.0)
    np.put_along_axis(u, truth[None], 0.0, axis=0)
    wt = mrf.pairwise_weights((2, 3), beta=0.5)
    res = mrf.solve_expansion(u, weights=wt)
    assert res.energy == pytest.approx(_brute(u, wt))
    np.testing.assert_array_equal(res.labels, truth)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.2, 2.0), st.sampled_from([4, 8]), st.booleans())
def test_graphcut_never_above_icm_or_anneal(seed, beta, nb, contrast):
    rng = np.random.default_rng(seed)
    img = rng.random((24, 16))
    u = np.stack([np.zeros_like(img), rng.normal(0, 2, img.shape)])
    wt = mrf.pairwise_weights(img.shape, beta=beta, neighbourhood=nb, image=img, contrast=contrast)
    gc = mrf.solve_graphcut(u, weights=wt)
    icm = mrf.solve_icm(u, weights=wt)
    ann = mrf.solve_anneal(u, weights=wt, seed=seed, schedule=mrf.AnnealSchedule(n_sweeps=15))
    assert gc.energy <= icm.energy + 1e-9
    assert gc.energy <= ann.energy + 1e-9
    # full-lattice cut (no reduction) reaches the same optimum
    assert mrf.solve_graphcut(u, weights=wt, reduce=False).energy == pytest.approx(gc.energy)


def test_reduction_fixes_dominant_pixels_and_denoises():
    rng = np.random.default_rng(0)
    truth = np.zeros((60, 40), dtype=np.int32)
    truth[20:30, 5:35] = 1
    noisy = np.where(rng.random(truth.shape) < 0.1, 1 - truth, truth)
    # strong unaries: most pixels are fixed by persistency, and the result is still the optimum
    u = np.stack([2.5 * (noisy == 1), 2.5 * (noisy == 0)]).astype(np.float64)
    res = mrf.solve_graphcut(u, beta=1.0)
    assert res.n_free < truth.size // 4
    full = mrf.solve_graphcut(u, beta=1.0, reduce=False)
    assert res.energy == pytest.approx(full.energy)
    # weaker unaries: the Potts prior removes isolated flips
    u = np.stack([1.5 * (noisy == 1), 1.5 * (noisy == 0)]).astype(np.float64)
    res = mrf.solve_graphcut(u, beta=1.0)
    assert (noisy != truth).mean() > 0.05
    assert (res.labels != truth).mean() < 0.01
    assert res.energy <= mrf.solve_icm(u, beta=1.0).energy


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.5, 1.0, 2.0]), st.sampled_from([1.0, 0.25]),
       st.sampled_from(["ties", "normal", "stripes"]))
def test_chain_reduction_keeps_the_least_minimiser(seed, beta, range_weight, kind):
    """The chain reduction (uniform 4-neighbourhood) fixes only pixels with one label in every
    minimiser: the labels equal the cut after the single-pixel reduction alone - also with exact
    ties (quarter-integer costs, where the cut reports the least minimiser) - and the energy is the
    full-lattice cut's."""
    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(3, 40, 2))
    if kind == "ties":
        margin = rng.integers(-16, 17, (h, w)) * 0.25
    elif kind == "normal":
        margin = rng.normal(0, 3, (h, w))
    else:                                   # long runs along the beams, as in sonar images
        margin = rng.normal(0, 1.5, (h, w)) + np.where(np.arange(h)[:, None] % 9 < 2, 3.0, -1.0)
    lut = np.stack([np.maximum(margin, 0), np.maximum(-margin, 0)]).reshape(2, -1)
    levels = np.arange(h * w).reshape(h, w)
    res = mrf.solve_graphcut_levels(levels, lut, beta=beta, range_weight=range_weight)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mrf, "_CHAIN_PASSES", 0)
        mp.setattr(mrf, "_REDUCTION_SWEEPS", 256)
        ref = mrf.solve_graphcut_levels(levels, lut, beta=beta, range_weight=range_weight)
    np.testing.assert_array_equal(res.labels, ref.labels)
    assert res.n_free <= ref.n_free
    wt = mrf.pairwise_weights((h, w), beta=beta, range_weight=range_weight)
    full = mrf.solve_graphcut(lut.reshape(2, h, w), weights=wt, reduce=False)
    assert res.energy == pytest.approx(full.energy, abs=1e-9)


def test_chain_reduction_decides_runs_the_pixel_test_cannot():
    """A range bin of weak evidence across the beams (margin 2: 1 after its edges to the background
    bins, below the weight 2 wb of its free edges along the bin) is decided by the chains: nothing
    is left to the cut."""
    margin = np.full((12, 30), -6.0)
    margin[5] = 2.0
    lut = np.stack([np.maximum(margin, 0), np.maximum(-margin, 0)]).reshape(2, -1)
    levels = np.arange(margin.size).reshape(margin.shape)
    res = mrf.solve_graphcut_levels(levels, lut, beta=2.0, range_weight=0.25)
    assert res.n_free == 0
    np.testing.assert_array_equal(res.labels, (margin > 0).astype(np.uint8))


def test_energy_counts_unary_and_cut_edges():
    u = np.zeros((2, 2, 2))
    u[1, 0, 0] = 1.5
    lab = np.array([[1, 0], [0, 0]])
    assert mrf.energy(lab, u, beta=2.0) == pytest.approx(1.5 + 2 * 2.0)
    assert mrf.energy(lab, u, beta=2.0, neighbourhood=8) == pytest.approx(1.5 + 4.0 + 2.0 / np.sqrt(2))


def test_unary_from_log_likelihood_and_bad_inputs():
    lp = np.log(np.array([[0.9, 0.1], [0.2, 0.8]]))
    u = mrf.unary_from_log_likelihood(np.array([[0, 1]]), lp, np.log([0.5, 0.5]))
    assert u.shape == (2, 1, 2)
    assert u[1, 0, 0] == pytest.approx(np.log(0.9 / 0.2), rel=1e-6)
    assert u[0, 0, 1] == pytest.approx(np.log(0.8 / 0.1), rel=1e-6)
    with pytest.raises(InputError, match="unary"):
        mrf.solve_graphcut(np.zeros((3, 2, 2)))
    with pytest.raises(InputError, match="beta"):
        mrf.solve_icm(np.zeros((2, 2, 2)), beta=-1)
    with pytest.raises(InputError, match="solver"):
        mrf.solve(np.zeros((2, 2, 2)), solver="nope")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="unary"):
        mrf.solve_icm(np.full((2, 2, 2), np.nan))


def test_anneal_deterministic_per_seed():
    rng = np.random.default_rng(1)
    u = rng.normal(0, 1, (3, 10, 8))
    a = mrf.solve_anneal(u, beta=0.7, seed=5)
    b = mrf.solve_anneal(u, beta=0.7, seed=5)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert a.energy == pytest.approx(mrf.energy(a.labels, u, beta=0.7))


def test_range_weight_scales_range_edges_only():
    w = mrf.pairwise_weights((4, 3), beta=2.0, range_weight=0.25)
    assert w[0, 0, 0] == pytest.approx(0.5) and w[1, 0, 0] == pytest.approx(2.0)
    assert w[0, -1].sum() == 0 and w[1, :, -1].sum() == 0
    rng = np.random.default_rng(0)
    u = rng.normal(0, 1, (2, 3, 3))
    wt = mrf.pairwise_weights((3, 3), beta=1.0, range_weight=0.3)
    assert mrf.solve_graphcut(u, weights=wt).energy == pytest.approx(_brute(u, wt))
    lev = np.arange(9).reshape(3, 3)
    a = mrf.solve_graphcut_levels(lev, u.reshape(2, 9), beta=1.0, range_weight=0.3)
    assert a.energy == pytest.approx(_brute(u, wt))
