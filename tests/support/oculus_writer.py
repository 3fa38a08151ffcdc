"""Test-only encoders for Oculus ``SimplePingResult`` messages and ViewPoint logs (v1, v2).

They follow the public layouts (Blueprint's ``Oculus.h``; ``RmLogHeader``/``RmLogItem``; the
SQLite ``data`` table) so the reader can be tested on v2 messages, gain rows, 16-bit data and log
containers, of which no public sample exists.
"""

from __future__ import annotations

import sqlite3
import struct
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sonarmap.io.oculus import (
    FIRE_V1,
    FIRE_V2_EXTRA,
    FLAG_SEND_GAIN,
    HEADER,
    LOG_HEADER,
    LOG_ITEM,
    PING_V1,
    PING_V2,
    SIZE_V1,
    SIZE_V2,
)


def encode_ping(
    image: np.ndarray,
    bearings_cdeg: np.ndarray,
    *,
    version: int = 2,
    resolution_m: float = 0.005,
    gain: np.ndarray | None = None,
    ping_id: int = 7,
    sound_speed: float = 1500.0,
    frequency: float = 1.2e6,
    heading: float = 10.0,
) -> bytes:
    """One message; ``image`` (n_ranges, n_beams) uint8 or uint16, range-major."""
    n_ranges, n_beams = image.shape
    bps = image.dtype.itemsize
    dsize = {1: 0, 2: 1, 4: 3}[bps]
    flags = 0x01 | (FLAG_SEND_GAIN if gain is not None else 0) | (0x02 if bps == 2 else 0)
    rows = []
    for r in range(n_ranges):
        row = image[r].astype(image.dtype.newbyteorder("<")).tobytes()
        rows.append((np.float32(gain[r]).tobytes() if gain is not None else b"") + row)
    img = b"".join(rows)
    head_size = SIZE_V2 if version == 2 else SIZE_V1
    img_off = head_size + 2 * n_beams + 6  # a few spare bytes, as real messages have
    msg_size = img_off + len(img)
    fire = FIRE_V1.pack(1, 0, 0, 127, flags, 2.0, 50.0, sound_speed, 0.0)
    if version == 2:
        fire += FIRE_V2_EXTRA.pack(0, 0, 0, 0, 0, 0, 0, 0, 0)
        ping = PING_V2.pack(ping_id, 0, frequency, 12.0, 1.0, heading, 1.0, -2.0, sound_speed,
                            123.456, dsize, resolution_m, n_ranges, n_beams, 0, 0, 0, 0,
                            img_off, len(img), msg_size)
    else:
        ping = PING_V1.pack(ping_id, 0, frequency, 12.0, 1.0, sound_speed, 1234, dsize,
                            resolution_m, n_ranges, n_beams, img_off, len(img), msg_size)
    header = HEADER.pack(0x4F53, 1, 0, 0x23, version, msg_size - HEADER.size, 1042)
    body = header + fire + ping + np.asarray(bearings_cdeg, "<i2").tobytes()
    body += b"\0" * (img_off - len(body))
    return body + img


def write_log_v1(path: Path, messages: Sequence[bytes], times_s: Sequence[float], *, compress: bool = False) -> None:
    """A ViewPoint v1 binary log holding ``messages`` as rt_oculusSonar items."""
    out = [LOG_HEADER.pack(0x11223344, LOG_HEADER.size, b"Oculus", 1, 0, 0, times_s[0])]
    for m, t in zip(messages, times_s, strict=True):
        payload = struct.pack(">I", len(m)) + zlib.compress(m) if compress else m
        out.append(LOG_ITEM.pack(0xAABBCCDD, LOG_ITEM.size, 10, 0, t, int(compress), len(m), len(payload)))
        out.append(payload)
        # a non-sonar item (serial port string) in between, which must be skipped
        junk = b"$GPGGA,..."
        out.append(LOG_ITEM.pack(0xAABBCCDD, LOG_ITEM.size, 2, 0, t, 0, len(junk), len(junk)))
        out.append(junk)
    path.write_bytes(b"".join(out))


def write_log_v2(path: Path, messages: Sequence[bytes], times_s: Sequence[float]) -> None:
    """A ViewPoint v2 SQLite log (tables as publicly described; ``data`` holds the messages)."""
    con = sqlite3.connect(path)
    with con:
        for t in ("metadata (key TEXT, value TEXT)", "dataSources (id INTEGER, name TEXT)",
                  "dataSourceProperties (id INTEGER, key TEXT, value TEXT)", "resources (id INTEGER)",
                  "bookmarks (id INTEGER)",
                  "data (entryId INTEGER PRIMARY KEY, timestamp REAL, type INTEGER, dataSourceId INTEGER, payload BLOB)"):
            con.execute(f"CREATE TABLE {t}")
        con.execute("INSERT INTO metadata VALUES ('version', '2')")
        con.execute("INSERT INTO data (timestamp, type, dataSourceId, payload) VALUES (?, 1, 1, ?)", (times_s[0], b"not sonar"))
        for m, t in zip(messages, times_s, strict=True):
            con.execute("INSERT INTO data (timestamp, type, dataSourceId, payload) VALUES (?, 0, 0, ?)", (t * 1000.0, m))
    con.close()
