"""ROS 1/2 bags of marine_acoustic_msgs/ProjectedSonarImage: write -> read round trips, conventions."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sonarmap.errors import DataFormatError, SonarmapWarning
from sonarmap.io import detect_format, read_pings, rosbag
from sonarmap.io.rosbag import MSGTYPE, typestore, write_bag
from sonarmap.ping import Ping


@pytest.fixture(scope="module")
def aris_pings(data_dir: Path) -> list[Ping]:
    return list(read_pings(data_dir / "aris" / "sample.aris"))[:3]


@pytest.mark.parametrize("version", [1, 2])
def test_round_trip_is_lossless(aris_pings: list[Ping], tmp_path: Path, version: int) -> None:
    path = tmp_path / ("s.bag" if version == 1 else "s_bag")
    assert write_bag(aris_pings, path, version=version) == 3
    assert detect_format(path) == "rosbag"
    assert rosbag.count_pings(path) == 3
    back = list(read_pings(path))
    assert len(back) == 3
    for a, b in zip(aris_pings, back, strict=True):
        assert np.array_equal(a.image, b.image)
        assert a.geometry == b.geometry and a.geometry.azimuth_source == b.geometry.azimuth_source
        assert a.time_ns == b.time_ns
    s = rosbag.summary(path)
    assert s["pings"] == 3 and s["ros_version"] == ("ROS 1" if version == 1 else "ROS 2")
    assert s["time_first_utc"].startswith("2013-06-14T08:21:19.122519")


def test_uint8_and_message_geometry(data_dir: Path, tmp_path: Path) -> None:
    """Without the geometry side channel the reader rebuilds geometry from the message fields."""
    pings = list(read_pings(data_dir / "oculus" / "three_pings_8bit.raw"))
    path = tmp_path / "o.bag"
    write_bag(pings, path, version=1, dtype="uint8", topic="/oculus/sonar_image")
    back = list(rosbag.iter_bag_pings(path, topic="/oculus/sonar_image"))
    assert np.array_equal(back[0].image, pings[0].image)  # 8-bit counts survive exactly
    ga, gb = pings[0].geometry, back[0].geometry
    assert np.allclose(ga.azimuth_rad, gb.azimuth_rad, atol=1e-12)
    with pytest.raises(DataFormatError, match="no ProjectedSonarImage messages on topic"):
        list(rosbag.iter_bag_pings(path, topic="/nope"))


def _foreign_bag(path: Path, ping: Ping, *, old_convention: bool, reverse: bool) -> None:
    """A bag as a ROS driver would write it: no side channel, optional z-forward / reversed beams."""
    from rosbags.rosbag1 import Writer

    store = typestore(1)
    msg = rosbag._encode(ping, store, 1, "oculus", "uint8", 0)
    v3 = store.types["geometry_msgs/msg/Vector3"]
    az = ping.geometry.azimuth_rad
    cols = np.arange(az.size)
    if reverse:
        cols = cols[::-1]
    dirs = []
    for a in az[cols]:
        if old_convention:  # fan in the y-z plane, z forward, y to port (old acoustic_msgs)
            dirs.append(v3(x=0.0, y=-math.sin(a), z=math.cos(a)))
        else:
            dirs.append(v3(x=math.cos(a), y=-math.sin(a), z=0.0))
    data = np.rint(ping.image[:, cols] * 255).astype(np.uint8)
    msg.beam_directions = dirs
    msg.image.data = np.frombuffer(data.tobytes(), np.uint8)
    with Writer(path) as w:
        c = w.add_connection("/sonar", MSGTYPE, typestore=store)
        w.write(c, ping.time_ns, bytes(store.serialize_ros1(msg, MSGTYPE)))


@pytest.mark.parametrize("old_convention", [False, True])
@pytest.mark.parametrize("reverse", [False, True])
def test_beam_direction_conventions(data_dir: Path, tmp_path: Path, old_convention: bool, reverse: bool) -> None:
    ping = next(read_pings(data_dir / "oculus" / "one_ping_8bit.raw"))
    path = tmp_path / "f.bag"
    _foreign_bag(path, ping, old_convention=old_convention, reverse=reverse)
    back = next(read_pings(path))
    # y to port: a beam with y < 0 is to starboard, i.e. positive azimuth in our convention
    assert np.allclose(back.geometry.azimuth_rad, ping.geometry.azimuth_rad, atol=1e-12)
    assert np.array_equal(back.image, ping.image)
    assert back.geometry.name == "oculus"


def test_corrupt_bags(aris_pings: list[Ping], tmp_path: Path) -> None:
    path = tmp_path / "c.bag"
    write_bag(aris_pings[:2], path, version=1)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataFormatError, match=r"c\.bag"):
        list(read_pings(path))
    path.write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 100)
    with pytest.raises(DataFormatError):
        list(read_pings(path))


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory: pytest.TempPathFactory, data_dir: Path) -> bytes:
    ping = next(read_pings(data_dir / "oculus" / "one_ping_8bit.raw"))
    small = Ping(image=ping.image[:20], geometry=ping.geometry.replace(range_m=ping.geometry.range_m[:20]), time_ns=5)
    p = tmp_path_factory.mktemp("bag") / "s.bag"
    write_bag([small, small], p, version=1, dtype="uint8")
    return p.read_bytes()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, 2**31), st.integers(0, 255)), min_size=1, max_size=6),
       cut=st.one_of(st.none(), st.integers(0, 2**31)))
@pytest.mark.slow
def test_fuzz_byte_flips(small_bag: bytes, tmp_path: Path, flips: list[tuple[int, int]], cut: int | None) -> None:
    data = bytearray(small_bag)
    for pos, val in flips:
        data[pos % len(data)] = val
    if cut is not None:
        data = data[: cut % (len(data) + 1)]
    p = tmp_path / "fuzz.bag"
    p.write_bytes(bytes(data))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SonarmapWarning)
        try:
            for ping in read_pings(p):
                assert ping.image.dtype == np.float32
        except DataFormatError as exc:
            assert str(p) in str(exc)


def test_corrupt_ros2_bag(aris_pings: list[Ping], tmp_path: Path) -> None:
    path = tmp_path / "r2"
    write_bag(aris_pings[:1], path, version=2)
    db = next(path.glob("*.db3"))
    data = db.read_bytes()
    db.write_bytes(data[:200] + b"\x13" * (len(data) - 200))
    with pytest.raises(DataFormatError, match="r2"):
        list(read_pings(path))
    (path / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed")
    with pytest.raises(DataFormatError, match="r2"):
        rosbag.count_pings(path)
