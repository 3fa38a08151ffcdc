"""The intensity-model stage (sonarmap.stats.model): fit of a level image and its gates."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.stats.config import FitConfig
from sonarmap.stats.mixture import fit_mixture, quantize
from sonarmap.stats.model import failed_gates, fit_counts, fit_levels


def test_fit_levels_is_the_fit_of_the_level_histogram(test_pings):
    from sonarmap.preprocess.pipeline import preprocess_image, recipe

    img = preprocess_image(test_pings[4].image, test_pings[4].geometry, recipe("paper-table1"))
    levels = quantize(img)
    fit = fit_levels(levels)
    ref = fit_mixture(np.bincount(levels.ravel(), minlength=256).astype(np.float64), families=("exponential", "rayleigh"),
                      method="em", n_levels=256, tol=FitConfig().fit_tol, accelerate=FitConfig().fit_accelerate)
    np.testing.assert_array_equal(fit.weights, ref.weights)
    # signed levels take the bincount route, same histogram
    np.testing.assert_array_equal(fit_levels(levels.astype(np.int32)).weights, fit.weights)
    assert failed_gates(fit) == frozenset()
    assert "kld" in failed_gates(fit, FitConfig(max_kld=1e-9))
    assert failed_gates(None) == frozenset()


def test_fit_counts_of_an_empty_histogram_is_none_and_bad_input_is_refused():
    assert fit_counts(np.zeros(256)) is None
    with pytest.raises(InputError, match="levels: expected integer"):
        fit_levels(np.zeros((4, 4)))
    with pytest.raises(InputError, match="config: expected a FitConfig"):
        fit_counts(np.ones(256), {"max_kld": 1})  # type: ignore[arg-type]


def test_level_counts_is_bincount():
    from sonarmap.stats._em_kernels import level_counts

    rng = np.random.default_rng(1)
    for shape in ((1, 1), (3, 5), (512, 96), (7, 13)):
        lev = rng.integers(0, 256, shape).astype(np.uint8)
        lev[rng.random(shape) < 0.6] = 0
        ref = np.bincount(lev.ravel(), minlength=256).astype(np.float64)
        assert np.array_equal(level_counts(lev, 256), ref)
