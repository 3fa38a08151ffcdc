"""Point-cloud files: binary PLY (plyfile), LAS 1.4 (laspy) and CSV, each readable back losslessly.

* **PLY** (binary little-endian): vertex element with ``x, y, z`` (float32), ``time`` (float64,
  seconds after the ``comment time_offset_ns N`` stamp: exact to the nanosecond for surveys up to
  ~100 days), ``beam`` (int32), ``range`` / ``intensity`` / ``confidence`` /
  ``elevation`` / ``sigma`` (float32; ``sigma`` = one-sigma range uncertainty, NaN = unknown).
  Coordinates are stored relative to an ``offset_m`` (default zero) recorded in a
  ``comment offset_m X Y Z`` line so large world coordinates keep float32 precision;
  a ``comment frame ned|enu`` line records the frame.  Opens in CloudCompare, MeshLab, Open3D.
* **LAS 1.4** (point format 6): coordinates as scaled integers (``scale_m``, default 0.1 mm;
  offset = the cloud's minimum rounded down to a metre), ``gps_time`` = seconds since the epoch,
  ``intensity`` = intensity x 65535 (uint16, clipped to [0, 1] first), ``point_source_id`` = beam,
  and extra bytes ``range_m``, ``confidence``, ``elevation_rad``, ``intensity_f`` (float32),
  ``beam_index`` (int32), ``time_ns`` (int64) and ``sigma_m`` (float32, one-sigma range
  uncertainty, NaN = unknown).  Reading back gives the written coordinates to
  within ``scale_m / 2`` (exactly the quantised values).
* **CSV**: ``x,y,z,time_ns,beam,range_m,intensity,confidence,elevation_rad,sigma_m`` with a
  ``# frame:`` comment; float64 coordinates are written with ``repr`` (exact round trip).

Files without the ``sigma`` / ``sigma_m`` attribute (written before it existed, or by other
tools) read back with NaN uncertainties.

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
* **CSV**: the comment lines ``# crs: EPSG:xxxx``, ``# crs_wkt: <OGC WKT>`` and
  ``# georef_origin_deg: ...`` after ``# frame: enu``, before the header row (pandas:
  ``read_csv(path, comment="#")``).

:func:`read_point_cloud_crs` returns the CRS of any of them (``None`` when there is none).

LAS/PLY viewers expect z up: pass ``frame="enu"`` to write ROS/ENU coordinates (the default is the
library's NED frame, in which depth is positive ``z``).
"""

from __future__ import annotations

import dataclasses
import io
import os
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from sonarmap._atomic import atomic_path, atomic_write_text
from sonarmap.errors import DataFormatError, InputError
from sonarmap.mapping.register import PointCloud

if TYPE_CHECKING:  # pragma: no cover - typing only (pyproj is imported lazily)
    import pyproj

    from sonarmap.mapping.georef import GeoReference

__all__ = [
    "CLOUD_FORMATS",
    "write_point_cloud",
    "read_point_cloud",
    "write_ply",
    "read_ply",
    "write_las",
    "read_las",
    "write_csv",
    "read_csv",
    "format_from_suffix",
    "read_point_cloud_crs",
]

CloudFormat = Literal["ply", "las", "csv"]
CLOUD_FORMATS: tuple[str, ...] = ("ply", "las", "csv")
_SUFFIX = {".ply": "ply", ".las": "las", ".laz": "las", ".csv": "csv", ".txt": "csv"}


def format_from_suffix(path: str | os.PathLike[str]) -> str:
    """``"ply"``, ``"las"`` or ``"csv"`` from a file name; raises :class:`InputError` otherwise."""
    sfx = Path(path).suffix.lower()
    if sfx not in _SUFFIX:
        raise InputError(f"output: cannot infer the point-cloud format from suffix {sfx!r}; use .ply, .las or .csv")
    return _SUFFIX[sfx]


def _in_frame(cloud: PointCloud, frame: str | None) -> PointCloud:
    return cloud if frame is None else cloud.to_frame(frame)


