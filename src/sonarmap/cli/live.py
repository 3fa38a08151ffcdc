"""``sonarmap live SOURCE``: process a sonar's stream as it arrives.

SOURCE is ``tcp://HOST[:PORT]`` or ``oculus://HOST[:PORT]`` (an Oculus sonar, port 52100 by
default), or a file with ``--follow`` (a recording being written: ARIS, ViewPoint ``.oculus`` v1
log, raw Oculus capture) or ``--replay`` (any recording, in real time).  Products go to a zarr
product store (``-o``, the layout of ``sonarmap process``, readable while written) and/or per-beam
ranges (``--ranges -`` for stdout, CSV with the ``sonarmap ranges`` columns or JSON lines).
A one-line status is redrawn on stderr (on a terminal); a summary line ends the run.  Ctrl-C
stops after the current ping and leaves a complete, valid store (none if no ping arrived: the
summary line says so).
"""

from __future__ import annotations

import contextlib
import dataclasses
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import typer

from sonarmap._text import counted
from sonarmap.cli._common import QUIET_OPTION, VERBOSE_OPTION, check_choice, compile_on_first_run, example, refuse_stdout

if TYPE_CHECKING:
    from sonarmap.live import BagSink, StoreSink

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


_SOURCE_ARGUMENT: Any = typer.Argument(..., help="tcp://HOST[:PORT] or oculus://HOST[:PORT] (an Oculus sonar), "
                                                 "or a file with --follow or --replay.")
_FOLLOW_OPTION: Any = typer.Option(False, "--follow", help="Follow a file while it is written (ARIS, Oculus).")
_REPLAY_OPTION: Any = typer.Option(False, "--replay", help="Replay a recording in real time.")
_RATE_OPTION: Any = typer.Option(None, "--rate", help="Replay at this many pings per second "
                                                      "(default: the recorded times).")
_SPEED_OPTION: Any = typer.Option(1.0, "--speed", help="Replay speed factor on the recorded times.")
_LOOP_OPTION: Any = typer.Option(False, "--loop", help="Replay: start again after the last ping.")
_OUTPUT_OPTION: Any = typer.Option(None, "--output", "-o", help="Product store (zarr) appended as pings arrive.",
                                   callback=refuse_stdout)
_RANGES_OPTION: Any = typer.Option(None, "--ranges", help="Per-beam ranges: - for stdout, or a file.")
_BAG_OPTION: Any = typer.Option(None, "--bag", help="Ranges as marine_acoustic_msgs/SonarRanges: a ROS 1 "
                                "*.bag file, else a ROS 2 bag directory (moved into place when the run ends).")
_FORMAT_OPTION: Any = typer.Option("csv", "--format", help="Ranges format: csv or jsonl.")
_CONFIG_OPTION: Any = typer.Option(None, "--config", "-c", help="Pipeline configuration TOML.")
_MAX_PINGS_OPTION: Any = typer.Option(None, "--max-pings", help="Stop after this many pings.")
_DURATION_OPTION: Any = typer.Option(None, "--duration", help="Stop after this many seconds.")
_QUEUE_OPTION: Any = typer.Option(2, "--queue", help="Pings waiting for processing before the oldest is dropped.")
_FLUSH_EVERY_OPTION: Any = typer.Option(16, "--flush-every", help="Flush the store every N pings ...")
_FLUSH_SECONDS_OPTION: Any = typer.Option(1.0, "--flush-seconds", help="... or every S seconds.")
_IDLE_TIMEOUT_OPTION: Any = typer.Option(5.0, "--idle-timeout", help="--follow: stop after S seconds without "
                                                                    "growth (0: never).")
_OVERWRITE_OPTION: Any = typer.Option(False, "--overwrite", help="Replace an existing output store or bag.")
_OCULUS_RANGE_OPTION: Any = typer.Option(2.0, "--oculus-range", help="tcp://: the Oculus range window (m).")
_OCULUS_GAIN_OPTION: Any = typer.Option(50.0, "--oculus-gain", help="tcp://: the Oculus receiver gain (percent).")
_OCULUS_FREQUENCY_OPTION: Any = typer.Option("high", "--oculus-frequency",
                                             help="tcp://: the Oculus frequency mode, high or low.")
_OCULUS_PING_RATE_OPTION: Any = typer.Option("highest", "--oculus-ping-rate",
                                             help="tcp://: the Oculus ping rate: lowest (2 Hz), low (5), normal (10), "
                                                  "high (15) or highest (40).")
_GAIN_ASSIST_OPTION: Any = typer.Option(True, "--gain-assist/--no-gain-assist",
                                        help="tcp://: let the Oculus lower its gain on bright targets.")


