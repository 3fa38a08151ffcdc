"""The Rice component's ``log i0e`` and ``I1/I0`` (numba, all levels at once) and the log-density the
EM kernel builds from them."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import special, stats

from sonarmap.stats._em_kernels import RICE_SWITCH, _logdens2, log_i0e_ratio
from sonarmap.stats.components import quantization_levels


def _log_i0e_ratio(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = np.ascontiguousarray(z, dtype=np.float64)
    f = np.empty_like(z)
    a = np.empty_like(z)
    log_i0e_ratio(z, f, a)
    return f, a


# from 0 through the series/asymptotic switch to arguments where I0 itself overflows (z > 713)
Z = np.concatenate([
    [0.0, 1e-300, 1e-12],
    np.geomspace(1e-8, 1e6, 3001),
    np.linspace(RICE_SWITCH - 1.0, RICE_SWITCH + 1.0, 401),
    np.nextafter(RICE_SWITCH, [0.0, np.inf]),
    [800.0, 1e4, 1e12, 1e300],
])


def test_log_i0e_ratio_matches_scipy_in_any_order():
    z = np.random.default_rng(0).permutation(Z)  # no ordering assumed
    f, a = _log_i0e_ratio(z)
    ref_f = np.log(special.i0e(z))
    ref_a = special.i1e(z) / special.i0e(z)
    assert np.all(np.isfinite(f)) and np.all(np.isfinite(a))
    # measured: 1.3e-15 (log i0e), 1.1e-15 (ratio), both near z = 17
    assert np.max(np.abs(f - ref_f) / np.maximum(1.0, np.abs(ref_f))) <= 3e-15
    assert np.max(np.abs(a - ref_a)) <= 3e-15
    assert np.all((a >= 0) & (a <= 1))


@pytest.mark.skipif(np.finfo(np.longdouble).eps > 1e-18, reason="needs an extended-precision long double")
def test_log_i0e_ratio_against_extended_precision_series():
    z = np.linspace(0.0, 60.0, 1201)
    f, a = _log_i0e_ratio(z)
    zl = z.astype(np.longdouble)
    t = zl * zl / 4
    s0 = np.ones_like(zl)
    s1 = np.ones_like(zl)
    term0 = np.ones_like(zl)
    term1 = np.ones_like(zl)
    for k in range(1, 250):  # all terms positive: the long double sum is good to ~1e-18
        term0 = term0 * t / (k * k)
        term1 = term1 * t / (k * (k + 1))
        s0 += term0
        s1 += term1
    ref_f = np.log(s0) - zl
    ref_a = zl / 2 * s1 / s0
    assert float(np.max(np.abs(f - ref_f))) <= 2e-15
    assert float(np.max(np.abs(a - ref_a))) <= 2e-15


@pytest.mark.parametrize("nu", [0.0, 0.01, 0.2, 0.6, 0.95])
@pytest.mark.parametrize("scale", [0.003, 0.02, 0.1, 0.5])
def test_rice_log_density_matches_scipy(nu, scale):
    """The kernel's unnormalised Rice log-density is scipy's log-pdf + 2 log(scale), including
    where x nu / scale^2 reaches 3e5 and a naive I0 overflows."""
    x = quantization_levels(256)
    xe = x.copy()
    xe[0] = 0.5 * x[1]
    g = np.empty(256)
    aux = np.empty(256)
    top = _logdens2(5, nu, 1.0 / scale**2, x, xe, np.log(xe), g, aux, np.empty((256, 2)), np.empty((256, 3)), False)
    assert g[0] == -np.inf and top == np.max(g)
    with np.errstate(divide="ignore", under="ignore"):
        ref = stats.rice.logpdf(x[1:], nu / scale, scale=scale) + 2 * np.log(scale)
        pdf = stats.rice.pdf(x[1:], nu / scale, scale=scale)
    ok = pdf > 1e-280  # scipy's logpdf is log(pdf): -inf once the pdf underflows
    assert ok.sum() >= 10
    # both sides round the quadratic term (x - nu)^2 / (2 scale^2) (up to 6e5 here) on their own
    size = 1.0 + np.abs(ref) + 0.5 * (x[1:] - nu) ** 2 / scale**2
    assert np.all(np.abs(g[1:][ok] - ref[ok]) <= 1e-14 * size[ok])
    assert np.all(np.isfinite(g[1:]))  # where scipy underflows the kernel still has the log
    assert np.all(np.abs(aux[1:] - special.i1e(x[1:] * nu / scale**2) / special.i0e(x[1:] * nu / scale**2)) <= 3e-15)
