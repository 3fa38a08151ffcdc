"""The real-time loop: pings from a source -> :func:`sonarmap.pipeline.process_ping` -> sinks.

A reader thread pulls pings from the source into a bounded queue; the calling thread takes them
out and processes them.  When processing falls behind and the queue is full, the *oldest* queued
ping is dropped (and counted) to make room for the new one: the products stay current and the
latency bounded (about ``queue_size + 1`` processing times at worst) instead of growing without
limit.  Latency is measured per ping from its arrival (the moment the source delivered it) to
its products being ready (``process_ping`` returned).

:func:`run_live` returns :class:`LiveStats`; a ``status`` callback gets a :class:`LiveSnapshot`
about twice a second (:mod:`sonarmap.live.status` draws it as one line on stderr).
"""

from __future__ import annotations

import collections
import dataclasses
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from sonarmap._text import counted
from sonarmap.errors import InputError
from sonarmap.ping import Ping

__all__ = ["LiveStats", "LiveSnapshot", "run_live", "warm_pipeline", "DEFAULT_QUEUE"]

#: Default bound of the queue between the reader and the processing loop (pings).
DEFAULT_QUEUE = 2
#: Latencies kept for the live status (the final statistics use every ping).
_RECENT = 256


@dataclasses.dataclass(frozen=True)
class LiveSnapshot:
    """What the live status line shows (a moment of a running loop).

    Attributes
    ----------
    elapsed_s : float
        Since the loop started.
    count, drops, flagged, malformed, reconnects : int
        Pings processed; dropped (processing behind); with a flagged fit; damaged packets
        skipped by the source; reconnections.
    pings_per_s : float
        Processing rate over the last ~2 s.
    latency_p50_ms, latency_p99_ms : float
        Over the last 256 pings (NaN before the first).
    """

    elapsed_s: float
    count: int
    drops: int
    flagged: int
    malformed: int
    reconnects: int
    pings_per_s: float
    latency_p50_ms: float
    latency_p99_ms: float


@dataclasses.dataclass(frozen=True)
class LiveStats:
    """Statistics of a finished :func:`run_live` run.

    Attributes
    ----------
    count : int
        Pings processed.
    received : int
        Pings the source delivered (``count + drops + unprocessed``).
    drops : int
        Pings dropped because processing was behind (the oldest queued ping goes first).
    unprocessed : int
        Pings still queued when the run was stopped (``max_pings``, duration, interrupt).
    flagged : int
        Processed pings whose fit was flagged implausible (no returns; ``PingProducts.flagged``).
    malformed : int
        Damaged packets / messages the source skipped.
    reconnects : int
        Reconnections of the source.
    latency_p50_ms, latency_p99_ms, latency_max_ms : float
        Arrival -> products ready, over every processed ping (NaN without one).
    process_p50_ms : float
        Median time of ``process_ping`` alone.
    elapsed_s : float
        Wall time of the run.
    stopped_by : str
        ``"source"`` (it ended), ``"max_pings"``, ``"duration"`` or ``"interrupt"``.
    """

    count: int
    received: int
    drops: int
    unprocessed: int
    flagged: int
    malformed: int
    reconnects: int
    latency_p50_ms: float
    latency_p99_ms: float
    latency_max_ms: float
    process_p50_ms: float
    elapsed_s: float
    stopped_by: str

    @property
    def pings_per_s(self) -> float:
        """Processed pings per second of wall time."""
        return self.count / self.elapsed_s if self.elapsed_s > 0 else math.nan

    def summary(self) -> str:
        """One line: counts, rate, latency."""
        lat = ("latency n/a" if math.isnan(self.latency_p50_ms) else
               f"latency p50 {self.latency_p50_ms:.1f} ms / p99 {self.latency_p99_ms:.1f} ms")
        return (f"{counted(self.count, 'ping')} in {self.elapsed_s:.1f} s ({self.pings_per_s:.1f}/s), {lat}, "
                f"{self.drops} dropped, {self.flagged} flagged, {self.malformed} malformed, "
                f"{self.reconnects} reconnects (stopped by {self.stopped_by})")


def _pct(values: Sequence[float] | np.ndarray, q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) * 1e3 if len(values) else math.nan


