"""CFAR detectors: design pFA is met in exponential noise; closed forms; targets are detected."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarmap.classify.cfar import SONAR_SLAM, CFARConfig, cfar, cfar_alpha, cfar_pfa
from sonarmap.errors import InputError


@pytest.fixture(scope="module")
def noise() -> np.ndarray:
    return np.random.default_rng(7).exponential(0.05, (1500, 120)).astype(np.float32)


@pytest.mark.parametrize("method", ["ca", "so", "go", "os"])
@pytest.mark.parametrize("two_d", [False, True])
def test_empirical_pfa_matches_design(noise, method, two_d):
    cfg = CFARConfig(method=method, n_train=20 if two_d else 40, n_guard=4 if two_d else 10,
                     pfa=0.02, two_d=two_d)
    res = cfar(noise, config=cfg)
    interior = res.mask[40:-40]
    # 180k cells: the binomial standard error of 0.02 is 3.3e-4
    assert interior.mean() == pytest.approx(0.02, rel=0.1)


def test_ca_closed_form_and_ordering():
    assert cfar_alpha(0.1, method="ca", n_train=40) == pytest.approx(40 * (0.1 ** (-1 / 40) - 1))
    a = {m: cfar_alpha(1e-3, method=m, n_train=32) for m in ("ca", "so", "go", "os")}
    # smallest-of needs the largest scale, greatest-of the smallest (Gandhi & Kassam 1988)
    assert a["so"] > a["ca"] > a["go"]
    for m, val in a.items():
        assert cfar_pfa(val, method=m, n_train=32) == pytest.approx(1e-3, rel=1e-8)


@settings(max_examples=30, deadline=None)
@given(st.sampled_from(["ca", "so", "go", "os"]), st.integers(1, 20).map(lambda k: 2 * k),
       st.floats(1e-6, 0.5))
def test_alpha_inverts_pfa(method, n_train, pfa):
    a = cfar_alpha(pfa, method=method, n_train=n_train)
    assert a > 0
    assert cfar_pfa(a, method=method, n_train=n_train) == pytest.approx(pfa, rel=1e-6)
    # the false-alarm probability falls with alpha
    assert cfar_pfa(a * 1.1, method=method, n_train=n_train) < pfa


def test_os_pfa_formula_matches_monte_carlo():
    rng = np.random.default_rng(0)
    n, k, alpha = 24, 18, 3.0
    x = rng.exponential(1.0, (200_000, n + 1))
    z = np.sort(x[:, 1:], axis=1)[:, k - 1]
    emp = (x[:, 0] > alpha * z).mean()
    assert emp == pytest.approx(cfar_pfa(alpha, method="os", n_train=n, rank=k), rel=0.05)


def test_detects_targets_and_so_handles_clutter_edges():
    rng = np.random.default_rng(3)
    img = rng.exponential(0.03, (400, 32)).astype(np.float32)
    img[200:203, 10:20] = 0.8   # a surface
    res = cfar(img, config=SONAR_SLAM)
    assert res.mask[200:203, 10:20].all()
    assert SONAR_SLAM.method == "so" and SONAR_SLAM.n_train == 40 and SONAR_SLAM.n_guard == 10
    assert SONAR_SLAM.pfa == 0.1
    assert math.isclose(res.alpha, cfar_alpha(0.1, method="so", n_train=40))


def test_bad_config_names_argument():
    with pytest.raises(InputError, match="method"):
        CFARConfig(method="xx")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="n_train"):
        CFARConfig(n_train=5)
    with pytest.raises(InputError, match="pfa"):
        CFARConfig(pfa=1.5)
    with pytest.raises(InputError, match="image"):
        cfar(np.full((4, 4), np.nan))


def test_all_zero_image_detects_nothing():
    res = cfar(np.zeros((100, 8), np.float32), config=CFARConfig(method="os"))
    assert not res.mask.any()
