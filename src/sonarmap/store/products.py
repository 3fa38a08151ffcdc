"""The product store of ``sonarmap process`` / ``sonarmap live``: schema, creation, resume markers,
progress, checked opening and loading, summary.

Layout (zarr v3, readable with :func:`open_products` / ``xarray.open_zarr``; dimensions and
coordinates those of every sonarmap store, :mod:`sonarmap.datamodel`)::

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
complete metadata or not at all.  Every chunk carries a CRC32C checksum; :func:`load_products`
(what ``sonarmap report`` reads) checks the metadata, the chunks and every value against the
documented ranges of the variables (:data:`PRODUCT_RANGES`).  Chunk ``k`` of every variable holds
pings ``k * chunk_size ...``; the survey stage (:mod:`sonarmap.survey`) fills them, the live
appender (:mod:`sonarmap.store.appender`) grows a store as pings arrive.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
import warnings
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap._atomic import atomic_write_text, remove_output, replace_output, temp_dir_beside, write_error
from sonarmap._config import config_dict, jsonable
from sonarmap.datamodel import (
    COORD_ATTRS,
    COORD_AZIMUTH,
    COORD_RANGE,
    COORDINATES,
    DIM_BEAM,
    DIM_PING,
    DIM_RANGE,
    INFORMATIONAL_FLAGS,
    PRODUCT_FILL,
    PRODUCT_RANGES,
    PRODUCT_VARIABLES,
    SURVEY_FORMAT,
    TIME_UNITS,
)
from sonarmap.errors import DataFormatError, InputError, SonarmapError
from sonarmap.ping import Ping, source_file
from sonarmap.store.check import (
    CheckedStore,
    check_chunk_files,
    check_times,
    check_values,
    crc_failures,
    inspect_store,
    kind_of,
    locate_error,
    read_array,
)
from sonarmap.store.chunks import (
    STATE_DIR,
    TMP_DIR,
    array_codec_kwargs,
    chunk_key,
    create_array,
    ignore_zarr_warnings,
)
from sonarmap.store.metadata import (
    consolidate,
    consolidated_status,
    geometry_from_json,
    geometry_json,
    int_attr,
    one_line,
    read_root_attrs,
)
from sonarmap.store.records import mixture_arrays, product_record, product_schema

#: Delete an existing output (renamed aside first: never half-deleted in place).
remove_store = remove_output

__all__ = [
    "DEFAULT_CHUNK_SIZE",
    "LIVE_SETTLE_S",
    "complete_marker",
    "create_products",
    "finish_store",
    "done_chunks",
    "damaged_chunks",
    "flagged_mask",
    "inspect_products",
    "is_product_store",
    "load_products",
    "marker_dir",
    "open_products",
    "product_ping",
    "product_summary",
    "reference_range",
    "remove_marker_temporaries",
    "remove_store",
    "store_geometry",
    "survey_status",
    "unmark_chunk",
    "write_marker",
]

#: Pings per task of ``sonarmap process`` and per zarr chunk of its store (hundreds keep overheads
#: negligible).
DEFAULT_CHUNK_SIZE = 256


def flagged_mask(flags: Iterable[Any]) -> NDArray[np.bool_]:
    """Which pings have a flagged fit: any flag other than :data:`INFORMATIONAL_FLAGS`.

    ``flags`` holds one space-separated flag string per ping (the ``flags`` variable).
    """
    return np.array([bool(set(str(f).split()) - INFORMATIONAL_FLAGS) for f in flags], dtype=bool)


# ---------------------------------------------------------------------- markers and progress
def marker_dir(store: Path) -> Path:
    """The directory of the per-chunk completion markers of a store."""
    return store / STATE_DIR / "chunks"


def done_chunks(store: Path) -> set[int]:
    """The chunks of a store marked complete."""
    d = marker_dir(store)
    if not d.is_dir():
        return set()
    out = set()
    for name in os.listdir(d):
        if name.endswith(".done"):
            with contextlib.suppress(ValueError):
                out.add(int(name[:-5]))
    return out


def _marker(store: Path, chunk_index: int) -> Path:
    """The completion marker file of chunk ``chunk_index``."""
    return marker_dir(store) / f"{chunk_index:08d}.done"


def write_marker(store: Path, chunk_index: int, start: int, stop: int) -> None:
    """The chunk's completion marker, written atomically once its data files are in place."""
    marker = _marker(store, chunk_index)
    # No scan for stale temporaries per marker (that would be quadratic in the chunks): the run
    # clears the marker directory's leftovers once, at its start (:func:`remove_marker_temporaries`).
    atomic_write_text(marker, json.dumps({"start": start, "stop": stop}) + "\n", clean=False)


