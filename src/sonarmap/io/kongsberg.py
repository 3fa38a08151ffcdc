"""Kongsberg EM multibeam recordings: ``.all`` (bathymetry, navigation) and ``.wcd`` (water column).

Layout (Kongsberg "EM Series Datagram Formats", public; little-endian for the EM 2040, 710, 302,
122, 3002 and later models).  A file is a stream of datagrams::

    uint32  length        bytes after this field (STX ... checksum)
    uint8   STX           0x02
    uint8   type          e.g. 0x6B 'k' water column, 0x4E 'N' raw range and angle, 0x58 'X' XYZ
    uint16  EM model      e.g. 2040
    uint32  date          year * 10000 + month * 100 + day
    uint32  time          ms since midnight (UTC)
    uint16  counter       ping counter (survey line number for 'I', sensor counter for 'P'/'A')
    uint16  serial        system (head) serial number
    ...     body
    uint8   ETX           0x03
    uint16  checksum      sum of the bytes from the type byte to the byte before ETX, mod 2**16

What this reader uses:

* ``k`` water column, one ping of one head spread over ``Nd`` datagrams: ``Ntx`` transmit sectors
  (tilt 0.01 deg, centre frequency 10 Hz) and ``Nrx`` beams each with its pointing angle re vertical
  (0.01 deg, **positive to port**), start range sample, ``Ns`` samples, the sonar's own detected
  range (samples from transmit, 0 = no detection), transmit sector, then ``Ns`` int8 amplitudes in
  0.5 dB; also sound speed (0.1 m/s), sample rate (0.01 Hz), TX time heave (cm), the TVG function
  ``X`` and offset ``C`` (dB) applied.  The ``.wcd`` file holds them (or the ``.all`` itself).
* ``N`` raw range and angle (two-way travel time, beam angle re the RX array, detection info,
  quality, reflectivity; TX signal length, delay, centre frequency, absorption per sector),
  ``X`` XYZ (depth below the transmit transducer; across- and along-track from the position fix, m), ``P`` position,
  ``A`` attitude, ``I`` installation parameters (ASCII ``KEY=value,`` text) and ``R`` runtime
  parameters, all from the ``.all`` file.  Other datagram types are skipped.

Conventions of the yielded :class:`~sonarmap.ping.Ping` (one per ping counter and head):

* ``image`` is ``(n_bins, n_beams)`` float32: row ``i`` is sample ``s0 + i`` (``s0`` the smallest
  start range sample of the ping, 0 in practice), at range ``(s0 + i) * c / (2 fs)``; beams with
  fewer samples are padded with 0.
* Columns are the beams ordered by azimuth, ``azimuth = -(pointing angle)`` (Kongsberg angles are
  positive to port, ours positive to starboard); the azimuth is measured in the swath plane from
  the sonar's boresight, which for a bathymetric multibeam is the vertical (nadir).
* Amplitudes ``a`` (dB, -64 ... +63.5 in 0.5 dB steps, TVG applied by the sonar) become linear
  intensity relative to the datagram's full scale: ``image = 10 ** ((a - 63.5) / 10)``, so the
  largest storable amplitude is 1.0 and -64 dB is 1.8e-13; padding (no sample) is exactly 0.
  The intensity domain is the one the speckle/mixture model of the pipeline is written for (a
  log mapping over the full 127.5 dB int8 range left the default pipeline without a plausible fit
  on the shared recording).  ``a = 63.5 + 10 log10(image)`` (:func:`image_to_db`) recovers the
  file's dB exactly after rounding to 0.5 dB; ``meta["amplitude_db_full_scale"] = 63.5``,
  ``meta["amplitude_db_step"] = 0.5``.
* A ping whose datagrams are not all in the file (e.g. the recording stopped between the two
  datagrams of a ping) is yielded with the beams that are there and a
  :class:`~sonarmap.io._binary.PartialFrameWarning`; ``meta["complete"]`` is False and
  ``meta["n_beams_total"]`` / ``meta["n_beams_received"]`` say how many are missing.  An
  incomplete trailing *datagram* is skipped with the same warning.
* A checksum mismatch is a :class:`~sonarmap.errors.DataFormatError` naming the datagram's offset
  (``checksum="warn"`` skips such a datagram with a :class:`KongsbergWarning` instead,
  ``checksum="ignore"`` does not verify).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import functools
import math
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import DataFormatError, SonarmapWarning
from sonarmap.geometry import SonarGeometry, as_geometry, plausible_elevation_beamwidth
from sonarmap.io._binary import (
    MAX_TIME_NS,
    ClosingFile,
    PartialFrameWarning,
    check_index,
    count_container_pings,
    iter_indexed,
    header_errors,
    make_summary,
    map_file,
    records_at,
    warn_partial,
)
from sonarmap._files import require_regular_file
from sonarmap.ping import Ping

__all__ = [
    "FORMAT",
    "DATAGRAM_TYPES",
    "EM_MODELS",
    "HEADER_DTYPE",
    "AMPLITUDE_DB_FULL_SCALE",
    "AMPLITUDE_DB_STEP",
    "image_to_db",
    "effective_pulse_us",
    "KongsbergFile",
    "KongsbergWarning",
    "sibling_paths",
    "parse_installation_text",
    "sniff",
    "iter_pings",
    "count_pings",
    "summary",
]

FORMAT = "kongsberg"

#: Datagram type byte -> name (EM Series Datagram Formats); other types are skipped when read.
DATAGRAM_TYPES: dict[int, str] = {
    0x30: "PU id", 0x31: "PU status", 0x33: "extra parameters", 0x41: "attitude",
    0x42: "PU BIST result", 0x43: "clock", 0x44: "depth", 0x45: "single-beam depth",
    0x46: "raw range and angle (F)", 0x47: "surface sound speed", 0x48: "heading",
    0x49: "installation parameters (start)", 0x4A: "mechanical transducer tilt",
    0x4B: "central beams echogram", 0x4E: "raw range and angle (N)", 0x50: "position",
    0x52: "runtime parameters", 0x53: "seabed image (S)", 0x54: "tide", 0x55: "sound speed profile",
    0x56: "sound velocity profile", 0x57: "SSP output", 0x58: "XYZ 88", 0x59: "seabed image 89",
    0x65: "raw range and angle (e)", 0x66: "raw range and angle (f)", 0x68: "depth or height",
    0x69: "installation parameters (stop)", 0x6B: "water column", 0x6C: "extra detections",
    0x6E: "network attitude velocity", 0x70: "installation parameters (remote)",
    0x72: "remote information",
}  # fmt: skip

#: EM model numbers accepted by :func:`sniff` (EM 3000D heads report 3003-3008, EM 2040C 2045).
EM_MODELS = frozenset(
    {70, 112, 120, 121, 122, 124, 300, 302, 304, 710, 712, 850, 1000, 1002, 2000, 2040, 2041,
     2042, 2045, 3000, 3002, 3003, 3004, 3005, 3006, 3007, 3008, 3020}
)  # fmt: skip

#: The 20 bytes every datagram starts with (the length field included).
HEADER_DTYPE = np.dtype(
    [("length", "<u4"), ("stx", "u1"), ("type", "u1"), ("model", "<u2"), ("date", "<u4"),
     ("time_ms", "<u4"), ("counter", "<u2"), ("serial", "<u2")]
)  # fmt: skip
_HEADER = HEADER_DTYPE.itemsize  # 20
_MIN_LENGTH = 16 + 3  # header after the length field + ETX + checksum
#: Largest datagram accepted (EM datagrams are UDP packets, < 64 KiB; generous margin).
MAX_DATAGRAM_BYTES = 1 << 24
_MAX_IMAGE_CELLS = 1 << 25
_MAX_BINS = 65535

_WC_DTYPE = np.dtype(
    [("nd", "<u2"), ("dn", "<u2"), ("ntx", "<u2"), ("total", "<u2"), ("nrx", "<u2"),
     ("sound_speed", "<u2"), ("sample_rate", "<u4"), ("tx_heave", "<i2"), ("tvg_x", "u1"),
     ("tvg_c", "i1"), ("scanning", "u1"), ("spare", "V3")]
)  # fmt: skip
_WC_TX_DTYPE = np.dtype([("tilt", "<i2"), ("frequency", "<u2"), ("sector", "u1"), ("spare", "u1")])
_N_DTYPE = np.dtype(
    [("sound_speed", "<u2"), ("ntx", "<u2"), ("nrx", "<u2"), ("n_valid", "<u2"),
     ("sample_rate", "<f4"), ("dscale", "<u4")]
)  # fmt: skip
_N_TX_DTYPE = np.dtype(
    [("tilt", "<i2"), ("focus", "<u2"), ("signal_length", "<f4"), ("delay", "<f4"),
     ("frequency", "<f4"), ("absorption", "<u2"), ("waveform", "u1"), ("sector", "u1"),
     ("bandwidth", "<f4")]
)  # fmt: skip
_N_RX_DTYPE = np.dtype(
    [("angle", "<i2"), ("sector", "u1"), ("detection", "u1"), ("window", "<u2"),
     ("quality", "u1"), ("d_corr", "i1"), ("twtt", "<f4"), ("reflectivity", "<i2"),
     ("cleaning", "i1"), ("spare", "u1")]
)  # fmt: skip
_X_DTYPE = np.dtype(
    [("heading", "<u2"), ("sound_speed", "<u2"), ("tx_depth", "<f4"), ("n", "<u2"),
     ("n_valid", "<u2"), ("sample_rate", "<f4"), ("scanning", "u1"), ("spare", "V3")]
)  # fmt: skip
_X_RX_DTYPE = np.dtype(
    [("depth", "<f4"), ("across", "<f4"), ("along", "<f4"), ("window", "<u2"), ("quality", "u1"),
     ("incidence_adjust", "i1"), ("detection", "u1"), ("cleaning", "i1"), ("reflectivity", "<i2")]
)  # fmt: skip
_P_DTYPE = np.dtype(
    [("lat", "<i4"), ("lon", "<i4"), ("quality", "<u2"), ("speed", "<u2"), ("course", "<u2"),
     ("heading", "<u2"), ("descriptor", "u1"), ("n_input", "u1")]
)  # fmt: skip
_A_DTYPE = np.dtype(
    [("time_ms", "<u2"), ("status", "<u2"), ("roll", "<i2"), ("pitch", "<i2"), ("heave", "<i2"),
     ("heading", "<u2")]
)  # fmt: skip
_R_DTYPE = np.dtype(
    [("operator_status", "u1"), ("pu_status", "u1"), ("bsp_status", "u1"), ("head_status", "u1"),
     ("mode", "u1"), ("filter_id", "u1"), ("min_depth", "<u2"), ("max_depth", "<u2"),
     ("absorption", "<u2"), ("pulse_length", "<u2"), ("tx_beamwidth", "<u2"), ("tx_power", "i1"),
     ("rx_beamwidth", "u1"), ("rx_bandwidth", "u1"), ("mode2", "u1"), ("tvg_crossover", "u1"),
     ("sound_speed_source", "u1"), ("max_port_swath", "<u2"), ("beam_spacing", "u1"),
     ("max_port_coverage", "u1"), ("stabilisation", "u1"), ("max_stbd_coverage", "u1"),
     ("max_stbd_swath", "<u2"), ("tx_along_tilt", "<i2"), ("filter_id2", "u1")]
)  # fmt: skip
assert _WC_DTYPE.itemsize == 24 and _WC_TX_DTYPE.itemsize == 6
assert _N_DTYPE.itemsize == 16 and _N_TX_DTYPE.itemsize == 24 and _N_RX_DTYPE.itemsize == 16
assert _X_DTYPE.itemsize == 20 and _X_RX_DTYPE.itemsize == 20
assert _P_DTYPE.itemsize == 18 and _A_DTYPE.itemsize == 12 and _R_DTYPE.itemsize == 33

#: dB level of image value 1.0: the largest amplitude a ``k`` datagram can hold (int8 127 x 0.5 dB).
AMPLITUDE_DB_FULL_SCALE = 63.5
#: Amplitude resolution of the ``k`` datagram, dB.
AMPLITUDE_DB_STEP = 0.5
#: Stored byte (an int8 read as uint8) -> linear intensity re full scale, float32:
#: ``10 ** ((0.5 * int8 - 63.5) / 10)``; from 1.8e-13 (-64 dB) to 1.0 (+63.5 dB).
_AMP_LUT = (10.0 ** ((np.arange(256, dtype=np.uint8).view(np.int8) * AMPLITUDE_DB_STEP
                      - AMPLITUDE_DB_FULL_SCALE) / 10.0)).astype(np.float32)

_KNOWN = np.zeros(256, dtype=np.bool_)
_KNOWN[list(DATAGRAM_TYPES)] = True

Checksum = Literal["error", "warn", "ignore"]
_T_WC, _T_N, _T_X, _T_P, _T_A, _T_I, _T_R = 0x6B, 0x4E, 0x58, 0x50, 0x41, 0x49, 0x52

#: Positions and attitude are held constant this far beyond the first/last sample, then omitted.
MAX_EXTRAPOLATION_S = 5.0


class KongsbergWarning(SonarmapWarning):
    """A Kongsberg file has a readable irregularity (e.g. a skipped datagram with a bad checksum)."""


# ---------------------------------------------------------------------- numba kernels (lazy)
# Plain Python here; jitted on first use (``_kernels()``) so that importing the module - which
# format detection does for every file - does not import numba.


def _walk_py(buf: Any, max_len: int, known: Any, kmall: bool) -> tuple[Any, int, int, int]:  # pragma: no cover - jitted
    """Offsets of the complete datagrams of an EM ``.all``/``.wcd`` stream or, with ``kmall``, of a
    KMALL one; status 0 ok, 1 trailing partial, >1 corrupt (the callers' ``_WALK_ERRORS``).

    Both formats start a datagram with a little-endian uint32 length and a marker byte after it.
    ``.all``: the length does not count its own 4 bytes, the marker is STX (0x02), the datagram ends
    with ETX (0x03) and a 2-byte checksum, and ``known[type]`` tells the datagram types.  KMALL:
    the length counts the whole datagram, the marker is ``'#'`` followed by three capital letters,
    and the last 4 bytes repeat the length.
    """
    lead = 0 if kmall else 4  # bytes of a datagram its length field does not count
    min_len = 24 if kmall else 19  # the shortest length field: the header (kmall/kongsberg _MIN_LENGTH)
    head = 8 if kmall else 5  # bytes up to the marker (KMALL: and the type)
    marker = 35 if kmall else 2  # '#' / STX
    size = buf.shape[0]
    cap = 256
    offs = np.empty(cap, np.int64)
    n = 0
    off = 0
    status = 0
    err_off = 0
    err_val = 0
    while True:
        rem = size - off
        if rem == 0:
            break
        if rem < head:
            status = 1
            err_off = off
            err_val = -1  # not even a length field and a marker
            break
        length = (np.int64(buf[off]) | (np.int64(buf[off + 1]) << 8) | (np.int64(buf[off + 2]) << 16)
                  | (np.int64(buf[off + 3]) << 24))
        if buf[off + 4] != marker:
            status = 2
            err_off = off + 4
            err_val = buf[off + 4]
            break
        if length < min_len:
            status = 3
            err_off = off
            err_val = length
            break
        if length > max_len:
            status = 4
            err_off = off
            err_val = length
            break
        if lead + length > rem:
            # a truncated tail - unless a complete datagram starts inside it (a corrupt length)
            status = 1
            err_off = off
            err_val = length
            p = off + 1
            while p + lead + min_len <= size:
                if buf[p + 4] == marker and (
                        (65 <= buf[p + 5] <= 90 and 65 <= buf[p + 6] <= 90 and 65 <= buf[p + 7] <= 90)
                        if kmall else known[buf[p + 5]]):
                    lp = (np.int64(buf[p]) | (np.int64(buf[p + 1]) << 8) | (np.int64(buf[p + 2]) << 16)
                          | (np.int64(buf[p + 3]) << 24))
                    if min_len <= lp <= max_len and p + lead + lp <= size:
                        e = p + lead + lp
                        if kmall:
                            whole = (np.int64(buf[e - 4]) | (np.int64(buf[e - 3]) << 8)
                                     | (np.int64(buf[e - 2]) << 16) | (np.int64(buf[e - 1]) << 24)) == lp
                        else:
                            whole = buf[e - 3] == 3
                        if whole:
                            status = 6
                            err_val = p
                            break
                p += 1
            break
        end = off + lead + length
        if kmall:
            trail = (np.int64(buf[end - 4]) | (np.int64(buf[end - 3]) << 8) | (np.int64(buf[end - 2]) << 16)
                     | (np.int64(buf[end - 1]) << 24))
            whole = trail == length
        else:
            trail = length  # reported: the length whose end has no ETX
            whole = buf[end - 3] == 3
        if not whole:
            status = 5
            err_off = off
            err_val = trail
            break
        if n == cap:
            cap *= 2
            grown = np.empty(cap, np.int64)
            grown[:n] = offs[:n]
            offs = grown
        offs[n] = off
        n += 1
        off = end
    return offs[:n], status, err_off, err_val


def _beams_py(buf: Any, offs: Any, lens: Any, ntx: Any, nrx: Any, angle: Any, srs: Any, ns: Any,
              dr: Any, sector: Any, data: Any) -> tuple[int, int]:  # pragma: no cover - jitted
    """Walk the beam records of a ping's water-column datagrams; (status, offset) on error."""
    k = 0
    for d in range(offs.shape[0]):
        base = offs[d] + 4
        end = base + lens[d] - 3  # the ETX
        p = base + 16 + 24 + 6 * np.int64(ntx[d])
        if p > end:
            return 1, offs[d]
        for _ in range(nrx[d]):
            if p + 10 > end:
                return 2, p
            a = np.int64(buf[p]) | (np.int64(buf[p + 1]) << 8)
            angle[k] = a - 65536 if a >= 32768 else a
            srs[k] = np.int64(buf[p + 2]) | (np.int64(buf[p + 3]) << 8)
            ns[k] = np.int64(buf[p + 4]) | (np.int64(buf[p + 5]) << 8)
            dr[k] = np.int64(buf[p + 6]) | (np.int64(buf[p + 7]) << 8)
            sector[k] = buf[p + 8]
            p += 10
            if p + ns[k] > end:
                return 3, p - 10
            data[k] = p
            p += ns[k]
            k += 1
        if end - p > 1:
            return 4, p
    return 0, 0


def _fill_py(buf: Any, data: Any, ns: Any, row0: Any, order: Any, lut: Any, out: Any) -> None:  # pragma: no cover - jitted
    """out[j, row0[b] + i] = lut[byte i of beam b = order[j]], and 0 in the rest of row ``j``.

    ``out`` is beam-major ``(n_beams, n_bins)``: every beam is one contiguous run; the caller
    transposes (numpy's transposing copy is faster than a numba one).
    """
    n_bins = out.shape[1]
    for j in range(order.shape[0]):
        b = order[j]
        n = ns[b]
        r = row0[b]
        row = out[j]
        src = buf[data[b] : data[b] + n]
        for i in range(r):
            row[i] = 0.0
        dst = row[r : r + n]
        for i in range(n):
            dst[i] = lut[src[i]]
        for i in range(r + n, n_bins):
            row[i] = 0.0


def _checksums_py(buf: Any, offs: Any, lens: Any) -> int:  # pragma: no cover - jitted
    """Index of the first datagram whose checksum does not match, or -1.

    The sum runs in uint32: it wraps, but only its low 16 bits are compared (and uint32 lanes let
    the loop vectorise).
    """
    for d in range(offs.shape[0]):
        stop = offs[d] + 4 + lens[d] - 3  # the ETX
        s = np.uint32(0)
        for x in buf[offs[d] + 5 : stop]:
            s += np.uint32(x)
        stored = np.uint32(buf[stop + 1]) | (np.uint32(buf[stop + 2]) << np.uint32(8))
        if (s & np.uint32(0xFFFF)) != stored:
            return d
    return -1


@functools.cache
def _kernels() -> Any:
    from numba import njit

    class K:
        walk = njit(cache=True, nogil=True)(_walk_py)
        beams = njit(cache=True, nogil=True)(_beams_py)
        fill = njit(cache=True, nogil=True)(_fill_py)
        checksums = njit(cache=True, nogil=True)(_checksums_py)

    return K


# ---------------------------------------------------------------------- small helpers
@functools.lru_cache(maxsize=4096)
def _day_ns(date: int) -> int:
    y, m, d = date // 10000, date // 100 % 100, date % 100
    try:
        day = _dt.date(y, m, d)
    except ValueError:
        raise ValueError(f"date field {date} is not a valid YYYYMMDD date") from None
    return (day.toordinal() - _dt.date(1970, 1, 1).toordinal()) * 86_400_000_000_000


def _time_ns(date: int, time_ms: int) -> int:
    if not 0 <= time_ms < 86_400_000 + 1000:  # a leap second may appear as 86 400 xxx ms
        raise ValueError(f"time field {time_ms} ms is not within one day")
    t = _day_ns(int(date)) + int(time_ms) * 1_000_000
    if not 0 <= t <= MAX_TIME_NS:
        raise ValueError(f"date {date} is outside the representable range")
    return t


def _beam_layout(
    angle_deg: NDArray[np.floating[Any]], start: NDArray[np.integer[Any]], n_samples: NDArray[np.integer[Any]],
) -> tuple[NDArray[np.floating[Any]], NDArray[np.intp], int, int]:
    """The columns and rows of a water-column ping image, from its beams (``.all`` and ``.kmall``).

    Parameters
    ----------
    angle_deg, start, n_samples : ndarray, shape (n_beams,)
        Pointing angle re vertical (degrees, positive to port), start range sample and sample
        count of every beam.

    Returns
    -------
    azimuth : ndarray
        ``-angle`` in radians (positive to starboard), in beam order.
    order : ndarray of intp
        The beams by increasing azimuth (the image columns).
    s0, n_bins : int
        Sample of row 0 (the smallest start sample) and the rows up to the last sample of any beam.

    Raises
    ------
    ValueError
        If every beam has 0 samples, or the image would be implausibly large.
    """
    n = angle_deg.size
    azimuth = -np.deg2rad(angle_deg)
    order = np.argsort(azimuth, kind="stable")
    s0 = int(start.min())
    n_bins = int((start - s0 + n_samples).max())
    if n_bins < 1:
        raise ValueError("every beam has 0 samples")
    if n_bins > _MAX_BINS or n_bins * n > _MAX_IMAGE_CELLS:
        raise ValueError(f"{n_bins} range samples x {n} beams is implausibly large "
                         "(start range sample numbers corrupt?)")
    return azimuth, order, s0, n_bins


def _u16(buf: Any, p: int) -> int:
    return int(buf[p]) | (int(buf[p + 1]) << 8)


def sibling_paths(path: str | os.PathLike[str]) -> tuple[Path | None, Path | None]:
    """The ``(.all, .wcd)`` pair of a recording given either file (``None`` where absent).

    The sibling has the same stem and the other extension (either case); the given file is always
    part of the pair, whatever its extension (a file with another extension is taken as the
    ``.all``; :class:`KongsbergFile` reads its water column from it when it holds ``k``
    datagrams).  A sibling that exists but is not a directory is returned even if it is not a
    regular file, so that the reader refuses it (a FIFO) rather than silently ignoring it.
    """
    p = Path(path)
    if p.suffix.lower() == ".wcd":
        return find_sibling(p, ".all"), p
    return p, find_sibling(p, ".wcd")


def find_sibling(path: Path, suffix: str) -> Path | None:
    """The file beside ``path`` with its stem and ``suffix`` (lower or upper case) that is not a directory."""
    for s in (suffix, suffix.upper()):
        q = path.with_suffix(s)
        if q.exists() and not q.is_dir():
            return q
    return None


def pair_key(pair: tuple[Path | None, Path | None]) -> tuple[str, ...]:
    """A recording's identity from its pair of files (resolved paths; ``""`` where one is absent)."""
    return tuple(str(q.resolve()) if q is not None else "" for q in pair)


@functools.lru_cache(maxsize=32)
def _installation(raw: bytes) -> dict[str, float | str]:
    return parse_installation_text(raw.split(b"\0", 1)[0].decode("latin-1"))


def parse_installation_text(text: str) -> dict[str, float | str]:
    """The ``KEY=value,`` pairs of an installation-parameter datagram (numbers as float).

    Examples
    --------
    >>> parse_installation_text("WLZ=-4.908,SMH=2004,OSV=SIS 4.3.2,")
    {'WLZ': -4.908, 'SMH': 2004.0, 'OSV': 'SIS 4.3.2'}
    """
    out: dict[str, float | str] = {}
    for item in text.replace("\r", ",").replace("\n", ",").split(","):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key:
            continue
        value = value.strip()
        try:
            num = float(value)
        except ValueError:
            out[key] = value
        else:
            out[key] = num if math.isfinite(num) else value
    return out


# ---------------------------------------------------------------------- datagram index
@dataclasses.dataclass(frozen=True, eq=False)
class _Index:
    """The complete datagrams of one file: offsets and the decoded 20-byte headers."""

    path: Path
    buf: NDArray[np.uint8]
    offsets: NDArray[np.int64]
    headers: NDArray[Any]  # HEADER_DTYPE records

    def of_type(self, typ: int) -> NDArray[np.intp]:
        return np.flatnonzero(self.headers["type"] == typ)

    @functools.cached_property
    def times_ns(self) -> NDArray[np.int64]:
        """Header time of every datagram in ns since the epoch (-1 where date/time are invalid)."""
        dates = self.headers["date"]
        ms = self.headers["time_ms"].astype(np.int64)
        out = np.full(dates.size, -1, dtype=np.int64)
        for d in np.unique(dates):
            try:
                day = _day_ns(int(d))
            except ValueError:
                continue
            if day > MAX_TIME_NS - 86_401_000 * 1_000_000:
                continue
            sel = (dates == d) & (ms < 86_401_000)
            out[sel] = day + ms[sel] * 1_000_000
        return out

    def time_of(self, row: int, what: str) -> int:
        """Header time of datagram ``row`` (DataFormatError naming it if its date/time is invalid)."""
        t = int(self.times_ns[row])
        if t < 0:
            h = self.headers[row]
            raise DataFormatError(f"{what} datagram has an invalid date/time ({int(h['date'])}, "
                                  f"{int(h['time_ms'])} ms)", self.path, int(self.offsets[row]))
        return t

    def counts(self) -> dict[str, int]:
        types, n = np.unique(self.headers["type"], return_counts=True)
        return {chr(int(t)) if 32 < t < 127 else f"0x{int(t):02X}": int(c) for t, c in zip(types, n)}


def _open_buffer(path: Path, what: str) -> NDArray[np.uint8]:
    """The file memory-mapped read-only (regular files only; an empty one is an error)."""
    buf = map_file(path, what=what)
    if buf.size == 0:
        raise DataFormatError(f"{what} is empty", path, 0)
    return buf.view(np.ndarray)


#: Message of each corrupt-datagram status of the walk kernel (``{value}`` its ``err_val``,
#: ``{length}`` the length field at the offset, ``{max_bytes}`` the largest datagram accepted).
_WALK_ERRORS = {
    2: "datagram does not start with STX (0x02) but 0x{value:02X}: corrupt file or not a Kongsberg EM "
       "datagram stream",
    3: "datagram length field {value} is shorter than a datagram header",
    4: "datagram length field {value} is absurd (more than {max_bytes} bytes)",
    5: "datagram of {value} bytes does not end with ETX (0x03) where its length field says: corrupt length",
    6: "datagram length field {length} runs past the end of the file although a complete datagram starts "
       "at byte {value}: corrupt length",
}


def _walk_error(path: Path, buf: NDArray[np.uint8], status: int, err_off: int, err_val: int,
                messages: dict[int, str], max_bytes: int) -> DataFormatError:
    """The error of a datagram walk that stopped at a corrupt datagram (status > 1 of the walk
    kernels of this module and :mod:`sonarmap.io.kmall`), worded by ``messages[status]``."""
    length = int.from_bytes(bytes(buf[err_off : err_off + 4]), "little")
    text = messages[status].format(value=err_val, length=length, max_bytes=max_bytes)
    return DataFormatError(text, path, err_off)


def _walk(buf: NDArray[np.uint8], max_len: int, *, kmall: bool = False) -> tuple[NDArray[np.int64], int, int, int]:
    """The datagram walk of an EM ``.all``/``.wcd`` (or, with ``kmall``, a KMALL) file's bytes:
    (offsets of the complete datagrams, status, error offset, error value), see :func:`_walk_py`."""
    offs, status, err_off, err_val = _kernels().walk(buf, max_len, _KNOWN, kmall)
    return np.asarray(offs, dtype=np.int64), status, err_off, err_val


def _scan(path: Path, what: str) -> _Index:
    buf = _open_buffer(path, what)
    offs, status, err_off, err_val = _walk(buf, MAX_DATAGRAM_BYTES)
    if status == 1:
        need = f"{err_val + 4}" if err_val >= 0 else "at least 23"
        warn_partial(path, err_off, buf.size - err_off, need, "datagram", stacklevel=5)
    elif status:
        raise _walk_error(path, buf, status, err_off, err_val, _WALK_ERRORS, MAX_DATAGRAM_BYTES)
    return _Index(path, buf, offs, records_at(buf, offs, HEADER_DTYPE))


def _verify(index: _Index, rows: NDArray[np.intp], mode: Checksum, what: str) -> NDArray[np.intp]:
    """``rows`` whose checksums match (all of them unless a mismatch is skipped with mode 'warn')."""
    if mode == "ignore" or rows.size == 0:
        return rows
    offs = index.offsets[rows]
    lens = index.headers["length"][rows].astype(np.int64)
    k = _kernels()
    if k.checksums(index.buf, offs, lens) < 0:
        return rows
    keep = np.ones(rows.size, dtype=bool)
    start = 0
    while start < rows.size:
        bad = int(k.checksums(index.buf, offs[start:], lens[start:]))
        if bad < 0:
            break
        i = start + bad
        msg = f"checksum mismatch in {what} datagram '{chr(int(index.headers['type'][rows[i]]))}'"
        if mode == "error":
            raise DataFormatError(msg, index.path, int(offs[i]))
        warnings.warn(f"{index.path}: at byte {int(offs[i])}: {msg}; skipped", KongsbergWarning,
                      stacklevel=4)
        keep[i] = False
        start = i + 1
    return rows[keep]


def effective_pulse_us(bandwidth_hz: Any) -> float | None:
    """The effective (matched-filter) pulse length ``1 / B`` in µs of the transmit sectors'
    signal bandwidths ``B`` (Hz; their mean), or None when none is a plausible bandwidth.

    The range resolution of a pulse of bandwidth ``B`` is ``c / 2B``: a shaped CW pulse is
    shorter than its total signal length (the shared EM2040 file: 216 µs of signal, 6687 Hz of
    bandwidth, 150 µs effective) and an FM pulse is compressed to about ``1 / B``.
    """
    b = np.asarray(bandwidth_hz, dtype=np.float64).ravel()
    b = b[np.isfinite(b) & (b >= 100.0) & (b <= 1e7)]
    if b.size == 0:
        return None
    return round(1e6 / float(b.mean()), 3)


def image_to_db(image: NDArray[np.floating[Any]], full_scale_db: float = AMPLITUDE_DB_FULL_SCALE,
                *, step_db: float | None = AMPLITUDE_DB_STEP) -> NDArray[np.float64]:
    """The file's water-column amplitudes (dB) from a Kongsberg ping image.

    Parameters
    ----------
    image : ndarray, shape (n_bins, n_beams)
        ``Ping.image`` as read (linear intensity re ``full_scale_db``).
    full_scale_db : float
        ``Ping.meta["amplitude_db_full_scale"]``.
    step_db : float or None
        Round to this resolution (the datagram's 0.5 dB) to undo float32 rounding; None keeps the
        exact ``10 log10``.

    Returns
    -------
    ndarray of float64, shape (n_bins, n_beams)
        ``full_scale_db + 10 log10(image)``; NaN where the image is 0 (padding: no sample).

    Examples
    --------
    >>> image_to_db(np.array([[1.0, 0.0, 1e-3]], dtype=np.float32)).tolist()
    [[63.5, nan, 33.5]]
    """
    img = np.asarray(image, dtype=np.float64)
    out = np.full(img.shape, np.nan)
    pos = img > 0
    out[pos] = full_scale_db + 10.0 * np.log10(img[pos])
    if step_db:
        out[pos] = np.round(out[pos] / step_db) * step_db
    return out


def _checksum_ok(index: _Index, row: int) -> bool:
    off = index.offsets[row : row + 1]
    return bool(_kernels().checksums(index.buf, off, index.headers["length"][row : row + 1]
                                     .astype(np.int64)) < 0)


def _body(index: _Index, row: int, dtype: np.dtype, at: int = 0, count: int = 1) -> NDArray[Any]:
    """``count`` records of ``dtype`` starting ``at`` bytes into the body (after the 20-byte header).

    Raises DataFormatError if they do not fit before the datagram's ETX.
    """
    off = int(index.offsets[row])
    length = int(index.headers["length"][row])
    start = off + _HEADER + at
    stop = start + dtype.itemsize * count
    if count < 0 or stop > off + 4 + length - 3:
        typ = chr(int(index.headers["type"][row]))
        raise DataFormatError(
            f"datagram '{typ}' of {length} bytes is too short for {count} x {dtype.itemsize}-byte "
            f"records at body offset {at}", index.path, off)
    return np.frombuffer(index.buf, dtype=dtype, count=count, offset=start)


# ---------------------------------------------------------------------- pings
@dataclasses.dataclass(frozen=True, eq=False)
class _PingRecord:
    serial: int
    counter: int
    model: int
    time_ns: int
    nd: int
    total: int
    rows: tuple[int, ...]  # index rows of the datagrams present, by datagram number
    numbers: tuple[int, ...]
    nrx: tuple[int, ...]
    wc: np.void  # the first datagram's water-column header (_WC_DTYPE)
    tx: NDArray[Any]  # its transmit-sector table (_WC_TX_DTYPE)

    @property
    def complete(self) -> bool:
        return len(self.numbers) == self.nd


def _ping_records(index: _Index) -> list[_PingRecord]:
    rows = index.of_type(_T_WC)
    h = index.headers
    lengths = h["length"][rows].astype(np.int64)
    short = np.flatnonzero(lengths < 16 + _WC_DTYPE.itemsize + 3)
    if short.size:
        r = int(rows[short[0]])
        raise DataFormatError(f"water-column datagram of {int(h['length'][r])} bytes is shorter than "
                              "its fixed header", index.path, int(index.offsets[r]))
    offs = index.offsets[rows]
    wcs = (np.ascontiguousarray(index.buf[offs[:, None] + _HEADER + np.arange(_WC_DTYPE.itemsize)])
           .view(_WC_DTYPE).reshape(-1)) if rows.size else np.zeros(0, _WC_DTYPE)
    groups: dict[tuple[int, int, int, int], list[tuple[int, Any]]] = {}
    keys = zip(h["serial"][rows].tolist(), h["counter"][rows].tolist(), h["date"][rows].tolist(),
               h["time_ms"][rows].tolist())
    fields = zip(wcs["nd"].tolist(), wcs["dn"].tolist(), wcs["ntx"].tolist(), wcs["total"].tolist(),
                 wcs["nrx"].tolist(), lengths.tolist(), offs.tolist(), rows.tolist())
    for i, (key, (nd, dn, ntx, total, nrx, length, off, r)) in enumerate(zip(keys, fields)):
        if not 1 <= dn <= nd:
            raise DataFormatError(f"water-column datagram number {dn} of {nd} is out of range",
                                  index.path, off + 20)
        if ntx < 1 or nrx > total:
            raise DataFormatError(f"water-column datagram has {ntx} transmit sectors and {nrx} of "
                                  f"{total} beams", index.path, off + 20)
        need = 16 + 24 + 6 * ntx + 10 * nrx + 3
        if need > length:
            raise DataFormatError(
                f"water-column datagram of {length} bytes cannot hold {ntx} sectors and {nrx} beam "
                f"records ({need} bytes at least)", index.path, off)
        groups.setdefault(key, []).append((r, wcs[i]))
    out: list[_PingRecord] = []
    for (serial, counter, date, time_ms), items in groups.items():
        items.sort(key=lambda it: int(it[1]["dn"]))
        first = items[0]
        off0 = int(index.offsets[first[0]])
        with header_errors(index.path, off0, f"water-column datagram of ping {counter}"):
            t = _time_ns(date, time_ms)
        nd, total, ntx = int(first[1]["nd"]), int(first[1]["total"]), int(first[1]["ntx"])
        numbers: list[int] = []
        for r, wc in items:
            off = int(index.offsets[r])
            if (int(wc["nd"]), int(wc["total"]), int(wc["ntx"])) != (nd, total, ntx):
                raise DataFormatError(
                    f"water-column datagrams of ping {counter} (head {serial}) disagree: "
                    f"{int(wc['nd'])} datagrams / {int(wc['total'])} beams / {int(wc['ntx'])} sectors "
                    f"here, {nd} / {total} / {ntx} in the first", index.path, off + 20)
            if numbers and int(wc["dn"]) == numbers[-1]:
                raise DataFormatError(f"ping {counter} (head {serial}) has datagram {int(wc['dn'])} "
                                      "twice", index.path, off)
            numbers.append(int(wc["dn"]))
        nrx = tuple(int(wc["nrx"]) for _, wc in items)
        got = sum(nrx)
        if got > total or (len(numbers) == nd and got != total):
            raise DataFormatError(f"ping {counter} (head {serial}): its datagrams hold {got} beams, "
                                  f"their header says {total}", index.path, off0)
        tx = _body(index, first[0], _WC_TX_DTYPE, _WC_DTYPE.itemsize, ntx)
        out.append(_PingRecord(serial, counter, int(h["model"][first[0]]), t, nd, total,
                               tuple(r for r, _ in items), tuple(numbers), nrx, first[1], tx))
    out.sort(key=lambda p: (p.time_ns, p.serial, p.counter))
    return out


@dataclasses.dataclass
class _Beams:
    angle_cdeg: NDArray[np.int64]
    start: NDArray[np.int64]
    n_samples: NDArray[np.int64]
    detected: NDArray[np.int64]
    sector: NDArray[np.int64]
    data: NDArray[np.int64]
    position: NDArray[np.int64]  # beam position within the whole ping (-1 unknown)


def _decode_beams(index: _Index, rec: _PingRecord) -> _Beams:
    rows = np.asarray(rec.rows, dtype=np.intp)
    offs = index.offsets[rows]
    lens = index.headers["length"][rows].astype(np.int64)
    ntx = np.full(rows.size, int(rec.wc["ntx"]), dtype=np.int64)  # equal in all (checked)
    nrx = np.asarray(rec.nrx, dtype=np.int64)
    n = int(nrx.sum())
    arrs = [np.zeros(n, dtype=np.int64) for _ in range(6)]
    status, where = _kernels().beams(index.buf, offs, lens, ntx, nrx, *arrs)
    if status:
        reason = {
            1: "transmit-sector table runs past the end of the datagram",
            2: "beam record runs past the end of the datagram",
            3: "beam's sample count runs past the end of the datagram",
            4: "bytes are left over after the last beam (beam count or sample counts corrupt)",
        }[int(status)]
        raise DataFormatError(f"water-column datagram of ping {rec.counter} (head {rec.serial}): "
                              f"{reason}", index.path, int(where))
    angle, start, ns, dr, sector, data = arrs
    position = np.full(n, -1, dtype=np.int64)
    # position of each datagram's first beam within the ping: count from the front while every
    # earlier datagram is present, else from the back while every later one is
    numbers = list(rec.numbers)
    k = 0
    for i, (num, cnt) in enumerate(zip(numbers, rec.nrx)):
        first = None
        if numbers[: i + 1] == list(range(1, num + 1)):
            first = sum(rec.nrx[:i])
        elif numbers[i:] == list(range(num, rec.nd + 1)):
            first = rec.total - sum(rec.nrx[i:])
        if first is not None:
            position[k : k + cnt] = np.arange(first, first + cnt)
        k += cnt
    return _Beams(angle, start, ns, dr, sector, data, position)


@functools.lru_cache(maxsize=256)
def _ping_geometry(azimuth: bytes, s0: int, n_bins: int, sound_speed: float, sample_rate: float,
                   frequency: float, name: str, tx_beamwidth_deg: float | None = None,
                   rx_beamwidth_deg: float | None = None) -> SonarGeometry:
    """One head's geometry of one ping (cached: consecutive pings usually share it).
    ``tx_beamwidth_deg`` (the along-track transmit beamwidth the runtime parameters record)
    becomes ``elevation_beamwidth_rad`` when it is a plausible positive width; the receive
    beamwidth ``rx_beamwidth_deg`` (across track, in the fan's plane) becomes
    ``azimuth_beamwidth_rad`` (:data:`DEFAULT_RX_BEAMWIDTH_DEG` when not recorded)."""
    step = sound_speed / (2.0 * sample_rate)
    elevation = plausible_elevation_beamwidth(None if tx_beamwidth_deg is None else math.radians(tx_beamwidth_deg))
    rx = plausible_elevation_beamwidth(None if rx_beamwidth_deg is None else math.radians(rx_beamwidth_deg))
    return SonarGeometry.from_window(
        min_range_m=s0 * step,
        max_range_m=(s0 + n_bins) * step,
        n_bins=n_bins,
        azimuth_rad=np.frombuffer(azimuth, dtype=np.float64),
        frequency_hz=frequency,
        sound_speed_m_s=sound_speed,
        name=name,
        azimuth_source="table",
        elevation_beamwidth_rad=elevation,
        azimuth_beamwidth_rad=rx if rx is not None else math.radians(DEFAULT_RX_BEAMWIDTH_DEG),
    )


#: Receive beamwidth (degrees, across track) assumed when the runtime parameters do not give one:
#: the 1 deg receive array of the EM 2040 / EM 712 class.
DEFAULT_RX_BEAMWIDTH_DEG = 1.0


# ---------------------------------------------------------------------- ancillary data (.all)
class _Series:
    """A time series (ns) of values, for interpolation to ping times.

    Angles listed in ``angles`` (degrees, e.g. heading) are unwrapped before interpolating and
    wrapped to [0, 360) after.
    """

    def __init__(self, t_ns: NDArray[np.int64], values: dict[str, NDArray[np.float64]],
                 descriptor: int, angles: tuple[str, ...] = ()) -> None:
        self.t_ns = t_ns
        self.descriptor = descriptor
        self.angles = angles
        self._x = (t_ns - t_ns[0]).astype(np.float64) if t_ns.size else np.zeros(0)
        self._keys = list(values)
        self._v = np.array([np.rad2deg(np.unwrap(np.deg2rad(values[k]))) if k in angles
                            else values[k] for k in self._keys], dtype=np.float64).reshape(
                                len(self._keys), t_ns.size)
        self._wrap = np.array([k in angles for k in self._keys], dtype=bool)

    def at(self, t_ns: NDArray[np.int64]) -> list[tuple[dict[str, float], float] | None]:
        """Values at each of ``t_ns`` and the distance (s) to the series' span (0 inside); None
        where that distance exceeds :data:`MAX_EXTRAPOLATION_S` or the series is empty.  Outside
        the span the first/last value is held."""
        t = np.asarray(t_ns, dtype=np.int64)
        n = self.t_ns.size
        if n == 0:
            return [None] * t.size
        t0, t1 = int(self.t_ns[0]), int(self.t_ns[-1])
        gap = np.maximum(np.maximum(t0 - t, t - t1), 0) * 1e-9
        xi = (t - t0).astype(np.float64)
        vals = np.array([np.interp(xi, self._x, v) for v in self._v]).reshape(len(self._keys), t.size)
        vals[self._wrap] %= 360.0
        out: list[tuple[dict[str, float], float] | None] = []
        for k in range(t.size):
            if gap[k] > MAX_EXTRAPOLATION_S:
                out.append(None)
            else:
                out.append((dict(zip(self._keys, vals[:, k].tolist())), float(gap[k])))
        return out


class _Ancillary:
    """Installation, runtime, position, attitude, raw range/angle and XYZ of a recording."""

    def __init__(self, index: _Index, checksum: Checksum) -> None:
        self.index = index
        self.path = index.path
        self.checksum = checksum
        h = index.headers
        self.installation: dict[str, float | str] = {}
        self.installation_serials: tuple[int, int] = (0, 0)
        for r in _verify(index, index.of_type(_T_I), checksum, "installation"):
            r = int(r)
            off, length = int(index.offsets[r]), int(h["length"][r])
            second = _u16(index.buf, off + _HEADER) if length >= 21 else 0
            raw = bytes(index.buf[off + _HEADER + 2 : off + 4 + length - 3])
            self.installation = _installation(raw)  # shared (cached): copied into each ping
            self.installation_serials = (int(h["serial"][r]), second)
            break
        self.runtime: list[tuple[int, int, dict[str, float]]] = []
        for r in _verify(index, index.of_type(_T_R), checksum, "runtime"):
            rec = _body(index, int(r), _R_DTYPE)[0]
            t = index.time_of(int(r), "runtime")
            self.runtime.append((t, int(h["serial"][r]), _runtime_dict(rec)))
        self.runtime.sort(key=lambda x: x[0])
        self.position = self._positions()
        self.attitude = self._attitude()
        self.raw = self._by_ping(_T_N)
        self.xyz = self._by_ping(_T_X)
        self._mounting: dict[int, dict[str, Any]] = {}

    def _time(self, r: int, what: str) -> int:
        return self.index.time_of(r, what)

    def _by_ping(self, typ: int) -> dict[tuple[int, int], list[tuple[int, int]]]:
        h = self.index.headers
        out: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for r in self.index.of_type(typ):
            r = int(r)
            out.setdefault((int(h["serial"][r]), int(h["counter"][r])), []).append(
                (self._time(r, chr(typ)), r))
        return out

    def _positions(self) -> _Series:
        rows = _verify(self.index, self.index.of_type(_T_P), self.checksum, "position")
        recs = [(_body(self.index, int(r), _P_DTYPE)[0], self._time(int(r), "position")) for r in rows]
        active = [x for x in recs if int(x[0]["descriptor"]) & 0x80]
        if not active and recs:  # no system flagged active: the lowest-numbered one
            sysno = min(int(x[0]["descriptor"]) & 0x03 for x in recs)
            active = [x for x in recs if int(x[0]["descriptor"]) & 0x03 == sysno]
        active = [x for x in active if abs(int(x[0]["lat"])) <= 90 * 20_000_000
                  and abs(int(x[0]["lon"])) <= 180 * 10_000_000]
        active.sort(key=lambda x: x[1])
        t = np.array([x[1] for x in active], dtype=np.int64)
        p = np.array([x[0] for x in active], dtype=_P_DTYPE)
        t, keep = np.unique(t, return_index=True)
        p = p[keep]
        return _Series(
            t,
            {
                "latitude_deg": p["lat"] / 20_000_000.0,
                "longitude_deg": p["lon"] / 10_000_000.0,
                "position_fix_quality_m": p["quality"] / 100.0,
                "speed_over_ground_m_s": p["speed"] / 100.0,
                "course_over_ground_deg": p["course"] / 100.0,
            },
            int(p["descriptor"][0]) if p.size else 0,
            angles=("course_over_ground_deg",),
        )

    def _attitude(self) -> _Series:
        rows = _verify(self.index, self.index.of_type(_T_A), self.checksum, "attitude")
        chunks: list[tuple[int, NDArray[np.int64], NDArray[Any]]] = []
        for r in rows:
            r = int(r)
            n = int(_body(self.index, r, np.dtype("<u2"))[0])
            entries = _body(self.index, r, _A_DTYPE, 2, n)
            desc = int(_body(self.index, r, np.dtype("u1"), 2 + 12 * n)[0])
            t = self._time(r, "attitude") + entries["time_ms"].astype(np.int64) * 1_000_000
            chunks.append((desc, t, entries))
        # the motion sensor whose roll is in use (descriptor bit 1 clear), else the most common one
        descs = [c[0] for c in chunks]
        in_use = [d for d in descs if not d & 0x02]
        pick = in_use[0] if in_use else (max(set(descs), key=descs.count) if descs else 0)
        sel = [c for c in chunks if (c[0] >> 4) & 0x03 == (pick >> 4) & 0x03]
        if sel:
            t = np.concatenate([c[1] for c in sel])
            e = np.concatenate([c[2] for c in sel])
            t, keep = np.unique(t, return_index=True)
            e = e[keep]
        else:
            t, e = np.zeros(0, np.int64), np.zeros(0, _A_DTYPE)
        return _Series(
            t,
            {
                "roll_deg": e["roll"] / 100.0,
                "pitch_deg": e["pitch"] / 100.0,
                "heave_m": e["heave"] / 100.0,
                "heading_deg": e["heading"] / 100.0,
            },
            pick,
            angles=("heading_deg",),
        )

    def nearest(self, table: dict[tuple[int, int], list[tuple[int, int]]], serial: int, counter: int,
                t_ns: int, what: str) -> int | None:
        best = None
        for t, r in table.get((serial, counter), []):
            dt = abs(t - t_ns)
            if dt <= 5_000_000_000 and (best is None or dt < best[0]):
                best = (dt, r)
        if best is None:
            return None
        r = best[1]
        if self.checksum == "ignore" or _checksum_ok(self.index, r):
            return r
        rows = _verify(self.index, np.array([r], dtype=np.intp), self.checksum, what)
        return int(rows[0]) if rows.size else None

    def runtime_at(self, serial: int, t_ns: int) -> dict[str, float] | None:
        cands = [x for x in self.runtime if x[1] == serial] or self.runtime
        before = [x for x in cands if x[0] <= t_ns]
        pick = before[-1] if before else (cands[0] if cands else None)
        return None if pick is None else pick[2]

    def mounting(self, serial: int) -> dict[str, Any]:
        """Lever arms (m) and mounting angles (deg) of the head's TX and RX transducers (cached)."""
        if serial not in self._mounting:
            self._mounting[serial] = self._mounting_of(serial)
        return self._mounting[serial]

    def _mounting_of(self, serial: int) -> dict[str, Any]:
        inst = self.installation
        if not inst:
            return {}
        stc = int(_num(inst.get("STC")) or 0)
        s1, s2 = self.installation_serials
        second = serial == s2 and serial != s1
        tx, rx = {0: ("S1", "S2"), 1: ("S1", "S1"), 2: ("S2", "S2") if second else ("S1", "S1"),
                  3: ("S1", "S3") if second else ("S1", "S2"),
                  4: ("S1", "S3") if second else ("S0", "S2")}.get(stc, ("S1", "S2"))
        out: dict[str, Any] = {}
        for role, pre in (("tx", tx), ("rx", rx)):
            xyz = [_num(inst.get(f"{pre}{a}")) for a in "XYZ"]
            rph = [_num(inst.get(f"{pre}{a}")) for a in "RPH"]
            if all(v is not None for v in xyz):
                out[f"{role}_lever_arm_m"] = np.array(xyz, dtype=np.float64)
            if all(v is not None for v in rph):
                out[f"{role}_mounting_deg"] = np.array(rph, dtype=np.float64)
            out[f"{role}_transducer"] = pre
        wlz = _num(inst.get("WLZ"))
        if wlz is not None:
            out["waterline_z_m"] = wlz
        return out


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, float) and math.isfinite(v) else None


