"""Exact persistency reduction of the binary Potts MRF by ladders of two range bins (numba, private;
see :func:`sonarmap.classify.mrf._graphcut_lut`).

After the chain reduction (:func:`sonarmap.classify._kernels.reduce_chains`) the pixels left
free are those whose label depends on their neighbours in the adjacent range bins, which a chain
only bounds.  A *ladder* takes two adjacent bins ``i`` and ``i + 1`` together: over each maximal
run of columns where either bin has a free pixel, the two-row problem (free pixels as variables,
fixed ones as constants, the edges between the two bins exact) is a chain of 4-state columns,
solved exactly by dynamic programming.  As for the chains, the free neighbours in bins ``i - 1``
and ``i + 2`` contribute anything in ``[-wr, wr]`` to the margins: a pixel that takes label 1 in
every minimiser of the ladder under the lowest margins has label 1 in every minimiser of the whole
problem, and one that takes 0 under the highest has 0 (the least minimiser of a submodular energy
grows with the margins).  A decision needs a min-marginal gap above a generous bound on the
programme's rounding error, so the fixing is exact in floating point too; the graph cut then
solves fewer pixels (an Oculus ping: ~2000 free pixels after the chains, ~700 after two ladder
passes).

States of a column: ``s = x_i + 2 x_{i+1}``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Relative bound on the dynamic programme's rounding error per column (a few ulps of the
#: column's cost scale per addition, with a wide margin): gaps below ``(n + 1) * LADDER_TOL * s``
#: (``n`` columns, ``s`` their summed cost scale) decide nothing.
LADDER_TOL = 1e-13


@njit(cache=True, nogil=True, inline="always")
def _min_step(f0, f1, f2, f3, wb):  # pragma: no cover - numba
    """The min-sum message of a column's costs ``f`` to the next column (``min_s' f[s'] + wb [bit
    0 differs] + wb [bit 1 differs]``, separably).  Not normalised: the costs stay below the run's
    summed cost scale, whose rounding the decisions' tolerance covers many times over."""
    g0 = min(f0, f1 + wb)
    g1 = min(f1, f0 + wb)
    g2 = min(f2, f3 + wb)
    g3 = min(f3, f2 + wb)
    o0 = min(g0, g2 + wb)
    o1 = min(g1, g3 + wb)
    o2 = min(g2, g0 + wb)
    o3 = min(g3, g1 + wb)
    return o0, o1, o2, o3


@njit(cache=True, nogil=True, inline="always")
def _gap(f, b0, b1, b2, b3, r):  # pragma: no cover - numba
    """Min-marginal gap of bit ``r`` of a column (forward costs ``f``, backward message ``b``): the
    least ``f[s] + b[s]`` with the bit 0 minus the least with it 1."""
    c0 = f[0] + b0
    c1 = f[1] + b1
    c2 = f[2] + b2
    c3 = f[3] + b3
    if r == 0:
        return min(c0, c2) - min(c1, c3)
    return min(c0, c1) - min(c2, c3)


@njit(cache=True, nogil=True, inline="always")
def _outside(fixed, oi, j, wr):  # pragma: no cover - numba
    """``(c, v)``: what the pixel ``(oi, j)`` outside the ladder adds to its neighbour's margin,
    ``c`` for sure and ``[-v, v]`` more (``+-wr`` if fixed, ``[-wr, wr]`` if free)."""
    g = fixed[oi, j]
    return (wr if g == 1 else -wr) if g >= 0 else 0.0, wr if g < 0 else 0.0


