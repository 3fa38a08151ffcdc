"""Chunk files of a zarr store: the codecs every array is written with, and the two chunk writers.

Every array sonarmap writes is encoded ``bytes`` (or ``vlen-utf8``) -> ``zstd`` -> ``crc32c``
(:func:`checksum_codecs`): the 4-byte little-endian CRC32C of the compressed chunk is appended, so a
corrupt chunk file is an error when read, never wrong values.  Every chunk is written, even one
equal to the fill value, so a missing chunk file is recognised as damage.

Two writers put whole chunks of a product store along ``ping_time``:

* :class:`ChunkRows` writes through zarr's own API (batch runs: a worker process writes its own
  chunk into the shared store; distinct chunks are distinct files, safe for concurrent writers).
* :class:`ChunkWriter` encodes the chunk files itself, exactly as zarr would (edge chunks padded
  with the fill value, default chunk keys ``c/<k>/0/...``), and writes each one atomically
  (temporary file in ``.sonarmap/tmp``, then ``os.replace``), so a reader of a growing store never
  sees a torn chunk.  A flush of the 21 product variables costs ~4 ms of CPU this way against
  ~29 ms through ``zarr.Array.__setitem__`` (event-loop round trips, metadata reads, all holding
  the GIL that the live processing loop needs; measured on one flush of 16 pings), which is why
  the live appender (:class:`sonarmap.store.ProductAppender`) uses it.  Arrays whose metadata uses
  anything else (e.g. written by another tool) are not handled: :meth:`ChunkWriter.open` returns
  ``None``.

Both check before every chunk that the store directory is still the one they were made for
(``(st_dev, st_ino)``): a store removed or re-created since (``--overwrite`` while a killed run's
worker is still busy) raises :class:`StoreReplacedError` instead of being written into.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import struct
import uuid
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from sonarmap._atomic import write_error
from sonarmap.errors import SonarmapError

__all__ = ["ChunkRange", "ChunkRows", "ChunkWriter", "STATE_DIR", "StoreReplacedError", "TMP_DIR", "ZSTD_LEVEL",
           "array_codec_kwargs", "checksum_codecs", "chunk_key", "create_array", "crc32c_suffix", "open_writable",
           "ignore_zarr_warnings", "put_file", "remove_tmp", "store_identity"]


_zarr_warnings_ignored = False


def ignore_zarr_warnings() -> None:
    """Ignore zarr's own warning categories (its specification and deprecation notices) from now on.

    Installed once, never undone: ``warnings.catch_warnings`` swaps the process-wide filter list,
    so a writer thread inside it (a live store appending) would swallow - or restore over - the
    warnings of the processing thread meanwhile.
    """
    global _zarr_warnings_ignored
    if _zarr_warnings_ignored:
        return
    from zarr import errors

    for category in (errors.ZarrFutureWarning, errors.ZarrDeprecationWarning, errors.ZarrUserWarning,
                     errors.ZarrRuntimeWarning):
        warnings.filterwarnings("ignore", category=category)
    _zarr_warnings_ignored = True


#: zstd level of every product variable (zarr's default; level 0 = zstd's default, 3).
ZSTD_LEVEL = 0


def checksum_codecs() -> dict[str, Any]:
    """Bytes-to-bytes codecs of every array this version writes: zstd, then a CRC32C checksum.

    The ``crc32c`` codec appends the 4-byte little-endian CRC32C of the compressed chunk, so any
    corruption of a chunk file (a flipped bit, a truncated or overwritten file) is detected when
    the chunk is read instead of decoding to wrong values.
    """
    from zarr.codecs import Crc32cCodec, ZstdCodec

    return {"compressors": (ZstdCodec(level=ZSTD_LEVEL, checksum=False), Crc32cCodec())}


def array_codec_kwargs() -> dict[str, Any]:
    """Codec / key options passed to ``zarr.Group.create_array`` for product variables.

    :func:`checksum_codecs` and zarr 3's default chunk keys, pinned so the store's metadata does
    not depend on zarr's defaults - :class:`ChunkWriter` encodes exactly these.
    """
    return {**checksum_codecs(), "chunk_key_encoding": {"name": "default", "separator": "/"}}


def create_array(group: Any, name: str, values: Any = None, **kwargs: Any) -> Any:
    """``group.create_array(name, **kwargs)`` with :func:`checksum_codecs`, every chunk written
    (even one equal to the fill value); ``values``, if given, are written into it.

    Returns
    -------
    zarr.Array
    """
    arr = group.create_array(name, **kwargs, **checksum_codecs(), config={"write_empty_chunks": True})
    if values is not None:
        arr[...] = values
    return arr


def chunk_key(coords: tuple[int, ...], *, separator: str = "/", v2: bool = False) -> str:
    """The store key of the chunk at grid position ``coords``: ``c/1/0`` (zarr 3's default
    encoding), or ``1.0`` with ``v2=True`` (``separator`` ``"."``; ``0`` for a 0-d array)."""
    parts = [str(int(c)) for c in coords]
    if v2:
        return separator.join(parts or ["0"])
    return separator.join(["c", *parts])


def crc32c_suffix(data: bytes) -> bytes:
    """The 4 bytes zarr's ``crc32c`` codec appends to ``data``: its CRC32C, little endian."""
    import google_crc32c

    return struct.pack("<I", google_crc32c.value(data))


