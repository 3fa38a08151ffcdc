"""ROS bag message types beyond ProjectedSonarImage: RawSonarImage, acoustic_msgs/SonarImage and
Oculus apl_msgs/RawData (read); SonarRanges and PointCloud2 (written, also by the CLI).

Bags are written and read back with ``rosbags`` and a typestore holding the upstream definitions
(fields and constants as in apl-ocean-engineering/marine_msgs, hydrographic_msgs / acoustic_msgs
and apl_msgs), registered here independently of sonarmap's own copies.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bag_writer import bag_path as _bag
from bag_writer import write_bag_items as _write

from sonarmap.cli import main
from sonarmap.errors import DataFormatError
from sonarmap.geometry import SonarGeometry, preset
from sonarmap.io import read_pings, rosbag
from sonarmap.io.oculus import HEADER
from sonarmap.io.rosbag import beamwidths, write_bag
from sonarmap.io.rosbag_products import write_points_bag, write_ranges_bag
from sonarmap.mapping.register import PointCloud
from sonarmap.ping import Ping
from sonarmap.ranges import BeamRanges

T0 = 1_700_000_000_123_456_789  # not representable as a float64 number of ns

# upstream field lists (the .msg files' fields and constants)
_UPSTREAM = {
    "marine_acoustic_msgs/msg/PingInfo": "float32 frequency\nfloat32 sound_speed\nfloat32[] tx_beamwidths\n"
    "float32[] rx_beamwidths\n",
    "marine_acoustic_msgs/msg/SonarImageData": "bool is_bigendian\nuint32 DTYPE_UINT8 = 0\nuint32 DTYPE_INT8 = 1\n"
    "uint32 DTYPE_UINT16 = 2\nuint32 DTYPE_INT16 = 3\nuint32 DTYPE_UINT32 = 4\nuint32 DTYPE_INT32 = 5\n"
    "uint32 DTYPE_UINT64 = 6\nuint32 DTYPE_INT64 = 7\nuint32 DTYPE_FLOAT32 = 8\nuint32 DTYPE_FLOAT64 = 9\n"
    "uint32 dtype\nuint32 beam_count\nuint8[] data\n",
    "marine_acoustic_msgs/msg/ProjectedSonarImage": "std_msgs/Header header\nPingInfo ping_info\n"
    "geometry_msgs/Vector3[] beam_directions\nfloat32[] ranges\nSonarImageData image\n",
    "marine_acoustic_msgs/msg/RawSonarImage": "std_msgs/Header header\nPingInfo ping_info\nfloat32 sample_rate\n"
    "uint32 samples_per_beam\nuint32 sample0\nfloat32[] tx_delays\nfloat32[] tx_angles\nfloat32[] rx_angles\n"
    "SonarImageData image\n",
    "marine_acoustic_msgs/msg/DetectionFlag": "uint8 DETECT_OK = 0\nuint8 DETECT_BAD_SONAR = 1\n"
    "uint8 DETECT_BAD_FILTER = 2\nuint8 DETECT_BAD_USER = 4\nuint8 flag\n",
    "marine_acoustic_msgs/msg/SonarRanges": "std_msgs/Header header\nPingInfo ping_info\nDetectionFlag[] flags\n"
    "float32[] transmit_delays\nfloat32[] intensities\ngeometry_msgs/Vector3[] beam_unit_vec\nfloat32[] ranges\n",
    "acoustic_msgs/msg/SonarImage": "Header header\nfloat32 frequency\nfloat32 sound_speed\n"
    "float32 azimuth_beamwidth\nfloat32 elevation_beamwidth\nfloat32[] azimuth_angles\n"
    "float32[] elevation_angles\nfloat32[] ranges\nbool is_bigendian\nuint8 data_size\nuint8[] intensities\n",
    "apl_msgs/msg/RawData": "std_msgs/Header header\nuint8 DATA_OUT = 0\nuint8 DATA_IN = 1\nuint8 direction\n"
    "uint8[] data\n",
}


def _store(version: int) -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if version == 1 else Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in _UPSTREAM.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def _read(path: Path, version: int) -> list[tuple[str, int, Any]]:
    """``(topic, record time, message)`` of every message, deserialised with the upstream definitions."""
    from rosbags.highlevel import AnyReader

    out = []
    with AnyReader([path], default_typestore=_store(version)) as r:
        for c, t, raw in r.messages():
            out.append((c.topic, int(t), r.deserialize(raw, c.msgtype)))
    return out


def _header(store: Any, version: int, t: int, frame: str = "sonar") -> Any:
    T = store.types
    stamp = T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)
    if version == 1:
        return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def _stamp(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)


# ---------------------------------------------------------------------- RawSonarImage
def _raw_sonar_image(store: Any, version: int, t: int, rx: np.ndarray, counts: np.ndarray, *,
                     sample0: int = 5, fs: float = 50_000.0, c: float = 1480.0) -> Any:
    T = store.types
    info = T["marine_acoustic_msgs/msg/PingInfo"](
        frequency=1.2e6, sound_speed=c, tx_beamwidths=np.zeros(0, np.float32), rx_beamwidths=np.zeros(0, np.float32))
    img = T["marine_acoustic_msgs/msg/SonarImageData"](
        is_bigendian=False, dtype=2, beam_count=rx.size,
        data=np.frombuffer(counts.astype("<u2").tobytes(), np.uint8))  # range-major
    return T["marine_acoustic_msgs/msg/RawSonarImage"](
        header=_header(store, version, t), ping_info=info, sample_rate=fs, samples_per_beam=counts.shape[0],
        sample0=sample0, tx_delays=np.zeros(0, np.float32), tx_angles=np.zeros(rx.size, np.float32),
        rx_angles=rx.astype(np.float32), image=img)


@pytest.mark.parametrize("version", [1, 2])
def test_raw_sonar_image(tmp_path: Path, version: int) -> None:
    store = _store(version)
    rng = np.random.default_rng(1)
    rx = np.deg2rad(np.linspace(-30.0, 25.0, 8) + 0.5 * np.sin(np.arange(8))).astype(np.float32)
    counts = [rng.integers(0, 65536, (20, 8)) for _ in range(2)]
    path = _bag(tmp_path, version)
    _write(path, version, store=store, items=[
        ("/sonar/raw", "marine_acoustic_msgs/msg/RawSonarImage", _raw_sonar_image(store, version, T0 + i, rx, counts[i]), T0 + i)
        for i in range(2)
    ])
    pings = list(read_pings(path))
    assert len(pings) == 2 == rosbag.count_pings(path)
    want_r = (np.arange(20) + 5) * 1480.0 / (2 * 50_000.0)
    for i, p in enumerate(pings):
        assert p.time_ns == T0 + i and isinstance(p.time_ns, int)
        assert np.array_equal(p.image, (counts[i] / 65535.0).astype(np.float32))
        assert np.allclose(p.geometry.azimuth_rad, rx.astype(np.float64), atol=0)
        assert np.allclose(p.geometry.range_m, want_r, rtol=1e-12)
        assert p.geometry.sound_speed_m_s == pytest.approx(1480.0)
        assert p.meta["topic"] == "/sonar/raw" and p.meta["sample0"] == 5
    assert rosbag.summary(path)["pings"] == 2


def test_raw_sonar_image_reversed_beams_are_sorted(tmp_path: Path) -> None:
    store = _store(2)
    rx = np.deg2rad(np.linspace(20.0, -20.0, 6)).astype(np.float32)
    counts = np.arange(6 * 4).reshape(4, 6) * 100
    path = _bag(tmp_path, 2)
    _write(path, 2, store=store, items=[("/raw", "marine_acoustic_msgs/msg/RawSonarImage",
                             _raw_sonar_image(store, 2, T0, rx, counts, sample0=0), T0)])
    (p,) = read_pings(path)
    assert np.allclose(p.geometry.azimuth_rad, rx[::-1].astype(np.float64))
    assert np.array_equal(p.image, (counts[:, ::-1] / 65535.0).astype(np.float32))
    assert p.geometry.range_m[0] == 0.0


# ---------------------------------------------------------------------- acoustic_msgs/SonarImage
def _legacy(store: Any, version: int, t: int, az: np.ndarray, r: np.ndarray, counts: np.ndarray, ds: int,
            big: bool) -> Any:
    dt = {1: "u1", 2: "u2", 4: "u4"}[ds]
    data = counts.astype(np.dtype(dt).newbyteorder(">" if big else "<")).tobytes()  # range-major
    return store.types["acoustic_msgs/msg/SonarImage"](
        header=_header(store, version, t), frequency=9e5, sound_speed=1490.0, azimuth_beamwidth=0.01,
        elevation_beamwidth=0.2, azimuth_angles=az.astype(np.float32), elevation_angles=np.zeros(0, np.float32),
        ranges=r.astype(np.float32), is_bigendian=big, data_size=ds, intensities=np.frombuffer(data, np.uint8))


@pytest.mark.parametrize(("version", "ds", "big"), [(1, 1, False), (2, 2, True), (1, 4, False)])
def test_legacy_sonar_image(tmp_path: Path, version: int, ds: int, big: bool) -> None:
    store = _store(version)
    az = np.deg2rad(np.linspace(-45.0, 45.0, 12))
    r = 0.5 + 0.1 * np.arange(30)
    top = 2 ** (8 * ds) - 1
    counts = np.random.default_rng(ds).integers(0, top, (30, 12), endpoint=True, dtype=np.uint64)
    path = _bag(tmp_path, version)
    _write(path, version, store=store, items=[("/sonar/image", "acoustic_msgs/msg/SonarImage",
                                   _legacy(store, version, T0 + 7, az, r, counts, ds, big), T0 + 7)])
    (p,) = read_pings(path)
    assert p.time_ns == T0 + 7
    want = counts / 255.0 if ds == 1 else counts.astype(np.float64) / top
    assert np.allclose(p.image, want.astype(np.float32), atol=1e-7)
    assert np.allclose(p.geometry.azimuth_rad, az.astype(np.float32).astype(np.float64))
    assert np.allclose(p.geometry.range_m, r.astype(np.float32).astype(np.float64))
    assert p.meta["elevation_beamwidth_rad"] == pytest.approx(0.2)


# ---------------------------------------------------------------------- Oculus RawData
def _oculus_messages(path: Path) -> list[bytes]:
    data = path.read_bytes()
    out, o = [], 0
    while o + HEADER.size <= len(data):
        total = HEADER.size + HEADER.unpack_from(data, o)[5]
        out.append(data[o : o + total])
        o += total
    return out


@pytest.mark.parametrize("version", [1, 2])
def test_oculus_raw_data(tmp_path: Path, version: int, data_dir: Path) -> None:
    raw_file = data_dir / "oculus" / "three_pings_8bit.raw"
    msgs = _oculus_messages(raw_file)
    ref = list(read_pings(raw_file))
    store = _store(version)
    T = store.types

    def rd(t: int, data: bytes, direction: int = 1) -> Any:
        return T["apl_msgs/msg/RawData"](header=_header(store, version, t), direction=direction,
                                         data=np.frombuffer(data, np.uint8))

    items = [("/oculus/raw_data", "apl_msgs/msg/RawData", rd(T0 - 5, msgs[0][:40], 0), T0 - 5),  # a command
             ("/oculus/raw_data", "apl_msgs/msg/RawData", rd(T0 - 3, b"\x00"), T0 - 3)]  # resync byte
    stamps = []
    for i, m in enumerate(msgs):
        t = T0 + i * 66_666_667
        items.append(("/oculus/raw_data", "apl_msgs/msg/RawData", rd(t, m), t))
        stamps.append(t)
    path = _bag(tmp_path, version)
    _write(path, version, store=store, items=items)
    with pytest.warns(UserWarning, match="1 run.s. of bytes that are not an Oculus message skipped"):  # the resync byte
        pings = list(read_pings(path))
    assert len(pings) == len(ref) == 3 == rosbag.count_pings(path)
    for p, q, t in zip(pings, ref, stamps):
        assert p.time_ns == t
        assert np.array_equal(p.image, q.image)
        assert np.array_equal(p.geometry.azimuth_rad, q.geometry.azimuth_rad)
        assert np.array_equal(p.geometry.range_m, q.geometry.range_m)
        assert p.meta["time_source"] == "header_stamp" and p.meta["topic"] == "/oculus/raw_data"
    s = rosbag.summary(path)
    assert s["pings"] == 3 and s["message_kind"] == "oculus_raw"


def test_oculus_raw_data_broken_message_is_skipped_with_a_warning(tmp_path: Path, data_dir: Path) -> None:
    msgs = _oculus_messages(data_dir / "oculus" / "one_ping_8bit.raw")
    store = _store(2)
    T = store.types
    items = [("/raw", "apl_msgs/msg/RawData",
              T["apl_msgs/msg/RawData"](header=_header(store, 2, T0 + i), direction=1,
                                        data=np.frombuffer(m, np.uint8)), T0 + i)
             for i, m in enumerate([msgs[0][:-10], msgs[0]])]
    path = _bag(tmp_path, 2)
    _write(path, 2, store=store, items=items)
    with pytest.warns(UserWarning, match="1 incomplete message"):
        pings = list(read_pings(path))
    assert [p.time_ns for p in pings] == [T0 + 1]


@pytest.mark.parametrize("pieces", [2, 3, 7])
def test_oculus_raw_data_split_and_merged_messages_are_reassembled(tmp_path: Path, data_dir: Path,
                                                                   pieces: int) -> None:
    """A driver may record what one network read returned: a message split over several RawData,
    or several messages in one.  Each ping is read once, at the stamp of the RawData that
    completed it, with the image of the capture."""
    raw_file = data_dir / "oculus" / "three_pings_8bit.raw"
    msgs = _oculus_messages(raw_file)
    ref = list(read_pings(raw_file))
    store = _store(2)
    T = store.types
    chunks: list[bytes] = []
    done_at: list[int] = []  # index of the chunk completing each ping
    # ping 0 split into `pieces`, pings 1 and 2 merged into one RawData with 5 garbage bytes between
    cuts = np.linspace(0, len(msgs[0]), pieces + 1).astype(int)
    chunks += [msgs[0][a:b] for a, b in zip(cuts[:-1], cuts[1:])]
    done_at.append(len(chunks) - 1)
    chunks.append(msgs[1] + b"\x00\x01\x02SO" + msgs[2])
    done_at += [len(chunks) - 1] * 2
    items = [("/raw", "apl_msgs/msg/RawData", T["apl_msgs/msg/RawData"](
        header=_header(store, 2, T0 + k), direction=1, data=np.frombuffer(c, np.uint8)), T0 + k)
        for k, c in enumerate(chunks)]
    path = _bag(tmp_path, 2)
    _write(path, 2, store=store, items=items)
    with pytest.warns(UserWarning, match="not an Oculus message skipped"):
        pings = list(read_pings(path))
    assert [p.time_ns for p in pings] == [T0 + k for k in done_at]
    for p, q in zip(pings, ref, strict=True):
        assert np.array_equal(p.image, q.image)
    assert rosbag.count_pings(path) == 3


# ---------------------------------------------------------------------- precedence
def _geometry() -> SonarGeometry:
    return SonarGeometry(azimuth_rad=np.deg2rad(np.linspace(-20, 20, 8)), range_m=1.0 + 0.1 * np.arange(10),
                         name="fls")


def test_projected_image_takes_precedence_and_topic_selects(tmp_path: Path) -> None:
    g = _geometry()
    proj = tmp_path / "p.bag"
    write_bag([Ping(image=np.full(g.shape, 0.5, np.float32), geometry=g, time_ns=T0)], proj, version=1)
    # add a RawSonarImage topic to a copy: rewrite with rosbags, projected + raw
    from rosbags.highlevel import AnyReader

    store = _store(1)
    items = []
    with AnyReader([proj], default_typestore=store) as r:
        for c, t, raw in r.messages():
            items.append((c.topic, c.msgtype, r.deserialize(raw, c.msgtype), t))
    rx = np.deg2rad(np.linspace(-10, 10, 4)).astype(np.float32)
    items.append(("/sonar/raw", "marine_acoustic_msgs/msg/RawSonarImage",
                  _raw_sonar_image(store, 1, T0 + 1, rx, np.zeros((6, 4), int)), T0 + 1))
    both = tmp_path / "both.bag"
    _write(both, 1, store=store, items=items)
    (p,) = read_pings(both)
    assert p.geometry.shape == g.shape and rosbag.count_pings(both) == 1
    (q,) = read_pings(both, topic="/sonar/raw")
    assert q.geometry.shape == (6, 4) and q.time_ns == T0 + 1


def test_unreadable_listing_names_the_new_types(tmp_path: Path) -> None:
    store = _store(2)
    T = store.types
    path = _bag(tmp_path, 2)
    _write(path, 2, store=store, items=[("/oculus/raw_data", "apl_msgs/msg/RawData",
                             T["apl_msgs/msg/RawData"](header=_header(store, 2, T0), direction=1,
                                                       data=np.arange(20, dtype=np.uint8)), T0)])
    with pytest.raises(DataFormatError, match=r"RawSonarImage, acoustic_msgs/SonarImage, apl_msgs/RawData with "
                       r"Oculus pings.*/oculus/raw_data: its RawData hold no Oculus SimplePingResult; the bag has"):
        rosbag.count_pings(path)


# ---------------------------------------------------------------------- ProjectedSonarImage beam widths
def test_projected_image_beamwidths_follow_the_geometry(tmp_path: Path) -> None:
    g = preset("didson-hf").replace(azimuth_beamwidth_rad=None)  # the beam pattern's width
    tx, rx = beamwidths(g)
    spacing = np.gradient(g.azimuth_rad)  # DIDSON's lens fan is not evenly spaced: one width per beam
    assert tx.size == 0 and rx.size == g.n_beams and np.all((0.5 * spacing < rx) & (rx < 10 * spacing))
    even = SonarGeometry(azimuth_rad=np.linspace(-0.2, 0.2, 9), range_m=[1.0, 2.0], psf=[0, 0, 0, 1, 2, 1, 0, 0, 0])
    assert np.allclose(beamwidths(even)[1], [2 * 0.05])  # half maximum one beam either side of the peak
    path = tmp_path / "d.bag"
    write_bag([Ping(image=np.zeros(g.shape, np.float32), geometry=g, time_ns=T0)], path, version=1)
    ((_, _, msg),) = [m for m in _read(path, 1) if m[0] == "/sonar/image"]
    assert np.allclose(msg.ping_info.rx_beamwidths, rx) and len(msg.ping_info.tx_beamwidths) == 0
    one = SonarGeometry(azimuth_rad=[0.0], range_m=[1.0, 2.0], fov_rad=0.05)
    assert np.allclose(beamwidths(one)[1], [0.05]) and beamwidths(_geometry())[1].size == 0


@pytest.mark.parametrize("version", [1, 2])
def test_tx_beamwidth_is_the_elevation_beamwidth_and_reads_back(tmp_path: Path, version: int) -> None:
    g = preset("aris3000-128")  # standard ARIS lens: 14 deg across the fan
    assert g.elevation_beamwidth_rad == pytest.approx(np.deg2rad(14.0))
    tx, _ = beamwidths(g)
    assert tx.dtype == np.float32 and tx.size == 1 and tx[0] == np.float32(np.deg2rad(14.0))
    path = _bag(tmp_path, version)
    write_bag([Ping(image=np.zeros(g.shape, np.float32), geometry=g, time_ns=T0)], path, version=version)
    ((_, _, msg),) = [m for m in _read(path, version) if m[0] == "/sonar/image"]
    assert np.array_equal(msg.ping_info.tx_beamwidths, tx)  # what a ROS consumer sees
    (back,) = read_pings(path)
    assert back.geometry.elevation_beamwidth_rad == g.elevation_beamwidth_rad  # exact (geometry side channel)
    assert rosbag.elevation_from_ping_info(msg.ping_info) == pytest.approx(float(tx[0]), rel=0, abs=0)


@pytest.mark.parametrize("version", [1, 2])
def test_rx_beamwidth_is_the_one_way_azimuth_beamwidth_and_reads_back(tmp_path: Path, version: int) -> None:
    g = preset("didson-hf")  # two-way 0.3 deg main lobe, the same for every beam
    two_way = float(g.azimuth_beamwidth_rad[0])
    _, rx = beamwidths(g)
    assert rx.dtype == np.float32 and rx.size == 1 and rx[0] == np.float32(np.sqrt(2.0) * two_way)
    path = _bag(tmp_path, version)
    write_bag([Ping(image=np.zeros(g.shape, np.float32), geometry=g, time_ns=T0)], path, version=version)
    ((_, _, msg),) = [m for m in _read(path, version) if m[0] == "/sonar/image"]
    assert np.array_equal(msg.ping_info.rx_beamwidths, rx)
    assert rosbag.azimuth_from_ping_info(msg.ping_info) == pytest.approx(two_way, rel=1e-6)
    (back,) = read_pings(path)
    assert np.allclose(back.geometry.azimuth_beamwidth_rad, two_way, rtol=1e-6)
    # without the geometry side channel the width comes from the message alone
    T = _store(2).types
    info = T["marine_acoustic_msgs/msg/PingInfo"](frequency=1e6, sound_speed=1500.0,
                                                 tx_beamwidths=np.zeros(0, np.float32),
                                                 rx_beamwidths=np.full(3, 0.02, np.float32))
    assert rosbag.azimuth_from_ping_info(info) == pytest.approx(0.02 / np.sqrt(2.0))
    for bad in ([], [0.02, 0.03], [0.0], [-0.1], [2.0], [float("nan")]):
        info = T["marine_acoustic_msgs/msg/PingInfo"](frequency=1e6, sound_speed=1500.0,
                                                     tx_beamwidths=np.zeros(0, np.float32),
                                                     rx_beamwidths=np.asarray(bad, np.float32))
        assert rosbag.azimuth_from_ping_info(info) is None, bad


def test_elevation_from_ping_info_needs_one_plausible_width() -> None:
    T = _store(2).types

    def info(tx: list[float]) -> Any:
        return T["marine_acoustic_msgs/msg/PingInfo"](frequency=1e6, sound_speed=1500.0,
                                                     tx_beamwidths=np.asarray(tx, np.float32),
                                                     rx_beamwidths=np.zeros(0, np.float32))

    assert rosbag.elevation_from_ping_info(info([])) is None  # not reported
    assert rosbag.elevation_from_ping_info(info([0.2, 0.2, 0.2])) == pytest.approx(0.2)  # one per beam, equal
    for bad in ([0.2, 0.3], [0.0], [-0.1], [4.0], [float("nan")]):
        assert rosbag.elevation_from_ping_info(info(bad)) is None, bad


def test_raw_sonar_image_tx_beamwidth_sets_the_elevation_beamwidth(tmp_path: Path) -> None:
    store = _store(2)
    rx = np.deg2rad(np.linspace(-30.0, 30.0, 8)).astype(np.float32)
    msg = _raw_sonar_image(store, 2, T0, rx, np.ones((20, 8), np.int64))
    msg.ping_info.tx_beamwidths = np.array([0.2], np.float32)
    path = _bag(tmp_path, 2)
    _write(path, 2, store=store, items=[("/sonar/raw", "marine_acoustic_msgs/msg/RawSonarImage", msg, T0)])
    (p,) = read_pings(path)
    assert p.geometry.elevation_beamwidth_rad == pytest.approx(float(np.float32(0.2)), rel=0)


# ---------------------------------------------------------------------- SonarRanges
def _beam_ranges(g: SonarGeometry, t: int, hits: dict[int, float]) -> BeamRanges:
    n = g.n_beams
    rng = np.full(n, np.nan)
    b = np.full(n, -1, np.int64)
    inten = np.full(n, np.nan, np.float32)
    for j, r in hits.items():
        rng[j], b[j], inten[j] = r, int(g.bin_of_range(r)), 0.25 + 0.01 * j
    return BeamRanges(range_m=rng, bin=b, intensity=inten, confidence=np.ones(n, np.float32),
                      azimuth_rad=g.azimuth_rad, time_ns=t)


@pytest.mark.parametrize("version", [1, 2])
def test_sonar_ranges_written(tmp_path: Path, version: int) -> None:
    g = preset("didson-hf")
    items = [(g, _beam_ranges(g, T0, {0: 3.25, 40: 5.5})), (g, _beam_ranges(g, T0 + 99, {95: 7.125}))]
    path = _bag(tmp_path, version, "ranges")
    assert write_ranges_bag(items, path, version=version, frame_id="didson") == 2
    msgs = _read(path, version)
    assert [t for _, t, _ in msgs] == [T0, T0 + 99] == [_stamp(m) for _, _, m in msgs]
    for (_, r), (topic, _, m) in zip(items, msgs):
        assert topic == "/sonar/ranges" and m.header.frame_id == "didson"
        got = np.asarray(m.ranges, np.float64)
        hit = r.bin >= 0
        assert np.allclose(got[hit], r.range_m[hit]) and np.all(np.isnan(got[~hit]))
        assert [f.flag for f in m.flags] == [0 if h else 2 for h in hit]
        v = np.array([[u.x, u.y, u.z] for u in m.beam_unit_vec])
        assert np.allclose(np.arctan2(-v[:, 1], v[:, 2]), g.azimuth_rad, atol=1e-12)
        assert np.allclose(np.linalg.norm(v, axis=1), 1.0) and np.all(v[:, 0] == 0)
        assert np.allclose(np.asarray(m.intensities)[hit], r.intensity[hit])
        assert m.ping_info.sound_speed == pytest.approx(g.sound_speed_m_s)
    if version == 1:  # the bag's MD5 is the upstream definition's: ROS 1 tools accept the messages
        from rosbags.rosbag1 import Reader

        with Reader(path) as r:
            (conn,) = r.connections
        assert conn.digest == _store(1).generate_msgdef("marine_acoustic_msgs/msg/SonarRanges")[1]


# ---------------------------------------------------------------------- PointCloud2
def _points(msg: Any) -> dict[str, np.ndarray]:
    codes = {2: "u1", 4: "<u2", 6: "<u4", 7: "<f4", 8: "<f8"}
    dt = np.dtype({"names": [f.name for f in msg.fields], "formats": [codes[f.datatype] for f in msg.fields],
                   "offsets": [f.offset for f in msg.fields], "itemsize": msg.point_step})
    rec = np.frombuffer(np.asarray(msg.data, np.uint8).tobytes(), dtype=dt, count=msg.width * msg.height)
    return {n: rec[n] for n in dt.names}


@pytest.mark.parametrize("version", [1, 2])
def test_point_cloud2_written(tmp_path: Path, version: int) -> None:
    n = 7
    xyz = np.column_stack([np.arange(n) * 0.5, -np.arange(n) * 0.25, 3.0 + np.arange(n)])
    times = np.array([T0] * 4 + [T0 + 10**8] * 3, np.int64)
    cloud = PointCloud(xyz_m=xyz, time_ns=times, beam=np.arange(n), range_m=np.linspace(1, 2, n),
                       intensity=np.linspace(0.1, 0.7, n), confidence=np.ones(n), elevation_rad=np.zeros(n),
                       frame="enu")
    path = _bag(tmp_path, version, "points")
    assert write_points_bag([cloud], path, version=version) == 2
    msgs = _read(path, version)
    assert [t for _, t, _ in msgs] == [T0, T0 + 10**8] == [_stamp(m) for _, _, m in msgs]
    for (_, _, m), sel in zip(msgs, [slice(0, 4), slice(4, 7)]):
        assert m.header.frame_id == "map" and m.height == 1 and not m.is_bigendian
        pts = _points(m)
        assert [f.name for f in m.fields][:4] == ["x", "y", "z", "intensity"]
        assert np.allclose(np.column_stack([pts["x"], pts["y"], pts["z"]]), xyz[sel])
        assert np.allclose(pts["intensity"], cloud.intensity[sel]) and np.all(pts["time"] == 0)
        assert np.array_equal(pts["beam"], np.arange(n)[sel])


# ---------------------------------------------------------------------- CLI
def test_cli_ranges_and_map_to_bags(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    inputs = [str(p) for p in test_ping_paths[:2]]
    pings = list(read_pings(inputs))
    csv_path, bag_path = tmp_path / "r.csv", tmp_path / "r.bag"
    assert main(["ranges", *inputs, "-o", str(csv_path), "-q"]) == 0
    assert main(["ranges", *inputs, "-o", str(bag_path), "-q"]) == 0
    rows = list(csv.DictReader(csv_path.open()))
    msgs = _read(bag_path, 1)
    assert [_stamp(m) for _, _, m in msgs] == [p.time_ns for p in pings] == [t for _, t, _ in msgs]
    for k, (_, _, m) in enumerate(msgs):
        mine = [r for r in rows if int(r["time_ns"]) == pings[k].time_ns]
        want = np.array([float(r["range_m"]) if r["range_m"] else np.nan for r in mine])
        got = np.asarray(m.ranges, np.float64)
        assert len(got) == pings[k].geometry.n_beams == len(want)
        assert np.array_equal(np.isnan(got), np.isnan(want))
        assert np.allclose(got[~np.isnan(got)], want[~np.isnan(want)], atol=1e-5)
    assert sum(int(np.sum(~np.isnan(np.asarray(m.ranges)))) for _, _, m in msgs) > 0
    bag2 = tmp_path / "r_ros2"
    assert main(["ranges", inputs[0], "-o", str(bag2), "--to", "bag2", "-q"]) == 0
    assert len(_read(bag2, 2)) == 1

    pts_csv, pts_bag = tmp_path / "p.csv", tmp_path / "p.bag"
    assert main(["map", *inputs, "--static", "-o", str(pts_csv), "-q"]) == 0
    assert main(["map", *inputs, "--static", "-o", str(pts_bag), "-q"]) == 0
    ref = np.genfromtxt(pts_csv, delimiter=",", names=True)
    pmsgs = _read(pts_bag, 1)
    assert len(pmsgs) >= 1 and all(_stamp(m) in {p.time_ns for p in pings} for _, _, m in pmsgs)
    assert all(m.header.frame_id == "map_ned" for _, _, m in pmsgs)
    xyz = np.concatenate([np.column_stack([(d := _points(m))["x"], d["y"], d["z"]]) for _, _, m in pmsgs])
    cols = [c for c in ref.dtype.names if c in ("x", "y", "z", "x_m", "y_m", "z_m")][:3]
    assert xyz.shape[0] == ref.shape[0]
    assert np.allclose(xyz, np.column_stack([ref[c] for c in cols]), atol=1e-4)


def test_cli_bag_outputs_checked_before_work(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    one = str(test_ping_paths[0])
    assert main(["ranges", one, "-o", str(tmp_path / "x.csv"), "--to", "bag3"]) == 2
    assert main(["map", one, "--static", "-o", str(tmp_path / "x.bag"), "--grid", "0.5", "--dims", "4"]) == 2
    assert main(["map", one, "--static", "-o", "-", "--format", "bag1"]) == 2
    assert not any(tmp_path.iterdir())



def test_cli_occupancy_map_to_a_bag(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    """`map --grid -o x.bag`: one PointCloud2 of the occupied cells (x, y, z, p_occupied,
    log_odds), stamped at the last ping, with the cells and probabilities of the PLY output."""
    from sonarmap.mapping.pointcloud import read_point_cloud

    inputs = [str(p) for p in test_ping_paths[4:6]]
    pings = list(read_pings(inputs))
    ply, bag = tmp_path / "occ.ply", tmp_path / "occ.bag"
    assert main(["map", *inputs, "--static", "--grid", "0.25", "-o", str(ply), "-q"]) == 0
    assert main(["map", *inputs, "--static", "--grid", "0.25", "-o", str(bag), "-q"]) == 0
    msgs = _read(bag, 1)
    assert len(msgs) == 1
    _, t, m = msgs[0]
    assert t == _stamp(m) == max(p.time_ns for p in pings)
    assert [f.name for f in m.fields] == ["x", "y", "z", "p_occupied", "log_odds"]
    d = _points(m)
    ref = read_point_cloud(ply)
    assert len(d["x"]) == len(ref) > 0
    assert np.allclose(np.column_stack([d["x"], d["y"], d["z"]]), ref.xyz_m, atol=1e-4)
    assert np.allclose(d["p_occupied"], ref.confidence, atol=1e-6)
    assert np.all((d["p_occupied"] > 0.5) & (d["p_occupied"] < 1))
    assert np.allclose(d["log_odds"], np.log(d["p_occupied"] / (1 - d["p_occupied"])), atol=1e-4)
