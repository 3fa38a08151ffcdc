"""``sonarmap preprocess``: deconvolution, taper and radial gain of pings (paper eq. 2-7)."""

from __future__ import annotations

from pathlib import Path

import typer

from sonarmap.cli._common import GEOMETRY_OPTION, load_geometry_option

__all__ = ["register"]


def register(app: typer.Typer) -> None:
    @app.command("preprocess")
    def preprocess_cmd(
        pings: list[Path] = typer.Argument(..., help="Ping files, directories or globs."),
        output: Path = typer.Option(..., "--output", "-o", help="Output directory."),
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
    ) -> None:
        """Pre-process PINGS and write 16-bit PNG + JSON pings (parameters recorded) to OUTPUT.

        Outputs are written atomically.  When a pre-processed ping exceeds 1 (e.g. after the taper
        division), the PNG holds ``image / intensity_scale`` and the JSON records
        ``intensity_scale``.
        """
        from sonarmap.io import read_pings
        from sonarmap.io.pngjson import write_png_ping
        from sonarmap.preprocess.pipeline import load_config, preprocess, recipe

        cfg = load_config(config) if config is not None else recipe(recipe_name)
        geom = load_geometry_option(sonar)
        n = 0
        for ping in read_pings([str(p) for p in pings], geometry=geom):
            out = preprocess(ping, cfg)
            stem = Path(ping.source).stem.removesuffix("_raw") if ping.source else None
            if not stem or not stem.isdigit():
                stem = f"{ping.time_ns // 1000}" if ping.time_ns else f"ping{n:06d}"
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
            n += 1
        typer.echo(f"preprocessed {n} ping(s) with recipe '{cfg.name}' -> {output}")
