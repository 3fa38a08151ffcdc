"""Leading edges combined along a surface (sonarmap.ranges.smoothing)."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.pipeline import PipelineConfig
from sonarmap.ranges._smoothing_kernels import smooth_edges
from sonarmap.ranges.smoothing import SIGMA_MIN_BINS


def _reference(y: np.ndarray, s: np.ndarray, h: int, trust: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The combination written with numpy for one run: leave-one-out weighted quadratic, its
    variance with the roughness term, inverse-variance combination, sigma update (``trust``: the
    factor on each sigma in the weights, the prediction's variance and the gain, not in the sigma
    update: that takes the gain the edge's own sigma has against the same prediction)."""
    n = y.size
    x = np.arange(n, dtype=float)
    s_own = np.maximum(s, SIGMA_MIN_BINS)
    s = np.maximum(s * (1.0 if trust is None else trust), SIGMA_MIN_BINS)
    new, sig = y.copy(), s_own.copy()
    for a in range(n):
        d = np.abs(x - x[a])
        tw = np.clip(1 - (d / (h + 1)) ** 3, 0, None) ** 3
        tw[a] = 0.0
        use = tw > 0
        if use.sum() < 4:
            continue
        X = np.vander(x[use] - x[a], 3, increasing=True)
        w = tw[use] / s[use] ** 2
        ainv = np.linalg.inv((X.T * w) @ X)
        coef = ainv @ ((X.T * w) @ y[use])
        weights = (ainv @ (X.T * w))[0]
        r = y[use] - X @ coef
        v_res = np.sum(tw[use] * r * r) / np.sum(tw[use]) / max(1 - 3 / use.sum(), 0.2)
        rough = max(v_res - np.sum(tw[use] * s[use] ** 2) / np.sum(tw[use]), 0.0)
        vp = np.sum(weights**2 * (s[use] ** 2 + rough)) + rough
        k = s[a] ** 2 / (s[a] ** 2 + vp)
        new[a] = y[a] + k * (coef[0] - y[a])
        k_own = s_own[a] ** 2 / (s_own[a] ** 2 + vp)
        sig[a] = np.sqrt(max(s_own[a] ** 2 - k_own * min(v_res, s_own[a] ** 2), 0.25 * s_own[a] ** 2))
    return new, sig


def test_kernel_is_the_numpy_formula():
    rng = np.random.default_rng(3)
    for _ in range(20):
        n = int(rng.integers(8, 60))
        y = 0.02 * (np.arange(n) - n / 2) ** 2 + rng.normal(0, 1.0, n)
        s = rng.uniform(0.1, 2.5, n)
        ref_e, ref_s = _reference(y, s, 8)
        e, sig = smooth_edges(y, s, np.zeros(n, np.int64), 8, 7, SIGMA_MIN_BINS, s)
        np.testing.assert_allclose(e, ref_e, rtol=0, atol=1e-9)
        np.testing.assert_allclose(sig, np.minimum(s, ref_s), rtol=0, atol=1e-9)


