"""Hardening of the binary readers: one regression test per fuzzing-run reproducer, then a seeded
mini-fuzz per reader (truncation, bit flips, header fields set to extreme values).

Every fuzz case must either yield valid pings (finite float32 images in [0, 1] of the geometry's
shape, finite geometry, int64 time) or raise a :class:`~sonarmap.errors.SonarmapError` - nothing
else - and finish in bounded time.
"""

from __future__ import annotations

import json
import math
import os
import sqlite3
import struct
import subprocess
import sys
import textwrap
import time
import tracemalloc
import warnings
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ddf_writer import write_ddf
from guards import Hang, deadline
from oculus_writer import encode_ping, write_log_v1, write_log_v2

from sonarmap.errors import DataFormatError, InputError, SonarmapError
from sonarmap.geometry import preset
from sonarmap.io import aris, ddf, detect_format, oculus, read_pings, rosbag
from sonarmap.io._binary import MAX_PING_BYTES, map_file
from sonarmap.io.aris import FILE_HEADER_DTYPE, FILE_HEADER_SIZE, FRAME_HEADER_DTYPE, FRAME_HEADER_SIZE, ArisFile
from sonarmap.io.ddf import FILE_HEADER_DTYPES, FRAME_HEADER_DTYPES, DdfFile
from sonarmap.io.oculus import (
    FIRE_V1,
    FIRE_V2_EXTRA,
    HEADER,
    LOG_HEADER,
    LOG_ITEM,
    PING_V1,
    PING_V2,
    OculusFile,
)
from sonarmap.io.rosbag import MSGTYPE, typestore, write_bag
from sonarmap.ping import Ping

BEARINGS = np.linspace(-6500, 6500, 16).round().astype(np.int16)
INT64_MAX = 2**63 - 1


@pytest.fixture(scope="module")
def sample_aris(data_dir: Path) -> bytes:
    return (data_dir / "aris" / "sample.aris").read_bytes()


@pytest.fixture(scope="module")
def oculus_raw(data_dir: Path) -> bytes:
    return (data_dir / "oculus" / "three_pings_8bit.raw").read_bytes()


def _msgs(n: int = 2, shape: tuple[int, int] = (30, 16), seed: int = 0) -> list[bytes]:
    rng = np.random.default_rng(seed)
    return [encode_ping(rng.integers(0, 256, shape, dtype=np.uint8), BEARINGS, ping_id=i) for i in range(n)]


def _patch(data: bytes | bytearray, offset: int, fmt: str, value: Any) -> bytearray:
    out = bytearray(data)
    struct.pack_into(fmt, out, offset, value)
    return out


def _aris_field(name: str, frame: int = 0) -> int:
    """Byte offset of frame ``frame``'s header field ``name`` in sample.aris (48 beams x 2000)."""
    return FILE_HEADER_SIZE + frame * (FRAME_HEADER_SIZE + 48 * 2000) + FRAME_HEADER_DTYPE.fields[name][1]


# ====================================================================== ViewPoint zlib bomb
def _zlib_bomb(prefix: bytes, n_mib: int) -> bytes:
    """A valid zlib stream of ``prefix`` + ``n_mib`` MiB of zeros, built without inflating it.

    After a full flush the compressor has no history, so compressing another MiB of zeros gives
    the same bytes every time: the segment is repeated and the Adler-32 trailer computed in closed
    form (zeros leave ``a`` unchanged and add ``a`` to ``b`` per byte).
    """
    c = zlib.compressobj(9)
    head = c.compress(prefix) + c.flush(zlib.Z_FULL_FLUSH)
    seg = c.compress(bytes(1 << 20)) + c.flush(zlib.Z_FULL_FLUSH)
    assert c.compress(bytes(1 << 20)) + c.flush(zlib.Z_FULL_FLUSH) == seg
    tail = c.flush()[:-4]  # final empty block; the trailer is replaced below
    adler = zlib.adler32(prefix)
    a, b = adler & 0xFFFF, adler >> 16
    b = (b + (n_mib << 20) * a) % 65521
    return head + seg * n_mib + tail + struct.pack(">I", (b << 16) | a)


def _log_v1_item(payload: bytes, *, time_s: float = 1.6e9, compressed: bool = True, orig: int = 0) -> bytes:
    return LOG_ITEM.pack(0xAABBCCDD, LOG_ITEM.size, 10, 0, time_s, int(compressed), orig, len(payload)) + payload


def _log_v1(items: list[bytes]) -> bytes:
    return LOG_HEADER.pack(0x11223344, LOG_HEADER.size, b"Oculus", 1, 0, 0, 1.6e9) + b"".join(items)


def test_zlib_bomb_helper_is_a_valid_stream() -> None:
    m = _msgs(1)[0]
    assert zlib.decompress(_zlib_bomb(m, 3)) == m + bytes(3 << 20)


def test_viewpoint_zlib_bomb_is_refused_in_bounded_memory(tmp_path: Path) -> None:
    """A ~3 MB log whose compressed item inflates to 3 GiB (the fuzzing run's MemoryError)."""
    m = _msgs(1)[0]
    bomb = _zlib_bomb(m, 3072)
    assert len(bomb) < 4_000_000
    p = tmp_path / "bomb.oculus"
    for declared, match in ((len(m), "inflates to more than"), (3 << 30, "declares 3221225472 bytes")):
        p.write_bytes(_log_v1([_log_v1_item(struct.pack(">I", declared) + bomb, orig=len(m))]))
        with OculusFile(p) as f:
            assert len(f) == 1  # the item's header is a SimplePingResult
        tracemalloc.start()
        t0 = time.perf_counter()
        try:
            with pytest.raises(DataFormatError, match=rf"bomb\.oculus: at byte 88: compressed payload {match}"):
                list(read_pings(p))
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 32 * 2**20 and time.perf_counter() - t0 < 5.0
    # the declared size is capped at one ping's maximum even when the stream is that large
    p.write_bytes(_log_v1([_log_v1_item(struct.pack(">I", MAX_PING_BYTES + 1) + bomb)]))
    with pytest.raises(DataFormatError, match="more than the 67108864 allowed"):
        list(read_pings(p))


