"""Model selection among component families and numbers of components (KLD + BIC/AIC)."""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from sonarmap.errors import InputError
from sonarmap.stats.mixture import Binning, MixtureFit, as_counts, fit_mixture

__all__ = ["ModelSelection", "select_model", "default_candidates"]

Criterion = Literal["bic", "aic", "kld"]


@dataclasses.dataclass(frozen=True, eq=False)
class ModelSelection:
    """Fits of every candidate model and the chosen one.

    Attributes
    ----------
    candidates : tuple of tuple of str
        Families of each candidate (after the zero spike).
    fits : tuple of MixtureFit
        One fit per candidate.
    scores : tuple of float
        The criterion of each candidate (lower is better; ``inf`` if the fit was flagged).
    criterion : str
        ``"bic"``, ``"aic"`` or ``"kld"``.
    best_index : int
        Index of the chosen candidate.
    """

    candidates: tuple[tuple[str, ...], ...]
    fits: tuple[MixtureFit, ...]
    scores: tuple[float, ...]
    criterion: str
    best_index: int

    @property
    def best(self) -> MixtureFit:
        """The chosen fit."""
        return self.fits[self.best_index]

    def table(self) -> list[dict[str, object]]:
        """One row per candidate: families, kld, bic, aic, flags, chosen."""
        return [
            {"families": "+".join(c), "kld": f.kld, "bic": f.bic, "aic": f.aic,
             "flags": ";".join(sorted(f.flags)), "chosen": i == self.best_index}
            for i, (c, f) in enumerate(zip(self.candidates, self.fits))
        ]


OBJECT_FAMILIES = ("exponential", "rayleigh", "rice", "weibull", "gamma")


#: A Rice component whose ``nu / sigma`` falls below this has become a Rayleigh: its density differs
#: from the Rayleigh's by ~(nu / sigma)^2 / 2 (2e-4), far less than the one parameter more costs in
#: any criterion.  :func:`select_model` stops such a candidate's EM there (``not_converged``, never
#: chosen) when the candidate with that Rayleigh in place of the Rice is fitted too: with ``nu``
#: near 0 the likelihood is flat in ``nu`` and EM creeps towards 0 until ``max_iter`` (three such
#: candidates were 0.58 of the 0.78 s that selection took on the normalised ARIS recording).
RICE_AS_RAYLEIGH = 0.02


def _canonical(c: Sequence[str]) -> tuple[str, ...]:
    """Candidate ``c`` with its object families in the order of :func:`default_candidates`
    (families not in :data:`OBJECT_FAMILIES` after them, by name)."""
    n = len(OBJECT_FAMILIES)
    return (c[0],) + tuple(sorted(c[1:], key=lambda f: (OBJECT_FAMILIES.index(f) if f in OBJECT_FAMILIES else n, f)))


def _rayleigh_for_rice(c: tuple[str, ...]) -> tuple[str, ...] | None:
    """Candidate ``c`` with its first Rice replaced by a Rayleigh, in :func:`_canonical` order
    (None without a Rice)."""
    if "rice" not in c[1:]:
        return None
    objs = list(c[1:])
    objs[objs.index("rice")] = "rayleigh"
    return _canonical((c[0], *objs))


def default_candidates(max_objects: int = 2) -> list[tuple[str, ...]]:
    """Exponential background plus 0..``max_objects`` object components from
    :data:`OBJECT_FAMILIES` (every multiset of families: 1 + 5 + 15 candidates for 2)."""
    if isinstance(max_objects, bool) or int(max_objects) != max_objects or max_objects < 0:
        raise InputError(f"max_objects: must be a non-negative integer, got {max_objects!r}")
    objs = OBJECT_FAMILIES
    out: list[tuple[str, ...]] = [("exponential",)]
    for n in range(1, max_objects + 1):
        for combo in itertools.combinations_with_replacement(objs, n):
            out.append(("exponential",) + combo)
    return out


def select_model(
    data: ArrayLike,
    *,
    candidates: Sequence[Sequence[str]] | None = None,
    criterion: Criterion = "bic",
    method: Literal["lsq", "em"] = "em",
    n_levels: int = 256,
    binning: Binning = "round",
    max_iter: int = 2000,
    workers: int = 1,
) -> ModelSelection:
    """Fit every candidate model and choose by BIC, AIC or KLD (eq. 11).

    Fits flagged ``not_converged``, ``collapsed_scale``, ``zero_mass`` or ``degenerate`` are never
    chosen (score ``inf``); a model whose extra object component has no weight (``no_object``) is
    only chosen if its criterion is still the best.  N > 2 classes arise from candidates with
    several object components.  A candidate with a Rice component is stopped (``not_converged``)
    once that Rice has become a Rayleigh (``nu / sigma`` below :data:`RICE_AS_RAYLEIGH`) when the
    candidate with the Rayleigh in its place is among ``candidates``: that candidate stands for
    it, with one parameter less.

    Parameters
    ----------
    data : ndarray
        Image or counts, as for :func:`fit_mixture`.
    candidates : sequence of family tuples, optional
        Default :func:`default_candidates` (up to two object components).
    criterion : {"bic", "aic", "kld"}
        Selection score (lower is better).
    method : {"lsq", "em"}
        Fitter (EM is the maximum-likelihood fit the information criteria assume).
    max_iter : int
        EM iteration limit per candidate (a fit that hits it is flagged ``not_converged`` and
        not chosen).
    workers : int
        Threads fitting candidates at once (the EM kernels release the GIL).  The fits do not
        depend on it: each candidate is fitted alone, exactly as with one thread.
    """
    if criterion not in ("bic", "aic", "kld"):
        raise InputError(f"criterion: must be 'bic', 'aic' or 'kld', got {criterion!r}")
    counts, _ = as_counts(data, n_levels, binning=binning)
    cands = [tuple(c) for c in (candidates if candidates is not None else default_candidates())]
    if not cands:
        raise InputError("candidates: empty")
    if isinstance(workers, bool) or int(workers) != workers or workers < 1:
        raise InputError(f"workers: must be a positive integer, got {workers!r}")

    fitted = {_canonical(c) for c in cands}  # whatever order the caller lists a candidate's families in

    def fit(c: tuple[str, ...]) -> MixtureFit:
        rice_min = RICE_AS_RAYLEIGH if _rayleigh_for_rice(c) in fitted else 0.0
        return fit_mixture(counts, families=c, method=method, binning=binning, max_iter=max_iter, rice_min=rice_min)

    if workers > 1 and len(cands) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=min(int(workers), len(cands))) as pool:
            fits = list(pool.map(fit, cands))
    else:
        fits = [fit(c) for c in cands]
    scores = []
    bad = {"not_converged", "collapsed_scale", "zero_mass", "degenerate"}
    for f in fits:
        s = {"bic": f.bic, "aic": f.aic, "kld": f.kld}[criterion]
        scores.append(math.inf if (f.flags & bad) or not math.isfinite(s) else float(s))
    best = int(np.argmin(scores))
    return ModelSelection(tuple(cands), tuple(fits), tuple(scores), criterion, best)
