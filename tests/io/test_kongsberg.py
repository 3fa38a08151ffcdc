"""Kongsberg EM .all/.wcd reader on the shared EM 2040 dual-head recording (RV Belgica).

Facts checked against ``../shared/data/kongsberg/README.md`` (verified there by an independent
parse): 5 ping counters x 2 heads, 256 beams per head, the last ping of head 2031 truncated to 234
beams, sound speed 1498.0 m/s, sample rate 15318.63 Hz, beam pointing angles +60.83...-33.99 deg
(head 2004) and +33.99...-59.15 deg (head 2031), positive to port.
"""

from __future__ import annotations

import math
import os
import shutil
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

from sonarmap.errors import DataFormatError, SonarmapError
from sonarmap.io import detect_format, read_pings
from sonarmap.io import kongsberg as kb
from sonarmap.io._binary import PartialFrameWarning

STEM = "0077_20221109_123655_Belgica"


@pytest.fixture(scope="module")
def kdir(data_dir: Path) -> Path:
    d = data_dir / "kongsberg"
    if not (d / f"{STEM}.all").exists() or not (d / f"{STEM}.wcd").exists():
        pytest.skip("shared Kongsberg recording absent")
    return d


@pytest.fixture(scope="module")
def pings(kdir: Path) -> list:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PartialFrameWarning)
        return list(read_pings(kdir / f"{STEM}.all"))


def _by_head(pings: list) -> dict[int, list]:
    out: dict[int, list] = {}
    for p in pings:
        out.setdefault(p.meta["system_serial"], []).append(p)
    return out


def _datagrams(data: bytes) -> list[tuple[int, int]]:
    """(offset, length) of every datagram - an independent minimal walk for the tests."""
    out, off = [], 0
    while off + 4 <= len(data):
        (n,) = struct.unpack_from("<I", data, off)
        if off + 4 + n > len(data):
            break
        out.append((off, n))
        off += 4 + n
    return out


def _fix_checksum(buf: bytearray, off: int, n: int) -> None:
    cs = sum(buf[off + 5 : off + 4 + n - 3]) & 0xFFFF
    struct.pack_into("<H", buf, off + 4 + n - 2, cs)


# ---------------------------------------------------------------------- real file
def test_counts_heads_and_the_truncated_ping(kdir: Path) -> None:
    with pytest.warns(PartialFrameWarning):
        assert kb.count_pings(kdir / f"{STEM}.all") == 10
    with pytest.warns(PartialFrameWarning):
        assert kb.count_pings(kdir / f"{STEM}.wcd") == 10
    with pytest.warns(PartialFrameWarning, match=r"ping 59685 of head 2031 is incomplete .*234 of 256 beams"):
        pings = list(kb.iter_pings(kdir / f"{STEM}.wcd"))
    heads = _by_head(pings)
    assert sorted(heads) == [2004, 2031]
    assert [p.meta["ping_counter"] for p in heads[2004]] == [59681, 59682, 59683, 59684, 59685]
    assert [p.meta["ping_counter"] for p in heads[2031]] == [59681, 59682, 59683, 59684, 59685]
    last = heads[2031][-1]
    assert not last.meta["complete"] and last.meta["n_datagrams_received"] == 1
    assert (last.meta["n_beams_received"], last.meta["n_beams_total"]) == (234, 256)
    assert last.shape[1] == 234
    assert all(p.meta["complete"] and p.shape[1] == 256 for p in pings if p is not last)
    assert last.source.endswith(f"{STEM}.wcd#head2031/ping59685")


