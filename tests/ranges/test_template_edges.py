"""Leading edges measured against the surface's own echo template (``template_edges``)."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import GeometryError, InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.pipeline import PipelineConfig
from sonarmap.ranges.echoes import find_echoes, pooled_edges
from sonarmap.ranges.template import template_edges


def _geom(n_bins: int = 300, n_beams: int = 96) -> SonarGeometry:
    return SonarGeometry(range_m=2.0 + 0.02 * np.arange(n_bins), azimuth_rad=np.linspace(-0.4, 0.4, n_beams))


def _echo_mean(truth: np.ndarray, n_bins: int = 300, rise: float = 8.0, depth: float = 20.0,
               floor: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """The mean image of an echo rising linearly over ``rise`` bins with its half-peak crossing at
    ``truth`` (per beam), flat for ``depth`` bins, over a ``floor``; and its support."""
    r = np.arange(n_bins, dtype=float)[:, None]
    x = r - (truth[None, :] - 0.5 * rise)
    env = np.clip(x / rise, 0.0, 1.0) * (x < rise + depth)
    return env + floor, env > 0.25


def _speckled(seed: int, truth: np.ndarray, n_bins: int = 300, rise: float = 8.0, depth: float = 20.0,
              floor: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Single-look (exponential) speckle on :func:`_echo_mean`'s echo; and its support."""
    mean, support = _echo_mean(truth, n_bins, rise, depth, floor)
    return mean * np.random.default_rng(seed).exponential(1.0, mean.shape), support


def _sloped_surface(seed: int) -> tuple[SonarGeometry, np.ndarray, object, np.ndarray]:
    """A surface sloped half a bin per beam over 96 beams in single-look speckle: the geometry,
    the image, its echoes and each beam's first echo (-1 none)."""
    g = _geom()
    img, mask = _speckled(seed, 100.0 + 0.5 * np.arange(g.n_beams))
    e = find_echoes(mask, img, g)
    first, count = e.per_beam()
    return g, img, e, np.where(count > 0, first, -1)


def _edges(img: np.ndarray, mask: np.ndarray, g: SonarGeometry, **kw: object) -> tuple[np.ndarray, np.ndarray, object]:
    """Per beam the pooled edge and the template edge (NaN: no return), and the template's echoes."""
    e = find_echoes(mask, img, g)
    first, count = e.per_beam()
    first = np.where(count > 0, first, -1)
    pooled = pooled_edges(e, first, img, g)
    tmpl = template_edges(pooled, first, img, g, **kw)
    s = np.maximum(first, 0)
    ok = first >= 0
    return np.where(ok, pooled.edge_bin[s], np.nan), np.where(ok, tmpl.edge_bin[s], np.nan), (tmpl, first)


def test_a_template_measures_simulated_sloped_hulls_better_than_the_pooled_profile():
    """The pipeline with and without the template stage on the simulator's ARIS 3000 hull sloped
    4 bins per beam (both noise levels, 2 seeds; without the smoothing along the surface that
    follows it), scored on the sub-bin surface truth: within a bin on more beams (measured 0.47 -> 0.64 with the default anchor; 0.73 with the template's own
    crossing), the median error within half a bin (-0.12)."""
    from sonarmap import preset
    from sonarmap.evaluate.segmentation import _simulate_seeds, preset_sim_configs
    from sonarmap.pipeline import process_ping

    g = preset("aris3000-128")
    dr = abs(g.range_resolution_m)
    errs: dict[int, list[np.ndarray]] = {0: [], 5: []}
    for sc in preset_sim_configs(g):
        for sim, _ in _simulate_seeds("hull_slope4", g, sc, (0, 1), -3.0, True):
            for beams in errs:
                cfg = PipelineConfig().replace(edge_template_beams=beams, edge_smooth_beams=0)
                r = process_ping(sim.ping, cfg).ranges.range_m
                errs[beams].append((np.asarray(r) - sim.surface_range_m) / dr)
    within = {k: np.mean(np.abs(np.nan_to_num(np.concatenate(v), nan=1e9)) <= 1.0) for k, v in errs.items()}
    assert within[5] > within[0] + 0.1, within
    assert abs(np.nanmedian(np.concatenate(errs[5]))) < 0.5


