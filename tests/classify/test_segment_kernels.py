"""The classification stage's per-level kernels against the numpy forms they replace, bit for bit:
the MRF cost table (level_costs), numpy's pairwise float64 summation and the pD / pFA sums."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarmap.classify._kernels import _pairwise_sum, decision_rates_pmf
from sonarmap.classify.segment import decision_pd_pfa, level_costs

SPECIAL = np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, -50.0, -49.999, -50.001, -1e300, 1e300])


def _level_costs_numpy(lp, prior, floor):
    lp = np.asarray(lp, dtype=np.float64)
    if prior is not None:
        lp = lp + np.asarray(prior, dtype=np.float64).reshape(-1)[:, None]
    lp = np.nan_to_num(lp, nan=floor, neginf=floor, posinf=0.0)
    cost = -np.maximum(lp, floor)
    return cost - cost.min(axis=0, keepdims=True)


def _rates_numpy(pmf, det, prior):
    pfa = float(pmf[0][det].sum())
    pd = float((pmf[1:][:, det].sum(axis=1) * prior[1:]).sum() / max(float(prior[1:].sum()), 1e-300))
    return min(pd, 1.0), min(pfa, 1.0)


def _same(a, b):
    return a == b or (np.isnan(a) and np.isnan(b))


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_level_costs_matches_numpy(seed):
    """Same table (and argmin) as nan_to_num / maximum / min / subtract, with NaN, infinities,
    values at the floor and -inf priors."""
    rng = np.random.default_rng(seed)
    n_cls, n = int(rng.integers(2, 5)), int(rng.integers(1, 300))
    lp = rng.normal(-10, 20, (n_cls, n)) * rng.choice([1, 0.01, 100])
    special = rng.random((n_cls, n)) < 0.1
    lp[special] = rng.choice(SPECIAL, special.sum())
    prior = None if seed % 3 == 0 else np.log(rng.dirichlet(np.ones(n_cls)))
    if prior is not None and seed % 7 == 0:
        prior[rng.integers(n_cls)] = -np.inf
    floor = float(rng.choice([-50.0, -10.0, -1e3]))
    with np.errstate(invalid="ignore"):
        ref = _level_costs_numpy(lp, prior, floor)
    got = level_costs(lp, prior, floor=floor)
    np.testing.assert_array_equal(got, ref)
    np.testing.assert_array_equal(np.argmin(got, axis=0), np.argmin(ref, axis=0))


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(0, 3000), st.integers(0, 5))
def test_pairwise_sum_is_numpys(seed, n, lo):
    a = np.exp(np.random.default_rng(seed).normal(-8, 6, n + lo))
    assert _pairwise_sum(a, lo, n) == a[lo:lo + n].sum()


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([256, 1, 7, 129, 300, 1000]))
def test_two_class_rates_match_numpy(seed, n_levels):
    """pD / pFA of the kernel equal the numpy sums bit for bit (NaN pmf entries, zero object
    prior included), also through decision_pd_pfa."""
    rng = np.random.default_rng(seed)
    pmf = np.exp(rng.normal(-8, 6, (2, n_levels)))
    pmf /= pmf.sum(axis=1, keepdims=True)
    det = rng.random(n_levels) < rng.random()
    prior = rng.dirichlet(np.ones(2))
    if seed % 11 == 0:
        prior[1] = 0.0
    if seed % 13 == 0:
        pmf[0, rng.integers(n_levels)] = np.nan
    # read-only, as a fit's cached class pmf and prior reach the kernel (its one compiled signature)
    pmf.setflags(write=False)
    prior.setflags(write=False)
    ref = _rates_numpy(pmf, det, prior)
    got = decision_rates_pmf(pmf, det, prior)
    assert all(_same(a, b) for a, b in zip(got, ref))

    class _Fit:
        def class_pmf(self):
            return pmf

        def class_prior(self):
            return prior

    got = decision_pd_pfa(_Fit(), det.astype(np.int64) * 3)
    assert all(_same(a, b) for a, b in zip(got, ref))
