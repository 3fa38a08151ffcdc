"""Point-cloud files: binary PLY (plyfile), LAS 1.4 (laspy) and CSV, each readable back losslessly.

Times are absolute in every file (the ping's UTC time; :attr:`PointCloud.time_ns` is integer ns
since the Unix epoch):

* **PLY** (binary little-endian): vertex element with ``x, y, z`` (float32), ``time`` (float64,
  **seconds since the Unix epoch**, UTC; float64 resolves 0.24 µs until 2038 and 0.48 µs until
  2106), ``time_residual_ns`` (int32, ``time_ns`` minus ``time`` rounded to ns, so the file reads
  back exactly; other tools can ignore it), ``beam`` (int32), ``range`` / ``intensity`` /
  ``confidence`` / ``elevation`` / ``sigma`` (float32; ``sigma`` = one-sigma range uncertainty,
  NaN = unknown).  Coordinates are stored relative to an ``offset_m`` (default zero) recorded in a
  ``comment offset_m X Y Z`` line so large world coordinates keep float32 precision;
  a ``comment frame ned|enu`` line records the frame.  Opens in CloudCompare, MeshLab, Open3D.
  Files of earlier versions (``time`` relative to a ``comment time_offset_ns N``) still read.
* **LAS 1.4** (point format 6): coordinates as scaled integers (``scale_m``, default 0.1 mm;
  offset = the cloud's minimum rounded down to a metre), ``gps_time`` = **adjusted standard GPS
  time** (GPS seconds - 1e9, with the global-encoding GPS-time-type bit set, as LAS 1.4 specifies;
  GPS seconds = Unix seconds - 315964800 + the leap seconds of :data:`GPS_LEAP_SECONDS`),
  ``intensity`` = intensity x 65535 (uint16, clipped to [0, 1] first), ``point_source_id`` = beam,
  and extra bytes ``range_m``, ``confidence``, ``elevation_rad``, ``intensity_f`` (float32),
  ``beam_index`` (int32), ``time_ns`` (int64, exact Unix ns) and ``sigma_m`` (float32, one-sigma
  range uncertainty, NaN = unknown).  Reading back gives the written coordinates to
  within ``scale_m / 2`` (exactly the quantised values).
* **CSV**: the header row is the first line,
  ``x,y,z,time_ns,beam,range_m,intensity,confidence,elevation_rad,sigma_m`` (``time_ns``: integer
  Unix ns), so ``pandas.read_csv(path)`` reads it as is; float64 coordinates are written with
  ``repr`` (exact round trip).  The metadata (frame, kind, CRS) is in a JSON sidecar
  ``<path>.json`` (:func:`csv_sidecar`); without it the file reads back as NED.  Files of earlier
  versions (``#`` comment lines before the header) still read.

Files without the ``sigma`` / ``sigma_m`` attribute (written before it existed, or by other
tools) read back with NaN uncertainties.

Occupancy maps
--------------
The cloud of :meth:`~sonarmap.mapping.occupancy.OccupancyMap.to_point_cloud` (occupied cell
centres) is not a set of returns and gets its own schema (``kind="occupancy"``; by default
recognised by :func:`cloud_kind`): ``x, y, z`` (cell centre), ``p_occupied`` (float32, the
cell's occupancy probability) and ``log_odds`` (float32, ``log(p / (1 - p))``) - no time, beam
or range.  PLY: those vertex properties and ``comment kind occupancy``; CSV: those columns and
``"kind": "occupancy"`` in the sidecar; LAS: the same coordinates, ``intensity`` =
``p_occupied`` x 65535, ``gps_time`` 0 and extra bytes ``p_occupied``, ``log_odds``.  They read
back as a cloud with ``confidence`` = ``intensity`` = ``p_occupied``, as ``to_point_cloud`` makes.

Georeferenced files
-------------------
With ``georef=`` (a :class:`~sonarmap.mapping.georef.GeoReference`) every writer converts the
cloud from its local frame into the georeference's projected CRS and records the CRS:
``x`` = easting, ``y`` = northing, ``z`` = height (up, metres; see :mod:`sonarmap.mapping.georef`),
so the file's frame is ``enu``-like and reads back with ``frame="enu"``.

* **LAS**: a WKT coordinate-system VLR (OGC WKT as LAS 1.4 specifies, see
  :func:`~sonarmap.mapping.georef.file_wkt`; ``laspy``'s ``header.parse_crs()``, PDAL and GDAL
  read it) with the global-encoding WKT bit set;
  scale 1 mm by default, offset = the minimum rounded down to a metre (so UTM-size coordinates
  keep full resolution in the 32-bit integers).
* **PLY**: float64 ``x, y, z`` (float32 would lose ~0.5 m at UTM northings) and the comments
  ``crs EPSG:xxxx`` (when the CRS has a code), ``crs_wkt <OGC WKT on one line>`` and
  ``georef_origin_deg <lat> <lon> <height_m>``.
* **CSV**: ``"crs": "EPSG:xxxx"``, ``"crs_wkt": "<OGC WKT>"`` and ``"georef_origin_deg": [lat,
  lon, height_m]`` in the JSON sidecar (``"frame": "enu"``).

:func:`read_point_cloud_crs` returns the CRS of any of them (``None`` when there is none).

LAS/PLY viewers expect z up: pass ``frame="enu"`` to write ROS/ENU coordinates (the default is the
library's NED frame, in which depth is positive ``z``).
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from sonarmap._atomic import atomic_path, atomic_write_text
from sonarmap.errors import DataFormatError, InputError
from sonarmap.mapping.register import PointCloud

if TYPE_CHECKING:  # pragma: no cover - typing only (laspy and pyproj are imported lazily)
    import laspy
    import pyproj

    from sonarmap.mapping.georef import GeoReference

__all__ = [
    "CLOUD_FORMATS",
    "CLOUD_KINDS",
    "GPS_LEAP_SECONDS",
    "write_point_cloud",
    "read_point_cloud",
    "write_ply",
    "read_ply",
    "write_las",
    "read_las",
    "write_csv",
    "read_csv",
    "csv_sidecar",
    "cloud_kind",
    "occupancy_columns",
    "format_from_suffix",
    "read_point_cloud_crs",
    "unix_ns_to_gps_adjusted",
    "gps_adjusted_to_unix_ns",
]

CloudFormat = Literal["ply", "las", "csv"]
CloudKind = Literal["points", "occupancy"]
CLOUD_FORMATS: tuple[str, ...] = ("ply", "las", "csv")
CLOUD_KINDS: tuple[str, ...] = ("points", "occupancy")
_SUFFIX = {".ply": "ply", ".las": "las", ".laz": "las", ".csv": "csv", ".txt": "csv"}

# ---------------------------------------------------------------------- time
#: Leap seconds since the GPS epoch: (UTC date from which it applies, GPS - UTC in seconds from
#: then on), from IERS Bulletin C.  No leap second has been announced after 2017-01-01.
GPS_LEAP_SECONDS: tuple[tuple[str, int], ...] = (
    ("1981-07-01", 1), ("1982-07-01", 2), ("1983-07-01", 3), ("1985-07-01", 4),
    ("1988-01-01", 5), ("1990-01-01", 6), ("1991-01-01", 7), ("1992-07-01", 8),
    ("1993-07-01", 9), ("1994-07-01", 10), ("1996-01-01", 11), ("1997-07-01", 12),
    ("1999-01-01", 13), ("2006-01-01", 14), ("2009-01-01", 15), ("2012-07-01", 16),
    ("2015-07-01", 17), ("2017-01-01", 18),
)  # fmt: skip
_GPS_EPOCH_UNIX_S = 315_964_800  # 1980-01-06T00:00:00Z
_ADJUSTED_GPS_OFFSET_S = 1_000_000_000  # LAS 1.4: adjusted standard GPS time = GPS time - 1e9
_NS = 1_000_000_000
_LEAP_UNIX_S = np.array([np.datetime64(d, "s").astype(np.int64) for d, _ in GPS_LEAP_SECONDS], np.int64)
_LEAP_COUNT = np.array([n for _, n in GPS_LEAP_SECONDS], np.int64)
_LEAP_GPS_S = _LEAP_UNIX_S - _GPS_EPOCH_UNIX_S + _LEAP_COUNT  # the same instants in GPS seconds


def _leap_at(seconds: np.ndarray, table: np.ndarray) -> np.ndarray:
    idx = np.searchsorted(table, seconds, side="right")
    return np.where(idx > 0, _LEAP_COUNT[np.maximum(idx - 1, 0)], 0)


def _ns_to_seconds(time_ns: np.ndarray, offset_s: np.ndarray | int = 0) -> np.ndarray:
    """Integer ns -> float64 seconds (+ an integer offset in s), rounding once."""
    t = np.asarray(time_ns, dtype=np.int64)
    whole = t // _NS + offset_s
    return np.asarray(whole, dtype=np.float64) + (t % _NS).astype(np.float64) * 1e-9


def _seconds_to_ns(seconds: np.ndarray, offset_s: np.ndarray | int = 0) -> np.ndarray:
    """float64 seconds (+ an integer offset in s) -> integer ns, to the nearest ns."""
    t = np.asarray(seconds, dtype=np.float64)
    whole = np.floor(t)
    frac = np.rint((t - whole) * 1e9).astype(np.int64)  # t - floor(t) is exact
    return (whole.astype(np.int64) + offset_s) * _NS + frac


def unix_ns_to_gps_adjusted(time_ns: np.ndarray) -> np.ndarray:
    """Unix time (integer ns, UTC) -> LAS adjusted standard GPS time (float64 s).

    ``GPS = Unix - 315964800 + leap seconds`` (:data:`GPS_LEAP_SECONDS`) and adjusted standard
    GPS time is ``GPS - 1e9``.

    Examples
    --------
    >>> float(unix_ns_to_gps_adjusted(np.array([1_483_228_800 * 10**9]))[0])   # 2017-01-01Z
    167264018.0
    """
    t = np.asarray(time_ns, dtype=np.int64)
    leap = _leap_at(t // _NS, _LEAP_UNIX_S)
    return _ns_to_seconds(t, leap - _GPS_EPOCH_UNIX_S - _ADJUSTED_GPS_OFFSET_S)


def gps_adjusted_to_unix_ns(gps_time: np.ndarray) -> np.ndarray:
    """LAS adjusted standard GPS time (float64 s) -> Unix time (integer ns): the inverse of
    :func:`unix_ns_to_gps_adjusted` (to the float64 resolution, ~30 ns)."""
    g = np.asarray(gps_time, dtype=np.float64)
    gps_s = np.floor(g).astype(np.int64) + _ADJUSTED_GPS_OFFSET_S
    leap = _leap_at(gps_s, _LEAP_GPS_S)
    return _seconds_to_ns(g, _ADJUSTED_GPS_OFFSET_S + _GPS_EPOCH_UNIX_S - leap)


# ---------------------------------------------------------------------- helpers
def format_from_suffix(path: str | os.PathLike[str]) -> str:
    """``"ply"``, ``"las"`` or ``"csv"`` from a file name; raises :class:`InputError` otherwise."""
    sfx = Path(path).suffix.lower()
    if sfx not in _SUFFIX:
        raise InputError(f"output: cannot infer the point-cloud format from suffix {sfx!r}; use .ply, .las or .csv")
    return _SUFFIX[sfx]


def _cloud_format(path: str | os.PathLike[str], format: str | None) -> str:  # noqa: A002
    """The point-cloud format of ``format`` (any case), else of ``path``'s suffix; InputError if
    it is not one of :data:`CLOUD_FORMATS`."""
    fmt = (format or format_from_suffix(path)).lower()
    if fmt not in CLOUD_FORMATS:
        raise InputError(f"format: must be one of {CLOUD_FORMATS}, got {format!r}")
    return fmt


def cloud_kind(cloud: PointCloud) -> str:
    """``"occupancy"`` for the occupied-cell cloud of ``OccupancyMap.to_point_cloud``, else ``"points"``.

    Recognised by what that cloud carries and a cloud of returns never does: at least one point,
    every ``beam`` -1, ``time_ns`` 0, ``range_m`` / ``sigma_m`` NaN, ``elevation_rad`` 0 and
    ``intensity`` equal to ``confidence`` (the probability), strictly inside (0, 1).  Pass
    ``kind=`` to the writers to decide explicitly.
    """
    n = len(cloud)
    if n == 0:
        return "points"
    p = cloud.confidence
    occ = (
        bool(np.all(cloud.beam == -1)) and bool(np.all(cloud.time_ns == 0))
        and bool(np.all(np.isnan(cloud.range_m))) and bool(np.all(np.isnan(np.asarray(cloud.sigma_m))))
        and bool(np.all(cloud.elevation_rad == 0)) and np.array_equal(cloud.intensity, p)
        and bool(np.all((p > 0) & (p < 1)))
    )
    return "occupancy" if occ else "points"


def _resolve_kind(cloud: PointCloud, kind: str | None) -> str:
    if kind is None:
        return cloud_kind(cloud)
    if kind not in CLOUD_KINDS:
        raise InputError(f"kind: must be one of {CLOUD_KINDS}, got {kind!r}")
    return kind


def occupancy_columns(cloud: PointCloud) -> tuple[np.ndarray, np.ndarray]:
    """``p_occupied`` and ``log_odds`` (float32) of an occupancy cloud (p = its confidence)."""
    p = np.asarray(cloud.confidence, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        lo = np.log(p) - np.log1p(-p)
    return p.astype(np.float32), lo.astype(np.float32)


def _occupancy_cloud(xyz: np.ndarray, p: np.ndarray, frame: str) -> PointCloud:
    """The cloud ``OccupancyMap.to_point_cloud`` makes from cell centres and probabilities."""
    n = xyz.shape[0]
    prob = np.asarray(p, dtype=np.float32)
    return PointCloud(
        xyz, np.zeros(n, np.int64), np.full(n, -1, np.int32), np.full(n, np.nan, np.float32), prob, prob,
        np.zeros(n, np.float32), frame=frame,
    )


def _in_frame(cloud: PointCloud, frame: str | None) -> PointCloud:
    return cloud if frame is None else cloud.to_frame(frame)


def georeferenced_cloud(cloud: PointCloud, frame: str | None, georef: GeoReference) -> PointCloud:
    """The cloud with ``xyz_m`` = projected ``(E, N, h)`` and ``frame="enu"`` (E, N, up axes)."""
    if frame is not None and str(frame).lower() != "enu":
        raise InputError(
            f"frame: a georeferenced cloud is written as easting, northing, height (z up); frame={frame!r} cannot apply"
        )
    return dataclasses.replace(cloud, xyz_m=georef.to_projected(cloud.xyz_m, cloud.frame), frame="enu")


def _crs_records(georef: GeoReference) -> list[tuple[str, str]]:
    """``crs``, ``crs_wkt`` and ``georef_origin_deg`` records (key, value)."""
    from sonarmap.mapping.georef import file_wkt

    recs = [] if georef.epsg is None else [("crs", f"EPSG:{georef.epsg}")]
    recs.append(("crs_wkt", file_wkt(georef.crs)))
    recs.append(("georef_origin_deg", f"{georef.lat0_deg!r} {georef.lon0_deg!r} {georef.height0_m!r}"))
    return recs


# ---------------------------------------------------------------------- PLY
def write_ply(
    cloud: PointCloud,
    path: str | os.PathLike[str],
    *,
    frame: str | None = None,
    offset_m: tuple[float, float, float] | None = None,
    georef: GeoReference | None = None,
    kind: str | None = None,
) -> None:
    """Write a binary little-endian PLY (float32 xyz, float64 when georeferenced, + attributes), atomically.

    Parameters
    ----------
    cloud : PointCloud
    path : path-like
    frame : {"ned", "enu"}, optional
        Convert coordinates first (default: the cloud's frame).  With ``georef`` only ``None`` or
        ``"enu"`` (the projected axes) are accepted.
    offset_m : 3 floats, optional
        Subtracted from the coordinates before the float32 cast (recorded in a comment).
    georef : GeoReference, optional
        Write projected ``(E, N, h)`` coordinates as float64, with the CRS in the comments.
    kind : {"points", "occupancy"}, optional
        Schema (module notes); default :func:`cloud_kind`.
    """
    from plyfile import PlyData, PlyElement

    knd = _resolve_kind(cloud, kind)
    c = _in_frame(cloud, frame) if georef is None else georeferenced_cloud(cloud, frame, georef)
    off = np.zeros(3) if offset_m is None else np.asarray(offset_m, dtype=np.float64)
    cdt = "<f4" if georef is None else "<f8"
    xyz = (c.xyz_m - off).astype(cdt)
    if knd == "occupancy":
        dt = [("x", cdt), ("y", cdt), ("z", cdt), ("p_occupied", "<f4"), ("log_odds", "<f4")]
        v = np.empty(len(c), dtype=dt)
        v["p_occupied"], v["log_odds"] = occupancy_columns(c)
    else:
        dt = [
            ("x", cdt), ("y", cdt), ("z", cdt), ("time", "<f8"), ("time_residual_ns", "<i4"), ("beam", "<i4"),
            ("range", "<f4"), ("intensity", "<f4"), ("confidence", "<f4"), ("elevation", "<f4"),
            ("sigma", "<f4"),
        ]
        v = np.empty(len(c), dtype=dt)
        t = _ns_to_seconds(c.time_ns)
        v["time"] = t
        v["time_residual_ns"] = c.time_ns - _seconds_to_ns(t)
        v["beam"] = c.beam
        v["range"] = c.range_m
        v["intensity"] = c.intensity
        v["confidence"] = c.confidence
        v["elevation"] = c.elevation_rad
        v["sigma"] = c.sigma_m
    v["x"], v["y"], v["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    comments = [
        "sonarmap occupancy map" if knd == "occupancy" else "sonarmap point cloud",
        f"kind {knd}",
        f"frame {c.frame}",
        "offset_m " + " ".join(repr(float(o)) for o in off),
    ]
    if knd == "points":
        comments.append("time unix_s")
    if georef is not None:
        comments += [f"{k} {val}" for k, val in _crs_records(georef)]
    ply = PlyData([PlyElement.describe(v, "vertex")], text=False, byte_order="<", comments=comments)
    with atomic_path(path) as tmp:
        ply.write(str(tmp))


def read_ply(path: str | os.PathLike[str]) -> PointCloud:
    """Read a PLY written by :func:`write_ply` (or any PLY with x, y, z vertices)."""
    from plyfile import PlyData

    p = Path(path)
    try:
        ply = PlyData.read(str(p))
        v = ply["vertex"].data
    except (OSError, KeyError, ValueError, Exception) as exc:  # plyfile raises its own errors
        raise DataFormatError(f"cannot read PLY: {exc}", p) from None
    frame, off, t_off = "ned", np.zeros(3), None
    for com in ply.comments:
        parts = com.split()
        if parts[:1] == ["frame"] and len(parts) > 1:
            frame = parts[1]
        elif parts[:1] == ["offset_m"] and len(parts) == 4:
            off = np.array([float(s) for s in parts[1:]])
        elif parts[:1] == ["time_offset_ns"] and len(parts) == 2:  # files of earlier versions
            t_off = int(parts[1])
    names = v.dtype.names or ()
    n = v.shape[0]
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64) + off
    if "p_occupied" in names:
        return _occupancy_cloud(xyz, np.asarray(v["p_occupied"]), frame)

    def get(name: str, default: float) -> np.ndarray:
        return np.asarray(v[name]) if name in names else np.full(n, default)

    t = get("time", 0.0).astype(np.float64)
    if t_off is not None:
        time_ns = np.rint(t * 1e9).astype(np.int64) + t_off
    else:
        time_ns = _seconds_to_ns(t) + get("time_residual_ns", 0).astype(np.int64)
    return PointCloud(
        xyz, time_ns, get("beam", -1), get("range", np.nan), get("intensity", 1.0),
        get("confidence", 1.0), get("elevation", 0.0), frame=frame, sigma_m=get("sigma", np.nan),
    )


# ---------------------------------------------------------------------- LAS
def write_las(
    cloud: PointCloud,
    path: str | os.PathLike[str],
    *,
    frame: str | None = None,
    scale_m: float | None = None,
    georef: GeoReference | None = None,
    kind: str | None = None,
) -> None:
    """Write a LAS 1.4 file (point format 6 + extra bytes), atomically.

    ``gps_time`` is adjusted standard GPS time (global-encoding GPS-time-type bit set).

    Parameters
    ----------
    cloud : PointCloud
    path : path-like
    frame : {"ned", "enu"}, optional
        Convert coordinates first (default: the cloud's frame).  With ``georef`` only ``None`` or
        ``"enu"`` are accepted.
    scale_m : float, optional
        Coordinate quantum; default 0.1 mm (local) or 1 mm (georeferenced).
    georef : GeoReference, optional
        Write projected ``(E, N, h)`` coordinates with the CRS as a WKT VLR.
    kind : {"points", "occupancy"}, optional
        Schema (module notes); default :func:`cloud_kind`.

    Raises
    ------
    InputError
        If the cloud's extent does not fit the 32-bit scaled integers at ``scale_m``.
    """
    import laspy

    knd = _resolve_kind(cloud, kind)
    c = _in_frame(cloud, frame) if georef is None else georeferenced_cloud(cloud, frame, georef)
    if scale_m is None:
        scale_m = 1e-4 if georef is None else 1e-3
    if not scale_m > 0:
        raise InputError(f"scale_m: must be positive, got {scale_m}")
    las = laspy.LasData(_las_header(c, knd, scale_m, georef))
    las.x = c.xyz_m[:, 0]
    las.y = c.xyz_m[:, 1]
    las.z = c.xyz_m[:, 2]
    _set_las_attributes(las, c, knd)
    with atomic_path(path) as tmp:
        las.write(str(tmp))


#: The extra bytes of each LAS schema: (name, type, description).
_LAS_EXTRA_DIMS: dict[str, tuple[tuple[str, type, str], ...]] = {
    "occupancy": (
        ("p_occupied", np.float32, "occupancy probability"),
        ("log_odds", np.float32, "occupancy log-odds"),
    ),
    "points": (
        ("range_m", np.float32, "measured range (m)"),
        ("confidence", np.float32, "return confidence"),
        ("elevation_rad", np.float32, "assumed elevation"),
        ("intensity_f", np.float32, "intensity (float)"),
        ("beam_index", np.int32, "beam index"),
        ("time_ns", np.int64, "ping time (Unix ns)"),
        ("sigma_m", np.float32, "range 1-sigma (m)"),
    ),
}


def _las_header(c: PointCloud, knd: str, scale_m: float, georef: GeoReference | None) -> laspy.LasHeader:
    """The LAS 1.4 point-format-6 header of cloud ``c`` (written as is) in schema ``knd``; raises
    :class:`InputError` if the cloud's extent does not fit the 32-bit scaled integers at ``scale_m``."""
    import laspy
    from laspy.header import GpsTimeType

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([scale_m] * 3)
    header.offsets = np.floor(c.xyz_m.min(axis=0)) if len(c) else np.zeros(3)
    if len(c):
        span = float(np.max(c.xyz_m.max(axis=0) - header.offsets)) / scale_m
        if not span < 2**31 - 1:
            raise InputError(
                f"scale_m: the cloud spans {span * scale_m:.0f} m, more than 2**31 quanta of {scale_m} m; "
                "use a larger scale_m"
            )
    header.system_identifier = f"sonarmap frame={c.frame}"[:32]
    header.generating_software = "sonarmap" if knd == "points" else "sonarmap occupancy"
    header.global_encoding.gps_time_type = GpsTimeType.STANDARD
    header.add_extra_dims([laspy.ExtraBytesParams(name=name, type=typ, description=description)
                           for name, typ, description in _LAS_EXTRA_DIMS[knd]])
    if georef is not None:
        from laspy.vlrs.known import WktCoordinateSystemVlr

        from sonarmap.mapping.georef import file_wkt

        header.vlrs.append(WktCoordinateSystemVlr(file_wkt(georef.crs)))
        header.global_encoding.wkt = True
    return header


def _set_las_attributes(las: laspy.LasData, c: PointCloud, knd: str) -> None:
    """Fill the time, intensity, point source and extra bytes of ``las`` from cloud ``c`` in schema ``knd``."""
    if knd == "occupancy":
        prob, lo = occupancy_columns(c)
        las.gps_time = np.zeros(len(c))
        las.intensity = np.rint(np.clip(prob, 0, 1) * 65535).astype(np.uint16)
        las.p_occupied = prob
        las.log_odds = lo
    else:
        las.gps_time = unix_ns_to_gps_adjusted(c.time_ns)
        las.intensity = np.rint(np.clip(np.nan_to_num(c.intensity), 0, 1) * 65535).astype(np.uint16)
        las.point_source_id = np.clip(c.beam, 0, 65535).astype(np.uint16)
        las.range_m = c.range_m
        las.confidence = c.confidence
        las.elevation_rad = c.elevation_rad
        las.intensity_f = c.intensity
        las.beam_index = c.beam
        las.time_ns = c.time_ns
        las.sigma_m = c.sigma_m


def read_las(path: str | os.PathLike[str]) -> PointCloud:
    """Read a LAS/LAZ file (extra dimensions written by :func:`write_las` are used when present).

    Without the ``time_ns`` extra bytes, ``gps_time`` is converted from adjusted standard GPS time
    when the file says so (global-encoding bit); GPS week time (no week number in the file) is
    read as seconds, a relative time.
    """
    import laspy

    p = Path(path)
    try:
        las = laspy.read(str(p))
    except Exception as exc:  # noqa: BLE001 - laspy raises several unrelated types
        raise DataFormatError(f"cannot read LAS: {exc}", p) from None
    dims = set(las.point_format.dimension_names)
    n = len(las.points)
    xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1).astype(np.float64)
    ident = str(las.header.system_identifier)
    frame = "enu" if "frame=enu" in ident else "ned"
    if "p_occupied" in dims:
        return _occupancy_cloud(xyz, np.asarray(las["p_occupied"]), frame)

    def get(name: str, default: float) -> np.ndarray:
        return np.asarray(las[name]) if name in dims else np.full(n, default)

    if "time_ns" in dims:
        t = np.asarray(las["time_ns"], dtype=np.int64)
    elif int(las.header.global_encoding.gps_time_type) == 1:
        t = gps_adjusted_to_unix_ns(np.asarray(las.gps_time, dtype=np.float64))
    else:
        t = np.rint(np.asarray(las.gps_time, dtype=np.float64) * 1e9).astype(np.int64)
    inten = get("intensity_f", np.nan)
    if "intensity_f" not in dims:
        inten = np.asarray(las.intensity, dtype=np.float32) / 65535.0
    beam = get("beam_index", -1) if "beam_index" in dims else np.asarray(las.point_source_id, dtype=np.int32)
    return PointCloud(
        xyz, t, beam, get("range_m", np.nan), inten, get("confidence", 1.0), get("elevation_rad", 0.0), frame=frame,
        sigma_m=get("sigma_m", np.nan),
    )


# ---------------------------------------------------------------------- CSV
_CSV_COLS = ("x", "y", "z", "time_ns", "beam", "range_m", "intensity", "confidence", "elevation_rad", "sigma_m")
_CSV_OCC_COLS = ("x", "y", "z", "p_occupied", "log_odds")


def csv_sidecar(path: str | os.PathLike[str]) -> Path:
    """The JSON sidecar of a point-cloud CSV: ``map.csv`` -> ``map.csv.json``."""
    p = Path(path)
    return p.with_name(p.name + ".json")


def _read_sidecar(path: Path) -> dict[str, Any]:
    side = csv_sidecar(path)
    if not side.is_file():
        return {}
    try:
        from sonarmap._files import MAX_SIDECAR_BYTES, read_bytes_bounded

        d = json.loads(read_bytes_bounded(side, MAX_SIDECAR_BYTES, "CSV sidecar").decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise DataFormatError(f"cannot read the CSV's sidecar {side.name}: {exc}", path) from None
    if not isinstance(d, dict):
        raise DataFormatError(f"sidecar {side.name} is not a JSON object", path)
    return d


def write_csv(
    cloud: PointCloud,
    path: str | os.PathLike[str],
    *,
    frame: str | None = None,
    georef: GeoReference | None = None,
    kind: str | None = None,
) -> None:
    """Write a CSV whose first line is its header row, and its JSON sidecar, atomically (exact round trip).

    The sidecar (:func:`csv_sidecar`) records the frame, the kind and the columns; with ``georef``
    the coordinates are projected ``(E, N, h)`` and it also records ``crs``, ``crs_wkt`` and
    ``georef_origin_deg``.

    Parameters
    ----------
    cloud : PointCloud
    path : path-like
    frame : {"ned", "enu"}, optional
        Convert coordinates first (default: the cloud's frame).
    georef : GeoReference, optional
        Write projected coordinates.
    kind : {"points", "occupancy"}, optional
        Schema (module notes); default :func:`cloud_kind`.
    """
    knd = _resolve_kind(cloud, kind)
    c = _in_frame(cloud, frame) if georef is None else georeferenced_cloud(cloud, frame, georef)
    cols = _CSV_OCC_COLS if knd == "occupancy" else _CSV_COLS
    meta: dict[str, Any] = {"sonarmap": "point cloud", "kind": knd, "frame": c.frame, "columns": list(cols)}
    if georef is not None:
        for key, value in _crs_records(georef):
            meta[key] = [float(x) for x in value.split()] if key == "georef_origin_deg" else value
    buf = io.StringIO()
    buf.write(",".join(cols) + "\n")
    n = len(c)
    if n:
        xyz = [np.array([repr(v) for v in c.xyz_m[:, k].tolist()]) for k in range(3)]
        if knd == "occupancy":
            prob, lo = occupancy_columns(c)
            fields = [*xyz, np.char.mod("%.9g", prob), np.char.mod("%.9g", lo)]
        else:
            fields = [
                *xyz,
                c.time_ns.astype(str),
                c.beam.astype(str),
                np.char.mod("%.9g", c.range_m),
                np.char.mod("%.9g", c.intensity),
                np.char.mod("%.9g", c.confidence),
                np.char.mod("%.9g", c.elevation_rad),
                np.char.mod("%.9g", c.sigma_m),
            ]
        rows = fields[0]
        for col in fields[1:]:
            rows = np.char.add(np.char.add(rows, ","), col)
        buf.write("\n".join(rows.tolist()))
        buf.write("\n")
    atomic_write_text(path, buf.getvalue())
    atomic_write_text(csv_sidecar(path), json.dumps(meta, indent=1) + "\n")


def read_csv(path: str | os.PathLike[str]) -> PointCloud:
    """Read a CSV written by :func:`write_csv` (needs at least ``x, y, z`` columns).

    The frame comes from the sidecar, else from a ``# frame:`` comment (files of earlier
    versions), else NED.
    """
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataFormatError(f"cannot read CSV: {exc}", p) from None
    side = _read_sidecar(p)
    frame = str(side.get("frame", "ned"))
    body = []
    for ln in lines:
        if ln.startswith("#"):
            s = ln.lstrip("#").strip()
            if s.startswith("frame:") and "frame" not in side:
                frame = s.split(":", 1)[1].strip()
            continue
        if ln.strip():
            body.append(ln)
    if not body:
        raise DataFormatError("empty CSV (no header)", p)
    header = [h.strip() for h in body[0].split(",")]
    if not {"x", "y", "z"} <= set(header):
        raise DataFormatError(f"missing x, y, z columns (header: {body[0]})", p)
    rows = [ln.split(",") for ln in body[1:]]
    n = len(rows)
    col = {h: i for i, h in enumerate(header)}
    try:
        table = np.array(rows, dtype=object).reshape(n, len(header)) if n else np.zeros((0, len(header)), object)

        def get(name: str, dtype: type, default: float) -> np.ndarray:
            if name not in col:
                return np.full(n, default, dtype=dtype)
            return np.array(table[:, col[name]].tolist() if n else [], dtype=dtype)

        xyz = np.stack([get(k, np.float64, np.nan) for k in "xyz"], axis=1) if n else np.zeros((0, 3))
        if "p_occupied" in col:
            return _occupancy_cloud(xyz, get("p_occupied", np.float32, np.nan), frame)
        return PointCloud(
            xyz, np.array([int(v) for v in table[:, col["time_ns"]]] if n and "time_ns" in col else np.zeros(n), np.int64),
            get("beam", np.int32, -1), get("range_m", np.float32, np.nan), get("intensity", np.float32, 1.0),
            get("confidence", np.float32, 1.0), get("elevation_rad", np.float32, 0.0), frame=frame,
            sigma_m=get("sigma_m", np.float32, np.nan),
        )
    except (ValueError, TypeError) as exc:
        raise DataFormatError(f"non-numeric or ragged CSV rows ({exc})", p) from None


# ---------------------------------------------------------------------- dispatch
def write_point_cloud(
    cloud: PointCloud,
    path: str | os.PathLike[str],
    *,
    format: str | None = None,  # noqa: A002 - the CLI's --format
    frame: str | None = None,
    georef: GeoReference | None = None,
    kind: str | None = None,
) -> str:
    """Write ``cloud`` as PLY, LAS or CSV (from ``format`` or the suffix); returns the format.

    Parameters
    ----------
    cloud : PointCloud
        Points in the local world frame (``cloud.frame``).
    path : path-like
    format : {"ply", "las", "csv"}, optional
        Default: from the suffix.
    frame : {"ned", "enu"}, optional
        Local frame to write (default the cloud's); must be ``None`` or ``"enu"`` with ``georef``.
    georef : GeoReference, optional
        Write projected coordinates (easting, northing, height) with the CRS recorded in the file
        (see the module notes).
    kind : {"points", "occupancy"}, optional
        The file's schema: returns, or the occupied cells of an occupancy map (``p_occupied``,
        ``log_odds``); default :func:`cloud_kind` (recognises ``OccupancyMap.to_point_cloud``).

    Examples
    --------
    >>> g = GeoReference.from_origin(51.3685, 3.139)              # doctest: +SKIP
    >>> write_point_cloud(cloud, "map.las", georef=g)             # doctest: +SKIP
    'las'
    """
    fmt = _cloud_format(path, format)
    writer = {"ply": write_ply, "las": write_las, "csv": write_csv}[fmt]
    writer(cloud, path, frame=frame, georef=georef, kind=kind)
    return fmt


def read_point_cloud(path: str | os.PathLike[str], *, format: str | None = None) -> PointCloud:  # noqa: A002
    """Read a PLY, LAS or CSV point cloud (format from ``format`` or the suffix)."""
    fmt = _cloud_format(path, format)
    return {"ply": read_ply, "las": read_las, "csv": read_csv}[fmt](path)


def read_point_cloud_crs(path: str | os.PathLike[str], *, format: str | None = None) -> pyproj.CRS | None:  # noqa: A002
    """The CRS recorded in a point-cloud file (``None`` when it has none).

    LAS: the WKT or GeoTIFF-key VLRs (``laspy``'s ``parse_crs``); PLY: the ``crs_wkt`` (else
    ``crs``) comment; CSV: ``crs_wkt`` (else ``crs``) in the sidecar (:func:`csv_sidecar`), else
    the ``# crs_wkt:`` / ``# crs:`` comment of files of earlier versions.

    Raises
    ------
    DataFormatError
        If the file cannot be read or its CRS record cannot be parsed.
    """
    import pyproj

    p = Path(path)
    fmt = _cloud_format(p, format)
    if fmt == "las":
        import laspy

        try:
            with laspy.open(str(p)) as fh:
                return fh.header.parse_crs()
        except Exception as exc:  # noqa: BLE001 - laspy / pyproj raise several unrelated types
            raise DataFormatError(f"cannot read the LAS CRS: {' '.join(str(exc).split())[:200]}", p) from None
    records: dict[str, str] = {}
    if fmt == "csv":
        side = _read_sidecar(p)
        records = {k: str(side[k]) for k in ("crs", "crs_wkt") if side.get(k)}
    try:
        with open(p, "rb") as fh:
            for n_line, raw in enumerate(fh):
                line = raw.decode("utf-8", "replace").rstrip("\r\n")
                if fmt == "ply":
                    if line.startswith("end_header") or n_line > 100_000:  # no header that long
                        break
                    if not line.startswith("comment "):
                        continue
                    key, _, value = line.removeprefix("comment ").partition(" ")
                else:
                    if records or not line.startswith("#"):
                        break
                    key, _, value = line.lstrip("#").strip().partition(":")
                if key in ("crs", "crs_wkt"):
                    records[key] = value.strip()
    except OSError as exc:
        raise DataFormatError(f"cannot read: {exc.strerror or exc}", p) from None
    text = records.get("crs_wkt") or records.get("crs")
    if not text:
        return None
    try:
        return pyproj.CRS.from_user_input(text)
    except pyproj.exceptions.CRSError as exc:
        raise DataFormatError(f"unreadable CRS record ({' '.join(str(exc).split())[:160]})", p) from None
