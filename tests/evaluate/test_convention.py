"""The range convention read on recorded echoes aligned on the truth (sonarmap.evaluate.convention)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sonarmap import preset
from sonarmap.errors import InputError
from sonarmap.evaluate.convention import RECORDED_FRONT_BINS, _crossing, recorded_edges_bins
from sonarmap.evaluate.segmentation import _simulate_seeds, preset_sim_configs


def _truth_bins(sim) -> np.ndarray:
    g = sim.ping.geometry
    return np.interp(sim.surface_range_m, g.range_m, np.arange(g.n_bins, dtype=np.float64))


def test_crossing_is_the_half_peak_crossing_behind_the_front_third():
    """A step echo starting at profile index 30 (offset +12 from the truth row at 18): its half-peak
    crossing is read between the two samples around it, a bump in the front third does not count."""
    y = np.zeros(RECORDED_FRONT_BINS + 49)
    y[:3] = 5.0                         # in the front third: ignored
    y[29], y[30:] = 0.25, 1.0           # 0.5 crossed halfway between 29 and 30
    assert _crossing(y, 0.5) == pytest.approx(29 + (0.5 - 0.25) / 0.75)
    assert math.isnan(_crossing(np.zeros_like(y), 0.5))


def test_without_speckle_the_recorded_edges_lie_on_the_surface():
    g = preset("didson-hf")
    quiet = dataclasses.replace(preset_sim_configs(g, (0.0,))[0], speckle=False)
    sim, _ = _simulate_seeds("curved_hull", g, quiet, [0], -3.0, True)[0]
    truth = _truth_bins(sim)
    for half in (0, 3):
        e = recorded_edges_bins(sim, half_beams=half)
        assert np.isfinite(e[np.isfinite(truth)]).all() and np.isnan(e[np.isnan(truth)]).all()
        assert np.nanmax(np.abs(e - truth)) < 0.6


def test_pooling_aligned_beams_narrows_the_recorded_edges_spread():
    """On speckled DIDSON hull pings one beam's recorded half-peak crossing scatters over bins
    (measured within 1 bin of the truth on 0.26 of the beams of seeds 0-1); averaging 21 beams
    aligned on the truth narrows it (0.53), but not to the noise-free echo's ~0.99."""
    g = preset("didson-hf")
    errs: dict[int, list[np.ndarray]] = {0: [], 10: []}
    for sim, _ in _simulate_seeds("hull", g, preset_sim_configs(g, (0.0,))[0], [0, 1], -3.0, True):
        truth = _truth_bins(sim)
        for half in errs:
            errs[half].append((recorded_edges_bins(sim, half_beams=half) - truth)[np.isfinite(truth)])
    w1 = {h: float(np.mean(np.abs(np.concatenate(v)) <= 1.0)) for h, v in errs.items()}
    assert w1[0] < 0.55 and w1[0] + 0.15 < w1[10] < 0.9


def test_bad_arguments_are_refused():
    g = preset("didson-hf")
    sim, _ = _simulate_seeds("hull", g, preset_sim_configs(g, (0.0,))[0], [0], -3.0, True)[0]
    for kw, word in (({"half_beams": -1}, "half_beams"), ({"half_beams": 1.5}, "half_beams"),
                     ({"fraction": 1.0}, "fraction"), ({"pulse_bins": 0}, "pulse_bins")):
        with pytest.raises(InputError, match=word):
            recorded_edges_bins(sim, **kw)
    with pytest.raises(InputError, match="surface_range_m"):
        recorded_edges_bins(dataclasses.replace(sim, surface_range_m=None))


def test_evaluate_ranges_scores_the_recorded_convention_rows():
    """``evaluate_ranges(recorded=True)``: three rows per preset (1, 7, 21 beams), scored on the
    scenes without fish, shown only when asked for."""
    from sonarmap.evaluate import evaluate_ranges
    from sonarmap.evaluate.segmentation import RECORDED, main

    rep = evaluate_ranges(presets=("didson-hf",), scenes=("hull", "fish"), seeds=(0,), noise_steps_db=(0.0,),
                          recorded=True)
    rows = {r.method: r for r in rep.rows}
    hull = rows["didson-hf | hull"]
    for suffix in RECORDED.values():
        r = rows["didson-hf" + suffix]
        assert r.n_pings == 1 and r.n_struct_beams == hull.n_struct_beams
        assert not math.isfinite(r.false_return_rate)  # no detection threshold: not scored
        assert suffix not in rep.table(per_scene=True, noise_free=True, bound=True)
        assert f"| didson-hf{suffix} |" in rep.table(recorded=True)
    one, many = rows["didson-hf" + RECORDED[0]], rows["didson-hf" + RECORDED[10]]
    assert one.recall_1bin < many.recall_1bin
    with pytest.raises(SystemExit):
        main(["--recorded", "--help"])
