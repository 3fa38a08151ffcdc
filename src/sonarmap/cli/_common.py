"""Options and helpers shared by the sub-commands (defined once)."""

from __future__ import annotations

import dataclasses

from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import typer

from sonarmap._text import counted

__all__ = [
    "CALIBRATION_OPTION", "GEOMETRY_OPTION", "OUTPUT_DIR_OPTION", "OUTPUT_OPTION", "PINGS_ARGUMENT", "PING_RATE_OPTION",
    "QUIET_OPTION", "START_TIME_OPTION", "STDOUT", "VERBOSE_OPTION", "refuse_stdout",
    "PingProgress", "apply_calibration", "check_choice", "check_clock_used", "clock_options", "console",
    "compile_on_first_run", "count_pings", "err_console", "example", "first_ping", "first_run_notice", "input_name",
    "input_progress", "load_calibration",
    "load_geometry_option", "open_output", "output_name", "ping_progress", "read_input_pings", "run_pings",
    "stop_progress",
]

#: The ``PINGS...`` argument of the commands that read pings.
PINGS_ARGUMENT: Any = typer.Argument(..., help="Ping files, directories or globs.")

GEOMETRY_OPTION: Any = typer.Option(
    None,
    "--sonar",
    "-s",
    metavar="PRESET|JSON",
    help="Sonar geometry: a preset name (list them with: sonarmap info --presets) or a geometry JSON file; "
    "overrides the pings' sidecar JSON.",
)
OUTPUT_OPTION: Any = typer.Option(..., "--output", "-o", help="Output path.")


def refuse_stdout(value: Path | None) -> Path | None:
    """``--output`` callback of the commands that write files or stores, not one stream: ``-o -``
    is a usage error there (it made a file or directory named ``-``)."""
    if value is not None and str(value) == "-":
        raise typer.BadParameter("'-' (stdout) is only for ranges, fit, calibrate and map; this command writes "
                                 "files: give a path")
    return value


#: ``-o`` of the commands that write a directory of files.
OUTPUT_DIR_OPTION: Any = typer.Option(..., "--output", "-o", help="Output directory.", callback=refuse_stdout)
QUIET_OPTION: Any = typer.Option(False, "--quiet", "-q", help="No progress bar and no summary.")
VERBOSE_OPTION: Any = typer.Option(False, "--verbose", "-v", help="One line per ping and the total time on stderr.")

#: ``--calibration`` of the commands that run the per-ping pipeline (ranges, map, segment, process).
CALIBRATION_OPTION: Any = typer.Option(
    None, "--calibration",
    help="Output of sonarmap calibrate on this recording: normalise every ping by the recording's "
    "background level instead of its own, and fit the intensity model it chose.",
)

#: ``--start-time`` / ``--ping-rate``: the clock of a recording that has none (Oculus network captures).
START_TIME_OPTION: Any = typer.Option(
    None, "--start-time", metavar="TIME",
    help="Recordings without a clock (Oculus network captures): time of the first ping, ISO 8601 "
    "(UTC unless an offset is given, e.g. 2024-05-01T10:20:30.5Z) or integer ns since 1970; "
    "default: the file's modification time.",
)
PING_RATE_OPTION: Any = typer.Option(
    None, "--ping-rate", metavar="HZ",
    help="Recordings without a clock: pings per second (default 10); ping i is at start + i / rate.",
)

#: The ``-o`` value that means standard output.
STDOUT = "-"


def first_ping(
    pings: Iterator[Any], argument: str = "PINGS",
    message: str = "no complete ping in the input (nothing written)",
) -> tuple[Any, Iterator[Any]]:
    """Read the first ping before any work, so that an unreadable input prints only its error.

    Returns
    -------
    first : Ping
        The first ping.
    pings : iterator of Ping
        All the pings, the first one included.

    Raises
    ------
    InputError
        ``"<argument>: <message>"`` when the input holds no ping.
    """
    import itertools

    from sonarmap.errors import InputError

    first = next(pings, None)
    if first is None:
        raise InputError(f"{argument}: {message}")
    return first, itertools.chain([first], pings)


