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
from collections.abc import Callable, Iterable, Iterator
from typing import Any, Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap._config import check_field_names
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
    "fit_range_profile",
    "intensity_profile",
    "range_profile",
    "background_intensity",
    "intensity_from_nonzero_mean",
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


# ---------------------------------------------------------------------- background under the zero spike
_GRIDS = (255.0, 65535.0)


def intensity_from_nonzero_mean(mean_nonzero: ArrayLike, quantum: float) -> NDArray[np.float64]:
    """Mean speckle intensity ``mu`` from the mean ``m`` of the *non-zero* pixels (threshold-free).

    Model (``docs/preprocessing.md``, ``docs/simulator.md``): pixel ``= Q(max(I - t, 0))`` with
    ``I`` exponential of mean ``mu`` (single-look speckle), an unknown threshold ``t`` and ``Q`` the
    quantiser of step ``quantum``.  By memorylessness ``I - t`` given ``I > t`` is again exponential
    with mean ``mu`` whatever ``t`` is, so:

    * ``quantum = 0`` (continuous data): ``m = mu``.
    * floor quantisation ``q = floor((I - t) / d) d``: given ``q > 0``, ``q / d - 1`` is geometric
      with ratio ``r = exp(-d / mu)``, so ``m = d / (1 - r)`` and
      ``mu = -d / ln(1 - d / m)``.
    * rounding ``q = rint((I - t) / d) d``: ``q > 0`` iff ``I - t >= d / 2`` and, given that,
      ``q / d - 1 = floor((I - t - d/2) / d)`` - the same geometric law, so the *same* formula.

    Parameters
    ----------
    mean_nonzero : array_like
        Mean of the non-zero pixel values (``>= quantum`` for quantised data; ``nan`` allowed).
    quantum : float
        Quantisation step (``1/255`` for 8-bit pixels), ``0`` for continuous values.

    Returns
    -------
    ndarray of float64
        ``mu`` (``0`` where ``m <= quantum``: all non-zero pixels at the first level).
    """
    m = np.asarray(mean_nonzero, dtype=np.float64)
    d = float(quantum)
    if d <= 0:
        return m.copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        mu = -d / np.log1p(-d / np.where(m > d, m, np.inf))
    return np.where(m > d, mu, np.where(np.isnan(m), np.nan, 0.0))


def _grid_of(img: NDArray[np.float32]) -> float:
    """Largest quantisation step (1/255, 1/65535) on whose grid all positive values lie, else 0."""
    v = img[img > 0].astype(np.float64)
    if v.size == 0:
        return math.inf  # compatible with any grid
    for levels in _GRIDS:
        s = v * levels
        if np.all(np.abs(s - np.rint(s)) < 1e-3):
            return 1.0 / levels
    return 0.0


def _resolve_quantum(quantum: float | Literal["auto"], detected: list[float]) -> float:
    if quantum == "auto":
        finite = [d for d in detected if math.isfinite(d)]
        return min(finite) if finite else 0.0
    try:
        q = float(quantum)
    except (TypeError, ValueError):
        raise InputError(f"quantum: must be 'auto' or a step >= 0, got {quantum!r}") from None
    if not math.isfinite(q) or q < 0:
        raise InputError(f"quantum: must be 'auto' or a step >= 0, got {quantum!r}")
    return q


@dataclasses.dataclass(frozen=True)
class _Cells:
    """Non-zero sums/counts of a background set, pooled over pings after outlier rejection."""

    block_sum: NDArray[np.float64]  # (n_blocks, n_beams)
    block_count: NDArray[np.float64]  # (n_blocks, n_beams)
    bin_sum: NDArray[np.float64] | None  # (n_bins, n_beams) or None
    bin_count: NDArray[np.float64] | None
    quantum: float
    n_images: int
    excluded: float  # fraction of (ping, block, beam) cells rejected as outliers
    geometry: SonarGeometry | None


