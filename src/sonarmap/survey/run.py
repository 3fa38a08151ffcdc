"""Running a survey: :func:`process_survey` (plan, create or resume the store, run the chunks)."""

from __future__ import annotations

import dataclasses
import json
import os
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sonarmap._atomic import WriterLock, remove_stale_dirs
from sonarmap._config import config_dict, jsonable
from sonarmap._text import counted
from sonarmap.datamodel import COORD_AZIMUTH, SURVEY_FORMAT, TIME_UNITS
from sonarmap.errors import DataFormatError, InputError, SonarmapError, SonarmapWarning
from sonarmap.ping import Ping
from sonarmap.store import (
    CheckedStore,
    ChunkRows,
    check_times,
    complete_marker,
    consolidate,
    consolidated_status,
    create_array,
    create_products,
    crc_failures,
    damaged_chunks,
    done_chunks,
    finish_store,
    flagged_mask,
    inspect_products,
    invalidate_consolidated,
    open_writable,
    product_record,
    product_schema,
    read_array,
    read_root_attrs,
    reference_range,
    remove_marker_temporaries,
    remove_store,
    remove_tmp,
    stack_product_records,
    store_geometry,
    unmark_chunk,
    write_marker,
)
from sonarmap.survey.plan import (
    ChunkSpec,
    DEFAULT_CHUNK_SIZE,
    PingFunction,
    SurveyExistsError,
    SurveyPlan,
    _default_ping_function,
    _fingerprint,
    _function_name,
    _iter_chunk_pings,
    _maybe_config,
    _resolve_config,
    plan_survey,
)
from sonarmap.survey.executors import _ProcessPool, _run_dask, _run_serial

__all__ = ["run_chunk", "SurveyResult", "process_survey", "replicate_pings"]


def run_chunk(
    chunk: ChunkSpec,
    config: Any,
    *,
    keep_labels: bool = False,
    schema: Mapping[str, tuple[tuple[int, ...], str]] | None = None,
    ping_function: PingFunction | None = None,
    reference: tuple[np.ndarray, np.ndarray] | None = None,
    background: Any = None,
) -> dict[str, np.ndarray]:
    """Process one chunk: read its pings, run the per-ping pipeline, stack the products.

    This is the task body on every executor; it only returns products (no images).

    Parameters
    ----------
    chunk : ChunkSpec
        Which pings.
    config : PipelineConfig
        The pipeline configuration.
    keep_labels : bool
        Also return the per-pixel labels, shape ``(n, n_bins, n_beams)`` uint8.
    schema : mapping, optional
        Shapes/dtypes of the product rows (from the store); inferred from the first ping if absent.
    ping_function : callable, optional
        ``f(ping, config, *, keep_labels) -> PingProducts``; default
        :func:`sonarmap.pipeline.process_ping`.
    reference : (azimuth_rad, range_m), optional
        The survey's beam azimuths and bin ranges; a ping with another geometry is an error
        (one product store holds one sonar configuration).
    background : RecordingBackground, optional
        The recording's background level (``sonarmap calibrate``), passed on as the ping
        function's ``background=``; without it each ping is normalised by its own.

    Returns
    -------
    dict of str to ndarray
        One array per product variable with leading dimension ``chunk.n_pings``.
    """
    fn = ping_function or _default_ping_function()
    records: list[dict[str, Any]] = []
    sources: list[str] = []
    for ping in _iter_chunk_pings(chunk):
        if reference is not None and not (
            np.array_equal(ping.geometry.azimuth_rad, reference[0])
            and np.array_equal(ping.geometry.range_m, reference[1])
        ):
            raise InputError(
                f"{ping.source}: sonar geometry '{ping.geometry.name}' (beams/range bins) differs from "
                "the survey's first ping; process each sonar configuration into its own store"
            )
        prod = _call(fn, ping, config, keep_labels, background)
        records.append(product_record(prod, keep_labels=keep_labels))
        sources.append(ping.source)
    if len(records) != chunk.n_pings:
        raise DataFormatError(f"chunk {chunk.index}: read {len(records)} pings, planned {chunk.n_pings}")
    return stack_product_records(records, schema or product_schema(records[0]), sources)


