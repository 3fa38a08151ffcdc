"""What a configuration change does to the returns of the real recordings.

Usage::

    python benchmarks/config_moves.py B.toml                 # the default -> B.toml
    python benchmarks/config_moves.py A.toml B.toml          # A.toml -> B.toml
    python benchmarks/config_moves.py default B.toml --recordings didson,oculus

Each TOML file is a pipeline configuration as ``sonarmap process --config`` reads it
(``PipelineConfig.from_toml``); ``default`` is ``PipelineConfig()``.  For every ping of each
shared recording (``../shared/data``, or ``$SONARMAP_DATA``: the 10 DIDSON test pings, the 6 ARIS
frames, the 3 Oculus pings, the 10 Kongsberg EM2040 water-column pings) both pipelines run
(``process_ping``) and the first returns are compared beam by beam, in range bins of the ping:
returns per ping on each side, how many of the returns both report move (by more than 1e-6 bin),
the median of the moves, their 5-95 % range, how many move by more than 3 bins, the share that
moves towards the sonar, and the largest moves with their ping and beam - the figures
``docs/ranges.md`` ("Options") tells how to read.  The
recordings have no ground truth: look at the beams it names (``sonarmap segment`` figures) before
calling a move right or wrong.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("SONARMAP_DATA", ROOT.parent / "shared" / "data"))
RECORDINGS = {
    "didson": ("didson", "test"),
    "aris": ("aris", "sample.aris"),
    "oculus": ("oculus", "three_pings_8bit.raw"),
    "kongsberg": ("kongsberg", "0077_20221109_123655_Belgica.wcd"),
}


@dataclasses.dataclass(frozen=True)
class Moves:
    """One recording: returns per ping under A and B, and the moves (bins) of the returns both give."""

    name: str
    returns_a: tuple[int, ...]
    returns_b: tuple[int, ...]
    moves_bins: NDArray[np.float64]  # B - A over the beams with a return in both
    ping: NDArray[np.int64]  # the ping of each move
    beam: NDArray[np.int64]  # the beam of each move

    def summary(self) -> str:
        """One markdown row: recording, returns per ping, moved, median |move|, 5-95 %, > 3 bins,
        towards the sonar, largest moves."""
        m = self.moves_bins
        moved = np.abs(m) > 1e-6
        mv = m[moved]
        if mv.size:
            lo, hi = np.percentile(mv, (5, 95))
            stats = (f"{mv.size} of {m.size} | {np.median(np.abs(mv)):.2f} | {lo:+.2f} .. {hi:+.2f} | "
                     f"{int(np.sum(np.abs(m) > 3))} | {np.mean(mv < 0):.2f}")
        else:
            stats = f"0 of {m.size} | - | - | 0 | -"
        top = np.argsort(-np.abs(m))[:4]
        largest = ", ".join(f"{m[k]:+.1f} (ping {self.ping[k]}, beam {self.beam[k]})" for k in top if moved[k])
        counts = ", ".join(f"{a}" if a == b else f"{a} -> {b}" for a, b in zip(self.returns_a, self.returns_b,
                                                                                 strict=True))
        return f"| {self.name} | {counts} | {stats} | {largest or '-'} |"


HEADER = ("| recording | returns per ping (A -> B) | returns moved | median abs move (bins) | 5-95 % of moved (bins) "
          "| more than 3 bins | towards the sonar | largest moves (bins) |\n|---|---|---|---|---|---|---|---|")


def compare(pings: Sequence[Any], config_a: Any, config_b: Any, name: str = "") -> Moves:
    """The returns of ``pings`` under ``config_a`` and ``config_b`` (``process_ping``), beam by beam."""
    from sonarmap.pipeline import process_ping

    na, nb, moves, where_p, where_b = [], [], [], [], []
    for i, p in enumerate(pings):
        bin_m = abs(float(p.geometry.range_resolution_m))
        ra = np.asarray(process_ping(p, config_a).ranges.range_m, dtype=np.float64)
        rb = np.asarray(process_ping(p, config_b).ranges.range_m, dtype=np.float64)
        na.append(int(np.isfinite(ra).sum()))
        nb.append(int(np.isfinite(rb).sum()))
        both = np.flatnonzero(np.isfinite(ra) & np.isfinite(rb))
        moves.append((rb[both] - ra[both]) / bin_m)
        where_p.append(np.full(both.size, i, dtype=np.int64))
        where_b.append(both.astype(np.int64))
    def cat(parts: list[NDArray[Any]], dtype: Any) -> NDArray[Any]:
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)

    return Moves(name, tuple(na), tuple(nb), cat(moves, np.float64), cat(where_p, np.int64),
                 cat(where_b, np.int64))


def load_config(arg: str) -> Any:
    """``default`` -> ``PipelineConfig()``, else the TOML file ``arg``."""
    from sonarmap.pipeline import PipelineConfig

    return PipelineConfig() if arg == "default" else PipelineConfig.from_toml(arg)


def read_recording(name: str, data: Path = DATA) -> list[Any]:
    """Every ping of the shared recording ``name`` (a key of :data:`RECORDINGS`)."""
    from sonarmap.io import expand_inputs, read_pings

    with warnings.catch_warnings():  # the Kongsberg file's truncated last ping warns
        warnings.simplefilter("ignore")
        return list(read_pings(expand_inputs(data.joinpath(*RECORDINGS[name]))))


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/config_moves.py", description=__doc__.split("\n")[0])
    ap.add_argument("configs", nargs="+", help="[A.toml|default] B.toml")
    ap.add_argument("--recordings", default=",".join(RECORDINGS), help="comma-separated: " + ", ".join(RECORDINGS))
    args = ap.parse_args(None if argv is None else list(argv))
    if len(args.configs) > 2:
        ap.error("give one configuration (compared with the default) or two")
    names = [r for r in args.recordings.split(",") if r]
    unknown = sorted(set(names) - set(RECORDINGS))
    if unknown:
        ap.error(f"--recordings: unknown {', '.join(unknown)}; choose from {', '.join(RECORDINGS)}")
    from sonarmap.errors import InputError

    pair = ["default", *args.configs] if len(args.configs) == 1 else args.configs
    try:
        a, b = (load_config(c) for c in pair)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(HEADER)
    for name in names:
        print(compare(read_recording(name), a, b, name).summary(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
