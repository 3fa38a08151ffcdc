"""Taper (eq. 5) and radial gain (eq. 6-7): synthetic truth and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import GeometryError, InputError
from sonarmap.geometry import SonarGeometry, preset
from sonarmap.ping import Ping
from sonarmap.preprocess.absorption import absorption_db_per_m
from sonarmap.preprocess.gain import (
    RadialGain,
    apply_radial_gain,
    correct_taper,
    estimate_radial_gain,
    estimate_taper,
    radial_gain_db,
)


def _background(rng, shape, taper, *, range_m=None, beta=0.0, alpha=0.0, p_nonzero=0.4):
    """Exponential background with a zero atom, scaled by taper and the channel loss."""
    x = rng.exponential(0.05, shape) * (rng.random(shape) < p_nonzero)
    if range_m is not None:
        loss_db = 20 * beta * np.log10(range_m) + 2 * alpha * range_m
        x = x * 10 ** (-loss_db / 10)[:, None]
    return (x * taper[None, :]).astype(np.float32)


def test_correct_taper_divides_columns():
    img = np.ones((4, 3), np.float32) * np.array([1.0, 2.0, 4.0], np.float32)
    out = correct_taper(img, [0.5, 1.0, 2.0])
    np.testing.assert_allclose(out, np.array([[2.0, 2.0, 2.0]] * 4))
    assert out.dtype == np.float32


def test_estimate_taper_recovers_truth_and_resists_outliers():
    rng = np.random.default_rng(0)
    g = preset("didson-hf")
    truth = np.asarray(g.taper) / np.max(g.taper)
    imgs = [_background(rng, g.shape, truth) for _ in range(100)]
    for k in range(5):  # outlier pings: a bright object in a few beams
        imgs[k][100:300, 10 + 5 * k : 14 + 5 * k] += 0.8
    est = estimate_taper(imgs)
    assert est.n_images == 100 and est.taper.max() == pytest.approx(1.0)
    assert np.max(np.abs(est.taper / truth - 1)) < 0.05
    naive = np.mean([im.mean(axis=0) for im in imgs], axis=0)
    naive /= naive.max()
    assert np.max(np.abs(naive / truth - 1)) > 0.2  # a plain mean would be fooled


def test_estimate_taper_bad_input():
    g = preset("didson-hf")
    with pytest.raises(InputError, match="empty"):
        estimate_taper([])
    bad = np.zeros(g.shape, np.float32)
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        estimate_taper([bad])
    with pytest.raises(GeometryError, match="mixed geometries"):
        estimate_taper([np.ones((10, 96)), np.ones((12, 96))])
    p1 = Ping(np.ones(g.shape, np.float32), g)
    p2 = Ping(np.ones(g.shape, np.float32), g.replace(noise=0.5))
    with pytest.raises(GeometryError, match="mixed geometries"):
        estimate_taper([p1, p2])
    with pytest.raises(GeometryError, match="taper: length 5"):
        correct_taper(np.ones((3, 4)), np.ones(5))


def test_radial_gain_formula_and_channel():
    gain = RadialGain.from_channel(beta=1.0, alpha_db_per_m=absorption_db_per_m(1.8e6))
    assert gain.k1 == 20.0 and gain.k2 == pytest.approx(2 * 1.0550, abs=0.01)
    r = np.array([1.0, 10.0])
    np.testing.assert_allclose(radial_gain_db(r, gain), [gain.k2, 20.0 + 10 * gain.k2])
    img = np.ones((2, 3), np.float32)
    out = apply_radial_gain(img, r, RadialGain(k1=10.0, k2=0.0))  # +10 dB at 10 m -> x10 power
    np.testing.assert_allclose(out[:, 0], [1.0, 10.0], rtol=1e-6)
    amp = apply_radial_gain(img, r, RadialGain(k1=20.0, k2=0.0, scale="amplitude"))
    np.testing.assert_allclose(amp[:, 0], [1.0, 10.0], rtol=1e-6)
    with pytest.raises(GeometryError, match="range_m"):
        apply_radial_gain(img, [1.0, 2.0, 3.0], gain)
    with pytest.raises(InputError, match=">= 0"):
        radial_gain_db([-1.0, 1.0], gain)
    with pytest.raises(InputError, match="all ranges are 0"):
        radial_gain_db([0.0, 0.0], gain)
    # a window starting at the transducer (Oculus): the first bin is evaluated at half a bin
    np.testing.assert_allclose(radial_gain_db([0.0, 0.5, 1.0], gain), radial_gain_db([0.25, 0.5, 1.0], gain))
    assert RadialGain.from_dict(gain.to_dict()) == gain


def test_estimate_radial_gain_flattens_background():
    rng = np.random.default_rng(5)
    g = SonarGeometry.from_window(min_range_m=1.0, max_range_m=20.0, n_bins=300, n_beams=32,
                                  fov_rad=0.5)
    pings = [Ping(_background(rng, g.shape, np.ones(32), range_m=g.range_m, beta=1.0, alpha=0.3), g)
             for _ in range(30)]
    gain = estimate_radial_gain(pings)
    assert gain.k1 == pytest.approx(20.0, abs=1.5)
    assert gain.k2 == pytest.approx(0.6, abs=0.08)
    flat = np.stack([apply_radial_gain(p.image, g, gain) for p in pings])
    prof = np.array([row[row > 0].mean() for row in flat.transpose(1, 0, 2).reshape(300, -1)])
    blocks = prof.reshape(10, 30).mean(axis=1)  # mean level in 10 range blocks
    assert blocks.max() / blocks.min() - 1 < 0.05
    # fixing k1 from the channel model leaves k2 to the regression
    assert estimate_radial_gain(pings, fix_k1=20.0).k2 == pytest.approx(0.6, abs=0.05)
    with pytest.raises(InputError, match="range_m"):
        estimate_radial_gain([p.image for p in pings])


@pytest.mark.parametrize("rule", ["floor", "round"])
def test_intensity_from_nonzero_mean_is_threshold_free(rule):
    # pixel = Q(max(I - t, 0)), I ~ Exp(mu): the non-zero mean gives mu whatever t is.
    from sonarmap.preprocess.gain import intensity_from_nonzero_mean

    rng = np.random.default_rng(3)
    d = 1 / 255
    for mu in (0.004, 0.0125, 0.05):
        for t in (0.0, 0.01218, 0.03):
            p = np.maximum(rng.exponential(mu, 400_000) - t, 0.0)
            q = (np.floor(p / d + 1e-9) if rule == "floor" else np.rint(p / d)) * d
            nz = q[q > 0]
            est = float(intensity_from_nonzero_mean(nz.mean(), d))
            assert est == pytest.approx(mu, rel=4 / np.sqrt(nz.size))  # 4 standard errors
    assert float(intensity_from_nonzero_mean(0.3, 0.0)) == 0.3


def test_estimate_taper_mean_estimator_kept_and_recorded():
    rng = np.random.default_rng(1)
    g = preset("didson-hf")
    truth = np.asarray(g.taper) / np.max(g.taper)
    imgs = [_background(rng, g.shape, truth) for _ in range(20)]
    old = estimate_taper(imgs, estimator="mean")
    new = estimate_taper(imgs, estimator="nonzero_mean")
    assert old.estimator == "mean" and old.statistic == "median"
    assert new.estimator == "nonzero-mean" and new.quantum == 0.0  # continuous values
    assert np.max(np.abs(new.taper / truth - 1)) < 0.05
    assert set(new.to_dict()) >= {"estimator", "quantum", "excluded"}
    with pytest.raises(InputError, match="estimator"):
        estimate_taper(imgs, estimator="mode")