def _call(fn: PingFunction, ping: Ping, config: Any, keep_labels: bool, background: Any) -> Any:
    """``fn(ping, config, keep_labels=)``, with ``background=`` only when there is one (a custom
    ping function need not take it unless the run has a calibration)."""
    if background is None:
        return fn(ping, config, keep_labels=keep_labels)
    return fn(ping, config, keep_labels=keep_labels, background=background)


@dataclasses.dataclass(frozen=True)
class _Stored:
    """What a task that wrote its own chunk returns instead of the products."""

    index: int
    n_pings: int


class _Sink:
    """The parent's side of storing chunks: data (unless a worker already wrote it), then marker."""

    def __init__(self, store: Path, writer: ChunkRows) -> None:
        self.store = store
        self.writer = writer

    def put(self, chunk: ChunkSpec, result: Any) -> None:
        """Store ``result`` of ``chunk`` (unless a worker did) and write the chunk's marker."""
        if isinstance(result, _Stored):
            if result.index != chunk.index or result.n_pings != chunk.n_pings:
                raise SonarmapError(f"chunk {chunk.index}: worker reported {result}")
        else:
            self.writer.write(chunk, result)
        write_marker(self.store, chunk.index, chunk.start, chunk.stop)


@dataclasses.dataclass(frozen=True)
class _Task:
    """Picklable task body: ``run_chunk`` with the run's fixed arguments."""

    config: Any
    keep_labels: bool
    schema: Mapping[str, tuple[tuple[int, ...], str]]
    ping_function: PingFunction | None
    reference: tuple[np.ndarray, np.ndarray] | None = None
    #: If set, the task writes its chunk itself and returns a :class:`_Stored`.
    writer: ChunkRows | None = None
    #: The recording's background level (``process_survey(background=)``).
    background: Any = None

    def __call__(self, chunk: ChunkSpec) -> dict[str, np.ndarray] | _Stored:
        data = run_chunk(chunk, self.config, keep_labels=self.keep_labels, schema=self.schema,
                         ping_function=self.ping_function, reference=self.reference, background=self.background)
        if self.writer is None:
            return data
        self.writer.write(chunk, data)
        return _Stored(chunk.index, chunk.n_pings)


# ============================================================================ driver
@dataclasses.dataclass(frozen=True)
class SurveyResult:
    """Summary of a :func:`process_survey` run.

    Attributes
    ----------
    output : Path
        The survey store.
    n_pings, n_flagged : int
        Pings in the survey; pings whose fit carries a flag (:func:`flagged_mask`).
    n_chunks, chunks_run, chunks_skipped : int
        Total chunks; processed by this run; already done by an earlier run (resume).
    elapsed_s : float
        Wall time of this run.
    executor : str
        ``"serial"``, ``"processes:<n>"`` or ``"dask:<address>"``.
    points_path : Path or None
        Point cloud written when poses were given.
    n_points : int
        Number of registered points.
    gates : tuple of tuple of str
        Per ping, the fit gates it failed (:mod:`sonarmap.stats.gates`): such pings have no
        returns.
    """

    output: Path
    n_pings: int
    n_flagged: int
    n_chunks: int
    chunks_run: int
    chunks_skipped: int
    elapsed_s: float
    executor: str
    points_path: Path | None = None
    n_points: int = 0
    gates: tuple[tuple[str, ...], ...] = ()

    @property
    def pings_per_s(self) -> float:
        """Throughput of this run (pings processed by it / wall time)."""
        n = self.n_pings if self.n_chunks == 0 else self.n_pings * self.chunks_run / self.n_chunks
        return n / self.elapsed_s if self.elapsed_s > 0 else float("inf")

    def summary(self) -> str:
        """One line: pings, flagged fits, time, rate (no time and rate when nothing was left to compute)."""
        resumed = f", resumed ({self.chunks_skipped}/{self.n_chunks} chunks already done)" if self.chunks_skipped else ""
        pts = f", {self.n_points} points" if self.points_path is not None else ""
        run = "" if self.chunks_skipped and not self.chunks_run else (
            f", {self.elapsed_s:.1f} s, {_rate(self.pings_per_s)} pings/s [{self.executor}]")
        return f"{counted(self.n_pings, 'ping')}, {counted(self.n_flagged, 'flagged fit')}{run}{resumed}{pts} -> {self.output}"


