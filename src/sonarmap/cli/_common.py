"""Options and helpers shared by the sub-commands (defined once)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import typer

__all__ = [
    "GEOMETRY_OPTION", "OUTPUT_OPTION", "STDOUT", "console", "err_console", "load_geometry_option", "open_output",
    "output_name",
]

GEOMETRY_OPTION: Any = typer.Option(
    None,
    "--sonar",
    "-s",
    help="Sonar geometry: a preset name (see `sonarmap info --presets`) or a geometry JSON file; "
    "overrides the pings' sidecar JSON.",
)
OUTPUT_OPTION: Any = typer.Option(..., "--output", "-o", help="Output path.")

#: The ``-o`` value that means standard output.
STDOUT = "-"


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


def output_name(path: str | Path) -> str:
    """``path`` for messages: ``"stdout"`` for ``-o -``."""
    return "stdout" if str(path) == STDOUT else str(path)


@contextmanager
def open_output(path: str | Path, *, newline: str | None = None) -> Iterator[IO[str]]:
    """A UTF-8 text output: standard output for ``-`` (:data:`STDOUT`), else the file, written atomically.

    Parameters
    ----------
    path : str or Path
        ``-`` or a file path (replaced only when the block completes without an error).
    newline : str, optional
        As for :func:`open` (``""`` for the ``csv`` module).

    Examples
    --------
    >>> with open_output("-") as fh:            # doctest: +SKIP
    ...     print("x,y", file=fh)
    """
    if str(path) == STDOUT:
        import sys

        out = sys.stdout
        try:
            yield out
        finally:
            out.flush()
        return
    from sonarmap._atomic import atomic_open

    with atomic_open(path, "w", newline=newline, encoding="utf-8") as fh:
        yield fh
