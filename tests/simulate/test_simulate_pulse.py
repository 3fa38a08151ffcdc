"""The simulator's transmit pulse, main lobe and sub-bin surface truth (``docs/simulator.md``).

Noise-free renders (``speckle=False`` and a high full scale, so nothing clips) of small scenes:
the echo starts where the surface is and lasts the pulse, sub-bin moves of a surface move its
truth and its echo by the same fraction of a bin, the main lobe puts a halo in front of a sloped
surface, and the half-peak crossing of the clean echo lies on the truth.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.geometry import preset
from sonarmap.simulate import (
    Scene,
    SimulationConfig,
    View,
    channel_gain,
    planar_hull,
    plane_patch,
    point_target,
    rudder,
    scene_from_name,
    simulate_ping,
    write_simulation,
)
from sonarmap.simulate.render import (
    first_peak_crossing,
    leading_edges_m,
    measure_edge_rise,
    pulse_envelope,
)
from sonarmap.simulate.scene import sloped_hull_yaw_deg

GEOM = preset("didson-hf")
BIN = GEOM.range_resolution_m
#: noise-free, unclipped, no cross-beam pattern unless a test asks for one
CLEAN = SimulationConfig(speckle=False, full_scale_db=300.0)


def test_pulse_envelope_is_causal_with_raised_cosine_rise() -> None:
    x = np.linspace(-0.01, 0.05, 6001)
    e = pulse_envelope(x, 0.04, 0.01)
    assert np.all(e[x < 0] == 0) and np.all(e[x > 0.04] == 0)
    assert np.all(e[(x >= 0.01) & (x <= 0.03)] == 1.0)
    assert pulse_envelope([0.005], 0.04, 0.01)[0] == pytest.approx(0.5)  # half-way up the rise
    assert pulse_envelope([0.035], 0.04, 0.01)[0] == pytest.approx(0.5)
    up = (x >= 0) & (x <= 0.01)
    assert np.all(np.diff(e[up]) >= 0)
    # 10-90 % rise of a raised cosine: (acos(-0.8) - acos(0.8)) / pi = 0.59 of the rise length
    rise = x[up][np.argmax(e[up] >= 0.9)] - x[up][np.argmax(e[up] >= 0.1)]
    assert rise == pytest.approx(0.59 * 0.01, abs=2e-5)
    assert np.trapezoid(e, x) == pytest.approx(0.04 - 0.01, rel=1e-3)  # area L - R
    with pytest.raises(InputError, match="rise"):
        pulse_envelope(x, 0.01, 0.02)
    with pytest.raises(InputError, match="pulse_rise_m"):
        SimulationConfig(pulse_length_m=0.01, pulse_rise_m=0.02)
    with pytest.raises(InputError, match="pulse_length_m"):
        SimulationConfig(pulse_length_m=-1.0)
    assert SimulationConfig(pulse_length_m=0.02).pulse == (0.02, 0.01)
    assert SimulationConfig(pulse_length_m=0.02).leading_edge_delay_m == pytest.approx(0.01)


@pytest.mark.parametrize("frac", [0.1, 0.45, 0.8])
def test_point_echo_starts_at_the_target_and_integrates_the_envelope_over_each_bin(frac: float) -> None:
    """A point target at a sub-bin range: each bin holds the envelope's integral over the bin."""
    g = GEOM.replace(psf=None)
    length = 4.0 * BIN
    cfg = CLEAN.replace(pulse_length_m=length, beam_width_rad=0.0)
    i0 = 200
    r0 = float(g.range_m[i0] - 0.5 * BIN + frac * BIN)  # inside bin i0, `frac` of the way through it
    beam = 40
    res = simulate_ping(point_target(r0, float(g.azimuth_rad[beam]), ts_db=-50.0), g, config=cfg, seed=0)
    col = res.clean[:, beam].astype(np.float64) / channel_gain(g, cfg)  # energy per bin
    nz = np.flatnonzero(col)
    assert nz[0] == i0  # the echo starts in the target's own bin (causal) ...
    assert nz[-1] == int(np.floor(frac + 4.0)) + i0  # ... and ends one pulse length later
    edges = g.range_m[i0 - 1: i0 + 7] + 0.5 * BIN
    x = np.linspace(0.0, length, 40001)
    env = pulse_envelope(x, length)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (env[1:] + env[:-1]) * np.diff(x))])
    share = np.diff(np.interp(edges - r0, x, cum / cum[-1], left=0.0, right=1.0))
    np.testing.assert_allclose(col[i0: i0 + 7] / col.sum(), share, atol=2e-4)
    # energy is conserved: the same total as without a pulse
    flat = simulate_ping(point_target(r0, float(g.azimuth_rad[beam]), ts_db=-50.0), g,
                         config=cfg.replace(pulse_length_m=0.0), seed=0)
    assert col.sum() == pytest.approx(float((flat.clean[:, beam] / channel_gain(g, cfg)).sum()), rel=1e-5)


