"""Per-ping intensity mixture models on the quantisation levels (paper eq. 8-11, 19-21).

The intensity ``y`` of a ping is modelled as a mixture of discrete pmfs on the ``L`` quantisation
levels (:mod:`sonarmap.stats.components`)::

    p(y) = pi_0 delta(y) + sum_c pi_c p_c(y)                                   (eq. 8, 19-21)

The zero spike ``delta`` (index 0, when ``zero_spike=True``) and the first family form the
*background* class (eq. 19: ``p(y|B) = (1 - pi_B) delta(y) + pi_B lambda e^{-lambda y}``); every
further component is an *object* class (eq. 20-21, the paper's Rayleigh).  With the paper's default
``families=("exponential", "rayleigh")`` the fitted weights are ``(1 - pi1 - pi2, pi1, pi2)``,
``lambda = 1 / scale_exponential`` and ``sigma = scale_rayleigh`` (Table I).

Histogram
---------
:func:`quantize` maps intensities to level indices: values are clipped to ``[0, 1]`` (negative
values after deconvolution count as level 0), then ``binning="round"``: ``k = round(y (L - 1))``
(exact for ``L``-level sensor data: 8-bit ``k/255`` maps to ``k``), or ``binning="floor"``:
``k = min(floor(y L), L - 1)`` (the bins ``[k/L, (k+1)/L)`` of ``numpy.histogram(y, linspace(0, 1,
L + 1))`` used by the paper's authors; there, values outside ``[0, 1]`` are *dropped* whereas we
clip them - the same thing for the paper's pre-processing, which clips negatives and rescales to
the input maximum).  The zero bin is therefore ``y < 0.5 / (L - 1)`` (round) or ``y < 1 / L``
(floor), including all ``y <= 0``.

Fitters
-------
``method="lsq"``: the paper's fit - least squares between the normalised histogram and the model
pmf (``scipy.optimize.least_squares``, trust-region reflective) - made robust: weights are
parametrised by stick-breaking fractions in ``[0, 1]`` (never negative, summing to 1), scales are
bounded below by one quantisation step and above by ``scale_max`` (default 1, the paper's bound),
and the better of two starts (the EM estimate and the paper's ``p0``) is kept.

``method="em"``: exact EM on the histogram counts - the E-step and M-step run over the ``L``
levels weighted by their counts, not over pixels.  For exponential and Rayleigh components the
M-step is exact (moment matching, a numba kernel); for gamma, Weibull and Rice it is a numerical
maximisation that is accepted only if it improves the expected log-likelihood (generalised EM).
Either way the log-likelihood never decreases; its trace is kept in :attr:`MixtureFit.loglik_trace`.
EM is accelerated by SQUAREM (``accelerate=True``, the default of :func:`fit_mixture`): two EM
steps, an extrapolation along them and a stabilising EM step, kept only if it does not lower the
log-likelihood (see :mod:`sonarmap.stats._em_kernels`); the stopping rule is the plain one (one EM
step gains at most ``tol``, relative).  The per-ping pipeline fits with plain EM
(:attr:`sonarmap.stats.config.FitConfig.fit_accelerate`).

KL divergence (eq. 11)
----------------------
``kld = D(p_hat || p_model) = sum_k p_hat_k ln(p_hat_k / p_model_k)`` in nats, with ``p_hat`` the
normalised histogram and ``p_model`` the fitted pmf, both summing to 1 over the same levels; bins
with ``p_hat_k = 0`` contribute 0.  The paper's Table I values are smaller by about ``1.1e-3``
because the authors' pmf is evaluated at ``k/256`` but normalised over ``k/255`` (it sums to
about 1.0011); see ``docs/statistics.md`` and :func:`sonarmap.paper.paper_kld`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from typing import Any, Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import FitError, InputError
from sonarmap.stats.components import Binning, family, log_pmf, quantization_levels

__all__ = [
    "MixtureFit",
    "fit_mixture",
    "histogram",
    "quantize",
    "quantize_lookup",
    "quantize_counts",
    "as_intensity_image",
    "as_counts",
    "kl_divergence",
    "monotone_object_log_pmf",
    "FLAG_DESCRIPTIONS",
    "component_pmf_matrix",
]

Method = Literal["lsq", "em"]

#: Meaning of every flag a fit can carry.
FLAG_DESCRIPTIONS: dict[str, str] = {
    "no_object": "total object-class weight below min_weight: no object in this ping",
    "collapsed_scale": "a component scale ended within 1.5 quantisation steps of zero",
    "scale_at_bound": "a component scale ended at its upper bound (parameter not identified)",
    "not_converged": "the optimiser stopped before converging",
    "degenerate": "fewer than 3 occupied levels: the fit is not identified",
    "all_zero": "every pixel is in the zero bin",
    "few_samples": "fewer than 100 pixels",
    "clipped": "more than 1% of the pixels were above 1 and clipped to the top level",
    "zero_mass": "the model gives zero probability to an occupied level (kld is infinite)",
    "collapsed_components": "two components of the same family ended with nearly identical "
    "parameters (within 5 %): the model has fewer distinct components than it claims",
}

#: Relative tolerance of the ``collapsed_components`` flag: two components of one family whose
#: parameters all agree within this fraction (of the larger) are one population.  Measured with
#: EM and ``families=("exponential", "rayleigh", "rayleigh")`` on the 10 real DIDSON test pings:
#: the 6 collapsed fits have object scales within 1.8 % of each other (0, 0, 0.01, 0.04, 1.4,
#: 1.8 %); the 4 separated fits differ by 75-145 % (0.17 vs 0.30, 0.12 vs 0.24, 0.12 vs 0.23,
#: 0.078 vs 0.19).
COLLAPSE_RTOL = 0.05


# ---------------------------------------------------------------------------- histogram


def _as_float_image(image: ArrayLike, name: str = "image") -> NDArray[np.floating[Any]]:
    """Validate dtype and size only (finiteness is checked by the fused kernels)."""
    try:
        arr = np.asarray(image)
    except Exception as exc:  # pragma: no cover - exotic array-likes
        raise InputError(f"{name}: cannot convert to an array ({exc})") from None
    if arr.dtype.kind in "biu":
        raise InputError(
            f"{name}: integer/bool dtype {arr.dtype}; intensities must be float in [0, 1] "
            "(convert 8-bit sensor data with image / 255)"
        )
    if arr.dtype.kind != "f":
        raise InputError(f"{name}: expected a float intensity image, got dtype {arr.dtype}")
    if arr.size == 0:
        raise InputError(f"{name}: image is empty (shape {arr.shape})")
    return arr


def _not_finite(name: str = "image") -> InputError:
    return InputError(f"{name}: contains NaN or infinite values")


def as_intensity_image(image: ArrayLike, name: str = "image") -> NDArray[np.floating[Any]]:
    """``image`` as a float array, validated: float dtype, not empty, finite (else an InputError naming ``name``)."""
    arr = _as_float_image(image, name)
    if not np.isfinite(arr).all():
        raise _not_finite(name)
    return arr


def _kernel_args(arr: NDArray[np.floating[Any]], n_levels: int, binning: str) -> tuple[Any, ...]:
    """Flat float32/float64 view, ``0``, ``1`` and the scale in the array's dtype, ``L``, floor.

    The scale has the image's dtype so that the kernels reproduce numpy's float32 arithmetic
    bit for bit (``rint(clip(y, 0, 1) * (L - 1))`` or ``floor(clip(y, 0, 1) * L)``).
    """
    n = _check_levels_binning(n_levels, binning)
    if arr.dtype not in (np.float32, np.float64):
        arr = arr.astype(np.float64)  # float16 / longdouble: rare, convert once
    flat = arr.reshape(-1)
    floor = binning == "floor"
    t = arr.dtype.type
    return flat, t(0), t(1), t(n if floor else n - 1), n, floor


_LEVELS_OK: dict[tuple[int, str], int] = {}
_NO_TABLE = np.zeros(0, dtype=np.uint8)  # levels_kernel: no look-up table


def _check_levels_binning(n_levels: int, binning: str) -> int:
    key = (n_levels, binning) if isinstance(n_levels, int) and isinstance(binning, str) else None
    if key is not None and key in _LEVELS_OK:
        return _LEVELS_OK[key]
    n = int(quantization_levels(n_levels, binning=binning).size)  # type: ignore[arg-type]
    if key is not None:
        _LEVELS_OK[key] = n
    return n


def quantize(
    image: ArrayLike, n_levels: int = 256, *, binning: Binning = "round"
) -> NDArray[np.unsignedinteger[Any]]:
    """Level index of every pixel.

    Parameters
    ----------
    image : ndarray of float, any shape
        Intensities in ``[0, 1]``; values outside are clipped (negatives -> level 0).
    n_levels : int
        Number of levels ``L``.
    binning : {"round", "floor"}
        ``"round"``: ``k = round(y (L - 1))`` (round half to even); ``"floor"``:
        ``k = min(floor(y L), L - 1)``.  See :func:`sonarmap.stats.components.quantization_levels`.

    Returns
    -------
    ndarray of uint8 (``L <= 256``) or uint16, same shape as ``image``

    Raises
    ------
    InputError
        Integer, bool or non-numeric dtype, empty image, NaN or inf.

    Notes
    -----
    One fused pass (numba): validation, clipping, scaling and rounding in the image's dtype.
    """
    return _fused_levels(image, n_levels, binning)


def quantize_lookup(
    image: ArrayLike, lut: NDArray[np.uint8], n_levels: int = 256, *, binning: Binning = "round"
) -> NDArray[np.uint8]:
    """``lut[quantize(image, n_levels, binning=binning)]``: a per-level table applied to every pixel.

    Parameters
    ----------
    image : ndarray of float, any shape
        Intensities in ``[0, 1]`` (see :func:`quantize`).
    lut : ndarray of uint8, shape (n_levels,)
        The value of every level (e.g. :func:`sonarmap.classify.local_map.map_lookup_table`).
    n_levels, binning
        As for :func:`quantize`.

    Returns
    -------
    ndarray of uint8, same shape as ``image``
        One fused pass (numba) of quantisation and look-up; the errors (:class:`InputError`) are
        those of :func:`quantize`.
    """
    return _fused_levels(image, n_levels, binning, lut)


def quantize_counts(image: ArrayLike, n_levels: int = 256, *, binning: Binning = "round"
                    ) -> tuple[NDArray[np.unsignedinteger[Any]], NDArray[np.float64]]:
    """:func:`quantize` and the histogram of its levels (float64 counts, shape ``(n_levels,)``)
    in one fused pass (numba); the errors are those of :func:`quantize`."""
    import sonarmap.stats._em_kernels as _emk

    arr = _as_float_image(image)
    flat, zero, one, scale, n, floor = _kernel_args(arr, n_levels, binning)
    out = np.empty(arr.shape, dtype=np.uint8 if n <= 256 else np.uint16)
    counts = np.empty(n)
    if not _emk.levels_counts_kernel(flat, zero, one, scale, n, floor, out.reshape(-1), counts):
        raise _not_finite()
    return out, counts


def _fused_levels(image: ArrayLike, n_levels: int, binning: str, lut: NDArray[np.uint8] | None = None) -> NDArray[Any]:
    """The level image, or ``lut`` applied to it, in one fused pass
    (:func:`sonarmap.stats._em_kernels.levels_kernel`)."""
    from sonarmap.stats._em_kernels import levels_kernel

    arr = _as_float_image(image)
    flat, zero, one, scale, n, floor = _kernel_args(arr, n_levels, binning)
    out = np.empty(arr.shape, dtype=np.uint8 if lut is not None or n <= 256 else np.uint16)
    table = _NO_TABLE if lut is None else lut
    if not levels_kernel(flat, zero, one, scale, n, floor, table, out.reshape(-1)):
        raise _not_finite()
    return out


def _histogram_clipped(
    image: ArrayLike, n_levels: int, binning: str
) -> tuple[NDArray[np.int64], int]:
    from sonarmap.stats._em_kernels import histogram_kernel

    arr = _as_float_image(image)
    flat, zero, one, scale, n, floor = _kernel_args(arr, n_levels, binning)
    counts = np.zeros(n, dtype=np.int64)
    clipped, finite = histogram_kernel(flat, zero, one, scale, n, floor, counts)
    if not finite:
        raise _not_finite()
    return counts, int(clipped)


def histogram(image: ArrayLike, n_levels: int = 256, *, binning: Binning = "round") -> NDArray[np.int64]:
    """Counts of pixels per quantisation level (:func:`quantize`), shape ``(n_levels,)``.

    One fused pass over the pixels (numba), no intermediate level image.
    """
    return _histogram_clipped(image, n_levels, binning)[0]


def as_counts(
    data: ArrayLike, n_levels: int = 256, *, binning: Binning = "round"
) -> tuple[NDArray[np.float64], int]:
    """Histogram counts from an image (ndim >= 2) or validated counts (1-D); also the clipped count."""
    arr = np.asarray(data)
    if arr.ndim == 1:
        if arr.dtype.kind not in "iuf":
            raise InputError(f"counts: expected numeric counts, got dtype {arr.dtype}")
        c = arr.astype(np.float64)
        if c.size < 2:
            raise InputError(f"counts: need at least 2 levels, got {c.size}")
        if not (c.min() >= 0.0 and c.max() < math.inf):  # = isfinite(c).all() and not (c < 0).any()
            raise InputError("counts: must be finite and non-negative")
        return c, 0
    counts, clipped = _histogram_clipped(arr, n_levels, binning)
    return counts.astype(np.float64), clipped


def monotone_object_log_pmf(class_log_pmf: ArrayLike) -> NDArray[np.float64]:
    """Class log-pmfs whose object classes' likelihood ratio against the background (row 0) never
    falls with intensity (see :meth:`MixtureFit.decision_log_pmf`).

    Parameters
    ----------
    class_log_pmf : ndarray, shape (n_classes, n_levels)
        ``log p(level | class)``, background first, levels in increasing intensity.

    Returns
    -------
    ndarray of float64, shape (n_classes, n_levels)
        A new array: every object row raised to ``log p(k|bg) + max_{j<=k} (log p(j|c) - log p(j|bg))``
        where that is finite; unchanged (bit for bit) wherever the ratio is at its running maximum,
        where the background is impossible, and in the background row.
    """
    import sonarmap.stats._em_kernels as _emk

    lp = np.array(class_log_pmf, dtype=np.float64)
    if lp.ndim != 2 or lp.shape[0] < 1:
        raise InputError(f"class_log_pmf: expected (n_classes, n_levels), got {np.shape(class_log_pmf)}")
    _emk.monotone_rows(lp)
    return lp


@functools.cache
def _rel_entr() -> Any:
    """:func:`scipy.special.rel_entr`, imported on first use (scipy stays out of ``import sonarmap``)."""
    from scipy.special import rel_entr

    return rel_entr


def kl_divergence(counts: ArrayLike, model_pmf: ArrayLike) -> float:
    """``D(p_hat || q) = sum p_hat ln(p_hat / q)`` in nats (eq. 11); ``p_hat = counts / sum``."""
    c = np.asarray(counts, dtype=np.float64)
    return _kl_of(c, np.asarray(model_pmf, dtype=np.float64), float(c.sum()))


def _kl_of(c: NDArray[np.float64], q: NDArray[np.float64], total: float) -> float:
    """:func:`kl_divergence` of float64 counts ``c`` whose sum is ``total`` (``float(c.sum())``)."""
    if total <= 0:
        raise FitError("counts: histogram is empty")
    return float(_rel_entr()(c / total, q).sum())


# ---------------------------------------------------------------------------- result


@dataclasses.dataclass(frozen=True, eq=False)
class MixtureFit:
    """A fitted intensity mixture (eq. 8, 19-21) with its diagnostics.

    Attributes
    ----------
    weights : ndarray, shape (n_components,)
        Mixture weights, summing to 1; index 0 is the zero spike when present.
    params : tuple of tuple of float
        Parameters of each component (``()`` for the spike; scale last).
    component_names : tuple of str
        Family of each component (``"zero"`` for the spike).
    component_classes : tuple of int
        Class index of each component (0 = background).
    class_names : tuple of str
        Class names, e.g. ``("background", "object")``.
    kld : float
        ``D(p_hat || p_model)`` in nats (eq. 11, see module notes).
    loglik : float
        Histogram log-likelihood ``sum_k n_k ln p_model(k)``.
    n_iter : int
        EM iterations (evaluations of the EM map, i.e. M-steps, under SQUAREM including the
        stabilising steps of rejected extrapolations) or least-squares function evaluations.
    converged : bool
        Whether the optimiser reported convergence.
    flags : frozenset of str
        Diagnostics (:data:`FLAG_DESCRIPTIONS`); a fit with flags must not be used blindly.
    levels : ndarray, shape (L,)
        Intensity of each level.
    counts : ndarray, shape (L,)
        The histogram that was fitted.
    method : str
        ``"lsq"`` or ``"em"``.
    binning : str
        Histogram binning (``"round"`` or ``"floor"``).
    loglik_trace : ndarray
        EM log-likelihood of the parameters held after each iteration (``n_iter + 1`` values,
        the start first; non-decreasing); empty for least squares.
    """

    weights: NDArray[np.float64]
    params: tuple[tuple[float, ...], ...]
    component_names: tuple[str, ...]
    component_classes: tuple[int, ...]
    class_names: tuple[str, ...]
    kld: float
    loglik: float
    n_iter: int
    converged: bool
    flags: frozenset[str]
    levels: NDArray[np.float64]
    counts: NDArray[np.float64]
    method: str
    binning: str = "round"
    loglik_trace: NDArray[np.float64] = dataclasses.field(
        default_factory=lambda: np.zeros(0), repr=False
    )
    discretization: str = "exact"
    # derived arrays computed once per fit (the fit is immutable); private
    _cache: dict[Any, Any] = dataclasses.field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    @classmethod
    def _of(cls, **fields: Any) -> MixtureFit:
        """The fit with every field given (``fields``, all but ``_cache``), built without the
        dataclass ``__init__``'s per-field ``object.__setattr__`` (one fit per ping)."""
        fit = object.__new__(cls)
        fit.__dict__.update(fields)
        fit.__dict__["_cache"] = {}
        return fit

    # ------------------------------------------------------------------ derived
    @property
    def n_components(self) -> int:
        """Number of components including the spike."""
        return len(self.component_names)

    @property
    def n_levels(self) -> int:
        """Number of quantisation levels ``L``."""
        return int(self.levels.size)

    @property
    def n_samples(self) -> float:
        """Total histogram count ``N``."""
        return float(self.counts.sum())

    @property
    def scales(self) -> tuple[float, ...]:
        """Scale of each component (NaN for the spike)."""
        return tuple(p[-1] if p else math.nan for p in self.params)

    @property
    def n_params(self) -> int:
        """Free parameters: ``n_components - 1`` weights plus all family parameters."""
        return self.n_components - 1 + sum(len(p) for p in self.params)

    @property
    def bic(self) -> float:
        """Bayesian information criterion ``k ln N - 2 loglik``."""
        return self.n_params * math.log(max(self.n_samples, 1.0)) - 2.0 * self.loglik

    @property
    def aic(self) -> float:
        """Akaike information criterion ``2 k - 2 loglik``."""
        return 2.0 * self.n_params - 2.0 * self.loglik

    @property
    def object_weight(self) -> float:
        """Total weight of the non-background classes."""
        cached = self._cache.get("object_weight")
        if cached is None:
            obj = _object_members(tuple(self.component_classes))  # = component_classes != 0
            cached = self._cache["object_weight"] = float(self.weights[obj].sum())
        return cached  # type: ignore[no-any-return]

    @property
    def ok(self) -> bool:
        """True when no flag other than ``no_object`` was raised."""
        return not (self.flags - {"no_object"})

    @property
    def classifiable(self) -> bool:
        """True when the fit can label pixels: a background and at least one object class, and
        not flagged ``all_zero`` or ``degenerate``."""
        return len(self.class_names) >= 2 and not self.flags & {"all_zero", "degenerate"}

    def _cached(self, key: str, make: Any) -> NDArray[np.float64]:
        """The read-only array ``make()`` computed once per fit under ``key`` (the fit is immutable)."""
        cached = self._cache.get(key)
        if cached is None:
            cached = np.asarray(make())
            cached.setflags(write=False)
            self._cache[key] = cached
        return cached  # type: ignore[no-any-return]

    def component_pmfs(self) -> NDArray[np.float64]:
        """``p_c(k)`` per component, shape ``(n_components, L)``, each summing to 1."""
        return self._pmf_matrix().copy()

    def _pmf_matrix(self) -> NDArray[np.float64]:
        """:meth:`component_pmfs`, read-only, computed once (:func:`fit_mixture` hands over the
        matrix it computed for the KLD)."""
        return self._cached("component_pmfs", lambda: component_pmf_matrix(
            self.component_names, self.params, self.levels, self.discretization))

    def component_log_pmfs(self) -> NDArray[np.float64]:
        """``log p_c(k)`` per component, shape ``(n_components, L)`` (``-inf`` where zero)."""
        with np.errstate(divide="ignore"):
            return np.log(self.component_pmfs())

    def pmf(self) -> NDArray[np.float64]:
        """Mixture pmf on the levels, shape ``(L,)``, summing to 1 (eq. 8)."""
        return self.weights @ self._pmf_matrix()

    def empirical_pmf(self) -> NDArray[np.float64]:
        """Normalised histogram ``p_hat``, shape ``(L,)``."""
        return self.counts / self.counts.sum()

    def class_prior(self, copy: bool = True) -> NDArray[np.float64]:
        """Prior probability of each class (sum of its component weights), shape ``(n_classes,)``;
        with ``copy=False`` the fit's own read-only array (computed once)."""
        prior = self._cache.get("class_prior")
        if prior is None:
            prior = self._cached("class_prior", self._class_prior)
        return prior.copy() if copy else prior  # type: ignore[no-any-return]

    def _class_prior(self) -> NDArray[np.float64]:
        return np.bincount(np.asarray(self.component_classes), weights=self.weights,
                           minlength=len(self.class_names)).astype(np.float64)

    def class_log_pmf(self, copy: bool = True) -> NDArray[np.float64]:
        """``log p(level | class)``, shape ``(n_classes, L)``, each class normalised over levels;
        with ``copy=False`` the fit's own read-only array (computed once).

        A class with zero weight uses the equal-weight average of its components' pmfs, so the
        result is always a proper pmf (classification with a zero prior is then well defined).
        """
        lp = self._cache.get("class_log_pmf")
        if lp is None:
            lp = self._cached("class_log_pmf", self._class_log_pmf)
        return lp.copy() if copy else lp  # type: ignore[no-any-return]

    def decision_log_pmf(self, copy: bool = True) -> NDArray[np.float64]:
        """:meth:`class_log_pmf` as the decisions use it: each object class's log-likelihood ratio
        against the background made non-decreasing in intensity (``copy=False``: the fit's own
        read-only array, computed once).

        A brighter echo is never less likely to be structure than a dimmer one.  A fitted family
        may still say so where the data has (almost) no pixels: a light-tailed object class (a
        Rayleigh or a gamma of large shape) against a heavier-tailed background falls below it
        again at the top levels, which would label the image's brightest pixels background (on
        the real ARIS frames with the gamma object that ``sonarmap calibrate`` chooses, up to 32
        of the brightest pixels of a frame).  Per object class ``c`` and level ``k``::

            log p'(k|c) = log p(k|background) + max_{j <= k} [log p(j|c) - log p(j|background)]

        (levels where both are impossible keep their values).  Used by the MRF unary (eq. 17-18),
        local MAP (eq. 12-13) and the ranges' echo evidence; the model itself (eq. 8-11, the
        KLD, :meth:`class_log_pmf`) is unchanged.  Where the ratio already rises with intensity
        (the paper's DIDSON fits) this is :meth:`class_log_pmf` exactly.

        Returns
        -------
        ndarray of float64, shape (n_classes, L)
        """
        lp = self._cache.get("decision_log_pmf")
        if lp is None:
            lp = self._cached("decision_log_pmf", lambda: monotone_object_log_pmf(self.class_log_pmf(copy=False)))
        return lp.copy() if copy else lp  # type: ignore[no-any-return]

    def _class_log_pmf(self) -> NDArray[np.float64]:
        comp = self._pmf_matrix()
        mix = np.empty((len(self.class_names), self.n_levels))
        for j, members in enumerate(_members_by_class(tuple(self.component_classes), len(self.class_names))):
            if len(members) == 1 and 0 < self.weights[members[0]] < math.inf:
                mix[j] = comp[members[0]]  # = (w / w) @ comp[members] = 1 x comp, exactly
                continue
            w = self.weights[members]
            tot = w.sum()
            w = w / tot if tot > 0 else np.full(w.size, 1.0 / w.size)
            mix[j] = w @ comp[members]
        with np.errstate(divide="ignore"):
            return np.log(mix)

    def class_pmf(self, copy: bool = True) -> NDArray[np.float64]:
        """``p(level | class)``, shape ``(n_classes, L)``; with ``copy=False`` the fit's own
        read-only array (computed once)."""
        pmf = self._cache.get("class_pmf")
        if pmf is None:
            pmf = self._cached("class_pmf", lambda: np.exp(self.class_log_pmf(copy=False)))
        return pmf.copy() if copy else pmf  # type: ignore[no-any-return]

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible summary (parameters, diagnostics, flags)."""
        return {
            "method": self.method,
            "binning": self.binning,
            "n_levels": self.n_levels,
            "component_names": list(self.component_names),
            "component_classes": list(self.component_classes),
            "class_names": list(self.class_names),
            "weights": [float(w) for w in self.weights],
            "params": [[float(v) for v in p] for p in self.params],
            "scales": [None if math.isnan(s) else float(s) for s in self.scales],
            "kld": float(self.kld),
            "loglik": float(self.loglik),
            "bic": float(self.bic),
            "aic": float(self.aic),
            "n_iter": int(self.n_iter),
            "converged": bool(self.converged),
            "flags": sorted(self.flags),
            "n_samples": float(self.n_samples),
        }


def _index(members: list[int]) -> NDArray[np.intp]:
    """``members`` as a read-only index array (numpy indexes with one faster than with a list)."""
    out = np.array(members, dtype=np.intp)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=64)
def _object_members(classes: tuple[Any, ...]) -> NDArray[np.intp]:
    """The indices of the components of the object classes (``classes != 0``), once per layout."""
    return _index([i for i, c in enumerate(classes) if c != 0])


@functools.lru_cache(maxsize=64)
def _members_by_class(classes: tuple[Any, ...], n_classes: int) -> tuple[NDArray[np.intp], ...]:
    """The component indices of each of ``n_classes`` classes (once per model layout)."""
    ints = [int(c) for c in classes]
    return tuple(_index([i for i, c in enumerate(ints) if c == j]) for j in range(n_classes))


# ---------------------------------------------------------------------------- fitting


@dataclasses.dataclass(frozen=True)
class _Spec:
    names: tuple[str, ...]
    spike: bool
    levels: NDArray[np.float64]
    smin: float
    smax: float
    min_ratio: float = 2.0
    discretization: str = "exact"
    rice_min: float = 0.0

    @functools.cached_property
    def free(self) -> tuple[int, ...]:
        """The indices of the continuous components."""
        return tuple(i for i, n in enumerate(self.names) if n != "zero")

    @functools.cached_property
    def general_bounds(self) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """:func:`_general_bounds` of this spec (computed once; the EM kernel only reads them)."""
        return _general_bounds(self)

    @functools.cached_property
    def fit_levels(self) -> NDArray[np.float64]:
        """A read-only view of ``levels`` for the fits (the fitters' kernels take the writable array)."""
        view = self.levels.view()
        view.setflags(write=False)
        return view


def component_pmf_matrix(
    names: Sequence[str],
    params: Sequence[tuple[float, ...]],
    levels: NDArray[np.float64],
    discretization: str = "exact",
) -> NDArray[np.float64]:
    """Component pmfs ``(C, L)`` on ``levels``.

    ``discretization="exact"``: each row sums to 1 on ``levels`` (closed-form fast path for the
    spike, exponential and Rayleigh).  ``"paper"``: the paper authors' discretisation - the density
    evaluated at ``levels`` (``k/L``, floor binning) but divided by its sum over ``k/(L-1)``, so rows
    sum to about 1.004; only for reproducing Table I.
    """
    x = np.asarray(levels, dtype=np.float64)
    L = x.size
    xn = np.arange(L) / (L - 1) if discretization == "paper" else x
    out = np.empty((len(names), L))
    for c, (name, p) in enumerate(zip(names, params)):
        e = out[c]  # each row computed in place (the same elementwise operations)
        if name == "zero":
            e[:] = 0.0
            e[0] = 1.0
        elif name == "exponential":
            np.exp(np.multiply(x, -1.0 / p[0], out=e), out=e)
            e /= e.sum() if xn is x else np.exp(xn * (-1.0 / p[0])).sum()
        elif name == "rayleigh":
            k = -0.5 / (p[0] * p[0])
            np.multiply(x, x, out=e)
            e *= k
            np.exp(e, out=e)
            e *= x
            e /= e.sum() if xn is x else (xn * np.exp((xn * xn) * k)).sum()
        elif discretization == "paper":
            raise InputError("discretization: 'paper' supports only exponential and rayleigh")
        else:
            out[c] = np.exp(log_pmf(name, p, x))
    return out


def _pmfs(spec: _Spec, params: Sequence[tuple[float, ...]]) -> NDArray[np.float64]:
    return component_pmf_matrix(spec.names, params, spec.levels, spec.discretization)


def _loglik(counts: NDArray[np.float64], q: NDArray[np.float64], positive: bool = False) -> float:
    """``sum_k n_k ln q_k`` over the occupied levels; ``positive`` promises ``q > 0`` there (a
    finite KLD of the same histogram): no zero to take the log of, no error state to set."""
    occ = counts > 0
    if positive:
        return float((counts[occ] * np.log(q[occ])).sum())
    with np.errstate(divide="ignore"):
        return float((counts[occ] * np.log(q[occ])).sum())


def _initial_guesses(
    spec: _Spec, counts: NDArray[np.float64]
) -> list[tuple[NDArray[np.float64], list[tuple[float, ...]]]]:
    """Data-driven starting points (several object scales), the preferred one first."""
    return list(_Starts(spec, counts))


class _Starts(Sequence[tuple[NDArray[np.float64], list[tuple[float, ...]]]]):
    """:func:`_initial_guesses` as a sequence that builds each start when it is first asked for
    (the fitters use the first alone unless its result looks unsound, see :func:`_em_best`)."""

    def __init__(self, spec: _Spec, counts: NDArray[np.float64], n_samples: float | None = None) -> None:
        import sonarmap.stats._em_kernels as _emk

        x = spec.levels
        N = float(counts.sum()) if n_samples is None else n_samples
        self._spec = spec
        self._frac0 = float(counts[0]) / N
        # the median and 99th percentile level above zero (np.cumsum + np.searchsorted, one pass)
        n_nz, i50, i99 = _emk.nonzero_quantiles(counts, 0.5, 0.99)
        if n_nz > 0:
            q50 = float(x[min(int(i50) + 1, x.size - 1)])
            q99 = float(x[min(int(i99) + 1, x.size - 1)])
        else:
            q50, q99 = 2 * spec.smin, 10 * spec.smin
        lo_s, hi_s = 2 * spec.smin, spec.smax / 2
        self._bg_scale = bg_scale = min(max(q50 / math.log(2.0), spec.smin * 1.5), hi_s)
        # the first start is the one used alone when its fit looks sound (see ``_needs_restart``);
        # q99 / 2 comes last: it can lead EM to an object that mimics the background
        obj_scales: list[float] = []
        for s in (q99, 4 * bg_scale, q99 / 2.0):
            s = min(max(s, lo_s), hi_s)
            if s not in obj_scales:
                obj_scales.append(s)
        self._obj_scales = obj_scales
        self._made: dict[int, tuple[NDArray[np.float64], list[tuple[float, ...]]]] = {}

    def __len__(self) -> int:
        return len(self._obj_scales)

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        i = range(len(self))[i]  # IndexError past the end, negative indices
        if i not in self._made:
            self._made[i] = _start_at(self._spec, self._frac0, self._bg_scale, self._obj_scales[i])
        return self._made[i]


def _start_at(spec: _Spec, frac0: float, bg_scale: float, so: float
              ) -> tuple[NDArray[np.float64], list[tuple[float, ...]]]:
    """The start of :func:`_initial_guesses` with background scale ``bg_scale`` and object scale ``so``."""
    params: list[tuple[float, ...]] = []
    w = [0.0] * len(spec.names)  # (Python floats: the weights' arithmetic is numpy's, see below)
    free = spec.free
    n_obj = len(free) - 1
    for j, i in enumerate(free):
        name = spec.names[i]
        scale = bg_scale if j == 0 else so * (1.0 + 0.5 * (j - 1))
        if name == "rayleigh":
            p: tuple[float, ...] = (scale / math.sqrt(math.pi / 2) if j == 0 else scale,)
        elif name == "exponential":
            p = (scale,)
        elif name == "gamma":
            p = (2.0, scale / 2.0)
        elif name == "weibull":
            p = (1.5, scale)
        elif name == "k":
            # moderately heavy-tailed start; the mean intensity matches the exponential's
            p = (4.0, scale)
        else:  # rice
            p = (0.8 * scale, 0.3 * scale)
        params.append(p)
        w[i] = (1.0 - frac0) * (0.95 if j == 0 else 0.05 / max(n_obj, 1)) if spec.spike else (
            0.95 if j == 0 else 0.05 / max(n_obj, 1)
        )
    full = [() if n == "zero" else params[free.index(i)] for i, n in enumerate(spec.names)]
    if len(w) >= 8:  # (numpy sums 8 terms and more pairwise)
        wa = np.array(w)
        if spec.spike:
            wa[0] = 1.0 - wa.sum()
        return wa / wa.sum(), full
    # numpy's float64 sum of fewer than 8 terms: added in order from 0.0
    if spec.spike:
        w[0] = 1.0 - _ordered_sum(w)
    total = _ordered_sum(w)
    return np.array([v / total for v in w]), full


def _ordered_sum(values: list[float]) -> float:
    """``0.0 + values[0] + values[1] + ...`` in that order (numpy's ``sum`` of fewer than 8 float64
    terms; Python's ``sum`` of floats compensates from 3.12 on)."""
    total = 0.0
    for v in values:
        total += v
    return total


def _bounds(spec: _Spec, name: str) -> list[tuple[float, float]]:
    fam = family(name)
    scale_b = (spec.smin, spec.smax)
    if fam.n_params == 1:
        return [scale_b]
    lo, hi = fam.shape_bounds
    return [(lo, hi), scale_b]


#: A restart that comes within this relative distance of the best converged result (every weight
#: and every parameter coordinate) is stopped there: it is climbing to the same maximum.  On the
#: DIDSON background pings, whose every fit runs all three starts, the restarts end within 2e-4 of
#: the first start's maximum (log-likelihood equal to 1e-5 nats) and pass 3e-2 of it after 9-18 of
#: their 24-57 EM steps.
MERGE_RTOL = 3e-2

_KernelArgs = tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]


