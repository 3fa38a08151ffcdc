"""The survey dataset: pings as an xarray Dataset stored in zarr - the data model, in one place.

Layout (following echopype's conventions where one exists)::

    dimensions   ping_time, range_sample, beam  (+ xyz, quaternion for poses)
    intensity    (ping_time, range_sample, beam) float32 in [0, 1], chunked along ping_time
    echo_range   (ping_time, range_sample) float64, m      coordinate: range of each bin
    beam_azimuth (beam) float64, rad                       coordinate: positive to starboard;
                 (ping_time, beam) if the pings' azimuth tables differ (beam-steered multibeams)
    geometry_index (ping_time) int32                       index into attrs["sonarmap_geometries"]
    source_index   (ping_time) int32                       index into attrs["sonarmap_sources"]
    pose_position_m (ping_time, xyz), pose_orientation_xyzw (ping_time, quaternion)  NaN if none
    meta_<key>   (ping_time)  numeric per-ping metadata (heading, gain, ...), see below

The coordinate layout is the one of every sonarmap store (:mod:`sonarmap.datamodel`, shared with
the product store of :mod:`sonarmap.survey`); stores written before it (``beam_azimuth`` always
``(ping_time, beam)``) still read, and appends to them keep their layout.  Every store has
consolidated metadata, written when a writer is done and removed while one changes the store
(:func:`sonarmap.datamodel.consolidate`); the readers here never use it.
Every variable has CF ``units`` and ``long_name``; the dataset has ``Conventions = "CF-1.8"``.
``ping_time`` is stored as int64 nanoseconds since 1970-01-01 (exact).  Each distinct
:class:`~sonarmap.geometry.SonarGeometry` is stored once as JSON in ``sonarmap_geometries``, so
``dataset_to_pings`` rebuilds pings losslessly (image, geometry, time, pose and numeric metadata).
Numeric scalar entries of ``Ping.meta`` become ``meta_<key>`` variables (ints as int64 with
:data:`INT_MISSING` for "absent", floats/bools as float64 with NaN); the set of meta variables is
fixed by the first batch written; strings and arrays in ``meta`` are not stored.

A store holds pings of one image shape ``(n_bins, n_beams)``.  :class:`SurveyWriter` writes in
chunks of ``chunk_pings`` (bounded memory); a new store is written to a temporary directory and
moved into place on success (atomic).  Appending to an existing store (``mode="a"``) is done in
place; an interrupted append leaves arrays of unequal length, which :func:`open_survey` detects
(and repairs with ``repair=True``).  Per-ping products of later processing stages (e.g. ranges
with dims ``(ping_time, beam)``) are declared with :class:`PingVariable` and either written with
each ping (``SurveyWriter(extra_variables=...)``) or added to an existing store with
:func:`add_ping_variable` + :func:`write_ping_variable` (region writes, resumable).

Integrity.  Every chunk is written with a CRC32C checksum (zarr's ``crc32c`` codec after
``zstd``) and every chunk is written, even one equal to the fill value; stores written before
(no checksum) still read.  Reading parses every metadata document first (one
:class:`~sonarmap.errors.DataFormatError` naming the file for a corrupt or missing one), requires
the arrays of the data model, and checks values as they are read: intensities in [0, 1], times
int64 ns in [0, 2**63 - 1], indices inside their tables; a corrupt or missing chunk is an error
naming the array and chunk.  A writer holds an exclusive lock on its store
(:class:`sonarmap._atomic.WriterLock`): a second writer fails at once, naming the first's pid.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
import struct
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap import __version__
from sonarmap._atomic import WriterLock, write_error
from sonarmap.datamodel import (
    COORD_ATTRS,
    COORD_AZIMUTH,
    COORD_RANGE,
    DIM_BEAM,
    DIM_PING,
    DIM_QUAT,
    DIM_RANGE,
    DIM_XYZ,
    VAR_INTENSITY,
    azimuth_dims,
    consolidate,
    invalidate_consolidated,
)
from sonarmap.errors import DataFormatError, InputError, SonarmapError
from sonarmap.geometry import SonarGeometry, geometry_from_dict
from sonarmap._files import MAX_SIDECAR_BYTES, read_bytes_bounded, require_regular_file
from sonarmap.ping import Ping, Pose

if TYPE_CHECKING:  # pragma: no cover
    import xarray as xr

__all__ = [
    "DIM_PING",
    "DIM_RANGE",
    "DIM_BEAM",
    "VAR_INTENSITY",
    "COORD_RANGE",
    "COORD_AZIMUTH",
    "DATA_MODEL_VERSION",
    "INT_MISSING",
    "PingVariable",
    "SurveyWriter",
    "pings_to_dataset",
    "dataset_to_pings",
    "write_survey",
    "open_survey",
    "add_ping_variable",
    "write_ping_variable",
    "survey_geometries",
    "CheckedStore",
    "TIME_UNITS_RE",
    "inspect_store",
    "kind_of",
    "read_array",
    "check_times",
    "check_chunk_files",
    "locate_error",
]

VAR_GEOMETRY = "geometry_index"
VAR_SOURCE = "source_index"
VAR_POSITION = "pose_position_m"
VAR_ORIENTATION = "pose_orientation_xyzw"
META_PREFIX = "meta_"
DATA_MODEL_VERSION = 1
#: Stored in int64 ``meta_*`` variables for pings that lack the key.
INT_MISSING = np.iinfo(np.int64).min
ATTR_GEOMETRIES = "sonarmap_geometries"
ATTR_SOURCES = "sonarmap_sources"
ATTR_POSE_FRAME = "sonarmap_pose_frame"
ATTR_MODEL = "sonarmap_data_model"

#: CF attributes of the core variables (the single definition used by writer and docs).
ATTRS: dict[str, dict[str, str]] = {
    **COORD_ATTRS,
    VAR_INTENSITY: {
        "long_name": "Received echo intensity, sensor counts scaled to [0, 1]",
        "units": "1",
        "valid_min": "0",
        "valid_max": "1",
    },
    VAR_GEOMETRY: {"long_name": f"Index into the {ATTR_GEOMETRIES} attribute", "units": "1"},
    VAR_SOURCE: {"long_name": f"Index into the {ATTR_SOURCES} attribute", "units": "1"},
    VAR_POSITION: {"long_name": "Vehicle position in the world frame (NaN if unknown)", "units": "m"},
    VAR_ORIENTATION: {
        "long_name": "Vehicle orientation quaternion x, y, z, w (NaN if unknown)",
        "units": "1",
    },
}


@dataclasses.dataclass(frozen=True)
class PingVariable:
    """Declaration of an extra per-ping variable (a processing product) in a survey store.

    Parameters
    ----------
    name : str
        Variable name, e.g. ``"first_return_range_m"``.
    dims : tuple of str
        Dimensions after ``ping_time``, e.g. ``("beam",)`` for per-beam ranges; ``()`` for scalars.
    dtype : str
        Storage dtype (``"float32"``, ``"float64"``, ``"int32"``, ``"uint8"``, ``"bool"`` ...).
    units, long_name : str
        CF attributes.
    fill_value : float
        Value of pings not (yet) written: NaN for floats; give one for integer dtypes.
    """

    name: str
    dims: tuple[str, ...] = ()
    dtype: str = "float32"
    units: str = "1"
    long_name: str = ""
    fill_value: float = math.nan

    def __post_init__(self) -> None:
        if not self.name.isidentifier():
            raise InputError(f"PingVariable name {self.name!r} is not an identifier")
        object.__setattr__(self, "dims", tuple(self.dims))

    def attrs(self) -> dict[str, str]:
        """CF attributes (plus the fill value, so appends can fill pings without a value)."""
        return {
            "units": self.units,
            "long_name": self.long_name or self.name,
            "sonarmap_fill_value": repr(float(self.fill_value)),
        }


# ---------------------------------------------------------------------- helpers
def _meta_kind(v: Any) -> str | None:
    if isinstance(v, bool | np.bool_):
        return "bool"
    if isinstance(v, int | np.integer):
        return "int" if np.iinfo(np.int64).min < int(v) <= np.iinfo(np.int64).max else None
    if isinstance(v, float | np.floating):
        return "float"
    return None


def _geometry_json(g: SonarGeometry) -> str:
    d = g.to_dict()
    d["azimuth_source"] = g.azimuth_source
    return json.dumps(d, sort_keys=True)


def _geometry_from_json(s: str) -> SonarGeometry:
    d = json.loads(s)
    src = d.pop("azimuth_source", "table")
    g = geometry_from_dict(d, source="survey geometry")
    return g if g.azimuth_source == src else dataclasses.replace(g, azimuth_source=src)


@dataclasses.dataclass
class _State:
    """What a store's attributes say: geometries, sources, meta variables and their kinds."""

    geometries: list[str] = dataclasses.field(default_factory=list)
    sources: list[str] = dataclasses.field(default_factory=list)
    meta: dict[str, str] = dataclasses.field(default_factory=dict)  # key -> kind
    shape: tuple[int, int] | None = None
    pose_frame: str = ""
    extras: dict[str, PingVariable] = dataclasses.field(default_factory=dict)
    #: The store's azimuth table (``beam_azimuth (beam)``), set by the first ping written.
    azimuth: NDArray[np.float64] | None = None
    #: ``beam_azimuth`` is ``(ping_time, beam)``: the pings' tables differ (or an old store).
    azimuth_per_ping: bool = False

    def azimuth_differs(self, pings: Sequence[Ping]) -> bool:
        """Whether a ping of ``pings`` has another azimuth table than the store's (1-D layout only)."""
        if self.azimuth_per_ping:
            return False
        ref = self.azimuth if self.azimuth is not None else pings[0].geometry.azimuth_rad
        return any(not np.array_equal(p.geometry.azimuth_rad, ref) for p in pings)

    def geometry_index(self, g: SonarGeometry, cache: dict[int, int]) -> int:
        gid = id(g)
        if gid in cache:
            return cache[gid]
        s = _geometry_json(g)
        try:
            idx = self.geometries.index(s)
        except ValueError:
            self.geometries.append(s)
            idx = len(self.geometries) - 1
        cache[gid] = idx
        return idx

    def source_index(self, source: str) -> int:
        src = source.split("#", 1)[0]
        if self.sources and self.sources[-1] == src:
            return len(self.sources) - 1
        try:
            return self.sources.index(src)
        except ValueError:
            self.sources.append(src)
            return len(self.sources) - 1


