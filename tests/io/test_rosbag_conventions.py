"""ROS bag conventions: upstream beam_directions, handedness, unreadable topics, sensor_msgs/Image, times.

Every bag here is written by ``rosbags`` itself (its Writer and typestore serialisation).
"""

from __future__ import annotations

import contextlib
import json
import math
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bag_writer import bag_path as _bag_path
from bag_writer import write_bag_items as _write

from sonarmap.errors import DataFormatError, InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.io import read_pings, rosbag
from sonarmap.io._binary import U8_SCALE
from sonarmap.io.rosbag import IMAGE_TYPE, MSGTYPE, BagConventionWarning, typestore, write_bag
from sonarmap.ping import Ping

T0 = 1_700_000_000_123_456_789  # not representable as a float64 number of ns


def _geometry(n_beams: int = 16, n_bins: int = 24) -> SonarGeometry:
    """An asymmetric, non-uniform fan (mirroring changes the azimuth table, not only the image)."""
    deg = np.linspace(-20.0, 40.0, n_beams) + 0.3 * np.sin(np.arange(n_beams))
    return SonarGeometry(azimuth_rad=np.deg2rad(deg), range_m=1.0 + 0.05 * np.arange(n_bins), name="fls")


def _pings(n: int = 2, geometry: SonarGeometry | None = None) -> list[Ping]:
    g = geometry or _geometry()
    rng = np.random.default_rng(7)
    return [
        Ping(image=np.multiply(rng.integers(0, 256, g.shape).astype(np.uint8), U8_SCALE, dtype=np.float32),
             geometry=g, time_ns=T0 + i)
        for i in range(n)
    ]


def _sonar_msg(ping: Ping, version: int, dirs: np.ndarray, cols: np.ndarray | None = None) -> Any:
    """A ProjectedSonarImage of ``ping`` (uint8) with the given (n_beams, 3) directions / column order."""
    store = typestore(version)
    msg = rosbag._encode(ping, store, version, "fls", "uint8", 0)
    v3 = store.types["geometry_msgs/msg/Vector3"]
    msg.beam_directions = [v3(x=float(x), y=float(y), z=float(z)) for x, y, z in dirs]
    cols = np.arange(ping.geometry.n_beams) if cols is None else cols
    data = np.rint(ping.image[:, cols] * 255).astype(np.uint8)
    msg.image.data = np.frombuffer(data.tobytes(), np.uint8)
    return msg


def _side_channel(ping: Ping, version: int) -> tuple[str, str, Any, int]:
    store = typestore(version)
    d = ping.geometry.to_dict()
    d["azimuth_source"] = ping.geometry.azimuth_source
    msg = store.types["std_msgs/msg/String"](data=json.dumps(d))
    return "/sonar/sonarmap_geometry", "std_msgs/msg/String", msg, ping.time_ns


def _raw_messages(path: Path) -> Iterator[Any]:
    from rosbags.highlevel import AnyReader

    with AnyReader([path], default_typestore=typestore(2)) as reader:
        conns = [c for c in reader.connections if c.msgtype == MSGTYPE]
        for conn, _t, raw in reader.messages(connections=conns):
            yield reader.deserialize(raw, conn.msgtype)