def _em(
    spec: _Spec,
    counts: NDArray[np.float64],
    w0: NDArray[np.float64],
    params0: list[tuple[float, ...]],
    max_iter: int,
    tol: float,
    accel: bool = True,
    merge: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> tuple[NDArray[np.float64], list[tuple[float, ...]], int, bool, NDArray[np.float64]] | None:
    """EM entirely in one numba kernel, :func:`em_general_kernel` in the coordinates of
    :func:`_general_coords` (the exact M-step for the spike, exponential and Rayleigh
    components); SQUAREM-accelerated unless ``accel`` is False (plain EM, kept for comparison).

    ``merge``: ``(weights, coordinates)`` of a converged result of the same histogram; the run
    stops and returns None once it is within :data:`MERGE_RTOL` of it (climbing to the same
    maximum).  With ``spec.rice_min`` a run whose Rice component has become a Rayleigh stops
    there, not converged."""
    import sonarmap.stats._em_kernels as _emk

    w = np.array(w0, dtype=np.float64)
    trace = np.empty(max_iter + 1)
    kind, par, lo, hi = _general_coords(spec, params0)
    tail = _emk.em_general_args(accel, merge, MERGE_RTOL, float(spec.rice_min))
    n_iter, status = _emk.em_general_kernel(counts, spec.levels, kind, par, w, lo, hi, int(max_iter), float(tol), 3,
                                            trace, *tail)
    if status == _emk.EM_MERGED:
        return None
    coords = par.tolist()  # (Python floats: no numpy scalar per coordinate)
    params = [_from_coords(n, *coords[c]) for c, n in enumerate(spec.names)]
    return w, params, int(n_iter), status == _emk.EM_CONVERGED, trace[: n_iter + 1].copy()


def _eta_of(name: str, scale: float) -> float:
    return -1.0 / scale if name == "exponential" else -1.0 / (2.0 * scale * scale)


def _scale_of(name: str, eta: float) -> float:
    return -1.0 / eta if name == "exponential" else math.sqrt(-1.0 / (2.0 * eta))


_KIND_GENERAL = {"zero": 0, "exponential": 1, "rayleigh": 2, "gamma": 3, "weibull": 4, "rice": 5,
                 "k": 6}


def _to_coords(name: str, p: tuple[float, ...]) -> tuple[float, float]:
    """Family parameters -> the coordinates of :func:`em_general_kernel`."""
    if name in ("exponential", "rayleigh"):
        return _eta_of(name, p[0]), 0.0
    if name == "gamma":
        return p[0], 1.0 / p[1]
    if name in ("weibull", "k"):
        return p[0], math.log(p[1])
    if name == "rice":
        return p[0], 1.0 / (p[1] * p[1])
    return 0.0, 0.0


def _from_coords(name: str, c0: float, c1: float) -> tuple[float, ...]:
    if name in ("exponential", "rayleigh"):
        return (_scale_of(name, c0),)
    if name == "gamma":
        return (c0, 1.0 / c1)
    if name in ("weibull", "k"):
        return (c0, math.exp(c1))
    if name == "rice":
        return (c0, 1.0 / math.sqrt(c1))
    return ()


def _general_coords(spec: _Spec, params0: list[tuple[float, ...]]) -> _KernelArgs:
    """``(kind, par, lo, hi)`` of :func:`em_general_kernel`, the generalised EM for any families.

    Exact E-step; exact M-step for the exponential and Rayleigh components; for gamma (in its
    natural parameters, where the expected log-likelihood is concave), Weibull, Rice and K
    (``(nu, log scale)``, Bessel function by quadrature: :func:`~sonarmap.stats._em_kernels.log_bessel_k`) a few
    damped Newton steps with analytic gradient and Hessian, each accepted only if it increases
    that component's expected log-likelihood - so the log-likelihood never decreases.
    ``kind``, ``lo`` and ``hi`` depend on ``spec`` alone (:func:`_general_bounds`, shared).
    """
    kind, lo, hi = spec.general_bounds
    par = np.zeros((len(spec.names), 2))
    for c, name in enumerate(spec.names):
        if name == "zero":
            continue
        p = params0[c]
        if len(p) == 2:
            (b_lo, b_hi) = _bounds(spec, name)[0]
            p = (min(max(p[0], b_lo), b_hi), min(max(p[1], spec.smin), spec.smax))
        par[c] = _to_coords(name, p)
    return kind, par, lo, hi


def _general_bounds(spec: _Spec) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """``(kind, lo, hi)`` of :func:`_general_coords`: every component's family code and the
    bounds of its coordinates (coordinate 1 decreases with the scale for gamma and Rice)."""
    C = len(spec.names)
    kind = np.empty(C, dtype=np.int64)
    lo = np.zeros((C, 2))
    hi = np.zeros((C, 2))
    for c, name in enumerate(spec.names):
        kind[c] = _KIND_GENERAL[name]
        if name == "zero":
            continue
        if name in ("exponential", "rayleigh"):
            lo[c, 0], hi[c, 0] = _eta_of(name, spec.smin), _eta_of(name, spec.smax)
        else:
            (b_lo, b_hi) = _bounds(spec, name)[0]
            a = _to_coords(name, (b_lo, spec.smin))
            b = _to_coords(name, (b_hi, spec.smax))
            lo[c] = (b_lo, min(a[1], b[1]))
            hi[c] = (b_hi, max(a[1], b[1]))
    return kind, lo, hi


def _em_best(
    spec: _Spec,
    counts: NDArray[np.float64],
    starts: Sequence[tuple[NDArray[np.float64], list[tuple[float, ...]]]],
    max_iter: int,
    tol: float,
    min_weight: float,
    accel: bool = True,
) -> tuple[NDArray[np.float64], list[tuple[float, ...]], int, bool, NDArray[np.float64]]:
    """EM (:func:`_em`) from the first (preferred) start; the other starts only when its result
    looks unsound (:func:`_needs_restart`), keeping the highest log-likelihood.  A later start
    that comes within :data:`MERGE_RTOL` of the converged best so far is climbing to the same
    maximum and is stopped there (its result would be that maximum)."""
    w0, p0 = starts[0]
    best = _em(spec, counts, w0, p0, max_iter, tol, accel)
    assert best is not None
    if len(starts) > 1 and _needs_restart(spec, best, min_weight):
        ref = _merge_reference(spec, best)
        for w0, p0 in starts[1:]:
            out = _em(spec, counts, w0, p0, max_iter, tol, accel, ref)
            if out is not None and out[4][-1] > best[4][-1]:
                best = out
                ref = _merge_reference(spec, best)
    return best


def _merge_reference(spec: _Spec, fit: tuple[NDArray[np.float64], list[tuple[float, ...]], int, bool, Any]
                     ) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """``(weights, kernel coordinates)`` of an :func:`_em` result for :func:`_em`'s ``merge``
    (None unless it converged: only a maximum is a reference)."""
    return (fit[0], _general_coords(spec, fit[1])[1]) if fit[3] else None


def _needs_restart(
    spec: _Spec,
    out: tuple[NDArray[np.float64], list[tuple[float, ...]], int, bool, NDArray[np.float64]],
    min_weight: float,
    min_ratio: float = 2.0,
) -> bool:
    """Whether an EM result from one start should be checked against the other starts.

    True when it did not converge, or when it would be flagged (object weight below
    ``min_weight``, a scale collapsed to a level step or at its bound), or when an object scale is
    below ``min_ratio`` times the background scale (an object component mimicking the background:
    a local optimum EM reaches from some starts, e.g. Table I image 6).
    """
    w, params, _, conv, trace = out
    if not conv or not math.isfinite(float(trace[-1])):
        return True
    free = spec.free
    bg = free[0]
    s_bg = params[bg][-1]
    obj_w = 0.0
    for c in free:
        s = params[c][-1]
        if w[c] >= min_weight and (s <= 1.5 * spec.smin or s >= spec.smax * (1 - 1e-6)):
            return True
        if c != bg:
            obj_w += float(w[c])
            # scale ratio only comparable between one-parameter families (exponential, Rayleigh)
            if len(params[c]) == 1 and s < min_ratio * s_bg:
                return True
    return len(free) > 1 and obj_w < min_weight


def _collapsed_pair(names: Sequence[str], params: Sequence[tuple[float, ...]],
                    rtol: float = COLLAPSE_RTOL) -> bool:
    """Whether two components of the same (continuous) family have all parameters within
    ``rtol`` of each other (relative to the larger), see :data:`COLLAPSE_RTOL`."""
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            if names[i] == "zero" or names[i] != names[j]:
                continue
            if all(abs(a - b) <= rtol * max(abs(a), abs(b)) for a, b in zip(params[i], params[j])):
                return True
    return False


def _stick_to_weights(v: NDArray[np.float64], spike: bool, n: int) -> NDArray[np.float64]:
    """Stick-breaking fractions -> weights (spike, or the last component, takes the remainder)."""
    w = np.zeros(n)
    rest = 1.0
    start = 1 if spike else 0
    k = 0
    for i in range(start, n):
        if not spike and i == n - 1:
            w[i] = rest
            break
        w[i] = rest * v[k]
        rest -= w[i]
        k += 1
    if spike:
        w[0] = rest
    return w


def _weights_to_stick(w: NDArray[np.float64], spike: bool) -> NDArray[np.float64]:
    n = w.size
    v = []
    rest = 1.0
    start = 1 if spike else 0
    stop = n if spike else n - 1
    for i in range(start, stop):
        v.append(0.0 if rest <= 1e-15 else min(max(w[i] / rest, 0.0), 1.0))
        rest -= w[i]
    return np.array(v, dtype=np.float64)


def _lsq_jacobian_factory(
    spec: _Spec, nv: int, bg: int
) -> Any:
    """Analytic Jacobian of the least-squares residual for spike/exponential/Rayleigh mixtures.

    ``p_c(k) = f(x_k; s) / sum_j f(xn_j; s)`` (``xn = x`` unless ``discretization="paper"``), so
    ``d p_c(k) / d s = p_c(k) (g(x_k) - E_n[g]) / s^m`` with ``g = x, m = 2`` (exponential) or
    ``g = x^2, m = 3`` (Rayleigh), ``E_n`` the mean over the normalising grid.  Returns None for
    other families (finite differences are used then).
    """
    names = spec.names
    if not all(n in ("zero", "exponential", "rayleigh") for n in names):
        return None
    x = spec.levels
    L = x.size
    xn = np.arange(L) / (L - 1) if spec.discretization == "paper" else x
    n = len(names)
    spike = spec.spike
    smax = spec.smax
    x2, xn2 = x * x, xn * xn

    def dlogp(name: str, s: float) -> NDArray[np.float64]:
        # d log p_c(x_k) / d s, shape (L,)
        if name == "exponential":
            e = np.exp(xn * (-1.0 / s))
            return (x - (e @ xn) / e.sum()) / (s * s)
        e = xn * np.exp(xn2 * (-0.5 / (s * s)))
        return (x2 - (e @ xn2) / e.sum()) / (s * s * s)

    def jac(theta: NDArray[np.float64], w: NDArray[np.float64], params: list[tuple[float, ...]],
            P: NDArray[np.float64]) -> NDArray[np.float64]:
        J = np.zeros((L, theta.size))
        # weights from stick-breaking fractions: w_i = v_i prod_{j<i} (1 - v_j), remainder
        v = theta[:nv]
        order = list(range(1, n)) if spike else list(range(0, n - 1))
        rest_idx = 0 if spike else n - 1
        for m in range(nv):
            dw = np.zeros(n)
            for pos, i in enumerate(order):
                if pos < m:
                    continue
                prod = 1.0
                for j in range(pos):
                    if j != m:
                        prod *= 1.0 - v[j]
                dw[i] = prod if pos == m else -v[pos] * prod
            prod = 1.0
            for j in range(nv):
                if j != m:
                    prod *= 1.0 - v[j]
            dw[rest_idx] = -prod
            J[:, m] = dw @ P
        s_bg = params[bg][0]
        col = nv
        for i, name in enumerate(names):
            if name == "zero":
                continue
            s = params[i][0]
            d = w[i] * P[i] * dlogp(name, s)  # d r / d s_i
            if i == bg:
                J[:, col] += d
                bg_col = col
            else:
                ratio = theta[col]
                if ratio * s_bg < smax:  # s_i = ratio * s_bg (not capped)
                    J[:, col] = d * s_bg
                    J[:, bg_col] += d * ratio
            col += 1
        return J

    return jac


@dataclasses.dataclass(frozen=True, eq=False)
class _LsqLayout:
    """The least-squares parameter vector ``theta``: ``nv`` stick-breaking weight fractions, then
    every family's parameters, each object scale as a ratio (>= ``min_ratio``) to the background's.

    Attributes
    ----------
    spec : _Spec
    nv : int
        Number of stick-breaking fractions (``theta[:nv]``).
    bg : int
        Component index of the background family (the first continuous one).
    n_par : tuple of int
        Number of parameters of every component (0 for the spike).
    lo, hi : ndarray
        Box bounds of ``theta``.
    """

    spec: _Spec
    nv: int
    bg: int
    n_par: tuple[int, ...]
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]

    @classmethod
    def of(cls, spec: _Spec, w0: NDArray[np.float64]) -> _LsqLayout:
        """The layout of ``spec``'s mixture, with ``w0`` giving the number of weight fractions."""
        lo: list[float] = []
        hi: list[float] = []
        nv = len(_weights_to_stick(w0, spec.spike))
        lo += [0.0] * nv
        hi += [1.0] * nv
        bg = spec.free[0]
        ratio_max = spec.smax / spec.smin
        for i in spec.free:
            for b in _bounds(spec, spec.names[i])[:-1]:
                lo.append(b[0])
                hi.append(b[1])
            # object scales are parametrised as a ratio >= 1 to the background scale (ordering)
            lo.append(spec.smin if i == bg else spec.min_ratio)
            hi.append(spec.smax if i == bg else ratio_max)
        n_par = tuple(family(name).n_params for name in spec.names)
        return cls(spec, nv, bg, n_par, np.array(lo), np.array(hi))

    def unpack(self, theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], list[tuple[float, ...]]]:
        """Weights and parameter tuples of ``theta`` (object scales capped at ``smax``)."""
        spec = self.spec
        n = len(spec.names)
        w = _stick_to_weights(theta[: self.nv], spec.spike, n)
        params: list[tuple[float, ...]] = []
        k = self.nv
        s_bg = float(theta[self.nv + self.n_par[self.bg] - 1])
        for i in range(n):
            m = self.n_par[i]
            vals = [float(t) for t in theta[k : k + m]]
            if m and i != self.bg:
                vals[-1] = min(vals[-1] * s_bg, spec.smax)
            params.append(tuple(vals))
            k += m
        return w, params

    def start(self, w0: NDArray[np.float64], p0: list[tuple[float, ...]]) -> NDArray[np.float64]:
        """``theta`` of a start ``(w0, p0)``, strictly inside the bounds."""
        bg, lo_a, hi_a = self.bg, self.lo, self.hi
        s_bg0 = p0[bg][-1]
        p0r = [p if (not p or i == bg) else tuple(p[:-1]) + (max(p[-1] / s_bg0, self.spec.min_ratio),)
               for i, p in enumerate(p0)]
        theta0 = np.concatenate([_weights_to_stick(w0, self.spec.spike)] + [np.array(p, float) for p in p0r])
        theta0 = np.clip(theta0, lo_a, hi_a)
        # keep starts strictly inside the box (trust-region reflective requirement)
        span = hi_a - lo_a
        return np.clip(theta0, lo_a + 1e-9 * span, hi_a - 1e-9 * span)


