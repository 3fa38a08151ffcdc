"""``sonarmap preprocess``: deconvolution, taper and radial gain of pings (paper eq. 2-7)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from sonarmap._text import counted
from sonarmap.cli._common import (
    PING_RATE_OPTION, START_TIME_OPTION, clock_options,
    GEOMETRY_OPTION, OUTPUT_DIR_OPTION, PINGS_ARGUMENT, QUIET_OPTION, VERBOSE_OPTION, check_choice, err_console,
    example, input_progress, load_geometry_option, read_input_pings, run_pings,
)

__all__ = ["register"]


def register(app: typer.Typer) -> None:
    """Add the ``preprocess`` command to ``app``."""

    @app.command("preprocess", epilog=example("preprocess pings/ -o clean/ --recipe paper-table1 --figure fig1.png"))
    def preprocess_cmd(
        pings: list[Path] = PINGS_ARGUMENT,
        output: Path = OUTPUT_DIR_OPTION,
        recipe_name: str = typer.Option(
            "default", "--recipe", "-r",
            help="default | paper-table1 | paper-background (ignored with --config).",
        ),
        config: Path | None = typer.Option(
            None, "--config", "-c", help="PreprocessConfig as .toml or .json (overrides --recipe)."
        ),
        figure: Path | None = typer.Option(
            None, "--figure", help="Write a before/after fan figure of the first ping (Fig. 1 style)."
        ),
        sonar: str | None = GEOMETRY_OPTION,
        start_time: str | None = START_TIME_OPTION,
        ping_rate: float | None = PING_RATE_OPTION,
        quiet: bool = QUIET_OPTION,
        verbose: bool = VERBOSE_OPTION,
    ) -> None:
        """Pre-process PINGS and write 16-bit PNG + JSON pings (parameters recorded) to OUTPUT.

        The output directory is created if needed; its files are replaced atomically.  When a
        pre-processed ping exceeds 1 (e.g. after the taper division), the PNG holds the image
        divided by intensity_scale and the JSON records intensity_scale.  The files are named by
        the ping's time, so two pings of one time (the heads of a dual-head sonar) are an error.
        """
        from sonarmap.preprocess.pipeline import RECIPES, load_config, recipe

        if config is None:
            check_choice(recipe_name, RECIPES, "--recipe")
        if figure is not None and figure.suffix.lower() not in (".png", ".pdf", ".svg"):
            raise typer.BadParameter(f"{figure}: expected a .png, .pdf or .svg file", param_hint="--figure")
        cfg = load_config(config) if config is not None else recipe(recipe_name)
        clock = clock_options(start_time, ping_rate)
        ping_iter = read_input_pings(pings, load_geometry_option(sonar), clock=clock)  # before the bar
        bar = input_progress("preprocess", pings, quiet=quiet, verbose=verbose)
        written: dict[str, str] = {}  # file stem -> the ping written under it
        n = run_pings(bar, ping_iter, lambda ping, i: _one(ping, i, cfg, output, figure, written))
        if not quiet:
            err_console().print(f"preprocessed {counted(n, 'ping')} with recipe '{cfg.name}' -> {output}", markup=False)


def _one(ping: Any, n: int, cfg: Any, output: Path, figure: Path | None, written: dict[str, str]) -> str:
    """Pre-process one ping and write it into ``output`` (and, for the first, the figure); returns
    the ``--verbose`` line.  ``written`` maps the file stems of this run to their pings: a second
    ping of the same time stamp (the other head of a dual-head sonar) is an error, not a file that
    silently replaces the first."""
    from sonarmap.errors import InputError
    from sonarmap.io.pngjson import write_png_ping
    from sonarmap.preprocess.pipeline import preprocess

    stem = Path(ping.source).stem.removesuffix("_raw") if ping.source else None
    if not stem or not stem.isdigit():
        stem = f"{ping.time_ns // 1000}" if ping.time_ns else f"ping{n:06d}"
    if stem in written:
        raise InputError(f"{ping.source}: has the time stamp of {written[stem]}; both would be written as "
                         f"{output / stem}_raw.png (a folder of PNG+JSON pings holds one ping per time: "
                         "the heads of a dual-head sonar, pinging together, do not fit in one)")
    written[stem] = ping.source
    out = preprocess(ping, cfg)
    extra = {"preprocess": out.meta["preprocess"]}
    peak = float(out.image.max())
    to_write = out
    if peak > 1.0:  # PNG holds [0, 1]: store image / scale and record the scale
        extra["intensity_scale"] = peak
        to_write = out.replace(image=out.image / peak)
    write_png_ping(to_write, output, stem=stem, bit_depth=16, extra=extra)
    if figure is not None and n == 0:
        from sonarmap.plots import fan_comparison, save_figure

        save_figure(fan_comparison(ping, out), figure)
    return f"{ping.source} -> {output}"
