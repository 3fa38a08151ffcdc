"""Consolidated metadata of sonarmap's zarr stores.

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

__all__ = ["consolidate", "consolidated_status", "invalidate_consolidated", "node_docs", "read_metadata_doc"]

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
