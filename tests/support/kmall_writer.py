"""Writer of small synthetic Kongsberg ``.kmall`` files for the tests (published KMALL layout).

The file holds ``#IIP`` (installation text), ``#SPO`` (positions) and ``#SKM`` (attitude) datagrams
and, per ping, an ``#MRZ`` depth datagram and an ``#MWC`` water-column datagram with one transmit
sector, ``n_beams`` beams of ``n_samples`` samples each and a seabed echo at a known sample per
beam.  The water column may be split into several partitions, carry phase data (``phase_flag``
1 or 2) and several RX fans per ping.
"""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import numpy as np

T0_S = 1_700_000_000  # 2023-11-14T22:13:20Z
LAT0, LON0 = 51.25, 3.125
HEADING = 45.0
SOUND_SPEED = 1500.0
SAMPLE_RATE = 15000.0
FREQUENCY = 300000.0
TILT = 1.25
INSTALLATION = (
    "OSCV:Empty,\nEMXV:EM2040P,\nPU_0,\nSN=53011,\nIP=157.237.14.60:0xffff0000,\nUDP=1997,\n"
    "TRAI_TX1:N=218;X=1.500;Y=-0.250;Z=2.000;R=0.100;P=0.200;H=180.000;S=0.7;V=1;,\n"
    "TRAI_RX1:N=131;X=1.400;Y=0.250;Z=2.100;R=0.300;P=0.400;H=0.500;S=0.7;V=1;,\n"
    "EMXI:SWLZ=-0.400,\n"
)


@dataclasses.dataclass
class KmallSpec:
    """What a synthetic file holds (the truth the tests compare against)."""

    n_pings: int = 3
    n_beams: int = 32
    n_samples: int = 200
    n_fans: int = 1
    phase_flag: int = 0
    partitions: int = 1
    ping_interval_s: float = 0.5
    angles_deg: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    seabed_sample: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    start_sample: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))

    def __post_init__(self) -> None:
        n = self.n_beams
        if self.angles_deg.size == 0:
            # Kongsberg order: first beam to port (positive angle), last to starboard
            self.angles_deg = np.linspace(60.0, -60.0, n)
        if self.seabed_sample.size == 0:
            depth_samples = 120.0
            self.seabed_sample = np.minimum(
                np.round(depth_samples / np.cos(np.deg2rad(self.angles_deg))).astype(np.int64),
                self.n_samples - 5)
        if self.start_sample.size == 0:
            self.start_sample = np.zeros(n, np.int64)

    def amplitude_half_db(self, ping: int, fan: int = 0) -> np.ndarray:
        """int8 amplitudes (0.5 dB units), shape (n_beams, n_samples): noise with a seabed echo."""
        rng = np.random.default_rng(1000 * ping + fan)
        a = rng.integers(-100, -40, size=(self.n_beams, self.n_samples))
        for b, s in enumerate(self.seabed_sample):
            a[b, s] = 120  # +60 dB
            a[b, s + 1] = 100
        a[0, 0] = -128  # the lowest storable amplitude, -64 dB
        a[-1, 1] = 127  # the highest, +63.5 dB
        return a.astype(np.int8)

    def time_s(self, ping: int) -> tuple[int, int]:
        t = ping * self.ping_interval_s
        return T0_S + int(t), int(round((t - int(t)) * 1e9))


def _datagram(typ: bytes, body: bytes, t: tuple[int, int], version: int = 1, system: int = 10,
              sounder: int = 2040) -> bytes:
    n = 20 + len(body) + 4
    return struct.pack("<I4s2BH2I", n, typ, version, system, sounder, t[0], t[1]) + body + struct.pack("<I", n)


def _cmn(ping: int, fan: int, n_fans: int) -> bytes:
    return struct.pack("<2H8B", 12, ping, n_fans, fan, 1, 0, 0, fan, n_fans, 0)


def iip(t: tuple[int, int]) -> bytes:
    text = INSTALLATION.encode()
    return _datagram(b"#IIP", struct.pack("<3H", 6 + len(text), 0, 0) + text, t)


def spo(t: tuple[int, int], lat: float, lon: float) -> bytes:
    block = struct.pack("<2If2d3f", t[0], t[1], 0.5, lat, lon, 2.0, HEADING, 40.0) + b"$GPGGA,dummy"
    return _datagram(b"#SPO", struct.pack("<4H", 8, 1, 1, 0) + block, t)


def skm(t: tuple[int, int], samples: list[tuple[int, int, float, float, float, float]]) -> bytes:
    out = b""
    for ts, tns, roll, pitch, heading, heave in samples:
        kmb = struct.pack("<4s2H3I2d", b"#KMB", 120, 1, ts, tns, 0, LAT0, LON0)
        kmb += struct.pack("<21f", 0.0, roll, pitch, heading, heave, *([0.0] * 16))
        out += kmb + struct.pack("<2If", ts, tns, 0.0)
    info = struct.pack("<H2B4H", 12, 1, 1, 1, len(samples), 132, 0x0F)
    return _datagram(b"#SKM", info + out, t)


