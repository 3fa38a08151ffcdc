"""From pings to a map: process every ping, place it, register its returns or integrate them.

:func:`map_from_pings` is the workflow behind ``sonarmap map``: each ping goes through the
per-ping pipeline (:func:`sonarmap.pipeline.process_ping`); its pose comes from a trajectory, the
ping's own navigation (ARIS, DDF, Kongsberg headers: :mod:`sonarmap.mapping.navigation`) or a fixed
mount (``static``); its returns become world points (:func:`sonarmap.mapping.register.register_ranges`)
or update an occupancy map (:class:`sonarmap.mapping.occupancy.OccupancyMap`, with each ping's
pD/pFA as the sensor model unless ``fixed_model``).  The first ping is read before any processing,
so a missing pose is an error before any work.

Examples
--------
>>> from sonarmap.mapping.build import MapConfig, map_from_pings  # doctest: +SKIP
>>> result = map_from_pings(read_pings("survey.all"), MapConfig(grid_m=0.5))  # doctest: +SKIP
>>> result.occupancy.to_point_cloud()  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Iterable
from typing import Any, NamedTuple

import numpy as np

from sonarmap.errors import InputError

__all__ = ["MapConfig", "MapResult", "map_from_pings"]

#: Pings registered or integrated together (one trajectory interpolation per batch).
BATCH_PINGS = 128


@dataclasses.dataclass(frozen=True)
class MapConfig:
    """How :func:`map_from_pings` places and accumulates the returns.

    Attributes
    ----------
    trajectory : Trajectory, optional
        Sensor-platform poses (:func:`sonarmap.mapping.poses.read_trajectory_csv`); default: the
        pings' own poses, else their navigation.
    extrinsics : optional
        Sonar mounting on the platform (:func:`sonarmap.mapping.poses.load_extrinsics`).
    static : bool
        A fixed sonar: every ping at the origin (placed by ``extrinsics`` if given).
    outside : {"error", "skip"}
        Pings outside the trajectory's time span.
    n_elevation : int
        Points (or occupancy rays) per return across the vertical aperture.
    min_confidence : float
        Drop weaker returns from the point cloud (point clouds only).
    grid_m : float, optional
        Build an occupancy map at this resolution instead of a point cloud.
    dims : {2, 3}
        Occupancy map dimensions.
    clamp : dict, optional
        ``l_min`` / ``l_max`` log-odds clamping of the occupancy map.
    fixed_model : bool
        Fixed 0.8 / 0.3 hit / miss probabilities instead of each ping's pD / pFA.
    origin_lat_lon : (float, float), optional
        Geodetic origin of the local frame (WGS 84 degrees) for trajectory or static maps.
    crs : str, optional
        Projected CRS of the georeference (default with navigation: the data's UTM zone).
    footprint_edge : bool
        Place each return at the near edge of its beam's footprint where the pings' geometry
        gives the beamwidth (:class:`~sonarmap.mapping.register.RegistrationConfig`); False: on
        the beam's axis (point clouds only).
    """

    trajectory: Any = None
    extrinsics: Any = None
    static: bool = False
    outside: str = "error"
    n_elevation: int = 1
    min_confidence: float = 0.0
    grid_m: float | None = None
    dims: int = 3
    clamp: dict[str, float] | None = None
    fixed_model: bool = False
    origin_lat_lon: tuple[float, float] | None = None
    crs: str | None = None
    footprint_edge: bool = True

    def __post_init__(self) -> None:
        if self.outside not in ("error", "skip"):
            raise InputError(f"map config: outside: must be 'error' or 'skip' (got {self.outside!r})")
        if self.static and self.trajectory is not None:
            raise InputError("map config: a fixed sonar (static) needs no trajectory")
        if self.grid_m is not None and self.min_confidence > 0:
            # a dropped return would leave its beam empty, and the map would carve it free
            raise InputError("map config: min_confidence applies to point clouds; the occupancy map keeps every return")


@dataclasses.dataclass(frozen=True, eq=False)
class MapResult:
    """What :func:`map_from_pings` built.

    Attributes
    ----------
    cloud : PointCloud or None
        The registered points (point-cloud maps).
    occupancy : OccupancyMap or None
        The occupancy map (``grid_m`` given).
    georef : GeoReference or None
        The local frame's geodetic origin and CRS (navigation, or ``origin_lat_lon``).
    n_pings, n_returns, n_skipped : int
        Pings processed, returns registered or integrated, pings skipped outside the trajectory.
    last_time_ns : int
        The latest ping time (the stamp of a map written once).
    """

    cloud: Any
    occupancy: Any
    georef: Any
    n_pings: int
    n_returns: int
    n_skipped: int
    last_time_ns: int


def map_from_pings(pings: Iterable[Any], config: MapConfig = MapConfig(), pipeline: Any = None, *,
                   background: Any = None, on_start: Callable[[Any], None] | None = None,
                   on_ping: Callable[[Any, Any], None] | None = None) -> MapResult:
    """Process, place and register (or integrate) every ping of ``pings``.

    Parameters
    ----------
    pings : iterable of Ping
    config : MapConfig
    pipeline : PipelineConfig, optional
        The per-ping pipeline (default ``PipelineConfig()``).
    background : RecordingBackground, optional
        The recording's background level (``sonarmap calibrate``), passed to every
        :func:`~sonarmap.pipeline.process_ping`; without it each ping is normalised by its own.
    on_start : callable, optional
        Called with the georeference (or None) once the first ping has been read and placed, before
        any processing (a caller's own checks of its outputs go there).
    on_ping : callable, optional
        Called with ``(ping, products)`` after each ping (progress, logging).

    Returns
    -------
    MapResult

    Raises
    ------
    InputError
        No pose can be had for the first ping (no trajectory, no pose, no navigation, not static),
        before anything is processed; an empty input.
    """
    from sonarmap.mapping.occupancy import OccupancyConfig, OccupancyMap, SensorModel
    from sonarmap.mapping.register import PointCloud, RegistrationConfig
    from sonarmap.pipeline import PipelineConfig

    pcfg = pipeline if pipeline is not None else PipelineConfig()
    it = iter(pings)
    first = next(it, None)
    if first is None:
        raise InputError("pings: no pings to map")
    georef, use_nav = _map_frame(first, config)
    if on_start is not None:
        on_start(georef)
    if config.crs is not None and georef is None:
        raise InputError("crs: needs a geodetic origin: navigation in the pings, or an origin LAT,LON")

    occ = (OccupancyMap(OccupancyConfig(resolution_m=config.grid_m, dims=config.dims, n_elevation=config.n_elevation,
                                        **(config.clamp or {})))
           if config.grid_m is not None else None)
    acc = _Accumulator(config, occ, use_nav, SensorModel.fixed(0.8, 0.3) if config.fixed_model else None,
                       RegistrationConfig(n_elevation=config.n_elevation, min_confidence=config.min_confidence,
                                          footprint_edge=config.footprint_edge))
    place = _placement(config.static, use_nav, georef)
    from sonarmap.pipeline import process_ping

    last_time_ns = 0
    last_shape = None
    n_pings = 0
    for ping in itertools.chain([first], it):
        last_time_ns = max(last_time_ns, int(ping.time_ns))
        if last_shape is not None and ping.geometry.shape != last_shape:
            acc.flush()
        last_shape = ping.geometry.shape
        ping = place(ping)
        prod = process_ping(ping, pcfg, background=background)
        acc.add(ping, prod)
        n_pings += 1
        if on_ping is not None:
            on_ping(ping, prod)
    acc.flush()
    cloud = PointCloud.concat(acc.clouds) if occ is None else None
    return MapResult(cloud=cloud, occupancy=occ, georef=georef, n_pings=n_pings, n_returns=acc.n_returns,
                     n_skipped=acc.n_skipped, last_time_ns=last_time_ns)


class _MapFrame(NamedTuple):
    """Where the map's local frame is, and whether the pings are placed by their navigation."""

    georef: Any
    """The local frame's GeoReference, or None (not georeferenced)."""
    use_nav: bool
    """Each ping's pose from its own navigation (no trajectory, no pose, not static)."""


def _map_frame(first: Any, config: MapConfig) -> _MapFrame:
    """The georeference and the placement of a map whose first ping is ``first``; raises
    :class:`InputError` if that ping can have no pose at all."""
    from sonarmap.mapping.georef import GeoReference
    from sonarmap.mapping.navigation import missing_navigation, navigation_origin

    georef = None
    use_nav = False
    if config.trajectory is None and first.pose is None and not config.static:
        why = missing_navigation(first)
        if why is not None:
            raise InputError(
                f"no pose for ping {first.source}: no --poses trajectory, the ping carries no pose and {why}; "
                "give --poses TRAJECTORY.csv, or --static for a fixed sonar"
            )
        use_nav = True
        if config.origin_lat_lon is None:
            georef = navigation_origin(first, crs=config.crs)
    if config.origin_lat_lon is not None:
        georef = GeoReference.from_origin(config.origin_lat_lon[0], config.origin_lat_lon[1], 0.0, crs=config.crs)
    return _MapFrame(georef, use_nav)


def _placement(static: bool, use_nav: bool, georef: Any) -> Callable[[Any], Any]:
    """The function that gives a ping its pose: the fixed mount, its navigation, or its own."""
    from sonarmap.mapping.navigation import navigation_pose, static_pose

    if static:
        return lambda ping: ping.replace(pose=static_pose())
    if use_nav:
        return lambda ping: ping.replace(pose=navigation_pose(ping, georef))
    return lambda ping: ping


class _Accumulator:
    """Batches of (ping, products), registered into clouds or integrated into the occupancy map."""

    def __init__(self, config: MapConfig, occ: Any, use_nav: bool, fixed: Any, rcfg: Any) -> None:
        self.config = config
        self.occ = occ
        self.use_nav = use_nav
        self.fixed = fixed
        self.rcfg = rcfg
        self.batch: list[tuple[Any, Any]] = []
        self.clouds: list[Any] = []
        self.n_returns = 0
        self.n_skipped = 0

    def add(self, ping: Any, prod: Any) -> None:
        self.batch.append((ping, prod))
        if len(self.batch) >= BATCH_PINGS:
            self.flush()

    def flush(self) -> None:
        from sonarmap.mapping.navigation import ping_sensor_poses, placed_ranges
        from sonarmap.mapping.register import register_ranges

        if not self.batch:
            return
        times = np.array([p.time_ns for p, _ in self.batch], dtype=np.int64)
        traj = self.config.trajectory
        sp = traj.interpolate(times, outside=self.config.outside) if traj is not None else \
            ping_sensor_poses([p for p, _ in self.batch])
        sp = sp.with_extrinsics(self.config.extrinsics)
        self.n_skipped += sp.n_skipped
        # poses from the pings' own navigation come with their ranges' placement (Kongsberg EM:
        # the bistatic range correction of the head's sensor frame)
        ranges = [placed_ranges(p, prod.ranges) if self.use_nav else prod.ranges for p, prod in self.batch]
        if self.occ is None:
            cloud = register_ranges(ranges, sp, config=self.rcfg,
                                    azimuth_beamwidth_rad=[p.geometry.azimuth_beamwidth_rad for p, _ in self.batch])
            self.clouds.append(cloud)
            self.n_returns += len(cloud) // self.rcfg.n_elevation
        else:
            g = self.batch[0][0].geometry
            fixed = self.fixed
            pd = None if fixed else np.array([float(prod.pd_range) for _, prod in self.batch])
            pfa = None if fixed else np.array([float(prod.pfa) for _, prod in self.batch])
            self.occ.integrate_ranges(
                ranges, sp, min_range_m=g.min_range_m, max_range_m=g.max_range_m, pd=pd, pfa=pfa, model=fixed,
                range_resolution_m=None if fixed else g.range_resolution_m,
            )
            self.n_returns += int(sum(r.n_returns for r in ranges))
        self.batch.clear()
