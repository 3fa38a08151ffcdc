"""The classification stage of the per-ping pipeline: labels of an image under its fitted mixture.

:func:`segment` is what :func:`sonarmap.pipeline.process_ping` runs between the fit and the
ranges; called alone with the default :class:`~sonarmap.classify.config.ClassifyConfig` it gives
the default pipeline's labels.  The MRF unary (eq. 17-18) is :func:`class_costs`, the pD / pFA of
a per-level decision (eq. 15-16) :func:`decision_pd_pfa`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.classify.config import ClassifyConfig
from sonarmap.errors import InputError
from sonarmap.stats.mixture import MixtureFit

__all__ = ["Segmentation", "segment", "class_costs", "level_costs", "decision_pd_pfa", "decision_rates"]


@dataclasses.dataclass(frozen=True, eq=False)
class Segmentation:
    """Labels of one image and the detection / false-alarm probabilities of the decision.

    Attributes
    ----------
    labels : ndarray of uint8, shape (n_bins, n_beams)
        0 background, >= 1 structure classes.
    pd, pfa : float
        Detection and false-alarm probabilities of the per-pixel decision under the fitted model
        (eq. 15-16; :func:`decision_rates`): NaN where the method has no model (CFAR's pD,
        a threshold without a fit).
    method : str
        The labelling method.
    """

    labels: NDArray[np.uint8]
    pd: float
    pfa: float
    method: str


def level_costs(class_log_pmf: ArrayLike, class_log_prior: ArrayLike | None = None, *,
                floor: float = -50.0) -> NDArray[np.float64]:
    """``-log p(level|k) - log pi_k`` per class and level (eq. 17-18), clipped below at ``floor``
    and shifted so that the cheapest class of every level costs 0.

    Parameters
    ----------
    class_log_pmf : ndarray, shape (n_classes, n_levels)
    class_log_prior : ndarray, shape (n_classes,), optional
        Uniform when omitted.
    floor : float
        Log-probabilities below it (a pmf of exactly zero) cost ``-floor``, a large finite amount.

    Returns
    -------
    ndarray of float64, shape (n_classes, n_levels)
    """
    import sonarmap.classify._kernels as _ck

    lp = np.ascontiguousarray(class_log_pmf, dtype=np.float64)
    if lp.ndim != 2 or lp.shape[0] < 2:
        raise InputError(f"class_log_pmf: expected (n_classes >= 2, n_levels), got {lp.shape}")
    pr = _NO_PRIOR
    if class_log_prior is not None:
        pr = np.ascontiguousarray(class_log_prior, dtype=np.float64).reshape(-1)
        if pr.size != lp.shape[0]:
            raise InputError(f"class_log_prior: {pr.size} entries for {lp.shape[0]} classes")
    # one pass over the table (numpy's nan_to_num / maximum / min / subtract, elementwise the same)
    return _ck.level_cost_table(lp, pr, class_log_prior is not None, float(floor))  # type: ignore[no-any-return]


_NO_PRIOR = np.zeros(0)


def _fit_array(fit: Any, name: str) -> NDArray[np.float64]:
    """``fit.<name>()``: a :class:`MixtureFit`'s own read-only array (``copy=False``, no copy to
    read), another object's method as it is."""
    if type(fit) is MixtureFit:
        return getattr(fit, name)(copy=False)  # type: ignore[no-any-return]
    return getattr(fit, name)()  # type: ignore[no-any-return]


def _class_prior(fit: Any, prior_min: float) -> NDArray[np.float64]:
    """Fitted class priors with every object class raised to at least ``prior_min``."""
    prior = np.array(_fit_array(fit, "class_prior"), dtype=np.float64)  # (a copy of its own)
    if prior_min > 0 and prior.size == 2:
        # (two classes, the pipeline's: the same operations on the one object prior - np.maximum's
        # NaN propagates as max's first argument does, and a one-term sum is that term)
        p1 = prior[1].item()
        p1 = prior_min if prior_min > p1 else p1
        prior[1] = p1
        prior[0] = max(1.0 - p1, 1e-12)
    elif prior_min > 0 and prior.size > 1:
        prior[1:] = np.maximum(prior[1:], prior_min)
        prior[0] = max(1.0 - prior[1:].sum(), 1e-12)
    return prior