def test_viewpoint_compressed_item_whose_header_needs_more_input(tmp_path: Path) -> None:
    """A compressed ping whose first 60 compressed bytes inflate to nothing is still found."""
    msgs = _msgs(2, shape=(100, 16))
    assert len(zlib.decompressobj().decompress(zlib.compress(msgs[0])[:60], 16)) < HEADER.size
    p = tmp_path / "c.oculus"
    write_log_v1(p, msgs, [1.6e9, 1.6e9 + 1], compress=True)
    with OculusFile(p) as f:
        assert len(f) == 2
        last_rows = np.frombuffer(msgs[1][-32:], np.uint8).reshape(2, 16)
        assert np.array_equal(np.rint(f[1].image * 255).astype(np.uint8)[-2:], last_rows)


# ====================================================================== ViewPoint SQLite paths
@pytest.mark.parametrize("name", ["a#b.oculus", "q?x.oculus", "100%.oculus", "two words.oculus", "%3F#?.oculus"])
def test_viewpoint_sqlite_path_characters(tmp_path: Path, name: str) -> None:
    msgs = _msgs(2)
    times = [1.6e9, 1.6e9 + 0.5]
    p = tmp_path / name
    write_log_v2(p, msgs, times)
    before = sorted(os.listdir(tmp_path))
    assert detect_format(p) == "oculus"
    pings = list(read_pings(p))
    assert [q.time_ns for q in pings] == [int(t * 1e9) for t in times]
    assert np.array_equal(np.rint(pings[1].image * 255).astype(np.uint8)[-1], np.frombuffer(msgs[1][-16:], np.uint8))
    assert oculus.summary(p)["pings"] == 2
    assert sorted(os.listdir(tmp_path)) == before  # no stray file ("q" for q?x.oculus)


def test_viewpoint_sqlite_is_opened_read_only(tmp_path: Path) -> None:
    """``mode=ro`` survives the URI quoting (even for root, who may write a 0444 file)."""
    p = tmp_path / "r#o.oculus"
    write_log_v2(p, _msgs(1), [1.6e9])
    with OculusFile(p) as f:
        with pytest.raises(sqlite3.OperationalError, match="readonly"):
            f._connect().execute("DELETE FROM data")
    assert len(OculusFile(p)) == 1


def test_viewpoint_sqlite_column_names_are_quoted(tmp_path: Path) -> None:
    msgs = _msgs(2)
    p = tmp_path / "cols.oculus"
    con = sqlite3.connect(p)
    with con:
        con.execute('CREATE TABLE data (entryId INTEGER PRIMARY KEY, "stamp ""time"" x" REAL, '
                    '"pay""load; DROP TABLE data; --" BLOB)')
        for i, m in enumerate(msgs):
            con.execute("INSERT INTO data VALUES (?, ?, ?)", (i + 1, 1.6e9 + i, m))
    con.close()
    with OculusFile(p) as f:
        assert f.kind == "log-v2" and len(f) == 2
        assert f[1].time_ns == int((1.6e9 + 1) * 1e9)
    con = sqlite3.connect(p)
    assert con.execute("SELECT count(*) FROM data").fetchone() == (2,)
    con.close()


# ====================================================================== absurd header values
def test_aris_sample_period_ffffffff(sample_aris: bytes, tmp_path: Path) -> None:
    """SamplePeriod 0xFFFFFFFF used to give a 6.2e9 m window without a word."""
    p = tmp_path / "sp.aris"
    p.write_bytes(_patch(sample_aris, _aris_field("SamplePeriod"), "<I", 0xFFFFFFFF))
    with ArisFile(p) as f:
        with pytest.raises(DataFormatError, match=r"sp\.aris: at byte 1024: .*SamplePeriod 4294967295 µs is outside 1-1000"):
            f[0]
    with pytest.raises(DataFormatError, match="SamplePeriod"):
        aris.summary(p)


@pytest.mark.parametrize("c", [0.0, -1500.0, 1e30, float("nan"), float("inf"), 1200.0, 1800.0, 340.0])
def test_aris_absurd_sound_speed(sample_aris: bytes, tmp_path: Path, c: float) -> None:
    p = tmp_path / "c.aris"
    p.write_bytes(_patch(sample_aris, _aris_field("SoundSpeed", 2), "<f", c))
    with ArisFile(p) as f:
        assert f[1].geometry.sound_speed_m_s == pytest.approx(1435.93, abs=0.01)
        with pytest.raises(DataFormatError, match=r"frame header 2: SoundSpeed .* is outside 1300-1700 m/s"):
            f[2]
    # an explicit geometry still reads the file (the header's window fields are then unused)
    with ArisFile(p, geometry=preset("aris-telephoto-48").replace(range_m=np.arange(2000) * 0.01 + 3)) as f:
        assert f[2].shape == (2000, 48)


