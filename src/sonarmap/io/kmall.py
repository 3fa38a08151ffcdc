"""Kongsberg ``.kmall`` multibeam recordings (EM 2040, 304, 712, 124 ... with SIS 5 / K-Controller).

Layout (Kongsberg "KMALL datagram description" / ``EMdgmFormat.h``, public; little-endian).  A file
is a stream of datagrams, each::

    uint32   numBytesDgm     length of the whole datagram, this field and the trailer included
    char[4]  dgmType         '#' and three letters: '#IIP', '#MRZ', '#MWC', '#SPO', '#SKM' ...
    uint8    dgmVersion
    uint8    systemID        separates the datagrams of several echosounders on one controller
    uint16   echoSounderID   EM model, e.g. 2040, 304, 712
    uint32   time_sec        UTC seconds since 1970-01-01
    uint32   time_nanosec
    ...      body
    uint32   numBytesDgm     the length repeated

Multibeam (``#M..``) datagrams continue with a partition struct (``numOfDgms``, ``dgmNum``: a
datagram split into UDP-sized parts; each part's bytes after its partition struct and before its
trailer are consecutive pieces of one body) and a common part (``numBytesCmnPart``, ``pingCnt``,
``rxFansPerPing``, ``rxFanIndex``, ``swathsPerPing``, ``swathAlongPosition``, ``txTransducerInd``,
``rxTransducerInd``, ``numRxTransducers``, ``algorithmType``).  Every struct starts with its own
size, which the reader uses to step over fields added by later format revisions.

What this reader uses:

* ``#MWC`` water column, one per ping and RX fan: transmit sectors (tilt re TX array, centre
  frequency, along-track beam width), the receiver info (beam count, beam-entry size, phase flag,
  TVG function ``X`` and offset, sample frequency, sound speed) and per beam the pointing angle re
  vertical (degrees, **positive to port** as in the EM ``.all`` water column), start range sample,
  detected range (samples, 0 = none; also the high-resolution float when present), transmit
  sector, ``Ns`` int8 amplitudes in 0.5 dB, then ``Ns`` phase values of 0 (``phaseFlag`` 0),
  1 (int8, flag 1) or 2 (int16, flag 2) bytes each, which are skipped.
* ``#MRZ`` depth datagram of the same ping and fan: ping info (vessel heading, sound speed at the
  transducer, transducer depth, water level, latitude/longitude of the reference point), and per
  main sounding: detection type/method, two-way travel time, beam angle re the RX array,
  ``x``/``y``/``z`` re the vessel reference point, the water-column beam number and range.
* ``#SPO`` position, ``#SKM`` attitude (KM binary samples: roll, pitch, heading, heave) and
  ``#IIP`` installation text (``GROUP:KEY=value;KEY=value;...,`` items).
* A recording may keep its water column in a ``.kmwcd`` file beside the ``.kmall`` (same stem):
  either file reads the pair (:func:`sibling_paths`, :func:`recording_key`).

Every count and size read from the file is checked against the bytes available before it is
used; inconsistencies are :class:`~sonarmap.errors.DataFormatError` naming the file and byte
offset, an incomplete trailing datagram or a missing partition a
:class:`~sonarmap.io._binary.PartialFrameWarning`.  Not read: phase samples, extra detections,
seabed image samples, runtime (``#IOP``) and sound-speed datagrams.

Conventions of the yielded :class:`~sonarmap.ping.Ping` are those of
:mod:`sonarmap.io.kongsberg` (same image mapping, angle convention, padding and meta key names;
``meta["format"] == "kongsberg"`` so that the Kongsberg placement of
:mod:`sonarmap.mapping.navigation` applies, ``meta["file_format"] == "kmall"``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import struct
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import DataFormatError
from sonarmap.geometry import SonarGeometry, as_geometry
from sonarmap.io._binary import (
    MAX_PLAUSIBLE_TIME_NS,
    ClosingFile,
    PartialFrameWarning,
    check_index,
    check_sound_speed,
    check_time_ns,
    header_errors,
    make_summary,
    records_at,
    warn_partial,
)
from sonarmap._files import require_regular_file
from sonarmap.io.kongsberg import (
    _AMP_LUT,
    _beam_layout,
    AMPLITUDE_DB_FULL_SCALE,
    AMPLITUDE_DB_STEP,
    effective_pulse_us,
    _open_buffer,
    _ping_geometry,
    _walk,
    _walk_error,
    find_sibling,
    pair_key,
    _kernels,
    _Series,
)
from sonarmap.io.reader import GeometrySpec, check_ping_range
from sonarmap.ping import Ping

__all__ = [
    "FORMAT",
    "DATAGRAM_TYPES",
    "HEADER_DTYPE",
    "KmallFile",
    "parse_kmall_installation_text",
    "sibling_paths",
    "recording_key",
    "sniff",
    "iter_pings",
    "count_pings",
    "summary",
]

FORMAT = "kmall"
#: ``Ping.meta["format"]``: the Kongsberg EM ping model shared with :mod:`sonarmap.io.kongsberg`.
PING_FORMAT = "kongsberg"

#: Datagram types of the KMALL format (others are indexed and skipped).
DATAGRAM_TYPES: frozenset[bytes] = frozenset(
    {b"#IIP", b"#IOP", b"#IBE", b"#IBR", b"#IBS", b"#MRZ", b"#MWC", b"#SPO", b"#SKM", b"#SVP",
     b"#SVT", b"#SCL", b"#SDE", b"#SHI", b"#CPO", b"#CHE", b"#CSV", b"#FCF", b"#SPD", b"#SPE"}
)  # fmt: skip

#: The 20 bytes every datagram starts with.
HEADER_DTYPE = np.dtype(
    [("length", "<u4"), ("type", "S4"), ("version", "u1"), ("system_id", "u1"),
     ("sounder_id", "<u2"), ("time_sec", "<u4"), ("time_nanosec", "<u4")]
)  # fmt: skip
_HEADER = HEADER_DTYPE.itemsize  # 20
_MIN_LENGTH = _HEADER + 4
#: Largest datagram accepted (a merged #MWC of a deep-water ping is a few MB).
MAX_DATAGRAM_BYTES = 1 << 26
_PARTITION = 4
_CMN = struct.Struct("<2H8B")  # numBytesCmnPart, pingCnt, rxFansPerPing ... algorithmType
_MWC_TX_INFO = struct.Struct("<3Hhf")
_MWC_TX_SECTOR = struct.Struct("<3fHh")
_MWC_RX_INFO = struct.Struct("<2H3Bb2f")
_MWC_BEAM = struct.Struct("<f4H")  # angle, start sample, detected range, sector, samples (+ f32)
_UNAVAILABLE_DEG = 200.0

#: ``#MRZ`` sounding (``EMdgmMRZ_sounding``, 120 bytes; ``numBytesPerSounding`` may be larger).
_SOUNDING_FIELDS = {
    "index": ("<u2", 0), "tx_sector": ("u1", 2), "detection_type": ("u1", 3),
    "detection_method": ("u1", 4), "quality_factor": ("<f4", 16),
    "uncertainty_vertical": ("<f4", 20), "uncertainty_horizontal": ("<f4", 24),
    "wc_beam": ("<u2", 36), "wc_range": ("<u2", 38), "wc_angle": ("<f4", 40),
    "reflectivity1": ("<f4", 48), "reflectivity2": ("<f4", 52), "angle_re_rx": ("<f4", 72),
    "twtt": ("<f4", 80), "delta_lat": ("<f4", 88), "delta_lon": ("<f4", 92), "z": ("<f4", 96),
    "y": ("<f4", 100), "x": ("<f4", 104),
}  # fmt: skip
_SOUNDING_BYTES = 120
#: KM binary sample of ``#SKM`` (first 56 bytes: type ... heave).
_KMB_DTYPE = np.dtype(
    [("type", "S4"), ("n", "<u2"), ("version", "<u2"), ("time_sec", "<u4"), ("time_nanosec", "<u4"),
     ("status", "<u4"), ("lat", "<f8"), ("lon", "<f8"), ("height", "<f4"), ("roll", "<f4"),
     ("pitch", "<f4"), ("heading", "<f4"), ("heave", "<f4")]
)  # fmt: skip
assert _KMB_DTYPE.itemsize == 56
_KMB_BYTES = 120


# ---------------------------------------------------------------------- #MWC beam walk (numba, lazy)
def _beams_py(  # pragma: no cover - jitted
    body: Any, p: int, n_beams: int, per_beam: int, bps: int, a_bits: Any, h_bits: Any,
    start: Any, det: Any, sector: Any, ns: Any, data: Any,
) -> tuple[int, int, int]:
    """Walk the #MWC beam entries from body offset ``p``: (beams decoded, status, offset);
    status 0 all beams, 1 an entry and 2 a beam's samples run past the end of ``body``."""
    size = body.shape[0]
    k = 0
    for _ in range(n_beams):
        if p + per_beam > size:
            return k, 1, p
        a_bits[k] = (np.int64(body[p]) | (np.int64(body[p + 1]) << 8) | (np.int64(body[p + 2]) << 16)
                     | (np.int64(body[p + 3]) << 24))
        start[k] = np.int64(body[p + 4]) | (np.int64(body[p + 5]) << 8)
        det[k] = np.int64(body[p + 6]) | (np.int64(body[p + 7]) << 8)
        sector[k] = np.int64(body[p + 8]) | (np.int64(body[p + 9]) << 8)
        n = np.int64(body[p + 10]) | (np.int64(body[p + 11]) << 8)
        ns[k] = n
        if per_beam >= 16:
            h_bits[k] = (np.int64(body[p + 12]) | (np.int64(body[p + 13]) << 8)
                         | (np.int64(body[p + 14]) << 16) | (np.int64(body[p + 15]) << 24))
        q = p + per_beam
        stop = q + n * bps
        if stop > size:
            return k, 2, q
        data[k] = q
        p = stop
        k += 1
    return k, 0, p


