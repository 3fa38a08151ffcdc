"""Kongsberg .kmall reader on synthetic files from ``kmall_writer`` (published KMALL layout).

The truth is the writer's spec: beam pointing angles (+60 ... -60 deg, positive to port), int8
amplitudes in 0.5 dB with a seabed echo at a known sample per beam, the MRZ soundings and the
navigation written beside them.
"""

from __future__ import annotations

import math
import struct
import warnings
from pathlib import Path

import kmall_writer as kw
import numpy as np
import pytest

from sonarmap.errors import DataFormatError, SonarmapError
from sonarmap.io import detect_format, read_pings
from sonarmap.io import kmall as km
from sonarmap.io import kongsberg as kb
from sonarmap.io._binary import PartialFrameWarning


def _write(tmp_path: Path, name: str, data: bytes | bytearray) -> Path:
    p = tmp_path / name
    p.write_bytes(bytes(data))
    return p


@pytest.fixture()
def synthetic(tmp_path: Path) -> tuple[Path, kw.KmallSpec]:
    path = tmp_path / "0001_synthetic.kmall"
    return path, kw.write_kmall(path)


def _read(path: Path) -> list:
    with warnings.catch_warnings():
        warnings.simplefilter("error", PartialFrameWarning)
        return list(km.iter_pings(path))


# ---------------------------------------------------------------------- round trip
def test_round_trip_image_angles_and_amplitudes(synthetic: tuple[Path, kw.KmallSpec]) -> None:
    path, spec = synthetic
    pings = _read(path)
    assert km.count_pings(path) == len(pings) == spec.n_pings
    for i, p in enumerate(pings):
        assert p.image.dtype == np.float32 and p.image.shape == (spec.n_samples, spec.n_beams)
        assert p.geometry.shape == p.image.shape
        assert p.time_ns == (kw.T0_S * 10**9 + int(i * spec.ping_interval_s * 1e9))
        assert p.source.endswith(f"#fan0/ping{i}")
        az = np.rad2deg(p.geometry.azimuth_rad)
        assert np.all(np.diff(az) > 0)  # increasing, port (negative) to starboard (positive)
        # angles are positive to port in the file: azimuth = -angle, columns by azimuth
        np.testing.assert_allclose(az, -spec.angles_deg, atol=1e-5)
        np.testing.assert_allclose(p.meta["beam_pointing_angle_deg"], -az, atol=1e-5)
        # dB recovered exactly (the writer's beams are already in azimuth order: +60 ... -60)
        want = spec.amplitude_half_db(i).T * 0.5
        np.testing.assert_array_equal(kb.image_to_db(p.image), want)
        assert p.image.max() == 1.0 and p.image.min() == pytest.approx(10 ** (-127.5 / 10), rel=1e-6)
        step = kw.SOUND_SPEED / (2 * kw.SAMPLE_RATE)
        assert p.meta["range_per_sample_m"] == pytest.approx(step)
        assert p.geometry.range_m[1] - p.geometry.range_m[0] == pytest.approx(step, rel=1e-6)
        assert p.meta["format"] == "kongsberg" and p.meta["file_format"] == "kmall"
        assert p.meta["amplitude_db_full_scale"] == 63.5 and p.meta["em_model"] == 2040


def test_detection_and_soundings_in_meta(synthetic: tuple[Path, kw.KmallSpec]) -> None:
    path, spec = synthetic
    p = _read(path)[1]
    m = p.meta
    np.testing.assert_array_equal(m["detected_range_samples"], spec.seabed_sample)
    np.testing.assert_array_equal(m["detected_bin"], spec.seabed_sample)
    np.testing.assert_allclose(m["detected_range_samples_hires"], spec.seabed_sample + 0.25)
    np.testing.assert_allclose(m["detected_range_m"], spec.seabed_sample * m["range_per_sample_m"])
    # the strongest sample of every beam is the seabed echo the writer put there (the last beam
    # also holds the +63.5 dB full-scale marker at sample 1)
    np.testing.assert_array_equal(np.argmax(p.image[:, :-1], axis=0), spec.seabed_sample[:-1])
    assert m["mrz_matched"] is True
    np.testing.assert_allclose(m["raw_range_samples"], spec.seabed_sample, rtol=1e-6)
    np.testing.assert_allclose(m["raw_beam_angle_deg"], spec.angles_deg + 0.5, atol=1e-5)
    assert m["raw_valid"].all() and (m["mrz_detection_method"] == 1).all()
    # across-track +y = starboard has the sign of the azimuth
    az = p.geometry.azimuth_rad
    off = np.abs(az) > 0.05
    assert np.all(np.sign(m["mrz_y_m"][off]) == np.sign(az[off]))
    r = spec.seabed_sample * m["range_per_sample_m"]
    np.testing.assert_allclose(np.hypot(m["mrz_y_m"], m["mrz_z_m"]), r, rtol=1e-5)
    assert m["pulse_width_us"] == pytest.approx(200.0)
    assert m["effective_pulse_us"] == pytest.approx(200.0)  # 1 / the sector's 5 kHz bandwidth
    np.testing.assert_allclose(m["tx_sector_tilt_deg"], [kw.TILT])
    np.testing.assert_allclose(m["tx_sector_frequency_hz"], [kw.FREQUENCY])
    np.testing.assert_allclose(m["tx_sector_beamwidth_along_deg"], [1.0])  # the writer's sector
    assert p.geometry.elevation_beamwidth_rad == pytest.approx(np.deg2rad(1.0))
    assert (m["tvg_function"], m["tvg_offset_db"], m["phase_flag"]) == (30, 40.0, 0)