def input_name(inputs: list[Path] | list[str], argument: str) -> str:
    """How an error about the input names it: the path when there is one, else ``argument``.

    Examples
    --------
    >>> input_name(["cut.aris"], "PINGS"), input_name(["a.aris", "b.aris"], "PINGS")
    ('cut.aris', 'PINGS')
    """
    return str(inputs[0]) if len(inputs) == 1 else argument


def clock_options(start_time: str | None, ping_rate: float | None) -> dict[str, Any]:
    """The readers' ``start_time_ns`` / ``rate_hz`` arguments from ``--start-time`` / ``--ping-rate``.

    ``--start-time`` is integer ns since the Unix epoch, or an ISO 8601 time (UTC unless it gives
    an offset; to the nanosecond).  A value that is neither, or a rate that is not a positive
    number, is a usage error (exit 2).

    Examples
    --------
    >>> clock_options("2024-05-01T10:20:30.5Z", 15.0)
    {'start_time_ns': 1714558830500000000, 'rate_hz': 15.0}
    >>> clock_options(None, None)
    {}
    """
    import math

    out: dict[str, Any] = {}
    if start_time is not None:
        out["start_time_ns"] = _parse_time_ns(start_time)
    if ping_rate is not None:
        if not (math.isfinite(ping_rate) and 0.0 < ping_rate <= 1e6):
            raise typer.BadParameter(f"{ping_rate!r}: must be a number of pings per second in (0, 1e6]",
                                     param_hint="--ping-rate")
        out["rate_hz"] = float(ping_rate)
    return out


def _parse_time_ns(text: str) -> int:
    """``--start-time``: integer ns since 1970, or ISO 8601 (UTC without an offset) to the ns."""
    import numpy as np

    t = text.strip()
    if t.isdigit():
        if int(t) < 10**16:  # before 1970-04-26: a year or seconds, not nanoseconds
            raise typer.BadParameter(f"{text!r}: integer times are nanoseconds since 1970 (e.g. 1714558830500000000); "
                                     "or give ISO 8601 (2024-05-01T10:20:30.5Z)", param_hint="--start-time")
        return int(t)
    import re

    offset_ns = 0
    m = re.fullmatch(r"(.*?)(Z|[+-]\d\d:?\d\d)?", t)
    body, zone = (m.group(1), m.group(2)) if m else (t, None)
    if zone and zone != "Z":
        sign = -1 if zone[0] == "+" else 1  # local time + offset -> UTC
        digits = zone[1:].replace(":", "")
        offset_ns = sign * (int(digits[:2]) * 3600 + int(digits[2:]) * 60) * 10**9
    try:
        value = np.datetime64(body, "ns")
    except ValueError:
        value = np.datetime64("NaT")
    if np.isnat(value) or "T" not in body and len(body) < 10:
        raise typer.BadParameter(
            f"{text!r}: give an ISO 8601 time (e.g. 2024-05-01T10:20:30.5Z) or integer ns since 1970",
            param_hint="--start-time")
    return int(value.astype(np.int64)) + offset_ns


def read_input_pings(
    inputs: list[Path], geometry: Any, argument: str = "PINGS",
    message: str = "no complete ping in the input (nothing written)", *, clock: dict[str, Any] | None = None,
) -> Iterator[Any]:
    """The pings of ``inputs`` (:func:`sonarmap.io.read_pings`), the first one already read.

    Reading the first ping before any work (:func:`first_ping`) makes an unreadable input print
    only its error.

    Parameters
    ----------
    inputs : list of Path
        Ping files, directories or globs.
    geometry : SonarGeometry, optional
        Overrides the pings' own geometry (``--sonar``).
    argument, message : str
        As for :func:`first_ping`; a single input is named by its path instead of ``argument``.
    clock : dict, optional
        :func:`clock_options` (the times of recordings without a clock).

    Returns
    -------
    iterator of Ping
        All the pings, the first one included.

    Raises
    ------
    InputError
        ``"<argument>: <message>"`` when the input holds no ping.
    """
    from sonarmap.io import read_pings

    first, pings = first_ping(read_pings([str(p) for p in inputs], geometry=geometry, **(clock or {})),
                              input_name(inputs, argument), message)
    check_clock_used(first, clock)
    return pings