def test_noise_free_echoes_keep_their_crossing():
    g = _geom()
    truth = 120.0 + 0.4 * np.arange(g.n_beams) + 0.25
    r = np.arange(g.n_bins, dtype=float)[:, None]
    x = r - (truth[None, :] - 4.0)
    env = np.clip(x / 8.0, 0.0, 1.0) * (x < 28.0)
    img = env + 0.02
    pooled, tmpl, (echoes, first) = _edges(img, env > 0.25, g)
    assert np.all(np.isfinite(tmpl))
    # on the crossing within a quarter bin on every beam (measured 0.16; the pooled profile's
    # 3-bin box and sampling leave 0.50)
    assert np.abs(tmpl - truth).max() < 0.25
    assert np.abs(tmpl - truth).max() < np.abs(pooled - truth).max()
    # each measured return's sigma is finite and at least the bin grid's spread
    sig = echoes.sigma_m[first]
    assert np.all(np.isfinite(sig)) and np.all(sig >= 0.02 / np.sqrt(12) - 1e-12)


def test_short_surfaces_and_skipped_echoes_keep_their_edges():
    g = _geom(n_beams=20)
    truth = 100.0 + 0.5 * np.arange(20)
    img, mask = _speckled(1, truth)
    pooled, tmpl, _ = _edges(img, mask, g)  # 20 beams: shorter than min_beams=30
    assert np.array_equal(pooled, tmpl, equal_nan=True)
    g, img, e, first = _sloped_surface(1)
    skip = np.ones(e.size, dtype=bool)
    assert np.array_equal(template_edges(e, first, img, g, skip=skip).edge_bin, e.edge_bin)
    assert np.array_equal(template_edges(e, first, img, g, min_beams=200).edge_bin, e.edge_bin)


def test_options_are_checked():
    g = _geom()
    truth = 100.0 + 0.5 * np.arange(g.n_beams)
    img, mask = _speckled(2, truth)
    e = find_echoes(mask, img, g)
    first = np.full(g.n_beams, -1)
    with pytest.raises(InputError, match="first"):
        template_edges(e, first[:5], img, g)
    for key, bad in (("half_template", 0), ("n_iter", 0), ("min_beams", 2), ("max_shift_bins", -1.0),
                     ("fraction", 1.0), ("min_contrast", float("nan")), ("sigma_scale", -1.0),
                     ("anchor_beams", -1), ("shared_beams", 0)):
        with pytest.raises(InputError, match=key):
            template_edges(e, first, img, g, **{key: bad})
    with pytest.raises(GeometryError, match="image"):
        template_edges(e, first, img[:10], g)


def test_moved_fields_are_those_of_the_numpy_formulation():
    """template_edges' one kernel (template_moved_edges) gives the echoes the numpy formulation
    gave them from the template kernel's outputs (runs from _first_runs, sigma
    edge_sigma_m(sqrt(var0 + var1), 1), the moved returns' ranges np.interp), bit for bit, with
    and without the anchor, pulse and skipped returns."""
    from sonarmap.ranges import _template_kernels
    from sonarmap.ranges.echoes import _bin_and_pulse_m, _first_runs, edge_sigma_m
    from sonarmap.ranges.template import _skipped_beams

    g = _geom()
    rng = np.random.default_rng(4)
    n_moved = 0
    for seed in range(6):
        truth = 100.0 + 0.5 * np.arange(g.n_beams) + rng.normal(0, 0.3, g.n_beams).cumsum()
        img, mask = _speckled(seed, truth)
        e = find_echoes(mask, img, g)
        first, count = e.per_beam()
        first = np.where(count > 0, first, -1)
        skip = rng.random(e.size) < 0.1 if seed % 2 else None
        anchor, pb, scale = (10, 1, 1.0) if seed < 3 else (0, 3, 1.7)
        shared = 1 + 3 * (seed % 3)
        got = template_edges(e, first, img, g, skip=skip, anchor_beams=anchor, pulse_bins=pb, sigma_scale=scale,
                             shared_beams=shared)
        sel = np.ascontiguousarray(first, dtype=np.int64)
        edge, stop, run = _first_runs(e, sel, 1.0)
        new, var = _template_kernels.template_edges(np.ascontiguousarray(img, dtype=np.float64), edge, stop, run,
                                                    _skipped_beams(sel, skip), 5, 1, 8, 30, 60, 4.0, 6, 0.5, 3, 24, 2,
                                                    12.0, anchor, float(shared))
        done = np.flatnonzero(np.isfinite(var[:, 0]))
        bin_m, pulse_m = _bin_and_pulse_m(g, pb)
        sigma = edge_sigma_m(np.sqrt(var[done, 0] + var[done, 1]), 1.0, bin_m, pulse_m=pulse_m, scale=scale)
        want = {"edge_bin": e.edge_bin.copy(), "edge_range_m": e.edge_range_m.copy(), "sigma_m": e.sigma_m.copy()}
        want["edge_bin"][sel[done]] = new[done]
        want["edge_range_m"][sel[done]] = np.interp(new[done], np.arange(g.n_bins, dtype=np.float64), g.range_m)
        want["sigma_m"][sel[done]] = sigma
        n_moved += done.size
        assert (got is e) == (done.size == 0)
        for f, v in want.items():
            assert np.array_equal(getattr(got, f), v, equal_nan=True), (seed, f)
    assert n_moved > 0


