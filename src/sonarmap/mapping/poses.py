"""Vehicle trajectories, interpolation to ping times, and sensor mounting extrinsics.

Frame conventions are those of :mod:`sonarmap.mapping.frames`: world NED, body FRD, sensor FRD,
orientations are body -> world rotations stored as unit quaternions, scalar last.  ROS REP-103
(ENU/FLU) trajectories and extrinsics are converted when read.

Trajectory CSV
--------------
A text file with one header row of column names and one row per pose::

    # frame: ned
    time_ns,x,y,z,qx,qy,qz,qw
    1700000000000000000,0.0,0.0,2.0,0.0,0.0,0.0,1.0
    ...

* ``time_ns`` (integer nanoseconds since the Unix epoch, UTC) **or** ``time_s`` (seconds, decimal;
  parsed exactly to the nanosecond from its text).
* ``x, y, z``: body origin in metres in the world frame.
* ``qx, qy, qz, qw``: body -> world rotation, scalar last (need not be exactly unit; normalised).
* Lines starting with ``#`` are comments; a comment ``# frame: enu`` (or ``ned``) declares the
  frame: ``ned`` = world NED / body FRD (the default), ``enu`` = ROS REP-103 world ENU / body FLU,
  converted to NED/FRD on reading.  The ``frame=`` argument of :func:`read_trajectory_csv`
  overrides the comment.  Extra columns are ignored; rows must have strictly increasing times
  (they are sorted if they are not; duplicates are an error).

Extrinsics JSON
---------------
The sensor's pose in the body frame (``p_b = R_bs p_s + t_bs``)::

    {"frame": "frd", "translation_m": [0.5, 0.0, 0.3], "rotation_xyzw": [0, 0, 0, 1]}

``rotation_xyzw`` may be replaced by ``rotation_rpy_deg: [roll, pitch, yaw]`` (intrinsic Z-Y-X,
i.e. ``Rotation.from_euler("ZYX", [yaw, pitch, roll])``).  With ``"frame": "flu"`` both the body and
the sensor frames are ROS FLU and are converted to FRD (``R_frd = F R_flu F``, ``t_frd = F t_flu``
with ``F = diag(1, -1, -1)``).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap._atomic import atomic_write_text
from sonarmap._files import parse_json
from sonarmap.errors import DataFormatError, InputError
from sonarmap.mapping.frames import (
    FRD_FROM_FLU,
    WORLD_FRAMES,
    compose_transforms,
    pose_enu_flu_to_ned_frd,
    pose_ned_frd_to_enu_flu,
    world_frame,
)
from sonarmap.ping import Pose

__all__ = [
    "Trajectory",
    "SensorPoses",
    "Extrinsics",
    "OutsidePolicy",
    "read_trajectory_csv",
    "write_trajectory_csv",
    "load_extrinsics",
    "save_extrinsics",
    "sensor_poses",
    "parse_time_s",
]

OutsidePolicy = Literal["error", "skip"]


def _rotation_cls() -> Any:
    from scipy.spatial.transform import Rotation

    return Rotation


def parse_time_s(text: str) -> int:
    """Exact integer nanoseconds from a decimal seconds string (``"1700000000.123456789"``).

    Raises
    ------
    InputError
        If ``text`` is not a plain decimal number.
    """
    s = text.strip()
    neg = s.startswith("-")
    if neg or s.startswith("+"):
        s = s[1:]
    if "e" in s.lower():
        try:
            return int(round(float(text) * 1e9))
        except ValueError:
            raise InputError(f"time_s: not a number ({text!r})") from None
    whole, _, frac = s.partition(".")
    if not (whole or frac) or not (whole.isdigit() or whole == "") or not (frac.isdigit() or frac == ""):
        raise InputError(f"time_s: not a number ({text!r})")
    frac9 = (frac + "000000000")[:9]
    rest = frac[9:]
    ns = int(whole or "0") * 1_000_000_000 + int(frac9)
    if rest and rest[0] >= "5":
        ns += 1
    return -ns if neg else ns


@dataclasses.dataclass(frozen=True, eq=False)
class Trajectory:
    """Vehicle poses over time in the world NED frame (body FRD).

    Parameters
    ----------
    time_ns : array_like of int, shape (n,)
        Strictly increasing stamps in nanoseconds since the Unix epoch.
    position_m : array_like, shape (n, 3)
        Body origin in the world frame (NED), metres.
    orientation_xyzw : array_like, shape (n, 4)
        Body -> world rotations, scalar last; normalised on construction.
    source : str
        Where the trajectory came from.
    """

    time_ns: NDArray[np.int64]
    position_m: NDArray[np.float64]
    orientation_xyzw: NDArray[np.float64]
    source: str = ""

    def __post_init__(self) -> None:
        name = self.source or "trajectory"
        t = np.asarray(self.time_ns)
        if t.dtype.kind not in "iu":
            if t.dtype.kind == "f" and np.all(np.isfinite(t)) and np.all(t == np.round(t)):
                t = t.astype(np.int64)
            else:
                raise InputError(f"{name}: time_ns must be integers (nanoseconds)")
        t = t.astype(np.int64).reshape(-1)
        p = np.asarray(self.position_m, dtype=np.float64)
        q = np.asarray(self.orientation_xyzw, dtype=np.float64)
        n = t.size
        if n < 1:
            raise InputError(f"{name}: trajectory has no poses")
        if p.shape != (n, 3):
            raise InputError(f"{name}: position_m must have shape ({n}, 3), got {p.shape}")
        if q.shape != (n, 4):
            raise InputError(f"{name}: orientation_xyzw must have shape ({n}, 4), got {q.shape}")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise InputError(f"{name}: positions/orientations contain NaN or infinite values")
        norm = np.linalg.norm(q, axis=1)
        if np.any(norm < 1e-6):
            raise InputError(f"{name}: zero-length quaternion at row {int(np.argmin(norm))}")
        q = q / norm[:, None]
        if n > 1 and np.any(np.diff(t) <= 0):
            order = np.argsort(t, kind="stable")
            t, p, q = t[order], p[order], q[order]
            dup = np.flatnonzero(np.diff(t) == 0)
            if dup.size:
                raise InputError(f"{name}: duplicate time stamp {int(t[dup[0]])} ns")
        for arr in (t, p, q):
            arr.setflags(write=False)
        object.__setattr__(self, "time_ns", t)
        object.__setattr__(self, "position_m", p)
        object.__setattr__(self, "orientation_xyzw", q)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_enu(
        cls, time_ns: ArrayLike, position_m: ArrayLike, orientation_xyzw: ArrayLike, *, source: str = ""
    ) -> Trajectory:
        """Build from ROS REP-103 poses (world ENU, body FLU), converting to NED/FRD."""
        p, q = pose_enu_flu_to_ned_frd(position_m, orientation_xyzw)
        return cls(np.asarray(time_ns), p, q, source=source)

    @classmethod
    def from_poses(
        cls, time_ns: Sequence[int] | ArrayLike, poses: Sequence[Pose], *, source: str = ""
    ) -> Trajectory:
        """Build from :class:`sonarmap.ping.Pose` values (``frame`` ``"ned"`` or ``"enu"``)."""
        pos = np.array([pp.position_m for pp in poses], dtype=np.float64).reshape(-1, 3)
        quat = np.array([pp.orientation_xyzw for pp in poses], dtype=np.float64).reshape(-1, 4)
        frames = {pp.frame.lower() for pp in poses}
        bad = frames - set(WORLD_FRAMES)
        if bad:
            raise InputError(f"poses: unknown frame(s) {sorted(bad)}; expected one of {WORLD_FRAMES}")
        enu = np.array([pp.frame.lower() == "enu" for pp in poses], dtype=bool)
        if enu.any():
            pos[enu], quat[enu] = pose_enu_flu_to_ned_frd(pos[enu], quat[enu])
        return cls(np.asarray(time_ns, dtype=np.int64), pos, quat, source=source)

    # ------------------------------------------------------------------ properties
    def __len__(self) -> int:
        return int(self.time_ns.size)

    @property
    def span_ns(self) -> tuple[int, int]:
        """First and last stamps."""
        return int(self.time_ns[0]), int(self.time_ns[-1])

    def pose(self, index: int) -> Pose:
        """The ``index``-th pose as a :class:`sonarmap.ping.Pose` (frame ``"ned"``)."""
        return Pose(self.position_m[index], self.orientation_xyzw[index], "ned")

    def to_enu(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Positions and orientations converted to ROS ENU/FLU."""
        return pose_ned_frd_to_enu_flu(self.position_m, self.orientation_xyzw)

    # ------------------------------------------------------------------ interpolation
    def inside(self, time_ns: ArrayLike, *, tolerance_ns: int = 0) -> NDArray[np.bool_]:
        """Whether each time lies within the trajectory's span (widened by ``tolerance_ns``)."""
        t = np.asarray(time_ns, dtype=np.int64)
        lo, hi = self.span_ns
        return (t >= lo - tolerance_ns) & (t <= hi + tolerance_ns)

    def interpolate(
        self,
        time_ns: ArrayLike,
        *,
        outside: OutsidePolicy = "error",
        tolerance_ns: int = 0,
    ) -> SensorPoses:
        """Body poses at ``time_ns``: positions linear, orientations by Slerp.

        Parameters
        ----------
        time_ns : array_like of int, shape (m,)
            Query times (nanoseconds).
        outside : {"error", "skip"}
            What to do with times outside the trajectory span: raise :class:`InputError`, or mark
            them invalid (``valid`` False, NaN pose) and count them in ``n_skipped``.
        tolerance_ns : int
            Times up to this far outside the span are clamped to the end pose instead.

        Returns
        -------
        SensorPoses
            Body -> world transforms (``frame="body"``).
        """
        if outside not in ("error", "skip"):
            raise InputError(f"outside: must be 'error' or 'skip', got {outside!r}")
        t = np.atleast_1d(np.asarray(time_ns)).astype(np.int64)
        valid = self.inside(t, tolerance_ns=int(tolerance_ns))
        lo, hi = self.span_ns
        if outside == "error" and not valid.all():
            bad = int(t[~valid][0])

            def utc(ns: int) -> str:
                return f"{np.datetime64(ns, 'ns')}Z"

            raise InputError(
                f"{self.source or 'trajectory'}: {int((~valid).sum())} of {t.size} ping time(s) lie outside "
                f"the trajectory span {utc(lo)} to {utc(hi)} (first: {utc(bad)}); drop them with "
                "--outside skip (outside='skip' in Python)"
            )
        m = t.size
        pos = np.full((m, 3), np.nan)
        rot = np.full((m, 3, 3), np.nan)
        quat = np.full((m, 4), np.nan)
        if valid.any():
            tq = np.clip(t[valid], lo, hi)
            rel = (self.time_ns - lo).astype(np.float64) * 1e-9
            relq = (tq - lo).astype(np.float64) * 1e-9
            for k in range(3):
                pos[valid, k] = np.interp(relq, rel, self.position_m[:, k])
            Rotation = _rotation_cls()
            if len(self) == 1:
                r = Rotation.from_quat(np.repeat(self.orientation_xyzw, relq.size, axis=0))
            else:
                from scipy.spatial.transform import Slerp

                r = Slerp(rel, Rotation.from_quat(self.orientation_xyzw))(relq)
            rot[valid] = r.as_matrix()
            quat[valid] = r.as_quat()
        return SensorPoses(
            time_ns=t, rotation=rot, translation_m=pos, orientation_xyzw=quat, valid=valid, frame="body"
        )


