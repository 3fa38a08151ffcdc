"""Polar -> Cartesian ("fan") rendering that honours the per-beam azimuth table.

The sonar image is sampled on a regular metric grid in the sonar's horizontal plane with
:func:`scipy.ndimage.map_coordinates` (bilinear).  For each output pixel at forward ``x`` and
starboard ``y`` the fractional range-bin index is interpolated from ``geometry.range_m`` and the
fractional beam index from ``geometry.azimuth_rad`` - so non-uniform azimuth tables (DIDSON, ARIS)
are placed exactly where the sonar looked.  The coordinate look-up is cached per geometry and
resolution, so rendering a sequence of pings costs one interpolation each.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ping import as_image

__all__ = ["FanImage", "MAX_FAN_PIXELS", "check_fan_resolution", "fan_image", "fan_extent_m", "polar_to_xy",
           "xy_to_polar"]

#: The most pixels a fan image may have: :func:`fan_image` refuses a finer resolution before it
#: allocates anything (50 Mpixel of float32 coordinates and image are about 0.6 GB).
MAX_FAN_PIXELS = 50_000_000


@dataclasses.dataclass(frozen=True, eq=False)
class FanImage:
    """A ping resampled onto a metric Cartesian grid.

    Attributes
    ----------
    image : ndarray, shape (n_x, n_y), float32
        Row ``i`` is forward distance ``x_m[i]`` (increasing), column ``k`` is starboard offset
        ``y_m[k]`` (increasing).  NaN outside the fan.  Show with
        ``plt.imshow(fan.image, origin="lower", extent=fan.extent_m)``.
    x_m : ndarray, shape (n_x,)
        Forward coordinate of each row's pixel centre (m).
    y_m : ndarray, shape (n_y,)
        Starboard coordinate of each column's pixel centre (m).
    resolution_m : float
        Pixel size (m).
    """

    image: NDArray[np.float32]
    x_m: NDArray[np.float64]
    y_m: NDArray[np.float64]
    resolution_m: float

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """``(left, right, bottom, top)`` = ``(y_min, y_max, x_min, x_max)`` of the pixel edges,
        for ``imshow(..., origin="lower", extent=...)``."""
        h = self.resolution_m / 2
        return (
            float(self.y_m[0] - h),
            float(self.y_m[-1] + h),
            float(self.x_m[0] - h),
            float(self.x_m[-1] + h),
        )

    def pixel_of(self, x_m: float, y_m: float) -> tuple[int, int]:
        """Row and column of the pixel containing the point ``(x_m, y_m)``."""
        row = int(np.rint((x_m - self.x_m[0]) / self.resolution_m))
        col = int(np.rint((y_m - self.y_m[0]) / self.resolution_m))
        return row, col


def polar_to_xy(
    range_m: ArrayLike, azimuth_rad: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Sonar-plane coordinates (forward ``x``, starboard ``y``) of range/azimuth pairs."""
    r = np.asarray(range_m, dtype=np.float64)
    a = np.asarray(azimuth_rad, dtype=np.float64)
    return r * np.cos(a), r * np.sin(a)