@contextlib.contextmanager
def _no_convention_warning() -> Iterator[None]:
    """Fail on any BagConventionWarning inside the block."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", BagConventionWarning)
        yield


# ---------------------------------------------------------------------- writing per the .msg
@pytest.mark.parametrize("version", [1, 2])
def test_written_directions_follow_upstream_msg(tmp_path: Path, version: int) -> None:
    """z forward, x up (0 for a flat fan), and sonar_image_proc's rules give back our azimuths."""
    pings = _pings(1)
    path = _bag_path(tmp_path, version)
    write_bag(pings, path, version=version, dtype="uint8")
    (msg,) = list(_raw_messages(path))
    xyz = np.array([[d.x, d.y, d.z] for d in msg.beam_directions])
    az = pings[0].geometry.azimuth_rad
    assert np.all(xyz[:, 0] == 0.0)  # no elevation: x (up) is 0
    assert np.all(xyz[:, 2] > 0.5)  # forward is z
    assert np.allclose(np.linalg.norm(xyz, axis=1), 1.0, atol=1e-12)
    # sonar_image_proc C++ (SonarImageMsgInterface): azimuth = atan2(-y, z)
    assert np.allclose(np.arctan2(-xyz[:, 1], xyz[:, 2]), az, atol=1e-12)
    # sonar_image_proc Python (SonarImageMetadata): azimuth = atan2(-y, sqrt(x^2 + z^2))
    assert np.allclose(np.arctan2(-xyz[:, 1], np.hypot(xyz[:, 0], xyz[:, 2])), az, atol=1e-12)
    # its drawer maps column 0 to the smallest azimuth: azimuths must increase with beam index
    assert np.all(np.diff(np.arctan2(-xyz[:, 1], xyz[:, 2])) > 0)
    # its index() reads data[range * n_beams + beam]
    n_beams = len(msg.beam_directions)
    data = np.asarray(msg.image.data)
    expect = np.rint(pings[0].image * 255).astype(np.uint8)
    assert int(msg.image.beam_count) == n_beams
    assert data[5 * n_beams + 3] == expect[5, 3] and data[7 * n_beams + 11] == expect[7, 11]


@pytest.mark.parametrize("version", [1, 2])
def test_upstream_bag_without_side_channel_reads_exactly(tmp_path: Path, version: int) -> None:
    """A producer following the .msg (no sonarmap side channel): right azimuths, no warning."""
    ping = _pings(1)[0]
    a = ping.geometry.azimuth_rad
    dirs = np.stack([np.zeros_like(a), -np.sin(a), np.cos(a)], axis=1)
    path = _bag_path(tmp_path, version)
    _write(path, version, [("/sonar", MSGTYPE, _sonar_msg(ping, version, dirs), ping.time_ns)])
    with _no_convention_warning():
        (back,) = list(read_pings(path))
    assert np.allclose(back.geometry.azimuth_rad, a, atol=1e-12)
    assert np.array_equal(back.image, ping.image)
    assert back.meta["handedness"] == "upstream" and back.meta["fan_plane"] == "yz"


# ---------------------------------------------------------------------- old sonarmap bags
@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("side_channel", [True, False])
def test_old_sonarmap_bags_still_read(tmp_path: Path, version: int, side_channel: bool) -> None:
    """The previous writer: fan in the x-y plane (x forward, y = -sin a, z = 0), with its side channel."""
    pings = _pings(2)
    a = pings[0].geometry.azimuth_rad
    dirs = np.stack([np.cos(a), -np.sin(a), np.zeros_like(a)], axis=1)
    items = [_side_channel(pings[0], version)] if side_channel else []
    items += [("/sonar", MSGTYPE, _sonar_msg(p, version, dirs), p.time_ns) for p in pings]
    path = _bag_path(tmp_path, version)
    _write(path, version, items)
    with _no_convention_warning():
        back = list(read_pings(path))
    assert len(back) == 2
    for p, b in zip(pings, back, strict=True):
        assert np.array_equal(b.image, p.image)
        assert np.allclose(b.geometry.azimuth_rad, a, atol=1e-12)
        assert b.meta["fan_plane"] == "xy" and b.meta["handedness"] == "upstream"
        if side_channel:
            assert b.geometry == p.geometry  # exact float64 geometry from the side channel


# ---------------------------------------------------------------------- handedness
def _mirrored_bag(tmp_path: Path, version: int, *, side_channel: bool = False) -> tuple[Path, Ping]:
    """A producer with +y to starboard, beams port to starboard: y = +sin a, z = cos a."""
    ping = _pings(1)[0]
    a = ping.geometry.azimuth_rad
    dirs = np.stack([np.zeros_like(a), np.sin(a), np.cos(a)], axis=1)
    items = [_side_channel(ping, version)] if side_channel else []
    items.append(("/sonar", MSGTYPE, _sonar_msg(ping, version, dirs), ping.time_ns))
    path = _bag_path(tmp_path, version, "m")
    _write(path, version, items)
    return path, ping


