"""Safe opening of input files: regular files only, bounded reads, bounded decompression, JSON
decoding.

Every reader goes through these so that a FIFO named like a ping cannot hang a run, a symlink to
``/dev/zero`` cannot read until memory runs out, and a small compressed item cannot inflate to
gigabytes.  Each failure is a :class:`~sonarmap.errors.DataFormatError` naming the file.
"""

from __future__ import annotations

import fcntl
import json
import os
import stat
import sys
import zlib
from pathlib import Path
from typing import Any, BinaryIO

from sonarmap.errors import DataFormatError

__all__ = [
    "MAX_SIDECAR_BYTES",
    "require_regular_file",
    "open_regular",
    "read_bytes_bounded",
    "decompress_bounded",
    "parse_json",
]

#: Largest JSON sidecar / geometry file read (a 4096-beam table with a PSF is ~0.5 MB).
MAX_SIDECAR_BYTES = 16 * 1024 * 1024

_KINDS = (
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISDIR, "a directory"),
)


def _kind(mode: int) -> str:
    for test, name in _KINDS:
        if test(mode):
            return name
    return "not a regular file"


def require_regular_file(path: str | os.PathLike[str], what: str = "file") -> Path:
    """Return ``path`` as a :class:`Path` if it is (a symlink to) a regular file.

    Raises
    ------
    DataFormatError
        If the path does not exist, cannot be stat'ed, or is a FIFO, device, socket or directory.
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise DataFormatError("no such file", p) from None
    except OSError as exc:
        raise DataFormatError(f"cannot read: {exc.strerror or exc}", p) from None
    if not stat.S_ISREG(st.st_mode):
        raise DataFormatError(f"{what} is {_kind(st.st_mode)}; sonarmap reads only regular files", p)
    return p


def open_regular(path: str | os.PathLike[str], what: str = "file") -> BinaryIO:
    """Open a regular file for binary reading without blocking on FIFOs.

    The file is opened non-blocking and checked with ``fstat`` on the open descriptor, so a path
    swapped for a FIFO between a check and the open still cannot hang the reader.
    """
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise DataFormatError("no such file", p) from None
    except OSError as exc:
        raise DataFormatError(f"cannot read: {exc.strerror or exc}", p) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise DataFormatError(f"{what} is {_kind(st.st_mode)}; sonarmap reads only regular files", p)
        flags = fcntl.fcntl(fd, fcntl.F_GETFL)
        fcntl.fcntl(fd, fcntl.F_SETFL, flags & ~os.O_NONBLOCK)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes_bounded(path: str | os.PathLike[str], max_bytes: int, what: str = "file") -> bytes:
    """The whole content of a regular file of at most ``max_bytes`` bytes.

    Raises
    ------
    DataFormatError
        If the file is not regular, cannot be read, or is larger than ``max_bytes``.
    """
    with open_regular(path, what) as fh:
        size = os.fstat(fh.fileno()).st_size
        if size > max_bytes:
            raise DataFormatError(f"{what} is {size} bytes, more than the {max_bytes} allowed", path)
        try:
            # read the size fstat gave (+1 to see growth), not max_bytes + 1: CPython allocates
            # the whole requested buffer first (16 MiB for a 3 kB sidecar)
            data = fh.read(size + 1)
            if len(data) > size:  # grew since fstat: read on, up to the bound
                data += fh.read(max_bytes + 1 - len(data))
        except OSError as exc:
            raise DataFormatError(f"cannot read: {exc.strerror or exc}", path) from None
    if len(data) > max_bytes:  # grew while reading
        raise DataFormatError(f"{what} is more than the {max_bytes} bytes allowed", path)
    return data


def decompress_bounded(
    data: bytes | bytearray | memoryview,
    max_bytes: int,
    path: str | os.PathLike[str] | None = None,
    what: str = "compressed item",
    *,
    wbits: int = zlib.MAX_WBITS,
) -> bytes:
    """zlib-decompress ``data`` into at most ``max_bytes`` bytes.

    Raises
    ------
    DataFormatError
        If the stream is corrupt, incomplete, or would inflate to more than ``max_bytes``.
    """
    d = zlib.decompressobj(wbits)
    try:
        out = d.decompress(bytes(data), max_bytes + 1)
    except zlib.error as exc:
        raise DataFormatError(f"corrupt {what}: {exc}", path) from None
    if len(out) > max_bytes or d.unconsumed_tail:
        raise DataFormatError(f"{what} inflates to more than the {max_bytes} bytes allowed", path)
    if not d.eof:
        raise DataFormatError(f"{what} is truncated (zlib stream incomplete)", path)
    return out


def parse_json(data: bytes | str, source: str | os.PathLike[str] | None = None) -> Any:
    """The value of a JSON document read from a file.

    Parameters
    ----------
    data : bytes or str
        The document (bytes in UTF-8, -16 or -32, as :func:`json.loads` detects them).
    source : str or path-like, optional
        The file, named in the errors.

    Returns
    -------
    Any
        What :func:`json.loads` returns.

    Raises
    ------
    DataFormatError
        Naming ``source``, if ``data`` is not JSON (with the line and column), not UTF-8 text,
        nested too deeply for the parser, or holds an integer over Python's digit limit.

    Examples
    --------
    >>> parse_json(b'{"num_beams": 96}')
    {'num_beams': 96}
    """
    try:
        return json.loads(data)
    except json.JSONDecodeError as exc:
        raise DataFormatError(
            f"invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}", source
        ) from None
    except UnicodeDecodeError as exc:
        raise DataFormatError(f"not UTF-8 text ({exc.reason})", source) from None
    except RecursionError:
        raise DataFormatError("invalid JSON: arrays or objects nested too deeply", source) from None
    except ValueError as exc:  # e.g. an integer beyond Python's int-str digit limit
        if "integer string conversion" in str(exc):
            raise DataFormatError(
                f"invalid JSON: an integer has more than {sys.get_int_max_str_digits()} digits", source
            ) from None
        raise DataFormatError(f"invalid JSON: {' '.join(str(exc).split())}", source) from None
