"""``sonarmap live SOURCE``: process a sonar's stream as it arrives.

SOURCE is ``tcp://HOST[:PORT]`` or ``oculus://HOST[:PORT]`` (an Oculus sonar, port 52100 by
default), or a file with ``--follow`` (a recording being written: ARIS, ViewPoint ``.oculus`` v1
log, raw Oculus capture) or ``--replay`` (any recording, in real time).  Products go to a zarr
product store (``-o``, the layout of ``sonarmap process``, readable while written) and/or per-beam
ranges (``--ranges -`` for stdout, CSV with the ``sonarmap ranges`` columns or JSON lines).
A one-line status is redrawn on stderr (on a terminal); a summary line ends the run.  Ctrl-C
stops after the current ping and leaves a complete, valid store.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import typer

from sonarmap.cli._common import QUIET_OPTION, VERBOSE_OPTION, check_choice, example

__all__ = ["register"]


#: ``--oculus-frequency`` -> the fire message's ``masterMode``.
_FREQUENCY_MODES = {"low": 1, "high": 2}
#: ``--oculus-ping-rate`` -> the fire message's ``pingRate`` code.
_PING_RATES = {"normal": 0, "high": 1, "highest": 2, "low": 3, "lowest": 4}


def _positive(value: float | None, option: str, *, integer: bool = False) -> None:
    """A usage error (exit 2) unless ``value`` is None or positive."""
    if value is None:
        return
    if value != value or value <= 0 or value == float("inf"):
        kind = "a positive integer" if integer else "a positive number"
        raise typer.BadParameter(f"must be {kind}, got {value!r}", param_hint=option)


@contextlib.contextmanager
def _sigint_stops(stop: threading.Event) -> Iterator[None]:
    """While the block runs, the first Ctrl-C sets ``stop`` (the loop finishes cleanly); a second
    one interrupts at once."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _first_ping(path: str) -> Any:
    """The first ping of a recording to replay (to warm the pipeline on), or None."""
    import warnings

    from sonarmap.io import read_pings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return next(iter(read_pings(path)), None)
    except Exception:  # noqa: BLE001 - the replay itself reports what is wrong with the file
        return None


class _PerPingLines:
    """``-v``: one line per processed ping on stderr."""

    def __init__(self, status: Any) -> None:
        self.status = status

    def write(self, ping: Any, products: Any) -> None:
        self.status.clear()
        gates = ";".join(products.gates)
        print(f"{ping.source}: {products.ranges.n_returns} returns" + (f" ({gates})" if gates else ""),
              file=sys.stderr, flush=True)