def _runtime_dict(r: np.void) -> dict[str, float]:
    scaled = {
        "runtime_mode": ("mode", 1.0), "runtime_filter_id": ("filter_id", 1.0),
        "runtime_min_depth_m": ("min_depth", 1.0), "runtime_max_depth_m": ("max_depth", 1.0),
        "runtime_absorption_db_km": ("absorption", 0.01),
        "runtime_pulse_length_us": ("pulse_length", 1.0),
        "runtime_tx_beamwidth_deg": ("tx_beamwidth", 0.1), "runtime_tx_power_db": ("tx_power", 1.0),
        "runtime_rx_beamwidth_deg": ("rx_beamwidth", 0.1),
        "runtime_rx_bandwidth_hz": ("rx_bandwidth", 50.0), "runtime_mode2": ("mode2", 1.0),
        "runtime_tvg_crossover_deg": ("tvg_crossover", 1.0),
        "runtime_max_port_coverage_deg": ("max_port_coverage", 1.0),
        "runtime_max_starboard_coverage_deg": ("max_stbd_coverage", 1.0),
        "runtime_tx_along_tilt_deg": ("tx_along_tilt", 0.1),
    }  # fmt: skip
    out: dict[str, float] = {}
    for key, (field, scale) in scaled.items():
        v = int(r[field])
        out[key] = v if scale == 1.0 and not key.endswith(("_m", "_us", "_db", "_deg")) else v * scale
    return out


