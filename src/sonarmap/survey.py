"""Survey-scale processing: chunked, resumable batch runs on local processes or dask.distributed.

A survey is a list of pings (one PNG+JSON file each, or frames of multi-ping files) cut into
chunks of ``chunk_size`` consecutive pings.  Each chunk is one task: a worker reads its own pings
from disk (tasks carry file names, never images), runs the fused per-ping pipeline
(:func:`sonarmap.pipeline.process_ping`: pre-process -> mixture fit -> segment -> ranges) and stores
chunk ``k`` in zarr chunk ``k`` of every product variable.  Who writes the chunk files depends on
the executor: local worker processes (same file system) write their own chunk's files directly
(:class:`sonarmap._survey_store.ChunkWriter`: whole chunk files encoded exactly as zarr would,
each moved into place atomically; distinct chunks are distinct files, so concurrent writers are
safe) and report success; dask workers, possibly on other machines, send back the products (a few
kB per ping) and the calling process writes them with the same encoder.  Either way the calling
process alone writes a chunk's completion marker, atomically, and only *after* the chunk's data is
in place.  Because the per-ping path is a pure function of (ping, configuration), every chunk has
a fixed place in the store and the chunk files are the same bytes whoever encodes them, the output
is identical whether chunks ran serially, in local worker processes or on a dask cluster, in any
order, with retries, or across an interruption and a resumed run.

Layout of the output store (zarr v3, readable with :func:`open_products` / ``xarray.open_zarr``;
dimensions and coordinates those of every sonarmap store, :mod:`sonarmap.datamodel`)::

    survey.zarr/
      zarr.json                 root attributes: provenance (sonarmap version, configuration,
                                inputs, fingerprint), written once when the store is created;
                                consolidated metadata (re-written whenever arrays change)
      range_sample, beam, echo_range (ping_time, range_sample), beam_azimuth (beam)  coordinates
      ping_time, source, kld, flags, mixture_weight, mixture_param, range, range_bin, ... arrays
      point_xyz, point_ping ... when poses were given (written after the last chunk)
      .sonarmap/chunks/<k>.done completion markers (data first, marker second)
      .sonarmap/tmp/            chunk files being written (moved into place; cleared on resume)
      .sonarmap/complete        the run finished (summary in JSON)

The store is created in a temporary directory and renamed into place, so it either exists with
complete metadata or not at all.  Every chunk carries a CRC32C checksum (``crc32c`` codec after
``zstd``); :func:`load_products` (what ``sonarmap report`` reads) checks the metadata, the chunks
and every value against the documented ranges of the variables (:data:`PRODUCT_RANGES`).  A run
holds an exclusive lock on its output (:class:`sonarmap._atomic.WriterLock`), so a second run on
the same output fails at once instead of interleaving with the first; the lock of a killed run
is taken over by the next.  Re-running the same command (same inputs, configuration and
options: compared through a fingerprint) resumes; anything else needs ``overwrite=True``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import shutil
import tempfile
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap._atomic import WriterLock, atomic_write_text, write_error
from sonarmap.datamodel import COORDINATES, consolidate, consolidated_status, invalidate_consolidated
from sonarmap.errors import DataFormatError, InputError, SonarmapError
from sonarmap.io.dataset import ATTRS as DATA_MODEL_ATTRS
from sonarmap.io.dataset import (
    COORD_AZIMUTH,
    COORD_RANGE,
    DIM_BEAM,
    DIM_PING,
    DIM_RANGE,
    CheckedStore,
    check_chunk_files,
    check_times,
    check_values,
    checksum_codecs,
    locate_error,
    read_array,
    remove_stale_store_temporaries,
)
from sonarmap.io.products import (
    INFORMATIONAL_FLAGS,
    N_OTHER_RETURNS,
    PRODUCT_VARIABLES,
    STATE_DIR,
    SURVEY_FORMAT,
    TIME_UNITS,
    done_chunks,
    flagged_mask,
    inspect_products,
    int_attr,
    is_product_store,
    marker_dir,
    product_summary,
    read_root_attrs,
    store_geometry,
    survey_status,
)
from sonarmap.ping import Ping

__all__ = [
    "ChunkSpec",
    "SurveyPlan",
    "SurveyResult",
    "SurveyExistsError",
    "plan_survey",
    "process_survey",
    "run_chunk",
    "open_products",
    "load_products",
    "survey_status",
    "is_product_store",
    "product_summary",
    "product_ping",
    "replicate_pings",
    "PRODUCT_VARIABLES",
    "INFORMATIONAL_FLAGS",
    "flagged_mask",
    "product_record",
    "product_schema",
    "stack_product_records",
    "create_product_store",
    "ProductAppender",
    "warm_pipeline_once",
]

DEFAULT_CHUNK_SIZE = 256

PingFunction = Callable[..., Any]


class SurveyExistsError(SonarmapError, FileExistsError):
    """The output exists and is not a resumable run of the same command."""


# ============================================================================ planning
@dataclasses.dataclass(frozen=True)
class ChunkSpec:
    """One task: pings ``start:stop`` of the survey, read from ``items``.

    Parameters
    ----------
    index : int
        Chunk number; the chunk is stored in zarr chunk ``index`` of every product variable.
    start, stop : int
        Survey-wide ping positions.
    items : tuple of (path, format, first, count)
        Where the pings are: ``count`` consecutive pings of ``path`` starting at frame ``first``.
    geometry : SonarGeometry, preset name or JSON path, optional
        Geometry override handed to the readers.
    """

    index: int
    start: int
    stop: int
    items: tuple[tuple[str, str, int, int], ...]
    geometry: Any = None

    @property
    def n_pings(self) -> int:
        """Number of pings in the chunk."""
        return self.stop - self.start


@dataclasses.dataclass(frozen=True)
class SurveyPlan:
    """The pings of a survey, in order, and how they are chunked.

    ``files`` lists ``(path, format, n_pings)``; ``stamps`` the size and modification time of each
    file (part of the fingerprint, so changed inputs are not silently resumed).
    """

    files: tuple[tuple[str, str, int], ...]
    stamps: tuple[tuple[int, int], ...]
    chunk_size: int
    geometry: Any = None

    @property
    def n_pings(self) -> int:
        """Total number of pings."""
        return int(self._offsets[-1]) + self.files[-1][2] if self.files else 0

    @property
    def n_chunks(self) -> int:
        """Number of chunks (tasks)."""
        return max(1, math.ceil(self.n_pings / self.chunk_size)) if self.n_pings else 0

    def chunk(self, index: int) -> ChunkSpec:
        """The :class:`ChunkSpec` of chunk ``index``."""
        start = index * self.chunk_size
        stop = min(self.n_pings, start + self.chunk_size)
        if not 0 <= start < stop:
            raise InputError(f"chunk index {index} out of range 0-{self.n_chunks - 1}")
        offs = self._offsets
        i = int(np.searchsorted(offs, start, side="right")) - 1
        items: list[tuple[str, str, int, int]] = []
        while i < len(self.files) and offs[i] < stop:
            path, fmt, n = self.files[i]
            lo = max(start, int(offs[i])) - int(offs[i])
            hi = min(stop, int(offs[i]) + n) - int(offs[i])
            if hi > lo:
                items.append((path, fmt, lo, hi - lo))
            i += 1
        return ChunkSpec(index, start, stop, tuple(items), self.geometry)

    @property
    def _offsets(self) -> NDArray[np.int64]:
        """Survey position of each file's first ping (cached)."""
        cached = self.__dict__.get("_offsets_cache")
        if cached is None:
            counts = np.fromiter((n for _, _, n in self.files), dtype=np.int64, count=len(self.files))
            cached = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
            object.__setattr__(self, "_offsets_cache", cached)
        return cached

    def chunks(self) -> list[ChunkSpec]:
        """All chunks, in order."""
        return [self.chunk(i) for i in range(self.n_chunks)]