@pytest.mark.parametrize(
    ("field", "fmt", "value", "match"),
    [
        ("SampleStartDelay", "<I", 0xFFFFFFFF, "reaches beyond 1000 m"),
        ("SamplePeriod", "<I", 0, "SamplePeriod 0 µs"),
        ("SamplePeriod", "<I", 700, "reaches beyond 1000 m"),
        ("WindowStart", "<f", float("nan"), "WindowStart nan m"),
        ("WindowLength", "<f", -3.0, "WindowLength -3.0 m"),
        ("WindowLength", "<f", 6.2e9, "WindowLength"),
        ("FrameRate", "<f", float("inf"), "FrameRate inf Hz"),
        ("ReceiverGain", "<I", 0xFFFFFFFF, "ReceiverGain 4294967295"),
    ],
)
def test_aris_implausible_frame_fields(sample_aris: bytes, tmp_path: Path, field: str, fmt: str, value: float, match: str) -> None:
    p = tmp_path / "f.aris"
    p.write_bytes(_patch(sample_aris, _aris_field(field), fmt, value))
    with pytest.raises(DataFormatError, match=match):
        ArisFile(p)[0]


def test_real_files_still_read(sample_aris: bytes, data_dir: Path) -> None:
    assert len(list(read_pings(data_dir / "aris" / "sample.aris"))) == 6
    pings = list(read_pings(data_dir / "oculus" / "three_pings_8bit.raw"))
    # the capture's temperature/pressure fields are garbage (1e-76, -1e194): meta only, not checked
    assert len(pings) == 3 and pings[0].geometry.sound_speed_m_s == pytest.approx(1490.66, abs=0.01)


_V1_PING = HEADER.size + FIRE_V1.size  # offset of the PING_V1 fields in a v1 message


_PING_V1_NAMES = ("pingId status frequency temperature pressure speedOfSoundUsed pingStartTime dataSize "
                  "rangeResolution nRanges nBeams imageOffset imageSize messageSize").split()


def _ping_v1_offset(name: str) -> int:
    """Byte offset of a ``PING_V1`` field in a v1 message."""
    return _struct_fields(PING_V1.format, _V1_PING)[_PING_V1_NAMES.index(name)][1]


@pytest.mark.parametrize(
    ("field", "fmt", "value", "match"),
    [
        ("speedOfSoundUsed", "<d", 1e30, "speedOfSoundUsed 1e\\+30 m/s is outside 1300-1700"),
        ("speedOfSoundUsed", "<d", -1490.0, "speedOfSoundUsed -1490.0"),
        ("speedOfSoundUsed", "<d", float("nan"), "speedOfSoundUsed nan"),
        ("rangeResolution", "<d", 5.0, "range window 703 x 5 m = 3515 m is beyond 1000 m"),
        ("rangeResolution", "<d", float("inf"), "rangeResolution inf"),
        ("frequency", "<d", -2.1e6, "frequency -2100000.0 Hz"),
    ],
)
def test_oculus_raw_implausible_fields(oculus_raw: bytes, tmp_path: Path, field: str, fmt: str, value: float, match: str) -> None:
    p = tmp_path / "o.raw"
    p.write_bytes(_patch(oculus_raw[:182016], _ping_v1_offset(field), fmt, value))
    with pytest.raises(DataFormatError, match=rf"o\.raw: at byte 0: inconsistent SimplePingResult: {match}"):
        list(read_pings(p))


def test_oculus_unset_sound_speed_and_frequency_are_defaults(oculus_raw: bytes, tmp_path: Path) -> None:
    data = _patch(oculus_raw[:182016], _ping_v1_offset("speedOfSoundUsed"), "<d", 0.0)
    data = _patch(data, _ping_v1_offset("frequency"), "<d", 0.0)
    p = tmp_path / "o.raw"
    p.write_bytes(data)
    (ping,) = read_pings(p)
    assert ping.geometry.sound_speed_m_s == 1500.0 and ping.meta["sound_speed_reported"] == 0.0
    assert ping.geometry.frequency_hz == 1.2e6


# ====================================================================== time overflow
def test_ping_refuses_time_outside_int64() -> None:
    g = preset("didson-hf")
    img = np.zeros(g.shape, np.float32)
    assert Ping(img, g, INT64_MAX).time_ns == INT64_MAX
    for t in (2**63, -(2**63) - 1, 2**64 - 1, 10**30, float("nan"), float("inf")):
        with pytest.raises(InputError, match="time_ns"):
            Ping(img, g, t)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("FrameTime", 2**64 - 1, "FrameTime 18446744073709551615000 ns is outside the years 1970-2200"),
        ("FrameTime", INT64_MAX // 1000 + 1, "FrameTime 9223372036854776000 ns"),
        ("FrameTime", 7_258_118_400 * 10**6 + 1, "FrameTime 7258118400000001000 ns is outside the years"),  # 2200-01-01 + 1 µs
        ("sonarTimeStamp", 2**63, "sonarTimeStamp"),
    ],
)
def test_aris_time_overflow(sample_aris: bytes, tmp_path: Path, field: str, value: int, match: str) -> None:
    p = tmp_path / "t.aris"
    p.write_bytes(_patch(sample_aris, _aris_field(field, 1), "<Q", value))
    with ArisFile(p) as f:
        f[0]
        with pytest.raises(DataFormatError, match=rf"t\.aris: at byte \d+: inconsistent frame 1 time: {match}"):
            f[1]
    p.write_bytes(_patch(sample_aris, _aris_field("FrameTime"), "<Q", 0))
    assert ArisFile(p)[0].time_ns == 0  # 0 = unknown