def _background_cells(
    images: Iterable[ArrayLike] | Iterable[Ping],
    *,
    rows: slice | None,
    block_rows: int,
    outlier_sigma: float | None,
    quantum: float | Literal["auto"],
    per_bin: bool,
) -> _Cells:
    """Per-(ping, range block, beam) sums and counts of the positive pixels; robust pooling.

    A (ping, block, beam) cell is rejected when its non-zero mean ``m`` departs from the median
    over pings ``med`` by more than ``outlier_sigma * med / sqrt(n)`` (``n`` its non-zero count;
    the standard error of an exponential mean), so an object or interference in a few pings does
    not bias the pooled means.  Non-positive pixels are the zero spike.
    """
    if isinstance(block_rows, bool) or not isinstance(block_rows, int | np.integer) or block_rows < 1:
        raise InputError(f"block_rows: must be a positive integer, got {block_rows!r}")
    if outlier_sigma is not None and not (math.isfinite(outlier_sigma) and outlier_sigma > 0):
        raise InputError(f"outlier_sigma: must be a positive number or None, got {outlier_sigma!r}")
    sl = slice(None) if rows is None else rows
    sums: list[NDArray[np.float64]] = []
    counts: list[NDArray[np.float64]] = []
    kept: list[NDArray[np.float32]] = []
    grids: list[float] = []
    geom: SonarGeometry | None = None
    starts: NDArray[np.intp] | None = None
    for img, g, label in _iter_images(images, "images"):
        geom = geom or g
        sub = img[sl]
        if sub.shape[0] == 0:
            raise InputError(f"rows: selects no range bins of {label}")
        if starts is None:
            starts = np.arange(0, sub.shape[0], int(block_rows))
        pos = np.where(sub > 0, sub, np.float32(0.0))
        sums.append(np.add.reduceat(pos, starts, axis=0, dtype=np.float64))
        counts.append(np.add.reduceat((sub > 0).astype(np.float64), starts, axis=0))
        grids.append(_grid_of(sub))
        if per_bin:
            kept.append(pos)
    S = np.stack(sums)  # (n_img, n_blocks, n_beams)
    N = np.stack(counts)
    keep = np.ones(S.shape, dtype=bool)
    if outlier_sigma is not None and S.shape[0] >= 3:
        with np.errstate(divide="ignore", invalid="ignore"):
            m = np.where(N > 0, S / np.where(N > 0, N, 1.0), np.nan)
            ok = ~np.all(np.isnan(m), axis=0)
            med = np.full(m.shape[1:], np.nan)
            med[ok] = np.nanmedian(m[:, ok], axis=0)
            dev = np.abs(m - med) > outlier_sigma * med / np.sqrt(np.where(N > 0, N, 1.0))
        keep = ~(dev & (N > 0))
    w = keep.astype(np.float64)
    bin_sum = bin_count = None
    if per_bin:
        assert starts is not None
        reps = np.diff(np.append(starts, kept[0].shape[0]))
        bin_sum = np.zeros(kept[0].shape, dtype=np.float64)
        bin_count = np.zeros(kept[0].shape, dtype=np.float64)
        for k, pos in enumerate(kept):
            wk = np.repeat(w[k], reps, axis=0)
            bin_sum += pos * wk
            bin_count += (pos > 0) * wk
    n_cells = int(np.count_nonzero(N > 0))
    return _Cells(
        block_sum=(S * w).sum(axis=0),
        block_count=(N * w).sum(axis=0),
        bin_sum=bin_sum,
        bin_count=bin_count,
        quantum=_resolve_quantum(quantum, grids),
        n_images=S.shape[0],
        excluded=float(np.count_nonzero(~keep & (N > 0)) / n_cells) if n_cells else 0.0,
        geometry=geom,
    )


