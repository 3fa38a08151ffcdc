"""Numba kernels of the per-ping pipeline (private; see :mod:`sonarmap.pipeline`)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def box_mean_f32(img, size0, size1):  # pragma: no cover - numba
    """``scipy.ndimage.uniform_filter(img, size=(size0, size1), mode="constant")`` of a 2-D float32
    image, bit for bit (scipy's arithmetic: axis 0 then axis 1, axes of size 1 skipped, each line
    zero-padded by ``size // 2`` before, a double running sum ``+= new - old`` divided by the size
    and rounded to float32; ``tests/test_pipeline.py`` checks the identity against scipy)."""
    h, w = img.shape
    mid = np.empty((h, w), dtype=np.float32)
    if size0 > 1:
        buf = np.zeros(h + size0 - 1)
        for j in range(w):
            _box_line(img[:, j], buf, size0, mid[:, j])
    else:
        mid[:, :] = img
    if size1 <= 1:
        return mid
    out = np.empty((h, w), dtype=np.float32)
    buf = np.zeros(w + size1 - 1)
    for i in range(h):
        _box_line(mid[i, :], buf, size1, out[i, :])
    return out


@njit(cache=True, nogil=True, inline="always")
def _box_line(line, buf, size, out):  # pragma: no cover - numba
    """One line of :func:`box_mean_f32`: ``line`` copied into the zero-padded ``buf`` (``size // 2``
    zeros before it), then the running sum ``+= new - old`` over ``size`` samples into ``out``."""
    b = size // 2
    for i in range(line.size):
        buf[b + i] = line[i]
    tmp = 0.0
    for k in range(size):
        tmp += buf[k]
    out[0] = tmp / size
    for k in range(1, line.size):
        tmp += buf[k + size - 1] - buf[k - 1]
        out[k] = tmp / size


@njit(cache=True, nogil=True)
def band_peak_pixels(band, img, cols):  # pragma: no cover - numba
    """Band pooling's pick: on each beam ``j`` with ``cols[j]``, the strongest ``img`` pixel of
    the first run of ``band`` rows (first maximum on ties); returns a boolean image with one pixel
    per picked beam.  Same as the numpy formulation in :func:`sonarmap.pipeline.pooled_band_pixels`."""
    h, w = band.shape
    out = np.zeros((h, w), dtype=np.bool_)
    for j in range(w):
        if not cols[j]:
            continue
        i = 0
        while i < h and not band[i, j]:
            i += 1
        if i == h:
            continue
        best = i
        bv = img[i, j]
        i += 1
        while i < h and band[i, j]:
            if img[i, j] > bv:
                bv = img[i, j]
                best = i
            i += 1
        out[best, j] = True
    return out


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
