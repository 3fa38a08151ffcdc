"""Ping readers and writers; :func:`read_pings` is the single entry point.

Formats are detected by content (magic bytes), not only by extension.  Each format module in
:data:`FORMAT_MODULES` is a :class:`~sonarmap.io.reader.Reader`::

    FORMAT: str                                     # short name, e.g. "aris"
    def sniff(path: Path, head: bytes) -> bool      # does this file look like our format?
    def count_pings(path) -> int                    # cheap (headers only)
    def iter_pings(path, *, geometry=None, start=0, stop=None, **options) -> Iterator[Ping]
                                                    # pings start:stop, lazy, bounded memory

:func:`~sonarmap.io.reader.reader_for` gives the reader of a path or format name.  Directories
and globs of PNG/BMP+JSON pings are handled by :mod:`sonarmap.io.pngjson`.
"""

from __future__ import annotations

import glob
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from sonarmap.errors import DataFormatError
from sonarmap._files import open_regular, require_regular_file
from sonarmap.io._binary import MAX_PING_BYTES, PartialFrameWarning, make_summary
from sonarmap.io.reader import FORMAT_MODULES, GeometrySpec, Reader, format_module, reader_for, reader_modules
from sonarmap.ping import Ping

__all__ = ["read_pings", "read_ping", "detect_format", "expand_inputs", "FORMAT_MODULES", "format_module",
           "inputs_with_readers", "is_store_dir", "make_summary", "MAX_PING_BYTES", "PartialFrameWarning", "Reader",
           "reader_for", "reader_modules", "total_pings"]


_modules = reader_modules  # the name the fuzz harness imports


def detect_format(path: str | os.PathLike[str]) -> str:
    """Name of the format of ``path``, detected from its content.

    Directories (of PNG pings, zarr stores, ROS 2 bags) are recognised by their entries; any other
    path must be a regular file, whose first 4096 bytes are read through
    :func:`~sonarmap._files.open_regular` (so a FIFO or device is refused at once, never read).

    Raises
    ------
    DataFormatError
        If the path does not exist, is a FIFO, device or socket, cannot be read, is an empty file,
        or no reader recognises it.
    """
    p = Path(path)
    if not p.exists():
        raise DataFormatError("no such file or directory", p)
    head = b""
    if not p.is_dir():
        with open_regular(p, "input") as fh:
            try:
                head = fh.read(4096)
            except OSError as exc:
                raise DataFormatError(f"cannot read: {exc.strerror or exc}", p) from None
    try:
        for mod in _modules():
            if mod.sniff(p, head):
                return str(getattr(mod, "FORMAT", mod.__name__.rsplit(".", 1)[-1]))
    except DataFormatError:
        raise
    except OSError as exc:  # e.g. a directory that cannot be listed
        raise DataFormatError(f"cannot read: {exc.strerror or exc}", p) from None
    if not head and not p.is_dir():
        raise DataFormatError("empty file (0 bytes): no pings", p)
    raise DataFormatError("unrecognised file format (no reader matched its content)", p)


def expand_inputs(inputs: str | os.PathLike[str] | Iterable[str | os.PathLike[str]]) -> list[Path]:
    """Expand globs; keep regular files and directories; raise if an input matches nothing.

    A directory stays one input when it holds PNG/BMP ping images or is a survey store or a ROS 2
    bag; otherwise it stands for the recordings in it (:func:`_recordings_in`: e.g. a folder of
    ``.aris`` files, or a Kongsberg ``.all`` + ``.wcd`` pair), in name order.

    Raises
    ------
    DataFormatError
        If an input does not exist, a glob matches nothing, a path (given or matched) is a FIFO,
        device or socket rather than a regular file or directory, or a directory holds neither
        ping images nor recordings (the message names its subdirectories that hold pings).
    """
    items = [inputs] if isinstance(inputs, str | os.PathLike) else list(inputs)
    out: list[Path] = []
    for item in items:
        s = str(item)
        if any(ch in s for ch in "*?[") and not Path(s).exists():
            hits = sorted(glob.glob(s))
            if not hits:
                raise DataFormatError("glob matched no files", s)
            paths = [Path(h) for h in hits]
        else:
            p = Path(s)
            if not p.exists():
                raise DataFormatError("no such file or directory", p)
            paths = [p]
        for p in paths:
            if not p.is_dir():
                require_regular_file(p, "input")
                out.append(p)
            else:
                out.extend(_recordings_in(p))
    return out


