"""The :class:`Reader` protocol every format module of :mod:`sonarmap.io` implements.

A reader is a module (``sonarmap.io.aris``, ``sonarmap.io.ddf``, ...) with four members:

``FORMAT``
    The format's short name (``"aris"``, ``"zarr"``, ...), as :func:`sonarmap.io.detect_format`
    reports it.
``sniff(path, head)``
    Whether ``path`` (whose first bytes are ``head``; empty for a directory) is of this format.
``count_pings(path)``
    The number of pings, from headers / indexes only (no image is decoded).
``iter_pings(path, *, geometry=None, start=0, stop=None, **options)``
    The pings ``start:stop`` of ``path``, lazily, in file order.  Pings before ``start`` are not
    decoded wherever the format has an index (the frame table of ARIS, DIDSON, Oculus, Kongsberg
    and KMALL files, the file list of PNG/BMP pings, the ping axis of a survey store, the message
    list of a ROS bag for ``ProjectedSonarImage`` and ``sensor_msgs/Image`` topics).

:func:`reader_for` returns the reader of a path (detected from its content) or of a format name.
"""

from __future__ import annotations

import functools
import importlib
import os
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any, Protocol, runtime_checkable

from sonarmap.errors import DataFormatError, InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ping import Ping

__all__ = ["Reader", "reader_for", "reader_modules", "check_ping_range", "FORMAT_MODULES"]

#: Modules tried in order by :func:`sonarmap.io.detect_format` (those that exist).
FORMAT_MODULES = ("zarrstore", "aris", "oculus", "ddf", "rosbag", "kongsberg", "kmall", "pngjson")

GeometrySpec = SonarGeometry | str | os.PathLike[str] | None


@runtime_checkable
class Reader(Protocol):
    """What a format module provides: detection, a cheap count and ranged, lazy reading.

    Every module named in :data:`FORMAT_MODULES` satisfies it (``isinstance(sonarmap.io.aris,
    Reader)`` is true).

    Attributes
    ----------
    FORMAT : str
        Short name of the format (``"aris"``, ``"ddf"``, ``"oculus"``, ``"rosbag"``, ``"zarr"``,
        ``"pngjson"``, ``"kongsberg"``, ``"kmall"``).
    """

    FORMAT: str

    def sniff(self, path: Path, head: bytes) -> bool:
        """Whether ``path`` is of this format.

        Parameters
        ----------
        path : Path
            A regular file or a directory.
        head : bytes
            The file's first bytes (up to 4096; empty for a directory).

        Returns
        -------
        bool
        """
        ...

    def count_pings(self, path: str | os.PathLike[str]) -> int:
        """Number of pings of ``path``, from headers or indexes only (no image decoded).

        Raises
        ------
        DataFormatError
            If the file is not readable as this format.
        """
        ...

    def iter_pings(
        self,
        path: str | os.PathLike[str],
        *,
        geometry: GeometrySpec = None,
        start: int = 0,
        stop: int | None = None,
        **options: Any,
    ) -> Iterator[Ping]:
        """Lazily yield pings ``start:stop`` of ``path`` in file order.

        Parameters
        ----------
        path : path-like
            A file (or directory) of this format.
        geometry : SonarGeometry, preset name or JSON path, optional
            Overrides the geometry read from the file.
        start, stop : int
            Ping positions ``[start, stop)`` (``stop`` None: to the end), clipped to the pings the
            file holds: the pings are ``list(iter_pings(path))[start:stop]``, without decoding
            the ones before ``start`` where the format has an index.
        **options
            Format-specific reading options (e.g. ``checksum`` of Kongsberg files, ``topic`` and
            ``handedness`` of ROS bags, ``start_time_ns`` / ``rate_hz`` of Oculus captures);
            readers ignore the options they do not know.

        Raises
        ------
        InputError
            If ``start`` or ``stop`` is not a non-negative integer.
        DataFormatError
            If the file is not readable as this format.
        """
        ...


def check_ping_range(start: int, stop: int | None) -> tuple[int, int | None]:
    """``(start, stop)`` checked: non-negative integers (``stop`` may be None).

    A ``stop`` below ``start`` selects nothing (as in a slice).

    Raises
    ------
    InputError
        If ``start`` or ``stop`` is negative, a boolean or not an integer.

    Examples
    --------
    >>> check_ping_range(2, None)
    (2, None)
    """
    for name, value in (("start", start), ("stop", stop)):
        if value is None and name == "stop":
            continue
        if isinstance(value, bool) or not hasattr(value, "__index__") or int(value) < 0:
            raise InputError(f"{name}: expected a non-negative integer, got {value!r}")
    return int(start), None if stop is None else int(stop)


def reader_modules() -> list[ModuleType]:
    """The format modules of :data:`FORMAT_MODULES` that exist, in detection order."""
    mods = []
    for name in FORMAT_MODULES:
        modname = f"sonarmap.io.{name}"
        try:
            mods.append(importlib.import_module(modname))
        except ModuleNotFoundError as exc:
            if exc.name != modname:
                raise
    return mods


@functools.cache
def _by_name(name: str) -> Reader:
    # a format's module is fixed for the process: found once (the walk imports every format
    # module, 8 import_module calls; a survey chunk of PNG pings asks once per ping)
    for mod in reader_modules():
        if getattr(mod, "FORMAT", mod.__name__.rsplit(".", 1)[-1]) == name:
            return mod  # type: ignore[return-value]
    raise DataFormatError(f"unknown format '{name}'")


def reader_for(path_or_format: str | os.PathLike[str]) -> Reader:
    """The reader of a format name or of a path.

    Parameters
    ----------
    path_or_format : str or path-like
        A format name (a ``FORMAT`` value, or a module name of :data:`FORMAT_MODULES` such as
        ``"zarrstore"``), or the path of a file or directory, whose format is detected from its
        content (:func:`sonarmap.io.detect_format`; a directory that is not a survey store or a
        ROS 2 bag is a folder of PNG/BMP pings).  A ``str`` that names a format is taken as the
        format; give a :class:`~pathlib.Path` to detect a file that happens to be named so.

    Returns
    -------
    Reader
        The format module.

    Raises
    ------
    DataFormatError
        If the path does not exist, cannot be read or is of no known format.

    Examples
    --------
    >>> reader_for("aris").FORMAT
    'aris'
    """
    if isinstance(path_or_format, str) and (path_or_format in FORMAT_MODULES or path_or_format == "zarr"):
        return _by_name("zarr" if path_or_format == "zarrstore" else path_or_format)
    from sonarmap.io import detect_format, is_store_dir

    p = Path(path_or_format)
    return _by_name("pngjson" if p.is_dir() and not is_store_dir(p) else detect_format(p))


def format_module(name: str) -> Reader:
    """The reader of format ``name`` (its ``FORMAT``); prefer :func:`reader_for`.

    Raises
    ------
    DataFormatError
        If no reader has that ``FORMAT``.
    """
    return _by_name(name)