def test_the_anchor_counts_the_offsets_of_pooled_edges_as_fewer_independent_ones():
    """Edges measured on the data of ``s`` neighbouring beams (pooled windows) give correlated
    anchor offsets: the anchor median's variance is that of independent offsets times
    ``min(c, s)`` for ``c`` offsets in the window (``c / s`` independent ones, at least one);
    the edges themselves do not change."""
    from sonarmap.ranges import _template_kernels
    from sonarmap.ranges.echoes import _first_runs
    from sonarmap.ranges.template import _skipped_beams

    g = _geom()
    truth = 100.0 + 0.5 * np.arange(g.n_beams)
    img, mask = _speckled(7, truth)
    e = find_echoes(mask, img, g)
    first, count = e.per_beam()
    sel = np.ascontiguousarray(np.where(count > 0, first, -1), dtype=np.int64)
    edge, stop, run = _first_runs(e, sel, 1.0)
    img64 = np.ascontiguousarray(img, dtype=np.float64)
    skip = _skipped_beams(sel, None)

    def kernel(anchor: int, shared: float) -> tuple[np.ndarray, np.ndarray]:
        return _template_kernels.template_edges(img64, edge, stop, run, skip, 5, 1, 8, 30, 60, 4.0, 6, 0.5, 3, 24,
                                                2, 12.0, anchor, shared)

    anchor = 10
    _, own = kernel(0, 1.0)
    new1, var1 = kernel(anchor, 1.0)
    ok = np.isfinite(own[:, 0])
    assert ok.sum() > 60
    # c: the measured beams of the beam's run within `anchor` beams of it
    idx = np.arange(edge.size)
    c = np.array([np.sum(ok & (run == run[j]) & (np.abs(idx - j) <= anchor)) for j in idx])
    part1 = var1[:, 1] - own[:, 1]
    assert np.all(part1[ok] > 0)
    for shared in (3.0, 7.0, 25.0):
        new_s, var_s = kernel(anchor, shared)
        assert np.array_equal(new_s, new1, equal_nan=True)
        assert np.array_equal(var_s[:, 0], var1[:, 0], equal_nan=True)
        ratio = (var_s[ok, 1] - own[ok, 1]) / part1[ok]
        assert np.allclose(ratio, np.minimum(c[ok], shared), rtol=1e-9), shared


def test_options_checked_once_are_still_checked_by_type_and_value():
    """The option check remembers the value sets that passed (per value and type): a value that
    equals a remembered one but is of another type (True for 1, 1.0 for 1 where an integer is
    due is fine, a bool is not) or a new bad value still raises."""
    g = _geom()
    truth = 100.0 + 0.5 * np.arange(g.n_beams)
    img, mask = _speckled(2, truth)
    e = find_echoes(mask, img, g)
    first = np.full(g.n_beams, -1)
    template_edges(e, first, img, g, half_template=1, half_window=1, anchor_beams=1)
    template_edges(e, first, img, g, half_template=1, half_window=1, anchor_beams=1)  # (remembered)
    for key in ("half_template", "half_window", "anchor_beams"):
        with pytest.raises(InputError, match=key):
            template_edges(e, first, img, g, **{"half_template": 1, "half_window": 1, "anchor_beams": 1, key: True})
    with pytest.raises(InputError, match="fraction"):
        template_edges(e, first, img, g, half_template=1, half_window=1, anchor_beams=1, fraction=1.0)
    with pytest.raises(TypeError):
        template_edges(e, first, img, g, half_template=[1])  # unhashable: checked as before