def check_clock_used(first: Any, clock: dict[str, Any] | None) -> None:
    """Warn (one line) when ``--start-time`` / ``--ping-rate`` were given for a recording that has
    its own clock, where they change nothing."""
    if not clock:
        return
    from sonarmap.io.oculus import CLOCKLESS_TIME_SOURCES

    if first.meta.get("time_source") not in CLOCKLESS_TIME_SOURCES:
        import warnings

        from sonarmap.errors import SonarmapWarning

        warnings.warn(f"{first.source}: has its own ping times; --start-time / --ping-rate ignored "
                      "(they set the times of recordings without a clock, such as Oculus network captures)",
                      SonarmapWarning, stacklevel=2)


#: Line width of a console that is not a terminal (a pipe or a file): wide enough that no line
#: of a summary or table is wrapped or cut (rich assumes 80 columns there).
PIPE_WIDTH = 10_000


def _console(*, stderr: bool) -> Any:
    """A rich console whose long lines are not broken: text is not wrapped (``soft_wrap``), and on
    a pipe or file (without ``COLUMNS`` set) the width is :data:`PIPE_WIDTH`, so a table keeps its
    rows on one line each and never shortens a value with an ellipsis."""
    import os

    from rich.console import Console

    c = Console(stderr=stderr, highlight=False, soft_wrap=True)
    if not c.is_terminal and not os.environ.get("COLUMNS"):
        c.width = PIPE_WIDTH
    return c


def console() -> Any:
    """A rich console on stdout (results: ``info``'s table)."""
    return _console(stderr=False)


def err_console() -> Any:
    """A rich console on stderr (progress bars, status and summaries)."""
    return _console(stderr=True)


def example(*lines: str) -> str:
    """The ``Example:`` epilog of a command's ``--help`` (one command line per argument).

    Parameters
    ----------
    *lines : str
        Command lines, without the leading ``sonarmap``.

    Returns
    -------
    str
        Text for ``app.command(epilog=...)``.

    Examples
    --------
    >>> example("ranges pings/ -o ranges.csv")
    'Example:  sonarmap ranges pings/ -o ranges.csv'
    """
    return "\n\n".join(f"Example:  sonarmap {line}" for line in lines)


def check_choice(value: str, choices: tuple[str, ...] | list[str], option: str) -> str:
    """``value`` if it is one of ``choices``, else a usage error (exit 2) naming them.

    Parameters
    ----------
    value : str
        The option's value.
    choices : sequence of str
        The accepted values.
    option : str
        The option's name for the message, e.g. ``"--method"``.

    Returns
    -------
    str
        ``value``.

    Raises
    ------
    typer.BadParameter
        If ``value`` is not in ``choices``.
    """
    if value not in choices:
        raise typer.BadParameter(f"{value!r} is not one of {', '.join(choices)}", param_hint=option)
    return value


def load_geometry_option(value: str | Path | None) -> Any:
    """Resolve ``--sonar`` to a SonarGeometry (or None).

    A value that names neither a preset nor an existing file is a usage error (exit 2) listing the
    presets; an existing file that is not a valid geometry JSON is a processing error (exit 1).

    Parameters
    ----------
    value : str or Path, optional
        A preset name or a geometry JSON path.

    Returns
    -------
    SonarGeometry or None

    Raises
    ------
    typer.BadParameter
        If ``value`` is neither a preset nor an existing path.
    """
    if value is None:
        return None
    from sonarmap.geometry import as_geometry, preset_names

    names = preset_names()
    if str(value) not in names and not Path(value).exists():
        raise typer.BadParameter(
            f"{str(value)!r} is neither a sonar preset nor a geometry JSON file; presets: {', '.join(names)}",
            param_hint="--sonar",
        )
    geometry = as_geometry(value)
    if str(value) not in names:
        _warn_if_background_calibration(Path(value))
    return geometry