def background_intensity(
    images: Iterable[ArrayLike] | Iterable[Ping],
    *,
    block_rows: int = 1,
    outlier_sigma: float | None = 5.0,
    quantum: float | Literal["auto"] = "auto",
    rows: slice | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Recovered speckle intensity ``mu`` per (range block, beam) of a set of background pings.

    ``mu`` is :func:`intensity_from_nonzero_mean` of the mean of the positive pixels of each cell
    (``block_rows`` range bins x 1 beam, pooled over the pings after outlier rejection, see
    ``outlier_sigma``): the mean of the exponential intensity *before* the receiver's threshold and
    quantisation, independent of the threshold.  Use raw (quantised) pings: dividing them by a
    taper first moves their values off the quantisation grid.

    Parameters
    ----------
    images : iterable of array_like (n_bins, n_beams) or Ping
    block_rows : int
        Range bins per cell (the last block may be shorter).
    outlier_sigma : float or None
        Reject a (ping, block, beam) cell whose non-zero mean is more than this many standard
        errors (``median / sqrt(count)``) from the median over pings; ``None`` keeps all.
    quantum : float or "auto"
        Quantisation step; ``"auto"``: 1/255 (or 1/65535) when every positive value lies on that
        grid, else 0 (continuous).
    rows : slice, optional
        Range bins used (default all).

    Returns
    -------
    mu : ndarray, shape (n_blocks, n_beams)
        ``nan`` where a cell has no positive pixel.
    count : ndarray, shape (n_blocks, n_beams)
        Number of positive pixels pooled per cell.
    """
    cells = _background_cells(images, rows=rows, block_rows=block_rows, outlier_sigma=outlier_sigma,
                              quantum=quantum, per_bin=False)
    return _cell_mu(cells.block_sum, cells.block_count, cells.quantum), cells.block_count


def _cell_mu(s: NDArray[np.float64], n: NDArray[np.float64], quantum: float) -> NDArray[np.float64]:
    with np.errstate(divide="ignore", invalid="ignore"):
        m = np.where(n > 0, s / np.where(n > 0, n, 1.0), np.nan)
    return intensity_from_nonzero_mean(m, quantum)




def _block_taper(
    cells: _Cells, combine: Callable[[NDArray[np.float64]], NDArray[np.float64]]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-beam level from the block intensities: each block divided by its mean over the beams,
    combined over blocks; returns (level scaled to the mean block intensity, per-block ratios)."""
    mu = _cell_mu(cells.block_sum, cells.block_count, cells.quantum)  # (n_blocks, n_beams)
    with np.errstate(invalid="ignore"):
        good = np.all(np.isfinite(mu), axis=1) & (mu.mean(axis=1) > 0)
    if not np.any(good):
        raise FitError("images: no range block has non-zero pixels in every beam; taper undefined")
    block_mean = mu[good].mean(axis=1, keepdims=True)
    lv = mu[good] / block_mean  # (n_good_blocks, n_beams), mean 1 per block
    return combine(lv) * float(block_mean.mean()), lv

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
    estimator : str
        ``"nonzero-mean"`` or ``"mean"`` (see :func:`estimate_taper`).  For ``"nonzero-mean"``,
        ``statistic`` combines range blocks and ``spread`` is the spread over the blocks.
    quantum : float
        Quantisation step assumed by ``nonzero-mean`` (``nan`` for ``mean``).
    excluded : float
        Fraction of (ping, block, beam) cells rejected as outliers (``nonzero-mean``).
    """

    taper: NDArray[np.float64]
    normalisation: str
    n_images: int
    statistic: str
    spread: NDArray[np.float64]
    scale: float
    estimator: str = "mean"
    quantum: float = math.nan
    excluded: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible dict."""
        return {
            "taper": self.taper.tolist(),
            "normalisation": self.normalisation,
            "n_images": self.n_images,
            "statistic": self.statistic,
            "spread": self.spread.tolist(),
            "scale": self.scale,
            "estimator": self.estimator,
            "quantum": None if math.isnan(self.quantum) else self.quantum,
            "excluded": self.excluded,
        }


def _checked_estimator(estimator: Any) -> str:
    """``estimator`` with underscores as hyphens, checked to be ``"nonzero-mean"`` or ``"mean"``."""
    est = estimator.replace("_", "-") if isinstance(estimator, str) else estimator
    if est not in ("nonzero-mean", "mean"):
        raise InputError(f"estimator: must be 'nonzero-mean' or 'mean', got {estimator!r}")
    return est  # type: ignore[no-any-return]


def _checked_taper_options(est: str, statistic: str | None, trim: float, normalisation: str) -> str:
    """The statistic of :func:`estimate_taper` (its default depends on the estimator ``est``);
    ``statistic``, ``trim`` and ``normalisation`` checked."""
    if statistic is None:
        statistic = "trimmed-mean" if est == "nonzero-mean" else "median"
    if statistic not in ("median", "trimmed-mean"):
        raise InputError(f"statistic: must be 'median' or 'trimmed-mean', got {statistic!r}")
    if not 0 <= trim < 0.5:
        raise InputError(f"trim: must be in [0, 0.5), got {trim}")
    if normalisation not in ("max", "mean", "none"):
        raise InputError(f"normalisation: must be 'max', 'mean' or 'none', got {normalisation!r}")
    return statistic


def _level_combiner(statistic: str, trim: float) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
    """Per-beam combination of level samples ``(n, n_beams)`` over axis 0: the median or the mean
    trimmed by ``trim`` at each end."""

    def combine(lv: NDArray[np.float64]) -> NDArray[np.float64]:
        if statistic == "median":
            return np.median(lv, axis=0)
        from scipy import stats

        return np.asarray(stats.trim_mean(lv, trim, axis=0), dtype=np.float64)

    return combine


class _BeamLevels(NamedTuple):
    """Per-beam levels of :func:`estimate_taper` before normalisation."""

    level: NDArray[np.float64]
    #: The samples combined into ``level``: per-ping levels (``mean``) or per-block ratios.
    samples: NDArray[np.float64]
    n_images: int
    quantum: float
    excluded: float


def _ping_beam_levels(images: Iterable[ArrayLike] | Iterable[Ping], rows: slice | None,
                      combine: Callable[[NDArray[np.float64]], NDArray[np.float64]]) -> _BeamLevels:
    """``estimator="mean"``: per ping the mean level of each beam over the range bins ``rows``,
    combined across pings."""
    sl = slice(None) if rows is None else rows
    levels = []
    for img, _geom, label in _iter_images(images, "images"):
        sub = img[sl]
        if sub.shape[0] == 0:
            raise InputError(f"rows: selects no range bins of {label}")
        levels.append(sub.mean(axis=0, dtype=np.float64))
    lv = np.vstack(levels)  # (n_images, n_beams)
    n_images = lv.shape[0]
    return _BeamLevels(combine(lv), lv, n_images, math.nan, 0.0)


def _block_beam_levels(images: Iterable[ArrayLike] | Iterable[Ping], *, rows: slice | None, block_rows: int,
                       outlier_sigma: float | None, quantum: float | Literal["auto"],
                       combine: Callable[[NDArray[np.float64]], NDArray[np.float64]]) -> _BeamLevels:
    """``estimator="nonzero-mean"``: the recovered intensity of every range block relative to its
    mean over the beams, combined across blocks (:func:`_block_taper`)."""
    cells = _background_cells(images, rows=rows, block_rows=block_rows,
                              outlier_sigma=outlier_sigma, quantum=quantum, per_bin=False)
    level, lv = _block_taper(cells, combine)
    return _BeamLevels(level, lv, cells.n_images, cells.quantum, cells.excluded)


def _taper_estimate(beams: _BeamLevels, *, normalisation: str, statistic: str, estimator: str) -> TaperEstimate:
    """The normalised taper and its per-beam spread (MAD / median of the samples); a FitError if a
    beam has no positive level."""
    level, lv = beams.level, beams.samples
    med = np.median(lv, axis=0)
    mad = np.median(np.abs(lv - med), axis=0) * 1.4826
    with np.errstate(divide="ignore", invalid="ignore"):
        spread = np.where(med > 0, mad / med, np.inf)
    if np.any(~(level > 0)):
        bad = np.flatnonzero(~(level > 0))
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
        n_images=beams.n_images,
        statistic=statistic,
        spread=spread,
        scale=scale,
        estimator=estimator,
        quantum=beams.quantum,
        excluded=beams.excluded,
    )


