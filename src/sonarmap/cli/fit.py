"""``sonarmap fit PING... -o params.csv``: per-ping mixture fits (eq. 19-21)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from sonarmap._text import counted
from sonarmap.cli._common import (
    PING_RATE_OPTION, START_TIME_OPTION, clock_options,
    GEOMETRY_OPTION, OUTPUT_OPTION, PINGS_ARGUMENT, QUIET_OPTION, VERBOSE_OPTION, check_choice, err_console,
    example, input_progress, load_geometry_option, open_output, output_name, read_input_pings,
)

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from sonarmap.ping import Ping
    from sonarmap.preprocess.pipeline import PreprocessConfig
    from sonarmap.stats.mixture import MixtureFit


def register(app: typer.Typer) -> None:
    """Add the ``fit`` command to ``app``."""

    @app.command("fit", epilog=example("fit pings/ -o fits.csv -m em", "fit recording.aris -o - -q"))
    def fit_cmd(
        pings: list[Path] = PINGS_ARGUMENT,
        output: Path = OUTPUT_OPTION,
        sonar: str | None = GEOMETRY_OPTION,
        start_time: str | None = START_TIME_OPTION,
        ping_rate: float | None = PING_RATE_OPTION,
        method: str = typer.Option("lsq", "--method", "-m", help="lsq (paper) or em."),
        families: str = typer.Option("exponential,rayleigh", "--families",
                                     help="Comma-separated families after the zero spike."),
        binning: str = typer.Option("round", "--binning", help="Histogram binning: round or floor."),
        recipe: str | None = typer.Option(
            None, "--recipe",
            help="Pre-process with a named recipe (e.g. paper-table1) the images that are not normalised: "
            "thresholded ones (DIDSON), or every image with --no-normalise."),
        normalise: bool = typer.Option(
            True, "--normalise/--no-normalise",
            help="Normalise images without a zero spike (ARIS, Oculus) by their background level first, "
            "as the pipeline does; thresholded images (DIDSON) are fitted as they are."),
        quiet: bool = QUIET_OPTION,
        verbose: bool = VERBOSE_OPTION,
    ) -> None:
        """Fit the zero-spike mixture to each ping's histogram; write ping, family, weights, scales, kld, flags, gates.

        The ping column is the file name, with the ping's place in a recording after # (sample.aris#3,
        em.all#head2004/ping59681).  The gates column lists the fit gates the ping fails (a ping
        failing one yields no returns in the pipeline).  Give -o - to write the CSV to stdout; a
        file is replaced atomically.
        """
        import csv

        from sonarmap.ping import source_name
        from sonarmap.stats.mixture import fit_mixture

        check_choice(method, ("lsq", "em"), "--method")
        check_choice(binning, ("round", "floor"), "--binning")
        fams = _family_names(families)
        cfg = None if recipe is None else _recipe_config(recipe)
        clock = clock_options(start_time, ping_rate)
        ping_iter = read_input_pings(pings, load_geometry_option(sonar), clock=clock)  # before the bar
        bar = input_progress("fit", pings, quiet=quiet, verbose=verbose)
        with open_output(output, newline="") as fh, bar:
            bar.start()
            w = csv.writer(fh)
            w.writerow(["ping", "family", "weights", "scales", "kld", "flags", "gates"])
            n = n_normalised = 0
            for ping in ping_iter:
                img, was_normalised = _image_to_fit(ping, normalise=normalise, recipe_config=cfg)
                f = fit_mixture(img, families=fams, method=method, binning=binning)  # type: ignore[arg-type]
                w.writerow(_fit_row(f, source_name(ping.source) or n))
                n += 1
                n_normalised += was_normalised
                bar.advance()
                bar.log(f"{ping.source}: KLD {f.kld:.3g}" + (f" ({';'.join(sorted(f.flags))})" if f.flags else ""))
        if cfg is not None and n_normalised:
            _warn_recipe_not_applied(recipe, n_normalised, n)
        if not quiet:
            err_console().print(f"fitted {counted(n, 'ping')} -> {output_name(output)}", markup=False)


def _family_names(families: str) -> tuple[str, ...]:
    """The ``--families`` names, or a usage error for an unknown name or an empty list."""
    from sonarmap.stats.components import FAMILIES

    fams = tuple(f.strip() for f in families.split(",") if f.strip())
    for f in fams:
        if f.lower() not in FAMILIES:
            raise typer.BadParameter(f"unknown family {f!r}; choose from {', '.join(sorted(FAMILIES))}",
                                     param_hint="--families")
    if not fams:
        raise typer.BadParameter("give at least one family", param_hint="--families")
    return fams


def _recipe_config(name: str) -> PreprocessConfig:
    """The pre-processing config of the ``--recipe`` ``name`` (an unknown name is a usage error)."""
    from sonarmap.preprocess.pipeline import RECIPES
    from sonarmap.preprocess.pipeline import recipe as get_recipe

    return get_recipe(check_choice(name, RECIPES, "--recipe"))


def _warn_recipe_not_applied(recipe: str | None, n_normalised: int, n: int) -> None:
    """One warning line: ``--recipe`` was not applied to the ``n_normalised`` of ``n`` pings that
    were fitted normalised instead."""
    import warnings

    from sonarmap.errors import SonarmapWarning

    warnings.warn(f"--recipe {recipe} was not applied to {n_normalised} of {counted(n, 'ping')}: their images "
                  "have no zero spike and were fitted normalised by their background level (give --no-normalise "
                  "to fit the recipe's image)", SonarmapWarning, stacklevel=2)


def _image_to_fit(ping: Ping, *, normalise: bool,
                  recipe_config: PreprocessConfig | None) -> tuple[NDArray[Any], bool]:
    """The image whose histogram is fitted, and whether it is the normalised one: normalised by its
    background level (``--normalise`` and not constant), else pre-processed with the ``--recipe``
    config if given, else the ping's image."""
    from sonarmap.preprocess.normalise import estimate_background

    img = ping.image
    normalised = None
    if normalise and float(img.max()) > float(img.min()):
        normalised = estimate_background(img)[1]
    if normalised is not None:
        return normalised, True
    if recipe_config is not None:
        from sonarmap.preprocess.pipeline import preprocess_image

        img = preprocess_image(img, ping.geometry, recipe_config)
    return img, False


def _fit_row(f: MixtureFit, name: str | int) -> list[str | int]:
    """The CSV row of one ping's fit ``f``: ``name``, family, weights, scales, kld, flags, gates."""
    from sonarmap.stats.gates import fit_gates

    return [
        name,
        "+".join(f.component_names),
        ";".join(f"{v:.6g}" for v in f.weights),
        ";".join("" if s != s else f"{s:.6g}" for s in f.scales),
        f"{f.kld:.6g}",
        ";".join(sorted(f.flags)),
        ";".join(sorted(fit_gates(f))),
    ]