@functools.cache
def _beam_kernel() -> Any:
    from numba import njit

    return njit(cache=True, nogil=True)(_beams_py)


@dataclasses.dataclass(frozen=True, eq=False)
class _Index:
    """The complete datagrams of a file: offsets and decoded 20-byte headers."""

    path: Path
    buf: NDArray[np.uint8]
    offsets: NDArray[np.int64]
    headers: NDArray[Any]

    def of_type(self, typ: bytes) -> NDArray[np.intp]:
        return np.flatnonzero(self.headers["type"] == typ)

    def time_ns(self, row: int) -> int:
        h = self.headers[row]
        ns = int(h["time_nanosec"])
        if ns >= 1_000_000_000:
            raise DataFormatError(f"datagram time has {ns} nanoseconds (more than one second)",
                                  self.path, int(self.offsets[row]))
        with header_errors(self.path, int(self.offsets[row]), "datagram time"):
            return check_time_ns(int(h["time_sec"]) * 1_000_000_000 + ns, "datagram time")

    def counts(self) -> dict[str, int]:
        types, n = np.unique(self.headers["type"], return_counts=True)
        return {t.decode("latin-1"): int(c) for t, c in zip(types.tolist(), n.tolist())}


#: Message of each corrupt-datagram status of the walk (``kongsberg._walk`` with ``kmall=True``; as
#: :data:`kongsberg._WALK_ERRORS`).
_WALK_ERRORS = {
    2: "datagram type does not start with '#' but 0x{value:02X}: corrupt file or not a KMALL datagram "
       "stream",
    3: "datagram length field {value} is shorter than a datagram header",
    4: "datagram length field {value} is absurd (more than {max_bytes} bytes)",
    5: "datagram's trailing length {value} does not repeat its length field: corrupt length",
    6: "datagram length field runs past the end of the file although a complete datagram starts at "
       "byte {value}: corrupt length",
}


def _scan(path: Path) -> _Index:
    buf = _open_buffer(path, "KMALL file")
    offs, status, err_off, err_val = _walk(buf, MAX_DATAGRAM_BYTES, kmall=True)
    if status == 1:
        warn_partial(path, err_off, buf.size - err_off, err_val if err_val > 0 else 24, "datagram")
    elif status:
        raise _walk_error(path, buf, status, err_off, err_val, _WALK_ERRORS, MAX_DATAGRAM_BYTES)
    return _Index(path, buf, offs, records_at(buf, offs, HEADER_DTYPE))