def test_navigation_and_installation_in_meta(synthetic: tuple[Path, kw.KmallSpec]) -> None:
    path, spec = synthetic
    for i, p in enumerate(_read(path)):
        m = p.meta
        lat, lon = kw.position(spec, i)
        assert (m["latitude_deg"], m["longitude_deg"]) == (lat, lon) and m["position_source"] == "MRZ"
        assert m["heading_deg"] == pytest.approx(kw.HEADING)
        roll, pitch, _, heave = kw.attitude(i * spec.ping_interval_s)
        assert m["roll_deg"] == pytest.approx(roll, abs=1e-5)
        assert m["pitch_deg"] == pytest.approx(pitch, abs=1e-5)
        assert m["heave_m"] == pytest.approx(heave, abs=1e-5) and m["attitude_gap_s"] == 0.0
        np.testing.assert_allclose(m["tx_lever_arm_m"], [1.5, -0.25, 2.0])
        np.testing.assert_allclose(m["rx_lever_arm_m"], [1.4, 0.25, 2.1])
        np.testing.assert_allclose(m["tx_mounting_deg"], [0.1, 0.2, 180.0])
        assert m["waterline_z_m"] == pytest.approx(-0.4)
        assert m["installation"]["EMXV"] == "EM2040P"


def test_position_from_spo_without_mrz(tmp_path: Path) -> None:
    data, spec = kw.kmall_bytes(kw.KmallSpec(n_pings=2, n_beams=8, n_samples=40))
    keep = b"".join(data[o : o + n] for o, t, n in kw.datagram_offsets(data) if t != b"#MRZ")
    p = _read(_write(tmp_path, "nomrz.kmall", keep))[1]
    assert p.meta["position_source"] == "SPO" and "mrz_matched" not in p.meta
    assert (p.meta["latitude_deg"], p.meta["longitude_deg"]) == pytest.approx(kw.position(spec, 1))
    assert p.meta["heading_deg"] == pytest.approx(kw.HEADING + 0.1, abs=1e-5)  # SKM's


