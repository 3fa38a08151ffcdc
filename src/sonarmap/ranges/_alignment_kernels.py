"""Numba kernel of the pooled edges' alignment on the surface's local line
(:func:`sonarmap.ranges.echoes.pooled_edges`' ``align_beams``)."""

from __future__ import annotations

import numpy as np
from numba import njit

from sonarmap.ranges._kernels import _median, _pair_slope_median


@njit(cache=True, nogil=True)
def line_aligned_edges(edge, run, half_beams):  # pragma: no cover - numba
    """Per beam, the Theil-Sen line through the leading edges of the beams of its surface within
    ``half_beams`` on either side, evaluated at the beam: the median of ``edge[k] + (j - k) s``
    over those beams ``k``, ``s`` the median of the slopes ``(edge[b] - edge[a]) / (b - a)`` of
    their pairs (:func:`~sonarmap.ranges._kernels._pair_slope_median`; medians of an even count:
    the mean of the two middle values).

    ``edge`` (float64, per beam; NaN: no return) and ``run`` (int64, per beam: the surface run of
    :func:`~sonarmap.ranges._kernels.surface_runs`, -1: in none).  A beam in no run, or with
    fewer than 3 beams of its run in the window, keeps its own edge; NaN stays NaN.  One wild edge
    among 7 (a single-look edge found far behind the surface's rise) does not move the line; a
    few more move it by a bounded amount (Theil-Sen's breakdown point: ~29 %).  It is where the
    pooling starts from, not a measurement."""
    m = edge.size
    out = edge.copy()
    w = 2 * half_beams + 1
    idx = np.empty(w, np.int64)
    vals = np.empty(w)
    slopes = np.empty(w * (w - 1) // 2)
    for j in range(m):
        if np.isnan(edge[j]) or run[j] < 0:
            continue
        n = 0
        for k in range(max(0, j - half_beams), min(m, j + half_beams + 1)):
            if run[k] == run[j] and not np.isnan(edge[k]):
                idx[n] = k
                n += 1
        if n < 3:
            continue
        for t in range(n):
            vals[t] = edge[idx[t]]
        s = _pair_slope_median(vals, idx, n, slopes)
        for t in range(n):
            vals[t] = vals[t] + (j - idx[t]) * s
        out[j] = _median(vals, n)
    return out