def _lsq(
    spec: _Spec,
    counts: NDArray[np.float64],
    starts: list[tuple[NDArray[np.float64], list[tuple[float, ...]]]],
    loss: str,
    min_weight: float = 0.0,
    lazy: bool = False,
) -> tuple[NDArray[np.float64], list[tuple[float, ...]], int, bool]:
    """Bounded least squares from each start (all of them, or with ``lazy`` only until a result
    is not suspicious, see :func:`_lsq_suspicious`); the lowest cost wins."""
    from scipy.optimize import least_squares

    p_hat = counts / counts.sum()
    layout = _LsqLayout.of(spec, starts[0][0])
    analytic = _lsq_jacobian_factory(spec, layout.nv, layout.bg)
    cache: dict[str, Any] = {}

    def model(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], list[tuple[float, ...]], NDArray[np.float64]]:
        key = theta.tobytes()
        if cache.get("key") != key:
            w, params = layout.unpack(theta)
            cache.update(key=key, val=(w, params, _pmfs(spec, params)))
        return cache["val"]  # type: ignore[no-any-return]

    def resid(theta: NDArray[np.float64]) -> NDArray[np.float64]:
        w, _, P = model(theta)
        return w @ P - p_hat

    def jac(theta: NDArray[np.float64]) -> NDArray[np.float64]:
        w, params, P = model(theta)
        return analytic(theta, w, params, P)  # type: ignore[no-any-return]

    best = None
    nfev = 0
    for w0, p0 in starts:
        res = least_squares(resid, layout.start(w0, p0), jac=jac if analytic is not None else "2-point",
                            bounds=(layout.lo, layout.hi), method="trf", loss=loss,
                            x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
        nfev += int(res.nfev)
        if best is None or res.cost < best.cost:
            best = res
        if lazy and not _lsq_suspicious(spec, res, layout.unpack, min_weight):
            break
    assert best is not None
    w, params = layout.unpack(best.x)
    return w, params, nfev, bool(best.status > 0)


def _lsq_suspicious(spec: _Spec, res: Any, unpack: Any, min_weight: float) -> bool:
    """A least-squares result worth checking against another start: not converged, or one that
    would be flagged (no object, a weighted scale collapsed or at its bound, an object scale at
    its lower ratio bound)."""
    if res.status <= 0:
        return True
    w, params = unpack(res.x)
    return _needs_restart(spec, (w, params, 0, True, np.zeros(1)), min_weight, spec.min_ratio * 1.001)


def _paper_start(spec: _Spec) -> tuple[NDArray[np.float64], list[tuple[float, ...]]] | None:
    """The paper authors' ``p0 = (pi1, pi2, s1, s2) = (0.32, 0.01, 0.03, 0.2)``."""
    if spec.names != ("zero", "exponential", "rayleigh"):
        return None
    return np.array([0.67, 0.32, 0.01]), [(), (0.03,), (0.2,)]


def _class_layout(names: tuple[str, ...], zero_spike: bool, class_names: Sequence[str] | None
                  ) -> tuple[tuple[int, ...], tuple[str, ...]]:
    """The class of every component (the spike and the first family are the background, each
    further family an object class) and the class names (default ``background``, ``object`` or
    ``object1``, ``object2``, ...)."""
    n_classes = len(names) - (1 if zero_spike else 0)
    classes = tuple(0 if (n == "zero" or i == (1 if zero_spike else 0)) else i - (1 if zero_spike else 0)
                    for i, n in enumerate(names))
    if class_names is None:
        cnames: tuple[str, ...] = ("background",) + (
            ("object",) if n_classes == 2 else tuple(f"object{j}" for j in range(1, n_classes))
        )
    else:
        cnames = tuple(str(c) for c in class_names)
        if len(cnames) != n_classes:
            raise InputError(f"class_names: need {n_classes} names, got {len(cnames)}")
    return classes, cnames


def _input_flags(counts: NDArray[np.float64], n_clipped: int, zero_spike: bool, N: float) -> set[str]:
    """Flags of the histogram itself (``N`` its total): ``few_samples``, ``clipped``, ``degenerate``,
    ``all_zero``."""
    flags: set[str] = set()
    if N < 100:
        flags.add("few_samples")
    if n_clipped > 0.01 * N:
        flags.add("clipped")
    if int(np.count_nonzero(counts)) < 3:
        flags.add("degenerate")
    if zero_spike and counts[0] == N:
        flags.add("all_zero")
    return flags


def _lsq_fit(spec: _Spec, counts: NDArray[np.float64], starts: Sequence[Any], loss: str, min_weight: float, *,
             warm: bool, accel: bool = True) -> tuple[NDArray[np.float64], list[tuple[float, ...]], int, bool]:
    """The least-squares fit (eq. 10); with ``warm`` (no caller's init) it starts from a short EM
    fit, and from the paper's p0 only when that result looks unsound."""
    lsq_starts = [] if warm else list(starts)
    if warm:
        em_out = _em_best(spec, counts, starts, 200, 1e-9, min_weight, accel)
        lsq_starts = [(em_out[0], em_out[1])]
        ps = _paper_start(spec)
        if ps is not None:
            lsq_starts.append(ps)
    return _lsq(spec, counts, lsq_starts, loss, min_weight, lazy=warm)


def _result_flags(flags: set[str], names: tuple[str, ...], classes: tuple[int, ...], w: NDArray[np.float64],
                  params: list[tuple[float, ...]], *, n_families: int, min_weight: float, step: float,
                  scale_max: float) -> list[tuple[float, ...]]:
    """Add the flags of a fitted result to ``flags`` (``no_object``, ``collapsed_scale``,
    ``scale_at_bound``, ``collapsed_components``); returns the parameters, an unidentified object
    scale reported at its bound."""
    obj = _object_members(tuple(classes))
    wl = w.tolist()
    # = w[classes != 0].sum() (one member: its weight, compared alike)
    obj_w = wl[obj[0]] if len(obj) == 1 else float(w[obj].sum())
    if n_families > 1 and obj_w < min_weight:
        flags.add("no_object")
    if "no_object" in flags:
        # an object scale with (almost) no weight is not identified: report it at its bound,
        # the convention of the paper's Table I (image 6: sigma = 1.000)
        params = [p if (cls == 0 or not p) else tuple(p[:-1]) + (float(scale_max),)
                  for p, cls in zip(params, classes)]
    for c, (name, p) in enumerate(zip(names, params)):
        if name == "zero" or wl[c] < min_weight:
            continue
        if p[-1] <= 1.5 * step:
            flags.add("collapsed_scale")
        if p[-1] >= scale_max * (1 - 1e-6):
            flags.add("scale_at_bound")
    if "no_object" not in flags and _collapsed_pair(names, params):
        flags.add("collapsed_components")
    return list(params)


class _FitProblem(NamedTuple):
    """What :func:`fit_mixture` fits: the histogram, the model and its class layout (a named tuple:
    one per ping, built without a frozen dataclass's per-field ``object.__setattr__``)."""

    spec: _Spec
    counts: NDArray[np.float64]
    n_clipped: int
    n_samples: float
    n_families: int
    classes: tuple[int, ...]
    class_names: tuple[str, ...]


def _fit_problem(data: ArrayLike, families: Sequence[str], *, method: str, zero_spike: bool, n_levels: int,
                 binning: Binning, class_names: Sequence[str] | None, min_weight: float, scale_max: float,
                 min_scale_ratio: float, discretization: str, rice_min: float = 0.0) -> _FitProblem:
    """Check :func:`fit_mixture`'s options (in its documented order of errors) and build the
    histogram of ``data``, the model spec and the class layout."""
    if method not in ("lsq", "em"):
        raise InputError(f"method: must be 'lsq' or 'em', got {method!r}")
    fams = _family_names(families)
    counts, n_clipped = as_counts(data, n_levels, binning=binning)
    N = float(counts.sum())
    if N <= 0:
        raise FitError("data: histogram is empty (no pixels)")
    if not 0 <= min_weight < 1:
        raise InputError(f"min_weight: must be in [0, 1), got {min_weight}")
    key = (fams, zero_spike, counts.size, binning, scale_max, min_scale_ratio, discretization, method, rice_min)
    try:
        cached = class_names is None and hash(key) is not None
    except TypeError:  # an option of an unhashable type: no caching
        cached = False
    layout = _LAYOUTS.get(key) if cached else None
    if layout is None:
        layout = _model_layout(fams, zero_spike, counts.size, binning, class_names, scale_max, min_scale_ratio,
                               discretization, method, rice_min)
        if cached:
            if len(_LAYOUTS) >= 64:
                _LAYOUTS.clear()
            _LAYOUTS[key] = layout
    spec, classes, cnames = layout
    return _FitProblem(spec, counts, n_clipped, N, len(fams), classes, cnames)


def _family_names(families: Sequence[str]) -> tuple[str, ...]:
    """The canonical names of ``families`` (at least one, no spike), else an InputError."""
    key = tuple(families) if isinstance(families, tuple) else None
    fams = _FAMILY_NAMES.get(key) if key is not None else None  # type: ignore[arg-type]
    if fams is None:
        fams = tuple(family(f).name for f in families)
        if not fams or "zero" in fams:
            raise InputError("families: need at least one continuous family (the spike is zero_spike)")
        if key is not None and all(isinstance(f, str) for f in key):
            _FAMILY_NAMES[key] = fams
    return fams


def _model_layout(fams: tuple[str, ...], zero_spike: bool, n: int, binning: Binning,
                  class_names: Sequence[str] | None, scale_max: float, min_scale_ratio: float,
                  discretization: str, method: str,
                  rice_min: float = 0.0) -> tuple[_Spec, tuple[int, ...], tuple[str, ...]]:
    """The model of :func:`_fit_problem` on ``n`` levels: its spec, the class of every component
    and the class names; an InputError for a bad option."""
    levels = quantization_levels(n, binning=binning)
    step = float(levels[1])
    if not step < scale_max:
        raise InputError(f"scale_max: must exceed one level step ({step:.3g}), got {scale_max}")
    names = (("zero",) if zero_spike else ()) + fams
    if discretization not in ("exact", "paper"):
        raise InputError(f"discretization: must be 'exact' or 'paper', got {discretization!r}")
    if discretization == "paper" and (method != "lsq" or binning != "floor"):
        raise InputError("discretization: 'paper' needs method='lsq' and binning='floor'")
    if not min_scale_ratio >= 1.0:
        raise InputError(f"min_scale_ratio: must be >= 1, got {min_scale_ratio}")
    if not (math.isfinite(rice_min) and rice_min >= 0):
        raise InputError(f"rice_min: must be a finite number >= 0, got {rice_min}")
    spec = _Spec(names, zero_spike, levels, step, float(scale_max), float(min_scale_ratio), discretization,
                 float(rice_min))
    return (spec, *_class_layout(names, zero_spike, class_names))


#: :func:`_family_names` per tuple of family names, :func:`_model_layout` per option set (at most
#: 64; the pings of a recording share one model, and their fits a read-only view of its levels).
_FAMILY_NAMES: dict[tuple[str, ...], tuple[str, ...]] = {}
_LAYOUTS: dict[tuple[Any, ...], tuple[_Spec, tuple[int, ...], tuple[str, ...]]] = {}


def _starting_points(spec: _Spec, counts: NDArray[np.float64],
                     init: tuple[ArrayLike, Sequence[tuple[float, ...]]] | None, n_samples: float | None = None
                     ) -> Sequence[tuple[NDArray[np.float64], list[tuple[float, ...]]]]:
    """The caller's ``init`` (checked, weights normalised) as the one start, else the initial
    guesses of :func:`_initial_guesses` (``n_samples``: ``float(counts.sum())`` when known)."""
    if init is None:
        return _Starts(spec, counts, n_samples)
    names = spec.names
    w_init = np.asarray(init[0], dtype=np.float64)
    p_init = [tuple(float(v) for v in p) for p in init[1]]
    if w_init.shape != (len(names),) or len(p_init) != len(names):
        raise InputError(f"init: need {len(names)} weights and parameter tuples")
    return [(w_init / w_init.sum(), p_init)]


class _RawFit(NamedTuple):
    """A fitter's result before normalisation and flagging."""

    weights: NDArray[np.float64]
    params: list[tuple[float, ...]]
    n_iter: int
    converged: bool
    loglik_trace: NDArray[np.float64]


def _run_fitter(problem: _FitProblem, flags: set[str], init: tuple[ArrayLike, Sequence[tuple[float, ...]]] | None,
                *, method: str, loss: str, max_iter: int, tol: float, min_weight: float,
                accelerate: bool = True) -> _RawFit:
    """Fit with ``method`` from ``init`` or the initial guesses (least squares without ``init``
    starts from a short EM fit); an all-zero histogram is the spike alone, without fitting."""
    spec, counts = problem.spec, problem.counts
    starts = _starting_points(spec, counts, init, problem.n_samples)
    trace = np.zeros(0)
    if "all_zero" in flags:
        w = np.zeros(len(spec.names))
        w[0] = 1.0
        params = starts[0][1]
        n_iter, conv = 0, True
    elif method == "em":
        w, params, n_iter, conv, trace = _em_best(spec, counts, starts, max_iter, tol, min_weight, accelerate)
    else:
        w, params, n_iter, conv = _lsq_fit(spec, counts, starts, loss, min_weight, warm=init is None,
                                           accel=accelerate)
    return _RawFit(w, params, n_iter, conv, trace)


def _model_kld(counts: NDArray[np.float64], q: NDArray[np.float64], discretization: str, total: float) -> float:
    """``D(p_hat || q)`` (eq. 11; ``total`` is ``float(counts.sum())``); with the paper's
    discretisation against the unnormalised model, as the authors computed it."""
    if discretization == "paper":
        from scipy.special import rel_entr

        return float(np.sum(rel_entr(counts / total, q)))
    return _kl_of(counts, q, total)


def _finished_fit(problem: _FitProblem, raw: _RawFit, flags: set[str], *, method: Method, binning: Binning,
                  min_weight: float) -> MixtureFit:
    """The :class:`MixtureFit` of a fitter's result: weights renormalised, KLD and
    log-likelihood of the model, the result's flags added to ``flags``."""
    spec, counts = problem.spec, problem.counts
    w = np.maximum(np.asarray(raw.weights, dtype=np.float64), 0.0)  # = np.clip(w, 0, None), without its wrapper
    w = w / w.sum()
    pmfs = _pmfs(spec, raw.params)
    q = w @ pmfs
    kld = _model_kld(counts, q, spec.discretization, problem.n_samples)
    ll = _loglik(counts, q, math.isfinite(kld))
    if not math.isfinite(kld):
        flags.add("zero_mass")
    if not raw.converged:
        flags.add("not_converged")
    params = _result_flags(flags, spec.names, problem.classes, w, raw.params, n_families=problem.n_families,
                           min_weight=min_weight, step=spec.smin, scale_max=spec.smax)
    w.setflags(write=False)
    counts.setflags(write=False)
    fit = MixtureFit._of(
        weights=w,
        params=tuple([tuple(map(float, p)) for p in params]),
        component_names=spec.names,
        component_classes=problem.classes,
        class_names=problem.class_names,
        kld=kld,
        loglik=ll,
        n_iter=int(raw.n_iter),
        converged=bool(raw.converged),
        flags=frozenset(flags),
        levels=spec.fit_levels,
        counts=counts,
        method=method,
        binning=binning,
        loglik_trace=raw.loglik_trace,
        discretization=spec.discretization,
    )
    if all(p is q for p, q in zip(params, raw.params)):
        # the fit's own parameters (none reported at a bound): its component pmfs are these
        pmfs.setflags(write=False)
        fit._cache["component_pmfs"] = pmfs
    return fit


def fit_mixture(
    data: ArrayLike, *, families: Sequence[str] = ("exponential", "rayleigh"), method: Method = "lsq",
    zero_spike: bool = True, n_levels: int = 256, binning: Binning = "round",
    class_names: Sequence[str] | None = None, min_weight: float = 2e-3, scale_max: float = 1.0,
    loss: str = "linear", max_iter: int = 1000, tol: float = 1e-11,
    init: tuple[ArrayLike, Sequence[tuple[float, ...]]] | None = None, min_scale_ratio: float = 2.0,
    discretization: Literal["exact", "paper"] = "exact", accelerate: bool = True, rice_min: float = 0.0,
) -> MixtureFit:
    """Fit a zero-spike mixture of discrete pmfs to one ping's intensity histogram.

    Parameters
    ----------
    data : ndarray
        A float intensity image in ``[0, 1]`` (any shape with ndim >= 2), or a 1-D array of
        ``n_levels`` histogram counts.
    families : sequence of str
        Component families after the spike; the first is the background's continuous part
        (eq. 19), the rest are object classes (eq. 20-21).  Default: the paper's exponential +
        Rayleigh.
    method : {"lsq", "em"}
        Bounded least squares on the normalised histogram (the paper's fit) or exact EM on the
        histogram counts (maximum likelihood).
    zero_spike : bool
        Include the explicit zero spike ``delta(y)`` (real DIDSON pings are ~60 % zeros).
    n_levels : int
        Number of quantisation levels ``L`` (ignored for counts input, where it is ``len(data)``).
    binning : {"round", "floor"}
        Histogram convention, see :func:`quantize`.
    class_names : sequence of str, optional
        One name per class (background first); default ``("background", "object")`` or
        ``("background", "object1", "object2", ...)``.
    min_weight : float
        Object-class weight below which the fit is flagged ``"no_object"``.
    scale_max : float
        Upper bound of every scale (intensity units); the lower bound is one level step.
    loss : str
        ``least_squares`` loss for ``method="lsq"`` (``"linear"``: the paper's; ``"soft_l1"``: robust).
    max_iter, tol : int, float
        EM iteration limit (EM map evaluations, see :attr:`MixtureFit.n_iter`) and relative
        log-likelihood tolerance: EM stops when one EM step gains at most ``tol * (|loglik| + 1)``.
    init : (weights, params), optional
        Starting point (same layout as :attr:`MixtureFit.weights` / ``params``).
    min_scale_ratio : float
        Least squares only: every object scale is at least this multiple of the background scale
        (else the object of an empty ping such as Table I image 6 mimics the background).
    discretization : {"exact", "paper"}
        ``"exact"`` (default): pmfs normalised on the levels.  ``"paper"``: the authors' discretisation
        (see :func:`component_pmf_matrix`), least squares with floor binning and exponential/Rayleigh
        only - for reproducing Table I; ``kld`` is then computed with the unnormalised model as they did.
    accelerate : bool
        SQUAREM-accelerated EM (also least squares' EM warm start): the same stopping rule, 3-10x
        fewer EM steps on overlapping components.  False: plain EM.
    rice_min : float
        EM stops (``not_converged``) after 30 steps once a Rice's ``nu / sigma`` is below this: it
        has become a Rayleigh, where EM creeps (:data:`~sonarmap.stats.selection.RICE_AS_RAYLEIGH`).

    Returns
    -------
    MixtureFit

    Raises
    ------
    InputError
        Bad image (NaN, integer dtype, empty) or bad options.
    FitError
        Empty histogram.

    Notes
    -----
    Implements eq. 8-11 and 19-21 of Teixeira et al. (IROS 2018).  Degenerate inputs (all-zero, constant, tiny
    images; a vanishing object component as in Table I image 6) give a result carrying :attr:`MixtureFit.flags`,
    never a silently wrong one.
    """
    problem = _fit_problem(data, families, method=method, zero_spike=zero_spike, n_levels=n_levels, binning=binning,
                           class_names=class_names, min_weight=min_weight, scale_max=scale_max,
                           min_scale_ratio=min_scale_ratio, discretization=discretization, rice_min=rice_min)
    flags = _input_flags(problem.counts, problem.n_clipped, zero_spike, problem.n_samples)
    raw = _run_fitter(problem, flags, init, method=method, loss=loss, max_iter=max_iter, tol=tol,
                      min_weight=min_weight, accelerate=accelerate)
    return _finished_fit(problem, raw, flags, method=method, binning=binning, min_weight=min_weight)