def register(app: typer.Typer) -> None:
    """Add the ``live`` command to ``app``."""

    @app.command("live", epilog=example(
        "live tcp://192.168.2.3 -o survey.zarr --ranges -",
        "live recording.aris --follow -o live.zarr",
        "live capture.raw --replay --rate 10 --ranges - --format jsonl --max-pings 100",
    ))
    def live_cmd(
        source: str = _SOURCE_ARGUMENT,
        follow: bool = _FOLLOW_OPTION,
        replay: bool = _REPLAY_OPTION,
        rate: float | None = _RATE_OPTION,
        speed: float = _SPEED_OPTION,
        loop: bool = _LOOP_OPTION,
        output: Path | None = _OUTPUT_OPTION,
        ranges: str | None = _RANGES_OPTION,
        bag: Path | None = _BAG_OPTION,
        fmt: str = _FORMAT_OPTION,
        config: Path | None = _CONFIG_OPTION,
        max_pings: int | None = _MAX_PINGS_OPTION,
        duration: float | None = _DURATION_OPTION,
        queue: int = _QUEUE_OPTION,
        flush_every: int = _FLUSH_EVERY_OPTION,
        flush_seconds: float = _FLUSH_SECONDS_OPTION,
        idle_timeout: float = _IDLE_TIMEOUT_OPTION,
        overwrite: bool = _OVERWRITE_OPTION,
        oculus_range: float = _OCULUS_RANGE_OPTION,
        oculus_gain: float = _OCULUS_GAIN_OPTION,
        oculus_frequency: str = _OCULUS_FREQUENCY_OPTION,
        oculus_ping_rate: str = _OCULUS_PING_RATE_OPTION,
        gain_assist: bool = _GAIN_ASSIST_OPTION,
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
        _check_limits(rate=rate, speed=speed, max_pings=max_pings, duration=duration, queue=queue,
                      flush_every=flush_every, flush_seconds=flush_seconds, idle_timeout=idle_timeout)
        is_tcp = _check_source(source, follow=follow, replay=replay, rate=rate, speed=speed, loop=loop)
        tcp = _tcp_settings(source, is_tcp, frequency=oculus_frequency, ping_rate=oculus_ping_rate,
                            gain_assist=gain_assist, range_m=oculus_range, gain_percent=oculus_gain)

        # ------------------------------------------------------------ set up (errors: exit 1)
        from sonarmap.cli.ranges import pipeline_config_from_options
        from sonarmap.live import StatusLine, StoreSink, open_source, run_live, warm_pipeline

        stop = threading.Event()
        with _sigint_stops(stop):  # a Ctrl-C while setting up ends the run as cleanly as one later
            cfg = pipeline_config_from_options(config, None, None, None)  # the route every command takes
            src = open_source(source, follow=follow, replay=replay, rate_hz=rate, speed=speed, loop=loop,
                              idle_timeout_s=idle_timeout, **tcp)
            status = StatusLine(quiet=quiet)
            outputs = _LiveOutputs(None if output is None else StoreSink(
                output, config=cfg, flush_every=flush_every, flush_s=flush_seconds, overwrite=overwrite,
                inputs=(src.name,)))
            stats = None
            try:
                outputs.open_bag_and_ranges(bag, ranges, fmt, overwrite=overwrite)
                if verbose:
                    outputs.sinks.append(_PerPingLines(status))
                if not stop.is_set():
                    # a cold numba cache: say so and compile with helper processes first
                    compile_on_first_run(quiet)
                    warm_pipeline(cfg, None if is_tcp else _first_ping(source))
                stats = run_live(src, config=cfg, sinks=outputs.sinks, max_pings=max_pings, duration_s=duration,
                                 queue_size=queue, status=None if quiet else status, stop_event=stop)
            finally:
                status.clear()
                outputs.close()
        status.finish(stats, outputs.summary(output, bag))


def _check_limits(*, rate: float | None, speed: float, max_pings: int | None, duration: float | None, queue: int,
                  flush_every: int, flush_seconds: float, idle_timeout: float) -> None:
    """Usage errors (exit 2) of the rates, limits and intervals: each positive, ``--idle-timeout`` 0 or positive."""
    _positive(rate, "--rate")
    _positive(speed, "--speed")
    _positive(max_pings, "--max-pings", integer=True)
    _positive(duration, "--duration")
    _positive(queue, "--queue", integer=True)
    _positive(flush_every, "--flush-every", integer=True)
    _positive(flush_seconds, "--flush-seconds")
    if idle_timeout != idle_timeout or idle_timeout < 0:
        raise typer.BadParameter(f"must be 0 or a positive number, got {idle_timeout!r}", param_hint="--idle-timeout")


def _check_source(source: str, *, follow: bool, replay: bool, rate: float | None, speed: float, loop: bool) -> bool:
    """Whether ``source`` is a ``tcp://`` / ``oculus://`` stream (else a file); usage errors (exit 2)
    for an unknown scheme and for the file modes and replay options that do not apply to it."""
    is_tcp = source.startswith(("tcp://", "oculus://"))
    if is_tcp and (follow or replay):
        raise typer.BadParameter("--follow / --replay apply to files, not to tcp:// sources", param_hint="SOURCE")
    if not is_tcp and "://" in source:
        raise typer.BadParameter(f"{source!r}: unknown scheme (tcp://, oculus:// or a file)", param_hint="SOURCE")
    if not is_tcp and follow == replay:
        raise typer.BadParameter("a file needs --follow (being written) or --replay", param_hint="SOURCE")
    if (rate is not None or speed != 1.0 or loop) and not replay:
        raise typer.BadParameter("--rate / --speed / --loop apply to --replay only", param_hint="--rate")
    return is_tcp


def _tcp_settings(source: str, is_tcp: bool, *, frequency: str, ping_rate: str, gain_assist: bool, range_m: float,
                  gain_percent: float) -> dict[str, Any]:
    """The ``open_source`` keywords of a ``tcp://`` source (its fire message; none for a file).  Usage errors
    (exit 2): a malformed address, invalid ``--oculus-*`` values, such settings with a file source."""
    check_choice(frequency, tuple(_FREQUENCY_MODES), "--oculus-frequency")
    check_choice(ping_rate, tuple(_PING_RATES), "--oculus-ping-rate")
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
            master_mode=_FREQUENCY_MODES[frequency], ping_rate=_PING_RATES[ping_rate],
            flags=FLAG_RANGE_METERS | FLAG_SIMPLE | (FLAG_GAIN_ASSIST if gain_assist else 0),
            range_m=range_m, gain_percent=gain_percent)
    except InputError as exc:
        raise typer.BadParameter(str(exc), param_hint="--oculus-range / --oculus-gain") from None
    if not is_tcp and fire != FireSettings():
        raise typer.BadParameter("the --oculus-* and --gain-assist settings are sent to a live Oculus "
                                 "(tcp://); a file is read as recorded", param_hint="--oculus-range")
    return {"fire": fire} if is_tcp else {}


