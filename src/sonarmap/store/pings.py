"""The raw-ping store of ``sonarmap convert``: pings <-> xarray Dataset, opening and reading back.

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
the product store, :mod:`sonarmap.store.products`); stores written before it (``beam_azimuth``
always ``(ping_time, beam)``) still read, and appends to them keep their layout.
Every variable has CF ``units`` and ``long_name``; the dataset has ``Conventions = "CF-1.8"``.
``ping_time`` is stored as int64 nanoseconds since 1970-01-01 (exact).  Each distinct
:class:`~sonarmap.geometry.SonarGeometry` is stored once as JSON in ``sonarmap_geometries``, so
:func:`dataset_to_pings` rebuilds pings losslessly (image, geometry, time, pose and numeric
metadata).  Numeric scalar entries of ``Ping.meta`` become ``meta_<key>`` variables (ints as int64
with :data:`INT_MISSING` for "absent", floats/bools as float64 with NaN); the set of meta
variables is fixed by the first batch written; strings and arrays in ``meta`` are not stored.
Per-ping products of later stages are declared with :class:`PingVariable`.

Reading (:func:`open_survey`, :func:`dataset_to_pings`) parses every metadata document first,
requires the arrays of the data model, and checks values as they are read: intensities in [0, 1],
times int64 ns in [0, 2**63 - 1], indices inside their tables; a corrupt or missing chunk is an
error naming the array and chunk (:mod:`sonarmap.store.check`).  Writing is
:mod:`sonarmap.store.writer`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap import __version__
from sonarmap._atomic import WriterLock
from sonarmap.datamodel import (
    ATTR_GEOMETRIES,
    ATTR_MODEL,
    ATTR_POSE_FRAME,
    ATTR_SOURCES,
    COORD_AZIMUTH,
    COORD_RANGE,
    DATA_MODEL_VERSION,
    DIM_BEAM,
    DIM_PING,
    DIM_QUAT,
    DIM_RANGE,
    DIM_XYZ,
    INT_MISSING,
    META_PREFIX,
    PING_ARRAYS,
    PING_ATTRS,
    TIME_MAX_NS,
    PING_TIME_UNITS,
    VAR_GEOMETRY,
    VAR_INTENSITY,
    VAR_ORIENTATION,
    VAR_POSITION,
    VAR_SOURCE,
    azimuth_dims,
)
from sonarmap.errors import DataFormatError, InputError, SonarmapError
from sonarmap.geometry import SonarGeometry
from sonarmap.ping import Ping, Pose, source_file
from sonarmap.store.check import (
    CheckedStore,
    _crc_scan,
    check_chunk_files,
    check_times,
    check_values,
    inspect_store,
    kind_of,
    locate_error,
    read_array,
)
from sonarmap.store.metadata import (
    consolidate,
    geometry_from_json,
    geometry_json,
    invalidate_consolidated,
    json_string_list,
    one_line,
)

if TYPE_CHECKING:  # pragma: no cover
    import xarray as xr

__all__ = [
    "PingVariable",
    "dataset_to_pings",
    "inspect_survey",
    "open_survey",
    "pings_to_dataset",
    "survey_geometries",
    "survey_length",
]



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


# ---------------------------------------------------------------------- pings -> dataset
def _meta_kind(v: Any) -> str | None:
    if isinstance(v, bool | np.bool_):
        return "bool"
    if isinstance(v, int | np.integer):
        return "int" if np.iinfo(np.int64).min < int(v) <= np.iinfo(np.int64).max else None
    if isinstance(v, float | np.floating):
        return "float"
    return None


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
        """Index of ``g`` in the geometry table (appended if new); ``cache`` maps ``id(g)`` -> index."""
        gid = id(g)
        if gid in cache:
            return cache[gid]
        s = geometry_json(g)
        try:
            idx = self.geometries.index(s)
        except ValueError:
            self.geometries.append(s)
            idx = len(self.geometries) - 1
        cache[gid] = idx
        return idx

    def source_index(self, source: str) -> int:
        """Index of the file of ``source`` (without ``#frame``) in the source table (appended if new)."""
        src = source_file(source)
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
        VAR_INTENSITY: ((DIM_PING, DIM_RANGE, DIM_BEAM), arrays.intensity, PING_ATTRS[VAR_INTENSITY]),
        VAR_GEOMETRY: ((DIM_PING,), arrays.geometry_index, PING_ATTRS[VAR_GEOMETRY]),
        VAR_SOURCE: ((DIM_PING,), arrays.source_index, PING_ATTRS[VAR_SOURCE]),
        VAR_POSITION: ((DIM_PING, DIM_XYZ), arrays.position, PING_ATTRS[VAR_POSITION]),
        VAR_ORIENTATION: ((DIM_PING, DIM_QUAT), arrays.orientation, PING_ATTRS[VAR_ORIENTATION]),
    }
    for key, kind in state.meta.items():
        data_vars[f"{META_PREFIX}{key}"] = _meta_variable(plist, key, kind)
    extras = extras or {}
    for var in extra_variables:
        state.extras[var.name] = var
        data_vars[var.name] = _extra_variable(var, extras.get(var.name), n, shape)
    coords = {
        DIM_PING: (DIM_PING, arrays.time_ns.astype("datetime64[ns]"), PING_ATTRS[DIM_PING]),
        DIM_RANGE: (DIM_RANGE, np.arange(shape[0], dtype=np.int32), PING_ATTRS[DIM_RANGE]),
        DIM_BEAM: (DIM_BEAM, np.arange(shape[1], dtype=np.int32), PING_ATTRS[DIM_BEAM]),
        COORD_RANGE: ((DIM_PING, DIM_RANGE), arrays.range_m, PING_ATTRS[COORD_RANGE]),
        COORD_AZIMUTH: (azimuth_dims(state.azimuth_per_ping),
                        arrays.azimuth if state.azimuth_per_ping else state.azimuth, PING_ATTRS[COORD_AZIMUTH]),
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


# ---------------------------------------------------------------------- the store's metadata
def _attr_json_list(st: CheckedStore, key: str) -> list[str]:
    """A root attribute holding a JSON list of strings (geometries, sources)."""
    v = st.attrs.get(key)
    if v is None:
        raise DataFormatError(f"root attribute {key} is missing; not a sonarmap survey store", st.meta_file())
    out = json_string_list(v)
    if out is None:
        raise DataFormatError(f"root attribute {key} is not a JSON list of strings", st.meta_file())
    return out




def inspect_survey(path: Path) -> CheckedStore:
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
    for name, (ndim, kinds, trailing) in PING_ARRAYS.items():
        arr = st.require(name, ndim=ndim, kinds=kinds)
        st.require_dims(name, (DIM_PING, *trailing))
        if name == DIM_PING:
            if np.dtype(arr.dtype) != np.int64:
                raise DataFormatError(f"array '{DIM_PING}' has data type {arr.dtype}, expected int64 nanoseconds",
                                      st.meta_file(name))
            st.require_time_units(DIM_PING, PING_TIME_UNITS)
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
    st = inspect_survey(path)
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


def survey_length(path: Path) -> int:
    """Number of pings of a raw-ping store (the shortest array along ``ping_time``; metadata only)."""
    lengths = _ping_lengths(inspect_survey(path))
    return min(lengths.values()) if lengths else 0


# ---------------------------------------------------------------------- dataset -> pings
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
    st = inspect_survey(p)
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
        st = inspect_survey(p)
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
        return [geometry_from_json(s, "survey geometry", default_source="table") for s in items]
    except Exception as exc:  # noqa: BLE001 - geometry parsing raises many types on corrupt JSON
        raise DataFormatError(f"corrupt {ATTR_GEOMETRIES} attribute ({one_line(exc)})", src) from None


def _sources(ds: xr.Dataset) -> list[str]:
    """The ``sonarmap_sources`` attribute (a JSON list of strings) of a survey dataset."""
    src = ds.encoding.get("source")
    items = json_string_list(ds.attrs.get(ATTR_SOURCES))
    if items is None:
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
    for name in PING_ARRAYS:
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
        return DataFormatError(f"cannot read {what}: {type(exc).__name__}: {one_line(exc)}")
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
