"""Test-only writer of DIDSON ``.ddf`` files (DDF_03 / DDF_04) following the published layout.

No public DDF sample exists, so the reader is tested on files made here.  The writer uses the
reader's header dtypes (one layout definition) but fills every field itself.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sonarmap.io.ddf import FILE_HEADER_DTYPES, FRAME_HEADER_DTYPES


def write_ddf(
    path: Path,
    frames: Sequence[np.ndarray],
    *,
    version: int = 4,
    high_frequency: bool = True,
    window_start_code: int = 6,
    window_length_code: int = 2,
    configflags: int = 1,
    serial_number: int = 230,
    reverse: int = 0,
    start_time: dt.datetime = dt.datetime(2016, 7, 19, 14, 3, 5, 250000, tzinfo=dt.UTC),
    frame_period_s: float = 0.1,
    heading_deg: float = 12.5,
) -> list[int]:
    """Write ``frames`` (uint8 ``(samples, beams)`` in *vendor* order, beam 0 right-most).

    Returns the frame times in ns (hundredth-second resolution, as stored).
    """
    n_samples, n_beams = frames[0].shape
    fh = np.zeros((), FILE_HEADER_DTYPES[version])
    fh["version"] = b"DDF" + bytes([version])
    fh["numframes"] = len(frames)
    fh["framerate"] = 10
    fh["resolution"] = int(high_frequency)
    fh["numbeams"] = n_beams
    fh["samplerate"] = 1.0
    fh["samplesperchannel"] = n_samples
    fh["receivergain"] = 20
    fh["windowstart"] = window_start_code
    fh["windowlength"] = window_length_code
    fh["reverse"] = reverse
    fh["serialnumber"] = serial_number
    fh["date"] = start_time.strftime("%Y-%m-%d_%H%M%S").encode()
    fh["idstring"] = b"sonarmap test file"
    times = []
    chunks = [fh.tobytes()]
    for i, frame in enumerate(frames):
        t = start_time + dt.timedelta(seconds=i * frame_period_s)
        h = np.zeros((), FRAME_HEADER_DTYPES[version])
        h["framenumber"] = i
        h["frametime"] = int(t.timestamp())
        h["frametime2"] = t.microsecond
        h["version"] = b"DDF" + bytes([version])
        h["year"], h["month"], h["day"] = t.year, t.month, t.day
        h["hour"], h["minute"], h["second"] = t.hour, t.minute, t.second
        h["hsecond"] = t.microsecond // 10000
        h["transmit"] = 3
        h["windowstart"] = window_start_code
        h["windowlength"] = window_length_code
        h["receivergain"] = 20
        h["heading"] = heading_deg
        h["configflags"] = configflags
        chunks.append(h.tobytes())
        chunks.append(np.ascontiguousarray(frame, dtype=np.uint8).tobytes())
        secs = int(t.replace(microsecond=0).timestamp())
        times.append(secs * 10**9 + (t.microsecond // 10000) * 10**7)
    Path(path).write_bytes(b"".join(chunks))
    return times
