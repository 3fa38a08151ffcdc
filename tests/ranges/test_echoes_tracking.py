"""Echoes (leading edge, peak, sigma) and surface tracking across beams."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ranges import _kernels, ranges_from_tracks
from sonarmap.ranges.echoes import Echoes, find_echoes, range_sigma_m
from sonarmap.ranges.tracking import TrackConfig, Tracks, front_surfaces, track_surfaces, tracks_and_front


def _geom(n_bins: int = 200, n_beams: int = 16) -> SonarGeometry:
    return SonarGeometry(range_m=1.0 + 0.01 * np.arange(n_bins),
                         azimuth_rad=np.linspace(-0.2, 0.2, n_beams))


def test_leading_edge_is_the_interpolated_half_peak_crossing():
    g = _geom(n_beams=2)
    img = np.zeros(g.shape)
    # linear rise over bins 10..14 to a peak of 1 at bin 14, then a slow decay
    img[10:15, 0] = [0.2, 0.4, 0.6, 0.8, 1.0]
    img[15:20, 0] = [0.9, 0.8, 0.7, 0.6, 0.5]
    mask = img > 0.3
    e = find_echoes(mask, img, g)
    assert e.size == 1
    assert e.peak_bin[0] == 14
    # the peak's parabola through 0.8, 1.0, 0.9 tops at 1.0042; half of it lies between bin 11
    # (0.4) and bin 12 (0.6)
    top = 1.0 + 0.125 * 0.1**2 / 0.3
    assert e.peak_value[0] == pytest.approx(top)
    assert e.edge_bin[0] == pytest.approx(11 + (0.5 * top - 0.4) / 0.2)
    assert e.edge_range_m[0] == pytest.approx(1.0 + 0.01 * e.edge_bin[0])
    assert e.peak_range_m[0] == pytest.approx(1.14)
    # the walk may leave the mask (its first pixel is bin 11, the crossing before bin 12 is kept)
    assert e.start_bin[0] == 11


def test_edge_moves_with_a_sub_bin_shift_of_the_echo():
    g = _geom(n_beams=1)
    r = np.arange(g.n_bins, dtype=float)
    edges = []
    for shift in (0.0, 0.25, 0.5):
        img = np.exp(-0.5 * ((r - (60.0 + shift)) / 3.0) ** 2)[:, None]
        e = find_echoes(img > 0.1, img, g)
        edges.append(float(e.edge_bin[0]))
    # half maximum of a Gaussian of sigma 3 bins lies 3.53 bins before its centre
    assert np.asarray(edges) - np.array([60.0, 60.25, 60.5]) == pytest.approx(-3.53, abs=0.05)
    assert np.diff(edges) == pytest.approx([0.25, 0.25], abs=0.03)


def test_first_peak_skips_a_weak_halo_in_front():
    g = _geom(n_beams=1)
    img = np.zeros(g.shape)
    img[40:44, 0] = [0.1, 0.2, 0.25, 0.2]  # halo (a local maximum of 0.25)
    img[44:50, 0] = [0.3, 0.6, 1.0, 1.0, 0.8, 0.4]
    e = find_echoes(img > 0.05, img, g)
    assert e.size == 1 and e.peak_bin[0] == 46
    assert e.edge_bin[0] == pytest.approx(44 + (0.5 - 0.3) / 0.3)


def test_gaps_inside_an_echo_are_bridged_and_far_runs_are_separate():
    g = _geom(n_beams=1)
    m = np.zeros(g.shape, dtype=bool)
    m[[10, 11, 13, 14, 40, 41], 0] = True
    e = find_echoes(m, m.astype(float), g, max_gap=2)
    assert e.size == 2
    assert list(e.start_bin) == [10, 40] and list(e.stop_bin) == [15, 42]
    assert list(e.n_pixels) == [4, 2]


def test_sigma_grows_with_noise_and_shrinks_with_slope_and_looks():
    base = float(range_sigma_m(0.5, 0.25, 0.01)[()])
    assert base > 0.01 / np.sqrt(12)
    assert float(range_sigma_m(0.5, 0.5, 0.01)[()]) < base
    assert float(range_sigma_m(0.5, 0.25, 0.01, looks=9)[()]) < base
    assert float(range_sigma_m(0.5, 0.25, 0.01, background=0.5)[()]) > base
    assert float(range_sigma_m(0.0, 1e9, 0.01)[()]) == pytest.approx(0.01 / np.sqrt(12))


def test_find_echoes_rejects_bad_arguments():
    g = _geom()
    with pytest.raises(InputError, match="fraction"):
        find_echoes(np.zeros(g.shape, bool), np.zeros(g.shape), g, fraction=1.5)
    with pytest.raises(InputError, match="llr"):
        find_echoes(np.zeros(g.shape, bool), np.zeros(g.shape), g, llr=np.zeros((3, 3)))
    with pytest.raises(InputError):
        TrackConfig(segment_cost=-1)
    with pytest.raises(InputError):
        TrackConfig(n_surfaces=0)


def test_a_returns_intensity_is_its_echos_strength_in_either_mode():
    """The reported intensity is the image at the echo's first peak, not the sample on its rise
    where the leading edge lies (half the peak in expectation, 0 on a thresholded image)."""
    g = _geom(n_beams=12)
    img = np.zeros(g.shape)
    img[50:57, :] = np.array([0.0, 0.3, 0.6, 0.9, 1.0, 0.8, 0.4])[:, None] * np.linspace(0.5, 1.0, 12)
    llr = 3.0 * (img > 0)
    e = find_echoes(img > 0.2, img, g, llr=llr)
    t = track_surfaces(e, TrackConfig(segment_cost=30.0))
    first = ranges_from_tracks(e, t, g, img)
    strongest = ranges_from_tracks(e, t, g, img, mode="strongest")
    assert first.n_returns == 12
    assert np.all(first.bin <= 52) and np.all(strongest.bin == 54)
    np.testing.assert_array_equal(first.intensity, img[54].astype(np.float32))
    np.testing.assert_array_equal(first.intensity, strongest.intensity)


def _line_image(g: SonarGeometry, rows, width: int = 2, value: float = 1.0):
    img = np.zeros(g.shape)
    for j, r in enumerate(rows):
        if r >= 0:
            img[r:r + width, j] = value
    return img


def test_tracking_keeps_the_surface_and_drops_specks_and_a_short_blob():
    g = _geom(n_beams=40)
    rows = 100 + np.arange(40) // 4
    img = _line_image(g, rows)
    rng = np.random.default_rng(0)
    for _ in range(15):  # isolated specks anywhere
        img[rng.integers(0, 90), rng.integers(0, 40)] = 1.0
    img[60:62, 10:14] = 1.0  # a short blob in front of the surface on 4 beams
    llr = 3.0 * (img > 0)
    e = find_echoes(img > 0, img, g, llr=llr)
    t = track_surfaces(e, TrackConfig(segment_cost=30.0))
    br = ranges_from_tracks(e, t, g, img)
    assert br.n_returns == 40
    assert np.all(np.abs(br.bin - rows) <= 1)
    assert np.all(np.isfinite(br.sigma_m))


def test_faint_gaps_are_bridged_and_a_front_surface_is_reported_first():
    g = _geom(n_beams=40)
    rows = np.full(40, 120)
    rows[[15, 16]] = -1  # two faint beams inside the surface
    img = _line_image(g, rows)
    img[80:82, 5:35] = 1.0  # a second, nearer surface over 30 beams
    e = find_echoes(img > 0, img, g, llr=3.0 * (img > 0))
    t = track_surfaces(e, TrackConfig(segment_cost=30.0))
    br = ranges_from_tracks(e, t, g, img)
    assert np.all(br.bin[5:35] == 80)
    assert np.all(br.bin[:5] == 120) and np.all(br.bin[35:] == 120)
    # the surface behind is kept where both exist
    behind = br.other_range_m[0]
    on = np.r_[5:15, 17:35]
    assert np.allclose(behind[on], g.range_m[120] - 0.005, atol=1e-9)
    assert np.all(np.isnan(behind[[15, 16]]))


def test_a_surface_is_bridged_across_beams_a_stronger_echo_behind_took():
    # the near surface spans every beam; a short, strong echo behind it on beams 18-20 wins those
    # beams in the first pass, and the 3 near echoes left over cannot pay for a piece of their own
    g = _geom(n_beams=40)
    img = np.zeros(g.shape)
    llr = np.zeros(g.shape)
    img[100:102, :] = 1.0
    llr[100:102, :] = 3.0
    img[150:153, 18:21] = 1.0
    llr[150:153, 18:21] = 20.0
    e = find_echoes(img > 0, img, g, llr=llr)
    plain = ranges_from_tracks(e, track_surfaces(e, TrackConfig(segment_cost=30.0, bridge_beams=0)), g, img)
    assert np.all(plain.bin[18:21] == 150)
    br = ranges_from_tracks(e, track_surfaces(e, TrackConfig(segment_cost=30.0)), g, img)
    assert np.all(br.bin == 100)
    # the echo behind stays a further surface
    assert np.allclose(br.other_range_m[0][18:21], g.range_m[150] - 0.005, atol=1e-9)
    assert np.all(np.isnan(br.other_range_m[0][:18]))
    # a bridge longer than bridge_beams is not made
    short = ranges_from_tracks(e, track_surfaces(e, TrackConfig(segment_cost=30.0, bridge_beams=2)), g, img)
    assert np.all(short.bin[18:21] == 150)


def _near_surface_ends_behind_another() -> tuple:
    """A faint surface in front (rows 100-101) on beams 0-20, a strong one behind (rows 150-152) on
    beams 18-39: the passes give beams 18-20 to the one behind."""
    g = _geom(n_beams=40)
    img = np.zeros(g.shape)
    llr = np.zeros(g.shape)
    img[100:102, :21] = 1.0
    llr[100:102, :21] = 3.0
    img[150:153, 18:40] = 1.0
    llr[150:153, 18:40] = 20.0
    return g, img, find_echoes(img > 0, img, g, llr=llr)


def test_no_bridge_without_the_surface_on_the_other_side():
    # the near surface ends where the echo behind starts: nothing to bridge to
    g, img, e = _near_surface_ends_behind_another()
    a = ranges_from_tracks(e, track_surfaces(e, TrackConfig(segment_cost=30.0, bridge_beams=0)), g, img)
    b = ranges_from_tracks(e, track_surfaces(e, TrackConfig(segment_cost=30.0)), g, img)
    np.testing.assert_array_equal(a.bin, b.bin)


def _extension_case(n_chain: int = 3, chain_unary: float = -5.0, behind_on_chain: bool = True,
                    overlap: bool = False) -> tuple:
    """Echo tables of :func:`_kernels.extend_ends` over 6 beams: a tracked surface on beams
    ``n_chain``.. at bins 10-12, untracked echoes at bins 10-12 in front on beams 0..n_chain-1
    (cost ``chain_unary``), a tracked surface behind them at bins 30-32 (``behind_on_chain``); with
    ``overlap`` the surface behind reaches up to the front surface's interval on the beam next to
    it (the front surface goes on there)."""
    rows = []  # (beam, lo, hi, unary, tracked)
    for j in range(6):
        if j < n_chain:
            rows.append((j, 10, 12, chain_unary, False))
            if behind_on_chain:
                lo = 11 if (overlap and j == n_chain - 1) else 30
                rows.append((j, lo, 32, -50.0, True))
        else:
            rows.append((j, 10, 12, -50.0, True))
    beam = np.array([r[0] for r in rows], dtype=np.int64)
    lo = np.array([r[1] for r in rows], dtype=np.int64)
    hi = np.array([r[2] for r in rows], dtype=np.int64)
    unary = np.array([r[3] for r in rows])
    pos = lo.astype(np.float64)
    tracks = np.full((3, 6), -1, dtype=np.int64)
    for a, r in enumerate(rows):
        if r[4]:
            tracks[0, r[0]] = a
    first, count = _kernels.beam_index(beam, 6)
    return first, count, pos, lo, hi, unary, tracks


def test_end_extension_continues_a_surface_over_beams_a_surface_behind_took():
    # slope_bins, slope_cost, jump_bins, touch_bins, max_beams
    rules = (2.0, 1.0, 20.0, 1.0)
    case = _extension_case()
    chosen, hit = _kernels.extend_ends(*case, *rules, 4)
    assert hit
    np.testing.assert_array_equal(chosen, [0, 2, 4, -1, -1, -1])  # the front echoes of beams 0-2
    # longer than max_beams: none
    assert not _kernels.extend_ends(*case, *rules, 2)[1]
    # evidence that does not pay for the beam: no candidate
    assert not _kernels.extend_ends(*_extension_case(chain_unary=0.5), *rules, 4)[1]
    # a beam no other surface took: the passes had their chance there (an ordinary surface end)
    assert not _kernels.extend_ends(*_extension_case(behind_on_chain=False), *rules, 4)[1]
    # the front surface goes on next to the anchor (an echo touching its interval is tracked):
    # not where that surface ends
    assert not _kernels.extend_ends(*_extension_case(overlap=True), *rules, 4)[1]


def test_tracks_and_front_extends_a_surface_end_behind_which_another_took_beams():
    # the near surface (rows 100-101) spans beams 0-20, the strong one behind (150-152) beams
    # 18-39: the passes give 18-20 to the one behind, and the near echoes there are left over;
    # nothing comes back on the other side, so there is no bridge: the end extension reports them
    g, img, e = _near_surface_ends_behind_another()
    cfg = TrackConfig(segment_cost=30.0)
    tracks, fronted = tracks_and_front(e, cfg)
    assert np.all(ranges_from_tracks(e, tracks, g, img).bin[18:21] == 150)
    br = ranges_from_tracks(e, fronted, g, img)
    assert np.all(br.bin[:21] == 100) and np.all(br.bin[21:] == 150)
    np.testing.assert_allclose(br.other_range_m[0][18:21], g.range_m[150] - 0.005, atol=1e-9)
    off = ranges_from_tracks(e, tracks_and_front(e, TrackConfig(segment_cost=30.0, extend_beams=0))[1], g, img)
    assert np.all(off.bin[18:21] == 150)


def _front_and_behind(front_beams: slice):
    """A faint surface in front (rows 100-101) on ``front_beams``, a strong one behind (rows
    150-152) on beams 20-39."""
    g = _geom(n_beams=40)
    img = np.zeros(g.shape)
    llr = np.zeros(g.shape)
    img[100:102, front_beams] = 1.0
    llr[100:102, front_beams] = 3.0
    img[150:153, 20:40] = 1.0
    llr[150:153, 20:40] = 20.0
    return g, img, find_echoes(img > 0, img, g, llr=llr)


def test_front_pass_reports_a_surface_the_passes_left_behind_a_stronger_one():
    # one pass: the strong surface takes beams 20-39, the faint one in front keeps only 0-19;
    # its 20 echoes left over on 20-39 pay for a piece of their own (20 x 5 nats > 30)
    g, img, e = _front_and_behind(slice(0, 40))
    cfg = TrackConfig(segment_cost=30.0, n_surfaces=1, bridge_beams=0)
    t = track_surfaces(e, cfg)
    assert np.all(ranges_from_tracks(e, t, g, img).bin[20:] == 150)
    f = front_surfaces(e, t, cfg)
    br = ranges_from_tracks(e, f, g, img)
    assert np.all(br.bin == 100)
    # the beam already held n_surfaces (1): the surface behind drops off there
    assert f.echo.shape == (1, 40)
    # with two surfaces the one behind is kept
    cfg2 = TrackConfig(segment_cost=30.0, n_surfaces=2, bridge_beams=0)
    t2 = track_surfaces(e, cfg2)
    f2 = front_surfaces(e, t2, cfg2)
    np.testing.assert_array_equal(f2.echo, t2.echo)  # two passes track both: nothing to add
    assert np.all(ranges_from_tracks(e, f2, g, img).other_range_m[0][20:] == g.range_m[150] - 0.005)


def test_front_pass_keeps_nothing_that_cannot_pay_for_a_surface():
    # only 4 faint echoes in front of the strong surface (4 x 5 nats < 30): unchanged
    g, img, e = _front_and_behind(slice(22, 26))
    cfg = TrackConfig(segment_cost=30.0, n_surfaces=1, bridge_beams=0)
    t = track_surfaces(e, cfg)
    assert front_surfaces(e, t, cfg) is t
    # and echoes behind the return never move it
    g, img, e = _front_and_behind(slice(0, 20))
    t = track_surfaces(e, cfg)
    assert front_surfaces(e, t, cfg) is t
    with pytest.raises(InputError, match="tracks"):
        front_surfaces(e, Tracks(echo=t.echo[:, :10]), cfg)


def _front_on_subset(e: Echoes, t: Tracks, cfg: TrackConfig, pulse_bins: int) -> Tracks:
    """The front pass as a second tracking run over the eligible echoes' own arrays (the
    definition the fused kernel must reproduce bit for bit)."""
    from sonarmap.ranges import _kernels
    from sonarmap.ranges.tracking import _point_arguments

    lo, hi = e.intervals()
    tracked = np.zeros(e.size, dtype=bool)
    tracked[t.echo[t.echo >= 0]] = True
    nearest = t.first[e.beam]
    front = ~tracked & (nearest >= 0)
    front[front] = hi[front] < lo[nearest[front]]
    idx = np.flatnonzero(front)
    if idx.size == 0:
        return t
    args = list(_point_arguments(e, cfg, pulse_bins))
    if args[0]:
        args[1:6] = [np.ascontiguousarray(a[idx]) for a in args[1:5]] + [args[5]]
    chosen = _kernels.track_surfaces(
        e.beam[idx], e.n_beams, e.edge_bin[idx], lo[idx], hi[idx], cfg.beam_cost - e.evidence[idx], 1, cfg.max_gap,
        cfg.slope_bins, cfg.slope_cost, cfg.jump_bins, cfg.touch_bins, cfg.segment_cost, cfg.gap_cost, 0, 0, *args,
        False)[0][0]
    hit = chosen >= 0
    if not hit.any():
        return t
    out = t.echo.copy()
    out[1:, hit] = t.echo[:-1, hit]
    out[0, hit] = idx[chosen[hit]]
    return Tracks(echo=out)


@pytest.mark.parametrize("seed", range(6))
def test_front_pass_in_the_tracking_kernel_is_the_subset_pass(seed: int) -> None:
    # random layered surfaces, fish and speckle, with and without the point rule
    rng = np.random.default_rng(seed)
    n_beams = 48
    g = SonarGeometry(range_m=1.0 + 0.01 * np.arange(160), azimuth_rad=np.deg2rad(np.linspace(-6, 6, n_beams)),
                      azimuth_beamwidth_rad=np.deg2rad(0.6) if seed % 2 else None)
    img = np.zeros(g.shape)
    llr = np.zeros(g.shape)
    for _ in range(rng.integers(2, 6)):
        j0, j1 = sorted(rng.integers(0, n_beams, 2))
        r = rng.integers(10, 140) + np.cumsum(rng.integers(-2, 3, j1 - j0 + 1))
        for j, i in zip(range(j0, j1 + 1), np.clip(r, 2, 150)):
            img[i:i + rng.integers(1, 5), j] = rng.uniform(0.5, 3.0)
            llr[i:i + 4, j] = rng.uniform(1.0, 25.0)
    speck = rng.random(g.shape) < 0.02
    img[speck] = rng.uniform(0.3, 2.0, speck.sum())
    llr[speck] = rng.uniform(1.0, 8.0, speck.sum())
    e = find_echoes(img > 0, img, g, llr=llr)
    hits = 0
    for cfg in (TrackConfig(segment_cost=20.0, n_surfaces=1, bridge_beams=0), TrackConfig(segment_cost=10.0),
                TrackConfig(segment_cost=15.0, n_surfaces=2, point_fraction=0.3)):
        # the front pass alone (no end extensions) is the pass over the subset
        alone = dataclasses.replace(cfg, extend_beams=0)
        t, f = tracks_and_front(e, alone, 2)
        np.testing.assert_array_equal(t.echo, track_surfaces(e, cfg, 2).echo)
        ref = _front_on_subset(e, t, alone, 2)
        np.testing.assert_array_equal(f.echo, ref.echo)
        np.testing.assert_array_equal(front_surfaces(e, t, alone, 2).echo, ref.echo)
        assert (f is t) == (ref is t) == (front_surfaces(e, t, alone, 2) is t)
        hits += ref is not t
        # with the extensions the kernel and front_surfaces still agree
        t2, f2 = tracks_and_front(e, cfg, 2)
        np.testing.assert_array_equal(t2.echo, t.echo)
        np.testing.assert_array_equal(f2.echo, front_surfaces(e, t, cfg, 2).echo)
        assert (f2 is t2) == (front_surfaces(e, t, cfg, 2) is t)
    assert hits >= 1  # every seed gives the front pass something to keep in one configuration


def test_viterbi_is_exact_on_small_problems():
    from sonarmap.ranges import _kernels

    rng = np.random.default_rng(1)
    cfg = TrackConfig(segment_cost=5.0, beam_cost=0.0, slope_cost=1.0, slope_bins=1.0, gap_cost=1.0,
                      max_gap=1, jump_bins=6.0, touch_bins=2.0)
    for _ in range(40):
        m = 5
        count = rng.integers(0, 3, m).astype(np.int64)
        first = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64)
        n = int(count.sum())
        beam = np.repeat(np.arange(m), count).astype(np.int64)
        pos = np.sort(rng.uniform(0, 10, n))
        lo = np.floor(pos).astype(np.int64)
        hi = lo + rng.integers(0, 3, n)
        unary = rng.uniform(-6, 1, n)
        chosen = _kernels.viterbi_surfaces(first, count, beam, pos, lo, hi, unary, np.ones(n, bool), cfg.max_gap,
                                           cfg.slope_bins, cfg.slope_cost, cfg.jump_bins, cfg.touch_bins,
                                           cfg.segment_cost, cfg.gap_cost)
        # cost of the kernel's choice under the same model, and the exhaustive optimum
        got = _path_cost(chosen, pos, lo, hi, unary, cfg)
        assert got == pytest.approx(_optimum(first, count, pos, lo, hi, unary, cfg), abs=1e-9)


def _path_cost(chosen, pos, lo, hi, unary, cfg):
    cost = 0.0
    last_j, last_e = -100, -1
    for j, a in enumerate(chosen):
        if a < 0:
            continue
        cost += unary[a]
        g = j - last_j
        if last_e >= 0 and g <= cfg.max_gap + 1 and _linkable(a, last_e, g, pos, lo, hi, cfg):
            link = cfg.slope_cost * abs(pos[a] - pos[last_e]) / g / cfg.slope_bins + cfg.gap_cost * (g - 1)
            cost += min(link, cfg.segment_cost)
        else:
            cost += cfg.segment_cost
        last_j, last_e = j, a
    return cost


def _linkable(a, b, g, pos, lo, hi, cfg):
    d = abs(pos[a] - pos[b]) / g
    sep = max(lo[a] - hi[b], lo[b] - hi[a])
    return d <= cfg.jump_bins and sep <= cfg.touch_bins * g


def _optimum(first, count, pos, lo, hi, unary, cfg):
    m = first.size
    opts = [[-1] + list(range(first[j], first[j] + count[j])) for j in range(m)]
    return min(_path_cost(np.array(c), pos, lo, hi, unary, cfg) for c in itertools.product(*opts))


def test_echoes_per_beam_index():
    g = _geom(n_beams=3)
    m = np.zeros(g.shape, dtype=bool)
    m[[5, 50], 0] = True
    m[70, 2] = True
    e = find_echoes(m, m.astype(float), g)
    assert isinstance(e, Echoes)
    first, count = e.per_beam()
    assert list(count) == [2, 0, 1] and list(first) == [0, 2, 2]


def test_pipeline_config_track_table_round_trip():
    import tomllib

    from sonarmap.pipeline import PipelineConfig

    c = PipelineConfig().replace(track={"segment_cost": 80.0}, pulse_length_m=0.01, edge_scan="forward")
    assert c.ranges.track == TrackConfig(segment_cost=80.0)
    assert PipelineConfig.from_dict(c.to_dict()) == c
    t = tomllib.loads('[pipeline]\ntracker = "surface"\n[pipeline.track]\nsegment_cost = 90\n')
    assert PipelineConfig.from_dict(t).ranges.track.segment_cost == 90.0
    with pytest.raises(InputError, match="track: unknown key 'bogus'"):
        PipelineConfig().replace(track={"bogus": 1})
    with pytest.raises(InputError, match="tracker"):
        PipelineConfig().replace(tracker="viterbi")
    with pytest.raises(InputError, match="pulse_length_m"):
        PipelineConfig().replace(pulse_length_m=-1.0)


def test_real_pings_leading_edges_sigma_and_p_detect(test_pings, aris_pings):
    """The default's returns are leading edges behind the halo (real DIDSON ping 0's steep seafloor
    and ping 5's steep hull: the previous rules' first structure pixel lay 9.6 / 4.3 bins in front),
    each with a finite sigma and a p_detect in [0, 1]; on ARIS nothing before the target."""
    from sonarmap.pipeline import PipelineConfig, process_ping

    for k, min_shift in ((0, 5.0), (5, 2.0)):
        p = test_pings[k]
        new = process_ping(p).ranges
        old = process_ping(p, PipelineConfig().replace(tracker="rules")).ranges
        both = new.valid & old.valid
        assert both.sum() >= 25
        shift = np.median(new.range_m[both] - old.range_m[both]) / p.geometry.range_resolution_m
        assert shift >= min_shift, (k, shift)
        assert np.all(np.isfinite(new.sigma_m[new.valid])) and np.all(np.isnan(new.sigma_m[~new.valid]))
        assert np.all((new.p_detect >= 0) & (new.p_detect <= 1))
        # sigma: between a quarter of a bin and 8 bins
        sig = new.sigma_m[new.valid] / p.geometry.range_resolution_m
        assert sig.min() >= 0.25 and sig.max() <= 8.5
        # the intensity is the echo's strength: its first peak, not the (often thresholded) rise
        # where the edge lies (DIDSON test pings: 545 returns, 3 with 0 at their peak; 180 at the edge)
        assert np.count_nonzero(new.intensity[new.valid] > 0) >= 0.95 * new.n_returns
    for f in aris_pings[:2]:
        r = process_ping(f).ranges
        assert r.n_returns >= 40
        assert np.all(r.intensity[r.valid] > 0)
        # the target's nearest leading edge lies at ~15.4 m (frame 0, beams 37-39; smoothed along
        # the surface 15.40 m): nothing in the water column in front, more than 5 bins before it
        assert np.nanmin(r.range_m) > 15.35
        assert np.all(np.isfinite(r.sigma_m[r.valid]))


def test_smoothing_along_range_is_scipy_uniform_filter1d_bit_for_bit():
    """smooth_along_range's kernel reproduces scipy.ndimage.uniform_filter1d (mode "nearest") exactly."""
    from scipy.ndimage import uniform_filter1d

    from sonarmap.ranges.echoes import smooth_along_range

    rng = np.random.default_rng(0)
    for t in range(120):
        h, w, size = int(rng.integers(2, 90)), int(rng.integers(1, 30)), int(rng.integers(2, 12))
        img = rng.exponential(1.0, (h, w)).astype(np.float32) if t % 2 else rng.normal(0.0, 1e3, (h, w))
        ref = uniform_filter1d(np.asarray(img, dtype=np.float64), size=size, axis=0, mode="nearest")
        assert np.array_equal(ref.view(np.int64), smooth_along_range(img, size).view(np.int64))