def plan_survey(
    inputs: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    geometry: Any = None,
) -> SurveyPlan:
    """List the pings of ``inputs`` (files, directories, globs) without decoding images.

    PNG/BMP pings given together are ordered by time stamp, as :func:`sonarmap.io.read_pings`
    does; multi-ping files contribute their frames in file order.

    Raises
    ------
    InputError
        If ``chunk_size`` is not a positive integer or the inputs hold no ping.
    DataFormatError
        If an input does not exist or is of an unknown format.
    """
    from sonarmap.io import detect_format, expand_inputs, format_module, is_store_dir
    from sonarmap.io.pngjson import find_png_pings

    if isinstance(chunk_size, bool) or int(chunk_size) != chunk_size or chunk_size < 1:
        raise InputError(f"chunk_size: must be a positive integer (got {chunk_size!r})")
    files: list[tuple[str, str, int]] = []
    pngs: list[Path] = []

    def flush() -> None:
        if pngs:
            files.extend((os.path.abspath(p), "pngjson", 1) for p in find_png_pings(list(pngs)))
            pngs.clear()

    for p in expand_inputs(inputs):
        fmt = "pngjson" if p.is_dir() and not is_store_dir(p) else detect_format(p)
        if fmt == "pngjson":
            pngs.append(p)
            continue
        flush()
        n = int(format_module(fmt).count_pings(p))
        if n:
            files.append((os.path.abspath(p), fmt, n))
    flush()
    if not files:
        raise InputError("inputs: no pings found")
    stamps = []
    for path, _, _ in files:
        st = os.stat(path)
        stamps.append((int(st.st_size), int(st.st_mtime_ns)))
    return SurveyPlan(tuple(files), tuple(stamps), int(chunk_size), geometry)


# ============================================================================ per-chunk work
def _iter_chunk_pings(chunk: ChunkSpec) -> Iterator[Ping]:
    import itertools

    from sonarmap.io import format_module
    from sonarmap.io.pngjson import read_png_ping

    for path, fmt, first, count in chunk.items:
        if fmt == "pngjson":
            yield read_png_ping(path, geometry=chunk.geometry)
            continue
        if fmt in ("zarr", "zarrstore"):  # a converted survey: read only this chunk's pings
            from sonarmap.geometry import as_geometry
            from sonarmap.io.dataset import dataset_to_pings
            from sonarmap.io.dataset import open_survey as open_dataset

            # Pings first:first+count of the whole store (not of a subset): messages about a bad
            # value or chunk give the store's ping and chunk numbers.
            g = None if chunk.geometry is None else as_geometry(chunk.geometry)
            it: Iterator[Ping] = dataset_to_pings(open_dataset(path), geometry=g, start=first, stop=first + count)
            first = 0
        else:
            it = format_module(fmt).iter_pings(Path(path), geometry=chunk.geometry)
        got = 0
        for ping in itertools.islice(it, first, first + count):
            got += 1
            yield ping
        if got != count:
            raise DataFormatError(f"expected {count} pings from frame {first}, found {got}", path)


def _fit_arrays(fit: Any) -> tuple[NDArray[np.float64], NDArray[np.float64], tuple[str, ...]]:
    """``(weights (K,), params (K, P), component names)`` of a mixture fit.

    Accepts :class:`sonarmap.stats.mixture.MixtureFit` or a mapping with ``weights`` and
    ``params``; ragged parameter lists (the zero spike has none) are padded with NaN.
    """
    if fit is None:
        return np.zeros(0), np.zeros((0, 0)), ()
    get = fit.get if isinstance(fit, Mapping) else (lambda k, d=None: getattr(fit, k, d))
    weights = np.asarray(get("weights"), dtype=np.float64).reshape(-1)
    params = get("params", None)
    rows = [np.asarray(r, dtype=np.float64).reshape(-1) for r in (params if params is not None else ())]
    width = max((r.size for r in rows), default=0)
    arr = np.full((len(rows), width), np.nan)
    for i, r in enumerate(rows):
        arr[i, : r.size] = r
    names = tuple(str(n) for n in (get("component_names", None) or ()))
    return weights, arr, names


def _record(products: Any, *, keep_labels: bool) -> dict[str, Any]:
    """One ping's products as plain arrays (the row of every product variable)."""
    if products.fit is None:  # no fit (e.g. a constant image): the mixture rows stay NaN
        weights, params = np.zeros(0), np.zeros((0, 0))
    else:
        weights, params, _ = _fit_arrays(products.fit)
    r = products.ranges
    rec: dict[str, Any] = {
        "ping_time": np.int64(products.time_ns),
        "source": str(products.source),
        "kld": np.float64(np.nan if products.kld is None else products.kld),
        "flags": " ".join(str(f) for f in (products.flags or ())),
        "background_range_db": np.float64(_background_db(products)),
        "floor_levels": np.int16(getattr(products, "floor_levels", 0)),
        "mixture_weight": weights,
        "mixture_param": params,
        "pd": np.float64(np.nan if getattr(products, "pd", None) is None else products.pd),
        "pfa": np.float64(np.nan if getattr(products, "pfa", None) is None else products.pfa),
        "range": np.asarray(r.range_m, dtype=np.float32),
        "range_bin": np.asarray(r.bin, dtype=np.int32),
        "range_intensity": np.asarray(r.intensity, dtype=np.float32),
        "range_confidence": np.asarray(r.confidence, dtype=np.float32),
        "range_sigma": _beam_row(r, "sigma_m"),
        "p_detect": _beam_row(r, "p_detect"),
        "other_range": _other_rows(r),
    }
    if keep_labels:
        labels = getattr(products, "labels", None)
        if labels is None:
            raise SonarmapError(f"{products.source}: pipeline returned no labels with keep_labels")
        rec["labels"] = np.asarray(labels).astype(np.uint8)
    return rec


def _beam_row(ranges: Any, name: str) -> NDArray[np.float32]:
    """``ranges.<name>`` as a float32 row (NaN when the ranges do not carry it)."""
    v = getattr(ranges, name, None)
    n = np.asarray(ranges.range_m).shape[0]
    return np.full(n, np.nan, np.float32) if v is None else np.asarray(v, dtype=np.float32)


def _other_rows(ranges: Any) -> NDArray[np.float32]:
    """``ranges.other_range_m`` as float32 ``(N_OTHER_RETURNS, n_beams)``: the nearest surfaces,
    NaN-padded (further ones are not stored)."""
    n = np.asarray(ranges.range_m).shape[0]
    out = np.full((N_OTHER_RETURNS, n), np.nan, np.float32)
    v = getattr(ranges, "other_range_m", None)
    if v is not None and np.ndim(v) == 2:
        v = np.asarray(v, dtype=np.float32)[:N_OTHER_RETURNS]
        out[: v.shape[0]] = v
    return out


def _background_db(products: Any) -> float:
    bg = getattr(products, "background", None)
    return float(bg.range_dependence_db) if bg is not None and bg.applied else math.nan


_FILL: dict[str, Any] = {
    "background_range_db": np.nan, "floor_levels": 0, "kld": np.nan, "pd": np.nan, "pfa": np.nan, "mixture_weight": np.nan, "mixture_param": np.nan,
    "range": np.nan, "range_bin": -1, "range_intensity": np.nan, "range_confidence": np.nan,
    "range_sigma": np.nan, "p_detect": np.nan, "other_range": np.nan,
    "labels": 0, "ping_time": 0, "source": "", "flags": "",
}


def _stack(records: Sequence[dict[str, Any]], schema: Mapping[str, tuple[tuple[int, ...], str]],
           sources: Sequence[str]) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    n = len(records)
    for name, (shape, dtype) in schema.items():
        if dtype == "str":
            out[name] = np.array([rec[name] for rec in records], dtype=object)
            continue
        arr = np.full((n, *shape), _FILL[name], dtype=dtype)
        for i, rec in enumerate(records):
            val = np.asarray(rec[name])
            if val.shape != shape:
                # Mixture fits with fewer components than the survey's keep their fill value.
                if name.startswith("mixture") and val.ndim == len(shape) and all(
                    a <= b for a, b in zip(val.shape, shape, strict=True)
                ):
                    arr[(i, *(slice(0, s) for s in val.shape))] = val
                    continue
                raise InputError(
                    f"{sources[i]}: product {name} has shape {val.shape}, the survey's is {shape} "
                    "(are all pings from the same sonar geometry?)"
                )
            arr[i] = val
        out[name] = arr
    return out