def mrz(spec: KmallSpec, ping: int, fan: int, lat: float, lon: float) -> bytes:
    body = _cmn(ping, fan, spec.n_fans)
    info = bytearray(144)
    struct.pack_into("<H", info, 0, 144)
    struct.pack_into("<2H", info, 92, 1, 36)
    struct.pack_into("<4f", info, 96, HEADING, SOUND_SPEED, 2.0, -0.4)
    struct.pack_into("<2df", info, 124, lat, lon, 42.0)
    body += bytes(info)
    body += struct.pack("<4B7f2BH", 0, 0, 0, 0, 0.0, TILT, 220.0, 0.0, FREQUENCY, 5000.0, 200e-6, 0, 0, 0)
    n = spec.n_beams
    body += struct.pack("<4H4f4H", 32, n, n, 120, SAMPLE_RATE, SAMPLE_RATE, -20.0, -30.0, 0, 0, 0, 4)
    step = SOUND_SPEED / (2 * SAMPLE_RATE)
    for b in range(n):
        s = bytearray(120)
        r = spec.seabed_sample[b] * step
        a = np.deg2rad(spec.angles_deg[b])
        struct.pack_into("<H8BH6f2H", s, 0, b, 0, 0, 1, 0, 0, 0, 0, 0, 0, 100.0, 0.5, 0.1, 0.2, 1e-4,
                         1e-4, b, int(spec.seabed_sample[b]))
        struct.pack_into("<f", s, 40, float(spec.angles_deg[b]))
        struct.pack_into("<f", s, 72, float(spec.angles_deg[b]) + 0.5)
        struct.pack_into("<f", s, 80, float(spec.seabed_sample[b] / SAMPLE_RATE))
        struct.pack_into("<3f", s, 96, float(r * np.cos(a)), float(-r * np.sin(a)), 0.1)
        body += bytes(s)
    # version 0: the 144-byte ping info and 36-byte sectors of the first revision
    return _datagram(b"#MRZ", struct.pack("<2H", 1, 1) + body, spec.time_s(ping), version=0)


def mwc_body(spec: KmallSpec, ping: int, fan: int) -> bytes:
    body = _cmn(ping, fan, spec.n_fans)
    body += struct.pack("<3Hhf", 12, 1, 16, 0, 0.05)
    body += struct.pack("<3fHh", TILT, FREQUENCY, 1.0, 0, 0)
    body += struct.pack("<2H3Bb2f", 16, spec.n_beams, 16, spec.phase_flag, 30, 40, SAMPLE_RATE, SOUND_SPEED)
    amp = spec.amplitude_half_db(ping, fan)
    for b in range(spec.n_beams):
        det = int(spec.seabed_sample[b])
        body += struct.pack("<f4Hf", float(spec.angles_deg[b]), int(spec.start_sample[b]), det, 0,
                            spec.n_samples, det + 0.25)
        body += amp[b].tobytes()
        if spec.phase_flag == 1:
            body += np.full(spec.n_samples, 7, np.int8).tobytes()
        elif spec.phase_flag == 2:
            body += np.full(spec.n_samples, -300, "<i2").tobytes()
    return body


def mwc(spec: KmallSpec, ping: int, fan: int) -> list[bytes]:
    """The #MWC datagram of a ping and fan, as ``spec.partitions`` consecutive parts."""
    body = mwc_body(spec, ping, fan)
    k = spec.partitions
    cuts = np.linspace(0, len(body), k + 1).astype(int)
    return [_datagram(b"#MWC", struct.pack("<2H", k, i + 1) + body[cuts[i] : cuts[i + 1]],
                      spec.time_s(ping), version=1) for i in range(k)]


def position(spec: KmallSpec, ping: int) -> tuple[float, float]:
    return LAT0 + 1e-5 * ping, LON0 + 2e-5 * ping


def attitude(t_s: float) -> tuple[float, float, float, float]:
    """(roll, pitch, heading, heave) at ``t_s`` seconds after T0_S: linear in time."""
    return 1.0 + 0.5 * t_s, -2.0 + 0.25 * t_s, HEADING + 0.1, 0.1 * t_s


def kmall_bytes(spec: KmallSpec | None = None) -> tuple[bytes, KmallSpec]:
    """The bytes of a synthetic ``.kmall`` file and its spec."""
    spec = spec or KmallSpec()
    out = [iip((T0_S - 1, 0))]
    samples = []
    for i in range(int((spec.n_pings * spec.ping_interval_s + 2) * 10)):
        t = -1.0 + 0.1 * i
        ts = T0_S + int(np.floor(t))
        tns = int(round((t - np.floor(t)) * 1e9)) % 1_000_000_000
        samples.append((ts, tns, *attitude(t)))
    out.append(skm((T0_S - 1, 0), samples))
    out.append(spo((T0_S - 1, 0), *position(spec, -2)))
    for p in range(spec.n_pings):
        lat, lon = position(spec, p)
        out.append(spo(spec.time_s(p), lat, lon))
        for fan in range(spec.n_fans):
            out.append(mrz(spec, p, fan, lat, lon))
            out.extend(mwc(spec, p, fan))
    return b"".join(out), spec


def write_kmall(path: str | Path, spec: KmallSpec | None = None) -> KmallSpec:
    """Write a synthetic ``.kmall`` file; returns its spec."""
    data, spec = kmall_bytes(spec)
    Path(path).write_bytes(data)
    return spec


def datagram_offsets(data: bytes) -> list[tuple[int, bytes, int]]:
    """(offset, type, length) of every datagram of a KMALL byte string."""
    out, off = [], 0
    while off + 8 <= len(data):
        n = struct.unpack_from("<I", data, off)[0]
        out.append((off, data[off + 4 : off + 8], n))
        if n < 24:
            break
        off += n
    return out
