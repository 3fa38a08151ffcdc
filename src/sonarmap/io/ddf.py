"""SoundMetrics DIDSON recordings (``.ddf``, file formats ``DDF_03`` and ``DDF_04``).

Layout (published DIDSON file-format description, as used by the vendor's MATLAB readers;
little-endian)::

    version  file header   frame header   magic
    DDF_03   512 bytes     256 bytes      b"DDF\\x03"
    DDF_04   1024 bytes    1024 bytes     b"DDF\\x04"

    frame    frame header + samplesperchannel x numbeams uint8, stored [sample][beam]

* ``numbeams`` (96 high-frequency / 48 low-frequency), ``samplesperchannel`` (512) and
  ``resolution`` (1 = HF) come from the file header; ``reverse == 0`` means beam 0 is the right-most
  beam (the reader flips the beam axis so azimuth increases with column), non-zero means an
  inverted mount (no flip).
* The range window is coded per frame: ``windowstart`` code 0-31 times 0.375 m (HF, classic
  windows) or 0.419 m (extended windows), doubled at LF; ``windowlength`` code 0-3 indexes, after
  adding 2 at LF, the table for the configuration (``configflags & 3`` - bit 0: classic windows,
  bit 1: long-range DIDSON): standard extended 1.25/2.5/5/10/20/40 m, standard classic
  1.125/2.25/4.5/9/18/36 m, LR extended 2.5/5/10/20/40/70 m, LR classic 2.25/4.5/9/18/36/72 m.
  Serial numbers below 19 are classic windows, serial 15 is an LR classic unit (vendor's special
  cases).  Range of row ``i`` is ``start + i * length / samples``.
* Time: the frame header's calendar fields (year ... hundredths), taken as UTC; if they are all
  zero, ``frametime`` (seconds, microseconds).  Times must lie in the years 1970-2200 (all-zero
  fields give 0, "unknown").
* Plausibility: ``numbeams`` 1-512, ``samplesperchannel`` 1-8192, file-header ``framerate``
  0-100 Hz, frame ``receivergain`` -100-100 dB; anything else is a
  :class:`~sonarmap.errors.DataFormatError`.
* Azimuths: 96-beam standard DIDSON frames use the measured table of the ``didson-hf`` preset
  (with its beam pattern and taper); other configurations assume uniform beams over 28.8 degrees
  (0.3 degree spacing x 96 or 0.6 degree x 48) with a :class:`~sonarmap.geometry.GeometryWarning`.

No public DDF sample exists; the reader is tested against files made by a test-only writer that
follows this layout (``tests/support/ddf_writer.py``).
"""

from __future__ import annotations

import calendar
import functools
import math
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from sonarmap.errors import DataFormatError
from sonarmap.geometry import GeometryWarning, SonarGeometry, as_geometry, preset, uniform_azimuths
from sonarmap.io._binary import (
    U8_SCALE,
    ClosingFile,
    check_index,
    check_plausible,
    check_time_ns,
    count_container_pings,
    finite_or,
    header_errors,
    iter_container_pings,
    make_summary,
    map_file,
    map_frames,
)
from sonarmap.io.reader import GeometrySpec
from sonarmap.ping import Ping

__all__ = [
    "FORMAT",
    "FILE_HEADER_DTYPES",
    "FRAME_HEADER_DTYPES",
    "WINDOW_LENGTHS_M",
    "DdfFile",
    "window_m",
    "sniff",
    "iter_pings",
    "count_pings",
    "summary",
]

FORMAT = "ddf"
_i4, _f4, _f8 = "<i4", "<f4", "<f8"


def _file_header(user_bytes: int) -> np.dtype:
    fields: list[tuple[str, Any]] = [("version", "S4")]
    fields += [(n, _i4) for n in ("numframes", "framerate", "resolution", "numbeams")]
    fields += [("samplerate", _f4)]
    fields += [(n, _i4) for n in ("samplesperchannel", "receivergain", "windowstart",
                                  "windowlength", "reverse", "serialnumber")]
    fields += [("date", "S32"), ("idstring", "S256")]
    fields += [(n, _i4) for n in ("id1", "id2", "id3", "id4", "startframe", "endframe",
                                  "timelapse", "recordinterval", "radioseconds", "frameinterval")]
    fields += [("userassigned", f"V{user_bytes}")]
    return np.dtype(fields)


