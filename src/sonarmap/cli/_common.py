"""Options and helpers shared by the sub-commands (defined once)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

__all__ = ["GEOMETRY_OPTION", "OUTPUT_OPTION", "console", "err_console", "load_geometry_option"]

GEOMETRY_OPTION: Any = typer.Option(
    None,
    "--sonar",
    "-s",
    help="Sonar geometry: a preset name (see `sonarmap info --presets`) or a geometry JSON file; "
    "overrides the pings' sidecar JSON.",
)
OUTPUT_OPTION: Any = typer.Option(..., "--output", "-o", help="Output path.")


def console() -> Any:
    """A rich console on stdout."""
    from rich.console import Console

    return Console(highlight=False)


def err_console() -> Any:
    """A rich console on stderr (progress bars and status)."""
    from rich.console import Console

    return Console(stderr=True, highlight=False)


def load_geometry_option(value: str | Path | None) -> Any:
    """Resolve ``--sonar`` to a SonarGeometry (or None)."""
    if value is None:
        return None
    from sonarmap.geometry import as_geometry

    return as_geometry(value)
