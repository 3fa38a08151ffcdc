"""Where a leading-edge return was measured: the near edge of its beam's footprint.

A return's range is the leading edge of its echo (``DESIGN.md``, "Range convention";
``docs/ranges.md``): the echo starts where the beam first meets the surface.  On a surface
inclined across the beams that is not on the beam's axis but at the part of its footprint nearest
the sonar.  The simulator's range truth (:attr:`sonarmap.simulate.SimResult.surface_range_m`)
states the same convention: the nearest surface within the beam's two-way -3 dB footprint.

Across the fan, with the surface's range locally linear in azimuth, ``r(theta) = r_c + s (theta -
theta_c)``, the nearest point of the footprint ``|theta - theta_c| <= W / 2`` (``W`` the two-way
-3 dB width, :attr:`sonarmap.geometry.SonarGeometry.azimuth_beamwidth_rad`) lies at
``theta_c - sign(s) W / 2`` whatever the magnitude of ``s``: there the surface is at the range
the return reports.  Registered on the axis instead, the point lies ``|s| W / 2`` in front of the
surface along the beam.  So the correction needs only the side the surface comes nearer on, the
sign of ``s``, which :func:`footprint_azimuths` takes from the neighbouring beams' returns of the
same ping.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError

__all__ = ["footprint_azimuths", "across_beam_slope", "FOOTPRINT_EDGE_FRACTION", "MAX_INCIDENCE_RAD"]

#: The -3 dB footprint's near edge, in units of the two-way -3 dB beamwidth from the axis.
FOOTPRINT_EDGE_FRACTION = 0.5
#: Neighbouring returns whose range differs by more than a surface at this incidence angle
#: would give (``|dr| > tan(incidence) r |dtheta|``) belong to another surface.
MAX_INCIDENCE_RAD = math.radians(80.0)


def across_beam_slope(
    range_m: ArrayLike,
    azimuth_rad: ArrayLike,
    *,
    half_beams: int = 2,
    max_incidence_rad: float = MAX_INCIDENCE_RAD,
) -> NDArray[np.float64]:
    """Local slope ``dr / dtheta`` (m/rad) of each return's surface across the beams of its ping.

    Least-squares line of range against azimuth through the return and those of the beams up to
    ``half_beams`` on either side that have a return on the same surface: within
    ``tan(max_incidence_rad) r |dtheta|`` of the return's range ``r`` (a larger jump is an edge to
    another surface, not a slope).  Averaging over the window makes the slope's sign robust to the
    returns' range noise (a central difference of two beams flips it on a tenth of the seafloor
    survey's returns, a five-beam line on a twentieth).

    Parameters
    ----------
    range_m : array_like, shape (n_pings, n_beams) or (n_beams,)
        Ranges; NaN (or non-positive) = no return.
    azimuth_rad : array_like, shape (n_beams,) or like ``range_m``
        Beam azimuths.
    half_beams : int
        Neighbours on each side.
    max_incidence_rad : float
        Steepest surface a neighbour's range may imply, in ``(0, pi/2)``.

    Returns
    -------
    ndarray of float64, shape like ``range_m``
        NaN where the return has no neighbour on its surface, or no return.
    """
    r = np.asarray(range_m, dtype=np.float64)
    one = r.ndim == 1
    r = np.atleast_2d(r)
    if r.ndim != 2:
        raise InputError(f"range_m: expected (n_pings, n_beams), got shape {np.shape(range_m)}")
    a = np.asarray(azimuth_rad, dtype=np.float64)
    if a.shape not in ((r.shape[1],), r.shape):
        raise InputError(f"azimuth_rad: shape {a.shape} does not match the ranges' {r.shape}")
    if int(half_beams) != half_beams or half_beams < 1:
        raise InputError(f"half_beams: must be a positive integer, got {half_beams}")
    if not 0.0 < max_incidence_rad < math.pi / 2:
        raise InputError(f"max_incidence_rad: must be in (0, pi/2), got {max_incidence_rad}")
    tan_max = math.tan(max_incidence_rad)
    with np.errstate(invalid="ignore"):
        has = np.isfinite(r) & (r > 0)
    B = r.shape[1]
    # sums over the window of the neighbours on the return's surface, in differences from the
    # return itself (which counts with 0, 0): a constant range gives a slope of exactly 0
    n = has.astype(np.float64)
    sa, sr, saa, sar = (np.zeros(r.shape) for _ in range(4))
    for k in range(1, int(half_beams) + 1):
        if k >= B:
            break
        for lo, hi in ((slice(k, None), slice(None, -k)), (slice(None, -k), slice(k, None))):
            # beam j (lo) and its neighbour j -/+ k (hi)
            with np.errstate(invalid="ignore"):
                da, dr = a[..., hi] - a[..., lo], r[:, hi] - r[:, lo]
                ok = has[:, lo] & has[:, hi] & (np.abs(dr) <= tan_max * np.abs(da) * r[:, lo])
            da, dr = np.where(ok, da, 0.0), np.where(ok, dr, 0.0)
            n[:, lo] += ok
            sa[:, lo] += da
            sr[:, lo] += dr
            saa[:, lo] += da * da
            sar[:, lo] += da * dr
    with np.errstate(invalid="ignore", divide="ignore"):
        den = saa - sa * sa / n
        slope = (sar - sa * sr / n) / den
    slope = np.where(has & (n >= 2) & (den > 0), slope, np.nan)
    return slope[0] if one else slope


def footprint_azimuths(
    range_m: ArrayLike,
    azimuth_rad: ArrayLike,
    beamwidth_rad: ArrayLike,
    *,
    fraction: float = FOOTPRINT_EDGE_FRACTION,
    half_beams: int = 2,
    max_incidence_rad: float = MAX_INCIDENCE_RAD,
) -> NDArray[np.float64]:
    """Azimuth at which each leading-edge return was measured: its footprint's near edge.

    A return's range is its echo's leading edge (``DESIGN.md``, "Range convention"): the nearest
    surface in the beam's two-way -3 dB footprint, which on a surface inclined across the beams
    lies ``fraction x beamwidth`` (1/2: the footprint's edge) from the axis, on the side where
    the surface comes nearer the sonar.  That side is the sign of the across-beam slope
    ``dr/dtheta`` of the return's surface (:func:`across_beam_slope`: a line through the
    neighbouring beams' returns of the same ping); the azimuth is ``theta_c - sign(s) x fraction
    x W``.  Where the slope is unknown (an isolated return), zero (a surface at normal incidence:
    every point of the footprint is equally near) or the beamwidth is unknown (NaN), the return
    stays on the axis.

    Parameters
    ----------
    range_m : array_like, shape (n_pings, n_beams) or (n_beams,)
        Ranges; NaN (or non-positive) = no return.
    azimuth_rad : array_like, shape (n_beams,) or like ``range_m``
        Beam-axis azimuths.
    beamwidth_rad : array_like, broadcastable to ``range_m``
        Each beam's two-way -3 dB width in the fan's plane
        (:attr:`~sonarmap.geometry.SonarGeometry.azimuth_beamwidth_rad`); NaN = unknown.
    fraction : float
        Offset of the near edge from the axis in beamwidths, in ``[0, 1]``.
    half_beams, max_incidence_rad
        The slope's window (:func:`across_beam_slope`).

    Returns
    -------
    ndarray of float64, shape like ``range_m``
        The azimuths (the axis where unchanged; also where there is no return).

    Examples
    --------
    A plane whose range grows to starboard: each return moves half a beamwidth to port.

    >>> import numpy as np
    >>> az = np.radians([-1.0, -0.5, 0.0, 0.5, 1.0])
    >>> r = 5.0 + 0.2 * np.degrees(az)
    >>> np.degrees(footprint_azimuths(r, az, np.radians(0.4))).round(2).tolist()
    [-1.2, -0.7, -0.2, 0.3, 0.8]
    """
    if not 0.0 <= fraction <= 1.0:
        raise InputError(f"fraction: must be in [0, 1], got {fraction}")
    r = np.asarray(range_m, dtype=np.float64)
    a = np.asarray(azimuth_rad, dtype=np.float64)
    try:
        w = np.broadcast_to(np.asarray(beamwidth_rad, dtype=np.float64), r.shape)
    except ValueError:
        raise InputError(f"beamwidth_rad: shape {np.shape(beamwidth_rad)} does not broadcast to {r.shape}") from None
    s = across_beam_slope(r, a, half_beams=half_beams, max_incidence_rad=max_incidence_rad)
    shift = np.sign(s) * (fraction * w)
    return np.where(np.isfinite(shift), a - shift, a)