def _frame_header(user_bytes: int) -> np.dtype:
    fields: list[tuple[str, Any]] = [("framenumber", _i4), ("frametime", _i4), ("frametime2", _i4)]
    fields += [("version", "S4")]
    fields += [(n, _i4) for n in ("status", "year", "month", "day", "hour", "minute", "second",
                                  "hsecond", "transmit", "windowstart", "windowlength",
                                  "threshold", "intensity", "receivergain", "degc1", "degc2",
                                  "humidity", "focus", "battery")]
    fields += [("status1", "S16"), ("status2", "S8")]
    fields += [(n, _f4) for n in ("panwcom", "tiltwcom", "velocity", "depth", "altitude", "pitch",
                                  "pitchrate", "roll", "rollrate", "heading", "headingrate",
                                  "sonarpan", "sonartilt", "sonarroll")]
    fields += [("latitude", _f8), ("longitude", _f8), ("sonarposition", _f4), ("configflags", _i4)]
    fields += [("userassigned", f"V{user_bytes}")]
    return np.dtype(fields)


#: File-header dtypes by DDF version (512 and 1024 bytes).
FILE_HEADER_DTYPES = {3: _file_header(136), 4: _file_header(648)}
#: Frame-header dtypes by DDF version (256 and 1024 bytes).
FRAME_HEADER_DTYPES = {3: _frame_header(60), 4: _frame_header(828)}
assert FILE_HEADER_DTYPES[3].itemsize == 512 and FILE_HEADER_DTYPES[4].itemsize == 1024
assert FRAME_HEADER_DTYPES[3].itemsize == 256 and FRAME_HEADER_DTYPES[4].itemsize == 1024

#: Window lengths (m) by configuration (configflags & 3), indexed by code + 2 * (low frequency).
WINDOW_LENGTHS_M = {
    0: (1.25, 2.5, 5.0, 10.0, 20.0, 40.0),  # DIDSON-S, extended windows
    1: (1.125, 2.25, 4.5, 9.0, 18.0, 36.0),  # DIDSON-S, classic windows
    2: (2.5, 5.0, 10.0, 20.0, 40.0, 70.0),  # DIDSON-LR, extended windows
    3: (2.25, 4.5, 9.0, 18.0, 36.0, 72.0),  # DIDSON-LR, classic windows
}
_MAX_BEAMS = 512
_MAX_SAMPLES = 8192
_MAX_FRAME_RATE_HZ = 100
_GAIN_DB = (-100.0, 100.0)


def effective_config(configflags: int, serial_number: int) -> int:
    """Window configuration ``configflags & 3`` with the vendor's serial-number special cases."""
    cfg = int(configflags) & 3
    if serial_number < 19:
        cfg = 1
    if serial_number == 15:
        cfg = 3
    return cfg


def window_m(start_code: int, length_code: int, *, high_frequency: bool, config: int) -> tuple[float, float]:
    """Decode DIDSON window codes into ``(start, length)`` in metres.

    Raises
    ------
    ValueError
        If a code is outside its range.
    """
    if not 0 <= start_code <= 31:
        raise ValueError(f"window start code {start_code} is outside 0-31")
    idx = int(length_code) + (0 if high_frequency else 2)
    if not 0 <= idx < 6 or not 0 <= length_code <= 3:
        raise ValueError(f"window length code {length_code} is outside 0-3")
    unit = 0.375 if config in (1, 3) else 0.419
    start = start_code * unit * (1 if high_frequency else 2)
    return start, WINDOW_LENGTHS_M[config][idx]


@functools.lru_cache(maxsize=128)
def _geometry(
    n_beams: int, n_samples: int, start_m: float, length_m: float, high_frequency: bool,
    long_range: bool, rx_gain_db: float,
) -> SonarGeometry:
    freq = (1.2e6 if high_frequency else 0.7e6) if long_range else (1.8e6 if high_frequency else 1.1e6)
    common: dict[str, Any] = {"frequency_hz": freq, "rx_gain_db": rx_gain_db}
    if n_beams == 96 and not long_range:
        base = preset("didson-hf")
        return SonarGeometry.from_window(
            min_range_m=start_m, max_range_m=start_m + length_m, n_bins=n_samples,
            azimuth_rad=base.azimuth_rad, fov_rad=base.fov_rad, psf=base.psf_raw, taper=base.taper,
            noise=base.noise, name="didson", azimuth_source="preset:didson-hf", **common,
        )
    fov = math.radians(28.8)
    warnings.warn(
        f"DIDSON {'LR ' if long_range else ''}{n_beams}-beam frames: no measured beam table; "
        f"assuming {n_beams} beams uniform over 28.8 degrees",
        GeometryWarning,
        stacklevel=4,
    )
    return SonarGeometry.from_window(
        min_range_m=start_m, max_range_m=start_m + length_m, n_bins=n_samples,
        azimuth_rad=uniform_azimuths(n_beams, fov), fov_rad=fov, name="didson",
        azimuth_source="uniform", **common,
    )