@dataclasses.dataclass(frozen=True, eq=False)
class SensorPoses:
    """Rigid transforms (to the world NED frame) at a set of times.

    Parameters
    ----------
    time_ns : ndarray of int64, shape (m,)
    rotation : ndarray, shape (m, 3, 3)
        Rotation matrices frame -> world (NaN where invalid).
    translation_m : ndarray, shape (m, 3)
        Frame origin in the world (NaN where invalid).
    orientation_xyzw : ndarray, shape (m, 4)
        The same rotations as quaternions, scalar last.
    valid : ndarray of bool, shape (m,)
        False for times outside the trajectory span (skipped).
    frame : str
        ``"body"`` (vehicle) or ``"sensor"`` (after applying extrinsics).
    """

    time_ns: NDArray[np.int64]
    rotation: NDArray[np.float64]
    translation_m: NDArray[np.float64]
    orientation_xyzw: NDArray[np.float64]
    valid: NDArray[np.bool_]
    frame: str = "sensor"

    def __len__(self) -> int:
        return int(self.time_ns.size)

    @property
    def n_skipped(self) -> int:
        """Number of times without a pose (outside the trajectory span)."""
        return int((~self.valid).sum())

    def with_extrinsics(self, extrinsics: Extrinsics | None) -> SensorPoses:
        """Sensor -> world transforms ``T_ws = T_wb T_bs`` from body -> world ones."""
        if extrinsics is None:
            return dataclasses.replace(self, frame="sensor")
        R, t = compose_transforms(self.rotation, self.translation_m, extrinsics.rotation, extrinsics.translation_m)
        q = np.full_like(self.orientation_xyzw, np.nan)
        if self.valid.any():
            q[self.valid] = _rotation_cls().from_matrix(R[self.valid]).as_quat()
        return SensorPoses(self.time_ns, R, t, q, self.valid, frame="sensor")

    def select(self, mask_or_index: ArrayLike | slice) -> SensorPoses:
        """A subset of the poses (slice, boolean mask or integer indices)."""
        k = mask_or_index if isinstance(mask_or_index, slice) else np.asarray(mask_or_index)
        return SensorPoses(
            self.time_ns[k], self.rotation[k], self.translation_m[k], self.orientation_xyzw[k], self.valid[k], self.frame
        )


