"""Scoring segmentations and per-beam ranges against simulator truth.

For every simulated ping (:func:`sonarmap.simulate.simulate_ping`) the truth is the class mask
(0 background, 1 structure, 2 clutter such as fish) and the per-beam first-return bin of structure
(-1 where a beam sees no structure).  A pipeline (:class:`sonarmap.pipeline.PipelineConfig`) is run
on the noisy ping and scored with:

``pixel_f1``
    F1 of predicted structure pixels (label >= 1) against truth structure (class 1); clutter
    counts as background, so labelling fish as structure is a false positive.
``recall``
    Fraction of beams *with* structure whose reported first return lies within ``tol_bins``
    (default 3) range bins of the truth.
``median_error_m``
    Median absolute range error (metres) over beams with structure that report a return.
``false_return_rate``
    Fraction of beams *without* structure that report a return (a false surface in the map).

Scores are pooled over all pings of a method (counts are summed before the ratios are taken).

Truth threshold: the simulator marks a pixel as structure when its unblurred expected echo is at
least ``truth_snr_db`` above the expected background.  The simulator's default (-3 dB) includes
echo tails far below the speckle, which no detector (nor a human annotator) can place within
3 bins; :func:`default_sim_configs` uses +6 dB - "clearly visible structure", the closest match to
the hand annotation of the real pings - at two receiver-noise levels.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from sonarmap.errors import InputError

__all__ = [
    "PEER_RANGE_RULES",
    "PingScore",
    "MethodScore",
    "score_ping",
    "pool_scores",
    "evaluate",
    "format_table",
    "DEFAULT_SCENES",
    "baseline_configs",
    "default_sim_configs",
    "preset_sim_configs",
    "evaluate_presets",
    "ACCEPTANCE_PRESETS",
    "ACCEPTANCE_SCENES",
    "main",
]

#: Scenes of the acceptance table (the simulator's names).
DEFAULT_SCENES = ("hull", "curved_hull", "propeller", "seafloor", "fish_over_hull", "fish", "empty")


@dataclasses.dataclass(frozen=True)
class PingScore:
    """Counts of one ping (see the module notes)."""

    tp: int
    fp: int
    fn: int
    n_struct_beams: int
    n_hit_beams: int
    n_empty_beams: int
    n_false_beams: int
    errors_m: tuple[float, ...]


@dataclasses.dataclass(frozen=True)
class MethodScore:
    """Pooled scores of one method."""

    method: str
    n_pings: int
    pixel_f1: float
    recall: float
    median_error_m: float
    false_return_rate: float
    n_struct_beams: int
    n_empty_beams: int

    def as_row(self) -> dict[str, Any]:
        """Plain dict for tables and CSV."""
        return dataclasses.asdict(self)


def score_ping(
    labels: ArrayLike | None,
    range_bins: ArrayLike,
    range_m: ArrayLike,
    class_mask: ArrayLike,
    truth_bins: ArrayLike,
    truth_range_m: ArrayLike,
    *,
    tol_bins: int = 3,
    empty_beams: ArrayLike | None = None,
) -> PingScore:
    """Score one ping's labels and per-beam first returns against truth.

    Parameters
    ----------
    labels : ndarray (n_bins, n_beams) or None
        Predicted labels (>= 1 = structure); ``None`` skips the pixel counts.
    range_bins, range_m : ndarray (n_beams,)
        Reported first-return bin (-1 none) and range (NaN none).
    class_mask : ndarray (n_bins, n_beams)
        Truth classes (1 = structure).
    truth_bins, truth_range_m : ndarray (n_beams,)
        Truth first-return bin (-1 none) and range (NaN none).
    tol_bins : int
        Recall tolerance in range bins.
    empty_beams : ndarray of bool (n_beams,), optional
        Beams that see no structure at all (default: beams without a truth first return).  Beams
        that are neither (faint structure below the truth threshold) count for neither recall
        nor false returns.
    """
    rb = np.asarray(range_bins, dtype=np.int64)
    tb = np.asarray(truth_bins, dtype=np.int64)
    if rb.shape != tb.shape:
        raise InputError(f"range_bins: shape {rb.shape} does not match truth {tb.shape}")
    cm = np.asarray(class_mask)
    tp = fp = fn = 0
    if labels is not None:
        lab = np.asarray(labels)
        if lab.shape != cm.shape:
            raise InputError(f"labels: shape {lab.shape} does not match truth {cm.shape}")
        pred = lab >= 1
        truth = cm == 1
        tp = int((pred & truth).sum())
        fp = int((pred & ~truth).sum())
        fn = int((~pred & truth).sum())
    has = tb >= 0
    empty = ~has if empty_beams is None else (np.asarray(empty_beams, dtype=bool) & ~has)
    rep = rb >= 0
    hit = has & rep & (np.abs(rb - tb) <= tol_bins)
    both = has & rep
    err = np.abs(np.asarray(range_m, dtype=np.float64)[both] - np.asarray(truth_range_m, dtype=np.float64)[both])
    return PingScore(tp=tp, fp=fp, fn=fn, n_struct_beams=int(has.sum()), n_hit_beams=int(hit.sum()),
                     n_empty_beams=int(empty.sum()), n_false_beams=int((empty & rep).sum()),
                     errors_m=tuple(float(e) for e in err))


def pool_scores(method: str, scores: Iterable[PingScore]) -> MethodScore:
    """Pool per-ping counts into a :class:`MethodScore`."""
    s = list(scores)
    tp = sum(x.tp for x in s)
    fp = sum(x.fp for x in s)
    fn = sum(x.fn for x in s)
    ns = sum(x.n_struct_beams for x in s)
    ne = sum(x.n_empty_beams for x in s)
    errs = [e for x in s for e in x.errors_m]
    return MethodScore(
        method=method,
        n_pings=len(s),
        pixel_f1=2 * tp / (2 * tp + fp + fn) if (2 * tp + fp + fn) else math.nan,
        recall=sum(x.n_hit_beams for x in s) / ns if ns else math.nan,
        median_error_m=float(np.median(errs)) if errs else math.nan,
        false_return_rate=sum(x.n_false_beams for x in s) / ne if ne else math.nan,
        n_struct_beams=ns,
        n_empty_beams=ne,
    )


#: Range rules of the "peer" protocol: the issue's per-beam extraction (first return, rejection of
#: isolated returns) without the default pipeline's component filter, linking, band pooling and
#: leading-edge refinement.
PEER_RANGE_RULES: dict[str, Any] = dict(min_component_beams=1, min_component_pixels=0, link_beams=0,
                                        pool_factor=0.0, refine_bins=0, min_component_extent_m=0.0)


def baseline_configs(default: Any = None, *, protocol: str = "peer") -> dict[str, Any]:
    """The methods of the acceptance table: the default pipeline and its baselines.

    Parameters
    ----------
    default : PipelineConfig, optional
        The pipeline under test (default ``PipelineConfig()``).
    protocol : {"peer", "shared"}
        ``"peer"``: each baseline is a detector followed by the plain per-beam extraction
        (:data:`PEER_RANGE_RULES`: first return + isolated-return rejection) - how the peers turn
        detections into ranges (sonar-SLAM takes CFAR detections as points); pipeline against
        pipeline.  ``"shared"``: every baseline gets the default's pre-processing *and* range rules
        (components, linking, band pooling, refinement), so only the classifier changes - the
        classifier ablation.  ``"cfar-so (sonar-SLAM)"`` is the peer's exact detector (40
        training, 10 guard cells, pFA 0.1).
    """
    from sonarmap.pipeline import PipelineConfig

    if protocol not in ("peer", "shared"):
        raise InputError(f"protocol: must be 'peer' or 'shared', got {protocol!r}")
    d = PipelineConfig() if default is None else default
    b = d if protocol == "shared" else d.replace(**PEER_RANGE_RULES)
    out = {
        "default (mrf graphcut)": d,
        "mrf icm": d.replace(solver="icm"),
        "mrf anneal (paper)": d.replace(solver="anneal"),
        "local MAP": b.replace(method="map"),
        f"fixed threshold {d.threshold:g}": b.replace(method="threshold"),
    }
    for m in ("ca", "so", "go", "os"):
        out[f"cfar-{m} pfa 1e-3"] = b.replace(method=f"cfar-{m}", cfar_pfa=1e-3)
    out["cfar-so (sonar-SLAM)"] = b.replace(method="cfar-so", cfar_train=40, cfar_guard=10, cfar_pfa=0.1)
    return out


def default_sim_configs(noise_levels_db: Sequence[float] = (80.0, 86.0), truth_snr_db: float = 6.0) -> list[Any]:
    """Simulator settings of the acceptance table: receiver noise levels x one truth threshold."""
    from sonarmap.simulate import SimulationConfig

    return [SimulationConfig(noise_level_db=float(n), truth_snr_db=float(truth_snr_db), beam_pattern="measured")
            for n in noise_levels_db]


#: Sonar presets and scenes of the every-sonar acceptance table (``docs/segmentation.md``).
ACCEPTANCE_PRESETS = ("didson-hf", "aris3000-128", "aris-telephoto-48", "oculus-m750d-like")
ACCEPTANCE_SCENES = ("hull", "seafloor", "propeller", "fish", "empty")


def preset_sim_configs(geometry: Any, noise_steps_db: Sequence[float] = (0.0, 6.0),
                       truth_snr_db: float = 6.0) -> list[Any]:
    """Two noise levels of ``geometry``'s simulator profile: its own noise floor and ``+6 dB``.

    DIDSON renders with the measured ghost pattern, the others with their geometry's beam pattern.
    """
    from sonarmap.simulate.render import simulation_config_for

    base = simulation_config_for(geometry)
    measured = not str(geometry.name).startswith(("aris", "oculus"))
    return [simulation_config_for(geometry, noise_level_db=float(base.noise_level_db + d),
                                  truth_snr_db=float(truth_snr_db),
                                  beam_pattern="measured" if measured else "geometry")
            for d in noise_steps_db]


def evaluate_presets(
    config: Any = None, *, presets: Sequence[str] = ACCEPTANCE_PRESETS,
    scenes: Sequence[str] = ACCEPTANCE_SCENES, seeds: Sequence[int] = (0, 1, 2), per_scene: bool = True,
) -> list[MethodScore]:
    """The same pipeline on every sonar preset: one row per preset (and per preset and scene).

    Rows are named ``"<preset>"`` and ``"<preset> | <scene>"``; the pings are those of
    :func:`preset_sim_configs` x ``seeds`` x ``scenes`` (scenes scaled to each sonar's window).
    """
    from sonarmap.geometry import preset
    from sonarmap.pipeline import PipelineConfig

    cfg = PipelineConfig() if config is None else config
    out: list[MethodScore] = []
    for name in presets:
        geom = preset(name)
        rows = evaluate({name: cfg}, scenes=scenes, sim_configs=preset_sim_configs(geom), seeds=seeds,
                        geometry=geom, per_scene=per_scene)
        out.extend(rows)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m sonarmap.evaluate [--presets NAME,...] [--seeds N]``: the every-sonar table."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m sonarmap.evaluate", description=main.__doc__)
    ap.add_argument("--presets", default=",".join(ACCEPTANCE_PRESETS), help="comma-separated preset names")
    ap.add_argument("--seeds", type=int, default=3, help="seeds per scene and noise level")
    args = ap.parse_args(None if argv is None else list(argv))
    rows = evaluate_presets(presets=[p for p in args.presets.split(",") if p], seeds=tuple(range(args.seeds)))
    print(format_table(rows))
    return 0


def _simulate(scene: str, geometry: Any, sim_config: Any, seed: int, empty_snr_db: float) -> tuple[Any, Any]:
    """The simulated ping and its 'no structure at all' beams (no structure pixel >= empty_snr_db)."""
    from sonarmap.simulate import scene_from_name, simulate_ping

    sc = scene_from_name(scene, geometry=geometry)
    sim = simulate_ping(sc, geometry, config=sim_config, seed=seed)
    if empty_snr_db >= sim_config.truth_snr_db:
        return sim, None
    return sim, ~(sim.structure_peak_snr_db >= empty_snr_db)


def evaluate(
    configs: Mapping[str, Any] | None = None,
    *,
    scenes: Sequence[str] = DEFAULT_SCENES,
    sim_configs: Sequence[Any] | None = None,
    seeds: Sequence[int] = (0, 1, 2),
    geometry: Any = None,
    tol_bins: int = 3,
    per_scene: bool = False,
    empty_snr_db: float = -3.0,
) -> list[MethodScore]:
    """Run every pipeline on simulated pings and pool the scores per method.

    Parameters
    ----------
    configs : mapping of name -> PipelineConfig, optional
        Methods to compare (default :func:`baseline_configs`).
    scenes : sequence of str
        Simulator scene names.
    sim_configs : sequence of SimulationConfig, optional
        Simulator settings (e.g. noise levels); default :func:`default_sim_configs`.
    seeds : sequence of int
        Simulator seeds.
    geometry : SonarGeometry, optional
        Default the ``didson-hf`` preset.
    tol_bins : int
        Recall tolerance.
    per_scene : bool
        Also return one row per (method, scene), named ``"<method> | <scene>"``.
    empty_snr_db : float
        A beam is "without structure" (false-return denominator) when no structure pixel's
        unblurred expected echo reaches this level re background (default -3 dB, the
        simulator's own truth threshold); beams with structure between this and the truth
        threshold are scored for neither recall nor false returns.

    Returns
    -------
    list of MethodScore
    """
    from sonarmap.geometry import preset
    from sonarmap.pipeline import process_ping

    geom = preset("didson-hf") if geometry is None else geometry
    cfgs = baseline_configs() if configs is None else dict(configs)
    if sim_configs is None:
        sim_configs = default_sim_configs()
    sims = [(scene, _simulate(scene, geom, sc, seed, empty_snr_db)) for scene in scenes for sc in sim_configs for seed in seeds]
    out: list[MethodScore] = []
    for name, cfg in cfgs.items():
        per: dict[str, list[PingScore]] = {}
        for scene, (sim, empty) in sims:
            prod = process_ping(sim.ping, cfg, keep_labels=True)
            sc = score_ping(prod.labels, prod.ranges.bin, prod.ranges.range_m, sim.class_mask,
                            sim.first_return_bin, sim.first_return_range_m, tol_bins=tol_bins,
                            empty_beams=empty)
            per.setdefault(scene, []).append(sc)
        out.append(pool_scores(name, [x for v in per.values() for x in v]))
        if per_scene:
            out.extend(pool_scores(f"{name} | {scene}", v) for scene, v in per.items())
    return out


def format_table(scores: Sequence[MethodScore]) -> str:
    """Markdown table of scores."""
    lines = [
        "| method | pings | pixel F1 | recall (3 bins) | median error (m) | false-return rate |",
        "|---|---|---|---|---|---|",
    ]
    for s in scores:
        lines.append(
            f"| {s.method} | {s.n_pings} | {s.pixel_f1:.3f} | {s.recall:.3f} | "
            f"{s.median_error_m:.3f} | {s.false_return_rate:.3f} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