def _warn_if_background_calibration(path: Path) -> None:
    """One warning when the ``--sonar`` file is the calibration of a recording that is normalised
    by its background level: ``--sonar`` takes its geometry only, ``--calibration`` applies it."""
    import json
    import warnings

    from sonarmap.errors import SonarmapWarning

    try:
        cal = json.loads(path.read_text(encoding="utf-8")).get("calibration")
    except (OSError, ValueError, AttributeError):
        return
    if isinstance(cal, dict) and cal.get("kind") == "normalised":
        warnings.warn(f"{path}: --sonar takes only the geometry of this calibration; give it with --calibration "
                      f"{path} to normalise the pings by its background level", SonarmapWarning, stacklevel=3)


def load_calibration(path: Path | None) -> tuple[Any, tuple[str, ...] | None]:
    """The recording background and model families of a ``sonarmap calibrate`` output.

    ``(None, None)`` without a path.  The calibration of a thresholded recording is its geometry
    (given with ``--sonar``) and has no background level: it is refused here.
    """
    if path is None:
        return None, None
    import json

    from sonarmap.errors import InputError
    from sonarmap.preprocess.normalise import RecordingBackground

    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"{path}: cannot read calibration ({exc.strerror or exc})") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not a JSON calibration ({exc})") from None
    cal = d.get("calibration") if isinstance(d, dict) else None
    if not isinstance(cal, dict) or "background_level" not in cal:
        raise InputError(f"{path}: no calibration.background_level table (write it with `sonarmap calibrate`)")
    try:
        rec = RecordingBackground.from_dict(cal["background_level"], name="calibration.background_level")
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    rec = dataclasses.replace(rec, source=str(path))
    if rec.thresholded:
        raise InputError(f"{path}: the calibration of a thresholded recording (DIDSON) is its geometry and has no "
                         f"background level to apply: give it with --sonar {path}, not --calibration")
    model = cal.get("model") or {}
    fams = model.get("families") if isinstance(model, dict) else None
    if fams is not None and (not isinstance(fams, list) or len(fams) < 2 or not all(isinstance(f, str) for f in fams)):
        raise InputError(f"{path}: calibration.model.families must be a list of at least two family names")
    return rec, (tuple(fams) if fams else None)


def apply_calibration(config: Any, path: Path | None) -> tuple[Any, Any]:
    """``(PipelineConfig, RecordingBackground or None)`` for ``--calibration``: the recording's
    background level for ``process_ping(..., background=)``, and ``config`` with the intensity
    model families that calibration chose (unchanged without a path or without a model)."""
    rec, families = load_calibration(path)
    if families is not None and config.fit.families != families:
        config = config.replace(families=families)  # the recording's model (chosen by calibrate)
    return config, rec


def output_name(path: str | Path) -> str:
    """``path`` for messages: ``"stdout"`` for ``-o -``."""
    return "stdout" if str(path) == STDOUT else str(path)


@contextmanager
def open_output(path: str | Path, *, newline: str | None = None) -> Iterator[IO[str]]:
    """A UTF-8 text output: standard output for ``-`` (:data:`STDOUT`), else the file, written atomically.

    Parameters
    ----------
    path : str or Path
        ``-`` or a file path (replaced only when the block completes without an error).
    newline : str, optional
        As for :func:`open` (``""`` for the ``csv`` module).

    Examples
    --------
    >>> with open_output("-") as fh:            # doctest: +SKIP
    ...     print("x,y", file=fh)
    """
    if str(path) == STDOUT:
        import sys

        out = sys.stdout
        try:
            yield out
        finally:
            out.flush()
        return
    from sonarmap._atomic import atomic_open

    with atomic_open(path, "w", newline=newline, encoding="utf-8") as fh:
        yield fh


