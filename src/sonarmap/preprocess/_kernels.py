"""numba kernels of :mod:`sonarmap.preprocess.normalise` (private to this package)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def pooled_ratio(img, level, factor, pool_r, pool_c):  # pragma: no cover - numba
    """``uniform_filter(img / (level[:, None] * factor), (pool_r, pool_c), mode="nearest")``.

    ``img`` and ``factor`` are float32 (n, m), ``level`` float32 (n,).  Separable running box
    sums (rows, then beams) with edge samples repeated, as scipy's ``mode="nearest"``; the box
    is centred (offset ``size // 2`` to the start, scipy's default origin).
    """
    n, m = img.shape
    z = np.empty((n, m), dtype=np.float32)
    for i in range(n):
        inv = 1.0 / level[i]
        for j in range(m):
            z[i, j] = img[i, j] * inv / factor[i, j]
    # along range
    tmp = np.empty((n, m), dtype=np.float32)
    hr = pool_r // 2
    for j in range(m):
        s = 0.0
        for k in range(-hr, pool_r - hr):
            ii = min(max(k, 0), n - 1)
            s += z[ii, j]
        for i in range(n):
            tmp[i, j] = s / pool_r
            out_i = min(max(i - hr, 0), n - 1)
            in_i = min(max(i - hr + pool_r, 0), n - 1)
            s += z[in_i, j] - z[out_i, j]
    # across beams
    hc = pool_c // 2
    for i in range(n):
        s = 0.0
        for k in range(-hc, pool_c - hc):
            jj = min(max(k, 0), m - 1)
            s += tmp[i, jj]
        for j in range(m):
            z[i, j] = s / pool_c
            out_j = min(max(j - hc, 0), m - 1)
            in_j = min(max(j - hc + pool_c, 0), m - 1)
            s += tmp[i, in_j] - tmp[i, out_j]
    return z


@njit(cache=True, nogil=True)
def excess(z, t, gain):  # pragma: no cover - numba
    """``min(gain * max(z - t, 0), 1)`` as float32, and the mean of ``z - t`` where positive."""
    n, m = z.shape
    out = np.empty((n, m), dtype=np.float32)
    s = 0.0
    c = 0
    for i in range(n):
        for j in range(m):
            e = z[i, j] - t
            if e > 0:
                s += e
                c += 1
                v = gain * e
                out[i, j] = 1.0 if v > 1.0 else v
            else:
                out[i, j] = 0.0
    return out, (s / c if c > 0 else 0.0), c
