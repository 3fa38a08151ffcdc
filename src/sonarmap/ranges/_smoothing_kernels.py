"""Numba kernel of :mod:`sonarmap.ranges.smoothing` (leading edges along a surface)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from sonarmap.ranges._kernels import _interp_index, first_interval_runs


@njit(cache=True, nogil=True)
def _solve3(a, b, x, row, inv):  # pragma: no cover - numba
    """``a x = b`` for a symmetric 3 x 3 ``a`` by Cramer's rule into ``x`` (NaN when singular); also
    ``a``'s inverse's first row (the prediction weights' coefficients) into ``row``; ``inv``: 3 x 3
    scratch.  Returns ``(x, row)``."""
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    x[:] = np.nan
    row[:] = np.nan
    if not abs(det) > 1e-300:
        return x, row
    inv[0, 0] = c00 / det
    inv[0, 1] = (a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]) / det
    inv[0, 2] = (a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]) / det
    inv[1, 0] = c01 / det
    inv[1, 1] = (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]) / det
    inv[1, 2] = (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]) / det
    inv[2, 0] = c02 / det
    inv[2, 1] = (a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]) / det
    inv[2, 2] = (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]) / det
    for r in range(3):
        x[r] = inv[r, 0] * b[0] + inv[r, 1] * b[1] + inv[r, 2] * b[2]
        row[r] = inv[0, r]
    return x, row


@njit(cache=True, nogil=True)
def _tricube_table(h):  # pragma: no cover - numba
    """The tricube weight of each offset ``0 .. h`` beams over a window of ``h`` beams either
    side (symmetric: an offset's weight is its absolute value's)."""
    tw = np.empty(h + 1)
    for d in range(h + 1):
        v = float(d) / (h + 1)
        t = 1.0 - v * v * v
        tw[d] = t * t * t
    return tw


@njit(cache=True, nogil=True)
def smooth_edges(edge, sigma, run, half_beams, min_beams, sigma_min, wsig):  # pragma: no cover - numba
    """Per beam ``(edge, sigma)`` (bins) after :func:`sonarmap.ranges.smoothing.smooth_surface_edges`.

    ``edge``, ``sigma`` (bins, NaN: none) and ``run`` (surface label, -1: none; a run is a
    contiguous block of beams) per beam; ``wsig`` (bins) the sigma each beam weighs with and is
    pulled by (its ``trust`` times ``sigma``).  Beams of runs with fewer than ``min_beams`` finite
    edges, and beams with fewer than 4 neighbours in their window, keep their values.
    """
    m = edge.size
    new = edge.copy()
    out_sigma = sigma.copy()
    h = half_beams
    a3 = np.empty((3, 3))
    b3 = np.empty(3)
    x3 = np.empty(3)
    r3 = np.empty(3)
    inv3 = np.empty((3, 3))
    # per beam, whether it has an edge and the square of the sigma it weighs with; per offset,
    # the tricube weight (each computed once, not once per window it falls in)
    ok = np.empty(m, np.bool_)
    s2w = np.empty(m)
    for j in range(m):
        ok[j] = np.isfinite(edge[j]) and np.isfinite(sigma[j])
        s2w[j] = max(wsig[j], sigma_min) ** 2
    tw = _tricube_table(h)
    j0 = 0
    while j0 < m:
        j1 = j0 + 1
        while j1 < m and run[j1] == run[j0]:
            j1 += 1
        n_ok = 0
        for j in range(j0, j1):
            if ok[j]:
                n_ok += 1
        if run[j0] >= 0 and n_ok >= min_beams:
            for a in range(j0, j1):
                if not ok[a]:
                    continue
                _smooth_beam(edge, sigma, a, max(j0, a - h), min(j1, a + h + 1), sigma_min, a3, b3, x3, r3,
                             inv3, new, out_sigma, wsig, ok, s2w, tw)
        j0 = j1
    return new, out_sigma


@njit(cache=True, nogil=True)
def _smooth_beam(edge, sigma, a, lo, hi, sigma_min, a3, b3, x3, r3, inv3, new, out_sigma, wsig, ok, s2w,
                 tw):  # pragma: no cover - numba
    """Beam ``a``'s edge and sigma combined with the leave-one-out weighted local quadratic of the
    beams ``lo .. hi - 1`` (see :func:`smooth_edges`), written to ``new`` / ``out_sigma``: the
    weights, the prediction's variance and the gain from the weighing sigmas ``wsig`` (their
    squares, at least ``sigma_min``'s, in ``s2w``; ``ok``: the beams with an edge; ``tw``: the
    tricube weight per offset), the reported sigma shrunk from ``sigma``."""
    a3[:, :] = 0.0
    b3[:] = 0.0
    n = 0
    for i in range(lo, hi):
        if i == a or not ok[i]:
            continue
        u = float(i - a)
        w = tw[abs(i - a)] / s2w[i]
        p = 1.0
        for r in range(3):
            q = p * p  # u^(r + c), from c = r
            for c in range(r, 3):
                a3[r, c] += w * q
                q *= u
            b3[r] += w * p * edge[i]
            p *= u
        n += 1
    if n < 4:
        return
    for r in range(3):
        for c in range(r):
            a3[r, c] = a3[c, r]
    coef, row = _solve3(a3, b3, x3, r3, inv3)
    if not np.isfinite(coef[0]):
        return
    # the neighbours' scatter about the quadratic (tricube weights), their sigmas, and the
    # prediction's variance: sum l_i^2 (sigma_i^2 + roughness) + roughness
    sw = 0.0
    sr = 0.0
    ss = 0.0
    for i in range(lo, hi):
        if i == a or not ok[i]:
            continue
        u = float(i - a)
        t = tw[abs(i - a)]
        r = edge[i] - (coef[0] + coef[1] * u + coef[2] * u * u)
        sw += t
        sr += t * r * r
        ss += t * s2w[i]
    dof = max(1.0 - 3.0 / n, 0.2)
    v_res = sr / sw / dof
    rough = max(v_res - ss / sw, 0.0)
    vp = rough
    for i in range(lo, hi):
        if i == a or not ok[i]:
            continue
        u = float(i - a)
        s2 = s2w[i]
        li = (row[0] + row[1] * u + row[2] * u * u) * tw[abs(i - a)] / s2
        vp += li * li * (s2 + rough)
    w_a = max(wsig[a], sigma_min)
    k = w_a * w_a / (w_a * w_a + vp)
    new[a] = edge[a] + k * (coef[0] - edge[a])
    s_a = max(sigma[a], sigma_min)
    # the beam-to-beam scatter the combination removes (never below half the sigma), with the
    # gain the beam's own sigma gives (a beam weighed as less trusted moves further, but its
    # reported sigma does not shrink for that; k itself where it is weighed by its own sigma)
    k_own = s_a * s_a / (s_a * s_a + vp)
    v_new = max(s_a * s_a - k_own * min(v_res, s_a * s_a), 0.25 * s_a * s_a)
    out_sigma[a] = min(sigma[a], math.sqrt(v_new))


@njit(cache=True, nogil=True)
def smoothed_echo_edges(sel, edge_bin, edge_range, sigma_m, start_bin, stop_bin, touch, half_beams, min_beams,
                        sigma_min, bin_m, range_m, trust):  # pragma: no cover - numba
    """:func:`smooth_edges` of the returns ``sel`` (echo index per beam, -1: none) on their runs
    (:func:`first_interval_runs` with ``touch``) applied to the echoes: ``(n_moved, edge_bin,
    edge_range, sigma_m)``, copies of the echoes' fields with each return whose edge or sigma
    (``bin_m`` x the kernel's, in bins) changed moved there, its range ``np.interp`` on
    ``range_m`` - the arithmetic of the numpy formulation (sigma in bins ``sigma_m / bin_m``, NaN
    without a return); ``trust`` per echo, the factor on its sigma inside the combination."""
    edge, _, run = first_interval_runs(sel, edge_bin, start_bin, stop_bin, touch, -1.0)
    m = sel.size
    sigma = np.full(m, np.nan)
    wsig = np.full(m, np.nan)
    for j in range(m):
        if sel[j] >= 0:
            sigma[j] = sigma_m[sel[j]] / bin_m
            wsig[j] = sigma[j] * trust[sel[j]]
    new, new_sigma = smooth_edges(edge, sigma, run, half_beams, min_beams, sigma_min, wsig)
    eb = edge_bin.copy()
    er = edge_range.copy()
    sg = sigma_m.copy()
    n_moved = 0
    for j in range(m):
        k = sel[j]
        if k < 0:
            continue
        s = new_sigma[j] * bin_m
        if new[j] != edge_bin[k] or s != sigma_m[k]:
            eb[k] = new[j]
            er[k] = _interp_index(range_m, new[j])
            sg[k] = s
            n_moved += 1
    return n_moved, eb, er, sg