@dataclasses.dataclass(frozen=True, eq=False)
class Extrinsics:
    """Sensor mounting: the sonar's pose in the vehicle body frame (FRD), ``p_b = R p_s + t``.

    Parameters
    ----------
    translation_m : array_like, shape (3,)
        Sensor origin in the body frame, metres.
    rotation_xyzw : array_like, shape (4,)
        Sensor -> body rotation, scalar last.
    """

    translation_m: NDArray[np.float64] = dataclasses.field(default_factory=lambda: np.zeros(3))
    rotation_xyzw: NDArray[np.float64] = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))

    def __post_init__(self) -> None:
        t = np.asarray(self.translation_m, dtype=np.float64).reshape(-1)
        q = np.asarray(self.rotation_xyzw, dtype=np.float64).reshape(-1)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise InputError(f"translation_m: need 3 finite numbers, got {t.tolist()}")
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-6:
            raise InputError(f"rotation_xyzw: need a non-zero finite quaternion (x, y, z, w), got {q.tolist()}")
        q = q / np.linalg.norm(q)
        t.setflags(write=False)
        q.setflags(write=False)
        object.__setattr__(self, "translation_m", t)
        object.__setattr__(self, "rotation_xyzw", q)

    @classmethod
    def from_rpy_deg(cls, translation_m: ArrayLike, roll: float, pitch: float, yaw: float) -> Extrinsics:
        """From roll/pitch/yaw in degrees (intrinsic Z-Y-X: yaw, then pitch, then roll)."""
        q = _rotation_cls().from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_quat()
        return cls(np.asarray(translation_m, dtype=np.float64), q)

    @property
    def rotation(self) -> NDArray[np.float64]:
        """Sensor -> body rotation matrix (3, 3)."""
        return _rotation_cls().from_quat(self.rotation_xyzw).as_matrix()

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible dict (frame ``frd``)."""
        return {
            "frame": "frd",
            "translation_m": [float(v) for v in self.translation_m],
            "rotation_xyzw": [float(v) for v in self.rotation_xyzw],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str = "extrinsics") -> Extrinsics:
        """Parse the JSON layout described in the module docstring."""
        if not isinstance(d, dict):
            raise DataFormatError("extrinsics must be a JSON object", source)
        frame = str(d.get("frame", "frd")).lower()
        if frame not in ("frd", "flu"):
            raise DataFormatError(f"'frame' must be 'frd' or 'flu', got {frame!r}", source)
        try:
            t = np.asarray(d.get("translation_m", [0.0, 0.0, 0.0]), dtype=np.float64)
            if "rotation_xyzw" in d and "rotation_rpy_deg" in d:
                raise DataFormatError("give either 'rotation_xyzw' or 'rotation_rpy_deg', not both", source)
            if "rotation_rpy_deg" in d:
                rpy = np.asarray(d["rotation_rpy_deg"], dtype=np.float64).reshape(-1)
                if rpy.shape != (3,):
                    raise DataFormatError("'rotation_rpy_deg' needs 3 numbers", source)
                q = _rotation_cls().from_euler("ZYX", rpy[::-1], degrees=True).as_quat()
            else:
                q = np.asarray(d.get("rotation_xyzw", [0.0, 0.0, 0.0, 1.0]), dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise DataFormatError(f"non-numeric extrinsics value ({exc})", source) from None
        try:
            ext = cls(t, q)
        except InputError as exc:
            raise DataFormatError(str(exc), source) from None
        if frame == "flu":
            F = FRD_FROM_FLU
            R = F @ ext.rotation @ F
            ext = cls(F @ ext.translation_m, _rotation_cls().from_matrix(R).as_quat())
        return ext


def load_extrinsics(path: str | os.PathLike[str]) -> Extrinsics:
    """Read a mounting-extrinsics JSON file (see the module docstring).

    Raises
    ------
    DataFormatError
        If the file is missing, not JSON, or has invalid fields.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise DataFormatError(f"cannot read extrinsics: {exc.strerror or exc}", p) from None
    return Extrinsics.from_dict(parse_json(data, p), source=str(p))


