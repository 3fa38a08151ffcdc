"""Georeferenced 2-D grids: occupancy and height / bathymetry rasters, written as GeoTIFF.

A :class:`GeoRaster` is a north-up grid in a projected CRS: ``data[band, row, col]`` (float32),
row 0 the **north** edge, column 0 the west edge, with the affine ``transform`` that GDAL and
rasterio use (``E = c + a col + b row``, ``N = f + d col + e row`` for the *corner* of a pixel;
``b = d = 0``, ``e = -a`` here).  Two builders make one from sonarmap's products:

* :func:`height_raster` grids a point cloud **in projected coordinates**: each point is projected
  exactly (:meth:`GeoReference.to_projected`) and binned in easting / northing, so the grid
  convergence and the projection's scale factor cost nothing.  Bands: ``shallowest``, ``mean``,
  ``deepest`` (metres; ``vertical="depth"``: below the origin's height, positive down - the
  bathymetry of a downward-looking survey - or ``vertical="height"``: the projected height,
  positive up, the LAS ``z``) and ``count`` (points per cell).
* :func:`occupancy_raster` projects an occupancy map onto the horizontal plane - the occupancy
  probability of the 2-D grid, or for a 3-D map the maximum over each vertical column of its
  observed voxels' probability - and **resamples** that local grid into the projected one
  (:func:`resample_local_grid`): the local frame's axes point to true north / east, which differ
  from grid north by the convergence angle (0.1 deg at 3.1 deg E in UTM 31, up to ~3 deg at the
  edge of a zone at high latitude), so the local grid cannot be written with a north-up transform
  as it is.  Each output pixel takes the value of the local cell under its centre (nearest
  neighbour, exact placement to within half a cell; no blending of probabilities).  Cells never
  observed are ``nodata``.

:func:`write_geotiff` writes a raster atomically (deflate, floating-point predictor), with the
CRS (as its EPSG code when it has one), the nodata value, and per band a description (its name)
and ``units`` / ``meaning`` tags.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap._atomic import atomic_path
from sonarmap.errors import DataFormatError, InputError
from sonarmap.mapping.frames import world_frame
from sonarmap.mapping.georef import GeoReference
from sonarmap.mapping.occupancy import OccupancyArray, OccupancyMap
from sonarmap.mapping.register import PointCloud

if TYPE_CHECKING:  # pragma: no cover
    import pyproj

__all__ = [
    "GeoRaster",
    "height_raster",
    "occupancy_raster",
    "resample_local_grid",
    "write_geotiff",
    "read_geotiff",
    "MAX_RASTER_CELLS",
]

#: Upper bound on ``rows * cols`` of one raster (400 M cells = 1.6 GB per float32 band).
MAX_RASTER_CELLS = 400_000_000

_MEANINGS = {
    "occupancy": ("1", "occupancy probability (max over the vertical column for a 3-D map); nodata = never observed"),
    "count": ("1", "number of points in the cell"),
}


@dataclasses.dataclass(frozen=True, eq=False)
class GeoRaster:
    """A north-up raster in a projected CRS.

    Parameters
    ----------
    data : ndarray, shape (n_bands, n_rows, n_cols), float32
        Row 0 is the north edge, column 0 the west edge; ``nodata`` (NaN by default) where there
        is no value.
    transform : tuple of 6 floats
        ``(a, b, c, d, e, f)``: ``E = a col + b row + c``, ``N = d col + e row + f`` for pixel
        corners (``rasterio``'s ``Affine``; GDAL's geotransform is ``(c, a, b, f, d, e)``).
    crs_wkt : str
        The CRS (WKT).
    epsg : int or None
        Its EPSG code when it has one.
    band_names : tuple of str
        One per band.
    band_units : tuple of str
        Units of each band (``"m"``, ``"1"`` for dimensionless).
    band_meanings : tuple of str
        One sentence per band (written as the band's ``meaning`` tag).
    nodata : float
        The value of empty cells (NaN by default).
    """

    data: NDArray[np.float32]
    transform: tuple[float, float, float, float, float, float]
    crs_wkt: str
    epsg: int | None
    band_names: tuple[str, ...]
    band_units: tuple[str, ...]
    band_meanings: tuple[str, ...]
    nodata: float = math.nan

    def __post_init__(self) -> None:
        d = np.asarray(self.data, dtype=np.float32)
        if d.ndim == 2:
            d = d[None]
        if d.ndim != 3:
            raise InputError(f"data: expected (n_bands, n_rows, n_cols), got shape {d.shape}")
        object.__setattr__(self, "data", d)
        t = tuple(float(v) for v in self.transform)
        if len(t) != 6 or not all(math.isfinite(v) for v in t) or t[0] * t[4] - t[1] * t[3] == 0:
            raise InputError(f"transform: need 6 finite numbers of an invertible affine map, got {self.transform}")
        object.__setattr__(self, "transform", t)
        n = d.shape[0]
        for name in ("band_names", "band_units", "band_meanings"):
            v = tuple(str(s) for s in getattr(self, name))
            if len(v) != n:
                raise InputError(f"{name}: {len(v)} entries for {n} bands")
            object.__setattr__(self, name, v)

    @property
    def shape(self) -> tuple[int, int]:
        """``(n_rows, n_cols)``."""
        return int(self.data.shape[1]), int(self.data.shape[2])

    @property
    def resolution_m(self) -> float:
        """Pixel width (metres, = height for the rasters built here)."""
        return float(math.hypot(self.transform[0], self.transform[3]))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(west, south, east, north)`` of a north-up raster."""
        a, _, c, _, e, f = self.transform
        rows, cols = self.shape
        return c, f + e * rows, c + a * cols, f

    @property
    def crs(self) -> pyproj.CRS:
        """The CRS as a :class:`pyproj.CRS`."""
        import pyproj

        return pyproj.CRS.from_epsg(self.epsg) if self.epsg is not None else pyproj.CRS.from_wkt(self.crs_wkt)

    def band(self, name: str) -> NDArray[np.float32]:
        """The band called ``name``, shape (n_rows, n_cols)."""
        if name not in self.band_names:
            raise InputError(f"band: {name!r} is not one of {self.band_names}")
        return self.data[self.band_names.index(name)]

    def xy(self, row: ArrayLike, col: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Projected coordinates ``(E, N)`` of pixel centres."""
        a, b, c, d, e, f = self.transform
        r = np.asarray(row, dtype=np.float64) + 0.5
        k = np.asarray(col, dtype=np.float64) + 0.5
        return a * k + b * r + c, d * k + e * r + f

    def rowcol(self, easting: ArrayLike, northing: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Row and column of the pixels containing projected points (may be outside the raster)."""
        a, b, c, d, e, f = self.transform
        det = a * e - b * d
        x = np.asarray(easting, dtype=np.float64) - c
        y = np.asarray(northing, dtype=np.float64) - f
        col = (e * x - b * y) / det
        row = (-d * x + a * y) / det
        return np.floor(row).astype(np.int64), np.floor(col).astype(np.int64)


# ---------------------------------------------------------------------------------- helpers


def _positive(value: float, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"{name}: must be positive and finite, got {value}")
    return v


def _check_cells(rows: int, cols: int, bands: int = 1) -> None:
    if rows * cols * bands > MAX_RASTER_CELLS:
        raise InputError(
            f"resolution_m: a {rows} x {cols} raster ({bands} band(s)) exceeds {MAX_RASTER_CELLS} cells; coarsen it"
        )


def _snap_grid(
    e_min: float, e_max: float, n_min: float, n_max: float, res: float
) -> tuple[float, float, int, int]:
    """West / north edges on multiples of ``res`` covering the box, and ``(rows, cols)``."""
    west = math.floor(e_min / res) * res
    north = (math.floor(n_max / res) + 1) * res
    cols = int(math.floor((e_max - west) / res)) + 1
    rows = int(math.floor((north - n_min) / res)) + 1
    return west, north, rows, cols


def _sigmoid(lo: NDArray[Any]) -> NDArray[np.float32]:
    return (1.0 / (1.0 + np.exp(-np.asarray(lo, dtype=np.float64)))).astype(np.float32)


# ---------------------------------------------------------------------------------- builders
def resample_local_grid(
    grid: ArrayLike,
    *,
    georef: GeoReference,
    origin_m: ArrayLike,
    resolution_m: float,
    frame: str = "ned",
    nodata: float = math.nan,
    band_names: tuple[str, ...] | None = None,
    band_units: tuple[str, ...] | None = None,
    band_meanings: tuple[str, ...] | None = None,
    out_resolution_m: float | None = None,
) -> GeoRaster:
    """Resample a grid of the local horizontal plane into a north-up raster of the projected CRS.

    Parameters
    ----------
    grid : array_like, shape (nx, ny) or (n_bands, nx, ny)
        Cell values indexed by the local frame's horizontal axes (``"ned"``: axis 0 north, axis 1
        east; ``"enu"``: axis 0 east, axis 1 north) - the layout of
        :meth:`OccupancyMap.to_array`; NaN = no value.
    georef : GeoReference
    origin_m : array_like, shape (2,) (or (3,), the third is ignored)
        Local coordinates of the minimum corner of cell ``[0, 0]``.
    resolution_m : float
        Local cell size.
    frame : {"ned", "enu"}
    nodata : float
        Written where the output pixel's centre falls on no cell or on a NaN cell.
    band_names, band_units, band_meanings : tuple of str, optional
        Per-band metadata (default ``"value"``, ``""``, ``""``).
    out_resolution_m : float, optional
        Output pixel size in projected metres (default ``resolution_m``).

    Returns
    -------
    GeoRaster
        Each pixel holds the value of the local cell containing its centre (nearest neighbour),
        located with the exact inverse projection at the origin's height.

    Notes
    -----
    The local axes are rotated against the projected grid by the grid convergence and scaled by
    the projection's scale factor, so local cells and output pixels do not coincide; placing each
    pixel by its centre bounds the position error by half a cell and never mixes values.  The
    inverse projection uses the origin's height: over 1 km a 20 m height difference moves the
    local position by ~3 mm (the tilt of the vertical across the survey).
    """
    fr = world_frame(frame)
    g = np.asarray(grid, dtype=np.float64)
    if g.ndim == 2:
        g = g[None]
    if g.ndim != 3 or g.shape[1] == 0 or g.shape[2] == 0:
        raise InputError(f"grid: expected a non-empty (nx, ny) or (n_bands, nx, ny) array, got shape {np.shape(grid)}")
    res = _positive(resolution_m, "resolution_m")
    out_res = res if out_resolution_m is None else _positive(out_resolution_m, "out_resolution_m")
    o = np.asarray(origin_m, dtype=np.float64).reshape(-1)
    if o.size not in (2, 3) or not np.isfinite(o).all():
        raise InputError(f"origin_m: need 2 finite local coordinates, got {np.asarray(origin_m).tolist()}")
    nb, nx, ny = g.shape
    pixels = _outline_pixels(georef, fr, o, nx, ny, res, out_res)
    _check_cells(pixels.rows, pixels.cols, nb)
    out = _sample_local_grid(g, georef, fr, o, res, pixels)
    names = band_names or (("value",) if nb == 1 else tuple(f"band{k + 1}" for k in range(nb)))
    return _raster(out, pixels.west, pixels.north, out_res, georef, names, band_units or ("",) * nb,
                   band_meanings or ("",) * nb, nodata)


class _PixelGrid(NamedTuple):
    """A north-up pixel grid of the projected CRS."""

    west: float
    """Easting of the west edge."""
    north: float
    """Northing of the north edge."""
    rows: int
    cols: int
    resolution_m: float
    """Pixel size."""


def _outline_pixels(georef: GeoReference, frame: str, origin_m: NDArray[np.float64], nx: int, ny: int,
                    res: float, out_res: float) -> _PixelGrid:
    """The pixels of size ``out_res`` covering the projected outline of the local ``nx`` x ``ny``
    grid of cell size ``res`` whose cell ``[0, 0]`` has its minimum corner at ``origin_m``."""
    # the local grid's outline (33 points per edge), projected, gives the output's extent
    s = np.linspace(0.0, 1.0, 33)
    u = np.concatenate([s * nx, np.full_like(s, nx), s[::-1] * nx, np.zeros_like(s)]) * res + origin_m[0]
    v = np.concatenate([np.zeros_like(s), s * ny, np.full_like(s, ny), s[::-1] * ny]) * res + origin_m[1]
    outline = georef.to_projected(np.stack([u, v, np.zeros_like(u)], axis=1), frame)
    west, north, rows, cols = _snap_grid(outline[:, 0].min(), outline[:, 0].max(),
                                         outline[:, 1].min(), outline[:, 1].max(), out_res)
    return _PixelGrid(west, north, rows, cols, out_res)


def _sample_local_grid(g: NDArray[np.float64], georef: GeoReference, frame: str, origin_m: NDArray[np.float64],
                       res: float, pixels: _PixelGrid) -> NDArray[np.float32]:
    """``(n_bands, rows, cols)``: per pixel, the bands of the local cell (of ``g``, cell size ``res``)
    under its centre, NaN where there is none; located by the inverse projection at the origin's height."""
    nb, nx, ny = g.shape
    rows, cols, out_res, north = pixels.rows, pixels.cols, pixels.resolution_m, pixels.north
    out = np.full((nb, rows, cols), np.nan, dtype=np.float32)
    e = pixels.west + (np.arange(cols) + 0.5) * out_res
    for r0 in range(0, rows, max(1, 2_000_000 // cols)):  # bounded memory: ~2 M pixels a block
        r1 = min(rows, r0 + max(1, 2_000_000 // cols))
        n = north - (np.arange(r0, r1) + 0.5) * out_res
        E, N = np.meshgrid(e, n)
        pts = np.stack([E.ravel(), N.ravel(), np.full(E.size, georef.height0_m)], axis=1)
        loc = georef.from_projected(pts, frame)
        i = np.floor((loc[:, 0] - origin_m[0]) / res).astype(np.int64)
        j = np.floor((loc[:, 1] - origin_m[1]) / res).astype(np.int64)
        inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        block = np.full((nb, E.size), np.nan, dtype=np.float32)
        block[:, inside] = g[:, i[inside], j[inside]]
        out[:, r0:r1, :] = block.reshape(nb, r1 - r0, cols)
    return out


def _raster(
    data: NDArray[np.float32], west: float, north: float, res: float, georef: GeoReference,
    names: tuple[str, ...], units: tuple[str, ...], meanings: tuple[str, ...], nodata: float,
) -> GeoRaster:
    nd = float(nodata)
    if not math.isnan(nd):
        data = np.where(np.isnan(data), np.float32(nd), data)
    return GeoRaster(data, (res, 0.0, west, 0.0, -res, north), georef.crs_wkt, georef.epsg,
                     tuple(names), tuple(units), tuple(meanings), nd)


def occupancy_raster(
    occupancy: OccupancyMap | OccupancyArray,
    *,
    georef: GeoReference,
    frame: str = "ned",
    nodata: float = math.nan,
    out_resolution_m: float | None = None,
    max_cells: int = MAX_RASTER_CELLS,
) -> GeoRaster:
    """Occupancy probability of a map's horizontal plane as a north-up projected raster.

    Parameters
    ----------
    occupancy : OccupancyMap or OccupancyArray
        A 2-D grid (its probability) or a 3-D voxel map (per vertical column, the maximum
        probability of its observed voxels).
    georef : GeoReference
        Ties the map's local frame to the CRS.
    frame : {"ned", "enu"}
        The map's local frame (OccupancyMap built from sonarmap poses: ``"ned"``).
    nodata : float
        Value of pixels over cells never observed (default NaN).
    out_resolution_m : float, optional
        Pixel size (default the map's cell size).
    max_cells : int
        Upper bound on the horizontal local grid.

    Returns
    -------
    GeoRaster
        One band ``"occupancy"`` in [0, 1] (see :func:`resample_local_grid` for the placement).

    Examples
    --------
    >>> g = GeoReference.from_origin(51.3685, 3.139)                   # doctest: +SKIP
    >>> write_geotiff("occupancy.tif", occupancy_raster(m, georef=g))  # doctest: +SKIP
    """
    if isinstance(occupancy, OccupancyMap):
        res = occupancy.config.resolution_m
        ijk = occupancy.observed_cells()
        if ijk.shape[0] == 0:
            raise InputError("occupancy: the map has no observed cells")
        lo, _ = occupancy.logodds_at(occupancy.cell_centers(ijk))
        lo_c = ijk[:, :2].min(axis=0)
        shape = tuple(int(v) for v in ijk[:, :2].max(axis=0) - lo_c + 1)
        if shape[0] * shape[1] > max_cells:
            raise InputError(f"max_cells: the horizontal grid {shape} has more than {max_cells} cells")
        best = np.full(shape, -np.inf, dtype=np.float64)
        np.maximum.at(best, (ijk[:, 0] - lo_c[0], ijk[:, 1] - lo_c[1]), lo.astype(np.float64))
        origin = lo_c.astype(np.float64) * res
    elif isinstance(occupancy, OccupancyArray):
        res = float(occupancy.resolution_m)
        lo = np.asarray(occupancy.logodds, dtype=np.float64)
        seen = np.asarray(occupancy.observed, dtype=bool)
        if lo.size == 0 or not seen.any():
            raise InputError("occupancy: the array has no observed cells")
        if lo.ndim == 3:
            best = np.where(seen, lo, -np.inf).max(axis=2)
        elif lo.ndim == 2:
            best = np.where(seen, lo, -np.inf)
        else:
            raise InputError(f"occupancy: expected a 2-D or 3-D array, got shape {lo.shape}")
        origin = np.asarray(occupancy.origin_m, dtype=np.float64)[:2]
    else:
        raise InputError(f"occupancy: expected an OccupancyMap or OccupancyArray, got {type(occupancy).__name__}")
    prob = np.where(np.isfinite(best), _sigmoid(np.where(np.isfinite(best), best, 0.0)), np.nan)
    units, meaning = _MEANINGS["occupancy"]
    return resample_local_grid(prob, georef=georef, origin_m=origin, resolution_m=res, frame=frame, nodata=nodata,
                               band_names=("occupancy",), band_units=(units,), band_meanings=(meaning,),
                               out_resolution_m=out_resolution_m)


def height_raster(
    cloud: PointCloud,
    *,
    georef: GeoReference,
    resolution_m: float,
    vertical: Literal["depth", "height"] = "depth",
    nodata: float = math.nan,
) -> GeoRaster:
    """Bathymetry / height grid of a point cloud, binned in projected coordinates.

    Parameters
    ----------
    cloud : PointCloud
        Points in the local frame (``cloud.frame``), e.g. the registered returns of a
        downward-looking survey.
    georef : GeoReference
    resolution_m : float
        Pixel size in projected metres; pixel edges are multiples of it (adjacent surveys align).
    vertical : {"depth", "height"}
        ``"depth"``: metres below the origin's height (``height0_m - h``, positive down: NED's
        ``z`` made exact over the curved Earth); ``"height"``: the projected height ``h``
        (positive up, the LAS ``z``).
    nodata : float
        Value of the depth bands where a pixel has no point (the ``count`` band is 0 there).

    Returns
    -------
    GeoRaster
        Bands ``shallowest``, ``mean``, ``deepest`` (metres, in the ``vertical`` convention:
        shallowest = the highest point of the cell) and ``count``.

    Examples
    --------
    >>> r = height_raster(cloud, georef=g, resolution_m=0.5)  # doctest: +SKIP
    >>> r.band("deepest")                                      # doctest: +SKIP
    """
    if not isinstance(cloud, PointCloud):
        raise InputError(f"cloud: expected a PointCloud, got {type(cloud).__name__}")
    if vertical not in ("depth", "height"):
        raise InputError(f"vertical: must be 'depth' or 'height', got {vertical!r}")
    res = _positive(resolution_m, "resolution_m")
    if len(cloud) == 0:
        raise InputError("cloud: no points to grid")
    p = georef.to_projected(cloud.xyz_m, cloud.frame)
    west, north, rows, cols = _snap_grid(p[:, 0].min(), p[:, 0].max(), p[:, 1].min(), p[:, 1].max(), res)
    _check_cells(rows, cols, 4)
    col = np.clip(np.floor((p[:, 0] - west) / res).astype(np.int64), 0, cols - 1)
    row = np.clip(np.floor((north - p[:, 1]) / res).astype(np.int64), 0, rows - 1)
    z = georef.height0_m - p[:, 2] if vertical == "depth" else p[:, 2]
    cell = row * cols + col
    order = np.argsort(cell, kind="stable")
    cs, zs = cell[order], z[order]
    starts = np.flatnonzero(np.r_[True, cs[1:] != cs[:-1]])
    ids = cs[starts]
    counts = np.diff(np.r_[starts, cs.size])
    lo = np.minimum.reduceat(zs, starts)
    hi = np.maximum.reduceat(zs, starts)
    mean = np.add.reduceat(zs, starts) / counts
    out = np.full((4, rows * cols), np.nan, dtype=np.float32)
    shallow, deep = (lo, hi) if vertical == "depth" else (hi, lo)
    out[0, ids], out[1, ids], out[2, ids] = shallow, mean, deep
    out[3] = 0.0
    out[3, ids] = counts
    word = "depth below the origin's height (m, positive down)" if vertical == "depth" else "height (m, positive up)"
    meanings = (f"shallowest {word}", f"mean {word}", f"deepest {word}", _MEANINGS["count"][1])
    return _raster(out.reshape(4, rows, cols), west, north, res, georef, ("shallowest", "mean", "deepest", "count"),
                   ("m", "m", "m", "1"), meanings, nodata)


# ---------------------------------------------------------------------------------- GeoTIFF
def write_geotiff(
    path: str | os.PathLike[str],
    grid: GeoRaster | ArrayLike,
    *,
    georef: GeoReference | None = None,
    origin_m: ArrayLike | None = None,
    resolution_m: float | None = None,
    frame: str = "ned",
    nodata: float = math.nan,
    band_names: tuple[str, ...] | None = None,
) -> GeoRaster:
    """Write a GeoTIFF (float32 bands, deflate-compressed), atomically.

    Parameters
    ----------
    path : path-like
    grid : GeoRaster or array_like
        A raster from :func:`occupancy_raster` / :func:`height_raster`, or a local grid
        ``(nx, ny)`` / ``(n_bands, nx, ny)`` to resample with :func:`resample_local_grid` (then
        ``georef``, ``origin_m`` and ``resolution_m`` are required).
    georef, origin_m, resolution_m, frame, nodata, band_names
        For a local grid only (see :func:`resample_local_grid`).

    Returns
    -------
    GeoRaster
        What was written.

    Raises
    ------
    InputError
        On missing or contradictory arguments.
    DataFormatError
        If GDAL cannot write the file (the target is left untouched).

    Examples
    --------
    >>> write_geotiff("bathy.tif", height_raster(cloud, georef=g, resolution_m=0.5))  # doctest: +SKIP
    """
    if isinstance(grid, GeoRaster):
        if any(v is not None for v in (georef, origin_m, resolution_m, band_names)):
            raise InputError(
                "grid: a GeoRaster carries its own georeference; drop georef/origin_m/resolution_m/band_names"
            )
        raster = grid
    else:
        if georef is None or origin_m is None or resolution_m is None:
            raise InputError("georef/origin_m/resolution_m: required to write a local grid")
        raster = resample_local_grid(grid, georef=georef, origin_m=origin_m, resolution_m=resolution_m, frame=frame,
                                     nodata=nodata, band_names=band_names)
    _write(Path(path), raster)
    return raster


def _rio_crs(raster: GeoRaster) -> Any:
    from rasterio.crs import CRS

    return CRS.from_epsg(raster.epsg) if raster.epsg is not None else CRS.from_wkt(raster.crs_wkt)


def _write(path: Path, raster: GeoRaster) -> None:
    import rasterio
    from affine import Affine
    from rasterio.errors import RasterioError

    nb = raster.data.shape[0]
    rows, cols = raster.shape
    profile: dict[str, Any] = {
        "driver": "GTiff", "width": cols, "height": rows, "count": nb, "dtype": "float32",
        "crs": _rio_crs(raster), "transform": Affine(*raster.transform), "nodata": raster.nodata,
        "compress": "deflate", "predictor": 3, "BIGTIFF": "IF_SAFER",
    }
    if rows >= 512 and cols >= 512:
        profile.update(tiled=True, blockxsize=256, blockysize=256)
    with atomic_path(path) as tmp:
        try:
            with rasterio.Env(GDAL_PAM_ENABLED="NO"), rasterio.open(tmp, "w", **profile) as dst:
                dst.write(raster.data)
                for k in range(nb):
                    dst.set_band_description(k + 1, raster.band_names[k])
                    tags = {"units": raster.band_units[k]}
                    if raster.band_meanings[k]:
                        tags["meaning"] = raster.band_meanings[k]
                    dst.update_tags(k + 1, **tags)
                dst.update_tags(software="sonarmap")
        except (RasterioError, OSError, ValueError) as exc:
            raise DataFormatError(f"cannot write GeoTIFF: {' '.join(str(exc).split())[:200]}", path) from None


def read_geotiff(path: str | os.PathLike[str]) -> GeoRaster:
    """Read a GeoTIFF written by :func:`write_geotiff` (or any single-CRS raster) as a :class:`GeoRaster`.

    Raises
    ------
    DataFormatError
        If rasterio cannot open it or it has no CRS.
    """
    import rasterio
    from rasterio.errors import RasterioError

    p = Path(path)
    try:
        with rasterio.open(p) as src:
            if src.crs is None:
                raise DataFormatError("the raster has no CRS", p)
            data = src.read().astype(np.float32)
            t = src.transform
            names = tuple(d or f"band{k + 1}" for k, d in enumerate(src.descriptions))
            tags = [src.tags(k + 1) for k in range(src.count)]
            epsg = src.crs.to_epsg()
            wkt = src.crs.to_wkt()
            nodata = math.nan if src.nodata is None else float(src.nodata)
    except (RasterioError, OSError) as exc:
        if isinstance(exc, DataFormatError):
            raise
        raise DataFormatError(f"cannot read GeoTIFF: {' '.join(str(exc).split())[:200]}", p) from None
    return GeoRaster(data, (t.a, t.b, t.c, t.d, t.e, t.f), wkt, epsg, names,
                     tuple(tg.get("units", "") for tg in tags), tuple(tg.get("meaning", "") for tg in tags), nodata)