@pytest.mark.parametrize("version", [1, 2])
def test_mirrored_producer_is_never_read_silently(tmp_path: Path, version: int) -> None:
    path, ping = _mirrored_bag(tmp_path, version)
    with pytest.warns(BagConventionWarning, match=r"/sonar: beam_directions do not increase .* handedness='mirrored'"):
        (guess,) = list(read_pings(path))
    # the guess follows the .msg rule: the azimuth table comes out negated and the columns reversed
    assert np.allclose(guess.geometry.azimuth_rad, -ping.geometry.azimuth_rad[::-1], atol=1e-12)
    assert np.array_equal(guess.image, ping.image[:, ::-1])
    assert guess.meta["handedness"] == "upstream"
    with _no_convention_warning():
        (right,) = list(read_pings(path, handedness="mirrored"))
        (forced,) = list(rosbag.iter_bag_pings(path, handedness="upstream"))
    assert np.allclose(right.geometry.azimuth_rad, ping.geometry.azimuth_rad, atol=1e-12)
    assert np.array_equal(right.image, ping.image)
    assert right.meta["handedness"] == "mirrored"
    assert np.array_equal(forced.image, guess.image)


def test_warning_once_per_topic(tmp_path: Path) -> None:
    pings = _pings(3)
    a = pings[0].geometry.azimuth_rad
    dirs = np.stack([np.zeros_like(a), np.sin(a), np.cos(a)], axis=1)
    path = tmp_path / "w.bag"
    _write(path, 1, [("/sonar", MSGTYPE, _sonar_msg(p, 1, dirs), p.time_ns) for p in pings])
    with pytest.warns(BagConventionWarning) as record:
        assert len(list(read_pings(path))) == 3
    assert len([w for w in record if issubclass(w.category, BagConventionWarning)]) == 1


def test_side_channel_decides_handedness(tmp_path: Path) -> None:
    """A side-channel geometry that matches the mirrored reading only decides it, without a warning."""
    path, ping = _mirrored_bag(tmp_path, 1, side_channel=True)
    with _no_convention_warning():
        (back,) = list(read_pings(path))
    assert back.geometry == ping.geometry and np.array_equal(back.image, ping.image)
    assert back.meta["handedness"] == "mirrored"


def test_handedness_option_is_validated(tmp_path: Path) -> None:
    path = tmp_path / "v.bag"
    write_bag(_pings(1), path, version=1)
    with pytest.raises(InputError, match="handedness: choose from auto, upstream, mirrored"):
        list(read_pings(path, handedness="left"))


def test_forced_mirrored_reads_own_bags_mirrored(tmp_path: Path) -> None:
    """The explicit option is obeyed (the side channel then no longer matches and is not used)."""
    pings = _pings(1)
    path = tmp_path / "o.bag"
    write_bag(pings, path, version=1)
    (back,) = list(read_pings(path, handedness="mirrored"))
    assert np.allclose(back.geometry.azimuth_rad, -pings[0].geometry.azimuth_rad[::-1], atol=1e-6)
    assert np.array_equal(back.image, pings[0].image[:, ::-1])


