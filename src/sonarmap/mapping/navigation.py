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

Kongsberg EM multibeam pings (``meta["format"] == "kongsberg"``) are placed differently, by
:func:`kongsberg_placement` (see its Notes and ``docs/mapping.md``): their pose is the *sensor*
pose of the head - the acoustic origin given by the installation datagram's lever arms, the
transmit fan's plane from the TX array's mounting, the vessel attitude and the transmit tilt -
rather than a body pose whose forward axis is the boresight; :func:`navigation_pose` dispatches to
it and :func:`placed_ranges` adds the small bistatic range correction that goes with it.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import InputError, SonarmapWarning
from sonarmap.ping import Ping, Pose, source_file

if TYPE_CHECKING:
    from sonarmap.geometry import SonarGeometry
    from sonarmap.mapping.poses import SensorPoses
    from sonarmap.ranges import BeamRanges

__all__ = [
    "KongsbergPlacement",
    "NavigationWarning",
    "kongsberg_placement",
    "kongsberg_pose",
    "missing_navigation",
    "navigation_origin",
    "navigation_pose",
    "ping_sensor_poses",
    "placed_ranges",
    "static_pose",
]

#: ``Ping.meta["format"]`` of the pings placed by :func:`kongsberg_placement`.
KONGSBERG_FORMAT = "kongsberg"


