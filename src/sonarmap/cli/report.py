"""``sonarmap report``: a self-contained HTML report of a processed survey."""

from __future__ import annotations

from pathlib import Path

import typer

from sonarmap.cli._common import console

__all__ = ["register", "report_command"]


def report_command(
    store: Path = typer.Argument(..., help="Survey store written by `sonarmap process`."),
    output: Path = typer.Option(..., "--output", "-o", help="HTML file to write."),
    examples: int = typer.Option(3, "--examples", min=0, help="Example pings drawn as fans."),
    title: str | None = typer.Option(None, "--title", help="Page title."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing report."),
) -> None:
    """Write an HTML report (summary, time series, ROC, flagged pings, fans, map) - one file."""
    from sonarmap.report import ReportConfig, build_report

    path = build_report(store, output, config=ReportConfig(n_examples=examples, title=title),
                        overwrite=overwrite)
    console().print(f"report: {path}", soft_wrap=True, markup=False)


def register(app: typer.Typer) -> None:
    """Add ``report`` to the CLI."""
    app.command("report")(report_command)
