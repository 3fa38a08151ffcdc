"""The product store of ``sonarmap process`` (read side): its variables, detection, progress,
metadata check and summary.

The store is written by :mod:`sonarmap.survey` (which re-exports these names); reading it is io's
business, so that the store reader (:mod:`sonarmap.io.zarrstore`) and ``sonarmap info`` recognise
and describe a product store without importing the survey stage.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap._files import MAX_SIDECAR_BYTES, read_bytes_bounded
from sonarmap.datamodel import COORDINATES, consolidated_status
from sonarmap.errors import DataFormatError
from sonarmap.io._binary import make_summary
from sonarmap.io.dataset import ATTRS as DATA_MODEL_ATTRS
from sonarmap.io.dataset import (
    COORD_AZIMUTH,
    COORD_RANGE,
    DIM_BEAM,
    DIM_PING,
    DIM_RANGE,
    TIME_UNITS_RE,
    CheckedStore,
    check_times,
    inspect_store,
    kind_of,
    read_array,
)

__all__ = [
    "STATE_DIR",
    "SURVEY_FORMAT",
    "TIME_UNITS",
    "DIM_OTHER",
    "N_OTHER_RETURNS",
    "PRODUCT_VARIABLES",
    "INFORMATIONAL_FLAGS",
    "flagged_mask",
    "marker_dir",
    "done_chunks",
    "read_root_attrs",
    "int_attr",
    "survey_status",
    "inspect_products",
    "is_product_store",
    "store_geometry",
    "product_summary",
]


#: Marker directory inside the store (not part of the dataset).
STATE_DIR = ".sonarmap"
#: The ``sonarmap_format`` root attribute of a product store.
SURVEY_FORMAT = "sonarmap-survey/1"
#: The CF units of the stored ping times.
TIME_UNITS = "nanoseconds since 1970-01-01T00:00:00"
#: Dimension of ``other_range``: the surfaces behind a beam's return that are stored.
DIM_OTHER = "other_return"
#: At most this many surfaces behind each return are stored (``other_range``).
N_OTHER_RETURNS = 2

#: Product variables: name -> (dims, attrs).  Dimension names follow the survey data model
#: (echopype style: ``ping_time``, ``range_sample``, ``beam``); ``component`` and ``parameter``
#: index the mixture model.
PRODUCT_VARIABLES: dict[str, tuple[tuple[str, ...], dict[str, str]]] = {
    DIM_PING: ((DIM_PING,), dict(DATA_MODEL_ATTRS[DIM_PING])),
    "source": ((DIM_PING,), {"long_name": "Source file (and frame) of the ping"}),
    "kld": ((DIM_PING,), {"long_name": "Kullback-Leibler divergence, data || mixture fit",
                          "units": "nat"}),
    "flags": ((DIM_PING,), {"long_name": "Fit quality flags, space separated (empty: none)"}),
    "background_range_db": ((DIM_PING,), {
        "long_name": "Range dependence of the estimated background level (90th / 10th percentile over "
                     "range; NaN: image not normalised, e.g. thresholded)", "units": "dB"}),
    "floor_levels": ((DIM_PING,), {
        "long_name": "Levels of the classified image merged into its zero level before the ping was modelled "
                     "(the quantisation floor; 0: none)", "units": "1"}),
    "mixture_weight": ((DIM_PING, "component"), {"long_name": "Mixture component weight",
                                                 "units": "1"}),
    "mixture_param": ((DIM_PING, "component", "parameter"),
                      {"long_name": "Mixture component parameters, scale last (NaN: unused)"}),
    "pd": ((DIM_PING,), {"long_name": "Probability of detection at the chosen threshold",
                         "units": "1"}),
    "pfa": ((DIM_PING,), {"long_name": "Probability of false alarm at the chosen threshold",
                          "units": "1"}),
    "range": ((DIM_PING, DIM_BEAM), {"long_name": "Range to the first return per beam (NaN: none)",
                                     "units": "m",
                                     "description": "Leading edge of the return's echo along the beam: the "
                                                    "first crossing of half its peak, interpolated "
                                                    "between range bins, on the edge-aligned mean profile "
                                                    "of up to 7 neighbouring beams of the same surface "
                                                    "(the echo's peak in strongest mode)"}),
    "range_bin": ((DIM_PING, DIM_BEAM), {"long_name": "Range-bin index of the return (-1: none)",
                                         "units": "1"}),
    "range_intensity": ((DIM_PING, DIM_BEAM), {"long_name": "Intensity at the return", "units": "1"}),
    "range_confidence": ((DIM_PING, DIM_BEAM), {"long_name": "Confidence of the return",
                                                "units": "1"}),
    "range_sigma": ((DIM_PING, DIM_BEAM), {
        "long_name": "One-sigma uncertainty of the return's range (NaN: no return or no estimate)",
        "units": "m",
        "description": "Standard deviation of the error of range, estimated per echo by the ranges "
                       "stage (sonarmap.ranges.echoes)"}),
    "p_detect": ((DIM_PING, DIM_BEAM), {
        "long_name": "Probability that a surface in the beam is detected and reported (NaN: unknown)",
        "units": "1",
        "description": "The occupancy map's per-beam pD: P(the beam reports a return | a surface in "
                       "the beam), for the hit and the free-space updates of that beam"}),
    "other_range": ((DIM_PING, DIM_OTHER, DIM_BEAM), {
        "long_name": "Ranges of further surfaces behind the return, nearest first (NaN: none)",
        "units": "m",
        "description": "Leading edges of the echoes of further surfaces on the beam behind the "
                       f"reported return; at most {N_OTHER_RETURNS}, NaN-padded"}),
    "labels": ((DIM_PING, DIM_RANGE, DIM_BEAM),
               {"long_name": "Segmentation labels (1: object, 0: free space)", "units": "1"}),
}


#: Flags that describe the scene rather than a doubtful fit (not counted as "flagged fits").
INFORMATIONAL_FLAGS = frozenset({"no_returns", "no_object", "collapsed"})


def flagged_mask(flags: Iterable[Any]) -> NDArray[np.bool_]:
    """Which pings have a flagged fit: any flag other than :data:`INFORMATIONAL_FLAGS`.

    ``flags`` holds one space-separated flag string per ping (the ``flags`` variable).
    """
    return np.array([bool(set(str(f).split()) - INFORMATIONAL_FLAGS) for f in flags], dtype=bool)


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


def read_root_attrs(store: Path) -> dict[str, Any] | None:
    """The root attributes of a store, or ``None`` if it has no readable root ``zarr.json``."""
    meta = store / "zarr.json"
    try:
        d = json.loads(read_bytes_bounded(meta, MAX_SIDECAR_BYTES, "group metadata").decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        return None
    attrs = d.get("attributes", {}) if isinstance(d, dict) else None
    return attrs if isinstance(attrs, dict) else None


def int_attr(attrs: Mapping[str, Any], key: str, store: Path, *, low: int = 0) -> int:
    """Root attribute ``key``, an integer >= ``low`` (else a DataFormatError naming zarr.json)."""
    v = attrs.get(key)
    if isinstance(v, bool) or not isinstance(v, int) or v < low:
        raise DataFormatError(f"root attribute {key} is {v!r:.40}, expected an integer >= {low}", store / "zarr.json")
    return v


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
        raise DataFormatError("not a sonarmap survey store", p)
    return {
        "n_chunks": int_attr(attrs, "n_chunks", p),
        "n_pings": int_attr(attrs, "n_pings", p),
        "done": len(done_chunks(p)),
        "complete": (p / STATE_DIR / "complete").exists(),
        "fingerprint": attrs.get("fingerprint"),
    }


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
        raise DataFormatError("not a sonarmap survey store", p)
    st = inspect_store(p)
    meta = st.meta_file()
    if st.attrs.get("sonarmap_format") != SURVEY_FORMAT:
        raise DataFormatError("not a sonarmap survey store", p)
    n = int_attr(st.attrs, "n_pings", p)
    int_attr(st.attrs, "n_chunks", p)
    int_attr(st.attrs, "chunk_size", p, low=1)
    schema = _parse_schema(st.attrs.get("schema"), meta)
    _check_schema_arrays(st, schema, n)
    _check_coordinates(st, schema, n)
    _check_point_arrays(st)
    units = st.arrays[DIM_PING].attrs.get("units")
    if not isinstance(units, str) or not TIME_UNITS_RE.fullmatch(units):
        raise DataFormatError(f"array '{DIM_PING}' has units {units!r:.60}, expected {TIME_UNITS!r}",
                              st.meta_file(DIM_PING))
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
        dims = st.dims(name)
        if dims != PRODUCT_VARIABLES[name][0]:
            raise DataFormatError(f"array '{name}' has dimensions {dims}, expected {PRODUCT_VARIABLES[name][0]}",
                                  st.meta_file(name))
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


def is_product_store(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a product store written by :func:`sonarmap.survey.process_survey` (root attributes only)."""
    p = Path(path)
    if not p.is_dir():
        return False
    attrs = read_root_attrs(p)
    return attrs is not None and attrs.get("sonarmap_format") == SURVEY_FORMAT