def stop_progress(progress: Any, *, failed: bool) -> None:
    """Stop a rich ``Progress``; after a failure remove it instead of printing it, so that the
    error is the only line: erased on a terminal, nothing at all (not even an empty line) on a
    pipe or file."""
    if failed:
        progress.live.transient = True  # a terminal: erase the bar
        if not progress.console.is_terminal:
            progress.console.quiet = True  # a pipe or file: print nothing at all
    progress.stop()


class PingProgress:
    """A progress bar over pings on stderr (rich), with optional per-ping lines.

    Nothing is drawn before :meth:`start` or with ``quiet``.  On a terminal the bar is live; on a
    pipe or file rich prints it once, completed, when the block ends.  When the block ends with an
    error the bar is dropped (transient), so the error stays the only line.

    Parameters
    ----------
    description : str
        Label at the left of the bar (the command name).
    total : int, optional
        Number of pings, if known (else the bar counts up).
    quiet : bool
        Draw nothing and print no per-ping line.
    verbose : bool
        :meth:`log` prints its lines (above the bar).
    compiles : bool
        The pings run the per-ping pipeline: on a cold numba cache :meth:`start` first prints
        :func:`first_run_notice` and compiles the pipeline's kernels with helper processes
        (:func:`sonarmap._precompile.compile_with_helpers`).
    """

    def __init__(self, description: str, total: int | None = None, *, quiet: bool = False,
                 verbose: bool = False, compiles: bool = False) -> None:
        self.description = description
        self.compiles = compiles
        self.total = total
        self.quiet = quiet
        self.verbose = verbose and not quiet
        self.done = 0
        self._progress: Any = None
        self._task: Any = None
        self._t0 = 0.0
        self._compiled = False

    def start(self) -> PingProgress:
        """Start drawing the bar (call after the first ping was read, so input errors come first)."""
        import time

        self._t0 = time.perf_counter()
        if self._progress is not None:
            return self
        if self.compiles and not self._compiled:
            # on a cold numba cache: say so, and compile in helper processes too
            self._compiled = True
            compile_on_first_run(self.quiet)
            self._t0 = time.perf_counter()
        if self.quiet:
            return self
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self._progress = Progress(
            TextColumn(self.description), BarColumn(), MofNCompleteColumn(), TextColumn("pings"),
            TimeElapsedColumn(), console=err_console(), transient=False,
        )
        self._progress.start()
        self._task = self._progress.add_task(self.description, total=self.total)
        return self

    def advance(self, n: int = 1) -> None:
        """Count ``n`` more pings done."""
        self.done += n
        if self._progress is not None:
            self._progress.advance(self._task, n)

    def log(self, text: str) -> None:
        """Print one line on stderr with ``verbose`` (above the bar)."""
        if not self.verbose:
            return
        if self._progress is not None:
            self._progress.console.print(text, markup=False, highlight=False, soft_wrap=True)
        else:
            err_console().print(text, markup=False, highlight=False, soft_wrap=True)

    @property
    def seconds(self) -> float:
        """Seconds since :meth:`start`."""
        import time

        return time.perf_counter() - self._t0 if self._t0 else 0.0

    def stop(self, *, failed: bool = False) -> None:
        """Stop the bar; with ``failed`` remove it instead of printing it completed."""
        if self._progress is None:
            return
        if not failed and self._task is not None and self.total is None:
            self._progress.update(self._task, total=self.done)
        stop_progress(self._progress, failed=failed)
        self._progress = None

    def __enter__(self) -> PingProgress:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.stop(failed=exc_type is not None)
        if exc_type is None and self.verbose:
            self.log(f"{self.description}: {counted(self.done, 'ping')} in {self.seconds:.2f} s")