def xy_to_polar(
    x_m: ArrayLike, y_m: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Range and azimuth (positive to starboard) of sonar-plane points."""
    x = np.asarray(x_m, dtype=np.float64)
    y = np.asarray(y_m, dtype=np.float64)
    return np.hypot(x, y), np.arctan2(y, x)


def _beam_edges(az: NDArray[np.float64]) -> tuple[float, float]:
    if az.size == 1:
        return float(az[0]) - 1e-3, float(az[0]) + 1e-3
    return float(az[0] - (az[1] - az[0]) / 2), float(az[-1] + (az[-1] - az[-2]) / 2)


def _range_edges(geometry: SonarGeometry) -> tuple[float, float]:
    r = geometry.range_m
    step = geometry.range_resolution_m
    return float(r[0] - step / 2), float(r[-1] + step / 2)


def fan_extent_m(geometry: SonarGeometry) -> tuple[float, float, float, float]:
    """Bounding box ``(x_min, x_max, y_min, y_max)`` of the fan (pixel-edge to pixel-edge)."""
    a0, a1 = _beam_edges(geometry.azimuth_rad)
    r0, r1 = _range_edges(geometry)
    r0 = max(r0, 0.0)
    angles = np.array([a0, a1, *([0.0] if a0 < 0 < a1 else [])])
    xs = np.concatenate([r0 * np.cos(angles), r1 * np.cos(angles)])
    ys = np.concatenate([r0 * np.sin(angles), r1 * np.sin(angles)])
    return float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max())


def _fan_shape(geometry: SonarGeometry, resolution_m: float) -> tuple[int, int]:
    """``(n_x, n_y)``: the fan image's rows and columns at ``resolution_m``."""
    x0, x1, y0, y1 = fan_extent_m(geometry)
    return max(1, math.ceil((x1 - x0) / resolution_m)), max(1, math.ceil((y1 - y0) / resolution_m))


def check_fan_resolution(geometry: SonarGeometry, resolution_m: float) -> float:
    """``resolution_m`` as a float, checked before a fan of ``geometry`` is rendered at it.

    Parameters
    ----------
    geometry : SonarGeometry
        The ping's geometry (its fan's extent).
    resolution_m : float
        The fan's pixel size (m).

    Returns
    -------
    float
        ``resolution_m``.

    Raises
    ------
    InputError
        If ``resolution_m`` is not a positive finite number, or gives a fan of more than
        :data:`MAX_FAN_PIXELS` pixels (the message gives the finest resolution allowed).

    Examples
    --------
    >>> from sonarmap.geometry import preset
    >>> check_fan_resolution(preset("didson-hf"), 0.02)
    0.02
    """
    r = float(resolution_m)
    if not math.isfinite(r) or r <= 0:
        raise InputError(f"resolution_m: must be a positive number of metres (got {r:g})")
    nx, ny = _fan_shape(geometry, r)
    if nx * ny > MAX_FAN_PIXELS:
        x0, x1, y0, y1 = fan_extent_m(geometry)
        finest = math.sqrt((x1 - x0) * (y1 - y0) / MAX_FAN_PIXELS)
        raise InputError(f"resolution_m: {r:g} m gives a fan of {nx * ny:.3g} pixels, more than "
                         f"{MAX_FAN_PIXELS:.0e}; give at least {1.01 * finest:.2g} m")
    return r


@functools.lru_cache(maxsize=16)
def _lookup(
    geometry: SonarGeometry, resolution_m: float
) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    x0, _, y0, _ = fan_extent_m(geometry)
    nx, ny = _fan_shape(geometry, resolution_m)
    x_m = x0 + (np.arange(nx) + 0.5) * resolution_m
    y_m = y0 + (np.arange(ny) + 0.5) * resolution_m
    r, a = xy_to_polar(x_m[:, None], y_m[None, :])
    az = geometry.azimuth_rad
    rng = geometry.range_m
    a0, a1 = _beam_edges(az)
    r0, r1 = _range_edges(geometry)
    inside = (r >= r0) & (r <= r1) & (a >= a0) & (a <= a1)
    # Fractional indices; outside the first/last centre (half a beam/bin) we clamp to the edge.
    row = np.interp(r, rng, np.arange(rng.size)) if rng.size > 1 else np.zeros_like(r)
    col = np.interp(a, az, np.arange(az.size)) if az.size > 1 else np.zeros_like(a)
    coords = np.stack([row, col]).astype(np.float32)
    return coords, inside, x_m, y_m


def fan_image(
    image: ArrayLike,
    geometry: SonarGeometry,
    *,
    resolution_m: float | None = None,
    order: int = 1,
) -> FanImage:
    """Render a polar ping (n_bins, n_beams) as a Cartesian fan.

    Parameters
    ----------
    image : array_like, shape (n_bins, n_beams)
        Polar image (rows = range bins, columns = beams with azimuth increasing).
    geometry : SonarGeometry
        Supplies the range-bin and per-beam azimuth tables.
    resolution_m : float, optional
        Output pixel size; defaults to the range resolution (at least 1 mm).
    order : int
        Spline order of the interpolation (0 nearest, 1 bilinear).

    Returns
    -------
    FanImage

    Raises
    ------
    InputError
        If ``resolution_m`` is not positive or too fine (:func:`check_fan_resolution`).
    """
    from scipy.ndimage import map_coordinates

    img = as_image(image)
    geometry.check_image(img)
    if resolution_m is None:
        resolution_m = max(geometry.range_resolution_m, 1e-3)
    resolution_m = check_fan_resolution(geometry, resolution_m)
    coords, inside, x_m, y_m = _lookup(geometry, resolution_m)
    out = map_coordinates(img, coords, order=order, mode="nearest", prefilter=False)
    out = out.astype(np.float32, copy=False)
    out[~inside] = np.nan
    return FanImage(image=out, x_m=x_m, y_m=y_m, resolution_m=resolution_m)
