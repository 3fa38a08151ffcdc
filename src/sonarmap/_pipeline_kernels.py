"""Numba kernels of the per-ping pipeline (:mod:`sonarmap.pipeline`)."""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["any_columns"]


@njit(cache=True, nogil=True)
def any_columns(img):  # pragma: no cover - numba
    """``img.any(axis=0)`` of a C-contiguous 2-D unsigned-integer image (a label image): one
    pass along its rows, OR-ing each row into the columns' accumulator (numpy's ``any`` along the
    short axis casts every pixel to bool first: 6x slower on a 512 x 96 ping)."""
    n, m = img.shape
    acc = np.zeros(m, img.dtype)
    for i in range(n):
        for j in range(m):
            acc[j] |= img[i, j]
    return acc != 0
