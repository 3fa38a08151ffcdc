"""``sonarmap demo``: the whole job on built-in data - simulate, process, map, report."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from sonarmap._text import counted
from sonarmap.cli._common import console, err_console, example, refuse_stdout

__all__ = ["register", "demo_command", "run_demo", "DEMO_CONFIG"]

#: Pipeline configuration of the demo, written to ``<dir>/pipeline.toml`` and passed like
#: ``sonarmap process --config``: the default pipeline (the same one ``sonarmap ranges`` runs), so
#: the file is a starting point for users to edit.  On the 40-ping demo survey it maps the hull
#: with RMS 3.9 range bins and 52 % coverage (``preprocess = "none"``: 5.7 bins, 28 %).
DEMO_CONFIG = """\
# sonarmap pipeline configuration used by `sonarmap demo` (see `sonarmap process --config`).
# Empty tables = the default pipeline. Uncomment an option to change it; every option and its
# meaning: sonarmap.config.PipelineConfig (docs/segmentation.md, "Changing the configuration").
[pipeline]
# normalise = "auto"

[pipeline.fit]
# max_kld = 0.05

[pipeline.classify]
# method = "mrf"
# beta = 2.0

[pipeline.candidates]
# min_component_beams = 16

[pipeline.ranges]
# range_mode = "first"
# edge_fraction = 0.5
"""


def run_demo(
    directory: Path,
    *,
    n_pings: int = 40,
    workers: int | None = None,
    overwrite: bool = False,
    quiet: bool = False,
) -> dict[str, object]:
    """Simulate a short hull survey with poses, process it, register the map and write the report.

    Returns a dict of output paths and numbers (``pings``, ``survey``, ``points``, ``report``,
    ``poses``, ``accuracy`` (:class:`~sonarmap.evaluate.mapping.RegistrationAccuracy`), ``seconds``).
    """
    from sonarmap._atomic import atomic_write_text
    from sonarmap.cli.process import survey_progress
    from sonarmap.errors import DataFormatError
    from sonarmap.evaluate.mapping import registration_accuracy
    from sonarmap.report import ReportConfig, build_report
    from sonarmap.simulate.survey import SurveyConfig, simulate_survey
    from sonarmap.survey import process_survey

    t0 = time.perf_counter()
    d = Path(directory)
    survey_path = d / "survey.zarr"
    report_path = d / "report.html"
    points_path = d / "map.ply"
    if not overwrite:
        clash = [p for p in (d / "pings", survey_path, report_path, points_path) if p.exists()]
        if clash:
            raise DataFormatError(f"demo output exists ({clash[0].name}); use --overwrite or another -o", d)
    elif d.exists():
        import shutil

        for p in (d / "pings", survey_path):
            shutil.rmtree(p, ignore_errors=True)
    status = err_console()
    if not quiet:
        status.print(f"[bold]1/4[/] simulating a {n_pings}-ping DIDSON hull survey ...")
    sim = simulate_survey(SurveyConfig(kind="hull", n_pings=n_pings))
    sim.write(d)
    config_path = d / "pipeline.toml"
    atomic_write_text(config_path, DEMO_CONFIG)
    if not quiet:
        status.print("[bold]2/4[/] processing it (pre-process, mixture fit, segmentation, ranges) ...")
    with survey_progress("survey", quiet=quiet) as bar:
        res = process_survey(
            [d / "pings"], survey_path, config=config_path, workers=workers, chunk_size=max(8, n_pings // 4),
            poses=d / "poses.csv", extrinsics=d / "mount.json", points=points_path,
            overwrite=True, progress=bar,
        )
    if not quiet:
        status.print("[bold]3/4[/] map: ranges registered with the poses -> point cloud")
    from sonarmap.survey import open_products

    xyz = open_products(survey_path)["point_xyz"].values
    acc = registration_accuracy(sim, xyz)
    if not quiet:
        status.print("[bold]4/4[/] writing the HTML report ...")
    build_report(survey_path, report_path, config=ReportConfig(title="sonarmap demo: simulated hull survey"),
                 overwrite=True)
    return {
        "pings": d / "pings",
        "poses": d / "poses.csv",
        "config": config_path,
        "survey": survey_path,
        "points": points_path,
        "report": report_path,
        "n_pings": res.n_pings,
        "n_points": res.n_points,
        "n_flagged": res.n_flagged,
        "accuracy": acc,
        "seconds": time.perf_counter() - t0,
    }


def demo_command(
    output: Path = typer.Option(Path("sonarmap-demo"), "--output", "-o", help="Directory for the demo outputs.",
                                callback=refuse_stdout),
    pings: int = typer.Option(40, "--pings", min=4, help="Pings in the simulated survey."),
    workers: int | None = typer.Option(None, "--workers", "-j", min=0, help="Worker processes (default: CPUs)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the outputs of an earlier demo."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Only print the output locations."),
) -> None:
    """Simulate a short hull survey with poses, process it, build the map and the report.

    Steps and the progress bar go to stderr, the output locations and the map accuracy to stdout.
    Earlier demo outputs in the directory are replaced only with --overwrite.
    """
    out = run_demo(output, n_pings=pings, workers=workers, overwrite=overwrite, quiet=quiet)
    c = console()
    acc = out["accuracy"]
    c.print(f"demo finished in {out['seconds']:.1f} s: {counted(out['n_pings'], 'ping')}, {counted(out['n_flagged'], 'flagged fit')}, "
            f"{counted(out['n_points'], 'map point')}", soft_wrap=True)
    for key, label in (("pings", "simulated pings (PNG+JSON)"), ("poses", "vehicle poses"),
                       ("config", "pipeline configuration"),
                       ("survey", "per-ping products (zarr)"), ("points", "map point cloud (PLY)"),
                       ("report", "HTML report")):
        c.print(f"  {label:28s} {out[key]}", soft_wrap=True, markup=False)
    c.print(f"map accuracy vs the simulated hull: RMS {100 * acc.rms_m:.1f} cm ({acc.rms_bins:.2f} range bins), "
            f"coverage {100 * acc.coverage:.0f} % of the visible surface", soft_wrap=True)
    c.print(f"open the report: file://{Path(str(out['report'])).resolve()}", soft_wrap=True)


def register(app: typer.Typer) -> None:
    """Add ``demo`` to the CLI."""
    app.command("demo", epilog=example("demo -o sonarmap-demo/ --pings 40", "demo -o sonarmap-demo/ --overwrite -q"))(
        demo_command)
