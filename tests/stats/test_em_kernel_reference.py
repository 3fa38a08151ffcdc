"""The plain-EM kernel (sonarmap.stats._em_kernels.em_general_kernel) against a simple reference
that evaluates every component pmf afresh on all levels in every E-step and every Newton iterate
of the M-step: the kernel's evaluation cache and its occupied-levels-only pmfs must give the same
numbers bit for bit (n_iter, converged, weights, parameters, log-likelihood trace)."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from sonarmap.stats import _em_kernels as K
from sonarmap.stats.components import quantization_levels
from sonarmap.stats.mixture import _fit_problem, _general_coords, _initial_guesses, component_pmf_matrix


@njit(cache=False)  # not cached: a cached test kernel keeps the old code of the src kernels it calls
def _reference_plain_em(counts, x, kind, par, w, lo, hi, max_iter, tol, trace):  # pragma: no cover - numba
    """Plain EM for kinds 0-2: full-level pmfs from :func:`_eval` every E-step, every M-step's
    Newton with an empty evaluation cache."""
    C = kind.shape[0]
    L = x.shape[0]
    occ, N = K._occupied(counts)
    P = np.zeros((C, L))
    Rsp = np.zeros((C, L))
    u = np.empty(L)
    m_lo, m_hi = K._eta_mean_bounds(kind, x, lo[:, 0], hi[:, 0], u)
    Nc = np.empty(C)
    tbar = np.empty(C)
    pk = np.empty(C)
    U = np.empty((1, L))
    EC = np.empty((1, 4))

    def estep():
        for c in range(C):
            if kind[c] == 0:
                P[c, 0] = 1.0
            else:
                z, _, _ = K._eval(kind[c], x, par[c, 0], u)
                inv = 1.0 / z
                for k in range(L):
                    P[c, k] = u[k] * inv
        return K._responsibilities(counts, x, kind, w, occ, P, Rsp, Nc, tbar, pk, False)

    ll = estep()
    trace[0] = ll
    it = 0
    converged = False
    while it < max_iter:
        for c in range(C):
            w[c] = Nc[c] / N
            if kind[c] == 0 or Nc[c] <= 0:
                continue
            EC[0, 0] = np.nan
            par[c, 0] = K._solve(kind[c], x, tbar[c] / Nc[c], par[c, 0], lo[c, 0], hi[c, 0], m_lo[c], m_hi[c],
                                 0, U, EC)
        ll_prev = ll
        it += 1
        ll = estep()
        trace[it] = ll
        if ll - ll_prev <= tol * (abs(ll) + 1.0):
            converged = True
            break
    return it, converged


def _random_problem(rng: np.random.Generator, n_levels: int):
    fams = ("exponential",) + (("rayleigh",) if rng.random() < 0.7 else ("rayleigh", "rayleigh"))
    x = quantization_levels(n_levels)
    names = ("zero",) + fams
    params = [()] + [(float(rng.uniform(0.01, 0.08)),)] + [(float(rng.uniform(0.1, 0.6)),) for _ in fams[1:]]
    w = rng.dirichlet(np.ones(len(names)) * 2.0)
    n_pix = int(rng.choice([300, 1024, 20_000, 49_152]))
    counts = rng.multinomial(n_pix, w @ component_pmf_matrix(names, params, x)).astype(float)
    problem = _fit_problem(counts, fams, method="em", zero_spike=True, n_levels=n_levels, binning="round",
                           class_names=None, min_weight=2e-3, scale_max=1.0, min_scale_ratio=2.0,
                           discretization="exact")
    return problem, _initial_guesses(problem.spec, problem.counts)


@pytest.mark.parametrize("seed", range(12))
def test_plain_em_kernel_equals_the_uncached_reference(seed):
    rng = np.random.default_rng(seed)
    problem, starts = _random_problem(rng, int(rng.choice([64, 256])))
    spec, counts = problem.spec, problem.counts
    for w0, p0 in starts:
        out = []
        for fn in ("kernel", "reference"):
            kind, par, lo, hi = _general_coords(spec, p0)
            w = np.array(w0, dtype=np.float64)
            trace = np.empty(1001)
            if fn == "kernel":
                n_iter, conv = K.em_general_kernel(counts, spec.levels, kind, par, w, lo, hi, 1000, 1e-6, 3, trace,
                                                   *K.em_general_args(False))
            else:
                n_iter, conv = _reference_plain_em(counts, spec.levels, kind, par, w, lo, hi, 1000, 1e-6, trace)
            out.append((n_iter, conv, par, w, trace[: n_iter + 1]))
        (n1, c1, p1, w1, t1), (n2, c2, p2, w2, t2) = out
        assert (n1, c1) == (n2, c2)
        assert np.array_equal(p1, p2) and np.array_equal(w1, w2) and np.array_equal(t1, t2)


def _monotone_reference(class_log_pmf: np.ndarray) -> np.ndarray:
    """The numpy expression of monotone_object_log_pmf (before its kernel)."""
    lp = np.array(class_log_pmf, dtype=np.float64)
    bg = lp[0]
    for c in range(1, lp.shape[0]):
        with np.errstate(invalid="ignore"):
            d = lp[c] - bg
        d = np.where(np.isfinite(d), d, -np.inf)
        m = np.maximum.accumulate(d)
        raise_ = np.isfinite(bg) & np.isfinite(m) & (d < m)
        lp[c] = np.where(raise_, bg + m, lp[c])
    return lp


@pytest.mark.parametrize("seed", range(20))
def test_monotone_object_log_pmf_equals_the_numpy_expression(seed):
    from sonarmap.stats.mixture import monotone_object_log_pmf

    rng = np.random.default_rng(seed)
    n_classes, n_levels = int(rng.integers(1, 5)), int(rng.integers(1, 300))
    lp = rng.normal(-5.0, 3.0, (n_classes, n_levels))
    special = rng.random(lp.shape)
    lp[special < 0.05] = -np.inf
    lp[(special >= 0.05) & (special < 0.07)] = np.inf
    lp[(special >= 0.07) & (special < 0.08)] = np.nan
    lp[(special >= 0.08) & (special < 0.1)] = 0.0
    lp[(special >= 0.1) & (special < 0.12)] = -0.0
    got = monotone_object_log_pmf(lp)
    want = _monotone_reference(lp)
    assert got.tobytes() == want.tobytes()
    assert monotone_object_log_pmf(lp.T.copy().T).tobytes() == want.tobytes()  # Fortran-ordered input


@pytest.mark.parametrize("seed", range(6))
def test_quantize_counts_is_quantize_and_its_histogram(seed):
    from sonarmap.errors import InputError
    from sonarmap.stats.mixture import quantize, quantize_counts

    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(1, 70)), int(rng.integers(1, 40)))
    dtype = np.float32 if seed % 2 else np.float64
    image = np.where(rng.random(shape) < 0.5, 0.0, rng.uniform(-0.2, 1.3, shape)).astype(dtype)
    for n_levels, binning in ((256, "round"), (256, "floor"), (300, "round"), (17, "floor")):
        levels, counts = quantize_counts(image, n_levels, binning=binning)
        want = quantize(image, n_levels, binning=binning)
        assert levels.dtype == want.dtype and np.array_equal(levels, want)
        assert counts.dtype == np.float64
        assert np.array_equal(counts, np.bincount(want.ravel(), minlength=n_levels).astype(np.float64))
    image[0, 0] = np.nan
    with pytest.raises(InputError):
        quantize_counts(image)
