"""Numba kernels of the per-ping pipeline (private; see :mod:`sonarmap.pipeline`)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def excess_ratio(raw, level, full, log_db, r0, r1):  # pragma: no cover - numba
    """``max(ratio - 1, 0)`` with ``ratio = raw / b`` (``log_db <= 0``) or ``10^(log_db (raw - b) / 10)``,
    ``b = level[i] * full[i, j]``, on rows ``r0 .. r1 - 1`` (zero elsewhere); float64."""
    n, m = raw.shape
    out = np.zeros((n, m))
    k = log_db * np.log(10.0) / 10.0
    for i in range(max(r0, 0), min(r1, n)):
        for j in range(m):
            b = level[i] * full[i, j]
            if log_db > 0:
                x = k * (raw[i, j] - b)
                if x > 69.0:
                    x = 69.0
                v = np.exp(x) - 1.0
            else:
                v = raw[i, j] / max(b, 1e-12) - 1.0
            if v > 0.0:
                out[i, j] = v
    return out


@njit(cache=True, nogil=True)
def first_clipped_rows(img, cols, lo, hi, level):  # pragma: no cover - numba
    """Per ``k``, the first row in ``lo[k] .. hi[k] - 1`` of column ``cols[k]`` of ``img`` that
    reaches ``level`` (-1 if none)."""
    out = np.full(cols.size, -1, dtype=np.int64)
    for k in range(cols.size):
        j = cols[k]
        for i in range(lo[k], hi[k]):
            if img[i, j] >= level:
                out[k] = i
                break
    return out