class NavigationWarning(SonarmapWarning):
    """A ping was placed with an assumption because its recording lacks a placement parameter."""

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

    For a Kongsberg EM ping this is the head's sensor pose, :func:`kongsberg_pose` (use it with
    :func:`placed_ranges`).

    Raises
    ------
    InputError
        If the ping lacks latitude, longitude or heading (message names the ping).
    """
    why = missing_navigation(ping)
    if why is not None:
        raise InputError(f"{ping.source or 'ping'}: no navigation ({why})")
    if ping.meta.get("format") == KONGSBERG_FORMAT:
        return kongsberg_pose(ping, georef)
    m = ping.meta
    depth = _number(m, "depth_m") or 0.0
    pos = georef.geodetic_to_local(m["latitude_deg"], m["longitude_deg"], -depth, frame="ned")[0]
    hpr = [float(m["heading_deg"]), _number(m, "pitch_deg") or 0.0, _number(m, "roll_deg") or 0.0]
    from scipy.spatial.transform import Rotation

    q = Rotation.from_euler("ZYX", hpr, degrees=True).as_quat()
    return Pose(position_m=pos, orientation_xyzw=q, frame="ned")


def ping_sensor_poses(pings: Sequence[Ping]) -> SensorPoses:
    """The poses the pings carry (:attr:`Ping.pose`) as the sensor -> world transforms of
    :func:`~sonarmap.mapping.register.register_ranges` (one per ping, in order).

    Returns
    -------
    SensorPoses
        ``frame="body"``: apply extrinsics with :meth:`~sonarmap.mapping.poses.SensorPoses.with_extrinsics`.

    Raises
    ------
    InputError
        If a ping carries no pose (message names it).

    Examples
    --------
    >>> placed = [p.replace(pose=navigation_pose(p, georef)) for p in pings]  # doctest: +SKIP
    >>> poses = ping_sensor_poses(placed).with_extrinsics(None)             # doctest: +SKIP
    """
    from sonarmap.mapping.poses import SensorPoses, Trajectory

    pings = list(pings)
    missing = [p.source for p in pings if p.pose is None]
    if missing:
        raise InputError(f"pings: {missing[0]} carries no pose (and no trajectory was given: --poses)")
    times = np.array([p.time_ns for p in pings], dtype=np.int64)
    # interpolated at its own knots (indices: pings may share a time stamp, e.g. two heads)
    tr = Trajectory.from_poses(np.arange(len(pings)), [p.pose for p in pings])
    body = tr.interpolate(np.arange(len(pings)))
    return SensorPoses(times, body.rotation, body.translation_m, body.orientation_xyzw, body.valid, "body")


def static_pose() -> Pose:
    """The pose of a sonar on a fixed mount: the body at the origin, axes along the world's.

    With ``--extrinsics`` the mount's translation and rotation place the sonar relative to it.
    """
    return Pose(position_m=np.zeros(3), orientation_xyzw=np.array([0.0, 0.0, 0.0, 1.0]), frame="ned")


# ---------------------------------------------------------------------- Kongsberg EM multibeam
@dataclasses.dataclass(frozen=True, eq=False)
class KongsbergPlacement:
    """Where the returns of one Kongsberg EM head lie at one ping, in the vessel's heading frame.

    The *heading frame* is the frame of the sonar's own XYZ 88 soundings: origin at the vessel
    reference point, ``x`` forward along the heading and ``y`` to starboard (both horizontal),
    ``z`` down.  A return at range ``r`` (from transmit, ``c t / 2``) in image column ``j``
    (azimuth ``a_j``) lies at ``origin_m + (r + range_offset_m[j]) * rotation @ (cos a_j, sin a_j,
    0)``; in the world (NED, height 0 = the water level) the heading frame's origin is
    ``(fix - Rz(heading) antenna_m)`` horizontally and ``reference_depth_m`` down.

    Attributes
    ----------
    rotation : ndarray, shape (3, 3)
        Sensor -> heading frame.  Columns: the boresight (the transmit fan's direction closest to
        the vertical), the in-fan starboard axis, and their cross product (~aft or ~forward along
        the TX array's axis).
    origin_m : ndarray, shape (3,)
        The sensor origin re the reference point: the lever arms' ``(x_TX, y_RX, z_RX)`` rotated
        by roll and pitch.
    antenna_m : ndarray, shape (3,)
        The point whose position the position datagrams give (the active positioning system's
        antenna), re the reference point; rotated by roll and pitch unless the installation says
        the positions are motion-corrected (``PnM = 1``).
    reference_depth_m : float
        Depth of the vessel reference point below the water level: ``-WLZ + heave``.
    heading_deg : float
        The heading of the heading frame (clockwise from true north).
    range_offset_m : ndarray, shape (n_beams,)
        Per image column, the bistatic correction ``d_j . (m - o)`` (``m`` the midpoint of the TX
        and RX transducers, ``o`` = ``origin_m``, ``d_j`` the beam's direction): the range of a
        return from the sensor origin is its ``c t / 2`` plus this.
    tx_axis : ndarray, shape (3,)
        The TX array's axis (its own ``+x``) in the heading frame.
    tilt_deg : float
        The transmit tilt ``tau`` re the TX array (mean over the beams' sectors).
    plane_tilt_deg : float
        The tilt of the sensor's imaging plane from the plane perpendicular to the TX array (the
        least-squares plane of the transmit cone over the ping's beams).
    """

    rotation: NDArray[np.float64]
    origin_m: NDArray[np.float64]
    antenna_m: NDArray[np.float64]
    reference_depth_m: float
    heading_deg: float
    range_offset_m: NDArray[np.float64]
    tx_axis: NDArray[np.float64]
    tilt_deg: float
    plane_tilt_deg: float

    def directions(self, azimuth_rad: NDArray[np.float64]) -> NDArray[np.float64]:
        """Unit directions ``(n, 3)`` in the heading frame of returns at azimuths ``azimuth_rad``
        in the sensor's imaging plane (as registered)."""
        a = np.asarray(azimuth_rad, dtype=np.float64).reshape(-1)
        return np.cos(a)[:, None] * self.rotation[:, 0] + np.sin(a)[:, None] * self.rotation[:, 1]

    def cone_directions(self, azimuth_rad: NDArray[np.float64]) -> NDArray[np.float64]:
        """Unit directions ``(n, 3)`` on the transmit cone itself, ``d . u = sin(tau)``: where the
        beams point, which the planar registration approximates (a diagnostic)."""
        a = np.asarray(azimuth_rad, dtype=np.float64).reshape(-1)
        u = self.tx_axis
        down = np.array([0.0, 0.0, 1.0])
        v = _unit(down - (down @ u) * u, "the fan's vertical")
        tau = math.radians(self.tilt_deg)
        fan = np.cos(a)[:, None] * v + np.sin(a)[:, None] * self.rotation[:, 1]
        return math.cos(tau) * fan + math.sin(tau) * u


def _vector(meta: Mapping[str, Any], key: str) -> NDArray[np.float64] | None:
    v = meta.get(key)
    if v is None:
        return None
    try:
        arr = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None
    return arr if arr.shape == (3,) and np.all(np.isfinite(arr)) else None


def _rotation(heading_deg: float, pitch_deg: float, roll_deg: float) -> NDArray[np.float64]:
    """``Rz(heading) Ry(pitch) Rx(roll)`` (intrinsic Z-Y-X), the marine convention of frames.py."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("ZYX", [heading_deg, pitch_deg, roll_deg], degrees=True).as_matrix()


def _unit(v: NDArray[np.float64], what: str) -> NDArray[np.float64]:
    n = float(np.linalg.norm(v))
    if not n > 1e-9:
        raise InputError(f"Kongsberg placement: {what} is undefined (the TX array axis is vertical)")
    return v / n


@dataclasses.dataclass(frozen=True, eq=False)
class _KongsbergInstallation:
    """A Kongsberg EM head's installation parameters (``I`` datagram), in the heading frame.

    Attributes
    ----------
    origin_m : ndarray, shape (3,)
        The sensor origin ``(x_TX, y_RX, z_RX)`` re the reference point, rotated by roll and pitch.
    midpoint_m : ndarray, shape (3,)
        The midpoint of the TX and RX transducers, rotated likewise.
    antenna_m : ndarray, shape (3,)
        The active positioning system's antenna (rotated unless the positions are motion-corrected).
    tx_mounting_deg : ndarray, shape (3,)
        The TX array's mounting angles (roll, pitch, heading).
    reference_depth_m : float
        Depth of the reference point below the water level: ``-WLZ + heave``.
    assumed : tuple of str
        The parameters the recording lacks (taken as 0), for the warning.
    """

    origin_m: NDArray[np.float64]
    midpoint_m: NDArray[np.float64]
    antenna_m: NDArray[np.float64]
    tx_mounting_deg: NDArray[np.float64]
    reference_depth_m: float
    assumed: tuple[str, ...]


def _kongsberg_installation(meta: Mapping[str, Any], att: NDArray[np.float64]) -> _KongsbergInstallation:
    """The lever arms, TX mounting, water line and heave of a Kongsberg EM ping's ``meta``, the
    arms rotated by the vessel attitude ``att``; what is missing is taken as 0 and named."""
    assumed: list[str] = []
    tx = _vector(meta, "tx_lever_arm_m")
    rx = _vector(meta, "rx_lever_arm_m")
    if tx is None and rx is None:
        assumed.append("transducer lever arms")
        tx = rx = np.zeros(3)
    tx = rx if tx is None else tx
    rx = tx if rx is None else rx
    mount = _vector(meta, "tx_mounting_deg")
    if mount is None:
        assumed.append("TX mounting angles")
        mount = np.zeros(3)
    wlz = _number(meta, "waterline_z_m")
    if wlz is None:
        assumed.append("waterline (WLZ)")
        wlz = 0.0
    heave = _number(meta, "tx_time_heave_m")
    if heave is None:
        heave = _number(meta, "heave_m") or 0.0
    antenna, missing = _position_antenna(meta, att)
    if missing is not None:
        assumed.append(missing)
    return _KongsbergInstallation(
        origin_m=att @ np.array([tx[0], rx[1], rx[2]]),
        midpoint_m=att @ (0.5 * (tx + rx)),
        antenna_m=antenna,
        tx_mounting_deg=mount,
        reference_depth_m=-wlz + heave,
        assumed=tuple(assumed),
    )


def _position_antenna(meta: Mapping[str, Any], att: NDArray[np.float64]) -> tuple[NDArray[np.float64], str | None]:
    """The active positioning system's antenna re the reference point (rotated by ``att`` unless
    the installation says the positions are motion-corrected), and what is missing of its offsets."""
    inst = meta.get("installation")
    inst = inst if isinstance(inst, Mapping) else {}
    system = int(_number(meta, "position_system") or 0) & 0x03 or 1
    offsets = [_number(inst, f"P{system}{a}") for a in "XYZ"]
    missing = None
    if any(v is None for v in offsets):
        missing = f"positioning system {system} offsets (P{system}X/Y/Z)"
    ant = np.array([v or 0.0 for v in offsets])
    motion_corrected = _number(inst, f"P{system}M") == 1.0
    return (ant if motion_corrected else att @ ant), missing


class _KongsbergFan(NamedTuple):
    """The sensor's imaging plane of a Kongsberg EM ping (see :class:`KongsbergPlacement`)."""

    rotation: NDArray[np.float64]
    """Sensor -> heading frame: boresight, in-fan starboard axis, their cross product."""
    tx_axis: NDArray[np.float64]
    """The TX array's axis in the heading frame."""
    tilt_deg: float
    """The transmit tilt re the TX array."""
    plane_tilt_rad: float
    """The imaging plane's tilt from the plane perpendicular to the TX array."""
    azimuth_rad: NDArray[np.float64]
    """The beams' azimuths in the imaging plane."""


def _kongsberg_fan(att: NDArray[np.float64], mount: NDArray[np.float64], meta: Mapping[str, Any],
                   geometry: SonarGeometry) -> _KongsbergFan:
    """The imaging plane closest to the transmit cone of the TX array mounted at ``mount`` (roll,
    pitch, heading) on a vessel of attitude ``att``, over the beams of ``geometry``."""
    u = att @ _rotation(float(mount[2]), float(mount[1]), float(mount[0]))[:, 0]
    down = np.array([0.0, 0.0, 1.0])
    v = _unit(down - (down @ u) * u, "the fan's vertical")
    across = _unit(np.cross(u, v), "the fan's starboard axis")
    if across[1] < 0:
        across = -across
    tilt = _transmit_tilt_deg(meta, geometry.n_beams)
    # the plane closest to the transmit cone over the ping's beams: boresight tilted by t with
    # sin t = sin(tau) <cos a> / <cos^2 a> (least squares of the cone's u-component, sin tau, by
    # the plane's, cos(a) sin t); t = tau would be the cone's tangent plane at the vertical
    az = np.asarray(geometry.azimuth_rad, dtype=np.float64)
    c = np.cos(az)
    sin_t = math.sin(math.radians(tilt)) * float(c.mean() / (c * c).mean())
    t = math.asin(min(1.0, max(-1.0, sin_t)))
    boresight = math.cos(t) * v + math.sin(t) * u
    rotation = np.column_stack([boresight, across, np.cross(boresight, across)])
    return _KongsbergFan(rotation, u, tilt, t, az)


def _transmit_tilt_deg(meta: Mapping[str, Any], n_beams: int) -> float:
    """The transmit tilt re the TX array: the mean of the beams' sector tilts (of all sectors when
    the beams' sectors are unknown; 0 without finite tilts)."""
    tilts = np.asarray(meta.get("tx_sector_tilt_deg", [0.0]), dtype=np.float64).reshape(-1)
    sectors = np.asarray(meta.get("beam_tx_sector", np.zeros(n_beams, np.int64))).reshape(-1)
    if tilts.size == 0 or not np.all(np.isfinite(tilts)):
        return 0.0
    if sectors.size and sectors.min() >= 0 and sectors.max() < tilts.size:
        return float(np.mean(tilts[sectors]))
    return float(np.mean(tilts))


def kongsberg_placement(ping: Ping) -> KongsbergPlacement:
    """The geometry of a Kongsberg EM ping's returns in the vessel's heading frame.

    Parameters
    ----------
    ping : Ping
        A ping of :mod:`sonarmap.io.kongsberg` (its ``meta`` carries the attitude, the installation
        parameters, the transmit tilt and the beam pointing angles).

    Returns
    -------
    KongsbergPlacement

    Warns
    -----
    NavigationWarning
        When the recording has no installation lever arms or TX mounting angles (assumed 0: the
        transducers at the reference point, the TX array along the keel).

    Notes
    -----
    Conventions (Kongsberg "EM Series Datagram Formats"; each checked on the shared EM 2040
    recording against the sonar's own XYZ 88 soundings, see ``docs/mapping.md``):

    * Attitude: roll positive starboard down, pitch positive bow up, heading clockwise from true
      north, heave positive down; the vessel's rotation is ``Rz(heading) Ry(pitch) Rx(roll)``.
      Heave is the water-column datagram's heave at transmit (``tx_time_heave_m``).
    * Installation (``I``): lever arms ``x`` forward, ``y`` starboard, ``z`` down from the vessel
      reference point; mounting angles (roll, pitch, heading) rotate the array the same way;
      ``WLZ`` is the water line's ``z``.
    * Transmit: a line array steered by the sector's tilt ``tau`` *re the TX array* radiates on
      the cone ``d . u = sin(tau)`` around the array's axis ``u`` (its own ``+x``, so positive
      tilt points aft for an array mounted with heading 180).  The array moves with the vessel:
      ``u = R(pitch, roll) R_mount e_x`` (pitch stabilisation steers ``tau``, which the datagram
      records).  Registration is planar, so the sensor's imaging plane is the plane closest to
      that cone over the ping's beams: boresight ``cos(t) v + sin(t) u`` with ``v`` the vertical
      made perpendicular to ``u``, starboard axis ``u x v`` and ``sin t = sin(tau) <cos a> /
      <cos^2 a>`` over the beams' azimuths ``a``; the cone departs from it by ``r (sin(tau) -
      cos(a) sin(t))`` along the TX array's axis (a few cm at ``tau`` = 1.25 deg, 20 m).
    * Receive: the beam pointing angle is re the vertical (roll-stabilised), positive to port; it
      is the azimuth in the fan with the sign flipped (the reader's ``azimuth = -angle``).
    * Origin: the transmit cone's apex fixes the along-track origin (the TX transducer's ``x``),
      the receive angle's apex the across-track and vertical one (the RX transducer's ``y, z``);
      the two-way range ``c t / 2`` is measured from the transducers' midpoint, hence
      ``range_offset_m``.
    * Position: the position datagram's fix is the active positioning system's antenna (``PnX,
      PnY, PnZ`` of system ``n`` = the descriptor's bits 0-1), not corrected for its lever arm.
    * Sound speed: constant (straight rays at the datagram's sound speed); no refraction.

    Examples
    --------
    >>> from sonarmap.io import read_pings
    >>> ping = next(iter(read_pings("0077_20221109_123655_Belgica.all")))   # doctest: +SKIP
    >>> k = kongsberg_placement(ping)                                       # doctest: +SKIP
    >>> k.origin_m + (ping.meta["detected_range_m"] + k.range_offset_m)[:, None] * k.directions(
    ...     ping.geometry.azimuth_rad)              # the sonar's detections, heading frame  # doctest: +SKIP
    """
    m = ping.meta
    heading = _number(m, "heading_deg")
    if heading is None:
        raise InputError(f"{ping.source or 'ping'}: no navigation (its header has no heading)")
    att = _rotation(0.0, _number(m, "pitch_deg") or 0.0, _number(m, "roll_deg") or 0.0)
    inst = _kongsberg_installation(m, att)
    if inst.assumed:
        src = source_file(str(ping.source or "ping"))
        warnings.warn(NavigationWarning(f"{src}: Kongsberg placement without {', '.join(inst.assumed)} (assumed 0)"),
                      stacklevel=2)
    fan = _kongsberg_fan(att, inst.tx_mounting_deg, m, ping.geometry)
    placement = KongsbergPlacement(
        rotation=fan.rotation, origin_m=inst.origin_m, antenna_m=inst.antenna_m,
        reference_depth_m=inst.reference_depth_m, heading_deg=heading, range_offset_m=np.zeros(0),
        tx_axis=fan.tx_axis, tilt_deg=fan.tilt_deg, plane_tilt_deg=math.degrees(fan.plane_tilt_rad),
    )
    offset = placement.directions(fan.azimuth_rad) @ (inst.midpoint_m - inst.origin_m)
    return dataclasses.replace(placement, range_offset_m=offset)


def kongsberg_pose(ping: Ping, georef: Any) -> Pose:
    """The sensor pose of a Kongsberg EM head at a ping, in ``georef``'s local NED frame.

    The pose is that of :func:`kongsberg_placement`'s sensor frame (its origin and rotation,
    turned by the heading and placed at the vessel reference point under the position fix);
    register the returns with :func:`placed_ranges` so that the bistatic range correction is
    applied.

    Raises
    ------
    InputError
        If the ping lacks latitude, longitude or heading (message names the ping).

    Examples
    --------
    >>> g = navigation_origin(first_ping)                                   # doctest: +SKIP
    >>> placed = ping.replace(pose=kongsberg_pose(ping, g))                 # doctest: +SKIP
    >>> cloud = register_ranges([placed_ranges(placed, ranges)], ping_sensor_poses([placed]))  # doctest: +SKIP
    """
    why = missing_navigation(ping)
    if why is not None:
        raise InputError(f"{ping.source or 'ping'}: no navigation ({why})")
    k = kongsberg_placement(ping)
    m = ping.meta
    yaw = _rotation(k.heading_deg, 0.0, 0.0)
    fix = georef.geodetic_to_local(m["latitude_deg"], m["longitude_deg"], 0.0, frame="ned").reshape(-1)
    reference = np.array([fix[0], fix[1], 0.0]) - yaw @ k.antenna_m
    reference[2] = k.reference_depth_m
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(yaw @ k.rotation).as_quat()
    return Pose(position_m=reference + yaw @ k.origin_m, orientation_xyzw=q, frame="ned")


def placed_ranges(ping: Ping, ranges: BeamRanges) -> BeamRanges:
    """``ranges`` (a :class:`~sonarmap.ranges.BeamRanges` of ``ping``) as registered with the
    ping's :func:`navigation_pose`: for a Kongsberg EM ping the bistatic correction
    :attr:`KongsbergPlacement.range_offset_m` is added to every range; other pings are unchanged.

    Raises
    ------
    InputError
        If ``ranges`` has another beam count than the ping.

    Examples
    --------
    >>> ranges = placed_ranges(ping, process_ping(ping).ranges)             # doctest: +SKIP
    """
    if ping.meta.get("format") != KONGSBERG_FORMAT:
        return ranges
    off = kongsberg_placement(ping).range_offset_m
    r = np.asarray(ranges.range_m, dtype=np.float64)
    if r.shape != off.shape:
        raise InputError(f"ranges: {r.size} beams for the {off.size} beams of {ping.source or 'the ping'}")
    other = np.asarray(ranges.other_range_m, dtype=np.float64)
    return dataclasses.replace(ranges, range_m=r + off, other_range_m=other + off)
