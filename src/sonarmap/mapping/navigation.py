"""Poses from the navigation a recording carries, and the fixed-mount (static) pose.

Sonar files record the platform's navigation beside each ping: ARIS and DIDSON frame headers hold
``Latitude``/``Longitude`` (WGS 84 degrees), ``Depth`` (m) and ``Heading``/``Pitch``/``Roll``
(degrees); the readers put them in ``Ping.meta`` as ``latitude_deg``, ``longitude_deg``,
``depth_m``, ``heading_deg``, ``pitch_deg`` and ``roll_deg``.  This module turns them into
:class:`~sonarmap.ping.Pose` objects in a local NED frame at a geodetic origin
(:class:`~sonarmap.mapping.georef.GeoReference`), so that ``sonarmap map RECORDING`` needs no
trajectory file.

Conventions (those of the ARIS and DIDSON file formats, and of marine navigation generally):

* heading: degrees clockwise from true north; pitch: positive bow up; roll: positive starboard
  down.  The body frame is x forward, y starboard, z down, and the body-to-NED rotation is
  ``Rz(heading) Ry(pitch) Rx(roll)`` (intrinsic Z-Y-X).
* position: latitude/longitude of the platform's navigation point; ``depth_m`` positive down below
  the sea surface, which is height 0 of the local frame (``GeoReference.height0_m = 0``).  A
  missing depth is taken as 0 (at the surface), as for a surface vessel.

A position of exactly (0, 0) is how these formats say "no fix"; the readers drop it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from sonarmap.errors import InputError
from sonarmap.ping import Ping, Pose

__all__ = ["missing_navigation", "navigation_origin", "navigation_pose", "static_pose"]

_POSITION_KEYS = ("latitude_deg", "longitude_deg")


def _number(meta: Mapping[str, Any], key: str) -> float | None:
    v = meta.get(key)
    if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def missing_navigation(ping: Ping) -> str | None:
    """What a ping lacks to be placed from its own navigation, or None when it has all of it."""
    absent = [k for k in (*_POSITION_KEYS, "heading_deg") if _number(ping.meta, k) is None]
    if not absent:
        return None
    names = {"latitude_deg": "latitude", "longitude_deg": "longitude", "heading_deg": "heading"}
    return "its header has no " + " / ".join(names[k] for k in absent)


def navigation_origin(ping: Ping, crs: Any = None) -> Any:
    """A :class:`~sonarmap.mapping.georef.GeoReference` at a ping's recorded position (sea surface).

    Parameters
    ----------
    ping : Ping
        Normally the first ping of the recording; its position becomes the local origin.
    crs : int, str or pyproj.CRS, optional
        Projected CRS of the outputs; default: the UTM zone of the position.
    """
    from sonarmap.mapping.georef import GeoReference

    why = missing_navigation(ping)
    if why is not None:
        raise InputError(f"{ping.source or 'ping'}: no navigation ({why})")
    return GeoReference.from_origin(ping.meta["latitude_deg"], ping.meta["longitude_deg"], 0.0, crs=crs)


def navigation_pose(ping: Ping, georef: Any) -> Pose:
    """The platform pose at a ping from its recorded navigation, in ``georef``'s local NED frame.

    Raises
    ------
    InputError
        If the ping lacks latitude, longitude or heading (message names the ping).
    """
    why = missing_navigation(ping)
    if why is not None:
        raise InputError(f"{ping.source or 'ping'}: no navigation ({why})")
    m = ping.meta
    depth = _number(m, "depth_m") or 0.0
    pos = georef.geodetic_to_local(m["latitude_deg"], m["longitude_deg"], -depth, frame="ned")[0]
    hpr = [float(m["heading_deg"]), _number(m, "pitch_deg") or 0.0, _number(m, "roll_deg") or 0.0]
    from scipy.spatial.transform import Rotation

    q = Rotation.from_euler("ZYX", hpr, degrees=True).as_quat()
    return Pose(position_m=pos, orientation_xyzw=q, frame="ned")


def static_pose() -> Pose:
    """The pose of a sonar on a fixed mount: the body at the origin, axes along the world's.

    With ``--extrinsics`` the mount's translation and rotation place the sonar relative to it.
    """
    return Pose(position_m=np.zeros(3), orientation_xyzw=np.array([0.0, 0.0, 0.0, 1.0]), frame="ned")
