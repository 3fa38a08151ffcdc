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

import math
from fractions import Fraction

import numpy as np
from numba import njit

from sonarmap._histogram_kernels import add_partial_counts

# ---------------------------------------------------------------------------- histogram


@njit(cache=True, nogil=True)
def level_counts(levels, n_levels):  # pragma: no cover - numba
    """``np.bincount(levels.ravel(), minlength=n_levels)`` as float64 (levels are non-negative; of
    one byte and ``n_levels >= 256``, none can lie beyond the table: no pass for the largest)."""
    h, w = levels.shape
    top = n_levels
    if not (levels.itemsize == 1 and n_levels >= 256):
        for i in range(h):
            for j in range(w):
                if levels[i, j] >= top:
                    top = levels[i, j] + 1
    out = np.empty(top)
    _counts_into(levels.ravel(), out)
    return out


@njit(cache=True, nogil=True)
def _counts_into(flat, counts):  # pragma: no cover - numba
    """``counts[v]`` = the number of ``v`` in ``flat`` (as float64; every value below
    ``counts.size``), from four interleaved partial histograms: runs of one level (the zeros) do
    not serialise."""
    top = counts.shape[0]
    part = np.zeros((4, top), dtype=np.int64)
    add_partial_counts(flat, flat.shape[0], part)
    for v in range(top):
        counts[v] = float(part[0, v] + part[1, v] + part[2, v] + part[3, v])


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
def levels_kernel(flat: np.ndarray, zero, one, scale, n: int, floor: bool, lut: np.ndarray, out: np.ndarray) -> bool:
    """Level index of every value (see :func:`histogram_kernel`), or ``lut[level]`` when ``lut`` is
    not empty, in one pass; False if a value is not finite."""
    acc = zero
    table = lut.shape[0] > 0
    for i in range(flat.shape[0]):
        y = flat[i]
        acc += y * zero
        if acc != acc:
            return False
        k = _level(y, zero, one, scale, n, floor)
        out[i] = lut[k] if table else k
    return True


@njit(cache=True, nogil=True)
def nonzero_quantiles(counts: np.ndarray, f1: float, f2: float) -> tuple[float, int, int]:  # pragma: no cover - numba
    """``(n, i1, i2)`` of the levels above zero: with ``cdf = np.cumsum(counts[1:])`` (the same
    sequential sums), ``n = cdf[-1]`` and ``i = np.searchsorted(cdf, f n)`` for ``f1`` and ``f2``
    (the first index whose cumulative count reaches ``f n``; ``len(cdf)`` when none does;
    ``f1 <= f2``)."""
    L = counts.shape[0]
    n = 0.0
    for k in range(1, L):
        n += counts[k]
    t1 = f1 * n
    t2 = f2 * n
    i1 = L - 1
    i2 = L - 1
    acc = 0.0
    for k in range(1, L):
        acc += counts[k]
        if i1 == L - 1 and acc >= t1:
            i1 = k - 1
        if acc >= t2:
            i2 = k - 1
            break
    return n, i1, i2


@njit(cache=True, nogil=True)
def monotone_rows(lp: np.ndarray) -> None:  # pragma: no cover - numba
    """In place on ``lp (n_classes, L)``: every row ``c >= 1`` raised to ``lp[0] + running max of
    (lp[c] - lp[0])`` where that is finite and above the row (see
    :func:`sonarmap.stats.mixture.monotone_object_log_pmf`, whose numpy expression this is element
    for element: ``np.maximum.accumulate``'s ``m >= d or isnan(m)``, the same sums)."""
    bg = lp[0]
    for c in range(1, lp.shape[0]):
        row = lp[c]
        m = -np.inf
        for k in range(lp.shape[1]):
            d = row[k] - bg[k]
            if not math.isfinite(d):
                d = -np.inf
            if k == 0 or not (m >= d or m != m):
                m = d
            if math.isfinite(bg[k]) and math.isfinite(m) and d < m:
                row[k] = bg[k] + m


@njit(cache=True, nogil=True)
def levels_counts_kernel(flat: np.ndarray, zero, one, scale, n: int, floor: bool, out: np.ndarray,
                         counts: np.ndarray) -> bool:
    """:func:`levels_kernel` (no table) and the histogram of the levels into ``counts (n,)`` as
    float64 (:func:`_counts_into`, as :func:`level_counts` of ``out``); False if a value is not
    finite (``counts`` is then not written).

    Two passes: the levels (branch-free, so it vectorises; ``y - y`` is 0 for every finite ``y``
    and NaN otherwise), then the histogram of ``out``."""
    m = flat.shape[0]
    bad = False
    for i in range(m):
        y = flat[i]
        bad |= y - y != zero
        out[i] = _level(y, zero, one, scale, n, floor)
    if bad:
        return False
    _counts_into(out, counts)
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
    h = x[1] - x[0]
    if kind == 1:
        return _tail_1(x, 0, 1.0, np.exp(eta * h), 0.0, 0.0, 0.0, u)
    q = np.exp(eta * h * h)
    return _tail_2(x, 0, 1.0, q, q * q, 0.0, 0.0, 0.0, u)


@njit(cache=True, nogil=True, inline="always")
def _level_1(x: np.ndarray, k: int, e: float, r: float, z: float, s1: float, s2: float,
             u: np.ndarray) -> tuple[float, float, float, float]:
    """Level ``k`` of :func:`_eval`'s exponential (``u[k] = e = r^k``): ``(e r, z, s1, s2)``
    with its terms added."""
    t = x[k]
    u[k] = e
    return e * r, z + e, s1 + e * t, s2 + e * t * t


@njit(cache=True, nogil=True, inline="always")
def _level_2(x: np.ndarray, k: int, e: float, g: float, q2: float, z: float, s1: float, s2: float,
             u: np.ndarray) -> tuple[float, float, float, float, float]:
    """Level ``k`` of :func:`_eval`'s Rayleigh (``u[k] = x_k e``, ``e = q^(k^2)``, ``g =
    q^(2k+1)``): ``(e g, g q^2, z, s1, s2)`` with its terms added."""
    xk = x[k]
    t = xk * xk
    v = xk * e
    u[k] = v
    return e * g, g * q2, z + v, s1 + v * t, s2 + v * t * t


@njit(cache=True, nogil=True, inline="always")
def _tail_1(x: np.ndarray, k: int, e: float, r: float, z: float, s1: float, s2: float,
            u: np.ndarray) -> tuple[float, float, float]:
    """:func:`_eval` of the exponential from level ``k`` on (its state there: ``e``, the sums);
    a term ``e`` below 1e-300 ends the recurrence (``u`` is 0 from there)."""
    L = x.shape[0]
    if not e < 1e-300:
        while k < L:
            e, z, s1, s2 = _level_1(x, k, e, r, z, s1, s2, u)
            k += 1
            if e < 1e-300:
                break
    while k < L:
        u[k] = 0.0
        k += 1
    return z, s1, s2


@njit(cache=True, nogil=True, inline="always")
def _tail_2(x: np.ndarray, k: int, e: float, g: float, q2: float, z: float, s1: float, s2: float,
            u: np.ndarray) -> tuple[float, float, float]:
    """:func:`_eval` of the Rayleigh from level ``k`` on (its state there: ``e``, ``g``, the
    sums); a term ``e`` below 1e-300 ends the recurrence (``u`` is 0 from there)."""
    L = x.shape[0]
    if not e < 1e-300:
        while k < L:
            e, g, z, s1, s2 = _level_2(x, k, e, g, q2, z, s1, s2, u)
            k += 1
            if e < 1e-300:
                break
    while k < L:
        u[k] = 0.0
        k += 1
    return z, s1, s2