def class_costs(fit: Any, *, object_prior_min: float = 0.0, speckle_eps: float = 0.0,
                floor: float = -50.0) -> NDArray[np.float64]:
    """The MRF unary of a fitted mixture per class and level (:func:`level_costs` of its classes).

    Parameters
    ----------
    fit : MixtureFit
        Gives ``decision_log_pmf()`` and ``class_prior()``.
    object_prior_min : float
        Every object class's prior raised to at least this (the background's lowered to match).
    speckle_eps : float
        With ``eps > 0`` every object class's pmf is ``(1 - eps) p(y|k) + eps p(y|background)``:
        a structure pixel may fade into the background's range (speckle, the receiver threshold's
        zeros), so a dark pixel costs structure at most ``-log eps`` instead of an unbounded amount.
    floor : float
        See :func:`level_costs`.

    Returns
    -------
    ndarray of float64, shape (n_classes, n_levels)
    """
    lp = np.asarray(_fit_array(fit, "decision_log_pmf"), dtype=np.float64)  # (copied before a change)
    if speckle_eps > 0 and lp.shape[0] > 1:
        lp = lp.copy()
        with np.errstate(divide="ignore"):
            lp[1:] = np.logaddexp(np.log1p(-speckle_eps) + lp[1:], math.log(speckle_eps) + lp[0])
    with np.errstate(divide="ignore"):
        log_prior = np.log(_class_prior(fit, object_prior_min))
    return level_costs(lp, log_prior, floor=floor)


def decision_pd_pfa(fit: Any, decision: ArrayLike) -> tuple[float, float]:
    """pD and pFA (eq. 15-16) of a per-level decision under ``fit``.

    ``decision[level]`` is non-zero where the level is labelled structure; pFA is the background
    class's probability of those levels, pD the object classes' (weighted by their priors).
    """
    pmf = np.asarray(_fit_array(fit, "class_pmf"))
    det = np.asarray(decision)
    det = det if det.dtype == np.bool_ else det != 0
    prior = np.asarray(_fit_array(fit, "class_prior"))
    if (pmf.dtype == np.float64 and pmf.ndim == 2 and pmf.shape[0] == 2 and det.shape == pmf.shape[1:]
            and prior.dtype == np.float64 and prior.shape == (2,)):
        # two classes (the pipeline's): one kernel, numpy's summation order (same bits)
        import sonarmap.classify._kernels as _ck

        pd, pfa = _ck.decision_rates_pmf(np.ascontiguousarray(pmf), det, prior)
        return float(pd), float(pfa)
    pfa = float(pmf[0][det].sum())
    pd = float((pmf[1:][:, det].sum(axis=1) * prior[1:]).sum() / max(float(prior[1:].sum()), 1e-300))
    return min(pd, 1.0), min(pfa, 1.0)


def _usable(fit: Any) -> bool:
    return fit is not None and fit.classifiable


def _decision_table(fit: Any, config: ClassifyConfig) -> NDArray[Any]:
    """The per-level table of a model-based method: the MAP lookup (``"map"``) or the MRF unary
    (:func:`class_costs`, ``"mrf"``) - computed once per ping for both its rates and its labels."""
    if config.method == "map":
        from sonarmap.classify.local_map import map_lookup_table

        return map_lookup_table(fit)
    return class_costs(fit, object_prior_min=config.object_prior_min, speckle_eps=config.speckle_eps)


def _table_rates(fit: Any, method: str, table: NDArray[Any]) -> tuple[float, float]:
    """pD / pFA of the decision a :func:`_decision_table` makes (the MRF's: its unary's argmin)."""
    if method == "map":
        return decision_pd_pfa(fit, table)
    # the unary's argmin (first least cost); two classes: label 1 where it costs strictly less
    return decision_pd_pfa(fit, table[1] < table[0] if table.shape[0] == 2 else np.argmin(table, axis=0))


def decision_rates(fit: Any, config: ClassifyConfig = ClassifyConfig()) -> tuple[float, float]:
    """``(pd, pfa)`` of ``config.method``'s per-pixel decision under ``fit`` (eq. 15-16).

    MRF: the decision of its own unary (object prior raised to ``object_prior_min``: the fitted
    prior alone can be so small - a thin surface, 0.001-0.02 - that the local MAP rule detects
    nothing while the MRF reports the surface); local MAP: the MAP rule (eq. 12-13); threshold:
    :func:`sonarmap.stats.roc.pd_pfa_at_threshold` (NaN without a fit); CFAR: ``(nan, cfar_pfa)``.
    A missing or degenerate fit gives ``(0, 0)`` for the model-based methods.
    """
    method = config.method
    if method.startswith("cfar-"):
        return math.nan, config.cfar_pfa
    if method == "threshold":
        if fit is None:
            return math.nan, math.nan
        from sonarmap.stats.roc import pd_pfa_at_threshold

        return pd_pfa_at_threshold(fit, config.threshold)
    if not _usable(fit):
        return 0.0, 0.0
    return _table_rates(fit, method, _decision_table(fit, config))