def _plan_run(inputs: Any, config: Any, *, chunk_size: int, geometry: Any, keep_labels: bool, poses: Any,
              extrinsics: Any, ping_function: PingFunction | None, workers: int | None = None,
              background: Any = None) -> tuple[Any, SurveyPlan, dict[str, Any], str]:
    """The run's configuration, plan, configuration dict and fingerprint (arguments and inputs
    checked first)."""
    from sonarmap import __version__
    from sonarmap.preprocess.normalise import RecordingBackground

    if workers is not None and (isinstance(workers, bool) or int(workers) != workers or workers < 0):
        raise InputError(f"workers: must be a non-negative integer (got {workers!r})")
    if background is not None and not isinstance(background, RecordingBackground):
        raise InputError(f"background: expected a RecordingBackground, got {type(background).__name__}")
    cfg = _resolve_config(config) if ping_function is None else _maybe_config(config)
    plan = plan_survey(inputs, chunk_size=chunk_size, geometry=geometry)
    _check_fixed_geometry(plan)
    if poses is not None and not Path(poses).is_file():
        raise DataFormatError("poses file not found", poses)
    cfg_dict = config_dict(cfg)
    fp = _fingerprint(plan, cfg_dict, keep_labels=keep_labels, poses=poses, extrinsics=extrinsics,
                      version=__version__, ping_function=_function_name(ping_function),
                      background=None if background is None else background.to_dict())
    return cfg, plan, cfg_dict, fp


#: Formats whose pings change geometry from ping to ping (the range window and the beam pointing
#: angles of a multibeam's water column), which a product store of one sonar geometry cannot hold,
#: with the name messages give them.
_PER_PING_GEOMETRY_FORMATS = {"kongsberg": "Kongsberg EM .all/.wcd", "kmall": "Kongsberg .kmall"}


def _check_fixed_geometry(plan: SurveyPlan) -> None:
    """Refuse, before any work, inputs whose sonar geometry changes with every ping."""
    for path, fmt, _ in plan.files:
        if fmt in _PER_PING_GEOMETRY_FORMATS:
            raise InputError(
                f"{path}: {_PER_PING_GEOMETRY_FORMATS[fmt]} water column changes its range window and beam angles "
                "with every ping, "
                "which a survey store (one sonar geometry) cannot hold yet; use `sonarmap ranges` "
                "(per-ping ranges) or `sonarmap map` (points and maps) on this recording")


def _create_and_run(out: Path, plan: SurveyPlan, task: "_Task", cfg_dict: dict[str, Any], fp: str, *,
                    poses: Any, client: Any, scheduler: str | None, workers: int | None,
                    progress: Callable[[int, int], None] | None) -> tuple[list[Any], str, Any, Any]:
    """Create the store if needed and run the chunks still to do, serially, on local workers or on dask.

    Returns what :func:`_store_chunks` returns.  The local pool (and a client this call opened)
    is closed however the run ends.
    """
    ping_function = task.ping_function
    own_client = None
    pool: _ProcessPool | None = None
    if client is None and scheduler is not None:
        from distributed import Client

        client = own_client = Client(scheduler, timeout="30s")
    n_workers = int(workers if workers is not None else (os.cpu_count() or 1))
    serial = client is None and (workers == 0 or (workers is None and n_workers == 1))
    if out.exists():
        _unmark_damaged(out)
    finished_before = complete_marker(out).exists()
    ok = False
    try:
        if client is None and not serial and not finished_before:
            # Start (and warm) the workers now: they load the pipeline while this process probes.
            n_workers = max(1, min(n_workers, plan.n_chunks))
            pool = _ProcessPool(n_workers, ping_function)
        if not out.exists():
            _probe_and_create(out, plan, task, cfg_dict, pool, poses=poses, fingerprint=fp)
        todo, executor, st, root = _store_chunks(out, plan, task, client=client, pool=pool, progress=progress)
        ok = True
    finally:
        if pool is not None:
            pool.close(ok)
        if own_client is not None:
            own_client.close()
    return todo, executor, st, root


