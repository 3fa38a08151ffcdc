"""Leading edges measured on a multi-look along the tracked surface (``pooled_edges``)."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.pipeline import PipelineConfig
from sonarmap.ranges.echoes import edge_sigma_m, find_echoes, pooled_edges, surface_runs


def _geom(n_bins: int = 300, n_beams: int = 96) -> SonarGeometry:
    return SonarGeometry(range_m=2.0 + 0.02 * np.arange(n_bins), azimuth_rad=np.linspace(-0.4, 0.4, n_beams))


def _speckled_surface(seed: int, truth: np.ndarray, n_bins: int = 300, rise: float = 8.0, depth: float = 20.0,
                      floor: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Single-look (exponential) speckle on an echo whose envelope rises linearly over ``rise``
    bins with its half-peak crossing at ``truth`` (per beam), stays flat ``depth`` bins, then
    ends; and the echo's support (the classifier's ideal mask)."""
    rng = np.random.default_rng(seed)
    r = np.arange(n_bins, dtype=float)[:, None]
    x = r - (truth[None, :] - 0.5 * rise)
    env = np.clip(x / rise, 0.0, 1.0) * (x < rise + depth)
    return (env + floor) * rng.exponential(1.0, (n_bins, truth.size)), env > 0.25


def _first(e) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Per beam the index of its nearest echo (-1 none): the tracker's pick without its costs."""
    first, count = e.per_beam()
    return np.where(count > 0, first, -1)


def _per_beam_and_pooled(img: np.ndarray, mask: np.ndarray, g: SonarGeometry,
                         **kw: object) -> tuple[np.ndarray, np.ndarray]:
    e = find_echoes(mask, img, g)
    first = _first(e)
    pooled = pooled_edges(e, first, img, g, **kw)
    ok = first >= 0
    s = np.maximum(first, 0)
    return np.where(ok, e.edge_bin[s], np.nan), np.where(ok, pooled.edge_bin[s], np.nan)


def test_pooling_removes_most_of_the_speckle_error_of_a_single_look_edge():
    g = _geom()
    truth = 100.0 + 1.5 * np.arange(g.n_beams) * 0.5 + 0.3  # sloped 0.75 bins per beam, sub-bin
    errs_beam, errs_pool = [], []
    for seed in range(4):
        img, mask = _speckled_surface(seed, truth)
        beam, pooled = _per_beam_and_pooled(img, mask, g)
        errs_beam.append(beam - truth)
        errs_pool.append(pooled - truth)
    eb, ep = np.concatenate(errs_beam), np.concatenate(errs_pool)
    assert np.isfinite(ep).mean() > 0.95
    within_beam = np.mean(np.abs(eb[np.isfinite(eb)]) <= 3)
    within_pool = np.mean(np.abs(ep[np.isfinite(ep)]) <= 3)
    # the per-beam half-peak crossing of single-look speckle lands late and scattered
    assert within_pool > within_beam + 0.25  # measured 0.61 against 0.20
    # what is left is late: the pooled profile's maximum over a 20-bin flat top of 21 looks is
    # still a noise maximum (about +45 %), so its half lies high on the rise
    assert 0.0 < np.nanmedian(ep) < 3.0 < np.nanmedian(eb)
    assert np.nanmedian(np.abs(ep)) < 0.6 * np.nanmedian(np.abs(eb))


def test_a_step_between_two_surfaces_does_not_mix_them():
    g = _geom(n_beams=40)
    truth = np.where(np.arange(40) < 20, 80.0, 160.0)
    rng = np.random.default_rng(3)
    r = np.arange(g.n_bins, dtype=float)[:, None]
    env = np.exp(-0.5 * ((r - truth[None, :] - 3.0) / 2.0) ** 2)
    img = env + 0.01 * rng.random(env.shape)
    beam, pooled = _per_beam_and_pooled(img, env > 0.1, g)
    # noise-free echoes: pooling agrees with the per-beam edges on both sides of the step
    # (measured: 0.27 bin early with the two samples around the pooled crossing, 0.32 with the
    # line through the flank, which lies a little early on a Gaussian's curved rise)
    assert np.all(np.isfinite(pooled))
    assert pooled == pytest.approx(beam, abs=0.35)
    assert np.abs(pooled - (truth + 3.0 - 2.0 * np.sqrt(2 * np.log(2)))).max() < 0.5


def test_surface_runs_split_at_gaps_and_jumps():
    g = _geom(n_beams=12)
    img = np.zeros(g.shape)
    rows = [50, 50, 51, 51, -1, 60, 60, 61, 200, 200, 201, 201]
    for j, i in enumerate(rows):
        if i >= 0:
            img[i:i + 3, j] = [0.5, 1.0, 0.5]
    e = find_echoes(img > 0.2, img, g)
    first = _first(e)
    run = surface_runs(e, first)
    assert run[4] == -1
    assert run[0] == run[3] and run[5] == run[7] and run[8] == run[11]
    assert len({run[0], run[5], run[8]}) == 3


def test_short_runs_and_zero_width_keep_their_own_edges():
    g = _geom(n_beams=6)
    img = np.zeros(g.shape)
    img[50:53, 0:2] = [[0.5], [1.0], [0.5]]
    e = find_echoes(img > 0.2, img, g)
    first = _first(e)
    out = pooled_edges(e, first, img, g)
    assert np.array_equal(out.edge_bin, e.edge_bin)
    assert pooled_edges(e, first, img, g, half_beams=0) is e


