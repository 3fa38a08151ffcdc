"""The Cramér-Rao bound of a leading edge (sonarmap.evaluate.bound)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.evaluate.bound import (
    _cell_intensities,
    _pooled_sd,
    attainable_recall,
    beam_correlation,
    censored_information,
    oracle_shifts,
    range_bound,
    shift_information,
)


def _echo(n: int, centre: float, width: float, level: float) -> np.ndarray:
    """A smooth echo (Gaussian in range) of peak ``level`` centred at ``centre`` bins."""
    r = np.arange(n, dtype=np.float64)
    return level * np.exp(-0.5 * ((r - centre) / width) ** 2)


def _loglik(samples: np.ndarray, mus: np.ndarray, looks: int, full_scale: float) -> np.ndarray:
    """Log-likelihood (up to terms free of mu) of each column of ``samples`` (n, cols) under each
    mean profile of ``mus`` (k, n): gamma speckle of ``looks`` looks, samples at or above
    ``full_scale`` censored there (one look only)."""
    from scipy.special import gammaincc

    mu = mus[:, :, None]
    x = samples[None, :, :]
    ll = -looks * (np.log(mu) + x / mu)
    if np.isfinite(full_scale):
        ll = np.where(x >= full_scale, np.log(gammaincc(looks, looks * full_scale / mu)), ll)
    return ll.sum(axis=1)  # (k, cols)


def _ml(samples: np.ndarray, profiles: np.ndarray, looks: int = 1, full_scale: float = np.inf) -> np.ndarray:
    """Index of the maximum-likelihood profile per column."""
    return _loglik(samples, profiles, looks, full_scale).argmax(axis=0)


def _draw(mu: np.ndarray, looks: int, cols: int, seed: int, full_scale: float = np.inf) -> np.ndarray:
    x = np.random.default_rng(seed).gamma(looks, 1.0 / looks, size=(mu.size, cols)) * mu[:, None]
    return np.minimum(x, full_scale)


N, CENTRE, WIDTH, BG = 48, 23.3, 3.0, 1.0
SHIFTS = np.arange(CENTRE - 3.0, CENTRE + 3.0, 0.02)


def _bound(level: float, looks: int = 1, full_scale: float = np.inf, level_known: bool = True) -> float:
    info = shift_information(_echo(N, CENTRE, WIDTH, level)[:, None], np.full(N, BG), looks,
                             full_scale=full_scale, level_known=level_known)
    return 1.0 / math.sqrt(info[0])


@pytest.mark.parametrize("looks", [1, 4])
def test_maximum_likelihood_reaches_the_bound_on_speckled_echoes(looks: int) -> None:
    # a bright echo 3 bins wide over a unit background, its level known: the ML estimate of its
    # position is efficient, so its spread over many speckle draws is the bound (and
    # 1/sqrt(looks) of the single-look one with looks)
    level = 30.0
    samples = _draw(_echo(N, CENTRE, WIDTH, level) + BG, looks, 1500, 1)
    est = SHIFTS[_ml(samples, np.stack([_echo(N, c, WIDTH, level) + BG for c in SHIFTS]), looks)]
    sd = _bound(level, looks)
    rms = float(np.sqrt(np.mean((est - CENTRE) ** 2)))
    assert abs(float(np.mean(est - CENTRE))) < 0.1 * sd + 0.01  # unbiased
    assert 0.9 * sd < rms < 1.15 * sd, (rms, sd)
    if looks == 4:
        assert sd == pytest.approx(_bound(level, 1) / 2.0)


def test_clipped_samples_carry_the_censored_information() -> None:
    # the same echo with its top above full scale: the censored likelihood's estimate reaches the
    # bound with clipping, which lies well above the unclipped one
    level, fs = 30.0, 4.0
    samples = _draw(_echo(N, CENTRE, WIDTH, level) + BG, 1, 1500, 2, full_scale=fs)
    est = SHIFTS[_ml(samples, np.stack([_echo(N, c, WIDTH, level) + BG for c in SHIFTS]), 1, fs)]
    sd = _bound(level, full_scale=fs)
    assert sd > 1.25 * _bound(level)
    rms = float(np.sqrt(np.mean((est - CENTRE) ** 2)))
    assert 0.9 * sd < rms < 1.15 * sd, (rms, sd)


def test_with_the_level_unknown_maximum_likelihood_still_reaches_the_bound() -> None:
    # position and level estimated together (ML over a grid of both): the position's spread is
    # the bound with the level unknown (on a symmetric echo the level and the position are
    # orthogonal: it costs nothing)
    level = 12.0
    samples = _draw(_echo(N, CENTRE, WIDTH, level) + BG, 1, 500, 3)
    levels = np.arange(0.8, 1.2, 0.02) * level
    shifts = np.arange(CENTRE - 2.0, CENTRE + 2.0, 0.04)
    profiles = np.stack([_echo(N, c, WIDTH, a) + BG for a in levels for c in shifts])
    est = shifts[_ml(samples, profiles) % shifts.size]
    sd = _bound(level, level_known=False)
    assert sd == pytest.approx(_bound(level), rel=1e-6)
    rms = float(np.sqrt(np.mean((est - CENTRE) ** 2)))
    assert 0.9 * sd < rms < 1.2 * sd, (rms, sd, _bound(level))


def test_censored_information_matches_its_integral() -> None:
    from scipy import integrate, stats

    for looks in (1, 3, 6):
        f = stats.gamma(looks, scale=1.0 / looks)
        for t in (0.2, 1.0, 3.0):
            inner = integrate.quad(lambda u: looks**2 * (u - 1.0) ** 2 * f.pdf(u), 0.0, t)[0]
            want = inner + t * t * f.pdf(t) ** 2 / f.sf(t)
            assert float(censored_information(t, looks)) == pytest.approx(want, rel=1e-9)
    assert censored_information(np.inf, 4) == pytest.approx(4.0)
    with pytest.raises(InputError):
        censored_information(-1.0)
    with pytest.raises(InputError):
        censored_information(1.0, looks=0)


def test_shift_information_is_the_sum_of_the_squared_relative_slopes() -> None:
    echo = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [2.0, 0.0]])
    info = shift_information(echo, np.array([1.0, 1.0, 1.0, 1.0, 1.0]), level_known=True)
    assert info[0] == pytest.approx((0.5 / 1) ** 2 + (1.0 / 2) ** 2 + (0.5 / 3) ** 2)  # slopes .5, 1, .5 over mu 1, 2, 3
    assert info[1] == 0.0  # no echo: nothing to place
    # per-pixel background of the image's shape
    assert shift_information(echo, np.ones((5, 2)), level_known=True) == pytest.approx(info)
    # the level unknown: less (the rising flank tells both), never more
    assert 0 < shift_information(echo, np.ones(5))[0] < info[0]


@pytest.mark.parametrize("bad", [
    dict(echo=np.ones(5)),                              # not 2-D
    dict(background=np.ones(4)),                         # shape
    dict(background=np.zeros(5)),                        # not positive
    dict(echo=np.full((5, 1), np.nan)),                  # not finite
    dict(looks=0),
    dict(full_scale=0.0),
])
def test_shift_information_refuses_bad_input(bad: dict) -> None:
    args = dict(echo=np.ones((5, 1)), background=np.ones(5), looks=1) | bad
    with pytest.raises(InputError):
        shift_information(**args)


def test_attainable_recall_is_the_gaussian_mass_within_the_tolerance() -> None:
    assert attainable_recall([1.0], 1.0) == pytest.approx(0.6827, abs=1e-4)
    assert attainable_recall([1.0, np.nan, 0.5], 1.0) == pytest.approx((0.6827 + 0.9545) / 2, abs=1e-4)
    assert attainable_recall([np.inf, 0.0], 1.0) == 0.5  # no information: 0; exact: 1
    assert math.isnan(attainable_recall([np.nan], 1.0))
    with pytest.raises(InputError):
        attainable_recall([1.0], 0.0)
    with pytest.raises(InputError):
        attainable_recall([-1.0], 1.0)


def test_pooled_bound_is_the_line_through_the_beams_estimates() -> None:
    info = np.full(20, 4.0)  # one beam: sd 0.5
    free = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    sd = _pooled_sd(info, 3, free)
    assert sd[10] == pytest.approx(0.5 / math.sqrt(7))  # independent, equal: the mean's
    # at the fan's edge the line through beams 0-3 is extrapolated to beam 0: worse than 4 beams' mean
    x = np.arange(4.0)
    want = 0.5 * math.sqrt(1 / 4 + x.mean() ** 2 / ((x - x.mean()) ** 2).sum())
    assert sd[0] == pytest.approx(want)
    # correlated neighbours know less together; a beam without information is left out
    assert _pooled_sd(info, 3, np.array([1.0, 0.7, 0.3, 0.1, 0.0, 0.0, 0.0]))[10] > 1.5 * sd[10]
    gap = info.copy()
    gap[9] = 0.0
    assert _pooled_sd(gap, 3, free)[10] > sd[10]
    alone = np.zeros(20)
    alone[5] = 4.0
    out = _pooled_sd(alone, 3, free)
    assert out[5] == pytest.approx(0.5) and np.isinf(out[4]) and np.isinf(out[6])


def test_beam_correlation_is_the_simulated_speckles() -> None:
    # the Oculus-like fan's beams overlap: neighbouring beams' speckle on a bright hull is as
    # correlated as the main lobe's taps say (20 dB more headroom: no expected echo clipped, so
    # clean is the mean; the image's own 8-bit range still truncates a little)
    from sonarmap.evaluate.bound import _before_assist
    from sonarmap.evaluate.segmentation import preset_sim_configs
    from sonarmap.geometry import preset
    from sonarmap.simulate import scene_from_name, simulate_pings

    g = preset("oculus-m750d-like")
    cfg = preset_sim_configs(g, (0.0,))[0]
    want = beam_correlation(g, cfg, 2)
    cfg = dataclasses.replace(cfg, full_scale_db=cfg.full_scale_db + 20.0)
    got: dict[int, list[float]] = {1: [], 2: []}
    for sim in simulate_pings(scene_from_name("hull_slope2", geometry=g), g, config=cfg, seeds=range(2)):
        assert sim.config.receiver == "linear" and sim.config.threshold == 0.0
        assert float(sim.clean.max()) < 0.99 and "gain_assist_db" not in sim.ping.meta
        bg, _ = _before_assist(sim)
        z = sim.ping.image.astype(np.float64) / (sim.clean + bg) - 1.0
        ok = (sim.clean > 3 * bg) & (sim.ping.image < 0.99) & (sim.ping.image > 0.05)
        for d in got:
            both = ok[:, :-d] & ok[:, d:]
            got[d].append(np.corrcoef(z[:, :-d][both], z[:, d:][both])[0, 1])
    for d, v in got.items():
        assert float(np.mean(v)) == pytest.approx(want[d], abs=0.06), (d, v, want)
    assert want[1] > 0.7
    # no main lobe overlap to speak of on the telephoto lens; none without speckle
    tele = preset("aris-telephoto-48")
    assert beam_correlation(tele, preset_sim_configs(tele, (0.0,))[0], 2)[1] < 0.01
    assert beam_correlation(g, dataclasses.replace(cfg, speckle=False), 2).tolist() == [1.0, 0.0, 0.0]


def test_range_bound_of_a_simulated_hull() -> None:
    from sonarmap.geometry import preset
    from sonarmap.simulate import scene_from_name, simulate_ping

    g = preset("didson-hf")
    sim = simulate_ping(scene_from_name("hull", geometry=g), g, seed=0)
    b = range_bound(sim)
    has = np.isfinite(sim.surface_range_m)
    assert has.sum() > 50
    assert np.isfinite(b.sd_bins[has]).all() and np.isnan(b.sd_bins[~has]).all()
    # seven beams of one straight surface know its middle better than one beam (about sqrt(7))
    assert (b.pooled_sd_bins[has] < b.sd_bins[has]).all()
    ratio = np.median(b.sd_bins[has] / b.pooled_sd_bins[has])
    assert 2.0 < ratio < 3.0
    # a single beam of this speckled hull: within a bin or so, not hundredths
    assert 0.2 < np.median(b.sd_bins[has]) < 3.0
    assert range_bound(sim, pool_beams=0).pooled_sd_bins == pytest.approx(b.sd_bins, nan_ok=True)
    with pytest.raises(InputError, match="pool_beams"):
        range_bound(sim, pool_beams=-1)


def test_a_gain_assist_is_undone_before_the_bound() -> None:
    # the Oculus-like hull is received 9 dB quieter by the gain assist, SimResult.clean being the
    # echo before it: the bound takes the background of the same ping rendered without the assist
    # (reverberation and noise 9 dB up, the ring-down as it is) and full scale 9 dB up
    from sonarmap.evaluate.bound import _before_assist
    from sonarmap.evaluate.segmentation import preset_sim_configs
    from sonarmap.geometry import preset
    from sonarmap.simulate import background_mean_image, level_intensity, scene_from_name, simulate_ping

    g = preset("oculus-m750d-like")
    cfg = preset_sim_configs(g, (0.0,))[0]
    scene = scene_from_name("hull", geometry=g)
    assisted = simulate_ping(scene, g, config=cfg, seed=0)
    assist_db = assisted.ping.meta.get("gain_assist_db", 0.0)
    assert assist_db > 0 and assisted.config.ring_down_level > 0
    plain = simulate_ping(scene, g, config=dataclasses.replace(cfg, gain_assist_saturation=0.0), seed=0)
    assert "gain_assist_db" not in plain.ping.meta
    assert np.array_equal(assisted.clean, plain.clean)
    bg, gain = _before_assist(assisted)
    fs = float(level_intensity(assisted.config, 1.0)) * gain  # full scale in clean's units
    assert bg == pytest.approx(background_mean_image(g, plain.config), rel=1e-12)
    assert fs == pytest.approx(float(level_intensity(plain.config, 1.0)) * 10.0 ** (assist_db / 10.0))
    # less clipping: the assisted ping's samples say more
    assert np.nanmedian(range_bound(assisted).sd_bins) < np.nanmedian(range_bound(plain).sd_bins)


@pytest.mark.parametrize("receiver", ["linear", "log"])
@pytest.mark.parametrize("quantization", ["floor", "round"])
def test_cell_intensities_invert_the_receiver(receiver: str, quantization: str) -> None:
    from sonarmap.simulate import SimulationConfig
    from sonarmap.simulate.render import _receive

    cfg = SimulationConfig(receiver=receiver, quantization=quantization, threshold=0.02, dynamic_range_db=40.0)
    rng = np.random.default_rng(0)
    intensity = rng.exponential(0.3, (100, 40)) * rng.choice([0.01, 0.1, 1.0, 3.0], (100, 40))
    lo, hi = _cell_intensities(_receive(intensity, cfg), cfg)
    assert ((intensity >= lo * (1 - 1e-9)) & (intensity < hi * (1 + 1e-9))).all()
    assert np.isinf(hi).any() and (lo == 0).any()  # clipped and thresholded samples: open cells


def test_a_detector_that_knows_the_echo_reaches_the_bound() -> None:
    # the maximum-likelihood shift of the known echo on the recorded 8-bit samples (threshold and
    # quantisation included) spreads as the bound says; 7 beams sharing it do far better
    from sonarmap.geometry import preset
    from sonarmap.simulate import scene_from_name, simulate_pings

    g = preset("didson-hf")
    ones, pooled, sds = [], [], []
    for sim in simulate_pings(scene_from_name("hull_slope4", geometry=g), g, seeds=range(3)):
        one, pool = oracle_shifts(sim)
        ones.append(one)
        pooled.append(pool)
        sd = range_bound(sim).sd_bins
        sds.append(sd[np.isfinite(sd)])
    rms = float(np.sqrt(np.mean(np.concatenate(ones) ** 2)))
    want = float(np.sqrt(np.mean(np.concatenate(sds) ** 2)))
    assert 0.85 * want < rms < 1.25 * want, (rms, want)
    assert float(np.sqrt(np.mean(np.concatenate(pooled) ** 2))) < 0.5 * rms
    with pytest.raises(InputError):
        oracle_shifts(sim, step_bins=0.0)


def test_evaluate_ranges_prints_the_bound_beside_the_scores(capsys: pytest.CaptureFixture[str]) -> None:
    from sonarmap.evaluate.segmentation import BOUND_BEAM, BOUND_POOLED, main

    assert main(["--ranges", "--bound", "--presets", "didson-hf", "--scenes", "hull_slope2,empty", "--seeds", "1"]) == 0
    out = capsys.readouterr().out
    beam = next(line for line in out.splitlines() if line.startswith(f"| didson-hf{BOUND_BEAM} |"))
    pooled = next(line for line in out.splitlines() if line.startswith(f"| didson-hf{BOUND_POOLED} |"))
    w1_beam, w1_pooled = float(beam.split("|")[5]), float(pooled.split("|")[5])
    assert 0.5 < w1_beam <= w1_pooled <= 1.0
    # the empty scene has no surface: no bound row of its own; per-scene bound rows only with --per-scene
    assert "empty | bound" not in out and f"hull_slope2{BOUND_BEAM}" not in out