def _facing_plate(range_m: float) -> object:
    """A small plate facing the sonar across the centre beams (a thin, flat echo)."""
    return plane_patch([range_m, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], u_extent_m=(-0.15, 0.15),
                       v_extent_m=(-0.1, 0.1), spacing_m=0.006, reflectivity_db=-20.0, view=View())


@pytest.mark.parametrize("shift_bins", [0.5, 0.25])
def test_sub_bin_truth_and_echo_move_with_the_surface(shift_bins: float) -> None:
    """Moving a plate by a fraction of a bin moves its truth and its echo's leading edge by that
    fraction: neither is quantised to the bin grid."""
    r0 = float(GEOM.range_m[250]) + 0.1 * BIN
    a = simulate_ping(_facing_plate(r0), GEOM, config=CLEAN, seed=0)
    b = simulate_ping(_facing_plate(r0 + shift_bins * BIN), GEOM, config=CLEAN, seed=0)
    beams = np.flatnonzero(np.isfinite(a.surface_range_m) & np.isfinite(b.surface_range_m))
    assert beams.size >= 5
    d_truth = (b.surface_range_m - a.surface_range_m)[beams] / BIN
    assert np.abs(d_truth - shift_bins).max() < 0.05
    # the integer truth does not move by a fraction
    assert set(np.unique(b.first_return_bin[beams] - a.first_return_bin[beams])) <= {0, 1}
    # the echo's energy is split over the bins at sub-bin resolution: on a tilted plate (an edge
    # rising over a few bins) its half-peak crossing moves by the same fraction of a bin
    tilt = [plane_patch([x, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 1.0], u_extent_m=(-0.15, 0.15),
                        v_extent_m=(-0.15, 0.15), spacing_m=0.006, reflectivity_db=-20.0)
            for x in (r0, r0 + shift_bins * BIN)]
    ea, eb = (leading_edges_m(simulate_ping(t, GEOM, config=CLEAN, seed=0).clean, GEOM) for t in tilt)
    ok = np.isfinite(ea) & np.isfinite(eb)
    assert ok.sum() >= 5
    assert np.median(np.abs((eb - ea)[ok] / BIN - shift_bins)) < 0.1


def _front(scene_name: str, width_spacings: float, ref: np.ndarray) -> float:
    """Median over beams 30-59 of the clean echo 2-8 bins in front of ``ref`` (the truth, bins),
    relative to the beam's peak, rendered with a main lobe of ``width_spacings`` beam spacings."""
    g = GEOM.replace(psf=None)  # no ghosts: only the main lobe spreads across beams
    spacing = float(np.diff(g.azimuth_rad).mean())
    res = simulate_ping(scene_from_name(scene_name, geometry=g), g,
                        config=CLEAN.replace(beam_width_rad=width_spacings * spacing), seed=0)
    out = []
    for j in range(30, 60):
        if np.isfinite(ref[j]):
            col = res.clean[:, j].astype(np.float64)
            t = int(ref[j])
            out.append(col[t - 8: t - 2].sum() / col.max())
    return float(np.median(out))


