"""Mixture components as discrete pmfs on the sensor's quantisation levels (paper eq. 8-10, 19-21).

Every component is a *probability mass function* over the ``L`` quantisation levels ``x_k``
(:func:`quantization_levels`), obtained by evaluating a continuous density at the levels and
normalising **on the same grid**, so ``sum_k p(x_k) = 1`` exactly.  Continuous densities are never
compared with histograms directly: the paper's histograms are pmfs, and so are our models.

Families
--------
=============  ===============  ==================================================================
name           parameters       unnormalised log-density at ``x > 0``
=============  ===============  ==================================================================
``zero``       ()               the zero spike: all mass on level 0 (``delta(y)`` of eq. 19)
``exponential``  (scale,)       ``-x / scale``                 (``lambda = 1 / scale``, eq. 19)
``rayleigh``   (scale,)         ``log x - x^2 / (2 scale^2)``  (``sigma = scale``, eq. 21)
``gamma``      (shape, scale)   ``(shape - 1) log x - x / scale``
``weibull``    (shape, scale)   ``(shape - 1) log x - (x / scale)^shape``
``rice``       (nu, scale)      ``log x - (x - nu)^2 / (2 scale^2) + log i0e(x nu / scale^2)``
``k``          (nu, scale)      ``(nu - 1)/2 log x + log K_{nu-1}(2 sqrt(nu x / scale))``
=============  ===============  ==================================================================

The scale is always the *last* parameter.  Densities singular at zero (gamma or Weibull with
``shape < 1``) are evaluated at half a level step instead of at ``x_0 = 0``.

K distribution
--------------
The intensity K distribution, the standard model of sonar and radar clutter: speckle
``e ~ Exp(mean scale)`` modulated by a gamma texture ``g ~ Gamma(nu, 1/nu)`` (mean 1), ``I = g e``::

    p(x) = 2 / (Gamma(nu) b) (x / b)^((nu - 1) / 2) K_{nu-1}(2 sqrt(x / b)),   b = scale / nu

``scale`` is the mean intensity, so ``nu -> infinity`` is the exponential of the same scale (eq.
19's background) and small ``nu`` is heavy-tailed.  ``K_v`` is evaluated as
``log(scipy.special.kve(v, z)) - z``, falling back to the quadrature of
:func:`sonarmap.stats._em_kernels.log_bessel_k` where ``kve`` overflows (large order, small
argument); level 0 is always evaluated at half a level step (the density is singular there for
``nu <= 1`` and finite otherwise), the same convention as the EM kernel.  ``nu`` is bounded to
``[0.1, 100]``: at ``nu = 100`` the pmf on 256 levels is within a few 1e-3 (total variation) of
the exponential.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy import special

from sonarmap.errors import InputError

__all__ = [
    "Binning",
    "FAMILIES",
    "Family",
    "family",
    "quantization_levels",
    "log_pmf",
    "pmf",
]

Binning = Literal["round", "floor"]


def quantization_levels(n_levels: int = 256, *, binning: Binning = "round") -> NDArray[np.float64]:
    """Intensity of each quantisation level.

    Parameters
    ----------
    n_levels : int
        Number of levels ``L`` (256 for 8-bit sensors).
    binning : {"round", "floor"}
        ``"round"``: levels ``x_k = k / (L - 1)``, ``k = 0 .. L-1`` - exactly the values of
        ``L``-level sensor data (8-bit: ``k / 255``); a continuous value ``y`` belongs to level
        ``round(y (L - 1))``.  ``"floor"``: ``L`` equal bins ``[k / L, (k + 1) / L)`` on ``[0, 1]``
        (last bin closed) represented by their left edges ``x_k = k / L`` - the convention of the
        paper authors' ``numpy.histogram(y, linspace(0, 1, L + 1))``.

    Returns
    -------
    ndarray, shape (n_levels,)
    """
    n = _check_levels(n_levels)
    k = np.arange(n, dtype=np.float64)
    if binning == "round":
        return k / (n - 1)
    if binning == "floor":
        return k / n
    raise InputError(f"binning: must be 'round' or 'floor', got {binning!r}")


def _check_levels(n_levels: int) -> int:
    if isinstance(n_levels, bool) or int(n_levels) != n_levels or not 2 <= int(n_levels) <= 65536:
        raise InputError(f"n_levels: must be an integer in [2, 65536], got {n_levels!r}")
    return int(n_levels)


@dataclasses.dataclass(frozen=True)
class Family:
    """A component family: name, parameter names, and parameter bounds.

    Attributes
    ----------
    name : str
        Family name (see the module table).
    param_names : tuple of str
        Parameter names; the last is always ``"scale"`` (none for ``"zero"``).
    shape_bounds : tuple of float
        Bounds of the first (shape) parameter for two-parameter families; for ``rice`` the bound of
        ``nu`` is in intensity units.
    half_step_at_zero : bool
        Level 0 is always evaluated at half a level step (the K distribution).
    """

    name: str
    param_names: tuple[str, ...]
    shape_bounds: tuple[float, float] = (0.0, 0.0)
    half_step_at_zero: bool = False

    @property
    def n_params(self) -> int:
        """Number of free parameters (weights excluded)."""
        return len(self.param_names)

    @property
    def is_spike(self) -> bool:
        """Whether this is the zero spike."""
        return self.name == "zero"

    def log_density(self, x: NDArray[np.float64], params: tuple[float, ...]) -> NDArray[np.float64]:
        """Unnormalised log-density at intensities ``x`` (``-inf`` where it is zero)."""
        x = np.asarray(x, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.name == "zero":
                return np.where(x == 0, 0.0, -np.inf)
            if self.name == "exponential":
                (s,) = params
                return -x / s
            if self.name == "rayleigh":
                (s,) = params
                return np.log(x) - x * x / (2 * s * s)
            if self.name == "gamma":
                a, s = params
                return (a - 1.0) * np.log(x) - x / s
            if self.name == "weibull":
                c, s = params
                z = x / s
                return (c - 1.0) * np.log(z) - z**c
            if self.name == "rice":
                nu, s = params
                s2 = s * s
                return np.log(x) - (x - nu) ** 2 / (2 * s2) + np.log(special.i0e(x * nu / s2))
            if self.name == "k":
                return _k_log_density(x, *params)
        raise InputError(f"family: unknown family {self.name!r}")  # pragma: no cover


def _k_log_density(x: NDArray[np.float64], nu: float, scale: float) -> NDArray[np.float64]:
    """Normalised log-density of the intensity K distribution (mean ``scale``, shape ``nu``)."""
    b = scale / nu
    v = nu - 1.0
    xb = x / b
    z = 2.0 * np.sqrt(xb)
    logk = np.log(special.kve(v, z)) - z
    bad = ~np.isfinite(logk) & (z > 0)
    if bad.any():  # kve overflows for a large order at a small argument
        from sonarmap.stats._em_kernels import log_bessel_k

        out = np.empty(5)
        logk[bad] = [log_bessel_k(v, float(zi), False, out) for zi in z[bad]]
    out_ld: NDArray[np.float64] = (
        math.log(2.0) - math.lgamma(nu) - math.log(b) + 0.5 * v * np.log(xb) + logk
    )
    return out_ld


FAMILIES: dict[str, Family] = {
    "zero": Family("zero", ()),
    "exponential": Family("exponential", ("scale",)),
    "rayleigh": Family("rayleigh", ("scale",)),
    "gamma": Family("gamma", ("shape", "scale"), (0.2, 50.0)),
    "weibull": Family("weibull", ("shape", "scale"), (0.2, 20.0)),
    "rice": Family("rice", ("nu", "scale"), (0.0, 1.0)),
    "k": Family("k", ("nu", "scale"), (0.1, 100.0), half_step_at_zero=True),
}


def family(name: str | Family) -> Family:
    """Look up a family by name.

    Raises
    ------
    InputError
        If the name is unknown (the message lists the valid names).
    """
    if isinstance(name, Family):
        return name
    try:
        return FAMILIES[str(name).lower()]
    except KeyError:
        raise InputError(
            f"families: unknown family {name!r}; choose from {', '.join(sorted(FAMILIES))}"
        ) from None


def log_pmf(
    fam: str | Family, params: tuple[float, ...], levels: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Log of the component pmf on ``levels``, normalised on the same grid (eq. 9-10, 19-21).

    Parameters
    ----------
    fam : str or Family
        Component family.
    params : tuple of float
        Family parameters (see the module table); scales in intensity units.
    levels : ndarray, shape (L,)
        The quantisation levels (:func:`quantization_levels`); ``levels[0]`` must be 0.

    Returns
    -------
    ndarray, shape (L,)
        ``log p(x_k)`` with ``logsumexp = 0``; ``-inf`` where the pmf is zero.
    """
    f = family(fam)
    x = np.asarray(levels, dtype=np.float64)
    logf = f.log_density(x, tuple(float(p) for p in params))
    if x.size > 1 and (f.half_step_at_zero or (not np.isfinite(logf[0]) and logf[0] > 0)):
        # density singular at zero: evaluate level 0 at half a step
        logf[0] = f.log_density(np.array([0.5 * x[1]]), tuple(params))[0]
    logf = np.where(np.isnan(logf), -np.inf, logf)
    top = float(np.max(logf))
    if not math.isfinite(top):
        raise InputError(f"params: {f.name}{tuple(params)} puts no mass on the levels")
    z = top + math.log(float(np.exp(logf - top).sum()))
    return logf - z


def pmf(fam: str | Family, params: tuple[float, ...], levels: NDArray[np.float64]) -> NDArray[np.float64]:
    """Component pmf on ``levels`` (sums to 1); see :func:`log_pmf`."""
    return np.exp(log_pmf(fam, params, levels))
