"""SoundMetrics ARIS recordings (``.aris``, file format ``DDF_05``).

Layout (SoundMetrics ``aris-file-sdk``, public; little-endian throughout)::

    FileHeader   1024 bytes, starts with b"DDF\\x05" (Version 0x05464444)
    frame 0      FrameHeader (1024 bytes) + beams x samples uint8
    frame 1      ...

* The beam count follows from ``PingMode`` (1-2: 48, 3-5: 96, 6-8: 64, 9-12: 128); the sample count
  is ``SamplesPerBeam``.  As the SDK recommends, the frame count is computed from the file size
  (``FileHeader.FrameCount`` is ignored); a trailing incomplete frame is skipped with a
  :class:`~sonarmap.io._binary.PartialFrameWarning`.
* Samples are stored ``[sample][beam]`` with **beam 0 the right-most beam**; the reader flips the
  beam axis so that azimuth increases with column (positive to starboard).
* Range of sample ``i``: ``(SampleStartDelay + i * SamplePeriod) * 1e-6 * SoundSpeed / 2`` metres.
* Beam azimuths come from the vendor's beam-angle tables (presets ``aris1800-48``, ``aris1800-96``,
  ``aris3000-64``, ``aris3000-128``, ``aris-telephoto-48``, ``aris-telephoto-96``), chosen from
  ``TheSystemType`` (0: ARIS 1800, 1: ARIS 3000, 2: ARIS 1200), ``LargeLens`` (1: telephoto lens)
  and the beam count.  The ARIS 1200 uses the 1800's 48-beam table (the SDK's table is named
  ``ARIS1800_1200_48``).
* Ping time is ``FrameTime`` (PC clock at recording, µs since the Unix epoch, UTC); the on-sonar
  clock ``sonarTimeStamp`` is kept in ``Ping.meta["sonar_time_ns"]``.  Both must be 0 (unknown) or
  lie in the years 1970-2200.
* Header fields are checked for plausibility (a corrupt frame is a
  :class:`~sonarmap.errors.DataFormatError`, never an absurd geometry): ``SamplePeriod`` 1-1000 µs,
  ``SoundSpeed`` 1300-1700 m/s, the range window (from ``SampleStartDelay``, ``SamplePeriod``,
  ``SoundSpeed``) and the recorded ``WindowStart``/``WindowLength`` within 1 km, ``ReceiverGain``
  0-100 dB, ``FrameRate`` 0-100 Hz.  With a ``geometry`` override the range-window fields are
  not used and not checked.
* 8-bit samples (0-255, i.e. 0-80 dB) map to [0, 1] as ``value / 255``.
"""

from __future__ import annotations

import functools
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import DataFormatError, SonarmapWarning
from sonarmap.geometry import SonarGeometry, as_geometry, preset
from sonarmap.io._binary import (
    MAX_WINDOW_M,
    U8_SCALE,
    ClosingFile,
    check_index,
    check_plausible,
    check_sound_speed,
    check_time_ns,
    count_container_pings,
    finite_or,
    header_errors,
    iter_container_pings,
    make_summary,
    map_file,
    map_frames,
    warn_partial,
)
from sonarmap.io.reader import GeometrySpec
from sonarmap.ping import Ping, Pose

__all__ = [
    "FORMAT",
    "MAGIC",
    "FILE_HEADER_SIZE",
    "FRAME_HEADER_SIZE",
    "FILE_HEADER_DTYPE",
    "FRAME_HEADER_DTYPE",
    "ArisFile",
    "beams_from_ping_mode",
    "aris_preset_name",
    "sniff",
    "iter_pings",
    "count_pings",
    "summary",
]

FORMAT = "aris"
MAGIC = b"DDF\x05"
FILE_HEADER_SIZE = 1024
FRAME_HEADER_SIZE = 1024
_MAX_SAMPLES = 1 << 16  # SamplesPerBeam is a small integer (<= a few thousand) in practice
_SAMPLE_PERIOD_US = (1, 1000)  # the SDK's sample periods are 4-100 µs
_MAX_GAIN_DB = 100.0
_MAX_FRAME_RATE_HZ = 100.0