def pings_to_dataset(
    pings: Iterable[Ping],
    *,
    extras: Mapping[str, Sequence[ArrayLike]] | None = None,
    extra_variables: Sequence[PingVariable] = (),
    _state: _State | None = None,
) -> xr.Dataset:
    """Build an in-memory survey Dataset from pings (all of one image shape).

    Parameters
    ----------
    pings : iterable of Ping
    extras : mapping name -> per-ping values, optional
        Values of ``extra_variables`` for each ping (same order as ``pings``).
    extra_variables : sequence of PingVariable
        Declarations of the extra variables.

    Raises
    ------
    InputError
        If there are no pings, or their image shapes differ.
    """
    import xarray as xr

    plist = list(pings)
    if not plist:
        raise InputError("pings: need at least one ping to build a dataset")
    state = _state if _state is not None else _State()
    shape = state.shape or plist[0].shape
    state.shape = shape
    _check_shapes(plist, shape)
    _record_layout(state, plist)
    n = len(plist)
    arrays = _stack_pings(plist, shape, state)
    data_vars: dict[str, Any] = {
        VAR_INTENSITY: ((DIM_PING, DIM_RANGE, DIM_BEAM), arrays.intensity, ATTRS[VAR_INTENSITY]),
        VAR_GEOMETRY: ((DIM_PING,), arrays.geometry_index, ATTRS[VAR_GEOMETRY]),
        VAR_SOURCE: ((DIM_PING,), arrays.source_index, ATTRS[VAR_SOURCE]),
        VAR_POSITION: ((DIM_PING, DIM_XYZ), arrays.position, ATTRS[VAR_POSITION]),
        VAR_ORIENTATION: ((DIM_PING, DIM_QUAT), arrays.orientation, ATTRS[VAR_ORIENTATION]),
    }
    for key, kind in state.meta.items():
        data_vars[f"{META_PREFIX}{key}"] = _meta_variable(plist, key, kind)
    extras = extras or {}
    for var in extra_variables:
        state.extras[var.name] = var
        data_vars[var.name] = _extra_variable(var, extras.get(var.name), n, shape)
    coords = {
        DIM_PING: (DIM_PING, arrays.time_ns.astype("datetime64[ns]"), ATTRS[DIM_PING]),
        DIM_RANGE: (DIM_RANGE, np.arange(shape[0], dtype=np.int32), ATTRS[DIM_RANGE]),
        DIM_BEAM: (DIM_BEAM, np.arange(shape[1], dtype=np.int32), ATTRS[DIM_BEAM]),
        COORD_RANGE: ((DIM_PING, DIM_RANGE), arrays.range_m, ATTRS[COORD_RANGE]),
        COORD_AZIMUTH: (azimuth_dims(state.azimuth_per_ping),
                        arrays.azimuth if state.azimuth_per_ping else state.azimuth, ATTRS[COORD_AZIMUTH]),
    }
    ds = xr.Dataset(data_vars=data_vars, coords=coords)
    ds.attrs.update(_global_attrs(state))
    return ds


def _check_shapes(plist: Sequence[Ping], shape: tuple[int, int]) -> None:
    """Raise :class:`InputError` naming the first ping whose image shape is not the survey's ``shape``."""
    for p in plist:
        if p.shape != shape:
            raise InputError(
                f"{p.source or 'ping'}: image shape {p.shape} differs from the survey's {shape}; "
                "write pings of different shapes to separate stores"
            )


def _record_layout(state: _State, plist: Sequence[Ping]) -> None:
    """Record in ``state`` what the first pings written fix: the meta variables and their kinds, the
    azimuth table and its layout (per ping once the tables differ) and the pose frame."""
    if not state.meta:
        for p in plist:
            for k, v in p.meta.items():
                kind = _meta_kind(v)
                if kind and f"{META_PREFIX}{k}".isidentifier():
                    state.meta.setdefault(k, kind)
    if state.azimuth_differs(plist):
        state.azimuth_per_ping = True
    if state.azimuth is None:
        state.azimuth = np.asarray(plist[0].geometry.azimuth_rad, dtype=np.float64)
    frames = {p.pose.frame for p in plist if p.pose is not None}
    if frames:
        state.pose_frame = state.pose_frame or sorted(frames)[0]


@dataclasses.dataclass(frozen=True)
class _PingArrays:
    """The per-ping arrays of a batch of pings, stacked along ``ping_time``."""

    intensity: NDArray[np.float32]
    range_m: NDArray[np.float64]
    azimuth: NDArray[np.float64]
    geometry_index: NDArray[np.int32]
    source_index: NDArray[np.int32]
    time_ns: NDArray[np.int64]
    position: NDArray[np.float64]
    orientation: NDArray[np.float64]


def _stack_pings(plist: Sequence[Ping], shape: tuple[int, int], state: _State) -> _PingArrays:
    """Stack the images, range and azimuth tables, times and poses (NaN if none) of ``plist``;
    new geometries and sources are appended to ``state``'s tables."""
    n = len(plist)
    intensity = np.empty((n, *shape), dtype=np.float32)
    rng = np.empty((n, shape[0]), dtype=np.float64)
    az = np.empty((n, shape[1]), dtype=np.float64)
    gidx = np.empty(n, dtype=np.int32)
    sidx = np.empty(n, dtype=np.int32)
    times = np.empty(n, dtype=np.int64)
    pos = np.full((n, 3), np.nan)
    quat = np.full((n, 4), np.nan)
    cache: dict[int, int] = {}
    for i, p in enumerate(plist):
        intensity[i] = p.image
        rng[i] = p.geometry.range_m
        az[i] = p.geometry.azimuth_rad
        gidx[i] = state.geometry_index(p.geometry, cache)
        sidx[i] = state.source_index(p.source)
        times[i] = p.time_ns
        if p.pose is not None:
            pos[i] = p.pose.position_m
            quat[i] = p.pose.orientation_xyzw
    return _PingArrays(intensity, rng, az, gidx, sidx, times, pos, quat)


def _meta_variable(
    plist: Sequence[Ping], key: str, kind: str
) -> tuple[tuple[str, ...], NDArray[Any], dict[str, str]]:
    """The ``meta_<key>`` variable of ``plist``: int64 with :data:`INT_MISSING`, or float64 with NaN,
    for the pings without a (fitting) value."""
    if kind == "int":
        arr = np.full(len(plist), INT_MISSING, dtype=np.int64)
    else:
        arr = np.full(len(plist), np.nan, dtype=np.float64)
    for i, p in enumerate(plist):
        v = p.meta.get(key)
        if v is not None and _meta_kind(v) is not None:
            if kind == "int":
                if _meta_kind(v) == "int":
                    arr[i] = int(v)
            else:
                arr[i] = float(v)
    attrs = {"long_name": f"Ping.meta['{key}']", "units": _meta_units(key), "sonarmap_kind": kind}
    if kind == "int":
        attrs["sonarmap_missing"] = str(INT_MISSING)
    return (DIM_PING,), arr, attrs


def _extra_variable(
    var: PingVariable, vals: Sequence[ArrayLike] | None, n: int, shape: tuple[int, int]
) -> tuple[tuple[str, ...], NDArray[Any], dict[str, str]]:
    """The declared extra variable ``var`` of ``n`` pings: ``vals`` (checked to fit), or its fill value."""
    if vals is None:
        arr = np.full((n, *_extra_shape(var, shape)), var.fill_value, dtype=var.dtype)
    else:
        arr = np.asarray(list(vals), dtype=var.dtype)
        want = (n, *_extra_shape(var, shape))
        if arr.shape != want:
            raise InputError(f"extra variable {var.name}: shape {arr.shape}, expected {want}")
    return (DIM_PING, *var.dims), arr, var.attrs()


def _extra_shape(var: PingVariable, shape: tuple[int, int]) -> tuple[int, ...]:
    sizes = {DIM_RANGE: shape[0], DIM_BEAM: shape[1], DIM_XYZ: 3, DIM_QUAT: 4}
    try:
        return tuple(sizes[d] for d in var.dims)
    except KeyError as exc:
        raise InputError(
            f"extra variable {var.name}: unknown dimension {exc}; use {DIM_RANGE} or {DIM_BEAM}"
        ) from None


def _meta_units(key: str) -> str:
    for suffix, units in (("_deg", "degree"), ("_m_s", "m s-1"), ("_m", "m"), ("_db", "dB"),
                          ("_c", "degree_Celsius"), ("_ns", "ns"), ("_us", "us"), ("_hz", "Hz"),
                          ("_bar", "bar"), ("_s", "s")):
        if key.endswith(suffix):
            return units
    return "1"


def _global_attrs(state: _State) -> dict[str, Any]:
    return {
        "Conventions": "CF-1.8",
        "title": "sonarmap multibeam imaging-sonar survey",
        "source": f"sonarmap {__version__}",
        ATTR_MODEL: DATA_MODEL_VERSION,
        ATTR_GEOMETRIES: json.dumps(state.geometries),
        ATTR_SOURCES: json.dumps(state.sources),
        ATTR_POSE_FRAME: state.pose_frame,
    }


