"""The simulated-survey figures of docs/mapping.md, for the default pipeline or another one.

Usage::

    python benchmarks/survey_figures.py                       # every table (~10 min on 2 cores)
    python benchmarks/survey_figures.py --parts registration  # registration, occupancy, range-mode
    python benchmarks/survey_figures.py --config my.toml      # a pipeline as `sonarmap process --config` reads it

* ``registration``: ``simulate_survey(kind=K, n_pings=40, seed=1)`` for the hull and the rippled
  seafloor: RMS (bins), p95 (m) and coverage of the registered points at the footprint edge (the
  default), on the beams' axes and at footprint fractions 0.3 / 0.7; the points' mean offset in
  front of the surface along its normal and its spread (bins); the returns' mean offset in front of
  the renderer's surface (``SimResult.surface_range_m``).
* ``occupancy``: the dense surveys (80 pings, 0.25 m/s at 10 Hz, seed 1, with and without 30 %
  dropouts): occupancy IoU at 0.05 / 0.10 m of every model of ``SURVEY_MODELS`` with rays in the
  imaging plane, and of the first three with three rays over the aperture.
* ``range-mode``: the first return (the pipeline's ``range_mode``) and the strongest, on the
  10 cm and 2.5 cm surveys: range error against ``SimSurvey.truth_range_m`` (median / sd, bins),
  RMS of the points, IoU pD/pFA / fixed 0.8/0.3.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

PARTS = ("registration", "occupancy", "range-mode")
#: The surveys: 40 pings 10 cm apart, and the dense ones (80 pings, 2.5 cm apart).
SPARSE = {"n_pings": 40}
DENSE = {"n_pings": 80, "speed_m_s": 0.25, "ping_rate_hz": 10}


def _products(survey: Any, config: Any) -> list[Any]:
    from sonarmap.pipeline import process_ping

    return [process_ping(p, config) for p in survey.pings]


def registered_points(survey: Any, products: Sequence[Any], registration: Any) -> np.ndarray:
    """The returns of ``products`` registered with the survey's true poses (as ``evaluate_survey``
    registers them), shape (n, 3)."""
    from sonarmap.mapping.register import register_ranges

    cloud = register_ranges([p.ranges for p in products], survey.poses,
                            azimuth_beamwidth_rad=survey.geometry.azimuth_beamwidth_rad, config=registration)
    return np.asarray(cloud.xyz_m, dtype=np.float64)


def normal_offsets_bins(survey: Any, points: np.ndarray) -> np.ndarray:
    """Each point's signed distance in front of the analytic surface along its normal (bins)."""
    d = -survey.surface.signed(points) / np.linalg.norm(survey.surface.gradient(points), axis=-1)
    return d / survey.geometry.range_resolution_m


def registration_rows(config: Any) -> list[str]:
    """The registration table, one row per survey and registration."""
    from sonarmap.evaluate.mapping import registration_accuracy
    from sonarmap.mapping.register import RegistrationConfig
    from sonarmap.simulate.survey import simulate_survey

    rows = ["| survey | registration | RMS (bins) | p95 (m) | coverage | offset in front, mean / sd (bins) |",
            "|---|---|---|---|---|---|"]
    for kind in ("hull", "seafloor"):
        s = simulate_survey(kind=kind, seed=1, **SPARSE)
        prods = _products(s, config)
        for label, reg in (("footprint edge", RegistrationConfig()), ("axes", RegistrationConfig(footprint_edge=False)),
                           ("fraction 0.3", RegistrationConfig(footprint_fraction=0.3)),
                           ("fraction 0.7", RegistrationConfig(footprint_fraction=0.7))):
            pts = registered_points(s, prods, reg)
            a = registration_accuracy(s, pts)
            off = normal_offsets_bins(s, pts)
            rows.append(f"| {kind} | {label} | {a.rms_bins:.3f} | {a.p95_m:.4f} | {100 * a.coverage:.2f} % "
                        f"({a.n_points} points, {a.n_visible} visible) | {off.mean():+.3f} / {off.std():.3f} |")
        err = []
        for p, t in zip(prods, s.sim_truth, strict=True):
            r = np.asarray(p.ranges.range_m, dtype=np.float64)
            tr = np.asarray(t.surface_range_m, dtype=np.float64)
            ok = np.isfinite(r) & np.isfinite(tr)
            err.append((tr[ok] - r[ok]) / s.geometry.range_resolution_m)
        rows.append(f"| {kind} | returns in front of `surface_range_m`, mean (bins) | {np.concatenate(err).mean():+.3f} "
                    "| | | |")
    return rows


