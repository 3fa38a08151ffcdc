"""``sonarmap info``: describe a geometry JSON, a ping file, a directory of pings or a recording."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

from sonarmap.cli._common import GEOMETRY_OPTION, console, load_geometry_option
from sonarmap.geometry import geometry_summary

__all__ = ["register", "geometry_summary", "describe_path"]


def _is_geometry_json(p: Path) -> bool:
    if p.suffix.lower() != ".json" or not p.is_file():
        return False
    return not any(
        (p.parent / f"{p.stem}{s}").exists() for s in ("_raw.png", ".png", "_raw.bmp", ".bmp")
    )


def describe_path(path: Path, geometry: Any = None) -> dict[str, Any]:
    """Summary of a geometry JSON or any readable ping source."""
    from sonarmap.geometry import load_geometry
    from sonarmap.io import reader_for

    if geometry is None and _is_geometry_json(path):
        g = load_geometry(path)
        return {"path": str(path), "kind": "geometry", **geometry_summary(g)}
    mod = reader_for(path)
    fmt = mod.FORMAT
    if hasattr(mod, "summary") and geometry is None:
        out = {k: v for k, v in mod.summary(path).items() if not k.startswith("_")}
        out.setdefault("path", str(path))
        out.setdefault("format", fmt)
        return out
    from sonarmap.io import make_summary, read_pings

    first = last = None
    n = 0
    for ping in read_pings(path, geometry=geometry):
        if first is None:
            first = ping
        last = ping
        n += 1
    assert first is not None and last is not None
    img = first.image
    out = make_summary(fmt, path, n_pings=n, geometry=first.geometry, time_start_ns=first.time_ns,
                       time_end_ns=last.time_ns, first_ping_zero_fraction=float((img == 0).mean()),
                       first_ping_mean_intensity=float(img.mean()))
    return {k: v for k, v in out.items() if not k.startswith("_")}


def _inputs_of(path: Path) -> list[Path]:
    """The inputs ``path`` stands for: itself, or for a directory of recordings each recording in
    it (a Kongsberg ``.all`` + ``.wcd`` pair once; :func:`sonarmap.io.inputs_with_readers`)."""
    if not path.is_dir():
        return [path]
    from sonarmap.io import expand_inputs, inputs_with_readers

    return [q for q, _ in inputs_with_readers(expand_inputs(path))]


def _print(info: dict[str, Any]) -> None:
    from rich.table import Table

    t = Table(show_header=False, box=None, pad_edge=False)
    t.add_column(style="bold")
    t.add_column()
    for k, v in info.items():
        if isinstance(v, float):
            v = f"{v:.6g}"
        elif isinstance(v, list):
            v = ", ".join(f"{x:.4g}" if isinstance(x, float) else str(x) for x in v)
        t.add_row(k, str(v))
    c = console()
    with c.capture() as captured:  # rich pads every row to the widest value: no trailing blanks
        c.print(t)
    typer.echo("\n".join(line.rstrip() for line in captured.get().splitlines()), color=c.is_terminal)


def register(app: typer.Typer) -> None:
    @app.command("info")
    def info(
        paths: list[Path] = typer.Argument(None, help="Geometry JSON, ping files, directories, recordings "
                                           "or stores (convert / process)."),
        sonar: str | None = GEOMETRY_OPTION,
        presets: bool = typer.Option(False, "--presets", help="List the built-in sonar presets."),
        as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
    ) -> None:
        """Describe sonar geometry, ping count and time span of each input.

        A product store of sonarmap process is summarised too: pings (done), time span,
        variables, flagged fits, whether the run completed.

        Example: sonarmap info ../shared/data/didson/test/1468966347175925_raw.png
        """
        from sonarmap.geometry import preset, preset_names

        items: list[dict[str, Any]] = []
        if presets:
            items.extend({"preset": n, **geometry_summary(preset(n))} for n in preset_names())
        geom = load_geometry_option(sonar)
        for p in paths or []:
            items.extend(describe_path(q, geom) for q in _inputs_of(p))
        if not items:
            raise typer.BadParameter("give at least one path, or --presets", param_hint="PATHS")
        if as_json:
            typer.echo(json.dumps(items if len(items) > 1 else items[0], indent=1, default=str))
            return
        for i, item in enumerate(items):
            if i:
                console().print()
            _print(item)
