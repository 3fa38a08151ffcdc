"""Per-beam taper (eq. 5) and range-dependent gain / TVG (eq. 6-7), with estimators.

Pixel values are treated as **linear intensity (power)**: a gain of ``k`` dB multiplies a pixel by
``10**(k / 10)``.  This matches the model of the paper (the image is a sum of intensities, eq. 2,
and the exponential background model of eq. 19 is a power model).  Data already log-compressed by
the sonar can use ``scale="amplitude"`` (``10**(k/20)``) or be linearised first; state it in the
configuration so that the choice is recorded in the output metadata.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Iterator
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import FitError, GeometryError, InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ping import Ping, as_image

__all__ = [
    "correct_taper",
    "estimate_taper",
    "TaperEstimate",
    "RadialGain",
    "radial_gain_db",
    "radial_gain_factor",
    "apply_radial_gain",
    "estimate_radial_gain",
    "range_profile",
]

Scale = Literal["power", "amplitude"]


# ---------------------------------------------------------------------- input helpers
def _check_taper(taper: ArrayLike | SonarGeometry | None, n_beams: int) -> NDArray[np.float32] | None:
    if isinstance(taper, SonarGeometry):
        taper = taper.taper
    if taper is None:
        return None
    try:
        t = np.asarray(taper, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError("taper: not a numeric array") from None
    if t.size != n_beams:
        raise GeometryError(f"taper: length {t.size} does not match the image's {n_beams} beams")
    if not np.all(np.isfinite(t)):
        raise InputError("taper: contains NaN or infinite values")
    if np.any(t <= 0):
        raise InputError("taper: per-beam gains must be positive")
    return t.astype(np.float32)


def _iter_images(
    images: Iterable[ArrayLike] | Iterable[Ping], name: str
) -> Iterator[tuple[NDArray[np.float32], SonarGeometry | None, str]]:
    """Yield (image, geometry or None, label); one clear error for mixed shapes/geometries."""
    if isinstance(images, np.ndarray) and images.ndim == 2:
        raise InputError(f"{name}: expected a collection of images, got a single 2-D array")
    first_shape: tuple[int, ...] | None = None
    first_geom: SonarGeometry | None = None
    first_label = ""
    for i, item in enumerate(images):
        if isinstance(item, Ping):
            img, geom, label = item.image, item.geometry, item.source or f"{name}[{i}]"
        else:
            img, geom, label = as_image(item, f"{name}[{i}]"), None, f"{name}[{i}]"
        if first_shape is None:
            first_shape, first_geom, first_label = img.shape, geom, label
        else:
            if img.shape != first_shape:
                raise GeometryError(
                    f"{name}: mixed geometries - {label} has shape {img.shape} but {first_label} "
                    f"has {first_shape}"
                )
            if geom is not None and first_geom is not None and geom.key != first_geom.key:
                raise GeometryError(
                    f"{name}: mixed geometries - {label} ('{geom.name}') differs from "
                    f"{first_label} ('{first_geom.name}') in beams, ranges, PSF, taper or constants"
                )
        yield img, geom, label
    if first_shape is None:
        raise InputError(f"{name}: no images given (empty set)")


# ---------------------------------------------------------------------- taper (eq. 5)
def correct_taper(image: ArrayLike, taper: ArrayLike | SonarGeometry | None) -> NDArray[np.float32]:
    """Divide column ``j`` of ``image`` by ``taper[j]`` (undo the per-beam gain ``k(theta)``).

    Parameters
    ----------
    image : array_like, shape (n_bins, n_beams)
    taper : array_like, shape (n_beams,), SonarGeometry or None
        Positive per-beam gains; ``None`` returns a float32 copy.

    Returns
    -------
    ndarray, float32, shape (n_bins, n_beams)

    Notes
    -----
    Eq. 5 of Teixeira et al. (2018): ``y = k(theta) x``, so ``x = y / k(theta)``.
    """
    img = as_image(image, "image")
    t = _check_taper(taper, img.shape[1])
    if t is None:
        return img.copy()
    return img / t


@dataclasses.dataclass(frozen=True)
class TaperEstimate:
    """Per-beam taper estimated from open-water pings.

    Attributes
    ----------
    taper : ndarray, shape (n_beams,)
        Estimated gains, scaled by ``normalisation``.
    normalisation : str
        ``"max"`` (largest gain 1, the DIDSON file convention), ``"mean"`` (mean 1) or ``"none"``.
    n_images : int
        Number of pings used.
    statistic : str
        How per-ping beam levels were combined across pings (``"median"`` or ``"trimmed-mean"``).
    spread : ndarray, shape (n_beams,)
        Robust relative spread (MAD / median) of the per-ping beam levels: a per-beam uncertainty.
    scale : float
        The factor the raw levels were divided by (undo with ``taper * scale``).
    """

    taper: NDArray[np.float64]
    normalisation: str
    n_images: int
    statistic: str
    spread: NDArray[np.float64]
    scale: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible dict."""
        return {
            "taper": self.taper.tolist(),
            "normalisation": self.normalisation,
            "n_images": self.n_images,
            "statistic": self.statistic,
            "spread": self.spread.tolist(),
            "scale": self.scale,
        }