def checksum_codecs() -> dict[str, Any]:
    """Bytes-to-bytes codecs of every array this version writes: zstd, then a CRC32C checksum.

    The ``crc32c`` codec appends the 4-byte little-endian CRC32C of the compressed chunk, so any
    corruption of a chunk file (a flipped bit, a truncated or overwritten file) is detected when
    the chunk is read instead of decoding to wrong values.
    """
    from zarr.codecs import Crc32cCodec, ZstdCodec

    return {"compressors": (ZstdCodec(level=0, checksum=False), Crc32cCodec())}


def _encoding(ds: xr.Dataset, chunk_pings: int) -> dict[str, dict[str, Any]]:
    enc: dict[str, dict[str, Any]] = {
        DIM_PING: {"units": "nanoseconds since 1970-01-01", "dtype": "int64", "chunks": (max(chunk_pings, 1024),),
                   **checksum_codecs()},
        DIM_RANGE: checksum_codecs(),
        DIM_BEAM: checksum_codecs(),
    }
    for name, var in ds.variables.items():
        if name in (DIM_PING, DIM_RANGE, DIM_BEAM):
            continue
        e: dict[str, Any] = dict(checksum_codecs())
        if var.dims and var.dims[0] == DIM_PING:
            e["chunks"] = (chunk_pings, *var.shape[1:])
            if var.dtype.kind in "iub" and name.startswith(META_PREFIX):
                e["fill_value"] = None
        enc[str(name)] = e
    return enc


#: Latest ping time a store holds (int64 nanoseconds since 1970: 2262-04-11).
TIME_MAX_NS = int(np.iinfo(np.int64).max)


def _check_ping_for_store(ping: Ping) -> None:
    """A ping a survey store can hold: time in [0, TIME_MAX_NS] ns, intensities in [0, 1]."""
    who = ping.source or "ping"
    if not 0 <= int(ping.time_ns) <= TIME_MAX_NS:
        raise InputError(
            f"{who}: ping time {int(ping.time_ns)} ns is outside what a survey store holds "
            f"(0 to {TIME_MAX_NS} ns since 1970, i.e. 1970-2262)"
        )
    img = ping.image
    if img.size and not (float(img.min()) >= 0.0 and float(img.max()) <= 1.0):
        raise InputError(
            f"{who}: intensities span [{float(img.min()):.6g}, {float(img.max()):.6g}]; a survey store "
            "holds raw intensities in [0, 1]"
        )


# ---------------------------------------------------------------------- writing
class SurveyWriter:
    """Write pings to a zarr survey store in chunks along ``ping_time``.

    Parameters
    ----------
    path : path-like
        The store (a directory, conventionally ``*.zarr``).
    mode : {"w", "a"}
        ``"w"``: create (replacing an existing store) atomically on :meth:`close`;
        ``"a"``: append to an existing store in place (created if missing).
    chunk_pings : int
        Pings per chunk (and per write); memory holds at most one chunk.
    extra_variables : sequence of PingVariable
        Extra per-ping variables given to :meth:`add`.

    Use as a context manager; on an exception a new store is discarded (an existing one is left
    untouched in ``"w"`` mode).  The writer holds an exclusive lock on the store
    (:class:`sonarmap._atomic.WriterLock`) from construction to :meth:`close` / :meth:`abort`;
    temporary directories of earlier writers that were killed are removed when it is taken.
    Every chunk is written with a CRC32C checksum (:func:`checksum_codecs`).

    Raises
    ------
    DataFormatError
        If another writer holds the store, or it cannot be written (the message names it).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        mode: str = "w",
        chunk_pings: int = 16,
        extra_variables: Sequence[PingVariable] = (),
    ) -> None:
        if mode not in ("w", "a"):
            raise InputError(f"mode must be 'w' or 'a', got {mode!r}")
        if int(chunk_pings) < 1:
            raise InputError(f"chunk_pings must be >= 1, got {chunk_pings}")
        self.path = Path(path)
        self.chunk_pings = int(chunk_pings)
        self.extra_variables = tuple(extra_variables)
        self._buffer: list[Ping] = []
        self._extras: dict[str, list[Any]] = {v.name: [] for v in self.extra_variables}
        self._state = _State()
        self._written = 0
        self._closed = False
        self._tmp: Path | None = None
        self._invalidated = False
        self._lock = WriterLock(self.path).acquire()
        try:
            remove_stale_store_temporaries(self.path)
            self._append = mode == "a" and _is_store(self.path)
            if self._append:
                self._target = self.path
                self._state = _read_state(self.path)
                self._written = _n_pings(self.path)
            else:
                try:
                    self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".tmp",
                                                      dir=self.path.parent))
                except OSError as exc:
                    raise write_error(exc, self.path, "cannot create the store") from None
                self._target = self._tmp / "store.zarr"
        except BaseException:
            self._lock.release()
            raise

    @property
    def n_written(self) -> int:
        """Pings written to the store so far (excluding the buffer)."""
        return self._written

    def add(self, ping: Ping, **extras: Any) -> None:
        """Buffer one ping (and its extra-variable values); writes a chunk when the buffer is full.

        Raises
        ------
        InputError
            If the writer is closed, an extra variable is undeclared, or the ping cannot be stored
            (time outside 1970-2262, intensities outside [0, 1]).
        """
        if self._closed:
            raise InputError("SurveyWriter is closed")
        unknown = set(extras) - set(self._extras)
        if unknown:
            raise InputError(f"undeclared extra variables: {', '.join(sorted(unknown))}")
        _check_ping_for_store(ping)
        self._buffer.append(ping)
        for name, values in self._extras.items():
            var = next(v for v in self.extra_variables if v.name == name)
            values.append(extras.get(name, np.full(_extra_shape(var, ping.shape), var.fill_value)))
        if len(self._buffer) >= self.chunk_pings:
            self.flush()

    def write(self, pings: Iterable[Ping], progress: Callable[[int], None] | None = None) -> int:
        """Add every ping of ``pings``; ``progress(n)`` is called after each one. Returns the count."""
        n = 0
        for p in pings:
            self.add(p)
            n += 1
            if progress is not None:
                progress(1)
        return n

    def flush(self) -> None:
        """Write the buffered pings as one chunk.

        Raises
        ------
        DataFormatError
            If the store cannot be written (disk full ...); the message names the store.
        """
        if not self._buffer:
            return
        declared = {v.name for v in self.extra_variables}
        stored = [v for name, v in self._state.extras.items() if name not in declared]
        per_ping_before = self._state.azimuth_per_ping
        ds = pings_to_dataset(
            self._buffer,
            extras=self._extras,
            extra_variables=(*self.extra_variables, *stored),  # undeclared: fill values
            _state=self._state,
        )
        try:
            if self._written == 0 and not self._append:
                ds.to_zarr(self._target, mode="w", encoding=_encoding(ds, self.chunk_pings), consolidated=False,
                           write_empty_chunks=True)
            else:
                if self._append and not self._invalidated:
                    # First change of an existing store: until close() re-consolidates, readers
                    # that trust consolidated metadata fall back to the arrays' own.
                    invalidate_consolidated(self._target)
                    self._invalidated = True
                if self._state.azimuth_per_ping and not per_ping_before:
                    _azimuth_per_ping(self._target, self._written, self.chunk_pings)
                _check_append_compatible(self._target, ds)
                ds.to_zarr(self._target, append_dim=DIM_PING, consolidated=False, write_empty_chunks=True)
                _update_attrs(self._target, _global_attrs(self._state))
        except SonarmapError:
            raise
        except OSError as exc:
            raise write_error(exc, self.path, "cannot write the store") from None
        self._written += len(self._buffer)
        self._buffer.clear()
        for v in self._extras.values():
            v.clear()

    def close(self) -> None:
        """Flush and, for a new store, move it into place atomically; releases the store's lock."""
        if self._closed:
            return
        try:
            self.flush()
            self._closed = True
            if self._tmp is None:
                if self._written:
                    consolidate(self._target)
                return
            if self._written == 0:
                shutil.rmtree(self._tmp, ignore_errors=True)
                raise InputError(f"{self.path}: no pings to write")
            consolidate(self._target)
            try:
                _replace_dir(self._target, self.path)
            except OSError as exc:
                raise write_error(exc, self.path, "cannot move the new store into place") from None
            shutil.rmtree(self._tmp, ignore_errors=True)
        finally:
            if self._closed:
                self._lock.release()

    def abort(self) -> None:
        """Discard a new store (no effect on appends already written); releases the store's lock."""
        self._closed = True
        try:
            if self._tmp is not None:
                shutil.rmtree(self._tmp, ignore_errors=True)
            elif self._append and self._invalidated:
                _consolidate_if_whole(self._target)
        finally:
            self._lock.release()

    def __enter__(self) -> SurveyWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            try:
                self.close()
            except BaseException:
                self.abort()
                raise
        else:
            self.abort()


def _replace_dir(src: Path, dst: Path) -> None:
    """Move directory ``src`` onto ``dst`` (replacing it) with renames only."""
    if dst.exists():
        trash = dst.with_name(f".{dst.name}.old-{os.getpid()}")
        if trash.exists():
            shutil.rmtree(trash)
        os.replace(dst, trash)
        try:
            os.replace(src, dst)
        except BaseException:
            os.replace(trash, dst)
            raise
        shutil.rmtree(trash, ignore_errors=True)
    else:
        os.replace(src, dst)