def estimate_taper(
    images: Iterable[ArrayLike] | Iterable[Ping], *, estimator: Literal["nonzero-mean", "mean"] = "nonzero-mean",
    statistic: Literal["median", "trimmed-mean"] | None = None, trim: float = 0.2,
    normalisation: Literal["max", "mean", "none"] = "max", rows: slice | None = None, block_rows: int = 32,
    outlier_sigma: float | None = 5.0, quantum: float | Literal["auto"] = "auto",
) -> TaperEstimate:
    """Estimate the per-beam taper ``k(theta)`` from a set of open-water (background) pings.

    ``estimator="nonzero-mean"`` (default): the recovered speckle intensity ``mu`` of
    :func:`background_intensity` - from the mean of the *non-zero* pixels, which under the
    threshold-and-quantise receiver model is independent of the threshold - in each range block of
    ``block_rows`` bins and each beam, pooled over the pings after rejecting outlier
    (ping, block, beam) cells.  Each block's ``mu`` is divided by its mean over the beams (removing
    the range dependence), and the blocks are combined per beam with ``statistic`` (default
    trimmed mean).  Unbiased under the zero spike: the per-beam mean of thresholded pixels is not
    proportional to ``k`` (on the simulator, 73 % error; see ``docs/preprocessing.md``).

    ``estimator="mean"``: the previous estimator - per ping the mean level of each beam over the
    range bins, combined across pings with ``statistic`` (default median).  Correct only when the
    pixel values are proportional to the intensity (no threshold).

    Use raw pings (or pings through the steps that precede the taper and keep the pixel scale,
    i.e. none with the default ``taper_order``); the result is normalised (largest gain 1 by
    default).

    Parameters
    ----------
    images : iterable of array_like (n_bins, n_beams) or of Ping
        Background pings, all of the same geometry.
    estimator : {"nonzero-mean", "mean"}
        See above (underscores accepted).
    statistic : {"median", "trimmed-mean"}, optional
        Combination across blocks (``nonzero-mean``, default ``"trimmed-mean"``) or across pings
        (``mean``, default ``"median"``).
    trim : float
        Fraction trimmed from *each* end for ``"trimmed-mean"`` (0 <= trim < 0.5).
    normalisation : {"max", "mean", "none"}
    rows : slice, optional
        Range bins used (default all).
    block_rows : int
        Range bins per block (``nonzero-mean``); small enough that the range dependence within a
        block is negligible, large enough for a few hundred non-zero pixels per block and beam.
    outlier_sigma : float or None
        Outlier rejection of :func:`background_intensity` (``nonzero-mean``).
    quantum : float or "auto"
        Quantisation step (``nonzero-mean``); ``"auto"`` detects 8-bit (1/255) pixels.

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
        If a beam has zero level (the taper is undefined there), or no range block has a non-zero
        pixel in every beam.

    Notes
    -----
    Eq. 5 of Teixeira et al. (2018) (``y = k(theta) x``): under a background that is statistically
    the same in every beam, the mean intensity of beam ``j`` is proportional to ``k(theta_j)``.
    """
    est = _checked_estimator(estimator)
    statistic = _checked_taper_options(est, statistic, trim, normalisation)
    combine = _level_combiner(statistic, trim)
    if est == "mean":
        beams = _ping_beam_levels(images, rows, combine)
    else:
        beams = _block_beam_levels(images, rows=rows, block_rows=block_rows, outlier_sigma=outlier_sigma,
                                   quantum=quantum, combine=combine)
    return _taper_estimate(beams, normalisation=normalisation, statistic=statistic, estimator=est)


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
        check_field_names(d, cls, "radial_gain")
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
    if np.any(r < 0):
        raise InputError("range_m: ranges must be >= 0")
    if np.any(r == 0):
        # a window starting at the transducer (Oculus: first bin at 0 m): log10(r) is evaluated at
        # half a bin, the centre of the first range cell
        pos = np.diff(np.sort(r))
        pos = pos[pos > 0]
        if pos.size == 0:
            raise InputError("range_m: all ranges are 0 (log10(r) is undefined)")
        r = np.maximum(r, 0.5 * float(pos.min()))
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


