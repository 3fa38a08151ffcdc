"""Fit gates: named reasons why a per-ping mixture fit cannot be trusted.

A ping whose fit fails a gate yields no returns (never confident garbage); every gate but
``collapsed`` also marks the ping as *flagged* (:data:`IMPLAUSIBLE`: the model cannot explain it).
The gate's name travels with the ping's products (:attr:`sonarmap.pipeline.PingProducts.flags`), the ranges CSV, the zarr
products, the CLI summary and the report.

Gates (:data:`GATE_DESCRIPTIONS`):

``kld``
    The KL divergence (eq. 11) exceeds ``max_kld`` (0.05) plus what sampling alone explains
    (:func:`sampling_kld`); with more than 1 % of the pixels in the top level (a saturated
    surface, a censored bin the pmfs do not model) the KLD over the other levels.  A correct
    model of ``N`` pixels on ``L`` occupied levels with ``k`` parameters leaves
    ``2 N kld ~ chi2(L - 1 - k)`` (the G-test), i.e. ``kld ~ L / 2N``: 0.002 for a 512 x 96 ping,
    so the limit stays 0.05 for the pings of real sonars, but 0.08 for a 64 x 16 window, which
    a fixed 0.05 refused however well the model fits.  The real DIDSON pings give 0.001-0.004, a
    binary image 0.6.
``object_weight``
    The object classes hold more than ``max_object_weight`` of the pixels: the "background" is
    then not the background (the un-normalised ARIS frames gave 1.00).
``collapsed``
    The object class is a reshaped background, not a separate population: its mean is less than
    ``min_separation`` x the mean of the background's continuous component.  Measured with the
    default pipeline: the real ARIS frames 2.5-3.3, the real Oculus pings 4.1-5.5, the DIDSON test
    pings 6.1-39.8; of 70 normalised pure-noise pings (Rayleigh, exponential, gamma, uniform;
    512 x 96, 2000 x 48 and 703 x 256 pixels) 10 fall below 1.9, 33 have no object class at all
    (``no_object``) and the other 27 lie at 2.0-4.7.  The gate therefore does not separate noise
    from the faint ARIS target on its own; the normalised component rule does the rest (no noise
    ping keeps a return, :class:`sonarmap.pipeline.PipelineConfig`).  A collapsed ping is
    explained by the background alone, so it is not *flagged* (not in :data:`IMPLAUSIBLE`).
``not_converged``
    The fitter stopped before converging (carried over from the fit's own flags).
``degenerate`` / ``all_zero`` / ``zero_mass``
    The fit's own flags of that name (see :data:`sonarmap.stats.mixture.FLAG_DESCRIPTIONS`).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import InputError
from sonarmap.stats.mixture import MixtureFit, _object_members

__all__ = ["GATE_DESCRIPTIONS", "REFUSING", "IMPLAUSIBLE", "fit_gates", "class_separation", "sampling_kld"]

GATE_DESCRIPTIONS: dict[str, str] = {
    "kld": "the fitted mixture does not describe the histogram (KL divergence too large)",
    "object_weight": "the object classes hold most of the pixels (the background model does not hold)",
    "collapsed": "the object class is a reshaped background, not a separate population",
    "not_converged": "the fitter stopped before converging",
    "degenerate": "fewer than 3 occupied levels: the fit is not identified",
    "all_zero": "every pixel is in the zero bin",
    "zero_mass": "the model gives zero probability to an occupied level",
}

#: Every gate: a ping failing any of them yields no returns.
REFUSING = frozenset(GATE_DESCRIPTIONS)

#: Gates that say the model cannot explain the ping ("flagged" pings; ``--strict`` exits 1 on them).
#: ``collapsed`` is not among them: a ping whose object class merely reshapes the background is
#: explained by the background alone (open water, pure speckle) - no returns, but nothing wrong.
IMPLAUSIBLE = REFUSING - {"collapsed"}


@functools.lru_cache(maxsize=64)
def _class_members(classes: tuple[int, ...], names: tuple[str, ...]) -> tuple[list[int], NDArray[np.intp]]:
    """The continuous background components and the object components (an index array,
    :func:`sonarmap.stats.mixture._object_members`) of a model layout (computed once per layout:
    every fit of a recording shares one)."""
    bg = [i for i, (c, n) in enumerate(zip(classes, names)) if c == 0 and n != "zero"]
    return bg, _object_members(classes)


def class_separation(fit: MixtureFit) -> float:
    """Mean of the object classes over the mean of the background's continuous component.

    NaN for a fit without an object class or with a zero background mean.
    """
    if len(fit.class_names) < 2:
        return math.nan
    levels = np.asarray(fit.levels, dtype=np.float64)
    comp = fit._pmf_matrix()  # read-only: component_pmfs() without its copy
    w = np.asarray(fit.weights, dtype=np.float64)
    bg, obj = _class_members(tuple(fit.component_classes), tuple(fit.component_names))
    if not bg or not len(obj):
        return math.nan
    bg_mean = float(comp[bg[0]] @ levels)
    wo = w[obj]
    if not bg_mean > 0:
        return math.nan
    wo_sum = wo.sum()
    if not wo_sum > 0:
        wo = np.ones(len(obj))
        wo_sum = wo.sum()
    obj_mean = float((wo / wo_sum) @ (comp[obj] @ levels))
    return obj_mean / bg_mean


#: Standard deviations of the G statistic above its mean that :func:`sampling_kld` allows.
SAMPLING_SIGMAS = 4.0


def sampling_kld(n_samples: float, n_levels: int, n_params: int) -> float:
    """The KL divergence (eq. 11) that sampling alone gives a correct model.

    A histogram of ``n_samples`` pixels on ``n_levels`` occupied levels, drawn from a model with
    ``n_params`` fitted parameters, has ``G = 2 N kld ~ chi2(dof)``, ``dof = n_levels - 1 -
    n_params`` (at least 1).  Returns the KLD of ``G`` at its mean plus :data:`SAMPLING_SIGMAS`
    standard deviations, ``(dof + 4 sqrt(2 dof)) / 2N``: 0.0028 for a 512 x 96 ping on 200 levels,
    0.12 for a 64 x 16 window on 170 (4 parameters).

    Parameters
    ----------
    n_samples : float
        Pixels in the histogram (> 0).
    n_levels : int
        Levels holding at least one pixel.
    n_params : int
        Free parameters of the fitted mixture.

    Returns
    -------
    float
        KLD in nats.
    """
    if not n_samples > 0:
        raise InputError(f"n_samples: must be positive (got {n_samples})")
    dof = max(int(n_levels) - 1 - int(n_params), 1)
    return (dof + SAMPLING_SIGMAS * math.sqrt(2.0 * dof)) / (2.0 * float(n_samples))


def _kld_unclipped(fit: MixtureFit) -> tuple[float, float]:
    """The fit's KLD and the KLD sampling explains (:func:`sampling_kld`) for the levels it is
    computed on: all levels, or - when more than 1 % of the pixels sit in the top level
    (saturated surfaces: the ``clipped`` flag, a censored bin the pmfs do not model) - the other
    levels, both pmfs renormalised there."""
    counts = np.asarray(fit.counts, dtype=np.float64)
    total = counts.sum()
    if "clipped" not in fit.flags and not counts[-1] > 0.01 * total:
        kld = float(fit.kld) if math.isfinite(fit.kld) else math.inf
    else:
        from sonarmap.stats.mixture import kl_divergence

        q = np.asarray(fit.pmf(), dtype=np.float64)[:-1]
        counts = counts[:-1]
        total = counts.sum()
        if not q.sum() > 0 or not total > 0:
            return math.inf, 0.0
        kld = float(kl_divergence(counts, q / q.sum()))
    if not total > 0:
        return kld, 0.0
    return kld, sampling_kld(float(total), int(np.count_nonzero(counts)), fit.n_params)


def fit_gates(fit: MixtureFit, *, max_kld: float = 0.05, max_object_weight: float = 0.5,
              min_separation: float = 1.9) -> frozenset[str]:
    """Names of the gates ``fit`` fails (empty when it is plausible).

    Parameters
    ----------
    fit : MixtureFit
        A per-ping fit (eq. 8-11).
    max_kld, max_object_weight, min_separation : float
        Gate limits; see the module docstring for the values measured on real and null pings.

    Returns
    -------
    frozenset of str
        Subset of :data:`GATE_DESCRIPTIONS`.

    Examples
    --------
    >>> import numpy as np
    >>> from sonarmap.stats.mixture import fit_mixture
    >>> rng = np.random.default_rng(0)
    >>> y = np.r_[np.zeros(6000), rng.exponential(0.02, 3500), rng.rayleigh(0.2, 500)]
    >>> fit = fit_mixture(np.clip(y, 0, 1).reshape(100, 100), method="em")
    >>> sorted(fit_gates(fit)), sorted(fit_gates(fit, max_object_weight=0.01))
    ([], ['object_weight'])
    """
    if not isinstance(fit, MixtureFit):
        raise InputError(f"fit: expected a MixtureFit, got {type(fit).__name__}")
    out = set(fit.flags & {"not_converged", "degenerate", "all_zero", "zero_mass"})
    if "all_zero" in out or "degenerate" in out:
        return frozenset(out)
    kld, sampling = _kld_unclipped(fit)
    if kld > max_kld + sampling:
        out.add("kld")
    if fit.object_weight > max_object_weight:
        out.add("object_weight")
    if "no_object" not in fit.flags:
        sep = class_separation(fit)
        if math.isfinite(sep) and sep < min_separation:
            out.add("collapsed")
    return frozenset(out)