def test_edge_sigma_kernel_is_the_numpy_formula_bit_for_bit():
    """edge_sigma_m (one kernel) gives the bits of its numpy formula, NaN and inf included."""
    from sonarmap.ranges.echoes import edge_sigma_m

    rng = np.random.default_rng(1)
    noise = rng.exponential(1.0, 5000) * 10 ** rng.uniform(-6, 3, 5000)
    slope = rng.normal(0.0, 1.0, 5000) * 10 ** rng.uniform(-14, 2, 5000)
    noise[::97], slope[::89], noise[::103], slope[::107] = np.nan, np.nan, np.inf, 0.0
    for bin_m, pulse_m, scale in ((0.01, 0.0, 1.5), (0.003, 0.012, 5.0)):
        s = np.maximum(slope, 1e-12)
        jitter = np.minimum(np.where(np.isnan(noise), np.inf, scale * noise / s), 8.0) * bin_m
        ref = np.sqrt(bin_m**2 / 12.0 + jitter**2 + (pulse_m**2) / 12.0)
        got = edge_sigma_m(noise, slope, bin_m, pulse_m=pulse_m, scale=scale)
        assert np.array_equal(ref.view(np.int64), got.view(np.int64))
def _fan(n_beams: int = 60, bw_deg: float | None = 0.5) -> SonarGeometry:
    """0.25 deg beams, a 0.5 deg (two-spacing) main lobe."""
    az = np.deg2rad(0.25 * (np.arange(n_beams) - n_beams / 2))
    return SonarGeometry(range_m=1.0 + 0.005 * np.arange(300), azimuth_rad=az,
                         azimuth_beamwidth_rad=None if bw_deg is None else np.deg2rad(bw_deg))


