"""numba kernels of :mod:`sonarmap.preprocess.normalise` (private to this package)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _running_mean(src, dst, size):  # pragma: no cover - numba
    """``dst[i]`` = mean of ``src[i - size // 2 : i - size // 2 + size]``, edge samples repeated
    (scipy ``uniform_filter1d(mode="nearest")``, default origin)."""
    n = src.shape[0]
    h = size // 2
    s = 0.0
    for k in range(-h, size - h):
        s += src[min(max(k, 0), n - 1)]
    for i in range(n):
        dst[i] = s / size
        s += src[min(max(i - h + size, 0), n - 1)] - src[min(max(i - h, 0), n - 1)]


@njit(cache=True, nogil=True)
def pooled_ratio(img, level, factor, pool_r, pool_c):  # pragma: no cover - numba
    """``uniform_filter(img / (level[:, None] * factor), (pool_r, pool_c), mode="nearest")``.

    ``img`` and ``factor`` are float32 (n, m), ``level`` float32 (n,): separable running means,
    along range then across beams.
    """
    n, m = img.shape
    z = np.empty((n, m), dtype=np.float32)
    for i in range(n):
        inv = 1.0 / level[i]
        for j in range(m):
            z[i, j] = img[i, j] * inv / factor[i, j]
    # along range for all beams at once, row by row (contiguous rows; a column-by-column pass
    # strides through memory): per beam the same arithmetic as _running_mean, so the same bits
    tmp = np.empty((n, m), dtype=np.float32)
    s = np.zeros(m)
    h = pool_r // 2
    for k in range(-h, pool_r - h):
        r = min(max(k, 0), n - 1)
        for j in range(m):
            s[j] += z[r, j]
    for i in range(n):
        a = min(max(i - h + pool_r, 0), n - 1)
        b = min(max(i - h, 0), n - 1)
        for j in range(m):
            tmp[i, j] = s[j] / pool_r
            s[j] += z[a, j] - z[b, j]
    for i in range(n):
        _running_mean(tmp[i], z[i], pool_c)
    return z


@njit(cache=True, nogil=True)
def excess(z, t, gain):  # pragma: no cover - numba
    """``min(gain * max(z - t, 0), 1)`` as float32."""
    n, m = z.shape
    out = np.empty((n, m), dtype=np.float32)
    for i in range(n):
        for j in range(m):
            e = (z[i, j] - t) * gain
            out[i, j] = 0.0 if e <= 0 else (1.0 if e > 1.0 else e)
    return out


@njit(cache=True, nogil=True)
def interpolate_rows(cols, r0, r1, fr):  # pragma: no cover - numba
    """``out[i] = (1 - fr[i]) cols[r0[i]] + fr[i] cols[r1[i]]`` (float32, elementwise: the same bits
    on every machine and thread count)."""
    n = r0.shape[0]
    m = cols.shape[1]
    out = np.empty((n, m), dtype=np.float32)
    one = np.float32(1.0)
    for i in range(n):
        f = fr[i]
        g = one - f
        a = cols[r0[i]]
        b = cols[r1[i]]
        for j in range(m):
            out[i, j] = a[j] * g + b[j] * f
    return out
