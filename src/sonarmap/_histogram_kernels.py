"""Numba histogram kernels shared by the stages (private)."""

from __future__ import annotations

from numba import njit

__all__ = ["add_partial_counts"]


@njit(cache=True, nogil=True, inline="always")
def add_partial_counts(keys, n, part):  # pragma: no cover - numba
    """Add the count of each key of ``keys[:n]`` (non-negative, each below ``part.shape[1]``) to
    ``part`` (int64, ``(4, n_keys)``), in 4 interleaved partial histograms: key ``keys[t]`` goes to
    row ``t % 4``, so that runs of one key (the zeros of an image, a background's crowded levels)
    do not serialise on one counter.  The counts are the column sums of ``part``."""
    n4 = n - n % 4
    for t in range(0, n4, 4):
        part[0, keys[t]] += 1
        part[1, keys[t + 1]] += 1
        part[2, keys[t + 2]] += 1
        part[3, keys[t + 3]] += 1
    for t in range(n4, n):
        part[0, keys[t]] += 1