def _beam_gains(cells: _Cells, taper: ArrayLike | SonarGeometry | TaperEstimate | None) -> NDArray[np.float64]:
    """The per-beam gain ``k_j`` the pings carry: the caller's ``taper``, or estimated from the
    cells as :func:`estimate_taper` does (up to scale); a FitError if a beam has no level."""
    assert cells.bin_sum is not None
    n_beams = cells.bin_sum.shape[1]
    if taper is None:  # as estimate_taper (trimmed mean over blocks); the scale is irrelevant
        from scipy import stats

        k, _ = _block_taper(cells, lambda lv: np.asarray(stats.trim_mean(lv, 0.2, axis=0)))
    else:
        tv = taper.taper if isinstance(taper, TaperEstimate) else taper
        t = _check_taper(tv, n_beams)
        if t is None:
            raise InputError("taper: the geometry has no taper")
        k = t.astype(np.float64)
    if np.any(~(k > 0)):
        raise FitError("images: a beam has zero level; taper undefined")
    return k


def intensity_profile(
    images: Iterable[ArrayLike] | Iterable[Ping], taper: ArrayLike | SonarGeometry | TaperEstimate | None = None,
    *, block_rows: int = 32, outlier_sigma: float | None = 5.0, quantum: float | Literal["auto"] = "auto",
) -> tuple[NDArray[np.float64], NDArray[np.int64], SonarGeometry | None]:
    """Background intensity per range bin: the profile :func:`estimate_radial_gain` regresses.

    Per range bin, the recovered speckle intensity of each beam (:func:`intensity_from_nonzero_mean`
    of the mean of its non-zero pixels over the pings) divided by the beam's taper, averaged over
    the beams with their non-zero counts as weights (``estimator="nonzero-mean"``).

    Parameters
    ----------
    images : iterable of array_like or Ping
        Background (open-water) pings of one geometry, raw (quantised).
    taper : array_like (n_beams,), SonarGeometry or TaperEstimate, optional
        Per-beam gain the pings carry; ``None`` estimates it with :func:`estimate_taper`.
    block_rows, outlier_sigma, quantum
        See :func:`background_intensity`.

    Returns
    -------
    level : ndarray (n_bins,)
        Background intensity (NaN where a bin has no non-zero pixel).
    count : ndarray of int64 (n_bins,)
        Non-zero pixels behind each bin's level.
    geometry : SonarGeometry or None
        The pings' geometry (None for bare arrays).

    Notes
    -----
    The level ``p(r)`` of eq. 6-7 of Teixeira et al. (2018).
    """
    cells = _background_cells(images, rows=None, block_rows=block_rows,
                              outlier_sigma=outlier_sigma, quantum=quantum, per_bin=True)
    assert cells.bin_sum is not None and cells.bin_count is not None
    k = _beam_gains(cells, taper)
    mu = _cell_mu(cells.bin_sum, cells.bin_count, cells.quantum)  # (n_bins, n_beams)
    n = cells.bin_count
    count = n.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        level = np.where(n > 0, mu / k, 0.0)
        level = np.where(count > 0, (n * level).sum(axis=1) / np.where(count > 0, count, 1), np.nan)
    return level, count.astype(np.int64), cells.geometry