@dataclass(frozen=True)
class _Var:
    """What is needed to encode one variable's chunk files."""

    name: str
    kind: str  # "numeric" or "string"
    dtype: str  # numpy dtype string, little endian (numeric only)
    chunk_shape: tuple[int, ...]
    fill: Any
    level: int
    separator: str
    checksum: bool = False  # a crc32c codec follows zstd


#: The directory of a store's own state (resume markers, temporary files; not part of the dataset).
STATE_DIR = ".sonarmap"
#: Temporary files are written here (inside the store, so ``os.replace`` stays on one file system)
#: and moved into place; whatever an interrupted run left there is removed by the next one.
TMP_DIR = os.path.join(STATE_DIR, "tmp")


def remove_tmp(store: str | os.PathLike[str]) -> None:
    """Remove the temporary files an interrupted writer left in ``.sonarmap/tmp`` (call before
    any writer of this run starts)."""
    d = Path(store) / TMP_DIR
    for f in d.iterdir() if d.is_dir() else ():
        with contextlib.suppress(OSError):
            f.unlink()


def put_file(store: str | os.PathLike[str], target: str | os.PathLike[str], payload: bytes, what: str) -> None:
    """Write ``payload`` to ``target`` inside ``store`` atomically: a temporary file in the store's
    ``.sonarmap/tmp`` (which must exist), then ``os.replace``, so readers never see a torn file.

    Raises
    ------
    DataFormatError
        ``cannot write <what>``, naming the store, if the data cannot be written.
    """
    tmp = os.path.join(store, TMP_DIR, f"{os.getpid()}-{uuid.uuid4().hex}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(payload)
        os.replace(tmp, target)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise write_error(exc, store, f"cannot write {what}") from None
        raise


class StoreReplacedError(SonarmapError, RuntimeError):
    """The store directory is not the one the writer was made for (deleted or replaced)."""


def store_identity(store: str | os.PathLike[str]) -> tuple[int, int]:
    """``(st_dev, st_ino)`` of the store directory, which a chunk writer checks before every chunk.

    Raises
    ------
    DataFormatError
        If the store cannot be found (naming it).
    """
    try:
        st = os.stat(store)
    except OSError as exc:
        raise write_error(exc, Path(store), "cannot prepare the store for writing") from None
    return st.st_dev, st.st_ino


def _check_identity(store: str, identity: tuple[int, int], index: int) -> None:
    """Raise :class:`StoreReplacedError` if ``store`` is gone or is not the directory ``identity`` was."""
    try:
        st = os.stat(store)
    except FileNotFoundError:
        st = None
    if st is None or (st.st_dev, st.st_ino) != identity:
        raise StoreReplacedError(f"{store}: the store was removed or replaced; not writing chunk {index}")


@dataclass(frozen=True)
class ChunkWriter:
    """Writes chunk ``k`` (along the first dimension) of every product variable of a store.

    ``identity`` is the store directory's :func:`store_identity` when the writer was made; a store
    replaced since is never written into (:class:`StoreReplacedError`).
    """

    store: str
    variables: tuple[_Var, ...]
    identity: tuple[int, int]
    _made_dirs: set[str] = field(default_factory=set, compare=False, repr=False)

    # ------------------------------------------------------------------ construction
    @classmethod
    def open(cls, store: str | os.PathLike[str], names: list[str]) -> ChunkWriter | None:
        """A writer for variables ``names`` of ``store``, or ``None`` if one uses other codecs."""
        root = Path(store)
        out = []
        for name in names:
            try:
                meta = json.loads((root / name / "zarr.json").read_text(encoding="utf-8"))
            except (OSError, ValueError):
                return None
            var = _parse(name, meta)
            if var is None:
                return None
            out.append(var)
        identity = store_identity(root)
        try:
            os.makedirs(root / TMP_DIR, exist_ok=True)
        except OSError as exc:
            raise write_error(exc, root, "cannot prepare the store for writing") from None
        return cls(os.fspath(root), tuple(out), identity)

    def __getstate__(self) -> dict[str, Any]:
        return {"store": self.store, "variables": self.variables, "identity": self.identity}

    def __setstate__(self, state: dict[str, Any]) -> None:
        for k in ("store", "variables", "identity"):
            object.__setattr__(self, k, state[k])
        object.__setattr__(self, "_made_dirs", set())

    # ------------------------------------------------------------------ writing
    def encode(self, var: _Var, values: Any) -> bytes:
        """The encoded chunk file of ``values`` (leading dimension <= the chunk length)."""
        from numcodecs.zstd import Zstd

        n = len(values)
        k = var.chunk_shape[0]
        if n > k:
            raise ValueError(f"{var.name}: {n} rows do not fit a chunk of {k}")
        if var.kind == "string":
            arr = np.empty(var.chunk_shape, dtype=object)
            arr[...] = var.fill
            arr[:n] = np.asarray(values, dtype=object)
            from numcodecs.vlen import VLenUTF8

            raw = VLenUTF8().encode(arr)
        else:
            vals = np.asarray(values)
            if tuple(vals.shape[1:]) != var.chunk_shape[1:]:
                raise ValueError(f"{var.name}: rows of shape {vals.shape[1:]}, expected {var.chunk_shape[1:]}")
            if n == k:
                arr = np.ascontiguousarray(vals, dtype=var.dtype)
            else:  # edge chunk: zarr stores the full chunk shape, padded with the fill value
                arr = np.full(var.chunk_shape, var.fill, dtype=var.dtype)
                arr[:n] = vals
            raw = arr.tobytes()
        out = bytes(Zstd(level=var.level, checksum=False).encode(raw))
        return out + crc32c_suffix(out) if var.checksum else out

    def write(self, index: int, data: Mapping[str, Any]) -> None:
        """Write chunk ``index`` of every variable from ``data`` (name -> rows), atomically per file."""
        missing = [v.name for v in self.variables if v.name not in data]
        if missing:
            raise KeyError(f"chunk {index}: no data for {', '.join(missing)}")
        payloads = [(var, self.encode(var, data[var.name])) for var in self.variables]
        _check_identity(self.store, self.identity, index)
        for var, payload in payloads:
            key = chunk_key((index, *[0] * (len(var.chunk_shape) - 1)), separator=var.separator)
            path = os.path.join(self.store, var.name, *key.split(var.separator))
            parent = os.path.dirname(path)
            if parent not in self._made_dirs:
                os.makedirs(parent, exist_ok=True)
                self._made_dirs.add(parent)
            put_file(self.store, path, payload, f"chunk {os.path.relpath(path, self.store)}")


def _parse(name: str, meta: Mapping[str, Any]) -> _Var | None:
    """The :class:`_Var` of an array's ``zarr.json``, or ``None`` if not a layout we encode."""
    try:
        if meta.get("zarr_format") != 3 or meta.get("node_type") != "array":
            return None
        if meta.get("storage_transformers"):
            return None
        grid = meta["chunk_grid"]
        if grid["name"] != "regular":
            return None
        chunk_shape = tuple(int(s) for s in grid["configuration"]["chunk_shape"])
        shape = tuple(int(s) for s in meta["shape"])
        if len(chunk_shape) != len(shape) or tuple(chunk_shape[1:]) != tuple(shape[1:]):
            return None  # only chunked along the first (ping) dimension
        cke = meta["chunk_key_encoding"]
        if cke["name"] != "default":
            return None
        sep = (cke.get("configuration") or {}).get("separator", "/")
        if sep != "/":
            return None
        codecs = meta["codecs"]
        checksum = len(codecs) == 3 and codecs[2].get("name") == "crc32c" and not codecs[2].get("configuration")
        if len(codecs) not in (2, 3) or (len(codecs) == 3 and not checksum) or codecs[1]["name"] != "zstd":
            return None
        zconf = codecs[1].get("configuration") or {}
        if zconf.get("checksum", False):
            return None
        level = int(zconf.get("level", 0))
        dtype_name = meta["data_type"]
        first = codecs[0]
        if dtype_name == "string":
            if first["name"] != "vlen-utf8":
                return None
            return _Var(name, "string", "", chunk_shape, str(meta.get("fill_value", "")), level, sep, checksum)
        if first["name"] != "bytes" or not isinstance(dtype_name, str):
            return None
        dt = np.dtype(dtype_name)
        if dt.kind not in "biuf":
            return None
        endian = (first.get("configuration") or {}).get("endian", "little")
        if dt.itemsize > 1 and endian != "little":
            return None
        fill = _fill_value(meta.get("fill_value"), dt)
        return _Var(name, "numeric", dt.newbyteorder("<").str, chunk_shape, fill, level, sep, checksum)
    except (KeyError, TypeError, ValueError, AttributeError):
        return None


def _fill_value(v: Any, dt: np.dtype) -> Any:
    if isinstance(v, str):
        table = {"NaN": np.nan, "Infinity": np.inf, "-Infinity": -np.inf}
        if v not in table:
            raise ValueError(f"fill value {v!r}")
        return dt.type(table[v])
    if isinstance(v, bool):
        return dt.type(v)
    return dt.type(0 if v is None else v)


class ChunkRange(Protocol):
    """Which rows a chunk covers (:class:`sonarmap.survey.ChunkSpec` is one)."""

    index: int
    start: int
    stop: int


@dataclasses.dataclass(frozen=True)
class ChunkRows:
    """Writes one chunk's rows of every product variable through zarr's own API (picklable).

    A local worker process writes its own chunk into the shared store (distinct chunks are
    distinct files: safe for concurrent writers) and only reports success to the parent, which
    then writes the completion marker; the parent writes what comes back from dask workers and
    split chunks.  Every chunk is written, even one equal to the fill value: a checksummed store
    has all its chunks, so a missing one is recognised as damage when read.

    ``identity`` is the store directory's :func:`store_identity` when the writer was made; a store
    replaced since is never written into (:class:`StoreReplacedError`).
    """

    store: str
    identity: tuple[int, int]

    @classmethod
    def open(cls, store: str | os.PathLike[str]) -> ChunkRows:
        """A writer for the product store ``store`` (which must exist)."""
        return cls(os.fspath(store), store_identity(store))

    def write(self, chunk: ChunkRange, data: Mapping[str, Any]) -> None:
        """Write rows ``chunk.start:chunk.stop`` of every variable in ``data`` (name -> rows)."""
        import zarr

        _check_identity(self.store, self.identity, chunk.index)
        root = _open_roots.get((self.store, self.identity))
        ignore_zarr_warnings()
        with zarr.config.set({"array.write_empty_chunks": True}):
            try:
                if root is None:
                    root = _open_roots[(self.store, self.identity)] = open_writable(Path(self.store))
                for name, values in data.items():
                    root[name][chunk.start : chunk.stop] = values
            except OSError as exc:
                raise write_error(exc, Path(self.store), f"cannot write chunk {chunk.index}") from None


#: The writable root group of each store this process writes chunks into (opened once).
_open_roots: dict[tuple[str, tuple[int, int]], Any] = {}


def open_writable(path: Path) -> Any:
    """The store's root zarr group, writable."""
    import zarr

    return zarr.open_group(str(path), mode="r+", zarr_format=3, use_consolidated=False)
