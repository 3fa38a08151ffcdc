"""ARIS reader: the real SoundMetrics sample, layout facts, lazy access and corruption handling."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sonarmap.errors import DataFormatError, SonarmapWarning
from sonarmap.geometry import preset
from sonarmap.io import aris, detect_format, read_pings
from sonarmap.io._binary import PartialFrameWarning
from sonarmap.io.aris import FILE_HEADER_SIZE, FRAME_HEADER_DTYPE, FRAME_HEADER_SIZE, ArisFile


@pytest.fixture(scope="module")
def sample(data_dir: Path) -> Path:
    return data_dir / "aris" / "sample.aris"


def test_sample_acceptance(sample: Path) -> None:
    with ArisFile(sample) as f:
        assert len(f) == 6
        p = f[0]
        g = p.geometry
        assert p.shape == (2000, 48) and p.image.dtype == np.float32
        assert g.range_m[0] == pytest.approx(3.2976, abs=1e-3)
        assert g.range_m[-1] == pytest.approx(23.39, abs=0.01)
        assert g.sound_speed_m_s == pytest.approx(1435.93, abs=0.01)
        assert str(p.datetime64).startswith("2013-06-14T08:21:19")
        assert g.name == "aris-telephoto-48" and g.frequency_hz == 1.2e6
        # range of sample i = (SampleStartDelay + i * SamplePeriod) * 1e-6 * c / 2
        h = f.frame_header(0)
        c = float(h["SoundSpeed"])
        assert g.range_m[10] == pytest.approx((h["SampleStartDelay"] + 10 * h["SamplePeriod"]) * 1e-6 * c / 2, rel=1e-9)
        assert h["PingMode"] == 1 and h["LargeLens"] == 1 and h["TheSystemType"] == 2
        assert p.meta["compass_heading_deg"] == pytest.approx(49.6, abs=1e-3)
        assert p.pose is None  # no SonarX/Y/Z in this recording
        times = [f[i].time_ns for i in range(len(f))]
        assert np.all(np.diff(times) > 0)


def test_beam_axis_is_flipped(sample: Path) -> None:
    """Beam 0 (stored first) is the right-most beam: it must land in the last column."""
    with ArisFile(sample) as f:
        raw = f.raw_samples(2)
        img = f[2].image
        assert np.array_equal(np.rint(img * 255).astype(np.uint8), raw[:, ::-1])
        assert img[:, -1].tolist() == (raw[:, 0] / np.float32(255)).astype(np.float32).tolist() or np.allclose(img[:, -1], raw[:, 0] / 255.0)
        az = f[2].geometry.azimuth_rad
        assert az[0] < 0 < az[-1]  # column 0 is port, last column starboard
        # the vendor table's beam 0 (angle -7.339 deg, right-most) is our last column (+7.339 deg)
        assert np.rad2deg(az[-1]) == pytest.approx(7.339, abs=1e-3)


def test_lazy_access_and_negative_index(sample: Path) -> None:
    with ArisFile(sample) as f:
        assert np.array_equal(f[-1].image, f[5].image)
        assert f.frame_offset(1) == FILE_HEADER_SIZE + f.frame_size
        with pytest.raises(IndexError):
            f[6]
        assert isinstance(f._mm, np.memmap)


def test_registry_and_summary(sample: Path) -> None:
    assert detect_format(sample) == "aris"
    assert aris.count_pings(sample) == 6
    s = aris.summary(sample)
    assert s["pings"] == 6 and s["lens"] == "telephoto" and s["system"] == "ARIS 1200"
    assert s["time_first_utc"].startswith("2013-06-14T08:21:19")
    pings = list(read_pings(sample))
    assert len(pings) == 6 and pings[3].source.endswith("#3")


@pytest.mark.parametrize(
    ("system", "lens", "beams", "name"),
    [(2, True, 48, "aris-telephoto-48"), (0, True, 96, "aris-telephoto-96"), (0, False, 96, "aris1800-96"),
     (2, False, 48, "aris1800-48"), (1, False, 128, "aris3000-128"), (1, False, 64, "aris3000-64")],
)
def test_preset_choice(system: int, lens: bool, beams: int, name: str) -> None:
    assert aris.aris_preset_name(system, lens, beams) == name
    assert preset(name).n_beams == beams


def test_ping_modes() -> None:
    assert [aris.beams_from_ping_mode(m) for m in (1, 3, 6, 9, 12)] == [48, 96, 64, 128, 128]
    with pytest.raises(ValueError):
        aris.beams_from_ping_mode(13)


# ---------------------------------------------------------------------- corruption
def _small_aris(sample: Path, out: Path, *, n_frames: int = 3, samples: int = 40) -> bytes:
    """A small valid ARIS file built from the sample's headers (fewer samples per beam)."""
    raw = sample.read_bytes()
    parts = [raw[:FILE_HEADER_SIZE]]
    big = FRAME_HEADER_SIZE + 48 * 2000
    for i in range(n_frames):
        off = FILE_HEADER_SIZE + i * big
        h = np.frombuffer(raw[off : off + FRAME_HEADER_SIZE], FRAME_HEADER_DTYPE).copy()
        h["SamplesPerBeam"] = samples
        parts.append(h.tobytes())
        parts.append(raw[off + FRAME_HEADER_SIZE : off + FRAME_HEADER_SIZE + 48 * samples])
    data = b"".join(parts)
    out.write_bytes(data)
    return data