@njit(cache=True, nogil=True)
def _local_costs(levels, margin_lut, fixed, i, j0, n, wr, wb, loc):  # pragma: no cover - numba
    """The column costs of the ladder of bins ``i, i + 1`` over columns ``j0 .. j0 + n - 1``:
    ``loc[v, t, s]`` for the lowest (``v = 0``) and highest (``v = 1``) margins, ``inf`` for a state
    that contradicts a fixed pixel; returns the summed cost scale of the columns.  A free pixel's
    margin: its own, the pixel outside the ladder in its column (``+-wr``, ``[-wr, wr]`` if free,
    nothing outside the lattice) and at the run's ends the fixed pixels beyond (``+-wb``)."""
    h, w = levels.shape
    inf = np.inf
    scale = 0.0
    for t in range(n):
        j = j0 + t
        fa = fixed[i, j]
        fb = fixed[i + 1, j]
        ma = margin_lut[levels[i, j]]
        mb = margin_lut[levels[i + 1, j]]
        va = vb = 0.0
        if i > 0:
            c, va = _outside(fixed, i - 1, j, wr)
            ma += c
        if i + 2 < h:
            c, vb = _outside(fixed, i + 2, j, wr)
            mb += c
        if t == 0 and j > 0:
            ma += wb if fixed[i, j - 1] == 1 else -wb
            mb += wb if fixed[i + 1, j - 1] == 1 else -wb
        if t == n - 1 and j + 1 < w:
            ma += wb if fixed[i, j + 1] == 1 else -wb
            mb += wb if fixed[i + 1, j + 1] == 1 else -wb
        # a fixed pixel: no margin, its other state forbidden (branch-free: the rows mix both)
        ka = 1.0 if fa < 0 else 0.0
        kb = 1.0 if fb < 0 else 0.0
        la = (ma - va) * ka
        ha = (ma + va) * ka
        lb = (mb - vb) * kb
        hb = (mb + vb) * kb
        pa0 = inf if fa == 1 else 0.0
        pa1 = inf if fa == 0 else 0.0
        pb0 = inf if fb == 1 else 0.0
        pb1 = inf if fb == 0 else 0.0
        scale += (abs(ma) + va) * ka + (abs(mb) + vb) * kb + wr + 2.0 * wb
        loc[0, t, 0] = pa0 + pb0
        loc[0, t, 1] = (wr - la) + pa1 + pb0
        loc[0, t, 2] = (wr - lb) + pa0 + pb1
        loc[0, t, 3] = (-la - lb) + pa1 + pb1
        loc[1, t, 0] = pa0 + pb0
        loc[1, t, 1] = (wr - ha) + pa1 + pb0
        loc[1, t, 2] = (wr - hb) + pa0 + pb1
        loc[1, t, 3] = (-ha - hb) + pa1 + pb1
    return scale


@njit(cache=True, nogil=True)
def _ladder_run(levels, margin_lut, fixed, i, j0, n, wr, wb, loc, fwd):  # pragma: no cover - numba
    """Decide what can be decided of the free pixels of bins ``i, i + 1`` in columns
    ``j0 .. j0 + n - 1`` (each column has a free pixel, the columns around them none): forward
    and backward min-sum messages under both margin bounds (``v = 0`` lowest, 1 highest; the two
    chains of additions side by side), min-marginals per pixel; fixes the decided pixels in
    ``fixed`` and returns how many.  ``loc``, ``fwd``: work arrays ``(2, >= n, 4)``."""
    tol = (n + 1) * LADDER_TOL * _local_costs(levels, margin_lut, fixed, i, j0, n, wr, wb, loc)
    a0 = a1 = a2 = a3 = b0 = b1 = b2 = b3 = 0.0
    for t in range(n):
        if t > 0:
            a0, a1, a2, a3 = _min_step(a0, a1, a2, a3, wb)
            b0, b1, b2, b3 = _min_step(b0, b1, b2, b3, wb)
        a0 += loc[0, t, 0]
        a1 += loc[0, t, 1]
        a2 += loc[0, t, 2]
        a3 += loc[0, t, 3]
        b0 += loc[1, t, 0]
        b1 += loc[1, t, 1]
        b2 += loc[1, t, 2]
        b3 += loc[1, t, 3]
        fwd[0, t, 0] = a0
        fwd[0, t, 1] = a1
        fwd[0, t, 2] = a2
        fwd[0, t, 3] = a3
        fwd[1, t, 0] = b0
        fwd[1, t, 1] = b1
        fwd[1, t, 2] = b2
        fwd[1, t, 3] = b3
    a0 = a1 = a2 = a3 = b0 = b1 = b2 = b3 = 0.0       # the backward messages
    n_fixed = 0
    for t in range(n - 1, -1, -1):
        j = j0 + t
        for r in range(2):
            if fixed[i + r, j] >= 0:
                continue
            if _gap(fwd[0, t], a0, a1, a2, a3, r) > tol:          # 1 under the lowest margins
                fixed[i + r, j] = 1
                n_fixed += 1
            elif _gap(fwd[1, t], b0, b1, b2, b3, r) < -tol:       # 0 under the highest
                fixed[i + r, j] = 0
                n_fixed += 1
        if t > 0:
            a0, a1, a2, a3 = _min_step(a0 + loc[0, t, 0], a1 + loc[0, t, 1], a2 + loc[0, t, 2],
                                       a3 + loc[0, t, 3], wb)
            b0, b1, b2, b3 = _min_step(b0 + loc[1, t, 0], b1 + loc[1, t, 1], b2 + loc[1, t, 2],
                                       b3 + loc[1, t, 3], wb)
    return n_fixed


