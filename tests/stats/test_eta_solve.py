"""The exact M-step of the exponential and Rayleigh components (``_solve`` of
sonarmap.stats._em_kernels, via ``solve_eta_kind``): its root of ``E_eta[T] = target`` against a
long-double bisection.  The solver stops once a Newton step is below the resolution of its double
evaluation (``eps / h`` for the exponential, ``eps / h^2`` for the Rayleigh); its error must stay
at the level of the evaluation's rounding noise (measured: at most ~21 resolutions, the same
before and after that stop rule)."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.stats import _em_kernels as K
from sonarmap.stats.components import quantization_levels


def _mean_ld(kind: int, x: np.ndarray, eta: float) -> float:
    xl = x.astype(np.longdouble)
    e = np.longdouble(eta)
    u, t = (np.exp(e * xl), xl) if kind == 1 else (xl * np.exp(e * xl * xl), xl * xl)
    return float((u * t).sum() / u.sum())


def _root_ld(kind: int, x: np.ndarray, target: float, lo: float, hi: float) -> float:
    a, b = lo, hi
    while True:
        m = 0.5 * (a + b)
        if m in (a, b):
            return m
        if _mean_ld(kind, x, m) > target:
            b = m
        else:
            a = m


@pytest.mark.parametrize("n_levels", [64, 256])
@pytest.mark.parametrize("kind", [1, 2])
def test_solve_eta_is_the_root_to_the_evaluation_resolution(kind, n_levels):
    rng = np.random.default_rng(10 * kind + n_levels)
    x = quantization_levels(n_levels)
    h = x[1] - x[0]
    res = np.finfo(float).eps / (h if kind == 1 else h * h)
    smin, smax = 0.002, 1.0
    lo, hi = (-1 / smin, -1 / smax) if kind == 1 else (-1 / (2 * smin**2), -1 / (2 * smax**2))
    for _ in range(12):
        s = rng.uniform(0.01, 0.6)
        eta_true = -1 / s if kind == 1 else -1 / (2 * s * s)
        target = _mean_ld(kind, x, eta_true)
        eta = K.solve_eta_kind(kind, x, target, eta_true * rng.uniform(0.7, 1.3), lo, hi)
        ref = _root_ld(kind, x, target, lo, hi)
        assert abs(eta - ref) <= 40 * res + 1e-14 * abs(ref)
        assert abs(eta - ref) <= 1e-11 * abs(ref)


def test_solve_eta_clamps_to_the_bounds():
    x = quantization_levels(256)
    for kind in (1, 2):
        lo, hi = (-500.0, -1.0) if kind == 1 else (-1e5, -0.5)
        m_lo, m_hi = _mean_ld(kind, x, lo), _mean_ld(kind, x, hi)
        assert K.solve_eta_kind(kind, x, 0.5 * m_lo, -10.0, lo, hi) == lo
        assert K.solve_eta_kind(kind, x, min(1.0, 2 * m_hi), -10.0, lo, hi) == hi
