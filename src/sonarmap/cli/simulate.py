"""``sonarmap simulate``: write synthetic pings of a named scene with their truth files."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import typer

from sonarmap._text import counted
from sonarmap.cli._common import (
    QUIET_OPTION, VERBOSE_OPTION, check_choice, example, load_geometry_option, refuse_stdout,
)

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
        output: Path = typer.Option(None, "--output", "-o", help="Output directory.", callback=refuse_stdout),
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
        from sonarmap.simulate import iter_simulated_pings, scene_from_name, simulate_ping, write_simulation

        geom = load_geometry_option(sonar)
        built = scene_from_name(scene, seed, geometry=geom)  # scaled into short windows (Oculus)
        t0_ns = 1_700_000_000_000_000_000
        out = Path(output)
        first = simulate_ping(built, geom, seed=seed, time_ns=t0_ns)
        _check_room(first, count, out)
        with ping_progress("simulate", count, quiet=quiet, verbose=verbose) as bar:
            bar.start()
            # ping 0 is rendered already (for the room check); the rest a batch of seeds per echo
            rest = iter_simulated_pings(built, geom, seeds=[seed + i for i in range(1, count)],
                                        time_ns=[t0_ns + i * 100_000_000 for i in range(1, count)])
            for i, res in enumerate(itertools.chain([first], rest)):
                write_simulation(res, out)
                bar.advance()
                bar.log(f"ping {i} (seed {seed + i}) -> {out}")
        if not quiet:
            typer.echo(f"wrote {counted(count, 'simulated ' + repr(scene) + ' ping')} ({geom.name}) + truth to {out}", err=True)


#: Share of the output file system's free space one ``simulate`` run may fill.
_FREE_SHARE = 0.5
#: Margin on the estimate: the PNGs of other seeds compress differently.
_SIZE_MARGIN = 1.25


def _check_room(first: Any, count: int, out: Path) -> None:
    """``--count`` against the free space: ``count`` times the files of the first ping (written
    to a temporary directory to measure them), with a margin, may fill at most half of the free
    space of the output's file system - a typo such as ``--count 1000000`` (about 40 GB of DIDSON
    pings) stops before writing anything instead of filling the disk.

    Raises
    ------
    InputError
        Naming ``--count``, the estimate and the free space.
    """
    import dataclasses
    import os
    import shutil
    import tempfile

    from sonarmap.errors import InputError
    from sonarmap.simulate import write_simulation

    with tempfile.TemporaryDirectory() as tmp:
        files = write_simulation(first, tmp)
        each = sum(max(st.st_size, st.st_blocks * 512) for st in map(os.stat, dataclasses.astuple(files)))  # blocks used
    where = out.absolute()
    while not where.exists() and where != where.parent:
        where = where.parent
    free = shutil.disk_usage(where).free
    need = count * each * _SIZE_MARGIN
    if need > free * _FREE_SHARE:
        raise InputError(f"--count {count}: the pings would take about {_size(need)} ({_size(each)} each), "
                         f"more than half of the {_size(free)} free on {where}; nothing written (ask for at "
                         f"most {int(free * _FREE_SHARE / (each * _SIZE_MARGIN))} pings, or write elsewhere)")


def _size(n: float) -> str:
    """A byte count for people: ``1.5 GB``."""
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    raise AssertionError  # pragma: no cover - the loop returns