def test_kernel_is_the_numpy_formula_with_a_trust_factor():
    """Edges trusted less than their sigma says (a factor on the sigma in the weights, the
    prediction's variance and the gain) - the numpy formula with that factor; the sigma update
    from the edge's own sigma."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        n = int(rng.integers(8, 60))
        y = 0.02 * (np.arange(n) - n / 2) ** 2 + rng.normal(0, 1.0, n)
        s = rng.uniform(0.1, 2.5, n)
        trust = np.where(rng.random(n) < 0.5, 2.0, 1.0)
        ref_e, ref_s = _reference(y, s, 8, trust)
        e, sig = smooth_edges(y, s, np.zeros(n, np.int64), 8, 7, SIGMA_MIN_BINS, s * trust)
        np.testing.assert_allclose(e, ref_e, rtol=0, atol=1e-9)
        np.testing.assert_allclose(sig, np.minimum(s, ref_s), rtol=0, atol=1e-9)


def test_an_edge_trusted_less_reports_the_sigma_its_own_weight_would_give():
    """Trusting one edge less moves it further towards what its neighbours predict, but the
    sigma it reports is the one its own sigma gives against that prediction: with the
    neighbours' weights unchanged (they are trusted as before) the prediction's variance is the
    same, so the edge's reported sigma is the same as without the factor - the factor says how
    far to lean on the neighbours, not that the edge became more precise."""
    rng = np.random.default_rng(5)
    n = 40
    y = 50.0 + 0.05 * np.arange(n) + rng.normal(0.0, 0.6, n)
    s = rng.uniform(0.4, 1.2, n)
    y[17] += 2.5
    run = np.zeros(n, np.int64)
    e1, s1 = smooth_edges(y, s, run, 8, 7, SIGMA_MIN_BINS, s)
    w = s.copy()
    w[17] *= 3.0
    e2, s2 = smooth_edges(y, s, run, 8, 7, SIGMA_MIN_BINS, w)
    assert abs(e2[17] - e1[17]) > 0.1 and abs(e2[17] - (50.0 + 0.05 * 17)) < abs(e1[17] - (50.0 + 0.05 * 17))
    assert s2[17] == s1[17], (s1[17], s2[17])


def test_an_edge_trusted_less_moves_further_towards_its_neighbours_and_keeps_its_sigma_scale():
    """A late edge on a flat surface whose edges scatter more than their sigmas say (template
    edges, one of which followed a speckle fade): at their sigmas the scatter reads as the
    surface's own roughness and the late edge keeps most of its lead; trusted half as much
    (factor 2) the scatter is noise, the edge moves most of the way back, and its sigma is shrunk
    from its own value, not from the doubled one."""
    from sonarmap.geometry import SonarGeometry
    from sonarmap.ranges.echoes import Echoes
    from sonarmap.ranges.smoothing import smooth_surface_edges

    rng = np.random.default_rng(2)
    n = 40
    y = 100.0 + rng.normal(0.0, 0.8, n)
    s = np.full(n, 0.5)
    y[20] += 3.0
    e1, s1 = smooth_edges(y, s, np.zeros(n, np.int64), 8, 7, SIGMA_MIN_BINS, s)
    e2, s2 = smooth_edges(y, s, np.zeros(n, np.int64), 8, 7, SIGMA_MIN_BINS, 2.0 * s)
    assert abs(e2[20] - 100.0) < 0.5 * abs(e1[20] - 100.0), (e1[20], e2[20])
    assert np.all(s2 <= s) and np.all(s2 >= 0.5 * s)
    # through smooth_surface_edges: the factor per echo; one factor per echo, each >= 1
    g = SonarGeometry(range_m=2.0 + 0.01 * np.arange(300), azimuth_rad=np.linspace(-0.3, 0.3, n))
    beam = np.arange(n, dtype=np.int64)
    start = np.floor(y).astype(np.int64) + 1
    fields = {f: np.zeros(n) for f in Echoes.__dataclass_fields__ if f not in
              ("beam", "n_beams", "clipped", "clip_row", "beamwidth_beams", "clip_fitted")}
    fields.update(beam=beam, start_bin=start, stop_bin=start + 3, edge_bin=y,
                  edge_range_m=np.interp(y, np.arange(300.0), g.range_m), sigma_m=s * 0.01,
                  peak_bin=start, n_pixels=np.ones(n, np.int64), n_beams=n)
    echoes = Echoes._of(**fields)
    plain = smooth_surface_edges(echoes, beam, g)
    same = smooth_surface_edges(echoes, beam, g, trust=np.ones(n))
    assert np.array_equal(plain.edge_bin, same.edge_bin) and np.array_equal(plain.sigma_m, same.sigma_m)
    less = smooth_surface_edges(echoes, beam, g, trust=np.full(n, 2.0))
    assert abs(less.edge_bin[20] - 100.0) < abs(plain.edge_bin[20] - 100.0)
    for bad in (np.ones(n - 1), np.full(n, 0.5), np.full(n, np.nan)):
        with pytest.raises(InputError, match="trust"):
            smooth_surface_edges(echoes, beam, g, trust=bad)
    with pytest.raises(ValueError, match="sigma_template_smooth_scale"):
        PipelineConfig().replace(ranges={"sigma_template_smooth_scale": 0.5})


def test_noisy_edges_of_a_smooth_surface_move_towards_it():
    """Edges scattered by their sigma about a curved surface: the combination's error is far
    smaller, its sigmas smaller but never below half and never larger than before."""
    rng = np.random.default_rng(0)
    n = 96
    truth = 200.0 + 0.004 * (np.arange(n) - 40.0) ** 2
    s = np.full(n, 1.5)
    err_before, err_after = [], []
    for _ in range(20):
        y = truth + rng.normal(0.0, 1.5, n)
        e, sig = smooth_edges(y, s, np.zeros(n, np.int64), 8, 7, SIGMA_MIN_BINS, s)
        err_before.append(y - truth)
        err_after.append(e - truth)
        assert np.all(sig <= s) and np.all(sig >= 0.5 * s)
    rms_before = np.sqrt(np.mean(np.square(err_before)))
    rms_after = np.sqrt(np.mean(np.square(err_after)))
    assert rms_after < 0.6 * rms_before, (rms_before, rms_after)


def test_precise_edges_and_real_structure_stay():
    """A precise edge among noisy neighbours barely moves; a staircase with small sigmas (a steep
    line sampled beam by beam: real structure, not noise) keeps its edges."""
    rng = np.random.default_rng(1)
    n = 40
    y = 100.0 + rng.normal(0.0, 3.0, n)
    s = np.full(n, 3.0)
    y[20], s[20] = 110.0, 0.3
    e, _ = smooth_edges(y, s, np.zeros(n, np.int64), 8, 7, SIGMA_MIN_BINS, s)
    assert abs(e[20] - 110.0) < 0.15 * abs(110.0 - np.median(y))
    stairs = 50.0 + 7.7 * np.arange(n) + np.tile([0.0, 3.0, -2.0, 1.0], n // 4)
    e, _ = smooth_edges(stairs, np.full(n, 0.4), np.zeros(n, np.int64), 8, 7, SIGMA_MIN_BINS, np.full(n, 0.4))
    assert np.max(np.abs(e - stairs)) < 0.5


def test_runs_are_combined_separately_and_short_runs_are_kept():
    rng = np.random.default_rng(2)
    y = np.concatenate([100.0 + rng.normal(0, 1, 20), 160.0 + rng.normal(0, 1, 20), 50.0 + rng.normal(0, 1, 5)])
    run = np.repeat([0, 1, 2], [20, 20, 5]).astype(np.int64)
    y[25] = np.nan
    run[25] = -1
    s = np.ones(y.size)
    s[25] = np.nan
    e, sig = smooth_edges(y, s, run, 8, 7, SIGMA_MIN_BINS, s)
    assert np.all(np.abs(e[:20] - 100.0) < 5) and np.all(np.abs(e[20:25] - 160.0) < 5)
    assert np.array_equal(e[40:], y[40:]) and np.array_equal(sig[40:], s[40:])  # 5 beams < 7
    assert np.isnan(e[25]) and np.isnan(sig[25])


def test_options_are_checked():
    from sonarmap.ranges.echoes import find_echoes
    from sonarmap.ranges.smoothing import smooth_surface_edges
    from sonarmap.geometry import SonarGeometry

    g = SonarGeometry(range_m=1.0 + 0.01 * np.arange(50), azimuth_rad=np.linspace(-0.2, 0.2, 8))
    echoes = find_echoes(np.zeros((50, 8), bool), np.zeros((50, 8)), g)
    first = np.full(8, -1)
    for kw in ({"half_beams": 1}, {"min_beams": 4}, {"half_beams": 2.5}):
        with pytest.raises(InputError):
            smooth_surface_edges(echoes, first, g, **kw)
    with pytest.raises(InputError, match="first"):
        smooth_surface_edges(echoes, first[:3], g)
    assert smooth_surface_edges(echoes, first, g) is echoes
    with pytest.raises(ValueError, match="edge_smooth_beams"):
        PipelineConfig().replace(edge_smooth_beams=1)


def moved_edges(echoes, idx: np.ndarray, edge_bin: np.ndarray, sigma_m: np.ndarray, geometry):
    """The numpy formulation the range kernels replaced: ``echoes`` with echoes ``idx`` moved to
    ``edge_bin`` (their ranges ``np.interp`` on the bins) with ``sigma_m``."""
    new_bin = echoes.edge_bin.copy()
    new_range = echoes.edge_range_m.copy()
    new_sigma = echoes.sigma_m.copy()
    new_bin[idx] = edge_bin
    new_range[idx] = np.interp(edge_bin, np.arange(geometry.n_bins, dtype=np.float64),
                               np.asarray(geometry.range_m, dtype=np.float64))
    new_sigma[idx] = sigma_m
    return echoes.replaced(edge_bin=new_bin, edge_range_m=new_range, sigma_m=new_sigma)


def test_echo_fields_are_those_of_the_numpy_formulation():
    """smooth_surface_edges' one kernel (smoothed_echo_edges) moves the returns to the values of
    the numpy formulation it replaced (sigmas in bins, smooth_edges, the moved returns' fields
    through moved_edges: np.interp of their ranges), bit for bit, on random surfaces with gaps,
    several runs and no returns at all."""
    from sonarmap.geometry import SonarGeometry
    from sonarmap.ranges.echoes import Echoes, _first_runs
    from sonarmap.ranges.smoothing import smooth_surface_edges

    rng = np.random.default_rng(11)
    g = SonarGeometry(range_m=2.0 + 0.013 * np.arange(300), azimuth_rad=np.linspace(-0.4, 0.4, 40))
    for trial in range(30):
        n = 40
        beam = np.arange(n, dtype=np.int64)
        edge = 100 + np.cumsum(rng.normal(0, 0.4, n)) + rng.normal(0, 1.5, n)
        edge[rng.random(n) < 0.1] = 250.0  # steps: several runs
        start = np.floor(edge).astype(np.int64) + 1
        fields = {f: np.zeros(n) for f in Echoes.__dataclass_fields__ if f not in
                  ("beam", "n_beams", "clipped", "clip_row", "beamwidth_beams", "clip_fitted")}
        fields.update(beam=beam, start_bin=start, stop_bin=start + rng.integers(1, 6, n), edge_bin=edge,
                      edge_range_m=np.interp(edge, np.arange(300.0), g.range_m), sigma_m=rng.uniform(0.002, 0.05, n),
                      peak_bin=start, n_pixels=np.ones(n, np.int64), n_beams=n)
        echoes = Echoes._of(**fields)
        first = np.where(rng.random(n) < (0.0 if trial == 0 else 0.15), -1, beam)
        sel = first.astype(np.int64)
        e, _, run = _first_runs(echoes, sel, 1.0)
        bin_m = abs(g.range_resolution_m)
        ok = sel >= 0
        sigma = np.full(n, np.nan)
        sigma[ok] = echoes.sigma_m[sel[ok]] / bin_m
        new, new_sigma = smooth_edges(e, sigma, run, 8, 7, SIGMA_MIN_BINS, sigma)
        new_sigma *= bin_m
        idx = sel[ok]
        moved = (new[ok] != echoes.edge_bin[idx]) | (new_sigma[ok] != echoes.sigma_m[idx])
        want = moved_edges(echoes, idx[moved], new[ok][moved], new_sigma[ok][moved], g) if moved.any() else echoes
        got = smooth_surface_edges(echoes, first, g)
        assert (got is echoes) == (want is echoes)
        for f in ("edge_bin", "edge_range_m", "sigma_m"):
            assert np.array_equal(getattr(got, f), getattr(want, f), equal_nan=True), (trial, f)


def test_simulated_surfaces_gain_within_a_bin():
    """The pipeline with and without the combination on simulated sloped and curved hulls (both
    noise levels, 2 seeds), scored on the sub-bin surface truth: within a bin measured 0.67 ->
    0.80 (ARIS 3000, sloped 4 bins per beam) and 0.77 -> 0.87 (telephoto, curved), within 3 bins
    unchanged (0.97-0.98, 1.00).  (The telephoto's gain was 0.76 -> 0.92 with the template sigma
    factor 1.55 and the anchor's offsets counted as independent: wider template sigmas let the
    combination move edges further.)"""
    from sonarmap import preset
    from sonarmap.evaluate.segmentation import _simulate_seeds, preset_sim_configs
    from sonarmap.pipeline import process_ping

    for name, scene in (("aris3000-128", "hull_slope4"), ("aris-telephoto-48", "curved_hull")):
        g = preset(name)
        errs: dict[int, list[np.ndarray]] = {0: [], 8: []}
        for sc in preset_sim_configs(g):
            for sim, _ in _simulate_seeds(scene, g, sc, (0, 1), -3.0, True):
                for beams in errs:
                    r = process_ping(sim.ping, PipelineConfig().replace(edge_smooth_beams=beams)).ranges.range_m
                    errs[beams].append((np.asarray(r) - sim.surface_range_m) / abs(g.range_resolution_m))
        e = {k: np.nan_to_num(np.concatenate(v), nan=1e9) for k, v in errs.items()}
        within1 = {k: np.mean(np.abs(v) <= 1.0) for k, v in e.items()}
        assert within1[8] > within1[0] + 0.08, (name, within1)
        assert np.mean(np.abs(e[8]) <= 3.0) >= np.mean(np.abs(e[0]) <= 3.0) - 0.02


def test_the_window_counts_beamwidths_where_the_beams_overlap():
    from sonarmap.ranges.smoothing import window_in_beamwidths

    assert window_in_beamwidths(8, [2.39, 2.4, 2.38]) == 19
    assert window_in_beamwidths(8, np.full(48, 0.5)) == 8  # narrower beams keep the beam count
    assert window_in_beamwidths(8, None) == 8  # no beamwidth known
    assert window_in_beamwidths(8, [np.nan, 2.0, 2.0]) == 16  # unknown entries ignored
    assert window_in_beamwidths(0, [3.0]) == 0  # off stays off
    # the median of the beamwidths is np.median's (even and odd counts, ties at the half beam),
    # and the caller's array is left as it was
    rng = np.random.default_rng(3)
    for n in (1, 2, 5, 48, 256, 257, 512):
        for bw in (rng.uniform(0.5, 3.0, n), np.round(rng.uniform(0.5, 3.0, n) * 16) / 16):
            kept = bw.copy()
            assert window_in_beamwidths(8, bw) == int(round(8 * max(1.0, float(np.median(bw)))))
            assert np.array_equal(bw, kept)


def test_the_pipeline_smooths_an_oculus_fan_over_its_beamwidths(monkeypatch, data_dir):
    # the real Oculus fan's beams are 2.4 spacings wide: the default 16 beamwidths = 38 beams either
    # side; the same ping with its beamwidth removed is smoothed over 16 beams
    import dataclasses

    import sonarmap.ranges.measure as measure
    from sonarmap.io import read_pings
    from sonarmap.pipeline import process_ping

    ping = next(iter(read_pings(data_dir / "oculus" / "one_ping_8bit.raw")))
    seen = []
    real = measure.smooth_surface_edges

    def spy(*args, **kwargs):
        seen.append(kwargs["half_beams"])
        return real(*args, **kwargs)

    monkeypatch.setattr(measure, "smooth_surface_edges", spy)
    process_ping(ping, PipelineConfig())
    narrow = dataclasses.replace(ping, geometry=ping.geometry.replace(azimuth_beamwidth_rad=None))
    process_ping(narrow, PipelineConfig())
    assert seen == [38, 16]