def ping_progress(description: str, total: int | None = None, *, quiet: bool = False,
                  verbose: bool = False, compiles: bool = False) -> PingProgress:
    """A :class:`PingProgress` (use as a context manager; call ``start()`` after the first ping).

    Examples
    --------
    >>> with ping_progress("ranges", 3, quiet=True) as bar:
    ...     _ = bar.start()
    ...     for _ in range(3):
    ...         bar.advance()
    >>> bar.done
    3
    """
    return PingProgress(description, total, quiet=quiet, verbose=verbose, compiles=compiles)


def compile_on_first_run(quiet: bool = False) -> None:
    """On a cold numba cache, :func:`first_run_notice` and then
    :func:`sonarmap._precompile.compile_with_helpers` - with a transient bar of the kernels taken
    when the notice was printed (a terminal, not ``quiet``); on a warm cache nothing."""
    from sonarmap._precompile import compile_with_helpers

    if not first_run_notice(quiet):
        compile_with_helpers()
        return
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn

    # (the bar advances by the kernels' recorded compile seconds: about linear in time)
    with Progress(TextColumn("compiling kernels"), BarColumn(), TaskProgressColumn(), TimeElapsedColumn(),
                  console=err_console(), transient=True) as bar:
        task = bar.add_task("compiling", total=None)
        compile_with_helpers(progress=lambda taken, total: bar.update(task, completed=taken, total=total))


#: What :func:`first_run_notice` prints.
FIRST_RUN_NOTICE = ("first run on this machine: numba is compiling sonarmap's kernels (about two minutes on 2 cores, "
                    "once; later runs load them from its cache)")


def first_run_notice(quiet: bool = False) -> bool:
    """Print :data:`FIRST_RUN_NOTICE` on stderr when the kernels are not compiled yet
    (:func:`sonarmap.ranges.compiled.kernels_cached`) and stderr is a terminal (a log or pipe gets
    no line it did not ask for); nothing with ``quiet``.  Returns whether it printed."""
    import sys

    if quiet or not sys.stderr.isatty():
        return False
    from sonarmap.ranges.compiled import kernels_cached

    if kernels_cached():
        return False
    err_console().print(f"sonarmap: {FIRST_RUN_NOTICE}", markup=False, highlight=False, soft_wrap=True)
    return True


def input_progress(description: str, inputs: list[Path], *, quiet: bool = False,
                   verbose: bool = False, compiles: bool = False) -> PingProgress:
    """A :func:`ping_progress` over the pings of ``inputs``, sized by :func:`count_pings` (not
    counted with ``quiet``)."""
    return ping_progress(description, None if quiet else count_pings(inputs), quiet=quiet, verbose=verbose,
                         compiles=compiles)


def run_pings(bar: PingProgress, pings: Iterable[Any], work: Callable[[Any, int], str]) -> int:
    """Start ``bar`` and do ``work(ping, index)`` for every ping, one step of the bar each.

    Parameters
    ----------
    bar : PingProgress
        The progress bar (not started yet).
    pings : iterable of Ping
        The pings, in order.
    work : callable
        ``work(ping, index)`` processes one ping and returns its ``--verbose`` line.

    Returns
    -------
    int
        The number of pings done.
    """
    n = 0
    with bar:
        bar.start()
        for ping in pings:
            line = work(ping, n)
            n += 1
            bar.advance()
            bar.log(line)
    return n


def count_pings(inputs: list[Path] | list[str]) -> int | None:
    """Total pings of ``inputs`` from headers only, or None when a reader cannot count cheaply.

    Parameters
    ----------
    inputs : list of Path or str
        Ping files, directories or globs.

    Returns
    -------
    int or None
    """
    try:
        from sonarmap.io import expand_inputs, total_pings

        return total_pings(expand_inputs([str(x) for x in inputs]))
    except Exception:  # noqa: BLE001 - the count only sizes the progress bar
        return None