def unmark_chunk(store: Path, chunk_index: int) -> None:
    """Remove the completion marker of chunk ``chunk_index`` and the store's :func:`complete_marker`
    (the chunk is to be computed again)."""
    complete_marker(store).unlink(missing_ok=True)
    _marker(store, chunk_index).unlink(missing_ok=True)


def damaged_chunks(st: CheckedStore, names: Iterable[str]) -> dict[int, DataFormatError]:
    """The chunks (along the ping dimension) in which a chunk file of one of the product variables
    ``names`` is missing or fails its CRC32C (:func:`~sonarmap.store.check.crc_failures`): chunk
    index -> the error of its first bad file.  Reads every chunk file once (no decoding): cheap
    next to computing the products."""
    out: dict[int, DataFormatError] = {}
    for _, coords, exc in crc_failures(st.path, names):
        out.setdefault(coords[0], exc)
    return dict(sorted(out.items()))


def remove_marker_temporaries(store: Path) -> None:
    """Remove what killed runs left among the markers: temporary files (``.<k>.done.*``) - call
    only while holding the store's lock (no other run writes markers then)."""
    d = marker_dir(store)
    for name in os.listdir(d) if d.is_dir() else ():
        if name.startswith("."):
            with contextlib.suppress(OSError):
                os.unlink(d / name)


def complete_marker(store: Path) -> Path:
    """The file that says a store is complete (every chunk stored; a JSON summary)."""
    return store / STATE_DIR / "complete"


def finish_store(store: Path, n_pings: int, n_flagged: int) -> None:
    """Mark a store complete: its emptied temporary directory removed, then - unless it exists -
    :func:`complete_marker` written (atomically) with the pings and flagged fits."""
    with contextlib.suppress(OSError):
        os.rmdir(store / TMP_DIR)  # empty once every chunk is stored
    marker = complete_marker(store)
    if not marker.exists():
        atomic_write_text(marker, json.dumps({"n_pings": n_pings, "n_flagged": n_flagged}) + "\n")


def survey_status(store: str | os.PathLike[str]) -> dict[str, Any]:
    """Progress of a survey store: ``n_chunks``, ``done`` (count), ``complete``, ``fingerprint``.

    Raises
    ------
    DataFormatError
        If ``store`` is not a sonarmap survey store.
    """
    p = Path(store)
    attrs = read_root_attrs(p)
    if attrs is None or attrs.get("sonarmap_format") != SURVEY_FORMAT:
        if (p / "zarr.json").is_file():
            inspect_store(p)  # a corrupt root zarr.json: say what is wrong with it
        raise not_a_product_store(p)
    return {
        "n_chunks": int_attr(attrs, "n_chunks", p),
        "n_pings": int_attr(attrs, "n_pings", p),
        "done": len(done_chunks(p)),
        "complete": complete_marker(p).exists(),
        "fingerprint": attrs.get("fingerprint"),
    }


# ---------------------------------------------------------------------- creation
def create_products(path: str | os.PathLike[str], geometry: Any, products: Any, *, config: Any, keep_labels: bool,
                    chunk_size: int, n_pings: int, n_chunks: int, inputs: list[str], n_input_files: int,
                    poses: str | None, fingerprint: str,
                    extra_attrs: Mapping[str, Any] | None = None) -> dict[str, tuple[tuple[int, ...], str]]:
    """Create an empty product store of ``n_pings`` pings for the sonar ``geometry``, atomically.

    The variables and their shapes come from one ping's ``products`` (:func:`product_record`),
    the static coordinates from ``geometry`` (one product store holds one sonar geometry); the
    root attributes record the provenance (``config``, ``inputs``, ``poses``, ``fingerprint``)
    and ``extra_attrs``.  The store is built beside ``path`` and renamed onto it.

    Returns
    -------
    dict
        The schema: variable -> (shape without the ping dimension, dtype).

    Raises
    ------
    DataFormatError
        If the store cannot be written (naming it).
    """
    import zarr

    schema = product_schema(product_record(products, keep_labels=keep_labels))
    attrs = _root_attrs(geometry, config_dict(config), schema, keep_labels=keep_labels, chunk_size=chunk_size,
                        n_pings=n_pings, n_chunks=n_chunks, n_input_files=n_input_files, inputs=inputs,
                        poses=poses, fingerprint=fingerprint)
    attrs.update(extra_attrs or {})
    out = Path(path)
    try:
        tmp = temp_dir_beside(out)
    except OSError as exc:
        raise write_error(exc, out, "cannot create the store") from None
    try:
        ignore_zarr_warnings()  # not catch_warnings: a live store is created in its writer thread
        root = zarr.open_group(str(tmp), mode="w", zarr_format=3, attributes=attrs)
        _create_variables(root, schema, n_pings, chunk_size, mixture_arrays(products.fit)[2])
        _create_coordinates(root, tmp, geometry, n_pings, chunk_size)
        (tmp / STATE_DIR / "chunks").mkdir(parents=True)
        consolidate(tmp)
        replace_output(tmp, out)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError) and not isinstance(exc, SonarmapError):
            raise write_error(exc, out, "cannot create the store") from None
        raise
    return schema