# ---------------------------------------------------------------------- multibeam datagrams
@dataclasses.dataclass(frozen=True, eq=False)
class _MRecord:
    """One multibeam datagram (#MWC or #MRZ), from its partitions in the file."""

    rows: tuple[int, ...]  # index rows of the parts present (a prefix 1..k is decodable)
    numbers: tuple[int, ...]
    n_parts: int
    time_ns: int
    sounder: int
    system: int
    version: int
    cmn: tuple[int, ...]  # numBytesCmnPart, pingCnt, rxFansPerPing, rxFanIndex, swathsPerPing,
    # swathAlongPosition, txTransducerInd, rxTransducerInd, numRxTransducers, algorithmType

    @property
    def complete(self) -> bool:
        return len(self.numbers) == self.n_parts

    @property
    def prefix(self) -> int:
        """Number of parts 1..k present without a gap (the decodable bytes)."""
        k = 0
        for n in self.numbers:
            if n != k + 1:
                break
            k += 1
        return k

    @property
    def key(self) -> tuple[int, int, int, int]:
        return (self.system, self.sounder, self.cmn[1], self.cmn[3])


def _part_body(index: _Index, row: int) -> tuple[int, int]:
    off = int(index.offsets[row])
    return off + _HEADER + _PARTITION, off + int(index.headers["length"][row]) - 4


def _m_records(index: _Index, typ: bytes) -> tuple[list[_MRecord], list[str]]:
    """The multibeam datagrams of type ``typ``; parts are joined (and warnings' texts returned)."""
    rows = index.of_type(typ)
    name = typ.decode()
    h = index.headers
    out: list[_MRecord] = []
    notes: list[str] = []
    groups: list[list[tuple[int, int, int]]] = []
    for r in rows.tolist():
        off = int(index.offsets[r])
        if int(h["length"][r]) < _MIN_LENGTH + _PARTITION:
            raise DataFormatError(f"{name} datagram of {int(h['length'][r])} bytes has no room for its "
                                  "partition struct", index.path, off)
        n_parts, num = struct.unpack_from("<2H", index.buf, off + _HEADER)
        if not 1 <= num <= n_parts:
            raise DataFormatError(f"{name} partition {num} of {n_parts} is out of range",
                                  index.path, off + _HEADER)
        g = groups[-1] if groups else None
        same = (g is not None and g[-1][2] == n_parts and num > g[-1][1]
                and all(h[f][g[-1][0]] == h[f][r] for f in ("time_sec", "time_nanosec", "system_id",
                                                                 "sounder_id")))
        if same and g is not None:
            g.append((r, num, n_parts))
        else:
            groups.append([(r, num, n_parts)])
    for g in groups:
        r0 = g[0][0]
        off0 = int(index.offsets[r0])
        rec_rows = tuple(x[0] for x in g)
        numbers = tuple(x[1] for x in g)
        n_parts = g[0][2]
        t = index.time_ns(r0)
        if numbers[0] != 1:
            notes.append(f"{index.path}: at byte {off0}: {name} datagram lacks its first partition "
                         f"(parts {', '.join(map(str, numbers))} of {n_parts}); skipped")
            continue
        start, end = _part_body(index, r0)
        if end - start < _CMN.size:
            raise DataFormatError(f"{name} datagram is too short for its common part", index.path, off0)
        cmn = _CMN.unpack_from(index.buf, start)
        if cmn[0] < _CMN.size:
            raise DataFormatError(f"{name} common part size {cmn[0]} is smaller than its "
                                  f"{_CMN.size} bytes", index.path, start)
        out.append(_MRecord(rec_rows, numbers, n_parts, t, int(h["sounder_id"][r0]),
                            int(h["system_id"][r0]), int(h["version"][r0]), tuple(cmn)))
    return out, notes


def _body_bytes(index: _Index, rec: _MRecord) -> bytes:
    """The datagram body (common part onwards) from the parts 1..k present without a gap."""
    pieces = []
    for r in rec.rows[: rec.prefix]:
        a, b = _part_body(index, r)
        pieces.append(bytes(index.buf[a:b]))
    return b"".join(pieces)


class _Short(ValueError):
    """A struct runs past the end of the bytes available."""


class _Incomplete(Exception):
    """A ping whose missing partition leaves no decodable beam (skipped with a warning)."""


def _unpack(fmt: struct.Struct, body: bytes, p: int, what: str) -> tuple[Any, ...]:
    if p < 0 or p + fmt.size > len(body):
        raise _Short(f"{what} at body offset {p} runs past the end of the datagram")
    return fmt.unpack_from(body, p)


@dataclasses.dataclass
class _Water:
    """The decoded #MWC of one ping and fan (beams in datagram order)."""

    heave_m: float
    tilt_deg: NDArray[np.float64]
    frequency_hz: NDArray[np.float64]
    beamwidth_along_deg: NDArray[np.float64]
    n_beams_total: int
    phase_flag: int
    tvg_function: int
    tvg_offset_db: float
    sample_rate_hz: float
    sound_speed_m_s: float
    angle_deg: NDArray[np.float64]
    start: NDArray[np.int64]
    detected: NDArray[np.int64]
    detected_hires: NDArray[np.float64]
    sector: NDArray[np.int64]
    n_samples: NDArray[np.int64]
    data: NDArray[np.int64]  # body offset of each beam's amplitudes
    truncated: bool  # the beams stop early because a partition is missing