def test_pooled_sigma_is_finite_and_grows_with_the_speckle():
    g = _geom()
    truth = np.full(g.n_beams, 120.0)
    sig = []
    for floor in (0.02, 0.3):
        img, mask = _speckled_surface(5, truth, floor=floor)
        e = find_echoes(mask, img, g)
        first = _first(e)
        p = pooled_edges(e, first, img, g, sigma_scale=5.0)
        s = p.sigma_m[first[first >= 0]]
        assert np.all(np.isfinite(s)) and np.all(s > 0)
        sig.append(float(np.median(s)))
    assert sig[1] > sig[0]
    # the quadrature terms: bin grid, noise over rise (capped at 8 bins)
    assert edge_sigma_m([0.0], [1.0], 0.02)[0] == pytest.approx(0.02 / np.sqrt(12))
    assert edge_sigma_m([np.nan], [1.0], 0.02)[0] == pytest.approx(np.sqrt(0.02**2 / 12 + (8 * 0.02) ** 2))


@pytest.mark.parametrize("rise", [12.0, 30.0])
def test_the_line_through_a_slow_rise_gives_the_crossing_a_sigma_that_covers_its_scatter(rise: float) -> None:
    """On an echo that rises slowly (over 12 or 30 bins; a flat surface in single-look speckle)
    the two samples around the pooled crossing rise by far more than the echo does per bin (the
    speckle's steps), so the sigma formed from their rise (noise / rise) is too narrow; the line
    through the flank (20-80 % of the peak, ``flank_bins=6``) rises as the echo does, and the
    crossings' scatter about their median lies within +-sigma on a far larger share."""
    g = _geom()
    truth = np.full(g.n_beams, 100.3)
    dev: dict[int, list[np.ndarray]] = {0: [], 6: []}
    for seed in range(4):
        img, mask = _speckled_surface(seed, truth, rise=rise, depth=10.0)
        e = find_echoes(mask, img, g)
        first = _first(e)
        s = np.maximum(first, 0)
        for w in dev:
            p = pooled_edges(e, first, img, g, flank_bins=w)
            err = p.edge_bin[s] - truth
            dev[w].append(np.abs(err - np.nanmedian(err)) / (p.sigma_m[s] / 0.02))
    cov = {w: float(np.nanmean(np.concatenate(v) <= 1.0)) for w, v in dev.items()}
    # measured (rise 12 / 30): 0.33 / 0.29 with the two samples, 0.66 / 0.54 with the line
    assert cov[6] > cov[0] + 0.15


def test_a_pooled_edge_in_front_of_a_late_labelled_core_is_kept() -> None:
    """Where the labels hold only the bright core of a slowly rising echo (the faint end of a
    surface), the echo's first structure bin lies late on the rise and the pooled crossing well in
    front of it.  Kept within the pulse + ``lead_bins`` = 12 of that bin, the pooled edges come
    near the surface; with 2 (the default) most are dropped for the beams' own, late edges."""
    g = _geom()
    truth = np.full(g.n_beams, 100.3)
    r = np.arange(g.n_bins, dtype=float)[:, None]
    x = r - (truth[None, :] - 8.0)
    core = (np.clip(x / 16.0, 0.0, 1.0) * (x < 36.0)) > 0.85  # the rise's top 15 %: ~6 bins late
    errs: dict[int, list[np.ndarray]] = {2: [], 12: []}
    for seed in range(4):
        img, _ = _speckled_surface(seed, truth, rise=16.0, depth=20.0)
        for lead in errs:
            _, pooled = _per_beam_and_pooled(img, core, g, lead_bins=lead)
            errs[lead].append(pooled - truth)
    within = {k: float(np.mean(np.abs(np.concatenate(v)) <= 3)) for k, v in errs.items()}
    med = {k: float(np.nanmedian(np.concatenate(v))) for k, v in errs.items()}
    # measured: within 3 bins 0.03 -> 0.52, median +5.8 -> +2.8 bins (the per-beam edges: +8.2)
    assert within[12] > within[2] + 0.3
    assert 0.0 < med[12] < med[2] - 2.0


def test_the_peak_height_is_the_maximum_of_a_parabola_through_the_samples_around_the_largest() -> None:
    """``_peak_level``: a sampled parabola gives its vertex; a noise spike on a plateau is averaged
    with its neighbours (the least-squares parabola through 1, 1, 1.5, 1, 1 is 1.243 at its
    top); a peak narrower than the window is not raised above its largest sample (the parabola
    through 0.1, 0.9, 1, 0.9, 0.1 peaks at 1.086); ``w = 0``, or fewer than 3 samples inside
    ``lo .. hi - 1``, give the largest sample."""
    from sonarmap.ranges._kernels import _peak_level

    A, T = np.empty((3, 3)), np.empty(3)
    u = np.arange(9, dtype=float)
    para = 2.0 - 0.1 * (u - 4.0) ** 2
    assert _peak_level(para, 4, 0, 9, 2, A, T) == pytest.approx(2.0, abs=1e-12)
    spike = np.array([0.0, 1.0, 1.0, 1.5, 1.0, 1.0, 0.0])
    assert _peak_level(spike, 3, 0, 7, 2, A, T) == pytest.approx(1.0 + 0.5 * 17.0 / 35.0, abs=1e-12)
    assert _peak_level(spike, 3, 0, 7, 0, A, T) == 1.5
    assert _peak_level(spike, 3, 3, 5, 2, A, T) == 1.5  # two samples inside lo .. hi - 1
    narrow = np.array([0.1, 0.9, 1.0, 0.9, 0.1])
    assert _peak_level(narrow, 2, 0, 5, 2, A, T) == 1.0
    # at the profile's end (a rising echo): the samples on one side only
    ramp = np.array([0.2, 0.4, 0.6, 0.8, 1.0])
    assert _peak_level(ramp, 4, 0, 5, 2, A, T) == pytest.approx(1.0, abs=1e-12)


