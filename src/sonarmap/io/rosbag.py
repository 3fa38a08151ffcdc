"""ROS 1 and ROS 2 bags: ``marine_acoustic_msgs/ProjectedSonarImage`` (read and write) and other sonar messages.

Reading and writing use the ``rosbags`` package (pure Python, no ROS installation).  The message
definitions ship with sonarmap (``sonarmap/io/msgs``) and are registered in rosbags' typestores.

Conventions at the boundary
---------------------------
* ``beam_directions`` follow the upstream ``ProjectedSonarImage.msg``: "The Z-axis is centered in
  the plane of the fan ("forward"), with X up ... the beams lie on the Y-Z plane, and each beam has
  an azimuth (rotation about X) value.  Zero azimuth is in the direction of the Z-axis".  A beam of
  our azimuth ``a`` (positive to starboard) is written as ``(x, y, z) = (0, -sin a, cos a)``, which
  is what the reference producer (the UW-APL Oculus driver, ``y = -sin(bearing)``,
  ``z = cos(bearing)``) writes and what the reference consumer (``sonar_image_proc``:
  ``azimuth = atan2(-y, z)``, drawn positive to the right, beams in increasing azimuth) reads back
  as ``a``.  So ``y`` points to port.  The .msg itself does not name y's direction (with X up a
  right-handed frame would put y to starboard, which is what some drivers and simulators write);
  the sign above is the one its reference producer and consumer agree on.  This is the
  ``"upstream"`` handedness; ``"mirrored"`` (``y`` to starboard) reads ``azimuth = atan2(y, forward)``.
* The fan plane is taken from the data: if ``z`` is 0 for every beam and ``x`` is not, the fan is
  in the x-y plane with ``x`` forward (REP-103 body frame, y to port: what sonarmap wrote before it
  followed the .msg); otherwise ``z`` is forward and ``x`` the out-of-fan (elevation) component.
* Handedness (``handedness=`` of :func:`iter_bag_pings`): ``"upstream"`` or ``"mirrored"`` force a
  rule.  ``"auto"`` (default) decides from the data where the data decide it: (1) the sonarmap
  geometry side channel (see below) matches one reading exactly -> that one; else (2) the azimuths
  of the upstream rule increase with beam index -> ``"upstream"`` (the order the reference
  producer writes and ``sonar_image_proc`` assumes); else (beams in decreasing or no azimuth order:
  upstream ``y`` with reversed beams and mirrored ``y`` with beams port to starboard look alike)
  the upstream rule is used and a :class:`BagConventionWarning` says it was a guess, once per topic.
  Beams are re-ordered, if needed, so that azimuth increases with column.
* ``image.data`` is range-major (``data[sample * beam_count + beam]``), which is what drivers
  publish in practice; unsigned integer data map to [0, 1] as ``value / max`` (``uint8``: / 255,
  ``uint16``: / 65535, ``uint32``: / (2**32 - 1), ``uint64``: / (2**64 - 1)); signed integer data
  as ``value / max`` too (``int8``: / 127 ...), and a negative sample is a
  :class:`~sonarmap.errors.DataFormatError`.  Float data are taken as is and must be finite and
  within [0, 1] (a raw ping's range, see :class:`~sonarmap.ping.Ping`) up to
  :data:`FLOAT_TOLERANCE`, by which they are clipped; anything else is a DataFormatError naming
  the bag, the topic and the message index.
* Header stamps must give a time of 0 (unknown) or in the years 1970-2200 (``nanosec`` < 1e9);
  ``sec * 10**9 + nanosec`` is computed in integers (no float on the way).
* Topics read, in order of precedence (the first kind a bag has is read; ``topic=`` reads one
  topic of any kind): ``ProjectedSonarImage`` (``marine_acoustic_msgs`` and the older
  ``acoustic_msgs``); ``marine_acoustic_msgs/RawSonarImage``; the legacy ``acoustic_msgs/SonarImage``;
  ``apl_msgs/RawData`` holding Oculus ``SimplePingResult`` messages (the last three decoded by
  :mod:`sonarmap.io.rosbag_sources`, whose notes give their mappings); ``sensor_msgs/Image`` only
  with a ``geometry=`` (rows = the geometry's range bins, row 0 nearest, columns = its beams in
  increasing azimuth; ``mono8``/``8UC1``, ``mono16``/``16UC1``, ``16SC1``, ``32SC1``, ``32FC1``,
  ``64FC1``).  A topic of a read type whose definition in the bag lacks the upstream fields, or a
  RawData topic without Oculus pings, is not readable.  A bag without a readable topic is a
  :class:`~sonarmap.errors.DataFormatError` saying why and listing the bag's topics and types.
* Written: :func:`write_bag` (ProjectedSonarImage); ranges (``SonarRanges``) and point clouds
  (``PointCloud2``) by :mod:`sonarmap.io.rosbag_products`.  ``ping_info`` beam widths come from
  :func:`beamwidths`.
* Only regular files are opened: a FIFO or device named ``x.bag`` (or inside a ROS 2 bag
  directory) is refused instead of hanging or reading forever.
* ``ranges`` are float32 in the message.  :func:`write_bag` therefore also writes, once per distinct
  geometry, a ``std_msgs/String`` with the geometry JSON on ``<topic>/sonarmap_geometry``; the
  reader uses it when it agrees with the message (so sonarmap -> bag -> sonarmap is lossless:
  ``dtype="float32"`` images, exact geometry and ns time stamps).
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import json
import math
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterable, Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from sonarmap.errors import DataFormatError, GeometryError, InputError, SonarmapWarning
from sonarmap.geometry import SonarGeometry, as_geometry, geometry_from_dict, plausible_elevation_beamwidth
from sonarmap.io._binary import U8_SCALE, check_time_ns, make_summary
from sonarmap._atomic import replace_output, temp_dir_beside
from sonarmap._files import open_regular, require_regular_file
from sonarmap.ping import Ping

__all__ = [
    "FORMAT",
    "HANDEDNESS",
    "BagConventionWarning",
    "MSGTYPE",
    "typestore",
    "write_bag",
    "beamwidths",
    "azimuth_from_ping_info",
    "ping_info",
    "bag_writer",
    "iter_bag_pings",
    "FLOAT_TOLERANCE",
    "sniff",
    "iter_pings",
    "count_pings",
    "summary",
]

FORMAT = "rosbag"
MSGTYPE = "marine_acoustic_msgs/msg/ProjectedSonarImage"
_SONAR_TYPES = {MSGTYPE, "acoustic_msgs/msg/ProjectedSonarImage"}
IMAGE_TYPE = "sensor_msgs/msg/Image"

#: Accepted values of ``handedness=`` (see the module notes).
HANDEDNESS = ("auto", "upstream", "mirrored")

#: ``sensor_msgs/Image`` encodings read (single channel), as numpy dtypes.
_IMAGE_ENCODINGS = {
    "mono8": np.dtype("u1"), "8UC1": np.dtype("u1"), "mono16": np.dtype("u2"), "16UC1": np.dtype("u2"),
    "16SC1": np.dtype("i2"), "32SC1": np.dtype("i4"), "32FC1": np.dtype("f4"), "64FC1": np.dtype("f8"),
}  # fmt: skip


class BagConventionWarning(SonarmapWarning):
    """The handedness of a bag's ``beam_directions`` was guessed (see :mod:`sonarmap.io.rosbag`)."""
