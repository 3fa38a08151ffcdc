"""numba kernel: EM on histogram counts for one-parameter exponential-family pmfs + fixed pmfs.

Each component ``c`` has a pmf on the levels of the form
``p_c(k) = exp(logB[c, k] + eta[c] T[c, k] - A(eta[c]))`` (exponential: ``T = x, eta = -1/s``;
Rayleigh: ``T = x^2, logB = log x, eta = -1 / (2 s^2)``); components with ``free[c] = False``
(the zero spike) keep their pmf.  The M-step for ``eta`` is exact: the expected log-likelihood of a
one-parameter exponential family is concave in ``eta``; its maximiser on ``[lo, hi]`` solves
``E_eta[T] = mean_r[T]`` (moment matching), found by safeguarded Newton.  So the log-likelihood
never decreases (the EM property), up to floating-point rounding.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _log_normalise(logB: np.ndarray, T: np.ndarray, eta: float, out: np.ndarray) -> None:
    L = logB.shape[0]
    m = -np.inf
    for k in range(L):
        v = logB[k] + eta * T[k]
        out[k] = v
        if v > m:
            m = v
    s = 0.0
    for k in range(L):
        if out[k] > -np.inf:
            s += np.exp(out[k] - m)
    lz = m + np.log(s)
    for k in range(L):
        out[k] -= lz


@njit(cache=True)
def _moments(logB: np.ndarray, T: np.ndarray, eta: float, work: np.ndarray) -> tuple[float, float]:
    _log_normalise(logB, T, eta, work)
    e1 = 0.0
    e2 = 0.0
    for k in range(T.shape[0]):
        if work[k] > -np.inf:
            p = np.exp(work[k])
            e1 += p * T[k]
            e2 += p * T[k] * T[k]
    return e1, max(e2 - e1 * e1, 0.0)


@njit(cache=True)
def solve_eta(
    logB: np.ndarray, T: np.ndarray, target: float, eta0: float, lo: float, hi: float
) -> float:
    """``eta`` in ``[lo, hi]`` with ``E_eta[T] = target`` (clamped to the bounds)."""
    work = np.empty(T.shape[0])
    m_lo, _ = _moments(logB, T, lo, work)
    if target <= m_lo:
        return lo
    m_hi, _ = _moments(logB, T, hi, work)
    if target >= m_hi:
        return hi
    a = lo
    b = hi
    eta = min(max(eta0, lo), hi)
    for _ in range(100):
        m, v = _moments(logB, T, eta, work)
        g = m - target
        if abs(g) <= 1e-13 * (abs(target) + 1e-300):
            break
        if g > 0:
            b = eta
        else:
            a = eta
        step = g / v if v > 0 else 0.0
        nxt = eta - step
        if not (a < nxt < b) or v <= 0:
            nxt = 0.5 * (a + b)
        if abs(nxt - eta) <= 1e-14 * (abs(eta) + 1.0):
            eta = nxt
            break
        eta = nxt
    return eta


@njit(cache=True)
def em_expfam(
    counts: np.ndarray,
    T: np.ndarray,
    logB: np.ndarray,
    eta: np.ndarray,
    w: np.ndarray,
    free: np.ndarray,
    eta_lo: np.ndarray,
    eta_hi: np.ndarray,
    max_iter: int,
    tol: float,
    ll_trace: np.ndarray,
) -> tuple[int, bool]:
    """Run EM in place on ``eta`` and ``w``; returns ``(n_iter, converged)``.

    ``ll_trace[i]`` receives the log-likelihood at the parameters *entering* iteration ``i``;
    ``ll_trace[n_iter]`` that of the returned parameters.
    """
    C, L = T.shape
    N = 0.0
    for k in range(L):
        N += counts[k]
    logp = np.empty((C, L))
    resp = np.empty((C, L))
    Nc = np.empty(C)
    tbar = np.empty(C)
    converged = False
    it = 0
    ll_prev = -np.inf
    while True:
        for c in range(C):
            _log_normalise(logB[c], T[c], eta[c], logp[c])
        ll = 0.0
        for c in range(C):
            Nc[c] = 0.0
            tbar[c] = 0.0
        for k in range(L):
            n = counts[k]
            if n <= 0:
                continue
            m = -np.inf
            for c in range(C):
                if w[c] > 0 and logp[c, k] > -np.inf:
                    v = np.log(w[c]) + logp[c, k]
                    resp[c, k] = v
                    if v > m:
                        m = v
                else:
                    resp[c, k] = -np.inf
            s = 0.0
            for c in range(C):
                if resp[c, k] > -np.inf:
                    resp[c, k] = np.exp(resp[c, k] - m)
                    s += resp[c, k]
                else:
                    resp[c, k] = 0.0
            ll += n * (m + np.log(s))
            for c in range(C):
                r = n * resp[c, k] / s
                Nc[c] += r
                tbar[c] += r * T[c, k]
        ll_trace[it] = ll
        if it > 0 and ll - ll_prev <= tol * (abs(ll) + 1.0):
            converged = True
            break
        if it >= max_iter:
            break
        ll_prev = ll
        for c in range(C):
            w[c] = Nc[c] / N
            if free[c] and Nc[c] > 0:
                eta[c] = solve_eta(logB[c], T[c], tbar[c] / Nc[c], eta[c], eta_lo[c], eta_hi[c])
        it += 1
    return it, converged
