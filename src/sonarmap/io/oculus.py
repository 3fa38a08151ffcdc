"""Blueprint Subsea Oculus multibeam sonars: network ``SimplePingResult`` streams and ViewPoint logs.

Three containers are read, all yielding the same decoded ``SimplePingResult`` messages:

``raw`` (network stream, e.g. liboculus test data)
    Concatenated messages, each a 16-byte ``OculusMessageHeader`` (``oculusId`` 0x4F53, i.e. the
    bytes ``b"SO"``; ``msgId``; ``msgVersion``; ``payloadSize``) followed by ``payloadSize`` bytes.
    Only ``msgId`` 0x23 (``SimplePingResult``) carries pings; other messages are skipped.  The
    stream has no wall clock (the sonar's own ``pingStartTime``, of undocumented unit and epoch,
    is kept in ``Ping.meta["ping_start_time"]``), so ping ``i`` is given the time
    ``start + i / rate``: ``start`` is ``start_time_ns=`` when the caller passes it (integer ns
    since the Unix epoch), else the file's modification time; ``rate`` is ``rate_hz=`` when
    passed, else 10 Hz (a 0.1 s spacing, :data:`DEFAULT_RAW_INTERVAL_S`; the fire message's
    ``pingRate`` is a maximum-rate setting, not the rate achieved).  Times are so unique and
    increasing, and ``Ping.meta["time_source"]`` says where they came from:
    ``"file_mtime+order"``, ``"file_mtime+rate_hz"``, ``"start_time_ns+order"`` or
    ``"start_time_ns+rate_hz"`` (``"log"`` for the time stamps of ViewPoint logs, ``"none"``
    for a log row without one).  ``sonarmap info`` shows it.
``log-v1`` (ViewPoint ``.oculus`` binary log, Blueprint's ``RmLogHeader``/``RmLogItem``)
    A file header (magic 0x11223344, its own size in ``sizeHeader``) then items (magic 0xAABBCCDD,
    ``sizeHeader``, ``type``, ``version``, ``time`` (double, seconds since the epoch),
    ``compression`` (0 none, 1 Qt ``qCompress``: 4-byte big-endian length + zlib), ``originalSize``,
    ``payloadSize``) with natural C alignment.  Items of type 10 (``rt_oculusSonar``) hold one
    network message.
``log-v2`` (ViewPoint ``.oculus`` SQLite database)
    Only partly described in public: a ``data`` table whose last BLOB column holds a network
    message and a ``timestamp``-like column.  Rows whose blob is an Oculus ``SimplePingResult``
    are read; the time unit is inferred from the magnitude (s, ms, µs or ns since the epoch).

Message versions: ``msgVersion`` 2 is ``SimplePingResult2`` (adds heading/pitch/roll, double
``pingStartTime``); anything else is version 1.  Fire-message flag bit 2 (0x04) means each range
row is prefixed by a 4-byte gain (float32, kept in ``Ping.meta["row_gain"]``); the image is
range-major (``nRanges`` rows of ``nBeams`` samples of 8/16/24/32 bits).

Geometry: the per-beam bearing table (int16, 1/100 degree) gives ``azimuth_rad`` directly -
Oculus bearings are negative on the left (port) side of the image, positive to starboard, which
is our convention.  Range of row ``i`` is ``i * rangeResolution``.

Hardening: only regular files are opened (FIFOs and devices are refused); one message may hold at
most :data:`~sonarmap.io._binary.MAX_PING_BYTES` (64 MiB), and a compressed log item is inflated
into at most its declared size (so a small "zip bomb" item cannot exhaust memory); the SQLite log
is opened read-only through a percent-encoded ``file:`` URI (paths with ``#``, ``?``, ``%`` or
spaces work and nothing is ever created) with quoted column names.  Plausibility checks:
``rangeResolution`` in (0, 10) m with the whole window within 1 km; ``speedOfSoundUsed`` 0
(unset: 1500 m/s is assumed) or 1300-1700 m/s; ``frequency`` 0 (unset) or 10 kHz-10 MHz;
``pingStartTime`` finite and non-negative; log time stamps 0 or in the years 1970-2200.
"""

from __future__ import annotations

import functools
import math
import os
import sqlite3
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from sonarmap.errors import DataFormatError, InputError
from sonarmap.geometry import SonarGeometry, as_geometry, oculus_azimuth_beamwidth_rad
from sonarmap.io._binary import (
    MAX_PING_BYTES,
    MAX_PLAUSIBLE_TIME_NS,
    MAX_WINDOW_M,
    U8_SCALE,
    ClosingFile,
    check_index,
    check_plausible,
    check_sound_speed,
    check_time_ns,
    count_container_pings,
    iter_indexed,
    header_errors,
    make_summary,
    map_file,
    warn_partial,
)
from sonarmap._files import decompress_bounded, open_regular, require_regular_file
from sonarmap.ping import Ping

