"""Simulator-truth scoring, and the acceptance comparison of the default pipeline with baselines."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sonarmap.evaluate import PingScore, baseline_configs, evaluate, format_table, pool_scores, score_ping


def test_score_ping_counts():
    cm = np.zeros((10, 4), np.uint8)
    cm[5, :3] = 1          # structure on beams 0-2
    cm[2, 3] = 2           # clutter (fish) on beam 3
    labels = np.zeros_like(cm)
    labels[5, :2] = 1      # 2 true positives, 1 false negative
    labels[2, 3] = 1       # the fish labelled as structure: a false positive
    truth_bins = np.array([5, 5, 5, -1])
    truth_m = np.array([1.5, 1.5, 1.5, np.nan])
    rb = np.array([5, 9, -1, 2])
    rm = np.array([1.5, 1.9, np.nan, 1.2])
    s = score_ping(labels, rb, rm, cm, truth_bins, truth_m, tol_bins=3)
    assert (s.tp, s.fp, s.fn) == (2, 1, 1)
    assert (s.n_struct_beams, s.n_hit_beams, s.n_empty_beams, s.n_false_beams) == (3, 1, 1, 1)
    assert s.errors_m == pytest.approx((0.0, 0.4))
    m = pool_scores("x", [s, s])
    assert m.pixel_f1 == pytest.approx(2 * 4 / (2 * 4 + 2 + 2))
    assert m.recall == pytest.approx(1 / 3)
    assert m.false_return_rate == pytest.approx(1.0)
    assert m.median_error_m == pytest.approx(0.2)
    assert "| x | 2 |" in format_table([m])


def test_pool_of_nothing_is_nan():
    m = pool_scores("none", [PingScore(0, 0, 0, 0, 0, 0, 0, ())])
    assert math.isnan(m.recall) and math.isnan(m.false_return_rate) and math.isnan(m.pixel_f1)


@pytest.fixture(scope="module")
def acceptance_scores():
    cfgs = baseline_configs()
    keep = {k: v for k, v in cfgs.items() if "icm" not in k and "anneal" not in k}
    return {s.method: s for s in evaluate(
        keep, scenes=("hull", "curved_hull", "seafloor", "fish_over_hull", "fish", "empty"), seeds=(0, 1))}


def test_default_beats_baselines_on_recall_and_false_returns(acceptance_scores):
    best = acceptance_scores["default (mrf graphcut)"]
    assert best.recall > 0.8
    assert best.false_return_rate < 0.05
    for name, s in acceptance_scores.items():
        if name.startswith("default"):
            continue
        assert best.recall >= s.recall, name
        assert best.false_return_rate <= s.false_return_rate, name
        # "together": strictly better on at least one of the two
        assert best.recall > s.recall or best.false_return_rate < s.false_return_rate, name
