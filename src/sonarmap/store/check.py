"""Checking a zarr store before and while it is read: metadata, chunk files, checksums, values.

:func:`inspect_store` parses every metadata document of a store and opens each array (one
:class:`~sonarmap.errors.DataFormatError` naming the file for anything wrong, never a foreign
exception) into a :class:`CheckedStore`.  Chunk files are checked to be regular files of plausible
size before zarr opens them (:func:`check_chunk_files`: no FIFO, device or absurdly large file is
ever read) and, in arrays written with a ``crc32c`` codec, to exist.  A read that fails is turned
into an error naming the array and chunk (:func:`locate_error`: the chunks' CRC32C first, then one
chunk at a time through zarr).  :func:`check_values` and :func:`check_times` check values against
their documented ranges, naming the store, variable and ping.  Both kinds of store (raw pings and
products) are read through these functions.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap._files import read_bytes_bounded, require_regular_file
from sonarmap.datamodel import DIM_PING, TIME_MAX_NS, TIME_UNITS_RE
from sonarmap.errors import DataFormatError
from sonarmap.store.chunks import chunk_key, crc32c_suffix
from sonarmap.store.metadata import is_zarr_store, one_line, read_metadata_doc

__all__ = [
    "CheckedStore",
    "MAX_CHUNK_BYTES",
    "check_chunk_files",
    "check_times",
    "check_values",
    "crc_failures",
    "inspect_store",
    "kind_of",
    "locate_error",
    "read_array",
]



# ---------------------------------------------------------------------- metadata
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

    def require_dims(self, name: str, expected: tuple[str, ...]) -> None:
        """A :class:`DataFormatError` naming array ``name`` if its dimensions are not ``expected``."""
        dims = self.dims(name)
        if dims != expected:
            raise DataFormatError(f"array '{name}' has dimensions {dims}, expected {expected}", self.meta_file(name))

    def require_time_units(self, name: str, expected: str) -> None:
        """A :class:`DataFormatError` naming array ``name`` if its ``units`` are not int64 nanoseconds
        since 1970 (:data:`~sonarmap.datamodel.TIME_UNITS_RE`; ``expected`` is named in the message)."""
        units = self.arrays[name].attrs.get("units")
        if not isinstance(units, str) or not TIME_UNITS_RE.fullmatch(units):
            raise DataFormatError(f"array '{name}' has units {units!r:.60}, expected {expected!r}", self.meta_file(name))

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
    if not is_zarr_store(path):
        raise DataFormatError("not a zarr survey store (no zarr.json/.zgroup)", path)
    fmt = 3 if (path / "zarr.json").exists() else 2
    _check_group_doc(path, fmt)
    names = _array_names(path, fmt)
    try:
        # never the consolidated copy: every array's own (checked) metadata is what is read
        group = zarr.open_group(str(path), mode="r", zarr_format=fmt, use_consolidated=False)
        attrs = dict(group.attrs)
    except Exception as exc:  # noqa: BLE001 - zarr raises many types on corrupt metadata
        raise DataFormatError(f"group metadata: {one_line(exc)}", path / ("zarr.json" if fmt == 3 else ".zgroup")) from None
    arrays: dict[str, Any] = {}
    for name in names:
        arr = _open_array(group, name, path / name / ("zarr.json" if fmt == 3 else ".zarray"))
        if arr is not None:
            arrays[name] = arr
    return CheckedStore(path, fmt, group, attrs, arrays)


def _read_optional(path: Path, what: str) -> None:
    """Check the metadata document ``path`` if it exists (zarr v2 ``.zattrs``)."""
    if os.path.lexists(path):
        read_metadata_doc(path, what)


def _check_group_doc(path: Path, fmt: int) -> None:
    """The root group's metadata document(s) of a zarr ``fmt`` store parse and describe a group."""
    if fmt == 3:
        root = read_metadata_doc(path / "zarr.json", "group metadata")
        if root.get("zarr_format") != 3 or root.get("node_type") != "group":
            raise DataFormatError("group metadata: not a zarr v3 group (zarr_format/node_type)", path / "zarr.json")
        if "attributes" in root and not isinstance(root["attributes"], dict):
            raise DataFormatError("group metadata: 'attributes' is not an object", path / "zarr.json")
    else:
        root = read_metadata_doc(path / ".zgroup", "group metadata")
        if root.get("zarr_format") != 2:
            raise DataFormatError("group metadata: not a zarr v2 group (zarr_format)", path / ".zgroup")
        _read_optional(path / ".zattrs", "group attributes")