def occupancy_rows(config: Any) -> list[str]:
    """The occupancy IoU tables (in-plane rays: every model; three rays: the first three)."""
    from sonarmap.evaluate.mapping import SURVEY_MODELS, evaluate_survey
    from sonarmap.simulate.survey import simulate_survey

    rows = [f"| survey | rays | IoU 0.05 m ({' / '.join(SURVEY_MODELS)}) | IoU 0.10 m |", "|---|---|---|---|"]
    for kind in ("hull", "seafloor"):
        for dropouts in (0.0, 0.3):
            s = simulate_survey(kind=kind, seed=1, dropout_fraction=dropouts, **DENSE)
            prods = _products(s, config)
            for n_el in (1, 3):
                models = SURVEY_MODELS if n_el == 1 else SURVEY_MODELS[:3]
                ev = evaluate_survey(s, products=prods, models=models, n_elevation=n_el)
                cells = [" / ".join(f"{ev.iou[(res, m)]:.3f}" for m in models) for res in (0.05, 0.1)]
                rows.append(f"| {kind}, 2.5 cm{', 30 % dropouts' if dropouts else ''}, seed 1 | {n_el} | "
                            f"{cells[0]} | {cells[1]} |")
    return rows


def range_mode_rows(config: Any) -> list[str]:
    """First against strongest returns on the 10 cm and 2.5 cm surveys."""
    from sonarmap.evaluate.mapping import evaluate_survey
    from sonarmap.simulate.survey import simulate_survey

    rows = ["| survey | mode | range error, median / sd (bins) | RMS (bins) | IoU 0.05 m, pD/pFA / fixed | IoU 0.10 m |",
            "|---|---|---|---|---|---|"]
    models = ("pd/pfa", "fixed 0.8/0.3")
    for kind in ("hull", "seafloor"):
        for label, kw in (("10 cm", SPARSE), ("2.5 cm", DENSE)):
            s = simulate_survey(kind=kind, seed=1, **kw)
            for mode in ("first", "strongest"):
                prods = _products(s, config.replace(range_mode=mode))
                r = np.array([np.asarray(p.ranges.range_m, dtype=np.float64) for p in prods])
                t = np.asarray(s.truth_range_m)
                ok = np.isfinite(r) & np.isfinite(t)
                e = (r[ok] - t[ok]) / s.geometry.range_resolution_m
                ev = evaluate_survey(s, products=prods, models=models)
                iou = [" / ".join(f"{ev.iou[(res, m)]:.3f}" for m in models) for res in (0.05, 0.1)]
                rows.append(f"| {kind}, {label}, seed 1 | {mode} | {np.median(e):+.2f} / {np.std(e):.2f} | "
                            f"{ev.accuracy.rms_bins:.2f} | {iou[0]} | {iou[1]} |")
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/survey_figures.py", description=__doc__.split("\n")[0])
    ap.add_argument("--parts", default=",".join(PARTS), help="comma-separated: " + ", ".join(PARTS))
    ap.add_argument("--config", default=None, help="pipeline configuration (TOML); default PipelineConfig()")
    args = ap.parse_args(None if argv is None else list(argv))
    parts = [p for p in args.parts.split(",") if p]
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        ap.error(f"--parts: unknown {', '.join(unknown)}; choose from {', '.join(PARTS)}")
    from sonarmap.errors import InputError
    from sonarmap.pipeline import PipelineConfig

    try:
        config = PipelineConfig() if args.config is None else PipelineConfig.from_toml(args.config)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    for part, rows in (("registration", registration_rows), ("occupancy", occupancy_rows),
                       ("range-mode", range_mode_rows)):
        if part in parts:
            print(f"\n{part}\n" + "\n".join(rows(config)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
