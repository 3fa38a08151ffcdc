"""``sonarmap show``: render a ping as a fan (metric axes) to an image file.

A product store (``sonarmap process -o STORE``) is shown too: its stored segmentation when it
has labels (``--keep-labels``), else the raw ping read again from the source file it records
(:func:`sonarmap.survey.product_ping`); ``--image`` picks one.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from sonarmap.cli._common import GEOMETRY_OPTION, load_geometry_option

if TYPE_CHECKING:
    from sonarmap.ping import Ping

__all__ = ["register"]

#: Figure formats matplotlib writes without extra backends.
_FIGURE_FORMATS = ("png", "pdf", "svg", "jpg", "jpeg", "eps", "ps", "tif", "tiff", "webp")


def register(app: typer.Typer) -> None:
    @app.command("show")
    def show(
        ping: Path = typer.Argument(..., help="A ping file (PNG+JSON), recording, or survey / product store."),
        output: Path = typer.Option(..., "--output", "-o", help="Figure to write (.png, .pdf, .svg)."),
        index: int = typer.Option(0, "--index", "-i", min=0, help="Ping index inside a recording or store."),
        sonar: str | None = GEOMETRY_OPTION,
        resolution: float | None = typer.Option(None, "--resolution", help="Fan pixel size in m."),
        polar: bool = typer.Option(False, "--polar", help="Also show the raw polar image."),
        vmax: float | None = typer.Option(None, "--vmax", help="Colour scale maximum (dB with a dB scale)."),
        scale: str = typer.Option("auto", "--scale", help="Colour scale: linear, db (10 log10, 60 dB below "
                                  "the maximum) or auto (dB when the ping spans more than 30 dB between its "
                                  "median and 99.9th percentile, e.g. a Kongsberg water column)."),
        image: str = typer.Option("auto", "--image", help="For a product store: labels, raw or auto "
                                  "(labels if stored, else the raw ping from its source)."),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="Do not print where the figure went."),
    ) -> None:
        """Render PING as a fan image with metric axes (honours the azimuth table).

        Example: sonarmap show survey.zarr -o ping.png -i 3
        """
        from sonarmap.io import read_ping
        from sonarmap.plots import save_figure, show_ping_figure
        from sonarmap.survey import is_product_store, product_ping

        fmt = output.suffix.lower().lstrip(".")
        if fmt not in _FIGURE_FORMATS:
            raise typer.BadParameter(f"must end in one of .{', .'.join(_FIGURE_FORMATS)} (got {output.name!r})",
                                     param_hint="--output")
        if scale not in ("auto", "linear", "db"):
            raise typer.BadParameter(f"must be auto, linear or db (got {scale!r})", param_hint="--scale")
        if image not in ("auto", "labels", "raw"):
            raise typer.BadParameter(f"must be auto, labels or raw (got {image!r})", param_hint="--image")
        _check_number_options(resolution, vmax)
        geom = load_geometry_option(sonar)
        if is_product_store(ping):
            if geom is not None:
                raise typer.BadParameter("a product store records its geometry; drop --sonar", param_hint="--sonar")
            p = product_ping(ping, index, image=image)
        else:
            if image == "labels":
                raise typer.BadParameter(f"labels are stored only in a product store (sonarmap process --keep-labels); "
                                         f"{ping} is a recording", param_hint="--image")
            p = read_ping(ping, geometry=geom, index=index)
        if resolution is not None:
            _check_resolution(p, resolution)
        fig = show_ping_figure(p, resolution_m=resolution, polar=polar, vmax=vmax, scale=scale)
        save_figure(fig, output)
        if not quiet:
            typer.echo(f"wrote {output}", err=True)


def _check_number_options(resolution: float | None, vmax: float | None) -> None:
    """Usage errors: a ``--resolution`` that is not a positive number, a ``--vmax`` that is not finite."""
    import math

    if resolution is not None and not (math.isfinite(resolution) and resolution > 0):
        raise typer.BadParameter(f"must be a positive number of metres (got {resolution:g})",
                                 param_hint="--resolution")
    if vmax is not None and not math.isfinite(vmax):
        raise typer.BadParameter(f"must be a finite number (got {vmax:g})", param_hint="--vmax")


def _check_resolution(ping: Ping, resolution: float) -> None:
    """A usage error when ``--resolution`` would give ``ping`` a fan too large to render."""
    from sonarmap.errors import InputError
    from sonarmap.fan import check_fan_resolution

    try:
        check_fan_resolution(ping.geometry, resolution)
    except InputError as exc:
        raise typer.BadParameter(str(exc).removeprefix("resolution_m: "), param_hint="--resolution") from None