def test_the_pipeline_option_switches_the_stage():
    for key in ("edge_template_beams", "edge_template_anchor_beams"):
        with pytest.raises(Exception, match=key):
            PipelineConfig().replace(**{key: -1})
    # on by default, anchored on the pooled edges (docs/ranges.md, "Template edges")
    assert PipelineConfig().ranges.edge_template_beams == 5
    assert PipelineConfig().ranges.edge_template_anchor_beams == 10
    assert PipelineConfig().replace(edge_template_beams=0).ranges.edge_template_beams == 0


def test_the_anchor_moves_each_run_by_the_median_offset():
    """``_anchor_run``: every measured beam of a run moves by the median of (edge before - template
    edge) over the measured beams within ``anchor`` beams; unmeasured beams stay; the median's
    variance is added to the crossing's."""
    from sonarmap.ranges._template_kernels import _anchor_run

    edge = np.arange(30, dtype=float) + 100.0
    new = edge - 1.0  # the template 1 bin early everywhere ...
    new[10] = edge[10] - 4.0  # ... but one outlier, which the median ignores
    var = np.full((30, 2), 0.04)
    var[5] = np.nan  # not measured by the template: keeps its edge
    new[5] = edge[5]
    before = var.copy()
    _anchor_run(edge, new, var, 0, 30, 3, 1.0)
    keep = np.arange(30) != 5
    moved = new - edge
    assert np.allclose(moved[keep & (np.arange(30) != 10)], 0.0)
    assert moved[10] == pytest.approx(-3.0)  # its own offset differs from its neighbours' median
    assert new[5] == edge[5] and np.isnan(var[5]).all()
    assert np.all(var[keep, 1] >= before[keep, 1]) and np.all(var[keep, 0] == before[keep, 0])


def test_anchored_edges_keep_the_pooled_level_and_the_templates_precision():
    """On speckled sloped echoes (96 beams, 3 seeds) the anchored edges lie at the pooled edges'
    level (the median error equal within 0.3 bin; measured 0.19, 0, 0) and scatter less about it
    (median absolute deviation: measured 1.80 / 1.07 / 1.10 bins pooled, 1.52 / 0.87 / 0.83
    anchored)."""
    g = _geom()
    truth = 100.0 + 0.7 * np.arange(g.n_beams) + 0.3
    mad = {"pooled": [], "anchored": []}
    for seed in range(3):
        img, mask = _speckled(10 + seed, truth, rise=6.0)
        pooled, anchored, _ = _edges(img, mask, g)
        ok = np.isfinite(pooled) & np.isfinite(anchored)
        assert ok.sum() > 80
        ep, ea = pooled[ok] - truth[ok], anchored[ok] - truth[ok]
        assert abs(np.median(ea) - np.median(ep)) < 0.3
        mad["pooled"].append(np.median(np.abs(ep - np.median(ep))))
        mad["anchored"].append(np.median(np.abs(ea - np.median(ea))))
    assert np.mean(mad["anchored"]) < 0.9 * np.mean(mad["pooled"]), mad


def test_the_anchor_median_and_spread_equal_numbas_median_mean_and_sum():
    """The anchor's median (insertion into a scratch array) and its spread (two sequential sums)
    are numba's np.median, w.mean() and ((w - mu) ** 2).sum() bit for bit, ties included."""
    from numba import njit

    from sonarmap.ranges._kernels import _median_of

    @njit(cache=False)
    def ours(w: np.ndarray, srt: np.ndarray) -> tuple[float, float]:
        mu = 0.0
        for q in range(w.size):
            mu += w[q]
        mu = mu / w.size
        ss = 0.0
        for q in range(w.size):
            e = w[q] - mu
            ss += e * e
        return _median_of(w, 0, w.size, srt), ss

    @njit(cache=False)
    def numbas(w: np.ndarray) -> tuple[float, float]:
        return np.median(w), ((w - w.mean()) ** 2).sum()

    rng = np.random.default_rng(5)
    srt = np.empty(21)
    for i in range(3000):
        w = rng.normal(size=int(rng.integers(1, 22))) * 10.0 ** rng.uniform(-3, 2)
        if i % 3 == 0:
            w = np.round(w, 1)  # ties
        before = w.copy()
        got, want = ours(w, srt), numbas(w)
        assert np.array_equal(w, before)
        assert got[0] == want[0] and (w.size < 2 or got[1] == want[1])