def _create_variables(root: Any, schema: Mapping[str, tuple[tuple[int, ...], str]], n: int, k: int,
                      component_names: Sequence[str]) -> None:
    """The product variables of ``schema``: ``n`` pings in chunks of ``k``, fill-valued, CF attributes."""
    for name, (shape, dtype) in schema.items():
        dims, vattrs = PRODUCT_VARIABLES[name]
        vattrs = dict(vattrs)
        if name == DIM_PING:
            vattrs.update(units=TIME_UNITS, calendar="proleptic_gregorian")
        if DIM_BEAM in dims:
            vattrs["coordinates"] = COORD_AZIMUTH
        if name.startswith("mixture_") and component_names:
            vattrs["components"] = " ".join(component_names)
        dt: Any = str if dtype == "str" else np.dtype(dtype)
        fill: Any = "" if dtype == "str" else PRODUCT_FILL[name]
        root.create_array(name, shape=(n, *shape), chunks=(k, *shape), dtype=dt, fill_value=fill,
                          dimension_names=dims, attributes=vattrs, **array_codec_kwargs())


def _create_coordinates(root: Any, store: Path, geometry: Any, n: int, k: int) -> None:
    """The coordinates of a product store: ``range_sample``, ``beam``, ``beam_azimuth`` (beam) and
    ``echo_range`` (ping_time, range_sample) - the layout of every sonarmap store (:mod:`sonarmap.datamodel`)."""
    for name, values in ((DIM_RANGE, np.arange(geometry.n_bins, dtype=np.int32)),
                         (DIM_BEAM, np.arange(geometry.n_beams, dtype=np.int32)),
                         (COORD_AZIMUTH, np.asarray(geometry.azimuth_rad, np.float64))):
        create_array(root, name, values, shape=values.shape, dtype=values.dtype, dimension_names=COORDINATES[name],
                     attributes=dict(COORD_ATTRS[name]))
    _write_echo_range(root, store, np.asarray(geometry.range_m, np.float64), n, k)


