"""ROS 1 and ROS 2 bags with ``marine_acoustic_msgs/ProjectedSonarImage`` (read and write).

Reading and writing use the ``rosbags`` package (pure Python, no ROS installation).  The message
definitions ship with sonarmap (``sonarmap/io/msgs``) and are registered in rosbags' typestores.

Conventions at the boundary
---------------------------
* ``beam_directions`` are unit vectors with **y to port** (REP-103 body frame: x forward, y left,
  z up), so ``azimuth_ours = atan2(-y, forward)``.  The forward axis is ``x``; bags written with the
  older ``acoustic_msgs`` convention (fan in the y-z plane, ``z`` forward) are recognised by
  ``x == 0`` for every beam and use ``z`` as forward.  Beams are re-ordered, if needed, so that
  azimuth increases with column.
* ``image.data`` is range-major (``data[sample * beam_count + beam]``), which is what drivers
  publish in practice; unsigned integer data map to [0, 1] as ``value / max`` (``uint8``: / 255,
  ``uint16``: / 65535, ``uint32``: / (2**32 - 1), ``uint64``: / (2**64 - 1)); signed integer data
  as ``value / max`` too (``int8``: / 127 ...), and a negative sample is a
  :class:`~sonarmap.errors.DataFormatError`.  Float data are taken as is and must be finite and
  within [0, 1] (a raw ping's range, see :class:`~sonarmap.ping.Ping`) up to
  :data:`FLOAT_TOLERANCE`, by which they are clipped; anything else is a DataFormatError naming
  the bag, the topic and the message index.
* Header stamps must give a time of 0 (unknown) or in the years 1970-2200 (``nanosec`` < 1e9).
* Only regular files are opened: a FIFO or device named ``x.bag`` (or inside a ROS 2 bag
  directory) is refused instead of hanging or reading forever.
* ``ranges`` are float32 in the message.  :func:`write_bag` therefore also writes, once per distinct
  geometry, a ``std_msgs/String`` with the geometry JSON on ``<topic>/sonarmap_geometry``; the
  reader uses it when it agrees with the message (so sonarmap -> bag -> sonarmap is lossless:
  ``dtype="float32"`` images, exact geometry and ns time stamps).
"""

from __future__ import annotations

import functools
import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from sonarmap.errors import DataFormatError, GeometryError, InputError
from sonarmap.geometry import SonarGeometry, as_geometry, geometry_from_dict
from sonarmap.io._binary import U8_SCALE, check_time_ns, make_summary
from sonarmap.io._files import open_regular, require_regular_file
from sonarmap.ping import Ping