@njit(cache=True, nogil=True)
def _eval_12(x: np.ndarray, eta1: float, eta2: float, u1: np.ndarray,
             u2: np.ndarray) -> tuple[float, float, float, float, float, float]:
    """:func:`_eval` of an exponential at ``eta1`` (into ``u1``) and of a Rayleigh at ``eta2``
    (into ``u2``) in one loop over the levels: each recurrence's operations are its own, in its
    own order (the same numbers), and the two dependency chains overlap (~25 % less time than
    two calls)."""
    L = x.shape[0]
    h = x[1] - x[0]
    r = np.exp(eta1 * h)
    q = np.exp(eta2 * h * h)
    q2 = q * q
    g = q
    e1 = 1.0
    e2 = 1.0
    z1 = s11 = s21 = 0.0
    z2 = s12 = s22 = 0.0
    k = 0
    while k < L:
        e1, z1, s11, s21 = _level_1(x, k, e1, r, z1, s11, s21, u1)
        e2, g, z2, s12, s22 = _level_2(x, k, e2, g, q2, z2, s12, s22, u2)
        k += 1
        if e1 < 1e-300 or e2 < 1e-300:
            break
    z1, s11, s21 = _tail_1(x, k, e1, r, z1, s11, s21, u1)
    z2, s12, s22 = _tail_2(x, k, e2, g, q2, z2, s12, s22, u2)
    return z1, s11, s21, z2, s12, s22


@njit(cache=True, nogil=True)
def _mean(kind: int, x: np.ndarray, eta: float, u: np.ndarray) -> float:
    z, s1, _ = _eval(kind, x, eta, u)
    return s1 / z


@njit(cache=True, nogil=True)
def _eval_cached(kind: int, x: np.ndarray, eta: float, c: int, U: np.ndarray, EC: np.ndarray) -> tuple[float, float, float]:
    """:func:`_eval` of component ``c`` into ``U[c]``, reused when ``U[c]`` already holds it.

    ``EC[c] = (eta, Z, sum u T, sum u T^2)`` of the last evaluation into ``U[c]`` (``eta`` NaN:
    none).  An EM step evaluates a component at its ``eta`` for the E-step's pmf, then at the
    same ``eta`` again as the M-step's first Newton iterate, and the E-step after it at the
    Newton iterate the M-step ended on: the cache gives each of them the one evaluation - the
    same numbers, since :func:`_eval` is a pure function of ``(kind, x, eta)``.
    """
    if EC[c, 0] == eta:
        return EC[c, 1], EC[c, 2], EC[c, 3]
    z, s1, s2 = _eval(kind, x, eta, U[c])
    EC[c, 0] = eta
    EC[c, 1] = z
    EC[c, 2] = s1
    EC[c, 3] = s2
    return z, s1, s2


@njit(cache=True, nogil=True)
def _eval_cached_12(x: np.ndarray, eta1: float, eta2: float, U: np.ndarray,
                    EC: np.ndarray) -> tuple[float, float, float, float, float, float]:
    """:func:`_eval_cached` of components 1 (an exponential at ``eta1``) and 2 (a Rayleigh at
    ``eta2``): both evaluated in one loop (:func:`_eval_12`) when neither is cached."""
    if EC[1, 0] == eta1 or EC[2, 0] == eta2:
        z1, s11, s21 = _eval_cached(1, x, eta1, 1, U, EC)
        z2, s12, s22 = _eval_cached(2, x, eta2, 2, U, EC)
        return z1, s11, s21, z2, s12, s22
    z1, s11, s21, z2, s12, s22 = _eval_12(x, eta1, eta2, U[1], U[2])
    EC[1, 0] = eta1
    EC[1, 1] = z1
    EC[1, 2] = s11
    EC[1, 3] = s21
    EC[2, 0] = eta2
    EC[2, 1] = z2
    EC[2, 2] = s12
    EC[2, 3] = s22
    return z1, s11, s21, z2, s12, s22


_EPS = 2.220446049250313e-16  # relative spacing of doubles (upper bound), np.finfo(float).eps
#: Newton steps of :func:`_solve` at most.
_SOLVE_MAX_STEPS = 100


@njit(cache=True, nogil=True)
def _solve(kind: int, x: np.ndarray, target: float, eta0: float, lo: float, hi: float,
           m_lo: float, m_hi: float, c: int, U: np.ndarray, EC: np.ndarray) -> float:
    """``eta`` in ``[lo, hi]`` with ``E_eta[T] = target`` (clamped to the bounds); the
    evaluations go through the cache ``(U, EC)`` of component ``c`` (:func:`_eval_cached`).

    Newton steps safeguarded by bisection; stops when ``|E_eta[T] - target| <= 1e-13 target``
    or when the next step is below the resolution of the evaluation: :func:`_eval` sees ``eta``
    only through ``q = exp(eta s)`` (``s = h`` for kind 1, ``h^2`` for kind 2) rounded to a
    double, whose relative spacing is at most ``eps``, so ``eta`` closer than ``eps / s`` give
    the same or an adjacent ``q`` - the computed mean cannot tell them apart, and bisecting
    below that (while ``E_eta[T] - target`` is rounding noise) moves ``eta`` by noise only.
    """
    a, b, eta, n = _solve_start(target, eta0, lo, hi, m_lo, m_hi)
    h = x[1] - x[0]
    res = _EPS / (h if kind == 1 else h * h)  # eta resolution of _eval (see above)
    for _ in range(n):
        z, s1, s2 = _eval_cached(kind, x, eta, c, U, EC)
        done, eta, a, b = _newton_step(z, s1, s2, target, eta, a, b, res)
        if done:
            break
    return eta


@njit(cache=True, nogil=True, inline="always")
def _newton_step(z: float, s1: float, s2: float, target: float, eta: float, a: float, b: float,
                 res: float) -> tuple[bool, float, float, float]:
    """One step of :func:`_solve` from its evaluation ``(z, s1, s2)`` at ``eta`` (bracket ``[a,
    b]``, resolution ``res``): ``(done, eta, a, b)``, ``eta`` the next iterate (the solution when
    done)."""
    m = s1 / z
    v = s2 / z - m * m
    g = m - target
    if abs(g) <= 1e-13 * abs(target):
        return True, eta, a, b
    if g > 0:
        b = eta
    else:
        a = eta
    nxt = eta - g / v if v > 0 else 0.5 * (a + b)
    if not (a < nxt < b):
        nxt = 0.5 * (a + b)
    return abs(nxt - eta) <= max(1e-14 * (abs(eta) + 1.0), res), nxt, a, b


@njit(cache=True, nogil=True)
def _solve_12(x: np.ndarray, t1: float, t2: float, eta0: np.ndarray, lo: np.ndarray, hi: np.ndarray,
              m_lo: np.ndarray, m_hi: np.ndarray, U: np.ndarray, EC: np.ndarray) -> tuple[float, float]:
    """:func:`_solve` of component 1 (an exponential, target ``t1``) and component 2 (a Rayleigh,
    target ``t2``) from the starts ``eta0[1:3, 0]`` with the bounds ``lo``, ``hi`` and their means
    ``m_lo``, ``m_hi`` (rows / entries 1 and 2), in lockstep: each solve's iterates are its own
    (the same numbers as alone), and while both go on, their evaluations share one loop over the
    levels (:func:`_eval_cached_12`)."""
    h = x[1] - x[0]
    res1 = _EPS / h
    res2 = _EPS / (h * h)
    a1, b1, eta1, n1 = _solve_start(t1, eta0[1, 0], lo[1, 0], hi[1, 0], m_lo[1], m_hi[1])
    a2, b2, eta2, n2 = _solve_start(t2, eta0[2, 0], lo[2, 0], hi[2, 0], m_lo[2], m_hi[2])
    while n1 > 0 or n2 > 0:
        if n1 > 0 and n2 > 0:
            z1, s11, s21, z2, s12, s22 = _eval_cached_12(x, eta1, eta2, U, EC)
        elif n1 > 0:
            z1, s11, s21 = _eval_cached(1, x, eta1, 1, U, EC)
        else:
            z2, s12, s22 = _eval_cached(2, x, eta2, 2, U, EC)
        if n1 > 0:
            done, eta1, a1, b1 = _newton_step(z1, s11, s21, t1, eta1, a1, b1, res1)
            n1 = 0 if done else n1 - 1
        if n2 > 0:
            done, eta2, a2, b2 = _newton_step(z2, s12, s22, t2, eta2, a2, b2, res2)
            n2 = 0 if done else n2 - 1
    return eta1, eta2


@njit(cache=True, nogil=True, inline="always")
def _solve_start(target: float, eta0: float, lo: float, hi: float, m_lo: float,
                 m_hi: float) -> tuple[float, float, float, int]:
    """:func:`_solve`'s start: ``(a, b, eta, steps)``, the bracket, the first iterate and the
    Newton steps left (0: the target is beyond a bound, ``eta`` is that bound)."""
    if target <= m_lo:
        return lo, hi, lo, 0
    if target >= m_hi:
        return lo, hi, hi, 0
    return lo, hi, min(max(eta0, lo), hi), _SOLVE_MAX_STEPS