def _decode_mwc(body: bytes, complete: bool) -> _Water:
    """Decode an #MWC body.  Raises _Short/ValueError on inconsistencies; a body cut by a
    missing partition (``complete`` False) keeps the whole beams before the cut."""
    p = _CMN.unpack_from(body, 0)[0]
    n_tx_info, ntx, per_tx, _, heave = _unpack(_MWC_TX_INFO, body, p, "transmit info")
    if n_tx_info < _MWC_TX_INFO.size or per_tx < _MWC_TX_SECTOR.size:
        raise ValueError(f"transmit info of {n_tx_info} bytes / sectors of {per_tx} bytes are too small")
    if ntx < 1:
        raise ValueError("no transmit sector")
    p += n_tx_info
    if p + ntx * per_tx > len(body):
        raise _Short(f"{ntx} transmit sectors of {per_tx} bytes run past the end of the datagram")
    tx = [_MWC_TX_SECTOR.unpack_from(body, p + i * per_tx) for i in range(ntx)]
    p += ntx * per_tx
    n_rx_info, n_beams, per_beam, phase, tvg_x, tvg_c, fs, c = _unpack(_MWC_RX_INFO, body, p,
                                                                         "receiver info")
    if n_rx_info < _MWC_RX_INFO.size or per_beam < _MWC_BEAM.size:
        raise ValueError(f"receiver info of {n_rx_info} bytes / beam entries of {per_beam} bytes "
                         "are too small")
    if phase not in (0, 1, 2):
        raise ValueError(f"phase flag {phase} is not 0, 1 or 2")
    if not (math.isfinite(fs) and 1.0 <= fs <= 1e8):
        raise ValueError(f"sample frequency {fs} Hz is not plausible")
    sound_speed = check_sound_speed(c)
    assert sound_speed is not None
    p += n_rx_info
    bytes_per_sample = 1 + phase
    # every beam needs at least its entry: a beam count beyond the bytes is corrupt
    if complete and p + n_beams * per_beam > len(body):
        raise _Short(f"{n_beams} beams of {per_beam}-byte entries run past the end of the datagram")
    raw = np.frombuffer(body, dtype=np.uint8)
    arrs = [np.zeros(n_beams, dtype=np.int64) for _ in range(7)]
    k, status, where = _beam_kernel()(raw, p, n_beams, per_beam, bytes_per_sample, *arrs)
    a_bits, h_bits, start, det, sector, ns, data = (a[:k] for a in arrs)
    truncated = status != 0
    if truncated and complete:
        what = "beam entry" if status == 1 else "beam's samples"
        raise _Short(f"{what} at body offset {where} runs past the end of the datagram")
    angle = a_bits.astype(np.uint32).view(np.float32).astype(np.float64)
    hires = h_bits.astype(np.uint32).view(np.float32).astype(np.float64)
    if per_beam < 16:
        hires[:] = math.nan
    bad = ~(np.isfinite(angle) & (np.abs(angle) <= 180.0))
    if bad.any():
        raise ValueError(f"beam pointing angle {angle[bad][0]} deg is not an angle")
    if sector.size and int(sector.max()) >= ntx:
        raise ValueError(f"a beam's transmit sector {int(sector.max())} is >= the {ntx} sectors")
    if complete and len(body) - where > 8:
        raise ValueError(f"{len(body) - where} bytes are left over after the last beam (beam count "
                         "or sample counts corrupt)")
    return _Water(
        heave_m=float(heave),
        tilt_deg=np.array([t[0] for t in tx], dtype=np.float64),
        frequency_hz=np.array([t[1] for t in tx], dtype=np.float64),
        beamwidth_along_deg=np.array([t[2] for t in tx], dtype=np.float64),
        n_beams_total=int(n_beams), phase_flag=int(phase), tvg_function=int(tvg_x),
        tvg_offset_db=float(tvg_c), sample_rate_hz=float(fs), sound_speed_m_s=float(sound_speed),
        angle_deg=angle, start=start, detected=det, detected_hires=hires, sector=sector,
        n_samples=ns, data=data, truncated=truncated,
    )


_PING_INFO_MIN = 144  # through latitude, longitude, ellipsoid height


def _decode_mrz(body: bytes) -> dict[str, Any]:
    """Ping info and main soundings of an #MRZ body (raises _Short/ValueError)."""
    p = _CMN.unpack_from(body, 0)[0]
    (n_info,) = _unpack(struct.Struct("<H"), body, p, "ping info")
    if n_info < _PING_INFO_MIN or p + n_info > len(body):
        raise _Short(f"ping info of {n_info} bytes does not fit (needs {_PING_INFO_MIN})")
    ntx, per_tx = struct.unpack_from("<2H", body, p + 92)
    heading, c, tx_depth, wl_z = struct.unpack_from("<4f", body, p + 96)
    lat, lon, height = struct.unpack_from("<2df", body, p + 124)
    p += n_info
    if per_tx < 36 or p + ntx * per_tx > len(body):
        raise _Short(f"{ntx} transmit sectors of {per_tx} bytes do not fit")
    sectors = [struct.unpack_from("<4B7f", body, p + i * per_tx) for i in range(ntx)]
    p += ntx * per_tx
    n_rx, n_main, n_valid, per_snd, wc_fs = _unpack(struct.Struct("<4Hf"), body, p, "receiver info")
    if n_rx < 32 or p + n_rx > len(body):
        raise _Short(f"receiver info of {n_rx} bytes does not fit")
    n_extra, n_classes, per_class = struct.unpack_from("<3H", body, p + 26)
    p += n_rx + n_classes * per_class
    if per_snd < _SOUNDING_BYTES:
        raise ValueError(f"soundings of {per_snd} bytes are smaller than {_SOUNDING_BYTES}")
    if p + (n_main + n_extra) * per_snd > len(body):
        raise _Short(f"{n_main + n_extra} soundings of {per_snd} bytes run past the end of the datagram")
    dt = np.dtype({"names": list(_SOUNDING_FIELDS), "formats": [v[0] for v in _SOUNDING_FIELDS.values()],
                   "offsets": [v[1] for v in _SOUNDING_FIELDS.values()], "itemsize": per_snd})
    snd = np.frombuffer(body, dtype=dt, count=n_main, offset=p)
    return {
        "heading": float(heading), "sound_speed": float(c), "tx_depth": float(tx_depth),
        "water_level_z": float(wl_z), "lat": float(lat), "lon": float(lon), "height": float(height),
        "n_valid": int(n_valid), "wc_sample_rate": float(wc_fs), "soundings": snd,
        "pulse_s": np.array([s[10] for s in sectors], dtype=np.float64),
        "bandwidth_hz": np.array([s[9] for s in sectors], dtype=np.float64),
        "tx_tilt": np.array([s[5] for s in sectors], dtype=np.float64),
    }


# ---------------------------------------------------------------------- installation text
def parse_kmall_installation_text(text: str) -> dict[str, float | str]:
    """The ``#IIP`` installation text as a flat dict (numbers as float).

    Items are separated by ``,`` (and line breaks); an item ``GROUP:KEY=value;KEY=value;...``
    gives ``GROUP.KEY`` entries, ``KEY=value`` a ``KEY`` entry and ``GROUP:value`` a ``GROUP``
    entry.  (The EM ``.all`` text is plain ``KEY=value,``:
    :func:`sonarmap.io.kongsberg.parse_installation_text`.)

    Examples
    --------
    >>> parse_kmall_installation_text("EMXV:EM2040P,\\nTRAI_TX1:N=218;X=1.5;R=0.1;,EMXI:SWLZ=-0.4,")
    {'EMXV': 'EM2040P', 'TRAI_TX1.N': 218.0, 'TRAI_TX1.X': 1.5, 'TRAI_TX1.R': 0.1, 'EMXI.SWLZ': -0.4}
    """

    def val(v: str) -> float | str:
        v = v.strip()
        try:
            f = float(v)
        except ValueError:
            return v
        return f if math.isfinite(f) else v

    out: dict[str, float | str] = {}
    for item in text.replace("\r", ",").replace("\n", ",").split(","):
        item = item.strip()
        if not item:
            continue
        colon, eq = item.find(":"), item.find("=")
        if colon > 0 and (eq < 0 or colon < eq):
            group, rest = item[:colon].strip(), item[colon + 1 :]
            if "=" not in rest:
                out[group] = val(rest)
                continue
            for sub in rest.split(";"):
                key, sep, v = sub.partition("=")
                if sep and key.strip():
                    out[f"{group}.{key.strip()}"] = val(v)
        elif eq > 0:
            out[item[:eq].strip()] = val(item[eq + 1 :])
    return out


