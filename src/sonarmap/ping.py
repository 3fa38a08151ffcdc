"""A single sonar ping: intensity image + geometry + time + optional pose."""

from __future__ import annotations

import dataclasses
import math
import numbers
import operator
import os
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry

__all__ = ["Ping", "Pose", "as_image", "source_file", "source_name"]

_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1


@dataclasses.dataclass(frozen=True, eq=False)
class Pose:
    """Pose of the vehicle (or sensor) in the world frame at a ping.

    Parameters
    ----------
    position_m : array_like, shape (3,)
        Position in metres.
    orientation_xyzw : array_like, shape (4,)
        Unit quaternion, scalar last (scipy's ``Rotation.from_quat`` order).
    frame : str
        Name of the world frame (e.g. ``"ned"`` or ``"enu"``).
    """

    position_m: NDArray[np.float64]
    orientation_xyzw: NDArray[np.float64]
    frame: str = "ned"

    def __post_init__(self) -> None:
        p = np.asarray(self.position_m, dtype=np.float64).reshape(-1)
        q = np.asarray(self.orientation_xyzw, dtype=np.float64).reshape(-1)
        if p.shape != (3,) or q.shape != (4,):
            raise InputError(f"pose: need position (3,) and quaternion (4,), got {p.shape}, {q.shape}")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise InputError("pose: contains NaN or infinite values")
        n = float(np.linalg.norm(q))
        if not 0.5 < n < 2.0:
            raise InputError(f"pose: quaternion norm {n:.3g} is not close to 1")
        q = q / n
        p.setflags(write=False)
        q.setflags(write=False)
        object.__setattr__(self, "position_m", p)
        object.__setattr__(self, "orientation_xyzw", q)


def source_name(source: str) -> str:
    """A ping's :attr:`Ping.source` without its directories: the file name, and after ``#`` the
    ping's place inside a recording (a Kongsberg ping keeps its head).

    Parameters
    ----------
    source : str
        ``Ping.source``: a path, with ``#<place>`` for a ping inside a recording.

    Returns
    -------
    str
        The name figure titles, reports and the ``fit`` CSV show.

    Examples
    --------
    >>> source_name("data/test/1468966347175925_raw.png"), source_name("data/sample.aris#3")
    ('1468966347175925_raw.png', 'sample.aris#3')
    >>> source_name("data/em.all#head2004/ping59681")   # the head is part of the name
    'em.all#head2004/ping59681'
    """
    path, sep, inside = source.partition("#")
    return os.path.basename(path) + sep + inside


def source_file(source: str) -> str:
    """The file (or stream address) of a ping's :attr:`Ping.source`: everything before ``#``.

    Examples
    --------
    >>> source_file("data/sample.aris#3"), source_file("data/test/1468966347175925_raw.png")
    ('data/sample.aris', 'data/test/1468966347175925_raw.png')
    >>> source_file("data/em.all#head2004/ping59681")
    'data/em.all'
    """
    return source.partition("#")[0]


def as_image(image: ArrayLike, name: str = "image", *, allow_empty: bool = False) -> NDArray[np.float32]:
    """Validate and convert an image to C-contiguous float32 of shape (n_bins, n_beams).

    Raises
    ------
    InputError
        If ``image`` is not 2-D, is empty, is not numeric, or contains NaN/inf.
    """
    try:
        arr = np.asarray(image)
    except Exception as exc:  # pragma: no cover - exotic array-likes
        raise InputError(f"{name}: cannot convert to an array ({exc})") from None
    if arr.dtype.kind not in "biuf":
        raise InputError(f"{name}: expected a numeric image, got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise InputError(f"{name}: expected a 2-D (n_bins, n_beams) image, got shape {arr.shape}")
    if arr.size == 0 and not allow_empty:
        raise InputError(f"{name}: image is empty (shape {arr.shape})")
    out = np.ascontiguousarray(arr, dtype=np.float32)
    if arr.dtype.kind == "f" and not np.isfinite(out).all():
        raise InputError(f"{name}: contains NaN or infinite values")
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class Ping:
    """One multibeam ping.

    Parameters
    ----------
    image : ndarray, shape (n_bins, n_beams), float32
        Intensities; raw pings are in [0, 1] (8-bit data maps 0-255 to 0-1).
    geometry : SonarGeometry
        The sonar geometry; ``image.shape`` must equal ``geometry.shape``.
    time_ns : int
        Ping time in integer nanoseconds since the Unix epoch (UTC); exact for µs file stamps.
        Must fit in int64 (``numpy.datetime64[ns]``), else :class:`~sonarmap.errors.InputError`.
    pose : Pose, optional
        Vehicle pose at the ping time, when known.
    source : str
        Where the ping came from (file path, ``path#frame``); empty if synthetic.
    meta : dict
        Free-form metadata (processing steps and parameters are recorded here).
    """

    image: NDArray[np.float32]
    geometry: SonarGeometry
    time_ns: int = 0
    pose: Pose | None = None
    source: str = ""
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        img = as_image(self.image, f"{self.source or 'ping'} image")
        if not isinstance(self.geometry, SonarGeometry):
            raise InputError(f"geometry: expected SonarGeometry, got {type(self.geometry).__name__}")
        self.geometry.check_image(img, f"{self.source or 'ping'} image")
        object.__setattr__(self, "image", img)
        object.__setattr__(self, "time_ns", _time_ns(self.time_ns, self.source or "ping"))

    @property
    def time_s(self) -> float:
        """Ping time in seconds since the Unix epoch (float; use ``time_ns`` for exactness)."""
        return self.time_ns * 1e-9

    @property
    def datetime64(self) -> np.datetime64:
        """Ping time as ``numpy.datetime64[ns]``."""
        return np.datetime64(self.time_ns, "ns")

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (n_bins, n_beams)."""
        return self.geometry.shape

    def replace(self, **changes: Any) -> Ping:
        """A copy with fields replaced; ``meta`` is copied, not shared."""
        changes.setdefault("meta", dict(self.meta))
        return dataclasses.replace(self, **changes)


def _time_ns(value: Any, name: str) -> int:
    """``value`` as a Python int of nanoseconds that fits in int64 (``datetime64[ns]``).

    Raises
    ------
    InputError
        If ``value`` is not a real number, is NaN/inf, or lies outside the int64 range.
    """
    if isinstance(value, bool):
        raise InputError(f"{name} time_ns: expected an integer number of ns, got bool")
    if isinstance(value, numbers.Integral):
        t = int(value)
    elif not isinstance(value, numbers.Real):
        try:
            t = operator.index(value)
        except TypeError:
            raise InputError(
                f"{name} time_ns: expected an integer number of ns, got {type(value).__name__}"
            ) from None
    else:
        f = float(value)
        if not math.isfinite(f):
            raise InputError(f"{name} time_ns: {f} is not a finite time")
        t = int(f)
    if not _INT64_MIN <= t <= _INT64_MAX:
        raise InputError(f"{name} time_ns: {t} is outside the int64 range of datetime64[ns]")
    return t
