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
from sonarmap.stats.mixture import MixtureFit, quantize_lookup

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
    return _lookup_table(fit, eta).copy()


def _lookup_table(fit: MixtureFit, eta: float | None) -> NDArray[np.uint8]:
    """The table of :func:`map_lookup_table`, computed once per fit and ``eta`` (read-only)."""
    key = ("map_lut", None if eta is None else float(eta))
    lut = fit._cache.get(key)
    if lut is None:
        lut = _compute_table(fit, eta)
        lut.setflags(write=False)
        fit._cache[key] = lut
    return lut  # type: ignore[no-any-return]


def _compute_table(fit: MixtureFit, eta: float | None) -> NDArray[np.uint8]:
    logp = fit.decision_log_pmf()
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
        # levels impossible under both classes (nan) count as llr = -inf
        lut = llr >= log_eta
        if log_eta == -math.inf:
            lut |= np.isnan(llr)
        return lut.astype(np.uint8)
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

    Notes
    -----
    The table is computed once per fit (cached on the immutable fit); quantisation and look-up
    are one fused pass over the pixels (numba), equal to ``map_lookup_table(fit)[quantize(image)]``.
    """
    lut = _lookup_table(fit, eta)
    return quantize_lookup(image, lut, fit.n_levels, binning=fit.binning)  # type: ignore[arg-type]