def remove_stale_store_temporaries(path: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporary directories that killed writers of store ``path`` left beside it.

    Call only while holding the store's :class:`~sonarmap._atomic.WriterLock`: no other writer of
    ``path`` then runs, so every ``.{name}.<random>.tmp`` / ``.old`` / ``.old-<pid>`` directory
    beside it (new stores being built, replaced stores being deleted) is left over.

    Returns
    -------
    list of Path
        The directories removed.
    """
    p = Path(os.path.abspath(path))
    pattern = re.compile(rf"\.{re.escape(p.name)}\.(?:[a-z0-9_]{{8}}\.(?:tmp|old)|old-\d+)")
    try:
        names = os.listdir(p.parent)
    except OSError:
        return []
    removed = []
    for name in names:
        d = p.parent / name
        if pattern.fullmatch(name) and d.is_dir() and not d.is_symlink():
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
    return removed


def _update_attrs(path: Path, attrs: Mapping[str, Any]) -> None:
    import zarr

    zarr.open_group(str(path), mode="r+", use_consolidated=False).attrs.update(dict(attrs))


def _consolidate_if_whole(path: Path) -> None:
    """Consolidate the metadata of a store whose arrays along ``ping_time`` agree in length.

    An interrupted append (arrays of different lengths) is left without consolidated metadata:
    :func:`open_survey` reports (and repairs) it from the arrays' own metadata.
    """
    try:
        lengths = _ping_lengths(_inspect_survey(path))
    except DataFormatError:
        return
    if len(set(lengths.values())) <= 1:
        consolidate(path)


def _azimuth_per_ping(path: Path, n: int, chunk_pings: int) -> None:
    """Turn a store's ``beam_azimuth (beam)`` into ``(ping_time, beam)`` for its ``n`` pings.

    Called when a ping with another azimuth table than the store's is written: the pings already
    stored all have the store's table, so each of their rows is that table.
    """
    import zarr

    g = zarr.open_group(str(path), mode="r+", use_consolidated=False)
    old = g[COORD_AZIMUTH]
    if _dims(old) != (DIM_BEAM,):
        return
    table = np.asarray(old[...], dtype=np.float64)
    attrs = dict(old.attrs)
    del g[COORD_AZIMUTH]
    arr = g.create_array(COORD_AZIMUTH, shape=(n, table.size), chunks=(chunk_pings, table.size), dtype=np.float64,
                         fill_value=np.nan, dimension_names=(DIM_PING, DIM_BEAM), attributes=attrs,
                         **checksum_codecs(), config={"write_empty_chunks": True})
    if n:
        arr[...] = np.broadcast_to(table, (n, table.size))


def _check_append_compatible(path: Path, ds: xr.Dataset) -> None:
    st = inspect_store(path)
    if VAR_INTENSITY in st.arrays:
        have = tuple(st.arrays[VAR_INTENSITY].shape[1:])
        want = tuple(ds[VAR_INTENSITY].shape[1:])
        if have != want:
            raise InputError(
                f"{path}: store holds images of shape {have}, cannot append shape {want}"
            )
    missing = [v for v in st.arrays if v not in ds.variables and v not in (DIM_RANGE, DIM_BEAM)]
    if missing:
        raise InputError(f"{path}: appended pings lack variables {', '.join(sorted(missing))}")


def write_survey(
    pings: Iterable[Ping],
    path: str | os.PathLike[str],
    *,
    append: bool = False,
    chunk_pings: int = 16,
    progress: Callable[[int], None] | None = None,
) -> int:
    """Write pings to a zarr survey store; returns the number written.

    A new store is written atomically (temporary directory + rename); ``append=True`` adds to an
    existing store in chunks.  Memory holds one chunk of ``chunk_pings`` pings.
    """
    with SurveyWriter(path, mode="a" if append else "w", chunk_pings=chunk_pings) as w:
        return w.write(pings, progress)


# ---------------------------------------------------------------------- reading: metadata
def _is_store(path: Path) -> bool:
    return path.is_dir() and ((path / "zarr.json").exists() or (path / ".zgroup").exists())


def _one_line(exc: BaseException, limit: int = 200) -> str:
    """An exception's message on one line, at most ``limit`` characters."""
    msg = " ".join(str(exc).split()) or type(exc).__name__
    return msg if len(msg) <= limit else msg[: limit - 3] + "..."


def _read_json_doc(path: Path, what: str, *, required: bool = True) -> dict[str, Any] | None:
    """A zarr metadata document (JSON object), or ``None`` if absent and not ``required``.

    Raises
    ------
    DataFormatError
        Naming the file, if it is missing (and required), not a regular file, too large, not
        UTF-8, not JSON, or not a JSON object.
    """
    if not required and not os.path.lexists(path):
        return None
    data = read_bytes_bounded(path, MAX_SIDECAR_BYTES, what)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DataFormatError(f"{what} is not valid UTF-8 (byte {exc.start})", path) from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataFormatError(f"{what} is not valid JSON ({exc.msg}; line {exc.lineno} column {exc.colno})",
                              path) from None
    except (ValueError, RecursionError) as exc:
        raise DataFormatError(f"{what} is not valid JSON ({_one_line(exc)})", path) from None
    if not isinstance(doc, dict):
        raise DataFormatError(f"{what} is a JSON {type(doc).__name__}, expected an object", path)
    return doc


def _check_array_doc(doc: Mapping[str, Any], fmt: int, path: Path) -> None:
    """Types of the keys of an array's metadata that zarr would otherwise trip over."""

    def bad(key: str, want: str) -> DataFormatError:
        return DataFormatError(f"array metadata: '{key}' is {doc.get(key)!r:.60}, expected {want}", path)

    shape = doc.get("shape")
    if not isinstance(shape, list) or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0
                                              for s in shape):
        raise bad("shape", "a list of non-negative integers")
    if fmt == 3:
        if doc.get("zarr_format") != 3 or doc.get("node_type") != "array":
            raise DataFormatError("array metadata: not a zarr v3 array (zarr_format/node_type)", path)
        if "attributes" in doc and not isinstance(doc["attributes"], dict):
            raise bad("attributes", "an object")
        if not isinstance(doc.get("codecs"), list) or not doc["codecs"]:
            raise bad("codecs", "a non-empty list")
        names = doc.get("dimension_names")
        if names is not None and (not isinstance(names, list) or len(names) != len(shape)
                                  or not all(n is None or isinstance(n, str) for n in names)):
            raise bad("dimension_names", f"a list of {len(shape)} names")
    else:
        if doc.get("zarr_format") != 2:
            raise DataFormatError("array metadata: not a zarr v2 array (zarr_format)", path)
        chunks = doc.get("chunks")
        if not isinstance(chunks, list) or len(chunks) != len(shape) or not all(
            isinstance(c, int) and not isinstance(c, bool) and c > 0 for c in chunks
        ):
            raise bad("chunks", f"a list of {len(shape)} positive integers")


@dataclasses.dataclass
class CheckedStore:
    """A zarr store whose metadata documents were all parsed and checked (:func:`inspect_store`).

    Attributes
    ----------
    path : Path
        The store directory.
    zarr_format : int
        2 or 3.
    group : zarr.Group
        The root group, read-only.
    attrs : dict
        Root attributes.
    arrays : dict of str to zarr.Array
        Every array of the root group, opened.
    files : dict
        Per array, its checked chunk files (key -> size), filled by :func:`_chunk_files`.
    """

    path: Path
    zarr_format: int
    group: Any
    attrs: dict[str, Any]
    arrays: dict[str, Any]
    files: dict[str, dict[str, int]] = dataclasses.field(default_factory=dict)

    def meta_file(self, name: str | None = None) -> Path:
        """The metadata file of array ``name`` (of the group if ``None``)."""
        base = self.path if name is None else self.path / name
        if self.zarr_format == 3:
            return base / "zarr.json"
        return base / (".zgroup" if name is None else ".zarray")

    def require(self, name: str, *, ndim: int | None = None, kinds: str | None = None,
                what: str = "survey store") -> Any:
        """Array ``name``; a :class:`DataFormatError` if it is missing or of another rank / dtype kind."""
        arr = self.arrays.get(name)
        if arr is None:
            where = f"{name}/ has no array metadata" if (self.path / name).is_dir() else "deleted?"
            raise DataFormatError(f"required array '{name}' is missing ({where}); not a readable {what}",
                                  self.path)
        if ndim is not None and len(arr.shape) != ndim:
            raise DataFormatError(f"array '{name}' has {len(arr.shape)} dimensions, expected {ndim}",
                                  self.meta_file(name))
        if kinds is not None and kind_of(arr) not in kinds:
            raise DataFormatError(f"array '{name}' has data type {arr.dtype}, expected "
                                  f"{_KIND_NAMES.get(kinds, kinds)}", self.meta_file(name))
        return arr

    def dims(self, name: str) -> tuple[str, ...]:
        """Dimension names of array ``name`` (checked when the store was inspected)."""
        return _dims(self.arrays[name])

    def checksummed(self, name: str) -> bool:
        """Whether the chunks of array ``name`` carry a CRC32C checksum (written by this version)."""
        arr = self.arrays[name]
        if self.zarr_format != 3:
            return False
        codecs = getattr(arr.metadata, "codecs", ()) or ()
        return any(getattr(c, "to_dict", lambda: {})().get("name") == "crc32c" for c in codecs)


_KIND_NAMES = {"f": "floating point", "i": "signed integer", "iu": "integer", "iub": "integer or boolean",
               "biuf": "numeric", "T": "string"}


def kind_of(arr: Any) -> str:
    """numpy dtype kind of a zarr array (``"T"`` for zarr's variable-length strings)."""
    try:
        k = np.dtype(arr.dtype).kind
    except TypeError:
        return "T"
    return "T" if k in "OUST" else k