@dataclasses.dataclass
class _LiveOutputs:
    """The outputs of a ``live`` run (store, bag, ranges stream) and their sinks, in write order."""

    store: StoreSink | None = None
    bag: BagSink | None = None
    ranges_fh: IO[str] | None = None
    sinks: list[Any] = dataclasses.field(default_factory=list)

    def __post_init__(self) -> None:
        """The store, if any, is the first sink."""
        if self.store is not None:
            self.sinks.append(self.store)

    def open_bag_and_ranges(self, bag: Path | None, ranges: str | None, fmt: str, *, overwrite: bool) -> None:
        """Open the ``--bag`` and then the ``--ranges`` output (``-``: stdout) and add their sinks."""
        from sonarmap.live import BagSink, RangesSink

        if bag is not None:
            self.bag = BagSink(bag, overwrite=overwrite)
            self.sinks.append(self.bag)
        if ranges is not None:
            if ranges == "-":
                self.ranges_fh = sys.stdout
            else:
                from sonarmap._atomic import write_error

                try:
                    self.ranges_fh = open(ranges, "w", encoding="utf-8", newline="")  # noqa: SIM115 - closed below
                except OSError as exc:
                    raise write_error(exc, ranges, "cannot open the ranges output") from None
            self.sinks.append(RangesSink(self.ranges_fh, fmt))

    def close(self) -> None:
        """Close the store, the bag and the ranges file (stdout is only flushed), each even when
        closing the one before fails."""
        try:
            try:
                if self.store is not None:
                    self.store.close()
            finally:
                if self.bag is not None:
                    self.bag.close()
        finally:
            if self.ranges_fh is not None and self.ranges_fh is not sys.stdout:
                self.ranges_fh.close()
            elif self.ranges_fh is not None:
                with contextlib.suppress(OSError, ValueError):
                    self.ranges_fh.flush()

    def summary(self, output: Path | None, bag: Path | None) -> str:
        """What the summary line adds after the run's statistics: the pings stored and the messages bagged."""
        extra = ""
        if self.store is not None:
            n = self.store.n_written
            extra = (f" -> {output} ({counted(n, 'ping')})" if n
                     else f"; no ping arrived, so {output} was not written")
        if self.bag is not None:
            extra += f" -> {bag} ({self.bag.n_written} SonarRanges)"
        return extra