@njit(cache=True)
def solve_eta_kind(kind: int, x: np.ndarray, target: float, eta0: float, lo: float, hi: float) -> float:
    """Exact M-step of one exponential (``kind 1``) or Rayleigh (``kind 2``) component."""
    u = np.empty(x.shape[0])
    U = np.empty((1, x.shape[0]))
    EC = np.full((1, 4), np.nan)
    # (np.int64(0): a literal 0 would compile _solve and _eval_cached once more for Literal[int](0))
    return _solve(kind, x, target, eta0, lo, hi, _mean(kind, x, lo, u), _mean(kind, x, hi, u), np.int64(0), U, EC)


@njit(cache=True, nogil=True)
def _occupied(counts: np.ndarray) -> tuple[np.ndarray, float]:
    """Indices of the levels with a positive count, and the total count."""
    L = counts.shape[0]
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
    return occ, N


@njit(cache=True, nogil=True)
def _eta_mean_bounds(kind: np.ndarray, x: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                     u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``E[T]`` at the ``eta`` bounds ``lo``, ``hi`` of the kind 1-2 components (0 for the others)."""
    C = kind.shape[0]
    m_lo = np.zeros(C)
    m_hi = np.zeros(C)
    for c in range(C):
        if kind[c] == 1 or kind[c] == 2:
            m_lo[c] = _mean(kind[c], x, lo[c], u)
            m_hi[c] = _mean(kind[c], x, hi[c], u)
    return m_lo, m_hi


@njit(cache=True, nogil=True, inline="always")
def _eta_pmf(kind: int, x: np.ndarray, eta: float, occ: np.ndarray, P: np.ndarray, c: int, U: np.ndarray,
             EC: np.ndarray) -> None:
    """Row ``c`` of ``P`` on the occupied levels ``occ`` (the only ones the E-step reads): the
    normalised pmf of a kind 1-2 component, evaluated through the cache ``(U, EC)``."""
    z, _, _ = _eval_cached(kind, x, eta, c, U, EC)
    inv = 1.0 / z
    u = U[c]
    for jj in range(occ.shape[0]):
        k = occ[jj]
        P[c, k] = u[k] * inv


@njit(cache=True, nogil=True, inline="always")
def _responsibilities(counts: np.ndarray, x: np.ndarray, kind: np.ndarray, w: np.ndarray, occ: np.ndarray,
                      P: np.ndarray, Rsp: np.ndarray, Nc: np.ndarray, tbar: np.ndarray, pk: np.ndarray,
                      keep: bool) -> float:
    """E-step over the occupied levels ``occ`` given the component pmfs ``P``: the sums ``Nc`` of
    the responsibilities and the sums ``tbar`` of ``r T`` (kinds 1-2), and with ``keep`` the
    responsibilities themselves in ``Rsp`` (untouched otherwise); returns the log-likelihood."""
    C = kind.shape[0]
    ll = 0.0
    for c in range(C):
        Nc[c] = 0.0
        tbar[c] = 0.0
    for jj in range(occ.shape[0]):
        k = occ[jj]
        n = counts[k]
        s = 0.0
        for c in range(C):
            v = w[c] * P[c, k]
            pk[c] = v
            s += v
        if s <= 0:
            ll = -np.inf
            if keep:
                for c in range(C):
                    Rsp[c, k] = 0.0
            continue
        ll += n * np.log(s)
        f = n / s
        xk = x[k]
        for c in range(C):
            rr = pk[c] * f
            if keep:
                Rsp[c, k] = rr
            Nc[c] += rr
            if kind[c] == 1:
                tbar[c] += rr * xk
            elif kind[c] == 2:
                tbar[c] += rr * xk * xk
    return ll


@njit(cache=True, nogil=True, inline="always")
def _responsibilities_012(counts: np.ndarray, x: np.ndarray, w: np.ndarray, occ: np.ndarray, U: np.ndarray,
                          inv1: float, inv2: float, Nc: np.ndarray, tbar: np.ndarray) -> float:
    """:func:`_responsibilities` (``keep`` False) of the spike, one exponential and one Rayleigh
    (kinds ``0, 1, 2``: the pipeline's model), with the pmfs ``P[c, k] = U[c, k] * inv_c`` formed
    where they are used: the same operations in the same order, in registers."""
    w0 = w[0]
    w1 = w[1]
    w2 = w[2]
    n0 = 0.0
    n1 = 0.0
    n2 = 0.0
    t1 = 0.0
    t2 = 0.0
    ll = 0.0
    u1 = U[1]
    u2 = U[2]
    for jj in range(occ.shape[0]):
        k = occ[jj]
        n = counts[k]
        v0 = w0 * (1.0 if k == 0 else 0.0)
        v1 = w1 * (u1[k] * inv1)
        v2 = w2 * (u2[k] * inv2)
        s = 0.0 + v0
        s += v1
        s += v2
        if s <= 0:
            ll = -np.inf
            continue
        ll += n * np.log(s)
        f = n / s
        xk = x[k]
        r0 = v0 * f
        r1 = v1 * f
        r2 = v2 * f
        n0 += r0
        n1 += r1
        n2 += r2
        t1 += r1 * xk
        t2 += r2 * xk * xk
    Nc[0] = n0
    Nc[1] = n1
    Nc[2] = n2
    tbar[0] = 0.0
    tbar[1] = t1
    tbar[2] = t2
    return ll


# ---------------------------------------------------------------------------- general EM
#
# Two-parameter families, in the coordinates the M-step works in (``kind``: coordinates):
#   3 gamma   (a, b = 1/scale):       g = (a - 1) log x - b x     (natural parameters: Q concave)
#   4 weibull (c, t = log scale):     g = (c - 1) l - exp(c l),   l = log x - t
#   5 rice    (nu, v = 1/scale^2):    g = log x - (x - nu)^2 v / 2 + log i0e(x nu v)
#   6 k       (nu, w = log scale):    g = (nu - 1)/2 log x + log K_{nu-1}(2 sqrt(nu x) e^{-w/2})
# ``g`` is the unnormalised log-density of :meth:`sonarmap.stats.components.Family.log_density`
# (up to terms constant in x); gamma and Weibull with shape < 1 evaluate level 0 at half a step,
# the K distribution always does.


# Rice: log i0e(z) and I1(z)/I0(z) on all levels at once.  Power series below RICE_SWITCH
# (I0 = sum t^k / (k!)^2, I1 = z/2 sum t^k / (k! (k+1)!), t = z^2 / 4, all terms positive) and
# Hankel's asymptotic series above it (e^-z sqrt(2 pi z) I_n(z) ~ sum_k b_k(n) z^-k, with
# b_k(n) = prod_{j<=k} ((2j-1)^2 - 4n^2) / (k! 8^k)), each by Horner's rule in t or 1/z with
# coefficients rounded once from exact rationals, the levels' Horner loops over contiguous arrays.
# The number of terms is the least whose truncation is below RICE_TRUNCATION relative at the
# largest (series) or smallest (asymptotic) z of the call: for the series the first omitted term
# times its geometric tail factor (a bound: the term ratios t / ((k+1)(k+2)) fall), for Hankel's
# series the first omitted term (the order of its remainder; the exponentially small e^-2z part of
# I_n is below 1e-19 from z = 22 on).  At z = 21 the asymptotic terms of I1 stop falling at 7e-20,
# hence the switch at 22 (39 series terms there, 31 asymptotic ones, 13 from z = 64 on).

RICE_SWITCH = 22.0
RICE_TRUNCATION = 1e-19
_RICE_MAX_TERMS = 60
_LN2_HI = 6.93147180369123816490e-01  # ln 2 = _LN2_HI + _LN2_LO, _LN2_HI * n exact for |n| < 2^20
_LN2_LO = 1.90821492927058770002e-10
_RICE_ASYM_CAP = 64  # beyond this z the asymptotic term count of z = 64 is used (it only falls)


def _rice_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients (series in t, asymptotic in 1/z, for I0 and I1) and the term counts: by
    ``ceil(z max)`` for the series, by ``floor(z min)`` for the asymptotic series."""
    n = _RICE_MAX_TERMS
    s0 = [Fraction(1, math.factorial(k) ** 2) for k in range(n)]
    s1 = [Fraction(1, math.factorial(k) * math.factorial(k + 1)) for k in range(n)]
    a0 = [Fraction(1)]
    a1 = [Fraction(1)]
    for k in range(1, n):
        o = (2 * k - 1) ** 2
        a0.append(a0[-1] * o / (8 * k))
        a1.append(a1[-1] * (o - 4) / (8 * k))
    c0 = [float(c) for c in s0]
    c1 = [float(c) for c in s1]
    series_terms = np.zeros(int(RICE_SWITCH) + 1, dtype=np.int64)
    for b in range(series_terms.size):
        t = 0.25 * b * b
        p0 = p1 = 0.0  # partial sums of the m terms kept
        for m in range(1, n):
            p0 += c0[m - 1] * t ** (m - 1)
            p1 += c1[m - 1] * t ** (m - 1)
            if t >= (m + 1) ** 2:
                continue  # the omitted terms do not yet fall geometrically
            tail0 = c0[m] * t ** m / (1.0 - t / (m + 1) ** 2)
            tail1 = c1[m] * t ** m / (1.0 - t / ((m + 1) * (m + 2)))
            if tail0 <= RICE_TRUNCATION * p0 and tail1 <= RICE_TRUNCATION * p1:
                series_terms[b] = m
                break
    asym_terms = np.zeros(_RICE_ASYM_CAP + 1, dtype=np.int64)
    for b in range(asym_terms.size):
        zb = max(float(b), RICE_SWITCH)
        for m in range(1, n):
            # I0's sum is at least 1, I1's at least 1 - 3 / (8 z) > 0.98 here
            if abs(float(a0[m])) / zb ** m <= RICE_TRUNCATION and abs(float(a1[m])) / zb ** m <= 0.98 * RICE_TRUNCATION:
                asym_terms[b] = m
                break
    if not (series_terms.all() and asym_terms.all()):
        raise AssertionError("Rice series: not enough terms")  # pragma: no cover - fixed tables
    f = np.array
    return (f([float(c) for c in s0]), f([float(c) for c in s1]), f([float(c) for c in a0]),
            f([float(c) for c in a1]), series_terms, asym_terms)


_RS0, _RS1, _RA0, _RA1, _RICE_SERIES_TERMS, _RICE_ASYM_TERMS = _rice_tables()


@njit(cache=True, nogil=True)
def log_i0e_ratio(z: np.ndarray, f: np.ndarray, a: np.ndarray) -> None:
    """``f = log(i0e(z))`` and ``a = I1(z) / I0(z)`` for an array ``z >= 0`` (any order).

    Power series below :data:`RICE_SWITCH`, Hankel's asymptotic series above, truncated where the
    omitted part is below :data:`RICE_TRUNCATION` relative (see the comment above).  What is left
    is the rounding of Horner's rule: within 1.0e-15 of ``log(scipy.special.i0e(z))`` and 1.6e-15
    of ``i1e(z) / i0e(z)`` for ``z`` in [1e-8, 1e6] (3e-15 is what tests/stats/test_rice_bessel.py
    allows, also against an extended-precision series up to ``z = 60``).  No ``I0`` is formed, so
    nothing overflows at any ``z``.
    """
    n = z.shape[0]
    idx = np.empty(n, dtype=np.int64)
    w = np.empty((3, n))
    tt = w[0]
    s0 = w[1]
    s1 = w[2]
    for asym in (False, True):
        # gather this part's arguments (t = z^2 / 4, or 1 / z) into contiguous arrays
        m = 0
        zlim = np.inf if asym else 0.0
        for i in range(n):
            zi = z[i]
            if (zi >= RICE_SWITCH) == asym:
                idx[m] = i
                tt[m] = 1.0 / zi if asym else 0.25 * zi * zi
                zlim = min(zlim, zi) if asym else max(zlim, zi)
                m += 1
        if m == 0:
            continue
        if asym:
            c0, c1 = _RA0, _RA1
            nt = _RICE_ASYM_TERMS[int(min(zlim, float(_RICE_ASYM_CAP)))]
        else:
            c0, c1 = _RS0, _RS1
            nt = _RICE_SERIES_TERMS[int(np.ceil(zlim))]
        for i in range(m):
            s0[i] = c0[nt - 1]
            s1[i] = c1[nt - 1]
        for j in range(nt - 2, -1, -1):
            for i in range(m):
                s0[i] = s0[i] * tt[i] + c0[j]
                s1[i] = s1[i] * tt[i] + c1[j]
        for i in range(m):
            k = idx[i]
            zi = z[k]
            if asym:
                f[k] = np.log(s0[i] / np.sqrt(2.0 * np.pi * zi))
                a[k] = s1[i] / s0[i]
            else:
                # log(s0) - z without the rounding of log(s0) ~ z: s0 = mant 2^ex, ln 2 split (fdlibm)
                mant, ex = math.frexp(s0[i])
                f[k] = np.log(mant) + ((ex * _LN2_HI - zi) + ex * _LN2_LO)
                a[k] = 0.5 * zi * s1[i] / s0[i]


@njit(cache=True, nogil=True, inline="always")
def _drop_crossing(t, z, av, amax, drop):  # pragma: no cover - numba
    """Newton from ``t`` to where the exponent ``-z cosh t + av t`` of :func:`log_bessel_k` falls
    ``drop`` under its maximum ``amax`` (monotone on either side of it; steps below 1e-3 stop it)."""
    for _ in range(80):
        d = -z * np.sinh(t) + av
        step = (-z * np.cosh(t) + av * t - amax + drop) / d
        t -= step
        if abs(step) < 1e-3:
            break
    return t


@njit(cache=True, nogil=True)
def log_bessel_k(v: float, z: float, derivs: bool, out: np.ndarray) -> float:
    """``log K_v(z)`` for real ``v`` and ``z > 0``; with ``derivs``, ``out[:5] = (F_v, F_z, F_vv,
    F_vz, F_zz)``, the first and second derivatives of ``F = log K_v(z)``.

    Trapezoid rule on ``K_v(z) = int_0^inf exp(-z cosh t) cosh(v t) dt``: the integrand is entire
    and even in ``t``, so the rule converges geometrically in the step.  The nodes cover the
    region where ``-z cosh t + |v| t`` is within 46 of its maximum (found by monotone Newton on
    the concave exponent), with a step of at most 0.6 / sqrt(curvature at the peak) and 0.25;
    everything is scaled by that maximum, so there is no overflow for any order (large ``v`` is
    the near-exponential end of the K distribution).  Within 2e-14 (relative) of
    ``log(scipy.special.kve(v, z)) - z`` wherever that is finite.  The derivatives use the same
    nodes (``d/dv`` brings ``t tanh(v t)``, ``d/dz`` brings ``-cosh t``).
    """
    av = abs(v)
    ts = np.arcsinh(av / z)
    cts = np.cosh(ts)
    amax = -z * cts + av * ts
    curv = z * cts
    drop = 46.0
    # right of the root (the exponent is more than quadratic)
    t_hi = _drop_crossing(ts + np.sqrt(2.0 * drop / curv), z, av, amax, drop)
    t_lo = 0.0
    if -z < amax - drop:
        t_lo = max(_drop_crossing(0.0, z, av, amax, drop) - 1e-3, 0.0)
    hmax = min(0.25, 0.6 / np.sqrt(curv))
    n = int(np.ceil((t_hi - t_lo) / hmax))
    if n < 8:
        n = 8
    hs = (t_hi - t_lo) / n
    sg = 1.0 if v >= 0 else -1.0
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    s4 = 0.0
    s5 = 0.0
    for j in range(n + 1):
        tj = t_lo + j * hs
        ch = np.cosh(tj)
        ep = np.exp(-z * ch + av * tj - amax)
        em = ep * np.exp(-2.0 * av * tj)
        wgt = 0.5 if (j == 0 or j == n) else 1.0
        c = wgt * 0.5 * (ep + em)
        s0 += c
        if derivs:
            sh = sg * wgt * 0.5 * (ep - em) * tj
            s1 += sh
            s2 += c * tj * tj
            s3 += c * ch
            s4 += c * ch * ch
            s5 += sh * ch
    if derivs:
        fv = s1 / s0
        fz = -s3 / s0
        out[0] = fv
        out[1] = fz
        out[2] = s2 / s0 - fv * fv
        out[3] = -s5 / s0 - fv * fz
        out[4] = s4 / s0 - fz * fz
    return amax + np.log(hs * s0)


@njit(cache=True, nogil=True)
def _logdens2(kind: int, p0: float, p1: float, x: np.ndarray, xe: np.ndarray, lx: np.ndarray,
              g: np.ndarray, aux: np.ndarray, gr: np.ndarray, hs: np.ndarray, derivs: bool) -> float:
    """Unnormalised log-density ``g`` (``-inf`` off the support) in the kernel's coordinates;
    returns ``max g``.

    For kinds 3-5 ``aux`` keeps what :func:`_grad2` needs beside the parameters (Weibull
    ``exp(c l)``, Rice ``I1/I0``), so gradient and Hessian are computed only when needed, without
    a second pass over the Bessel function.  The K distribution's derivatives come out of the
    same quadrature: with ``derivs`` they go into ``gr (L, 2)`` and ``hs (L, 3)`` (``h00, h01,
    h11``) at once.
    """
    L = x.shape[0]
    top = -np.inf
    fk = np.empty(5)
    if kind == 6:
        c2 = 2.0 * np.sqrt(p0) * np.exp(-0.5 * p1)  # z = c2 sqrt(x)
    elif kind == 5:
        zr = np.empty(L)
        for k in range(L):
            zr[k] = x[k] * p0 * p1
        fr = np.empty(L)
        log_i0e_ratio(zr, fr, aux)  # aux = I1/I0
    for k in range(L):
        if kind == 6:
            # K distribution (level 0 at half a step, xe[0]); F = log K_{nu-1}(z)
            z = c2 * np.sqrt(xe[k])
            v = 0.5 * (p0 - 1.0) * lx[k] + log_bessel_k(p0 - 1.0, z, derivs, fk)
            if derivs:
                zn = z / (2.0 * p0)
                zw = -0.5 * z
                gr[k, 0] = 0.5 * lx[k] + fk[0] + fk[1] * zn
                gr[k, 1] = fk[1] * zw
                hs[k, 0] = fk[2] + 2.0 * fk[3] * zn + fk[4] * zn * zn - fk[1] * z / (4.0 * p0 * p0)
                hs[k, 1] = fk[3] * zw + fk[4] * zn * zw - fk[1] * z / (4.0 * p0)
                hs[k, 2] = fk[4] * zw * zw + 0.25 * fk[1] * z
            if v != v:
                v = -np.inf
            g[k] = v
            if v > top:
                top = v
            continue
        if k == 0 and (kind == 5 or (p0 >= 1.0)):
            g[0] = -np.inf
            continue
        if kind == 3:
            v = (p0 - 1.0) * lx[k] - p1 * xe[k]
        elif kind == 4:
            l = lx[k] - p1
            zc = np.exp(p0 * l)
            aux[k] = zc
            v = (p0 - 1.0) * l - zc
        else:
            d = x[k] - p0
            v = lx[k] - 0.5 * d * d * p1 + fr[k]
        if v != v:
            v = -np.inf
        g[k] = v
        if v > top:
            top = v
    return top


@njit(cache=True, nogil=True)
def _grad2(kind: int, p0: float, p1: float, x: np.ndarray, xe: np.ndarray, lx: np.ndarray,
           g: np.ndarray, aux: np.ndarray, gr: np.ndarray, hs: np.ndarray) -> None:
    """Gradient ``gr (L, 2)`` and Hessian ``hs (L, 3)`` (``h00, h01, h11``) of ``g`` for kinds
    3-5 at the levels on the support, from :func:`_logdens2`'s ``g`` and ``aux``."""
    for k in range(x.shape[0]):
        if not g[k] > -np.inf:
            continue
        if kind == 3:
            gr[k, 0] = lx[k]
            gr[k, 1] = -xe[k]
            hs[k, 0] = 0.0
            hs[k, 1] = 0.0
            hs[k, 2] = 0.0
        elif kind == 4:
            l = lx[k] - p1
            zc = aux[k]
            gr[k, 0] = l * (1.0 - zc)
            gr[k, 1] = -(p0 - 1.0) + p0 * zc
            hs[k, 0] = -l * l * zc
            hs[k, 1] = -1.0 + zc * (1.0 + p0 * l)
            hs[k, 2] = -p0 * p0 * zc
        else:
            xk = x[k]
            z = xk * p0 * p1
            a = aux[k]
            d = xk - p0
            dd = a - 1.0
            dp = 0.5 if z < 1e-6 else 1.0 - a / z - a * a
            gr[k, 0] = d * p1 + xk * p1 * dd
            gr[k, 1] = -0.5 * d * d + xk * p0 * dd
            hs[k, 0] = -p1 + (xk * p1) ** 2 * dp
            hs[k, 1] = d + xk * dd + xk * p1 * xk * p0 * dp
            hs[k, 2] = (xk * p0) ** 2 * dp


# Evaluations of a two-parameter component are cached in "slots" (two per component: the current
# point and a trial point), keyed by the parameters they were computed at.  One EM iteration
# evaluates each component's log-density once per Newton trial point; the E-step reuses the
# accepted point's ``exp(g - top)``, and gradient and Hessian are computed only at accepted points
# (from the density pass's ``aux``).  Every cached number is computed by the same expression, in
# the same order, as a fresh evaluation, so the iterates are bit-identical to evaluating afresh.
#
# A slot is ``V (4, L)``: rows g, e = exp(g - top) (0 off the support), p = exp(g - log Z), aux
# (see _logdens2); ``gr (L, 2)``, ``hs (L, 3)``; and ``sc``: p0, p1, top, z = sum e, log Z, the
# model means m0, m1 of gr, state (0: g, e, aux; 1: also gr, hs; 2: also p, m0, m1).

_SC_SIZE = 8


@njit(cache=True, nogil=True)
def _eval_slot(kind: int, p0: float, p1: float, x: np.ndarray, xe: np.ndarray, lx: np.ndarray,
               V: np.ndarray, gr: np.ndarray, hs: np.ndarray, sc: np.ndarray) -> None:
    """Log-density at ``(p0, p1)``, ``e``, ``z`` and ``log Z`` into one slot (state 0)."""
    g = V[0]
    e = V[1]
    top = _logdens2(kind, p0, p1, x, xe, lx, g, V[3], gr, hs, False)
    z = 0.0
    for k in range(x.shape[0]):
        if g[k] > -np.inf:
            v = np.exp(g[k] - top)
            e[k] = v
            z += v
        else:
            e[k] = 0.0
    sc[0] = p0
    sc[1] = p1
    sc[2] = top
    sc[3] = z
    sc[4] = top + np.log(z)
    sc[7] = 0.0


@njit(cache=True, nogil=True)
def _q_slot(g: np.ndarray, sc: np.ndarray, r: np.ndarray, R: float) -> float:
    """Expected complete-data log-likelihood ``Q = sum_k r_k log p(k)`` of one component from its
    slot (``-inf`` if some ``r_k > 0`` is off the support)."""
    top = sc[2]
    if not top > -np.inf or top != top:
        return -np.inf
    q = 0.0
    for k in range(g.shape[0]):
        if r[k] > 0:
            if not g[k] > -np.inf:
                return -np.inf
            q += r[k] * g[k]
    q -= R * sc[4]
    return q


@njit(cache=True, nogil=True)
def _dq_slot(kind: int, x: np.ndarray, xe: np.ndarray, lx: np.ndarray, V: np.ndarray,
             gr: np.ndarray, hs: np.ndarray, sc: np.ndarray, r: np.ndarray, R: float,
             out: np.ndarray) -> None:
    """Gradient and Hessian of ``Q`` into ``out = (dQ0, dQ1, H00, H01, H11)`` from a slot
    (completing it to state 2 first if needed)."""
    L = x.shape[0]
    g = V[0]
    p = V[2]
    if sc[7] < 1.0:
        if kind == 6:
            _logdens2(kind, sc[0], sc[1], x, xe, lx, g, V[3], gr, hs, True)  # the same g
        else:
            _grad2(kind, sc[0], sc[1], x, xe, lx, g, V[3], gr, hs)
        sc[7] = 1.0
    logz = sc[4]
    if sc[7] < 2.0:
        m0 = 0.0
        m1 = 0.0
        for k in range(L):
            if g[k] > -np.inf:
                pk = np.exp(g[k] - logz)
                p[k] = pk
                m0 += pk * gr[k, 0]
                m1 += pk * gr[k, 1]
        sc[5] = m0
        sc[6] = m1
        sc[7] = 2.0
    m0 = sc[5]
    m1 = sc[6]
    g0 = 0.0
    g1 = 0.0
    h00 = 0.0
    h01 = 0.0
    h11 = 0.0
    for k in range(L):
        if g[k] > -np.inf:
            pk = p[k]
            d0 = gr[k, 0] - m0
            d1 = gr[k, 1] - m1
            h00 -= R * pk * (hs[k, 0] + d0 * d0)
            h01 -= R * pk * (hs[k, 1] + d0 * d1)
            h11 -= R * pk * (hs[k, 2] + d1 * d1)
            if r[k] > 0:
                g0 += r[k] * d0
                g1 += r[k] * d1
                h00 += r[k] * hs[k, 0]
                h01 += r[k] * hs[k, 1]
                h11 += r[k] * hs[k, 2]
    out[0] = g0
    out[1] = g1
    out[2] = h00
    out[3] = h01
    out[4] = h11


@njit(cache=True, nogil=True)
def _slot_at(kind: int, p0: float, p1: float, x: np.ndarray, xe: np.ndarray, lx: np.ndarray,
             V: np.ndarray, GR: np.ndarray, HS: np.ndarray, SC: np.ndarray, cur: int) -> int:
    """The slot (of the two of one component) that holds ``(p0, p1)``, evaluating into ``cur`` if
    neither does."""
    if SC[cur, 0] == p0 and SC[cur, 1] == p1:
        return cur
    o = 1 - cur
    if SC[o, 0] == p0 and SC[o, 1] == p1:
        return o
    _eval_slot(kind, p0, p1, x, xe, lx, V[cur], GR[cur], HS[cur], SC[cur])
    return cur


@njit(cache=True, nogil=True)
def _mstep2(kind: int, par: np.ndarray, lo: np.ndarray, hi: np.ndarray, x: np.ndarray,
            xe: np.ndarray, lx: np.ndarray, r: np.ndarray, R: float, V: np.ndarray, GR: np.ndarray,
            HS: np.ndarray, SC: np.ndarray, cur: int, max_newton: int) -> int:
    """Damped Newton on ``Q`` of one two-parameter component, in place on ``par`` (2,), inside
    the box ``[lo, hi]``; a step is taken only if it increases ``Q`` (so EM stays monotone).

    ``V, GR, HS, SC`` are the component's two slots; returns the one that holds the final ``par``.
    """
    out = np.empty(5)
    p0 = par[0]
    p1 = par[1]
    s = _slot_at(kind, p0, p1, x, xe, lx, V, GR, HS, SC, cur)
    q0 = _q_slot(V[s, 0], SC[s], r, R)
    if not q0 > -np.inf:
        return s
    _dq_slot(kind, x, xe, lx, V[s], GR[s], HS[s], SC[s], r, R, out)
    for _ in range(max_newton):
        # ascent direction: solve (-H + mu I) d = grad with -H + mu I positive definite
        a00 = -out[2]
        a01 = -out[3]
        a11 = -out[4]
        g0 = out[0]
        g1 = out[1]
        tr = a00 + a11
        det = a00 * a11 - a01 * a01
        mu = 0.0
        if not (a00 > 0 and det > 1e-12 * tr * tr):
            # smallest eigenvalue of the 2x2 symmetric matrix
            disc = np.sqrt(0.25 * (a00 - a11) ** 2 + a01 * a01)
            lam = 0.5 * tr - disc
            mu = -lam + 1e-6 * (abs(tr) + 1e-300) + 1e-300
        b00 = a00 + mu
        b11 = a11 + mu
        det = b00 * b11 - a01 * a01
        if not det > 0 or det != det:
            return s  # par stays where this M-step started (its slot is looked up again)
        d0 = (b11 * g0 - a01 * g1) / det
        d1 = (b00 * g1 - a01 * g0) / det
        step = 1.0
        accepted = False
        qc = q0
        c0 = p0
        c1 = p1
        t = 1 - s
        pred = g0 * d0 + g1 * d1  # first-order gain of the full step
        for _bt in range(40):
            if step * pred <= 1e-13 * (abs(q0) + 1.0):
                break  # a shorter step cannot gain more than the rounding of Q: stop halving
            c0 = min(max(p0 + step * d0, lo[0]), hi[0])
            if (kind == 3 or kind == 4) and p0 >= 1.0 and c0 < 1.0:
                c0 = 1.0  # shape 1 bounds the step like the box (level 0 enters the support below)
            c1 = min(max(p1 + step * d1, lo[1]), hi[1])
            if c0 == p0 and c1 == p1:
                break
            _eval_slot(kind, c0, c1, x, xe, lx, V[t], GR[t], HS[t], SC[t])
            qc = _q_slot(V[t, 0], SC[t], r, R)
            if qc > q0:
                accepted = True
                break
            step *= 0.5
        if not accepted:
            break
        gain = qc - q0
        p0 = c0
        p1 = c1
        q0 = qc
        s = t
        if gain <= 1e-13 * (abs(q0) + 1.0):
            break
        _dq_slot(kind, x, xe, lx, V[s], GR[s], HS[s], SC[s], r, R, out)
    par[0] = p0
    par[1] = p1
    return s


@njit(cache=True, nogil=True)
def _estep_general(counts, x, xe, lx, kind, par, w, occ, P, Rsp, Nc, tbar, pk, U, EC, V, GR, HS, SC,
                   cur, keep) -> float:
    """Component pmfs at ``(par, w)`` (two-parameter ones from their slots, kinds 1-2 on the
    occupied levels through the cache ``(U, EC)``), ``Nc``, ``tbar`` and with ``keep`` the
    responsibilities ``Rsp`` (the M-step of kinds 3-6 needs them); returns the log-likelihood."""
    C = kind.shape[0]
    L = x.shape[0]
    if not keep and C == 3 and kind[0] == 0 and kind[1] == 1 and kind[2] == 2:
        z1, _, _, z2, _, _ = _eval_cached_12(x, par[1, 0], par[2, 0], U, EC)
        return _responsibilities_012(counts, x, w, occ, U, 1.0 / z1, 1.0 / z2, Nc, tbar)
    for c in range(C):
        kc = kind[c]
        if kc == 0:
            P[c, 0] = 1.0
        elif kc <= 2:
            _eta_pmf(kc, x, par[c, 0], occ, P, c, U, EC)
        else:
            s = _slot_at(kc, par[c, 0], par[c, 1], x, xe, lx, V[c], GR[c], HS[c], SC[c], cur[c])
            cur[c] = s
            e = V[c, s, 1]
            inv = 1.0 / SC[c, s, 3]
            for k in range(L):
                P[c, k] = e[k] * inv
    return _responsibilities(counts, x, kind, w, occ, P, Rsp, Nc, tbar, pk, keep)


@njit(cache=True, nogil=True)
def _mstep_general(x, xe, lx, kind, par, w, lo, hi, N, Rsp, Nc, tbar, m_lo, m_hi, U, EC, V, GR, HS, SC,
                   cur, max_newton) -> None:
    C = kind.shape[0]
    if C == 3 and kind[0] == 0 and kind[1] == 1 and kind[2] == 2 and Nc[1] > 0 and Nc[2] > 0:
        # the pipeline's model: the two solves in lockstep (the same iterates)
        for c in range(C):
            w[c] = Nc[c] / N
        par[1, 0], par[2, 0] = _solve_12(x, tbar[1] / Nc[1], tbar[2] / Nc[2], par, lo, hi, m_lo, m_hi, U, EC)
        return
    for c in range(C):
        w[c] = Nc[c] / N
        kc = kind[c]
        if kc == 0 or Nc[c] <= 0:
            continue
        if kc <= 2:
            par[c, 0] = _solve(kc, x, tbar[c] / Nc[c], par[c, 0], lo[c, 0], hi[c, 0],
                               m_lo[c], m_hi[c], c, U, EC)
        else:
            cur[c] = _mstep2(kc, par[c], lo[c], hi[c], x, xe, lx, Rsp[c], Nc[c], V[c], GR[c],
                             HS[c], SC[c], cur[c], max_newton)


# ---------------------------------------------------------------------------- SQUAREM
#
# EM converges linearly, and slowly where components overlap (hundreds to thousands of iterations).
# SQUAREM (Varadhan & Roland 2008, scheme S3) extrapolates from x0, x1 = F(x0) and x2 = F(x1),
# F the EM map (one E-step and one M-step):
#     r = x1 - x0,  v = x2 - 2 x1 + x0,  a = ||r|| / ||v|| clipped to [1, step_max],
#     x' = x0 + 2 a r + a^2 v                                  (a = 1 gives x' = x2),
# then takes one stabilising EM step x3 = F(x'), kept only if ll(x3) >= ll(x2); otherwise the
# cycle ends at x2, so the log-likelihood of the kept iterates never decreases.  ``step_max``
# starts at SQ_STEP_MAX0, grows 4x after an accepted step clipped at it and shrinks 4x after a
# rejected step clipped at it (a rejected shorter step leaves it).  The coordinates
# (:func:`_sq_coords`) are log weights (the interior of the simplex; the extrapolated weights are
# renormalised), log |p| for a parameter whose bounds exclude 0 (eta, gamma's shape and 1/scale, Rice's 1/scale^2,
# Weibull's and K's shape) and p itself otherwise (Rice's nu, Weibull's and K's log scale); the
# extrapolated point is kept inside the box and off its boundary (:func:`_sq_point`).  A zero
# weight stays zero (as under EM).  ``n_iter`` counts EM map evaluations: 3 per cycle.

SQ_STEP_MAX0 = 4.0
SQ_MIN_SHRINK = 1e-3
_SQ_GROW = 4.0


@njit(cache=True, nogil=True)
def _sq_coords(kind: np.ndarray, par: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               y: np.ndarray) -> None:
    """The extrapolation coordinates of ``(par, w)`` into ``y (3 C,)``: ``C`` log weights
    (``-inf`` for a zero weight), then ``(C, 2)`` parameters (log |p| where the box excludes 0)."""
    C = kind.shape[0]
    for c in range(C):
        y[c] = np.log(w[c]) if w[c] > 0 else -np.inf
        for j in range(2):
            p = par[c, j]
            i = C + 2 * c + j
            if lo[c, j] > 0:
                y[i] = np.log(p)
            elif hi[c, j] < 0:
                y[i] = np.log(-p)
            else:
                y[i] = p


@njit(cache=True, nogil=True)
def _sq_step_length(y0: np.ndarray, y1: np.ndarray, y2: np.ndarray, step_max: float) -> float:
    """SQUAREM's S3 step length ``a = ||r|| / ||v||`` of three successive EM iterates (in
    :func:`_sq_coords`), clipped to ``[1, step_max]``; coordinates that are not finite in all
    three (zero weights) do not count."""
    sr = 0.0
    sv = 0.0
    for i in range(y0.shape[0]):
        if math.isfinite(y0[i]) and math.isfinite(y1[i]) and math.isfinite(y2[i]):
            r = y1[i] - y0[i]
            v = y2[i] - 2.0 * y1[i] + y0[i]
            sr += r * r
            sv += v * v
    a = math.sqrt(sr / sv) if sv > 0 else step_max
    if not a >= 1.0:
        a = 1.0
    return min(a, step_max)


@njit(cache=True, nogil=True)
def _sq_extrapolate(y0: np.ndarray, y1: np.ndarray, y2: np.ndarray, a: float, y: np.ndarray) -> None:
    """SQUAREM's point ``y = y0 + 2 a r + a^2 v`` (``y2`` for ``a = 1``); coordinates that are
    not finite in all three iterates keep ``y2``'s value."""
    for i in range(y0.shape[0]):
        yi = y2[i]
        if math.isfinite(y0[i]) and math.isfinite(y1[i]) and math.isfinite(y2[i]):
            r = y1[i] - y0[i]
            v = y2[i] - 2.0 * y1[i] + y0[i]
            yi = y0[i] + 2.0 * a * r + a * a * v
            if not math.isfinite(yi):
                yi = y2[i]
        y[i] = yi


@njit(cache=True, nogil=True)
def _sq_point(kind: np.ndarray, y: np.ndarray, lo: np.ndarray, hi: np.ndarray, par2: np.ndarray,
              w2: np.ndarray, par: np.ndarray, w: np.ndarray) -> None:
    """``(par, w)`` of the extrapolated coordinates ``y`` (:func:`_sq_coords`), kept off the
    boundary that the last EM iterate ``(par2, w2)`` is off.

    A weight falls at most to ``SQ_MIN_SHRINK`` times ``w2``'s, and the weights are normalised;
    a parameter beyond its box goes halfway from ``par2``'s value to the bound it crossed.  A
    point on the boundary can be a fixed point of EM that the data do not support (a zero weight;
    Rice at ``nu = 0``, where the likelihood is even in ``nu``): plain EM creeps away from near
    it, clipping onto it would stop there.  Likewise the shape of a gamma or Weibull does not
    cross 1 by extrapolation (halfway to 1 instead): below 1 level 0 is in the component's support
    (evaluated at half a step), at and above 1 it is not, and once the component takes some of
    level 0's count the M-step cannot leave that side (its expected log-likelihood is ``-inf``
    beyond), so a jump across would trap EM in the other side's optimum.
    """
    C = kind.shape[0]
    top = -np.inf
    for c in range(C):
        top = max(top, y[c])
    tot = 0.0
    for c in range(C):
        v = np.exp(y[c] - top) if y[c] > -np.inf else 0.0
        w[c] = v
        tot += v
    tot2 = 0.0
    for c in range(C):
        w[c] = max(w[c] / tot, SQ_MIN_SHRINK * w2[c])
        tot2 += w[c]
    for c in range(C):
        w[c] /= tot2
        for j in range(2):
            yi = y[C + 2 * c + j]
            if lo[c, j] > 0:
                p = np.exp(yi)
            elif hi[c, j] < 0:
                p = -np.exp(yi)
            else:
                p = yi
            if p < lo[c, j]:
                p = 0.5 * (lo[c, j] + par2[c, j])
            elif p > hi[c, j]:
                p = 0.5 * (hi[c, j] + par2[c, j])
            elif j == 0 and (kind[c] == 3 or kind[c] == 4) and (p >= 1.0) != (par2[c, 0] >= 1.0):
                p = 0.5 * (1.0 + par2[c, 0])  # level 0's side of shape 1, see above
            par[c, j] = p


#: :func:`em_general_kernel` statuses.
EM_MAX_ITER = 0
EM_CONVERGED = 1
EM_MERGED = 2
EM_RICE_AT_ZERO = 3
#: EM steps before :func:`em_general_kernel`'s ``rice_min`` test applies (a start may begin near 0).
RICE_MIN_ITER = 30
#: :func:`em_general_kernel`'s reference weights and parameters when it has none (``merge_rtol = 0``;
#: writable, as the references passed are: one signature; empty, so never written).
NO_REF_W = np.zeros(0)
NO_REF_PAR = np.zeros((0, 2))


def em_general_args(accel: bool = True, ref: tuple[np.ndarray, np.ndarray] | None = None, merge_rtol: float = 0.0,
                    rice_min: float = 0.0) -> tuple[bool, np.ndarray, np.ndarray, float, float]:
    """The last five arguments of :func:`em_general_kernel` (``accel, ref_w, ref_par, merge_rtol,
    rice_min``) in the types of its one compiled signature: ``ref`` = ``(w, par)`` or None (no
    merge test), as writable float64 C arrays."""
    if ref is None:
        return bool(accel), NO_REF_W, NO_REF_PAR, 0.0, float(rice_min)
    rw = np.array(ref[0], dtype=np.float64, order="C")
    rp = np.array(ref[1], dtype=np.float64, order="C").reshape(-1, 2)
    return bool(accel), rw, rp, float(merge_rtol), float(rice_min)


@njit(cache=True, nogil=True)
def _rice_at_zero(kind: np.ndarray, par: np.ndarray, rice_min: float) -> bool:
    """Whether a Rice component (kind 5, coordinates ``(nu, 1 / sigma^2)``) has ``nu / sigma`` below
    ``rice_min``."""
    for c in range(kind.shape[0]):
        if kind[c] == 5 and par[c, 0] * math.sqrt(par[c, 1]) < rice_min:
            return True
    return False


@njit(cache=True, nogil=True)
def _near(w: np.ndarray, par: np.ndarray, ref_w: np.ndarray, ref_par: np.ndarray, rtol: float) -> bool:
    """Whether every weight and non-zero coordinate lies within ``rtol`` (relative) of the reference."""
    for c in range(w.shape[0]):
        if abs(w[c] - ref_w[c]) > rtol * abs(ref_w[c]):
            return False
        for j in range(2):
            if abs(par[c, j] - ref_par[c, j]) > rtol * abs(ref_par[c, j]):
                return False
    return True


@njit(cache=True, nogil=True, inline="always")
def _small_gain(ll: float, ll_prev: float, tol: float) -> bool:
    """The stopping rule: one EM step gained at most ``tol * (|ll| + 1)``."""
    return ll - ll_prev <= tol * (abs(ll) + 1.0)


@njit(cache=True, nogil=True)
def em_general_kernel(
    counts: np.ndarray,
    x: np.ndarray,
    kind: np.ndarray,
    par: np.ndarray,
    w: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    max_iter: int,
    tol: float,
    max_newton: int,
    ll_trace: np.ndarray,
    accel: bool,
    ref_w: np.ndarray,
    ref_par: np.ndarray,
    merge_rtol: float,
    rice_min: float,
) -> tuple[int, int]:
    """(Generalised) EM for any mix of kinds 0-6, in place on ``par (C, 2)`` and ``w``; returns
    ``(n_iter, status)``: :data:`EM_MAX_ITER` (0), :data:`EM_CONVERGED` (1), :data:`EM_MERGED` (2)
    or :data:`EM_RICE_AT_ZERO` (3) - the last two stop a run early (below).

    Every argument is required, in these types (float64 C arrays, ``accel`` a bool, the two
    tolerances floats), so that every caller runs the one compiled signature: without a reference
    pass :data:`NO_REF_W`, :data:`NO_REF_PAR` and ``merge_rtol = 0.0``, without the Rice stop
    ``rice_min = 0.0`` (:func:`em_general_args` gives the tail of the arguments).

    With ``ref_w`` / ``ref_par`` (a converged result of the same problem from another start) and
    ``merge_rtol > 0`` the run stops (``EM_MERGED``) once, at the start of an iteration (a SQUAREM
    cycle), every weight and every non-zero parameter coordinate lies within ``merge_rtol``
    (relative) of the reference: it is climbing to the same maximum.  With ``rice_min > 0`` it
    stops (``EM_RICE_AT_ZERO``) at the start of an iteration after the first
    :data:`RICE_MIN_ITER` once a Rice component's ``nu / sigma`` is below ``rice_min``: the Rice
    has become a Rayleigh, where EM converges sublinearly (the likelihood is even in ``nu``).

    ``par[c, 0]`` is ``eta`` for kinds 1-2 (exact M-step: moment matching) and the first
    coordinate of kinds 3-6 (damped Newton, improvement only); ``lo``/``hi`` are ``(C, 2)``
    bounds.  With ``accel`` (default) the EM map is accelerated by SQUAREM (see the notes above
    :data:`SQ_STEP_MAX0`), otherwise plain EM.

    ``n_iter`` counts EM map evaluations (M-steps; under SQUAREM including the stabilising steps
    of rejected extrapolations) and is at most ``max_iter``.  ``ll_trace[i]`` receives the
    log-likelihood of the parameters held after ``i`` of them (``ll_trace[0]``: the start,
    ``ll_trace[n_iter]``: the returned parameters); it never decreases (but for the rounding of
    an EM step that gains nothing).  The fit has converged when one EM step - from the held
    parameters, or the stabilising step from an extrapolated point - gains at most
    ``tol * (|ll| + 1)``; the parameters returned are that step's result.
    """
    C = kind.shape[0]
    L = x.shape[0]
    h = x[1] - x[0]
    xe = x.copy()
    xe[0] = 0.5 * h
    keep = False  # responsibilities per level: only the Newton M-step of kinds 3-6 needs them
    for c in range(C):
        keep = keep or kind[c] >= 3
    lx = np.log(xe) if keep else xe  # log levels: only kinds 3-6 read them
    occ, N = _occupied(counts)
    P = np.zeros((C, L))
    Rsp = np.zeros((C, L)) if keep else np.zeros((C, 1))
    u = np.empty(L)
    # kinds 1-2: each component's last evaluation (:func:`_eval_cached`)
    U = np.empty((C, L))
    EC = np.full((C, 4), np.nan)
    # two evaluation slots per two-parameter component (see _eval_slot); sc NaN = empty
    Ls = L if keep else 1
    V = np.empty((C, 2, 4, Ls))
    GR = np.empty((C, 2, Ls, 2))
    HS = np.empty((C, 2, Ls, 3))
    SC = np.full((C, 2, _SC_SIZE), np.nan)
    cur = np.zeros(C, dtype=np.int64)
    m_lo, m_hi = _eta_mean_bounds(kind, x, lo[:, 0], hi[:, 0], u)
    Nc = np.empty(C)
    tbar = np.empty(C)
    pk = np.empty(C)

    def estep() -> float:
        return _estep_general(counts, x, xe, lx, kind, par, w, occ, P, Rsp, Nc, tbar, pk, U, EC, V, GR, HS,
                              SC, cur, keep)

    def mstep() -> None:
        _mstep_general(x, xe, lx, kind, par, w, lo, hi, N, Rsp, Nc, tbar, m_lo, m_hi, U, EC, V, GR, HS,
                       SC, cur, max_newton)

    Y = np.empty((4, 3 * C))  # SQUAREM: coordinates of x0, x1, x2 and the extrapolated point
    par2 = np.empty((C, 2))
    w2 = np.empty(C)
    step_max = SQ_STEP_MAX0
    converged = False
    it = 0
    ll = estep()
    ll_trace[0] = ll
    while it < max_iter:
        if merge_rtol > 0.0 and _near(w, par, ref_w, ref_par, merge_rtol):
            return it, EM_MERGED
        if rice_min > 0.0 and it >= RICE_MIN_ITER and _rice_at_zero(kind, par, rice_min):
            return it, EM_RICE_AT_ZERO
        # x1 = F(x0) and x2 = F(x1): plain EM steps (one per pass without ``accel``)
        for k in range(2 if accel else 1):
            if accel:
                _sq_coords(kind, par, w, lo, hi, Y[k])
            ll_prev = ll
            mstep()
            it += 1
            ll = estep()
            ll_trace[it] = ll
            if _small_gain(ll, ll_prev, tol):
                converged = True
                break
            if it >= max_iter:
                break
        if converged:
            break
        if not accel or it >= max_iter:
            continue
        # x' = x0 + 2 a r + a^2 v, then x3 = F(x'), kept if ll(x3) >= ll(x2)
        ll2 = ll
        _sq_coords(kind, par, w, lo, hi, Y[2])
        a = _sq_step_length(Y[0], Y[1], Y[2], step_max)
        ll_prev = ll2
        if a > 1.0:
            par2[:, :] = par
            w2[:] = w
            _sq_extrapolate(Y[0], Y[1], Y[2], a, Y[3])
            _sq_point(kind, Y[3], lo, hi, par2, w2, par, w)
            ll_prev = estep()
        stepped = ll_prev > -np.inf  # else x' is off the support (or NaN): no EM step from it
        if stepped:
            mstep()
            it += 1
            ll = estep()
        if a > 1.0 and not (stepped and ll >= ll2):
            # rejected: back to x2
            par[:, :] = par2
            w[:] = w2
            ll = estep()
            ll_trace[it] = ll
            if a >= step_max:
                step_max = max(1.0, step_max / _SQ_GROW)
            continue
        ll_trace[it] = ll
        if a >= step_max:
            step_max *= _SQ_GROW
        if _small_gain(ll, ll_prev, tol):
            converged = True
            break
    return it, EM_CONVERGED if converged else EM_MAX_ITER
