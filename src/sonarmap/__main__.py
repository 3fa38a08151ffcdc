"""``python -m sonarmap`` runs the CLI."""

from sonarmap.cli import run

# Guarded: multiprocessing (the spawned workers of `sonarmap process`) re-imports the main
# module in its child processes, which must not run the CLI again.
if __name__ == "__main__":
    run()