def _dims(arr: Any) -> tuple[str, ...]:
    """Dimension names of a zarr array written by xarray (v3 metadata or v2 attribute)."""
    dims = getattr(arr.metadata, "dimension_names", None)
    if dims is None:
        dims = arr.attrs.get("_ARRAY_DIMENSIONS")
    if dims is None:
        return ()
    if not isinstance(dims, list | tuple) or not all(isinstance(d, str) for d in dims):
        raise DataFormatError(f"dimension names {dims!r:.60} are not a list of names")
    return tuple(dims)


def inspect_store(path: Path) -> CheckedStore:
    """Parse and check every metadata document of a zarr store and open each of its arrays.

    Every failure is one :class:`DataFormatError` naming the metadata file (``zarr.json``,
    ``.zgroup``, ``.zarray`` or ``.zattrs``) - never a foreign exception.
    """
    import zarr

    path = Path(path)
    if not _is_store(path):
        raise DataFormatError("not a zarr survey store (no zarr.json/.zgroup)", path)
    fmt = 3 if (path / "zarr.json").exists() else 2
    if fmt == 3:
        root = _read_json_doc(path / "zarr.json", "group metadata")
        assert root is not None
        if root.get("zarr_format") != 3 or root.get("node_type") != "group":
            raise DataFormatError("group metadata: not a zarr v3 group (zarr_format/node_type)", path / "zarr.json")
        if "attributes" in root and not isinstance(root["attributes"], dict):
            raise DataFormatError("group metadata: 'attributes' is not an object", path / "zarr.json")
    else:
        root = _read_json_doc(path / ".zgroup", "group metadata")
        assert root is not None
        if root.get("zarr_format") != 2:
            raise DataFormatError("group metadata: not a zarr v2 group (zarr_format)", path / ".zgroup")
        _read_json_doc(path / ".zattrs", "group attributes", required=False)
    names = []
    try:
        entries = sorted(os.listdir(path))
    except OSError as exc:
        raise DataFormatError(f"cannot list the store: {exc.strerror or exc}", path) from None
    for name in entries:
        d = path / name
        if name.startswith(".") or not d.is_dir():
            continue
        if fmt == 3:
            meta = d / "zarr.json"
            if not os.path.lexists(meta):
                continue
            doc = _read_json_doc(meta, "array metadata")
            assert doc is not None
            if doc.get("node_type") == "group":
                continue
            _check_array_doc(doc, 3, meta)
        else:
            meta = d / ".zarray"
            if not os.path.lexists(meta):
                continue
            doc = _read_json_doc(meta, "array metadata")
            assert doc is not None
            _check_array_doc(doc, 2, meta)
            _read_json_doc(d / ".zattrs", "array attributes", required=False)
        names.append(name)
    try:
        # never the consolidated copy: every array's own (checked) metadata is what is read
        group = zarr.open_group(str(path), mode="r", zarr_format=fmt, use_consolidated=False)
        attrs = dict(group.attrs)
    except Exception as exc:  # noqa: BLE001 - zarr raises many types on corrupt metadata
        raise DataFormatError(f"group metadata: {_one_line(exc)}", path / ("zarr.json" if fmt == 3 else ".zgroup")) from None
    arrays: dict[str, Any] = {}
    for name in names:
        meta = path / name / ("zarr.json" if fmt == 3 else ".zarray")
        try:
            arr = group[name]
            _ = arr.dtype, arr.shape, arr.chunks, dict(arr.attrs)
            dims = _dims(arr)
            if dims and len(dims) != len(arr.shape):
                raise DataFormatError(f"{len(dims)} dimension names for {len(arr.shape)} dimensions")
        except DataFormatError as exc:
            raise DataFormatError(f"array metadata: {exc}", meta) from None
        except Exception as exc:  # noqa: BLE001
            raise DataFormatError(f"array metadata: {type(exc).__name__}: {_one_line(exc)}", meta) from None
        if not hasattr(arr, "shape") or isinstance(arr, zarr.Group):
            continue
        n_chunk = int(np.prod([int(c) for c in arr.chunks], dtype=object)) if arr.chunks else 1
        if n_chunk > MAX_CHUNK_BYTES:
            raise DataFormatError(f"array metadata: chunks of {n_chunk} elements are larger than sonarmap reads",
                                  meta)
        arrays[name] = arr
    return CheckedStore(path, fmt, group, attrs, arrays)


def _open_group(path: Path) -> Any:
    """The root group of a store whose metadata was checked (:func:`inspect_store`)."""
    return inspect_store(path).group


def _attr_json_list(st: CheckedStore, key: str) -> list[str]:
    """A root attribute holding a JSON list of strings (geometries, sources)."""
    v = st.attrs.get(key)
    if v is None:
        raise DataFormatError(f"root attribute {key} is missing; not a sonarmap survey store", st.meta_file())
    try:
        out = json.loads(v) if isinstance(v, str) else None
    except (ValueError, RecursionError):
        out = None
    if not isinstance(out, list) or not all(isinstance(s, str) for s in out):
        raise DataFormatError(f"root attribute {key} is not a JSON list of strings", st.meta_file())
    return out


#: The arrays every raw survey store holds: name -> (rank, dtype kinds, trailing dims).
_RAW_ARRAYS: dict[str, tuple[int, str, tuple[str, ...]]] = {
    VAR_INTENSITY: (3, "f", (DIM_RANGE, DIM_BEAM)),
    DIM_PING: (1, "i", ()),
    VAR_GEOMETRY: (1, "iu", ()),
    VAR_SOURCE: (1, "iu", ()),
    VAR_POSITION: (2, "f", (DIM_XYZ,)),
    VAR_ORIENTATION: (2, "f", (DIM_QUAT,)),
}

TIME_UNITS_RE = re.compile(r"nanoseconds since 1970-01-01(?:[ T]00:00(?::00(?:\.0+)?)?)?Z?")


def _inspect_survey(path: Path) -> CheckedStore:
    """:func:`inspect_store` plus the survey data model: required arrays, ranks, dtypes, attributes.

    Raises
    ------
    DataFormatError
        Naming the store and the file or array at fault.
    """
    st = inspect_store(path)
    if VAR_INTENSITY not in st.arrays:
        raise DataFormatError(f"zarr store has no '{VAR_INTENSITY}' variable (not a survey)", st.path)
    model = st.attrs.get(ATTR_MODEL)
    if model is None:
        raise DataFormatError(f"root attribute {ATTR_MODEL} is missing; not a sonarmap survey store", st.meta_file())
    if isinstance(model, bool) or model != DATA_MODEL_VERSION:
        raise DataFormatError(f"root attribute {ATTR_MODEL} is {model!r:.40}; this sonarmap reads data model "
                              f"{DATA_MODEL_VERSION}", st.meta_file())
    _attr_json_list(st, ATTR_GEOMETRIES)
    _attr_json_list(st, ATTR_SOURCES)
    img = st.require(VAR_INTENSITY, ndim=3, kinds="f")
    sizes = {DIM_RANGE: int(img.shape[1]), DIM_BEAM: int(img.shape[2]), DIM_XYZ: 3, DIM_QUAT: 4}
    for name, arr in st.arrays.items():
        for dim, size in zip(st.dims(name), arr.shape, strict=False):
            if dim in sizes and int(size) != sizes[dim]:
                raise DataFormatError(f"array '{name}' has {size} along {dim}, the survey has {sizes[dim]}",
                                      st.meta_file(name))
    for name, (ndim, kinds, trailing) in _RAW_ARRAYS.items():
        arr = st.require(name, ndim=ndim, kinds=kinds)
        dims = st.dims(name)
        if dims != (DIM_PING, *trailing):
            raise DataFormatError(f"array '{name}' has dimensions {dims}, expected {(DIM_PING, *trailing)}",
                                  st.meta_file(name))
        if name == DIM_PING:
            if np.dtype(arr.dtype) != np.int64:
                raise DataFormatError(f"array '{DIM_PING}' has data type {arr.dtype}, expected int64 nanoseconds",
                                      st.meta_file(name))
            units = arr.attrs.get("units")
            if not isinstance(units, str) or not TIME_UNITS_RE.fullmatch(units):
                raise DataFormatError(f"array '{DIM_PING}' has units {units!r:.60}, expected 'nanoseconds since "
                                      "1970-01-01'", st.meta_file(name))
    if not isinstance(st.attrs.get(ATTR_POSE_FRAME), str):
        raise DataFormatError(f"root attribute {ATTR_POSE_FRAME} is missing or not a string", st.meta_file())
    for name in st.arrays:
        if name.startswith(META_PREFIX):
            arr = st.require(name, ndim=1, kinds="biuf")
            kind = arr.attrs.get("sonarmap_kind")
            if kind not in ("int", "float", "bool"):
                raise DataFormatError(f"array '{name}': sonarmap_kind {kind!r:.40} is not int, float or bool",
                                      st.meta_file(name))
            if kind == "int" and kind_of(arr) not in "iu":
                raise DataFormatError(f"array '{name}': sonarmap_kind int but data type {arr.dtype}",
                                      st.meta_file(name))
    return st