__all__ = [
    "FORMAT",
    "DEFAULT_RAW_INTERVAL_S",
    "CLOCKLESS_TIME_SOURCES",
    "OCULUS_ID",
    "MSG_SIMPLE_PING_RESULT",
    "OculusFile",
    "decode_simple_ping",
    "sniff",
    "iter_pings",
    "count_pings",
    "summary",
]

FORMAT = "oculus"
#: Spacing of the pings of a raw network capture without ``rate_hz`` (s).
DEFAULT_RAW_INTERVAL_S = 0.1
OCULUS_ID = 0x4F53
MSG_SIMPLE_PING_RESULT = 0x23
LOG_FILE_MAGIC = 0x11223344
LOG_ITEM_MAGIC = 0xAABBCCDD
RT_OCULUS_SONAR = 10
SQLITE_MAGIC = b"SQLite format 3\x00"

FLAG_RANGE_METERS = 0x01
FLAG_16BIT = 0x02
FLAG_SEND_GAIN = 0x04
FLAG_SIMPLE = 0x08

HEADER = struct.Struct("<HHHHHIH")  # oculusId src dst msgId msgVersion payloadSize partNumber
FIRE_V1 = struct.Struct("<BBBBBdddd")  # masterMode pingRate networkSpeed gamma flags range gain c salinity
FIRE_V2_EXTRA = struct.Struct("<I2II5I")  # extFlags reserved0[2] beaconLocatorFrequency reserved1[5]
PING_V1 = struct.Struct("<IIddddIBdHHIII")
PING_V2 = struct.Struct("<IIddddddddBdHH4IIII")
SIZE_V1 = HEADER.size + FIRE_V1.size + PING_V1.size  # 122
SIZE_V2 = HEADER.size + FIRE_V1.size + FIRE_V2_EXTRA.size + PING_V2.size  # 202

LOG_HEADER = struct.Struct("<II16sHH4xqd")  # natural alignment, 48 bytes
LOG_ITEM = struct.Struct("<IIHH4xdH2xII4x")  # natural alignment, 40 bytes
_LOG_ITEM_MIN = 36

_BYTES_PER_SAMPLE = {0: 1, 1: 2, 2: 3, 3: 4}
_PART_NUMBERS = {
    1041: "M370s", 2418: "MT370s", 1433: "MD370s", 4713: "C550d", 1032: "M750d", 2419: "MT750d",
    1434: "MD750d", 1042: "M1200d", 2420: "MT1200d", 1435: "MD1200d", 2203: "M3000d",
    2599: "MT3000d",
}  # fmt: skip


class _Record(NamedTuple):
    offset: int  # byte offset of the message (raw, log-v1) or SQLite rowid (log-v2)
    length: int
    time_ns: int
    compressed: bool


def _epoch_ns(value: Any) -> int:
    """A time stamp since the epoch in s, ms, µs or ns (by magnitude) -> integer ns.

    Raises
    ------
    ValueError
        If the stamp is not a finite non-negative number or lies outside the years 1970-2200
        (0, "unknown", is accepted).
    """
    if isinstance(value, bytes | bytearray | memoryview):
        raise ValueError("time stamp is a BLOB, not a number")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"time stamp {value!r} is not a number") from None
    if not math.isfinite(v) or v < 0:
        raise ValueError(f"time stamp {value!r} is not a finite non-negative number")
    scale = 1e9 if v < 1e11 else 1e6 if v < 1e14 else 1e3 if v < 1e17 else 1.0
    return check_time_ns(int(round(v * scale)), f"time stamp {value!r} ->")


def _q_uncompress(
    data: bytes | memoryview, path: str | os.PathLike[str] | None = None, offset: int | None = None
) -> bytes:
    """Qt ``qUncompress``: 4-byte big-endian expected length, then a zlib stream.

    The stream is inflated into at most the declared length (itself at most
    :data:`~sonarmap.io._binary.MAX_PING_BYTES`), so a compression bomb cannot exhaust memory.

    Raises
    ------
    DataFormatError
        If the prefix is missing, declares an implausible size, or the stream is corrupt or does
        not inflate to exactly the declared size.
    """
    if len(data) < 4:
        raise DataFormatError("compressed payload shorter than its 4-byte length prefix", path, offset)
    (n,) = struct.unpack_from(">I", data, 0)
    if n > MAX_PING_BYTES:
        raise DataFormatError(
            f"compressed payload declares {n} bytes, more than the {MAX_PING_BYTES} allowed for "
            "one message", path, offset,
        )
    try:
        out = decompress_bounded(data[4:], n, None, "compressed payload")
    except DataFormatError as exc:
        raise DataFormatError(str(exc), path, offset) from None
    if len(out) != n:
        raise DataFormatError(f"compressed payload inflates to {len(out)} bytes, its prefix says {n}",
                              path, offset)
    return out


