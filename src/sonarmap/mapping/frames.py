"""Frame conventions and conversions (marine NED/FRD inside, ROS ENU/FLU at the boundary).

Conventions
-----------
sonarmap uses the marine-robotics convention everywhere inside the library:

* **World frame: NED** - ``x`` north, ``y`` east, ``z`` down (metres, local tangent plane).
* **Body frame: FRD** - ``x`` forward, ``y`` right (starboard), ``z`` down.
* **Sensor frame: FRD** - the sonar's ``x`` is its boresight, ``y`` points to the side of positive
  azimuth (starboard, see :mod:`sonarmap.geometry`), ``z`` completes a right-handed frame (down
  when the sonar is mounted upright).  A return at range ``r``, azimuth ``a`` and elevation ``e``
  is at ``r (cos e cos a, cos e sin a, sin e)``; ``e > 0`` is *below* the imaging plane.

An orientation is the rotation ``R_wb`` that maps body-frame vectors into the world frame
(``p_w = R_wb p_b + t_wb``), stored as a unit quaternion, scalar last (``x, y, z, w``; scipy's
:meth:`scipy.spatial.transform.Rotation.from_quat` order).  With this convention a quaternion
built from ``Rotation.from_euler("ZYX", [yaw, pitch, roll])`` has the usual marine meaning
(heading clockwise from north, pitch nose-up, roll starboard-down).

ROS REP-103 data (world **ENU**: east, north, up; body **FLU**: forward, left, up) is converted at
the boundary with :func:`enu_to_ned`, :func:`ned_to_enu`, :func:`flu_to_frd`, :func:`frd_to_flu`,
:func:`pose_enu_flu_to_ned_frd` and :func:`pose_ned_frd_to_enu_flu`.  All conversions are exact
axis permutations/sign flips (involutions), so round trips are exact up to floating point.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError

__all__ = [
    "WORLD_FRAMES",
    "NED_FROM_ENU",
    "FRD_FROM_FLU",
    "enu_to_ned",
    "ned_to_enu",
    "flu_to_frd",
    "frd_to_flu",
    "pose_enu_flu_to_ned_frd",
    "pose_ned_frd_to_enu_flu",
    "transform_points",
    "invert_transform",
    "compose_transforms",
    "as_points",
    "polar_to_sensor",
    "world_frame",
]

#: Accepted world-frame names: ``"ned"`` (world NED, body FRD) and ``"enu"`` (ROS: ENU/FLU).
WORLD_FRAMES = ("ned", "enu")


def world_frame(frame: str) -> str:
    """``frame`` in lower case, checked against :data:`WORLD_FRAMES`.

    Raises
    ------
    InputError
        If it names no world frame.
    """
    fr = str(frame).lower()
    if fr not in WORLD_FRAMES:
        raise InputError(f"frame: must be one of {WORLD_FRAMES}, got {frame!r}")
    return fr

#: ``p_ned = NED_FROM_ENU @ p_enu`` (swap x/y, negate z); its own inverse.
NED_FROM_ENU: NDArray[np.float64] = np.array(
    [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]
)
NED_FROM_ENU.setflags(write=False)

#: ``p_frd = FRD_FROM_FLU @ p_flu`` (negate y and z); its own inverse.
FRD_FROM_FLU: NDArray[np.float64] = np.diag([1.0, -1.0, -1.0])
FRD_FROM_FLU.setflags(write=False)


def as_points(points: ArrayLike, name: str = "points") -> NDArray[np.float64]:
    """Validate ``points`` as a float64 array of shape ``(..., 3)``.

    Raises
    ------
    InputError
        If the last axis is not of length 3 or the array is not numeric.
    """
    try:
        p = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not a numeric array ({exc})") from None
    if p.ndim < 1 or p.shape[-1] != 3:
        raise InputError(f"{name}: expected shape (..., 3), got {p.shape}")
    return p


def enu_to_ned(points: ArrayLike) -> NDArray[np.float64]:
    """World ENU coordinates ``(..., 3)`` to NED (``(e, n, u) -> (n, e, -u)``)."""
    p = as_points(points)
    return np.stack([p[..., 1], p[..., 0], -p[..., 2]], axis=-1)


def ned_to_enu(points: ArrayLike) -> NDArray[np.float64]:
    """World NED coordinates ``(..., 3)`` to ENU (``(n, e, d) -> (e, n, -d)``)."""
    return enu_to_ned(points)


def flu_to_frd(points: ArrayLike) -> NDArray[np.float64]:
    """Body FLU coordinates ``(..., 3)`` to FRD (``(f, l, u) -> (f, -l, -u)``)."""
    p = as_points(points)
    return np.stack([p[..., 0], -p[..., 1], -p[..., 2]], axis=-1)


def frd_to_flu(points: ArrayLike) -> NDArray[np.float64]:
    """Body FRD coordinates ``(..., 3)`` to FLU."""
    return flu_to_frd(points)


def _as_quat(q: ArrayLike, name: str) -> NDArray[np.float64]:
    arr = np.asarray(q, dtype=np.float64)
    if arr.ndim < 1 or arr.shape[-1] != 4:
        raise InputError(f"{name}: expected quaternions of shape (..., 4), got {arr.shape}")
    return arr


def _convert_pose(
    position: ArrayLike, quat_xyzw: ArrayLike, world: NDArray[np.float64], body: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    from scipy.spatial.transform import Rotation

    p = as_points(position, "position")
    q = _as_quat(quat_xyzw, "orientation_xyzw")
    shape = q.shape[:-1]
    rot = Rotation.from_quat(q.reshape(-1, 4)).as_matrix()
    new = world @ rot @ body
    q_new = Rotation.from_matrix(new).as_quat().reshape(*shape, 4)
    return p @ world.T, q_new


def pose_enu_flu_to_ned_frd(
    position: ArrayLike, orientation_xyzw: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Convert ROS poses (ENU world, FLU body) to NED world / FRD body.

    Parameters
    ----------
    position : array_like, shape (..., 3)
        Body origin in ENU.
    orientation_xyzw : array_like, shape (..., 4)
        Rotation FLU body -> ENU world, scalar last.

    Returns
    -------
    position_ned : ndarray, shape (..., 3)
    orientation_xyzw : ndarray, shape (..., 4)
        Rotation FRD body -> NED world, ``R_ned_frd = NED_FROM_ENU @ R_enu_flu @ FRD_FROM_FLU``.
    """
    return _convert_pose(position, orientation_xyzw, NED_FROM_ENU, FRD_FROM_FLU)