_u4, _i4, _f4, _f8, _u8, _u2 = "<u4", "<i4", "<f4", "<f8", "<u8", "<u2"


def _fields(spec: str, typ: str) -> list[tuple[str, str]]:
    return [(name, typ) for name in spec.split()]


#: The 1024-byte ARIS file header (DDF_05); most fields are legacy DIDSON fields.
FILE_HEADER_DTYPE = np.dtype(
    [("Version", _u4)]
    + _fields("FrameCount FrameRate HighResolution NumRawBeams", _u4)
    + [("SampleRate", _f4), ("SamplesPerChannel", _u4), ("ReceiverGain", _u4)]
    + [("WindowStart", _f4), ("WindowLength", _f4), ("Reverse", _u4), ("SN", _u4)]
    + [("strDate", "S32"), ("strHeaderID", "S256")]
    + _fields("UserID1 UserID2 UserID3 UserID4", _i4)
    + _fields(
        "StartFrame EndFrame TimeLapse RecordInterval RadioSeconds FrameInterval Flags AuxFlags "
        "Sspd Flags3D SoftwareVersion WaterTemp Salinity PulseLength TxMode VersionFGPA "
        "VersionPSuC ThumbnailFI",
        _u4,
    )
    + _fields("FileSize OptionalHeaderSize OptionalTailSize", _u8)
    + _fields("VersionMinor LargeLens", _u4)
    + [("padding", "V568")]
)

#: The 1024-byte ARIS frame header (field names as in the SDK's FrameHeader.h).
FRAME_HEADER_DTYPE = np.dtype(
    [("FrameIndex", _u4), ("FrameTime", _u8), ("Version", _u4), ("Status", _u4)]
    + [("sonarTimeStamp", _u8)]
    + _fields("TS_Day TS_Hour TS_Minute TS_Second TS_Hsecond TransmitMode", _u4)
    + [("WindowStart", _f4), ("WindowLength", _f4), ("Threshold", _u4), ("Intensity", _i4)]
    + _fields("ReceiverGain DegC1 DegC2 Humidity Focus Battery", _u4)
    + _fields(" ".join(f"UserValue{i}" for i in range(1, 9)), _f4)
    + _fields(
        "Velocity Depth Altitude Pitch PitchRate Roll RollRate Heading HeadingRate "
        "CompassHeading CompassPitch CompassRoll",
        _f4,
    )
    + [("Latitude", _f8), ("Longitude", _f8), ("SonarPosition", _f4), ("ConfigFlags", _u4)]
    + [("BeamTilt", _f4), ("TargetRange", _f4), ("TargetBearing", _f4)]
    + _fields("TargetPresent FirmwareRevision Flags SourceFrame", _u4)
    + [("WaterTemp", _f4), ("TimerPeriod", _u4)]
    + _fields("SonarX SonarY SonarZ SonarPan SonarTilt SonarRoll PanPNNL TiltPNNL RollPNNL", _f4)
    + [("VehicleTime", _f8), ("TimeGGK", _f4), ("DateGGK", _u4), ("QualityGGK", _u4)]
    + [("NumSatsGGK", _u4), ("DOPGGK", _f4), ("EHTGGK", _f4), ("HeaveTSS", _f4)]
    + _fields("YearGPS MonthGPS DayGPS HourGPS MinuteGPS SecondGPS HSecondGPS", _u4)
    + _fields(
        "SonarPanOffset SonarTiltOffset SonarRollOffset SonarXOffset SonarYOffset SonarZOffset",
        _f4,
    )
    + [("Tmatrix", _f4, (16,)), ("SampleRate", _f4)]
    + _fields("AccellX AccellY AccellZ", _f4)
    + _fields("PingMode FrequencyHiLow PulseWidth CyclePeriod SamplePeriod TransmitEnable", _u4)
    + [("FrameRate", _f4), ("SoundSpeed", _f4)]
    + _fields("SamplesPerBeam Enable150V SampleStartDelay LargeLens TheSystemType", _u4)
    + [("SonarSerialNumber", _u4), ("ReservedEK", _u8)]
    + _fields("ArisErrorFlagsUint MissedPackets ArisAppVersion Available2 ReorderedSamples", _u4)
    + [("Salinity", _u4)]
    + _fields("Pressure BatteryVoltage MainVoltage SwitchVoltage", _f4)
    + _fields(
        "FocusMotorMoving VoltageChanging FocusTimeoutFault FocusOverCurrentFault "
        "FocusNotFoundFault FocusStalledFault FPGATimeoutFault FPGABusyFault FPGAStuckFault "
        "CPUTempFault PSUTempFault WaterTempFault HumidityFault PressureFault VoltageReadFault "
        "VoltageWriteFault FocusCurrentPosition",
        _u4,
    )
    + _fields("TargetPan TargetTilt TargetRoll", _f4)
    + _fields("PanMotorErrorCode TiltMotorErrorCode RollMotorErrorCode", _u4)
    + _fields("PanAbsPosition TiltAbsPosition RollAbsPosition", _f4)
    + _fields(" ".join(f"{a}Accel{x}" for a in ("Pan", "Tilt", "Roll") for x in "XYZ"), _f4)
    + _fields(
        "AppliedSettings ConstrainedSettings InvalidSettings EnableInterpacketDelay "
        "InterpacketDelayPeriod Uptime",
        _u4,
    )
    + [("ArisAppVersionMajor", _u2), ("ArisAppVersionMinor", _u2), ("GoTime", _u8)]
    + _fields("PanVelocity TiltVelocity RollVelocity", _f4)
    + [("GpsTimeAge", _u4), ("padding", "V292")]
)