def estimate_taper(
    images: Iterable[ArrayLike] | Iterable[Ping],
    *,
    statistic: Literal["median", "trimmed-mean"] = "median",
    trim: float = 0.2,
    normalisation: Literal["max", "mean", "none"] = "max",
    rows: slice | None = None,
) -> TaperEstimate:
    """Estimate the per-beam taper ``k(theta)`` from a set of open-water (background) pings.

    Each ping contributes one level per beam: the mean intensity of that beam over the range
    bins (``rows``).  The per-beam levels of all pings are combined with a robust statistic (median
    or trimmed mean across pings), so pings containing objects or interference do not bias the
    estimate.  The result is normalised (largest gain 1 by default).

    The images should already have been through the pre-processing steps that precede the taper
    in the pipeline (e.g. deconvolution) if the estimate is to be used after them.

    Parameters
    ----------
    images : iterable of array_like (n_bins, n_beams) or of Ping
        Background pings, all of the same geometry.
    statistic : {"median", "trimmed-mean"}
        Combination across pings.
    trim : float
        Fraction trimmed from *each* end for ``"trimmed-mean"`` (0 <= trim < 0.5).
    normalisation : {"max", "mean", "none"}
    rows : slice, optional
        Range bins used (default all).

    Returns
    -------
    TaperEstimate

    Raises
    ------
    InputError
        Empty set, NaN/inf, bad options.
    GeometryError
        Images of different shapes or pings of different geometries.
    FitError
        If a beam has zero mean level in every ping (the taper is undefined there).

    Notes
    -----
    Eq. 5 of Teixeira et al. (2018) (``y = k(theta) x``): under a background that is statistically
    the same in every beam, the mean level of beam ``j`` is proportional to ``k(theta_j)``.
    """
    if statistic not in ("median", "trimmed-mean"):
        raise InputError(f"statistic: must be 'median' or 'trimmed-mean', got {statistic!r}")
    if not 0 <= trim < 0.5:
        raise InputError(f"trim: must be in [0, 0.5), got {trim}")
    if normalisation not in ("max", "mean", "none"):
        raise InputError(f"normalisation: must be 'max', 'mean' or 'none', got {normalisation!r}")
    sl = slice(None) if rows is None else rows
    levels = []
    for img, _geom, label in _iter_images(images, "images"):
        sub = img[sl]
        if sub.shape[0] == 0:
            raise InputError(f"rows: selects no range bins of {label}")
        levels.append(sub.mean(axis=0, dtype=np.float64))
    lv = np.vstack(levels)  # (n_images, n_beams)
    if statistic == "median":
        level = np.median(lv, axis=0)
    else:
        from scipy import stats

        level = np.asarray(stats.trim_mean(lv, trim, axis=0), dtype=np.float64)
    med = np.median(lv, axis=0)
    mad = np.median(np.abs(lv - med), axis=0) * 1.4826
    with np.errstate(divide="ignore", invalid="ignore"):
        spread = np.where(med > 0, mad / med, np.inf)
    if np.any(level <= 0):
        bad = np.flatnonzero(level <= 0)
        raise FitError(f"images: beams {bad.tolist()[:10]} have zero level; taper undefined")
    if normalisation == "max":
        scale = float(level.max())
    elif normalisation == "mean":
        scale = float(level.mean())
    else:
        scale = 1.0
    taper = level / scale
    taper.setflags(write=False)
    spread.setflags(write=False)
    return TaperEstimate(
        taper=taper,
        normalisation=normalisation,
        n_images=lv.shape[0],
        statistic=statistic,
        spread=spread,
        scale=scale,
    )