def _recordings_in(directory: Path) -> list[Path]:
    """``[directory]`` when it is a folder of PNG/BMP pings, a survey store or a ROS 2 bag; else
    the regular files in it that a reader other than the PNG/BMP one recognises (by content, as
    :func:`detect_format`), in name order.  Other files (licences, READMEs, beam tables, a stray
    JSON) are skipped; subdirectories are not entered (a recording's pings are not mixed with
    another's)."""
    from sonarmap.io.pngjson import _is_ping_image

    if is_store_dir(directory):
        return [directory]
    try:
        entries = sorted(directory.iterdir())
    except OSError as exc:
        raise DataFormatError(f"cannot list: {exc.strerror or exc}", directory) from None
    if any(_is_ping_image(e) for e in entries):
        return [directory]  # PNG/BMP pings (the PNG reader's own test, find_png_pings)
    found: list[Path] = []
    for e in entries:
        if not e.is_file():  # (subdirectories, FIFOs, devices)
            continue
        try:
            fmt = detect_format(e)
        except DataFormatError:
            continue
        if fmt != "pngjson":
            found.append(e)
    if found:
        return found
    subs = [e.name + "/" for e in entries if e.is_dir() and (is_store_dir(e) or any(
        _is_ping_image(c) for c in _listing(e)))]
    hint = f"; pass one of its subdirectories: {', '.join(subs)}" if subs else ""
    raise DataFormatError(f"no pings found: no PNG/BMP ping images and no recording this reads{hint}",
                          directory)


def _listing(directory: Path) -> list[Path]:
    try:
        return list(directory.iterdir())
    except OSError:
        return []


def read_pings(
    inputs: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    *,
    geometry: GeometrySpec = None,
    **kwargs: Any,
) -> Iterator[Ping]:
    """Lazily yield the pings of one or more files, directories or globs, in order.

    PNG/BMP pings given together (a directory, a glob, or several image files) are sorted by time
    stamp; other formats yield their pings in file order.

    Parameters
    ----------
    inputs : path-like or iterable of path-likes
        Files (any supported format), directories of PNG+JSON pings, or globs.
    geometry : SonarGeometry, preset name or JSON path, optional
        Overrides the geometry read from the files.
    """
    paths = expand_inputs(inputs)
    pngs: list[Path] = []

    def flush() -> Iterator[Ping]:
        if pngs:
            from sonarmap.io import pngjson

            yield from pngjson.iter_png_pings(list(pngs), geometry=geometry)
            pngs.clear()

    for p, reader in inputs_with_readers(paths):
        if reader.FORMAT == "pngjson":
            pngs.append(p)
            continue
        yield from flush()
        yield from reader.iter_pings(p, geometry=geometry, **kwargs)
    yield from flush()


def inputs_with_readers(paths: Iterable[str | os.PathLike[str]]) -> Iterator[tuple[Path, Reader]]:
    """Each of the expanded inputs ``paths`` (:func:`expand_inputs`) with its reader, in order; a
    recording split over several files (Kongsberg ``.all`` + ``.wcd``, the reader's
    ``recording_key``) once, from whichever of its files comes first - so that it is read,
    counted and planned once however often it is named."""
    seen: set[object] = set()
    for item in paths:
        p = Path(item)
        reader = reader_for(p)
        key_of = getattr(reader, "recording_key", None)
        if key_of is not None:
            key = key_of(p)
            if key in seen:
                continue
            seen.add(key)
        yield p, reader


def is_store_dir(p: Path) -> bool:
    """A directory that is a dataset store (zarr) or a ROS 2 bag rather than a folder of PNG pings."""
    from sonarmap.store import is_zarr_store

    return is_zarr_store(p) or (p / "metadata.yaml").exists()


def read_ping(path: str | os.PathLike[str], *, geometry: GeometrySpec = None, index: int = 0) -> Ping:
    """Read the ``index``-th ping of a file (the only ping of a PNG+JSON file).

    A single file or directory is read through its reader's ``start``/``stop`` (the pings before
    ``index`` are not decoded where the format has an index); a glob or several recordings are
    read in :func:`read_pings` order.

    Raises
    ------
    DataFormatError
        If the input has no ping ``index`` (a negative ``index`` never matches), or cannot be read.
    """
    paths = expand_inputs(path)
    if len(paths) == 1 and int(index) >= 0:
        k = int(index)
        for ping in reader_for(paths[0]).iter_pings(paths[0], geometry=geometry, start=k, stop=k + 1):
            return ping
    else:
        for i, ping in enumerate(read_pings(paths, geometry=geometry)):
            if i == index:
                return ping
    raise DataFormatError(f"has no ping with index {index}{_indices_held(paths)}", path)


def total_pings(paths: Iterable[str | os.PathLike[str]]) -> int:
    """The pings of the expanded inputs ``paths``, counted from headers (each reader's
    ``count_pings``); the readers' warnings about damaged records are left to the reading."""
    import warnings

    total = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for p, reader in inputs_with_readers(paths):
            total += int(reader.count_pings(p))
    return total


def _indices_held(paths: Iterable[str | os.PathLike[str]]) -> str:
    """`` (it has 6 pings: 0-5)`` for the message of a missing index; empty if they cannot be counted."""
    from sonarmap._text import counted

    try:
        n = total_pings(paths)
    except Exception:  # noqa: BLE001 - only the message's detail
        return ""
    return f" (it has {counted(n, 'ping')}" + ("" if n == 0 else ": index 0" if n == 1 else f": 0-{n - 1}") + ")"