def _read_state(path: Path) -> _State:
    st = _inspect_survey(path)
    state = _State(
        geometries=_attr_json_list(st, ATTR_GEOMETRIES),
        sources=_attr_json_list(st, ATTR_SOURCES),
        pose_frame=str(st.attrs.get(ATTR_POSE_FRAME, "")),
    )
    core = {VAR_INTENSITY, VAR_GEOMETRY, VAR_SOURCE, VAR_POSITION, VAR_ORIENTATION, COORD_RANGE,
            COORD_AZIMUTH, DIM_PING, DIM_RANGE, DIM_BEAM}
    for name, arr in st.arrays.items():
        if name.startswith(META_PREFIX):
            state.meta[name[len(META_PREFIX):]] = str(arr.attrs["sonarmap_kind"])
        elif name not in core:
            dims = st.dims(name)
            if dims and dims[0] == DIM_PING:
                try:
                    fill = float(arr.attrs.get("sonarmap_fill_value", "nan"))
                except (TypeError, ValueError):
                    fill = math.nan
                try:
                    var = PingVariable(
                        name, tuple(dims[1:]), dtype=str(arr.dtype), units=str(arr.attrs.get("units", "1")),
                        long_name=str(arr.attrs.get("long_name", "")), fill_value=fill,
                    )
                except InputError as exc:
                    raise DataFormatError(f"array '{name}': {exc}", st.meta_file(name)) from None
                state.extras[name] = var
    state.shape = tuple(st.arrays[VAR_INTENSITY].shape[1:])  # type: ignore[assignment]
    if COORD_AZIMUTH in st.arrays and st.dims(COORD_AZIMUTH) == (DIM_BEAM,):
        state.azimuth = np.asarray(read_array(st, COORD_AZIMUTH), dtype=np.float64)
    else:  # a store of pings with different tables, or written before the common layout
        state.azimuth_per_ping = True
    return state


def _ping_lengths(st: CheckedStore) -> dict[str, int]:
    out = {}
    for name, arr in st.arrays.items():
        dims = st.dims(name)
        if dims and dims[0] == DIM_PING:
            out[name] = int(arr.shape[0])
    return out


def _n_pings(path: Path) -> int:
    lengths = _ping_lengths(_inspect_survey(path))
    return min(lengths.values()) if lengths else 0