# ---------------------------------------------------------------------- the file
@dataclasses.dataclass(frozen=True, eq=False)
class _Ping:
    mwc: _MRecord
    mrz: _MRecord | None


class KmallFile(ClosingFile):
    """Lazy, memory-mapped access to the water-column pings of a ``.kmall`` file.

    One ping per #MWC datagram, i.e. per ping counter and RX fan (head / swath); pings in time
    order (ties: RX fan index).

    Parameters
    ----------
    path : path-like
        The ``.kmall`` or the ``.kmwcd`` file of a recording.  The water column (#MWC) is read
        from the ``.kmall`` when it holds any, else from the ``.kmwcd`` beside it (same stem);
        depth, navigation, attitude and installation from the ``.kmall`` (from the given file when
        there is no ``.kmall``).
    geometry : SonarGeometry, preset name or JSON path, optional
        Overrides the geometry derived from each ping (its shape must match).

    Raises
    ------
    DataFormatError
        Missing, non-regular or corrupt files (the message gives the byte offset), or no #MWC
        datagram.

    Examples
    --------
    >>> with KmallFile("0001_20200101_000000.kmall") as f:   # doctest: +SKIP
    ...     print(len(f), f[0].shape)
    """

    def __init__(self, path: str | os.PathLike[str], *,
                 geometry: SonarGeometry | str | os.PathLike[str] | None = None) -> None:
        self.path = require_regular_file(path, "KMALL file")
        self._override = None if geometry is None else as_geometry(geometry)
        kmall_path, wcd_path = sibling_paths(self.path)
        given = _scan(self.path)
        if given.of_type(b"#MWC").size or wcd_path is None or wcd_path == self.path:
            self._wc = given
        else:
            self._wc = _scan(require_regular_file(wcd_path, "KMALL .kmwcd file"))
        # depth, navigation and installation from the .kmall (from the given file without one)
        if kmall_path is not None and kmall_path != self.path:
            self.index = _scan(require_regular_file(kmall_path, "KMALL .kmall file"))
        else:
            self.index = given
        mwc, notes = _m_records(self._wc, b"#MWC")
        mrz, notes_z = _m_records(self.index, b"#MRZ")
        for note in notes + notes_z:
            warnings.warn(note, PartialFrameWarning, stacklevel=3)
        depth = {r.key: r for r in mrz if r.complete}
        self.records = sorted((_Ping(r, depth.get(r.key)) for r in mwc),
                              key=lambda p: (p.mwc.time_ns, p.mwc.cmn[3], p.mwc.cmn[1]))
        if not self.records:
            extra = "" if wcd_path is not None else " and no .kmwcd file beside it"
            raise DataFormatError(f"no water-column (#MWC) datagrams{extra}", self._wc.path)
        for p in self.records:
            if not p.mwc.complete:
                r = p.mwc
                missing = sorted(set(range(1, r.n_parts + 1)) - set(r.numbers))
                warnings.warn(
                    f"{self._wc.path}: at byte {int(self._wc.offsets[r.rows[0]])}: ping {r.cmn[1]} "
                    f"(RX fan {r.cmn[3]}) is incomplete (partition {', '.join(map(str, missing))} "
                    f"of {r.n_parts} missing); yielded with the whole beams before the gap",
                    PartialFrameWarning, stacklevel=3)
        self._ancillary: dict[str, Any] | None = None

    # ------------------------------------------------------------------ sequence protocol
    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, index: int) -> Ping:
        i = check_index(index, len(self.records))
        try:
            return self._ping(self.records[i])
        except _Incomplete as exc:
            raise DataFormatError(str(exc).replace("; skipped", "")) from None

    def __iter__(self) -> Iterator[Ping]:
        for rec in self.records:
            try:
                ping = self._ping(rec)
            except _Incomplete as exc:
                warnings.warn(str(exc), PartialFrameWarning, stacklevel=2)
                continue
            yield ping

    def pings(self, start: int = 0, stop: int | None = None) -> Iterator[Ping]:
        """Pings ``start:stop`` of ``iter(self)``, without decoding the complete pings before ``start``.

        Iteration skips an incomplete ping that has no whole beam (with a warning), so positions
        are those of ``list(self)``; an incomplete ping before ``start`` is decoded to learn
        whether it counts.

        Raises
        ------
        InputError
            If ``start`` or ``stop`` is not a non-negative integer.
        """
        start, stop = check_ping_range(start, stop)
        pos = 0
        for rec in self.records:
            if stop is not None and pos >= stop:
                return
            if pos < start and rec.mwc.complete:  # a complete ping always yields a Ping
                pos += 1
                continue
            try:
                ping = self._ping(rec)
            except _Incomplete as exc:
                warnings.warn(str(exc), PartialFrameWarning, stacklevel=2)
                continue
            if pos >= start:
                yield ping
            pos += 1

    def close(self) -> None:
        """Release the memory map (pings already returned stay valid: images are copies)."""
        self.records = []
        self._ancillary = None
        empty = _Index(self.path, np.zeros(0, np.uint8), np.zeros(0, np.int64), np.zeros(0, HEADER_DTYPE))
        self.index = self._wc = empty

    def __repr__(self) -> str:
        return f"KmallFile({str(self.path)!r}, pings={len(self)})"

    @property
    def water_column_path(self) -> Path:
        """The file the #MWC datagrams are read from (the ``.kmall`` or its ``.kmwcd``)."""
        return self._wc.path

    # ------------------------------------------------------------------ ancillary
    @property
    def ancillary(self) -> dict[str, Any]:
        """Installation, position (#SPO) and attitude (#SKM), parsed on first use."""
        if self._ancillary is None:
            self._ancillary = {"installation": self._installation(), "position": self._positions(),
                               "attitude": self._attitude()}
        return self._ancillary

    def _installation(self) -> dict[str, float | str]:
        idx = self.index
        for r in idx.of_type(b"#IIP").tolist():
            off, length = int(idx.offsets[r]), int(idx.headers["length"][r])
            if length < _MIN_LENGTH + 6:
                raise DataFormatError("#IIP datagram is too short for its common part", idx.path, off)
            (n_cmn,) = struct.unpack_from("<H", idx.buf, off + _HEADER)
            # numBytesCmnPart, info, status (uint16 each), then the text up to numBytesCmnPart
            stop = min(off + _HEADER + max(n_cmn, 6), off + length - 4)
            raw = bytes(idx.buf[off + _HEADER + 6 : stop]).split(b"\0", 1)[0]
            return parse_kmall_installation_text(raw.decode("utf-8", errors="replace"))
        return {}

    def _positions(self) -> _Series:
        idx = self.index
        t_list, vals = [], []
        for r in idx.of_type(b"#SPO").tolist():
            off, length = int(idx.offsets[r]), int(idx.headers["length"][r])
            if length < _HEADER + 8 + 40 + 4:
                raise DataFormatError("#SPO datagram is too short for its position block", idx.path, off)
            (n_cmn,) = struct.unpack_from("<H", idx.buf, off + _HEADER)
            p = off + _HEADER + max(n_cmn, 8)
            if p + 40 > off + length - 4:
                raise DataFormatError("#SPO position block runs past the end of the datagram",
                                      idx.path, off)
            ts, tns, quality, lat, lon, sog, cog, _ = struct.unpack_from("<2If2d3f", idx.buf, p)
            if not (abs(lat) <= 90 and abs(lon) <= 180) or tns >= 1_000_000_000:
                continue
            t = ts * 1_000_000_000 + tns if ts else idx.time_ns(r)
            t_list.append(t)
            vals.append((lat, lon, quality, sog, cog))
        t = np.array(t_list, dtype=np.int64)
        v = np.array(vals, dtype=np.float64).reshape(-1, 5)
        t, keep = np.unique(t, return_index=True)
        v = v[keep]
        return _Series(t, {"latitude_deg": v[:, 0], "longitude_deg": v[:, 1],
                           "position_fix_quality_m": v[:, 2], "speed_over_ground_m_s": v[:, 3],
                           "course_over_ground_deg": v[:, 4]}, 0, angles=("course_over_ground_deg",))

    def _attitude(self) -> _Series:
        idx = self.index
        chunks = []
        for r in idx.of_type(b"#SKM").tolist():
            off, length = int(idx.offsets[r]), int(idx.headers["length"][r])
            end = off + length - 4
            if off + _HEADER + 12 > end:
                raise DataFormatError("#SKM datagram is too short for its info part", idx.path, off)
            n_info, _, _, _, n, per = struct.unpack_from("<H2B3H", idx.buf, off + _HEADER)
            p = off + _HEADER + n_info
            if n_info < 12 or per < _KMB_BYTES or p + n * per > end:
                raise DataFormatError(f"#SKM datagram: {n} samples of {per} bytes do not fit",
                                      idx.path, off)
            if n == 0:
                continue
            rows = np.ascontiguousarray(idx.buf[(p + np.arange(n) * per)[:, None] + np.arange(56)])
            chunks.append(rows.view(_KMB_DTYPE).reshape(-1))
        e = np.concatenate(chunks) if chunks else np.zeros(0, _KMB_DTYPE)
        ok = (e["type"] == b"#KMB") & (e["time_nanosec"] < 1_000_000_000)
        for f in ("roll", "pitch", "heading", "heave"):
            ok &= np.isfinite(e[f]) & (np.abs(e[f]) <= 1000)
        e = e[ok]
        t = e["time_sec"].astype(np.int64) * 1_000_000_000 + e["time_nanosec"].astype(np.int64)
        t, keep = np.unique(t, return_index=True)
        e = e[keep]
        return _Series(t, {"roll_deg": e["roll"].astype(np.float64), "pitch_deg": e["pitch"].astype(np.float64),
                           "heave_m": e["heave"].astype(np.float64),
                           "heading_deg": e["heading"].astype(np.float64)}, 0, angles=("heading_deg",))

    # ------------------------------------------------------------------ pings
    def geometry(self, index: int = 0) -> SonarGeometry:
        """Geometry of ping ``index``."""
        return self[index].geometry

    def _ping(self, rec: _Ping) -> Ping:
        m = rec.mwc
        off = int(self._wc.offsets[m.rows[0]])
        what = f"#MWC datagram of ping {m.cmn[1]} (RX fan {m.cmn[3]})"
        body = _body_bytes(self._wc, m)
        with header_errors(self._wc.path, off, what):
            try:
                w = _decode_mwc(body, m.complete)
            except _Short as exc:
                if m.complete:
                    raise
                raise _Incomplete(f"{self._wc.path}: at byte {off}: {what} is incomplete and its "
                                  f"partitions received end early ({exc}); skipped") from None
            n = w.angle_deg.size
            if n == 0 and w.truncated:
                raise _Incomplete(f"{self._wc.path}: at byte {off}: {what} is incomplete and has no "
                                  "whole beam before the missing partition; skipped")
            if n == 0:
                raise ValueError("no beams")
            azimuth, order, s0, n_bins = _beam_layout(w.angle_deg, w.start, w.n_samples)
            freq = float(np.mean(w.frequency_hz))
            if not (math.isfinite(freq) and freq > 0):
                freq = 0.0
            along = w.beamwidth_along_deg[np.isfinite(w.beamwidth_along_deg)]
            geom = _ping_geometry(np.ascontiguousarray(azimuth[order]).tobytes(), s0, n_bins,
                                  w.sound_speed_m_s, w.sample_rate_hz, freq,
                                  f"em{m.sounder}-{m.system}-rx{m.cmn[7]}",
                                  float(along.max()) if along.size else None)
        if self._override is not None:
            geom = self._override
        by_beam = np.empty((n, n_bins), dtype=np.float32)
        _kernels().fill(np.frombuffer(body, dtype=np.uint8), w.data, w.n_samples, w.start - s0,
                        order.astype(np.int64), _AMP_LUT, by_beam)
        image = np.ascontiguousarray(by_beam.T)
        return Ping(image=image, geometry=geom, time_ns=m.time_ns,
                    source=f"{self._wc.path}#fan{m.cmn[3]}/ping{m.cmn[1]}",
                    meta=self._meta(rec, w, order, s0, n_bins))

    def _meta(self, rec: _Ping, w: _Water, order: NDArray[np.intp], s0: int, n_bins: int) -> dict[str, Any]:
        m = rec.mwc
        step = w.sound_speed_m_s / (2.0 * w.sample_rate_hz)
        dr = w.detected[order]
        det = dr.astype(np.float64)
        det[dr == 0] = math.nan
        det_bin = dr - s0
        det_bin[(dr == 0) | (det_bin < 0) | (det_bin >= n_bins)] = -1
        hires = w.detected_hires[order]
        n = int(w.angle_deg.size)
        meta: dict[str, Any] = {
            "format": PING_FORMAT,
            "file_format": FORMAT,
            "em_model": m.sounder,
            "system_id": m.system,
            "datagram_version": m.version,
            "ping_counter": m.cmn[1],
            "rx_fans_per_ping": m.cmn[2],
            "rx_fan_index": m.cmn[3],
            "swaths_per_ping": m.cmn[4],
            "swath_along_position": m.cmn[5],
            "tx_transducer_index": m.cmn[6],
            "rx_transducer_index": m.cmn[7],
            "complete": m.complete and not w.truncated and n == w.n_beams_total,
            "n_datagrams": m.n_parts,
            "n_datagrams_received": len(m.numbers),
            "n_beams_total": w.n_beams_total,
            "n_beams_received": n,
            "sound_speed_m_s": w.sound_speed_m_s,
            "sample_rate_hz": w.sample_rate_hz,
            "range_per_sample_m": step,
            "start_range_sample": s0,
            "tvg_function": w.tvg_function,
            "tvg_offset_db": w.tvg_offset_db,
            "tx_time_heave_m": w.heave_m,
            "phase_flag": w.phase_flag,
            "n_tx_sectors": int(w.tilt_deg.size),
            "tx_sector_tilt_deg": w.tilt_deg,
            "tx_sector_frequency_hz": w.frequency_hz,
            "tx_sector_beamwidth_along_deg": w.beamwidth_along_deg,
            "amplitude_db_full_scale": AMPLITUDE_DB_FULL_SCALE,
            "amplitude_db_step": AMPLITUDE_DB_STEP,
            "beam_pointing_angle_deg": w.angle_deg[order],
            "beam_index": order.astype(np.int64),
            "beam_tx_sector": w.sector[order],
            "beam_start_sample": w.start[order],
            "beam_n_samples": w.n_samples[order],
            "detected_range_samples": det,
            "detected_range_samples_hires": np.where(dr == 0, math.nan, hires),
            "detected_range_m": det * step,
            "detected_bin": det_bin,
            "water_column_file": str(self._wc.path),
            "ancillary_file": str(self.index.path),
        }
        if rec.mrz is not None:
            self._mrz_meta(meta, rec.mrz, order, w.sample_rate_hz)
        anc = self.ancillary
        if "latitude_deg" not in meta:
            pos = anc["position"].at(np.array([m.time_ns], dtype=np.int64))[0]
            if pos is not None:
                meta.update(pos[0])
                meta["position_gap_s"] = pos[1]
                meta["position_source"] = "SPO"
        att = anc["attitude"].at(np.array([m.time_ns], dtype=np.int64))[0]
        if att is not None:
            mrz_heading = meta.get("heading_deg")
            meta.update(att[0])
            meta["attitude_gap_s"] = att[1]
            meta["attitude_source"] = "SKM"
            if mrz_heading is not None:
                meta["heading_deg"] = mrz_heading  # the ping's own (exact at transmit)
        inst = anc["installation"]
        if inst:
            meta.update(_mounting(inst, m.cmn[6], m.cmn[7]))
            meta["installation"] = dict(inst)
        return meta

    def _mrz_meta(self, meta: dict[str, Any], rec: _MRecord, order: NDArray[np.intp], fs: float) -> None:
        off = int(self.index.offsets[rec.rows[0]])
        with header_errors(self.index.path, off, f"#MRZ datagram of ping {rec.cmn[1]} (RX fan {rec.cmn[3]})"):
            z = _decode_mrz(_body_bytes(self.index, rec))
        meta["mrz_sound_speed_m_s"] = z["sound_speed"]
        meta["mrz_tx_transducer_depth_m"] = z["tx_depth"]
        meta["mrz_water_level_z_m"] = z["water_level_z"]
        meta["mrz_n_valid"] = z["n_valid"]
        if z["pulse_s"].size:
            pulse = round(float(np.mean(z["pulse_s"])) * 1e6, 3)
            if math.isfinite(pulse) and pulse > 0:
                meta["pulse_width_us"] = pulse
        effective = effective_pulse_us(z["bandwidth_hz"])
        if effective is not None:
            meta["effective_pulse_us"] = effective
        if abs(z["lat"]) <= 90 and abs(z["lon"]) <= 180:
            meta["latitude_deg"] = z["lat"]
            meta["longitude_deg"] = z["lon"]
            meta["position_gap_s"] = 0.0
            meta["position_source"] = "MRZ"
            if math.isfinite(z["height"]):
                meta["ellipsoid_height_m"] = z["height"]
        if math.isfinite(z["heading"]) and abs(z["heading"]) <= 360:
            meta["heading_deg"] = z["heading"] % 360.0
        snd = z["soundings"]
        n_total = int(meta["n_beams_total"])
        beam = snd["wc_beam"].astype(np.int64)
        # sounding -> water-column beam: by WCBeamNumb when it is a permutation of the beams,
        # else by position (one sounding per beam)
        if snd.size == n_total and np.array_equal(np.sort(beam), np.arange(n_total)):
            of_beam = np.empty(n_total, np.int64)
            of_beam[beam] = np.arange(n_total)
        elif snd.size == n_total:
            of_beam = np.arange(n_total)
        else:
            meta["mrz_matched"] = False
            return
        meta["mrz_matched"] = True
        pos = meta["beam_index"]
        s = snd[of_beam[pos]]
        f64 = {k: s[k].astype(np.float64) for k in ("twtt", "angle_re_rx", "z", "y", "x", "quality_factor",
                                                     "reflectivity1", "reflectivity2", "wc_range",
                                                     "uncertainty_vertical", "uncertainty_horizontal")}
        meta["raw_twtt_s"] = f64["twtt"]
        meta["raw_range_samples"] = f64["twtt"] * fs
        meta["raw_beam_angle_deg"] = f64["angle_re_rx"]
        meta["raw_valid"] = (s["detection_type"] != 2) & (s["detection_method"] != 0)
        meta["mrz_detection_type"] = s["detection_type"].astype(np.int64)
        meta["mrz_detection_method"] = s["detection_method"].astype(np.int64)
        meta["mrz_quality_factor"] = f64["quality_factor"]
        meta["mrz_uncertainty_vertical_m"] = f64["uncertainty_vertical"]
        meta["mrz_uncertainty_horizontal_m"] = f64["uncertainty_horizontal"]
        meta["mrz_reflectivity1_db"] = f64["reflectivity1"]
        meta["mrz_reflectivity2_db"] = f64["reflectivity2"]
        meta["mrz_wc_range_samples"] = f64["wc_range"]
        meta["mrz_z_m"] = f64["z"]
        meta["mrz_y_m"] = f64["y"]
        meta["mrz_x_m"] = f64["x"]


