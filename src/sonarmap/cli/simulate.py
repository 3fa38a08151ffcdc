"""``sonarmap simulate``: write synthetic pings of a named scene with their truth files."""

from __future__ import annotations

from pathlib import Path

import typer

from sonarmap.cli._common import QUIET_OPTION, VERBOSE_OPTION, check_choice, example, load_geometry_option

__all__ = ["register"]


def register(app: typer.Typer) -> None:
    """Add the ``simulate`` command to ``app``."""

    @app.command("simulate", epilog=example("simulate --scene hull --count 10 --sonar aris3000-128 -o sim/",
                                            "simulate --list-scenes"))
    def simulate(
        scene: str = typer.Option("hull", "--scene", help="Scene name (see --list-scenes)."),
        seed: int = typer.Option(0, "--seed", help="Seed of the first ping; ping i uses seed + i."),
        count: int = typer.Option(1, "--count", "-n", min=1, help="Number of pings."),
        sonar: str = typer.Option(
            "didson-hf", "--sonar", "-s", metavar="PRESET|JSON",
            help="Sonar geometry: preset name (list them with: sonarmap info --presets) or geometry JSON file.",
        ),
        output: Path = typer.Option(None, "--output", "-o", help="Output directory."),
        list_scenes: bool = typer.Option(False, "--list-scenes", help="List scene names and exit."),
        quiet: bool = QUIET_OPTION,
        verbose: bool = VERBOSE_OPTION,
    ) -> None:
        """Simulate pings (PNG + JSON, like the real DIDSON data) plus truth (_truth.png/.json).

        Each sonar renders with its profile's gain, floor and receiver (docs/simulator.md).  The
        output directory is created if needed; files of the same names in it are replaced.
        """
        from sonarmap.simulate import SCENE_NAMES

        if list_scenes:
            for name in SCENE_NAMES:
                typer.echo(name)
            return
        if output is None:
            raise typer.BadParameter("an output directory is required (or use --list-scenes)", param_hint="--output")
        check_choice(scene, tuple(SCENE_NAMES), "--scene")
        from sonarmap.cli._common import ping_progress
        from sonarmap.simulate import scene_from_name, simulate_ping, write_simulation

        geom = load_geometry_option(sonar)
        built = scene_from_name(scene, seed, geometry=geom)  # scaled into short windows (Oculus)
        t0_ns = 1_700_000_000_000_000_000
        out = Path(output)
        with ping_progress("simulate", count, quiet=quiet, verbose=verbose) as bar:
            bar.start()
            for i in range(count):
                res = simulate_ping(built, geom, seed=seed + i, time_ns=t0_ns + i * 100_000_000)
                write_simulation(res, out)
                bar.advance()
                bar.log(f"ping {i} (seed {seed + i}) -> {out}")
        if not quiet:
            typer.echo(f"wrote {count} simulated '{scene}' ping(s) ({geom.name}) + truth to {out}", err=True)
