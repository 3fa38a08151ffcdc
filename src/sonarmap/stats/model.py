"""The intensity-model stage of the per-ping pipeline: the mixture fit of an image's levels and
the gates that refuse an implausible fit.

:func:`fit_counts` (of :func:`sonarmap.stats.mixture.quantize_counts`' histogram, i.e.
:func:`fit_levels` of the level image) and :func:`failed_gates` are what
:func:`sonarmap.pipeline.process_ping` runs after pre-processing or normalisation; called alone with the default
:class:`~sonarmap.stats.config.FitConfig` they give the default pipeline's fit.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import FitError, InputError
from sonarmap.stats.config import FitConfig

__all__ = ["fit_levels", "fit_counts", "failed_gates"]


def fit_counts(counts: ArrayLike, config: FitConfig = FitConfig()) -> Any:
    """The mixture fit (eq. 8-11, 19-21) of a level histogram; None when it cannot be computed.

    Parameters
    ----------
    counts : ndarray, shape (n_levels,)
        Pixel count of every quantisation level.
    config : FitConfig
        Families, method, tolerance and number of levels.

    Returns
    -------
    MixtureFit or None
        None where :func:`sonarmap.stats.mixture.fit_mixture` raises :class:`FitError`
        (e.g. an empty histogram).
    """
    import sonarmap.stats.mixture as _mixture

    if not isinstance(config, FitConfig):
        raise InputError(f"config: expected a FitConfig, got {type(config).__name__}")
    try:
        return _mixture.fit_mixture(
            np.asarray(counts, dtype=np.float64), families=config.families,  # type: ignore[arg-type]
            method=config.fit_method, n_levels=config.n_levels, tol=config.fit_tol,  # type: ignore[arg-type]
            accelerate=config.fit_accelerate)
    except FitError:
        return None


def fit_levels(levels: ArrayLike, config: FitConfig = FitConfig()) -> Any:
    """:func:`fit_counts` of the histogram of a level image (:func:`sonarmap.stats.mixture.quantize`).

    Parameters
    ----------
    levels : ndarray of non-negative int, shape (n_bins, n_beams)
    config : FitConfig

    Returns
    -------
    MixtureFit or None
    """
    lev = np.asarray(levels)
    if lev.dtype.kind not in "iu":
        raise InputError(f"levels: expected integer level indices, got {lev.dtype}")
    if lev.ndim == 2 and lev.dtype.kind == "u":
        from sonarmap.stats._em_kernels import level_counts

        counts: NDArray[np.float64] = level_counts(lev, int(config.n_levels))
    else:
        counts = np.bincount(lev.ravel(), minlength=config.n_levels).astype(np.float64)
    return fit_counts(counts, config)


def failed_gates(fit: Any, config: FitConfig = FitConfig()) -> frozenset[str]:
    """The gates of :func:`sonarmap.stats.gates.fit_gates` that ``fit`` fails under ``config``'s
    limits (none without a fit)."""
    if fit is None:
        return frozenset()
    import sonarmap.stats.gates as _gates_mod

    return _gates_mod.fit_gates(fit, max_kld=config.max_kld, max_object_weight=config.max_object_weight,
                                min_separation=config.min_separation)