def test_shapes_dtype_and_range_axis(pings: list) -> None:
    c, fs = 1498.0, 15318.63
    for p in pings:
        assert p.image.dtype == np.float32 and p.image.flags.c_contiguous
        assert p.image.shape == p.geometry.shape
        assert 0.0 <= p.image.min() and p.image.max() <= 1.0
        assert p.meta["sound_speed_m_s"] == c and p.geometry.sound_speed_m_s == c
        assert p.meta["sample_rate_hz"] == pytest.approx(fs, abs=1e-9)
        # row i = sample i (start range sample 0): range i * c / (2 fs)
        assert p.meta["start_range_sample"] == 0
        np.testing.assert_allclose(p.geometry.range_m, np.arange(p.shape[0]) * c / (2 * fs), rtol=1e-12)
        # as many rows as the longest beam; shorter beams padded with 0
        assert p.shape[0] == p.meta["beam_n_samples"].max()
        j = int(np.argmin(p.meta["beam_n_samples"]))
        assert np.all(p.image[p.meta["beam_n_samples"][j] :, j] == 0)
        assert p.geometry.frequency_hz == 300000.0
    assert [p.shape[0] for p in pings[:2]] == [458, 438]
    assert pings[0].datetime64 == np.datetime64("2022-11-09T12:36:54.649", "ns")
    assert pings[-1].datetime64 == np.datetime64("2022-11-09T12:36:58.701", "ns")


def test_beam_angles_map_to_increasing_starboard_azimuths(pings: list) -> None:
    heads = _by_head(pings)
    spans = {2004: (60.83, -33.99), 2031: (33.99, -59.15)}
    for serial, plist in heads.items():
        for p in plist:
            az = np.rad2deg(p.geometry.azimuth_rad)
            assert np.all(np.diff(az) > 0)
            ang = p.meta["beam_pointing_angle_deg"]
            np.testing.assert_allclose(az, -ang, atol=1e-9)  # Kongsberg angles: positive to port
            first, last = spans[serial]
            assert ang[0] == pytest.approx(first)
            if p.meta["complete"]:
                assert ang[-1] == pytest.approx(last)
    assert heads[2031][-1].meta["beam_pointing_angle_deg"][-1] == pytest.approx(-51.12)
    # starboard really is positive: the sonar's own XYZ soundings are across-track +y (starboard)
    for p in pings:
        if "xyz_across_m" not in p.meta:
            continue
        az = p.geometry.azimuth_rad
        off = np.abs(np.rad2deg(az)) > 5
        assert np.mean(np.sign(p.meta["xyz_across_m"][off]) == np.sign(az[off])) > 0.95  # 0.97-1
        rx_y = p.meta["rx_lever_arm_m"][1]
        seen = np.rad2deg(np.arctan2(p.meta["xyz_across_m"] - rx_y, p.meta["xyz_depth_m"]))
        assert np.median(np.abs(np.rad2deg(az) - seen)) < 8.0


def test_amplitudes_are_the_file_db(kdir: Path, pings: list) -> None:
    """The first beam of the first water-column datagram, decoded by hand from the bytes."""
    data = (kdir / f"{STEM}.wcd").read_bytes()
    off = next(o for o, _ in _datagrams(data) if data[o + 5] == 0x6B)
    ntx = struct.unpack_from("<H", data, off + 24)[0]
    p = off + 20 + 24 + 6 * ntx
    angle, start, ns, dr = struct.unpack_from("<hHHH", data, p)
    raw = np.frombuffer(data, np.int8, ns, p + 10).astype(np.float64) * 0.5  # dB
    ping = pings[0]
    assert (ping.meta["system_serial"], angle / 100) == (2004, 60.83)
    col = ping.meta["beam_index"].tolist().index(0)
    m = ping.meta
    assert (m["amplitude_db_full_scale"], m["amplitude_db_step"]) == (63.5, 0.5)
    # linear intensity re the datagram's full scale (+63.5 dB = 1.0)
    np.testing.assert_allclose(ping.image[start : start + ns, col], 10 ** ((raw - 63.5) / 10), rtol=1e-6)
    db = kb.image_to_db(ping.image, m["amplitude_db_full_scale"])
    np.testing.assert_array_equal(db[start : start + ns, col], raw)  # exact after 0.5 dB rounding
    exact = kb.image_to_db(ping.image, step_db=None)
    np.testing.assert_allclose(exact[start : start + ns, col], raw, atol=1e-5)
    assert m["detected_range_samples"][col] == dr
    # padding (no sample) is exactly 0, and nothing else is
    n_s = m["beam_n_samples"]
    rows = np.arange(ping.shape[0])[:, None]
    assert np.array_equal(ping.image == 0, rows >= n_s[None, :])
    assert "log_dynamic_range_db" not in m  # linear samples for the pipeline