def register(app: typer.Typer) -> None:
    """Add the ``live`` command to ``app``."""

    @app.command("live", epilog=example(
        "live tcp://192.168.2.3 -o survey.zarr --ranges -",
        "live recording.aris --follow -o live.zarr",
        "live capture.raw --replay --rate 10 --ranges - --format jsonl --max-pings 100",
    ))
    def live_cmd(
        source: str = typer.Argument(..., help="tcp://HOST[:PORT] or oculus://HOST[:PORT] (an Oculus sonar), "
                                               "or a file with --follow or --replay."),
        follow: bool = typer.Option(False, "--follow", help="Follow a file while it is written (ARIS, Oculus)."),
        replay: bool = typer.Option(False, "--replay", help="Replay a recording in real time."),
        rate: float | None = typer.Option(None, "--rate", help="Replay at this many pings per second "
                                                               "(default: the recorded times)."),
        speed: float = typer.Option(1.0, "--speed", help="Replay speed factor on the recorded times."),
        loop: bool = typer.Option(False, "--loop", help="Replay: start again after the last ping."),
        output: Path | None = typer.Option(None, "--output", "-o", help="Product store (zarr) appended as pings arrive."),
        ranges: str | None = typer.Option(None, "--ranges", help="Per-beam ranges: - for stdout, or a file."),
        bag: Path | None = typer.Option(None, "--bag", help="Ranges as marine_acoustic_msgs/SonarRanges: a ROS 1 "
                                        "*.bag file, else a ROS 2 bag directory (moved into place when the run ends)."),
        fmt: str = typer.Option("csv", "--format", help="Ranges format: csv or jsonl."),
        config: Path | None = typer.Option(None, "--config", "-c", help="Pipeline configuration TOML."),
        max_pings: int | None = typer.Option(None, "--max-pings", help="Stop after this many pings."),
        duration: float | None = typer.Option(None, "--duration", help="Stop after this many seconds."),
        queue: int = typer.Option(2, "--queue", help="Pings waiting for processing before the oldest is dropped."),
        flush_every: int = typer.Option(16, "--flush-every", help="Flush the store every N pings ..."),
        flush_seconds: float = typer.Option(1.0, "--flush-seconds", help="... or every S seconds."),
        idle_timeout: float = typer.Option(5.0, "--idle-timeout", help="--follow: stop after S seconds without "
                                                                      "growth (0: never)."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output store or bag."),
        oculus_range: float = typer.Option(2.0, "--oculus-range", help="tcp://: the Oculus range window (m)."),
        oculus_gain: float = typer.Option(50.0, "--oculus-gain", help="tcp://: the Oculus receiver gain (percent)."),
        oculus_frequency: str = typer.Option("high", "--oculus-frequency",
                                             help="tcp://: the Oculus frequency mode, high or low."),
        oculus_ping_rate: str = typer.Option("highest", "--oculus-ping-rate",
                                             help="tcp://: the Oculus ping rate: lowest (2 Hz), low (5), normal (10), "
                                                  "high (15) or highest (40)."),
        gain_assist: bool = typer.Option(True, "--gain-assist/--no-gain-assist",
                                         help="tcp://: let the Oculus lower its gain on bright targets."),
        quiet: bool = QUIET_OPTION,
        verbose: bool = VERBOSE_OPTION,
    ) -> None:
        """Process a sonar's pings as they arrive: product store, ranges, live status.

        When processing falls behind, the oldest waiting ping is dropped (counted in the status
        and the summary) so the products stay current.  The status line shows pings/s, latency
        (arrival to products ready) p50/p99, drops, flagged fits, malformed packets and
        reconnects.  Ctrl-C stops after the current ping and leaves a valid store.
        """
        # ------------------------------------------------------------ usage checks (exit 2)
        check_choice(fmt, ("csv", "jsonl"), "--format")
        _positive(rate, "--rate")
        _positive(speed, "--speed")
        _positive(max_pings, "--max-pings", integer=True)
        _positive(duration, "--duration")
        _positive(queue, "--queue", integer=True)
        _positive(flush_every, "--flush-every", integer=True)
        _positive(flush_seconds, "--flush-seconds")
        if idle_timeout != idle_timeout or idle_timeout < 0:
            raise typer.BadParameter(f"must be 0 or a positive number, got {idle_timeout!r}", param_hint="--idle-timeout")
        is_tcp = source.startswith(("tcp://", "oculus://"))
        if is_tcp and (follow or replay):
            raise typer.BadParameter("--follow / --replay apply to files, not to tcp:// sources", param_hint="SOURCE")
        if not is_tcp and "://" in source:
            raise typer.BadParameter(f"{source!r}: unknown scheme (tcp://, oculus:// or a file)", param_hint="SOURCE")
        if not is_tcp and follow == replay:
            raise typer.BadParameter("a file needs --follow (being written) or --replay", param_hint="SOURCE")
        if (rate is not None or speed != 1.0 or loop) and not replay:
            raise typer.BadParameter("--rate / --speed / --loop apply to --replay only", param_hint="--rate")
        check_choice(oculus_frequency, tuple(_FREQUENCY_MODES), "--oculus-frequency")
        check_choice(oculus_ping_rate, tuple(_PING_RATES), "--oculus-ping-rate")
        from sonarmap.errors import InputError
        from sonarmap.live.protocol import FLAG_GAIN_ASSIST, FLAG_RANGE_METERS, FLAG_SIMPLE, FireSettings

        if is_tcp:
            from sonarmap.live.sources import parse_tcp_url

            try:
                parse_tcp_url(source)
            except InputError as exc:
                raise typer.BadParameter(str(exc), param_hint="SOURCE") from None
        try:
            fire = FireSettings(
                master_mode=_FREQUENCY_MODES[oculus_frequency], ping_rate=_PING_RATES[oculus_ping_rate],
                flags=FLAG_RANGE_METERS | FLAG_SIMPLE | (FLAG_GAIN_ASSIST if gain_assist else 0),
                range_m=oculus_range, gain_percent=oculus_gain)
        except InputError as exc:
            raise typer.BadParameter(str(exc), param_hint="--oculus-range / --oculus-gain") from None
        if not is_tcp and fire != FireSettings():
            raise typer.BadParameter("the --oculus-* and --gain-assist settings are sent to a live Oculus "
                                     "(tcp://); a file is read as recorded", param_hint="--oculus-range")
        tcp: dict[str, Any] = {"fire": fire} if is_tcp else {}

        # ------------------------------------------------------------ set up (errors: exit 1)
        from sonarmap.cli.ranges import pipeline_config_from_options
        from sonarmap.live import BagSink, RangesSink, StatusLine, StoreSink, open_source, run_live, warm_pipeline

        cfg = pipeline_config_from_options(config, None, None, None)  # the route every command takes
        src = open_source(source, follow=follow, replay=replay, rate_hz=rate, speed=speed, loop=loop,
                          idle_timeout_s=idle_timeout, **tcp)
        status = StatusLine(quiet=quiet)
        sinks: list[Any] = []
        store: StoreSink | None = None
        ranges_fh: Any = None
        if output is not None:
            store = StoreSink(output, config=cfg, flush_every=flush_every, flush_s=flush_seconds,
                              overwrite=overwrite, inputs=(src.name,))
            sinks.append(store)
        stats = None
        stop = threading.Event()
        bag_sink: BagSink | None = None
        try:
            if bag is not None:
                bag_sink = BagSink(bag, overwrite=overwrite)
                sinks.append(bag_sink)
            if ranges is not None:
                if ranges == "-":
                    ranges_fh = sys.stdout
                else:
                    from sonarmap._atomic import write_error

                    try:
                        ranges_fh = open(ranges, "w", encoding="utf-8", newline="")  # noqa: SIM115 - closed below
                    except OSError as exc:
                        raise write_error(exc, ranges, "cannot open the ranges output") from None
                sinks.append(RangesSink(ranges_fh, fmt))
            if verbose:
                sinks.append(_PerPingLines(status))
            warm_pipeline(cfg, None if is_tcp else _first_ping(source))
            with _sigint_stops(stop):
                stats = run_live(src, config=cfg, sinks=sinks, max_pings=max_pings, duration_s=duration,
                                 queue_size=queue, status=None if quiet else status, stop_event=stop)
        finally:
            status.clear()
            try:
                try:
                    if store is not None:
                        store.close()
                finally:
                    if bag_sink is not None:
                        bag_sink.close()
            finally:
                if ranges_fh is not None and ranges_fh is not sys.stdout:
                    ranges_fh.close()
                elif ranges_fh is not None:
                    with contextlib.suppress(OSError, ValueError):
                        ranges_fh.flush()
        extra = ""
        if store is not None:
            extra = f" -> {output} ({store.n_written} pings)" if store.n_written else f"; no pings, {output} not written"
        if bag_sink is not None:
            extra += f" -> {bag} ({bag_sink.n_written} SonarRanges)"
        status.finish(stats, extra)
