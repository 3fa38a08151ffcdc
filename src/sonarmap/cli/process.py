"""``sonarmap process``: a whole survey into a resumable zarr store of per-ping products."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from sonarmap._text import counted
from sonarmap.cli._common import (
    CALIBRATION_OPTION, GEOMETRY_OPTION, err_console, example, first_run_notice, refuse_stdout, stop_progress,
)

__all__ = ["register", "process_command", "survey_progress"]


class survey_progress:  # noqa: N801 - used as a context manager, reads like a function
    """Rich progress bar (rate, ETA) on stderr, fed by ``process_survey(progress=...)``.

    Disabled (a no-op callback) when ``quiet`` is true.
    """

    def __init__(self, description: str = "processing", *, quiet: bool = False) -> None:
        self.quiet = quiet
        self.description = description
        self._progress: Any = None
        self._task: Any = None

    def __enter__(self) -> survey_progress:
        if not self.quiet:
            first_run_notice()
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            class _Rate(TextColumn):
                def __init__(self) -> None:
                    super().__init__("")

                def render(self, task: Any) -> Any:  # noqa: D102
                    from rich.text import Text

                    speed = task.finished_speed or task.speed
                    return Text("" if speed is None else f"{speed:,.0f} pings/s", style="cyan")

            self._progress = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                _Rate(),
                TimeElapsedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                console=err_console(),
                transient=False,
            )
            self._progress.start()
        return self

    def __call__(self, done: int, total: int) -> None:
        if self._progress is None:
            return
        if self._task is None:
            # Pings done by an earlier run count as completed but not toward the rate.
            self._task = self._progress.add_task(self.description, total=total, completed=done)
            return
        self._progress.update(self._task, completed=done)

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if self._progress is not None:
            stop_progress(self._progress, failed=exc_type is not None)
            self._progress = None


def _with_calibration(config: Path | None, calibration: Path | None) -> tuple[Any, Any]:
    """``(config, background)`` for :func:`process_survey`: the ``--config`` path as given and no
    background without ``--calibration``; with it, the configuration with the model families the
    calibration chose and the recording's background level."""
    if calibration is None:
        return config, None
    from sonarmap.cli._common import apply_calibration
    from sonarmap.pipeline import PipelineConfig

    return apply_calibration(PipelineConfig.from_toml(config) if config is not None else PipelineConfig(), calibration)


def process_command(
    inputs: list[Path] = typer.Argument(..., help="Ping files, directories (of PNG+JSON pings or of recordings), or globs."),
    output: Path = typer.Option(..., "--output", "-o", help="Output survey store (e.g. survey.zarr).",
                                callback=refuse_stdout),
    config: Path | None = typer.Option(
        None, "--config", "-c", help="Pipeline configuration (TOML); validated, recorded in the output."
    ),
    workers: int | None = typer.Option(
        None, "--workers", "-j", min=0, help="Local worker processes (default: CPU count; 0: in-process)."
    ),
    scheduler: str | None = typer.Option(
        None, "--scheduler", help="dask.distributed scheduler address (tcp://HOST:PORT); chunks run there."
    ),
    chunk_size: int = typer.Option(256, "--chunk-size", "-k", min=1, help="Pings per task and zarr chunk."),
    keep_labels: bool = typer.Option(False, "--keep-labels", help="Also store per-pixel labels (large)."),
    poses: Path | None = typer.Option(
        None, "--poses", help="Vehicle poses CSV: register the ranges into a point cloud."
    ),
    points: Path | None = typer.Option(
        None, "--points", help="Point-cloud file written with --poses (.ply/.las; default: the output path with suffix .ply)."
    ),
    extrinsics: Path | None = typer.Option(
        None, "--extrinsics", help="Sensor mounting JSON used with --poses (default: sensor = body)."
    ),
    sonar: str | None = GEOMETRY_OPTION,
    calibration: Path | None = CALIBRATION_OPTION,
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing store of other inputs or configuration."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and no summary."),
    strict: bool = typer.Option(False, "--strict", help="Exit 1 when the model could not explain some ping (a flagged fit)."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Also print the total time on stderr."),
) -> None:
    """Process a survey: read -> pre-process -> fit -> segment -> ranges (-> points), per chunk.

    Re-running the same command after an interruption resumes where it stopped; the result is
    identical to an uninterrupted run.  A store of another input or configuration is replaced
    only with --overwrite.  The progress bar and the two summary lines are on stderr.
    """
    import time

    from sonarmap.cli._common import load_geometry_option
    from sonarmap.survey import process_survey

    t0 = time.perf_counter()
    load_geometry_option(sonar)  # an unknown preset is a usage error before any work
    run_config, background = _with_calibration(config, calibration)
    if scheduler is not None and workers is not None:
        raise typer.BadParameter("give either --workers or --scheduler, not both", param_hint="--workers")
    if scheduler is not None:
        import distributed  # noqa: F401 - configures its loggers on import; quiet them afterwards

        from sonarmap.cli import quiet_library_loggers

        quiet_library_loggers()
    with survey_progress(f"{output.name}", quiet=quiet) as bar:
        result = process_survey(
            [str(p) for p in inputs], output, config=run_config, workers=workers, scheduler=scheduler,
            chunk_size=chunk_size, keep_labels=keep_labels, poses=poses, points=points, extrinsics=extrinsics,
            geometry=sonar, overwrite=overwrite, progress=bar, background=background,
        )
    if not quiet:
        from sonarmap.cli.ranges import flagged_summary

        err_console().print(result.summary(), soft_wrap=True, markup=False)
        err_console().print(flagged_summary(list(result.gates)), soft_wrap=True, markup=False)
        if verbose:
            err_console().print(f"process: {counted(result.n_pings, 'ping')} in {time.perf_counter() - t0:.2f} s",
                                soft_wrap=True, markup=False)
    if strict:
        from sonarmap.cli.ranges import flagged_any

        if flagged_any(list(result.gates)):
            raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    """Add ``process`` to the CLI."""
    app.command("process", epilog=example("process pings/ -o survey.zarr -j 2",
                                          "process recording.aris -o survey.zarr --poses poses.csv -q"))(process_command)
