"""DIDSON DDF_03/DDF_04 reader, tested on files from the test-only writer (no public sample exists)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from ddf_writer import write_ddf
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sonarmap.errors import DataFormatError, SonarmapWarning
from sonarmap.geometry import GeometryWarning, preset
from sonarmap.io import ddf, detect_format, read_pings
from sonarmap.io._binary import PartialFrameWarning
from sonarmap.io.ddf import DdfFile, window_m


def _frames(n: int = 3, beams: int = 96, samples: int = 512, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (samples, beams), dtype=np.uint8) for _ in range(n)]


@pytest.mark.parametrize("version", [3, 4])
def test_round_trip(tmp_path: Path, version: int) -> None:
    frames = _frames()
    p = tmp_path / "a.ddf"
    times = write_ddf(p, frames, version=version, window_start_code=6, window_length_code=3)
    assert detect_format(p) == "ddf"
    pings = list(read_pings(p))
    assert len(pings) == 3 == ddf.count_pings(p)
    for ping, frame, t in zip(pings, frames, times, strict=True):
        # lossless: 8-bit counts come back exactly, beam 0 (right-most) in the last column
        assert np.array_equal(np.rint(ping.image * 255).astype(np.uint8), frame[:, ::-1])
        assert ping.time_ns == t
    g = pings[0].geometry
    # the paper's DIDSON window: code 6 x 0.375 m = 2.25 m, classic HF length code 3 = 9 m
    assert (g.min_range_m, g.max_range_m) == (2.25, 11.25)
    assert g.range_m[1] - g.range_m[0] == pytest.approx(9 / 512)
    assert np.array_equal(g.azimuth_rad, preset("didson-hf").azimuth_rad)
    assert pings[0].meta["heading_deg"] == 12.5 and pings[0].meta["ddf_version"] == version
    s = ddf.summary(p)
    assert s["pings"] == 3 and s["ddf_version"] == version and s["duration_s"] == pytest.approx(0.2)


def test_reverse_mount_not_flipped(tmp_path: Path) -> None:
    frames = _frames(1)
    p = tmp_path / "r.ddf"
    write_ddf(p, frames, reverse=1)
    assert np.array_equal(np.rint(next(read_pings(p)).image * 255).astype(np.uint8), frames[0])


def test_window_codes() -> None:
    assert window_m(6, 3, high_frequency=True, config=1) == (2.25, 9.0)
    assert window_m(6, 3, high_frequency=False, config=1) == (4.5, 36.0)  # LF: doubled start, +2 index
    assert window_m(4, 0, high_frequency=True, config=0) == pytest.approx((4 * 0.419, 1.25))
    assert window_m(1, 3, high_frequency=False, config=3) == (0.75, 72.0)
    with pytest.raises(ValueError):
        window_m(32, 0, high_frequency=True, config=1)
    with pytest.raises(ValueError):
        window_m(0, 4, high_frequency=True, config=1)


def test_low_frequency_uniform_with_warning(tmp_path: Path) -> None:
    p = tmp_path / "lf.ddf"
    write_ddf(p, _frames(2, beams=48), high_frequency=False, version=3, serial_number=500,
              configflags=0, window_start_code=2, window_length_code=1)
    with pytest.warns(GeometryWarning, match="uniform"):
        g = DdfFile(p).geometry(0)
    assert g.n_beams == 48 and g.frequency_hz == 1.1e6
    assert g.min_range_m == pytest.approx(2 * 0.838) and g.max_range_m == pytest.approx(2 * 0.838 + 10.0)


def test_corruption(tmp_path: Path) -> None:
    p = tmp_path / "c.ddf"
    write_ddf(p, _frames(2))
    data = p.read_bytes()
    p.write_bytes(data[:300])
    with pytest.raises(DataFormatError, match="at byte 300: truncated DDF_04"):
        DdfFile(p)
    p.write_bytes(b"DDF\x07" + data[4:])
    with pytest.raises(DataFormatError, match="at byte 0: not a DIDSON"):
        DdfFile(p)
    p.write_bytes(data[:-10])
    with pytest.warns(PartialFrameWarning):
        assert len(DdfFile(p)) == 1
    bad = bytearray(data)
    off = 1024 + ddf.FRAME_HEADER_DTYPES[4].fields["windowlength"][1]
    bad[off : off + 4] = (9).to_bytes(4, "little")
    p.write_bytes(bytes(bad))
    with pytest.raises(DataFormatError, match="at byte 1024: inconsistent frame header 0: window length code 9"):
        DdfFile(p)[0]
    bad = bytearray(data)
    bad[16:20] = (0).to_bytes(4, "little")  # numbeams
    p.write_bytes(bytes(bad))
    with pytest.raises(DataFormatError, match="numbeams 0"):
        DdfFile(p)


@pytest.fixture(scope="module")
def small_ddf(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    p = tmp_path_factory.mktemp("ddf") / "s.ddf"
    write_ddf(p, _frames(2, samples=16), version=3)
    return p.read_bytes()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, 2**31), st.integers(0, 255)), min_size=1, max_size=8),
       cut=st.one_of(st.none(), st.integers(0, 2**31)))
def test_fuzz_byte_flips(small_ddf: bytes, tmp_path: Path, flips: list[tuple[int, int]], cut: int | None) -> None:
    data = bytearray(small_ddf)
    for pos, val in flips:
        data[pos % (512 + 256) if pos % 3 else pos % len(data)] = val
    if cut is not None:
        data = data[: cut % (len(data) + 1)]
    p = tmp_path / "fuzz.ddf"
    p.write_bytes(bytes(data))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SonarmapWarning)
        try:
            for ping in read_pings(p):
                assert ping.image.dtype == np.float32
            ddf.summary(p)
        except DataFormatError as exc:
            assert str(p) in str(exc)