def _range_or_geometry(range_m: ArrayLike | SonarGeometry | None, geom: SonarGeometry | None
                       ) -> ArrayLike | SonarGeometry:
    """``range_m``, or the pings' geometry when it is not given (an InputError for bare arrays)."""
    if range_m is None:
        if geom is None:
            raise InputError("range_m: required when images are bare arrays (not Pings)")
        return geom
    return range_m


def estimate_radial_gain(
    images: Iterable[ArrayLike] | Iterable[Ping], range_m: ArrayLike | SonarGeometry | None = None, *,
    estimator: Literal["nonzero-mean", "mean"] = "nonzero-mean",
    taper: ArrayLike | SonarGeometry | TaperEstimate | None = None, nonzero: bool = True,
    statistic: Literal["mean", "trimmed-mean", "median"] = "mean", fix_k1: float | None = None,
    fix_k2: float | None = None, min_count: int = 10, scale: Scale = "power", block_rows: int = 32,
    outlier_sigma: float | None = 5.0, quantum: float | Literal["auto"] = "auto",
) -> RadialGain:
    """Fit ``k1, k2, k3`` of eq. 7 so that the background level is flat in range after the gain.

    The level ``p(r)`` of each range bin is converted to dB and regressed on ``[log10 r, r, 1]``::

        10 log10 p(r) = c - k1 log10 r - k2 r + e(r)

    ``k3`` is set so that the corrected profile equals the mean dB level of the raw profile, so the
    gain flattens the background without changing its overall brightness.

    Levels (``estimator``):

    * ``"nonzero-mean"`` (default): the recovered speckle intensity of each (bin, beam) cell,
      ``mu_ij`` = :func:`intensity_from_nonzero_mean` of the mean of its non-zero pixels over the
      pings (threshold-free; outlier (ping, block, beam) cells rejected as in
      :func:`background_intensity`), divided by the beam's taper ``k_j`` and averaged over the
      beams with the non-zero counts as weights: ``p(r_i) = sum_j n_ij mu_ij / k_j / sum_j n_ij``.
      The gain then flattens the *intensity* of the background, which the pixel means of a
      thresholded receiver do not follow.  Use raw (quantised) pings.
    * ``"mean"``: the previous estimator, :func:`range_profile` (``nonzero``, ``statistic``) of the
      pixel values pooled over beams and pings.

    Parameters
    ----------
    images : iterable of array_like or Ping
        Background (open-water) pings of one geometry.
    range_m : array_like (n_bins,) or SonarGeometry, optional
        Required for bare arrays; defaults to the pings' geometry.
    estimator : {"nonzero-mean", "mean"}
        See above (underscores accepted).
    taper : array_like (n_beams,), SonarGeometry or TaperEstimate, optional
        Per-beam gain the raw pings carry (``nonzero-mean``); ``None`` estimates it from the same
        pings with :func:`estimate_taper`.
    nonzero, statistic
        See :func:`range_profile` (``mean`` estimator only).
    fix_k1, fix_k2 : float, optional
        Hold a coefficient fixed (e.g. ``fix_k1=20*beta`` from the channel model) and fit the rest.
    min_count : int
        Range bins with fewer (non-zero) samples are left out of the regression.
    scale : {"power", "amplitude"}
        ``"amplitude"`` fits with ``20 log10``.
    block_rows, outlier_sigma, quantum
        See :func:`background_intensity` (``nonzero-mean`` only; ``block_rows`` is the block of the
        outlier test and of the taper estimate).

    Returns
    -------
    RadialGain
        ``source="fit"``, ``rms_db`` the residual RMS in dB.

    Raises
    ------
    InputError, GeometryError
        Empty or mixed sets, missing ``range_m``, a taper not matching the beams.
    FitError
        Fewer usable range bins than free parameters.

    Notes
    -----
    Eq. 6-7 of Teixeira et al. (2018).
    """
    est = _checked_estimator(estimator)
    if est == "mean":
        level, count, geom = range_profile(images, nonzero=nonzero, statistic=statistic)
    else:
        level, count, geom = intensity_profile(images, taper, block_rows=block_rows, outlier_sigma=outlier_sigma,
                                              quantum=quantum)
    range_m = _range_or_geometry(range_m, geom)
    ok = (count >= min_count) & np.isfinite(level) & (level > 0)
    return fit_range_profile(level, range_m, usable=ok, scale=scale, fix_k1=fix_k1, fix_k2=fix_k2,
                             what=f"range bins have >= {min_count} non-zero samples")