def process_survey(
    inputs: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    output: str | os.PathLike[str],
    *,
    config: Any = None,
    workers: int | None = None,
    scheduler: str | None = None,
    client: Any = None,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    keep_labels: bool = False,
    poses: str | os.PathLike[str] | None = None,
    points: str | os.PathLike[str] | None = None,
    extrinsics: str | os.PathLike[str] | None = None,
    geometry: Any = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    ping_function: PingFunction | None = None,
    background: Any = None,
) -> SurveyResult:
    """Process a whole survey into a zarr store of per-ping products; resumable.

    Parameters
    ----------
    inputs : path-like or iterable of path-likes
        Ping files, directories of PNG+JSON pings, or globs.
    output : path-like
        The survey store (a directory, conventionally ``*.zarr``).
    config : PipelineConfig, mapping or TOML path, optional
        Pipeline configuration (validated); defaults to ``PipelineConfig()``.
    workers, scheduler, client : int, str, distributed.Client, optional
        Local worker processes (default: CPU count; ``0`` runs in the calling process), or run the
        chunks on a dask.distributed scheduler (``tcp://host:port``) or client (first).
    chunk_size : int
        Pings per task and per zarr chunk (hundreds keep overheads negligible).
    keep_labels : bool
        Also store per-pixel labels ``(ping_time, range_sample, beam)``.
    poses, points, extrinsics : path-like, optional
        Vehicle poses (CSV): the ranges are registered into a world point cloud, stored (``point_*``
        variables) and written to ``points`` (``.ply``/``.las``, default ``<output stem>.ply``),
        with the sensor mounting ``extrinsics`` (JSON, see :mod:`sonarmap.mapping.poses`).
    geometry : SonarGeometry, preset name or JSON path, optional
        Geometry override for the readers.
    overwrite : bool
        Replace an existing output that is not a resumable run of the same command.
    progress : callable, optional
        ``progress(done_pings, total_pings)``, called after each stored chunk (and once at start).
    ping_function : callable, optional
        Replacement for :func:`sonarmap.pipeline.process_ping` (must be picklable by reference).
    background : RecordingBackground, optional
        The recording's background level (``sonarmap calibrate``) for every ping; part of the
        run's fingerprint, so a store is never resumed under another calibration.

    Returns
    -------
    SurveyResult

    Raises
    ------
    SurveyExistsError
        ``output`` exists and was made by a different command (inputs, configuration, options)
        or is not a survey store, and ``overwrite`` is false.
    """
    t0, out = time.perf_counter(), Path(output)
    cfg, plan, cfg_dict, fp = _plan_run(inputs, config, chunk_size=chunk_size, geometry=geometry, workers=workers,
                                        keep_labels=keep_labels, poses=poses, extrinsics=extrinsics,
                                        ping_function=ping_function, background=background)

    # one writer per output (a killed run's lock is taken over and its leftovers removed)
    with WriterLock(out):
        remove_stale_dirs(out)
        _check_existing(out, fp, overwrite)
        task = _Task(cfg, bool(keep_labels), {}, ping_function, background=background)
        todo, executor, st, root = _create_and_run(out, plan, task, cfg_dict, fp, poses=poses, client=client,
                                                   scheduler=scheduler, workers=workers, progress=progress)
        n_flagged, gates, points_path, n_points = _finalise(out, st, root, plan, poses=poses, points=points,
                                                            extrinsics=extrinsics)
        return SurveyResult(output=out, n_pings=plan.n_pings, n_flagged=n_flagged, n_chunks=plan.n_chunks,
                            chunks_run=len(todo), chunks_skipped=plan.n_chunks - len(todo),
                            elapsed_s=time.perf_counter() - t0, executor=executor, points_path=points_path,
                            n_points=n_points, gates=gates)