def save_extrinsics(extrinsics: Extrinsics, path: str | os.PathLike[str]) -> None:
    """Write extrinsics as JSON (frame ``frd``), atomically."""
    atomic_write_text(path, json.dumps(extrinsics.to_dict(), indent=1) + "\n")


_REQUIRED = ("x", "y", "z", "qx", "qy", "qz", "qw")


def read_trajectory_csv(path: str | os.PathLike[str], *, frame: str | None = None) -> Trajectory:
    """Read a trajectory CSV (layout in the module docstring), converting ENU/FLU to NED/FRD.

    Parameters
    ----------
    path : path-like
        The CSV file.
    frame : {"ned", "enu"}, optional
        Overrides the ``# frame:`` comment (default ``"ned"`` when neither is given).

    Raises
    ------
    DataFormatError
        If the file is missing, lacks required columns, or has non-numeric values.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise DataFormatError(f"cannot read trajectory: {exc.strerror or exc}", p) from None
    except UnicodeDecodeError:
        raise DataFormatError("not a UTF-8 text file", p) from None
    declared = None
    body: list[str] = []
    for line in text.splitlines():
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            c = s.lstrip("#").strip().lower()
            if c.startswith("frame"):
                declared = c.split(":", 1)[-1].split("=", 1)[-1].strip().split()[0] if (":" in c or "=" in c) else None
            continue
        body.append(line)
    fr = (frame or declared or "ned").lower()
    if fr not in WORLD_FRAMES:
        raise DataFormatError(f"frame must be one of {WORLD_FRAMES}, got {fr!r}", p)
    if not body:
        raise DataFormatError("empty trajectory (no header row)", p)
    reader = csv.reader(io.StringIO("\n".join(body)))
    header = [h.strip().lower() for h in next(reader)]
    col = {h: i for i, h in enumerate(header)}
    missing = [c for c in _REQUIRED if c not in col]
    tcol = "time_ns" if "time_ns" in col else ("time_s" if "time_s" in col else None)
    if tcol is None:
        missing.insert(0, "time_ns|time_s")
    if missing:
        raise DataFormatError(f"missing column(s) {', '.join(missing)} (header: {','.join(header)})", p)
    times: list[int] = []
    vals: list[list[float]] = []
    idx = [col[c] for c in _REQUIRED]
    for lineno, row in enumerate(reader, start=2):
        if not row or all(not v.strip() for v in row):
            continue
        try:
            tv = row[col[tcol]].strip()
            times.append(int(tv) if tcol == "time_ns" else parse_time_s(tv))
            vals.append([float(row[i]) for i in idx])
        except (ValueError, IndexError):
            raise DataFormatError(f"row {lineno}: missing or non-numeric value", p) from None
    if not times:
        raise DataFormatError("trajectory has no rows", p)
    arr = np.asarray(vals, dtype=np.float64)
    t = np.asarray(times, dtype=np.int64)
    try:
        if fr == "enu":
            return Trajectory.from_enu(t, arr[:, :3], arr[:, 3:], source=str(p))
        return Trajectory(t, arr[:, :3], arr[:, 3:], source=str(p))
    except InputError as exc:
        raise DataFormatError(str(exc).removeprefix(f"{p}: "), p) from None


def write_trajectory_csv(
    trajectory: Trajectory, path: str | os.PathLike[str], *, frame: str = "ned"
) -> None:
    """Write a trajectory CSV (``time_ns,x,y,z,qx,qy,qz,qw``) atomically, in NED/FRD or ENU/FLU."""
    fr = world_frame(frame)
    if fr == "enu":
        pos, quat = trajectory.to_enu()
        desc = "world ENU, body FLU (ROS REP-103)"
    else:
        pos, quat = trajectory.position_m, trajectory.orientation_xyzw
        desc = "world NED, body FRD"
    lines = [
        f"# sonarmap trajectory: {desc}; orientation = body->world quaternion, scalar last",
        f"# frame: {fr}",
        "time_ns,x,y,z,qx,qy,qz,qw",
    ]
    for t, p, q in zip(trajectory.time_ns.tolist(), pos.tolist(), quat.tolist(), strict=True):
        lines.append(f"{t}," + ",".join(repr(float(v)) for v in (*p, *q)))
    atomic_write_text(path, "\n".join(lines) + "\n")


def sensor_poses(
    trajectory: Trajectory,
    time_ns: ArrayLike,
    *,
    extrinsics: Extrinsics | None = None,
    outside: OutsidePolicy = "error",
    tolerance_ns: int = 0,
) -> SensorPoses:
    """Sensor -> world (NED) transforms at ping times: interpolate, then apply the mounting.

    See :meth:`Trajectory.interpolate` for ``outside`` and ``tolerance_ns``.
    """
    return trajectory.interpolate(time_ns, outside=outside, tolerance_ns=tolerance_ns).with_extrinsics(extrinsics)