def _ddf_bytes(tmp_path: Path, version: int = 4, n: int = 2) -> bytes:
    p = tmp_path / "src.ddf"
    rng = np.random.default_rng(1)
    write_ddf(p, [rng.integers(0, 256, (32, 96), dtype=np.uint8) for _ in range(n)], version=version)
    return p.read_bytes()


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [("year", 0x7FFFFFFF, r"invalid date/time fields \[2147483647, 7, 19"),
     ("year", 2201, r"invalid date/time fields \[2201, 7, 19"), ("year", -1, r"invalid date/time fields \[-1, 7"),
     ("day", 30, r"invalid date/time fields \[2016, 2, 30, .*\] \(no day 30 in 2016-02\)")],
)
def test_ddf_time_out_of_range(tmp_path: Path, field: str, value: int, match: str) -> None:
    data = bytearray(_ddf_bytes(tmp_path))
    off = 1024 + FRAME_HEADER_DTYPES[4].fields[field][1]
    struct.pack_into("<i", data, off, value)
    if field == "day":
        struct.pack_into("<i", data, 1024 + FRAME_HEADER_DTYPES[4].fields["month"][1], 2)
    p = tmp_path / "t.ddf"
    p.write_bytes(bytes(data))
    with pytest.raises(DataFormatError, match=rf"t\.ddf: at byte 1044: inconsistent frame 0 time: {match}"):
        DdfFile(p)[0]


def test_ddf_implausible_header_fields(tmp_path: Path) -> None:
    data = _ddf_bytes(tmp_path)
    p = tmp_path / "h.ddf"
    p.write_bytes(_patch(data, FILE_HEADER_DTYPES[4].fields["framerate"][1], "<i", -7))
    with pytest.raises(DataFormatError, match="framerate -7 Hz"):
        DdfFile(p)
    p.write_bytes(_patch(data, 1024 + FRAME_HEADER_DTYPES[4].fields["receivergain"][1], "<i", 2**31 - 1))
    with pytest.raises(DataFormatError, match="receivergain 2147483647 dB"):
        DdfFile(p)[0]


@pytest.mark.parametrize(("t", "match"), [(1e30, "outside the years"), (9.3e18, "outside the years"),
                                          (float("nan"), "not a finite"), (-1.0, "not a finite"),
                                          (7.3e9, "outside the years")])
def test_oculus_log_time_overflow(tmp_path: Path, t: float, match: str) -> None:
    msgs = _msgs(2)
    p = tmp_path / "t1.oculus"
    write_log_v1(p, msgs, [1.6e9, t])
    with pytest.raises(DataFormatError, match=rf"t1\.oculus: at byte \d+: inconsistent log item time: time stamp .*{match}"):
        OculusFile(p)
    if math.isnan(t):
        return  # SQLite stores NaN as NULL, which reads as time 0 ("unknown")
    p2 = tmp_path / "t2.oculus"
    write_log_v2(p2, msgs, [1.6e9, t / 1000.0])  # the writer stores ms
    with pytest.raises(DataFormatError, match=rf"t2\.oculus: inconsistent row \d+ time stamp: time stamp .*{match}"):
        OculusFile(p2)


def test_oculus_log_time_blob_or_text(tmp_path: Path) -> None:
    p = tmp_path / "t.oculus"
    write_log_v2(p, _msgs(1), [1.6e9])
    for bad in (b"\x01\x02", "yesterday"):
        con = sqlite3.connect(p)
        with con:
            con.execute("UPDATE data SET timestamp = ? WHERE type = 0", (bad,))
        con.close()
        with pytest.raises(DataFormatError, match="time stamp"):
            OculusFile(p)


# ====================================================================== ROS bag pixels
def _bag_with_images(path: Path, images: list[np.ndarray], dtype_code: int, topic: str = "/sonar/image") -> None:
    """A ROS 1 bag whose messages carry ``images`` raw (any dtype code), no geometry side channel."""
    from rosbags.rosbag1 import Writer

    store = typestore(1)
    g = preset("didson-hf").replace(range_m=np.arange(images[0].shape[0]) * 0.1 + 1.0)
    base = Ping(np.zeros(g.shape, np.float32), g, 1_600_000_000 * 10**9)
    with Writer(path) as w:
        c = w.add_connection(topic, MSGTYPE, typestore=store)
        for i, img in enumerate(images):
            msg = rosbag._encode(base.replace(time_ns=base.time_ns + i), store, 1, "sonar", "float32", i)
            msg.image.dtype = dtype_code
            msg.image.data = np.frombuffer(np.ascontiguousarray(img).tobytes(), np.uint8)
            w.write(c, base.time_ns + i, bytes(store.serialize_ros1(msg, MSGTYPE)))


@pytest.mark.parametrize("bad", [-9e35, 1e30, 5.0, -0.01, 1.001])
def test_bag_float_pixels_out_of_range(tmp_path: Path, bad: float) -> None:
    g = preset("didson-hf").replace(range_m=np.arange(20) * 0.1 + 1.0)
    imgs = [np.full(g.shape, 0.5, np.float32) for _ in range(3)]
    imgs[1][3, 4] = bad
    path = tmp_path / "f.bag"
    write_bag([Ping(im, g, 1_600_000_000 * 10**9 + i) for i, im in enumerate(imgs)], path, version=1)
    it = rosbag.iter_bag_pings(path)
    assert np.all(next(it).image == 0.5)
    with pytest.raises(DataFormatError, match=r"f\.bag: message 1 on /sonar/image: float32 pixels lie in .* outside the \[0, 1\]"):
        next(it)