def _mounting(inst: dict[str, float | str], tx_ind: int, rx_ind: int) -> dict[str, Any]:
    """Lever arms (m) and mounting angles (deg) of the fan's TX and RX transducers (``TRAI_*``)."""

    def num(key: str) -> float | None:
        v = inst.get(key)
        return float(v) if isinstance(v, float) and math.isfinite(v) else None

    out: dict[str, Any] = {}
    for role, name, alt in (("tx", f"TRAI_TX{tx_ind + 1}", f"TRAI_HD{tx_ind + 1}"),
                            ("rx", f"TRAI_RX{rx_ind + 1}", f"TRAI_HD{rx_ind + 1}")):
        pre = name if any(k.startswith(name + ".") for k in inst) else alt
        xyz = [num(f"{pre}.{a}") for a in "XYZ"]
        rph = [num(f"{pre}.{a}") for a in "RPH"]
        if all(v is not None for v in xyz):
            out[f"{role}_lever_arm_m"] = np.array(xyz, dtype=np.float64)
        if all(v is not None for v in rph):
            out[f"{role}_mounting_deg"] = np.array(rph, dtype=np.float64)
        out[f"{role}_transducer"] = pre
    wlz = num("EMXI.SWLZ")
    if wlz is not None:
        out["waterline_z_m"] = wlz
    return out


