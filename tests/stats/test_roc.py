"""ROC (eq. 15-16)."""

from __future__ import annotations

import numpy as np

from sonarmap.stats.roc import pd_pfa_at_threshold, roc_curve
from sonarmap.stats.components import quantization_levels
from sonarmap.stats.mixture import component_pmf_matrix, fit_mixture


def _fit(w_obj):
    lv = quantization_levels(256)
    P = component_pmf_matrix(("zero", "exponential", "rayleigh"), [(), (0.02,), (0.2,)], lv)
    return fit_mixture(np.rint(1e6 * (np.array([0.6, 0.4 - w_obj, w_obj]) @ P)), method="em")


def test_roc_monotone_auc_and_points():
    f = _fit(0.05)
    r = roc_curve(f)
    assert np.all(np.diff(r.pfa) >= -1e-15) and np.all(np.diff(r.pd) >= -1e-15)
    assert abs(r.pfa[-1] - 1) < 1e-9 and abs(r.pd[-1] - 1) < 1e-9
    assert 0.9 < r.auc <= 1.0
    pd, pfa = pd_pfa_at_threshold(f, 0.2)
    pb, po = f.class_pmf()
    assert np.isclose(pfa, pb[f.levels >= 0.2 - 1e-12].sum())
    assert np.isclose(pd, po[f.levels >= 0.2 - 1e-12].sum())
    assert np.isclose(r.pd_at_pfa(pfa), pd, atol=1e-6)
