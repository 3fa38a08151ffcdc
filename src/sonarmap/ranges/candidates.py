"""The candidate stage of the per-ping pipeline: which structure pixels can carry a return.

:func:`candidate_mask` keeps the structure components large enough to be surfaces (rule 0) and
drops the ones smaller than ``min_component_extent_m`` both ways; band pooling
(:func:`pooled_band_mask`, :func:`pooled_band_pixels`) recovers thin single-look-speckle surface
bands the per-pixel labels leave in pieces.  Called alone with the default
:class:`~sonarmap.ranges.config.CandidateConfig` they give what
:func:`sonarmap.pipeline.process_ping` uses.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ranges import component_rule, rule0
from sonarmap.ranges.config import CandidateConfig

__all__ = ["candidate_mask", "pooled_band_mask", "pooled_band_pixels", "continued_bands"]


def candidate_mask(labels: NDArray[np.uint8], geometry: SonarGeometry, config: CandidateConfig = CandidateConfig(),
                   *, normalised: bool = False) -> NDArray[np.bool_]:
    """Structure pixels (``labels >= 1``) in components large enough to be surfaces (rule 0),
    without the ones smaller than ``min_component_extent_m`` both ways.

    Parameters
    ----------
    labels : ndarray of uint8, shape (n_bins, n_beams)
        The classification stage's labels (:func:`sonarmap.classify.segment.segment`).
    geometry : SonarGeometry
        For the components' metric extent.
    config : CandidateConfig
    normalised : bool
        The labels are of a normalised image (ARIS, Oculus, water column): the
        ``normalised_component_*`` thresholds apply (its multi-looked pixels are correlated).

    Returns
    -------
    ndarray of bool, shape (n_bins, n_beams)
    """
    if not isinstance(config, CandidateConfig):
        raise InputError(f"config: expected a CandidateConfig, got {type(config).__name__}")
    c = config
    if normalised:
        rule = (c.normalised_component_beams, c.normalised_component_bins, c.normalised_component_pixels)
    else:
        rule = (c.min_component_beams, c.min_component_bins, c.min_component_pixels)
    # rule 0 and the metric extent rule in one labelling of the lattice
    return component_rule(np.asarray(labels) >= 1, rule[0], rule[1], c.link_beams, rule[2], geometry=geometry,
                          min_extent_m=c.min_component_extent_m)


def pooled_band_mask(image: NDArray[np.float32], level: float, *, pool_beams: int = 4, pool_bins: int = 3,
                     min_beams: int = 40, link_beams: int = 0, link_bins: float = 2.0) -> NDArray[np.bool_] | None:
    """Band pooling as a mask: pixels of ``image`` averaged over ``pool_bins`` x ``2 pool_beams + 1``
    that reach ``level`` and belong to an 8-connected band spanning >= ``min_beams`` beams (None: none).

    With ``link_beams >= 2`` the shorter bands that continue a kept one across beams are kept too
    (:func:`continued_bands`, with ``link_bins``)."""
    from sonarmap.ranges._kernels import box_band

    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2 or img.size == 0 or type(level) not in (float, int) or not abs(level) < 3e38:
        return _pooled_band_mask_numpy(img, level, pool_beams, pool_bins, min_beams, link_beams, link_bins)
    # = uniform_filter(img, size=(pool_bins, 2 pool_beams + 1), mode="constant") >= level, compared
    # in float32 as numpy compares a float32 image with a Python number
    band, r0, r1, n_cols = box_band(np.ascontiguousarray(img), int(pool_bins), 2 * int(pool_beams) + 1,
                                    np.float32(level))
    if n_cols < min_beams:
        return None  # no component can span min_beams beams
    # the components lie within rows r0 .. r1 - 1: label only those
    if link_beams >= 2:
        from sonarmap.ranges._kernels import continued_bands as kernel

        kept = kernel(band[r0:r1], int(min_beams), _NO_SEEDS, int(link_beams), float(link_bins))
    else:
        kept = rule0(band[r0:r1], min_beams, img.shape[0] + 1, 0)
    if not kept.any():
        return None
    band[r0:r1] = kept
    return band


_NO_SEEDS = np.zeros((0, 0), dtype=np.bool_)


def continued_bands(band: NDArray[np.bool_], kept: NDArray[np.bool_], link_beams: int,
                    link_bins: float = 2.0) -> NDArray[np.bool_]:
    """``kept`` (8-connected components of ``band``) and the shorter components of ``band`` that
    continue them across beams.

    A surface's pooled band breaks where its echo fades for a beam or two, or where it is steep
    (the box mean flattens a steep flank's band and cuts it there: a rippled seafloor), and band
    pooling's width rule (``pool_min_beams``) drops the short pieces.  A piece is kept when it
    continues a kept band: one of its pixels lies ``d`` <= ``link_beams`` beams from a kept pixel
    and at most ``link_bins`` bins per beam (``floor(link_bins d)``, at least 1) from it in range
    (the scale of the surface tracker's slope prior, :mod:`sonarmap.ranges.tracking`), and it adds
    beams: at most half of the beams it spans hold a kept pixel (over beams the surface already
    holds, it is something in front of or behind it).  Repeated until no piece is added, so a chain
    of pieces is kept from its anchor; pieces that no kept band reaches are not (a school of fish
    without a surface).

    Parameters
    ----------
    band : ndarray of bool, shape (n_bins, n_beams)
        Pooled pixels at or above the band level.
    kept : ndarray of bool, shape (n_bins, n_beams)
        Pixels of the components of ``band`` kept so far (every pixel of such a component).
    link_beams : int
        Longest step across beams between a kept pixel and a piece (>= 2; 2: one beam between).
    link_bins : float
        Largest range step per beam between them.

    Returns
    -------
    ndarray of bool, shape (n_bins, n_beams)
    """
    from sonarmap.ranges._kernels import continued_bands as kernel

    b = np.ascontiguousarray(band, dtype=bool)
    k = np.ascontiguousarray(kept, dtype=bool)
    if b.ndim != 2 or k.shape != b.shape:
        raise InputError(f"kept: expected the band's shape {b.shape}, got {k.shape}")
    return kernel(b, 0, k, int(link_beams), float(link_bins))


def _pooled_band_mask_numpy(img: NDArray[np.float32], level: float, pool_beams: int, pool_bins: int,
                            min_beams: int, link_beams: int = 0, link_bins: float = 2.0) -> NDArray[np.bool_] | None:
    """:func:`pooled_band_mask` in numpy (images that are not 2-D, levels that are not Python numbers)."""
    from scipy.ndimage import uniform_filter

    pooled = uniform_filter(img, size=(pool_bins, 2 * pool_beams + 1), mode="constant")
    band = pooled >= level
    if not band.any():
        return None
    kept = rule0(band, min_beams, img.shape[0] + 1, 0)
    if link_beams >= 2 and kept.any():
        kept = continued_bands(band, kept, link_beams, link_bins)
    return kept if kept.any() else None


def pooled_band_pixels(image: NDArray[np.float32], level: float, *, pool_beams: int = 4, pool_bins: int = 3,
                       min_beams: int = 40, beams: NDArray[np.bool_] | None = None) -> NDArray[np.bool_] | None:
    """Band pooling (see :class:`~sonarmap.ranges.config.CandidateConfig`): one structure pixel per beam of every wide band.

    The bands of :func:`pooled_band_mask`; on each of their beams (only those with ``beams[j]``
    when given) the strongest pixel of the first run of band rows is returned.  None if no band.
    """
    from sonarmap.ranges._kernels import band_peak_pixels

    band = pooled_band_mask(image, level, pool_beams=pool_beams, pool_bins=pool_bins, min_beams=min_beams)
    if band is None:
        return None
    cols = band.any(axis=0)
    if beams is not None:
        cols &= np.asarray(beams, dtype=bool)
    if not cols.any():
        return None
    return band_peak_pixels(band, np.ascontiguousarray(image, dtype=np.float32), cols)