@pytest.mark.slow
def test_main_lobe_puts_a_halo_in_front_of_a_sloped_surface() -> None:
    """On a sloped hull (4 bins/beam) the neighbouring beams, whose surface is nearer, light the
    ranges in front of a beam's own surface through the main lobe - the more, the wider the lobe;
    on the flat hull the neighbours' surface is at the same range, so nothing changes."""
    for name, sloped in (("hull_slope4", True), ("hull", False)):
        g = GEOM.replace(psf=None)
        ref = simulate_ping(scene_from_name(name, geometry=g), g, config=CLEAN, seed=0)
        truth = (ref.surface_range_m - g.range_m[0]) / BIN
        front = [_front(name, w, truth) for w in (0.0, 1.0, 2.0)]
        if sloped:
            assert front[1] > 1.1 * front[0] and front[2] > 2.0 * front[0], front
        else:
            assert front[1] == pytest.approx(front[0], rel=0.02) and front[2] == pytest.approx(front[0], rel=0.02)


@pytest.mark.parametrize("scene, tol", [("hull", 0.25), ("seafloor", 0.3), ("hull_slope4", 0.25),
                                        ("hull_slope8", 0.25)])
def test_clean_half_peak_crossing_lies_on_the_surface_truth(scene: str, tol: float) -> None:
    """The 0.5-of-first-peak crossing of the noise-free echo (DIDSON: 5 mm pulse, measured
    ghosts, main lobe) is within ``tol`` bins of ``surface_range_m`` (median over beams; measured
    -0.11 / -0.26 / -0.00 / -0.03 bins, docs/simulator.md)."""
    cfg = CLEAN.replace(beam_pattern="measured")
    res = simulate_ping(scene_from_name(scene), GEOM, config=cfg, seed=0)
    err = (leading_edges_m(res.clean, GEOM) - res.surface_range_m) / BIN
    ok = np.isfinite(err)
    assert ok.sum() >= 60
    assert abs(float(np.median(err[ok]))) < tol
    assert float(np.percentile(np.abs(err[ok]), 75)) < 2 * tol + 0.2


def test_leading_edge_lags_by_half_the_pulse() -> None:
    """A causal pulse delays the half-peak crossing of a surface's echo by half its length."""
    scene = scene_from_name("hull")
    cross = []
    for length in (0.0, 2.0 * BIN):
        res = simulate_ping(scene, GEOM, config=CLEAN.replace(pulse_length_m=length), seed=0)
        cross.append(leading_edges_m(res.clean, GEOM))
    lag = np.nanmedian(cross[1] - cross[0]) / BIN
    assert lag == pytest.approx(SimulationConfig(pulse_length_m=2.0 * BIN).leading_edge_delay_m / BIN, abs=0.1)


def test_surface_truth_beams_match_first_return_and_further_surfaces() -> None:
    for name in ("propeller", "fish_over_hull", "seafloor"):
        res = simulate_ping(scene_from_name(name, 0), GEOM, seed=0)
        assert np.array_equal(np.isfinite(res.surface_range_m), res.first_return_bin >= 0), name
        ok = res.first_return_bin >= 0
        # the footprint truth lies behind the (skirt-inclusive) integer first return
        assert np.all(res.surface_range_m[ok] >= res.first_return_range_m[ok] - BIN), name
    # a rudder in front of a hull: the hull is the further surface on the rudder's beams
    scene = Scene.concat(rudder(range_m=5.0, yaw_deg=0.0), planar_hull(7.0))
    res = simulate_ping(scene, GEOM, seed=0)
    assert res.surface_ranges_m.ndim == 2 and res.surface_ranges_m.shape[1] == GEOM.n_beams
    assert res.surface_ranges_m.shape[0] >= 1
    behind = np.isfinite(res.surface_ranges_m[0])
    assert behind.sum() >= 5
    assert np.all(res.surface_range_m[behind] < 5.2) and np.all(res.surface_ranges_m[0][behind] > 6.5)
    empty = simulate_ping(scene_from_name("empty"), GEOM, seed=0)
    assert np.isnan(empty.surface_range_m).all() and empty.surface_ranges_m.shape == (0, GEOM.n_beams)


