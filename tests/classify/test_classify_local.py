"""Local MAP lookup table (eq. 12-13) and thresholds."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.classify.local_map import local_map_labels, map_lookup_table
from sonarmap.classify.threshold import neyman_pearson_threshold, otsu_threshold, threshold_labels
from sonarmap.errors import InputError
from sonarmap.stats.mixture import MixtureFit, fit_mixture


def _fit(w_obj: float) -> MixtureFit:
    from sonarmap.stats.components import quantization_levels
    from sonarmap.stats.mixture import component_pmf_matrix

    lv = quantization_levels(256)
    w = np.array([0.6, 0.4 - w_obj, w_obj])
    P = component_pmf_matrix(("zero", "exponential", "rayleigh"), [(), (0.02,), (0.2,)], lv)
    counts = np.rint(1e6 * (w @ P))
    return fit_mixture(counts, method="em")


def test_lut_matches_bruteforce_posterior():
    f = _fit(0.05)
    lut = map_lookup_table(f)
    post = np.log(f.class_prior())[:, None] + f.class_log_pmf()
    assert np.array_equal(lut, np.argmax(post, axis=0))
    assert lut[0] == 0 and lut[-1] == 1 and lut[2] == 0
    img = f.levels[np.arange(256)].reshape(16, 16).astype(np.float32)
    assert np.array_equal(local_map_labels(img, f).ravel(), lut)


def test_zero_object_weight_is_all_background():
    f = _fit(0.0)
    assert f.class_prior()[1] < 0.002
    img = np.linspace(0, 1, 1000, dtype=np.float32).reshape(10, 100)
    lab = local_map_labels(img, f)
    assert lab.dtype == np.uint8
    if f.class_prior()[1] == 0:
        assert lab.max() == 0


def test_thresholds():
    img = np.array([[0.1, 0.5, 0.9]], np.float32)
    assert threshold_labels(img, 0.5).tolist() == [[0, 1, 1]]
    rng = np.random.default_rng(0)
    two = np.concatenate([rng.normal(0.2, 0.02, 500), rng.normal(0.8, 0.02, 500)]).reshape(10, 100)
    t_otsu = otsu_threshold(two)
    assert threshold_labels(two, t_otsu).sum() == 500
    with pytest.raises(InputError):
        otsu_threshold(np.ones((3, 3)))
    f = _fit(0.05)
    t = neyman_pearson_threshold(f, 1e-3)
    pb = f.class_pmf()[0]
    assert pb[f.levels >= t].sum() <= 1e-3 < pb[f.levels >= t - 1 / 255].sum()