def test_the_local_quadratic_solves_its_normal_equations_as_lapack_does():
    """_solve_small agrees with numba's np.linalg.solve (LAPACK's dgesv) within the rounding a
    backward-stable solve allows (a few units of cond(A) * eps), on the normal equations of every
    window of the template's course (half-widths 1-12, both clipped ends) and on random 2 x 2 /
    3 x 3 systems.  Bit for bit only with some LAPACK builds: OpenBLAS 0.3.31's dgesv rounds
    differently from its older releases, so the bits are not what is tested."""
    from numba import njit

    from sonarmap.ranges._kernels import _solve_small

    @njit(cache=False)
    def both(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        want = np.linalg.solve(a, b)
        A = np.zeros((3, 3))
        rhs = np.zeros(3)
        n = b.size
        A[:n, :n] = a
        rhs[:n] = b
        _solve_small(A, rhs, n)
        return rhs[:n].copy(), want

    rng = np.random.default_rng(11)
    systems = []
    for half in range(1, 13):
        for xmin in range(-half, 1):
            for xmax in range(0, half + 1):
                if xmax - xmin + 1 < 3:
                    continue
                deg = 3 if xmax - xmin + 1 >= 5 else 2
                x = np.arange(xmin, xmax + 1, dtype=float)
                p = x[None, :] ** np.arange(deg)[:, None]
                for _ in range(20):
                    cur = rng.uniform(0, 4000) + rng.normal(size=x.size) * 10.0 ** rng.uniform(-2, 2)
                    systems.append((p @ p.T, p @ cur))
    for i in range(20000):
        n = 2 + i % 2
        a = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-2, 4, size=(n, n))
        systems.append((a + a.T if i % 3 == 0 else a, rng.normal(size=n) * 10.0 ** rng.uniform(-2, 4, size=n)))
    for a, b in systems:
        got, want = both(np.ascontiguousarray(a), np.ascontiguousarray(b))
        tol = 8.0 * np.linalg.cond(a) * np.finfo(float).eps * np.abs(want).max()
        assert np.abs(got - want).max() <= tol, (a, b, got, want)


def test_the_local_quadratics_of_a_course_are_each_positions_own() -> None:
    """``_local_quadratics`` (one factored normal matrix for the positions whose whole window is
    inside the course) gives the bits of ``_local_quadratic`` at every position, for courses
    shorter and longer than the window and half-widths whose windows fit a line or nothing."""
    from sonarmap.ranges._template_kernels import _local_quadratic, _local_quadratics

    rng = np.random.default_rng(12)
    A = np.empty((3, 3))
    rhs = np.empty(3)
    for nb in (1, 2, 4, 7, 11, 40):
        cur = 300.0 + np.cumsum(rng.normal(0.0, 0.7, nb))
        for half in (0, 1, 2, 5, 12):
            line = np.full(nb, np.nan)
            slope = np.full(nb, np.nan)
            _local_quadratics(cur, half, A, rhs, line, slope)
            want = np.array([_local_quadratic(cur, a, half, A, rhs) for a in range(nb)]).reshape(nb, 2)
            assert line.tobytes() == want[:, 0].copy().tobytes()
            assert slope.tobytes() == want[:, 1].copy().tobytes()


