"""Shared helpers of the binary sonar-file readers (ARIS, DIDSON, Oculus).

One place for: the partial-frame warning, memory-mapping a regular file read-only, the frames of a
file of fixed-size frames and the fixed-size headers of a datagram stream, the plausibility
limits every reader applies to header fields (times, sound speed, range window, ping size),
checking a ping index, and turning any inconsistency found while decoding headers into a
:class:`~sonarmap.errors.DataFormatError` that names the file and the byte offset.
"""

from __future__ import annotations

import contextlib
import math
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Self

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import DataFormatError, GeometryError, InputError, SonarmapWarning
from sonarmap._files import open_regular
from sonarmap.io.reader import check_ping_range

__all__ = [
    "PartialFrameWarning",
    "ClosingFile",
    "map_file",
    "map_frames",
    "records_at",
    "check_index",
    "iter_container_pings",
    "iter_indexed",
    "count_container_pings",
    "header_errors",
    "warn_partial",
    "finite_or",
    "make_summary",
    "U8_SCALE",
    "MAX_TIME_NS",
    "MAX_PLAUSIBLE_TIME_NS",
    "MAX_PING_BYTES",
    "MAX_WINDOW_M",
    "SOUND_SPEED_RANGE_M_S",
    "check_plausible",
    "check_time_ns",
    "check_sound_speed",
]


class PartialFrameWarning(SonarmapWarning):
    """The last frame/record of a file is incomplete (e.g. the recording was cut) and was skipped."""


class ClosingFile:
    """``with`` support of the reader file classes (``ArisFile``, ``DdfFile``, ``OculusFile``,
    ``KongsbergFile``, ``KmallFile``): ``__enter__`` returns the file, ``__exit__`` calls its
    ``close()``."""

    def close(self) -> None:  # pragma: no cover - every subclass defines it
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def map_file(path: str | os.PathLike[str], *, min_size: int = 0, what: str = "file") -> np.memmap | np.ndarray:
    """Memory-map ``path`` read-only as a flat ``uint8`` array (empty files give an empty array).

    The file is opened with :func:`~sonarmap._files.open_regular` and mapped through that
    descriptor, so FIFOs, devices (a symlink to ``/dev/zero``), sockets and directories are refused
    before anything is read or mapped.

    Raises
    ------
    DataFormatError
        If the file is not a regular file, cannot be opened, or is shorter than ``min_size`` bytes.
    """
    p = Path(path)
    with open_regular(p, what) as fh:
        try:
            size = os.fstat(fh.fileno()).st_size
        except OSError as exc:
            raise DataFormatError(f"cannot read: {exc.strerror or exc}", p) from None
        if size < min_size:
            raise DataFormatError(
                f"truncated {what}: {size} bytes, the header alone needs {min_size}", p, size
            )
        if size == 0:
            return np.zeros(0, dtype=np.uint8)
        try:
            return np.memmap(fh, dtype=np.uint8, mode="r", shape=(size,))
        except (OSError, ValueError) as exc:
            raise DataFormatError(f"cannot memory-map: {exc}", p) from None


def map_frames(
    mm: NDArray[np.uint8], path: str | os.PathLike[str], offset: int, header_dtype: np.dtype,
    n_samples: int, n_beams: int,
) -> tuple[np.ndarray, int]:
    """The complete frames after the first ``offset`` bytes of ``mm``, as a structured view.

    A frame is a ``header_dtype`` header and ``n_samples x n_beams`` uint8 samples stored
    ``[sample][beam]`` (fields ``"header"`` and ``"samples"``); an incomplete trailing frame is
    left out with a :class:`PartialFrameWarning`.

    Returns
    -------
    frames : ndarray
        ``(n,)`` records viewing ``mm`` (no copy).
    n : int
        Number of complete frames.
    """
    frame_size = header_dtype.itemsize + n_beams * n_samples
    n, rem = divmod(int(mm.size) - offset, frame_size)
    if rem:
        warn_partial(path, offset + n * frame_size, rem, frame_size, "frame", stacklevel=4)
    frame_dtype = np.dtype([("header", header_dtype), ("samples", np.uint8, (n_samples, n_beams))])
    return np.ndarray(shape=(n,), dtype=frame_dtype, buffer=mm, offset=offset), n


