"""The exponential and Rayleigh evaluations and M-step solves of the pipeline's EM model run in
lockstep (``_eval_12``, ``_solve_12`` of sonarmap.stats._em_kernels): the same numbers, bit for
bit, as one component after the other, and the evaluations those of a plain numpy reference."""

from __future__ import annotations

import numpy as np

from sonarmap.stats import _em_kernels as K
from sonarmap.stats.components import quantization_levels


def _reference(kind: int, x: np.ndarray, eta: float) -> tuple[np.ndarray, float, float, float]:
    """``(u, Z, sum u T, sum u T^2)`` with an ``exp`` per level (numpy)."""
    u, t = (np.exp(eta * x), x) if kind == 1 else (x * np.exp(eta * x * x), x * x)
    return u, float(u.sum()), float((u * t).sum()), float((u * t * t).sum())


def _etas(rng: np.random.Generator) -> tuple[float, float]:
    """An exponential's and a Rayleigh's ``eta``: mostly decaying, now and then so steeply that
    the recurrence stops early (below 1e-300), or rising."""
    e1 = -float(np.exp(rng.uniform(-3.0, 12.0)))
    e2 = -float(np.exp(rng.uniform(-3.0, 14.0)))
    if rng.random() < 0.1:
        e1 = float(rng.uniform(0.0, 50.0))
    if rng.random() < 0.1:
        e2 = float(rng.uniform(0.0, 50.0))
    return e1, e2


def test_the_paired_evaluation_is_two_evaluations_bit_for_bit_and_the_reference():
    rng = np.random.default_rng(0)
    stopped = [0, 0]
    for n_levels in (2, 3, 16, 256, 1000):
        x = quantization_levels(n_levels)
        for _ in range(300):
            e1, e2 = _etas(rng)
            u1, u2, v1, v2 = (np.full(n_levels, 7.0) for _ in range(4))
            one = K._eval(1, x, e1, u1)
            two = K._eval(2, x, e2, u2)
            both = K._eval_12(x, e1, e2, v1, v2)
            assert both == one + two
            assert np.array_equal(u1, v1) and np.array_equal(u2, v2)
            for kind, eta, u, sums in ((1, e1, u1, one), (2, e2, u2, two)):
                ru, *rs = _reference(kind, x, eta)
                stopped[kind - 1] += bool(u[-1] == 0.0 and ru[-1] > 0.0)
                np.testing.assert_allclose(u, ru, rtol=1e-9, atol=1e-290)
                np.testing.assert_allclose(sums, rs, rtol=1e-9, atol=1e-290)
    assert min(stopped) > 0  # both recurrences were seen to stop early


def test_the_lockstep_solves_are_the_solves_one_after_the_other():
    rng = np.random.default_rng(1)
    x = quantization_levels(256)
    lo = np.array([[0.0, 0.0], [-2000.0, 0.0], [-20000.0, 0.0]])
    hi = np.array([[0.0, 0.0], [-0.5, 0.0], [-0.5, 0.0]])
    u = np.empty(x.size)
    m_lo = np.array([0.0] + [K._mean(k, x, lo[k, 0], u) for k in (1, 2)])
    m_hi = np.array([0.0] + [K._mean(k, x, hi[k, 0], u) for k in (1, 2)])
    for _ in range(400):
        targets = [float(np.exp(rng.uniform(np.log(0.5 * m_lo[k]), np.log(1.5 * m_hi[k])))) for k in (1, 2)]
        eta0 = np.zeros((3, 2))
        eta0[1:, 0] = [-float(np.exp(rng.uniform(0.0, 9.0))) for _ in range(2)]
        U1, U2 = np.empty((3, x.size)), np.empty((3, x.size))
        EC1, EC2 = np.full((3, 4), np.nan), np.full((3, 4), np.nan)
        if rng.random() < 0.5:  # a start already evaluated (the E-step's cache)
            K._eval_cached_12(x, eta0[1, 0], eta0[2, 0], U1, EC1)
            K._eval_cached_12(x, eta0[1, 0], eta0[2, 0], U2, EC2)
        alone = tuple(K._solve(k, x, targets[k - 1], eta0[k, 0], lo[k, 0], hi[k, 0], m_lo[k], m_hi[k], k, U1, EC1)
                      for k in (1, 2))
        paired = K._solve_12(x, targets[0], targets[1], eta0, lo, hi, m_lo, m_hi, U2, EC2)
        assert paired == alone
        assert np.array_equal(EC1, EC2, equal_nan=True) and np.array_equal(U1[1:], U2[1:])