def _schema_of(record: Mapping[str, Any]) -> dict[str, tuple[tuple[int, ...], str]]:
    schema: dict[str, tuple[tuple[int, ...], str]] = {}
    for name, val in record.items():
        if isinstance(val, str):
            schema[name] = ((), "str")
        else:
            a = np.asarray(val)
            schema[name] = (tuple(a.shape), a.dtype.str)
    return schema


def _default_ping_function() -> PingFunction:
    from sonarmap.pipeline import process_ping

    return process_ping


def run_chunk(
    chunk: ChunkSpec,
    config: Any,
    *,
    keep_labels: bool = False,
    schema: Mapping[str, tuple[tuple[int, ...], str]] | None = None,
    ping_function: PingFunction | None = None,
    reference: tuple[np.ndarray, np.ndarray] | None = None,
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
        prod = fn(ping, config, keep_labels=keep_labels)
        records.append(_record(prod, keep_labels=keep_labels))
        sources.append(ping.source)
    if len(records) != chunk.n_pings:
        raise DataFormatError(f"chunk {chunk.index}: read {len(records)} pings, planned {chunk.n_pings}")
    return _stack(records, schema or _schema_of(records[0]), sources)


# ============================================================================ configuration
def _resolve_config(config: Any) -> Any:
    from sonarmap.pipeline import PipelineConfig

    if config is None:
        return PipelineConfig()
    if isinstance(config, PipelineConfig):
        return config
    if isinstance(config, Mapping):
        return PipelineConfig.from_dict(dict(config))
    if isinstance(config, str | os.PathLike):
        return PipelineConfig.from_toml(config)
    raise InputError(f"config: expected PipelineConfig, mapping or TOML path, got {type(config).__name__}")


def _config_dict(config: Any) -> dict[str, Any]:
    if hasattr(config, "to_dict"):
        return dict(config.to_dict())
    if dataclasses.is_dataclass(config):
        return dataclasses.asdict(config)  # type: ignore[arg-type]
    if isinstance(config, Mapping):
        return dict(config)
    return {"repr": repr(config)}


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return repr(obj)
    if isinstance(obj, str | int | float | bool) or obj is None:
        return obj
    return repr(obj)


def _geometry_token(geometry: Any) -> Any:
    if geometry is None:
        return None
    from sonarmap.geometry import SonarGeometry

    if isinstance(geometry, SonarGeometry):
        return {"name": geometry.name, "key": geometry.key}
    p = Path(str(geometry))
    if p.exists():
        return {"file": os.path.abspath(p), "sha": hashlib.blake2b(p.read_bytes(), digest_size=16).hexdigest()}
    return {"preset": str(geometry)}


def _fingerprint(plan: SurveyPlan, config: dict[str, Any], *, keep_labels: bool, poses: Any,
                 extrinsics: Any, version: str, ping_function: str) -> str:
    h = hashlib.blake2b(digest_size=20)
    head = {
        "format": SURVEY_FORMAT,
        "version": version,
        "config": _jsonable(config),
        "keep_labels": bool(keep_labels),
        "chunk_size": plan.chunk_size,
        "geometry": _geometry_token(plan.geometry),
        "poses": None if poses is None else _file_token(poses),
        "extrinsics": None if extrinsics is None else _file_token(extrinsics),
        "ping_function": ping_function,
    }
    h.update(json.dumps(head, sort_keys=True).encode())
    for (path, fmt, n), (size, mtime) in zip(plan.files, plan.stamps, strict=True):
        h.update(f"{path}\0{fmt}\0{n}\0{size}\0{mtime}\n".encode())
    return h.hexdigest()


def _file_token(path: Any) -> Any:
    p = Path(str(path))
    if not p.is_file():
        return repr(path)
    return {"file": os.path.abspath(p), "sha": hashlib.blake2b(p.read_bytes(), digest_size=16).hexdigest()}


def _function_name(fn: PingFunction | None) -> str:
    if fn is None:
        return "sonarmap.pipeline.process_ping"
    return f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"


# ============================================================================ store
def _create_store(path: Path, plan: SurveyPlan, schema: Mapping[str, tuple[tuple[int, ...], str]],
                  attrs: dict[str, Any], coords: dict[str, Any]) -> None:
    """Create the empty store in a temporary directory, then rename it onto ``path``."""
    import zarr

    from sonarmap._survey_store import array_codec_kwargs

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            root = zarr.open_group(str(tmp), mode="w", zarr_format=3, attributes=attrs)
            n, k = plan.n_pings, plan.chunk_size
            for name, (shape, dtype) in schema.items():
                dims, vattrs = PRODUCT_VARIABLES[name]
                vattrs = dict(vattrs)
                if name == "ping_time":
                    vattrs.update(units=TIME_UNITS, calendar="proleptic_gregorian")
                if DIM_BEAM in dims:
                    vattrs["coordinates"] = COORD_AZIMUTH
                if name.startswith("mixture_") and coords.get("component_names"):
                    vattrs["components"] = " ".join(coords["component_names"])
                if dtype == "str":
                    dt: Any = str
                    fill: Any = ""
                else:
                    dt = np.dtype(dtype)
                    fill = _FILL[name]
                root.create_array(
                    name, shape=(n, *shape), chunks=(k, *shape), dtype=dt, fill_value=fill,
                    dimension_names=dims, attributes=vattrs, **array_codec_kwargs(),
                )
            # Static coordinates along beam / range_sample.
            for name, values, dims, vattrs in coords.get("arrays", ()):
                arr = root.create_array(name, shape=values.shape, dtype=values.dtype,
                                        dimension_names=dims, attributes=vattrs, **checksum_codecs(),
                                        config={"write_empty_chunks": True})
                arr[...] = values
            if coords.get("echo_range") is not None:
                _write_echo_range(root, tmp, np.asarray(coords["echo_range"], np.float64), n, k)
        (tmp / STATE_DIR / "chunks").mkdir(parents=True)
        consolidate(tmp)
        os.replace(tmp, path)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError) and not isinstance(exc, SonarmapError):
            raise write_error(exc, path, "cannot create the store") from None
        raise


def _store_layout(geom: Any, cfg_dict: dict[str, Any], schema: Mapping[str, tuple[tuple[int, ...], str]], *,
                  keep_labels: bool, chunk_size: int, n_pings: int, n_chunks: int, n_input_files: int,
                  inputs: list[str], poses: str | None, fingerprint: str) -> tuple[list[Any], dict[str, Any]]:
    """The static coordinate arrays and root attributes of a new product store.

    The coordinate layout of every sonarmap store (:mod:`sonarmap.datamodel`); shared by
    :func:`process_survey` and :func:`create_product_store` (live runs).
    """
    from sonarmap import __version__

    coord_arrays = [
        (DIM_RANGE, np.arange(geom.n_bins, dtype=np.int32), COORDINATES[DIM_RANGE],
         dict(DATA_MODEL_ATTRS[DIM_RANGE])),
        (DIM_BEAM, np.arange(geom.n_beams, dtype=np.int32), COORDINATES[DIM_BEAM],
         dict(DATA_MODEL_ATTRS[DIM_BEAM])),
        (COORD_AZIMUTH, np.asarray(geom.azimuth_rad, np.float64), COORDINATES[COORD_AZIMUTH],
         dict(DATA_MODEL_ATTRS[COORD_AZIMUTH])),
    ]
    attrs = {
        "sonarmap_format": SURVEY_FORMAT,
        "sonarmap_version": __version__,
        "title": "sonarmap survey products",
        "Conventions": "CF-1.8",
        "source_geometry": json.dumps(_jsonable(geom.to_dict())),
        "pipeline_config": json.dumps(_jsonable(cfg_dict), sort_keys=True),
        "keep_labels": bool(keep_labels),
        "chunk_size": chunk_size,
        "n_pings": n_pings,
        "n_chunks": n_chunks,
        "n_input_files": n_input_files,
        "inputs": inputs,
        "poses": poses,
        "fingerprint": fingerprint,
        "schema": {k: [list(s), d] for k, (s, d) in schema.items()},
        "coordinates": f"{COORD_RANGE} {COORD_AZIMUTH}",
    }
    return coord_arrays, attrs