def warm_pipeline(config: Any = None, ping: Ping | None = None) -> None:
    """Run the pipeline once before the stream starts, so the first real ping is not slowed by
    loading the compiled kernels and lazily imported modules (~1 s).

    Parameters
    ----------
    config : PipelineConfig, optional
    ping : Ping, optional
        A ping like those to come (e.g. the first of the recording); default synthetic
        thresholded and speckle images.
    """
    from sonarmap.geometry import preset
    from sonarmap.pipeline import PipelineConfig, process_ping
    from sonarmap.survey import warm_pipeline_once

    warm_pipeline_once()  # the thresholded-image path

    cfg = config if config is not None else PipelineConfig()
    if ping is None:
        g = preset("oculus-m750d-like")
        img = np.random.default_rng(0).exponential(0.1, g.shape).astype(np.float32)
        img[g.n_bins // 2 : g.n_bins // 2 + 6] += 0.8
        ping = Ping(np.clip(img, 0, 1), g)
    try:
        process_ping(ping, cfg)
    except Exception:  # noqa: BLE001 - warming is an optimisation, never a requirement
        pass


def run_live(
    source: Any,
    *,
    config: Any = None,
    sinks: Sequence[Any] = (),
    max_pings: int | None = None,
    duration_s: float | None = None,
    queue_size: int = DEFAULT_QUEUE,
    status: Callable[[LiveSnapshot], None] | None = None,
    status_interval_s: float = 0.5,
    stop_event: threading.Event | None = None,
    process: Callable[..., Any] | None = None,
) -> LiveStats:
    """Process a live source's pings as they arrive, dropping the oldest when behind.

    Parameters
    ----------
    source : PingSource or iterable of Ping
        Where pings come from (:mod:`sonarmap.live.sources`); its ``stop()`` is called at the end,
        its ``malformed`` / ``reconnects`` counters are reported.
    config : PipelineConfig, optional
        Pipeline configuration (default ``PipelineConfig()``).
    sinks : sequence
        Objects with ``write(ping, products)`` (and optionally ``tick()``, called while idle, and
        ``flush()``), e.g. :class:`~sonarmap.live.sinks.RangesSink`, :class:`~sonarmap.live.sinks.StoreSink`.
        They are not closed here.
    max_pings : int, optional
        Stop after processing this many pings.
    duration_s : float, optional
        Stop after this long.
    queue_size : int
        Bound of the queue between the reader and the processing (>= 1).
    status : callable, optional
        Called with a :class:`LiveSnapshot` every ``status_interval_s``.
    stop_event : threading.Event, optional
        Set it (e.g. from a SIGINT handler) to stop after the current ping.
    process : callable, optional
        ``process(ping, config) -> PingProducts`` (default :func:`sonarmap.pipeline.process_ping`).

    Returns
    -------
    LiveStats

    Raises
    ------
    InputError
        On invalid arguments.
    SonarmapError, OSError
        What the source raised (e.g. it cannot connect, the file is not readable) - after the
        pings that arrived before were processed.

    Examples
    --------
    >>> from sonarmap.live import ReplaySource, run_live
    >>> stats = run_live(ReplaySource("sample.aris", rate_hz=10), max_pings=6)  # doctest: +SKIP
    >>> stats.count, stats.drops                                                  # doctest: +SKIP
    (6, 0)
    """
    from sonarmap.pipeline import PipelineConfig, process_ping

    _check_limits(queue_size, max_pings, duration_s)
    cfg = config if config is not None else PipelineConfig()
    fn = process or process_ping
    stop = stop_event if stop_event is not None else threading.Event()
    arrivals = _Arrivals(source, queue_size, stop)
    timing = _Timing(source)
    arrivals.start()
    try:
        stopped_by = _serve(arrivals, timing, sinks, fn, cfg, stop=stop, duration_s=duration_s, max_pings=max_pings,
                            status=status, status_interval_s=status_interval_s)
    finally:
        stop_source = getattr(source, "stop", None)
        if stop_source is not None:
            stop_source()
        arrivals.thread.join(5.0)
    if arrivals.failure and stopped_by == "source":
        raise arrivals.failure[0]
    return timing.stats(arrivals, stopped_by)


def _check_limits(queue_size: Any, max_pings: Any, duration_s: Any) -> None:
    """The queue bound and the stop limits of :func:`run_live` are valid."""
    if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
        raise InputError(f"queue_size: must be a positive integer, got {queue_size!r}")
    if max_pings is not None and (isinstance(max_pings, bool) or not isinstance(max_pings, int) or max_pings < 1):
        raise InputError(f"max_pings: must be a positive integer, got {max_pings!r}")
    if duration_s is not None and not (isinstance(duration_s, int | float) and duration_s > 0):
        raise InputError(f"duration_s: must be a positive number of seconds, got {duration_s!r}")


def _tick(sinks: Sequence[Any]) -> None:
    """Let each sink that has ``tick()`` do its idle work (e.g. a timed flush)."""
    for sink in sinks:
        tick = getattr(sink, "tick", None)
        if tick is not None:
            tick()


def _serve(arrivals: _Arrivals, timing: _Timing, sinks: Sequence[Any], fn: Callable[..., Any], cfg: Any, *,
           stop: threading.Event, duration_s: float | None, max_pings: int | None,
           status: Callable[[LiveSnapshot], None] | None, status_interval_s: float) -> str:
    """Process arrivals until the source ends, a limit is reached or ``stop`` is set; returns why it stopped."""
    next_status = timing.t0 + status_interval_s
    while True:
        item, done, why = arrivals.take(stop, duration_s, timing.t0)
        if why is not None:
            return why
        if item is None:
            _tick(sinks)
            now = time.perf_counter()
            if status is not None and now >= next_status:
                status(timing.snapshot(now, arrivals.drops))
                next_status = now + status_interval_s
            if done:
                return "source"
            continue
        ping, t_arrival = item
        t_start = time.perf_counter()
        products = fn(ping, cfg)
        t_ready = time.perf_counter()
        timing.record(t_arrival, t_start, t_ready, bool(getattr(products, "flagged", False)))
        for sink in sinks:
            sink.write(ping, products)
        if status is not None and t_ready >= next_status:
            status(timing.snapshot(t_ready, arrivals.drops))
            next_status = t_ready + status_interval_s
        if max_pings is not None and timing.count >= max_pings:
            return "max_pings"


class _Arrivals:
    """The reader thread: the source's pings, with their arrival times, into a queue of at most
    ``queue_size`` (when processing falls behind, the oldest waiting ping is dropped and counted)."""

    def __init__(self, source: Any, queue_size: int, stop: threading.Event) -> None:
        self.cond = threading.Condition()
        self.queue: collections.deque[tuple[Ping, float]] = collections.deque()
        self.received = 0
        self.drops = 0
        self.done = False
        self.failure: list[BaseException] = []
        self.thread = threading.Thread(target=self._read, args=(source, queue_size, stop),
                                       name="sonarmap-live-reader", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def _read(self, source: Any, queue_size: int, stop: threading.Event) -> None:
        try:
            for ping in source:
                t = time.perf_counter()
                with self.cond:
                    if len(self.queue) >= queue_size:
                        self.queue.popleft()
                        self.drops += 1
                    self.queue.append((ping, t))
                    self.received += 1
                    self.cond.notify()
                if stop.is_set():
                    break
        except BaseException as exc:  # noqa: BLE001 - handed to the processing thread
            self.failure.append(exc)
        finally:
            with self.cond:
                self.done = True
                self.cond.notify()

    def take(self, stop: threading.Event, duration_s: float | None, t0: float
             ) -> tuple[tuple[Ping, float] | None, bool, str | None]:
        """The next waiting ping (None after a short wait without one), whether the source is
        finished and drained, and why the loop must stop now (``interrupt``, ``duration``)."""
        with self.cond:
            if not self.queue and not self.done and not stop.is_set():
                self.cond.wait(0.05)  # wake up now and then: status line, time-based flushes
            now = time.perf_counter()
            if stop.is_set():
                return None, False, "interrupt"
            if duration_s is not None and now - t0 >= duration_s:
                return None, False, "duration"
            item = self.queue.popleft() if self.queue else None
            return item, self.done and not self.queue, None

    def drain(self) -> int:
        """Drop the pings still waiting; returns how many."""
        with self.cond:
            n = len(self.queue)
            self.queue.clear()
        return n


class _Timing:
    """Latencies, processing times and the throughput of the loop."""

    def __init__(self, source: Any) -> None:
        self.source = source
        self.latencies: list[float] = []
        self.proc_times: list[float] = []
        self.recent: collections.deque[float] = collections.deque(maxlen=_RECENT)
        self.finished: collections.deque[float] = collections.deque(maxlen=512)
        self.count = 0
        self.flagged = 0
        self.t0 = time.perf_counter()

    def counter(self, name: str) -> int:
        return int(getattr(self.source, name, 0) or 0)

    def record(self, t_arrival: float, t_start: float, t_ready: float, flagged: bool) -> None:
        self.latencies.append(t_ready - t_arrival)
        self.recent.append(t_ready - t_arrival)
        self.proc_times.append(t_ready - t_start)
        self.finished.append(t_ready)
        self.count += 1
        self.flagged += int(flagged)

    def snapshot(self, now: float, drops: int) -> LiveSnapshot:
        while self.finished and now - self.finished[0] > 2.0:
            self.finished.popleft()
        window = min(2.0, now - self.t0)
        return LiveSnapshot(now - self.t0, self.count, drops, self.flagged, self.counter("malformed"),
                            self.counter("reconnects"), len(self.finished) / window if window > 0 else 0.0,
                            _pct(self.recent, 50), _pct(self.recent, 99))

    def stats(self, arrivals: _Arrivals, stopped_by: str) -> LiveStats:
        lat = self.latencies
        return LiveStats(
            count=self.count, received=arrivals.received, drops=arrivals.drops, unprocessed=arrivals.drain(),
            flagged=self.flagged, malformed=self.counter("malformed"), reconnects=self.counter("reconnects"),
            latency_p50_ms=_pct(lat, 50), latency_p99_ms=_pct(lat, 99),
            latency_max_ms=max(lat) * 1e3 if lat else math.nan, process_p50_ms=_pct(self.proc_times, 50),
            elapsed_s=time.perf_counter() - self.t0, stopped_by=stopped_by,
        )