def test_detection_agrees_with_raw_range_and_the_echo(pings: list) -> None:
    for p in pings:
        m = p.meta
        assert m["raw_matched"] and m["raw_twtt_s"].shape == (p.shape[1],)
        ratio = m["detected_range_samples"] / m["raw_range_samples"]
        assert np.all((ratio > 0.994) & (ratio <= 1.0 + 1e-9))  # README: 0.995-1.000
        np.testing.assert_allclose(m["detected_range_m"], m["detected_range_samples"] * 1498.0 / (2 * 15318.63))
        assert 9.0 < np.nanmin(m["detected_range_m"]) and np.nanmax(m["detected_range_m"]) < 21.5
        # the amplitude maximum near the detection lies 0-2 samples after it on most beams
        lag = []
        for j, b in enumerate(m["detected_bin"]):
            lo, hi = max(b - 10, 0), min(b + 11, m["beam_n_samples"][j])
            lag.append(lo + int(np.argmax(p.image[lo:hi, j])) - b)
        lag = np.array(lag)
        assert np.mean((lag >= 0) & (lag <= 2)) > 0.7
        assert m["pulse_width_us"] == pytest.approx(216.0)
        # a shaped pulse of 6687 Hz bandwidth: 150 us effective, the length the echoes are
        # smoothed over (2 samples of 4.9 cm, where the 216 us signal length gave 3)
        assert m["effective_pulse_us"] == pytest.approx(1e6 / 6687.0, abs=1e-3)
        from sonarmap.ranges.measure import pulse_bins

        assert pulse_bins(p) == 2


def test_effective_pulse_is_one_over_the_bandwidth() -> None:
    from sonarmap.io.kongsberg import effective_pulse_us

    assert effective_pulse_us([5000.0, 5000.0]) == pytest.approx(200.0)
    assert effective_pulse_us([4000.0, 6000.0]) == pytest.approx(200.0)  # the sectors' mean bandwidth
    assert effective_pulse_us([np.nan, 0.0, -5.0, 1e9]) is None  # nothing plausible
    assert effective_pulse_us([]) is None


def test_xyz_position_attitude_installation(pings: list) -> None:
    with_xyz = [p for p in pings if p.meta.get("xyz_matched")]
    assert len(with_xyz) == 9  # the .all has no X datagram for the truncated ping
    for p in with_xyz:
        m = p.meta
        assert np.all((m["xyz_depth_m"] > 9.4) & (m["xyz_depth_m"] < 10.3))
        assert -19.7 < m["xyz_across_m"].min() and m["xyz_across_m"].max() < 16.7
        assert np.all(np.abs(m["xyz_along_m"] - 8.2) < 0.5)
        assert m["xyz_valid"].all()
    for p in pings:
        m = p.meta
        assert m["latitude_deg"] == pytest.approx(51.3685, abs=5e-4)
        assert m["longitude_deg"] == pytest.approx(3.139, abs=5e-4)
        assert m["position_system"] & 0x80  # the active positioning system only
        assert m["heading_deg"] == pytest.approx(311.5, abs=1.0)
        assert abs(m["roll_deg"]) < 2 and abs(m["pitch_deg"]) < 2
        assert m["position_gap_s"] < 2.5 and m["attitude_gap_s"] < 2.5
        assert m["tvg_function"] == 30 and m["tvg_offset_db"] == 40
        np.testing.assert_allclose(m["tx_sector_tilt_deg"], [1.25])
        assert m["installation"]["WLZ"] == -4.908 and m["waterline_z_m"] == -4.908
        np.testing.assert_allclose(m["tx_lever_arm_m"], [0.377, 0.008, 0.426])
        rx = {2004: ([0.246, -0.374, 0.301], [35.54, 3.21, 0.32]),
              2031: ([0.235, 0.387, 0.307], [-34.13, 3.19, 1.29])}[m["system_serial"]]
        np.testing.assert_allclose(m["rx_lever_arm_m"], rx[0])
        np.testing.assert_allclose(m["rx_mounting_deg"], rx[1])
        assert m["runtime_absorption_db_km"] == pytest.approx(77.65)
        # the EM2040's along-track transmit beamwidth (runtime 0.5 deg) is the width across the swath fan
        assert m["runtime_tx_beamwidth_deg"] == pytest.approx(0.5)
        assert p.geometry.elevation_beamwidth_rad == pytest.approx(np.deg2rad(0.5))
    # positions move with the ship (1.6 m/s) once inside the fixes' span
    lats = [p.meta["latitude_deg"] for p in pings]
    assert lats[-1] > lats[0]