class DdfFile(ClosingFile):
    """Lazy, memory-mapped access to the frames of a DIDSON ``.ddf`` file (DDF_03/DDF_04).

    ``len(f)`` frames (from the file size), ``f[i]`` a :class:`Ping`, ``f.frame_header(i)`` a dict.

    Raises
    ------
    DataFormatError
        Short file, bad magic/version, or header fields inconsistent with each other.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        geometry: SonarGeometry | str | os.PathLike[str] | None = None,
    ) -> None:
        self.path = Path(path)
        self._override = None if geometry is None else as_geometry(geometry)
        mm = map_file(self.path, min_size=4, what="DDF file")
        magic = bytes(mm[:4])
        if magic[:3] != b"DDF" or magic[3] not in (3, 4):
            raise DataFormatError(
                f"not a DIDSON DDF_03/DDF_04 file (magic {magic!r})", self.path, 0
            )
        self.version = magic[3]
        fdt, hdt = FILE_HEADER_DTYPES[self.version], FRAME_HEADER_DTYPES[self.version]
        if mm.size < fdt.itemsize:
            raise DataFormatError(
                f"truncated DDF_0{self.version} file: {mm.size} bytes, the file header needs "
                f"{fdt.itemsize}", self.path, int(mm.size),
            )
        self._mm = mm
        self.file_header_record: np.void = mm[: fdt.itemsize].view(fdt)[0]
        fh = self.file_header_record
        with header_errors(self.path, 16, "file header"):
            self.n_beams = int(fh["numbeams"])
            self.n_samples = int(fh["samplesperchannel"]) or 512
            if not 0 < self.n_beams <= _MAX_BEAMS:
                raise ValueError(f"numbeams {self.n_beams} is outside 1-{_MAX_BEAMS}")
            if not 0 < self.n_samples <= _MAX_SAMPLES:
                raise ValueError(f"samplesperchannel {self.n_samples} is outside 1-{_MAX_SAMPLES}")
            check_plausible(int(fh["framerate"]), 0, _MAX_FRAME_RATE_HZ, "framerate", "Hz")
        self.high_frequency = bool(fh["resolution"])
        self.reverse = bool(fh["reverse"])
        self.serial_number = int(fh["serialnumber"])
        self.header_size = fdt.itemsize
        frames, self._n = map_frames(mm, self.path, self.header_size, hdt, self.n_samples, self.n_beams)
        self.frame_size = frames.dtype.itemsize
        self._frames: np.ndarray | None = frames

    def __len__(self) -> int:
        return self._n

    def __iter__(self) -> Iterator[Ping]:
        for i in range(self._n):
            yield self[i]

    def close(self) -> None:
        """Release the memory map."""
        self._frames = None
        self._mm = None  # type: ignore[assignment]

    def _index(self, index: int) -> int:
        return check_index(index, self._n, "frame")

    def _rec(self, i: int) -> np.void:
        if self._frames is None:
            raise DataFormatError("file is closed", self.path)
        return self._frames[i]

    def frame_header(self, index: int) -> dict[str, Any]:
        """Frame header ``index`` as a dict of Python scalars."""
        h = self._rec(self._index(index))["header"]
        return {n: (h[n].item().rstrip(b"\0").decode("latin-1") if h[n].dtype.kind == "S" else h[n].item())
                for n in h.dtype.names or () if n != "userassigned"}

    def geometry(self, index: int = 0) -> SonarGeometry:
        """Geometry of frame ``index`` (the window may change between frames)."""
        i = self._index(index)
        return self._geometry(i, self._rec(i)["header"])

    def _geometry(self, i: int, h: np.void) -> SonarGeometry:
        if self._override is not None:
            return self._override
        offset = self.header_size + i * self.frame_size
        with header_errors(self.path, offset, f"frame header {i}"):
            cfg = effective_config(int(h["configflags"]), self.serial_number)
            start, length = window_m(int(h["windowstart"]), int(h["windowlength"]),
                                     high_frequency=self.high_frequency, config=cfg)
            gain = check_plausible(int(h["receivergain"]), *_GAIN_DB, "receivergain", "dB")
            return _geometry(self.n_beams, self.n_samples, start, length, self.high_frequency,
                             bool(cfg & 2), gain)

    def _time_ns(self, i: int, h: np.void) -> int:
        offset = self.header_size + i * self.frame_size
        cal = [int(h[f]) for f in ("year", "month", "day", "hour", "minute", "second", "hsecond")]
        with header_errors(self.path, offset + 20, f"frame {i} time"):
            if any(cal):
                y, mo, d, hh, mi, s, hs = cal
                if not (1970 <= y <= 2200 and 1 <= mo <= 12 and 0 <= hh < 24
                        and 0 <= mi < 60 and 0 <= s < 61 and 0 <= hs < 100):
                    raise ValueError(f"invalid date/time fields {cal}")
                if not 1 <= d <= calendar.monthrange(y, mo)[1]:
                    raise ValueError(f"invalid date/time fields {cal} (no day {d} in {y}-{mo:02d})")
                secs = calendar.timegm((y, mo, d, hh, mi, s, 0, 0, 0))
                t = secs * 10**9 + hs * 10**7
            else:
                sec, usec = int(h["frametime"]), int(h["frametime2"])
                if sec < 0 or not 0 <= usec < 10**6:
                    raise ValueError(f"invalid frametime ({sec}, {usec})")
                t = sec * 10**9 + usec * 1000
            check_time_ns(t, "frame time")
        return t

    def __getitem__(self, index: int) -> Ping:
        i = self._index(index)
        rec = self._rec(i)
        h = rec["header"]
        geom = self._geometry(i, h)
        samples = rec["samples"]
        src = samples if self.reverse else samples[:, ::-1]
        image = np.multiply(src, U8_SCALE, dtype=np.float32)
        meta: dict[str, Any] = {
            "format": FORMAT,
            "ddf_version": self.version,
            "frame_index": i,
            "frame_number": int(h["framenumber"]),
            "window_start_code": int(h["windowstart"]),
            "window_length_code": int(h["windowlength"]),
            "config_flags": int(h["configflags"]),
            "receiver_gain_db": int(h["receivergain"]),
            "serial_number": self.serial_number,
        }
        for key, field in (("heading_deg", "heading"), ("pitch_deg", "pitch"), ("roll_deg", "roll"),
                           ("depth_m", "depth"), ("altitude_m", "altitude"),
                           ("sonar_pan_deg", "sonarpan"), ("sonar_tilt_deg", "sonartilt"),
                           ("sonar_roll_deg", "sonarroll")):
            v = finite_or(h[field])
            if v is not None:
                meta[key] = v
        # WGS 84 degrees of the platform's fix; (0, 0) is how the format says "no fix"
        lat, lon = finite_or(h["latitude"]), finite_or(h["longitude"])
        if lat is not None and lon is not None and (lat, lon) != (0.0, 0.0) and abs(lat) <= 90 and abs(lon) <= 180:
            meta["latitude_deg"] = lat
            meta["longitude_deg"] = lon
        return Ping(image=image, geometry=geom, time_ns=self._time_ns(i, h),
                    source=f"{self.path}#{i}", meta=meta)


# ---------------------------------------------------------------------- registry hooks
def sniff(path: Path, head: bytes) -> bool:
    """DIDSON files start with ``b"DDF\\x03"`` or ``b"DDF\\x04"``."""
    return head[:3] == b"DDF" and len(head) >= 4 and head[3] in (3, 4)


def iter_pings(path: str | os.PathLike[str], *, geometry: GeometrySpec = None, start: int = 0,
               stop: int | None = None, **_: Any) -> Iterator[Ping]:
    """:meth:`Reader.iter_pings <sonarmap.io.reader.Reader.iter_pings>` of DIDSON files: frames
    ``start:stop``, memory-mapped; the frames before ``start`` are not read.  File errors: see
    :class:`DdfFile`."""
    yield from iter_container_pings(DdfFile, path, geometry, start, stop)


def count_pings(path: str | os.PathLike[str]) -> int:
    """Number of complete frames (from the file size)."""
    return count_container_pings(DdfFile, path)


def summary(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Geometry of frame 0, frame count, time span and DIDSON fields."""
    with DdfFile(path) as f:
        n = len(f)
        fh = f.file_header_record
        details: dict[str, Any] = {
            "ddf_version": f.version,
            "n_beams": f.n_beams,
            "samples_per_beam": f.n_samples,
            "high_frequency": f.high_frequency,
            "reverse": f.reverse,
            "serial_number": f.serial_number,
            "date": fh["date"].rstrip(b"\0").decode("latin-1", "replace"),
        }
        if n == 0:
            return make_summary(FORMAT, path, n_pings=0, **details)
        g = f.geometry(0)
        return make_summary(
            FORMAT, path, n_pings=n, geometry=g,
            time_start_ns=f._time_ns(0, f._rec(0)["header"]),
            time_end_ns=f._time_ns(n - 1, f._rec(n - 1)["header"]),
            range_window_m=(round(g.min_range_m, 4), round(g.max_range_m, 4)), **details,
        )
