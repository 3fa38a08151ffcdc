"""numba kernels: fused histogram / MAP look-up, and EM on histogram counts.

EM
--
Components are the zero spike (``kind 0``, fixed pmf) and one-parameter exponential-family pmfs
on the levels ``x_k`` of the form ``p_c(k) = B_c(x_k) exp(eta_c T_c(x_k)) / Z(eta_c)``:
exponential (``kind 1``: ``T = x, B = 1, eta = -1/s``) and Rayleigh (``kind 2``: ``T = x^2,
B = x, eta = -1 / (2 s^2)``).  The M-step for ``eta`` is exact: the expected log-likelihood of a
one-parameter exponential family is concave in ``eta``; its maximiser on ``[lo, hi]`` solves
``E_eta[T] = mean_r[T]`` (moment matching), found by safeguarded Newton warm-started at the
previous ``eta``.  So the log-likelihood never decreases (the EM property), up to rounding.

Because the levels lie in ``[0, 1]`` and ``eta < 0``, ``exp(eta T) <= 1`` and the normaliser is
never smaller than the largest term, so the pmfs are evaluated directly (no log-sum-exp), by
recurrence on the uniform level grid (no ``exp`` per level, see :func:`_eval`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

# ---------------------------------------------------------------------------- histogram


@njit(cache=True, nogil=True, inline="always")
def _level(y, zero, one, scale, n: int, floor: bool) -> int:
    # clip in the image's dtype (NaN propagates into v and is caught by the caller's check)
    v = (min(max(y, zero), one)) * scale
    if floor:
        k = int(np.floor(v))
        return k if k < n else n - 1
    return int(np.rint(v))


@njit(cache=True, nogil=True)
def histogram_kernel(flat: np.ndarray, zero, one, scale, n: int, floor: bool, counts: np.ndarray) -> tuple[int, bool]:
    """Add the level of every value of ``flat`` to ``counts``; returns ``(n_clipped, all_finite)``.

    Bit-identical to numpy's ``rint(clip(y, 0, 1) * (L - 1))`` (round) or ``min(floor(clip(y, 0,
    1) * L), L - 1)`` (floor) in the dtype of ``flat`` (``zero``, ``one`` and ``scale`` have that
    dtype).  Four interleaved sub-histograms avoid the store-to-load stalls of runs of one level
    (real pings are mostly zeros).
    """
    m = flat.shape[0]
    sub = np.zeros((4, n), dtype=np.int64)
    clipped = 0
    acc = zero
    m4 = m - m % 4
    for i in range(0, m4, 4):
        for j in range(4):
            y = flat[i + j]
            acc += y * zero  # NaN if y is NaN or +-inf
            clipped += y > 1.000001
            if acc != acc:
                return clipped, False
            sub[j, _level(y, zero, one, scale, n, floor)] += 1
    for i in range(m4, m):
        y = flat[i]
        acc += y * zero
        clipped += y > 1.000001
        if acc != acc:
            return clipped, False
        sub[0, _level(y, zero, one, scale, n, floor)] += 1
    for k in range(n):
        counts[k] += sub[0, k] + sub[1, k] + sub[2, k] + sub[3, k]
    return clipped, True


@njit(cache=True, nogil=True)
def quantize_kernel(flat: np.ndarray, zero, one, scale, n: int, floor: bool, out: np.ndarray) -> bool:
    """Level index of every value (see :func:`histogram_kernel`); False if a value is not finite."""
    acc = zero
    for i in range(flat.shape[0]):
        y = flat[i]
        acc += y * zero
        if acc != acc:
            return False
        out[i] = _level(y, zero, one, scale, n, floor)
    return True


@njit(cache=True, nogil=True)
def lookup_kernel(flat: np.ndarray, zero, one, scale, n: int, floor: bool, lut: np.ndarray, out: np.ndarray) -> bool:
    """``out[i] = lut[level(flat[i])]`` in one pass; False if a value is not finite."""
    acc = zero
    for i in range(flat.shape[0]):
        y = flat[i]
        acc += y * zero
        if acc != acc:
            return False
        out[i] = lut[_level(y, zero, one, scale, n, floor)]
    return True


# ---------------------------------------------------------------------------- EM


@njit(cache=True, nogil=True)
def _eval(kind: int, x: np.ndarray, eta: float, u: np.ndarray) -> tuple[float, float, float]:
    """Unnormalised pmf into ``u``; returns ``(Z, sum u T, sum u T^2)``.

    The levels are uniform (``x_k = k h``), so ``exp(eta x_k) = r^k`` and ``exp(eta x_k^2) =
    q^(k^2)`` are evaluated by recurrence (``q^((k+1)^2) = q^(k^2) q^(2k+1)``): two
    multiplications per level instead of an ``exp``, relative error below ``L^2`` ulps.  Both
    sequences decrease, so once a term is below 1e-300 the rest are set to 0.
    """
    L = x.shape[0]
    h = x[1] - x[0]
    z = 0.0
    s1 = 0.0
    s2 = 0.0
    k = 0
    if kind == 1:
        r = np.exp(eta * h)
        e = 1.0
        while k < L:
            t = x[k]
            u[k] = e
            z += e
            s1 += e * t
            s2 += e * t * t
            e *= r
            k += 1
            if e < 1e-300:
                break
    else:
        q = np.exp(eta * h * h)
        q2 = q * q
        g = q  # q^(2k+1)
        e = 1.0  # q^(k^2)
        while k < L:
            xk = x[k]
            t = xk * xk
            v = xk * e
            u[k] = v
            z += v
            s1 += v * t
            s2 += v * t * t
            e *= g
            g *= q2
            k += 1
            if e < 1e-300:
                break
    while k < L:
        u[k] = 0.0
        k += 1
    return z, s1, s2


@njit(cache=True, nogil=True)
def _mean(kind: int, x: np.ndarray, eta: float, u: np.ndarray) -> float:
    z, s1, _ = _eval(kind, x, eta, u)
    return s1 / z


@njit(cache=True, nogil=True)
def _solve(kind: int, x: np.ndarray, target: float, eta0: float, lo: float, hi: float,
           m_lo: float, m_hi: float, u: np.ndarray) -> float:
    """``eta`` in ``[lo, hi]`` with ``E_eta[T] = target`` (clamped to the bounds)."""
    if target <= m_lo:
        return lo
    if target >= m_hi:
        return hi
    a = lo
    b = hi
    eta = min(max(eta0, lo), hi)
    for _ in range(100):
        z, s1, s2 = _eval(kind, x, eta, u)
        m = s1 / z
        v = s2 / z - m * m
        g = m - target
        if abs(g) <= 1e-13 * abs(target):
            break
        if g > 0:
            b = eta
        else:
            a = eta
        nxt = eta - g / v if v > 0 else 0.5 * (a + b)
        if not (a < nxt < b):
            nxt = 0.5 * (a + b)
        if abs(nxt - eta) <= 1e-14 * (abs(eta) + 1.0):
            eta = nxt
            break
        eta = nxt
    return eta


@njit(cache=True)
def solve_eta_kind(kind: int, x: np.ndarray, target: float, eta0: float, lo: float, hi: float) -> float:
    """Exact M-step of one exponential (``kind 1``) or Rayleigh (``kind 2``) component."""
    u = np.empty(x.shape[0])
    return _solve(kind, x, target, eta0, lo, hi, _mean(kind, x, lo, u), _mean(kind, x, hi, u), u)


@njit(cache=True, nogil=True)
def em_kernel(
    counts: np.ndarray,
    x: np.ndarray,
    kind: np.ndarray,
    eta: np.ndarray,
    w: np.ndarray,
    eta_lo: np.ndarray,
    eta_hi: np.ndarray,
    max_iter: int,
    tol: float,
    ll_trace: np.ndarray,
) -> tuple[int, bool]:
    """Run EM in place on ``eta`` and ``w``; returns ``(n_iter, converged)``.

    ``ll_trace[i]`` receives the log-likelihood at the parameters *entering* iteration ``i``;
    ``ll_trace[n_iter]`` that of the returned parameters.  Stops when the log-likelihood gain is
    at most ``tol * (|ll| + 1)``.
    """
    C = kind.shape[0]
    L = x.shape[0]
    n_occ = 0
    N = 0.0
    for k in range(L):
        if counts[k] > 0:
            n_occ += 1
            N += counts[k]
    occ = np.empty(n_occ, dtype=np.int64)
    j = 0
    for k in range(L):
        if counts[k] > 0:
            occ[j] = k
            j += 1
    P = np.zeros((C, L))
    u = np.empty(L)
    m_lo = np.zeros(C)
    m_hi = np.zeros(C)
    for c in range(C):
        if kind[c] != 0:
            m_lo[c] = _mean(kind[c], x, eta_lo[c], u)
            m_hi[c] = _mean(kind[c], x, eta_hi[c], u)
    Nc = np.empty(C)
    tbar = np.empty(C)
    pk = np.empty(C)
    converged = False
    it = 0
    ll_prev = -np.inf
    while True:
        # component pmfs at the current parameters
        for c in range(C):
            if kind[c] == 0:
                P[c, 0] = 1.0
                continue
            z, _, _ = _eval(kind[c], x, eta[c], u)
            inv = 1.0 / z
            for k in range(L):
                P[c, k] = u[k] * inv
        # E-step over the occupied levels
        ll = 0.0
        for c in range(C):
            Nc[c] = 0.0
            tbar[c] = 0.0
        for jj in range(n_occ):
            k = occ[jj]
            n = counts[k]
            s = 0.0
            for c in range(C):
                v = w[c] * P[c, k]
                pk[c] = v
                s += v
            if s <= 0:
                ll = -np.inf
                continue
            ll += n * np.log(s)
            f = n / s
            xk = x[k]
            for c in range(C):
                r = pk[c] * f
                Nc[c] += r
                if kind[c] == 1:
                    tbar[c] += r * xk
                elif kind[c] == 2:
                    tbar[c] += r * xk * xk
        ll_trace[it] = ll
        if it > 0 and ll - ll_prev <= tol * (abs(ll) + 1.0):
            converged = True
            break
        if it >= max_iter:
            break
        ll_prev = ll
        # M-step (exact)
        for c in range(C):
            w[c] = Nc[c] / N
            if kind[c] != 0 and Nc[c] > 0:
                eta[c] = _solve(kind[c], x, tbar[c] / Nc[c], eta[c], eta_lo[c], eta_hi[c],
                                m_lo[c], m_hi[c], u)
        it += 1
    return it, converged
