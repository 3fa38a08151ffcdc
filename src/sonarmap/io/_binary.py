"""Shared helpers of the binary sonar-file readers (ARIS, DIDSON, Oculus).

One place for: the partial-frame warning, memory-mapping a file read-only, and turning any
inconsistency found while decoding headers into a :class:`~sonarmap.errors.DataFormatError` that
names the file and the byte offset.
"""

from __future__ import annotations

import contextlib
import math
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from sonarmap.errors import DataFormatError, GeometryError, InputError, SonarmapWarning

__all__ = [
    "PartialFrameWarning",
    "map_file",
    "header_errors",
    "warn_partial",
    "finite_or",
    "make_summary",
    "U8_SCALE",
    "MAX_TIME_NS",
]


class PartialFrameWarning(SonarmapWarning):
    """The last frame/record of a file is incomplete (e.g. the recording was cut) and was skipped."""


def map_file(path: str | os.PathLike[str], *, min_size: int = 0, what: str = "file") -> np.memmap | np.ndarray:
    """Memory-map ``path`` read-only as a flat ``uint8`` array (empty files give an empty array).

    Raises
    ------
    DataFormatError
        If the file cannot be opened or is shorter than ``min_size`` bytes.
    """
    p = Path(path)
    try:
        size = p.stat().st_size
    except FileNotFoundError:
        raise DataFormatError("no such file", p) from None
    except OSError as exc:
        raise DataFormatError(f"cannot read: {exc.strerror or exc}", p) from None
    if size < min_size:
        raise DataFormatError(
            f"truncated {what}: {size} bytes, the header alone needs {min_size}", p, size
        )
    if size == 0:
        return np.zeros(0, dtype=np.uint8)
    try:
        return np.memmap(p, dtype=np.uint8, mode="r")
    except (OSError, ValueError) as exc:
        raise DataFormatError(f"cannot memory-map: {exc}", p) from None


@contextlib.contextmanager
def header_errors(path: str | os.PathLike[str], offset: int | None, what: str) -> Iterator[None]:
    """Re-raise geometry/validation errors raised while decoding a header as DataFormatError."""
    try:
        yield
    except DataFormatError:
        raise
    except (GeometryError, InputError, ValueError, OverflowError, ZeroDivisionError) as exc:
        raise DataFormatError(f"inconsistent {what}: {exc}", path, offset) from None


def warn_partial(path: str | os.PathLike[str], offset: int, have: int, need: int, what: str) -> None:
    """Warn (PartialFrameWarning) that the trailing ``what`` at ``offset`` is incomplete."""
    warnings.warn(
        f"{path}: at byte {offset}: last {what} is incomplete ({have} of {need} bytes); skipped",
        PartialFrameWarning,
        stacklevel=3,
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


def make_summary(
    fmt: str,
    path: str | os.PathLike[str],
    *,
    n_pings: int,
    geometry: Any,
    time_start_ns: int | None,
    time_end_ns: int | None,
    **details: Any,
) -> dict[str, Any]:
    """The flat dict returned by every format module's ``summary(path)`` hook (for ``sonarmap info``).

    Keys: ``path``, ``format``, ``pings``, the geometry fields of
    :func:`sonarmap.cli.info.geometry_summary` for the first ping (absent without pings),
    ``time_first_utc``/``time_last_utc`` (``"unknown"`` when the format has no clock),
    ``duration_s``, then the format-specific ``details``.  The first ping's
    :class:`~sonarmap.geometry.SonarGeometry` itself is under the private key ``_geometry``.
    """

    def iso(t: int | None) -> str:
        if t is None:
            return "unknown"
        if not 0 <= int(t) <= MAX_TIME_NS:
            return f"invalid ({t} ns)"
        return str(np.datetime64(int(t), "ns"))

    out: dict[str, Any] = {"path": str(path), "format": fmt, "pings": int(n_pings)}
    if geometry is not None:
        try:
            from sonarmap.cli.info import geometry_summary
        except ImportError:  # pragma: no cover - CLI not installed
            out["geometry"] = geometry.name
        else:
            out.update(geometry_summary(geometry))
    out["time_first_utc"] = iso(time_start_ns)
    out["time_last_utc"] = iso(time_end_ns)
    if time_start_ns is not None and time_end_ns is not None:
        out["duration_s"] = (time_end_ns - time_start_ns) * 1e-9
    out.update(details)
    out["_geometry"] = geometry
    return out


def iter_container_pings(opener: Any, path: str | os.PathLike[str], geometry: Any = None) -> Iterator[Any]:
    """Registry hook body shared by the file readers: open, yield every ping lazily, close.

    ``opener`` is a reader class (``ArisFile``, ``DdfFile``, ``OculusFile``) usable as a context
    manager that iterates over its pings.
    """
    with opener(path, geometry=geometry) as f:
        yield from f


def count_container_pings(opener: Any, path: str | os.PathLike[str]) -> int:
    """Registry hook body: number of pings of a reader, closing its memory map afterwards."""
    with opener(path) as f:
        return len(f)