def _quote_ident(name: object) -> str:
    """``name`` as an SQL quoted identifier (double quotes, internal quotes doubled)."""
    return '"' + str(name).replace('"', '""') + '"'


def _sqlite_uri(path: Path) -> str:
    """A read-only SQLite ``file:`` URI for ``path`` (percent-encoded: ``#``, ``?``, ``%`` work)."""
    return Path(path).resolve().as_uri() + "?mode=ro"


@functools.lru_cache(maxsize=64)
def _geometry(
    bearings: bytes, n_ranges: int, resolution_m: float, sound_speed: float, frequency: float,
    part: int,
) -> SonarGeometry:
    az = np.deg2rad(np.frombuffer(bearings, dtype="<i2").astype(np.float64) / 100.0)
    model = _PART_NUMBERS.get(part)
    return SonarGeometry.from_window(
        min_range_m=0.0,
        max_range_m=n_ranges * resolution_m,
        n_bins=n_ranges,
        azimuth_rad=az,
        frequency_hz=frequency,
        sound_speed_m_s=sound_speed,
        name=f"oculus-{model.lower()}" if model else "oculus",
        azimuth_source="table",
        azimuth_beamwidth_rad=oculus_azimuth_beamwidth_rad(frequency),
    )


def _checked_header(mv: memoryview, path: str | os.PathLike[str], offset: int) -> tuple[int, ...]:
    """The unpacked 16-byte ``OculusMessageHeader`` of ``mv``, which must be a ``SimplePingResult``.

    Raises :class:`DataFormatError` for a short message, a bad ``oculusId`` or another ``msgId``.
    """
    n = len(mv)
    if n < HEADER.size:
        raise DataFormatError(f"message of {n} bytes is shorter than its 16-byte header", path, offset)
    header = HEADER.unpack_from(mv, 0)
    oid, msg_id = header[0], header[3]
    if oid != OCULUS_ID:
        raise DataFormatError(f"bad Oculus message id 0x{oid:04X} (expected 0x4F53)", path, offset)
    if msg_id != MSG_SIMPLE_PING_RESULT:
        raise DataFormatError(f"message 0x{msg_id:02X} is not a SimplePingResult", path, offset)
    return header


def _checked_row_stride(
    n: int, need: int, payload: int, dsize: int, n_ranges: int, n_beams: int, gain: bool, img_off: int,
    img_size: int,
) -> int:
    """Bytes per image row (``n_beams`` samples, plus a 4-byte gain if ``gain``), after checking that
    the message's sizes agree; raises ValueError (under :func:`header_errors`) if they do not."""
    if HEADER.size + payload != n:
        raise ValueError(f"payloadSize {payload} + 16 != message length {n}")
    if dsize not in _BYTES_PER_SAMPLE:
        raise ValueError(f"dataSize {dsize} is not 0-3 (8/16/24/32 bit)")
    if n_beams < 1 or n_ranges < 1:
        raise ValueError(f"empty image ({n_ranges} ranges x {n_beams} beams)")
    bps = _BYTES_PER_SAMPLE[dsize]
    stride = n_beams * bps + (4 if gain else 0)
    if img_size != n_ranges * stride:
        raise ValueError(
            f"imageSize {img_size} != nRanges {n_ranges} x ({n_beams} beams x {bps} bytes"
            f"{' + 4 gain bytes' if gain else ''})"
        )
    if img_off < need + 2 * n_beams or img_off + img_size > n:
        raise ValueError(
            f"image [{img_off}, {img_off + img_size}) does not fit after the bearings in a "
            f"{n}-byte message"
        )
    return stride


def _check_range_window(res: float, n_ranges: int) -> None:
    """Raise ValueError unless ``rangeResolution`` is in (0, 10) m and the window within ``MAX_WINDOW_M``."""
    if not (math.isfinite(res) and 0 < res < 10):
        raise ValueError(f"rangeResolution {res} m is not a positive number below 10 m")
    if n_ranges * res > MAX_WINDOW_M:
        raise ValueError(
            f"range window {n_ranges} x {res:.6g} m = {n_ranges * res:.6g} m is beyond "
            f"{MAX_WINDOW_M:g} m"
        )


