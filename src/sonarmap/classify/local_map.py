"""Local MAP classification as a per-level lookup table (paper eq. 12-13).

For a pixel at level ``k`` the MAP class is ``argmax_c P(c) p(x_k | c)``; in the binary case the
object is chosen when the likelihood ratio ``p(x_k|O) / p(x_k|B) >= eta`` with
``eta = P(B) / P(O)`` (eq. 13).  Because the intensities are quantised, the decision is a table of
``L`` labels computed once per fit; classifying a ping is one quantisation and one table look-up.

Unlike the authors' code (which divides by the object weight), an object weight of 0 gives
``eta = inf`` and an all-background table, never a division by zero.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.stats.mixture import MixtureFit, quantize

__all__ = ["map_lookup_table", "local_map_labels"]


def map_lookup_table(fit: MixtureFit, *, eta: float | None = None) -> NDArray[np.uint8]:
    """Class label of every quantisation level (eq. 12-13).

    Parameters
    ----------
    fit : MixtureFit
        Fitted mixture; classes from :attr:`MixtureFit.class_names` (0 = background).
    eta : float, optional
        Binary fits only: likelihood-ratio threshold (eq. 13); default the prior ratio
        ``P(B) / P(O)`` from the fitted weights (``inf`` when the object weight is 0).  For more
        than two classes ``eta`` must be None (MAP with the fitted priors).

    Returns
    -------
    ndarray of uint8, shape (L,)
    """
    logp = fit.class_log_pmf()
    prior = fit.class_prior()
    n_cls = logp.shape[0]
    if n_cls == 1:
        return np.zeros(fit.n_levels, dtype=np.uint8)
    if n_cls == 2:
        if eta is None:
            eta = math.inf if prior[1] <= 0 else float(prior[0] / prior[1])
        eta = float(eta)
        if math.isnan(eta) or eta < 0:
            raise InputError(f"eta: must be >= 0, got {eta}")
        if math.isinf(eta):
            return np.zeros(fit.n_levels, dtype=np.uint8)
        with np.errstate(invalid="ignore"):
            llr = logp[1] - logp[0]
        log_eta = math.log(eta) if eta > 0 else -math.inf
        # levels impossible under both classes (nan) default to background
        return np.where(np.nan_to_num(llr, nan=-np.inf) >= log_eta, 1, 0).astype(np.uint8)
    if eta is not None:
        raise InputError("eta: only defined for two classes")
    with np.errstate(divide="ignore"):
        score = np.log(prior)[:, None] + logp
    score = np.where(np.isnan(score), -np.inf, score)
    lut = np.argmax(score, axis=0).astype(np.uint8)
    lut[~np.isfinite(score.max(axis=0))] = 0
    return lut


def local_map_labels(
    image: ArrayLike, fit: MixtureFit, *, eta: float | None = None
) -> NDArray[np.uint8]:
    """Local MAP labels of a ping (eq. 12-13): 0 background, 1 object (2, ... further classes).

    Parameters
    ----------
    image : ndarray of float, shape (n_bins, n_beams)
        Intensities, quantised exactly as for the fit (its ``binning`` and number of levels).
    fit : MixtureFit
        The ping's fitted mixture.
    eta : float, optional
        See :func:`map_lookup_table`.

    Returns
    -------
    ndarray of uint8, same shape as ``image``
    """
    lut = map_lookup_table(fit, eta=eta)
    q = quantize(image, fit.n_levels, binning=fit.binning)  # type: ignore[arg-type]
    return lut[q]