def test_kongsberg_placement_works_on_kmall_pings(synthetic: tuple[Path, kw.KmallSpec]) -> None:
    from sonarmap.mapping.navigation import kongsberg_placement, navigation_origin, navigation_pose

    path, _ = synthetic
    p = _read(path)[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        k = kongsberg_placement(p)
        pose = navigation_pose(p, navigation_origin(p))
    assert k.tilt_deg == pytest.approx(kw.TILT)
    assert np.isfinite(pose.position_m).all()


def test_installation_text_parse() -> None:
    d = km.parse_kmall_installation_text("SN=53011,\nTRAI_RX1:N=131;X=1.4;Y=bad;,EMXV:EM2040P,junk,")
    assert d == {"SN": 53011.0, "TRAI_RX1.N": 131.0, "TRAI_RX1.X": 1.4, "TRAI_RX1.Y": "bad",
                 "EMXV": "EM2040P"}


# ---------------------------------------------------------------------- layout variants
@pytest.mark.parametrize("phase_flag", [1, 2])
def test_phase_flag_changes_layout_not_image(tmp_path: Path, phase_flag: int) -> None:
    base = _read(_write(tmp_path, "p0.kmall", kw.kmall_bytes(kw.KmallSpec(n_pings=2))[0]))
    spec = kw.KmallSpec(n_pings=2, phase_flag=phase_flag)
    got = _read(_write(tmp_path, f"p{phase_flag}.kmall", kw.kmall_bytes(spec)[0]))
    assert len(got) == len(base)
    for a, b in zip(got, base):
        np.testing.assert_array_equal(a.image, b.image)
        assert a.meta["phase_flag"] == phase_flag


def test_partitions_joined(tmp_path: Path) -> None:
    one = _read(_write(tmp_path, "one.kmall", kw.kmall_bytes(kw.KmallSpec(n_pings=2))[0]))
    spec = kw.KmallSpec(n_pings=2, partitions=3)
    data = kw.kmall_bytes(spec)[0]
    three = _read(_write(tmp_path, "three.kmall", data))
    assert len(three) == 2
    for a, b in zip(three, one):
        np.testing.assert_array_equal(a.image, b.image)
        assert a.meta["complete"] and a.meta["n_datagrams"] == 3 == a.meta["n_datagrams_received"]


def test_missing_partition_yields_beams_received(tmp_path: Path) -> None:
    spec = kw.KmallSpec(n_pings=2, partitions=3)
    data = kw.kmall_bytes(spec)[0]
    dgs = [d for d in kw.datagram_offsets(data)]
    mwc = [d for d in dgs if d[1] == b"#MWC"]
    drop = mwc[1]  # partition 2 of ping 0
    assert struct.unpack_from("<2H", data, drop[0] + 20) == (3, 2)
    cut = data[: drop[0]] + data[drop[0] + drop[2] :]
    path = _write(tmp_path, "gap.kmall", cut)
    with pytest.warns(PartialFrameWarning, match=r"ping 0 .*partition 2 of 3 missing"):
        pings = list(km.iter_pings(path))
    assert len(pings) == 2
    p, full = pings[0], pings[1]
    assert not p.meta["complete"] and p.meta["n_datagrams_received"] == 2
    n = p.meta["n_beams_received"]
    assert 0 < n < spec.n_beams == p.meta["n_beams_total"]
    assert p.image.shape == (spec.n_samples, n) == p.geometry.shape
    want = spec.amplitude_half_db(0)[:n].T * 0.5  # the first beams, before the missing bytes
    np.testing.assert_array_equal(kb.image_to_db(p.image), want)
    assert full.meta["complete"]


def test_missing_first_partition_skips_ping(tmp_path: Path) -> None:
    data = kw.kmall_bytes(kw.KmallSpec(n_pings=2, partitions=2))[0]
    first = [d for d in kw.datagram_offsets(data) if d[1] == b"#MWC"][0]
    cut = data[: first[0]] + data[first[0] + first[2] :]
    with pytest.warns(PartialFrameWarning, match="lacks its first partition"):
        pings = list(km.iter_pings(_write(tmp_path, "nofirst.kmall", cut)))
    assert [p.meta["ping_counter"] for p in pings] == [1]


def test_two_rx_fans_one_ping_each(tmp_path: Path) -> None:
    spec = kw.KmallSpec(n_pings=2, n_fans=2)
    pings = _read(_write(tmp_path, "dual.kmall", kw.kmall_bytes(spec)[0]))
    assert [(p.meta["ping_counter"], p.meta["rx_fan_index"]) for p in pings] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    np.testing.assert_array_equal(kb.image_to_db(pings[1].image), spec.amplitude_half_db(0, 1).T * 0.5)
    assert all(p.meta["mrz_matched"] for p in pings)


# ---------------------------------------------------------------------- detection, errors
def test_detect_format_by_content(synthetic: tuple[Path, kw.KmallSpec], tmp_path: Path) -> None:
    path, _ = synthetic
    assert detect_format(path) == "kmall"
    renamed = _write(tmp_path, "recording.bin", path.read_bytes())
    assert detect_format(renamed) == "kmall"
    head = path.read_bytes()[:4096]
    assert km.sniff(path, head) and not kb.sniff(path, head)
    assert not km.sniff(path, b"\x00" * 64)
    bad = bytearray(head)
    bad[5:8] = b"XYZ"  # not a KMALL datagram type
    assert not km.sniff(path, bytes(bad))
    assert len(list(read_pings(renamed))) == 3


def test_truncated_last_datagram_warns(synthetic: tuple[Path, kw.KmallSpec], tmp_path: Path) -> None:
    path, spec = synthetic
    data = path.read_bytes()
    cut = _write(tmp_path, "cut.kmall", data[:-100])  # the last #MWC loses its end
    with pytest.warns(PartialFrameWarning, match="last datagram is incomplete"):
        pings = list(km.iter_pings(cut))
    assert len(pings) == spec.n_pings - 1
    with pytest.warns(PartialFrameWarning, match="last datagram is incomplete"):
        assert km.count_pings(cut) == spec.n_pings - 1


def test_corrupt_length_and_counts_raise(synthetic: tuple[Path, kw.KmallSpec], tmp_path: Path) -> None:
    path, _ = synthetic
    data = path.read_bytes()
    dgs = kw.datagram_offsets(data)
    off, _, n = dgs[2]
    buf = bytearray(data)
    struct.pack_into("<I", buf, off, n + 8)  # length no longer repeated at the end
    with pytest.raises(DataFormatError, match=rf"at byte {off}: .*trailing length"):
        km.count_pings(_write(tmp_path, "len.kmall", buf))
    off, _, n = next(d for d in dgs if d[1] == b"#MWC")
    buf = bytearray(data)
    rx = off + 24 + 12 + 12 + 16  # header, partition, common part, tx info, 1 sector
    struct.pack_into("<H", buf, rx + 2, 60000)  # numBeams
    with pytest.raises(DataFormatError, match="60000 beams .* run past the end"):
        list(km.iter_pings(_write(tmp_path, "beams.kmall", buf)))
    buf = bytearray(data)
    struct.pack_into("<B", buf, rx + 5, 3)  # phaseFlag
    with pytest.raises(DataFormatError, match="phase flag 3"):
        list(km.iter_pings(_write(tmp_path, "phase.kmall", buf)))
    with pytest.raises(DataFormatError, match="empty"):
        km.count_pings(_write(tmp_path, "empty.kmall", b""))


def _mutate(rng: np.random.Generator, base: bytes) -> bytearray:
    buf = bytearray(base)
    dgs = kw.datagram_offsets(base)
    kind = int(rng.integers(0, 4))
    if kind == 0:  # truncation
        return buf[: int(rng.integers(0, len(buf)))]
    if kind == 1:  # bit flips anywhere
        for _ in range(int(rng.integers(1, 9))):
            buf[int(rng.integers(0, len(buf)))] ^= 1 << int(rng.integers(0, 8))
        return buf
    off, _, n = dgs[int(rng.integers(0, len(dgs)))]
    if kind == 2:  # bit flips inside one datagram's body (lengths intact)
        for _ in range(int(rng.integers(1, 5))):
            buf[off + int(rng.integers(20, n - 4))] ^= 1 << int(rng.integers(0, 8))
        return buf
    # an absurd value in a length / count field: the length, or one of the first 120 body bytes
    if rng.random() < 0.2:
        struct.pack_into("<I", buf, off, int(rng.choice([0, 23, 0xFFFFFFFF, n + 1, n - 1])))
        return buf
    pos = off + 20 + 2 * int(rng.integers(0, 60))
    value = int(rng.choice([0, 1, 3, 0xFFFF, 0x7FFF, int(rng.integers(0, 65536))]))
    if pos + 2 <= off + n - 4:
        struct.pack_into("<H", buf, pos, value)
    return buf


def test_fuzz_only_sonarmap_errors_or_valid_pings(tmp_path: Path) -> None:
    rng = np.random.default_rng(20260101)
    base = kw.kmall_bytes(kw.KmallSpec(n_pings=2, n_beams=8, n_samples=40, partitions=2))[0]
    dgs = kw.datagram_offsets(base)
    depth = b"".join(base[o : o + n] for o, t, n in dgs if t != b"#MWC")  # a .kmall + .kmwcd pair
    water = b"".join(base[o : o + n] for o, t, n in dgs if t == b"#MWC")
    outcomes = {"pings": 0, "error": 0}
    for case in range(200):
        if case % 4 == 3:  # a corrupted .kmall beside a clean .kmwcd, or the other way round
            pair = [depth, water]
            pair[case % 8 == 3] = bytes(_mutate(rng, pair[case % 8 == 3]))
            _write(tmp_path, f"c{case}.kmwcd", pair[1])
            path = _write(tmp_path, f"c{case}.kmall", pair[0])
        else:
            path = _write(tmp_path, f"c{case}.kmall", _mutate(rng, base))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                got = list(read_pings(path)) if case % 2 else list(km.iter_pings(path))
        except SonarmapError as exc:
            assert str(exc).startswith(str(path.with_suffix(""))), str(exc)
            outcomes["error"] += 1
            continue
        for p in got:
            assert p.image.dtype == np.float32 and p.image.shape == p.geometry.shape
            assert np.isfinite(p.image).all() and p.image.min() >= 0 and p.image.max() <= 1
            assert math.isfinite(p.geometry.range_m[-1])
        outcomes["pings"] += bool(got)
        path.unlink()
    print("kmall fuzz outcomes:", outcomes)
    assert outcomes["pings"] > 20 and outcomes["error"] > 20, outcomes


# ---------------------------------------------------------------------- CLI, cross-check
def test_info_cli(synthetic: tuple[Path, kw.KmallSpec], capsys: pytest.CaptureFixture[str]) -> None:
    from sonarmap.cli import main

    path, _ = synthetic
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "kmall" in out and "#MWC 3" in out


def test_pykmall_reads_the_synthetic_file(synthetic: tuple[Path, kw.KmallSpec]) -> None:
    """An independent reader (pykmall) agrees with the writer's layout and with this reader."""
    pk = pytest.importorskip("KMALL.kmall")
    path, spec = synthetic
    ours = _read(path)
    k = pk.kmall(str(path))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pandas deprecations inside pykmall
        k.index_file()
    mwc = [int(o) for o, t in zip(k.Index.ByteOffset, k.Index.MessageType) if "#MWC" in str(t)]
    mrz = [int(o) for o, t in zip(k.Index.ByteOffset, k.Index.MessageType) if "#MRZ" in str(t)]
    assert len(mwc) == len(ours) == spec.n_pings
    k.FID.seek(mwc[0])
    d = k.read_EMdgmMWC()
    np.testing.assert_allclose(d["beamData"]["beamPointAngReVertical_deg"],
                               ours[0].meta["beam_pointing_angle_deg"], atol=1e-6)
    amp = np.array(d["beamData"]["sampleAmplitude05dB_p"], dtype=np.float64) * 0.5
    np.testing.assert_array_equal(kb.image_to_db(ours[0].image), amp.T)
    assert d["rxInfo"]["soundVelocity_mPerSec"] == ours[0].meta["sound_speed_m_s"]
    k.FID.seek(mrz[0])
    z = k.read_EMdgmMRZ()
    assert z["pingInfo"]["latitude_deg"] == ours[0].meta["latitude_deg"]
    np.testing.assert_allclose(z["sounding"]["twoWayTravelTime_sec"], ours[0].meta["raw_twtt_s"], rtol=1e-7)
    k.closeFile()


def test_kmwcd_pair_read_once_from_either_file(synthetic: tuple[Path, kw.KmallSpec], tmp_path: Path) -> None:
    """SIS 5 may write #MWC to a .kmwcd beside the .kmall: either file reads the pair."""
    path, spec = synthetic
    data = path.read_bytes()
    dgs = kw.datagram_offsets(data)
    kmall = b"".join(data[o : o + n] for o, t, n in dgs if t != b"#MWC")
    kmwcd = b"".join(data[o : o + n] for o, t, n in dgs if t in (b"#IIP", b"#MWC"))
    a = _write(tmp_path, "0002_pair.kmall", kmall)
    w = _write(tmp_path, "0002_pair.kmwcd", kmwcd)
    ref = _read(path)
    for given in (a, w):
        got = _read(given)
        assert len(got) == spec.n_pings and km.count_pings(given) == spec.n_pings
        for p, q in zip(got, ref):
            np.testing.assert_array_equal(p.image, q.image)
            assert p.meta["water_column_file"] == str(w) and p.meta["ancillary_file"] == str(a)
            np.testing.assert_array_equal(p.meta["raw_twtt_s"], q.meta["raw_twtt_s"])
            assert p.meta["latitude_deg"] == q.meta["latitude_deg"] and p.meta["roll_deg"] == q.meta["roll_deg"]
    assert len(list(read_pings([a, w]))) == spec.n_pings  # the recording once
    w.unlink()
    assert km.count_pings(a) == 0
    with pytest.raises(DataFormatError, match=r"no water-column \(#MWC\) datagrams and no .kmwcd"):
        list(km.iter_pings(a))


def test_missing_partition_before_any_whole_beam_skips_ping(tmp_path: Path) -> None:
    spec = kw.KmallSpec(n_pings=2, partitions=40)  # part 1 ends inside the first beam's samples
    data = kw.kmall_bytes(spec)[0]
    parts = [d for d in kw.datagram_offsets(data) if d[1] == b"#MWC"]
    drop = parts[1]
    cut = data[: drop[0]] + data[drop[0] + drop[2] :]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pings = list(km.iter_pings(_write(tmp_path, "early.kmall", cut)))
    msgs = [str(w.message) for w in caught if issubclass(w.category, PartialFrameWarning)]
    assert len(msgs) == 2 and "partition 2 of 40 missing" in msgs[0]
    assert "no whole beam before the missing partition" in msgs[1] or "end early" in msgs[1]
    assert [p.meta["ping_counter"] for p in pings] == [1]