def _checked_sound_speed(c_used: float, meta: dict[str, Any]) -> float:
    """``speedOfSoundUsed`` checked; 0 (unset) gives 1500 m/s and keeps the reported value in ``meta``."""
    checked_c = check_sound_speed(c_used, "speedOfSoundUsed", unset_ok=True)
    c = 1500.0 if checked_c is None else checked_c
    if checked_c is None:
        meta["sound_speed_reported"] = c_used
    return c


def _image_from_samples(
    mv: memoryview, img_off: int, img_size: int, n_ranges: int, n_beams: int, stride: int, dsize: int,
    gain: bool, meta: dict[str, Any],
) -> np.ndarray:
    """The range-major image of 8/16/24/32-bit samples scaled to float32 [0, 1]; the per-row gains
    (when ``gain``) go to ``meta["row_gain"]``."""
    raw = np.frombuffer(mv, dtype=np.uint8, count=img_size, offset=img_off).reshape(n_ranges, stride)
    if gain:
        meta["row_gain"] = raw[:, :4].copy().view("<f4").reshape(-1)
        raw = raw[:, 4:]
    bps = _BYTES_PER_SAMPLE[dsize]
    if bps == 1:
        return np.multiply(raw, U8_SCALE, dtype=np.float32)
    if bps == 2:
        return np.ascontiguousarray(raw).view("<u2").astype(np.float32) / np.float32(65535.0)
    if bps == 3:
        r = raw.reshape(n_ranges, n_beams, 3).astype(np.uint32)
        v = r[..., 0] | (r[..., 1] << 8) | (r[..., 2] << 16)
        return (v.astype(np.float64) / float(2**24 - 1)).astype(np.float32)
    v = np.ascontiguousarray(raw).view("<u4")
    return (v.astype(np.float64) / float(2**32 - 1)).astype(np.float32)


def decode_simple_ping(
    msg: bytes | memoryview,
    *,
    path: str | os.PathLike[str] = "<bytes>",
    offset: int = 0,
    time_ns: int = 0,
    geometry: SonarGeometry | None = None,
    source: str = "",
) -> Ping:
    """Decode one ``SimplePingResult`` (v1 or v2) network message into a :class:`Ping`.

    Parameters
    ----------
    msg : bytes-like
        The whole message, starting with the 16-byte message header.
    path, offset : optional
        Used in error messages (file and byte offset of the message).
    time_ns : int
        Ping time (the message itself has no wall clock).

    Raises
    ------
    DataFormatError
        When the message is short, has a bad id, or its sizes disagree with each other.
    """
    mv = memoryview(msg).cast("B") if not isinstance(msg, bytes) else memoryview(msg)
    n = len(mv)
    _oid, _src, _dst, _msg_id, version, payload, part = _checked_header(mv, path, offset)
    v2 = version == 2
    need = SIZE_V2 if v2 else SIZE_V1
    if n < need:
        raise DataFormatError(
            f"SimplePingResult v{2 if v2 else 1} needs {need} bytes, message has {n}", path, offset
        )
    fire = FIRE_V1.unpack_from(mv, HEADER.size)
    flags = fire[4]
    meta: dict[str, Any] = {
        "format": FORMAT,
        "message_version": 2 if v2 else 1,
        "part_number": part,
        "flags": flags,
        "range_setting": fire[5],
        "gain_percent": fire[6],
    }
    if v2:
        p = PING_V2.unpack_from(mv, HEADER.size + FIRE_V1.size + FIRE_V2_EXTRA.size)
        (ping_id, status, freq, temp, pressure, heading, pitch, roll, c_used, start, dsize, res,
         n_ranges, n_beams, _s0, _s1, _s2, _s3, img_off, img_size, msg_size) = p
        meta.update(heading_deg=heading, pitch_deg=pitch, roll_deg=roll)
    else:
        p = PING_V1.unpack_from(mv, HEADER.size + FIRE_V1.size)
        (ping_id, status, freq, temp, pressure, c_used, start, dsize, res, n_ranges, n_beams,
         img_off, img_size, msg_size) = p
    meta.update(
        ping_id=ping_id, status=status, temperature_c=temp, pressure_bar=pressure,
        ping_start_time=start,
    )
    gain = bool(flags & FLAG_SEND_GAIN)
    with header_errors(path, offset, "SimplePingResult"):
        stride = _checked_row_stride(n, need, payload, dsize, n_ranges, n_beams, gain, img_off, img_size)
        _check_range_window(res, n_ranges)
        c = _checked_sound_speed(c_used, meta)
        f_hz = 1.2e6 if freq == 0 else check_plausible(freq, 1e4, 1e7, "frequency", "Hz")
        if not (math.isfinite(start) and start >= 0):
            raise ValueError(f"pingStartTime {start} s is not a finite non-negative time")
        bearings = bytes(mv[need : need + 2 * n_beams])
        geom = geometry if geometry is not None else _geometry(
            bearings, n_ranges, float(res), float(c), float(f_hz), int(part)
        )
        if msg_size not in (0, n):
            meta["message_size_reported"] = msg_size
    image = _image_from_samples(mv, img_off, img_size, n_ranges, n_beams, stride, dsize, gain, meta)
    with header_errors(path, offset, "SimplePingResult"):
        return Ping(image=image, geometry=geom, time_ns=time_ns, source=source, meta=meta)


