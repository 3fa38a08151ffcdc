"""The ranges CSV: one row per (ping, beam), written by ``sonarmap ranges`` and the live CSV sink.

The columns are :data:`CSV_HEADER`; their meaning is documented with the command
(:mod:`sonarmap.cli.ranges`).  An empty cell is "none" / "unknown", never a number that looks like one.
"""

from __future__ import annotations

from typing import Any

__all__ = ["CSV_HEADER", "iso_time", "write_ranges_rows"]

#: Columns of the ranges CSV, in order (their meaning: the notes of :mod:`sonarmap.cli.ranges`).
CSV_HEADER = (
    "ping", "beam", "azimuth_rad", "bin", "range_m", "intensity", "flags", "sigma_m", "p_detect", "time", "time_ns",
)


def _fmt(v: float, digits: int = 6) -> str:
    return "" if v != v else f"{v:.{digits}g}"


def iso_time(time_ns: int) -> str:
    """ISO 8601 UTC with nanoseconds: ``1468936985250000000`` -> ``"2016-07-19T14:03:05.250000000Z"``.

    Examples
    --------
    >>> iso_time(1468936985250000000)
    '2016-07-19T14:03:05.250000000Z'
    """
    import numpy as np

    return str(np.datetime_as_string(np.datetime64(int(time_ns), "ns"), unit="ns")) + "Z"


def write_ranges_rows(
    writer: Any, source: str, ranges: Any, flags: str = "", *, time_ns: int | None = None
) -> int:
    """Write one CSV row per beam of ``ranges``; returns the number of rows.

    Parameters
    ----------
    writer : csv.writer
    source : str
        The ping's source (``ping`` column).
    ranges : BeamRanges
    flags : str
        The ping's gates, ``;``-separated.
    time_ns : int, optional
        The ping's time (``time`` and ``time_ns`` columns; empty when None).
    """
    n = ranges.n_beams
    sigma = getattr(ranges, "sigma_m", None)
    p_det = getattr(ranges, "p_detect", None)
    t_iso, t_ns = ("", "") if time_ns is None else (iso_time(time_ns), str(int(time_ns)))
    for j in range(n):
        b = int(ranges.bin[j])
        writer.writerow([
            source,
            j,
            f"{float(ranges.azimuth_rad[j]):.9g}",
            "" if b < 0 else b,
            "" if b < 0 else f"{float(ranges.range_m[j]):.6f}",
            "" if b < 0 else _fmt(float(ranges.intensity[j])),
            flags,
            "" if b < 0 or sigma is None else _fmt(float(sigma[j])),
            "" if p_det is None else _fmt(float(p_det[j])),
            t_iso,
            t_ns,
        ])
    return n