def _write_echo_range(root: Any, store: Path, range_m: NDArray[np.float64], n: int, k: int) -> None:
    """``echo_range (ping_time, range_sample)`` of a product store: every ping's row is ``range_m``.

    One product store holds one sonar geometry (:func:`run_chunk` refuses pings of another), so
    the coordinate is known when the store is created.  Every full chunk holds the same values,
    hence the same bytes: the first is encoded by zarr and copied to the others' files.
    """
    attrs = dict(DATA_MODEL_ATTRS[COORD_RANGE])
    arr = root.create_array(COORD_RANGE, shape=(n, range_m.size), chunks=(k, range_m.size), dtype=np.float64,
                            fill_value=np.nan, dimension_names=COORDINATES[COORD_RANGE], attributes=attrs,
                            **checksum_codecs(), config={"write_empty_chunks": True})
    if n == 0:
        return
    full = n // k
    rows = np.broadcast_to(range_m, (min(n, k), range_m.size))
    arr[: rows.shape[0]] = rows
    if full > 1:
        first = store / COORD_RANGE / "c" / "0" / "0"
        data = first.read_bytes()
        for i in range(1, full):
            d = store / COORD_RANGE / "c" / str(i)
            d.mkdir(parents=True, exist_ok=True)
            (d / "0").write_bytes(data)
    if n % k and full:
        arr[full * k :] = np.broadcast_to(range_m, (n - full * k, range_m.size))


def remove_store(path: Path) -> None:
    """Delete an existing output by renaming it aside first (never half-deleted in place)."""
    if not path.exists() and not path.is_symlink():
        return
    if path.is_dir() and not path.is_symlink():
        trash = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
        os.replace(path, trash / "old")
        shutil.rmtree(trash, ignore_errors=True)
    else:
        path.unlink()


def _write_marker(store: Path, chunk_index: int, start: int, stop: int) -> None:
    """The chunk's completion marker, written atomically once its data files are in place."""
    marker = marker_dir(store) / f"{chunk_index:08d}.done"
    # No scan for stale temporaries per marker (that would be quadratic in the chunks): the run
    # clears the marker directory's leftovers once, at its start (_remove_marker_temporaries).
    atomic_write_text(marker, json.dumps({"start": start, "stop": stop}) + "\n", clean=False)


def _remove_marker_temporaries(store: Path) -> None:
    """Remove what killed runs left among the markers: temporary files (``.<k>.done.*``) - call
    only while holding the store's lock (no other run writes markers then)."""
    d = marker_dir(store)
    for name in os.listdir(d) if d.is_dir() else ():
        if name.startswith("."):
            with contextlib.suppress(OSError):
                os.unlink(d / name)


@dataclasses.dataclass(frozen=True)
class _Stored:
    """What a task that wrote its own chunk returns instead of the products."""

    index: int
    n_pings: int


class _Sink:
    """The parent's side of storing chunks: data (unless a worker already wrote it), then marker.

    With a :class:`~sonarmap._survey_store.ChunkWriter` (stores this module creates) chunk files
    are encoded and written directly; otherwise (an unrecognised array layout) through zarr, with
    the group and arrays opened once.
    """

    def __init__(self, store: Path, writer: Any) -> None:
        self.store = store
        self.writer = writer
        self._arrays: dict[str, Any] = {}

    def put(self, chunk: ChunkSpec, result: Any) -> None:
        if isinstance(result, _Stored):
            if result.index != chunk.index or result.n_pings != chunk.n_pings:
                raise SonarmapError(f"chunk {chunk.index}: worker reported {result}")
        elif self.writer is not None:
            self.writer.write(chunk.index, result)
        else:
            import zarr

            # Every chunk is written, even one equal to the fill value: a checksummed store has
            # all its chunks, so a missing one is recognised as damage when read.
            with warnings.catch_warnings(), zarr.config.set({"array.write_empty_chunks": True}):
                warnings.simplefilter("ignore")
                try:
                    for name, values in result.items():
                        arr = self._arrays.get(name)
                        if arr is None:
                            if not self._arrays:
                                self._root = _zarr_open(self.store)
                            arr = self._arrays[name] = self._root[name]
                        arr[chunk.start : chunk.stop] = values
                except OSError as exc:
                    raise write_error(exc, self.store, f"cannot write chunk {chunk.index}") from None
        _write_marker(self.store, chunk.index, chunk.start, chunk.stop)


# ============================================================================ executors
def _pool_initializer(parent_pid: int) -> None:  # pragma: no cover - runs in workers
    import signal
    import threading

    # Ctrl-C is handled by the parent, which stops the pool; workers must not die half-way.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # warnings raised while a worker reads its chunk print as one line, as the CLI prints its own
    from sonarmap.errors import show_warning_one_line

    warnings.showwarning = show_warning_one_line

    def watch() -> None:
        # A parent killed with SIGKILL cannot stop its pool: leave instead of idling forever.
        while True:
            time.sleep(0.5)
            try:
                os.kill(parent_pid, 0)
            except ProcessLookupError:
                os._exit(1)
            except OSError:
                pass

    threading.Thread(target=watch, name="sonarmap-parent-watch", daemon=True).start()


def _run_serial(chunks, task):  # type: ignore[no-untyped-def]
    for c in chunks:
        yield c, task(c)