def _clock_source(start_given: bool, rate_given: bool) -> str:
    """``Ping.meta["time_source"]`` of a clockless capture (module notes)."""
    return f"{'start_time_ns' if start_given else 'file_mtime'}+{'rate_hz' if rate_given else 'order'}"


#: Every ``time_source`` of a capture without a clock: its times come from the file's modification
#: time or ``start_time_ns``, and the packet order or ``rate_hz``.
CLOCKLESS_TIME_SOURCES = tuple(_clock_source(s, r) for s in (False, True) for r in (False, True))


class OculusFile(ClosingFile):
    """Lazy access to the pings of an Oculus network stream or ViewPoint log.

    ``len(f)`` pings; ``f[i]`` decodes ping ``i``; ``f.kind`` is ``"raw"``, ``"log-v1"`` or
    ``"log-v2"``.  Only the message headers are scanned on opening (bounded memory).

    Parameters
    ----------
    path : path-like
    geometry : SonarGeometry, preset name or JSON path, optional
        Overrides the geometry of the messages.
    start_time_ns : int, optional
        Raw captures (no clock): time of the first ping, integer ns since the Unix epoch
        (default: the file's modification time).  Ignored for logs, which have time stamps.
    rate_hz : float, optional
        Raw captures: ping rate (default 1 / :data:`DEFAULT_RAW_INTERVAL_S`).  Ignored for logs.

    Attributes
    ----------
    time_source : str
        Where the ping times come from (module notes).

    Raises
    ------
    DataFormatError
        Unknown container, bad magic or ids, or sizes that disagree with the file.
    InputError
        If ``start_time_ns`` or ``rate_hz`` is not a plausible value.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        geometry: SonarGeometry | str | os.PathLike[str] | None = None,
        start_time_ns: int | None = None,
        rate_hz: float | None = None,
    ) -> None:
        self.path = Path(path)
        _check_clock_arguments(start_time_ns, rate_hz)
        self._override = None if geometry is None else as_geometry(geometry)
        self._db: sqlite3.Connection | None = None
        self._mm: Any = None
        self.time_source = "log"
        #: Spacing of the pings of a raw capture (s); None for logs.
        self.ping_interval_s: float | None = None
        with open_head(self.path) as head:
            pass
        if head[:16] == SQLITE_MAGIC:
            self.kind = "log-v2"
            self._records = self._index_sqlite()
            return
        self._mm = map_file(self.path, min_size=1, what="Oculus file")
        if head[:4] == struct.pack("<I", LOG_FILE_MAGIC):
            self.kind = "log-v1"
            self._records = self._index_log_v1()
        elif head[:2] == b"SO":
            self.kind = "raw"
            self._records = self._clock_raw(self._index_raw(), start_time_ns, rate_hz)
        else:
            raise DataFormatError(
                f"not an Oculus stream or ViewPoint log (starts with {bytes(head[:4])!r})",
                self.path, 0,
            )

    # ------------------------------------------------------------------ indexing
    def _index_raw(self) -> list[_Record]:
        mm, size, out, o = self._mm, int(self._mm.size), [], 0
        while o < size:
            if size - o < HEADER.size:
                warn_partial(self.path, o, size - o, HEADER.size, "message header")
                break
            oid, _s, _d, msg_id, _v, payload, _p = HEADER.unpack_from(mm, o)
            if oid != OCULUS_ID:
                raise DataFormatError(
                    f"bad Oculus message id 0x{oid:04X} (expected 0x4F53); stream out of sync",
                    self.path, o,
                )
            total = HEADER.size + payload
            if total > MAX_PING_BYTES:
                raise DataFormatError(
                    f"message declares {total} bytes, more than the {MAX_PING_BYTES} allowed for one "
                    "message", self.path, o + 10,
                )
            if o + total > size:
                warn_partial(self.path, o, size - o, total, "message")
                break
            if msg_id == MSG_SIMPLE_PING_RESULT:
                out.append(_Record(o, total, 0, False))
            o += total
        return out

    def _clock_raw(self, records: list[_Record], start_time_ns: int | None, rate_hz: float | None) -> list[_Record]:
        """Give the pings of a clockless capture ``start + i / rate`` (module notes)."""
        if start_time_ns is None:
            try:
                start = int(os.stat(self.path).st_mtime_ns)
            except OSError as exc:
                raise DataFormatError(f"cannot stat: {exc.strerror or exc}", self.path) from None
        else:
            start = int(start_time_ns)
        step_ns = 1e9 / rate_hz if rate_hz is not None else DEFAULT_RAW_INTERVAL_S * 1e9
        self.time_source = _clock_source(start_time_ns is not None, rate_hz is not None)
        self.ping_interval_s = step_ns * 1e-9
        end = start + round((len(records) - 1) * step_ns) if records else start
        if not 0 < start <= end <= MAX_PLAUSIBLE_TIME_NS:
            if start_time_ns is None:
                raise DataFormatError(
                    f"no clock, and the file's modification time ({start} ns) puts the pings outside the "
                    "years 1970-2200; pass start_time_ns", self.path,
                )
            raise InputError(f"start_time_ns: {start_time_ns} ns puts the last ping of {self.path} after 2200")
        return [r._replace(time_ns=start + round(i * step_ns)) for i, r in enumerate(records)]

    def _index_log_v1(self) -> list[_Record]:
        mm, size = self._mm, int(self._mm.size)
        if size < LOG_HEADER.size:
            raise DataFormatError(
                f"truncated ViewPoint log: {size} bytes, the file header needs {LOG_HEADER.size}",
                self.path, size,
            )
        _magic, hsize, _src, _ver, encryption, _key, _t = LOG_HEADER.unpack_from(mm, 0)
        if encryption != 0:
            raise DataFormatError(f"encrypted ViewPoint log (encryption {encryption})", self.path, 26)
        if not LOG_HEADER.size - 16 <= hsize <= size:
            raise DataFormatError(f"file header size {hsize} is inconsistent", self.path, 4)
        out: list[_Record] = []
        o = hsize
        while o < size:
            if size - o < LOG_ITEM.size:
                warn_partial(self.path, o, size - o, LOG_ITEM.size, "log item header")
                break
            magic, isize, typ, _ver, t, comp, _orig, payload = LOG_ITEM.unpack_from(mm, o)
            if magic != LOG_ITEM_MAGIC:
                raise DataFormatError(
                    f"bad log item magic 0x{magic:08X} (expected 0xAABBCCDD)", self.path, o
                )
            if not _LOG_ITEM_MIN <= isize <= 4096:
                raise DataFormatError(f"log item header size {isize} is inconsistent", self.path, o + 4)
            start = o + isize
            if start + payload > size:
                warn_partial(self.path, o, size - o, isize + payload, "log item")
                break
            if typ == RT_OCULUS_SONAR:
                if comp not in (0, 1):
                    raise DataFormatError(f"unknown compression {comp}", self.path, o + 24)
                if payload > MAX_PING_BYTES:
                    raise DataFormatError(
                        f"log item payload of {payload} bytes is more than the {MAX_PING_BYTES} "
                        "allowed for one message", self.path, o + 32,
                    )
                if comp == 1:
                    head = self._peek_compressed(start, payload)
                else:
                    head = bytes(mm[start : start + min(payload, HEADER.size)])
                if len(head) >= HEADER.size:
                    oid, _s, _d, msg_id, _v, _p, _pn = HEADER.unpack_from(head, 0)
                    if oid == OCULUS_ID and msg_id == MSG_SIMPLE_PING_RESULT:
                        with header_errors(self.path, o + 16, "log item time"):
                            tns = _epoch_ns(t)
                        out.append(_Record(start, payload, tns, comp == 1))
            o = start + payload
        return out

    def _peek_compressed(self, start: int, payload: int) -> bytes:
        """The first (up to) 16 inflated bytes of the qCompress'ed item at ``start``.

        Input is fed in small chunks until the message header is out (a deflate stream may need
        more than a few dozen bytes before its first output byte); output is capped at 16 bytes.
        """
        d = zlib.decompressobj()
        out = b""
        pos, end = start + 4, start + payload
        try:
            while len(out) < HEADER.size and pos < end and not d.eof:
                chunk = bytes(self._mm[pos : min(pos + 4096, end)])
                pos += len(chunk)
                out += d.decompress(chunk, HEADER.size - len(out))
        except zlib.error as exc:
            raise DataFormatError(f"corrupt compressed payload ({exc})", self.path, start) from None
        return out

    def _connect(self) -> sqlite3.Connection:
        if self._db is None:
            require_regular_file(self.path, "ViewPoint log")
            try:
                self._db = sqlite3.connect(_sqlite_uri(self.path), uri=True)
            except (sqlite3.Error, OSError, ValueError) as exc:
                raise DataFormatError(f"cannot open ViewPoint v2 log: {exc}", self.path) from None
        return self._db

    def _index_sqlite(self) -> list[_Record]:
        db = self._connect()
        try:
            cols = db.execute("PRAGMA table_info(data)").fetchall()
            if not cols:
                raise DataFormatError("SQLite file has no 'data' table (not a ViewPoint v2 log)", self.path)
            blobs = [str(c[1]) for c in cols if str(c[2]).upper() == "BLOB"]
            self._payload_col = blobs[-1] if blobs else str(cols[-1][1])
            times = [str(c[1]) for c in cols if "time" in str(c[1]).lower()]
            self._time_col = times[0] if times else None
            tsel = _quote_ident(self._time_col) if self._time_col else "0"
            pcol = _quote_ident(self._payload_col)
            q = f"SELECT rowid, {tsel}, substr({pcol}, 1, 16), length({pcol}) FROM data ORDER BY rowid"
            out: list[_Record] = []
            for rowid, t, head, length in db.execute(q):
                if not isinstance(head, bytes | bytearray) or len(head) < HEADER.size:
                    continue
                oid, _s, _d, msg_id, _v, _p, _pn = HEADER.unpack_from(head, 0)
                if oid != OCULUS_ID or msg_id != MSG_SIMPLE_PING_RESULT:
                    continue
                if int(length) > MAX_PING_BYTES:
                    raise DataFormatError(
                        f"row {rowid}: message of {length} bytes is more than the {MAX_PING_BYTES} "
                        "allowed for one message", self.path,
                    )
                tns = 0
                if self._time_col is not None and t is not None:
                    with header_errors(self.path, None, f"row {rowid} time stamp"):  # type: ignore[arg-type]
                        tns = _epoch_ns(t)
                out.append(_Record(int(rowid), int(length), tns, False))
            return out
        except sqlite3.Error as exc:
            raise DataFormatError(f"corrupt ViewPoint v2 log: {exc}", self.path) from None

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return len(self._records)

    def __getitem__(self, index: int) -> Ping:
        i = check_index(index, len(self._records))
        rec = self._records[i]
        ping = decode_simple_ping(
            self._message(rec),
            path=self.path,
            offset=rec.offset if self.kind != "log-v2" else None,  # type: ignore[arg-type]
            time_ns=rec.time_ns,
            geometry=self._override,
            source=f"{self.path}#{i}",
        )
        ping.meta["time_source"] = self.time_source if rec.time_ns or self.kind == "raw" else "none"
        return ping

    def __iter__(self) -> Iterator[Ping]:
        for i in range(len(self)):
            yield self[i]

    def close(self) -> None:
        """Close the memory map / database connection."""
        if self._db is not None:
            self._db.close()
            self._db = None
        self._mm = None

    def _message(self, rec: _Record) -> bytes | memoryview:
        if self.kind == "log-v2":
            pcol = _quote_ident(self._payload_col)
            try:
                row = self._connect().execute(
                    f"SELECT {pcol} FROM data WHERE rowid = ? AND length({pcol}) <= ?",
                    (rec.offset, MAX_PING_BYTES),
                ).fetchone()
            except sqlite3.Error as exc:
                raise DataFormatError(f"corrupt ViewPoint v2 log: {exc}", self.path) from None
            if row is None or not isinstance(row[0], bytes | bytearray):
                raise DataFormatError(f"row {rec.offset} disappeared or changed", self.path)
            return bytes(row[0])
        data = memoryview(self._mm)[rec.offset : rec.offset + rec.length]
        if rec.compressed:
            return _q_uncompress(data, self.path, rec.offset)
        return data


class open_head:  # noqa: N801 - tiny context manager
    """Read the first 64 bytes of a regular file (DataFormatError if it cannot be read).

    FIFOs, devices, sockets and directories are refused without reading (no hang, no endless read).
    """

    def __init__(self, path: Path) -> None:
        with open_regular(path, "Oculus file") as fh:
            try:
                self.head = fh.read(64)
            except OSError as exc:
                raise DataFormatError(f"cannot read: {exc.strerror or exc}", path) from None

    def __enter__(self) -> bytes:
        return self.head

    def __exit__(self, *exc: object) -> None:
        return None


def _check_clock_arguments(start_time_ns: int | None, rate_hz: float | None) -> None:
    """Validate the ``start_time_ns`` / ``rate_hz`` arguments (InputError, one line)."""
    if start_time_ns is not None:
        if isinstance(start_time_ns, bool) or not isinstance(start_time_ns, int | np.integer):
            raise InputError(f"start_time_ns: expected integer ns since the Unix epoch, got {start_time_ns!r}")
        if not 0 < int(start_time_ns) <= MAX_PLAUSIBLE_TIME_NS:
            raise InputError(f"start_time_ns: {start_time_ns} ns is outside the years 1970-2200")
    if rate_hz is not None:
        try:
            r = float(rate_hz)
        except (TypeError, ValueError):
            raise InputError(f"rate_hz: expected a number of pings per second, got {rate_hz!r}") from None
        if not (math.isfinite(r) and 0 < r <= 1e6):
            raise InputError(f"rate_hz: must be in (0, 1e6] pings per second, got {rate_hz!r}")


def _is_viewpoint_sqlite(path: Path) -> bool:
    try:
        con = sqlite3.connect(_sqlite_uri(path), uri=True)
        try:
            names = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        finally:
            con.close()
    except (sqlite3.Error, OSError, ValueError):
        return False
    return "data" in names and "messages" not in names


# ---------------------------------------------------------------------- registry hooks
def sniff(path: Path, head: bytes) -> bool:
    """Network streams (``b"SO"``), ViewPoint v1 logs (0x11223344) and v2 SQLite logs."""
    if not path.is_file():
        return False
    if head[:2] == b"SO" and len(head) >= HEADER.size:
        _oid, _s, _d, msg_id, version, _p, _pn = HEADER.unpack_from(head, 0)
        return msg_id < 0x100 and version < 16  # rejects text that merely starts with "SO"
    if head[:4] == struct.pack("<I", LOG_FILE_MAGIC):
        return True
    return head[:16] == SQLITE_MAGIC and _is_viewpoint_sqlite(path)


def iter_pings(
    path: str | os.PathLike[str],
    *,
    geometry: SonarGeometry | str | os.PathLike[str] | None = None,
    start: int = 0,
    stop: int | None = None,
    start_time_ns: int | None = None,
    rate_hz: float | None = None,
    **_: Any,
) -> Iterator[Ping]:
    """Lazily yield pings ``start:stop`` of an Oculus stream or ViewPoint log.

    Parameters
    ----------
    path : path-like
    geometry : SonarGeometry, preset name or JSON path, optional
    start, stop : int
        Ping positions ``[start, stop)`` (``stop`` None: to the end); the messages before
        ``start`` are not decoded (their offsets come from the file's message index).
    start_time_ns, rate_hz : optional
        Clock of a raw network capture (see :class:`OculusFile`); ``read_pings`` passes them on.

    Raises
    ------
    InputError
        If ``start`` or ``stop`` is not a non-negative integer, or the clock arguments are invalid.
    DataFormatError
        See :class:`OculusFile`.

    Examples
    --------
    >>> pings = list(iter_pings("capture.raw", start_time_ns=1_468_936_985 * 10**9, rate_hz=15))  # doctest: +SKIP
    >>> pings[1].time_ns - pings[0].time_ns, pings[0].meta["time_source"]                       # doctest: +SKIP
    (66666667, 'start_time_ns+rate_hz')
    """
    with OculusFile(path, geometry=geometry, start_time_ns=start_time_ns, rate_hz=rate_hz) as f:
        yield from iter_indexed(f, start, stop)


def count_pings(path: str | os.PathLike[str]) -> int:
    """Number of ``SimplePingResult`` messages (headers only)."""
    return count_container_pings(OculusFile, path)


def summary(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Geometry of the first ping, ping count, time span (logs only) and Oculus fields."""
    with OculusFile(path) as f:
        n = len(f)
        if n == 0:
            return make_summary(FORMAT, path, n_pings=0, container=f.kind)
        first = f[0]
        g = first.geometry
        has_clock = f._records[0].time_ns > 0
        return make_summary(
            FORMAT,
            path,
            n_pings=n,
            geometry=g,
            time_start_ns=f._records[0].time_ns if has_clock else None,
            time_end_ns=f._records[-1].time_ns if has_clock else None,
            container=f.kind,
            time_source=first.meta["time_source"],
            **({} if f.ping_interval_s is None else {"ping_interval_s": f.ping_interval_s}),
            message_version=first.meta["message_version"],
            model=_PART_NUMBERS.get(first.meta["part_number"], "unknown"),
            n_beams=g.n_beams,
            n_ranges=g.n_bins,
            range_resolution_m=round(g.range_resolution_m, 7),
            bearing_span_deg=(round(float(np.rad2deg(g.azimuth_rad[0])), 3),
                              round(float(np.rad2deg(g.azimuth_rad[-1])), 3)),
            frequency_hz=g.frequency_hz,
            sound_speed_m_s=g.sound_speed_m_s,
            gain_rows="row_gain" in first.meta,
        )
