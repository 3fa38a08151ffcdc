"""Threshold classifiers: fixed (eq. 14), Neyman-Pearson from the fitted background, Otsu baseline."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.stats.mixture import MixtureFit, as_intensity_image

__all__ = ["threshold_labels", "otsu_threshold", "neyman_pearson_threshold"]


def threshold_labels(image: ArrayLike, threshold: float) -> NDArray[np.uint8]:
    """Fixed-threshold classification (eq. 14): 1 (object) where ``image >= threshold``, else 0.

    Parameters
    ----------
    image : ndarray of float, shape (n_bins, n_beams)
        Intensities.
    threshold : float
        Intensity threshold ``tau``.

    Returns
    -------
    ndarray of uint8, same shape
    """
    img = as_intensity_image(image)
    t = float(threshold)
    if not math.isfinite(t):
        raise InputError(f"threshold: must be finite, got {threshold!r}")
    return (img >= t).astype(np.uint8)


def otsu_threshold(image: ArrayLike, *, nbins: int = 256) -> float:
    """Otsu's threshold of the image (scikit-image), the usual unsupervised baseline.

    Raises
    ------
    InputError
        Constant images (Otsu is undefined).
    """
    from skimage.filters import threshold_otsu

    img = as_intensity_image(image)
    if float(img.min()) == float(img.max()):
        raise InputError("image: constant image, Otsu threshold is undefined")
    return float(threshold_otsu(img, nbins=nbins))


def neyman_pearson_threshold(fit: MixtureFit, pfa: float) -> float:
    """Lowest level threshold whose background false-alarm probability is at most ``pfa``.

    ``pFA(tau) = P(y >= tau | background) = sum_{x_k >= tau} p(x_k | B)`` (eq. 15) from the
    fitted background class pmf (spike + exponential, eq. 19).

    Parameters
    ----------
    fit : MixtureFit
        A fitted mixture.
    pfa : float
        Requested false-alarm probability in ``(0, 1]``.

    Returns
    -------
    float
        The intensity of the first level ``x_k`` with ``pFA(x_k) <= pfa`` (``inf`` if none).
    """
    if not 0.0 < float(pfa) <= 1.0:
        raise InputError(f"pfa: must be in (0, 1], got {pfa!r}")
    pb = fit.class_pmf()[0]
    sf = np.cumsum(pb[::-1])[::-1]  # P(y >= x_k | B)
    ok = np.nonzero(sf <= float(pfa) + 1e-15)[0]
    return float(fit.levels[ok[0]]) if ok.size else math.inf