def test_truncated_and_bad_magic(sample: Path, tmp_path: Path) -> None:
    p = tmp_path / "t.aris"
    p.write_bytes(sample.read_bytes()[:500])
    with pytest.raises(DataFormatError, match=r"t\.aris: at byte 500: truncated"):
        ArisFile(p)
    data = bytearray(sample.read_bytes())
    data[:4] = b"XXXX"
    p.write_bytes(bytes(data))
    with pytest.raises(DataFormatError, match="at byte 0: not an ARIS file"):
        ArisFile(p)


def test_partial_last_frame_is_skipped_with_warning(sample: Path, tmp_path: Path) -> None:
    p = tmp_path / "p.aris"
    p.write_bytes(sample.read_bytes()[:-1000])
    with pytest.warns(PartialFrameWarning, match="last frame is incomplete"):
        f = ArisFile(p)
    assert len(f) == 5
    assert np.array_equal(f[4].image, ArisFile(sample)[4].image)


def test_header_disagreeing_with_file(sample: Path, tmp_path: Path) -> None:
    data = bytearray(_small_aris(sample, tmp_path / "s.aris"))
    # frame 1 claims another ping mode: sizes disagree with frame 0
    off = FILE_HEADER_SIZE + (FRAME_HEADER_SIZE + 48 * 40) + FRAME_HEADER_DTYPE.fields["PingMode"][1]
    data[off : off + 4] = (3).to_bytes(4, "little")
    p = tmp_path / "bad.aris"
    p.write_bytes(bytes(data))
    f = ArisFile(p)
    f[0]
    with pytest.raises(DataFormatError, match=f"at byte {FILE_HEADER_SIZE + FRAME_HEADER_SIZE + 48 * 40}: .*frame size changes"):
        f[1]
    # an invalid sound speed in frame 0 is a format error, not a GeometryError
    data = bytearray(_small_aris(sample, tmp_path / "s.aris"))
    off = FILE_HEADER_SIZE + FRAME_HEADER_DTYPE.fields["SoundSpeed"][1]
    data[off : off + 4] = np.float32(np.nan).tobytes()
    p.write_bytes(bytes(data))
    with pytest.raises(DataFormatError, match="SoundSpeed"):
        ArisFile(p)[0]


@pytest.fixture(scope="module")
def small_aris(sample: Path, tmp_path_factory: pytest.TempPathFactory) -> bytes:
    return _small_aris(sample, tmp_path_factory.mktemp("aris") / "small.aris")


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, 2**31), st.integers(0, 255)), min_size=1, max_size=8),
       cut=st.one_of(st.none(), st.integers(0, 2**31)))
def test_fuzz_byte_flips_only_raise_data_format_error(small_aris: bytes, tmp_path: Path, flips: list[tuple[int, int]], cut: int | None) -> None:
    data = bytearray(small_aris)
    for pos, val in flips:
        # bias towards the headers, where the structure lives
        pos = pos % (FILE_HEADER_SIZE + FRAME_HEADER_SIZE) if pos % 3 else pos % len(data)
        data[pos] = val
    if cut is not None:
        data = data[: cut % (len(data) + 1)]
    p = tmp_path / "fuzz.aris"
    p.write_bytes(bytes(data))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SonarmapWarning)
        try:
            for ping in read_pings(p):
                assert ping.image.dtype == np.float32
            aris.summary(p)
        except DataFormatError as exc:
            assert str(p) in str(exc)


def test_pose_from_sonar_position(sample: Path, tmp_path: Path) -> None:
    data = bytearray(_small_aris(sample, tmp_path / "s.aris", n_frames=1))
    h = np.frombuffer(bytes(data[FILE_HEADER_SIZE : FILE_HEADER_SIZE + FRAME_HEADER_SIZE]), FRAME_HEADER_DTYPE).copy()
    h["SonarX"], h["SonarY"], h["SonarZ"], h["Heading"] = 10.0, -2.0, 3.5, 90.0
    data[FILE_HEADER_SIZE : FILE_HEADER_SIZE + FRAME_HEADER_SIZE] = h.tobytes()
    p = tmp_path / "pose.aris"
    p.write_bytes(bytes(data))
    ping = ArisFile(p)[0]
    assert ping.pose is not None and ping.pose.frame == "ned"
    assert ping.pose.position_m.tolist() == [10.0, -2.0, 3.5]
    assert np.allclose(ping.pose.orientation_xyzw, [0, 0, np.sqrt(0.5), np.sqrt(0.5)])  # 90 deg yaw


def test_header_only_file_has_no_frames(sample: Path, tmp_path: Path) -> None:
    p = tmp_path / "empty.aris"
    p.write_bytes(sample.read_bytes()[:FILE_HEADER_SIZE])
    assert len(ArisFile(p)) == 0 and list(read_pings(p)) == []
    assert aris.summary(p)["pings"] == 0
