"""``sonarmap show``: render a ping as a fan (metric axes) to an image file."""

from __future__ import annotations

from pathlib import Path

import typer

from sonarmap.cli._common import GEOMETRY_OPTION, load_geometry_option

__all__ = ["register"]


def register(app: typer.Typer) -> None:
    @app.command("show")
    def show(
        ping: Path = typer.Argument(..., help="A ping file (PNG+JSON) or recording."),
        output: Path = typer.Option(..., "--output", "-o", help="Figure to write (.png, .pdf, .svg)."),
        index: int = typer.Option(0, "--index", "-i", min=0, help="Ping index inside a recording."),
        sonar: str | None = GEOMETRY_OPTION,
        resolution: float | None = typer.Option(None, "--resolution", help="Fan pixel size in m."),
        polar: bool = typer.Option(False, "--polar", help="Also show the raw polar image."),
        vmax: float | None = typer.Option(None, "--vmax", help="Colour scale maximum."),
    ) -> None:
        """Render PING as a fan image with metric axes (honours the azimuth table)."""
        from sonarmap.io import read_ping
        from sonarmap.plots import save_figure, show_ping_figure

        geom = load_geometry_option(sonar)
        p = read_ping(ping, geometry=geom, index=index)
        fig = show_ping_figure(p, resolution_m=resolution, polar=polar, vmax=vmax)
        save_figure(fig, output)
        typer.echo(f"wrote {output}")
