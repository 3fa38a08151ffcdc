"""Decisions are monotone in intensity: a brighter pixel is never less likely structure.

``MixtureFit.decision_log_pmf`` (``stats.mixture.monotone_object_log_pmf``) is what the MRF
unary, local MAP and the ranges' echo evidence use; the model (``class_log_pmf``) is unchanged.
"""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.classify.local_map import map_lookup_table
from sonarmap.classify.segment import class_costs, segment
from sonarmap.errors import InputError
from sonarmap.ranges.echoes import level_llr
from sonarmap.stats.mixture import fit_mixture, monotone_object_log_pmf


def test_a_rising_ratio_is_returned_bit_for_bit():
    x = np.linspace(0.0, 1.0, 64)
    bg = -x / 0.05
    obj = np.log(x + 1e-3) - x / 0.3  # ratio rises over [0, 1]
    lp = np.vstack([bg, obj])
    assert np.all(np.diff(obj - bg) > 0)
    out = monotone_object_log_pmf(lp)
    np.testing.assert_array_equal(out, lp)
    assert out is not lp


def test_a_falling_tail_is_raised_to_the_running_maximum():
    bg = np.array([-1.0, -2.0, -3.0, -4.0, -5.0, -6.0])
    obj = np.array([-5.0, -3.0, -2.0, -2.5, -5.0, -9.0])  # ratio -4, -1, 1, 1.5, 0, -3
    out = monotone_object_log_pmf(np.vstack([bg, obj]))
    np.testing.assert_array_equal(out[0], bg)
    ratio = out[1] - out[0]
    np.testing.assert_allclose(ratio, [-4.0, -1.0, 1.0, 1.5, 1.5, 1.5])
    np.testing.assert_array_equal(out[1, :4], obj[:4])  # untouched up to the peak


def test_every_object_class_is_made_monotone_and_impossible_levels_stay():
    bg = np.array([0.0, -1.0, -2.0, -np.inf, -np.inf])
    o1 = np.array([-3.0, -1.0, -4.0, -2.0, -np.inf])
    o2 = np.array([-np.inf, -0.5, -0.1, -9.0, -1.0])
    out = monotone_object_log_pmf(np.vstack([bg, o1, o2]))
    np.testing.assert_array_equal(out[1], [-3.0, -1.0, -2.0, -2.0, -np.inf])
    np.testing.assert_array_equal(out[2], [-np.inf, -0.5, -0.1, -9.0, -1.0])
    assert not np.isnan(out).any()


def test_bad_shapes_are_refused():
    with pytest.raises(InputError, match="class_log_pmf"):
        monotone_object_log_pmf(np.zeros(5))


@pytest.fixture(scope="module")
def light_tailed():
    """Exponential background, a gamma object of large shape (light tail: shape 20, mean 0.1, as
    ``sonarmap calibrate`` chooses a gamma of shape 7-9 for the real ARIS frames) and a patch of
    very bright echoes; the mixture at those parameters - the object pmf falls below the
    background's again in the upper levels."""
    rng = np.random.default_rng(3)
    img = rng.exponential(0.02, (400, 64))
    obj = rng.gamma(20.0, 0.005, (40, 64))
    img[200:240] = obj
    img[216:224, 10:22] = 0.95  # the brightest echoes of the ping
    img = np.clip(img, 0.0, 1.0).astype(np.float32)
    fit = fit_mixture(img, families=("exponential", "gamma"), method="em", zero_spike=False,
                      init=([0.9, 0.1], [(0.02,), (20.0, 0.005)]), max_iter=0)
    return img, fit


def test_the_raw_model_would_call_the_brightest_levels_background(light_tailed):
    _, fit = light_tailed
    lp = fit.class_log_pmf()
    ratio = lp[1] - lp[0]
    assert ratio[30] > 0 > ratio[100]  # the model's ratio falls below zero again: the defect guarded


def test_every_decision_calls_the_brightest_levels_structure(light_tailed):
    img, fit = light_tailed
    ratio = fit.decision_log_pmf()[1] - fit.decision_log_pmf()[0]
    assert np.all(np.diff(ratio) >= -1e-12)  # (bg + m) - bg rounds
    np.testing.assert_array_equal(fit.decision_log_pmf()[0], fit.class_log_pmf()[0])
    top = np.arange(ratio.size) >= 25
    cost = class_costs(fit, object_prior_min=0.2)  # the pipeline's prior floor
    assert np.all(cost[1, top] < cost[0, top])
    assert map_lookup_table(fit, eta=1.0)[top].all()
    llr = level_llr(fit)
    assert np.all(np.diff(llr[np.argmax(llr):]) >= -1e-12) and llr[-1] > 0
    labels = segment(img, fit).labels
    assert (labels[216:224, 10:22] >= 1).all()