def test_the_parabola_takes_the_speckles_maximum_out_of_the_level() -> None:
    """On single-look speckle the largest sample of the pooled profile's flat top is a noise
    maximum, which puts the half-peak level high and the crossing late on the rise; the height
    of the parabola through the samples around it (``peak_bins = 2``) brings the crossings nearer
    the truth than the largest sample (``peak_bins = 0``; 2 is the default).  An echo shallower than
    6 x ``peak_bins`` (here 4 bins of rise and 4 flat: a window depth of ~6) keeps its largest
    sample: the same edges either way."""
    g = _geom()
    truth = 100.0 + 0.75 * np.arange(g.n_beams) + 0.3
    med, within = {}, {}
    for pb in (0, 2):
        errs = []
        for seed in range(4):
            img, mask = _speckled_surface(seed, truth)
            _, pooled = _per_beam_and_pooled(img, mask, g, peak_bins=pb)
            errs.append(pooled - truth)
        e = np.concatenate(errs)
        med[pb] = float(np.nanmedian(e))
        within[pb] = float(np.mean(np.abs(e[np.isfinite(e)]) <= 3))
    # measured: median +1.77 -> +1.64 bins, within 3 bins 0.758 -> 0.784
    assert 0.0 < med[2] < med[0] - 0.1
    assert within[2] > within[0] + 0.015
    img, mask = _speckled_surface(0, truth, rise=4.0, depth=4.0)
    shallow = [_per_beam_and_pooled(img, mask, g, peak_bins=pb)[1] for pb in (0, 2)]
    assert np.isfinite(shallow[0]).mean() > 0.9
    assert np.array_equal(shallow[0], shallow[1], equal_nan=True)
    assert PipelineConfig().ranges.edge_pool_peak_bins == 2


def test_a_pooled_edges_jitter_is_floored_at_a_share_of_its_neighbours() -> None:
    """``floor_jitter``: an edge whose jitter (noise / rise) is below ``fraction`` x the median of
    its run's edges within ``half_beams`` is raised to it (its rise kept); edges of another run,
    edges that were not pooled (NaN noise) and windows of fewer than 3 jitters are left alone."""
    from sonarmap.ranges._kernels import floor_jitter

    rise = np.array([1.0, 2.0, 1.0, 0.5, 1.0, 1.0, 1.0, 1.0, 1.0])
    q = np.array([4.0, 4.0, 0.4, 4.0, 5.0, 6.0, 0.1, 0.1, np.nan])  # jitter in bins
    noise = q * rise
    run = np.array([0, 0, 0, 0, 0, 0, 1, 1, 1])
    out = noise.copy()
    floor_jitter(out, rise, run, 2, 0.5)
    # beam 2's window (beams 0-4) has jitters 4, 4, 0.4, 4, 5: median 4, floor 2
    assert out[2] / rise[2] == pytest.approx(2.0)
    assert np.array_equal(out[[0, 1, 3, 4, 5]], noise[[0, 1, 3, 4, 5]])
    # run 1 holds two finite jitters: too few for a median, left alone; NaN stays NaN
    assert np.array_equal(out[6:8], noise[6:8]) and np.isnan(out[8])
    same = noise.copy()
    floor_jitter(same, rise, run, 2, 0.0)
    assert np.array_equal(same, noise, equal_nan=True)


@pytest.mark.parametrize(("name", "default", "other"), [("sigma_pool_floor", 0.5, 0.0),
                                                       ("edge_pool_follow_slope", 0.0, 2.0)])
def test_the_jitter_floor_and_the_slope_following_are_checked_options(name: str, default: float,
                                                                      other: float) -> None:
    assert PipelineConfig().option(name) == default
    assert PipelineConfig().replace(**{name: other}).option(name) == other
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(InputError, match=name):
            PipelineConfig().replace(**{name: bad})


def test_pooled_edges_rejects_bad_arguments():
    g = _geom(n_beams=4)
    img = np.zeros(g.shape)
    img[50:53, :] = np.array([0.5, 1.0, 0.5])[:, None]
    e = find_echoes(img > 0.2, img, g)
    first = _first(e)
    for kw in ({"half_beams": -1}, {"front_bins": 1.5}, {"max_bins": 2}, {"smooth_bins": 0}, {"n_iter": 0},
               {"fraction": 1.0}, {"flank_bins": -1}, {"flank_bins": 1.5}, {"lead_bins": -1}, {"peak_bins": -1},
               {"peak_bins": 0.5}):
        with pytest.raises(InputError):
            pooled_edges(e, first, img, g, **kw)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="first"):
        pooled_edges(e, first[:2], img, g)
    with pytest.raises(InputError, match="edge_pool_beams"):
        PipelineConfig().replace(edge_pool_beams=-1)
    with pytest.raises(InputError, match="edge_pool_flank_bins"):
        PipelineConfig().replace(edge_pool_flank_bins=-1)
    with pytest.raises(InputError, match="edge_pool_lead_bins"):
        PipelineConfig().replace(edge_pool_lead_bins=-1)
    with pytest.raises(InputError, match="edge_pool_peak_bins"):
        PipelineConfig().replace(edge_pool_peak_bins=-1)
    with pytest.raises(InputError, match="sigma_pool_scale"):
        PipelineConfig().replace(sigma_pool_scale=-1.0)


def _surface_case(edges: np.ndarray, llr: np.ndarray, faint: np.ndarray) -> tuple[object, np.ndarray, tuple]:
    """Echoes, tracked first returns and (levels, evidence per level) of a surface with leading
    edges ``edges`` over 200 bins: beams 0-19 strong (classifier structure, 3 nats per pixel),
    the others a faint stretch whose 6 pixels carry ``faint[j]`` (noise ``llr`` elsewhere)."""
    from sonarmap.ranges.tracking import TrackConfig, track_surfaces

    g = _geom(n_bins=200, n_beams=edges.size)
    img = np.zeros(g.shape)
    mask = np.zeros(g.shape, dtype=bool)
    for j, t in enumerate(edges.astype(int)):
        if j < 20:
            img[t:t + 6, j] = [0.5, 1.0, 1.0, 1.0, 0.8, 0.4]
            mask[t:t + 6, j] = True
            llr[t:t + 6, j] = 3.0
        else:
            llr[t:t + 6, j] = faint[j]
    e = find_echoes(mask, img, g)
    first = track_surfaces(e, TrackConfig(segment_cost=10.0)).first
    # the kernel takes quantised levels and the evidence per level: here one level per 0.1 nat
    values = np.unique(llr)
    return e, first, (np.searchsorted(values, llr), values)


