"""Crosstalk: range rows lit across the whole fan at a bright echo's range.

A bright echo in some beams lights the same range row on beams far from it in azimuth (the real
DIDSON test pings: ping 9's rows 192-196 on 71-96 % of the beams, behind the hull's apex at the
same range; ping 4's rows 278-284; ping 8's rows 181-196).  The stated beam pattern's ghosts
are at +-8 / 16 / 24 beams; this band is flat across the fan.  The deconvolution of the beam
pattern removes most of it from the classified image, but the leading edges are measured on the
image without that deconvolution (``RangeConfig.edge_image``), where a steep flank beside the
bright echo starts behind the band and its half-peak walk runs on into it.

:func:`crosstalk_by_row` estimates the band from the beams that cannot have an echo of their own
at a row - those whose first structure pixel (the classifier's labels) lies more than
``margin_bins`` behind it: per row the median of those *water-column* pixels (lit across the fan:
on most of them, not on the few a neighbouring echo's main lobe or ghosts reach), against the
ping's typical water column (the median of the rows' medians).  A row whose median exceeds that
by more than ``z`` standard errors (the pooled spread of the water-column pixels, over the
square root of the row's count) carries the excess as crosstalk, if some beam holds structure at
that row (crosstalk lies at an echo's range; the brighter water column near the sonar is no
crosstalk); :func:`remove_crosstalk` subtracts it from every pixel of the row (clipped at 0).  A row without enough water-column beams (a flat surface across the fan, seen
head on) gets no estimate and is left alone: its light is the surface's own - unless it continues
a band found on the rows beside it and has at least :data:`CROSSTALK_GROW_BEAMS` water-column
beams that pass the same tests (a band is contiguous in range; on the real DIDSON ping 8 the band
at rows 181-189 lies in front of a hull that fills three quarters of the fan from row 183 on).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError

__all__ = ["crosstalk_by_row", "remove_crosstalk", "CROSSTALK_MARGIN_BINS", "CROSSTALK_Z", "CROSSTALK_FRONT_BINS",
           "CROSSTALK_GROW_BEAMS"]

#: A pixel is water column when its beam's first structure pixel lies more than this many bins
#: behind it (a beam's own echo rises over its pulse, 1-2 DIDSON bins, before the classifier's
#: first structure pixel).
CROSSTALK_MARGIN_BINS = 4
#: A row's water-column median must exceed the ping's typical one by this many standard errors.
CROSSTALK_Z = 4.0
#: A band found on rows with enough water-column beams grows into the rows beside it that have at
#: least this many (and pass the same tests).
CROSSTALK_GROW_BEAMS = 8
#: Rows further than this in front of the first structure pixel are no edge's: not estimated
#: (the ping's typical water column is taken over the rows from there on).
CROSSTALK_FRONT_BINS = 64


def crosstalk_by_row(image: ArrayLike, labels: ArrayLike, *, margin_bins: int = CROSSTALK_MARGIN_BINS,
                     z: float = CROSSTALK_Z, min_beams: int | None = None) -> NDArray[np.float64]:
    """Per range row, the level lit across the fan beyond the ping's water column (0 where none).

    Parameters
    ----------
    image : array_like, shape (n_bins, n_beams)
        The image the edges are measured on (linear intensity).
    labels : array_like of int, shape (n_bins, n_beams)
        The classifier's labels (0: background).
    margin_bins : int
        Water column: more than this many bins in front of the beam's first structure pixel.
    z : float
        Significance of a row's excess, in standard errors of its median (the rows whose mean is
        not that many standard errors of the mean above the typical one are not tested).
    min_beams : int, optional
        Fewest water-column beams a row needs for an estimate (default ``max(8, n_beams // 4)``);
        a band found so grows into the rows beside it with at least :data:`CROSSTALK_GROW_BEAMS`
        (at most ``min_beams``).

    Returns
    -------
    ndarray of float64, shape (n_bins,)

    Raises
    ------
    InputError
        If the shapes differ or an option is out of range.
    """
    import sonarmap.preprocess._kernels as _pk

    img = np.ascontiguousarray(image, dtype=np.float32)
    lab = np.ascontiguousarray(labels)
    if img.ndim != 2 or lab.shape != img.shape:
        raise InputError(f"labels: expected the image's shape {img.shape}, got {lab.shape}")
    if isinstance(margin_bins, bool) or int(margin_bins) != margin_bins or margin_bins < 0:
        raise InputError(f"margin_bins: must be an integer >= 0 (got {margin_bins!r})")
    if not (isinstance(z, (int, float)) and np.isfinite(z) and z > 0):
        raise InputError(f"z: must be a finite number > 0 (got {z!r})")
    n, m = img.shape
    need = max(8, m // 4) if min_beams is None else int(min_beams)
    if n == 0 or m == 0:
        return np.zeros(n)
    struct = lab.view(np.uint8) if lab.dtype.itemsize == 1 else (lab != 0).view(np.uint8)
    return _pk.crosstalk_rows(img, struct, int(margin_bins), CROSSTALK_FRONT_BINS, need, float(z),  # type: ignore[no-any-return]
                              min(CROSSTALK_GROW_BEAMS, need))


def remove_crosstalk(image: ArrayLike, labels: ArrayLike, **kwargs: object) -> NDArray[np.float32]:
    """``image`` less each row's :func:`crosstalk_by_row` level (clipped at 0), float32; the
    image itself (not a copy) when no row carries crosstalk."""
    img = np.asarray(image, dtype=np.float32)
    level = crosstalk_by_row(img, labels, **kwargs)  # type: ignore[arg-type]
    rows = np.flatnonzero(level > 0)
    if not rows.size:
        return img
    out = img.copy()
    out[rows] = np.maximum(img[rows] - level[rows, None].astype(np.float32), np.float32(0.0))
    return out
