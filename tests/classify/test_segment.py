"""The classification stage (sonarmap.classify.segment): the public function is the default."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.classify.config import ClassifyConfig
from sonarmap.classify.segment import Segmentation, class_costs, decision_rates, level_costs, segment
from sonarmap.errors import InputError
from sonarmap.pipeline import PipelineConfig, process_ping
from sonarmap.stats.mixture import quantize
from sonarmap.stats.model import fit_levels


def _staged(pings):
    """(classifier image, fit, pipeline labels) of every ungated ping."""
    out = []
    for p in pings:
        pr = process_ping(p, keep_labels=True)
        if pr.fit is not None and not pr.gates and pr.floor_levels == 0:
            out.append((pr.image, pr.fit, pr.labels))
    assert out
    return out


@pytest.fixture(scope="module")
def staged(test_pings, aris_pings, oculus_pings):
    return _staged(test_pings) + _staged(aris_pings) + _staged(oculus_pings)


def test_segment_alone_reproduces_the_pipeline_labels_on_every_real_sonar(staged):
    for image, fit, labels in staged:
        seg = segment(image, fit)
        assert isinstance(seg, Segmentation) and seg.method == "mrf"
        np.testing.assert_array_equal(seg.labels, labels)
        # the fit is the one fit_levels gives (the pipeline's fit stage)
        np.testing.assert_allclose(fit_levels(quantize(image)).weights, fit.weights)


def test_segment_mrf_defaults_are_the_pipeline(staged):
    from sonarmap.classify.mrf import segment_mrf

    for image, fit, labels in staged[:12]:
        np.testing.assert_array_equal(segment_mrf(image, fit).labels, labels)


def test_methods_and_their_rates(test_pings):
    pr = process_ping(test_pings[4], keep_labels=True)
    image, fit = pr.image, pr.fit
    levels = quantize(image)
    from sonarmap.classify.local_map import map_lookup_table
    from sonarmap.classify.threshold import threshold_labels
    from sonarmap.stats.roc import pd_pfa_at_threshold

    m = segment(image, fit, ClassifyConfig(method="map"))
    np.testing.assert_array_equal(m.labels, map_lookup_table(fit)[levels])
    t = segment(image, fit, ClassifyConfig(method="threshold", threshold=0.4))
    np.testing.assert_array_equal(t.labels, threshold_labels(image, 0.4))
    assert (t.pd, t.pfa) == pd_pfa_at_threshold(fit, 0.4)
    c = segment(image, None, ClassifyConfig(method="cfar-ca", cfar_pfa=1e-3))
    assert np.isnan(c.pd) and c.pfa == 1e-3 and c.labels.any()
    mrf = segment(image, fit)
    assert (mrf.pd, mrf.pfa) == decision_rates(fit) and 0 < mrf.pfa < mrf.pd <= 1
    # the MRF's own unary decision (object prior raised) detects more than local MAP here
    assert mrf.pd >= m.pd
    assert segment(image, None).labels.sum() == 0 and decision_rates(None) == (0.0, 0.0)
    assert np.isnan(segment(image, None, ClassifyConfig(method="threshold")).pd)


def test_grow_hysteresis_keeps_faint_structure_connected_to_the_first_cut(test_pings):
    from sonarmap.classify.segment import _seeded_components
    from sonarmap.ranges import wide_components

    rng = np.random.default_rng(3)
    for _ in range(5):
        mask = rng.random((60, 40)) < 0.3
        seeds = mask & (rng.random((60, 40)) < 0.05)
        np.testing.assert_array_equal(_seeded_components(mask, seeds), wide_components(mask, 1, seeds=seeds))
    pr = process_ping(test_pings[4], keep_labels=True)
    base = segment(pr.image, pr.fit).labels
    grown = segment(pr.image, pr.fit, ClassifyConfig(grow_prior_min=0.45, grow_beta=0.5)).labels
    assert (grown >= base).all() and grown.sum() > base.sum()


def test_costs_are_the_unary_of_the_mrf_module(test_pings):
    from sonarmap.classify.mrf import unary_from_fit

    pr = process_ping(test_pings[4], keep_labels=True)
    levels = quantize(pr.image)
    u = unary_from_fit(pr.image, pr.fit)
    np.testing.assert_array_equal(u, class_costs(pr.fit).astype(np.float32)[:, levels])
    lc = level_costs(np.log([[0.5, 0.0], [0.5, 1.0]]))
    assert lc[0, 1] == 50.0 and lc[1, 1] == 0.0 and lc.min(axis=0).tolist() == [0.0, 0.0]
    raised = class_costs(pr.fit, object_prior_min=0.4)
    assert (raised[1] - raised[0] <= class_costs(pr.fit)[1] - class_costs(pr.fit)[0] + 1e-12).all()


def test_bad_arguments_are_refused(test_pings):
    pr = process_ping(test_pings[4], keep_labels=True)
    with pytest.raises(InputError, match="config: expected a ClassifyConfig"):
        segment(pr.image, pr.fit, PipelineConfig())  # type: ignore[arg-type]
    with pytest.raises(InputError, match="image: expected"):
        segment(pr.image[0], pr.fit)
    with pytest.raises(InputError, match="levels: shape"):
        segment(pr.image, pr.fit, levels=quantize(pr.image)[:10])
    with pytest.raises(InputError, match="class_log_pmf"):
        level_costs(np.zeros((1, 4)))