def _continuation_case(seed: int, faint_llr: float) -> tuple[np.ndarray, object, np.ndarray, tuple]:
    """A surface sloped 2 bins per beam: beams 0-19 strong (classifier structure), beams 20-31 a
    faint stretch whose pixels carry ``faint_llr`` nats each over 6 bins, noise (-1 +- 1) elsewhere."""
    rng = np.random.default_rng(seed)
    truth = 60.0 + 2.0 * np.arange(32)
    llr = np.round(rng.normal(-1.0, 1.0, (200, 32)), 1)
    faint = np.round(faint_llr + rng.normal(0, 0.5, (32, 6)), 1)
    return (truth, *_surface_case(truth, llr, faint))


def test_continuation_follows_a_faint_stretch_along_the_slope_and_not_noise():
    from sonarmap.ranges.tracking import continuation_mask

    truth, e, first, llr = _continuation_case(0, 2.5)
    assert (first[:20] >= 0).all() and (first[20:] < 0).all()
    add = continuation_mask(e, first, *llr, min_evidence=10.0)
    assert not add[:, :20].any()
    for j in range(20, 32):
        rows = np.flatnonzero(add[:, j])
        assert rows.size and abs(rows[0] - truth[j]) <= 3, (j, rows)
    # no faint stretch: only noise beyond the surface's end - nothing reaches 10 nats
    truth, e, first, llr = _continuation_case(1, -1.0)
    assert not continuation_mask(e, first, *llr, min_evidence=10.0).any()
    with pytest.raises(InputError, match="levels"):
        continuation_mask(e, first, llr[0][:, :3], llr[1])


def test_continuation_searches_a_missed_beam_again_between_the_beams_found_around_it():
    """A step in a faint stretch: the extrapolation misses beam 21 (8 bins behind the line), finds
    beam 22 (its window widens by a bin per beam); beam 21 is then searched around the line from
    beam 20 to beam 22 and found."""
    from sonarmap.ranges.tracking import continuation_mask

    edges = np.concatenate([60.0 + 2.0 * np.arange(21), [108.0, 110.0], 110.0 + 2.0 * np.arange(1, 10)])
    e, first, llr = _surface_case(edges, np.full((200, 32), -1.0), np.full(32, 2.5))
    add = continuation_mask(e, first, *llr, min_evidence=10.0)
    for j in range(20, 32):
        rows = np.flatnonzero(add[:, j])
        assert rows.size and abs(rows[0] - edges[j]) <= 1, (j, rows)


def test_a_clipped_echo_carries_the_clipping_in_its_sigma():
    """Half of a clipped peak is only a lower bound: the true crossing lies between the measured
    one and the first sample at full scale, so that interval's spread joins the sigma."""
    from sonarmap.ranges.measure import CLIP_LEVEL, clipped_echo_sigma

    g = _geom(n_bins=100, n_beams=2)
    img = np.zeros(g.shape)
    img[40:50, 0] = [0.1, 0.3, 0.6, 0.9, 1.0, 1.0, 1.0, 1.0, 0.8, 0.4]  # clipped from bin 44
    img[40:50, 1] = [0.1, 0.3, 0.6, 0.9, 0.95, 0.9, 0.8, 0.6, 0.4, 0.2]  # not clipped
    e = find_echoes(img > 0.2, img, g)
    first = _first(e)
    out = clipped_echo_sigma(e, first, img, g)
    bin_m = 0.02
    spread = (44 - e.edge_bin[first[0]]) * bin_m
    assert spread > 0 and img[44, 0] >= CLIP_LEVEL
    assert out.sigma_m[first[0]] == pytest.approx(np.hypot(e.sigma_m[first[0]], spread / np.sqrt(12)))
    assert out.sigma_m[first[1]] == e.sigma_m[first[1]]
    assert np.array_equal(out.edge_bin, e.edge_bin)  # the range is not moved


def test_a_full_scale_sample_behind_the_first_peak_does_not_widen_the_sigma():
    """The level an edge is measured at is half the echo's *first* peak: a full-scale speckle
    spike deeper in the echo, after the profile has peaked and fallen, did not set it, so the
    sigma stays; the same spike on the rise before the first peak widens it."""
    from sonarmap.ranges.measure import CLIP_LEVEL, clipped_echo_sigma

    g = _geom(n_bins=100, n_beams=2)
    img = np.zeros(g.shape)
    img[40:52, 0] = [0.1, 0.3, 0.6, 0.8, 0.6, 0.5, 0.4, 1.0, 0.4, 0.3, 0.2, 0.1]  # spike behind the peak
    img[40:52, 1] = [0.1, 0.3, 0.6, 1.0, 0.6, 0.5, 0.4, 0.4, 0.4, 0.3, 0.2, 0.1]  # clipped first peak
    e = find_echoes(img > 0.05, img, g)
    first = _first(e)
    assert img[47, 0] >= CLIP_LEVEL and e.peak_bin[first[0]] == 43 and e.peak_bin[first[1]] == 43
    out = clipped_echo_sigma(e, first, img, g)
    assert out.sigma_m[first[0]] == e.sigma_m[first[0]]
    assert out.sigma_m[first[1]] == pytest.approx(np.hypot(e.sigma_m[first[1]],
                                                           (43 - e.edge_bin[first[1]]) * 0.02 / np.sqrt(12)))