def test_truth_json_holds_surface_range(tmp_path: Path) -> None:
    res = simulate_ping(scene_from_name("hull_slope2"), GEOM, seed=1)
    files = write_simulation(res, tmp_path, "s")
    info = json.loads(files.truth_json.read_text())
    got = np.array([np.nan if v is None else v for v in info["surface_range_m"]])
    np.testing.assert_allclose(got, res.surface_range_m, equal_nan=True)
    assert len(info["surface_ranges_m"]) == res.surface_ranges_m.shape[0]
    assert info["config"]["pulse_length_m"] == res.config.pulse_length_m


@pytest.mark.parametrize("bins", [2.0, 4.0, 8.0])
def test_sloped_hull_scenes_slope_as_named(bins: float) -> None:
    g = preset("aris3000-128")
    res = simulate_ping(scene_from_name(f"hull_slope{bins:g}", geometry=g), g,
                        config=SimulationConfig(speckle=False), seed=0)
    c = int(np.argmin(np.abs(g.azimuth_rad)))
    slope = np.median(np.abs(np.diff(res.surface_range_m[c - 3: c + 3]))) / g.range_resolution_m
    assert slope == pytest.approx(bins, rel=0.1)
    assert sloped_hull_yaw_deg(0.0, g) == 0.0
    assert 0 < sloped_hull_yaw_deg(2.0) < sloped_hull_yaw_deg(8.0) < 90


def test_first_peak_crossing_and_edge_rise_helpers() -> None:
    assert first_peak_crossing([0.0, 0.0, 0.2, 0.6, 1.0, 0.7, 0.9]) == pytest.approx(2.75)
    # a speck in front below half of the maximum is not the first peak
    assert first_peak_crossing([0.0, 0.3, 0.0, 0.0, 1.0, 1.0]) == pytest.approx(3.5)
    assert math.isnan(first_peak_crossing(np.zeros(5)))
    # the edge-rise measurement sees a longer pulse as a longer rise (noise-free, two pulses)
    g = GEOM.replace(psf=None)
    scene = plane_patch([6.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], u_extent_m=(-0.8, 0.8),
                        v_extent_m=(-0.1, 0.1), reflectivity_db=-20.0)
    rises = []
    for length in (0.0, 8.0 * BIN):
        res = simulate_ping(scene, g, config=CLEAN.replace(pulse_length_m=length), seed=0)
        img = res.clean / res.clean.max() + 1e-3
        rises.append(measure_edge_rise([img], g, min_range_m=5.0, max_range_m=7.0).rise_bins)
    assert rises[0] < 1.5 and rises[1] > rises[0] + 1.0
    with pytest.raises(InputError, match="leading edge"):
        measure_edge_rise([np.zeros(g.shape)], g, min_range_m=5.0, max_range_m=7.0)


def test_recording_meta_declares_pulse_and_log_compression() -> None:
    g = preset("aris-telephoto-48")
    res = simulate_ping(scene_from_name("empty"), g, seed=0, recording_meta=True)
    meta = res.ping.meta
    assert meta["pulse_width_us"] == pytest.approx(2e6 * 0.009 / g.sound_speed_m_s)  # ARIS: 12 us
    assert meta["log_dynamic_range_db"] == res.config.dynamic_range_db == 37.0
    assert "log_dynamic_range_db" not in simulate_ping(scene_from_name("empty"), GEOM, seed=0,
                                                       recording_meta=True).ping.meta
    assert simulate_ping(scene_from_name("empty"), g, seed=0).ping.meta == {"simulated": "empty"}
