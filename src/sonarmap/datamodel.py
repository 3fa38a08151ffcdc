"""The data model of sonarmap's zarr stores, in one place: dimensions, coordinates, CF attributes.

Both kinds of store share one coordinate layout - the raw-ping store that ``sonarmap convert``
writes (:mod:`sonarmap.store.pings`) and the product store that ``sonarmap process`` writes
(:mod:`sonarmap.survey`)::

    dimensions    ping_time, range_sample, beam
    ping_time     (ping_time)                int64 ns since 1970, decoded as datetime64[ns]
    range_sample  (range_sample)             int32 0 .. n_bins - 1 (0 = nearest)
    beam          (beam)                     int32 0 .. n_beams - 1 (azimuth increases with beam)
    echo_range    (ping_time, range_sample)  float64, m: the range of each bin of each ping's
                                             geometry (the range window can change between pings)
    beam_azimuth  (beam)                     float64, rad, positive to starboard: the store's
                                             azimuth table; (ping_time, beam) only in a raw-ping
                                             store whose pings' tables differ (beam-steered
                                             multibeams), see :func:`azimuth_dims`

``echo_range`` and ``beam_azimuth`` are coordinates (``xarray.open_zarr`` lists them under
``Coordinates``) in both stores.  Stores written before this layout still read: raw-ping stores
with ``beam_azimuth (ping_time, beam)`` always, product stores with ``echo_range (range_sample)``
and no ``range_sample`` / ``beam`` index arrays.

Both stores carry consolidated metadata (zarr 3: inline in the root ``zarr.json``), so
``xarray.open_zarr`` opens them without a warning.  A writer removes it before it changes any
array or attribute (:func:`invalidate_consolidated`) and writes it again when done
(:func:`consolidate`): an interrupted change leaves a store without consolidated metadata (which
xarray reads, with its warning, from the arrays' own metadata), never a stale one.  sonarmap's own
readers never use consolidated metadata: they parse and check every array's ``zarr.json``
(:func:`consolidated_status` tells whether the consolidated copy agrees with them).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from sonarmap._atomic import atomic_write_bytes, write_error
from sonarmap.errors import DataFormatError

__all__ = [
    "DIM_PING",
    "DIM_RANGE",
    "DIM_BEAM",
    "DIM_XYZ",
    "DIM_QUAT",
    "COORD_RANGE",
    "COORD_AZIMUTH",
    "VAR_INTENSITY",
    "COORD_ATTRS",
    "COORDINATES",
    "azimuth_dims",
    "consolidate",
    "invalidate_consolidated",
    "consolidated_status",
    "read_metadata_doc",
    "node_docs",
]

DIM_PING = "ping_time"
DIM_RANGE = "range_sample"
DIM_BEAM = "beam"
DIM_XYZ = "xyz"
DIM_QUAT = "quaternion"
VAR_INTENSITY = "intensity"
COORD_RANGE = "echo_range"
COORD_AZIMUTH = "beam_azimuth"

#: CF attributes of the dimensions and coordinates (the single definition both stores use).
COORD_ATTRS: dict[str, dict[str, str]] = {
    DIM_PING: {"long_name": "Ping transmit time (UTC)", "axis": "T", "standard_name": "time"},
    DIM_RANGE: {"long_name": "Range sample number (0 = nearest)", "units": "1"},
    DIM_BEAM: {"long_name": "Beam number (azimuth increases with beam)", "units": "1"},
    COORD_RANGE: {"long_name": "Range from the transducer to the range bin", "units": "m"},
    COORD_AZIMUTH: {
        "long_name": "Beam centre azimuth in the sonar frame, positive to starboard",
        "units": "rad",
    },
}

#: The coordinates of both stores: name -> dimensions (``beam_azimuth``: see :func:`azimuth_dims`).
COORDINATES: dict[str, tuple[str, ...]] = {
    DIM_PING: (DIM_PING,),
    DIM_RANGE: (DIM_RANGE,),
    DIM_BEAM: (DIM_BEAM,),
    COORD_RANGE: (DIM_PING, DIM_RANGE),
    COORD_AZIMUTH: (DIM_BEAM,),
}


def azimuth_dims(per_ping: bool) -> tuple[str, ...]:
    """Dimensions of ``beam_azimuth``: ``(beam,)``, or ``(ping_time, beam)`` if the tables differ.

    Parameters
    ----------
    per_ping : bool
        Whether the pings of the store have different azimuth tables.

    Returns
    -------
    tuple of str
    """
    return (DIM_PING, DIM_BEAM) if per_ping else (DIM_BEAM,)


# ---------------------------------------------------------------------- consolidated metadata
_ROOT = "zarr.json"
_KEY = "consolidated_metadata"


#: Largest metadata document read here (the root ``zarr.json`` with every array's metadata inline).
MAX_METADATA_BYTES = 16 * 1024 * 1024


def read_metadata_doc(path: Path) -> dict[str, Any]:
    """A zarr metadata document (JSON object of at most ``MAX_METADATA_BYTES``), else a DataFormatError."""
    try:
        if os.stat(path).st_size > MAX_METADATA_BYTES:
            raise DataFormatError(f"group metadata is larger than {MAX_METADATA_BYTES} bytes", path)
        doc = json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, ValueError, RecursionError) as exc:
        raise DataFormatError(f"group metadata is unreadable ({type(exc).__name__})", path) from None
    if not isinstance(doc, dict):
        raise DataFormatError("group metadata is not a JSON object", path)
    return doc


def _write_doc(path: Path, doc: dict[str, Any]) -> None:
    try:
        atomic_write_bytes(path, json.dumps(doc, indent=2).encode("utf-8"), clean=False)
    except OSError as exc:
        raise write_error(exc, path.parent, "cannot write the group metadata") from None


def node_docs(root: Path) -> dict[str, dict[str, Any]]:
    """The ``zarr.json`` of every node below ``root`` (key: path relative to ``root``, ``/``-separated)."""
    out: dict[str, dict[str, Any]] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        rel = os.path.relpath(dirpath, root)
        dirnames[:] = sorted(d for d in dirnames
                             if not d.startswith(".") and not os.path.islink(os.path.join(dirpath, d)))
        if rel == ".":
            continue
        if _ROOT not in filenames:
            dirnames[:] = []
            continue
        doc = read_metadata_doc(Path(dirpath) / _ROOT)
        key = "/".join(Path(rel).parts)
        out[key] = doc
        if doc.get("node_type") != "group":
            dirnames[:] = []  # an array: below it are chunks only
    return dict(sorted(out.items()))


def consolidate(path: str | os.PathLike[str]) -> None:
    """Write the consolidated metadata of a zarr v3 store (inline in its root ``zarr.json``), atomically.

    The same document ``zarr.consolidate_metadata`` writes (every node's ``zarr.json``), but the
    root file is replaced in one rename, so an interrupted write never leaves it half written.
    A zarr v2 store (no root ``zarr.json``) is left as it is.

    Raises
    ------
    DataFormatError
        If a metadata document cannot be read or the root cannot be written (naming the file).
    """
    root = Path(path)
    meta = root / _ROOT
    if not meta.is_file():
        return
    doc = read_metadata_doc(meta)
    doc[_KEY] = {"kind": "inline", "must_understand": False, "metadata": node_docs(root)}
    _write_doc(meta, doc)


def invalidate_consolidated(path: str | os.PathLike[str]) -> None:
    """Remove the consolidated metadata of a store (before its arrays or attributes change).

    Raises
    ------
    DataFormatError
        If the root metadata cannot be read or written (naming the file).
    """
    meta = Path(path) / _ROOT
    if not meta.is_file():
        return
    doc = read_metadata_doc(meta)
    if doc.get(_KEY) is None:
        return
    doc.pop(_KEY)
    _write_doc(meta, doc)


def consolidated_status(path: str | os.PathLike[str]) -> str:
    """Whether a store's consolidated metadata agrees with its nodes' own metadata.

    Returns
    -------
    str
        ``"current"`` (it lists exactly the nodes' documents), ``"stale"`` (it differs - readers
        that trust it would be misled; re-consolidate) or ``"absent"``.
    """
    root = Path(path)
    meta = root / _ROOT
    if not meta.is_file():
        return "absent"
    try:
        cm = read_metadata_doc(meta).get(_KEY)
    except DataFormatError:
        return "absent"
    if not isinstance(cm, dict) or not isinstance(cm.get("metadata"), dict):
        return "absent"
    try:
        nodes = node_docs(root)
    except DataFormatError:
        return "stale"
    return "current" if cm["metadata"] == nodes else "stale"