# ---------------------------------------------------------------------- the file
class KongsbergFile(ClosingFile):
    """Lazy, memory-mapped access to the water-column pings of a Kongsberg EM recording.

    Parameters
    ----------
    path : path-like
        The ``.all`` or the ``.wcd`` file of a recording; its sibling (same stem, other extension)
        is found automatically.  Water column comes from the ``.wcd`` (or from the ``.all`` when it
        holds ``k`` datagrams and no ``.wcd`` exists); navigation, attitude, installation, runtime,
        raw range/angle and XYZ from the ``.all`` (from the ``.wcd`` when there is no ``.all``).
    geometry : SonarGeometry, preset name or JSON path, optional
        Overrides the geometry derived from each ping (its shape must match).
    checksum : {"error", "warn", "ignore"}
        What a datagram whose checksum does not match does: raise :class:`DataFormatError`
        (default), be skipped with a :class:`KongsbergWarning`, or go unchecked.

    Examples
    --------
    >>> with KongsbergFile("0077_20221109_123655_Belgica.all") as f:   # doctest: +SKIP
    ...     print(len(f), f[0].shape, f[0].meta["system_serial"])

    Raises
    ------
    DataFormatError
        Missing, non-regular or corrupt files (the message gives the file and byte offset), or no
        water-column datagrams in either file.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        geometry: SonarGeometry | str | os.PathLike[str] | None = None,
        checksum: Checksum = "error",
    ) -> None:
        if checksum not in ("error", "warn", "ignore"):
            raise DataFormatError(f"checksum must be 'error', 'warn' or 'ignore', not {checksum!r}")
        self.path = require_regular_file(path, "Kongsberg file")
        self.checksum: Checksum = checksum
        self._override = None if geometry is None else as_geometry(geometry)
        all_path, wcd_path = sibling_paths(self.path)
        if wcd_path is not None:
            wcd_path = require_regular_file(wcd_path, "Kongsberg .wcd file")
        if all_path is not None:
            all_path = require_regular_file(all_path, "Kongsberg .all file")
        self.all_path = all_path
        self.wcd_path = wcd_path
        given = _scan(self.path, "Kongsberg file")
        if self.path == wcd_path or (wcd_path is None and given.of_type(_T_WC).size):
            self._wc = given
        elif wcd_path is not None:
            self._wc = _scan(wcd_path, "Kongsberg .wcd file")
        else:
            raise DataFormatError("no water-column ('k') datagrams and no .wcd file beside it",
                                  self.path)
        self._anc_index = given if (self.path == all_path or all_path is None) else None
        self._ancillary: _Ancillary | None = None
        self._scratch = np.empty(0, dtype=np.float32)
        self._nav: dict[int, tuple[Any, Any]] | None = None
        self.records = _ping_records(self._wc)
        if not self.records:
            raise DataFormatError("no water-column ('k') datagrams", self._wc.path)
        for rec in self.records:
            if not rec.complete:
                missing = sorted(set(range(1, rec.nd + 1)) - set(rec.numbers))
                warnings.warn(
                    f"{self._wc.path}: at byte {int(self._wc.offsets[rec.rows[0]])}: ping "
                    f"{rec.counter} of head {rec.serial} is incomplete (datagram "
                    f"{', '.join(map(str, missing))} of {rec.nd} missing, {sum(rec.nrx)} of "
                    f"{rec.total} beams); yielded with the beams received",
                    PartialFrameWarning,
                    stacklevel=3,
                )

    # ------------------------------------------------------------------ sequence protocol
    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, index: int) -> Ping:
        return self._ping(self.records[self._index(index)])

    def __iter__(self) -> Iterator[Ping]:
        for rec in self.records:
            yield self._ping(rec)

    def close(self) -> None:
        """Release the memory maps (pings already returned stay valid: images are copies)."""
        self.records = []
        self._ancillary = None
        self._anc_index = None
        self._nav = None
        self._scratch = np.empty(0, dtype=np.float32)
        self.all_path = None
        self._wc = _Index(self._wc.path, np.zeros(0, np.uint8), np.zeros(0, np.int64),
                          np.zeros(0, HEADER_DTYPE))

    def __repr__(self) -> str:
        heads = sorted({r.serial for r in self.records})
        return f"KongsbergFile({str(self.path)!r}, pings={len(self)}, heads={heads})"

    # ------------------------------------------------------------------ access
    @property
    def water_column_path(self) -> Path:
        """The file the water-column datagrams are read from."""
        return self._wc.path

    @property
    def heads(self) -> list[int]:
        """System serial numbers of the heads, in ping order."""
        return list(dict.fromkeys(r.serial for r in self.records))

    def datagram_counts(self) -> dict[str, dict[str, int]]:
        """Datagram counts by type character for each file read (headers only)."""
        out = {str(self._wc.path): self._wc.counts()}
        anc = self.ancillary_index
        if anc is not None and anc.path != self._wc.path:
            out[str(anc.path)] = anc.counts()
        return out

    @property
    def ancillary_index(self) -> _Index | None:
        if self._anc_index is None:
            if self.all_path is not None and self.all_path != self._wc.path:
                self._anc_index = _scan(self.all_path, "Kongsberg .all file")
            else:
                self._anc_index = self._wc
        return self._anc_index

    @property
    def ancillary(self) -> _Ancillary:
        """Installation, runtime, navigation and bottom-detection datagrams (parsed on first use)."""
        if self._ancillary is None:
            idx = self.ancillary_index
            assert idx is not None
            self._ancillary = _Ancillary(idx, self.checksum)
        return self._ancillary

    def _navigation(self) -> dict[int, tuple[Any, Any]]:
        """Position and attitude at every ping time, interpolated once for all pings."""
        if self._nav is None:
            anc = self.ancillary
            times = np.array(sorted({r.time_ns for r in self.records}), dtype=np.int64)
            self._nav = dict(zip(times.tolist(), zip(anc.position.at(times), anc.attitude.at(times))))
        return self._nav

    def geometry(self, index: int = 0) -> SonarGeometry:
        """Geometry of ping ``index`` (decodes its beam headers only)."""
        rec = self.records[self._index(index)]
        if self._override is not None:
            return self._override
        return self._geometry(rec, _decode_beams(self._wc, rec))[0]

    # ------------------------------------------------------------------ internals
    def _index(self, index: int) -> int:
        return check_index(index, len(self.records))

    @staticmethod
    def _wc_header(rec: _PingRecord) -> tuple[np.void, NDArray[Any]]:
        return rec.wc, rec.tx

    def _geometry(self, rec: _PingRecord, beams: _Beams) -> tuple[SonarGeometry, NDArray[np.intp], int, int]:
        wc, tx = self._wc_header(rec)
        off = int(self._wc.offsets[rec.rows[0]])
        n = beams.angle_cdeg.size
        with header_errors(self._wc.path, off, f"water-column datagram of ping {rec.counter} "
                           f"(head {rec.serial})"):
            if n == 0:
                raise ValueError("no beams")
            if np.any(beams.sector >= int(wc["ntx"])):
                raise ValueError(f"a beam's transmit sector is >= the {int(wc['ntx'])} sectors")
            azimuth, order, s0, n_bins = _beam_layout(beams.angle_cdeg / 100.0, beams.start, beams.n_samples)
            sample_rate = int(wc["sample_rate"]) / 100.0
            if sample_rate <= 0:
                raise ValueError("sample rate is 0")
            freq = float(np.mean(tx["frequency"])) * 10.0
            run = self.ancillary.runtime_at(rec.serial, rec.time_ns)
            geom = _ping_geometry(
                np.ascontiguousarray(azimuth[order]).tobytes(), s0, n_bins,
                int(wc["sound_speed"]) / 10.0, sample_rate, freq, f"em{rec.model}-{rec.serial}",
                None if run is None else run["runtime_tx_beamwidth_deg"],
                None if run is None else run["runtime_rx_beamwidth_deg"])
        return geom, order, s0, n_bins

    def _ping(self, rec: _PingRecord) -> Ping:
        wc_index = self._wc
        rows = np.asarray(rec.rows, dtype=np.intp)
        kept = _verify(wc_index, rows, self.checksum, "water-column")
        if kept.size != rows.size:  # checksum="warn" skipped a datagram: use those that remain
            good = set(kept.tolist())
            keep = [i for i, r in enumerate(rec.rows) if r in good]
            if not keep:
                raise DataFormatError(f"ping {rec.counter} (head {rec.serial}) has no datagram with "
                                      "a valid checksum", wc_index.path, int(wc_index.offsets[rows[0]]))
            rec = dataclasses.replace(rec, rows=tuple(rec.rows[i] for i in keep),
                                      numbers=tuple(rec.numbers[i] for i in keep),
                                      nrx=tuple(rec.nrx[i] for i in keep))
        beams = _decode_beams(wc_index, rec)
        geom, order, s0, n_bins = self._geometry(rec, beams)
        cells = order.size * n_bins
        if self._scratch.size < cells:
            self._scratch = np.empty(max(cells, 2 * self._scratch.size), dtype=np.float32)
        by_beam = self._scratch[:cells].reshape(order.size, n_bins)  # reused: no page faults
        _kernels().fill(wc_index.buf, beams.data, beams.n_samples, beams.start - s0,
                        order.astype(np.int64), _AMP_LUT, by_beam)
        image = np.ascontiguousarray(by_beam.T)
        return Ping(
            image=image,
            geometry=geom if self._override is None else self._override,
            time_ns=rec.time_ns,
            source=f"{self.path}#head{rec.serial}/ping{rec.counter}",
            meta=self._meta(rec, beams, order, s0, n_bins),
        )

    def _meta(self, rec: _PingRecord, beams: _Beams, order: NDArray[np.intp], s0: int,
              n_bins: int) -> dict[str, Any]:
        wc, tx = self._wc_header(rec)
        c = int(wc["sound_speed"]) / 10.0
        fs = int(wc["sample_rate"]) / 100.0
        step = c / (2.0 * fs)
        dr = beams.detected[order]
        det_samples = dr.astype(np.float64)
        det_bin = dr - s0
        bad = (dr == 0) | (det_bin < 0) | (det_bin >= n_bins)
        if bad.any():
            det_samples[dr == 0] = math.nan
            det_bin[bad] = -1
        position = beams.position[order]
        meta: dict[str, Any] = {
            "format": FORMAT,
            "em_model": rec.model,
            "system_serial": rec.serial,
            "ping_counter": rec.counter,
            "complete": rec.complete,
            "n_datagrams": rec.nd,
            "n_datagrams_received": len(rec.numbers),
            "n_beams_total": rec.total,
            "n_beams_received": int(beams.angle_cdeg.size),
            "sound_speed_m_s": c,
            "sample_rate_hz": fs,
            "range_per_sample_m": step,
            "start_range_sample": s0,
            "tvg_function": int(wc["tvg_x"]),
            "tvg_offset_db": float(wc["tvg_c"]),
            "tx_time_heave_m": int(wc["tx_heave"]) / 100.0,
            "scanning_info": int(wc["scanning"]),
            "n_tx_sectors": int(wc["ntx"]),
            "tx_sector_tilt_deg": tx["tilt"] / 100.0,
            "tx_sector_frequency_hz": tx["frequency"] * 10.0,
            "amplitude_db_full_scale": AMPLITUDE_DB_FULL_SCALE,
            "amplitude_db_step": AMPLITUDE_DB_STEP,
            "beam_pointing_angle_deg": beams.angle_cdeg[order] / 100.0,
            "beam_index": position,
            "beam_tx_sector": beams.sector[order],
            "beam_start_sample": beams.start[order],
            "beam_n_samples": beams.n_samples[order],
            "detected_range_samples": det_samples,
            "detected_range_m": det_samples * step,
            "detected_bin": det_bin,
            "water_column_file": str(self._wc.path),
        }
        anc = self.ancillary
        meta["ancillary_file"] = str(anc.path)
        self._raw_meta(meta, anc, rec, position, fs)
        self._xyz_meta(meta, anc, rec, position)
        pos, att = self._navigation()[rec.time_ns]
        if pos is not None:
            meta.update(pos[0])
            meta["position_gap_s"] = pos[1]
            meta["position_system"] = anc.position.descriptor
        if att is not None:
            meta.update(att[0])
            meta["attitude_gap_s"] = att[1]
            meta["attitude_sensor"] = anc.attitude.descriptor
        run = anc.runtime_at(rec.serial, rec.time_ns)
        if run is not None:
            meta.update(run)
            meta.setdefault("pulse_width_us", run["runtime_pulse_length_us"])
        for key, v in anc.mounting(rec.serial).items():
            meta[key] = v.copy() if isinstance(v, np.ndarray) else v
        if anc.installation:
            meta["installation"] = dict(anc.installation)
        return meta

    def _raw_meta(self, meta: dict[str, Any], anc: _Ancillary, rec: _PingRecord,
                  position: NDArray[np.int64], fs: float) -> None:
        r = anc.nearest(anc.raw, rec.serial, rec.counter, rec.time_ns, "raw range and angle")
        if r is None:
            return
        head = _body(anc.index, r, _N_DTYPE)[0]
        ntx, nrx = int(head["ntx"]), int(head["nrx"])
        txs = _body(anc.index, r, _N_TX_DTYPE, 16, ntx)
        rx = _body(anc.index, r, _N_RX_DTYPE, 16 + 24 * ntx, nrx)
        meta["raw_sample_rate_hz"] = float(head["sample_rate"])
        meta["raw_n_valid"] = int(head["n_valid"])
        meta["raw_tx_signal_length_s"] = txs["signal_length"].astype(np.float64)
        meta["raw_tx_delay_s"] = txs["delay"].astype(np.float64)
        meta["raw_tx_frequency_hz"] = txs["frequency"].astype(np.float64)
        meta["raw_tx_bandwidth_hz"] = txs["bandwidth"].astype(np.float64)
        if ntx:
            meta["absorption_db_km"] = float(txs["absorption"].sum()) / ntx / 100.0
            pulse = round(float(txs["signal_length"].sum()) / ntx * 1e6, 3)
            if math.isfinite(pulse) and pulse > 0:
                meta["pulse_width_us"] = pulse
            effective = effective_pulse_us(txs["bandwidth"])
            if effective is not None:
                meta["effective_pulse_us"] = effective
        meta["raw_matched"] = nrx == rec.total
        if nrx != rec.total:
            return
        beam = _per_beam(rx, position, {"raw_twtt_s": ("twtt", 1.0),
                                        "raw_beam_angle_deg": ("angle", 0.01),
                                        "raw_detection_info": ("detection", 1.0),
                                        "raw_quality_factor": ("quality", 1.0),
                                        "raw_reflectivity_db": ("reflectivity", 0.1)})
        meta["raw_valid"] = beam.pop("_valid")
        meta.update(beam)
        meta["raw_range_samples"] = beam["raw_twtt_s"] * fs

    def _xyz_meta(self, meta: dict[str, Any], anc: _Ancillary, rec: _PingRecord,
                  position: NDArray[np.int64]) -> None:
        r = anc.nearest(anc.xyz, rec.serial, rec.counter, rec.time_ns, "XYZ")
        if r is None:
            return
        head = _body(anc.index, r, _X_DTYPE)[0]
        n = int(head["n"])
        rx = _body(anc.index, r, _X_RX_DTYPE, 20, n)
        meta["xyz_heading_deg"] = int(head["heading"]) / 100.0
        meta["xyz_sound_speed_m_s"] = int(head["sound_speed"]) / 10.0
        meta["xyz_tx_depth_m"] = float(head["tx_depth"])
        meta["xyz_n_valid"] = int(head["n_valid"])
        meta["xyz_matched"] = n == rec.total
        if n != rec.total:
            return
        beam = _per_beam(rx, position, {"xyz_depth_m": ("depth", 1.0),
                                        "xyz_across_m": ("across", 1.0),
                                        "xyz_along_m": ("along", 1.0),
                                        "xyz_detection_info": ("detection", 1.0),
                                        "xyz_quality_factor": ("quality", 1.0),
                                        "xyz_reflectivity_db": ("reflectivity", 0.1)})
        meta["xyz_valid"] = beam.pop("_valid")
        meta.update(beam)


def _per_beam(rx: NDArray[Any], position: NDArray[np.int64],
              fields: dict[str, tuple[str, float]]) -> dict[str, NDArray[Any]]:
    """Per-column float64 arrays of ``rx`` fields (times a scale) at the beams' positions in the
    ping (NaN where a column's position is unknown, -1), and under ``"_valid"`` whether the
    beam's detection is valid (detection-info bit 7 clear; False where unknown)."""
    ok = position >= 0
    identity = position.size == rx.size and bool(np.array_equal(position, np.arange(rx.size)))
    pos = None if identity else np.where(ok, position, 0)
    missing = None if identity or ok.all() else ~ok
    out: dict[str, NDArray[Any]] = {}
    for key, (field, scale) in fields.items():
        v = rx[field] if pos is None else rx[field][pos]
        arr = v.astype(np.float64)
        if scale != 1.0:
            arr *= scale
        if missing is not None:
            arr[missing] = math.nan
        out[key] = arr
    det = rx["detection"] if pos is None else rx["detection"][pos]
    valid = (det & 0x80) == 0
    if missing is not None:
        valid &= ok
    out["_valid"] = valid
    return out


# ---------------------------------------------------------------------- registry hooks
def sniff(path: Path, head: bytes) -> bool:
    """A Kongsberg EM datagram at the start: plausible length, STX, known type and EM model, a
    valid date, and ETX where the length says (when that byte is within ``head``)."""
    if len(head) < _HEADER:
        return False
    h = np.frombuffer(head[:_HEADER], dtype=HEADER_DTYPE)[0]
    length = int(h["length"])
    if not (_MIN_LENGTH <= length <= MAX_DATAGRAM_BYTES and int(h["stx"]) == 0x02):
        return False
    if int(h["type"]) not in DATAGRAM_TYPES or int(h["model"]) not in EM_MODELS:
        return False
    try:
        _time_ns(int(h["date"]), int(h["time_ms"]))
    except ValueError:
        return False
    end = 4 + length - 3
    return not (end < len(head) and head[end] != 0x03)


def iter_pings(
    path: str | os.PathLike[str],
    *,
    geometry: SonarGeometry | str | os.PathLike[str] | None = None,
    start: int = 0,
    stop: int | None = None,
    checksum: Checksum = "error",
    **_: Any,
) -> Iterator[Ping]:
    """Lazily yield water-column pings ``start:stop`` of a recording (one per ping counter and head).

    Pings are in time order (ties: head serial).  Given the ``.all`` or the ``.wcd``, both files
    of the recording are used; see :class:`KongsbergFile`.  The pings before ``start`` are not
    decoded (the datagram index locates every ping).

    Raises
    ------
    InputError
        If ``start`` or ``stop`` is not a non-negative integer.
    DataFormatError
        See :class:`KongsbergFile`.
    """
    with KongsbergFile(path, geometry=geometry, checksum=checksum) as f:
        yield from iter_indexed(f, start, stop)


def recording_key(path: str | os.PathLike[str]) -> tuple[str, ...]:
    """The recording a file belongs to: its ``.all`` / ``.wcd`` pair (read once when both are given)."""
    return pair_key(sibling_paths(path))


def count_pings(path: str | os.PathLike[str]) -> int:
    """Number of pings (ping counter x head) from the datagram headers only."""
    return count_container_pings(KongsbergFile, path)


def summary(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Ping count, heads, time span, first ping's geometry and datagram counts (no sample decoding)."""
    with KongsbergFile(path) as f:
        recs = f.records
        geom = f.geometry(0)
        wc, _ = f._wc_header(recs[0])
        per_head = {str(s): sum(1 for r in recs if r.serial == s) for s in f.heads}
        counts = f.datagram_counts()
        details: dict[str, Any] = {
            "em_model": recs[0].model,
            "heads": ", ".join(str(s) for s in f.heads),
            "pings_per_head": ", ".join(f"{k}: {v}" for k, v in per_head.items()),
            "incomplete_pings": sum(1 for r in recs if not r.complete),
            "water_column_file": str(f.water_column_path),
            "ancillary_file": str(f.ancillary_index.path) if f.ancillary_index else "none",
            "sound_speed_m_s": int(wc["sound_speed"]) / 10.0,
            "sample_rate_hz": int(wc["sample_rate"]) / 100.0,
        }
        for name, c in counts.items():
            details[f"datagrams {Path(name).suffix or Path(name).name}"] = ", ".join(
                f"{k} {v}" for k, v in c.items())
        return make_summary(FORMAT, path, n_pings=len(recs), geometry=geom,
                            time_start_ns=recs[0].time_ns, time_end_ns=recs[-1].time_ns, **details)
