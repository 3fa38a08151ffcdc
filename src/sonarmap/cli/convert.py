"""``sonarmap convert INPUT... -o survey.zarr``: any supported input to a zarr survey (or a ROS bag)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from sonarmap._text import counted
from sonarmap.cli._common import (
    GEOMETRY_OPTION,
    PING_RATE_OPTION,
    QUIET_OPTION,
    START_TIME_OPTION,
    VERBOSE_OPTION,
    check_choice,
    check_clock_used,
    clock_options,
    count_pings,
    first_ping,
    input_name,
    example,
    load_geometry_option,
    ping_progress,
    refuse_stdout,
)

__all__ = ["register", "convert"]


def convert(
    inputs: list[Path] = typer.Argument(
        ..., help="Input files or directories: .aris, .ddf, Oculus .raw/.oculus, ROS 1/2 bags, "
        "PNG+JSON ping folders, zarr surveys (detected by content)."
    ),
    output: Path = typer.Option(..., "--output", "-o", help="Output: a .zarr survey store, or a .bag (ROS 1) / --to bag2 directory.",
                                callback=refuse_stdout),
    sonar: str | None = GEOMETRY_OPTION,
    start_time: str | None = START_TIME_OPTION,
    ping_rate: float | None = PING_RATE_OPTION,
    to: str | None = typer.Option(
        None, "--to", help="Output kind: zarr, bag1 or bag2 (default: bag1 for *.bag, else zarr)."
    ),
    append: bool = typer.Option(False, "--append", help="Append to an existing zarr survey."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output (survey or bag)."),
    chunk_pings: int = typer.Option(16, "--chunk-pings", min=1, help="Pings per zarr chunk (and per write)."),
    topic: str | None = typer.Option(None, "--topic", help="ROS topic to read (bags) or write (default /sonar/image)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar on stderr."),
    quiet: bool = QUIET_OPTION,
    verbose: bool = VERBOSE_OPTION,
) -> None:
    """Convert sonar recordings into one survey dataset (xarray/zarr, chunked along ping_time).

    An existing output is extended with --append (zarr) or replaced with --overwrite; without
    either it is left alone and the command exits 1 before reading anything.
    """

    from sonarmap.io import expand_inputs, read_pings

    if to is not None:
        check_choice(to, ("zarr", "bag1", "bag2"), "--to")
    clock = clock_options(start_time, ping_rate)
    kind = to or ("bag1" if output.suffix == ".bag" else "zarr")
    if append and kind != "zarr":
        raise typer.BadParameter("only zarr surveys can be appended to", param_hint="--append")
    if append and overwrite:
        raise typer.BadParameter("give either --append or --overwrite, not both", param_hint="--overwrite")
    if output.exists() and not (append or overwrite):
        from sonarmap.errors import DataFormatError

        raise DataFormatError("output exists; use --append (zarr), --overwrite or another -o", output)
    no_bar = quiet or not progress
    geometry = load_geometry_option(sonar)
    paths = expand_inputs([str(p) for p in inputs])
    if kind == "zarr":
        _refuse_per_ping_geometry(paths)
    read_kwargs: dict[str, Any] = {"topic": topic} if topic else {}
    ping_iter = read_pings(paths, geometry=geometry, **read_kwargs, **clock)
    first, ping_iter = first_ping(ping_iter, input_name(paths, "INPUTS"))
    check_clock_used(first, clock)  # before the bar: an unreadable input prints only its error
    with ping_progress("convert", None if no_bar else count_pings(paths), quiet=no_bar, verbose=verbose) as bar:
        bar.start()

        def pings() -> Any:
            for ping in ping_iter:
                yield ping
                bar.advance()
                bar.log(f"{ping.source}")

        if kind == "zarr":
            from sonarmap.store import SurveyWriter

            with SurveyWriter(output, mode="a" if append else "w", chunk_pings=chunk_pings) as w:
                n = w.write(pings())
        else:
            from sonarmap.io.rosbag import write_bag

            n = write_bag(pings(), output, version=1 if kind == "bag1" else 2,
                          topic=topic or "/sonar/image")
    if not quiet:  # -q silences the summary too; --no-progress only the bar
        typer.echo(f"wrote {counted(n, 'ping')} to {output}", err=True)


def register(app: typer.Typer) -> None:
    """Add the ``convert`` command to ``app``."""
    app.command("convert", epilog=example("convert recording.aris -o survey.zarr",
                                          "convert survey.zarr -o survey.bag --no-progress"))(convert)


def _refuse_per_ping_geometry(paths: list[Path]) -> None:
    """A zarr survey holds one range window: refuse water column whose window changes every ping."""
    from sonarmap.errors import InputError
    from sonarmap.io import detect_format, is_store_dir

    for p in paths:
        if not is_store_dir(p) and p.is_file() and detect_format(p) in ("kongsberg", "kmall"):
            raise InputError(f"{p}: Kongsberg water column changes its range window with every ping, which a "
                             "zarr survey (one range window) cannot hold yet; convert it to a ROS bag "
                             "(--to bag2) or process it with `sonarmap ranges` / `sonarmap map`")