def pose_ned_frd_to_enu_flu(
    position: ArrayLike, orientation_xyzw: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Convert NED/FRD poses to ROS ENU/FLU (inverse of :func:`pose_enu_flu_to_ned_frd`)."""
    return _convert_pose(position, orientation_xyzw, NED_FROM_ENU, FRD_FROM_FLU)


def transform_points(
    rotation: ArrayLike, translation: ArrayLike, points: ArrayLike
) -> NDArray[np.float64]:
    """Apply ``p' = R p + t`` with broadcasting over leading axes.

    Parameters
    ----------
    rotation : array_like, shape (..., 3, 3)
    translation : array_like, shape (..., 3)
    points : array_like, shape (..., 3)
    """
    R = np.asarray(rotation, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    p = as_points(points)
    return np.einsum("...ij,...j->...i", R, p) + t


def invert_transform(
    rotation: ArrayLike, translation: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Inverse of ``(R, t)``: ``(R^T, -R^T t)`` (batched over leading axes)."""
    R = np.asarray(rotation, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    Rt = np.swapaxes(R, -1, -2)
    return Rt, -np.einsum("...ij,...j->...i", Rt, t)


def compose_transforms(
    r_ab: ArrayLike, t_ab: ArrayLike, r_bc: ArrayLike, t_bc: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``T_ac = T_ab T_bc``: ``(R_ab R_bc, R_ab t_bc + t_ab)`` (batched over leading axes)."""
    Rab = np.asarray(r_ab, dtype=np.float64)
    Rbc = np.asarray(r_bc, dtype=np.float64)
    tab = np.asarray(t_ab, dtype=np.float64)
    tbc = np.asarray(t_bc, dtype=np.float64)
    return Rab @ Rbc, np.einsum("...ij,...j->...i", Rab, tbc) + tab


def polar_to_sensor(
    range_m: ArrayLike, azimuth_rad: ArrayLike, elevation_rad: ArrayLike | float = 0.0
) -> NDArray[np.float64]:
    """Sensor-frame (FRD) coordinates of returns: ``r (cos e cos a, cos e sin a, sin e)``.

    Inputs broadcast against each other; the result has a trailing axis of length 3.
    """
    r = np.asarray(range_m, dtype=np.float64)
    a = np.asarray(azimuth_rad, dtype=np.float64)
    e = np.asarray(elevation_rad, dtype=np.float64)
    ce = np.cos(e)
    return np.stack(np.broadcast_arrays(r * ce * np.cos(a), r * ce * np.sin(a), r * np.sin(e)), axis=-1)