def _store_chunks(out: Path, plan: SurveyPlan, task: Any, *, client: Any, pool: Any,
                  progress: Callable[[int, int], None] | None) -> tuple[list[Any], str, Any, Any]:
    """Run the chunks the store does not hold yet - on a dask client, the local pool, or serially
    in this process - and store their products; returns ``(chunks run, executor, products, root)``."""
    st, schema = inspect_products(out)  # metadata checked: a damaged store is a clean error
    remove_marker_temporaries(out)
    root = open_writable(out)
    reference = (np.asarray(read_array(st, COORD_AZIMUTH)), reference_range(st))
    task = dataclasses.replace(task, schema=schema, reference=reference)
    remove_tmp(out)  # temporary files of an interrupted run (no writer of ours runs yet)
    writer = ChunkRows.open(out)
    sink = _Sink(out, writer)

    done = done_chunks(out)
    todo = [plan.chunk(i) for i in range(plan.n_chunks) if i not in done]
    n_done = sum(plan.chunk(i).n_pings for i in done if i < plan.n_chunks)
    if progress:
        progress(n_done, plan.n_pings)
    if not todo:
        stream: Iterator[Any] = iter(())
        executor = "none"
    elif client is not None:
        stream = _run_dask(todo, task, client)
        executor = f"dask:{client.scheduler.address}"
    elif pool is None:
        stream = _run_serial(todo, task)
        executor = "serial"
    else:
        # Local workers share the file system: each writes its own chunk files (distinct
        # files, so concurrent writers are safe) and reports back; this process only writes
        # the completion markers.  (Dask workers may be on other machines: they return the
        # products and this process writes them.)  The last chunks run in parts whose
        # products come back to be stored here, to balance the tail.
        stream = pool.run(todo, dataclasses.replace(task, writer=writer), part_task=task)
        executor = f"processes:{pool.workers}"
    for chunk, result in stream:
        sink.put(chunk, result)
        n_done += chunk.n_pings
        if progress:
            progress(n_done, plan.n_pings)
    return todo, executor, st, root


def _unmark_damaged(out: Path) -> None:
    """Before a resumed run trusts its completion markers: the chunks marked done whose files are
    missing or fail their checksum (:func:`~sonarmap.store.damaged_chunks`) are unmarked, so this run
    computes them again (one warning line); damaged point arrays are registered again.

    Raises
    ------
    DataFormatError
        If a file written when the store was created (a coordinate) is damaged: resuming cannot
        repair that, the message says to run again with ``--overwrite``.
    """
    st, schema = inspect_products(out)
    chunked = [n for n in schema if n in st.arrays]
    for name, _, exc in crc_failures(out, [n for n in st.arrays if n not in schema]):
        if not name.startswith("point_"):
            raise DataFormatError(f"{str(exc).removeprefix(f'{out}: ')}; written when the store was created, "
                                  "so resuming cannot repair it: run again with --overwrite", out)
        complete_marker(out).unlink(missing_ok=True)  # the points are registered again
        break
    done = done_chunks(out)
    bad = {k: exc for k, exc in damaged_chunks(st, chunked).items() if k in done}
    if not bad:
        return
    k, exc = next(iter(bad.items()))
    size, n = int(st.attrs["chunk_size"]), int(st.attrs["n_pings"])
    more = f" and {len(bad) - 1} more chunk(s)" if len(bad) > 1 else ""
    warnings.warn(f"{out}: chunk {k} (pings {k * size}-{min(n, (k + 1) * size) - 1}) is damaged "
                  f"({str(exc).removeprefix(f'{out}: ')}){more}; computing again", SonarmapWarning, stacklevel=2)
    for k in bad:
        unmark_chunk(out, k)


def _check_existing(out: Path, fingerprint: str, overwrite: bool) -> None:
    """An existing output is resumed when it is a survey store of the same command (same
    fingerprint), replaced with ``overwrite``, else refused (:class:`SurveyExistsError`)."""
    if not (out.exists() or out.is_symlink()):
        return
    attrs = read_root_attrs(out) if out.is_dir() else None
    same = attrs is not None and attrs.get("sonarmap_format") == SURVEY_FORMAT and attrs.get("fingerprint") == fingerprint
    if overwrite:
        remove_store(out)
    elif not same:
        why = ("is not a sonarmap survey store" if not attrs or attrs.get("sonarmap_format") != SURVEY_FORMAT
               else "was made from different inputs, configuration or options")
        raise SurveyExistsError(f"{out}: output exists and {why}; use --overwrite to replace it")


