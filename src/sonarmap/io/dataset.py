"""The survey dataset: pings as an xarray Dataset stored in zarr - the data model, in one place.

Layout (following echopype's conventions where one exists)::

    dimensions   ping_time, range_sample, beam  (+ xyz, quaternion for poses)
    intensity    (ping_time, range_sample, beam) float32 in [0, 1], chunked along ping_time
    echo_range   (ping_time, range_sample) float64, m      coordinate: range of each bin
    beam_azimuth (ping_time, beam) float64, rad            coordinate: positive to starboard
    geometry_index (ping_time) int32                       index into attrs["sonarmap_geometries"]
    source_index   (ping_time) int32                       index into attrs["sonarmap_sources"]
    pose_position_m (ping_time, xyz), pose_orientation_xyzw (ping_time, quaternion)  NaN if none
    meta_<key>   (ping_time)  numeric per-ping metadata (heading, gain, ...), see below

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
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from sonarmap import __version__
from sonarmap.errors import DataFormatError, InputError
from sonarmap.geometry import SonarGeometry, geometry_from_dict
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
]

DIM_PING = "ping_time"
DIM_RANGE = "range_sample"
DIM_BEAM = "beam"
DIM_XYZ = "xyz"
DIM_QUAT = "quaternion"
VAR_INTENSITY = "intensity"
COORD_RANGE = "echo_range"
COORD_AZIMUTH = "beam_azimuth"
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
    DIM_PING: {"long_name": "Ping transmit time (UTC)", "axis": "T", "standard_name": "time"},
    DIM_RANGE: {"long_name": "Range sample number (0 = nearest)", "units": "1"},
    DIM_BEAM: {"long_name": "Beam number (azimuth increases with beam)", "units": "1"},
    VAR_INTENSITY: {
        "long_name": "Received echo intensity, sensor counts scaled to [0, 1]",
        "units": "1",
        "valid_min": "0",
        "valid_max": "1",
    },
    COORD_RANGE: {"long_name": "Range from the transducer to the range bin", "units": "m"},
    COORD_AZIMUTH: {
        "long_name": "Beam centre azimuth in the sonar frame, positive to starboard",
        "units": "rad",
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
    n = len(plist)
    for p in plist:
        if p.shape != shape:
            raise InputError(
                f"{p.source or 'ping'}: image shape {p.shape} differs from the survey's {shape}; "
                "write pings of different shapes to separate stores"
            )
    if not state.meta:
        for p in plist:
            for k, v in p.meta.items():
                kind = _meta_kind(v)
                if kind and f"{META_PREFIX}{k}".isidentifier():
                    state.meta.setdefault(k, kind)
    frames = {p.pose.frame for p in plist if p.pose is not None}
    if frames:
        state.pose_frame = state.pose_frame or sorted(frames)[0]
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
    data_vars: dict[str, Any] = {
        VAR_INTENSITY: ((DIM_PING, DIM_RANGE, DIM_BEAM), intensity, ATTRS[VAR_INTENSITY]),
        VAR_GEOMETRY: ((DIM_PING,), gidx, ATTRS[VAR_GEOMETRY]),
        VAR_SOURCE: ((DIM_PING,), sidx, ATTRS[VAR_SOURCE]),
        VAR_POSITION: ((DIM_PING, DIM_XYZ), pos, ATTRS[VAR_POSITION]),
        VAR_ORIENTATION: ((DIM_PING, DIM_QUAT), quat, ATTRS[VAR_ORIENTATION]),
    }
    for key, kind in state.meta.items():
        if kind == "int":
            arr = np.full(n, INT_MISSING, dtype=np.int64)
        else:
            arr = np.full(n, np.nan, dtype=np.float64)
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
        data_vars[f"{META_PREFIX}{key}"] = ((DIM_PING,), arr, attrs)
    extras = extras or {}
    for var in extra_variables:
        state.extras[var.name] = var
        vals = extras.get(var.name)
        if vals is None:
            arr = np.full((n, *_extra_shape(var, shape)), var.fill_value, dtype=var.dtype)
        else:
            arr = np.asarray(list(vals), dtype=var.dtype)
            want = (n, *_extra_shape(var, shape))
            if arr.shape != want:
                raise InputError(f"extra variable {var.name}: shape {arr.shape}, expected {want}")
        data_vars[var.name] = ((DIM_PING, *var.dims), arr, var.attrs())
    coords = {
        DIM_PING: (DIM_PING, times.astype("datetime64[ns]"), ATTRS[DIM_PING]),
        DIM_RANGE: (DIM_RANGE, np.arange(shape[0], dtype=np.int32), ATTRS[DIM_RANGE]),
        DIM_BEAM: (DIM_BEAM, np.arange(shape[1], dtype=np.int32), ATTRS[DIM_BEAM]),
        COORD_RANGE: ((DIM_PING, DIM_RANGE), rng, ATTRS[COORD_RANGE]),
        COORD_AZIMUTH: ((DIM_PING, DIM_BEAM), az, ATTRS[COORD_AZIMUTH]),
    }
    ds = xr.Dataset(data_vars=data_vars, coords=coords)
    ds.attrs.update(_global_attrs(state))
    return ds


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


def _encoding(ds: xr.Dataset, chunk_pings: int) -> dict[str, dict[str, Any]]:
    enc: dict[str, dict[str, Any]] = {
        DIM_PING: {"units": "nanoseconds since 1970-01-01", "dtype": "int64", "chunks": (max(chunk_pings, 1024),)},
    }
    for name, var in ds.variables.items():
        if name in (DIM_PING, DIM_RANGE, DIM_BEAM):
            continue
        if var.dims and var.dims[0] == DIM_PING:
            chunks = (chunk_pings, *var.shape[1:])
            e: dict[str, Any] = {"chunks": chunks}
            if var.dtype.kind in "iub" and name.startswith(META_PREFIX):
                e["fill_value"] = None
            enc[str(name)] = e
    return enc


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
    untouched in ``"w"`` mode).
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
        self._append = mode == "a" and _is_store(self.path)
        if self._append:
            self._target = self.path
            self._state = _read_state(self.path)
            self._written = _n_pings(self.path)
            self._tmp: Path | None = None
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent))
            self._target = self._tmp / "store.zarr"

    @property
    def n_written(self) -> int:
        """Pings written to the store so far (excluding the buffer)."""
        return self._written

    def add(self, ping: Ping, **extras: Any) -> None:
        """Buffer one ping (and its extra-variable values); writes a chunk when the buffer is full."""
        if self._closed:
            raise InputError("SurveyWriter is closed")
        unknown = set(extras) - set(self._extras)
        if unknown:
            raise InputError(f"undeclared extra variables: {', '.join(sorted(unknown))}")
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
        """Write the buffered pings as one chunk."""
        if not self._buffer:
            return
        declared = {v.name for v in self.extra_variables}
        stored = [v for name, v in self._state.extras.items() if name not in declared]
        ds = pings_to_dataset(
            self._buffer,
            extras=self._extras,
            extra_variables=(*self.extra_variables, *stored),  # undeclared: fill values
            _state=self._state,
        )
        if self._written == 0 and not self._append:
            ds.to_zarr(self._target, mode="w", encoding=_encoding(ds, self.chunk_pings), consolidated=False)
        else:
            _check_append_compatible(self._target, ds)
            ds.to_zarr(self._target, append_dim=DIM_PING, consolidated=False)
            _update_attrs(self._target, _global_attrs(self._state))
        self._written += len(self._buffer)
        self._buffer.clear()
        for v in self._extras.values():
            v.clear()

    def close(self) -> None:
        """Flush and, for a new store, move it into place atomically."""
        if self._closed:
            return
        self.flush()
        self._closed = True
        if self._tmp is None:
            return
        if self._written == 0:
            shutil.rmtree(self._tmp, ignore_errors=True)
            raise InputError(f"{self.path}: no pings to write")
        _replace_dir(self._target, self.path)
        shutil.rmtree(self._tmp, ignore_errors=True)

    def abort(self) -> None:
        """Discard a new store (no effect on appends already written)."""
        self._closed = True
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> SurveyWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            self.close()
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


def _update_attrs(path: Path, attrs: Mapping[str, Any]) -> None:
    import zarr

    zarr.open_group(str(path), mode="r+").attrs.update(dict(attrs))


def _check_append_compatible(path: Path, ds: xr.Dataset) -> None:
    import zarr

    g = zarr.open_group(str(path), mode="r")
    if VAR_INTENSITY in g:
        have = tuple(g[VAR_INTENSITY].shape[1:])
        want = tuple(ds[VAR_INTENSITY].shape[1:])
        if have != want:
            raise InputError(
                f"{path}: store holds images of shape {have}, cannot append shape {want}"
            )
    missing = [v for v in g.array_keys() if v not in ds.variables and v not in (DIM_RANGE, DIM_BEAM)]
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


# ---------------------------------------------------------------------- reading
def _is_store(path: Path) -> bool:
    return path.is_dir() and ((path / "zarr.json").exists() or (path / ".zgroup").exists())


def _open_group(path: Path) -> Any:
    import zarr

    if not _is_store(path):
        raise DataFormatError("not a zarr survey store (no zarr.json/.zgroup)", path)
    try:
        return zarr.open_group(str(path), mode="r")
    except Exception as exc:  # noqa: BLE001 - zarr raises many types on corrupt metadata
        raise DataFormatError(f"cannot open zarr store: {exc}", path) from None


def _read_state(path: Path) -> _State:
    g = _open_group(path)
    attrs = dict(g.attrs)
    try:
        st = _State(
            geometries=list(json.loads(attrs.get(ATTR_GEOMETRIES, "[]"))),
            sources=list(json.loads(attrs.get(ATTR_SOURCES, "[]"))),
            pose_frame=str(attrs.get(ATTR_POSE_FRAME, "")),
        )
    except (json.JSONDecodeError, TypeError) as exc:
        raise DataFormatError(f"corrupt survey attributes ({exc})", path) from None
    core = {VAR_INTENSITY, VAR_GEOMETRY, VAR_SOURCE, VAR_POSITION, VAR_ORIENTATION, COORD_RANGE,
            COORD_AZIMUTH, DIM_PING, DIM_RANGE, DIM_BEAM}
    for name in g.array_keys():
        arr = g[name]
        if name.startswith(META_PREFIX):
            st.meta[name[len(META_PREFIX):]] = str(arr.attrs.get("sonarmap_kind", "float"))
        elif name not in core:
            dims = _dims(arr)
            if dims and dims[0] == DIM_PING:
                try:
                    fill = float(arr.attrs.get("sonarmap_fill_value", "nan"))
                except ValueError:
                    fill = math.nan
                st.extras[name] = PingVariable(
                    name, tuple(dims[1:]), dtype=str(arr.dtype), units=str(arr.attrs.get("units", "1")),
                    long_name=str(arr.attrs.get("long_name", "")), fill_value=fill,
                )
    if VAR_INTENSITY in g:
        st.shape = tuple(g[VAR_INTENSITY].shape[1:])  # type: ignore[assignment]
    return st


def _dims(arr: Any) -> tuple[str, ...]:
    """Dimension names of a zarr array written by xarray (v3 metadata or v2 attribute)."""
    dims = getattr(arr.metadata, "dimension_names", None)
    if dims is None:
        dims = arr.attrs.get("_ARRAY_DIMENSIONS")
    return tuple(dims or ())


def _ping_lengths(g: Any) -> dict[str, int]:
    out = {}
    for name in g.array_keys():
        arr = g[name]
        dims = _dims(arr)
        if dims and dims[0] == DIM_PING:
            out[name] = int(arr.shape[0])
    return out


def _n_pings(path: Path) -> int:
    lengths = _ping_lengths(_open_group(path))
    return min(lengths.values()) if lengths else 0


def open_survey(path: str | os.PathLike[str], *, repair: bool = False) -> xr.Dataset:
    """Open a survey store lazily (dask-backed, chunked along ``ping_time``).

    Raises
    ------
    DataFormatError
        If the path is not a survey store, or an interrupted append left arrays of different
        lengths (pass ``repair=True`` to truncate them to the common length).
    """
    import xarray as xr

    p = Path(path)
    g = _open_group(p)
    if VAR_INTENSITY not in g:
        raise DataFormatError(f"zarr store has no '{VAR_INTENSITY}' variable (not a survey)", p)
    lengths = _ping_lengths(g)
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

        gw = zarr.open_group(str(p), mode="r+")
        for name, length in lengths.items():
            if length != n:
                arr = gw[name]
                arr.resize((n, *arr.shape[1:]))
    try:
        ds = xr.open_zarr(p, consolidated=False, chunks={})
    except Exception as exc:  # noqa: BLE001
        raise DataFormatError(f"cannot open survey: {exc}", p) from None
    ds.encoding["source"] = str(p)
    return ds


def survey_geometries(ds: xr.Dataset) -> list[SonarGeometry]:
    """The distinct geometries of a survey dataset (indexed by ``geometry_index``)."""
    try:
        return [_geometry_from_json(s) for s in json.loads(ds.attrs.get(ATTR_GEOMETRIES, "[]"))]
    except (json.JSONDecodeError, TypeError, ValueError) as exc:
        raise DataFormatError(f"corrupt {ATTR_GEOMETRIES} attribute ({exc})") from None


def dataset_to_pings(
    ds: xr.Dataset,
    *,
    geometry: SonarGeometry | None = None,
    source: str | None = None,
) -> Iterator[Ping]:
    """Lazily rebuild pings from a survey dataset, one ``ping_time`` chunk in memory at a time."""
    geoms = survey_geometries(ds)
    sources = json.loads(ds.attrs.get(ATTR_SOURCES, "[]"))
    frame = str(ds.attrs.get(ATTR_POSE_FRAME, "")) or "ned"
    n = int(ds.sizes.get(DIM_PING, 0))
    chunk = 16
    enc_chunks = ds[VAR_INTENSITY].encoding.get("chunks") or ds[VAR_INTENSITY].encoding.get("preferred_chunks")
    if isinstance(enc_chunks, tuple | list) and enc_chunks:
        chunk = int(enc_chunks[0])
    meta_vars = [v for v in ds.data_vars if str(v).startswith(META_PREFIX)]
    times = ds[DIM_PING].values.astype("datetime64[ns]").astype(np.int64)
    for i0 in range(0, n, chunk):
        sl = slice(i0, min(i0 + chunk, n))
        try:
            block = ds.isel({DIM_PING: sl}).compute()  # one dask pass for all variables
        except Exception as exc:  # noqa: BLE001 - codecs/zarr raise many types on corrupt chunks
            raise DataFormatError(
                f"cannot read pings {sl.start}-{sl.stop - 1}: {type(exc).__name__}: {exc}",
                ds.encoding.get("source"),
            ) from None
        img = np.asarray(block[VAR_INTENSITY].values, dtype=np.float32)
        gi = block[VAR_GEOMETRY].values
        si = block[VAR_SOURCE].values if VAR_SOURCE in block else np.zeros(img.shape[0], int)
        pos = block[VAR_POSITION].values if VAR_POSITION in block else None
        quat = block[VAR_ORIENTATION].values if VAR_ORIENTATION in block else None
        metas = {v: (block[v].values, block[v].attrs.get("sonarmap_kind", "float")) for v in meta_vars}
        for k in range(img.shape[0]):
            i = i0 + k
            meta: dict[str, Any] = {}
            for v, (vals, kind) in metas.items():
                x = vals[k]
                key = str(v)[len(META_PREFIX):]
                if kind == "int":
                    if int(x) != INT_MISSING:
                        meta[key] = int(x)
                elif np.isfinite(x):
                    meta[key] = bool(x) if kind == "bool" else float(x)
            pose = None
            if pos is not None and quat is not None and np.all(np.isfinite(pos[k])):
                pose = Pose(position_m=pos[k], orientation_xyzw=quat[k], frame=frame)
            if geometry is not None:
                g = geometry
            elif 0 <= int(gi[k]) < len(geoms):
                g = geoms[int(gi[k])]
            else:
                raise DataFormatError(
                    f"ping {i}: geometry_index {int(gi[k])} outside the {len(geoms)} stored geometries"
                )
            src = source if source is not None else (
                sources[int(si[k])] if 0 <= int(si[k]) < len(sources) else ""
            )
            yield Ping(image=img[k], geometry=g, time_ns=int(times[i]), pose=pose, source=src, meta=meta)


# ---------------------------------------------------------------------- extra variables
def add_ping_variable(path: str | os.PathLike[str], var: PingVariable, *, chunk_pings: int | None = None) -> None:
    """Add an (unwritten, fill-valued) per-ping variable to an existing survey store.

    Existing variables of the same name are left as they are (the call is idempotent, so a
    resumed batch run can call it again).
    """
    import dask.array as da
    import xarray as xr

    p = Path(path)
    g = _open_group(p)
    if var.name in g:
        return
    st = _read_state(p)
    if st.shape is None:
        raise DataFormatError("store has no intensity variable", p)
    n = _n_pings(p)
    shape = (n, *_extra_shape(var, st.shape))
    cp = chunk_pings or int(g[VAR_INTENSITY].chunks[0])
    data = da.full(shape, var.fill_value, dtype=var.dtype, chunks=(cp, *shape[1:]))
    ds = xr.Dataset({var.name: ((DIM_PING, *var.dims), data, var.attrs())}, attrs=dict(g.attrs))
    enc: dict[str, Any] = {var.name: {"chunks": (cp, *shape[1:])}}
    if np.dtype(var.dtype).kind in "iub":
        enc[var.name]["fill_value"] = None
    ds.to_zarr(p, mode="a", encoding=enc, consolidated=False, compute=True)


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
    g = _open_group(p)
    if name not in g:
        raise InputError(f"{p}: no variable {name!r}; declare it with add_ping_variable first")
    arr = g[name]
    vals = np.asarray(values, dtype=arr.dtype)
    if vals.shape[1:] != tuple(arr.shape[1:]):
        raise InputError(f"{name}: values of shape {vals.shape[1:]} per ping, store has {arr.shape[1:]}")
    if not 0 <= start and start + vals.shape[0] <= arr.shape[0]:
        raise InputError(f"{name}: pings {start}..{start + vals.shape[0]} outside 0..{arr.shape[0]}")
    ds = xr.Dataset({name: (_dims(arr), vals)}, attrs=dict(g.attrs))
    ds.to_zarr(p, region={DIM_PING: slice(start, start + vals.shape[0])}, consolidated=False)