_GEOMETRY_SUFFIX = "/sonarmap_geometry"
ROS1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"

_DTYPES = {
    0: np.dtype("u1"), 1: np.dtype("i1"), 2: np.dtype("u2"), 3: np.dtype("i2"), 4: np.dtype("u4"),
    5: np.dtype("i4"), 6: np.dtype("u8"), 7: np.dtype("i8"), 8: np.dtype("f4"), 9: np.dtype("f8"),
}  # fmt: skip
_DTYPE_CODES = {"uint8": 0, "uint16": 2, "float32": 8, "float64": 9}

#: How far outside [0, 1] a float pixel may lie (rounding in a producer) before it is an error.
FLOAT_TOLERANCE = 1e-6

#: Files of a ROS 2 bag directory that rosbags may open (checked to be regular files first).
_ROS2_FILE_SUFFIXES = (".yaml", ".db3", ".mcap", ".zstd")


@functools.cache
def typestore(ros_version: int = 2) -> Any:
    """A rosbags typestore (ROS 1 Noetic or ROS 2 Humble) with the marine_acoustic_msgs types."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros_version == 1 else Stores.ROS2_HUMBLE)
    base = resources.files("sonarmap.io.msgs").joinpath("marine_acoustic_msgs", "msg")
    types: dict[str, Any] = {}
    for name in ("PingInfo", "SonarImageData", "ProjectedSonarImage"):
        text = base.joinpath(f"{name}.msg").read_text(encoding="utf-8")
        types.update(get_types_from_msg(text, f"marine_acoustic_msgs/msg/{name}"))
    store.register(types)
    from sonarmap.io import rosbag_msgs

    rosbag_msgs.register(store)  # RawSonarImage, SonarRanges, DetectionFlag, acoustic_msgs, apl_msgs
    return store


def beamwidths(geometry: SonarGeometry) -> tuple[np.ndarray, np.ndarray]:
    """``PingInfo`` ``(tx_beamwidths, rx_beamwidths)`` (radians, float32) from a geometry.

    ``PingInfo.msg``: "-3db beamwidths, may be empty if not reported"; the package conventions:
    an empty array is "not reported", one value is constant across the ping, else one per beam.

    * ``rx_beamwidths`` (the across-fan width of each receive beam): a single-beam geometry's
      ``fov_rad`` (its beam's width); else the geometry's ``azimuth_beamwidth_rad`` - a two-way
      -3 dB width, written as the one-way -3 dB width ``sqrt(2)`` times larger (Gaussian main
      lobe) and read back by :func:`azimuth_from_ping_info`; else, when the geometry has a beam
      pattern (``psf``, an intensity pattern across beams), its full width at half maximum (-3 dB)
      in beams times the local beam spacing; one value when every beam has the same width, one
      per beam otherwise; else empty (a geometry without a pattern says nothing about the beams'
      widths).
    * ``tx_beamwidths`` (the width across the fan: an imaging sonar's vertical aperture, a swath
      multibeam's along-track transmit beamwidth): the geometry's ``elevation_beamwidth_rad`` as
      one value, else empty (not reported).  Read back by :func:`elevation_from_ping_info`.

    Examples
    --------
    >>> from sonarmap.geometry import preset
    >>> tx, rx = beamwidths(preset("didson-hf"))  # 0.3 deg two-way main lobe on every beam
    >>> tx.size, round(float(np.rad2deg(rx[0])), 3)
    (0, 0.424)
    >>> tx, rx = beamwidths(preset("didson-hf").replace(azimuth_beamwidth_rad=None))
    >>> rx.size  # the beam pattern's width; the lens fan is not evenly spaced: one per beam
    96
    >>> tx, rx = beamwidths(preset("aris3000-128"))  # standard ARIS lens: 14 deg vertical, per-beam widths
    >>> round(float(np.rad2deg(tx[0])), 3), rx.size
    (14.0, 128)
    """
    g = geometry
    tx = (np.zeros(0, np.float32) if g.elevation_beamwidth_rad is None
          else np.array([g.elevation_beamwidth_rad], np.float32))
    return tx, _rx_beamwidths(g)


def _rx_beamwidths(g: SonarGeometry) -> np.ndarray:
    """The ``rx_beamwidths`` of :func:`beamwidths`."""
    empty = np.zeros(0, np.float32)
    if g.n_beams == 1:
        return np.array([g.fov_rad], np.float32)
    pattern = g.psf_raw if g.psf_raw is not None else g.psf
    if g.azimuth_beamwidth_rad is not None:
        rx = math.sqrt(2.0) * np.asarray(g.azimuth_beamwidth_rad, dtype=np.float64)
    elif pattern is None:
        return empty
    else:
        w = _fwhm(np.asarray(pattern, dtype=np.float64))
        if not w > 0:
            return empty
        rx = w * np.gradient(np.asarray(g.azimuth_rad, dtype=np.float64))
    if np.allclose(rx, rx[0], rtol=1e-6, atol=0.0):
        rx = rx[:1]
    return rx.astype(np.float32)


def elevation_from_ping_info(info: Any) -> float | None:
    """The width across the fan a ``PingInfo`` reports: its ``tx_beamwidths`` when they hold one
    finite width in (0, pi] rad (one value, or the same value for every beam), else None."""
    tx = _one_width(getattr(info, "tx_beamwidths", ()))
    return None if tx is None else plausible_elevation_beamwidth(tx)


def azimuth_from_ping_info(info: Any) -> float | None:
    """The geometry's ``azimuth_beamwidth_rad`` (two-way -3 dB) from a ``PingInfo``'s
    ``rx_beamwidths`` (one-way -3 dB, see :func:`beamwidths`): when they hold one finite width in
    (0, pi/2] rad (one value, or the same value for every beam), that width over ``sqrt(2)``;
    else None (not reported, or widths that differ across beams)."""
    rx = _one_width(getattr(info, "rx_beamwidths", ()))
    return None if rx is None else two_way_beamwidth(rx)


def _one_width(widths: Any) -> float | None:
    """The width a ``PingInfo`` beamwidth array holds when it holds one: one finite value, or the
    same finite value for every beam (None: empty, non-finite or differing widths)."""
    w = np.asarray(widths, dtype=np.float64).reshape(-1)
    if w.size == 0 or not np.all(np.isfinite(w)) or not np.allclose(w, w[0], rtol=1e-6, atol=0.0):
        return None
    return float(w[0])


def two_way_beamwidth(one_way_rad: Any) -> float | None:
    """A beam's two-way -3 dB width from a message's one-way -3 dB width (Gaussian main lobe:
    ``1 / sqrt(2)`` of it); None unless it is a number in (0, pi/2] rad."""
    try:
        w = float(one_way_rad)
    except (TypeError, ValueError):
        return None
    return w / math.sqrt(2.0) if math.isfinite(w) and 0.0 < w <= math.pi / 2 else None


def _fwhm(p: np.ndarray) -> float:
    """Full width at half maximum (in samples, linear interpolation) of a single-peaked pattern."""
    if p.size == 0 or not np.all(np.isfinite(p)):
        return 0.0
    k = int(np.argmax(p))
    half = 0.5 * float(p[k])
    if half <= 0:
        return 0.0
    left = right = None
    for j in range(k, 0, -1):
        if p[j - 1] < half:
            left = j - (p[j] - half) / (p[j] - p[j - 1])
            break
    for j in range(k, p.size - 1):
        if p[j + 1] < half:
            right = j + (p[j] - half) / (p[j] - p[j + 1])
            break
    if left is None or right is None:
        return 0.0  # the pattern does not fall to half its peak inside the table
    return float(right - left)


# ---------------------------------------------------------------------- writing
def ping_info(geometry: SonarGeometry, store: Any) -> Any:
    """``marine_acoustic_msgs/PingInfo`` of a geometry: frequency, sound speed, :func:`beamwidths`."""
    tx, rx = beamwidths(geometry)
    return store.types["marine_acoustic_msgs/msg/PingInfo"](
        frequency=float(geometry.frequency_hz), sound_speed=float(geometry.sound_speed_m_s),
        tx_beamwidths=tx, rx_beamwidths=rx,
    )


def header(store: Any, ros_version: int, time_ns: int, frame_id: str, seq: int) -> Any:
    """``std_msgs/Header`` stamped ``time_ns`` (integer ns, split without a float)."""
    T = store.types
    sec, nsec = divmod(int(time_ns), 10**9)
    stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    if ros_version == 1:
        return T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame_id)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def beam_vectors(azimuth_rad: np.ndarray, store: Any) -> list[Any]:
    """Upstream ``beam_directions`` / ``beam_unit_vec``: ``(0, -sin a, cos a)`` (module notes)."""
    v3 = store.types["geometry_msgs/msg/Vector3"]
    return [v3(x=0.0, y=float(-math.sin(a)), z=float(math.cos(a))) for a in azimuth_rad]


@contextlib.contextmanager
def bag_writer(path: str | os.PathLike[str], version: int) -> Iterator[tuple[Any, Any, Any]]:
    """An open rosbags Writer on a temporary path beside ``path``, renamed onto it on success.

    Yields ``(writer, serialize, store)``: ``serialize(message, msgtype)`` gives the bytes
    (ROS 1 or CDR) and ``store`` is :func:`typestore` of ``version``.

    Raises
    ------
    InputError
        ``version`` not 1 or 2.
    """
    if version not in (1, 2):
        raise InputError(f"version: must be 1 or 2 (got {version!r})")
    target = Path(path)
    store = typestore(version)
    tmpdir = temp_dir_beside(target)
    tmp = tmpdir / target.name
    try:
        if version == 1:
            from rosbags.rosbag1 import Writer as W1

            writer: Any = W1(tmp)
            raw_serialize = store.serialize_ros1
        else:
            from rosbags.rosbag2 import Writer as W2

            writer = W2(tmp, version=9)
            raw_serialize = store.serialize_cdr

        def serialize(msg: Any, msgtype: str) -> bytes:
            return bytes(raw_serialize(msg, msgtype))

        with writer:
            yield writer, serialize, store
        replace_output(tmp, target)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


def _encode(ping: Ping, store: Any, ros_version: int, frame_id: str, dtype: str, seq: int) -> Any:
    T = store.types
    g = ping.geometry
    info = ping_info(g, store)
    # upstream .msg: z forward, x up, azimuth = rotation about x -> (0, -sin a, cos a), y to port
    dirs = beam_vectors(g.azimuth_rad, store)
    if dtype == "float32":
        data = np.ascontiguousarray(ping.image, dtype="<f4")
    elif dtype == "float64":
        data = np.ascontiguousarray(ping.image, dtype="<f8")
    elif dtype == "uint8":
        data = np.rint(np.clip(ping.image, 0, 1) * 255.0).astype(np.uint8)
    elif dtype == "uint16":
        data = np.rint(np.clip(ping.image, 0, 1) * 65535.0).astype("<u2")
    else:
        raise InputError(f"dtype: choose from {', '.join(_DTYPE_CODES)} (got {dtype!r})")
    image = T["marine_acoustic_msgs/msg/SonarImageData"](
        is_bigendian=False,
        dtype=_DTYPE_CODES[dtype],
        beam_count=g.n_beams,
        data=np.frombuffer(data.tobytes(), dtype=np.uint8),
    )
    return T[MSGTYPE](
        header=header(store, ros_version, ping.time_ns, frame_id, seq),
        ping_info=info,
        beam_directions=dirs,
        ranges=g.range_m.astype(np.float32),
        image=image,
    )


def write_bag(
    pings: Iterable[Ping],
    path: str | os.PathLike[str],
    *,
    version: int = 2,
    topic: str = "/sonar/image",
    frame_id: str = "sonar",
    dtype: str = "float32",
) -> int:
    """Write pings as ``marine_acoustic_msgs/ProjectedSonarImage`` messages; returns the count.

    Parameters
    ----------
    pings : iterable of Ping
    path : path-like
        ROS 1: the ``.bag`` file; ROS 2: the bag directory (sqlite3 storage).  Written atomically
        (temporary path beside the target, then renamed).
    version : {1, 2}
        ROS version.
    topic, frame_id : str
        Topic of the images and ``header.frame_id``.
    dtype : {"float32", "float64", "uint8", "uint16"}
        Pixel type; ``float32`` is lossless, ``uint8`` matches 8-bit sensor data.

    Returns
    -------
    int
        Number of ProjectedSonarImage messages written.

    Notes
    -----
    ``beam_directions`` follow the upstream .msg (z forward, x up): ``(0, -sin a, cos a)`` for
    azimuth ``a``, beams in increasing azimuth, so ``sonar_image_proc``'s ``atan2(-y, z)`` gives
    ``a`` back (see the module notes).  ``ping_info`` beam widths are those of :func:`beamwidths`.

    Examples
    --------
    >>> write_bag(pings, "survey.bag", version=1, dtype="uint8")  # doctest: +SKIP
    """
    if version not in (1, 2):
        raise InputError(f"version: must be 1 or 2 (got {version!r})")
    if dtype not in _DTYPE_CODES:
        raise InputError(f"dtype: choose from {', '.join(_DTYPE_CODES)} (got {dtype!r})")
    n = 0
    with bag_writer(path, version) as (writer, serialize, store):
        string_t = store.types["std_msgs/msg/String"]
        conn = writer.add_connection(topic, MSGTYPE, typestore=store)
        gconn = writer.add_connection(topic.rstrip("/") + _GEOMETRY_SUFFIX, "std_msgs/msg/String",
                                      typestore=store)
        seen: set[str] = set()
        for ping in pings:
            key = ping.geometry.key + ping.geometry.name
            if key not in seen:
                seen.add(key)
                d = ping.geometry.to_dict()
                d["azimuth_source"] = ping.geometry.azimuth_source
                writer.write(gconn, int(ping.time_ns), serialize(string_t(data=json.dumps(d)), "std_msgs/msg/String"))
            msg = _encode(ping, store, version, frame_id, dtype, n)
            writer.write(conn, int(ping.time_ns), serialize(msg, MSGTYPE))
            n += 1
    return n


# ---------------------------------------------------------------------- reading
def _bag_root(path: Path) -> Path:
    """The path rosbags opens: a ROS 1 file, or a ROS 2 bag directory."""
    if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").exists():
        return path.parent
    if path.is_file() and path.name == "metadata.yaml":
        return path.parent
    return path


@functools.lru_cache(maxsize=64)
def _fan_azimuths(dirs: bytes) -> tuple[np.ndarray, str]:
    """Azimuths by the upstream rule (message beam order, positive to starboard) and the fan plane.

    Parameters
    ----------
    dirs : bytes
        ``beam_directions`` as float64 ``(n_beams, 3)`` ``x, y, z`` rows.

    Returns
    -------
    azimuth_rad : ndarray of float64, shape (n_beams,)
        ``atan2(-y, forward)`` with ``forward = z`` (the .msg's axis) or, for a fan in the x-y plane
        (``z == 0`` for every beam, some ``x != 0``), ``forward = x``.
    plane : {"yz", "xy"}
        Which plane the fan lies in.

    Raises
    ------
    ValueError
        If no beam has a forward component.
    """
    v = np.frombuffer(dirs, dtype=np.float64).reshape(-1, 3)
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    if np.all(np.abs(z) < 1e-9) and np.any(np.abs(x) > 1e-9):
        forward, plane = x, "xy"
    else:
        forward, plane = z, "yz"
    if not np.any(forward > 0):
        raise ValueError("no beam direction points forward (z > 0, or x > 0 for a fan in the x-y plane)")
    az = np.arctan2(-y, forward)
    az.flags.writeable = False
    return az, plane


@functools.lru_cache(maxsize=64)
def _message_geometry(
    az_bytes: bytes, ranges: bytes, frequency: float, sound_speed: float, name: str,
    elevation_beamwidth_rad: float | None = None, azimuth_beamwidth_rad: float | None = None,
) -> tuple[SonarGeometry, np.ndarray | None]:
    """Geometry from per-beam azimuths (message order) and ranges; the column order if re-sorted."""
    return sorted_beam_geometry(np.frombuffer(az_bytes, dtype=np.float64),
                                np.frombuffer(ranges, dtype=np.float32).astype(np.float64), frequency, sound_speed, name,
                                elevation_beamwidth_rad=elevation_beamwidth_rad,
                                azimuth_beamwidth_rad=azimuth_beamwidth_rad)


def sorted_beam_geometry(
    az: np.ndarray, range_m: np.ndarray, frequency: float, sound_speed: float, name: str, *,
    elevation_beamwidth_rad: float | None = None, azimuth_beamwidth_rad: float | None = None,
) -> tuple[SonarGeometry, np.ndarray | None]:
    """Geometry of a message's beams, sorted by azimuth (with the column order if it re-sorted them);
    an unknown frequency reads as 1.8 MHz, a sound speed outside 1300-1700 m/s as 1500 m/s; the
    widths across the fan (see :func:`elevation_from_ping_info`) and of the beams in it (two-way,
    :func:`azimuth_from_ping_info`) the message reports, if any."""
    order = None
    if az.size > 1 and np.any(np.diff(az) <= 0):
        order = np.argsort(az, kind="stable")
        az = az[order]
    c = sound_speed if 1300.0 <= sound_speed <= 1700.0 else 1500.0
    geom = SonarGeometry(azimuth_rad=az, range_m=range_m, sound_speed_m_s=c, name=name,
                         frequency_hz=frequency if math.isfinite(frequency) and frequency > 0 else 1.8e6,
                         elevation_beamwidth_rad=elevation_beamwidth_rad, azimuth_beamwidth_rad=azimuth_beamwidth_rad)
    return geom, order


def _geometry_key(ranges_f32: np.ndarray, azimuth_rad: np.ndarray) -> bytes:
    """Side-channel lookup key: float32 ranges and float32 azimuths in increasing order."""
    return ranges_f32.astype(np.float32).tobytes() + np.sort(azimuth_rad).astype(np.float32).tobytes()


def _resolve_handedness(
    handedness: str, az_up: np.ndarray, ranges_f32: np.ndarray, exact: dict[bytes, SonarGeometry]
) -> tuple[int, bool]:
    """Sign applied to the upstream-rule azimuths (+1 upstream, -1 mirrored) and whether it is a guess.

    ``"auto"``: a side-channel geometry matching one reading decides; else upstream, which is
    certain only when its azimuths increase with beam index (or the fan is a single beam at 0).
    """
    if handedness == "upstream":
        return 1, False
    if handedness == "mirrored":
        return -1, False
    if exact:
        if _geometry_key(ranges_f32, az_up) in exact:
            return 1, False
        if _geometry_key(ranges_f32, -az_up) in exact:
            return -1, False
    if az_up.size > 1:
        return 1, not bool(np.all(np.diff(az_up) > 0))
    return 1, bool(az_up.size == 1 and az_up[0] != 0.0)


def _scale_pixels(a: np.ndarray) -> np.ndarray:
    """Pixels of any numeric dtype -> float32 in [0, 1] (see the module notes).

    Raises
    ------
    ValueError
        Non-finite or out-of-range floats, negative signed integers.
    """
    dt = a.dtype
    if dt.kind == "f":
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{dt.name} image contains NaN or infinite values")
        lo, hi = (float(a.min()), float(a.max())) if a.size else (0.0, 0.0)
        if lo < -FLOAT_TOLERANCE or hi > 1.0 + FLOAT_TOLERANCE:
            raise ValueError(
                f"{dt.name} pixels lie in [{lo:.6g}, {hi:.6g}], outside the [0, 1] of a raw ping"
            )
        return np.clip(a, 0.0, 1.0).astype(np.float32)
    if dt.itemsize == 1 and dt.kind == "u":
        return np.multiply(a, U8_SCALE, dtype=np.float32)
    info = np.iinfo(dt)
    if dt.kind == "i" and a.size and int(a.min()) < 0:
        raise ValueError(
            f"{dt.name} image has negative samples (min {int(a.min())}); intensities are >= 0"
        )
    return np.clip(a.astype(np.float64) / float(info.max), 0.0, 1.0).astype(np.float32)


def _decode_image(img: Any, n_ranges: int, n_beams: int) -> np.ndarray:
    """``SonarImageData`` -> float32 ``(n_ranges, n_beams)`` (range-major data)."""
    dt = _DTYPES.get(int(img.dtype))
    if dt is None:
        raise ValueError(f"unknown image dtype code {img.dtype}")
    dt = dt.newbyteorder(">" if img.is_bigendian else "<")
    raw = np.asarray(img.data, dtype=np.uint8)
    if raw.size != n_ranges * n_beams * dt.itemsize:
        raise ValueError(
            f"image has {raw.size} bytes, expected {n_ranges} ranges x {n_beams} beams x "
            f"{dt.itemsize} bytes"
        )
    if int(img.beam_count) not in (0, n_beams):
        raise ValueError(f"beam_count {img.beam_count} != {n_beams} beam directions")
    return _scale_pixels(raw.view(dt).reshape(n_ranges, n_beams))


def _decode_sensor_image(msg: Any, geometry: SonarGeometry) -> np.ndarray:
    """``sensor_msgs/Image`` -> float32 ``(n_bins, n_beams)`` of ``geometry`` (rows = range bins)."""
    enc = str(msg.encoding)
    dt = _IMAGE_ENCODINGS.get(enc)
    if dt is None:
        raise ValueError(f"image encoding {enc!r} is not a single-channel one ({', '.join(_IMAGE_ENCODINGS)})")
    dt = dt.newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if (h, w) != geometry.shape:
        raise ValueError(
            f"image is {h} x {w} (height x width), the geometry needs {geometry.n_bins} range bins x "
            f"{geometry.n_beams} beams"
        )
    raw = np.asarray(msg.data, dtype=np.uint8)
    if step < w * dt.itemsize or raw.size < step * h:
        raise ValueError(f"image step {step} / {raw.size} bytes do not hold {h} rows of {w} {enc} pixels")
    rows = raw[: step * h].reshape(h, step)[:, : w * dt.itemsize]
    return _scale_pixels(np.ascontiguousarray(rows).view(dt).reshape(h, w))


def _require_regular_bag(root: Path) -> None:
    """Refuse a bag that is (or, for a ROS 2 directory, contains) a FIFO, device or socket.

    Raises
    ------
    DataFormatError
        Naming the offending file.
    """
    if root.is_dir():
        try:
            entries = sorted(root.iterdir())
        except OSError as exc:
            raise DataFormatError(f"cannot list bag directory: {exc.strerror or exc}", root) from None
        for entry in entries:
            if entry.name == "metadata.yaml" or entry.suffix in _ROS2_FILE_SUFFIXES:
                require_regular_file(entry, "bag file")
        return
    require_regular_file(root, "bag")


def _reader(path: Path) -> Any:
    """An *opened* rosbags AnyReader (ROS 1 bags of any file name are opened via a symlink)."""
    from rosbags.highlevel import AnyReader

    root = _bag_root(path)
    _require_regular_bag(root)
    link_dir = None
    if root.is_file() and root.suffix != ".bag":
        with open_regular(root, "bag") as fh:
            is_ros1 = fh.read(len(ROS1_MAGIC)) == ROS1_MAGIC
        if is_ros1:  # rosbags picks the reader by extension; content decides here
            link_dir = Path(tempfile.mkdtemp(prefix="sonarmap-bag-"))
            link = link_dir / "bag.bag"
            link.symlink_to(root.resolve())
            root = link
    try:
        reader = AnyReader([root], default_typestore=typestore(2))
        reader.open()
    finally:
        if link_dir is not None:
            shutil.rmtree(link_dir, ignore_errors=True)
    return reader


def _describe_topics(reader: Any) -> str:
    """``/a (pkg/msg/T), /b (...)`` for every connection of an opened bag (sorted, deduplicated)."""
    seen = sorted({(c.topic, c.msgtype) for c in reader.connections})
    if not seen:
        return "the bag has no topics"
    return "the bag has " + ", ".join(f"{t} ({m})" for t, m in seen)


#: Kinds of sonar topics in order of precedence (the first kind a bag has is read), with their types.
_KINDS: tuple[tuple[str, frozenset[str]], ...] = (
    ("projected", frozenset(_SONAR_TYPES)),
    ("raw_image", frozenset({"marine_acoustic_msgs/msg/RawSonarImage", "acoustic_msgs/msg/RawSonarImage"})),
    ("legacy_image", frozenset({"acoustic_msgs/msg/SonarImage"})),
    ("oculus_raw", frozenset({"apl_msgs/msg/RawData"})),
)
_READABLE = "ProjectedSonarImage, RawSonarImage, acoustic_msgs/SonarImage, apl_msgs/RawData with Oculus pings"


def _field_names(reader: Any, msgtype: str) -> set[str]:
    """Field names of ``msgtype`` as the opened bag defines it (empty if unknown)."""
    try:
        return {name for name, _desc in reader.typestore.fielddefs[msgtype][1]}
    except (AttributeError, KeyError, TypeError, ValueError):
        return set()


def _unreadable(reader: Any, path: Path, conn: Any, counts: dict[str, int] | None = None) -> str | None:
    """Why a connection of a readable type cannot be read (None if it can); the pings found on an
    Oculus RawData topic are added to ``counts``."""
    from sonarmap.io.rosbag_msgs import RAW_DATA, REQUIRED_FIELDS
    from sonarmap.io.rosbag_sources import count_oculus

    need = REQUIRED_FIELDS.get(conn.msgtype)
    if need is not None:
        missing = sorted(need - _field_names(reader, conn.msgtype))
        if missing:
            return f"{conn.topic}: its {conn.msgtype} definition has no {', '.join(missing)} (not the upstream one)"
    if conn.msgtype == RAW_DATA:
        n = count_oculus(reader, path, [conn])[conn.topic]
        if counts is not None:
            counts[conn.topic] = counts.get(conn.topic, 0) + n
        if not n:
            return f"{conn.topic}: its RawData hold no Oculus SimplePingResult"
    return None


def _select_connections(
    reader: Any, path: Path, topic: str | None, has_geometry: bool, counts: dict[str, int] | None = None
) -> tuple[str, list[Any]]:
    """The kind of sonar topic to read and its connections.

    Kinds, in order of precedence (:data:`_KINDS`): ``"projected"`` (ProjectedSonarImage),
    ``"raw_image"`` (RawSonarImage), ``"legacy_image"`` (acoustic_msgs/SonarImage),
    ``"oculus_raw"`` (apl_msgs/RawData holding Oculus pings); then ``"sensor_image"``
    (``sensor_msgs/Image``, only with a user geometry).  With ``topic`` only that topic counts.
    ``counts`` receives the pings per Oculus RawData topic (which are scanned to decide).

    Raises
    ------
    DataFormatError
        No readable topic (listing the bag's topics and types, and why a topic of a readable
        type could not be read), or ``topic`` is not readable.
    """
    conns = [c for c in reader.connections if topic is None or c.topic == topic]
    reasons: list[str] = []
    for kind, types in _KINDS:
        ok = []
        for c in (c for c in conns if c.msgtype in types):
            why = _unreadable(reader, path, c, counts)
            if why is None:
                ok.append(c)
            else:
                reasons.append(why)
        if ok:
            return kind, ok
    images = [c for c in conns if c.msgtype == IMAGE_TYPE]
    why = "".join(f"; {r}" for r in reasons)
    if topic is not None:
        if images and has_geometry:
            return "sensor_image", images
        if images:
            raise DataFormatError(
                f"topic {topic!r} is a sensor_msgs/Image: pass a geometry (geometry=, or --sonar PRESET|JSON on the command line) "
                "whose range bins and beams match its rows and columns", path
            )
        raise DataFormatError(
            f"no ProjectedSonarImage messages on topic {topic!r}; {_describe_topics(reader)}{why}", path
        )
    if images and has_geometry:
        return "sensor_image", images
    hint = ""
    if images:
        hint = "; its sensor_msgs/Image topics need a geometry (geometry=, --geometry)"
    raise DataFormatError(
        f"no readable sonar topic ({_READABLE}{', or sensor_msgs/Image with a geometry' if not images else ''})"
        f"{why}; {_describe_topics(reader)}{hint}", path
    )


def iter_bag_pings(
    path: str | os.PathLike[str],
    *,
    topic: str | None = None,
    geometry: SonarGeometry | str | os.PathLike[str] | None = None,
    handedness: str = "auto",
    start: int = 0,
    stop: int | None = None,
) -> Iterator[Ping]:
    """Lazily yield the sonar pings of a ROS 1 or ROS 2 bag, in time order.

    Parameters
    ----------
    path : path-like
        ROS 1 ``.bag`` file, ROS 2 bag directory (or its ``metadata.yaml`` / storage file).
    topic : str, optional
        Only this topic (default: every topic of the first kind the bag has, in the order
        ProjectedSonarImage, RawSonarImage, acoustic_msgs/SonarImage, Oculus RawData, then
        ``sensor_msgs/Image`` when ``geometry`` is given; see the module notes).
    geometry : SonarGeometry, preset name or JSON path, optional
        Overrides the geometry of every ping; required for ``sensor_msgs/Image`` topics (rows =
        its range bins, row 0 nearest; columns = its beams).
    handedness : {"auto", "upstream", "mirrored"}
        How ``beam_directions`` map to azimuth: ``"upstream"`` ``atan2(-y, forward)`` (the .msg's
        frame, ``y`` to port), ``"mirrored"`` ``atan2(y, forward)`` (``y`` to starboard), ``"auto"``
        decides from the data and warns (:class:`BagConventionWarning`) when it had to guess; see
        the module notes.
    start, stop : int
        Ping positions ``[start, stop)`` (``stop`` None: to the end).  ProjectedSonarImage and
        ``sensor_msgs/Image`` messages before ``start`` are not deserialized (one message is one
        ping); the other kinds are decoded and dropped (a raw Oculus message may hold no ping).

    Yields
    ------
    Ping
        ``meta`` holds ``topic``, ``message_index``, ``seq`` (ROS 1) and, for ProjectedSonarImage,
        ``handedness`` (the rule used) and ``fan_plane`` (``"yz"`` or ``"xy"``).

    Raises
    ------
    DataFormatError
        If the bag cannot be parsed, has no readable sonar topic (the message lists its topics and
        types), or a message is inconsistent (sizes, directions, ranges, stamps).
    InputError
        If ``handedness`` is not one of :data:`HANDEDNESS`.

    Examples
    --------
    >>> pings = iter_bag_pings("survey.bag", handedness="mirrored")  # doctest: +SKIP
    """
    from sonarmap.io.reader import check_ping_range

    override = _reading_options(geometry, handedness)
    start, stop = check_ping_range(start, stop)
    p = Path(path)
    reader = _open_reader(p)
    try:
        kind, conns = _select_connections(reader, p, topic, override is not None)
        if kind == "sensor_image":
            assert override is not None
            yield from _iter_sensor_images(reader, p, conns, override, start, stop)
            return
        if kind != "projected":
            from sonarmap.io.rosbag_sources import iter_kind

            yield from itertools.islice(iter_kind(kind, reader, p, conns, override), start, stop)
            return
        exact = _exact_geometries(reader, p, conns)
        warned: set[str] = set()
        # one message is one ping: the messages before start are skipped undecoded
        messages = _guarded(p, reader.messages(connections=conns)) if conns else iter(())
        for idx, (conn, _t, raw) in itertools.islice(enumerate(messages), start, stop):
            ping, guessed = _projected_ping(reader, conn, raw, p, idx, override, exact, handedness)
            # warned here, not in a helper: the warning's stacklevel points at our caller
            if guessed and conn.topic not in warned:
                warned.add(conn.topic)
                warn_guessed_handedness(p, conn.topic)
            yield ping
    finally:
        _close_quietly(reader)


def _reading_options(geometry: SonarGeometry | str | os.PathLike[str] | None, handedness: str) -> SonarGeometry | None:
    """The geometry override of a bag reader (None without one), once ``handedness`` is checked;
    shared by :func:`iter_bag_pings` and :func:`sonarmap.io.rosbag_follow.follow_sqlite_bag`.

    Raises
    ------
    InputError
        If ``handedness`` is not one of :data:`HANDEDNESS`.
    """
    if handedness not in HANDEDNESS:
        raise InputError(f"handedness: choose from {', '.join(HANDEDNESS)} (got {handedness!r})")
    return None if geometry is None else as_geometry(geometry)


def _open_reader(path: Path) -> Any:
    """An open rosbags reader of the bag at ``path``; its failures are DataFormatErrors."""
    try:
        return _reader(path)
    except DataFormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags raises various types on corrupt bags
        raise DataFormatError(f"cannot read bag: {type(exc).__name__}: {exc}", path) from None


def _close_quietly(reader: Any) -> None:
    """Close ``reader``, ignoring any error that raises."""
    try:
        reader.close()
    except Exception:  # noqa: BLE001,S110 - closing a corrupt bag must not mask the real error
        pass


def _exact_geometries(reader: Any, path: Path, conns: list[Any]) -> dict[bytes, SonarGeometry]:
    """The geometries of the exact-geometry side channels of the ProjectedSonarImage topics
    ``conns`` (see :func:`add_exact_geometry`); damaged messages are skipped."""
    gtopics = {c.topic + _GEOMETRY_SUFFIX for c in conns} | {c.topic.rstrip("/") + _GEOMETRY_SUFFIX for c in conns}
    gconns = [c for c in reader.connections if c.topic in gtopics and c.msgtype == "std_msgs/msg/String"]
    exact: dict[bytes, SonarGeometry] = {}
    for conn, _t, raw in _guarded(path, reader.messages(connections=gconns)) if gconns else ():
        try:
            text = reader.deserialize(raw, conn.msgtype).data
        except Exception:  # noqa: BLE001,S112 - damaged side channel: use the message fields
            continue
        add_exact_geometry(exact, text, path)
    return exact


def _projected_ping(
    reader: Any, conn: Any, raw: bytes, path: Path, idx: int, override: SonarGeometry | None,
    exact: dict[bytes, SonarGeometry], handedness: str,
) -> tuple[Ping, bool]:
    """Message ``idx`` (a ProjectedSonarImage on ``conn``) -> (Ping, whether the handedness was a
    guess); a message that does not deserialise or decode is a DataFormatError."""
    try:
        msg = reader.deserialize(raw, conn.msgtype)
    except Exception as exc:  # noqa: BLE001
        raise DataFormatError(f"corrupt message {idx}: {type(exc).__name__}: {exc}", path) from None
    try:
        return _ping_from_msg(msg, path, conn.topic, idx, override, exact, handedness)
    except (ValueError, GeometryError) as exc:
        raise DataFormatError(f"message {idx} on {conn.topic}: {exc}", path) from None


def warn_guessed_handedness(path: Path, topic: str) -> None:
    """The :class:`BagConventionWarning` for a topic whose handedness had to be guessed."""
    warnings.warn(
        f"{path}: {topic}: beam_directions do not increase in azimuth with beam index, "
        "so y to port (upstream) and y to starboard cannot be told apart; read as upstream "
        "(azimuth = atan2(-y, forward)); pass handedness='mirrored' if the producer's y "
        "points to starboard, or handedness='upstream' to confirm",
        BagConventionWarning, stacklevel=3,
    )


def add_exact_geometry(exact: dict[bytes, SonarGeometry], text: str, path: Path) -> None:
    """Parse one message of the exact-geometry side channel sonarmap writes beside a
    ProjectedSonarImage topic into ``exact`` (keyed by its float32 ranges and azimuths); a
    damaged one is ignored (the image messages' own fields are used)."""
    try:
        d = json.loads(text)
        src = d.pop("azimuth_source", "table")
        g = geometry_from_dict(d, source=f"{path} geometry")
        if g.azimuth_source != src:
            g = g.replace(azimuth_source=src)
        exact[_geometry_key(g.range_m, g.azimuth_rad)] = g
    except Exception:  # noqa: BLE001 - damaged side channel
        return


def _iter_sensor_images(reader: Any, path: Path, conns: list[Any], geometry: SonarGeometry, start: int = 0,
                        stop: int | None = None) -> Iterator[Ping]:
    """Pings ``start:stop`` of ``sensor_msgs/Image`` topics with a user geometry (see
    :func:`iter_bag_pings`); the messages before ``start`` are not deserialized."""
    for idx, (conn, _t, raw) in itertools.islice(enumerate(_guarded(path, reader.messages(connections=conns))),
                                                 start, stop):
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # noqa: BLE001
            raise DataFormatError(f"corrupt message {idx}: {type(exc).__name__}: {exc}", path) from None
        try:
            image = _decode_sensor_image(msg, geometry)
            t_ns = _stamp_ns(msg.header.stamp)
        except ValueError as exc:
            raise DataFormatError(f"message {idx} on {conn.topic}: {exc}", path) from None
        meta: dict[str, Any] = {"format": FORMAT, "topic": conn.topic, "message_index": idx}
        if hasattr(msg.header, "seq"):
            meta["seq"] = int(msg.header.seq)
        yield Ping(image=image, geometry=geometry, time_ns=t_ns, source=f"{path}#{conn.topic}:{idx}", meta=meta)


def _stamp_ns(stamp: Any) -> int:
    """``sec * 10**9 + nanosec`` in integers, checked (0 or 1970-2200)."""
    sec, nsec = int(stamp.sec), int(stamp.nanosec)
    if not 0 <= nsec < 10**9:
        raise ValueError(f"header stamp nanosec {nsec} is outside 0-999999999")
    return check_time_ns(sec * 10**9 + nsec, "header stamp")


def _guarded(path: Path, it: Iterator[Any]) -> Iterator[Any]:
    """Iterate rosbags' message generator, turning its parse errors into DataFormatError."""
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - rosbags raises various types on corrupt bags
            raise DataFormatError(f"corrupt bag: {type(exc).__name__}: {exc}", path) from None
        yield item


def _ping_from_msg(
    msg: Any, path: Path, topic: str, idx: int, override: SonarGeometry | None,
    exact: dict[bytes, SonarGeometry], handedness: str = "auto",
) -> tuple[Ping, bool]:
    """One ProjectedSonarImage -> (Ping, whether the handedness was a guess)."""
    dirs = np.array([[d.x, d.y, d.z] for d in msg.beam_directions], dtype=np.float64).reshape(-1, 3)
    ranges = np.asarray(msg.ranges, dtype=np.float32)
    if dirs.shape[0] < 1 or ranges.size < 1:
        raise ValueError(f"empty geometry ({dirs.shape[0]} beams, {ranges.size} ranges)")
    if not (np.all(np.isfinite(dirs)) and np.all(np.isfinite(ranges))):
        raise ValueError("beam directions or ranges contain NaN/inf")
    name = (msg.header.frame_id or topic).strip("/").replace("/", "-") or "sonar"
    az_up, plane = _fan_azimuths(dirs.tobytes())
    sign, guessed = _resolve_handedness(handedness, az_up, ranges, exact)
    if override is not None:
        guessed = False  # the user's geometry decides the azimuths
    az = az_up if sign > 0 else -az_up
    geom, order = _message_geometry(
        np.ascontiguousarray(az).tobytes(), ranges.tobytes(), float(msg.ping_info.frequency),
        float(msg.ping_info.sound_speed), name, elevation_from_ping_info(msg.ping_info),
        azimuth_from_ping_info(msg.ping_info),
    )
    image = _decode_image(msg.image, ranges.size, dirs.shape[0])
    if order is not None:
        image = np.ascontiguousarray(image[:, order])
    if override is not None:
        geom = override
    else:
        g = exact.get(_geometry_key(ranges, geom.azimuth_rad))
        if g is not None and np.allclose(g.azimuth_rad, geom.azimuth_rad, atol=1e-9):
            geom = g
    t_ns = _stamp_ns(msg.header.stamp)
    meta: dict[str, Any] = {
        "format": FORMAT, "topic": topic, "message_index": idx,
        "handedness": "upstream" if sign > 0 else "mirrored", "fan_plane": plane,
    }
    if hasattr(msg.header, "seq"):
        meta["seq"] = int(msg.header.seq)
    ping = Ping(image=image, geometry=geom, time_ns=t_ns, source=f"{path}#{topic}:{idx}", meta=meta)
    return ping, guessed


# ---------------------------------------------------------------------- registry hooks
def sniff(path: Path, head: bytes) -> bool:
    """ROS 1 bags (``#ROSBAG V2.0``), ROS 2 bag directories (``metadata.yaml``) and their files."""
    if path.is_dir():
        return (path / "metadata.yaml").exists()
    if head.startswith(ROS1_MAGIC):
        return True
    if path.name == "metadata.yaml" or (
        path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").exists()
    ):
        return True
    return head.startswith(MCAP_MAGIC)


def iter_pings(
    path: str | os.PathLike[str],
    *,
    geometry: SonarGeometry | str | os.PathLike[str] | None = None,
    topic: str | None = None,
    handedness: str = "auto",
    start: int = 0,
    stop: int | None = None,
    **_: Any,
) -> Iterator[Ping]:
    """Registry hook: :func:`iter_bag_pings` (``read_pings(..., handedness=...)`` reaches it)."""
    yield from iter_bag_pings(path, topic=topic, geometry=geometry, handedness=handedness, start=start, stop=stop)


def _sonar_connections(path: Path) -> tuple[Any, str, list[Any], dict[str, int]]:
    """Opened reader, the kind and connections :func:`iter_bag_pings` would read given a
    geometry, and their ping counts per topic (Oculus RawData topics are scanned; the others
    counted from the bag's index).

    Raises
    ------
    DataFormatError
        Unreadable bag, or no readable sonar topic.
    """
    try:
        reader = _reader(path)
    except DataFormatError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise DataFormatError(f"cannot read bag: {type(exc).__name__}: {exc}", path) from None
    try:
        scanned: dict[str, int] = {}
        kind, conns = _select_connections(reader, path, None, True, scanned)
        counts: dict[str, int] = {}
        if kind == "oculus_raw":
            counts = {c.topic: scanned.get(c.topic, 0) for c in conns}
        else:
            for c in conns:
                counts[c.topic] = counts.get(c.topic, 0) + int(c.msgcount)
    except BaseException:
        reader.close()
        raise
    return reader, kind, conns, counts


def count_pings(path: str | os.PathLike[str]) -> int:
    """Number of sonar messages of the kind :func:`iter_bag_pings` reads (module notes).

    ProjectedSonarImage, RawSonarImage, acoustic_msgs/SonarImage and sensor_msgs/Image are counted
    from the bag's index; Oculus RawData topics by scanning their messages for pings.

    Raises
    ------
    DataFormatError
        Unreadable bag, or no readable sonar topic (the message lists the bag's topics and types).
    """
    reader, _kind, _conns, counts = _sonar_connections(Path(path))
    reader.close()
    return int(sum(counts.values()))


def summary(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Geometry of the first ping, ping count, time span and the sonar topics.

    A bag of ``sensor_msgs/Image`` sonar topics has no geometry of its own (``geometry`` None).
    """
    p = Path(path)
    reader, kind, conns, topics = _sonar_connections(p)
    images = kind == "sensor_image"
    try:
        n = int(sum(topics.values()))
        t0 = int(reader.start_time) if n else None
        t1 = int(reader.end_time) - 1 if n else None  # rosbags reports an exclusive end
    except Exception as exc:  # noqa: BLE001
        raise DataFormatError(f"cannot read bag index: {exc}", p) from None
    finally:
        reader.close()
    ros = "ROS 2" if p.is_dir() or p.suffix in (".db3", ".mcap") or p.name == "metadata.yaml" else "ROS 1"
    first = None
    if n and not images:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", BagConventionWarning)  # reading all pings warns
            first = next(iter_bag_pings(p), None)
    return make_summary(
        FORMAT, p, n_pings=n, geometry=first.geometry if first else None, time_start_ns=t0,
        time_end_ns=t1, ros_version=ros, topics=topics, message_kind=kind,
        time_source="bag record times (header stamps may differ slightly)",
    )
