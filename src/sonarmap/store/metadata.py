"""The metadata of sonarmap's zarr stores: documents, root attributes and consolidated metadata.

Every metadata document is read bounded and checked (:func:`read_metadata_doc`: one
:class:`~sonarmap.errors.DataFormatError` naming the file for anything wrong).  Root attributes
that hold JSON (the geometries of a store, their sources) are written and parsed here.

Both stores carry consolidated metadata (zarr 3: inline in the root ``zarr.json``), so
``xarray.open_zarr`` opens them without a warning.  A writer removes it before it changes any
array or attribute (:func:`invalidate_consolidated`) and writes it again when done
(:func:`consolidate`): an interrupted change leaves a store without consolidated metadata (which
xarray reads, with its warning, from the arrays' own metadata), never a stale one.  sonarmap's own
readers never use consolidated metadata: they parse and check every array's ``zarr.json``
(:func:`consolidated_status` tells whether the consolidated copy agrees with them).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from sonarmap._atomic import atomic_write_bytes, write_error
from sonarmap._config import jsonable
from sonarmap._files import MAX_SIDECAR_BYTES, read_bytes_bounded
from sonarmap.errors import DataFormatError
from sonarmap.geometry import SonarGeometry, geometry_from_dict

__all__ = ["consolidate", "consolidated_status", "geometry_from_json", "geometry_json", "int_attr",
           "invalidate_consolidated", "is_zarr_store", "json_string_list", "node_docs", "one_line",
           "read_metadata_doc", "read_root_attrs", "with_consolidated"]

_ROOT = "zarr.json"
_KEY = "consolidated_metadata"


# ---------------------------------------------------------------------- documents and attributes
def is_zarr_store(path: Path) -> bool:
    """Whether ``path`` is a directory holding a zarr group (v3 ``zarr.json`` or v2 ``.zgroup``)."""
    return path.is_dir() and ((path / "zarr.json").exists() or (path / ".zgroup").exists())


def one_line(exc: BaseException, limit: int = 200) -> str:
    """An exception's message on one line, at most ``limit`` characters."""
    msg = " ".join(str(exc).split()) or type(exc).__name__
    return msg if len(msg) <= limit else msg[: limit - 3] + "..."


def read_metadata_doc(path: Path, what: str = "group metadata") -> dict[str, Any]:
    """A zarr metadata document (a JSON object of at most 16 MiB: a root ``zarr.json`` holds every
    array's metadata inline).

    Raises
    ------
    DataFormatError
        Naming the file, if it is missing, not a regular file, too large, not UTF-8, not JSON, or
        not a JSON object.
    """
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
        raise DataFormatError(f"{what} is not valid JSON ({one_line(exc)})", path) from None
    if not isinstance(doc, dict):
        raise DataFormatError(f"{what} is a JSON {type(doc).__name__}, expected an object", path)
    return doc


def read_root_attrs(store: Path) -> dict[str, Any] | None:
    """The root attributes of a store, or ``None`` if it has no readable root ``zarr.json``."""
    try:
        doc = read_metadata_doc(store / _ROOT)
    except DataFormatError:
        return None
    attrs = doc.get("attributes", {})
    return attrs if isinstance(attrs, dict) else None


def int_attr(attrs: Mapping[str, Any], key: str, store: Path, *, low: int = 0) -> int:
    """Root attribute ``key``, an integer >= ``low`` (else a DataFormatError naming zarr.json)."""
    v = attrs.get(key)
    if isinstance(v, bool) or not isinstance(v, int) or v < low:
        raise DataFormatError(f"root attribute {key} is {v!r:.40}, expected an integer >= {low}", store / "zarr.json")
    return v


def json_string_list(raw: Any) -> list[str] | None:
    """The list of strings in the JSON text ``raw`` (an attribute), or ``None`` if it is not one."""
    try:
        out = json.loads(raw) if isinstance(raw, str) else None
    except (ValueError, RecursionError):
        return None
    return out if isinstance(out, list) and all(isinstance(s, str) for s in out) else None


def geometry_json(geometry: SonarGeometry, *, with_source: bool = True) -> str:
    """A sonar geometry as the JSON text of a root attribute.

    The raw-ping store records each geometry with its ``azimuth_source``, keys sorted
    (``with_source=True``); a product store's ``source_geometry`` is the geometry's dict as it
    always was (``with_source=False``).  :func:`geometry_from_json` reads both.
    """
    d = geometry.to_dict()
    if not with_source:
        return json.dumps(jsonable(d))
    d["azimuth_source"] = geometry.azimuth_source
    return json.dumps(d, sort_keys=True)


def geometry_from_json(text: str, source: str, *, default_source: str | None = None) -> SonarGeometry:
    """The geometry of a :func:`geometry_json` text (``source`` names it in errors); its azimuth
    source is the recorded one, else ``default_source``, else what the geometry's dict implies.

    Raises
    ------
    Exception
        Whatever parsing raises on corrupt text (the callers say which attribute it is).
    """
    d = json.loads(text)
    src = d.pop("azimuth_source", default_source) if isinstance(d, dict) else None
    g = geometry_from_dict(d, source=source)
    return g if src is None or g.azimuth_source == src else dataclasses.replace(g, azimuth_source=src)


# ---------------------------------------------------------------------- consolidated metadata
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
        doc = read_metadata_doc(Path(dirpath) / _ROOT, "node metadata")
        key = "/".join(Path(rel).parts)
        out[key] = doc
        if doc.get("node_type") != "group":
            dirnames[:] = []  # an array: below it are chunks only
    return dict(sorted(out.items()))


def with_consolidated(doc: dict[str, Any], nodes: Mapping[str, dict[str, Any]]) -> dict[str, Any]:
    """The root document ``doc`` with the consolidated metadata of ``nodes`` (:func:`node_docs`)
    inline, as ``zarr.consolidate_metadata`` writes it (nodes sorted by key)."""
    doc[_KEY] = {"kind": "inline", "must_understand": False, "metadata": dict(sorted(nodes.items()))}
    return doc


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
    _write_doc(meta, with_consolidated(doc, node_docs(root)))


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
