"""``sonarmap simulate``: write synthetic pings of a named scene with their truth files."""

from __future__ import annotations

from pathlib import Path

import typer

__all__ = ["register"]


def register(app: typer.Typer) -> None:
    """Add the ``simulate`` command to ``app``."""

    @app.command("simulate")
    def simulate(
        scene: str = typer.Option("hull", "--scene", help="Scene name (see --list-scenes)."),
        seed: int = typer.Option(0, "--seed", help="Seed of the first ping; ping i uses seed + i."),
        count: int = typer.Option(1, "--count", "-n", min=1, help="Number of pings."),
        sonar: str = typer.Option(
            "didson-hf", "--sonar", "-s", help="Sonar geometry: preset name or geometry JSON file."
        ),
        output: Path = typer.Option(None, "--output", "-o", help="Output directory."),
        list_scenes: bool = typer.Option(False, "--list-scenes", help="List scene names and exit."),
    ) -> None:
        """Simulate pings (PNG + JSON, like the real DIDSON data) plus truth (_truth.png/.json).

        Each sonar renders with its profile's gain, floor and receiver (docs/simulator.md).
        """
        from sonarmap.simulate import SCENE_NAMES

        if list_scenes:
            for name in SCENE_NAMES:
                typer.echo(name)
            return
        from sonarmap.errors import InputError

        if output is None:
            raise InputError("--output: an output directory is required (or use --list-scenes)")
        from sonarmap.geometry import as_geometry
        from sonarmap.simulate import scene_from_name, simulate_ping, write_simulation

        geom = as_geometry(sonar)
        built = scene_from_name(scene, seed, geometry=geom)  # scaled into short windows (Oculus)
        t0_ns = 1_700_000_000_000_000_000
        out = Path(output)
        for i in range(count):
            res = simulate_ping(built, geom, seed=seed + i, time_ns=t0_ns + i * 100_000_000)
            write_simulation(res, out)
        typer.echo(f"wrote {count} simulated '{scene}' ping(s) ({geom.name}) + truth to {out}")