assert FILE_HEADER_DTYPE.itemsize == FILE_HEADER_SIZE
assert FRAME_HEADER_DTYPE.itemsize == FRAME_HEADER_SIZE

_BEAMS_BY_PING_MODE = {1: 48, 2: 48, 3: 96, 4: 96, 5: 96, 6: 64, 7: 64, 8: 64}
_BEAMS_BY_PING_MODE.update({m: 128 for m in range(9, 13)})
_SYSTEMS = {0: "ARIS 1800", 1: "ARIS 3000", 2: "ARIS 1200"}
# (HF, LF) centre frequencies in Hz per system type (vendor data sheets).
_FREQUENCIES = {0: (1.8e6, 1.1e6), 1: (3.0e6, 1.8e6), 2: (1.2e6, 0.7e6)}


class ArisWarning(SonarmapWarning):
    """An ARIS file has an unusual but readable configuration (assumption stated in the message)."""


def beams_from_ping_mode(ping_mode: int) -> int:
    """Number of beams of an ARIS ping mode (1-12), as in the SDK's ``get_beams_from_pingmode``.

    Raises
    ------
    ValueError
        If ``ping_mode`` is not 1-12.
    """
    try:
        return _BEAMS_BY_PING_MODE[int(ping_mode)]
    except KeyError:
        raise ValueError(f"PingMode {ping_mode} is not a valid ARIS ping mode (1-12)") from None


def aris_preset_name(system_type: int, large_lens: bool, n_beams: int) -> str:
    """Name of the beam-angle preset for an ARIS model, lens and beam count.

    The telephoto ("large") lens has its own tables for 48 and 96 beams; otherwise the table
    follows the beam count (48: ARIS 1200/1800, 96: ARIS 1800, 64/128: ARIS 3000).

    Raises
    ------
    ValueError
        If no vendor table exists for this combination.
    """
    if large_lens and n_beams in (48, 96):
        return f"aris-telephoto-{n_beams}"
    by_beams = {48: "aris1800-48", 96: "aris1800-96", 64: "aris3000-64", 128: "aris3000-128"}
    if n_beams not in by_beams:
        raise ValueError(f"no ARIS beam table for {n_beams} beams")
    name = by_beams[n_beams]
    if large_lens:
        warnings.warn(
            f"ARIS telephoto lens with {n_beams} beams has no vendor table; using {name}",
            ArisWarning,
            stacklevel=3,
        )
    return name


