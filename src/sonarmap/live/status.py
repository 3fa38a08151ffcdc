"""The one-line live status of ``sonarmap live`` on stderr.

On a terminal the line is redrawn in place (``\\r``) about twice a second::

    live 12.5 s | 412 pings | 33.1 pings/s | latency p50 28.4 ms p99 41.0 ms | drops 3 | flagged 0 | malformed 1 | reconnects 0

On a pipe or file nothing is drawn while running (no stream of partial lines); the final
summary line is printed either way, unless quiet.
"""

from __future__ import annotations

import math
import sys
from typing import IO

from sonarmap.live.loop import LiveSnapshot, LiveStats

__all__ = ["StatusLine", "format_snapshot"]


def _ms(v: float) -> str:
    return "-" if math.isnan(v) else f"{v:.1f} ms"


def format_snapshot(s: LiveSnapshot) -> str:
    """The status line of a snapshot (no trailing newline).

    Examples
    --------
    >>> from sonarmap.live.loop import LiveSnapshot
    >>> format_snapshot(LiveSnapshot(2.0, 40, 1, 0, 0, 0, 20.0, 30.0, 45.5, ))
    'live 2.0 s | 40 pings | 20.0 pings/s | latency p50 30.0 ms p99 45.5 ms | drops 1 | flagged 0 | malformed 0 | reconnects 0'
    """
    return (f"live {s.elapsed_s:.1f} s | {s.count} pings | {s.pings_per_s:.1f} pings/s | latency p50 "
            f"{_ms(s.latency_p50_ms)} p99 {_ms(s.latency_p99_ms)} | drops {s.drops} | flagged {s.flagged} | "
            f"malformed {s.malformed} | reconnects {s.reconnects}")


class StatusLine:
    """Draw :class:`LiveSnapshot` updates as one line on ``stream`` (default stderr).

    Parameters
    ----------
    stream : text file, optional
    quiet : bool
        Draw nothing, print no summary.
    live : bool, optional
        Redraw in place; default: when ``stream`` is a terminal.
    """

    def __init__(self, stream: IO[str] | None = None, *, quiet: bool = False, live: bool | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.quiet = quiet
        self.live = (bool(getattr(self.stream, "isatty", lambda: False)()) if live is None else live) and not quiet
        self._width = 0

    def __call__(self, snap: LiveSnapshot) -> None:
        """Redraw the line (the ``status`` callback of :func:`sonarmap.live.run_live`)."""
        if not self.live:
            return
        text = format_snapshot(snap)
        pad = max(0, self._width - len(text))
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()
        self._width = len(text)

    def clear(self) -> None:
        """Remove the live line (before other output on the stream)."""
        if self.live and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
            self._width = 0

    def finish(self, stats: LiveStats, extra: str = "") -> None:
        """Replace the live line by the final summary line (nothing when quiet)."""
        self.clear()
        if not self.quiet:
            self.stream.write(f"live: {stats.summary()}{extra}\n")
            self.stream.flush()
