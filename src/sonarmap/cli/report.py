"""``sonarmap report``: a self-contained HTML report of a processed survey."""

from __future__ import annotations

from pathlib import Path

import typer

from sonarmap.cli._common import err_console, example, refuse_stdout

__all__ = ["register", "report_command"]


def report_command(
    store: Path = typer.Argument(..., help="Survey store written by sonarmap process."),
    output: Path = typer.Option(..., "--output", "-o", help="HTML file to write.", callback=refuse_stdout),
    examples: int = typer.Option(3, "--examples", min=0, help="Example pings drawn as fans."),
    title: str | None = typer.Option(None, "--title", help="Page title."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing report."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Do not print the report's location."),
) -> None:
    """Write an HTML report (summary, time series, ROC, flagged pings, fans, map) - one file.

    An existing report is replaced only with --overwrite.
    """
    from sonarmap.report import ReportConfig, build_report

    path = build_report(store, output, config=ReportConfig(n_examples=examples, title=title),
                        overwrite=overwrite)
    if not quiet:
        err_console().print(f"report: {path}", soft_wrap=True, markup=False)


def register(app: typer.Typer) -> None:
    """Add ``report`` to the CLI."""
    app.command("report", epilog=example("report survey.zarr -o report.html --examples 5"))(report_command)