def segment(image: ArrayLike, fit: Any, config: ClassifyConfig = ClassifyConfig(), *,
            levels: ArrayLike | None = None, n_levels: int = 256) -> Segmentation:
    """Label an image (pre-processed or normalised) under its fitted mixture: the pipeline's
    classification stage.

    Parameters
    ----------
    image : ndarray, shape (n_bins, n_beams)
        Intensities in [0, 1].
    fit : MixtureFit or None
        The image's fit (:func:`sonarmap.stats.mixture.fit_mixture` of its level histogram); not
        needed by CFAR, optional for the threshold (then pD / pFA are NaN).
    config : ClassifyConfig
        Method and parameters; the default is the default pipeline's exact graph-cut MRF.
    levels : ndarray of int, optional
        The image's quantisation levels (:func:`sonarmap.stats.mixture.quantize` with
        ``n_levels``), when already computed.
    n_levels : int
        Quantisation levels of the fit.

    Returns
    -------
    Segmentation
        A missing or degenerate fit labels everything background for MAP and the MRF.

    Notes
    -----
    Local MAP: eq. 12-13; threshold: eq. 14; MRF: unary eq. 17-18 (:func:`class_costs`) with the
    Potts prior of eq. 22 along range weighted by ``range_weight``; with ``grow_prior_min > 0`` a
    second, more permissive cut adds the faint structure 8-connected to the first cut's.

    Examples
    --------
    >>> from sonarmap.stats.mixture import fit_mixture, quantize
    >>> seg = segment(image, fit_mixture(np.bincount(quantize(image).ravel(), minlength=256)))  # doctest: +SKIP
    >>> seg.labels.shape == image.shape                                                          # doctest: +SKIP
    True
    """
    if not isinstance(config, ClassifyConfig):
        raise InputError(f"config: expected a ClassifyConfig, got {type(config).__name__}")
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2:
        raise InputError(f"image: expected (n_bins, n_beams), got shape {img.shape}")
    method = config.method
    model_based = not (method.startswith("cfar-") or method == "threshold")
    if not model_based or not _usable(fit):
        pd, pfa = decision_rates(fit, config)
    if method.startswith("cfar-"):
        from sonarmap.classify.cfar import CFARConfig, cfar

        cfg = CFARConfig(method=method[5:], n_train=config.cfar_train, n_guard=config.cfar_guard,  # type: ignore[arg-type]
                         pfa=config.cfar_pfa, two_d=config.cfar_two_d)
        return Segmentation(cfar(img, config=cfg).labels, pd, pfa, method)
    if method == "threshold":
        from sonarmap.classify.threshold import threshold_labels

        return Segmentation(threshold_labels(img, config.threshold), pd, pfa, method)
    if not _usable(fit):
        return Segmentation(np.zeros(img.shape, dtype=np.uint8), pd, pfa, method)
    if levels is None:
        from sonarmap.stats.mixture import quantize

        levels = quantize(img, n_levels)
    lev = np.asarray(levels)
    if lev.shape != img.shape:
        raise InputError(f"levels: shape {lev.shape} does not match image {img.shape}")
    table = _decision_table(fit, config)
    pd, pfa = _table_rates(fit, method, table)
    if method == "map":
        return Segmentation(table[lev], pd, pfa, method)
    labels = _mrf_labels(img, lev, table, config.beta, config)
    if config.grow_prior_min > 0:
        weak = _mrf_labels(img, lev, class_costs(fit, object_prior_min=config.grow_prior_min,
                                                 speckle_eps=config.speckle_eps), config.grow_beta, config)
        labels = np.where(_seeded_components((weak >= 1) | (labels >= 1), labels >= 1) & (labels == 0),
                          np.uint8(1), labels).astype(np.uint8)
    return Segmentation(labels, pd, pfa, method)


def _seeded_components(mask: NDArray[np.bool_], seeds: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The 8-connected components of ``mask`` holding at least one seed pixel (hysteresis)."""
    from scipy import ndimage

    lab, n = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
    if n == 0:
        return np.zeros(mask.shape, dtype=bool)
    keep = np.zeros(n + 1, dtype=bool)
    keep[np.unique(lab[seeds & mask])] = True
    keep[0] = False
    return keep[lab]  # type: ignore[no-any-return]


def _mrf_labels(image: NDArray[np.float32], levels: NDArray[Any], cost: NDArray[np.float64], beta: float,
                config: ClassifyConfig) -> NDArray[np.uint8]:
    """The MRF labels for a per-level unary ``cost`` (the level-LUT graph cut where it applies)."""
    import sonarmap.classify.mrf as mrf

    if config.solver == "graphcut" and cost.shape[0] == 2 and not config.contrast:
        if cost.dtype == np.float64 and cost.flags.c_contiguous and mrf._table_cut_applies(levels, cost,
                                                                                            config.neighbourhood):
            # a level_costs table is finite (its floor): graphcut_levels_labels without its checks
            return mrf._table_cut(levels, cost, float(beta), config.neighbourhood, float(config.range_weight))
        return mrf.graphcut_levels_labels(levels, cost, beta=beta, neighbourhood=config.neighbourhood,
                                          range_weight=config.range_weight)
    unary = np.ascontiguousarray(cost[:, levels])
    wt = mrf.pairwise_weights(image.shape, beta=beta, neighbourhood=config.neighbourhood,
                              image=image, contrast=config.contrast, range_weight=config.range_weight)
    return mrf.solve(unary, solver=config.solver, beta=beta,  # type: ignore[arg-type]
                     neighbourhood=config.neighbourhood, weights=wt).labels