def _school_image(g: SonarGeometry) -> np.ndarray:
    """Five fish at different ranges side by side, each smeared over the beams by a Gaussian
    two-way lobe of 2 beam spacings (peak 30 x its weakest beam), with halos chaining them."""
    img = np.zeros(g.shape)
    for centre, r in ((8, 100), (15, 106), (22, 97), (29, 103), (36, 110)):
        for j in range(centre - 4, centre + 5):
            img[r:r + 2, j] = max(img[r, j], 30.0 * 2.0 ** (-((j - centre) / 2.0) ** 2 * 4))
    return img


def test_point_streaks_drop_a_fish_school_but_not_a_flat_surface():
    from sonarmap.ranges.tracking import point_streaks

    g = _fan()
    img = _school_image(g)
    mask = img > 0.5
    e = find_echoes(mask, img, g, llr=4.0 * mask)
    chosen = track_surfaces(e, TrackConfig(segment_cost=30.0, point_fraction=0.0)).first
    assert (chosen >= 0).sum() >= 20  # the tracker chains the school into pieces
    assert point_streaks(e, chosen)[chosen >= 0].all()
    assert not (track_surfaces(e, TrackConfig(segment_cost=30.0)).first >= 0).any()
    # without the geometry's beamwidth the rule is off
    e0 = find_echoes(mask, img, _fan(bw_deg=None), llr=4.0 * mask)
    assert e0.beamwidth_beams is None and not point_streaks(e0, chosen).any()
    # a flat, strong, thin surface of level echoes: far wider than a point of its strength
    flat = _line_image(g, np.full(g.n_beams, 150))
    e2 = find_echoes(flat > 0, flat, g, llr=4.0 * (flat > 0))
    c2 = track_surfaces(e2, TrackConfig(segment_cost=30.0)).first
    assert (c2 >= 0).all() and not point_streaks(e2, c2).any()
    with pytest.raises(InputError):
        point_streaks(e, chosen[:5])


