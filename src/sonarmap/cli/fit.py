"""``sonarmap fit PING... -o params.csv``: per-ping mixture fits (eq. 19-21)."""

from __future__ import annotations

from pathlib import Path

import typer

from sonarmap.cli._common import GEOMETRY_OPTION, OUTPUT_OPTION, load_geometry_option


def register(app: typer.Typer) -> None:
    """Add the ``fit`` command to ``app``."""

    @app.command("fit")
    def fit_cmd(
        pings: list[Path] = typer.Argument(..., help="Ping files, directories or globs."),
        output: Path = OUTPUT_OPTION,
        sonar: str | None = GEOMETRY_OPTION,
        method: str = typer.Option("lsq", "--method", "-m", help="lsq (paper) or em."),
        families: str = typer.Option("exponential,rayleigh", help="Comma-separated families after the zero spike."),
        binning: str = typer.Option("round", help="Histogram binning: round or floor."),
        recipe: str | None = typer.Option(None, help="Pre-process first with a named recipe (e.g. paper-table1)."),
        normalise: bool = typer.Option(
            True, "--normalise/--no-normalise",
            help="Normalise images without a zero spike (ARIS, Oculus) by their background level first, "
            "as the pipeline does; thresholded images (DIDSON) are fitted as they are."),
    ) -> None:
        """Fit the zero-spike mixture to each ping's histogram; write ping, family, weights, scales, kld, flags, gates.

        ``gates`` lists the fit gates the ping fails (a ping failing one yields no returns in the
        pipeline).
        """
        import csv

        from sonarmap._atomic import atomic_open
        from sonarmap.io import read_pings
        from sonarmap.stats.mixture import fit_mixture

        cfg = None
        if recipe is not None:
            from sonarmap.preprocess.pipeline import recipe as get_recipe

            cfg = get_recipe(recipe)
        geom = load_geometry_option(sonar)
        fams = tuple(f.strip() for f in families.split(",") if f.strip())
        with atomic_open(output, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["ping", "family", "weights", "scales", "kld", "flags", "gates"])
            n = 0
            from sonarmap.preprocess.normalise import estimate_background
            from sonarmap.stats.gates import fit_gates

            for ping in read_pings([str(p) for p in pings], geometry=geom):
                img = ping.image
                normalised = None
                if normalise and float(img.max()) > float(img.min()):
                    normalised = estimate_background(img)[1]
                if normalised is not None:
                    img = normalised
                elif cfg is not None:
                    from sonarmap.preprocess.pipeline import preprocess_image

                    img = preprocess_image(img, ping.geometry, cfg)
                f = fit_mixture(img, families=fams, method=method, binning=binning)  # type: ignore[arg-type]
                w.writerow([
                    Path(ping.source).name or n,
                    "+".join(f.component_names),
                    ";".join(f"{v:.6g}" for v in f.weights),
                    ";".join("" if s != s else f"{s:.6g}" for s in f.scales),
                    f"{f.kld:.6g}",
                    ";".join(sorted(f.flags)),
                    ";".join(sorted(fit_gates(f))),
                ])
                n += 1
        typer.echo(f"fitted {n} pings -> {output}", err=True)
