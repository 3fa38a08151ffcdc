"""``python -m sonarmap`` runs the CLI."""

from sonarmap.cli import run

run()
