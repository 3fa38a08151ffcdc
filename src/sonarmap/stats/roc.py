"""ROC curves of a fitted mixture (paper eq. 15-16).

For a level threshold ``tau = x_k`` (classify ``y >= tau`` as object)::

    pFA(tau) = sum_{x_j >= tau} p(x_j | B)        pD(tau) = sum_{x_j >= tau} p(x_j | O)

with ``p(.|B)`` the fitted background class (spike + exponential, eq. 19) and ``p(.|O)`` the object
class (eq. 20-21), both discrete pmfs on the quantisation levels.  For more than two classes the
object class is the union of all non-background components weighted by their fitted weights.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import InputError
from sonarmap.stats.mixture import MixtureFit

__all__ = ["RocCurve", "roc_curve", "pd_pfa_at_threshold"]


@dataclasses.dataclass(frozen=True, eq=False)
class RocCurve:
    """A ROC curve (eq. 15-16).

    Attributes
    ----------
    thresholds : ndarray, shape (L + 1,)
        Intensity thresholds, decreasing; the last is ``+inf`` placed first (nothing detected).
    pfa, pd : ndarray, shape (L + 1,)
        False-alarm and detection probabilities, non-decreasing from (0, 0) to (1, 1).
    auc : float
        Area under the curve (trapezoidal).
    """

    thresholds: NDArray[np.float64]
    pfa: NDArray[np.float64]
    pd: NDArray[np.float64]
    auc: float

    def pd_at_pfa(self, pfa: float) -> float:
        """Detection probability at false-alarm probability ``pfa`` (linear interpolation)."""
        if not 0.0 <= float(pfa) <= 1.0:
            raise InputError(f"pfa: must be in [0, 1], got {pfa!r}")
        return float(np.interp(float(pfa), self.pfa, self.pd))

    def to_dict(self) -> dict[str, object]:
        """JSON-compatible dict."""
        return {"auc": self.auc, "pfa": self.pfa.tolist(), "pd": self.pd.tolist(),
                "thresholds": [None if math.isinf(t) else float(t) for t in self.thresholds]}


def _object_and_background(fit: MixtureFit) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    comp = fit.component_pmfs()
    cls = np.asarray(fit.component_classes)
    out = []
    for sel in (cls == 0, cls != 0):
        w = fit.weights[sel]
        w = w / w.sum() if w.sum() > 0 else np.full(w.size, 1.0 / max(w.size, 1))
        out.append(w @ comp[sel])
    return out[0], out[1]


def roc_curve(fit: MixtureFit) -> RocCurve:
    """ROC of the level-threshold detector under the fitted class pmfs (eq. 15-16).

    Raises
    ------
    InputError
        If the fit has no object class.
    """
    if len(fit.class_names) < 2:
        raise InputError("fit: needs an object class for a ROC curve")
    pb, po = _object_and_background(fit)
    sf_b = np.cumsum(pb[::-1])  # P(y >= x_k), k from the top level down
    sf_o = np.cumsum(po[::-1])
    pfa = np.concatenate([[0.0], np.minimum(sf_b, 1.0)])
    pd = np.concatenate([[0.0], np.minimum(sf_o, 1.0)])
    thr = np.concatenate([[math.inf], fit.levels[::-1]])
    auc = float(np.trapezoid(pd, pfa)) if hasattr(np, "trapezoid") else float(np.trapz(pd, pfa))
    return RocCurve(thresholds=thr, pfa=pfa, pd=pd, auc=auc)


def pd_pfa_at_threshold(fit: MixtureFit, threshold: float) -> tuple[float, float]:
    """``(pD, pFA)`` of classifying ``y >= threshold`` as object, from the fitted pmfs (eq. 15-16).

    A level counts as detected when its intensity ``x_k >= threshold`` (1e-12 tolerance).

    Returns
    -------
    (pd, pfa) : tuple of float
    """
    t = float(threshold)
    if math.isnan(t):
        raise InputError("threshold: is NaN")
    pb, po = _object_and_background(fit)
    sel = fit.levels >= t - 1e-12
    return float(min(po[sel].sum(), 1.0)), float(min(pb[sel].sum(), 1.0))
