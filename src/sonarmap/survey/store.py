"""The product store of a survey: creation, chunk markers, opening and checked loading, appending."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import shutil
import tempfile
import time
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap._atomic import atomic_write_text, write_error
from sonarmap.datamodel import COORDINATES, consolidate
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
)
from sonarmap.io.products import (
    PRODUCT_VARIABLES,
    STATE_DIR,
    SURVEY_FORMAT,
    TIME_UNITS,
    done_chunks,
    flagged_mask,
    inspect_products,
    int_attr,
    marker_dir,
    read_root_attrs,
    store_geometry,
)
from sonarmap.ping import Ping
from sonarmap.survey.plan import ChunkSpec, DEFAULT_CHUNK_SIZE, SurveyPlan, _config_dict, _jsonable
from sonarmap.survey.records import _FILL, _fit_arrays, _record, _schema_of, stack_product_records
from sonarmap.survey._chunk_writer import StoreReplacedError, array_codec_kwargs

__all__ = ["ChunkRows", "remove_store", "PRODUCT_RANGES", "open_products", "load_products", "product_ping", "LIVE_SETTLE_S", "create_product_store", "ProductAppender"]


# ============================================================================ store
def _create_store(path: Path, plan: SurveyPlan, schema: Mapping[str, tuple[tuple[int, ...], str]],
                  attrs: dict[str, Any], coords: dict[str, Any]) -> None:
    """Create the empty store in a temporary directory, then rename it onto ``path``."""
    import zarr


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


def _remove_temporaries(store: Path) -> None:
    """Remove the temporary files an interrupted writer left in ``.sonarmap/tmp`` (call before
    any writer of this run starts)."""
    d = store / STATE_DIR / "tmp"
    for f in d.iterdir() if d.is_dir() else ():
        with contextlib.suppress(OSError):
            f.unlink()


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


@dataclasses.dataclass(frozen=True)
class ChunkRows:
    """Writes one chunk's rows of every product variable through zarr's own API (picklable).

    A local worker process writes its own chunk into the shared store (distinct chunks are
    distinct files: safe for concurrent writers) and only reports success to the parent, which
    then writes the completion marker; the parent writes what comes back from dask workers and
    split chunks.  Every chunk is written, even one equal to the fill value: a checksummed store
    has all its chunks, so a missing one is recognised as damage when read.

    ``identity`` is the ``(st_dev, st_ino)`` of the store directory when the writer was made: a
    write into a store that has since been replaced (e.g. a worker left over from a killed run
    while the output is re-created with ``--overwrite``) raises :class:`StoreReplacedError`
    instead of writing.
    """

    store: str
    identity: tuple[int, int]

    @classmethod
    def open(cls, store: str | os.PathLike[str]) -> ChunkRows:
        """A writer for the product store ``store`` (which must exist)."""
        try:
            st = os.stat(store)
        except OSError as exc:
            raise write_error(exc, Path(store), "cannot prepare the store for writing") from None
        return cls(os.fspath(store), (st.st_dev, st.st_ino))

    def write(self, chunk: ChunkSpec, data: Mapping[str, Any]) -> None:
        """Write rows ``chunk.start:chunk.stop`` of every variable in ``data`` (name -> rows)."""
        import zarr

        try:
            st = os.stat(self.store)
        except FileNotFoundError:
            st = None
        if st is None or (st.st_dev, st.st_ino) != self.identity:
            raise StoreReplacedError(f"{self.store}: the store was removed or replaced; not writing chunk {chunk.index}")
        root = _open_roots.get((self.store, self.identity))
        with warnings.catch_warnings(), zarr.config.set({"array.write_empty_chunks": True}):
            warnings.simplefilter("ignore")
            try:
                if root is None:
                    root = _open_roots[(self.store, self.identity)] = _zarr_open(Path(self.store))
                for name, values in data.items():
                    root[name][chunk.start : chunk.stop] = values
            except OSError as exc:
                raise write_error(exc, Path(self.store), f"cannot write chunk {chunk.index}") from None


#: The writable root group of each store this process writes chunks into (opened once).
_open_roots: dict[tuple[str, tuple[int, int]], Any] = {}


class _Sink:
    """The parent's side of storing chunks: data (unless a worker already wrote it), then marker."""

    def __init__(self, store: Path, writer: ChunkRows) -> None:
        self.store = store
        self.writer = writer

    def put(self, chunk: ChunkSpec, result: Any) -> None:
        if isinstance(result, _Stored):
            if result.index != chunk.index or result.n_pings != chunk.n_pings:
                raise SonarmapError(f"chunk {chunk.index}: worker reported {result}")
        else:
            self.writer.write(chunk, result)
        _write_marker(self.store, chunk.index, chunk.start, chunk.stop)


def _zarr_open(path: Path) -> Any:
    """The store's root zarr group, writable."""
    import zarr

    return zarr.open_group(str(path), mode="r+", zarr_format=3, use_consolidated=False)


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


# ============================================================================ growing (live) stores
#: How long :func:`open_products` keeps trying while a live run is publishing a flush (s).
LIVE_SETTLE_S = 2.0

def _live_status(path: Path) -> str | None:
    """The root attribute ``live_status`` of a store written by a live run ("writing" while it
    appends, "complete" after); None for other stores."""
    attrs = read_root_attrs(path)
    v = None if attrs is None else attrs.get("live_status")
    return v if isinstance(v, str) else None


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
        from sonarmap.survey._chunk_writer import ChunkWriter
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