def records_at(buf: NDArray[np.uint8], offsets: NDArray[np.int64], dtype: np.dtype) -> NDArray[Any]:
    """The ``dtype`` records that start at ``offsets`` in ``buf`` (a copy; empty for no offsets).

    The headers of a datagram stream, whose datagrams start at the offsets found by a walk.
    """
    if not offsets.size:
        return np.zeros(0, dtype=dtype)
    idx = offsets[:, None] + np.arange(dtype.itemsize, dtype=np.int64)
    return np.ascontiguousarray(buf[idx]).view(dtype).reshape(-1)


def check_index(index: int, n: int, what: str = "ping") -> int:
    """``index`` (negative counts from the end) as a position in ``range(n)``.

    Raises
    ------
    IndexError
        If it is outside ``-n .. n - 1`` (message: ``"<what> index ... out of range for n <what>s"``).
    """
    i = int(index)
    if i < 0:
        i += n
    if not 0 <= i < n:
        raise IndexError(f"{what} index {index} out of range for {n} {what}s")
    return i


@contextlib.contextmanager
def header_errors(path: str | os.PathLike[str], offset: int | None, what: str) -> Iterator[None]:
    """Re-raise geometry/validation errors raised while decoding a header as DataFormatError."""
    try:
        yield
    except DataFormatError:
        raise
    except (GeometryError, InputError, ValueError, OverflowError, ZeroDivisionError) as exc:
        raise DataFormatError(f"inconsistent {what}: {exc}", path, offset) from None


def warn_partial(
    path: str | os.PathLike[str], offset: int, have: int, need: int | str, what: str, *, stacklevel: int = 3
) -> None:
    """Warn (PartialFrameWarning) that the trailing ``what`` at ``offset`` is incomplete.

    ``stacklevel`` as in :func:`warnings.warn`, counted from this function (default: the caller
    of its caller).
    """
    warnings.warn(
        f"{path}: at byte {offset}: last {what} is incomplete ({have} of {need} bytes); skipped",
        PartialFrameWarning,
        stacklevel=stacklevel,
    )


def finite_or(value: Any, default: float | None = None) -> float | None:
    """``float(value)`` if finite, else ``default``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return default
    return v if math.isfinite(v) else default


#: 8-bit sensor data -> [0, 1] (the same factor as the PNG reader, so values agree bit for bit).
U8_SCALE = np.float32(1.0 / 255.0)

#: Largest ping time representable as datetime64[ns] (int64 nanoseconds).
MAX_TIME_NS = 2**63 - 1

#: Latest plausible ping time, 2200-01-01T00:00:00Z in ns since the epoch (0 means "unknown").
MAX_PLAUSIBLE_TIME_NS = 7_258_118_400 * 10**9

#: Largest single ping message / frame a reader accepts (also the cap on decompressed items).
MAX_PING_BYTES = 64 * 1024 * 1024

#: Farthest plausible range of an imaging sonar's window (start or end), in metres.
MAX_WINDOW_M = 1000.0

#: Plausible sound speed in water (m/s), the range :class:`~sonarmap.geometry.SonarGeometry` accepts.
SOUND_SPEED_RANGE_M_S = (1300.0, 1700.0)


def check_plausible(value: Any, lo: float, hi: float, what: str, unit: str = "") -> float:
    """``float(value)`` if it is finite and within ``[lo, hi]``.

    Raises
    ------
    ValueError
        Otherwise (message names ``what``, the value and the accepted range).
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} {value!r} is not a number") from None
    if not (math.isfinite(v) and lo <= v <= hi):
        u = f" {unit}" if unit else ""
        raise ValueError(f"{what} {value}{u} is outside {lo:g}-{hi:g}{u}")
    return v