def _probe_and_create(out: Path, plan: SurveyPlan, task: Any, cfg_dict: dict[str, Any], pool: Any, *,
                      poses: Any, fingerprint: str) -> None:
    """Probe the first ping(s) in this process - product shapes and static coordinates - and
    create the empty store; a local pool starts its first chunks meanwhile."""
    fn = task.ping_function or _default_ping_function()
    first: Ping | None = None
    for ping in _iter_chunk_pings(plan.chunk(0)):
        prod = _call(fn, ping, task.config, task.keep_labels, task.background)
        first = first or ping
        if prod.fit is not None:  # a ping with a mixture fit gives the mixture's shape
            break
    assert first is not None
    schema = product_schema(product_record(prod, keep_labels=task.keep_labels))
    geom = first.geometry
    if pool is not None:
        # Start the first chunks now (products sent back) while the store is created.
        pool.start(plan.chunks(), dataclasses.replace(task, schema=schema, reference=(
            np.asarray(geom.azimuth_rad, np.float64), np.asarray(geom.range_m, np.float64))))
    create_products(out, geom, prod, config=cfg_dict, keep_labels=task.keep_labels, chunk_size=plan.chunk_size,
                    n_pings=plan.n_pings, n_chunks=plan.n_chunks,
                    inputs=[p for p, _, _ in plan.files[:20]] + (["..."] if len(plan.files) > 20 else []),
                    n_input_files=len(plan.files), poses=None if poses is None else os.path.abspath(poses),
                    fingerprint=fingerprint, extra_attrs=_calibration_attrs(task.background))


def _calibration_attrs(background: Any) -> dict[str, str] | None:
    """The store's ``calibration`` attribute: the recording background the pings were normalised
    by (``--calibration``, :meth:`RecordingBackground.to_dict` as JSON), so that ``report``
    processes its example pings as the run did; None without one."""
    if background is None:
        return None
    return {"calibration": json.dumps(jsonable(background.to_dict()), sort_keys=True)}


def _finalise(out: Path, st: Any, root: Any, plan: SurveyPlan, *, poses: Any, points: Any,
              extrinsics: Any) -> tuple[int, tuple[tuple[str, ...], ...], Path | None, int]:
    """Flag counts, the registered points (with ``poses``), consolidated metadata and the
    completion marker of a stored survey; returns ``(n_flagged, gates, points_path, n_points)``."""
    from sonarmap.stats.gates import REFUSING

    all_flags = read_array(st, "flags")
    n_flagged = int(flagged_mask(all_flags).sum())
    gates = tuple(tuple(sorted(set(str(f).split()) & REFUSING)) for f in all_flags)
    points_path: Path | None = None
    n_points = 0
    complete = complete_marker(out)
    if poses is not None:
        target = Path(points) if points is not None else out.with_suffix(".ply")
        if complete.exists() and "point_xyz" in root and target.exists():
            points_path, n_points = target, int(root["point_xyz"].shape[0])
        else:
            invalidate_consolidated(out)  # arrays change: no stale consolidated metadata meanwhile
            points_path, n_points = _register_points(root, st, out, poses, target, extrinsics)
    if consolidated_status(out) != "current":  # new points, or a store of an older version
        consolidate(out)
    finish_store(out, plan.n_pings, n_flagged)
    return n_flagged, gates, points_path, n_points