def fit_range_profile(
    level: ArrayLike,
    range_m: ArrayLike | SonarGeometry,
    *,
    usable: ArrayLike | None = None,
    scale: Scale = "power",
    fix_k1: float | None = None,
    fix_k2: float | None = None,
    what: str = "range bins have a positive level",
) -> RadialGain:
    """Regress a level profile on the channel model: ``10 log10 p(r) = c - k1 log10 r - k2 r``.

    The regression of :func:`estimate_radial_gain`, for a profile measured any other way (e.g.
    the background level of :mod:`sonarmap.preprocess.normalise`).

    Parameters
    ----------
    level : array_like (n_bins,)
        Level per range bin (intensity units).
    range_m : array_like (n_bins,) or SonarGeometry
    usable : array_like of bool (n_bins,), optional
        Bins to regress on (default: finite, positive levels).
    scale, fix_k1, fix_k2
        As in :func:`estimate_radial_gain`.
    what : str
        What the usable bins are, for the error message.

    Returns
    -------
    RadialGain
        ``k3`` set so the corrected profile keeps the raw profile's mean dB level; ``rms_db`` the
        residual RMS.

    Raises
    ------
    FitError
        Fewer usable bins than free parameters.

    Notes
    -----
    Eq. 6-7 of Teixeira et al. (2018).
    """
    level = np.asarray(level, dtype=np.float64).reshape(-1)
    r = _check_range(range_m, level.size)
    ok = np.isfinite(level) & (level > 0)
    if usable is not None:
        ok &= np.asarray(usable, dtype=bool).reshape(-1)
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
            f"images: only {t.size} {what}; cannot fit {X.shape[1]} parameters"
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