@functools.lru_cache(maxsize=256)
def _frame_geometry(
    system_type: int,
    large_lens: bool,
    n_beams: int,
    n_samples: int,
    start_delay_us: int,
    sample_period_us: int,
    sound_speed_m_s: float,
    high_frequency: bool,
    rx_gain_db: float,
) -> SonarGeometry:
    check_plausible(sample_period_us, *_SAMPLE_PERIOD_US, "SamplePeriod", "µs")
    check_sound_speed(sound_speed_m_s, "SoundSpeed")
    check_plausible(rx_gain_db, 0.0, _MAX_GAIN_DB, "ReceiverGain", "dB")
    half_c = 1e-6 * sound_speed_m_s / 2.0
    start = start_delay_us * half_c
    step = sample_period_us * half_c
    end = start + n_samples * step
    if end > MAX_WINDOW_M:
        raise ValueError(
            f"range window {start:.6g}-{end:.6g} m (SampleStartDelay {start_delay_us} µs, "
            f"SamplePeriod {sample_period_us} µs, SoundSpeed {sound_speed_m_s:.6g} m/s, "
            f"{n_samples} samples) reaches beyond {MAX_WINDOW_M:g} m"
        )
    name = aris_preset_name(system_type, large_lens, n_beams)
    base = preset(name)
    hf, lf = _FREQUENCIES.get(system_type, _FREQUENCIES[0])
    return SonarGeometry.from_window(
        min_range_m=start,
        max_range_m=end,
        n_bins=n_samples,
        azimuth_rad=base.azimuth_rad,
        fov_rad=base.fov_rad,
        frequency_hz=hf if high_frequency else lf,
        sound_speed_m_s=sound_speed_m_s,
        rx_gain_db=rx_gain_db,
        name=name,
        azimuth_source=f"preset:{name}",
        elevation_beamwidth_rad=base.elevation_beamwidth_rad,
        azimuth_beamwidth_rad=base.azimuth_beamwidth_rad,
    )


def _deg(h: np.void, field: str) -> float | None:
    return finite_or(h[field])


