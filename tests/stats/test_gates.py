"""The kld gate allows what sampling explains (stats.gates.sampling_kld)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.stats.gates import SAMPLING_SIGMAS, fit_gates, sampling_kld
from sonarmap.stats.mixture import fit_mixture


def _zero_exp_rayleigh(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` pixels of the paper's model on the 8-bit grid: 40 % zero, exponential, 10 % Rayleigh."""
    k = rng.choice(3, size=n, p=[0.4, 0.5, 0.1])
    y = np.where(k == 0, 0.0, np.where(k == 1, rng.exponential(0.03, n), rng.rayleigh(0.25, n)))
    return (np.round(np.clip(y, 0, 1) * 255) / 255).astype(np.float32)


def test_sampling_kld_is_the_g_test_quantile():
    dof, n = 200 - 1 - 4, 512 * 96
    assert sampling_kld(n, 200, 4) == pytest.approx((dof + SAMPLING_SIGMAS * math.sqrt(2 * dof)) / (2 * n))
    assert sampling_kld(512 * 96, 200, 4) < 0.003  # real pings: the limit stays ~max_kld
    assert sampling_kld(1024, 170, 4) > 0.1  # a 64 x 16 window
    assert sampling_kld(10, 2, 5) == pytest.approx((1 + SAMPLING_SIGMAS * math.sqrt(2)) / 20)  # dof >= 1
    with pytest.raises(InputError, match="n_samples"):
        sampling_kld(0, 10, 2)


def test_small_images_of_the_model_pass_the_kld_gate_that_a_fixed_limit_refused():
    """A correct model's KLD on a 64 x 16 image is ~L / 2N (0.08): a fixed 0.05 refused most of them."""
    rng = np.random.default_rng(7)
    klds, gated = [], 0
    for _ in range(40):
        fit = fit_mixture(_zero_exp_rayleigh(rng, 1024).reshape(64, 16), method="em")
        klds.append(fit.kld)
        gated += "kld" in fit_gates(fit)
    assert np.mean(np.asarray(klds) > 0.05) > 0.5  # the old fixed limit
    assert gated <= 1
    # a histogram the model cannot describe, on the same sample size, is still refused: two
    # narrow peaks (KLD ~2.4 against a limit of ~0.17)
    y = np.where(rng.random(1024) < 0.5, rng.normal(0.3, 0.01, 1024), rng.normal(0.8, 0.01, 1024))
    img = (np.round(np.clip(y, 0, 1) * 255) / 255).astype(np.float32).reshape(64, 16)
    assert "kld" in fit_gates(fit_mixture(img, method="em"))


def test_large_images_keep_the_fixed_limit():
    """On a 512 x 96 ping the sampling term is < 0.003: the gate is max_kld, as measured on real pings."""
    rng = np.random.default_rng(3)
    fit = fit_mixture(_zero_exp_rayleigh(rng, 512 * 96).reshape(512, 96), method="em")
    assert "kld" not in fit_gates(fit)
    assert "kld" not in fit_gates(fit, max_kld=fit.kld - sampling_kld(512 * 96, np.count_nonzero(fit.counts),
                                                                       fit.n_params) + 1e-12)
