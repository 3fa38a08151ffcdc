"""ARIS (shared ``sample.aris``): how firmly the slanted target is followed, and by what.

Usage::

    python benchmarks/aris_target_checks.py                   # prints the table of docs/ranges.md
    python benchmarks/aris_target_checks.py --config my.toml  # and a row for another configuration

The recording has no ground truth.  The target is the slanted line at 15.4-17.3 m across beams
0-40 of its 6 frames; its curve per frame is a robust cubic (three rounds of dropping points more
than max(0.15 m, 3 x the median distance) from the fit) through the returns at 15-17.6 m on
beams 0-40 of every configuration compared (three fits - the default, converged to the likelihood
maximum, and two that stop when an EM step gains less than 1e-6 of the log-likelihood: plain EM,
the default until the fit was converged, and SQUAREM-accelerated EM, which stops nearer to the
maximum - each with and without the tracker's front pass), so that no configuration defines the
curve it is scored on.  A beam is *on the target* when its return lies within 0.2 m of that curve;
*in front* counts returns more than 0.2 m nearer than it.  Each tracker configuration is scored
with every fit, so the table shows both how many beams follow the target and how much that
depends on where the fit stopped.  ``--config`` adds a row for another pipeline configuration,
scored against the same curves (which it does not help define).
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("SONARMAP_DATA", ROOT.parent / "shared" / "data"))
RECORDING = DATA / "aris" / "sample.aris"
BEAMS = 41  # the target spans beams 0-40
BAND_M = (15.0, 17.6)
TOLERANCE_M = 0.2


def _configs() -> dict[str, Any]:
    from sonarmap.pipeline import PipelineConfig

    base = PipelineConfig()
    return {"converged fit (default)": base,
            "plain EM stopped at 1e-6": base.replace(fit={"fit_accelerate": False, "fit_tol": 1e-6}),
            "SQUAREM stopped at 1e-6": base.replace(fit={"fit_accelerate": True, "fit_tol": 1e-6})}


def target_curves(pings: list[Any]) -> NDArray[np.float64]:
    """Per frame, the target's range (m) on every beam (the module notes)."""
    from sonarmap.pipeline import process_ping

    curves = []
    for p in pings:
        xs: list[float] = []
        ys: list[float] = []
        for cfg in [c.replace(track={"front_pass": f}) for c in _configs().values() for f in (False, True)]:
            r = process_ping(p, cfg).ranges.range_m
            b = np.arange(r.size)
            sel = (b < BEAMS) & (r > BAND_M[0]) & (r < BAND_M[1])
            xs += list(b[sel])
            ys += list(r[sel])
        x, y = np.asarray(xs, float), np.asarray(ys, float)
        for _ in range(3):
            coef = np.polyfit(x, y, 3)
            d = np.abs(np.polyval(coef, x) - y)
            keep = d < max(0.15, 3 * float(np.median(d)))
            x, y = x[keep], y[keep]
        curves.append(np.polyval(coef, np.arange(p.geometry.n_beams)))
    return np.asarray(curves)


def score(pings: list[Any], curves: NDArray[np.float64], front_pass: bool) -> dict[str, tuple[int, int, int, list[int]]]:
    """Per fit: (beams on the target, returns in front of it, returns in all, on-target per frame)."""
    return {name: score_config(pings, curves, cfg.replace(track={"front_pass": front_pass}))
            for name, cfg in _configs().items()}


def score_config(pings: list[Any], curves: NDArray[np.float64], cfg: Any) -> tuple[int, int, int, list[int]]:
    """(beams on the target, returns in front of it, returns in all, on-target per frame) of ``cfg``."""
    from sonarmap.pipeline import process_ping

    on_t = front_t = n_ret = 0
    per = []
    for p, c in zip(pings, curves):
        r = process_ping(p, cfg).ranges.range_m
        n_ret += int(np.isfinite(r).sum())
        near = r[:BEAMS]
        with np.errstate(invalid="ignore"):
            on = np.abs(near - c[:BEAMS]) < TOLERANCE_M
            front = near < c[:BEAMS] - TOLERANCE_M
        on_t += int(on.sum())
        front_t += int(front.sum())
        per.append(int(on.sum()))
    return on_t, front_t, n_ret, per


def main(argv: list[str] | None = None) -> int:
    import argparse

    from sonarmap.io import read_pings
    from sonarmap.pipeline import PipelineConfig

    ap = argparse.ArgumentParser(description="How firmly the real ARIS target is followed")
    ap.add_argument("--config", default=None, help="also score this pipeline configuration (TOML)")
    args = ap.parse_args(argv)
    extra = PipelineConfig.from_toml(args.config) if args.config else None
    warnings.simplefilter("ignore")
    if not RECORDING.exists():
        print(f"{RECORDING}: not found (set SONARMAP_DATA)", file=sys.stderr)
        return 1
    pings = list(read_pings(RECORDING))
    curves = target_curves(pings)
    n = BEAMS * len(pings)
    print(f"ARIS {RECORDING.name}: beams 0-{BEAMS - 1} of {len(pings)} frames on the target (within {TOLERANCE_M} m)")
    print("| tracker | fit | on the target | in front of it | returns | on the target per frame |")
    print("|---|---|---|---|---|---|")
    for front_pass in (False, True):
        label = "with the front pass (default)" if front_pass else "without the front pass"
        for fit, (on_t, front_t, n_ret, per) in score(pings, curves, front_pass).items():
            print(f"| {label} | {fit} | {on_t} of {n} | {front_t} | {n_ret} | {', '.join(map(str, per))} |")
    if extra is not None:
        on_t, front_t, n_ret, per = score_config(pings, curves, extra)
        print(f"| {args.config} | as configured | {on_t} of {n} | {front_t} | {n_ret} | {', '.join(map(str, per))} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