class ArisFile(ClosingFile):
    """Lazy, memory-mapped access to the frames of an ARIS recording.

    Parameters
    ----------
    path : path-like
        The ``.aris`` file.
    geometry : SonarGeometry, preset name or JSON path, optional
        Overrides the geometry derived from the frame headers.

    Examples
    --------
    >>> with ArisFile("sample.aris") as f:          # doctest: +SKIP
    ...     print(len(f), f[0].shape, f.frame_header(0)["SoundSpeed"])

    Raises
    ------
    DataFormatError
        Missing/short file, bad magic, or frame headers inconsistent with the first one (message
        gives the file and byte offset).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        geometry: SonarGeometry | str | os.PathLike[str] | None = None,
    ) -> None:
        self.path = Path(path)
        self._override = None if geometry is None else as_geometry(geometry)
        mm = map_file(self.path, min_size=FILE_HEADER_SIZE, what="ARIS file")
        self._mm = mm
        if bytes(mm[:4]) != MAGIC:
            raise DataFormatError(
                f"not an ARIS file (magic {bytes(mm[:4])!r}, expected {MAGIC!r})", self.path, 0
            )
        self.file_header_record: np.void = mm[:FILE_HEADER_SIZE].view(FILE_HEADER_DTYPE)[0]
        size = int(mm.size)
        body = size - FILE_HEADER_SIZE
        self.n_beams = 0
        self.n_samples = 0
        self.frame_size = FRAME_HEADER_SIZE
        self._frames: np.ndarray | None = None
        if body < FRAME_HEADER_SIZE:
            if body > 0:
                warn_partial(self.path, FILE_HEADER_SIZE, body, FRAME_HEADER_SIZE, "frame header")
            self._n = 0
            return
        h0 = mm[FILE_HEADER_SIZE : FILE_HEADER_SIZE + FRAME_HEADER_SIZE].view(FRAME_HEADER_DTYPE)[0]
        with header_errors(self.path, FILE_HEADER_SIZE, "frame header 0"):
            self.n_beams = beams_from_ping_mode(int(h0["PingMode"]))
            self.n_samples = int(h0["SamplesPerBeam"])
            if not 0 < self.n_samples <= _MAX_SAMPLES:
                raise ValueError(f"SamplesPerBeam {self.n_samples} is outside 1-{_MAX_SAMPLES}")
        self._frames, self._n = map_frames(mm, self.path, FILE_HEADER_SIZE, FRAME_HEADER_DTYPE,
                                           self.n_samples, self.n_beams)
        self.frame_size = self._frames.dtype.itemsize
        if int(h0["ReorderedSamples"]) == 0:
            warnings.warn(
                f"{self.path}: ReorderedSamples is 0 (live-stream order); reading the samples in "
                "file order, as all recorded ARIS files are",
                ArisWarning,
                stacklevel=2,
            )

    # ------------------------------------------------------------------ sequence protocol
    def __len__(self) -> int:
        return self._n

    def __getitem__(self, index: int) -> Ping:
        i = self._index(index)
        return self._ping(i)

    def __iter__(self) -> Iterator[Ping]:
        for i in range(self._n):
            yield self._ping(i)

    def close(self) -> None:
        """Release the memory map (frames already returned stay valid: images are copies)."""
        self._frames = None
        self._mm = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"ArisFile({str(self.path)!r}, frames={self._n}, beams={self.n_beams}, samples={self.n_samples})"

    # ------------------------------------------------------------------ access
    def frame_offset(self, index: int) -> int:
        """Byte offset of frame ``index``'s header in the file."""
        return FILE_HEADER_SIZE + self._index(index) * self.frame_size

    def frame_header(self, index: int) -> dict[str, Any]:
        """Frame header ``index`` as a dict of Python scalars (SDK field names)."""
        h = self._header(self._index(index))
        out: dict[str, Any] = {}
        for name in FRAME_HEADER_DTYPE.names or ():
            if name == "padding":
                continue
            v = h[name]
            out[name] = v.tolist() if isinstance(v, np.ndarray) else v.item()
        return out

    @property
    def file_header(self) -> dict[str, Any]:
        """The file header as a dict (legacy fields; prefer :meth:`frame_header`)."""
        h = self.file_header_record
        out: dict[str, Any] = {}
        for name in FILE_HEADER_DTYPE.names or ():
            if name == "padding":
                continue
            v = h[name].item()
            out[name] = v.rstrip(b"\0").decode("latin-1") if isinstance(v, bytes) else v
        return out

    def raw_samples(self, index: int) -> NDArray[np.uint8]:
        """Frame ``index``'s samples as stored: ``(n_samples, n_beams)`` uint8, beam 0 right-most.

        A read-only view into the memory map (no copy).
        """
        frames = self._require()
        return frames[self._index(index)]["samples"]

    def geometry(self, index: int = 0) -> SonarGeometry:
        """Geometry of frame ``index`` (range window and sound speed may change between frames)."""
        i = self._index(index)
        return self._geometry(i, self._header(i))

    # ------------------------------------------------------------------ internals
    def _require(self) -> np.ndarray:
        if self._frames is None:
            if self._mm is None:
                raise DataFormatError("file is closed", self.path)
            raise IndexError("ARIS file has no complete frame")
        return self._frames

    def _index(self, index: int) -> int:
        return check_index(index, self._n, "frame")

    def _header(self, i: int) -> np.void:
        return self._require()[i]["header"]

    def _geometry(self, i: int, h: np.void) -> SonarGeometry:
        offset = FILE_HEADER_SIZE + i * self.frame_size
        with header_errors(self.path, offset, f"frame header {i}"):
            if int(h["SamplesPerBeam"]) != self.n_samples or int(h["PingMode"]) not in _BEAMS_BY_PING_MODE \
                    or beams_from_ping_mode(int(h["PingMode"])) != self.n_beams:
                raise ValueError(
                    f"frame size changes: PingMode {int(h['PingMode'])}, SamplesPerBeam "
                    f"{int(h['SamplesPerBeam'])} (frame 0: {self.n_beams} beams x "
                    f"{self.n_samples} samples)"
                )
            check_plausible(float(h["FrameRate"]), 0.0, _MAX_FRAME_RATE_HZ, "FrameRate", "Hz")
            if self._override is not None:
                return self._override
            check_plausible(float(h["WindowStart"]), 0.0, MAX_WINDOW_M, "WindowStart", "m")
            check_plausible(float(h["WindowLength"]), 0.0, MAX_WINDOW_M, "WindowLength", "m")
            return _frame_geometry(
                int(h["TheSystemType"]),
                bool(h["LargeLens"]),
                self.n_beams,
                self.n_samples,
                int(h["SampleStartDelay"]),
                int(h["SamplePeriod"]),
                float(h["SoundSpeed"]),
                bool(h["FrequencyHiLow"]),
                float(h["ReceiverGain"]),
            )

    def _ping(self, i: int) -> Ping:
        frames = self._require()
        rec = frames[i]
        h = rec["header"]
        geom = self._geometry(i, h)
        t_ns, sonar_ns = self._times(i, h)
        # [sample][beam] with beam 0 right-most -> columns of increasing (starboard) azimuth.
        image = np.multiply(rec["samples"][:, ::-1], U8_SCALE, dtype=np.float32)
        return Ping(
            image=image,
            geometry=geom,
            time_ns=t_ns,
            pose=_pose(h),
            source=f"{self.path}#{i}",
            meta=_meta(h, i, sonar_ns),
        )

    def _times(self, i: int, h: np.void) -> tuple[int, int]:
        """``(FrameTime, sonarTimeStamp)`` of frame ``i`` in ns, checked (0 = unknown, 1970-2200)."""
        offset = FILE_HEADER_SIZE + i * self.frame_size
        with header_errors(self.path, offset + FRAME_HEADER_DTYPE.fields["FrameTime"][1], f"frame {i} time"):
            t_ns = check_time_ns(int(h["FrameTime"]) * 1000, "FrameTime")
        with header_errors(self.path, offset + FRAME_HEADER_DTYPE.fields["sonarTimeStamp"][1], f"frame {i} time"):
            sonar_ns = check_time_ns(int(h["sonarTimeStamp"]) * 1000, "sonarTimeStamp")
        return t_ns, sonar_ns