def test_thin_curving_hull_line_survives_the_point_rule():
    # a DIDSON-like hull line: strong, thin (2 bins), speckled (single look), flat over runs of 6
    # beams with 3-bin steps between them - the steps are range jumps, so only the width of the
    # runs tells them from point streaks: 6 beams of level echoes, while a point of their
    # strength (peak / weakest < 3) spans 1.3 beamwidths
    rng = np.random.default_rng(3)
    r = 150 + 3 * (np.arange(96) // 6)
    img = np.zeros((300, 96))
    img[r, np.arange(96)] = rng.uniform(0.4, 1.0, 96)
    img[r + 1, np.arange(96)] = rng.uniform(0.4, 1.0, 96)
    mask = img > 0
    kept = []
    for bw in (0.3, 1.0, 5.0):
        e = find_echoes(mask, img, _fan(96, bw_deg=bw), llr=4.0 * mask)
        kept.append(track_surfaces(e, TrackConfig(segment_cost=30.0)).first)
    off = track_surfaces(e, TrackConfig(segment_cost=30.0, point_fraction=0.0)).first
    assert (off >= 0).sum() >= 90
    # the DIDSON's 0.3 deg beams, and a beam three times as wide: every return stays
    assert np.array_equal(kept[0], off) and np.array_equal(kept[1], off)
    assert not (kept[2] >= 0).any()  # 5 deg beams (20 spacings) could smear a point over each run


def test_real_didson_hull_lines_keep_every_return_with_a_beamwidth(test_pings):
    # the DIDSON sidecars do not give a beamwidth; with the sonar's 0.3 deg every return of the
    # 10 test pings stays where it was; with 1 deg (three times too wide) every beam keeps its
    # return, and nearly all stay within 2 bins (the smoothing across beams then spans 3.3x as
    # many beams; measured: 16 of the 518 returns of pings 4-9 move by 3-4 bins, at the fan's
    # ends of pings 4, 7, 8 and 9 and on ping 9's steep flanks)
    import dataclasses
    import warnings

    from sonarmap.pipeline import PipelineConfig, process_ping

    moved, n = 0, 0
    for p in test_pings[4:]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            base = process_ping(p, PipelineConfig()).ranges
            for deg in (0.3, 1.0):
                g = p.geometry.replace(azimuth_beamwidth_rad=np.deg2rad(deg))
                r = process_ping(dataclasses.replace(p, geometry=g), PipelineConfig()).ranges
                if deg == 0.3:
                    np.testing.assert_array_equal(r.bin, base.bin)
                else:
                    np.testing.assert_array_equal(r.bin >= 0, base.bin >= 0)
                    moved += int(np.sum(np.abs(r.bin - base.bin) > 2))
                    n += int(np.sum(base.bin >= 0))
    assert n > 500 and moved <= 0.04 * n


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_oculus_fish_school_gives_few_returns_on_empty_beams(seed):
    # a school of 40 fish on the Oculus-like preset: each fish is smeared over 5-10 beams by the
    # 0.55 deg (2.3-spacing) main lobe; 49-50 false returns per ping without the point rule
    import warnings

    from sonarmap.evaluate.segmentation import _simulate, preset_sim_configs
    from sonarmap.geometry import preset
    from sonarmap.pipeline import PipelineConfig, process_ping

    g = preset("oculus-m750d-like")
    sim, empty = _simulate("fish", g, preset_sim_configs(g)[0], seed, -3.0, recording_meta=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pr = process_ping(sim.ping, PipelineConfig())
    assert empty.sum() > 200
    assert int((pr.ranges.valid & empty).sum()) <= 0.03 * empty.sum()


def test_clipped_fish_streak_is_a_point_although_its_half_clip_edges_drift():
    # a fish clipped at full scale on 5 beams, pulse unknown (1 bin): the half-clip crossings of
    # its echoes drift by 2.5 bins across the streak (the stronger the echo over full scale, the
    # earlier half the clip level is crossed), which breaks it into flat runs without a range
    # jump between them; the unclipped echo's half-peak edge lies between each measured edge and
    # the echo's first full-scale row (104), and those intervals agree: one point
    from sonarmap.ranges.tracking import clip_rise, point_streaks

    g = _fan()
    img = np.zeros(g.shape)
    img[100:110, 10:15] = 1.0
    mask = img > 0
    e = find_echoes(mask, img, g, llr=4.0 * mask)
    assert e.size == 5
    e = e.replaced(edge_bin=np.array([100.2, 100.2, 101.5, 102.6, 102.7]), peak_value=np.full(5, 30.0),
                   clipped=np.ones(5, dtype=bool), peak_bin=np.full(5, 104))
    chosen = np.full(g.n_beams, -1)
    chosen[10:15] = np.arange(5)
    assert not point_streaks(e, chosen).any()  # the first full-scale row unknown: a rise of 0
    np.testing.assert_array_equal(clip_rise(e), np.zeros(5))
    e = e.replaced(clip_row=np.full(5, 104))
    np.testing.assert_allclose(clip_rise(e), [3.8, 3.8, 2.5, 1.4, 1.3])
    assert point_streaks(e, chosen)[10:15].all()
    # a full-scale row behind the first peak (a second fish in the echo) does not move the edge
    np.testing.assert_array_equal(clip_rise(e.replaced(peak_bin=np.full(5, 102))), np.zeros(5))
    # unclipped echoes at those edges are no point: their edges are where the echoes are
    assert not point_streaks(e.replaced(clipped=np.zeros(5, dtype=bool)), chosen).any()
    # nor is a clipped surface wider than the lobe lets a point be
    g40 = _fan(40)
    plate = np.zeros(g40.shape)
    plate[100:110] = 1.0
    e40 = find_echoes(plate > 0, plate, g40, llr=4.0 * (plate > 0))
    e40 = e40.replaced(clipped=np.ones(40, dtype=bool), clip_row=np.full(40, 104), peak_value=np.full(40, 30.0))
    assert not point_streaks(e40, np.arange(40)).any()


@pytest.mark.slow
def test_oculus_clipped_fish_without_a_recording_header_give_few_returns():
    # no header: the pulse length is unknown (1 bin) and the clipped fish's half-clip edges drift
    # by more than that across a streak; 14 false returns before the edges of clipped echoes were
    # taken as intervals up to their first full-scale row, 5 now (a piece whose echoes merge two
    # fish at different ranges)
    import warnings

    from sonarmap.evaluate.segmentation import _simulate, preset_sim_configs
    from sonarmap.geometry import preset
    from sonarmap.pipeline import PipelineConfig, process_ping

    g = preset("oculus-m750d-like")
    sim, empty = _simulate("fish", g, preset_sim_configs(g)[0], 0, -3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pr = process_ping(sim.ping, PipelineConfig())
    assert int((pr.ranges.valid & empty).sum()) <= 5


def test_dense_masks_give_the_echoes_of_the_column_walk() -> None:
    """A mask filling more than half its rows (walked along the rows, without gathering its pixels)
    gives the echoes of the walk down the columns (``find_echoes_in`` on every beam): gaps, ties,
    both edge scans.  The image is float64, as the range stage passes it (a float32 one would
    only compile a specialisation no caller uses)."""
    from sonarmap.ranges import _kernels

    rng = np.random.default_rng(3)
    for t in range(200):
        n, m = int(rng.integers(1, 50)), int(rng.integers(1, 30))
        r0 = int(rng.integers(0, n))
        r1 = int(rng.integers(r0 + 1, n + 1))
        mask = np.zeros((n, m), dtype=bool)
        mask[r0:r1] = rng.random((r1 - r0, m)) < rng.uniform(0.55, 1.0)
        img = rng.random((n, m))
        if t % 3 == 0:
            img = np.round(img * 4) / 4
        code = rng.integers(0, 8, (n, m)).astype(np.uint8)
        args = (mask, img, code, rng.random(8), np.zeros((1, 1), dtype=bool), 1.0, int(rng.integers(0, 4)),
                float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.2, 1.0)), int(rng.integers(0, 5)), bool(t % 4 == 1))
        got = _kernels.find_echoes(*args, r0, r1)
        expected = _kernels.find_echoes_in(*args, np.arange(m, dtype=np.int64), r0, r1)
        for g, e in zip(got, expected):
            assert g.dtype == e.dtype and g.tobytes() == e.tobytes()