# ---------------------------------------------------------------------- registry hooks
def sniff(path: Path, head: bytes) -> bool:
    """A KMALL datagram at the start: plausible length, a known ``#XXX`` type, a plausible time,
    and the trailing length repeated where the length says (when within ``head``)."""
    if len(head) < _HEADER:
        return False
    h = np.frombuffer(head[:_HEADER], dtype=HEADER_DTYPE)[0]
    length = int(h["length"])
    if not _MIN_LENGTH <= length <= MAX_DATAGRAM_BYTES or bytes(h["type"]) not in DATAGRAM_TYPES:
        return False
    if int(h["time_nanosec"]) >= 1_000_000_000:
        return False
    if int(h["time_sec"]) * 1_000_000_000 > MAX_PLAUSIBLE_TIME_NS:
        return False
    if length <= len(head):
        return int.from_bytes(head[length - 4 : length], "little") == length
    return True


def iter_pings(path: str | os.PathLike[str], *, geometry: GeometrySpec = None, start: int = 0,
               stop: int | None = None, **_: Any) -> Iterator[Ping]:
    """:meth:`Reader.iter_pings <sonarmap.io.reader.Reader.iter_pings>` of KMALL recordings:
    water-column pings ``start:stop`` (one per ping counter and RX fan); the pings before ``start``
    are not decoded (:meth:`KmallFile.pings`).  File errors: see :class:`KmallFile`."""
    start, stop = check_ping_range(start, stop)
    with KmallFile(path, geometry=geometry) as f:
        if start == 0 and stop is None:
            yield from f
        else:
            yield from f.pings(start, stop)