#: Estimated dB per unit of ARIS pixel value (see :func:`_meta`).
ARIS_LOG_DYNAMIC_RANGE_DB = 37.0


def _meta(h: np.void, i: int, sonar_time_ns: int) -> dict[str, Any]:
    meta: dict[str, Any] = {
        "format": FORMAT,
        "frame_index": i,
        "frame_number": int(h["FrameIndex"]),
        "sonar_time_ns": sonar_time_ns,
        "ping_mode": int(h["PingMode"]),
        "frequency_high": bool(h["FrequencyHiLow"]),
        "receiver_gain_db": int(h["ReceiverGain"]),
        "sample_period_us": int(h["SamplePeriod"]),
        "sample_start_delay_us": int(h["SampleStartDelay"]),
        "pulse_width_us": int(h["PulseWidth"]),
        "system_type": int(h["TheSystemType"]),
        "large_lens": bool(h["LargeLens"]),
        "serial_number": int(h["SonarSerialNumber"]),
        # ARIS samples are log-compressed: their speckle spread is the same at every level
        # (~0.05 of full scale on sample.aris).  37 dB over the 8-bit range is the compression at
        # which the simulator's 6-look speckle reproduces that spread (simulate/presets.py) - an
        # estimate, not a vendor figure; PipelineConfig.ranges.log_dynamic_range_db overrides it.
        "log_dynamic_range_db": ARIS_LOG_DYNAMIC_RANGE_DB,
    }
    floats = {
        "water_temperature_c": "WaterTemp",
        "heading_deg": "Heading",
        "pitch_deg": "Pitch",
        "roll_deg": "Roll",
        "depth_m": "Depth",
        "altitude_m": "Altitude",
        "velocity_m_s": "Velocity",
        "compass_heading_deg": "CompassHeading",
        "compass_pitch_deg": "CompassPitch",
        "compass_roll_deg": "CompassRoll",
        "sonar_pan_deg": "SonarPan",
        "sonar_tilt_deg": "SonarTilt",
        "sonar_roll_deg": "SonarRoll",
    }
    for key, field in floats.items():
        v = finite_or(h[field])
        if v is not None:
            meta[key] = v
    lat, lon = finite_or(h["Latitude"]), finite_or(h["Longitude"])
    if lat is not None and lon is not None and (lat, lon) != (0.0, 0.0) and abs(lat) <= 90 and abs(lon) <= 360:
        meta["latitude_deg"] = lat
        meta["longitude_deg"] = lon
    return meta