def _clipped_gaussian_surface(seed: int, n_beams: int = 48, peak: float = 4.0, width: float = 4.0
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A surface sloped 0.5 bin per beam whose echo along range is a Gaussian of ``width`` bins
    and ``peak`` times full scale above the background (the pipeline measures the excess over it),
    16-look speckle, clipped at full scale (1); the truth is the unclipped echo's half-peak
    crossing per beam."""
    rng = np.random.default_rng(seed)
    centre = 120.0 + 0.5 * np.arange(n_beams) + 0.3
    r = np.arange(300, dtype=float)[:, None]
    env = peak * np.exp(-0.5 * ((r - centre[None, :]) / width) ** 2)
    img = np.minimum(env * rng.gamma(16.0, 1.0 / 16.0, env.shape), 1.0)
    return img, env > 0.25, centre - width * np.sqrt(2.0 * np.log(2.0))


def test_a_clipped_echo_is_measured_by_a_gaussian_fitted_to_its_flanks():
    """The first peak of a clipped echo is the clip level, below the echo's own: half of it is
    crossed early on the rise (here ~3.4 bins).  With the clip mask, the edge is the half-peak
    crossing of a Gaussian fitted to the unclipped flanks, inside the clipped run when the echo
    peaks above twice full scale; such returns are marked and keep their own sigma."""
    from sonarmap.ranges.measure import CLIP_LEVEL, clipped_echo_sigma

    g = _geom(n_bins=300, n_beams=48)
    naive, fitted = [], []
    for seed in range(3):
        img, mask, truth = _clipped_gaussian_surface(seed)
        e = find_echoes(mask, img, g)
        first = _first(e)
        ok = first >= 0
        s = np.maximum(first, 0)
        plain = pooled_edges(e, first, img, g)
        fit = pooled_edges(e, first, img, g, clip=img >= CLIP_LEVEL)
        naive.append(np.where(ok, plain.edge_bin[s], np.nan) - truth)
        fitted.append(np.where(ok, fit.edge_bin[s], np.nan) - truth)
        assert plain.clip_fitted is None
        assert fit.clip_fitted is not None and fit.clip_fitted[s[ok]].mean() > 0.8
        # a fitted edge is not given the clipped-peak interval's spread as well
        marked = first[ok][fit.clip_fitted[s[ok]]]
        out = clipped_echo_sigma(fit, first, img, g)
        assert np.array_equal(out.sigma_m[marked], fit.sigma_m[marked])
        assert np.all(fit.sigma_m[marked] < 2 * 0.02)  # within 2 bins
    en, ef = np.concatenate(naive), np.concatenate(fitted)
    assert np.nanmedian(en) < -2.5  # measured -3.4
    assert abs(np.nanmedian(ef)) < 0.5 and np.mean(np.abs(ef) <= 1) > 0.9


def test_the_fit_reaches_a_wide_echos_rising_flank_beyond_the_walk_window():
    """A wide clipped echo (Gaussian of 8 bins, 4 x full scale) rises from 5 % to half the clip
    level over ~7 bins: a fit limited to the half-peak walk's 6 bins in front of the alignment
    has too few rising samples (no fit: the edge stays ~6 bins early); ``fit_front_bins`` 16 fits
    every beam, and the fitted sigma scales with ``fit_sigma_scale``."""
    from sonarmap.ranges.measure import CLIP_LEVEL

    g = _geom(n_bins=300, n_beams=48)
    for seed in range(2):
        img, mask, truth = _clipped_gaussian_surface(seed, width=8.0)
        e = find_echoes(mask, img, g)
        first = _first(e)
        s = np.maximum(first, 0)
        ok = first >= 0
        err = {}
        for ff in (6, 16):
            out = pooled_edges(e, first, img, g, clip=img >= CLIP_LEVEL, fit_front_bins=ff, sigma_scale=5.0)
            err[ff] = out.edge_bin[s[ok]] - truth[ok]
        assert np.median(err[6]) < -4  # measured -6.1
        assert abs(np.median(err[16])) < 0.5 and np.mean(np.abs(err[16]) <= 1) > 0.9
        assert out.clip_fitted is not None and out.clip_fitted[s[ok]].all()
        wide = pooled_edges(e, first, img, g, clip=img >= CLIP_LEVEL, sigma_scale=5.0, fit_sigma_scale=10.0)
        assert np.array_equal(wide.edge_bin, out.edge_bin, equal_nan=True)
        assert np.all(wide.sigma_m[s[ok]] > out.sigma_m[s[ok]])
        # the fitted returns' calibration does not go through the pooled profile's
        alone = pooled_edges(e, first, img, g, clip=img >= CLIP_LEVEL, sigma_scale=0.0, fit_sigma_scale=10.0)
        assert np.array_equal(alone.sigma_m[s[ok]], wide.sigma_m[s[ok]])
    with pytest.raises(InputError, match="fit_sigma_scale"):
        pooled_edges(e, first, img, g, fit_sigma_scale=float("nan"))
    with pytest.raises(InputError, match="fit_front_bins"):
        pooled_edges(e, first, img, g, fit_front_bins=-1)


def test_an_unclipped_echo_is_not_refitted():
    g = _geom(n_bins=300, n_beams=48)
    img, mask, _ = _clipped_gaussian_surface(0, peak=0.4)  # below full scale everywhere
    assert img.max() < 1.0
    e = find_echoes(mask, img, g)
    first = _first(e)
    a = pooled_edges(e, first, img, g)
    b = pooled_edges(e, first, img, g, clip=img >= 1.0)
    assert np.array_equal(a.edge_bin, b.edge_bin, equal_nan=True) and b.clip_fitted is None


def test_a_clip_mask_of_another_shape_is_refused():
    g = _geom(n_bins=300, n_beams=48)
    img, mask, _ = _clipped_gaussian_surface(0)
    e = find_echoes(mask, img, g)
    with pytest.raises(InputError, match="clip"):
        pooled_edges(e, _first(e), img, g, clip=np.zeros((10, 48), dtype=bool))


def test_first_interval_runs_is_first_intervals_then_surface_runs() -> None:
    from sonarmap.ranges import _kernels

    rng = np.random.default_rng(5)
    for _ in range(300):
        n_e, m = int(rng.integers(1, 60)), int(rng.integers(1, 40))
        edge_bin = rng.random(n_e) * 100
        edge_bin[rng.random(n_e) < 0.1] = np.nan
        start = rng.integers(0, 100, n_e)
        stop = start + rng.integers(1, 20, n_e)
        sel = rng.integers(-1, n_e, m)
        touch = float(rng.choice([0.0, 1.0, 2.5]))
        edge, lo, hi, st = _kernels.first_intervals(sel, edge_bin, start, stop)
        got = _kernels.first_interval_runs(sel, edge_bin, start, stop, touch)
        assert np.array_equal(got[0], edge, equal_nan=True) and np.array_equal(got[1], st)
        assert np.array_equal(got[2], _kernels.surface_runs(edge, lo, hi, touch))


def test_forward_scan_finds_the_first_crossing_of_a_deep_echo_with_a_dip():
    """A deep echo whose front (bins 100-111, level 0.8) is followed by a dip (0.2) and its
    brightest part (1.0 from bin 117): half of the peak is first reached on the front. Scanning
    forward finds it there; walking back from the peak stops at the dip, behind the front (the
    real Oculus seabed on 6 beams of ping 0). Both agree on an echo without a dip."""
    g = _geom()
    env = np.zeros((g.n_bins, g.n_beams))
    env[100:112] = np.linspace(0.3, 0.8, 12)[:, None]
    env[112:117] = 0.2
    env[117:140] = 1.0
    img = env + 0.01
    mask = env > 0.1
    e = find_echoes(mask, img, g)
    first = _first(e)
    s = np.maximum(first, 0)
    fwd = pooled_edges(e, first, img, g, scan="forward").edge_bin[s]
    back = pooled_edges(e, first, img, g, scan="back").edge_bin[s]
    assert np.all(np.abs(fwd - 104.0) < 1.5), fwd  # 0.5 is reached at bin ~104.4 on the front
    assert np.all(back > 115.0), back
    plain = np.zeros_like(env)
    plain[100:140] = np.clip((np.arange(40) + 1) / 8.0, 0, 1)[:, None]
    e = find_echoes(plain > 0.1, plain + 0.01, g)
    first = _first(e)
    s = np.maximum(first, 0)
    np.testing.assert_allclose(pooled_edges(e, first, plain + 0.01, g, scan="forward").edge_bin[s],
                               pooled_edges(e, first, plain + 0.01, g, scan="back").edge_bin[s])
    with pytest.raises(InputError, match="scan"):
        pooled_edges(e, first, plain, g, scan="sideways")
    assert PipelineConfig().ranges.edge_pool_scan == "forward"
    with pytest.raises(ValueError, match="edge_pool_scan"):
        PipelineConfig().replace(edge_pool_scan="up")


@pytest.mark.parametrize("deep", ["first", "last"])
@pytest.mark.parametrize("with_clip", [False, True])
def test_the_profiles_are_computed_as_far_as_the_windows_read_them(monkeypatch: pytest.MonkeyPatch,
                                                                   with_clip: bool, deep: str) -> None:
    """The kernel computes each beam's profile and running sums only as far as the windows ending
    past it read them (_profile_needs): the same outputs as with every profile at the full width
    (the kernel run as Python with the full width), on a run whose first or last 6 beams echo 10x
    deeper than the others (the last: every beam before them is read at their depth)."""
    from sonarmap.ranges import _kernels

    rng = np.random.default_rng(3)
    n, m = 160, 24
    img = rng.exponential(0.05, (n, m))
    edge = 40.0 + rng.normal(0.0, 1.0, m)
    beams = np.arange(m)
    depth = np.where(beams < 6 if deep == "first" else (beams >= 14) & (beams < 20), 90.0, 9.0)
    for j in range(m):  # echoes rising to their end: the deep ones peak far behind their edge
        d = int(depth[j])
        img[int(edge[j]):int(edge[j]) + d, j] += np.linspace(0.3, 1.0, d)
    stop = edge + depth
    run = np.where(beams < 20, 0, 1).astype(np.int64)
    clip = ((img >= 1.02) if with_clip else np.zeros((0, 0), bool)).astype(np.float32)  # (as the pipeline's raw image)
    args = (img, edge, stop, run, 3, 8, 200, 3, 0.5, 2, clip, 1.0, 16, True, 6, 2, 0.0)
    got = _kernels.pooled_edges(*args)

    def full_width(run: np.ndarray, count: np.ndarray, depth: np.ndarray, half_beams: int, extra: int) -> np.ndarray:
        # the kernel's width, front + kmax + 1 + tail + 2 h, for every beam
        return np.full(run.size, extra + int(depth[count >= 3].max(initial=0)), np.int64)

    monkeypatch.setattr(_kernels, "_profile_needs", full_width)
    want = _kernels.pooled_edges.py_func(*args)
    for a, b in zip(got, want):
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes()


def test_a_profile_span_interpolates_as_each_bin_alone() -> None:
    """``_interp_span`` (exact sums read without converting each position) gives the bits of
    ``_interp_column`` at every offset: sums that round (crossing a power of two from just
    below it), fractions near 0 and 1, the clamped ends, positions below 1 and infinite rows (a
    NaN row is no position: ``_interp_column`` reads no defined sample)."""
    from sonarmap.ranges._kernels import _interp_column, _interp_span

    rng = np.random.default_rng(7)
    img = rng.random((700, 3))
    starts = (0.0, 1e-300, 0.3, 0.9999999999999999, 3.999999999999999, 12.25, 255.99999999999997,
              511.99999999999994, 300.1234567, 447.75, 650.5, 698.9999999999999, 699.0, 750.0, -3.5, np.inf,
              -np.inf, 2.0 ** 52, 1e300)
    for a in starts + tuple(rng.uniform(-20.0, 720.0, 40)):
        for off, n_out in ((-17, 230), (0, 5), (-300, 400), (3, 0)):
            out = np.full(n_out, -1.0)
            _interp_span(img, 1, a, off, out, n_out)
            want = np.array([_interp_column(img, 1, a + (k + off)) for k in range(n_out)])
            assert out.tobytes() == want.tobytes(), (a, off)


def test_the_clipped_profile_bins_come_from_the_listed_clipped_rows() -> None:
    """``_clipped_bins`` finds a beam's clipped profile bins from its column's clipped rows
    (``_clipped_rows``) without testing every bin: the same bins as testing every bin with
    ``_clipped_at``, also where ``a + (k + off)`` rounds up to the next row (sums crossing a power
    of two), in runs of clipped rows, at the first and last rows and for a non-finite ``a``."""
    from sonarmap.ranges._kernels import _clipped_at, _clipped_bins, _clipped_rows

    rng = np.random.default_rng(5)
    n = 1100
    clip = (rng.random((n, 8)) < 0.03).astype(np.float32)
    clip[:, 0] = 0
    clip[n - 1, 1] = 1  # only in the last row
    clip[0, 2] = 1      # only in the first row
    clip[500:530, 3] = 1  # a run
    clip[1020:1030, 4] = 1
    clip[:, 5] = rng.random(n) < 0.4  # dense: neighbouring clipped rows
    first, rows = _clipped_rows(clip, 1.0)
    for j in range(clip.shape[1]):
        np.testing.assert_array_equal(rows[first[j]:first[j + 1]], np.flatnonzero(clip[:, j] >= 1.0))
    starts = (-7.3, -0.5, 0.0, 3.999999999999999, 12.25, 38.5, 45.0, 511.99999999999994, 1023.9999999999999,
              1007.9999999999999, 495.99999999999994, 1098.5, np.nan, np.inf)
    for j in range(clip.shape[1]):
        col = rows[first[j]:first[j + 1]]
        for a in starts:
            for off, n_read in ((-5, 30), (-5, 0), (0, 1), (-2, 12), (-17, 200)):
                # (compiled: python's int() of a NaN row raises)
                want = [k for k in range(n_read) if _clipped_at(clip, 1.0, j, a + (k + off))]
                out = np.full(n_read + 3, -1, np.int64)
                end = _clipped_bins(clip, 1.0, j, col, a, off, n_read, out, 2)
                assert out[2:end].tolist() == want


def test_the_raw_image_and_its_level_clip_as_the_full_scale_mask() -> None:
    """The range stage hands the kernel the raw image (float32, as every ping's) and the full-scale
    level instead of the mask of its clipped samples: the same edges, values, fits and noise as
    with the mask, which ``pooled_edges`` passes as float32 samples 0 / 1 at the level 1 (one
    compiled specialisation of the kernel for both)."""
    from sonarmap.ranges import _kernels
    from sonarmap.ranges.echoes import _mask_as_samples
    from sonarmap.ranges.measure import _CLIP_LEVEL_F32, CLIP_LEVEL, full_scale_mask

    rng = np.random.default_rng(4)
    n, m = 160, 24
    img = rng.exponential(0.05, (n, m))
    edge = 40.0 + rng.normal(0.0, 1.0, m)
    for j in range(m):
        img[int(edge[j]):int(edge[j]) + 12, j] += np.r_[np.linspace(0.3, 1.4, 6), np.linspace(1.4, 0.3, 6)]
    stop = edge + 12.0
    run = np.zeros(m, np.int64)
    raw = np.minimum(img, 1.0).astype(np.float32)
    raw[int(edge[3]) + 5, 3] = _CLIP_LEVEL_F32  # at the level
    raw[int(edge[4]) + 5, 4] = np.nextafter(_CLIP_LEVEL_F32, np.float32(0))  # just below it
    mask = full_scale_mask(raw)
    assert mask.any() and mask[int(edge[3]) + 5, 3] and not mask[int(edge[4]) + 5, 4]
    common = (img, edge, stop, run, 3, 8, 200, 3, 0.5, 2)
    want = _kernels.pooled_edges(*common, _mask_as_samples(mask), 1.0, 16, True, 6, 2, 0.0)
    got = _kernels.pooled_edges(*common, raw, CLIP_LEVEL, 16, True, 6, 2, 0.0)
    assert want[5].any()
    for a, b in zip(got, want):
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes()


def test_the_simulated_didson_hull_under_fish_keeps_its_fan_edge_edges() -> None:
    """The simulated DIDSON hull under fish (seed 0, the preset's noise floor): on its fan-edge
    beams 0-17 the classifier labels only the grazing echo's core, 6-8 bins behind its rise.  The
    default guard (pulse + 12 bins) keeps the pooled edges found on the rise (median -0.32 bins
    from the surface); a guard of 2 bins drops them for the single-look edges (median +8.09)."""
    from sonarmap.evaluate.segmentation import preset_sim_configs
    from sonarmap.geometry import preset
    from sonarmap.pipeline import process_ping
    from sonarmap.simulate import scene_from_name, simulate_ping

    g = preset("didson-hf")
    sc = preset_sim_configs(g, (0.0,))[0]
    sim = simulate_ping(scene_from_name("fish_over_hull", geometry=g), g, config=sc, seed=0, recording_meta=True)
    truth = (sim.surface_range_m[:18] - g.range_m[0]) / g.range_resolution_m
    err = {}
    for lead in (12, 2):
        r = process_ping(sim.ping, PipelineConfig().replace(edge_pool_lead_bins=lead)).ranges
        e = (np.asarray(r.range_m[:18]) - g.range_m[0]) / g.range_resolution_m - truth
        assert np.isfinite(e).sum() >= 14  # measured 16
        err[lead] = float(np.nanmedian(e))
    assert abs(err[12]) <= 1.0  # measured -0.32
    assert err[2] >= 5.0  # measured +8.09


def test_the_sloped_median_is_the_own_beams_value_on_the_robust_line() -> None:
    """``_sloped_median``: on edges along a line with noise and an outlier it gives the window's
    own beam's value on the Theil-Sen line (the noise averaged out), where the plain median of a
    monotone slope is the own beam's noisy edge; a slope under half of ``min_slope`` (or
    ``min_slope = 0``) keeps the plain median, one between half and all of it follows a share of
    the slope."""
    from sonarmap.ranges._kernels import _sloped_median

    offs = np.arange(-3.0, 4.0)
    noise = np.array([0.4, -0.3, 0.2, 0.9, -0.2, 0.1, -0.4])
    edges = 50.0 + 4.0 * offs + noise
    edges[1] += 15.0  # an outlier
    work = np.empty(21)
    got = _sloped_median(edges.copy(), offs, 7, work, 1.0)
    assert abs(got - 50.0) < 0.45  # the own beam's edge is 50.9
    plain = float(np.median(edges))  # 53.8: the outlier moved it up the slope
    assert _sloped_median(edges.copy(), offs, 7, work, 0.0) == pytest.approx(plain)
    assert _sloped_median(edges.copy(), offs, 7, work, 10.0) == pytest.approx(plain)  # under half of it
    # a slope of ~4 against min_slope 6: two thirds of it followed, between the two medians
    part = _sloped_median(edges.copy(), offs, 7, work, 6.0)
    assert got < part < plain
    flat = 50.0 + noise
    assert _sloped_median(flat.copy(), offs, 7, work, 1.0) == np.median(flat)


def test_following_the_slope_sharpens_the_pooled_edges_of_a_steep_surface() -> None:
    """Single-look speckled surfaces sloped 4 bins per beam: aligned on the plain running median
    (each beam's own noisy edge) the pooled profiles are smeared; along the window's slope
    (``min_slope = 2``) more edges lie within 1 and 3 bins of the truth.  On a flat surface the
    single-look edges' own scatter sometimes makes a window's slope look steep, and aligning along
    it costs a little (measured, 4 seeds: sloped within 3 bins 0.57 -> 0.88, within 1 bin 0.22 ->
    0.30; flat within 3 bins 0.83 -> 0.82, within 1 bin 0.33 -> 0.30)."""
    from sonarmap.ranges.echoes import POOL_FIT_FRONT_BINS, POOL_FRONT_BINS, POOL_MAX_BINS, POOL_N_ITER, _pooled

    g = _geom(n_bins=600)
    window = (3, POOL_FRONT_BINS, POOL_MAX_BINS, 3, POOL_N_ITER, POOL_FIT_FRONT_BINS)
    within: dict[tuple[float, float], tuple[float, float]] = {}
    for slope in (0.0, 4.0):
        truth = 60.0 + slope * np.arange(g.n_beams) + 0.3
        for min_slope in (0.0, 2.0):
            errs = []
            for seed in range(4):
                img, mask = _speckled_surface(seed, truth, n_bins=600)
                e = find_echoes(mask, img, g)
                first = _first(e)
                p = _pooled(e, first, img, g, 1, window, (0.5, 1.0), (1.0, 1.0), None, min_slope=min_slope)
                s = np.maximum(first, 0)
                errs.append(np.where(first >= 0, p.edge_bin[s], np.nan) - truth)
            x = np.concatenate(errs)
            x = x[np.isfinite(x)]
            within[slope, min_slope] = (float(np.mean(np.abs(x) <= 1)), float(np.mean(np.abs(x) <= 3)))
    assert within[4.0, 2.0][1] > within[4.0, 0.0][1] + 0.2
    assert within[4.0, 2.0][0] > within[4.0, 0.0][0] + 0.05
    assert within[0.0, 2.0][1] > within[0.0, 0.0][1] - 0.03


def test_the_public_pooled_edges_take_the_slope_following_and_the_jitter_floor() -> None:
    """``pooled_edges(min_slope=, jitter_floor=)`` gives what the range stage's call with the same
    options gives (the pipeline's ``edge_pool_follow_slope`` and ``sigma_pool_floor``), changes
    the edges of a steep surface and the sigmas, and refuses negative or non-finite values."""
    from sonarmap.ranges.echoes import POOL_FIT_FRONT_BINS, POOL_FRONT_BINS, POOL_MAX_BINS, POOL_N_ITER, _pooled

    g = _geom(n_bins=600)
    truth = 60.0 + 4.0 * np.arange(g.n_beams) + 0.3
    img, mask = _speckled_surface(1, truth, n_bins=600)
    e = find_echoes(mask, img, g)
    first = _first(e)
    window = (3, POOL_FRONT_BINS, POOL_MAX_BINS, 3, POOL_N_ITER, POOL_FIT_FRONT_BINS)
    plain = pooled_edges(e, first, img, g)
    both = pooled_edges(e, first, img, g, min_slope=2.0, jitter_floor=0.5)
    inner = _pooled(e, first, img, g, 1, window, (0.5, 1.0), (1.0, 1.0), None, min_slope=2.0, jitter_floor=0.5)
    np.testing.assert_array_equal(both.edge_bin, inner.edge_bin)
    np.testing.assert_array_equal(both.sigma_m, inner.sigma_m)
    sel = first[first >= 0]
    assert np.mean(both.edge_bin[sel] != plain.edge_bin[sel]) > 0.5
    floor_only = pooled_edges(e, first, img, g, jitter_floor=0.5)
    np.testing.assert_array_equal(floor_only.edge_bin, plain.edge_bin)  # (the floor moves sigmas only)
    assert np.all(floor_only.sigma_m[sel] >= plain.sigma_m[sel]) and np.any(floor_only.sigma_m[sel] > plain.sigma_m[sel])
    for key, bad in (("min_slope", -1.0), ("jitter_floor", float("nan")), ("min_slope", float("inf"))):
        with pytest.raises(InputError, match=key):
            pooled_edges(e, first, img, g, **{key: bad})
