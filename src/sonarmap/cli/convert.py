"""``sonarmap convert INPUT... -o survey.zarr``: any supported input to a zarr survey (or a ROS bag)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from sonarmap.cli._common import GEOMETRY_OPTION, err_console, load_geometry_option

__all__ = ["register", "convert"]


def _count(paths: list[Path], **kwargs: Any) -> int | None:
    """Total pings of the inputs from headers only (``None`` if a reader cannot tell cheaply)."""
    from sonarmap.io import _is_store_dir, detect_format, format_module, pngjson

    total = 0
    for p in paths:
        fmt = "pngjson" if p.is_dir() and not _is_store_dir(p) else detect_format(p)
        mod = pngjson if fmt == "pngjson" else format_module(fmt)
        try:
            total += int(mod.count_pings(p))
        except Exception:  # noqa: BLE001 - the count only sizes the progress bar
            return None
    return total


def convert(
    inputs: list[Path] = typer.Argument(
        ..., help="Input files or directories: .aris, .ddf, Oculus .raw/.oculus, ROS 1/2 bags, "
        "PNG+JSON ping folders, zarr surveys (detected by content)."
    ),
    output: Path = typer.Option(..., "--output", "-o", help="Output: a .zarr survey store, or a .bag (ROS 1) / --to bag2 directory."),
    sonar: str | None = GEOMETRY_OPTION,
    to: str | None = typer.Option(
        None, "--to", help="Output kind: zarr, bag1 or bag2 (default: bag1 for *.bag, else zarr)."
    ),
    append: bool = typer.Option(False, "--append", help="Append to an existing zarr survey."),
    chunk_pings: int = typer.Option(16, "--chunk-pings", min=1, help="Pings per zarr chunk (and per write)."),
    topic: str | None = typer.Option(None, "--topic", help="ROS topic to read (bags) or write (default /sonar/image)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar on stderr."),
) -> None:
    """Convert sonar recordings into one survey dataset (xarray/zarr, chunked along ping_time)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from sonarmap.errors import InputError
    from sonarmap.io import expand_inputs, read_pings

    kind = to or ("bag1" if output.suffix == ".bag" else "zarr")
    if kind not in ("zarr", "bag1", "bag2"):
        raise InputError(f"--to: choose zarr, bag1 or bag2 (got {kind!r})")
    if append and kind != "zarr":
        raise InputError("--append is only supported for zarr surveys")
    geometry = load_geometry_option(sonar)
    paths = expand_inputs([str(p) for p in inputs])
    read_kwargs: dict[str, Any] = {"topic": topic} if topic else {}
    total = _count(paths) if progress else None
    console = err_console()
    columns = [TextColumn("[bold]converting"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn()]
    with Progress(*columns, console=console, disable=not progress, transient=False) as bar:
        task = bar.add_task("convert", total=total)

        def pings() -> Any:
            for ping in read_pings(paths, geometry=geometry, **read_kwargs):
                yield ping
                bar.advance(task)

        if kind == "zarr":
            from sonarmap.io.dataset import SurveyWriter

            with SurveyWriter(output, mode="a" if append else "w", chunk_pings=chunk_pings) as w:
                n = w.write(pings())
        else:
            from sonarmap.io.rosbag import write_bag

            n = write_bag(pings(), output, version=1 if kind == "bag1" else 2,
                          topic=topic or "/sonar/image")
    typer.echo(f"wrote {n} pings to {output}")


def register(app: typer.Typer) -> None:
    """Add the ``convert`` command to ``app``."""
    app.command("convert")(convert)
