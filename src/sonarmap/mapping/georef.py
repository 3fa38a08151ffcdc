"""Georeferencing: sonarmap's local world frame <-> geodetic coordinates <-> a projected CRS.

The local world frame (:mod:`sonarmap.mapping.frames`) is a *local tangent plane* at a geodetic
origin ``(lat0, lon0, height0)`` on the WGS 84 ellipsoid: ``"ned"`` = x north, y east, z down,
``"enu"`` = x east, y north, z up, both in metres, with the axes along the origin's true north,
east and ellipsoid normal.  :class:`GeoReference` ties that frame to a projected coordinate
reference system (by default the UTM zone of the origin) and converts exactly, through pyproj:

    local (ned/enu) -> ENU at the origin -> ECEF (WGS 84, EPSG:4978) -> projected (E, N, h)

The first two steps are an exact rotation and offset (the topocentric conversion); the last is
pyproj's transformation from geocentric WGS 84 to the CRS, with ``h`` the ellipsoidal height
passed through.  Projected coordinates therefore include everything a flat offset would miss:
the grid convergence (the angle between grid north and true north, ~0.1 deg at 3.1 deg E in UTM
zone 31), the projection's scale factor (0.9996 on a UTM central meridian) and the Earth's
curvature (the tangent plane rises above the ellipsoid by ``d**2 / 2R``, 8 cm at 1 km).

Heights: ``height0_m`` is the origin's height in the same sense as the output ``h`` - the
ellipsoidal height above WGS 84 when it is one.  When it is given relative to another level (the
sea surface at 0 m, say), ``h`` is relative to that level too, to within the variation of the
geoid over the survey (negligible over a few km).  Latitudes and longitudes in and out are WGS 84
degrees.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.mapping.frames import as_points, enu_to_ned, world_frame

if TYPE_CHECKING:  # pragma: no cover - typing only (pyproj is imported lazily)
    import pyproj

__all__ = ["GeoReference", "utm_epsg", "as_crs", "file_wkt"]

_ECEF_EPSG = 4978  # WGS 84 geocentric
_GEODETIC_EPSG = 4979  # WGS 84 geographic 3-D (lat, lon, ellipsoidal height)


def utm_epsg(lat_deg: float, lon_deg: float) -> int:
    """EPSG code of the WGS 84 UTM zone (or UPS polar zone) that contains a point.

    Zones are 6 degrees wide from 180 W (zone 1), with the standard exceptions: zone 32 is widened
    to 3-12 E between 56 and 64 N (south-west Norway), and between 72 and 84 N zones 31-37 are
    replaced by 31X (0-9 E), 33X (9-21 E), 35X (21-33 E) and 37X (33-42 E) (Svalbard).  North of
    84 N and south of 80 S the Universal Polar Stereographic zones are used (EPSG:32661 / 32761).

    Parameters
    ----------
    lat_deg, lon_deg : float
        WGS 84 latitude in [-90, 90] and longitude in [-180, 180] (degrees).

    Returns
    -------
    int
        ``32600 + zone`` (north), ``32700 + zone`` (south), or 32661 / 32761 (UPS).

    Examples
    --------
    >>> utm_epsg(51.3685, 3.139)
    32631
    >>> utm_epsg(-33.86, 151.21)
    32756
    """
    lat, lon = _check_lat_lon(lat_deg, lon_deg)
    if lat > 84.0:
        return 32661
    if lat < -80.0:
        return 32761
    lon = (lon + 180.0) % 360.0 - 180.0  # 180 E is 180 W
    zone = int(math.floor((lon + 180.0) / 6.0)) + 1
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        zone = 32
    elif 72.0 <= lat <= 84.0 and 0.0 <= lon < 42.0:
        zone = 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37
    zone = min(max(zone, 1), 60)
    return (32600 if lat >= 0.0 else 32700) + zone


def _check_lat_lon(lat_deg: Any, lon_deg: Any) -> tuple[float, float]:
    try:
        lat, lon = float(lat_deg), float(lon_deg)
    except (TypeError, ValueError):
        raise InputError(f"lat/lon: need two numbers, got {lat_deg!r}, {lon_deg!r}") from None
    if not (math.isfinite(lat) and -90.0 <= lat <= 90.0):
        raise InputError(f"lat_deg: must be finite and in [-90, 90], got {lat_deg}")
    if not (math.isfinite(lon) and -180.0 <= lon <= 180.0):
        raise InputError(f"lon_deg: must be finite and in [-180, 180], got {lon_deg}")
    return lat, lon


def as_crs(crs: Any) -> pyproj.CRS:
    """A projected, metre-based :class:`pyproj.CRS` from ``"EPSG:xxxx"``, an int, a WKT/PROJ string or a CRS.

    Raises
    ------
    InputError
        If pyproj cannot parse it, or it is not a projected CRS in metres.
    """
    import pyproj

    if isinstance(crs, bool):
        raise InputError(f"crs: expected an EPSG code, 'EPSG:xxxx', WKT or pyproj.CRS, got {crs!r}")
    try:
        c = pyproj.CRS.from_user_input(crs)
    except (pyproj.exceptions.CRSError, TypeError, ValueError) as exc:
        msg = " ".join(str(exc).split())[:160]
        raise InputError(f"crs: cannot interpret {str(crs)[:60]!r} as a coordinate reference system ({msg})") from None
    name = _crs_label(c)
    if not c.is_projected:
        raise InputError(f"crs: {name} is not a projected CRS (need easting/northing in metres, e.g. a UTM zone)")
    axes = c.axis_info[:2]
    if len(axes) < 2 or any(abs(a.unit_conversion_factor - 1.0) > 1e-12 for a in axes):
        unit = axes[0].unit_name if axes else "unknown"
        raise InputError(f"crs: {name} has {unit} axes; sonarmap needs a projected CRS in metres")
    return c


def file_wkt(crs: pyproj.CRS) -> str:
    """The CRS as one line of ASCII OGC WKT, for file headers (LAS VLR, PLY / CSV comments).

    WKT1 (GDAL flavour, the "OGC WKT" of the LAS 1.4 specification, read by laspy, PDAL, GDAL and
    LAStools) when it can express the CRS; otherwise WKT2:2019 with any non-ASCII character (they
    occur only in descriptive texts such as the area of use) replaced by ``?``.
    """
    try:
        text = crs.to_wkt("WKT1_GDAL")
    except Exception:  # noqa: BLE001 - pyproj raises CRSError or returns None when WKT1 cannot say it
        text = None
    if not text:
        text = crs.to_wkt("WKT2_2019")
    return " ".join(text.split()).encode("ascii", "replace").decode("ascii")


def _crs_label(c: pyproj.CRS) -> str:
    epsg = c.to_epsg()
    return f"EPSG:{epsg}" if epsg is not None else repr(c.name)


def _finite(a: NDArray[np.float64], name: str) -> None:
    if not np.isfinite(a).all():
        raise InputError(f"{name}: contains NaN or infinite values")


@dataclasses.dataclass(frozen=True)
class GeoReference:
    """The link between the local world frame and a projected CRS.

    Build it with :meth:`from_origin`; the fields are plain values so the object is hashable,
    comparable and cheap to pickle (the pyproj transformers are made on first use).

    Parameters
    ----------
    lat0_deg, lon0_deg : float
        WGS 84 latitude / longitude of the local frame's origin (degrees).
    height0_m : float
        Height of the origin (ellipsoidal, or relative to the level the user works in; see the
        module notes).
    crs_wkt : str
        The projected CRS as WKT2:2019 (pyproj's ``CRS.to_wkt()``).
    epsg : int or None
        Its EPSG code when it has one.

    Examples
    --------
    >>> g = GeoReference.from_origin(51.3685, 3.139)
    >>> g.epsg
    32631
    >>> e, n, h = g.to_projected([[100.0, 0.0, 2.0]], "ned").T  # 100 m north, 2 m down
    """

    lat0_deg: float
    lon0_deg: float
    height0_m: float
    crs_wkt: str
    epsg: int | None = None

    def __post_init__(self) -> None:
        lat, lon = _check_lat_lon(self.lat0_deg, self.lon0_deg)
        h = float(self.height0_m)
        if not math.isfinite(h):
            raise InputError(f"height_m: must be finite, got {self.height0_m}")
        object.__setattr__(self, "lat0_deg", lat)
        object.__setattr__(self, "lon0_deg", lon)
        object.__setattr__(self, "height0_m", h)
        if not isinstance(self.crs_wkt, str) or not self.crs_wkt.strip():
            raise InputError("crs_wkt: must be a non-empty WKT string")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_origin(
        cls, lat_deg: float, lon_deg: float, height_m: float = 0.0, crs: Any = None
    ) -> GeoReference:
        """A georeference whose local origin is the geodetic point ``(lat_deg, lon_deg, height_m)``.

        Parameters
        ----------
        lat_deg, lon_deg : float
            WGS 84 latitude in [-90, 90] and longitude in [-180, 180] of the local origin.
        height_m : float
            Height of the origin (see the module notes).
        crs : int, str or pyproj.CRS, optional
            The projected CRS (``32631``, ``"EPSG:32631"``, WKT, a ``pyproj.CRS``); default the
            WGS 84 UTM zone of the origin (:func:`utm_epsg`).

        Raises
        ------
        InputError
            On an out-of-range origin, a CRS that is not projected in metres, or an origin the
            CRS cannot project.
        """
        lat, lon = _check_lat_lon(lat_deg, lon_deg)
        c = as_crs(utm_epsg(lat, lon) if crs is None else crs)
        g = cls(lat, lon, height_m, c.to_wkt(), c.to_epsg())
        e, n, _ = g.to_projected(np.zeros((1, 3)), "enu")[0]
        if not (math.isfinite(e) and math.isfinite(n)):
            raise InputError(f"crs: {_crs_label(c)} cannot project the origin ({lat}, {lon})")
        return g

    def __getstate__(self) -> dict[str, Any]:
        # only the fields: the cached pyproj objects are rebuilt on first use after unpickling
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def __setstate__(self, state: dict[str, Any]) -> None:
        for k, v in state.items():
            object.__setattr__(self, k, v)

    # ------------------------------------------------------------------ cached pyproj objects
    @functools.cached_property
    def crs(self) -> pyproj.CRS:
        """The projected CRS as a :class:`pyproj.CRS`."""
        import pyproj

        return pyproj.CRS.from_epsg(self.epsg) if self.epsg is not None else pyproj.CRS.from_wkt(self.crs_wkt)

    @property
    def crs_name(self) -> str:
        """``"EPSG:xxxx"`` when the CRS has an EPSG code, else its name."""
        return f"EPSG:{self.epsg}" if self.epsg is not None else str(self.crs.name)

    @functools.cached_property
    def _ecef_to_crs(self) -> Any:
        import pyproj

        return pyproj.Transformer.from_crs(_ECEF_EPSG, self.crs, always_xy=True)

    @functools.cached_property
    def _geodetic_to_ecef(self) -> Any:
        import pyproj

        return pyproj.Transformer.from_crs(_GEODETIC_EPSG, _ECEF_EPSG, always_xy=True)

    @functools.cached_property
    def _enu_basis(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(R, X0)``: ECEF = X0 + R @ enu, with R's columns the east, north, up unit vectors."""
        phi, lam = math.radians(self.lat0_deg), math.radians(self.lon0_deg)
        sp, cp, sl, cl = math.sin(phi), math.cos(phi), math.sin(lam), math.cos(lam)
        R = np.array([[-sl, -sp * cl, cp * cl], [cl, -sp * sl, cp * sl], [0.0, cp, sp]])
        x0 = np.array(self._geodetic_to_ecef.transform(self.lon0_deg, self.lat0_deg, self.height0_m), dtype=np.float64)
        R.setflags(write=False)
        x0.setflags(write=False)
        return R, x0

    # ------------------------------------------------------------------ conversions
    def _local_to_enu(self, points: ArrayLike, frame: str, name: str) -> NDArray[np.float64]:
        fr = world_frame(frame)
        p = as_points(points, name)
        _finite(p, name)
        return enu_to_ned(p) if fr == "ned" else p  # the permutation is its own inverse

    def _enu_to_local(self, enu: NDArray[np.float64], frame: str) -> NDArray[np.float64]:
        return enu_to_ned(enu) if world_frame(frame) == "ned" else enu

    def local_to_ecef(self, points_local: ArrayLike, frame: str = "ned") -> NDArray[np.float64]:
        """Geocentric WGS 84 coordinates (EPSG:4978) of local points, shape ``(..., 3)``."""
        R, x0 = self._enu_basis
        return self._local_to_enu(points_local, frame, "points_local") @ R.T + x0

    def ecef_to_local(self, ecef: ArrayLike, frame: str = "ned") -> NDArray[np.float64]:
        """Local coordinates of geocentric WGS 84 points (inverse of :meth:`local_to_ecef`)."""
        R, x0 = self._enu_basis
        x = as_points(ecef, "ecef")
        _finite(x, "ecef")
        return self._enu_to_local((x - x0) @ R, frame)

    def to_projected(self, points_local: ArrayLike, frame: str = "ned") -> NDArray[np.float64]:
        """Projected coordinates ``(E, N, h)`` of local points.

        Parameters
        ----------
        points_local : array_like, shape (..., 3)
            Local world coordinates in metres.
        frame : {"ned", "enu"}
            The local frame of ``points_local``.

        Returns
        -------
        ndarray, shape (..., 3), float64
            Easting and northing in the CRS (always in that order, whatever the CRS's axis
            order), and the height ``h`` (positive up; see the module notes).

        Raises
        ------
        InputError
            On a bad shape, NaN/inf, or points the CRS cannot project.

        Examples
        --------
        >>> g = GeoReference.from_origin(51.3685, 3.139)
        >>> g.to_projected([0.0, 0.0, 0.0])[:2].round(3).tolist()
        [509676.11, 5690813.948]
        """
        x = self.local_to_ecef(points_local, frame)
        flat = x.reshape(-1, 3)
        e, n, h = self._ecef_to_crs.transform(flat[:, 0], flat[:, 1], flat[:, 2])
        out = np.stack([np.asarray(e, np.float64), np.asarray(n, np.float64), np.asarray(h, np.float64)], axis=-1)
        if not np.isfinite(out).all():
            raise InputError(f"points_local: some points cannot be projected into {self.crs_name}")
        return out.reshape(x.shape)

    def from_projected(self, points_projected: ArrayLike, frame: str = "ned") -> NDArray[np.float64]:
        """Local coordinates of projected ``(E, N, h)`` points (inverse of :meth:`to_projected`)."""
        p = as_points(points_projected, "points_projected")
        _finite(p, "points_projected")
        flat = p.reshape(-1, 3)
        x, y, z = self._ecef_to_crs.transform(flat[:, 0], flat[:, 1], flat[:, 2], direction="INVERSE")
        ecef = np.stack([np.asarray(x, np.float64), np.asarray(y, np.float64), np.asarray(z, np.float64)], axis=-1)
        if not np.isfinite(ecef).all():
            raise InputError(f"points_projected: some points are outside the domain of {self.crs_name}")
        return self.ecef_to_local(ecef, frame).reshape(p.shape)

    def geodetic_to_local(
        self, lat_deg: ArrayLike, lon_deg: ArrayLike, height_m: ArrayLike = 0.0, frame: str = "ned"
    ) -> NDArray[np.float64]:
        """Local positions of geodetic points (e.g. each ping's recorded latitude, longitude, depth).

        Parameters
        ----------
        lat_deg, lon_deg : array_like, shape (n,) or broadcastable
            WGS 84 latitude in [-90, 90] and longitude (degrees).
        height_m : array_like
            Height in the sense of ``height0_m`` (for a vehicle: ``-depth`` when the origin is at
            the surface, ``height0_m = 0``).
        frame : {"ned", "enu"}

        Returns
        -------
        ndarray, shape (n, 3), float64
            The vehicle positions in the local frame (NED: north, east, down).

        Examples
        --------
        >>> g = GeoReference.from_origin(51.3685, 3.139)
        >>> g.geodetic_to_local(51.3685, 3.139, -5.0).round(9).tolist()  # 5 m deep at the origin
        [[0.0, 0.0, 5.0]]
        """
        lat, lon, h = (np.asarray(v, dtype=np.float64) for v in (lat_deg, lon_deg, height_m))
        try:
            lat, lon, h = np.broadcast_arrays(lat, lon, h)
        except ValueError:
            raise InputError(
                f"lat_deg/lon_deg/height_m: shapes {lat.shape}, {lon.shape}, {h.shape} do not broadcast"
            ) from None
        for a, name in ((lat, "lat_deg"), (lon, "lon_deg"), (h, "height_m")):
            _finite(a, name)
        if (np.abs(lat) > 90.0).any():
            raise InputError(f"lat_deg: must be in [-90, 90], got values up to {float(np.abs(lat).max())}")
        x, y, z = self._geodetic_to_ecef.transform(lon.ravel(), lat.ravel(), h.ravel())
        ecef = np.stack([np.asarray(x, np.float64), np.asarray(y, np.float64), np.asarray(z, np.float64)], axis=-1)
        return self.ecef_to_local(ecef, frame)

    def local_to_geodetic(
        self, points_local: ArrayLike, frame: str = "ned"
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """WGS 84 ``(lat_deg, lon_deg, height_m)`` of local points (each of shape ``points.shape[:-1]``)."""
        x = self.local_to_ecef(points_local, frame)
        flat = x.reshape(-1, 3)
        lon, lat, h = self._geodetic_to_ecef.transform(flat[:, 0], flat[:, 1], flat[:, 2], direction="INVERSE")
        shape = x.shape[:-1]
        return (np.asarray(lat, np.float64).reshape(shape), np.asarray(lon, np.float64).reshape(shape),
                np.asarray(h, np.float64).reshape(shape))

    # ------------------------------------------------------------------ diagnostics
    @property
    def grid_convergence_rad(self) -> float:
        """Angle from true north to grid north at the origin (radians, positive east of the CM).

        A local north axis points ``grid_convergence_rad`` to the *left* of the projected grid's
        north (grid azimuth of true north = ``-convergence``), which is how much a local grid is
        rotated against the projected one.
        """
        e, n, _ = self.to_projected(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), "ned").T
        return float(math.atan2(-(e[1] - e[0]), n[1] - n[0]))

    @property
    def scale_factor(self) -> float:
        """Projected distance per local metre at the origin (0.9996 on a UTM central meridian)."""
        pts = self.to_projected(np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), "ned")
        return float(np.hypot(*(pts[1, :2] - pts[0, :2])))

    def summary(self) -> str:
        """One line: origin, CRS, convergence and scale factor."""
        return (f"origin {self.lat0_deg:.7f}, {self.lon0_deg:.7f}, {self.height0_m:g} m -> {self.crs_name} "
                f"(convergence {math.degrees(self.grid_convergence_rad):.4f} deg, scale {self.scale_factor:.6f})")
