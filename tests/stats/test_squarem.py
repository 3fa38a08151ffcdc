"""SQUAREM-accelerated EM (sonarmap.stats._em_kernels): the optimum of plain EM in fewer EM steps,
a non-decreasing trace, parameters inside their box."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.stats._em_kernels import _sq_point, em_general_args, em_general_kernel
from sonarmap.stats.components import quantization_levels
from sonarmap.stats.mixture import _fit_problem, _general_coords, _initial_guesses, component_pmf_matrix, fit_mixture

LEVELS = quantization_levels(256)
N_PIX = 200_000

# (families after the spike, weights, parameters): known mixtures, the object components
# overlapping the exponential background (where plain EM needs hundreds of steps)
CASES = {
    "rayleigh": (("exponential", "rayleigh"), (0.55, 0.42, 0.03), [(0.025,), (0.18,)]),
    "rayleigh+rayleigh": (("exponential", "rayleigh", "rayleigh"), (0.55, 0.38, 0.05, 0.02),
                          [(0.025,), (0.09,), (0.35,)]),
    "gamma": (("exponential", "gamma"), (0.55, 0.42, 0.03), [(0.025,), (3.0, 0.06)]),
    "weibull": (("exponential", "weibull"), (0.55, 0.39, 0.06), [(0.025,), (1.5, 0.25)]),
    "rice": (("exponential", "rice"), (0.55, 0.42, 0.03), [(0.025,), (0.45, 0.06)]),
    "rice+gamma": (("exponential", "rice", "gamma"), (0.55, 0.37, 0.05, 0.03),
                   [(0.025,), (0.3, 0.05), (2.5, 0.08)]),
}


def _counts(key: str, seed: int) -> np.ndarray:
    fams, w, params = CASES[key]
    P = component_pmf_matrix(("zero",) + fams, [()] + list(params), LEVELS)
    return np.random.default_rng(seed).multinomial(N_PIX, np.asarray(w) @ P).astype(float)


def _monotone(trace: np.ndarray) -> bool:
    return bool(np.all(np.diff(trace) >= -1e-12 * np.abs(trace[1:])))


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("key", list(CASES))
def test_accelerated_em_reaches_the_optimum_of_plain_em(key, seed):
    counts = _counts(key, seed)
    fams = CASES[key][0]
    plain = fit_mixture(counts, families=fams, method="em", max_iter=20000, accelerate=False)
    fast = fit_mixture(counts, families=fams, method="em", max_iter=20000)
    assert plain.converged and fast.converged
    assert fast.loglik >= plain.loglik - 1e-9 * abs(plain.loglik)
    assert np.allclose(fast.weights, plain.weights, atol=2e-3)
    for pf, pp in zip(fast.params[1:], plain.params[1:]):
        assert np.allclose(pf, pp, rtol=0.02), (pf, pp)
    assert fast.n_iter <= plain.n_iter
    for f in (plain, fast):
        tr = f.loglik_trace
        assert tr.size == f.n_iter + 1 and _monotone(tr)
        assert abs(tr[-1] - f.loglik) < 1e-6 * abs(f.loglik)


def test_accelerated_em_is_several_times_faster_on_overlapping_components():
    # measured: plain 350-550 EM steps, SQUAREM 60-120
    counts = _counts("rayleigh+rayleigh", 0)
    fams = CASES["rayleigh+rayleigh"][0]
    plain = fit_mixture(counts, families=fams, method="em", max_iter=20000, accelerate=False)
    fast = fit_mixture(counts, families=fams, method="em", max_iter=20000)
    assert 3 * fast.n_iter <= plain.n_iter, (fast.n_iter, plain.n_iter)


@pytest.mark.parametrize("max_iter", [1, 2, 3, 4, 5, 7, 10])
def test_iteration_limit_counts_em_steps(max_iter):
    counts = _counts("rice+gamma", 3)
    f = fit_mixture(counts, families=CASES["rice+gamma"][0], method="em", max_iter=max_iter)
    assert f.n_iter == max_iter and not f.converged and "not_converged" in f.flags
    assert f.loglik_trace.size == max_iter + 1 and _monotone(f.loglik_trace)


def _kernel_fit(counts, fams, scale_max=1.0, accel=True, max_iter=2000):
    problem = _fit_problem(counts, fams, method="em", zero_spike=True, n_levels=256, binning="round",
                           class_names=None, min_weight=2e-3, scale_max=scale_max, min_scale_ratio=2.0,
                           discretization="exact")
    w0, p0 = _initial_guesses(problem.spec, problem.counts)[0]
    kind, par, lo, hi = _general_coords(problem.spec, p0)
    w = np.array(w0, dtype=np.float64)
    trace = np.empty(max_iter + 1)
    n_iter, conv = em_general_kernel(problem.counts, LEVELS, kind, par, w, lo, hi, max_iter, 1e-11, 3, trace,
                                     *em_general_args(accel))
    return par, w, lo, hi, trace[: n_iter + 1], conv


@pytest.mark.parametrize("fams,scale_max", [
    # the second Rayleigh's scale (0.35) beyond scale_max: it ends at the bound
    (("exponential", "rayleigh", "rayleigh"), 0.2),
    # a Rice on Rayleigh data: nu is not identified near 0
    (("exponential", "rice", "rayleigh"), 1.0),
    (("exponential", "gamma", "weibull"), 0.3),
])
def test_accelerated_kernel_keeps_parameters_in_their_box(fams, scale_max):
    counts = _counts("rayleigh+rayleigh", 2)
    par, w, lo, hi, trace, _ = _kernel_fit(counts, fams, scale_max)
    assert np.all(par >= lo) and np.all(par <= hi)
    assert np.all(w >= 0) and abs(w.sum() - 1) < 1e-12
    assert _monotone(trace)
    plain = _kernel_fit(counts, fams, scale_max, accel=False, max_iter=20000)
    assert trace[-1] >= plain[4][-1] - 1e-7 * abs(plain[4][-1])


def test_extrapolated_point_is_projected_inside_the_box():
    rng = np.random.default_rng(0)
    kind = np.array([0, 1, 5, 3])
    lo = np.array([[0, 0], [-255.0, 0], [0.0, 1.0], [0.2, 1.0]])
    hi = np.array([[0, 0], [-1.0, 0], [1.0, 65025.0], [50.0, 255.0]])
    par2 = np.array([[0, 0], [-40.0, 0], [0.02, 300.0], [3.0, 20.0]])
    w2 = np.array([0.5, 0.4, 0.05, 0.05])
    par = np.empty((4, 2))
    w = np.empty(4)
    for _ in range(200):
        y = rng.normal(0.0, 30.0, 12)
        _sq_point(kind, y, lo, hi, par2, w2, par, w)
        assert abs(w.sum() - 1) < 1e-12 and np.all(w >= 1e-3 * w2 / w2.sum() * 0.999)
        free = lo < hi
        # strictly inside where the last EM iterate is: never onto a bound (Rice nu = 0 is a fixed point)
        assert np.all(par[free] > lo[free]) and np.all(par[free] < hi[free])
        assert np.all(par[~free] == lo[~free])


def test_newton_m_step_does_not_stall_at_weibull_shape_one(test_ping_paths):
    """On DIDSON image 6 the Newton step of an exponential + Weibull fit heads for shape < 1, where
    level 0 enters the Weibull's support and Q drops: halving the step until the shape stayed >= 1
    froze the scale too, and EM stopped at shape 1.0000000000009 (log-likelihood -88107.89).  The
    step is now clipped at shape 1 like a bound: the fit leaves it (shape 2.82, -88084.43)."""
    from sonarmap.io import read_ping

    img = read_ping(test_ping_paths[6]).image
    for accelerate in (False, True):
        f = fit_mixture(img, families=("exponential", "weibull"), method="em", accelerate=accelerate)
        assert f.converged and f.params[2][0] > 2.5 and f.loglik > -88085.0, (accelerate, f.params, f.loglik)


def test_a_restart_climbing_to_the_same_maximum_is_merged(background_paths):
    """On a DIDSON background ping every start runs (its object scale is close to the
    background's); the later starts reach the first start's maximum, and ``_em_best`` stops them
    once they are within MERGE_RTOL of it: the fit is that maximum, and the kernel reports the
    merge as a negative step count."""
    from sonarmap.io import read_ping
    from sonarmap.pipeline import process_ping
    from sonarmap.stats import mixture as M

    counts = process_ping(read_ping(background_paths[0])).fit.counts
    problem = _fit_problem(counts, ("exponential", "rayleigh"), method="em", zero_spike=True, n_levels=256,
                           binning="round", class_names=None, min_weight=2e-3, scale_max=1.0, min_scale_ratio=2.0,
                           discretization="exact")
    spec = problem.spec
    starts = list(M._starting_points(spec, problem.counts, None))
    assert len(starts) == 3
    first = M._em(spec, problem.counts, *starts[0], 1000, 1e-11)
    assert first is not None and first[3] and M._needs_restart(spec, first, 2e-3)
    ref = (first[0], _general_coords(spec, first[1])[1])
    for w0, p0 in starts[1:]:
        full = M._em(spec, problem.counts, w0, p0, 1000, 1e-11)
        assert full is not None and full[3]
        np.testing.assert_allclose(full[0], first[0], rtol=1e-3)  # the same maximum
        assert abs(full[4][-1] - first[4][-1]) < 1e-3
        assert M._em(spec, problem.counts, w0, p0, 1000, 1e-11, merge=ref) is None
    best = M._em_best(spec, problem.counts, starts, 1000, 1e-11, 2e-3)
    np.testing.assert_array_equal(best[0], first[0])
    # with a reference far from the start's maximum the kernel runs to convergence
    w, trace = np.array(starts[1][0], dtype=np.float64), np.empty(1001)
    kind, par, lo, hi = _general_coords(spec, starts[1][1])
    n, conv = em_general_kernel(problem.counts, spec.levels, kind, par, w, lo, hi, 1000, 1e-11, 3, trace,
                                *em_general_args(True, (ref[0], ref[1] * 3.0), M.MERGE_RTOL))
    assert n > 0 and conv