def test_detection_by_content_and_sibling_lookup(kdir: Path, tmp_path: Path) -> None:
    assert detect_format(kdir / f"{STEM}.all") == "kongsberg"
    assert detect_format(kdir / f"{STEM}.wcd") == "kongsberg"
    odd = tmp_path / "recording.dat"  # content, not the extension, decides (temp copy)
    shutil.copy(kdir / f"{STEM}.wcd", odd)
    assert detect_format(odd) == "kongsberg"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PartialFrameWarning)
        alone = list(read_pings(odd))
    assert len(alone) == 10
    # no .all beside it: position/attitude/installation from the .wcd's own datagrams, no N/X
    assert "raw_twtt_s" not in alone[0].meta and "xyz_depth_m" not in alone[0].meta
    assert alone[0].meta["latitude_deg"] == pytest.approx(51.3685, abs=5e-4)
    head = (kdir / f"{STEM}.all").read_bytes()[:4096]
    assert kb.sniff(kdir / f"{STEM}.all", head)
    assert not kb.sniff(tmp_path / "x", b"DDF\x05" + bytes(4092))
    assert not kb.sniff(tmp_path / "x", head[:4] + b"\x03" + head[5:])  # no STX
    assert not kb.sniff(tmp_path / "x", head[:6] + b"\x00\x00" + head[8:])  # EM model 0