def _georeferenced(cloud: PointCloud, frame: str | None, georef: GeoReference) -> PointCloud:
    """The cloud with ``xyz_m`` = projected ``(E, N, h)`` and ``frame="enu"`` (E, N, up axes)."""
    if frame is not None and str(frame).lower() != "enu":
        raise InputError(
            f"frame: a georeferenced cloud is written as easting, northing, height (z up); frame={frame!r} cannot apply"
        )
    return dataclasses.replace(cloud, xyz_m=georef.to_projected(cloud.xyz_m, cloud.frame), frame="enu")


def _crs_comments(georef: GeoReference) -> list[str]:
    """``crs``, ``crs_wkt`` and ``georef_origin_deg`` lines (without a comment prefix)."""
    from sonarmap.mapping.georef import file_wkt

    lines = [] if georef.epsg is None else [f"crs EPSG:{georef.epsg}"]
    lines.append("crs_wkt " + file_wkt(georef.crs))
    lines.append(f"georef_origin_deg {georef.lat0_deg!r} {georef.lon0_deg!r} {georef.height0_m!r}")
    return lines


# ---------------------------------------------------------------------- PLY
def write_ply(
    cloud: PointCloud,
    path: str | os.PathLike[str],
    *,
    frame: str | None = None,
    offset_m: tuple[float, float, float] | None = None,
    georef: GeoReference | None = None,
) -> None:
    """Write a binary little-endian PLY (float32 xyz, float64 when georeferenced, + attributes), atomically.

    Parameters
    ----------
    frame : {"ned", "enu"}, optional
        Convert coordinates first (default: the cloud's frame).  With ``georef`` only ``None`` or
        ``"enu"`` (the projected axes) are accepted.
    offset_m : 3 floats, optional
        Subtracted from the coordinates before the float32 cast (recorded in a comment).
    georef : GeoReference, optional
        Write projected ``(E, N, h)`` coordinates as float64, with the CRS in the comments.
    """
    from plyfile import PlyData, PlyElement

    c = _in_frame(cloud, frame) if georef is None else _georeferenced(cloud, frame, georef)
    off = np.zeros(3) if offset_m is None else np.asarray(offset_m, dtype=np.float64)
    cdt = "<f4" if georef is None else "<f8"
    xyz = (c.xyz_m - off).astype(cdt)
    dt = [
        ("x", cdt), ("y", cdt), ("z", cdt), ("time", "<f8"), ("beam", "<i4"),
        ("range", "<f4"), ("intensity", "<f4"), ("confidence", "<f4"), ("elevation", "<f4"),
        ("sigma", "<f4"),
    ]
    v = np.empty(len(c), dtype=dt)
    v["x"], v["y"], v["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    t_off = int(c.time_ns.min()) if len(c) else 0
    v["time"] = (c.time_ns - t_off).astype(np.float64) * 1e-9
    v["beam"] = c.beam
    v["range"] = c.range_m
    v["intensity"] = c.intensity
    v["confidence"] = c.confidence
    v["elevation"] = c.elevation_rad
    v["sigma"] = c.sigma_m
    comments = [
        "sonarmap point cloud",
        f"frame {c.frame}",
        "offset_m " + " ".join(repr(float(o)) for o in off),
        f"time_offset_ns {t_off}",
    ]
    if georef is not None:
        comments += _crs_comments(georef)
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
    frame, off, t_off = "ned", np.zeros(3), 0
    for com in ply.comments:
        parts = com.split()
        if parts[:1] == ["frame"] and len(parts) > 1:
            frame = parts[1]
        elif parts[:1] == ["offset_m"] and len(parts) == 4:
            off = np.array([float(s) for s in parts[1:]])
        elif parts[:1] == ["time_offset_ns"] and len(parts) == 2:
            t_off = int(parts[1])
    names = v.dtype.names or ()
    n = v.shape[0]
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64) + off

    def get(name: str, default: float) -> np.ndarray:
        return np.asarray(v[name]) if name in names else np.full(n, default)

    time_ns = np.rint(get("time", 0.0).astype(np.float64) * 1e9).astype(np.int64) + t_off
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
) -> None:
    """Write a LAS 1.4 file (point format 6 + extra bytes), atomically.

    Parameters
    ----------
    frame : {"ned", "enu"}, optional
        Convert coordinates first (default: the cloud's frame).  With ``georef`` only ``None`` or
        ``"enu"`` are accepted.
    scale_m : float, optional
        Coordinate quantum; default 0.1 mm (local) or 1 mm (georeferenced).
    georef : GeoReference, optional
        Write projected ``(E, N, h)`` coordinates with the CRS as a WKT VLR.

    Raises
    ------
    InputError
        If the cloud's extent does not fit the 32-bit scaled integers at ``scale_m``.
    """
    import laspy

    c = _in_frame(cloud, frame) if georef is None else _georeferenced(cloud, frame, georef)
    if scale_m is None:
        scale_m = 1e-4 if georef is None else 1e-3
    if not scale_m > 0:
        raise InputError(f"scale_m: must be positive, got {scale_m}")
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
    header.generating_software = "sonarmap"
    header.add_extra_dims(
        [
            laspy.ExtraBytesParams(name="range_m", type=np.float32, description="measured range (m)"),
            laspy.ExtraBytesParams(name="confidence", type=np.float32, description="return confidence"),
            laspy.ExtraBytesParams(name="elevation_rad", type=np.float32, description="assumed elevation"),
            laspy.ExtraBytesParams(name="intensity_f", type=np.float32, description="intensity (float)"),
            laspy.ExtraBytesParams(name="beam_index", type=np.int32, description="beam index"),
            laspy.ExtraBytesParams(name="time_ns", type=np.int64, description="ping time (ns)"),
            laspy.ExtraBytesParams(name="sigma_m", type=np.float32, description="range 1-sigma (m)"),
        ]
    )
    if georef is not None:
        from laspy.vlrs.known import WktCoordinateSystemVlr

        from sonarmap.mapping.georef import file_wkt

        header.vlrs.append(WktCoordinateSystemVlr(file_wkt(georef.crs)))
        header.global_encoding.wkt = True
    las = laspy.LasData(header)
    las.x = c.xyz_m[:, 0]
    las.y = c.xyz_m[:, 1]
    las.z = c.xyz_m[:, 2]
    las.gps_time = c.time_ns.astype(np.float64) * 1e-9
    las.intensity = np.rint(np.clip(np.nan_to_num(c.intensity), 0, 1) * 65535).astype(np.uint16)
    las.point_source_id = np.clip(c.beam, 0, 65535).astype(np.uint16)
    las.range_m = c.range_m
    las.confidence = c.confidence
    las.elevation_rad = c.elevation_rad
    las.intensity_f = c.intensity
    las.beam_index = c.beam
    las.time_ns = c.time_ns
    las.sigma_m = c.sigma_m
    with atomic_path(path) as tmp:
        las.write(str(tmp))


