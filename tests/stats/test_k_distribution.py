"""The intensity K distribution component (gamma-textured speckle): pmf, EM, LSQ, selection."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import special

from sonarmap.stats._em_kernels import log_bessel_k
from sonarmap.stats.components import pmf, quantization_levels
from sonarmap.stats.mixture import component_pmf_matrix, fit_mixture, histogram
from sonarmap.stats.selection import select_model

LEVELS = quantization_levels(256)
N_PIX = 512 * 96 * 4


@pytest.mark.parametrize("nu", [0.1, 0.7, 1.0, 2.5, 20.0, 100.0])
def test_k_pmf_sums_to_one_and_tends_to_exponential(nu):
    p = pmf("k", (nu, 0.05), LEVELS)
    assert np.all(np.isfinite(p)) and np.all(p >= 0) and abs(p.sum() - 1) < 1e-12
    tv = 0.5 * np.abs(p - pmf("exponential", (0.05,), LEVELS)).sum()
    # measured: 0.37 (nu 0.1) ... 0.029 (nu 10), 0.0038 (nu 100)
    assert tv < {0.1: 0.5, 0.7: 0.4, 1.0: 0.3, 2.5: 0.2, 20.0: 0.03, 100.0: 0.005}[nu]


def test_log_bessel_k_quadrature_matches_scipy():
    out = np.empty(5)
    for v in (-0.9, -0.3, 0.0, 0.4, 1.0, 3.5, 30.0, 99.0):
        for z in np.geomspace(1e-3, 300, 40):
            ref = np.log(special.kve(v, z)) - z
            if not np.isfinite(ref):
                continue
            assert abs(log_bessel_k(v, z, True, out) - ref) <= 1e-12 * max(1.0, abs(ref))
            dv = 1e-5 * max(1.0, abs(v))
            fd = (np.log(special.kve(v + dv, z)) - np.log(special.kve(v - dv, z))) / (2 * dv)
            assert abs(out[0] - fd) <= 1e-5 * max(1.0, abs(fd))


@pytest.mark.parametrize("nu,mu", [(1.5, 0.04), (0.7, 0.03), (5.0, 0.05)])
def test_k_pmf_matches_monte_carlo(nu, mu):
    rng = np.random.default_rng(1)
    n = 2_000_000
    y = rng.gamma(nu, 1.0 / nu, n) * rng.exponential(mu, n)  # I = g e
    c = histogram(y.reshape(-1, 100)).astype(float)
    p = pmf("k", (nu, mu), LEVELS)
    # level 0 is a half-width bin and the top level collects the clipped tail: compare 1..L-2
    ph, q = c[1:-1] / c[1:-1].sum(), p[1:-1] / p[1:-1].sum()
    # measured TV 0.003 (nu 1.5), the rest of the mismatch is the point-evaluated pmf
    assert 0.5 * np.abs(ph - q).sum() < 0.01
    m = c[1:-1] > 5000
    assert np.median(np.abs(ph[m] / q[m] - 1)) < 0.03


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("nu,mu", [(0.7, 0.03), (1.5, 0.04), (5.0, 0.05)])
def test_em_recovers_k_background(seed, nu, mu):
    w = np.array([0.5, 0.47, 0.03])
    P = component_pmf_matrix(("zero", "k", "rayleigh"), [(), (nu, mu), (0.25,)], LEVELS)
    c = np.random.default_rng(seed).multinomial(N_PIX, w @ P).astype(float)
    f = fit_mixture(c, families=("k", "rayleigh"), method="em")
    assert f.converged and f.ok
    # measured over 6 seeds: |rel err| nu <= 5.2 %, scale <= 2.2 %, rayleigh <= 1.6 %
    assert abs(f.params[1][0] / nu - 1) < 0.08
    assert abs(f.params[1][1] / mu - 1) < 0.04
    assert abs(f.params[2][0] / 0.25 - 1) < 0.03
    tr = f.loglik_trace
    assert np.all(np.diff(tr) >= -1e-9 * np.abs(tr[1:]))
    assert abs(tr[-1] - f.loglik) < 1e-6 * abs(f.loglik)


def test_lsq_fits_k():
    P = component_pmf_matrix(("zero", "k"), [(), (1.5, 0.04)], LEVELS)
    c = np.random.default_rng(3).multinomial(N_PIX, np.array([0.5, 0.5]) @ P).astype(float)
    f = fit_mixture(c, families=("k",), method="lsq")
    assert f.converged and f.ok
    assert abs(f.params[1][0] / 1.5 - 1) < 0.1 and abs(f.params[1][1] / 0.04 - 1) < 0.05


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.slow
def test_selection_k_vs_exponential(seed):
    # counts drawn from the discretised pmfs (as in test_selection): continuous exponential
    # samples are not an exponential pmf on the levels (point-evaluated densities), and K's
    # extra shape parameter absorbs that mismatch (measured: BIC -82 in favour of K)
    rng = np.random.default_rng(seed)
    n = 512 * 96
    heavy = rng.multinomial(n, pmf("k", (1.0, 0.05), LEVELS)).astype(float)
    sel = select_model(heavy, candidates=[("exponential",), ("k",)])
    assert sel.candidates[sel.best_index] == ("k",), sel.table()
    plain = rng.multinomial(n, pmf("exponential", (0.05,), LEVELS)).astype(float)
    sel = select_model(plain, candidates=[("exponential",), ("k",)])
    assert sel.candidates[sel.best_index] == ("exponential",), sel.table()
