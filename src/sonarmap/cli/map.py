"""``sonarmap map``: pings + trajectory -> registered point cloud or occupancy map."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from sonarmap._text import counted
from sonarmap.cli._common import (
    CALIBRATION_OPTION,
    GEOMETRY_OPTION,
    PING_RATE_OPTION,
    QUIET_OPTION,
    START_TIME_OPTION,
    STDOUT,
    VERBOSE_OPTION,
    apply_calibration,
    check_choice,
    check_clock_used,
    clock_options,
    count_pings,
    first_ping,
    input_name,
    err_console,
    example,
    load_geometry_option,
    output_name,
    ping_progress,
)

if TYPE_CHECKING:
    from sonarmap.mapping import MapResult, OccupancyMap, PointCloud

__all__ = ["register", "map_command"]

def _cloud_to_stdout(cloud: Any, fmt: str, **kwargs: Any) -> None:
    """Write ``cloud`` in ``fmt`` to standard output (through a temporary file: the writers take paths).

    Parameters
    ----------
    cloud : PointCloud
    fmt : str
        ``ply``, ``las`` or ``csv``.
    **kwargs
        Passed to :func:`sonarmap.mapping.pointcloud.write_point_cloud`.
    """
    import shutil
    import sys
    import tempfile

    from sonarmap.mapping.pointcloud import write_point_cloud

    with tempfile.TemporaryDirectory(prefix="sonarmap-map-") as d:
        tmp = Path(d) / f"cloud.{fmt}"
        write_point_cloud(cloud, tmp, format=fmt, **kwargs)
        sys.stdout.flush()
        out = getattr(sys.stdout, "buffer", None)
        with tmp.open("rb") as fh:
            if out is not None:
                shutil.copyfileobj(fh, out)
                out.flush()
            else:  # a text-only stream (tests): the formats that are text
                sys.stdout.write(fh.read().decode("utf-8", errors="replace"))


def _clamp_bounds(text: str) -> dict[str, float]:
    """``"PMIN,PMAX"`` probabilities -> the ``l_min``/``l_max`` of :class:`OccupancyConfig`, or a
    ``--clamp`` usage error."""
    from sonarmap.mapping.occupancy import logit

    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise typer.BadParameter(f"expected two probabilities PMIN,PMAX, got {text!r}", param_hint="--clamp") from None
    if not 0.0 < lo < 0.5 < hi < 1.0:
        raise typer.BadParameter(f"need 0 < PMIN < 0.5 < PMAX < 1, got {text!r}", param_hint="--clamp")
    return {"l_min": float(logit(lo)), "l_max": float(logit(hi))}


def _lat_lon(text: str) -> tuple[float, float]:
    try:
        lat, lon = (float(v) for v in text.split(","))
    except ValueError:
        raise typer.BadParameter(f"expected LAT,LON in degrees, got {text!r}", param_hint="--origin") from None
    if not (abs(lat) <= 90.0 and abs(lon) <= 180.0):
        raise typer.BadParameter(f"latitude within +-90 and longitude within +-180, got {text!r}",
                                 param_hint="--origin")
    return lat, lon


_PINGS_ARGUMENT: Any = typer.Argument(..., help="Ping files, directories or globs (any supported format).")
_POSES_OPTION: Any = typer.Option(
    None, "--poses", "-p",
    help="Trajectory CSV: time_ns|time_s,x,y,z,qx,qy,qz,qw (see docs/mapping.md); default: the pings' own poses.",
)
_EXTRINSICS_OPTION: Any = typer.Option(
    None, "--extrinsics", "-e", help="Sonar mounting JSON (translation_m + rotation_xyzw|rotation_rpy_deg)."
)
_OUTPUT_OPTION: Any = typer.Option(
    ..., "--output", "-o", help="Output point cloud (.ply, .las or .csv; .bag: ROS 1 PointCloud2 per ping, or of the occupied cells with --grid); "
    "- writes it to stdout (give --format)."
)
_GRID_OPTION: Any = typer.Option(
    None, "--grid", min=1e-4, help="Build an occupancy map at this resolution (m) and write its occupied cells."
)
_FORMAT_OPTION: Any = typer.Option(
    None, "--format", "-f",
    help="ply | las | csv, or bag1 | bag2 (ROS 1 / ROS 2 bag of sensor_msgs/PointCloud2, one per ping; with --grid one of the occupied cells) "
    "(default: from the output suffix).",
)
_CONFIG_OPTION: Any = typer.Option(None, "--config", "-c", help="Pipeline configuration (TOML).")
_DIMS_OPTION: Any = typer.Option(3, "--dims", min=2, max=3, help="Occupancy map: 3 = voxels, 2 = horizontal grid.")
_GRID_ARRAY_OPTION: Any = typer.Option(
    None, "--grid-array", help="Also save the occupancy grid as a dense array (.npz: logodds, observed, origin_m)."
)
_SPREAD_OPTION: Any = typer.Option(
    1, "--spread", min=1,
    help="Points per return across the vertical aperture (with --grid: rays per beam in the occupancy map).",
)
_MIN_CONFIDENCE_OPTION: Any = typer.Option(
    0.0, "--min-confidence", min=0.0, max=1.0, help="Drop weaker returns from the point cloud (not with --grid)."
)
_BEAM_AXIS_OPTION: Any = typer.Option(
    False, "--beam-axis",
    help="Place each return on its beam's axis instead of the near edge of the beam's footprint, where its "
    "leading edge was measured (point clouds).",
)
_POSES_FRAME_OPTION: Any = typer.Option(None, "--poses-frame", help="Override the CSV's frame: ned | enu.")
_FRAME_OPTION: Any = typer.Option("ned", "--frame", help="Output coordinates: ned (default) | enu (z up, for viewers).")
_OUTSIDE_OPTION: Any = typer.Option(
    "error", "--outside", help="Pings outside the trajectory's time span: error | skip (counted)."
)
_FIXED_MODEL_OPTION: Any = typer.Option(
    False, "--fixed-model", help="Use fixed 0.8/0.3 hit/miss probabilities instead of each ping's pD/pFA."
)
_CLAMP_OPTION: Any = typer.Option(
    None, "--clamp",
    help="Occupancy clamping probabilities PMIN,PMAX (default 0.001,0.999 for static scenes; "
    "OctoMap's 0.1192,0.971 forget faster, for scenes that change).",
)
_STATIC_OPTION: Any = typer.Option(
    False, "--static",
    help="Fixed sonar (tripod, pier, tank): every ping at the origin, placed by --extrinsics if given.",
)
_CRS_OPTION: Any = typer.Option(
    None, "--crs",
    help="Projected CRS of the outputs, e.g. EPSG:32631 (default with navigation: the data's UTM zone).",
)
_ORIGIN_OPTION: Any = typer.Option(
    None, "--origin", help="LAT,LON (WGS 84 degrees) of the local frame's origin, to georeference "
    "--poses or --static maps.",
)
_GEOTIFF_OPTION: Any = typer.Option(
    None, "--geotiff",
    help="Also write a GeoTIFF: occupancy probability with --grid, else a bathymetry grid of the points.",
)
_RASTER_RESOLUTION_OPTION: Any = typer.Option(
    0.5, "--raster-resolution", min=1e-3, help="Pixel size (m) of the bathymetry GeoTIFF."
)
_OCTOMAP_OPTION: Any = typer.Option(
    None, "--octomap", help="Also write the 3-D occupancy map (--grid, --dims 3) as an OctoMap .bt."
)


def map_command(
    pings: list[Path] = _PINGS_ARGUMENT,
    poses: Path | None = _POSES_OPTION,
    extrinsics: Path | None = _EXTRINSICS_OPTION,
    output: Path = _OUTPUT_OPTION,
    grid: float | None = _GRID_OPTION,
    fmt: str | None = _FORMAT_OPTION,
    sonar: str | None = GEOMETRY_OPTION,
    start_time: str | None = START_TIME_OPTION,
    ping_rate: float | None = PING_RATE_OPTION,
    config: Path | None = _CONFIG_OPTION,
    calibration: Path | None = CALIBRATION_OPTION,
    dims: int = _DIMS_OPTION,
    grid_array: Path | None = _GRID_ARRAY_OPTION,
    spread: int = _SPREAD_OPTION,
    min_confidence: float = _MIN_CONFIDENCE_OPTION,
    beam_axis: bool = _BEAM_AXIS_OPTION,
    poses_frame: str | None = _POSES_FRAME_OPTION,
    out_frame: str = _FRAME_OPTION,
    outside: str = _OUTSIDE_OPTION,
    fixed_model: bool = _FIXED_MODEL_OPTION,
    clamp: str | None = _CLAMP_OPTION,
    static: bool = _STATIC_OPTION,
    crs: str | None = _CRS_OPTION,
    origin: str | None = _ORIGIN_OPTION,
    geotiff: Path | None = _GEOTIFF_OPTION,
    raster_resolution: float = _RASTER_RESOLUTION_OPTION,
    octomap: Path | None = _OCTOMAP_OPTION,
    quiet: bool = QUIET_OPTION,
    verbose: bool = VERBOSE_OPTION,
) -> None:
    """Register per-beam ranges into a world point cloud, or build an occupancy map (--grid).

    Output files are replaced atomically when the command succeeds.
    """
    import contextlib

    from sonarmap.io import expand_inputs, read_pings
    from sonarmap.mapping.build import MapConfig, map_from_pings
    from sonarmap.mapping.poses import load_extrinsics, read_trajectory_csv
    from sonarmap.pipeline import PipelineConfig

    out_fmt, bag_kind = _check_options(output, fmt, outside, out_frame, poses_frame, geotiff, octomap, grid_array,
                                       grid, min_confidence, crs)
    bounds = None if clamp is None else _clamp_bounds(clamp)
    _check_static_and_octomap(static, poses, octomap, grid, dims)
    origin_ll = None if origin is None else _lat_lon(origin)
    geometry = load_geometry_option(sonar)
    clock = clock_options(start_time, ping_rate)
    pcfg, background = apply_calibration(PipelineConfig.from_toml(config) if config is not None else PipelineConfig(),
                                         calibration)
    mcfg = MapConfig(
        trajectory=read_trajectory_csv(poses, frame=poses_frame) if poses is not None else None,
        extrinsics=load_extrinsics(extrinsics) if extrinsics is not None else None,
        static=static, outside=outside, n_elevation=spread, min_confidence=min_confidence, grid_m=grid, dims=dims,
        clamp=bounds, fixed_model=fixed_model, origin_lat_lon=origin_ll, crs=crs, footprint_edge=not beam_axis)
    inputs = expand_inputs([str(p) for p in pings])
    total = None if quiet else count_pings(inputs)
    progress = ping_progress("map", total, quiet=quiet, verbose=verbose)

    def checks(georef: Any) -> None:
        # before any processing: the outputs that need a georeference
        _check_georeferenced_outputs(georef, crs, geotiff, out_frame)
        shown.enter_context(progress)
        progress.start()

    def advance(ping: Any, prod: Any) -> None:
        progress.advance()
        progress.log(f"{ping.source}: {prod.ranges.n_returns} returns")

    # the first ping is read before any processing, so that input and pose errors come first
    ping_iter = read_pings(inputs, geometry=geometry, **clock)
    first, ping_iter = first_ping(ping_iter, input_name(inputs, "PINGS"))
    check_clock_used(first, clock)
    with contextlib.ExitStack() as shown:  # the progress display, from the first processed ping on
        res = map_from_pings(ping_iter, mcfg, pcfg, background=background, on_start=checks, on_ping=advance)
        out_cloud = _write_results(res, output, out_fmt, bag_kind, out_frame, grid_array=grid_array, geotiff=geotiff,
                                   octomap=octomap, raster_resolution=raster_resolution)
    if not quiet:
        _print_summary(res, out_cloud, output, geotiff=geotiff, octomap=octomap, grid_array=grid_array)


def _check_static_and_octomap(static: bool, poses: Path | None, octomap: Path | None, grid: float | None,
                              dims: int) -> None:
    """Usage errors: ``--static`` with ``--poses``, and ``--octomap`` without a 3-D occupancy map."""
    if static and poses is not None:
        raise typer.BadParameter("a fixed sonar needs no trajectory; give --static or --poses", param_hint="--static")
    if octomap is not None and (grid is None or dims != 3):
        raise typer.BadParameter("needs a 3-D occupancy map (--grid RES, --dims 3)", param_hint="--octomap")


def _check_georeferenced_outputs(georef: Any, crs: str | None, geotiff: Path | None, out_frame: str) -> None:
    """Errors of the outputs that need (or exclude) a georeference, once the map's georeference
    (None without navigation or ``--origin``) is known."""
    from sonarmap.errors import InputError

    if crs is not None and georef is None:
        raise typer.BadParameter("needs a geodetic origin: navigation in the pings, or --origin LAT,LON",
                                 param_hint="--crs")
    if geotiff is not None and georef is None:
        raise InputError("--geotiff: needs a georeferenced map (navigation in the pings, or --origin LAT,LON)")
    if georef is not None and out_frame != "ned":
        raise typer.BadParameter("georeferenced outputs are in the projected CRS (E, N, up)", param_hint="--frame")


def _write_results(res: MapResult, output: Path, out_fmt: str, bag_kind: str | None, out_frame: str, *,
                   grid_array: Path | None, geotiff: Path | None, octomap: Path | None,
                   raster_resolution: float) -> PointCloud:
    """Write the map, in this order: the grid array, the main output, the GeoTIFF and the OctoMap
    (those asked for); returns the cloud written (the points, or the occupied cells with ``--grid``)."""
    georef, occ = res.georef, res.occupancy
    if occ is None:
        out_cloud = res.cloud
    else:
        out_cloud = occ.to_point_cloud()
        if grid_array is not None:
            _save_grid_array(grid_array, occ)
    _write_outputs(out_cloud, occ, georef, output, out_fmt, bag_kind, out_frame, res.last_time_ns)
    if geotiff is not None:
        from sonarmap.mapping.raster import height_raster, occupancy_raster, write_geotiff

        if occ is not None:
            write_geotiff(geotiff, occupancy_raster(occ, georef=georef))
        else:
            write_geotiff(geotiff, height_raster(out_cloud, georef=georef, resolution_m=raster_resolution))
    if octomap is not None and occ is not None:
        from sonarmap.mapping.octomap import write_octomap_bt

        write_octomap_bt(octomap, occ)
    return out_cloud


def _save_grid_array(path: Path, occ: OccupancyMap) -> None:
    """Save the occupancy grid as a dense array (``--grid-array``, ``.npz``), replaced atomically."""
    import numpy as np

    from sonarmap._atomic import atomic_path

    arr = occ.to_array()
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(
            fh, logodds=arr.logodds, observed=arr.observed, origin_m=arr.origin_m,
            resolution_m=np.float64(arr.resolution_m), frame=np.str_("ned"),
        )


def _print_summary(res: MapResult, out_cloud: PointCloud, output: Path, *, geotiff: Path | None,
                   octomap: Path | None, grid_array: Path | None) -> None:
    """The summary line of ``map`` on stderr: pings, returns, skipped pings, what was written where,
    the projected CRS of a georeferenced map, and the other files written."""
    grid = res.occupancy is not None
    also = {"OctoMap": octomap, "grid array": grid_array, ("occupancy" if grid else "bathymetry") + " GeoTIFF": geotiff}
    what = counted(len(out_cloud), "occupied cell" if grid else "point")
    skipped = f", {res.n_skipped} skipped outside the trajectory" if res.n_skipped else ""
    crs = f" ({res.georef.crs_name})" if res.georef is not None else ""
    extra = "".join(f"; {label} -> {output_name(path)}" for label, path in also.items() if path is not None)
    err_console().print(f"{counted(res.n_pings, 'ping')}, {counted(res.n_returns, 'return')}{skipped} -> {what} in "
                        f"{output_name(output)}{crs}{extra}", markup=False, soft_wrap=True)


def _check_options(output: Path, fmt: str | None, outside: str, out_frame: str, poses_frame: str | None,
                   geotiff: Path | None, octomap: Path | None, grid_array: Path | None, grid: float | None,
                   min_confidence: float, crs: str | None = None) -> tuple[str, str | None]:
    """Usage errors of ``sonarmap map``'s output options, before any work; returns the output
    format and the bag kind (``bag1`` / ``bag2`` / None)."""
    from sonarmap.errors import SonarmapError
    from sonarmap.mapping.pointcloud import CLOUD_FORMATS, format_from_suffix

    if crs is not None:
        _check_crs(crs)

    check_choice(outside, ("error", "skip"), "--outside")
    check_choice(out_frame, ("ned", "enu"), "--frame")
    if poses_frame is not None:
        check_choice(poses_frame, ("ned", "enu"), "--poses-frame")
    if str(output) == STDOUT and fmt is None:
        raise typer.BadParameter("-o - needs --format ply, las or csv", param_hint="--format")
    bag_kind = fmt.lower() if fmt is not None and fmt.lower() in ("bag1", "bag2") else (
        "bag1" if fmt is None and output.suffix.lower() == ".bag" else None)
    if bag_kind is not None:
        if str(output) == STDOUT:
            raise typer.BadParameter("a bag cannot be written to stdout; give a path", param_hint="--output")
        out_fmt = bag_kind
    else:
        try:
            out_fmt = (fmt or format_from_suffix(output)).lower()
        except (ValueError, SonarmapError) as exc:
            raise typer.BadParameter(str(exc).removeprefix("output: ") + " (.bag or --format bag2 for a ROS bag)",
                                     param_hint="--output") from None
        if out_fmt not in CLOUD_FORMATS:
            raise typer.BadParameter(f"must be one of {', '.join(CLOUD_FORMATS)}, bag1, bag2", param_hint="--format")
    for opt, path, suffixes in (("--geotiff", geotiff, (".tif", ".tiff")), ("--octomap", octomap, (".bt",)),
                                ("--grid-array", grid_array, (".npz",))):
        if path is not None and path.suffix.lower() not in suffixes:
            raise typer.BadParameter(f"{path}: expected a {' or '.join(suffixes)} file", param_hint=opt)
    if grid is not None and min_confidence > 0:
        # a dropped return would leave its beam empty, and the map would carve it free to the maximum range
        raise typer.BadParameter("applies to point clouds; the occupancy map keeps every return",
                                 param_hint="--min-confidence")
    return out_fmt, bag_kind


def _check_crs(crs: str) -> None:
    """A usage error for a ``--crs`` that is not a projected CRS in metres (or not a CRS at all)."""
    from sonarmap.errors import InputError
    from sonarmap.mapping.georef import as_crs

    try:
        as_crs(crs)
    except InputError as exc:
        raise typer.BadParameter(str(exc).removeprefix("crs: "), param_hint="--crs") from None


def _write_outputs(out_cloud: Any, occ: Any, georef: Any, output: Path, out_fmt: str, bag_kind: str | None,
                   out_frame: str, last_time_ns: int) -> None:
    """The map's main output: a bag, the cloud on stdout, or a point-cloud file."""
    from sonarmap.mapping.pointcloud import write_point_cloud

    kind = "occupancy" if occ is not None else "points"
    where = {"georef": georef} if georef is not None else {"frame": out_frame}
    if bag_kind is not None:
        from sonarmap.io.rosbag_products import write_points_bag

        if georef is not None:
            from sonarmap.mapping.pointcloud import georeferenced_cloud

            bag_cloud = georeferenced_cloud(out_cloud, None, georef)  # projected E, N, up: float64 needed
        else:
            bag_cloud = out_cloud.to_frame(out_frame)
        if occ is not None:  # the occupied cells, one message at the last ping's time
            from sonarmap.io.rosbag_products import write_occupancy_bag
            from sonarmap.mapping.pointcloud import occupancy_columns

            write_occupancy_bag(bag_cloud.xyz_m, *occupancy_columns(bag_cloud), output, stamp_ns=last_time_ns,
                                frame=bag_cloud.frame, version=1 if bag_kind == "bag1" else 2,
                                xyz_dtype="float64" if georef is not None else "float32")
        else:
            write_points_bag([bag_cloud], output, version=1 if bag_kind == "bag1" else 2,
                             xyz_dtype="float64" if georef is not None else "float32")
    elif str(output) == STDOUT:
        _cloud_to_stdout(out_cloud, out_fmt, kind=kind, **where)
    else:
        write_point_cloud(out_cloud, output, format=out_fmt, kind=kind, **where)


def register(app: typer.Typer) -> None:
    """Add ``map`` to the CLI."""
    app.command(
        "map",
        help="Register ranges into a point cloud or an occupancy map (PLY/LAS/CSV).\n\n"
        "Give -o - with --format to write the cloud to stdout.  Output files are replaced atomically "
        "when the command succeeds.",
        epilog=example("map pings/ --poses poses.csv -o cloud.ply",
                       "map recording.kmall --grid 0.2 -o occupied.ply --geotiff occupancy.tif"),
    )(map_command)