def read_las(path: str | os.PathLike[str]) -> PointCloud:
    """Read a LAS/LAZ file (extra dimensions written by :func:`write_las` are used when present)."""
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

    def get(name: str, default: float) -> np.ndarray:
        return np.asarray(las[name]) if name in dims else np.full(n, default)

    if "time_ns" in dims:
        t = np.asarray(las["time_ns"], dtype=np.int64)
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


def write_csv(
    cloud: PointCloud, path: str | os.PathLike[str], *, frame: str | None = None, georef: GeoReference | None = None
) -> None:
    """Write a CSV with a header row and a ``# frame:`` comment, atomically (exact round trip).

    With ``georef`` the coordinates are projected ``(E, N, h)`` and ``# crs:``, ``# crs_wkt:`` and
    ``# georef_origin_deg:`` comments follow the frame comment.
    """
    c = _in_frame(cloud, frame) if georef is None else _georeferenced(cloud, frame, georef)
    buf = io.StringIO()
    buf.write(f"# sonarmap point cloud\n# frame: {c.frame}\n")
    if georef is not None:
        for line in _crs_comments(georef):
            key, _, value = line.partition(" ")
            buf.write(f"# {key}: {value}\n")
    buf.write(",".join(_CSV_COLS) + "\n")
    n = len(c)
    if n:
        cols = [
            *(np.array([repr(v) for v in c.xyz_m[:, k].tolist()]) for k in range(3)),
            c.time_ns.astype(str),
            c.beam.astype(str),
            np.char.mod("%.9g", c.range_m),
            np.char.mod("%.9g", c.intensity),
            np.char.mod("%.9g", c.confidence),
            np.char.mod("%.9g", c.elevation_rad),
            np.char.mod("%.9g", c.sigma_m),
        ]
        rows = cols[0]
        for col in cols[1:]:
            rows = np.char.add(np.char.add(rows, ","), col)
        buf.write("\n".join(rows.tolist()))
        buf.write("\n")
    atomic_write_text(path, buf.getvalue())


