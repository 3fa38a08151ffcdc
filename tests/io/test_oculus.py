"""Oculus reader: liboculus network captures, v2 messages, gain rows, ViewPoint logs, corruption."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from oculus_writer import encode_ping, write_log_v1, write_log_v2

from sonarmap.errors import DataFormatError, SonarmapWarning
from sonarmap.io import detect_format, oculus, read_pings
from sonarmap.io._binary import PartialFrameWarning
from sonarmap.io.oculus import OculusFile, decode_simple_ping


@pytest.fixture(scope="module")
def oculus_dir(data_dir: Path) -> Path:
    return data_dir / "oculus"


@pytest.mark.parametrize(("name", "n"), [("one_ping_8bit.raw", 1), ("three_pings_8bit.raw", 3)])
def test_liboculus_captures(oculus_dir: Path, name: str, n: int) -> None:
    p = oculus_dir / name
    assert detect_format(p) == "oculus"
    assert oculus.count_pings(p) == n
    pings = list(read_pings(p))
    assert len(pings) == n
    g = pings[0].geometry
    assert pings[0].shape == (703, 256)
    assert np.rad2deg(g.azimuth_rad[0]) == pytest.approx(-30.0) and np.rad2deg(g.azimuth_rad[-1]) == pytest.approx(30.0)
    assert g.range_resolution_m == pytest.approx(0.0028422, abs=1e-7)
    assert g.range_m[0] == 0.0 and g.range_m[-1] == pytest.approx(702 * 0.0028421889710794315)
    assert g.sound_speed_m_s == pytest.approx(1490.66, abs=0.01)
    assert pings[0].meta["message_version"] == 1
    assert [p.meta["ping_id"] for p in pings] == list(range(415323, 415323 + n))
    # bytes at imageOffset are the range-major image
    raw = p.read_bytes()
    img = np.frombuffer(raw, np.uint8, 703 * 256, 2048).reshape(703, 256)
    assert np.array_equal(np.rint(pings[0].image * 255).astype(np.uint8), img)
    s = oculus.summary(p)
    # no clock in the capture: the pings start at the file's modification time, 0.1 s apart
    assert s["pings"] == n and s["container"] == "raw" and s["time_source"] == "file_mtime+order"
    assert s["time_first_utc"] == str(np.datetime64(p.stat().st_mtime_ns, "ns"))


def _image(rng: np.random.Generator, dtype: type = np.uint8, shape: tuple[int, int] = (30, 16)) -> np.ndarray:
    return rng.integers(0, np.iinfo(dtype).max + 1, shape, dtype=dtype)


BEARINGS = np.linspace(-6500, 6500, 16).round().astype(np.int16)


def test_v2_with_gain_and_16bit() -> None:
    rng = np.random.default_rng(1)
    img = _image(rng, np.uint16)
    gain = np.linspace(1, 2, 30).astype(np.float32)
    p = decode_simple_ping(encode_ping(img, BEARINGS, version=2, gain=gain, resolution_m=0.01))
    assert p.meta["message_version"] == 2 and p.meta["heading_deg"] == 10.0
    assert np.array_equal(np.rint(p.image * 65535).astype(np.uint16), img)
    assert np.array_equal(p.meta["row_gain"], gain)
    assert np.allclose(np.rad2deg(p.geometry.azimuth_rad), BEARINGS / 100.0)
    assert p.geometry.range_m[5] == pytest.approx(0.05)
    p8 = decode_simple_ping(encode_ping(_image(rng), BEARINGS, version=1, gain=gain))
    assert "row_gain" in p8.meta and p8.shape == (30, 16)


def test_viewpoint_logs(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    imgs = [_image(rng) for _ in range(3)]
    msgs = [encode_ping(im, BEARINGS, ping_id=i) for i, im in enumerate(imgs)]
    times = [1.6e9 + 0.25 * i for i in range(3)]
    for compress in (False, True):
        p = tmp_path / f"log{int(compress)}.oculus"
        write_log_v1(p, msgs, times, compress=compress)
        assert detect_format(p) == "oculus"
        with OculusFile(p) as f:
            assert f.kind == "log-v1" and len(f) == 3
            assert [x.time_ns for x in f] == [int(t * 1e9) for t in times]
            assert np.array_equal(np.rint(f[2].image * 255).astype(np.uint8), imgs[2])
    p = tmp_path / "v2.oculus"
    write_log_v2(p, msgs, times)
    assert detect_format(p) == "oculus"
    with OculusFile(p) as f:
        assert f.kind == "log-v2" and len(f) == 3
        assert f[1].time_ns == int(times[1] * 1e9)
        assert np.array_equal(np.rint(f[1].image * 255).astype(np.uint8), imgs[1])
    s = oculus.summary(p)
    assert s["pings"] == 3 and s["duration_s"] == pytest.approx(0.5)


def test_bad_id_truncated_and_partial(oculus_dir: Path, tmp_path: Path) -> None:
    data = (oculus_dir / "three_pings_8bit.raw").read_bytes()
    p = tmp_path / "x.raw"
    bad = bytearray(data)
    bad[182016:182018] = b"XX"  # second message's id
    p.write_bytes(bytes(bad))
    with pytest.raises(DataFormatError, match="at byte 182016: bad Oculus message id"):
        OculusFile(p)
    p.write_bytes(data[:-100])
    with pytest.warns(PartialFrameWarning, match="at byte 364032"):
        assert len(OculusFile(p)) == 2
    # sizes inside the message that disagree with the message
    m = bytearray(data[:182016])
    m[16 + 37 + 69 - 8 : 16 + 37 + 69 - 4] = (999).to_bytes(4, "little")  # imageSize
    p.write_bytes(bytes(m))
    with pytest.raises(DataFormatError, match="at byte 0: inconsistent SimplePingResult: imageSize 999"):
        list(read_pings(p))
    p.write_bytes(b"")
    with pytest.raises(DataFormatError):
        OculusFile(p)


@pytest.fixture(scope="module")
def small_stream() -> bytes:
    rng = np.random.default_rng(3)
    return b"".join(encode_ping(_image(rng, shape=(12, 16)), BEARINGS, version=v, gain=np.ones(12) if v == 2 else None)
                    for v in (1, 2, 1))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, 2**31), st.integers(0, 255)), min_size=1, max_size=6),
       cut=st.one_of(st.none(), st.integers(0, 2**31)), container=st.sampled_from(["raw", "log"]))
def test_fuzz_byte_flips(small_stream: bytes, tmp_path: Path, flips: list[tuple[int, int]], cut: int | None, container: str) -> None:
    p = tmp_path / "fuzz.oculus"
    if container == "log":
        n = len(small_stream) // 3
        write_log_v1(p, [small_stream[:n], small_stream[n : 2 * n]], [1e9, 1e9 + 1])
        data = bytearray(p.read_bytes())
    else:
        data = bytearray(small_stream)
    for pos, val in flips:
        data[pos % len(data)] = val
    if cut is not None:
        data = data[: cut % (len(data) + 1)]
    p.write_bytes(bytes(data))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SonarmapWarning)
        try:
            for ping in read_pings(p):
                assert np.all((ping.image >= 0) & (ping.image <= 1))
        except DataFormatError as exc:
            assert str(p) in str(exc)


def test_corrupt_sqlite_log(tmp_path: Path) -> None:
    p = tmp_path / "v2.oculus"
    write_log_v2(p, [encode_ping(_image(np.random.default_rng(5)), BEARINGS)], [1.6e9])
    data = p.read_bytes()
    p.write_bytes(data[:100] + b"\xff" * (len(data) - 100))
    with pytest.raises(DataFormatError, match=r"v2\.oculus"):
        list(read_pings(p))
