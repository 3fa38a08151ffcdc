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


def _start_weights_numpy(spec, frac0: float) -> np.ndarray:
    """The start weights of ``_start_at`` in the numpy arithmetic it replaced."""
    free = spec.free
    n_obj = len(free) - 1
    w = np.zeros(len(spec.names))
    for j, i in enumerate(free):
        w[i] = (1.0 - frac0) * (0.95 if j == 0 else 0.05 / max(n_obj, 1)) if spec.spike else (
            0.95 if j == 0 else 0.05 / max(n_obj, 1))
    if spec.spike:
        w[0] = 1.0 - w.sum()
    return w / w.sum()


def test_start_weights_are_numpys() -> None:
    """``_start_at``'s weights (Python floats, summed in numpy's order) equal the numpy formulation
    bit for bit, with and without the spike, for one to nine components."""
    from sonarmap.stats.mixture import _fit_problem, _start_at

    rng = np.random.default_rng(5)
    counts = rng.integers(0, 50, 256).astype(np.float64)
    for families in (("exponential",), ("exponential", "rayleigh"), ("exponential", "rayleigh", "rayleigh"),
                     ("gamma", "rayleigh", "rice"), ("exponential",) + ("rayleigh",) * 6,
                     ("exponential",) + ("rayleigh",) * 8):
        for spike in (True, False):
            spec = _fit_problem(counts, families, method="em", zero_spike=spike, n_levels=256, binning="round",
                                class_names=None, min_weight=2e-3, scale_max=1.0, min_scale_ratio=2.0,
                                discretization="exact").spec
            for frac0 in np.r_[0.0, 1.0, rng.random(200), rng.random(50) * 1e-9]:
                w, _ = _start_at(spec, float(frac0), 0.05, 0.3)
                assert np.array_equal(w, _start_weights_numpy(spec, float(frac0))), (families, spike, frac0)