def read_csv(path: str | os.PathLike[str]) -> PointCloud:
    """Read a CSV written by :func:`write_csv` (needs at least ``x, y, z`` columns)."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataFormatError(f"cannot read CSV: {exc}", p) from None
    frame = "ned"
    body = []
    for ln in lines:
        if ln.startswith("#"):
            s = ln.lstrip("#").strip()
            if s.startswith("frame:"):
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

    Examples
    --------
    >>> g = GeoReference.from_origin(51.3685, 3.139)              # doctest: +SKIP
    >>> write_point_cloud(cloud, "map.las", georef=g)             # doctest: +SKIP
    'las'
    """
    fmt = (format or format_from_suffix(path)).lower()
    if fmt not in CLOUD_FORMATS:
        raise InputError(f"format: must be one of {CLOUD_FORMATS}, got {format!r}")
    writer = {"ply": write_ply, "las": write_las, "csv": write_csv}[fmt]
    if georef is None:
        writer(cloud, path, frame=frame)
    else:
        writer(cloud, path, frame=frame, georef=georef)
    return fmt


def read_point_cloud(path: str | os.PathLike[str], *, format: str | None = None) -> PointCloud:  # noqa: A002
    """Read a PLY, LAS or CSV point cloud (format from ``format`` or the suffix)."""
    fmt = (format or format_from_suffix(path)).lower()
    if fmt not in CLOUD_FORMATS:
        raise InputError(f"format: must be one of {CLOUD_FORMATS}, got {format!r}")
    return {"ply": read_ply, "las": read_las, "csv": read_csv}[fmt](path)


def read_point_cloud_crs(path: str | os.PathLike[str], *, format: str | None = None) -> pyproj.CRS | None:  # noqa: A002
    """The CRS recorded in a point-cloud file (``None`` when it has none).

    LAS: the WKT or GeoTIFF-key VLRs (``laspy``'s ``parse_crs``); PLY: the ``crs_wkt`` (else
    ``crs``) comment; CSV: the ``# crs_wkt:`` (else ``# crs:``) comment.

    Raises
    ------
    DataFormatError
        If the file cannot be read or its CRS record cannot be parsed.
    """
    import pyproj

    p = Path(path)
    fmt = (format or format_from_suffix(p)).lower()
    if fmt not in CLOUD_FORMATS:
        raise InputError(f"format: must be one of {CLOUD_FORMATS}, got {format!r}")
    if fmt == "las":
        import laspy

        try:
            with laspy.open(str(p)) as fh:
                return fh.header.parse_crs()
        except Exception as exc:  # noqa: BLE001 - laspy / pyproj raise several unrelated types
            raise DataFormatError(f"cannot read the LAS CRS: {' '.join(str(exc).split())[:200]}", p) from None
    records: dict[str, str] = {}
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
                    if not line.startswith("#"):
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