def _warm_worker(ping_function: PingFunction | None) -> int:  # pragma: no cover - in workers
    """Import the pipeline and run it once on a synthetic ping (numba kernels, scipy imports), so
    the first real chunk does not pay for it; runs while the parent probes the survey."""
    try:
        from sonarmap.geometry import preset

        g = preset("didson-hf")
        img = np.random.default_rng(0).random(g.shape, dtype=np.float32) * 0.3
        img[g.n_bins // 2 : g.n_bins // 2 + 8] = 0.9
        fn = ping_function or _default_ping_function()
        fn(Ping(img, g), _resolve_config(None) if ping_function is None else None)
    except Exception:  # noqa: BLE001 - warming must never fail a run
        pass
    return os.getpid()


def warm_pipeline_once() -> bool:
    """Warm this process's per-ping pipeline the way the worker pool's fork server is warmed
    (:mod:`sonarmap._survey_warm`: the default pipeline runs once on a synthetic ping, on the first
    call in a process only; any failure is swallowed).  ``True`` if the warm-up run worked."""
    import sonarmap._survey_warm  # warms on (first) import

    return bool(sonarmap._survey_warm.WARMED)


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


class _ProcessPool:
    """Local worker processes (forkserver: safe with the parent's threads), warmed at creation."""

    def __init__(self, workers: int, ping_function: PingFunction | None) -> None:
        import concurrent.futures as cf
        import multiprocessing

        ctx = multiprocessing.get_context("forkserver")
        with contextlib.suppress(Exception):
            ctx.set_forkserver_preload(["sonarmap.survey", "sonarmap.pipeline", "sonarmap._survey_warm"])
        self.workers = workers
        self.ex = cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_pool_initializer,
                                         initargs=(os.getpid(),))
        # Parallelism is across processes: each worker's numerical libraries get one thread
        # (set before the fork server - and so the workers - import numpy; restored after).
        saved = {v: os.environ.get(v) for v in _THREAD_VARS}
        os.environ.update({v: "1" for v, old in saved.items() if old is None})
        try:
            for _ in range(workers):
                self.ex.submit(_warm_worker, ping_function)
        finally:
            for v, old in saved.items():
                if old is None:
                    os.environ.pop(v, None)

    def start(self, chunks: Sequence[ChunkSpec], part_task: Callable[[ChunkSpec], Any],
              task: Callable[[ChunkSpec], Any] | None = None) -> None:
        """Plan the jobs of ``chunks`` and submit the first ones now, with ``task``.

        Without ``task``, whole chunks also run ``part_task``, which returns the products instead
        of storing them: the workers can start before the store exists - the first chunks of a
        new survey run while this process creates the store (their products are stored here).
        """
        jobs: list[tuple[ChunkSpec, ChunkSpec | None]] = [(c, None) for c in chunks]
        if self.workers > 1:
            jobs = _tail_parts(list(chunks), self.workers)
        self._chunks = [c.index for c in chunks]
        self._part_task = part_task
        self._pending = jobs[::-1]
        self._inflight: dict[Any, tuple[ChunkSpec, ChunkSpec | None]] = {}
        self._fill(task or part_task)

    def _fill(self, task: Callable[[ChunkSpec], Any]) -> None:
        while self._pending and len(self._inflight) < 2 * self.workers:
            c, part = self._pending.pop()
            fut = self.ex.submit(task, c) if part is None else self.ex.submit(self._part_task, part)
            self._inflight[fut] = (c, part)

    def run(self, chunks: Sequence[ChunkSpec], task: Callable[[ChunkSpec], Any],
            part_task: Callable[[ChunkSpec], Any]) -> Iterator[tuple[ChunkSpec, Any]]:
        """Yield ``(chunk, result)`` as chunks finish (at most 2 per worker in flight).

        Whole chunks run ``task``.  With several workers the last chunks are cut into parts run
        with ``part_task`` (returns the products of the part), so the workers finish together
        instead of one worker running the last whole chunk alone (:func:`_tail_parts`); a split
        chunk is yielded once all its parts are back, with its parts' products concatenated.
        Continues what :meth:`start` began, if it was called with the same chunks.
        """
        import concurrent.futures as cf

        if getattr(self, "_chunks", None) != [c.index for c in chunks]:
            if getattr(self, "_inflight", None):
                raise SonarmapError("internal: the pool was started on other chunks")
            self.start(chunks, part_task, task)
        pending, inflight = self._pending, self._inflight
        n_parts: dict[int, int] = {}
        for c, part in [*pending, *inflight.values()]:
            if part is not None:
                n_parts[c.index] = n_parts.get(c.index, 0) + 1
        got: dict[int, list[tuple[int, Any]]] = {}
        while pending or inflight:
            self._fill(task)
            done, _ = cf.wait(inflight, return_when=cf.FIRST_COMPLETED)
            for fut in sorted(done, key=lambda f: (inflight[f][0].index, inflight[f][1] is not None)):
                c, part = inflight.pop(fut)
                if part is None:
                    yield c, fut.result()
                    continue
                parts = got.setdefault(c.index, [])
                parts.append((part.start, fut.result()))
                if len(parts) == n_parts[c.index]:
                    del got[c.index]
                    yield c, _concat_parts([data for _, data in sorted(parts, key=lambda p: p[0])])

    def close(self, ok: bool) -> None:
        """Shut down; on failure or interrupt, terminate the workers at once."""
        if ok:
            self.ex.shutdown(wait=True)
            return
        procs = list((getattr(self.ex, "_processes", None) or {}).values())
        self.ex.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            with contextlib.suppress(Exception):
                p.terminate()
        for p in procs:
            with contextlib.suppress(Exception):
                p.join(timeout=5)


def _sub_chunk(chunk: ChunkSpec, lo: int, hi: int) -> ChunkSpec:
    """Pings ``lo:hi`` (positions within the chunk) of ``chunk`` as a :class:`ChunkSpec` of its own
    (same ``index``: a part is never stored on its own)."""
    if not 0 <= lo < hi <= chunk.n_pings:
        raise InputError(f"chunk {chunk.index}: part {lo}:{hi} out of range 0:{chunk.n_pings}")
    items: list[tuple[str, str, int, int]] = []
    pos = 0
    for path, fmt, first, count in chunk.items:
        a, b = max(lo, pos), min(hi, pos + count)
        if b > a:
            items.append((path, fmt, first + a - pos, b - a))
        pos += count
    return ChunkSpec(chunk.index, chunk.start + lo, chunk.start + hi, tuple(items), chunk.geometry)


#: Minimum pings per part when the tail is split (a part costs a task round trip: keep it useful).
_MIN_PART = 4


