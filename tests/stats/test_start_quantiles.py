"""The EM start's level quantiles (``_em_kernels.nonzero_quantiles``) are numpy's cumsum and
searchsorted, bit for bit."""

from __future__ import annotations

import numpy as np

from sonarmap.stats._em_kernels import nonzero_quantiles


def test_nonzero_quantiles_are_numpys() -> None:
    rng = np.random.default_rng(2)
    for t in range(2000):
        n_levels = int(rng.choice([2, 3, 16, 256, 1024]))
        counts = rng.integers(0, 1000, n_levels).astype(np.float64) * (rng.random(n_levels) < rng.random())
        if t % 7 == 0:
            counts = np.round(rng.random(n_levels) * 1e6) / 7.0  # sums that round
        cdf = np.cumsum(counts[1:])
        n, i50, i99 = nonzero_quantiles(counts, 0.5, 0.99)
        assert n == float(cdf[-1])
        if n > 0:
            assert i50 == np.searchsorted(cdf, 0.5 * n) and i99 == np.searchsorted(cdf, 0.99 * n)
