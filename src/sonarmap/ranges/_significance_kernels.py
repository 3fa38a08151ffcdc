"""Numba kernel of :mod:`sonarmap.ranges.significance` (a surface's echo against its water column)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from sonarmap.ranges._kernels import _median, _median_of, first_interval_runs, run_spans


@njit(cache=True, nogil=True)
def _resistant_line(o, v, n, work):  # pragma: no cover - numba
    """Tukey's resistant line through ``(o[:n], v[:n])`` (``o`` increasing): the slope through the
    medians of the outer thirds, the intercept the median of ``v - slope o`` (``work``: scratch)."""
    k = n // 3
    ol = _median_of(o, 0, k, work)
    vl = _median_of(v, 0, k, work)
    orr = _median_of(o, n - k, n, work)
    vr = _median_of(v, n - k, n, work)
    slope = (vr - vl) / (orr - ol) if orr > ol else 0.0
    for t in range(n):
        work[t] = v[t] - slope * o[t]
    return _median(work, n), slope


@njit(cache=True, nogil=True)
def _run_z(raw, rows, j0, depth, gap, window, min_shifts, null, offs, work):  # pragma: no cover - numba
    """``(z, n_shifts)`` of one surface: its beams ``j0 .. j0 + rows.size - 1`` with echo rows
    ``rows`` (the bin of each leading edge), ``depth`` bins deep (fewer where the window ends first; see
    :func:`surface_z`); ``null``, ``offs`` and ``work`` are scratch of at least ``window``
    values."""
    n = raw.shape[0]
    nb = rows.size
    lo_row = n
    hi_row = 0
    for q in range(nb):
        lo_row = min(lo_row, rows[q])
        hi_row = max(hi_row, rows[q])
    # the offsets towards the sonar that keep every beam's samples inside the window: from -gap
    # down to -(gap + window - 1), none above row 0
    first = max(-(gap + window - 1), -lo_row)
    depth = min(depth, n - hi_row)  # (a surface at the end of the window: the bins it has)
    if depth < 1 or -gap < first:
        return math.nan, 0
    a = lo_row + first  # the first row any offset reads
    b = hi_row + depth  # one past the last
    span = b - a
    # per beam the running sums of the samples over rows a .. b - 1 (only the rows the surface
    # and its shifts read: an image-sized array would cost page faults on every ping)
    # (``prefix[t, q]``: the sum over rows a .. a + t - 1 of beam q, accumulated along the rows -
    # each beam's additions in the same order as a walk down its column, which missed the cache at
    # every row)
    prefix = np.empty((span + 1, nb))
    acc = np.zeros(nb)
    prefix[0] = 0.0
    for t in range(span):
        src = raw[a + t, j0:j0 + nb]
        row = prefix[t + 1]
        for q in range(nb):
            acc[q] += src[q]
            row[q] = acc[q]
    scale = 1.0 / (nb * depth)
    s0 = 0.0
    for q in range(nb):
        k = rows[q] - a
        s0 += prefix[k + depth, q] - prefix[k, q]
    s0 *= scale
    m = 0
    for off in range(first, -gap + 1):
        s = 0.0
        for q in range(nb):
            k = rows[q] + off - a
            s += prefix[k + depth, q] - prefix[k, q]
        null[m] = s * scale
        offs[m] = off
        m += 1
    if m < min_shifts:
        return math.nan, m
    # the water column's trend along range (the background's level changes with range), then the
    # spread of the shifted copies about it
    c, slope = _resistant_line(offs, null, np.int64(m), work)
    for t in range(m):
        work[t] = abs(null[t] - (c + slope * offs[t]))
    mad = 1.4826 * _median(work, m)
    if not mad > 0:
        return (math.inf if s0 > c else 0.0), m
    return (s0 - c) / mad, m


@njit(cache=True, nogil=True)
def surface_z(raw, sel, edge_bin, start_bin, stop_bin, touch, min_depth, max_depth, gap, window,
              min_shifts, min_beams, jump=-1.0):  # pragma: no cover - numba
    """Per beam the significance ``z`` of its return's surface (NaN: no return, a surface of fewer
    than ``min_beams`` beams, or too few rows in front to test) and per beam the number of offsets
    its surface was compared with.

    The surfaces are the runs of :func:`first_interval_runs` (``touch``; with ``jump >= 0`` also
    neighbouring beams whose edges lie within ``jump`` bins).  A surface's
    statistic is the mean of ``raw`` over its beams and ``depth`` bins from each leading edge's bin (``depth``:
    the median over its beams of ``stop - edge``, clipped to ``min_depth .. max_depth``); the null
    is the same statistic with the whole surface moved ``gap .. gap + window - 1`` bins towards
    the sonar (each beam's samples in front of its first return: its water column); ``z`` is the
    statistic's distance from the null's resistant line in the offset, extrapolated to offset 0,
    in units of the scaled median absolute deviation of the null about that line.
    """
    m = sel.size
    z = np.full(m, np.nan)
    used = np.zeros(m, np.int64)
    if edge_bin.size == 0:
        return z, used
    # (with jump >= 0, neighbouring returns whose edges lie within it are one surface too)
    edge, stop, run = first_interval_runs(sel, edge_bin, start_bin, stop_bin, touch, jump)
    n = raw.shape[0]
    null = np.empty(max(window, 1))
    offs = np.empty(max(window, 1))
    work = np.empty(max(window, 1))
    d = np.empty(m)
    starts, stops = run_spans(run)
    for r in range(starts.size):
        j, j1 = starts[r], stops[r]
        nb = j1 - j
        if nb < min_beams:
            continue
        rows = np.empty(nb, np.int64)
        for q in range(nb):
            e = edge[j + q]  # (finite: surface_runs labels only beams with an edge)
            rows[q] = min(max(int(math.floor(e + 0.5)), 0), n - 1)
            d[q] = stop[j + q] - e
        depth = int(math.floor(_median(d, nb) + 0.5))
        depth = min(max(depth, min_depth), max_depth)
        zz, k = _run_z(raw, rows, j, depth, gap, window, min_shifts, null, offs, work)
        for q in range(nb):
            z[j + q] = zz
            used[j + q] = k
    return z, used