def _pose(h: np.void) -> Pose | None:
    """A pose when the frame carries a sonar position (``SonarX/Y/Z``, Bluefin-style integration).

    Orientation from the platform ``Heading``/``Pitch``/``Roll`` (degrees, ZYX); frame ``"ned"``.
    """
    xyz = [finite_or(h[f]) for f in ("SonarX", "SonarY", "SonarZ")]
    if any(v is None for v in xyz) or not any(xyz):
        return None
    hpr = [finite_or(h[f], 0.0) for f in ("Heading", "Pitch", "Roll")]
    from scipy.spatial.transform import Rotation

    q = Rotation.from_euler("ZYX", hpr, degrees=True).as_quat()
    try:
        return Pose(position_m=np.array(xyz, dtype=np.float64), orientation_xyzw=q, frame="ned")
    except ValueError:
        return None


# ---------------------------------------------------------------------- registry hooks
def sniff(path: Path, head: bytes) -> bool:
    """ARIS files start with ``b"DDF\\x05"``."""
    return head[:4] == MAGIC


def iter_pings(path: str | os.PathLike[str], *, geometry: GeometrySpec = None, start: int = 0,
               stop: int | None = None, **_: Any) -> Iterator[Ping]:
    """:meth:`Reader.iter_pings <sonarmap.io.reader.Reader.iter_pings>` of ARIS files: frames
    ``start:stop``, memory-mapped, one image in memory at a time; the frames before ``start`` are
    not read.  File errors: see :class:`ArisFile`."""
    yield from iter_container_pings(ArisFile, path, geometry, start, stop)


def count_pings(path: str | os.PathLike[str]) -> int:
    """Number of complete frames (from the file size and the first frame header)."""
    return count_container_pings(ArisFile, path)


def summary(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Geometry, frame count, time span and ARIS-specific fields (headers only)."""
    with ArisFile(path) as f:
        n = len(f)
        if n == 0:
            return make_summary(FORMAT, path, n_pings=0)
        h0 = f.frame_header(0)
        geom = f.geometry(0)
        t0 = f._times(0, f._header(0))[0]
        t1 = f._times(n - 1, f._header(n - 1))[0]
        return make_summary(
            FORMAT,
            path,
            n_pings=n,
            geometry=geom,
            time_start_ns=t0,
            time_end_ns=t1,
            system=_SYSTEMS.get(int(h0["TheSystemType"]), f"unknown ({h0['TheSystemType']})"),
            lens="telephoto" if h0["LargeLens"] else "standard",
            beam_table=geom.name,
            serial_number=h0["SonarSerialNumber"],
            n_beams=f.n_beams,
            samples_per_beam=f.n_samples,
            ping_mode=h0["PingMode"],
            sound_speed_m_s=round(float(h0["SoundSpeed"]), 3),
            range_window_m=(round(geom.min_range_m, 4), round(float(geom.range_m[-1]), 4)),
            frame_rate_hz=round(float(h0["FrameRate"]), 3),
            frame_bytes=f.frame_size,
        )