def test_info_cli(kdir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from sonarmap.cli import main

    assert main(["info", str(kdir / f"{STEM}.all")]) == 0
    out = capsys.readouterr().out
    assert "kongsberg" in out and "2004, 2031" in out


def test_installation_text() -> None:
    d = kb.parse_installation_text("WLZ=-4.908,SMH=2004,TSV=1.07   Mar  8 2018 ,,junk,")
    assert d == {"WLZ": -4.908, "SMH": 2004.0, "TSV": "1.07   Mar  8 2018"}


# ---------------------------------------------------------------------- robustness
@pytest.fixture(scope="module")
def small_wcd(kdir: Path) -> bytes:
    """The .wcd's first 6 datagrams (I, U, R and the first ping of head 2004 + one more)."""
    data = (kdir / f"{STEM}.wcd").read_bytes()
    dgs = _datagrams(data)
    end = dgs[6][0]
    return data[:end]


def _write(tmp_path: Path, name: str, data: bytes | bytearray) -> Path:
    p = tmp_path / name
    p.write_bytes(bytes(data))
    return p


@pytest.mark.filterwarnings("ignore::sonarmap.io._binary.PartialFrameWarning")
def test_checksum_mismatch(small_wcd: bytes, tmp_path: Path) -> None:
    buf = bytearray(small_wcd)
    off, n = _datagrams(small_wcd)[3]  # first water-column datagram
    buf[off + 5000] ^= 0x01
    p = _write(tmp_path, "bad.wcd", buf)
    with pytest.raises(DataFormatError, match=rf"at byte {off}: checksum mismatch"):
        list(kb.iter_pings(p))
    with pytest.warns(kb.KongsbergWarning, match="checksum mismatch"):
        got = list(kb.iter_pings(p, checksum="warn"))
    assert len(got) == 2 and not got[0].meta["complete"] and got[0].shape[1] == 26
    assert len(list(kb.iter_pings(p, checksum="ignore"))) == 2
    with pytest.raises(DataFormatError, match="checksum must be"):
        kb.KongsbergFile(p, checksum="maybe")  # type: ignore[arg-type]


@pytest.mark.filterwarnings("ignore::sonarmap.io._binary.PartialFrameWarning")
def test_truncated_and_corrupt_lengths(small_wcd: bytes, tmp_path: Path) -> None:
    dgs = _datagrams(small_wcd)
    cut = _write(tmp_path, "cut.wcd", small_wcd[: dgs[5][0] + 1000])
    with pytest.warns(PartialFrameWarning, match=rf"at byte {dgs[5][0]}: last datagram is incomplete"):
        assert kb.count_pings(cut) == 1
    buf = bytearray(small_wcd)
    struct.pack_into("<I", buf, 0, 0xFFFFFFF0)
    with pytest.raises(DataFormatError, match="at byte 0: datagram length field .* absurd"):
        kb.count_pings(_write(tmp_path, "absurd.wcd", buf))
    buf = bytearray(small_wcd)
    struct.pack_into("<I", buf, 0, len(small_wcd) + 10)  # past the end, yet datagrams follow
    with pytest.raises(DataFormatError, match="at byte 0: .*corrupt length"):
        kb.count_pings(_write(tmp_path, "past.wcd", buf))
    buf = bytearray(small_wcd)
    struct.pack_into("<I", buf, dgs[1][0], dgs[1][1] + 2)  # ETX not where the length says
    with pytest.raises(DataFormatError, match=rf"at byte {dgs[1][0]}: .*ETX"):
        kb.count_pings(_write(tmp_path, "etx.wcd", buf))
    buf = bytearray(small_wcd)
    off, n = dgs[3]
    struct.pack_into("<H", buf, off + 28, 5000)  # Nrx beams: more than the 256 total
    _fix_checksum(buf, off, n)
    with pytest.raises(DataFormatError, match=rf"at byte {off + 20}: .*5000 of 256 beams"):
        kb.count_pings(_write(tmp_path, "nrx.wcd", buf))
    buf = bytearray(small_wcd)
    ntx = struct.unpack_from("<H", buf, off + 24)[0]
    struct.pack_into("<H", buf, off + 20 + 24 + 6 * ntx + 4, 60000)  # first beam's Ns
    _fix_checksum(buf, off, n)
    with pytest.raises(DataFormatError, match="sample count runs past the end"):
        list(kb.iter_pings(_write(tmp_path, "ns.wcd", buf)))
    with pytest.raises(DataFormatError, match="empty"):
        kb.count_pings(_write(tmp_path, "empty.wcd", b""))


def test_missing_water_column_and_fifo(kdir: Path, tmp_path: Path) -> None:
    alone = tmp_path / "only.all"
    shutil.copy(kdir / f"{STEM}.all", alone)
    with pytest.raises(DataFormatError, match="no water-column .* no .wcd file"):
        kb.count_pings(alone)
    fifo = tmp_path / "only.wcd"
    os.mkfifo(fifo)
    with pytest.raises(DataFormatError, match="FIFO"):
        kb.count_pings(alone)  # the sibling is a FIFO: refused, never opened for reading
    with pytest.raises(DataFormatError, match="FIFO"):
        kb.count_pings(fifo)


def test_count_reads_headers_only(kdir: Path, tmp_path: Path) -> None:
    """A corrupt N datagram in the .all does not matter to count_pings (headers only) but does
    to decoding (checksums of the datagrams used are verified)."""
    data = bytearray((kdir / f"{STEM}.all").read_bytes())
    off = next(o for o, _ in _datagrams(bytes(data)) if data[o + 5] == 0x4E)
    data[off + 100] ^= 0xFF
    _write(tmp_path, f"{STEM}.all", data)
    shutil.copy(kdir / f"{STEM}.wcd", tmp_path / f"{STEM}.wcd")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PartialFrameWarning)
        assert kb.count_pings(tmp_path / f"{STEM}.all") == 10
        with pytest.raises(DataFormatError, match=rf"at byte {off}: checksum mismatch in raw range"):
            list(kb.iter_pings(tmp_path / f"{STEM}.all"))