# ---------------------------------------------------------------------- reading: chunks and values
def _chunk_coords(arr: Any, rows: slice | None = None) -> Iterator[tuple[int, ...]]:
    """Chunk-grid coordinates of ``arr`` covering rows ``rows`` of its first dimension."""
    import itertools

    shape, chunks = tuple(arr.shape), tuple(arr.chunks)
    if not shape:
        yield ()
        return
    if any(s == 0 for s in shape):
        return
    lo, hi = (0, shape[0]) if rows is None else (max(0, rows.start or 0), min(shape[0], rows.stop))
    if hi <= lo:
        return
    first = range(lo // chunks[0], (hi - 1) // chunks[0] + 1)
    rest = [range(-(-s // c)) for s, c in zip(shape[1:], chunks[1:], strict=True)]
    yield from itertools.product(first, *rest)


def _chunk_key(arr: Any, coords: tuple[int, ...]) -> str:
    """The store key of chunk ``coords`` of ``arr`` (``c/1/0/0`` in v3, ``1.0.0`` in v2)."""
    try:
        return str(arr.metadata.encode_chunk_key(coords))
    except Exception:  # noqa: BLE001 - only for messages
        return "c/" + "/".join(str(c) for c in coords)


def _reason(exc: BaseException) -> str:
    """What a failed chunk decode means, for the message."""
    msg = _one_line(exc, 160)
    if "checksum" in msg.lower():
        return "checksum mismatch (the chunk file is corrupt)"
    return f"corrupt, cannot be decoded ({type(exc).__name__}: {msg})"


#: Largest chunk (decoded bytes) sonarmap reads; a store's writers use a few MB.
MAX_CHUNK_BYTES = 1 << 30
#: Bytes per element assumed for variable-length strings when bounding a chunk's size.
_STRING_ITEM_BYTES = 1024


def _chunk_limit(arr: Any) -> int:
    """Largest plausible size of one encoded chunk file of ``arr`` (zstd's worst case + checksum)."""
    n = int(np.prod([int(c) for c in arr.chunks], dtype=object)) if arr.chunks else 1
    try:
        item = int(np.dtype(arr.dtype).itemsize) if kind_of(arr) != "T" else _STRING_ITEM_BYTES
    except TypeError:
        item = _STRING_ITEM_BYTES
    raw = n * max(item, 1)
    return raw + raw // 64 + 4096


def _chunk_files(st: CheckedStore, name: str) -> dict[str, int]:
    """The chunk files of array ``name`` (key -> size), every one checked to be a regular file of
    plausible size - so zarr never opens a FIFO (hangs), a device such as ``/dev/zero`` (reads
    without end) or an absurdly large file.  Cached on ``st``.

    Raises
    ------
    DataFormatError
        Naming the chunk file that is not a regular file or is too large.
    """
    cached = st.files.get(name)
    if cached is not None:
        return cached
    root = st.path / name
    meta_names = {"zarr.json"} if st.zarr_format == 3 else {".zarray", ".zattrs"}
    limit = _chunk_limit(st.arrays[name])
    out: dict[str, int] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = [d for d in dirnames if not os.path.islink(os.path.join(dirpath, d))]
        rel = os.path.relpath(dirpath, root)
        for fname in filenames:
            if rel == "." and fname in meta_names:
                continue
            path = Path(dirpath) / fname
            if not os.path.exists(path):  # a dangling symlink: as good as missing
                continue
            require_regular_file(path, f"chunk file of array '{name}'")
            size = os.stat(path).st_size
            if size > limit:
                raise DataFormatError(f"chunk file of array '{name}' is {size} bytes, more than a chunk of "
                                      f"this array can take ({limit})", path)
            out[fname if rel == "." else "/".join([*Path(rel).parts, fname])] = size
    st.files[name] = out
    return out


def check_chunk_files(st: CheckedStore, name: str, rows: slice | None = None, *, required: bool | None = None) -> None:
    """The chunk files of array ``name`` are regular files of plausible size (:func:`_chunk_files`)
    and - if ``required`` (default: the array is checksummed, i.e. written by this version, which
    writes every chunk) - every chunk covering ``rows`` exists.

    zarr reads a missing chunk as the fill value; for arrays written without checksums (older
    stores, where all-fill chunks were legitimately not written) presence cannot be required.

    Raises
    ------
    DataFormatError
        Naming the store, array and chunk.
    """
    files = _chunk_files(st, name)
    if not (st.checksummed(name) if required is None else required):
        return
    arr = st.arrays[name]
    for coords in _chunk_coords(arr, rows):
        key = _chunk_key(arr, coords)
        if key not in files:
            raise DataFormatError(f"array '{name}', chunk {key}: missing (deleted?)", st.path)


def _crc_scan(path: Path, names: Iterable[str], rows: slice | None) -> DataFormatError | None:
    """Find a missing or corrupt chunk file of checksummed arrays by their CRC32C, without zarr.

    For arrays whose last codec is ``crc32c`` (the 4-byte little-endian CRC32C of the rest of the
    file is appended), each chunk file covering ``rows`` is read and its checksum recomputed.
    Cheap enough for the error path: no zarr round trips, just the files.  Returns the error of
    the first bad chunk, or ``None`` (nothing found, or no checksums to check).
    """
    import itertools

    import google_crc32c

    for name in names:
        try:
            doc = json.loads((path / name / "zarr.json").read_text(encoding="utf-8"))
            if [c.get("name") if isinstance(c, dict) else c for c in doc["codecs"]][-1] != "crc32c":
                continue
            shape = [int(x) for x in doc["shape"]]
            chunks = [int(x) for x in doc["chunk_grid"]["configuration"]["chunk_shape"]]
            cke = doc.get("chunk_key_encoding") or {}
            sep = (cke.get("configuration") or {}).get("separator", "/")
            v2 = cke.get("name") == "v2"
            if len(shape) != len(chunks) or any(c <= 0 for c in chunks):
                continue
            dt = doc.get("data_type")
            item = np.dtype(dt).itemsize if isinstance(dt, str) and dt != "string" else _STRING_ITEM_BYTES
            raw = int(np.prod(chunks, dtype=object)) * max(int(item), 1)
            limit = raw + raw // 64 + 4096
        except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError, OverflowError):
            continue
        if any(n == 0 for n in shape):
            continue
        ranges = [range(-(-n // c)) for n, c in zip(shape, chunks, strict=True)]
        if shape and rows is not None:
            lo, hi = max(0, rows.start or 0), min(shape[0], rows.stop)
            if hi <= lo:
                continue
            ranges[0] = range(lo // chunks[0], (hi - 1) // chunks[0] + 1)
        for coords in itertools.product(*ranges):
            parts = [str(c) for c in coords] or (["0"] if v2 else [])
            key = sep.join(parts) if v2 else sep.join(["c", *parts])
            f = path / name / key
            try:
                size = os.stat(f).st_size
            except OSError:
                return DataFormatError(f"array '{name}', chunk {key}: missing (deleted?)", path)
            try:
                # bounded by the file's size (read() allocates its bound) and by what a chunk can take
                data = read_bytes_bounded(f, min(size, limit), f"chunk file of array '{name}'")
            except DataFormatError as exc:
                return exc
            if len(data) < 4 or struct.unpack("<I", data[-4:])[0] != google_crc32c.value(data[:-4]):
                return DataFormatError(f"array '{name}', chunk {key}: checksum mismatch (the chunk file is corrupt)",
                                       path)
    return None


def locate_error(st: CheckedStore, names: Iterable[str], rows: slice | None, exc: BaseException,
                  what: str | None = None) -> DataFormatError:
    """The :class:`DataFormatError` naming the array and chunk that made a read fail.

    Checks the chunk files of ``names`` covering ``rows`` (only after a failure): first their
    checksums (:func:`_crc_scan`), then, one chunk at a time through zarr, whether they decode
    (corrupt compressed data in a store without checksums ...).  The message starts
    ``cannot read <what>:`` when ``what`` is given.
    """
    prefix = f"cannot read {what}: " if what else ""
    names = list(names)
    found = _crc_scan(st.path, names, rows)
    if found is not None:
        return DataFormatError(prefix + str(found).removeprefix(f"{st.path}: "), st.path)
    for name in names:
        arr = st.arrays.get(name)
        if arr is None:
            continue
        try:
            check_chunk_files(st, name, rows)
        except DataFormatError as missing:
            return DataFormatError(prefix + str(missing).removeprefix(f"{st.path}: "), st.path)
        for coords in _chunk_coords(arr, rows):
            sel = tuple(slice(c * k, (c + 1) * k) for c, k in zip(coords, arr.chunks, strict=True))
            try:
                arr[sel] if sel else arr[...]
            except Exception as e:  # noqa: BLE001 - whatever the codecs raise
                return DataFormatError(f"{prefix}array '{name}', chunk {_chunk_key(arr, coords)}: {_reason(e)}",
                                       st.path)
    return DataFormatError(f"{prefix or 'cannot read: '}{type(exc).__name__}: {_one_line(exc)}", st.path)


def read_array(st: CheckedStore, name: str, rows: slice | None = None) -> NDArray[Any]:
    """Rows ``rows`` of array ``name`` (all if ``None``), chunks checked: errors name the chunk."""
    arr = st.arrays[name]
    check_chunk_files(st, name, rows)
    try:
        if not arr.shape:
            return np.asarray(arr[...])
        return np.asarray(arr[rows if rows is not None else slice(None)])
    except Exception as exc:  # noqa: BLE001
        raise locate_error(st, [name], rows, exc) from None


def check_values(
    values: ArrayLike,
    name: str,
    path: str | os.PathLike[str] | None,
    *,
    low: float = -math.inf,
    high: float = math.inf,
    nan: bool = False,
    inf: bool = False,
    start: int = 0,
    item: str = "ping",
    allowed: Iterable[float] = (),
) -> None:
    """Check stored values of variable ``name`` against their documented range.

    Parameters
    ----------
    values : array_like
        Rows along the first axis (pings, or points); ``start`` is the index of the first row.
    name : str
        The variable (for the message).
    path : path-like or None
        The store (for the message).
    low, high : float
        Inclusive range of valid values.
    nan : bool
        NaN is valid ("none" / "unknown" / unwritten).
    inf : bool
        Infinities are valid if inside ``[low, high]``.
    item : str
        What a row is (``"ping"``, ``"point"``).
    allowed : iterable of float
        Extra valid values outside the range (sentinels such as -1 for "none").

    Raises
    ------
    DataFormatError
        Naming the store, the variable and the first offending row.
    """
    v = np.asarray(values)
    if v.size == 0 or v.dtype.kind not in "biuf":
        return
    if v.dtype.kind == "f":
        isnan = np.isnan(v)
        ok = (v >= low) & (v <= high)
        if not inf:
            ok &= np.isfinite(v)
        if nan:
            ok |= isnan
    else:
        isnan = np.zeros(v.shape, bool)
        ok = (v >= low) & (v <= high)
    for a in allowed:
        ok |= v == a
    if ok.all():
        return
    bad = np.argwhere(~ok)[0]
    x = v[tuple(bad)]
    row = start + int(bad[0]) if v.ndim else start
    at = f" at index {tuple(int(b) for b in bad[1:])}" if v.ndim > 1 else ""
    if isnan[tuple(bad)]:
        problem = "is NaN"
    elif v.dtype.kind == "f" and not np.isfinite(x):
        problem = f"is {float(x)}"
    else:
        lo = "-inf" if low == -math.inf else f"{low:g}"
        hi = "inf" if high == math.inf else f"{high:g}"
        extra = f" (or {', '.join(f'{a:g}' for a in allowed)})" if allowed else ""
        problem = f"{x.item()!r} is outside the documented range [{lo}, {hi}]{extra}"
    raise DataFormatError(f"{name}: {item} {row}{at}: value {problem}", path)


def check_times(times: ArrayLike, path: str | os.PathLike[str] | None, start: int = 0, *,
                 name: str = DIM_PING, item: str = "ping") -> None:
    """Times are int64 ns since 1970 in [0, TIME_MAX_NS] (NaT, i.e. int64 min, and negatives are not).

    Raises
    ------
    DataFormatError
        Naming the store, the variable ``name`` and the first offending ``item``.
    """
    t = np.asarray(times)
    if t.dtype.kind == "M":
        t = t.astype("datetime64[ns]").astype(np.int64)
    if t.dtype.kind not in "iu":
        raise DataFormatError(f"{name}: stored as {t.dtype}, expected int64 nanoseconds", path)
    if t.dtype.kind == "i":
        neg = np.flatnonzero(t < 0)
        if neg.size:
            i = int(neg[0])
            what = "not a time (NaT)" if int(t[i]) == np.iinfo(np.int64).min else f"{int(t[i])} ns, before 1970"
            raise DataFormatError(f"{name}: {item} {start + i}: time is {what}", path)
    elif t.size and int(t.max()) > TIME_MAX_NS:
        i = int(np.argmax(t > TIME_MAX_NS))
        raise DataFormatError(f"{name}: {item} {start + i}: time {int(t[i])} ns is beyond the int64 range", path)


# ---------------------------------------------------------------------- reading: datasets and pings
def open_survey(path: str | os.PathLike[str], *, repair: bool = False) -> xr.Dataset:
    """Open a survey store lazily (dask-backed, chunked along ``ping_time``).

    Every metadata document is parsed and checked first, the ping times are read and checked
    (int64 ns in [0, 2**63 - 1]), and every chunk of a checksummed array must exist.

    Raises
    ------
    DataFormatError
        If the path is not a survey store, its metadata is corrupt or incomplete (the message
        names the file or array), a time is out of range or a chunk is missing or corrupt, or an
        interrupted append left arrays of different lengths (pass ``repair=True`` to truncate
        them to the common length).
    """
    import xarray as xr

    p = Path(path)
    st = _inspect_survey(p)
    lengths = _ping_lengths(st)
    if len(set(lengths.values())) > 1:
        n = min(lengths.values())
        if not repair:
            raise DataFormatError(
                f"arrays along {DIM_PING} have different lengths {sorted(set(lengths.values()))} "
                "(an append was interrupted); open with repair=True to truncate to "
                f"{n} pings",
                p,
            )
        import zarr

        with WriterLock(p):
            invalidate_consolidated(p)
            gw = zarr.open_group(str(p), mode="r+", use_consolidated=False)
            for name, length in lengths.items():
                if length != n:
                    arr = gw[name]
                    arr.resize((n, *arr.shape[1:]))
            consolidate(p)
        st = _inspect_survey(p)
    for name in st.arrays:
        check_chunk_files(st, name)
    raw_times = read_array(st, DIM_PING)
    check_times(raw_times, p)
    try:
        ds = xr.open_zarr(p, consolidated=False, chunks={})
        decoded = ds[DIM_PING].values
    except SonarmapError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise locate_error(st, list(st.arrays), None, exc, "the survey") from None
    if decoded.dtype.kind != "M" or not np.array_equal(decoded.astype("datetime64[ns]").astype(np.int64), raw_times):
        raise DataFormatError(f"array '{DIM_PING}': decoded times differ from the stored nanoseconds "
                              f"(units {st.arrays[DIM_PING].attrs.get('units')!r})", st.meta_file(DIM_PING))
    ds.encoding["source"] = str(p)
    return ds


def survey_geometries(ds: xr.Dataset) -> list[SonarGeometry]:
    """The distinct geometries of a survey dataset (indexed by ``geometry_index``).

    Raises
    ------
    DataFormatError
        If the ``sonarmap_geometries`` attribute is missing or corrupt (naming the store).
    """
    src = ds.encoding.get("source")
    raw = ds.attrs.get(ATTR_GEOMETRIES)
    if raw is None:
        raise DataFormatError(f"no {ATTR_GEOMETRIES} attribute; not a sonarmap survey", src)
    try:
        items = json.loads(raw) if isinstance(raw, str) else None
        if not isinstance(items, list):
            raise TypeError("not a JSON list")
        return [_geometry_from_json(s) for s in items]
    except Exception as exc:  # noqa: BLE001 - geometry parsing raises many types on corrupt JSON
        raise DataFormatError(f"corrupt {ATTR_GEOMETRIES} attribute ({_one_line(exc)})", src) from None


def _sources(ds: xr.Dataset) -> list[str]:
    """The ``sonarmap_sources`` attribute (a JSON list of strings) of a survey dataset."""
    src = ds.encoding.get("source")
    raw = ds.attrs.get(ATTR_SOURCES)
    try:
        items = json.loads(raw) if isinstance(raw, str) else None
    except (ValueError, RecursionError):
        items = None
    if not isinstance(items, list) or not all(isinstance(s, str) for s in items):
        raise DataFormatError(f"{ATTR_SOURCES} attribute is missing or not a JSON list of strings", src)
    return items


def dataset_to_pings(
    ds: xr.Dataset,
    *,
    geometry: SonarGeometry | None = None,
    source: str | None = None,
    start: int = 0,
    stop: int | None = None,
) -> Iterator[Ping]:
    """Lazily rebuild pings from a survey dataset, one ``ping_time`` chunk in memory at a time.

    Every value is checked against the data model as it is read: intensities in [0, 1], times in
    [0, 2**63 - 1] ns, geometry and source indices inside their tables, poses all-NaN or valid.

    Parameters
    ----------
    ds : xarray.Dataset
        From :func:`open_survey` or :func:`pings_to_dataset`.
    geometry : SonarGeometry, optional
        Replaces the stored geometries.
    source : str, optional
        Replaces the stored sources.
    start, stop : int
        Pings ``start:stop`` of ``ds`` only (default: all).

    Raises
    ------
    DataFormatError
        If a chunk is corrupt or missing (naming store, array and chunk) or a value is outside the
        data model (naming store, variable and ping).
    """
    path = ds.encoding.get("source")
    for name in _RAW_ARRAYS:
        if name not in ds.variables:
            raise DataFormatError(f"no '{name}' variable; not a sonarmap survey", path)
    geoms = survey_geometries(ds)
    sources = _sources(ds) if source is None else []
    frame = str(ds.attrs.get(ATTR_POSE_FRAME, "")) or "ned"
    n = int(ds.sizes.get(DIM_PING, 0))
    stop = n if stop is None else min(int(stop), n)
    start = max(0, int(start))
    chunk = _ping_chunk(ds)
    meta_vars = [v for v in ds.data_vars if str(v).startswith(META_PREFIX)]
    times = _ping_times_ns(ds, path)
    check_times(times[start:stop], path, start)
    for i0 in range(start - start % chunk, stop, chunk):
        sl = slice(max(i0, start), min(i0 + chunk, stop))
        block = _read_block(ds, sl)
        img = np.asarray(block[VAR_INTENSITY].values, dtype=np.float32)
        check_values(img, VAR_INTENSITY, path, low=0.0, high=1.0, start=sl.start)
        gi = block[VAR_GEOMETRY].values
        si = block[VAR_SOURCE].values
        pos = block[VAR_POSITION].values
        quat = block[VAR_ORIENTATION].values
        if geometry is None:
            check_values(gi, VAR_GEOMETRY, path, low=0, high=len(geoms) - 1, start=sl.start)
        if source is None:
            check_values(si, VAR_SOURCE, path, low=0, high=len(sources) - 1, start=sl.start)
        metas = _block_metas(block, meta_vars, path, sl.start)
        for k in range(img.shape[0]):
            i = sl.start + k
            meta = _ping_meta(metas, k)
            pose = _pose(pos[k], quat[k], frame, i, path)
            g = geometry if geometry is not None else geoms[int(gi[k])]
            src = source if source is not None else sources[int(si[k])]
            yield Ping(image=img[k], geometry=g, time_ns=int(times[i]), pose=pose, source=src, meta=meta)


def _ping_chunk(ds: xr.Dataset) -> int:
    """Pings per block read by :func:`dataset_to_pings`: the store's ``ping_time`` chunk (else 16)."""
    chunk = 16
    enc_chunks = ds[VAR_INTENSITY].encoding.get("chunks") or ds[VAR_INTENSITY].encoding.get("preferred_chunks")
    if isinstance(enc_chunks, tuple | list) and enc_chunks:
        chunk = max(1, int(enc_chunks[0]))
    return chunk


def _ping_times_ns(ds: xr.Dataset, path: Any) -> NDArray[np.int64]:
    """The ``ping_time`` coordinate as int64 ns; DataFormatError if it was not decoded as times."""
    times = ds[DIM_PING].values
    if times.dtype.kind != "M":
        raise DataFormatError(f"{DIM_PING}: not decoded as times (dtype {times.dtype})", path)
    return times.astype("datetime64[ns]").astype(np.int64)


def _read_block(ds: xr.Dataset, rows: slice) -> xr.Dataset:
    """Pings ``rows`` of ``ds`` loaded into memory; a failed read is a DataFormatError naming the chunk."""
    try:
        # One pass for all variables, in this thread: a block is one chunk of each, so threads
        # would only add their overhead (~30 ms per block for small pings).
        return ds.isel({DIM_PING: rows}).compute(scheduler="synchronous")
    except Exception as exc:  # noqa: BLE001 - codecs/zarr raise many types on corrupt chunks
        raise _block_error(ds, rows, exc) from None


def _block_metas(
    block: xr.Dataset, meta_vars: Sequence[Any], path: Any, start: int
) -> dict[Any, tuple[NDArray[Any], Any]]:
    """``{variable: (values, sonarmap_kind)}`` of the ``meta_*`` variables of a block, their kinds
    checked (int, float or bool) and bool values checked to be 0, 1 or NaN."""
    metas = {v: (block[v].values, block[v].attrs.get("sonarmap_kind")) for v in meta_vars}
    for v, (vals, kind) in metas.items():
        if kind not in ("int", "float", "bool"):
            raise DataFormatError(f"{v}: sonarmap_kind attribute {kind!r:.40} is not int, float or bool", path)
        if kind == "bool":
            check_values(vals, str(v), path, low=0, high=1, nan=True, start=start)
    return metas


def _ping_meta(metas: Mapping[Any, tuple[NDArray[Any], Any]], k: int) -> dict[str, Any]:
    """``Ping.meta`` of ping ``k`` of a block: its stored values, without the missing ones."""
    meta: dict[str, Any] = {}
    for v, (vals, kind) in metas.items():
        x = vals[k]
        key = str(v)[len(META_PREFIX):]
        if kind == "int":
            if int(x) != INT_MISSING:
                meta[key] = int(x)
        elif np.isfinite(x):
            meta[key] = bool(x) if kind == "bool" else float(x)
    return meta


def _pose(pos: NDArray[Any], quat: NDArray[Any], frame: str, i: int, path: Any) -> Pose | None:
    """The stored pose of ping ``i``: all NaN is "no pose", anything else must be a valid pose."""
    if np.isnan(pos).all() and np.isnan(quat).all():
        return None
    try:
        return Pose(position_m=pos, orientation_xyzw=quat, frame=frame)
    except InputError as exc:
        raise DataFormatError(f"{VAR_POSITION}/{VAR_ORIENTATION}: ping {i}: invalid pose ({exc})", path) from None


def _block_error(ds: xr.Dataset, rows: slice, exc: BaseException) -> DataFormatError:
    """The error of a failed read of pings ``rows`` of ``ds``, naming the array and chunk if it can."""
    path = ds.encoding.get("source")
    what = f"pings {rows.start}-{rows.stop - 1}"
    if path is None:
        return DataFormatError(f"cannot read {what}: {type(exc).__name__}: {_one_line(exc)}")
    found = _crc_scan(Path(path), [str(v) for v in ds.variables], rows)
    if found is not None:
        return DataFormatError(f"cannot read {what}: " + str(found).removeprefix(f"{path}: "), path)
    try:
        st = inspect_store(Path(path))
    except DataFormatError as e:
        return e
    names = [str(v) for v in ds.variables if str(v) in st.arrays]
    ping_names = [v for v in names if st.dims(v)[:1] == (DIM_PING,)]
    return locate_error(st, ping_names + [v for v in names if v not in ping_names], rows, exc, what)


# ---------------------------------------------------------------------- extra variables
def add_ping_variable(path: str | os.PathLike[str], var: PingVariable, *, chunk_pings: int | None = None) -> None:
    """Add an (unwritten, fill-valued) per-ping variable to an existing survey store.

    Existing variables of the same name are left as they are (the call is idempotent, so a
    resumed batch run can call it again).
    """
    import dask.array as da
    import xarray as xr

    p = Path(path)
    st = _inspect_survey(p)
    if var.name in st.arrays:
        return
    state = _read_state(p)
    assert state.shape is not None
    n = _n_pings(p)
    shape = (n, *_extra_shape(var, state.shape))
    cp = chunk_pings or int(st.arrays[VAR_INTENSITY].chunks[0])
    data = da.full(shape, var.fill_value, dtype=var.dtype, chunks=(cp, *shape[1:]))
    ds = xr.Dataset({var.name: ((DIM_PING, *var.dims), data, var.attrs())}, attrs=dict(st.attrs))
    enc: dict[str, Any] = {var.name: {"chunks": (cp, *shape[1:]), **checksum_codecs()}}
    if np.dtype(var.dtype).kind in "iub":
        enc[var.name]["fill_value"] = None
    try:
        invalidate_consolidated(p)
        ds.to_zarr(p, mode="a", encoding=enc, consolidated=False, compute=True, write_empty_chunks=True)
    except OSError as exc:
        raise write_error(exc, p, f"cannot add variable {var.name}") from None
    consolidate(p)


def write_ping_variable(
    path: str | os.PathLike[str],
    name: str,
    values: ArrayLike,
    *,
    start: int,
) -> None:
    """Write ``values`` (shape ``(n, ...)``) into variable ``name`` for pings ``start .. start+n``.

    Region writes aligned to the ``ping_time`` chunks are safe to run concurrently from several
    processes (each chunk is written by one writer).
    """
    import xarray as xr

    p = Path(path)
    st = inspect_store(p)
    if name not in st.arrays:
        raise InputError(f"{p}: no variable {name!r}; declare it with add_ping_variable first")
    arr = st.arrays[name]
    vals = np.asarray(values, dtype=arr.dtype)
    if vals.shape[1:] != tuple(arr.shape[1:]):
        raise InputError(f"{name}: values of shape {vals.shape[1:]} per ping, store has {arr.shape[1:]}")
    if not (0 <= start and start + vals.shape[0] <= arr.shape[0]):
        raise InputError(f"{name}: pings {start}..{start + vals.shape[0]} outside 0..{arr.shape[0]}")
    ds = xr.Dataset({name: (st.dims(name), vals)}, attrs=dict(st.attrs))
    try:
        ds.to_zarr(p, region={DIM_PING: slice(start, start + vals.shape[0])}, consolidated=False,
                   write_empty_chunks=True)
    except OSError as exc:
        raise write_error(exc, p, f"cannot write variable {name}") from None