def check_time_ns(t: int, what: str = "ping time") -> int:
    """``t`` if it is 0 (unknown) or a time between 1970 and 2200 in integer ns since the epoch.

    Raises
    ------
    ValueError
        If ``t`` is negative or later than 2200-01-01 (which includes everything beyond int64).
    """
    t = int(t)
    if not 0 <= t <= MAX_PLAUSIBLE_TIME_NS:
        raise ValueError(f"{what} {t} ns is outside the years 1970-2200")
    return t


def check_sound_speed(c: Any, what: str = "sound speed", *, unset_ok: bool = False) -> float | None:
    """A plausible sound speed in water (m/s); ``None`` for 0 when ``unset_ok`` (0 = not set).

    Raises
    ------
    ValueError
        If ``c`` is not finite or outside :data:`SOUND_SPEED_RANGE_M_S`.
    """
    if unset_ok and finite_or(c) == 0.0:
        return None
    lo, hi = SOUND_SPEED_RANGE_M_S
    return check_plausible(c, lo, hi, what, "m/s")


def make_summary(
    fmt: str,
    path: str | os.PathLike[str],
    *,
    n_pings: int,
    geometry: Any = None,
    time_start_ns: int | None = None,
    time_end_ns: int | None = None,
    **details: Any,
) -> dict[str, Any]:
    """The flat dict returned by every format module's ``summary(path)`` hook (for ``sonarmap info``).

    Keys: ``path``, ``format``, ``pings``, the geometry fields of
    :func:`sonarmap.geometry.geometry_summary` for the first ping (absent without pings),
    ``time_first_utc``/``time_last_utc`` (``"unknown"`` when the format has no clock),
    ``duration_s``, then the format-specific ``details``.  The first ping's
    :class:`~sonarmap.geometry.SonarGeometry` itself is under the private key ``_geometry``.
    A file without pings needs neither ``geometry`` nor times (``make_summary(fmt, path, n_pings=0)``).
    """

    def iso(t: int | None) -> str:
        if t is None:
            return "unknown"
        if not 0 <= int(t) <= MAX_TIME_NS:
            return f"invalid ({t} ns)"
        return str(np.datetime64(int(t), "ns"))

    out: dict[str, Any] = {"path": str(path), "format": fmt, "pings": int(n_pings)}
    if geometry is not None:
        from sonarmap.geometry import geometry_summary

        out.update(geometry_summary(geometry))
    out["time_first_utc"] = iso(time_start_ns)
    out["time_last_utc"] = iso(time_end_ns)
    if time_start_ns is not None and time_end_ns is not None:
        out["duration_s"] = (time_end_ns - time_start_ns) * 1e-9
    out.update(details)
    out["_geometry"] = geometry
    return out


def iter_container_pings(opener: Any, path: str | os.PathLike[str], geometry: Any = None, start: int = 0,
                         stop: int | None = None) -> Iterator[Any]:
    """Registry hook body shared by the file readers: open, yield pings ``start:stop`` lazily, close.

    ``opener`` is a reader class (``ArisFile``, ``DdfFile``, ``KongsbergFile``, ...) usable as a
    context manager that iterates over its pings and indexes them (``f[i]``); see
    :func:`iter_indexed`.
    """
    with opener(path, geometry=geometry) as f:
        yield from iter_indexed(f, start, stop)


def iter_indexed(f: Any, start: int = 0, stop: int | None = None) -> Iterator[Any]:
    """Pings ``start:stop`` of an open reader ``f``: all of them through ``iter(f)``, else ``f[i]``
    for the positions in range only (the others are not decoded).

    Raises
    ------
    InputError
        If ``start`` or ``stop`` is negative or not an integer.
    """
    start, stop = check_ping_range(start, stop)
    if start == 0 and stop is None:
        yield from f
        return
    for i in range(*slice(start, stop).indices(len(f))):
        yield f[i]


def count_container_pings(opener: Any, path: str | os.PathLike[str]) -> int:
    """Registry hook body: number of pings of a reader, closing its memory map afterwards."""
    with opener(path) as f:
        return len(f)
