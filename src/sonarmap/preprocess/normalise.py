"""Background normalisation: one background distribution over the whole lattice, for any sonar.

The paper's per-ping model (eq. 19: a zero spike plus an exponential background) describes a
DIDSON's output, whose receiver thresholds the background so that ~60 % of the pixels are zero.
Other sonars deliver the background itself: ARIS raw samples are never zero and their
reverberation falls by ~3x over the window; Oculus images carry the sonar's own gain and a
brighter fan edge.  This module estimates that background level from the data and maps the
image into the domain the paper's model describes, which is what a DIDSON receiver does in
hardware:

1. **Level vs range** ``b(r)``: the lower quartile of each range row across the beams, median
   filtered over 5 bins along range.  A surface must cover more than 3/4 of the beams at one
   range to bias it; artefacts at constant range across the whole fan (transmit ring-down near
   the sonar) are part of the background, as they should be.
2. **Level vs beam** ``f(r, theta)``: the lower quartile of ``y / b(r)`` in blocks of
   ``n_bins / 16`` bins x ``max(16, n_beams / 16)`` beams, bilinearly interpolated - the beam
   pattern's taper and range-dependent fan-edge brightening.
3. **Multi-look**: ``z = y / (b f)`` averaged over ``pool`` = 5 bins x 3 beams (the background of
   a single look is speckle; surfaces are coherent over a few bins and beams).
4. **Receiver threshold**: ``u = g max(z - t, 0)``, ``t`` the ``floor_quantile`` (0.9) of ``z``;
   ``g`` puts the mean background excess at ``1 / 44.6`` (the DIDSON background scale of the
   paper's Table I, so that its 256-level quantisation resolves the background tail).

The result is a zero spike (the pixels under the threshold) plus the excess of the background
over it - exponential for any background whose tail is (gamma, Rayleigh and K speckle all are) -
plus the objects: the paper's mixture, on every sonar.

Images that are already thresholded (>= ``thresholded_fraction`` of the pixels are zero: DIDSON,
many vendor displays) are left alone; the paper's calibrated pre-processing applies to them.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import InputError

__all__ = ["BackgroundLevel", "estimate_background", "normalise_image", "BACKGROUND_MEAN"]

#: Mean of the background excess after normalisation (the DIDSON background's 1/lambda, Table I).
BACKGROUND_MEAN = 1.0 / 44.6
_ZERO = 0.5 / 255.0


@dataclasses.dataclass(frozen=True, eq=False)
class BackgroundLevel:
    """What :func:`estimate_background` measured on one ping (or a recording).

    Attributes
    ----------
    applied : bool
        Whether the image is normalised (False for thresholded images and degenerate ones).
    reason : str
        ``"estimated"`` (normalised), ``"thresholded"`` (already has a zero spike: left alone),
        ``"degenerate"`` (the background level is zero or not finite in most rows: no estimate).
    zero_fraction : float
        Fraction of pixels at the zero level of the raw image.
    level_by_bin : ndarray, shape (n_bins,), float32, or None
        Background level ``b(r)`` in raw intensity units.
    beam_factor : ndarray, shape (n_blocks_range, n_blocks_beam), float32, or None
        Block grid of ``f(r, theta)`` (median 1).
    range_dependence_db : float
        ``10 log10`` of the ratio of the 90th to the 10th percentile of ``b(r)``: how much the
        background changes over the window (~0 dB when the sonar applied TVG).
    floor : float
        Threshold ``t`` on the normalised, multi-looked scale.
    gain : float
        Factor ``g`` of the excess.
    """

    applied: bool
    reason: str
    zero_fraction: float
    level_by_bin: NDArray[np.float32] | None = None
    beam_factor: NDArray[np.float32] | None = None
    range_dependence_db: float = math.nan
    floor: float = math.nan
    gain: float = math.nan

    def to_dict(self) -> dict[str, object]:
        """JSON-compatible summary (scalars only)."""
        return {"applied": self.applied, "reason": self.reason, "zero_fraction": self.zero_fraction,
                "range_dependence_db": self.range_dependence_db, "floor": self.floor, "gain": self.gain}


def _lower_quartile(x: NDArray[np.float32], axis: int) -> NDArray[np.float32]:
    n = x.shape[axis]
    k = (n - 1) // 4
    return np.partition(x, k, axis=axis).take(k, axis=axis)


def _block_factor(z: NDArray[np.float32]) -> NDArray[np.float32]:
    n, m = z.shape
    br = max(n // 16, 16)
    bc = max(m // 16, 16)
    nr, nc = max(n // br, 1), max(m // bc, 1)
    br, bc = n // nr, m // nc
    blocks = z[: nr * br, : nc * bc].reshape(nr, br, nc, bc).transpose(0, 2, 1, 3).reshape(nr, nc, -1)
    grid = _lower_quartile(blocks, 2).astype(np.float32)
    med = float(np.median(grid))
    if not med > 0 or not np.all(np.isfinite(grid)):
        return np.ones((nr, nc), dtype=np.float32)
    return np.maximum(grid / med, 1e-3).astype(np.float32)


def _expand(grid: NDArray[np.float32], shape: tuple[int, int]) -> NDArray[np.float32]:
    """Bilinear interpolation of a block grid to the full lattice (block centres; edges held)."""
    nr, nc = grid.shape
    n, m = shape
    ri = np.clip((np.arange(n) + 0.5) * nr / n - 0.5, 0, nr - 1)
    ci = np.clip((np.arange(m) + 0.5) * nc / m - 0.5, 0, nc - 1)
    r0 = np.minimum(ri.astype(np.int64), max(nr - 2, 0))
    c0 = np.minimum(ci.astype(np.int64), max(nc - 2, 0))
    r1 = np.minimum(r0 + 1, nr - 1)
    c1 = np.minimum(c0 + 1, nc - 1)
    fr = (ri - r0).astype(np.float32)[:, None]
    fc = (ci - c0).astype(np.float32)[None, :]
    g = grid
    top = g[r0][:, c0] * (1 - fc) + g[r0][:, c1] * fc
    bot = g[r1][:, c0] * (1 - fc) + g[r1][:, c1] * fc
    return (top * (1 - fr) + bot * fr).astype(np.float32)


def estimate_background(
    image: NDArray[np.floating], *, thresholded_fraction: float = 0.2, floor_quantile: float = 0.9,
    pool: tuple[int, int] = (5, 3),
) -> tuple[BackgroundLevel, NDArray[np.float32] | None]:
    """Estimate the background level of one ping and return it with the normalised image.

    Parameters
    ----------
    image : ndarray, shape (n_bins, n_beams)
        Raw intensities (any non-negative scale).
    thresholded_fraction : float
        An image with at least this fraction of zero pixels is taken as already thresholded
        and is not normalised.
    floor_quantile : float
        Quantile of the normalised, multi-looked image used as the receiver threshold ``t``.
    pool : (int, int)
        Multi-look box (range bins, beams).

    Returns
    -------
    (BackgroundLevel, ndarray or None)
        The estimate and the normalised image (float32 in ``[0, 1]``), or None when the image
        is not normalised (``applied`` False).

    Notes
    -----
    Generalises the paper's background model (sec. IV, eq. 19) from a calibrated open-water set
    to the data of the ping itself; see the module docstring.
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2 or img.size == 0:
        raise InputError(f"image: expected a non-empty (n_bins, n_beams) array, got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise InputError("image: contains NaN or infinite values")
    if not 0 < thresholded_fraction <= 1:
        raise InputError(f"thresholded_fraction: must lie in (0, 1], got {thresholded_fraction}")
    if not 0.5 <= floor_quantile < 1:
        raise InputError(f"floor_quantile: must lie in [0.5, 1), got {floor_quantile}")
    zero_fraction = float(np.count_nonzero(img <= _ZERO)) / img.size
    if zero_fraction >= thresholded_fraction:
        return BackgroundLevel(False, "thresholded", zero_fraction), None
    n, m = img.shape
    level = _lower_quartile(np.maximum(img, 0.0), 1)
    if n >= 5:
        from scipy.ndimage import median_filter

        level = median_filter(level, size=5, mode="nearest")
    good = level > _ZERO
    if np.count_nonzero(good) < 0.5 * n:
        return BackgroundLevel(False, "degenerate", zero_fraction), None
    level = np.where(good, level, float(np.median(level[good]))).astype(np.float32)
    z = img / level[:, None]
    factor = _block_factor(z)
    z /= _expand(factor, z.shape)
    if pool[0] > 1 or pool[1] > 1:
        from scipy.ndimage import uniform_filter

        z = uniform_filter(z, size=(min(pool[0], n), min(pool[1], m)), mode="nearest")
    flat = z.ravel()
    k = min(int(floor_quantile * (flat.size - 1)), flat.size - 1)
    t = float(np.partition(flat, k)[k])
    excess = np.maximum(z - t, 0.0)
    pos = excess[excess > 0]
    if pos.size == 0 or not float(pos.mean()) > 0:
        return BackgroundLevel(False, "degenerate", zero_fraction, level, factor), None
    g = BACKGROUND_MEAN / float(pos.mean())
    u = np.minimum(excess * g, 1.0).astype(np.float32)
    q10, q90 = np.percentile(level, [10, 90])
    dep = float(10 * np.log10(q90 / q10)) if q10 > 0 else math.inf
    return BackgroundLevel(True, "estimated", zero_fraction, level.astype(np.float32), factor, dep, t, g), u


def normalise_image(image: NDArray[np.floating], **kwargs: object) -> NDArray[np.float32]:
    """The normalised image of :func:`estimate_background` (the input as float32 when not applied)."""
    bg, u = estimate_background(image, **kwargs)  # type: ignore[arg-type]
    return np.asarray(image, dtype=np.float32) if u is None else u