def _mutate(rng: np.random.Generator, base: bytes) -> bytearray:
    buf = bytearray(base)
    dgs = _datagrams(base)
    kind = rng.integers(0, 4)
    if kind == 0:  # truncation
        return buf[: int(rng.integers(0, len(buf)))]
    if kind == 1:  # bit flips, checksums left as they are
        for _ in range(int(rng.integers(1, 9))):
            buf[int(rng.integers(0, len(buf)))] ^= 1 << int(rng.integers(0, 8))
        return buf
    off, n = dgs[int(rng.integers(0, len(dgs)))]
    if kind == 2:  # bit flips inside one datagram's body, checksum recomputed
        for _ in range(int(rng.integers(1, 5))):
            buf[off + int(rng.integers(5, 4 + n - 3))] ^= 1 << int(rng.integers(0, 8))
        _fix_checksum(buf, off, n)
        return buf
    # an absurd value in a length/count field (common length, or the first 40 body bytes)
    pos = off if rng.random() < 0.3 else off + 20 + 2 * int(rng.integers(0, 20))
    value = int(rng.choice([0, 1, 0xFFFF, 0x7FFF, int(rng.integers(0, 65536))]))
    if pos == off:
        struct.pack_into("<I", buf, pos, int(rng.choice([0, 18, 0xFFFFFFFF, value, n + 1])))
    elif pos + 2 <= off + 4 + n - 3:
        struct.pack_into("<H", buf, pos, value)
        _fix_checksum(buf, off, n)
    return buf


def test_fuzz_only_sonarmap_errors_or_valid_pings(kdir: Path, small_wcd: bytes, tmp_path: Path) -> None:
    rng = np.random.default_rng(20221109)
    all_bytes = (kdir / f"{STEM}.all").read_bytes()
    small_all = all_bytes[: _datagrams(all_bytes)[12][0]]  # I, U, R, n, N/X pairs of 2 pings
    outcomes = {"pings": 0, "error": 0}
    for case in range(200):
        d = tmp_path / f"c{case}"
        d.mkdir()
        if case % 4 == 3:  # the .all corrupted, with a clean water column beside it
            _write(d, "r.wcd", small_wcd)
            path = _write(d, "r.all", _mutate(rng, small_all))
        else:
            path = _write(d, "r.wcd", _mutate(rng, small_wcd))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                got = list(read_pings(path)) if case % 2 else list(kb.iter_pings(path))
        except SonarmapError as exc:
            assert str(exc).startswith(str(d)) or "unrecognised" in str(exc), str(exc)
            outcomes["error"] += 1
            continue
        for p in got:
            assert p.image.dtype == np.float32 and p.image.shape == p.geometry.shape
            assert np.isfinite(p.image).all() and p.image.min() >= 0 and p.image.max() <= 1
            assert math.isfinite(p.geometry.range_m[-1])
        outcomes["pings"] += bool(got)
        shutil.rmtree(d)
    assert outcomes["pings"] > 20 and outcomes["error"] > 20, outcomes


def test_both_files_of_a_recording_read_once(data_dir: Path) -> None:
    from sonarmap.io import read_pings

    k = data_dir / "kongsberg"
    one = [p.source for p in read_pings(k / "0077_20221109_123655_Belgica.all")]
    both = [p.source for p in read_pings([k / "0077_20221109_123655_Belgica.all",
                                          k / "0077_20221109_123655_Belgica.wcd"])]
    assert both == one and len(one) >= 9
