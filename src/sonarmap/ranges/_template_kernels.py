"""Numba kernels of :mod:`sonarmap.ranges.template` (private).

Images are ``(n_bins, n_beams)``; a surface run is a contiguous block of beams with the same
non-negative ``run`` label (:func:`sonarmap.ranges.echoes.surface_runs`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from sonarmap.ranges._kernels import (_edge_sigma, _interp_column, _interp_index, _lu_small, _lu_solve_small,
                                      _median, _median_of, _solve_small, run_spans,
                                      runs_of_returns)


@njit(cache=True, nogil=True, inline="always")
def _power(x, e):  # pragma: no cover - numba
    """``x^e`` as the running product ``1.0 x x ...`` (``e`` factors)."""
    v = 1.0
    for _ in range(e):
        v = v * x
    return v


@njit(cache=True, nogil=True)
def _local_quadratic(cur, a, half, A, rhs):  # pragma: no cover - numba
    """``(value, slope)`` at position ``a`` of the least-squares quadratic through ``cur`` over
    positions ``a - half .. a + half`` (clipped to the array; a line below 5 points, ``cur[a]``
    and 0 below 3).  ``A (3, 3)`` and ``rhs (3,)`` are scratch: the normal equations are summed
    in their leading block (:func:`_normal_matrix`, :func:`_normal_rhs`)."""
    nb = cur.size
    lo = max(0, a - half)
    hi = min(nb, a + half + 1)
    c = hi - lo
    if c < 3:
        return cur[a], 0.0
    deg = 3 if c >= 5 else 2
    _normal_matrix(A, lo - a, hi - a, deg)
    _normal_rhs(cur, a, lo, hi, deg, rhs)
    _solve_small(A, rhs, deg)
    return rhs[0], rhs[1]


@njit(cache=True, nogil=True, inline="always")
def _normal_matrix(A, x0, x1, deg):  # pragma: no cover - numba
    """The normal matrix of a polynomial of degree ``deg - 1`` through the positions ``x0 .. x1 -
    1`` (relative to the fitted one) in ``A[:deg, :deg]``, summed over the positions in order, the
    powers of each formed in registers."""
    for r in range(deg):
        for q in range(deg):
            A[r, q] = 0.0
    for b in range(x0, x1):
        x = float(b)
        for r in range(deg):
            pr = _power(x, r)
            for q in range(deg):
                A[r, q] += pr * _power(x, q)


@njit(cache=True, nogil=True, inline="always")
def _normal_rhs(cur, a, lo, hi, deg, rhs):  # pragma: no cover - numba
    """The right-hand side of :func:`_normal_matrix` for the values ``cur[lo:hi]`` around position
    ``a`` in ``rhs[:deg]``."""
    for r in range(deg):
        rhs[r] = 0.0
    for b in range(lo, hi):
        x = float(b - a)
        for r in range(deg):
            rhs[r] += _power(x, r) * cur[b]


@njit(cache=True, nogil=True)
def _local_quadratics(cur, half, A, rhs, line, slope):  # pragma: no cover - numba
    """``line[a], slope[a] = _local_quadratic(cur, a, half, A, rhs)`` for every position ``a``.
    The positions with the whole window inside the array share its normal matrix: summed and
    factored once (the same factors; on the Oculus runs 2 x 256 matrices a call otherwise)."""
    nb = cur.size
    lu = np.empty((3, 3))
    piv = (0, 0, 0)
    done = False
    for a in range(nb):
        if a < half or a + half >= nb or 2 * half + 1 < 5:
            line[a], slope[a] = _local_quadratic(cur, a, half, A, rhs)
            continue
        if not done:
            _normal_matrix(lu, -half, half + 1, 3)
            piv = _lu_small(lu, 3)
            done = True
        _normal_rhs(cur, a, a - half, a + half + 1, 3, rhs)
        _lu_solve_small(lu, piv, rhs, 3)
        line[a], slope[a] = rhs[0], rhs[1]


@njit(cache=True, nogil=True)
def _median_depth(edge, stop, j0, j1, max_bins):  # pragma: no cover - numba
    """The run's median echo depth behind its edges (bins, 3 .. ``max_bins``)."""
    d = np.empty(j1 - j0)
    for j in range(j0, j1):
        d[j - j0] = stop[j] - edge[j]
    d.sort()
    n = d.size
    med = d[n // 2] if n % 2 == 1 else 0.5 * (d[n // 2 - 1] + d[n // 2])
    return int(min(max(med, 3.0), max_bins))


@njit(cache=True, nogil=True)
def _template_crossing(T, sm, k0, depth, fraction):  # pragma: no cover - numba
    """``(ok, t0, p)``: the first peak ``p`` (index into ``T``) of the 3-bin mean ``sm`` of the
    template ``T`` (offsets ``k0 ..``; unsmoothed for echoes under 6 bins deep) within offsets
    -6 .. ``depth``, and the ``fraction`` crossing ``t0`` (an offset, interpolated) walking from
    it towards the sonar."""
    K = T.size
    # smoothed only where the echo is deep enough for the box not to widen it (a one-bin echo
    # smoothed over 3 bins has its crossing a bin early), as in pooled_edges
    h = 1 if depth >= 6 else 0
    if h == 1 and K >= 3:
        # the same sums in the same order, the interior without the window's bounds (a loop
        # that vectorises: Oculus templates 0.37 -> 0.23 ms a ping)
        sm[0] = (0.0 + T[0] + T[1]) / 2.0
        for k in range(1, K - 1):
            sm[k] = (0.0 + T[k - 1] + T[k] + T[k + 1]) / 3.0
        sm[K - 1] = (0.0 + T[K - 2] + T[K - 1]) / 2.0
    else:
        for k in range(K):
            lo = max(k - h, 0)
            hi = min(k + h + 1, K)
            acc = 0.0
            for i in range(lo, hi):
                acc += T[i]
            sm[k] = acc / (hi - lo)
    p = -1
    for k in range(K):
        off = k + k0
        if -6 <= off <= depth and (p < 0 or sm[k] > sm[p]):
            p = k
    if p < 0 or not sm[p] > 0:
        return False, 0.0, p
    lv = fraction * sm[p]
    i = p
    while i > 0 and sm[i - 1] >= lv:
        i -= 1
    if i == 0:
        return False, 0.0, p
    t0 = (i - 1 + k0) + (lv - sm[i - 1]) / max(sm[i] - sm[i - 1], 1e-12)
    return True, t0, p


@njit(cache=True, nogil=True)
def _front_level(T, k0, front):  # pragma: no cover - numba
    """The template's mean level in front of the surface (offsets ``k0 .. -front``)."""
    acc = 0.0
    c = 0
    for k in range(0, -front - k0 + 1):
        acc += T[k]
        c += 1
    return acc / max(c, 1)


@njit(cache=True, nogil=True)
def _crossing_var(csum, sm, lo, hi, x):  # pragma: no cover - numba
    """The variance (bins^2) of the template's crossing at index ``x`` (fractional) from the spread
    of its beams ``lo .. hi - 1`` there (each column's 3-bin mean; the standard error of their
    mean over the template's rise per bin)."""
    K = sm.size
    i = min(max(int(np.floor(x)), 1), K - 3)
    f = x - i
    rise = sm[i + 1] - sm[i]
    if not rise > 0:
        return 0.0
    s1 = 0.0
    s2 = 0.0
    for b in range(lo, hi):
        v = 0.0
        for k in range(i - 1, i + 3):
            col = csum[b + 1, k] - csum[b, k]
            # column b's 3-bin means at i (k = i-1..i+1) and i + 1 (k = i..i+2)
            if k <= i + 1:
                v += (1.0 - f) * col / 3.0
            if k >= i:
                v += f * col / 3.0
        s1 += v
        s2 += v * v
    c = hi - lo
    if c < 2:
        return 0.0
    var = max(s2 / c - (s1 / c) ** 2, 0.0) * c / (c - 1)
    return var / c / (rise * rise)


@njit(cache=True, nogil=True)
def _score_shift(img, j0, line, slope, T, k0, a, lo, hi, front, top, floor, max_shift, n_score,
                 max_rows):  # pragma: no cover - numba
    """``(c, fisher, spread)``: Fisher scoring of the template position ``c`` at beam ``a`` of the
    run (each beam ``b`` of ``lo .. hi - 1`` sees the template at ``c + slope[a] (b - a)``), for
    exponential (single-look) intensities of mean ``max(T, floor)``, from ``line[a]``, within
    ``max_shift`` of it; at the result, the Fisher information ``J`` (0: none) and the sum over
    the beams of the square of each beam's score ``K``.  ``K / J^2`` is the sandwich (robust)
    variance of ``c``: it equals ``1 / J`` for single-look speckle, ``1 / (L J)`` for intensities
    averaged over ``L`` looks, and grows where the template explains the samples poorly; a beam's
    samples along range share their score (they may share speckle through the pulse)."""
    n = img.shape[0]
    K = T.size
    c = line[a]
    fisher = 0.0
    spread = 0.0
    for _ in range(n_score + 1):
        g = 0.0
        fisher = 0.0
        spread = 0.0
        for b in range(lo, hi):
            r0 = max(int(np.floor(line[b] - front)), 0)
            r1 = min(int(np.ceil(line[b] + top)), n - 1)
            stride = max(1, (r1 - r0 + 1) // max_rows)
            off = c + slope[a] * (b - a)
            gb = 0.0
            for r in range(r0, r1 + 1, stride):
                u = r - off - k0
                i0 = int(np.floor(u))
                if i0 < 0 or i0 >= K - 1:
                    continue
                tp = T[i0 + 1] - T[i0]
                mu = max(T[i0] + (u - i0) * tp, floor)
                v = img[r, j0 + b]
                gi = tp * (v - mu) / (mu * mu)
                g += gi
                gb += gi
                fisher += tp * tp / (mu * mu)
            spread += gb * gb
        if not fisher > 0:
            return c, 0.0, 0.0
        step = min(max(-g / fisher, -2.0), 2.0)
        if abs(step) < 0.01:
            break
        c = min(max(c + step, line[a] - max_shift), line[a] + max_shift)
    return c, fisher, spread


@njit(cache=True, nogil=True)
def _run_edges(img, edge, stop, skip, j0, j1, half_template, half_window, front, max_bins, max_shift,
               n_score, fraction, peak_rows, max_rows, n_iter, min_contrast, new, var):  # pragma: no cover - numba
    """:func:`template_edges` of the run of beams ``j0 .. j1 - 1`` (in place on ``new``, ``var``);
    ``n_iter`` rounds, each aligning the template on the edges of the round before."""
    nb = j1 - j0
    cur = edge[j0:j1].copy()
    line = np.empty(nb)
    slope = np.empty(nb)
    depth = _median_depth(edge, stop, j0, j1, max_bins)
    pad = front + int(np.ceil(max_shift)) + 10
    k0 = -pad
    K = depth + 2 * pad + 1
    csum = np.zeros((nb + 1, K))
    T = np.empty(K)
    sm = np.empty(K)
    A = np.empty((3, 3))
    rhs = np.empty(3)
    for _ in range(n_iter):
        _local_quadratics(cur, half_template, A, rhs, line, slope)
        # every beam's column at offsets k0 .. from its line, and their running sum over beams
        for a in range(nb):
            for k in range(K):
                csum[a + 1, k] = csum[a, k] + _interp_column(img, j0 + a, line[a] + (k + k0))
        for a in range(nb):
            if skip[j0 + a]:
                continue
            lo = max(0, a - half_template)
            hi = min(nb, a + half_template + 1)
            for k in range(K):
                T[k] = (csum[hi, k] - csum[lo, k]) / (hi - lo)
            ok, t0, p = _template_crossing(T, sm, k0, depth, fraction)
            if not ok or not sm[p] >= min_contrast * _front_level(T, k0, front):
                continue
            floor = max(1e-6, 0.01 * sm[p])
            wlo = max(0, a - half_window)
            whi = min(nb, a + half_window + 1)
            c, fisher, spread = _score_shift(img, j0, line, slope, T, k0, a, wlo, whi, front,
                                             (p + k0) + peak_rows, floor, max_shift, n_score, max_rows)
            if not fisher > 0:
                continue
            new[j0 + a] = c + t0
            var[j0 + a, 0] = spread / (fisher * fisher) if spread > 0 else 1.0 / fisher
            var[j0 + a, 1] = _crossing_var(csum, sm, lo, hi, t0 - k0)
        for a in range(nb):
            cur[a] = new[j0 + a]


@njit(cache=True, nogil=True)
def _anchor_run(edge, new, var, j0, j1, anchor, shared):  # pragma: no cover - numba
    """Anchor the template-measured edges of the run ``j0 .. j1 - 1`` on the edges they replace
    (in place): each measured beam's edge moves by the median, over the measured beams of the
    run within ``anchor`` beams, of (edge before - template edge), and ``var[:, 1]`` adds that
    median's variance (``pi / 2`` times the offsets' variance over their number of independent
    ones) to the template crossing's.  Each edge before was measured on the data of ``shared``
    neighbouring beams (a pooled edge's window), so ``c`` offsets count as ``max(c / shared, 1)``
    independent ones: the mean of ``c`` running means of width ``shared`` over independent beams
    has the variance of ``c / shared`` of them."""
    nb = j1 - j0
    d = np.empty(nb)
    ok = np.zeros(nb, np.bool_)
    for a in range(nb):
        ok[a] = np.isfinite(var[j0 + a, 0]) and np.isfinite(edge[j0 + a]) and np.isfinite(new[j0 + a])
        d[a] = edge[j0 + a] - new[j0 + a] if ok[a] else 0.0
    buf = np.empty(2 * anchor + 1)
    srt = np.empty(2 * anchor + 1)
    for a in range(nb):
        if not ok[a]:
            continue
        c = 0
        for k in range(max(0, a - anchor), min(nb, a + anchor + 1)):
            if ok[k]:
                buf[c] = d[k]
                c += 1
        w = buf[:c]
        new[j0 + a] += _median_of(w, 0, c, srt)
        if c >= 2:
            # w.mean() and ((w - mu) ** 2).sum(): the same sequential sums, without temporaries
            mu = 0.0
            for q in range(c):
                mu += w[q]
            mu = mu / c
            ss = 0.0
            for q in range(c):
                e = w[q] - mu
                ss += e * e
            var[j0 + a, 1] += 0.5 * np.pi * ss / (c - 1) / max(c / shared, 1.0)


@njit(cache=True, nogil=True)
def template_edges(img, edge, stop, run, skip, half_template, half_window, front, min_beams, max_bins,
                   max_shift, n_score, fraction, peak_rows, max_rows, n_iter, min_contrast,
                   anchor, shared):  # pragma: no cover - numba
    """Per beam the leading edge re-measured against its surface's echo template, and the
    variances (bins^2; NaN where the beam keeps its edge) of the template's position (the
    sandwich variance of :func:`_score_shift`) and of its crossing (the template beams' spread;
    with ``anchor > 0`` plus the anchor's, :func:`_anchor_run`): see
    :func:`sonarmap.ranges.template.template_edges`.  ``edge`` and ``stop`` (fractional bins;
    one past the echo's last structure bin) per beam, ``run`` the surface runs (-1: none),
    ``skip`` the beams that keep their edge."""
    m = edge.size
    new = edge.copy()
    var = np.full((m, 2), np.nan)
    starts, stops = run_spans(run)
    for k in range(starts.size):
        j, j1 = starts[k], stops[k]
        if j1 - j >= min_beams:
            _run_edges(img, edge, stop, skip, j, j1, half_template, half_window, front, max_bins, max_shift,
                       n_score, fraction, peak_rows, max_rows, n_iter, min_contrast, new, var)
            if anchor > 0:
                _anchor_run(edge, new, var, j, j1, anchor, shared)
    return new, var


@njit(cache=True, nogil=True)
def template_moved_edges(sel, edge_bin, start_bin, stop_bin, touch, img, skip, half_template, half_window, front,
                         min_beams, max_bins, max_shift, n_score, fraction, peak_rows, max_rows, n_iter, min_contrast,
                         anchor, shared, edge_range, sigma_m, range_m, bin_m, bin_var, pulse_var,
                         scale, want_trust):  # pragma: no cover - numba
    """:func:`template_edges` of the returns ``sel`` on their runs (:func:`runs_of_returns` with
    ``touch``) applied to the echoes: ``(n_moved, edge_bin, edge_range, sigma_m, trust)``, copies
    of the echoes' fields with each measured return (finite position variance) moved to its new
    edge, its range ``np.interp`` on ``range_m`` and its sigma :func:`_edge_sigma` of ``sqrt`` of
    the two variances' sum at slope 1 (``bin_var``, ``pulse_var``: ``bin_m^2 / 12``, ``pulse^2 /
    12``) - the numpy formulation's arithmetic; nothing moved when no return is in a run.
    ``trust`` (per echo, 1 where not moved; with ``want_trust`` only, else empty): the sigma with
    the anchor's variance raised to :func:`_anchor_floor` (the incoming edges' own sigmas) where
    that is larger, over the sigma."""
    edge, stop, run, any_run = runs_of_returns(sel, edge_bin, start_bin, stop_bin, touch)
    if not any_run:
        z = np.zeros(0)
        return 0, z, z, z, z
    new, var = template_edges(img, edge, stop, run, skip, half_template, half_window, front, min_beams, max_bins,
                              max_shift, n_score, fraction, peak_rows, max_rows, n_iter, min_contrast, anchor,
                              shared)
    eb = edge_bin.copy()
    er = edge_range.copy()
    sg = sigma_m.copy()
    trust = np.ones(sigma_m.size if want_trust else 0)
    buf = np.empty(2 * max(anchor, 0) + 1)
    n_moved = 0
    for j in range(new.size):
        if np.isfinite(var[j, 0]):
            k = sel[j]
            eb[k] = new[j]
            er[k] = _interp_index(range_m, new[j])
            v = var[j, 0] + var[j, 1]
            sg[k] = _edge_sigma(np.sqrt(v), 1.0, bin_m, bin_var, pulse_var, scale)
            n_moved += 1
            if want_trust:
                floor = _anchor_floor(sel, run, var, sigma_m, j, anchor, shared, bin_m, buf)
                if floor > var[j, 1]:
                    wide = _edge_sigma(np.sqrt(var[j, 0] + floor), 1.0, bin_m, bin_var, pulse_var, scale)
                    if wide > sg[k] > 0:
                        trust[k] = wide / sg[k]
    return n_moved, eb, er, sg, trust


@njit(cache=True, nogil=True)
def _anchor_floor(sel, run, var, sigma_m, j, anchor, shared, bin_m, buf):  # pragma: no cover - numba
    """The variance (bins^2) the anchor of beam ``j`` would have if its median took the
    incoming edges' own sigmas (``sigma_m`` of the returns ``sel``, metres) instead of the offsets'
    scatter: ``pi / 2`` times the median of their squares, over the measured beams of ``j``'s run
    within ``anchor`` beams, counted as ``max(c / shared, 1)`` independent ones (0 without an
    anchor or a finite sigma; ``buf``: scratch of ``2 anchor + 1`` values)."""
    if anchor <= 0:
        return 0.0
    c = 0
    for q in range(max(0, j - anchor), min(sel.size, j + anchor + 1)):
        if run[q] == run[j] and np.isfinite(var[q, 0]) and sel[q] >= 0 and np.isfinite(sigma_m[sel[q]]):
            buf[c] = (sigma_m[sel[q]] / bin_m) ** 2
            c += 1
    if c == 0:
        return 0.0
    return 0.5 * np.pi * _median(buf, c) / max(c / shared, 1.0)