__all__ = [
    "FORMAT",
    "MSGTYPE",
    "typestore",
    "write_bag",
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
    return store


# ---------------------------------------------------------------------- writing
def _encode(ping: Ping, store: Any, ros_version: int, frame_id: str, dtype: str, seq: int) -> Any:
    T = store.types
    sec, nsec = divmod(int(ping.time_ns), 10**9)
    stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    if ros_version == 1:
        header = T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame_id)
    else:
        header = T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)
    g = ping.geometry
    info = T["marine_acoustic_msgs/msg/PingInfo"](
        frequency=float(g.frequency_hz),
        sound_speed=float(g.sound_speed_m_s),
        tx_beamwidths=np.zeros(0, np.float32),
        rx_beamwidths=np.zeros(0, np.float32),
    )
    v3 = T["geometry_msgs/msg/Vector3"]
    dirs = [v3(x=float(math.cos(a)), y=float(-math.sin(a)), z=0.0) for a in g.azimuth_rad]
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
        header=header,
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
    """
    if version not in (1, 2):
        raise InputError(f"version: must be 1 or 2 (got {version!r})")
    if dtype not in _DTYPE_CODES:
        raise InputError(f"dtype: choose from {', '.join(_DTYPE_CODES)} (got {dtype!r})")
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    store = typestore(version)
    tmpdir = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    tmp = tmpdir / target.name
    n = 0
    try:
        if version == 1:
            from rosbags.rosbag1 import Writer as W1

            writer: Any = W1(tmp)
            serialize = store.serialize_ros1
        else:
            from rosbags.rosbag2 import Writer as W2

            writer = W2(tmp, version=9)
            serialize = store.serialize_cdr
        string_t = store.types["std_msgs/msg/String"]
        with writer:
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
                    writer.write(gconn, int(ping.time_ns),
                                 bytes(serialize(string_t(data=json.dumps(d)), "std_msgs/msg/String")))
                msg = _encode(ping, store, version, frame_id, dtype, n)
                writer.write(conn, int(ping.time_ns), bytes(serialize(msg, MSGTYPE)))
                n += 1
        if target.exists():
            if target.is_dir():
                shutil.rmtree(target)
            else:
                target.unlink()
        os.replace(tmp, target)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
    return n


# ---------------------------------------------------------------------- reading
def _bag_root(path: Path) -> Path:
    """The path rosbags opens: a ROS 1 file, or a ROS 2 bag directory."""
    if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").exists():
        return path.parent
    if path.is_file() and path.name == "metadata.yaml":
        return path.parent
    return path


def _is_uniform(r: np.ndarray) -> bool:
    d = np.diff(r)
    return r.size > 1 and bool(np.allclose(d, d.mean(), rtol=1e-5, atol=0))


@functools.lru_cache(maxsize=64)
def _message_geometry(
    dirs: bytes, ranges: bytes, frequency: float, sound_speed: float, name: str
) -> tuple[SonarGeometry, np.ndarray | None]:
    v = np.frombuffer(dirs, dtype=np.float64).reshape(-1, 3)
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    forward = z if (np.all(np.abs(x) < 1e-9) and np.any(np.abs(z) > 0)) else x
    az = np.arctan2(-y, forward)
    order = None
    if az.size > 1 and np.any(np.diff(az) <= 0):
        order = np.argsort(az, kind="stable")
        az = az[order]
    r = np.frombuffer(ranges, dtype=np.float32).astype(np.float64)
    c = sound_speed if 1300.0 <= sound_speed <= 1700.0 else 1500.0
    kw: dict[str, Any] = {
        "frequency_hz": frequency if math.isfinite(frequency) and frequency > 0 else 1.8e6,
        "sound_speed_m_s": c,
        "name": name,
    }
    geom = SonarGeometry(azimuth_rad=az, range_m=r, **kw)
    return geom, order


def _decode_image(img: Any, n_ranges: int, n_beams: int) -> np.ndarray:
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
    a = raw.view(dt).reshape(n_ranges, n_beams)
    if dt.kind == "f":
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{dt.name} image contains NaN or infinite values")
        lo, hi = float(a.min()), float(a.max())
        if lo < -FLOAT_TOLERANCE or hi > 1.0 + FLOAT_TOLERANCE:
            raise ValueError(
                f"{dt.name} pixels lie in [{lo:.6g}, {hi:.6g}], outside the [0, 1] of a raw ping"
            )
        return np.clip(a, 0.0, 1.0).astype(np.float32)
    if dt == np.dtype("u1"):
        return np.multiply(a, U8_SCALE, dtype=np.float32)
    info = np.iinfo(dt)
    if dt.kind == "i" and a.size and int(a.min()) < 0:
        raise ValueError(
            f"{dt.name} image has negative samples (min {int(a.min())}); intensities are >= 0"
        )
    return np.clip(a.astype(np.float64) / float(info.max), 0.0, 1.0).astype(np.float32)


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


def iter_bag_pings(
    path: str | os.PathLike[str],
    *,
    topic: str | None = None,
    geometry: SonarGeometry | str | os.PathLike[str] | None = None,
) -> Iterator[Ping]:
    """Lazily yield the ProjectedSonarImage pings of a ROS 1 or ROS 2 bag, in time order.

    Parameters
    ----------
    topic : str, optional
        Only this topic (default: every ProjectedSonarImage topic).

    Raises
    ------
    DataFormatError
        If the bag cannot be parsed or a message is inconsistent (sizes, directions, ranges).
    """
    p = Path(path)
    override = None if geometry is None else as_geometry(geometry)
    try:
        reader = _reader(p)
    except DataFormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags raises various types on corrupt bags
        raise DataFormatError(f"cannot read bag: {type(exc).__name__}: {exc}", p) from None
    try:
        conns = [c for c in reader.connections if c.msgtype in _SONAR_TYPES and (topic is None or c.topic == topic)]
        if topic is not None and not conns:
            raise DataFormatError(f"no ProjectedSonarImage messages on topic {topic!r}", p)
        gtopics = {c.topic + _GEOMETRY_SUFFIX for c in conns} | {c.topic.rstrip("/") + _GEOMETRY_SUFFIX for c in conns}
        gconns = [c for c in reader.connections if c.topic in gtopics and c.msgtype == "std_msgs/msg/String"]
        exact: dict[bytes, SonarGeometry] = {}
        for conn, _t, raw in _guarded(p, reader.messages(connections=gconns)) if gconns else ():
            try:
                d = json.loads(reader.deserialize(raw, conn.msgtype).data)
                src = d.pop("azimuth_source", "table")
                g = geometry_from_dict(d, source=f"{p} geometry")
                if g.azimuth_source != src:
                    g = g.replace(azimuth_source=src)
                exact[g.range_m.astype(np.float32).tobytes() + np.float32(g.azimuth_rad).tobytes()] = g
            except Exception:  # noqa: BLE001,S112 - damaged side channel: use the message fields
                continue
        idx = 0
        for conn, _t, raw in _guarded(p, reader.messages(connections=conns)) if conns else ():
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:  # noqa: BLE001
                raise DataFormatError(f"corrupt message {idx}: {type(exc).__name__}: {exc}", p) from None
            try:
                ping = _ping_from_msg(msg, p, conn.topic, idx, override, exact)
            except (ValueError, GeometryError) as exc:
                raise DataFormatError(f"message {idx} on {conn.topic}: {exc}", p) from None
            idx += 1
            yield ping
    finally:
        try:
            reader.close()
        except Exception:  # noqa: BLE001,S110 - closing a corrupt bag must not mask the real error
            pass


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
    exact: dict[bytes, SonarGeometry],
) -> Ping:
    dirs = np.array([[d.x, d.y, d.z] for d in msg.beam_directions], dtype=np.float64).reshape(-1, 3)
    ranges = np.asarray(msg.ranges, dtype=np.float32)
    if dirs.shape[0] < 1 or ranges.size < 1:
        raise ValueError(f"empty geometry ({dirs.shape[0]} beams, {ranges.size} ranges)")
    if not (np.all(np.isfinite(dirs)) and np.all(np.isfinite(ranges))):
        raise ValueError("beam directions or ranges contain NaN/inf")
    name = (msg.header.frame_id or topic).strip("/").replace("/", "-") or "sonar"
    geom, order = _message_geometry(
        dirs.tobytes(), ranges.tobytes(), float(msg.ping_info.frequency),
        float(msg.ping_info.sound_speed), name,
    )
    image = _decode_image(msg.image, ranges.size, dirs.shape[0])
    if order is not None:
        image = np.ascontiguousarray(image[:, order])
    g = exact.get(ranges.tobytes() + np.float32(geom.azimuth_rad).tobytes()) if override is None else None
    if override is not None:
        geom = override
    elif g is not None and np.allclose(g.azimuth_rad, geom.azimuth_rad, atol=1e-9):
        geom = g
    sec, nsec = int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)
    if not 0 <= nsec < 10**9:
        raise ValueError(f"header stamp nanosec {nsec} is outside 0-999999999")
    t_ns = check_time_ns(sec * 10**9 + nsec, "header stamp")
    meta: dict[str, Any] = {"format": FORMAT, "topic": topic, "message_index": idx}
    if hasattr(msg.header, "seq"):
        meta["seq"] = int(msg.header.seq)
    return Ping(image=image, geometry=geom, time_ns=t_ns, source=f"{path}#{topic}:{idx}", meta=meta)


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
    **_: Any,
) -> Iterator[Ping]:
    """Registry hook: :func:`iter_bag_pings`."""
    yield from iter_bag_pings(path, topic=topic, geometry=geometry)


def _sonar_connections(path: Path) -> tuple[Any, list[Any]]:
    try:
        reader = _reader(path)
    except DataFormatError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise DataFormatError(f"cannot read bag: {type(exc).__name__}: {exc}", path) from None
    return reader, [c for c in reader.connections if c.msgtype in _SONAR_TYPES]


def count_pings(path: str | os.PathLike[str]) -> int:
    """Number of ProjectedSonarImage messages (from the bag's index)."""
    reader, conns = _sonar_connections(Path(path))
    try:
        return int(sum(c.msgcount for c in conns))
    finally:
        reader.close()


def summary(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Geometry of the first ping, ping count, time span and the sonar topics."""
    p = Path(path)
    reader, conns = _sonar_connections(p)
    try:
        n = int(sum(c.msgcount for c in conns))
        topics = {c.topic: int(c.msgcount) for c in conns}
        t0 = int(reader.start_time) if n else None
        t1 = int(reader.end_time) - 1 if n else None  # rosbags reports an exclusive end
    except Exception as exc:  # noqa: BLE001
        raise DataFormatError(f"cannot read bag index: {exc}", p) from None
    finally:
        reader.close()
    ros = "ROS 2" if p.is_dir() or p.suffix in (".db3", ".mcap") or p.name == "metadata.yaml" else "ROS 1"
    first = next(iter_bag_pings(p), None) if n else None
    return make_summary(
        FORMAT, p, n_pings=n, geometry=first.geometry if first else None, time_start_ns=t0,
        time_end_ns=t1, ros_version=ros, topics=topics,
        time_source="bag record times (header stamps may differ slightly)",
    )