def _array_names(path: Path, fmt: int) -> list[str]:
    """The arrays directly below the root (sorted), each one's metadata document checked."""
    names = []
    try:
        entries = sorted(os.listdir(path))
    except OSError as exc:
        raise DataFormatError(f"cannot list the store: {exc.strerror or exc}", path) from None
    for name in entries:
        d = path / name
        if name.startswith(".") or not d.is_dir():
            continue
        meta = d / ("zarr.json" if fmt == 3 else ".zarray")
        if not os.path.lexists(meta):
            continue
        doc = read_metadata_doc(meta, "array metadata")
        if fmt == 3 and doc.get("node_type") == "group":
            continue
        _check_array_doc(doc, fmt, meta)
        if fmt == 2:
            _read_optional(d / ".zattrs", "array attributes")
        names.append(name)
    return names


def _open_array(group: Any, name: str, meta: Path) -> Any:
    """Array ``name`` of ``group`` opened and its metadata checked (``None`` for a sub-group)."""
    import zarr

    try:
        arr = group[name]
        _ = arr.dtype, arr.shape, arr.chunks, dict(arr.attrs)
        dims = _dims(arr)
        if dims and len(dims) != len(arr.shape):
            raise DataFormatError(f"{len(dims)} dimension names for {len(arr.shape)} dimensions")
    except DataFormatError as exc:
        raise DataFormatError(f"array metadata: {exc}", meta) from None
    except Exception as exc:  # noqa: BLE001
        raise DataFormatError(f"array metadata: {type(exc).__name__}: {one_line(exc)}", meta) from None
    if not hasattr(arr, "shape") or isinstance(arr, zarr.Group):
        return None
    n_chunk = int(np.prod([int(c) for c in arr.chunks], dtype=object)) if arr.chunks else 1
    if n_chunk > MAX_CHUNK_BYTES:
        raise DataFormatError(f"array metadata: chunks of {n_chunk} elements are larger than sonarmap reads", meta)
    return arr


# ---------------------------------------------------------------------- chunks and values
def chunk_grid(shape: Sequence[int], chunks: Sequence[int], rows: slice | None = None) -> Iterator[tuple[int, ...]]:
    """Grid coordinates of the chunks of an array of ``shape`` in ``chunks`` that cover rows ``rows``
    of its first dimension (all rows if ``None``); ``()`` once for a 0-d array."""
    import itertools

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


def _chunk_coords(arr: Any, rows: slice | None = None) -> Iterator[tuple[int, ...]]:
    """Chunk-grid coordinates of the zarr array ``arr`` covering rows ``rows`` (:func:`chunk_grid`)."""
    return chunk_grid(tuple(arr.shape), tuple(arr.chunks), rows)


def _chunk_key(arr: Any, coords: tuple[int, ...]) -> str:
    """The store key of chunk ``coords`` of ``arr`` (``c/1/0/0`` in v3, ``1.0.0`` in v2)."""
    try:
        return str(arr.metadata.encode_chunk_key(coords))
    except Exception:  # noqa: BLE001 - only for messages
        return chunk_key(coords)


def _reason(exc: BaseException) -> str:
    """What a failed chunk decode means, for the message."""
    msg = one_line(exc, 160)
    if "checksum" in msg.lower():
        return "checksum mismatch (the chunk file is corrupt)"
    return f"corrupt, cannot be decoded ({type(exc).__name__}: {msg})"


#: Largest chunk (decoded bytes) sonarmap reads; a store's writers use a few MB.
MAX_CHUNK_BYTES = 1 << 30