def _tail_parts(chunks: list[ChunkSpec], workers: int) -> list[tuple[ChunkSpec, ChunkSpec | None]]:
    """Jobs ``(chunk, part or None)``: the chunks in order, the last ``workers`` of them cut into
    ``2 * workers`` parts each.

    Whole chunks keep the workers busy with few round trips; near the end, when fewer chunks than
    workers remain, each worker would otherwise idle while another finishes a whole chunk (on
    average half a chunk of lost time per worker).  Parts bound that to half a part.
    """
    n_split = min(workers, len(chunks))
    jobs: list[tuple[ChunkSpec, ChunkSpec | None]] = [(c, None) for c in chunks[: len(chunks) - n_split]]
    for c in chunks[len(chunks) - n_split :]:
        n = max(1, min(2 * workers, c.n_pings // _MIN_PART))
        if n == 1:
            jobs.append((c, None))
            continue
        edges = [round(i * c.n_pings / n) for i in range(n + 1)]
        jobs.extend((c, _sub_chunk(c, lo, hi)) for lo, hi in zip(edges[:-1], edges[1:], strict=True))
    return jobs


def _concat_parts(parts: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """One chunk's products from its parts' (in ping order)."""
    return {name: np.concatenate([p[name] for p in parts], axis=0) for name in parts[0]}


def _run_dask(chunks, task, client):  # type: ignore[no-untyped-def]
    """Yield ``(chunk, products)`` from a dask.distributed cluster (bounded number in flight)."""
    import uuid

    from distributed import as_completed

    run_id = uuid.uuid4().hex[:12]
    nthreads = max(1, sum(client.nthreads().values()))
    pending = list(chunks)[::-1]
    futures: dict[Any, ChunkSpec] = {}
    ac = as_completed()

    def submit() -> None:
        c = pending.pop()
        f = client.submit(task, c, key=f"sonarmap-chunk-{c.index}-{run_id}", pure=False, retries=3)
        futures[f] = c
        ac.add(f)

    try:
        while pending and len(futures) < 2 * nthreads + 1:
            submit()
        for f in ac:
            c = futures.pop(f)
            result = f.result()
            f.release()
            if pending:
                submit()
            yield c, result
    finally:
        if futures:
            client.cancel(list(futures))


@dataclasses.dataclass(frozen=True)
class _Task:
    """Picklable task body: ``run_chunk`` with the run's fixed arguments."""

    config: Any
    keep_labels: bool
    schema: Mapping[str, tuple[tuple[int, ...], str]]
    ping_function: PingFunction | None
    reference: tuple[np.ndarray, np.ndarray] | None = None
    #: If set, the task writes its chunk files itself and returns a :class:`_Stored`.
    writer: Any = None

    def __call__(self, chunk: ChunkSpec) -> dict[str, np.ndarray] | _Stored:
        data = run_chunk(chunk, self.config, keep_labels=self.keep_labels, schema=self.schema,
                         ping_function=self.ping_function, reference=self.reference)
        if self.writer is None:
            return data
        self.writer.write(chunk.index, data)
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
        """One line: pings, flagged fits, time, rate."""
        resumed = f", resumed ({self.chunks_skipped}/{self.n_chunks} chunks already done)" if self.chunks_skipped else ""
        pts = f", {self.n_points} points" if self.points_path is not None else ""
        return (
            f"{self.n_pings} pings, {self.n_flagged} flagged fits, {self.elapsed_s:.1f} s, "
            f"{self.pings_per_s:.0f} pings/s [{self.executor}]{resumed}{pts} -> {self.output}"
        )


def _plan_run(inputs: Any, config: Any, *, chunk_size: int, geometry: Any, keep_labels: bool, poses: Any,
              extrinsics: Any, ping_function: PingFunction | None) -> tuple[Any, SurveyPlan, dict[str, Any], str]:
    """The run's configuration, plan, configuration dict and fingerprint (inputs checked first)."""
    from sonarmap import __version__

    cfg = _resolve_config(config) if ping_function is None else _maybe_config(config)
    plan = plan_survey(inputs, chunk_size=chunk_size, geometry=geometry)
    if poses is not None and not Path(poses).is_file():
        raise DataFormatError("poses file not found", poses)
    cfg_dict = _config_dict(cfg)
    fp = _fingerprint(plan, cfg_dict, keep_labels=keep_labels, poses=poses, extrinsics=extrinsics,
                      version=__version__,
                      ping_function=_function_name(ping_function))
    return cfg, plan, cfg_dict, fp


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
    finished_before = (out / STATE_DIR / "complete").exists()
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
    workers : int, optional
        Local worker processes (default: CPU count); ``0`` runs in the calling process.
    scheduler, client : str, distributed.Client, optional
        Run the chunks on a dask.distributed scheduler (``tcp://host:port``) or client (first).
    chunk_size : int
        Pings per task and per zarr chunk (hundreds keep overheads negligible).
    keep_labels : bool
        Also store per-pixel labels ``(ping_time, range_sample, beam)``.
    poses, points : path-like, optional
        Vehicle poses (CSV): the ranges are registered into a world point cloud, stored (``point_*``
        variables) and written to ``points`` (``.ply``/``.las``, default ``<output stem>.ply``).
    extrinsics : path-like, optional
        Sensor mounting (extrinsics JSON, see :mod:`sonarmap.mapping.poses`) used with ``poses``.
    geometry : SonarGeometry, preset name or JSON path, optional
        Geometry override for the readers.
    overwrite : bool
        Replace an existing output that is not a resumable run of the same command.
    progress : callable, optional
        ``progress(done_pings, total_pings)``, called after each stored chunk (and once at start).
    ping_function : callable, optional
        Replacement for :func:`sonarmap.pipeline.process_ping` (must be picklable by reference).

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
    if workers is not None and (isinstance(workers, bool) or int(workers) != workers or workers < 0):
        raise InputError(f"workers: must be a non-negative integer (got {workers!r})")
    cfg, plan, cfg_dict, fp = _plan_run(inputs, config, chunk_size=chunk_size, geometry=geometry,
                                        keep_labels=keep_labels, poses=poses, extrinsics=extrinsics,
                                        ping_function=ping_function)

    # one writer per output (a killed run's lock is taken over and its leftovers removed)
    with WriterLock(out):
        remove_stale_store_temporaries(out)
        _check_existing(out, fp, overwrite)
        task = _Task(cfg, bool(keep_labels), {}, ping_function)
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
    _remove_marker_temporaries(out)
    root = _zarr_open(out)
    reference = (np.asarray(read_array(st, COORD_AZIMUTH)), _reference_range(st))
    task = dataclasses.replace(task, schema=schema, reference=reference)
    from sonarmap._survey_store import ChunkWriter

    writer = ChunkWriter.open(out, list(schema))
    if writer is not None:
        writer.clean_tmp()  # temporary files of an interrupted run (no writer of ours runs yet)
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
        stream = pool.run(todo, task if writer is None else dataclasses.replace(task, writer=writer),
                          part_task=task)
        executor = f"processes:{pool.workers}"
    for chunk, result in stream:
        sink.put(chunk, result)
        n_done += chunk.n_pings
        if progress:
            progress(n_done, plan.n_pings)
    return todo, executor, st, root


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
        prod = fn(ping, task.config, keep_labels=task.keep_labels)
        first = first or ping
        if prod.fit is not None:  # a ping with a mixture fit gives the mixture's shape
            break
    assert first is not None
    rec = _record(prod, keep_labels=task.keep_labels)
    schema = _schema_of(rec)
    _, _, cnames = _fit_arrays(prod.fit)
    geom = first.geometry
    if pool is not None:
        # Start the first chunks now (products sent back) while the store is created.
        pool.start(plan.chunks(), dataclasses.replace(task, schema=schema, reference=(
            np.asarray(geom.azimuth_rad, np.float64), np.asarray(geom.range_m, np.float64))))
    coord_arrays, attrs = _store_layout(
        geom, cfg_dict, schema, keep_labels=task.keep_labels, chunk_size=plan.chunk_size,
        n_pings=plan.n_pings, n_chunks=plan.n_chunks, n_input_files=len(plan.files),
        inputs=[p for p, _, _ in plan.files[:20]] + (["..."] if len(plan.files) > 20 else []),
        poses=None if poses is None else os.path.abspath(poses), fingerprint=fingerprint,
    )
    _create_store(out, plan, schema, attrs, {"arrays": coord_arrays, "component_names": cnames,
                                             "echo_range": geom.range_m})


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
    complete = out / STATE_DIR / "complete"
    if poses is not None:
        target = Path(points) if points is not None else out.with_suffix(".ply")
        if complete.exists() and "point_xyz" in root and target.exists():
            points_path, n_points = target, int(root["point_xyz"].shape[0])
        else:
            invalidate_consolidated(out)  # arrays change: no stale consolidated metadata meanwhile
            points_path, n_points = _register_points(root, st, out, poses, target, extrinsics)
    with contextlib.suppress(OSError):
        os.rmdir(out / STATE_DIR / "tmp")  # empty once every chunk is stored
    if consolidated_status(out) != "current":  # new points, or a store of an older version
        consolidate(out)
    if not complete.exists():
        atomic_write_text(complete, json.dumps({"n_pings": plan.n_pings, "n_flagged": n_flagged}) + "\n")
    return n_flagged, gates, points_path, n_points


def _zarr_open(path: Path) -> Any:
    """The store's root zarr group, writable."""
    import zarr

    return zarr.open_group(str(path), mode="r+", zarr_format=3, use_consolidated=False)


def _maybe_config(config: Any) -> Any:
    """Configuration for an injected ping function: resolved if the pipeline module exists."""
    try:
        return _resolve_config(config)
    except ModuleNotFoundError:
        return config


def _register_points(root: Any, st: CheckedStore, out: Path, poses: Any, points: Any,
                     extrinsics: Any) -> tuple[Path, int]:
    """Register the stored ranges with the trajectory into world points (stored + written to a file).

    Pings outside the trajectory's time span are skipped.  The cloud is stored in the survey as
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
            arr = root.create_array(name, shape=values.shape, chunks=(block, *values.shape[1:]),
                                    dtype=values.dtype, dimension_names=dims, attributes=attrs,
                                    **checksum_codecs(), config={"write_empty_chunks": True})
            arr[...] = values
    target = Path(points) if points is not None else out.with_suffix(".ply")
    write_point_cloud(cloud, target)
    return target, n


#: Documented value range of each product variable, checked by :func:`load_products`
#: (keyword arguments of :func:`sonarmap.io.dataset.check_values`).  NaN is "none" / "unknown" /
#: "not yet written" wherever a float variable has it as fill value.  ``range_bin`` is checked
#: against the number of range bins, ``point_beam`` against the number of beams, the times by
#: :func:`sonarmap.io.dataset.check_times`; ``labels`` (uint8) and the strings are not checked.
PRODUCT_RANGES: dict[str, dict[str, Any]] = {
    "kld": {"low": 0.0, "high": math.inf, "nan": True, "inf": True},  # inf: zero_mass fits
    "background_range_db": {"nan": True},
    "floor_levels": {"low": 0},
    "mixture_weight": {"low": 0.0, "high": 1.0, "nan": True},
    "mixture_param": {"nan": True},
    "pd": {"low": 0.0, "high": 1.0, "nan": True},
    "pfa": {"low": 0.0, "high": 1.0, "nan": True},
    "range": {"low": 0.0, "nan": True},
    "range_intensity": {"nan": True},
    "range_confidence": {"low": 0.0, "high": 1.0, "nan": True},
    "range_sigma": {"low": 0.0, "nan": True},
    "p_detect": {"low": 0.0, "high": 1.0, "nan": True},
    "other_range": {"low": 0.0, "nan": True},
    "point_xyz": {"nan": True, "item": "point"},
    "point_intensity": {"nan": True, "item": "point"},
    "point_range_sigma": {"low": 0.0, "nan": True, "item": "point"},
    COORD_AZIMUTH: {"low": -math.pi, "high": math.pi, "item": "beam"},
    COORD_RANGE: {"low": 0.0, "item": "range bin"},
}


def _reference_range(st: CheckedStore) -> NDArray[np.float64]:
    """The bin ranges of a product store's sonar: ``echo_range`` (its first row in this layout)."""
    arr = st.arrays[COORD_RANGE]
    if len(arr.shape) == 1:  # a store of an earlier version
        return np.asarray(read_array(st, COORD_RANGE), np.float64)
    if int(arr.shape[0]) == 0:
        return np.zeros(int(arr.shape[1]), np.float64)
    return np.asarray(read_array(st, COORD_RANGE, slice(0, 1))[0], np.float64)


def open_products(path: str | os.PathLike[str]) -> Any:
    """Open a survey store as an ``xarray.Dataset`` (lazy, decoded times).

    The metadata is checked first (:func:`load_products` also checks the chunks and values).

    Raises
    ------
    DataFormatError
        If ``path`` is not a sonarmap survey store, or its metadata is corrupt or incomplete (the
        message names the file or array).
    """
    p = Path(path)
    deadline = None
    settled = False
    while True:
        try:
            st, _ = inspect_products(p)
            check_chunk_files(st, DIM_PING, required=False)  # read when opened (an index): no FIFO, no /dev/zero
            return _open_checked(st)
        except DataFormatError:
            # A store written by a live run (root attribute ``live_status``) grows array by array
            # for a few ms per flush: while it is "writing", and once more after it stopped, try
            # again.  Other stores: the error as it is.
            status = _live_status(p)
            deadline = deadline if deadline is not None else time.monotonic() + LIVE_SETTLE_S
            if status is None or time.monotonic() > deadline:
                raise
            if status != "writing":
                if settled:
                    raise
                settled = True
            time.sleep(0.005)


def _open_checked(st: CheckedStore, *, lazy: bool = True) -> Any:
    """``xarray.open_zarr`` of a checked store (dask-backed if ``lazy``); errors name the chunk."""
    import xarray as xr

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            kw: dict[str, Any] = {} if lazy else {"chunks": None}
            return xr.open_zarr(str(st.path), consolidated=False, zarr_format=3, **kw)
    except SonarmapError:
        raise
    except Exception as exc:  # noqa: BLE001 - zarr/xarray raise many types on damaged stores
        raise locate_error(st, list(st.arrays), None, exc, "the survey") from None


def load_products(path: str | os.PathLike[str]) -> Any:
    """Load a survey store into memory, checking everything read.

    Checks the metadata (:func:`open_products`), that every chunk of a completed task (its
    marker exists) and of the other checksummed arrays is present, every chunk's checksum, and
    every value against :data:`PRODUCT_RANGES` (times: int64 ns >= 0, 0 for pings not written).

    Returns
    -------
    xarray.Dataset

    Raises
    ------
    DataFormatError
        Naming the store and the array and chunk (damaged data) or the variable and ping (a value
        outside its documented range).
    """
    p = Path(path)
    st, schema = inspect_products(p)
    k = int_attr(st.attrs, "chunk_size", p, low=1)
    done = sorted(done_chunks(p))
    for name in st.arrays:
        if name in schema:  # chunks of unfinished tasks are legitimately missing (fill values)
            check_chunk_files(st, name, required=False)
            for c in done:
                check_chunk_files(st, name, slice(c * k, (c + 1) * k))
        else:
            check_chunk_files(st, name)
    ds = _open_checked(st, lazy=False)  # one read per array, not one dask task per chunk
    try:
        ds = ds.load()
    except SonarmapError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise locate_error(st, list(st.arrays), None, exc, "the survey") from None
    n_bins, n_beams = int(ds[COORD_RANGE].shape[-1]), int(ds[COORD_AZIMUTH].shape[-1])
    check_times(ds[DIM_PING].values, p)
    if "point_time" in ds:
        check_times(ds["point_time"].values, p, name="point_time", item="point")
    for name, kw in PRODUCT_RANGES.items():
        if name in ds.variables:
            check_values(ds[name].values, name, p, **kw)
    if "range_bin" in ds:
        check_values(ds["range_bin"].values, "range_bin", p, low=0, high=n_bins - 1, allowed=(-1,))
    if "point_beam" in ds:
        check_values(ds["point_beam"].values, "point_beam", p, low=0, high=n_beams - 1, item="point")
    return ds


# ============================================================================ info / show
def product_ping(path: str | os.PathLike[str], index: int = 0, *, image: str = "auto") -> Ping:
    """Ping ``index`` of a product store as a :class:`~sonarmap.ping.Ping` to draw.

    Parameters
    ----------
    path : path-like
        A store written by :func:`process_survey`.
    index : int
        The ping (0-based, in the store's order).
    image : {"auto", "labels", "raw"}
        ``"labels"``: the stored segmentation (1 object, 0 free space; needs ``keep_labels``);
        ``"raw"``: the ping read again from its source file; ``"auto"``: labels if stored, else raw.

    Returns
    -------
    Ping
        With the store's geometry (labels) or the source's (raw), the stored time and source;
        ``meta["image"]`` says which image it is.

    Raises
    ------
    InputError
        If ``index`` is outside the store or ``image`` is not one of the choices.
    DataFormatError
        If the ping's chunk is not written yet, the labels are not stored, or the source cannot
        be read or no longer holds the ping (its time differs).
    """
    if image not in ("auto", "labels", "raw"):
        raise InputError(f"image must be 'auto', 'labels' or 'raw', got {image!r}")
    p = Path(path)
    st, schema = inspect_products(p)
    n = int_attr(st.attrs, "n_pings", p)
    if not 0 <= int(index) < n:
        raise InputError(f"{p}: index {index} is outside the store's {n} pings")
    i = int(index)
    k = int_attr(st.attrs, "chunk_size", p, low=1)
    if i // k not in done_chunks(p):
        raise DataFormatError(f"ping {i} is not processed yet (chunk {i // k} unfinished)", p)
    row = slice(i, i + 1)
    t = int(np.asarray(read_array(st, DIM_PING, row), np.int64)[0])
    check_times(np.asarray([t]), p, i)
    source = str(read_array(st, "source", row)[0])
    if image == "labels" or (image == "auto" and "labels" in schema):
        if "labels" not in schema:
            raise DataFormatError("no labels stored (run sonarmap process with --keep-labels)", p)
        labels = np.asarray(read_array(st, "labels", row)[0])
        check_values(labels, "labels", p, low=0, high=1, start=i)
        return Ping(image=labels.astype(np.float32), geometry=store_geometry(st), time_ns=t, source=source,
                    meta={"image": "labels"})
    from sonarmap.io import read_ping

    file = source.split("#", 1)[0]
    if not file or not os.path.exists(file):
        raise DataFormatError(f"ping {i}: its source {file!r:.200} is not available (and no labels are stored)", p)
    sources = [str(x).split("#", 1)[0] for x in read_array(st, "source", slice(0, i))]
    raw = read_ping(file, index=sum(1 for x in sources if x == file))
    if raw.time_ns != t:
        raise DataFormatError(f"ping {i}: the ping read from {file} has another time than the stored one "
                              "(the source changed)", p)
    return raw.replace(meta={**raw.meta, "image": "raw"})


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


# ============================================================================ growing (live) stores
#: How long :func:`open_products` keeps trying while a live run is publishing a flush (s).
LIVE_SETTLE_S = 2.0


def _live_status(path: Path) -> str | None:
    """The root attribute ``live_status`` of a store written by a live run ("writing" while it
    appends, "complete" after); None for other stores."""
    attrs = read_root_attrs(path)
    v = None if attrs is None else attrs.get("live_status")
    return v if isinstance(v, str) else None


def product_record(products: Any, *, keep_labels: bool = False) -> dict[str, Any]:
    """One ping's products as the row of every product variable (what a store holds per ping).

    Parameters
    ----------
    products : PingProducts
        The output of :func:`sonarmap.pipeline.process_ping`.
    keep_labels : bool
        Include the ``labels`` image.

    Returns
    -------
    dict of str to ndarray or str
    """
    return _record(products, keep_labels=keep_labels)


def product_schema(record: Mapping[str, Any]) -> dict[str, tuple[tuple[int, ...], str]]:
    """Shapes (without the ping dimension) and dtypes of a :func:`product_record`."""
    return _schema_of(record)


def stack_product_records(records: Sequence[dict[str, Any]],
                          schema: Mapping[str, tuple[tuple[int, ...], str]]) -> dict[str, np.ndarray]:
    """Stack :func:`product_record` rows into one array per variable (leading dimension: pings).

    Raises
    ------
    InputError
        If a ping's products do not fit the schema (another sonar geometry).
    """
    return _stack(records, schema, [str(r.get("source", "")) for r in records])


def create_product_store(path: str | os.PathLike[str], ping: Ping, products: Any, *, config: Any,
                         chunk_size: int = DEFAULT_CHUNK_SIZE, keep_labels: bool = False,
                         inputs: Sequence[str] = (), fingerprint: str = "") -> None:
    """Create an empty product store (0 pings) for :class:`ProductAppender`, atomically.

    The layout, attributes and codecs are those of :func:`process_survey`'s stores; the schema
    and static coordinates come from the first ping and its products.  The root attribute
    ``live_status`` is ``"writing"`` until the appender is closed.

    Raises
    ------
    InputError
        If ``chunk_size`` is not a positive integer.
    """
    import types

    if isinstance(chunk_size, bool) or int(chunk_size) != chunk_size or chunk_size < 1:
        raise InputError(f"chunk_size: must be a positive integer (got {chunk_size!r})")
    out = Path(path)
    rec = _record(products, keep_labels=keep_labels)
    schema = _schema_of(rec)
    _, _, cnames = _fit_arrays(products.fit)
    geom = ping.geometry
    coord_arrays, attrs = _store_layout(
        geom, _config_dict(config), schema, keep_labels=keep_labels, chunk_size=int(chunk_size), n_pings=0,
        n_chunks=0, n_input_files=len(inputs), inputs=list(inputs)[:20], poses=None, fingerprint=fingerprint,
    )
    attrs["live_status"] = "writing"
    plan = types.SimpleNamespace(n_pings=0, chunk_size=int(chunk_size))
    _create_store(out, plan, schema, attrs, {"arrays": coord_arrays, "component_names": cnames,  # type: ignore[arg-type]
                                             "echo_range": geom.range_m})


class ProductAppender:
    """Append pings' products to a store made by :func:`create_product_store`; readers see prefixes.

    Each :meth:`append` is one flush, published so that readers always see a consistent prefix
    of the pings: (1) the chunk files of the new rows are written, each atomically (a partly
    filled last chunk is rewritten with its earlier rows unchanged); (2) every per-ping array's
    ``zarr.json`` gets the new length; (3) the root ``zarr.json`` - the ``n_pings`` / ``n_chunks``
    attributes and the consolidated metadata - is replaced in one rename.  Readers of the
    consolidated metadata (``xarray.open_zarr``) switch from one prefix to the next at (3);
    :func:`open_products` retries for up to :data:`LIVE_SETTLE_S` while (2)-(3) are under way.
    Full chunks get their completion marker; :meth:`close` marks the store complete.

    Parameters
    ----------
    path : path-like
        The store.
    range_m : ndarray, shape (n_bins,), optional
        Ranges of the sonar's bins (the ``echo_range`` row of every ping): pass the first ping's
        ``geometry.range_m``; default: from the store's ``source_geometry`` attribute.

    Raises
    ------
    DataFormatError
        If ``path`` is not a product store this version writes.
    """

    def __init__(self, path: str | os.PathLike[str], *, range_m: Any = None) -> None:
        from sonarmap._survey_store import ChunkWriter
        from sonarmap.datamodel import node_docs, read_metadata_doc

        self.path = Path(path)
        st, schema = inspect_products(self.path)
        self.schema = schema
        self.chunk_size = int_attr(st.attrs, "chunk_size", self.path, low=1)
        self.n_pings = int_attr(st.attrs, "n_pings", self.path)
        if self.n_pings:
            raise DataFormatError("ProductAppender needs a new, empty store", self.path)
        self._range_m = np.asarray(store_geometry(st).range_m if range_m is None else range_m, np.float64)
        if self._range_m.shape != (int(st.arrays[COORD_RANGE].shape[-1]),):
            raise InputError(f"range_m: shape {self._range_m.shape}, the store has "
                             f"{int(st.arrays[COORD_RANGE].shape[-1])} range bins")
        self._names = [*schema, COORD_RANGE]
        writer = ChunkWriter.open(self.path, self._names)
        if writer is None:
            raise DataFormatError("the store's arrays use codecs this version does not write", self.path)
        self._writer = writer
        self._root_doc = read_metadata_doc(self.path / "zarr.json")
        self._nodes = node_docs(self.path)
        self._tail: list[dict[str, Any]] = []
        self.n_flagged = 0
        self.closed = False

    def append(self, records: Sequence[dict[str, Any]]) -> None:
        """Write and publish the rows ``records`` (:func:`product_record`) after the stored pings."""
        if self.closed:
            raise SonarmapError(f"{self.path}: the store was closed")
        if not records:
            return
        k = self.chunk_size
        n0, n1 = self.n_pings, self.n_pings + len(records)
        c0 = n0 // k
        rows = [*self._tail, *records]
        for c in range(c0, -(-n1 // k)):
            part = rows[(c - c0) * k : (c - c0 + 1) * k]
            data = stack_product_records(part, self.schema)
            data[COORD_RANGE] = np.broadcast_to(self._range_m, (len(part), self._range_m.size))
            self._writer.write(c, data)
        self._tail = rows[(n1 // k - c0) * k :]
        self.n_flagged += int(flagged_mask([r["flags"] for r in records]).sum())
        for name in self._names:
            doc = self._nodes[name]
            doc["shape"] = [n1, *doc["shape"][1:]]
            self._replace(self.path / name / "zarr.json", doc)
        self._publish(n1)
        for c in range(c0, n1 // k):
            _write_marker(self.path, c, c * k, (c + 1) * k)
        self.n_pings = n1

    def close(self) -> None:
        """Mark the store complete (last chunk's marker, ``live_status`` "complete", summary)."""
        if self.closed:
            return
        k, n = self.chunk_size, self.n_pings
        if n % k:
            _write_marker(self.path, n // k, (n // k) * k, n)
        self._publish(n, status="complete")
        with contextlib.suppress(OSError):
            os.rmdir(self.path / STATE_DIR / "tmp")
        atomic_write_text(self.path / STATE_DIR / "complete",
                          json.dumps({"n_pings": n, "n_flagged": self.n_flagged}) + "\n")
        self.closed = True

    def _publish(self, n: int, status: str = "writing") -> None:
        doc = self._root_doc
        attrs = doc.setdefault("attributes", {})
        attrs.update(n_pings=n, n_chunks=-(-n // self.chunk_size), live_status=status)
        doc["consolidated_metadata"] = {"kind": "inline", "must_understand": False,
                                        "metadata": dict(sorted(self._nodes.items()))}
        self._replace(self.path / "zarr.json", doc)

    def _replace(self, target: Path, doc: dict[str, Any]) -> None:
        """Replace one metadata document atomically (temporary file in the store, then rename)."""
        import uuid

        tmp = self.path / STATE_DIR / "tmp" / f"meta-{os.getpid()}-{uuid.uuid4().hex}"
        try:
            tmp.write_bytes(json.dumps(doc).encode("utf-8"))  # compact: the C encoder, ~10x faster
            os.replace(tmp, target)
        except OSError as exc:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise write_error(exc, self.path, f"cannot write {target.relative_to(self.path)}") from None