# ---------------------------------------------------------------------- unreadable bags
def _foreign_store(version: int) -> Any:
    """A fresh typestore with stand-ins for message types sonarmap does not decode."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if version == 1 else Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    types.update(get_types_from_msg("std_msgs/Header header\nuint8[] data", "apl_msgs/msg/RawData"))
    types.update(get_types_from_msg(
        "std_msgs/Header header\nfloat32 sample_rate\nuint32 samples_per_beam\nfloat32[] rx_angles\nuint8[] data",
        "marine_acoustic_msgs/msg/RawSonarImage",
    ))
    store.register(types)
    return store


def _header(store: Any, version: int, t: int) -> Any:
    T = store.types
    stamp = T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)
    if version == 1:
        return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="s")
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id="s")


def _sensor_image(store: Any, version: int, img: np.ndarray, encoding: str, *, pad: int = 0,
                  bigendian: bool = False, t: int = T0) -> Any:
    h, w = img.shape
    a = img.astype(img.dtype.newbyteorder(">" if bigendian else "<"))
    rows = np.frombuffer(a.tobytes(), np.uint8).reshape(h, w * a.itemsize)
    data = np.concatenate([rows, np.full((h, pad), 0xAB, np.uint8)], axis=1)
    return store.types[IMAGE_TYPE](
        header=_header(store, version, t), height=h, width=w, encoding=encoding,
        is_bigendian=int(bigendian), step=w * a.itemsize + pad, data=data.reshape(-1),
    )


@pytest.mark.parametrize("version", [1, 2])
def test_bag_without_sonar_topic_is_an_error(tmp_path: Path, version: int) -> None:
    store = _foreign_store(version)
    T = store.types
    raw = T["apl_msgs/msg/RawData"](header=_header(store, version, T0), data=np.arange(8, dtype=np.uint8))
    rsi = T["marine_acoustic_msgs/msg/RawSonarImage"](
        header=_header(store, version, T0), sample_rate=1e5, samples_per_beam=2,
        rx_angles=np.zeros(2, np.float32), data=np.zeros(4, np.uint8),
    )
    path = _bag_path(tmp_path, version)
    _write(path, version, [("/oculus/raw_data", "apl_msgs/msg/RawData", raw, T0),
                           ("/sonar/raw", "marine_acoustic_msgs/msg/RawSonarImage", rsi, T0)], store)
    listing = (r"no readable sonar topic .*the bag has /oculus/raw_data \(apl_msgs/msg/RawData\), "
               r"/sonar/raw \(marine_acoustic_msgs/msg/RawSonarImage\)$")
    for call in (lambda: list(read_pings(path)), lambda: rosbag.count_pings(path), lambda: rosbag.summary(path)):
        with pytest.raises(DataFormatError, match=listing) as info:
            call()
        assert str(path) in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(DataFormatError, match=r"no ProjectedSonarImage messages on topic '/sonar/raw'; the bag has"):
        list(read_pings(path, topic="/sonar/raw"))


@pytest.mark.parametrize("version", [1, 2])
def test_sensor_image_needs_a_geometry(tmp_path: Path, version: int) -> None:
    g = _geometry()
    store = typestore(version)
    img = np.zeros(g.shape, np.uint8)
    path = _bag_path(tmp_path, version)
    _write(path, version, [("/sonar/image_raw", IMAGE_TYPE, _sensor_image(store, version, img, "mono8"), T0)])
    need = r"/sonar/image_raw \(sensor_msgs/msg/Image\); its sensor_msgs/Image topics need a geometry"
    with pytest.raises(DataFormatError, match=need):
        list(read_pings(path))
    with pytest.raises(DataFormatError, match=r"topic '/sonar/image_raw' is a sensor_msgs/Image: pass a geometry"):
        list(read_pings(path, topic="/sonar/image_raw"))
    assert rosbag.count_pings(path) == 1
    assert rosbag.summary(path)["pings"] == 1


# ---------------------------------------------------------------------- sensor_msgs/Image
@pytest.mark.parametrize("version", [1, 2])
def test_sensor_image_with_geometry(tmp_path: Path, version: int) -> None:
    g = _geometry()
    store = typestore(version)
    rng = np.random.default_rng(3)
    u8 = rng.integers(0, 256, g.shape).astype(np.uint8)
    u16 = rng.integers(0, 65536, g.shape).astype(np.uint16)
    f32 = rng.random(g.shape).astype(np.float32)
    items = [
        ("/a", IMAGE_TYPE, _sensor_image(store, version, u8, "mono8", pad=3), T0),
        ("/a", IMAGE_TYPE, _sensor_image(store, version, u16, "mono16", bigendian=True, t=T0 + 1), T0 + 1),
        ("/a", IMAGE_TYPE, _sensor_image(store, version, f32, "32FC1", pad=4, t=T0 + 2), T0 + 2),
    ]
    path = _bag_path(tmp_path, version)
    _write(path, version, items)
    back = list(read_pings(path, geometry=g))
    assert [p.time_ns for p in back] == [T0, T0 + 1, T0 + 2]
    assert all(type(p.time_ns) is int for p in back)
    assert all(p.geometry == g and p.image.dtype == np.float32 for p in back)
    assert np.array_equal(back[0].image, np.multiply(u8, U8_SCALE, dtype=np.float32))
    assert np.allclose(back[1].image, u16 / 65535.0, atol=1e-7)
    assert np.array_equal(back[2].image, f32)
    wrong = g.replace(range_m=g.range_m[:-1])
    shape = r"message 0 on /a: image is 24 x 16 \(height x width\), the geometry needs 23"
    with pytest.raises(DataFormatError, match=shape):
        list(read_pings(path, geometry=wrong))


def test_sensor_image_topic_beside_projected(tmp_path: Path) -> None:
    """With both kinds, ProjectedSonarImage is read by default; topic= picks the Image one."""
    g = _geometry()
    store = typestore(1)
    ping = _pings(1, g)[0]
    img = np.full(g.shape, 51, np.uint8)
    items = [("/sonar", MSGTYPE, rosbag._encode(ping, store, 1, "fls", "float32", 0), T0),
             ("/sonar/rendered", IMAGE_TYPE, _sensor_image(store, 1, img, "8UC1", t=T0 + 5), T0 + 5)]
    path = tmp_path / "both.bag"
    _write(path, 1, items)
    (a,) = list(read_pings(path, geometry=g))
    assert a.meta["topic"] == "/sonar" and np.array_equal(a.image, ping.image)
    (b,) = list(read_pings(path, geometry=g, topic="/sonar/rendered"))
    assert b.meta["topic"] == "/sonar/rendered" and np.all(b.image == np.multiply(51, U8_SCALE, dtype=np.float32))
    assert b.time_ns == T0 + 5


def test_sensor_image_bad_encoding(tmp_path: Path) -> None:
    g = _geometry()
    store = typestore(1)
    msg = _sensor_image(store, 1, np.zeros(g.shape, np.uint8), "mono8")
    msg.encoding = "rgb8"
    path = tmp_path / "e.bag"
    _write(path, 1, [("/a", IMAGE_TYPE, msg, T0)])
    with pytest.raises(DataFormatError, match=r"message 0 on /a: image encoding 'rgb8' is not a single-channel one"):
        list(read_pings(path, geometry=g))


# ---------------------------------------------------------------------- integer times
@pytest.mark.parametrize("version", [1, 2])
def test_stamps_stay_integer_ns(tmp_path: Path, version: int) -> None:
    """sec/nanosec -> time_ns exactly (a float64 on the way would round T0 to a multiple of 256 ns)."""
    assert float(T0) != T0
    ping = _pings(1)[0]
    a = ping.geometry.azimuth_rad
    dirs = np.stack([np.zeros_like(a), -np.sin(a), np.cos(a)], axis=1)
    msg = _sonar_msg(ping, version, dirs)
    assert (int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)) == divmod(T0, 10**9)
    path = _bag_path(tmp_path, version)
    _write(path, version, [("/sonar", MSGTYPE, msg, T0)])
    (back,) = list(read_pings(path))
    assert type(back.time_ns) is int and back.time_ns == T0
    assert math.isclose(back.time_ns / 1e9, T0 / 1e9)


@pytest.mark.parametrize("version", [1, 2])
def test_empty_bags(tmp_path: Path, version: int) -> None:
    """A sonarmap bag of zero pings has its (empty) sonar topic: 0 pings; a bag of no topics is an error."""
    path = _bag_path(tmp_path, version)
    assert write_bag([], path, version=version) == 0
    assert list(read_pings(path)) == [] and rosbag.count_pings(path) == 0
    empty = _bag_path(tmp_path, version, "none")
    _write(empty, version, [])
    with pytest.raises(DataFormatError, match=r"no readable sonar topic .*; the bag has no topics$"):
        list(read_pings(empty))