@njit(cache=True, nogil=True)
def _pair_columns(stack, w, i, a0, a1, b1, fixed, cols):  # pragma: no cover - numba
    """The columns (ascending) where bin ``i`` or ``i + 1`` still has a free pixel, from their
    entries ``stack[a0:a1]`` and ``stack[a1:b1]`` of the free list; returns how many."""
    n = 0
    ka = a0
    kb = a1
    while ka < a1 or kb < b1:
        ja = stack[ka] - i * w if ka < a1 else w
        jb = stack[kb] - (i + 1) * w if kb < b1 else w
        j = min(ja, jb)
        ka += ja == j
        kb += jb == j
        if fixed[i, j] < 0 or fixed[i + 1, j] < 0:
            cols[n] = j
            n += 1
    return n


@njit(cache=True, nogil=True)
def reduce_ladders(levels, margin_lut, fixed, stack, n_free, wr, wb, max_passes):  # pragma: no cover - numba
    """Exact persistency reduction by ladders of two range bins (see the module docstring), after
    :func:`sonarmap.classify._kernels.reduce_chains`: up to ``max_passes`` passes over the pairs
    of adjacent bins, each fixing what it decides at once; ``stack[:n_free]`` (the free pixels,
    ascending) is compacted after each pass.  Returns the new ``n_free``."""
    h, w = levels.shape
    loc = np.empty((2, w, 4))
    fwd = np.empty((2, w, 4))
    cols = np.empty(w, dtype=np.int64)
    row_start = np.empty(h + 2, dtype=np.int64)
    flat = fixed.reshape(h * w)
    for _ in range(max_passes):
        k = 0
        for r in range(h + 2):
            while k < n_free and stack[k] < r * w:
                k += 1
            row_start[r] = k
        n_fixed = 0
        for i in range(h - 1):
            a0 = row_start[i]
            a1 = row_start[i + 1]
            b1 = row_start[i + 2]
            if a0 == b1:
                continue
            nc = _pair_columns(stack, w, i, a0, a1, b1, fixed, cols)
            t = 0
            while t < nc:
                n = 1
                both = fixed[i, cols[t]] < 0 and fixed[i + 1, cols[t]] < 0
                while t + n < nc and cols[t + n] == cols[t] + n:
                    both |= fixed[i, cols[t + n]] < 0 and fixed[i + 1, cols[t + n]] < 0
                    n += 1
                # without a column free in both bins the ladder is two chains (reduce_chains)
                if both:
                    n_fixed += _ladder_run(levels, margin_lut, fixed, i, cols[t], n, wr, wb, loc, fwd)
                t += n
        k_out = 0
        for k in range(n_free):
            p = stack[k]
            if flat[p] < 0:
                stack[k_out] = p
                k_out += 1
        n_free = k_out
        if n_fixed == 0 or n_free == 0:
            break
    return n_free
