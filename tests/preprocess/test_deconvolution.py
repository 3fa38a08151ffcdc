"""Wiener deconvolution along the beams (eq. 3-4): synthetic truth, edges, caching, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import GeometryError, InputError
from sonarmap.geometry import preset
from sonarmap.preprocess.deconvolution import (
    convolve_beams,
    deconvolve,
    wiener_filter,
    wiener_matrix,
)


@pytest.fixture(scope="module")
def didson():
    return preset("didson-hf")


def _ghost_beams(b: int, n: int = 96) -> list[int]:
    return [b + k for k in range(-48, 49, 8) if k != 0 and 0 <= b + k < n]


def test_single_pixel_back_to_one_dominant_beam(didson):
    x = np.zeros(didson.shape, np.float32)
    x[200, 48] = 1.0
    y = convolve_beams(x, didson)
    assert y[200, 48] < 0.25  # the beam pattern spreads the echo over 12 beams
    for edge in ("pad", "truncated", "circular"):
        d = deconvolve(y, didson, noise=1e-3, edge=edge)
        assert d.dtype == np.float32 and d.shape == didson.shape
        assert np.unravel_index(np.argmax(d), d.shape) == (200, 48)  # no shift in range or azimuth
        assert d[200, 48] > 0.85
        assert np.abs(d[200, _ghost_beams(48)]).max() < 0.06 * d[200, 48]
        assert np.abs(np.delete(d, 200, axis=0)).max() < 1e-6  # nothing leaks to other range bins


def test_truncated_model_removes_ghosts_at_fan_edge(didson):
    for b in (0, 5, 30, 90, 95):
        x = np.zeros((4, 96), np.float32)
        x[1, b] = 1.0
        y = convolve_beams(x, didson)  # side lobes of an edge echo fall partly outside the fan
        d = deconvolve(y, didson, noise=1e-3, edge="truncated")
        assert d[1].argmax() == b
        assert np.abs(d[1, _ghost_beams(b)]).max() < 0.07 * d[1, b]
        dp = deconvolve(y, didson, noise=1e-3, edge="pad")
        assert dp[1].argmax() == b


def test_bright_outer_beam_does_not_wrap_to_opposite_edge(didson):
    for b, opposite in ((0, slice(72, 96)), (95, slice(0, 24))):
        x = np.zeros((3, 96), np.float32)
        x[1, b] = 1.0
        y = convolve_beams(x, didson)  # linear model: nothing reaches the opposite quarter
        assert np.abs(y[1, opposite]).max() < 1e-12
        leak = {}
        for edge in ("truncated", "pad", "circular"):
            d = deconvolve(y, didson, noise=1e-3, edge=edge)
            leak[edge] = float(np.abs(d[1, opposite]).max() / d[1, b])
        assert leak["truncated"] < 0.02
        assert leak["circular"] > 0.4  # circular convolution wraps the outer beam around
        assert leak["pad"] < leak["circular"]


def test_circular_matches_plain_fft_reference(didson):
    rng = np.random.default_rng(1)
    img = rng.random((16, 96)).astype(np.float32)
    H = np.fft.fft(np.roll(didson.psf, -48))
    ref = np.fft.ifft(np.fft.fft(img, axis=1) * np.conj(H) / (np.abs(H) ** 2 + 0.01), axis=1).real
    out = deconvolve(img, didson, noise=0.01, edge="circular")
    np.testing.assert_allclose(out, ref, atol=2e-5)


def test_fft_and_matrix_paths_agree(didson):
    rng = np.random.default_rng(2)
    img = rng.random((64, 96)).astype(np.float32)
    a = deconvolve(img, didson, method="fft", edge="pad")
    b = deconvolve(img, didson, method="matmul", edge="pad")
    np.testing.assert_allclose(a, b, atol=1e-5)
    M = wiener_matrix(didson, noise=1e-2)
    np.testing.assert_allclose(img @ M, b, atol=1e-6)


def test_clip_negative_is_explicit(didson):
    x = np.zeros((3, 96), np.float32)
    x[1, 30] = 1.0
    y = convolve_beams(x, didson)
    d = deconvolve(y, didson, noise=1e-3)
    assert d.min() < 0  # ringing of the inverse filter
    assert deconvolve(y, didson, noise=1e-3, clip_negative=True).min() == 0.0


def test_frequency_dependent_noise(didson):
    n_freq = wiener_filter(didson, noise=0.01).size
    assert n_freq == 97  # L = 192 >= 2 * 96
    g_flat = wiener_filter(didson, noise=[0.01, 0.01])
    np.testing.assert_allclose(g_flat, wiener_filter(didson, noise=0.01))
    g_call = wiener_filter(didson, noise=lambda f: 0.001 + 0.1 * f)
    g_arr = wiener_filter(didson, noise=[0.001, 0.051])
    np.testing.assert_allclose(g_call, g_arr, rtol=1e-9)
    assert wiener_filter(didson, noise=0.01) is wiener_filter(didson, noise=0.01)  # cached


def test_no_psf_is_identity():
    g = preset("aris3000-128")
    img = np.random.default_rng(3).random(g.shape).astype(np.float32)
    np.testing.assert_array_equal(deconvolve(img, g), img)


def test_bad_input(didson):
    img = np.ones(didson.shape, np.float32)
    with pytest.raises(GeometryError, match="psf: length 64 does not match"):
        deconvolve(img, np.ones(64))
    bad = img.copy()
    bad[3, 4] = np.nan
    with pytest.raises(InputError, match="NaN"):
        deconvolve(bad, didson)
    with pytest.raises(InputError, match="edge"):
        deconvolve(img, didson, edge="reflect")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="noise"):
        deconvolve(img, didson, noise=-1.0)
    with pytest.raises(InputError, match="noise"):
        deconvolve(img, didson, noise=[0.1, 0.2], edge="truncated")