#: Bytes per element assumed for variable-length strings when bounding a chunk's size.
_STRING_ITEM_BYTES = 1024


def _encoded_limit(chunks: Sequence[int], item: int) -> int:
    """Largest plausible size of one encoded chunk file of ``chunks`` elements of ``item`` bytes
    (zstd's worst case + checksum)."""
    raw = int(np.prod([int(c) for c in chunks], dtype=object)) * max(int(item), 1)
    return raw + raw // 64 + 4096


def _chunk_limit(arr: Any) -> int:
    """:func:`_encoded_limit` of the zarr array ``arr``."""
    try:
        item = int(np.dtype(arr.dtype).itemsize) if kind_of(arr) != "T" else _STRING_ITEM_BYTES
    except TypeError:
        item = _STRING_ITEM_BYTES
    return _encoded_limit(tuple(arr.chunks or ()), item)


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

    Cheap enough for the error path: no zarr round trips, just the files.  Returns the error of
    the first bad chunk (:func:`crc_failures`), or ``None`` (nothing found, or no checksums to check).
    """
    return next((exc for _, _, exc in crc_failures(path, names, rows)), None)


def crc_failures(path: Path, names: Iterable[str],
                 rows: slice | None = None) -> Iterator[tuple[str, tuple[int, ...], DataFormatError]]:
    """Every missing or corrupt chunk file of the checksummed arrays ``names`` of the store ``path``.

    For arrays whose last codec is ``crc32c`` (the 4-byte little-endian CRC32C of the rest of the
    file is appended), each chunk file covering ``rows`` is read and its checksum recomputed;
    other arrays are skipped.  Yields ``(array, chunk coordinates, error)`` per bad chunk file.
    """
    for name in names:
        layout = _crc_layout(path / name / "zarr.json")
        if layout is None:
            continue
        shape, chunks, sep, v2, limit = layout
        for coords in chunk_grid(shape, chunks, rows):
            key = chunk_key(coords, separator=sep, v2=v2)
            f = path / name / key
            try:
                size = os.stat(f).st_size
            except OSError:
                yield name, coords, DataFormatError(f"array '{name}', chunk {key}: missing (deleted?)", path)
                continue
            try:
                # bounded by the file's size (read() allocates its bound) and by what a chunk can take
                data = read_bytes_bounded(f, min(size, limit), f"chunk file of array '{name}'")
            except DataFormatError as exc:
                yield name, coords, exc
                continue
            if len(data) < 4 or data[-4:] != crc32c_suffix(data[:-4]):
                yield name, coords, DataFormatError(
                    f"array '{name}', chunk {key}: checksum mismatch (the chunk file is corrupt)", path)


def _crc_layout(meta: Path) -> tuple[list[int], list[int], str, bool, int] | None:
    """``(shape, chunks, key separator, v2 keys, largest chunk file)`` of a zarr v3 array whose last
    codec is ``crc32c``; ``None`` for any other array or unreadable metadata."""
    try:
        doc = json.loads(meta.read_text(encoding="utf-8"))
        if [c.get("name") if isinstance(c, dict) else c for c in doc["codecs"]][-1] != "crc32c":
            return None
        shape = [int(x) for x in doc["shape"]]
        chunks = [int(x) for x in doc["chunk_grid"]["configuration"]["chunk_shape"]]
        cke = doc.get("chunk_key_encoding") or {}
        sep = (cke.get("configuration") or {}).get("separator", "/")
        if len(shape) != len(chunks) or any(c <= 0 for c in chunks):
            return None
        dt = doc.get("data_type")
        item = np.dtype(dt).itemsize if isinstance(dt, str) and dt != "string" else _STRING_ITEM_BYTES
        return shape, chunks, sep, cke.get("name") == "v2", _encoded_limit(chunks, item)
    except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError, OverflowError):
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
    return DataFormatError(f"{prefix or 'cannot read: '}{type(exc).__name__}: {one_line(exc)}", st.path)


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
