"""Streaming: process a sonar's pings as they arrive (``sonarmap live``).

* :mod:`~sonarmap.live.sources` - :class:`OculusTcpSource` (an Oculus over TCP),
  :class:`FollowSource` (a recording being written), :class:`ReplaySource` (a recording in real
  time); :func:`open_source` picks one from a ``SOURCE`` argument.
* :mod:`~sonarmap.live.loop` - :func:`run_live`: reader thread, bounded queue that drops the
  oldest ping when processing is behind, :func:`sonarmap.pipeline.process_ping`, sinks;
  returns :class:`LiveStats`.
* :mod:`~sonarmap.live.sinks` - :class:`RangesSink` (CSV / JSON lines per ping) and
  :class:`StoreSink` (a zarr product store, appended and readable while written).
* :mod:`~sonarmap.live.status` - the one-line status on stderr.
* :mod:`~sonarmap.live.server` - :class:`ReplayServer`, a loopback Oculus for tests and demos.
* :mod:`~sonarmap.live.protocol` - the fire message and message framing.

Examples
--------
>>> from sonarmap.live import ReplayServer, OculusTcpSource, run_live
>>> with ReplayServer("three_pings_8bit.raw", rate_hz=10, count=30) as srv:  # doctest: +SKIP
...     stats = run_live(OculusTcpSource("127.0.0.1", srv.port), max_pings=30)
>>> stats.count, stats.drops  # doctest: +SKIP
(30, 0)
"""

from __future__ import annotations

from sonarmap.live.loop import DEFAULT_QUEUE, LiveSnapshot, LiveStats, run_live, warm_pipeline
from sonarmap.live.protocol import FireSettings, MessageFramer, decode_fire_message, encode_fire_message
from sonarmap.live.sinks import RANGES_FORMATS, BagSink, RangesSink, StoreSink
from sonarmap.live.sources import (
    FollowSource,
    LiveWarning,
    OculusTcpSource,
    PingSource,
    ReplaySource,
    SourceError,
    open_source,
    parse_tcp_url,
)
from sonarmap.live.status import StatusLine, format_snapshot


def __getattr__(name: str) -> object:
    # The server is imported on first use: ``python -m sonarmap.live.server`` must not find it
    # imported already (runpy warns about that).
    if name == "ReplayServer":
        from sonarmap.live.server import ReplayServer

        return ReplayServer
    raise AttributeError(f"module 'sonarmap.live' has no attribute {name!r}")

__all__ = [
    "DEFAULT_QUEUE", "LiveSnapshot", "LiveStats", "run_live", "warm_pipeline",
    "FireSettings", "MessageFramer", "decode_fire_message", "encode_fire_message",
    "ReplayServer", "RANGES_FORMATS", "BagSink", "RangesSink", "StoreSink",
    "FollowSource", "LiveWarning", "OculusTcpSource", "PingSource", "ReplaySource", "SourceError", "open_source",
    "parse_tcp_url", "StatusLine", "format_snapshot",
]