def _register_points(root: Any, st: CheckedStore, out: Path, poses: Any, points: Any,
                     extrinsics: Any) -> tuple[Path, int]:
    """Register the stored ranges with the trajectory into world points (stored + written to a file).

    Pings outside the trajectory's time span are skipped; each return is placed at the near edge of
    its beam's footprint when the store's geometry gives the beamwidth
    (:func:`sonarmap.mapping.register.register_returns`).  The cloud is stored in the survey as
    ``point_xyz (point, xyz)``, ``point_time``, ``point_beam``, ``point_intensity``,
    ``point_range_sigma`` (NaN in a store without ``range_sigma``) and written to ``points``
    (default ``<output>.ply``) in the format given by its suffix.
    """
    from sonarmap.mapping import (
        load_extrinsics,
        read_trajectory_csv,
        register_returns,
        sensor_poses,
        write_point_cloud,
    )

    traj = read_trajectory_csv(poses)
    t = np.asarray(read_array(st, "ping_time"), dtype=np.int64)
    check_times(t, out)
    ext = load_extrinsics(extrinsics) if extrinsics is not None else None
    sp = sensor_poses(traj, t, extrinsics=ext, outside="skip")
    cloud = register_returns(
        read_array(st, "range"), read_array(st, COORD_AZIMUTH), sp,
        intensity=np.nan_to_num(read_array(st, "range_intensity"), nan=0.0),
        confidence=np.nan_to_num(read_array(st, "range_confidence"), nan=0.0),
        sigma_m=read_array(st, "range_sigma") if "range_sigma" in st.arrays else None,
        azimuth_beamwidth_rad=store_geometry(st).azimuth_beamwidth_rad,
    )
    n = len(cloud)
    block = max(1, min(n, 1 << 18))
    arrays = {
        "point_xyz": (cloud.xyz_m, ("point", "xyz"), {"long_name": f"Registered return ({cloud.frame.upper()} world frame)", "units": "m"}),
        "point_time": (cloud.time_ns, ("point",), {"long_name": "Ping time of the point", "units": TIME_UNITS,
                                                   "calendar": "proleptic_gregorian"}),
        "point_beam": (cloud.beam, ("point",), {"long_name": "Beam index of the point"}),
        "point_intensity": (cloud.intensity, ("point",), {"long_name": "Intensity of the return"}),
        "point_range_sigma": (cloud.sigma_m, ("point",), {
            "long_name": "One-sigma uncertainty of the return's range (NaN: unknown)", "units": "m"}),
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, (values, dims, attrs) in arrays.items():
            if name in root:
                del root[name]
            create_array(root, name, values, shape=values.shape, chunks=(block, *values.shape[1:]),
                         dtype=values.dtype, dimension_names=dims, attributes=attrs)
    target = Path(points) if points is not None else out.with_suffix(".ply")
    write_point_cloud(cloud, target)
    return target, n


def replicate_pings(
    sources: Sequence[str | os.PathLike[str]],
    n_pings: int,
    directory: str | os.PathLike[str],
    *,
    start_time_ns: int = 1_500_000_000_000_000_000,
    period_ns: int = 100_000_000,
) -> Path:
    """A synthetic survey of ``n_pings`` PNG+JSON pings made of symbolic links to real ones.

    Ping ``i`` links to ``sources[i % len(sources)]`` (and its JSON sidecar) under a new time stamp
    ``start_time_ns + i * period_ns`` (microsecond file names), so a few real pings make a
    survey of any length at no disk cost - for benchmarks and tests of the batch machinery.

    Returns
    -------
    Path
        ``directory``.
    """
    from sonarmap.io.pngjson import sidecar_json

    if not sources:
        raise InputError("sources: need at least one ping image")
    if period_ns < 1000:
        raise InputError("period_ns: must be at least 1 µs (file names are in µs)")
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    srcs = [(os.path.abspath(s), os.path.abspath(sidecar_json(s))) for s in sources]
    for i in range(int(n_pings)):
        img, side = srcs[i % len(srcs)]
        stem = str((start_time_ns + i * period_ns) // 1000)
        os.symlink(img, d / f"{stem}_raw.png")
        os.symlink(side, d / f"{stem}.json")
    return d


def _rate(per_s: float) -> str:
    """A throughput for a summary line: whole pings per second from 10 up, else 2 significant
    digits (a 6-ping run at 0.46 pings/s does not read as 0)."""
    return f"{per_s:.0f}" if per_s >= 10 or per_s != per_s or per_s == float("inf") else f"{per_s:.2g}"