def sibling_paths(path: str | os.PathLike[str]) -> tuple[Path | None, Path | None]:
    """The ``(.kmall, .kmwcd)`` pair of a recording given either file (``None`` where absent).

    SIS 5 may write the water column to a ``.kmwcd`` file beside the ``.kmall`` (same stem);
    a file with another extension is taken as the ``.kmall``.
    """
    p = Path(path)
    if p.suffix.lower() == ".kmwcd":
        return find_sibling(p, ".kmall"), p
    return p, find_sibling(p, ".kmwcd")


def recording_key(path: str | os.PathLike[str]) -> tuple[str, ...]:
    """The recording a file belongs to: its ``.kmall`` / ``.kmwcd`` pair (read once when both are given)."""
    return pair_key(sibling_paths(path))


def count_pings(path: str | os.PathLike[str]) -> int:
    """Number of water-column pings (#MWC datagrams with their first partition), headers only."""
    p = require_regular_file(path, "KMALL file")
    idx = _scan(p)
    recs, _ = _m_records(idx, b"#MWC")
    wcd = sibling_paths(p)[1]
    if not recs and wcd is not None and wcd != p:
        recs, _ = _m_records(_scan(require_regular_file(wcd, "KMALL .kmwcd file")), b"#MWC")
    return len(recs)


def summary(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Ping count, RX fans, time span, first ping's geometry and datagram counts."""
    with KmallFile(path) as f:
        recs = [r.mwc for r in f.records]
        first = f[0]
        details: dict[str, Any] = {
            "em_model": recs[0].sounder,
            "rx_fans": ", ".join(str(x) for x in sorted({r.cmn[3] for r in recs})),
            "incomplete_pings": sum(1 for r in recs if not r.complete),
            "pings_with_depth_datagram": sum(1 for r in f.records if r.mrz is not None),
            "sound_speed_m_s": first.meta["sound_speed_m_s"],
            "sample_rate_hz": first.meta["sample_rate_hz"],
            "water_column_file": str(f.water_column_path),
            "datagrams": ", ".join(f"{k} {v}" for k, v in f.index.counts().items()),
        }
        if f.water_column_path != f.index.path:
            details["datagrams .kmwcd"] = ", ".join(f"{k} {v}" for k, v in f._wc.counts().items())
        return make_summary(FORMAT, path, n_pings=len(recs), geometry=first.geometry,
                            time_start_ns=recs[0].time_ns, time_end_ns=recs[-1].time_ns, **details)