@pytest.mark.parametrize(("dtype", "code"), [("<f4", 8), ("<f8", 9)])
def test_bag_float_pixels_non_finite_and_tolerance(tmp_path: Path, dtype: str, code: int) -> None:
    ok = np.full((20, 96), 0.25, dtype)
    ok[0, 0], ok[0, 1] = 1.0 + 1e-7, -1e-7  # rounding in a producer: clipped
    for bad in (np.nan, np.inf, -np.inf):
        img = ok.copy()
        img[5, 5] = bad
        p = tmp_path / "nf.bag"
        p.unlink(missing_ok=True)
        _bag_with_images(p, [ok, img], code, topic="/a/b")
        pings = rosbag.iter_bag_pings(p)
        first = next(pings)
        assert first.image.dtype == np.float32 and first.image.min() == 0.0 and first.image.max() == 1.0
        with pytest.raises(DataFormatError, match=r"nf\.bag: message 1 on /a/b: float\d\d image contains NaN or infinite"):
            next(pings)


@pytest.mark.parametrize(
    ("dtype", "code", "scale"),
    [("<u2", 2, 65535.0), ("<i2", 3, 32767.0), ("<u4", 4, 2**32 - 1.0), ("i1", 1, 127.0), ("<i4", 5, 2**31 - 1.0)],
)
def test_bag_integer_encodings_scale(tmp_path: Path, dtype: str, code: int, scale: float) -> None:
    info = np.iinfo(np.dtype(dtype))
    img = np.zeros((20, 96), dtype)
    img[0, :3] = [0, info.max // 2, info.max]
    p = tmp_path / "i.bag"
    _bag_with_images(p, [img], code)
    (ping,) = rosbag.iter_bag_pings(p)
    assert ping.image[0, :3].tolist() == pytest.approx([0.0, (info.max // 2) / scale, 1.0], rel=1e-6)
    assert 0.0 <= ping.image.min() and ping.image.max() <= 1.0
    if info.min < 0:
        img[7, 7] = -5
        p.unlink()
        _bag_with_images(p, [img], code)
        with pytest.raises(DataFormatError, match=rf"message 0 on /sonar/image: {np.dtype(dtype).name} image has negative samples \(min -5\)"):
            list(rosbag.iter_bag_pings(p))


def test_bag_header_stamp_checked(tmp_path: Path) -> None:
    from rosbags.rosbag1 import Writer

    store = typestore(1)
    g = preset("didson-hf").replace(range_m=np.arange(20) * 0.1 + 1.0)
    msg = rosbag._encode(Ping(np.zeros(g.shape, np.float32), g, 0), store, 1, "sonar", "float32", 0)
    msg.header.stamp.nanosec = 2_000_000_000
    p = tmp_path / "s.bag"
    with Writer(p) as w:
        c = w.add_connection("/s", MSGTYPE, typestore=store)
        w.write(c, 1, bytes(store.serialize_ros1(msg, MSGTYPE)))
    with pytest.raises(DataFormatError, match="message 0 on /s: header stamp nanosec 2000000000"):
        list(rosbag.iter_bag_pings(p))


# ====================================================================== FIFOs and devices
_SPECIAL_FILES_SCRIPT = textwrap.dedent(
    """
    import json, os, sys, warnings
    from pathlib import Path
    from sonarmap.errors import SonarmapError
    from sonarmap.io import aris, ddf, oculus, read_pings, rosbag
    from sonarmap.io._binary import map_file

    d = Path(sys.argv[1])
    calls = {
        "aris": lambda p: list(aris.ArisFile(p)), "oculus": lambda p: list(oculus.OculusFile(p)),
        "ddf": lambda p: list(ddf.DdfFile(p)), "bag": lambda p: list(rosbag.iter_bag_pings(p)),
        "read_pings": lambda p: list(read_pings(p)), "map_file": lambda p: map_file(p),
        "count": lambda p: {"aris": aris, "oculus": oculus, "ddf": ddf, "bag": rosbag}[p.suffix[1:]].count_pings(p),
        "summary": lambda p: {"aris": aris, "oculus": oculus, "ddf": ddf, "bag": rosbag}[p.suffix[1:]].summary(p),
    }
    cases = []
    for kind in ("fifo", "zero"):
        for ext in ("aris", "oculus", "ddf", "bag"):
            p = d / f"{kind}.{ext}"
            for name in ({"aris": "aris", "oculus": "oculus", "ddf": "ddf", "bag": "bag"}[ext],
                         "read_pings", "map_file", "count", "summary"):
                cases.append((name, p))
    cases.append(("bag", d / "ros2_fifo"))
    cases.append(("read_pings", d / "ros2_fifo"))
    warnings.simplefilter("ignore")
    for name, p in cases:
        try:
            calls[name](p)
            out = "no error"
        except SonarmapError as exc:
            out = "SonarmapError: " + str(exc)
        except BaseException as exc:
            out = "FOREIGN " + type(exc).__name__ + ": " + str(exc)
        print(json.dumps([name, p.name, out]), flush=True)
    print("DONE", flush=True)
    """
)


@pytest.mark.skipif(not hasattr(os, "mkfifo") or not os.path.exists("/dev/zero"), reason="needs FIFOs and /dev/zero")
@pytest.mark.slow
def test_fifos_and_device_symlinks_are_refused_without_hanging(tmp_path: Path) -> None:
    for ext in ("aris", "oculus", "ddf", "bag"):
        os.mkfifo(tmp_path / f"fifo.{ext}")
        (tmp_path / f"zero.{ext}").symlink_to("/dev/zero")
    ros2 = tmp_path / "ros2_fifo"
    ros2.mkdir()
    os.mkfifo(ros2 / "metadata.yaml")
    script = tmp_path / "special.py"
    script.write_text(_SPECIAL_FILES_SCRIPT)
    try:
        proc = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True, text=True,
                              timeout=60, check=False)
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"a reader hung on a FIFO or device; output so far: {exc.stdout!r}")
    lines = proc.stdout.splitlines()
    assert lines and lines[-1] == "DONE", proc.stderr[-2000:]
    results = [json.loads(line) for line in lines[:-1]]
    assert len(results) == 42
    for name, file, out in results:
        assert out.startswith("SonarmapError: "), (name, file, out)
        assert file in out, (name, file, out)
    direct = [out for name, file, out in results if name in ("aris", "oculus", "ddf", "bag", "map_file")]
    assert all("FIFO" in o or "character device" in o for o in direct), direct


def test_map_file_refuses_special_files(tmp_path: Path) -> None:
    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs")
    f = tmp_path / "x.aris"
    os.mkfifo(f)
    with pytest.raises(DataFormatError, match=r"x\.aris: .*FIFO"):
        map_file(f)
    d = tmp_path / "dir.aris"
    d.mkdir()
    with pytest.raises(DataFormatError, match="directory"):
        map_file(d)
    r = tmp_path / "r.aris"
    r.write_bytes(b"abc")
    assert isinstance(map_file(r), np.memmap) and bytes(map_file(r)) == b"abc"
    r.write_bytes(b"")
    assert map_file(r).size == 0


# ====================================================================== seeded mini-fuzz

#: 2200-01-01T00:00:00Z in ns: the readers accept ping times 0 (unknown) or 1970-2200.
_YEAR_2200_NS = 7_258_118_400 * 10**9


def _ping_problem(ping: Any) -> str | None:
    """Why ``ping`` is not a valid raw ping from a plausible header, or None.

    Beyond the basic contract (finite float32 image in [0, 1] of the geometry's shape, finite
    geometry, int64 time) the readers promise plausible headers: a window within 1 km and a time
    of 0 or in the years 1970-2200.
    """
    if not isinstance(ping, Ping):
        return f"not a Ping: {type(ping).__name__}"
    img, g = ping.image, ping.geometry
    if img.dtype != np.float32 or img.shape != g.shape:
        return f"image {img.dtype} {img.shape} vs geometry {g.shape}"
    if not np.all(np.isfinite(img)) or img.min() < 0 or img.max() > 1:
        return f"image values outside [0, 1]: {img.min()}..{img.max()}"
    if not (np.all(np.isfinite(g.range_m)) and np.all(np.isfinite(g.azimuth_rad))):
        return "geometry has non-finite ranges/azimuths"
    for field in ("sound_speed_m_s", "frequency_hz", "rx_gain_db", "noise", "fov_rad"):
        if not math.isfinite(float(getattr(g, field))):
            return f"geometry {field} is {getattr(g, field)}"
    if not isinstance(ping.time_ns, int) or not -(2**63) <= ping.time_ns <= INT64_MAX:
        return f"time_ns {ping.time_ns!r}"
    if g.range_m[-1] > 1000.0:
        return f"implausible window reaching {g.range_m[-1]:.4g} m"
    if not 0 <= ping.time_ns <= _YEAR_2200_NS:
        return f"implausible time {ping.time_ns} ns"
    return None


def _exercise(path: Path, opener: Callable[[Path], Any], module: Any) -> str | None:
    """Read every ping, then the summary and count; None if all fine or a SonarmapError was raised."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            with opener(path) as f:
                for ping in f:
                    problem = _ping_problem(ping)
                    if problem:
                        return problem
            module.count_pings(path)
            module.summary(path)
        except SonarmapError:
            return None
        except Hang:
            raise
        except Exception as exc:  # noqa: BLE001 - that is what the fuzz looks for
            return f"{type(exc).__name__}: {exc}"
    return None


_EXTREME_INTS = {
    "u": lambda bits: [0, 2**bits - 1, 2 ** (bits - 1) - 1, 2 ** (bits - 1), 1],
    "i": lambda bits: [0, -1, -(2 ** (bits - 1)), 2 ** (bits - 1) - 1, -5],
}
_EXTREME_FLOATS = [float("nan"), float("inf"), float("-inf"), -1.0, 0.0, 1e30, -9e35, 5.0, 3.4e38, 1e-30]


def _extremes(kind: str, size: int) -> list[float | int]:
    if kind == "f":
        return _EXTREME_FLOATS
    return _EXTREME_INTS[kind](8 * size)


def _numeric_fields(dtype: np.dtype) -> list[tuple[str, int, np.dtype]]:
    """(name, offset, scalar dtype) of a structured dtype's numeric fields (sub-arrays: first element)."""
    out = []
    for name in dtype.names or ():
        sub, off = dtype.fields[name][:2]
        base = sub.base if sub.subdtype else sub
        if base.kind in "uif":
            out.append((name, off, base))
    return out


def _struct_fields(fmt: str, base: int) -> list[tuple[str, int, np.dtype]]:
    """(index, offset, dtype) of every field of a little-endian ``struct`` format."""
    codes = {"B": "u1", "H": "<u2", "I": "<u4", "Q": "<u8", "b": "i1", "h": "<i2", "i": "<i4",
             "q": "<i8", "f": "<f4", "d": "<f8"}
    out, off, body, i = [], base, fmt.lstrip("<"), 0
    while i < len(body):
        j = i
        while body[j].isdigit():
            j += 1
        count, code = int(body[i:j] or 1), body[j]
        i = j + 1
        if code in "xs":
            off += count
            continue
        for _ in range(count):
            out.append((f"{code}@{off}", off, np.dtype(codes[code])))
            off += struct.calcsize("<" + code)
    return out


def _set(data: bytearray, off: int, dt: np.dtype, value: float | int) -> None:
    if off + dt.itemsize <= len(data):
        data[off : off + dt.itemsize] = np.array(value).astype(dt).tobytes() if dt.kind == "f" else \
            int(value).to_bytes(dt.itemsize, "little", signed=dt.kind == "i")


def _mutate(
    rng: np.random.Generator, data: bytes, fields: list[tuple[str, int, np.dtype]], hot: int,
    key: tuple[str, ...] = (),
) -> tuple[str, bytes]:
    """One fuzz case: a header field set to an extreme value, bit flips, or a truncation.

    A field mutation sets 1-3 fields; each is, with probability 0.6, one whose name is in ``key``
    (the fields that drive geometry, sizes and time), else any numeric field.
    """
    buf = bytearray(data)
    mode = rng.choice(["field", "field", "flip", "cut"] if fields else ["flip", "flip", "cut"])
    if mode == "field":
        keyed = [f for f in fields if f[0].rsplit(".", 1)[-1] in key]
        done = []
        for _ in range(int(rng.integers(1, 4))):
            pool = keyed if keyed and rng.random() < 0.6 else fields
            name, off, dt = pool[int(rng.integers(len(pool)))]
            vals = _extremes(dt.kind, dt.itemsize)
            v = vals[int(rng.integers(len(vals)))]
            _set(buf, off, dt, v)
            done.append(f"{name}={v}")
        return ", ".join(done), bytes(buf)
    if mode == "flip":
        flips = []
        for _ in range(int(rng.integers(1, 9))):
            pos = int(rng.integers(hot)) if rng.random() < 0.7 else int(rng.integers(len(buf)))
            bit = int(rng.integers(8))
            buf[pos] ^= 1 << bit
            flips.append((pos, bit))
        return f"flips {flips}", bytes(buf)
    cut = int(rng.integers(len(buf) + 1))
    return f"cut at {cut}", bytes(buf[:cut])


def _run_fuzz(cases: Iterator[tuple[str, Path]], opener: Callable[[Path], Any], module: Any) -> tuple[int, list[str]]:
    bad, n = [], 0
    for desc, path in cases:
        n += 1
        t0 = time.perf_counter()
        try:
            with deadline(10.0):
                problem = _exercise(path, opener, module)
        except Hang as exc:
            problem = str(exc)
        dt = time.perf_counter() - t0
        if problem is None and dt > 5.0:
            problem = f"slow: {dt:.1f} s"
        if problem:
            bad.append(f"{desc}: {problem}")
    return n, bad


N_CASES = 200
_ARIS_KEY = ("SamplePeriod", "SampleStartDelay", "SoundSpeed", "SamplesPerBeam", "PingMode", "FrameTime",
             "sonarTimeStamp", "FrameRate", "WindowStart", "WindowLength", "ReceiverGain", "TheSystemType",
             "LargeLens", "FrequencyHiLow", "ReorderedSamples", "SonarX", "SonarY", "SonarZ", "Heading")
_DDF_KEY = ("numbeams", "samplesperchannel", "resolution", "reverse", "serialnumber", "framerate", "year",
            "month", "day", "hour", "minute", "second", "hsecond", "frametime", "frametime2", "windowstart",
            "windowlength", "configflags", "receivergain")


def test_fuzz_aris(sample_aris: bytes, tmp_path: Path) -> None:
    fields = [(f"file.{n}", o, d) for n, o, d in _numeric_fields(FILE_HEADER_DTYPE)]
    frame = FRAME_HEADER_SIZE + 48 * 2000
    for k in (0, 1, 5):
        fields += [(f"frame{k}.{n}", FILE_HEADER_SIZE + k * frame + o, d) for n, o, d in _numeric_fields(FRAME_HEADER_DTYPE)]
    rng = np.random.default_rng(20240601)
    p = tmp_path / "fuzz.aris"

    def cases() -> Iterator[tuple[str, Path]]:
        for _ in range(N_CASES):
            desc, data = _mutate(rng, sample_aris, fields, FILE_HEADER_SIZE + FRAME_HEADER_SIZE, _ARIS_KEY)
            p.write_bytes(data)
            yield desc, p

    n, bad = _run_fuzz(cases(), ArisFile, aris)
    assert n == N_CASES and not bad, "\n".join(bad[:20])


def test_fuzz_oculus_raw(oculus_raw: bytes, tmp_path: Path) -> None:
    fields = []
    for k, base in enumerate((0, 182016, 364032)):
        for fmt, off in ((HEADER.format, 0), (FIRE_V1.format, HEADER.size), (PING_V1.format, _V1_PING)):
            fields += [(f"msg{k}.{n}", base + o, d) for n, o, d in _struct_fields(fmt, off)]
    rng = np.random.default_rng(20240602)
    p = tmp_path / "fuzz.raw"

    def cases() -> Iterator[tuple[str, Path]]:
        for _ in range(N_CASES):
            desc, data = _mutate(rng, oculus_raw, fields, 2048 + 512)
            p.write_bytes(data)
            yield desc, p

    n, bad = _run_fuzz(cases(), OculusFile, oculus)
    assert n == N_CASES and not bad, "\n".join(bad[:20])


def _message_fields(version: int) -> list[tuple[str, int, np.dtype]]:
    parts: list[tuple[str, int]] = [(HEADER.format, 0), (FIRE_V1.format, HEADER.size)]
    if version == 2:
        parts += [(FIRE_V2_EXTRA.format, _V1_PING), (PING_V2.format, _V1_PING + FIRE_V2_EXTRA.size)]
    else:
        parts += [(PING_V1.format, _V1_PING)]
    return [f for fmt, off in parts for f in _struct_fields(fmt, off)]


@pytest.mark.slow  # over a second in the fast subset
def test_fuzz_viewpoint_logs(tmp_path: Path) -> None:
    rng = np.random.default_rng(20240603)
    img_rng = np.random.default_rng(7)
    msgs = [encode_ping(img_rng.integers(0, 256, (24, 16), dtype=np.uint8), BEARINGS, version=v, ping_id=i,
                        gain=np.linspace(1, 2, 24) if v == 2 else None) for i, v in enumerate((1, 2))]
    mfields = {1: _message_fields(1), 2: _message_fields(2)}
    times = [1.6e9, 1.6e9 + 0.25]
    ref = tmp_path / "ref.oculus"
    containers = {}
    for kind in ("v1", "v1z", "v2"):
        if kind == "v2":
            write_log_v2(ref, msgs, times)
        else:
            write_log_v1(ref, msgs, times, compress=kind == "v1z")
        containers[kind] = ref.read_bytes()
        ref.unlink()
    # item and file header fields of the v1 log (offsets found by walking the items)
    log = containers["v1"]
    lfields = [(f"loghdr.{n}", o, d) for n, o, d in _struct_fields(LOG_HEADER.format, 0)]
    o = LOG_HEADER.size
    while o < len(log):
        lfields += [(f"item@{o}.{n}", o2, d) for n, o2, d in _struct_fields(LOG_ITEM.format, o)]
        o += LOG_ITEM.size + struct.unpack_from("<I", log, o + 36)[0]
    extreme_times: list[Any] = [1e30, -1.0, float("nan"), float("inf"), 2.0**63, 9.3e18, 0, 2**62, "x", b"\x00", None]
    counter = iter(range(10**6))

    def cases() -> Iterator[tuple[str, Path]]:
        for _ in range(N_CASES):
            p = tmp_path / f"fuzz{next(counter)}.oculus"
            kind = str(rng.choice(["v1", "v1z", "v2"]))
            what = rng.choice(["container", "message", "time"] if kind == "v2" else ["container", "message"])
            if what == "container":
                desc, data = _mutate(rng, containers[kind], lfields if kind != "v2" else [], 400)
                p.write_bytes(data)
            elif what == "message":
                k = int(rng.integers(2))
                desc, m = _mutate(rng, msgs[k], mfields[k + 1], 250)
                ms = [m if i == k else msgs[i] for i in range(2)]
                if kind == "v2":
                    write_log_v2(p, ms, times)
                else:
                    write_log_v1(p, ms, times, compress=kind == "v1z")
                desc = f"message {k}: {desc}"
            else:
                t = extreme_times[int(rng.integers(len(extreme_times)))]
                write_log_v2(p, msgs, times)
                con = sqlite3.connect(p)
                with con:
                    con.execute("UPDATE data SET timestamp = ? WHERE entryId = 3", (t,))
                con.close()
                desc = f"timestamp={t!r}"
            yield f"{kind} {desc}", p
            p.unlink()

    n, bad = _run_fuzz(cases(), OculusFile, oculus)
    assert n == N_CASES and not bad, "\n".join(bad[:20])


def test_fuzz_ddf(tmp_path: Path) -> None:
    rng = np.random.default_rng(20240604)
    img_rng = np.random.default_rng(8)
    srcs = {}
    for version in (3, 4):
        p = tmp_path / "src.ddf"
        write_ddf(p, [img_rng.integers(0, 256, (24, 96), dtype=np.uint8) for _ in range(3)], version=version)
        srcs[version] = p.read_bytes()
    fields: dict[int, list[tuple[str, int, np.dtype]]] = {}
    for version in (3, 4):
        fdt, hdt = FILE_HEADER_DTYPES[version], FRAME_HEADER_DTYPES[version]
        fsize = hdt.itemsize + 96 * 24
        fields[version] = [(f"file.{n}", o, d) for n, o, d in _numeric_fields(fdt)]
        for k in (0, 2):
            fields[version] += [(f"frame{k}.{n}", fdt.itemsize + k * fsize + o, d) for n, o, d in _numeric_fields(hdt)]
    p = tmp_path / "fuzz.ddf"

    def cases() -> Iterator[tuple[str, Path]]:
        for _ in range(N_CASES):
            version = int(rng.choice([3, 4]))
            fdt, hdt = FILE_HEADER_DTYPES[version], FRAME_HEADER_DTYPES[version]
            desc, data = _mutate(rng, srcs[version], fields[version], fdt.itemsize + hdt.itemsize, _DDF_KEY)
            p.write_bytes(data)
            yield f"DDF_0{version} {desc}", p

    n, bad = _run_fuzz(cases(), DdfFile, ddf)
    assert n == N_CASES and not bad, "\n".join(bad[:20])
