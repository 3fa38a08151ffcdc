"""Component pmfs on the quantisation levels."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import InputError
from sonarmap.stats.components import FAMILIES, pmf, quantization_levels


@pytest.mark.parametrize("name,params", [("exponential", (0.03,)), ("rayleigh", (0.2,)),
                                         ("gamma", (0.5, 0.1)), ("weibull", (1.5, 0.2)),
                                         ("rice", (0.3, 0.05))])
def test_pmfs_sum_to_one_and_match_density(name, params):
    lv = quantization_levels(256)
    p = pmf(name, params, lv)
    assert np.isclose(p.sum(), 1.0) and np.all(p >= 0)
    from scipy import stats

    dist = {"exponential": lambda: stats.expon(scale=params[0]),
            "rayleigh": lambda: stats.rayleigh(scale=params[0]),
            "gamma": lambda: stats.gamma(params[0], scale=params[1]),
            "weibull": lambda: stats.weibull_min(params[0], scale=params[1]),
            "rice": lambda: stats.rice(params[0] / params[1], scale=params[1])}[name]()
    ref = dist.pdf(lv[1:])
    assert np.allclose(p[1:] / p[1:].sum(), ref / ref.sum(), rtol=1e-6)


def test_unknown_family_and_levels():
    assert set(FAMILIES) >= {"zero", "exponential", "rayleigh", "rice", "weibull", "gamma"}
    with pytest.raises(InputError, match="unknown family"):
        pmf("lognormal", (1.0,), quantization_levels(8))
    with pytest.raises(InputError):
        quantization_levels(1)