def store_geometry(st: CheckedStore) -> Any:
    """The sonar geometry of a product store (its ``source_geometry`` attribute)."""
    from sonarmap.geometry import geometry_from_dict

    try:
        d = json.loads(st.attrs.get("source_geometry", ""))
        return geometry_from_dict(d, source="source_geometry attribute")
    except (TypeError, ValueError, RecursionError, AttributeError) as exc:
        raise DataFormatError(f"root attribute source_geometry is not a geometry ({_short(exc)})",
                              st.meta_file()) from None


def _short(exc: BaseException) -> str:
    msg = " ".join(str(exc).split()) or type(exc).__name__
    return msg[:160]


def product_summary(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What ``sonarmap info`` says about a product store: pings, time span, variables, flagged fits.

    The metadata is checked (:func:`inspect_products`); only the times and flags of the completed
    chunks are read (a run still in progress, or interrupted, is summarised as far as it got).

    Returns
    -------
    dict
        :func:`sonarmap.io.make_summary` fields (``format`` is ``"zarr-products"``) plus
        ``pings_done``, ``complete``, ``flagged``, ``variables``, ``keep_labels``, ``chunk_pings``,
        ``consolidated`` (see :func:`sonarmap.datamodel.consolidated_status`).

    Raises
    ------
    DataFormatError
        If the store's metadata, times or flags are corrupt (naming the store, array and chunk).
    """
    p = Path(path)
    st, schema = inspect_products(p)
    status = survey_status(p)
    k = int_attr(st.attrs, "chunk_size", p, low=1)
    n = int_attr(st.attrs, "n_pings", p)
    rows = np.zeros(n, bool)
    for c in done_chunks(p):
        rows[c * k : (c + 1) * k] = True
    times = np.asarray(read_array(st, DIM_PING), np.int64)[rows] if rows.any() else np.zeros(0, np.int64)
    check_times(times, p)
    flags = read_array(st, "flags")[rows] if rows.any() else np.zeros(0, object)
    geometry = store_geometry(st)
    return make_summary(
        "zarr-products", p, n_pings=n, geometry=geometry,
        time_start_ns=int(times.min()) if times.size else None,
        time_end_ns=int(times.max()) if times.size else None,
        pings_done=int(rows.sum()),
        complete=bool(status["complete"]),
        flagged=int(flagged_mask(flags).sum()),
        variables=sorted(schema),
        keep_labels=bool(st.attrs.get("keep_labels", False)),
        chunk_pings=k,
        consolidated=consolidated_status(p),
        sonarmap_version=str(st.attrs.get("sonarmap_version", "")),
    )