def test_the_position_variance_follows_the_speckles_looks():
    """The template position's variance is the sandwich (robust) estimate - the scatter of each
    beam's score over the square of the Fisher information of single-look intensities - so an
    echo averaged over ``L`` looks (gamma intensities of the same mean: the simulated ARIS and
    Oculus presets) is placed with about ``1 / L`` the variance of a single-look one; the
    single-look Fisher information alone gave both the same variance."""
    from sonarmap.ranges import _template_kernels
    from sonarmap.ranges.echoes import _first_runs
    from sonarmap.ranges.template import _skipped_beams

    g = _geom()
    truth = 100.0 + 0.5 * np.arange(g.n_beams)
    single, mask = _speckled(7, truth)
    env, _ = _echo_mean(truth)
    looks = 16
    multi = env * np.random.default_rng(8).gamma(looks, 1.0 / looks, env.shape)
    pos_var = []
    for img in (single, multi):
        e = find_echoes(mask, img, g)
        first, count = e.per_beam()
        sel = np.ascontiguousarray(np.where(count > 0, first, -1), dtype=np.int64)
        edge, stop, run = _first_runs(e, sel, 1.0)
        _, var = _template_kernels.template_edges(np.ascontiguousarray(img, dtype=np.float64), edge, stop, run,
                                                  _skipped_beams(sel, None), 5, 6, 8, 30, 60, 4.0, 6, 0.5, 3, 24, 2,
                                                  12.0, 0, 1.0)
        assert np.isfinite(var[:, 0]).sum() > 60
        pos_var.append(np.nanmedian(var[:, 0]))
    assert 4.0 < pos_var[0] / pos_var[1] < 40.0, pos_var  # measured 7.8 (the single-look Fisher: 0.70)


def test_the_smoothing_trust_is_what_the_incoming_edges_sigmas_allow():
    """``Echoes.smooth_trust``: 1 for the returns the template does not measure and without an
    anchor; >= 1 everywhere; larger where the incoming edges' own sigmas say more than the anchor
    offsets' scatter (here: the same echoes given sigmas of 8 bins); edges and sigmas unchanged."""
    g, img, e, first = _sloped_surface(7)
    assert template_edges(e, first, img, g, anchor_beams=10).smooth_trust is None  # (not asked for)
    own = template_edges(e, first, img, g, anchor_beams=0, anchor_trust=True)
    assert own.smooth_trust is not None and np.all(own.smooth_trust == 1.0)
    got = template_edges(e, first, img, g, anchor_beams=10, anchor_trust=True)
    moved = got.edge_bin != e.edge_bin
    assert moved.sum() > 60 and np.all(got.smooth_trust >= 1.0) and np.all(got.smooth_trust[~moved] == 1.0)
    wide = template_edges(e.replaced(sigma_m=np.full(e.size, 8 * 0.02)), first, img, g, anchor_beams=10,
                          anchor_trust=True)
    assert np.array_equal(wide.edge_bin, got.edge_bin) and np.array_equal(wide.sigma_m[moved], got.sigma_m[moved])
    # measured: medians 1.00 (the echoes' own sigmas) and 1.67 (8 bins)
    assert np.median(got.smooth_trust[moved]) < 1.1 and np.median(wide.smooth_trust[moved]) > 1.4


def test_the_anchor_trust_brings_the_flat_didson_hulls_late_run_back():
    """``edge_template_anchor_trust``: on the simulated flat DIDSON hull (seed 0, its floor noise),
    beams 74-79, whose single-look edges drag their pooled windows 3-6 bins late, come 2.4-3.5
    bins late by default (mean 2.93) and 1.3-2.0 with the option (mean 1.80: the smoothing leans
    on the neighbours)."""
    from sonarmap import preset
    from sonarmap.evaluate.segmentation import _simulate, preset_sim_configs
    from sonarmap.pipeline import process_ping

    g = preset("didson-hf")
    sim = _simulate("hull", g, preset_sim_configs(g)[0], 0, -3.0, True)[0]
    bins = np.arange(g.n_bins, dtype=float)
    truth = np.interp(sim.surface_range_m, g.range_m, bins)
    late = {}
    for on in (False, True):
        r = process_ping(sim.ping, PipelineConfig().replace(edge_template_anchor_trust=on)).ranges
        late[on] = (np.interp(r.range_m, g.range_m, bins) - truth)[74:80]
    assert np.mean(late[False]) > 2.7 and np.all(late[True] < 2.2), late
    assert np.mean(late[True]) < np.mean(late[False]) - 0.9