def _root_attrs(geom: Any, cfg_dict: dict[str, Any], schema: Mapping[str, tuple[tuple[int, ...], str]], *,
                keep_labels: bool, chunk_size: int, n_pings: int, n_chunks: int, n_input_files: int,
                inputs: list[str], poses: str | None, fingerprint: str) -> dict[str, Any]:
    """The root attributes of a new product store: format, provenance, chunking and schema."""
    from sonarmap import __version__

    return {
        "sonarmap_format": SURVEY_FORMAT,
        "sonarmap_version": __version__,
        "title": "sonarmap survey products",
        "Conventions": "CF-1.8",
        "source_geometry": geometry_json(geom, with_source=False),
        "pipeline_config": json.dumps(jsonable(cfg_dict), sort_keys=True),
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


def _write_echo_range(root: Any, store: Path, range_m: NDArray[np.float64], n: int, k: int) -> None:
    """``echo_range (ping_time, range_sample)`` of a product store: every ping's row is ``range_m``.

    One product store holds one sonar geometry (:func:`sonarmap.survey.run_chunk` refuses pings
    of another), so the coordinate is known when the store is created.  Every full chunk holds the
    same values, hence the same bytes: the first is encoded by zarr and copied to the others' files.
    """
    arr = create_array(root, COORD_RANGE, shape=(n, range_m.size), chunks=(k, range_m.size), dtype=np.float64,
                       fill_value=np.nan, dimension_names=COORDINATES[COORD_RANGE],
                       attributes=dict(COORD_ATTRS[COORD_RANGE]))
    if n == 0:
        return
    full = n // k
    rows = np.broadcast_to(range_m, (min(n, k), range_m.size))
    arr[: rows.shape[0]] = rows
    if full > 1:
        data = (store / COORD_RANGE / chunk_key((0, 0))).read_bytes()
        for i in range(1, full):
            f = store / COORD_RANGE / chunk_key((i, 0))
            f.parent.mkdir(parents=True, exist_ok=True)
            f.write_bytes(data)
    if n % k and full:
        arr[full * k :] = np.broadcast_to(range_m, (n - full * k, range_m.size))


# ---------------------------------------------------------------------- checking
def inspect_products(p: Path) -> tuple[CheckedStore, dict[str, tuple[tuple[int, ...], str]]]:
    """Check a product store's metadata: every document parses, the schema's arrays exist with
    the shapes, dimensions and dtypes it gives, the coordinates exist, the time units are ns.

    Raises
    ------
    DataFormatError
        Naming the store and the file or array at fault (``not a sonarmap survey store`` for a
        directory that is not one).
    """
    if not (p / "zarr.json").is_file() and not (p / ".zgroup").exists():
        raise not_a_product_store(p)
    st = inspect_store(p)
    meta = st.meta_file()
    if st.attrs.get("sonarmap_format") != SURVEY_FORMAT:
        raise not_a_product_store(p)
    n = int_attr(st.attrs, "n_pings", p)
    int_attr(st.attrs, "n_chunks", p)
    int_attr(st.attrs, "chunk_size", p, low=1)
    schema = _parse_schema(st.attrs.get("schema"), meta)
    _check_schema_arrays(st, schema, n)
    _check_coordinates(st, schema, n)
    _check_point_arrays(st)
    st.require_time_units(DIM_PING, TIME_UNITS)
    return st, schema


def _parse_schema(raw: Any, meta: Path) -> dict[str, tuple[tuple[int, ...], str]]:
    """The root attribute ``schema`` as ``{name: (shape, dtype)}``; it must name the required variables."""
    schema: dict[str, tuple[tuple[int, ...], str]] = {}
    try:
        for name, (shape, dtype) in raw.items():
            if not isinstance(name, str) or not isinstance(dtype, str) or not all(
                    isinstance(k, int) and not isinstance(k, bool) and k >= 0 for k in shape):
                raise TypeError(name)
            schema[name] = (tuple(shape), dtype)
    except (AttributeError, TypeError, ValueError):
        raise DataFormatError("root attribute schema is not {name: [shape, dtype]}", meta) from None
    for name in (DIM_PING, "source", "flags", "kld", "range"):
        if name not in schema:
            raise DataFormatError(f"root attribute schema lacks the required variable {name}", meta)
    return schema


def _check_schema_arrays(st: CheckedStore, schema: Mapping[str, tuple[tuple[int, ...], str]], n: int) -> None:
    """Each variable of the schema is a known product, stored as an array of ``n`` pings with the
    schema's shape and dtype and the product's dimensions."""
    meta = st.meta_file()
    for name, (shape, dtype) in schema.items():
        if name not in PRODUCT_VARIABLES:
            raise DataFormatError(f"root attribute schema names an unknown variable {name!r:.40}", meta)
        arr = st.require(name, what="sonarmap survey store")
        if tuple(arr.shape) != (n, *shape):
            raise DataFormatError(f"array '{name}' has shape {tuple(arr.shape)}, the store's schema says "
                                  f"{(n, *shape)}", st.meta_file(name))
        st.require_dims(name, PRODUCT_VARIABLES[name][0])
        ok = kind_of(arr) == "T" if dtype == "str" else np.dtype(arr.dtype) == np.dtype(dtype)
        if not ok:
            raise DataFormatError(f"array '{name}' has data type {arr.dtype}, the store's schema says {dtype}",
                                  st.meta_file(name))


def _check_coordinates(st: CheckedStore, schema: Mapping[str, tuple[tuple[int, ...], str]], n: int) -> None:
    """The azimuth and range coordinates exist with the survey's beam and bin counts, and the index
    coordinates (when present) match them."""
    sizes = {DIM_BEAM: schema["range"][0][0] if schema["range"][0] else None,
             DIM_RANGE: schema["labels"][0][0] if "labels" in schema else _n_bins(st.attrs)}
    for name, dim in ((COORD_AZIMUTH, DIM_BEAM), (COORD_RANGE, DIM_RANGE)):
        arr = st.require(name, kinds="f", what="sonarmap survey store")
        # echo_range is (ping_time, range_sample); stores of earlier versions hold (range_sample)
        allowed = [(dim,)] + ([COORDINATES[COORD_RANGE]] if name == COORD_RANGE else [])
        if st.dims(name) not in allowed or len(arr.shape) != len(st.dims(name)):
            raise DataFormatError(f"array '{name}' has dimensions {st.dims(name)}, expected "
                                  f"{' or '.join(str(a) for a in allowed)}", st.meta_file(name))
        if len(arr.shape) == 2 and int(arr.shape[0]) != n:
            raise DataFormatError(f"array '{name}' has {arr.shape[0]} along {DIM_PING}, the survey has {n}",
                                  st.meta_file(name))
        if sizes[dim] is not None and int(arr.shape[-1]) != sizes[dim]:
            raise DataFormatError(f"array '{name}' has {arr.shape[-1]} along {dim}, the survey has {sizes[dim]}",
                                  st.meta_file(name))
    for name, dim in ((DIM_RANGE, DIM_RANGE), (DIM_BEAM, DIM_BEAM)):
        if name in st.arrays:  # index coordinates (absent in stores of earlier versions)
            arr = st.require(name, ndim=1, kinds="iu", what="sonarmap survey store")
            if st.dims(name) != (dim,) or int(arr.shape[0]) != int(st.arrays[COORD_RANGE if dim == DIM_RANGE
                                                                            else COORD_AZIMUTH].shape[-1]):
                raise DataFormatError(f"array '{name}' has shape {tuple(arr.shape)} / dimensions {st.dims(name)}, "
                                      "inconsistent with the coordinates", st.meta_file(name))


def _check_point_arrays(st: CheckedStore) -> None:
    """The ``point_*`` arrays (when present) are ``(point, ...)`` of one length; ``point_xyz`` is (point, 3)."""
    points = {name: arr for name, arr in st.arrays.items() if name.startswith("point_")}
    for name, arr in points.items():
        if not arr.shape or st.dims(name)[:1] != ("point",) or (
                int(arr.shape[0]) != int(next(iter(points.values())).shape[0])) or (
                name == "point_xyz" and tuple(arr.shape[1:]) != (3,)):
            raise DataFormatError(f"array '{name}' has shape {tuple(arr.shape)} / dimensions {st.dims(name)}, "
                                  "inconsistent with the other point arrays", st.meta_file(name))


def _n_bins(attrs: Mapping[str, Any]) -> int | None:
    """Range bins of the survey's sonar (``source_geometry`` attribute), if recorded."""
    try:
        n = json.loads(attrs.get("source_geometry", "{}")).get("num_bins")
    except (TypeError, ValueError, AttributeError, RecursionError):
        return None
    return n if isinstance(n, int) and not isinstance(n, bool) else None


def not_a_product_store(path: Path) -> DataFormatError:
    """The error for ``path`` where a product store of ``sonarmap process`` is needed: it does
    not exist, it is the raw-ping store of ``sonarmap convert`` (to be processed first), or it is
    something else."""
    from sonarmap.datamodel import ATTR_MODEL

    if not path.exists():
        return DataFormatError("no such file or directory", path)
    attrs = read_root_attrs(path) if path.is_dir() else None
    if attrs is not None and ATTR_MODEL in attrs:
        return DataFormatError("is a store of raw pings (sonarmap convert), not a sonarmap survey store of "
                               f"products: process it first (sonarmap process {path} -o products.zarr)", path)
    return DataFormatError("not a sonarmap survey store (the product store written by sonarmap process)", path)


def is_product_store(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a product store written by :func:`sonarmap.survey.process_survey` (root attributes only)."""
    p = Path(path)
    if not p.is_dir():
        return False
    attrs = read_root_attrs(p)
    return attrs is not None and attrs.get("sonarmap_format") == SURVEY_FORMAT


def store_geometry(st: CheckedStore) -> Any:
    """The sonar geometry of a product store (its ``source_geometry`` attribute)."""
    try:
        return geometry_from_json(st.attrs.get("source_geometry", ""), "source_geometry attribute")
    except (TypeError, ValueError, RecursionError, AttributeError) as exc:
        raise DataFormatError(f"root attribute source_geometry is not a geometry ({one_line(exc, 160)})",
                              st.meta_file()) from None


def product_summary(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What ``sonarmap info`` says about a product store: pings, time span, variables, flagged fits.

    The metadata is checked (:func:`inspect_products`); only the times and flags of the completed
    chunks are read (a run still in progress, or interrupted, is summarised as far as it got).

    Returns
    -------
    dict
        :func:`sonarmap.io.make_summary` fields (``format`` is ``"zarr-products"``) plus
        ``pings_done``, ``complete``, ``flagged``, ``variables``, ``keep_labels``, ``chunk_pings``,
        ``consolidated`` (see :func:`sonarmap.store.metadata.consolidated_status`).

    Raises
    ------
    DataFormatError
        If the store's metadata, times or flags are corrupt (naming the store, array and chunk).
    """
    from sonarmap.io import make_summary

    p = Path(path)
    st, schema = inspect_products(p)
    status = survey_status(p)
    k = int_attr(st.attrs, "chunk_size", p, low=1)
    n = int_attr(st.attrs, "n_pings", p)
    # Only the completed chunks: those of an interrupted run's unfinished chunks are not written.
    spans = [slice(c * k, min((c + 1) * k, n)) for c in sorted(done_chunks(p)) if c * k < n]
    times = np.concatenate([np.asarray(read_array(st, DIM_PING, s), np.int64) for s in spans]
                           ) if spans else np.zeros(0, np.int64)
    check_times(times, p)
    flags = np.concatenate([read_array(st, "flags", s) for s in spans]) if spans else np.zeros(0, object)
    geometry = store_geometry(st)
    return make_summary(
        "zarr-products", p, n_pings=n, geometry=geometry,
        time_start_ns=int(times.min()) if times.size else None,
        time_end_ns=int(times.max()) if times.size else None,
        pings_done=int(times.size),
        complete=bool(status["complete"]),
        flagged=int(flagged_mask(flags).sum()),
        variables=sorted(schema),
        keep_labels=bool(st.attrs.get("keep_labels", False)),
        chunk_pings=k,
        consolidated=consolidated_status(p),
        sonarmap_version=str(st.attrs.get("sonarmap_version", "")),
    )


# ---------------------------------------------------------------------- reading


def reference_range(st: CheckedStore) -> NDArray[np.float64]:
    """The bin ranges of a product store's sonar: ``echo_range`` (its first row in this layout)."""
    arr = st.arrays[COORD_RANGE]
    if len(arr.shape) == 1:  # a store of an earlier version
        return np.asarray(read_array(st, COORD_RANGE), np.float64)
    if int(arr.shape[0]) == 0:
        return np.zeros(int(arr.shape[1]), np.float64)
    return np.asarray(read_array(st, COORD_RANGE, slice(0, 1))[0], np.float64)


#: How long :func:`open_products` keeps trying while a live run is publishing a flush (s).
LIVE_SETTLE_S = 2.0


def _live_status(path: Path) -> str | None:
    """The root attribute ``live_status`` of a store written by a live run ("writing" while it
    appends, "complete" after); None for other stores."""
    attrs = read_root_attrs(path)
    v = None if attrs is None else attrs.get("live_status")
    return v if isinstance(v, str) else None


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


def _geometry_to_read(st: Any, file: str) -> Any:
    """The geometry to read a source ping with again: the store's for a PNG/BMP image without a
    sidecar JSON (the survey was given its geometry, e.g. ``--sonar``), else None (the file's
    own)."""
    from sonarmap.io.pngjson import IMAGE_SUFFIXES, sidecar_json

    if Path(file).suffix.lower() in IMAGE_SUFFIXES and not os.path.lexists(sidecar_json(file)):
        return store_geometry(st)
    return None


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
        With the store's geometry (labels) or the source's (raw; the store's for a PNG/BMP image
        without a sidecar JSON, whose survey was given its geometry), the stored time and source;
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

    file = source_file(source)
    if not file or not os.path.exists(file):
        raise DataFormatError(f"ping {i}: its source {file!r:.200} is not available (and no labels are stored)", p)
    sources = [source_file(str(x)) for x in read_array(st, "source", slice(0, i))]
    raw = read_ping(file, index=sum(1 for x in sources if x == file), geometry=_geometry_to_read(st, file))
    if raw.time_ns != t:
        raise DataFormatError(f"ping {i}: the ping read from {file} has another time than the stored one "
                              "(the source changed)", p)
    return raw.replace(meta={**raw.meta, "image": "raw"})
