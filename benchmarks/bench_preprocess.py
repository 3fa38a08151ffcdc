"""Pre-processing speed: full per-ping pipeline vs a naive per-call complex-FFT Wiener filter."""

from __future__ import annotations

from typing import Any

import numpy as np
from run import timeit

from sonarmap.geometry import SonarGeometry, preset
from sonarmap.preprocess.gain import RadialGain
from sonarmap.preprocess.pipeline import PreprocessConfig, preprocess_image


def _naive(image: np.ndarray, psf: np.ndarray, noise: float, taper: np.ndarray) -> np.ndarray:
    """Baseline: recompute H every call, complex float64 np.fft, padded, then taper."""
    n = image.shape[1]
    L = 2 * n
    h = np.zeros(L)
    h[(np.arange(n) - n // 2) % L] = psf / psf.sum()
    H = np.fft.fft(h)
    G = np.conj(H) / (np.abs(H) ** 2 + noise)
    out = np.fft.ifft(np.fft.fft(image, n=L, axis=1) * G, axis=1).real[:, :n]
    return np.maximum(out, 0) / taper


def _geometry_128() -> SonarGeometry:
    psf = np.zeros(128)
    psf[64] = 1.0
    for k in range(1, 8):
        psf[64 + 8 * k] = psf[64 - 8 * k] = 0.5 / k
    return SonarGeometry.from_window(min_range_m=1.0, max_range_m=20.0, n_bins=2000, n_beams=128,
                                     fov_rad=0.5, psf=psf, taper=np.linspace(0.5, 1.0, 128), noise=0.01)


def run(quick: bool) -> list[dict[str, Any]]:
    rows = []
    cases = [("512x96 DIDSON", preset("didson-hf"), 0.3), ("2000x128", _geometry_128(), 5.0)]
    rep = 10 if quick else 50
    for label, g, target in cases:
        img = np.random.default_rng(0).random(g.shape).astype(np.float32)
        gain = RadialGain.from_channel(1.0, 1.05)
        for cname, cfg in (
            ("default+gain", PreprocessConfig(radial_gain=gain)),
            ("paper-table1", PreprocessConfig.paper_table1()),
            ("pad/fft-edge", PreprocessConfig(edge="pad", radial_gain=gain)),
        ):
            preprocess_image(img, g, cfg)  # build the cached plan
            med = timeit(lambda cfg=cfg: preprocess_image(img, g, cfg), repeat=rep)
            base = timeit(lambda: _naive(img, np.asarray(g.psf), 0.01, np.asarray(g.taper)), repeat=rep)
            rows.append({
                "benchmark": "preprocess", "case": f"{label} {cname}", "median_ms": med,
                "target_ms": target, "baseline": "naive np.fft per call", "baseline_ms": base,
            })
        from sonarmap.preprocess.deconvolution import deconvolve

        med = timeit(lambda g=g, img=img: deconvolve(img, g, method="fft"), repeat=rep)
        rows.append({"benchmark": "preprocess", "case": f"{label} deconvolve rfft path",
                     "median_ms": med, "note": "scipy.fft rfft/irfft, workers=1, cached G"})
    return rows