# ---------------------------------------------------------------------- radial gain (eq. 6-7)
@dataclasses.dataclass(frozen=True)
class RadialGain:
    """Range-dependent gain ``k(r) = k1 log10(r) + k2 r + k3`` in dB (eq. 7).

    Attributes
    ----------
    k1 : float
        Spreading coefficient in dB per decade of range (``20 beta``).
    k2 : float
        Absorption coefficient in dB per metre (``2 alpha``: two-way).
    k3 : float
        Constant offset in dB.
    scale : {"power", "amplitude"}
        How the dB gain acts on pixel values: ``10**(k/10)`` (power, default) or ``10**(k/20)``.
    source : str
        ``"channel"`` (from beta/alpha), ``"fit"`` (regression) or ``"manual"``.
    rms_db : float
        RMS residual of the regression in dB (``nan`` unless fitted).
    """

    k1: float
    k2: float
    k3: float = 0.0
    scale: Scale = "power"
    source: str = "manual"
    rms_db: float = math.nan

    def __post_init__(self) -> None:
        for name in ("k1", "k2", "k3"):
            v = getattr(self, name)
            try:
                fv = float(v)
            except (TypeError, ValueError):
                raise InputError(f"{name}: not a number ({v!r})") from None
            if not math.isfinite(fv):
                raise InputError(f"{name}: must be finite (got {fv})")
            object.__setattr__(self, name, fv)
        if self.scale not in ("power", "amplitude"):
            raise InputError(f"scale: must be 'power' or 'amplitude', got {self.scale!r}")

    @classmethod
    def from_channel(
        cls, beta: float, alpha_db_per_m: float, k3: float = 0.0, *, scale: Scale = "power"
    ) -> RadialGain:
        """Gain undoing spreading and two-way absorption: ``k1 = 20 beta``, ``k2 = 2 alpha`` (eq. 7).

        Parameters
        ----------
        beta : float
            Spreading exponent of eq. 6 (``k1 = 20 beta`` dB per decade).
        alpha_db_per_m : float
            One-way absorption in dB/m (e.g. :func:`sonarmap.preprocess.absorption.absorption_db_per_m`);
            the two-way loss is ``2 alpha r``.
        k3 : float
            Constant offset in dB.
        """
        return cls(k1=20.0 * float(beta), k2=2.0 * float(alpha_db_per_m), k3=k3, scale=scale,
                   source="channel")

    @property
    def beta(self) -> float:
        """Spreading exponent ``k1 / 20``."""
        return self.k1 / 20.0

    @property
    def alpha_db_per_m(self) -> float:
        """One-way absorption ``k2 / 2`` in dB/m."""
        return self.k2 / 2.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible dict."""
        return {"k1": self.k1, "k2": self.k2, "k3": self.k3, "scale": self.scale,
                "source": self.source, "rms_db": None if math.isnan(self.rms_db) else self.rms_db}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RadialGain:
        """Inverse of :meth:`to_dict` (unknown keys are an error naming the key)."""
        known = {f.name for f in dataclasses.fields(cls)}
        for key in d:
            if key not in known:
                raise InputError(f"radial_gain.{key}: unknown key (expected {sorted(known)})")
        kw = dict(d)
        if kw.get("rms_db") is None:
            kw.pop("rms_db", None)
        return cls(**kw)


def _check_range(range_m: ArrayLike | SonarGeometry, n_bins: int | None = None) -> NDArray[np.float64]:
    if isinstance(range_m, SonarGeometry):
        range_m = range_m.range_m
    try:
        r = np.asarray(range_m, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError("range_m: not a numeric array") from None
    if n_bins is not None and r.size != n_bins:
        raise GeometryError(f"range_m: {r.size} ranges do not match the image's {n_bins} range bins")
    if not np.all(np.isfinite(r)):
        raise InputError("range_m: contains NaN or infinite values")
    if np.any(r <= 0):
        raise InputError("range_m: ranges must be positive (log10(r) is undefined at r <= 0)")
    return r


def radial_gain_db(range_m: ArrayLike | SonarGeometry, gain: RadialGain) -> NDArray[np.float64]:
    """``k(r) = k1 log10(r) + k2 r + k3`` in dB (eq. 7) at each range."""
    r = _check_range(range_m)
    return gain.k1 * np.log10(r) + gain.k2 * r + gain.k3


def radial_gain_factor(range_m: ArrayLike | SonarGeometry, gain: RadialGain) -> NDArray[np.float32]:
    """Multiplicative factor per range bin: ``10**(k(r)/10)`` (power) or ``10**(k(r)/20)``."""
    div = 10.0 if gain.scale == "power" else 20.0
    return np.power(10.0, radial_gain_db(range_m, gain) / div).astype(np.float32)


def apply_radial_gain(
    image: ArrayLike, range_m: ArrayLike | SonarGeometry, gain: RadialGain
) -> NDArray[np.float32]:
    """Multiply range bin ``i`` of ``image`` by the gain factor at ``range_m[i]`` (eq. 6-7).

    Parameters
    ----------
    image : array_like, shape (n_bins, n_beams)
        Linear intensities (see the module notes on ``scale``).
    range_m : array_like, shape (n_bins,), or SonarGeometry
    gain : RadialGain

    Returns
    -------
    ndarray, float32

    Notes
    -----
    Eq. 6-7 of Teixeira et al. (2018): the received intensity falls as ``r**(-2 beta)`` times the
    two-way absorption ``10**(-2 alpha r / 10)``; ``k(r) = 20 beta log10 r + 2 alpha r + k3``
    compensates both.
    """
    img = as_image(image, "image")
    r = _check_range(range_m, img.shape[0])
    return img * radial_gain_factor(r, gain)[:, None]


def range_profile(
    images: Iterable[ArrayLike] | Iterable[Ping],
    *,
    nonzero: bool = True,
    statistic: Literal["mean", "trimmed-mean", "median"] = "mean",
    trim: float = 0.1,
) -> tuple[NDArray[np.float64], NDArray[np.int64], SonarGeometry | None]:
    """Per-range-bin level of a set of pings: mean (or robust mean) over beams and pings.

    Returns ``(level, count, geometry)`` where ``count`` is the number of samples per bin and
    ``geometry`` that of the pings (``None`` for bare arrays).  With ``nonzero=True`` only the
    non-zero intensities are used (zeros are the empty part of the background model, eq. 19).
    """
    stacks: list[NDArray[np.float32]] = []
    geom: SonarGeometry | None = None
    for img, g, _label in _iter_images(images, "images"):
        stacks.append(img)
        geom = geom or g
    data = np.stack(stacks, axis=1).reshape(stacks[0].shape[0], -1)  # (n_bins, n_img*n_beams)
    if statistic not in ("mean", "trimmed-mean", "median"):
        raise InputError(f"statistic: must be 'mean', 'trimmed-mean' or 'median', got {statistic!r}")
    mask = data != 0 if nonzero else np.ones(data.shape, dtype=bool)
    count = mask.sum(axis=1)
    level = np.full(data.shape[0], np.nan)
    if statistic == "mean":
        s = np.where(mask, data, 0.0).sum(axis=1, dtype=np.float64)
        ok = count > 0
        level[ok] = s[ok] / count[ok]
    else:
        from scipy import stats

        for i in range(data.shape[0]):
            v = data[i][mask[i]]
            if v.size:
                level[i] = float(np.median(v)) if statistic == "median" else float(stats.trim_mean(v, trim))
    return level, count.astype(np.int64), geom


def estimate_radial_gain(
    images: Iterable[ArrayLike] | Iterable[Ping],
    range_m: ArrayLike | SonarGeometry | None = None,
    *,
    nonzero: bool = True,
    statistic: Literal["mean", "trimmed-mean", "median"] = "mean",
    fix_k1: float | None = None,
    fix_k2: float | None = None,
    min_count: int = 10,
    scale: Scale = "power",
) -> RadialGain:
    """Fit ``k1, k2, k3`` of eq. 7 so that the background level is flat in range after the gain.

    The level ``p(r)`` of each range bin (mean of the non-zero intensities over beams and pings by
    default) is converted to dB and regressed on ``[log10 r, r, 1]``::

        10 log10 p(r) = c - k1 log10 r - k2 r + e(r)

    ``k3`` is set so that the corrected profile equals the mean dB level of the raw profile, so the
    gain flattens the background without changing its overall brightness.

    Parameters
    ----------
    images : iterable of array_like or Ping
        Background (open-water) pings of one geometry.
    range_m : array_like (n_bins,) or SonarGeometry, optional
        Required for bare arrays; defaults to the pings' geometry.
    nonzero, statistic
        See :func:`range_profile`.
    fix_k1, fix_k2 : float, optional
        Hold a coefficient fixed (e.g. ``fix_k1=20*beta`` from the channel model) and fit the rest.
    min_count : int
        Range bins with fewer samples are left out of the regression.
    scale : {"power", "amplitude"}
        ``"amplitude"`` fits with ``20 log10``.

    Returns
    -------
    RadialGain
        ``source="fit"``, ``rms_db`` the residual RMS in dB.

    Raises
    ------
    InputError, GeometryError
        Empty or mixed sets, missing ``range_m``.
    FitError
        Fewer usable range bins than free parameters.

    Notes
    -----
    Eq. 6-7 of Teixeira et al. (2018).
    """
    level, count, geom = range_profile(images, nonzero=nonzero, statistic=statistic)
    if range_m is None:
        if geom is None:
            raise InputError("range_m: required when images are bare arrays (not Pings)")
        range_m = geom
    r = _check_range(range_m, level.size)
    ok = (count >= min_count) & np.isfinite(level) & (level > 0)
    mul = 10.0 if scale == "power" else 20.0
    y = np.full(level.size, np.nan)
    y[ok] = mul * np.log10(level[ok])
    cols: list[NDArray[np.float64]] = []
    names: list[str] = []
    target = y.copy()
    if fix_k1 is None:
        cols.append(-np.log10(r)); names.append("k1")  # noqa: E702
    else:
        target = target + float(fix_k1) * np.log10(r)
    if fix_k2 is None:
        cols.append(-r); names.append("k2")  # noqa: E702
    else:
        target = target + float(fix_k2) * r
    cols.append(np.ones_like(r)); names.append("c")  # noqa: E702
    X = np.column_stack(cols)[ok]
    t = target[ok]
    if t.size < X.shape[1] + 1:
        raise FitError(
            f"images: only {t.size} range bins have >= {min_count} non-zero samples; "
            f"cannot fit {X.shape[1]} parameters"
        )
    coef, *_ = np.linalg.lstsq(X, t, rcond=None)
    vals = dict(zip(names, coef.tolist(), strict=True))
    k1 = vals.get("k1", float(fix_k1) if fix_k1 is not None else 0.0)
    k2 = vals.get("k2", float(fix_k2) if fix_k2 is not None else 0.0)
    resid = t - X @ coef
    rms = float(np.sqrt(np.mean(resid**2)))
    # corrected level (dB) = y + k(r) = c + e(r) + k3  ->  choose k3 so it equals mean(y).
    k3 = float(np.mean(y[ok]) - vals["c"])
    return RadialGain(k1=k1, k2=k2, k3=k3, scale=scale, source="fit", rms_db=rms)
