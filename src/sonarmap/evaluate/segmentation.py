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
    (default 3) range bins of the truth.  Two truths (``truth=``): the integer first-return bin
    of the class mask (``"first_return"``, the default of :func:`evaluate` and
    :func:`evaluate_presets`, which the existing acceptance tables were measured with), or the
    simulator's sub-bin physical surface ``SimResult.surface_range_m`` (``"surface"``: the
    nearest range of the beam's -3 dB footprint on the structure, what a leading-edge detector
    should report), converted to fractional bins, the reported ``range_m`` likewise (a
    leading-edge range between two bins is scored by its real position) - the ranges
    acceptance :func:`evaluate_ranges` scores against it.
``recall_1bin``
    The same within 1 bin.
``recall_1bin_local``
    The same within 1 bin once each ping's *local offset* is taken out: every signed error
    ``reported - truth`` less the median of the signed errors of the ``2 x 10 + 1`` scored beams
    around it (:func:`local_offset_residuals`).  Not a score a detector could reach (it uses the
    truth) but a split of the misses: where it is far above ``recall_1bin`` the errors are an
    offset that neighbouring beams share - a surface read a little early or late over tens of
    beams - rather than scatter from beam to beam.
``median_error_m``
    Median absolute range error (metres) over beams with structure that report a return.
``median_signed_error_bins``
    Median of ``reported - truth`` in bins (positive: ranges too far, e.g. a leading edge not
    corrected for the pulse's delay).
``false_return_rate``
    Fraction of beams *without* structure that report a return (a false surface in the map).
``sigma_coverage``
    When the ranges carry a one-sigma uncertainty (``BeamRanges.sigma_m``): the fraction of the
    scored returns with ``|range_m - truth| <= sigma_m`` (0.68 for calibrated Gaussian sigmas);
    NaN when no scored return has a finite sigma.
``hull_under_fish``
    Recall (within ``tol_bins``) on the beams whose structure has clutter (fish) in front of it
    in the truth mask: is the hull still reported, not the fish?
``fish_first_under_fish``
    On the same beams, the fraction whose reported first return lies on a fish (within
    ``tol_bins`` of a clutter pixel of the beam and more than ``tol_bins`` in front of the
    structure).  What ``hull_under_fish`` misses is this, beams without a return, and returns
    elsewhere (usually the hull, reported more than ``tol_bins`` from its truth: a range error,
    not the fish).

Scores are pooled over all pings of a method (counts are summed before the ratios are taken).

Truth threshold: the simulator marks a pixel as structure when its unblurred expected echo is at
least ``truth_snr_db`` above the expected background.  The simulator's default (-3 dB) includes
echo tails far below the speckle, which no detector (nor a human annotator) can place within
3 bins; :func:`default_sim_configs` uses +6 dB - "clearly visible structure", the closest match to
the hand annotation of the real pings - at two receiver-noise levels.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap._config import check_integer_argument
from sonarmap.errors import InputError

__all__ = [
    "PEER_RANGE_RULES",
    "RangesReport",
    "TRUTHS",
    "RANGES_PRESETS",
    "RANGES_SCENES",
    "SLOPED_SCENES",
    "evaluate_ranges",
    "PingScore",
    "local_offset_residuals",
    "LOCAL_OFFSET_HALF_BEAMS",
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
    """Counts of one ping (see the module notes).

    Attributes
    ----------
    tp, fp, fn : int
        Pixel counts of predicted structure against truth structure.
    n_struct_beams, n_hit_beams : int
        Beams with truth structure; those reported within ``tol_bins`` of the truth.
    n_empty_beams, n_false_beams : int
        Beams without structure; those that report a return.
    errors_m : tuple of float
        Absolute range errors (m) of the beams with structure that report a return.
    n_hit1_beams : int
        Beams with structure reported within 1 bin.
    errors_bins : tuple of float
        Signed errors ``reported - truth`` (bins), same beams as ``errors_m``.
    n_sigma_beams, n_within_sigma : int
        Scored returns with a finite ``sigma_m``; those with ``|error| <= sigma_m``.
    n_hit1_local_beams : int
        Beams with structure whose signed error lies within 1 bin of the local offset
        (:func:`local_offset_residuals` of ``errors_bins``).
    n_fish_beams, n_fish_hit_beams : int
        Beams with clutter in front of their structure (truth mask); those reported within
        ``tol_bins`` of the structure.
    n_fish_first_beams, n_fish_none_beams : int
        Of those beams, the ones whose first return is reported on the clutter (the module
        notes, ``fish_first_under_fish``), and the ones without a return.
    """

    tp: int
    fp: int
    fn: int
    n_struct_beams: int
    n_hit_beams: int
    n_empty_beams: int
    n_false_beams: int
    errors_m: tuple[float, ...]
    n_hit1_beams: int = 0
    errors_bins: tuple[float, ...] = ()
    n_sigma_beams: int = 0
    n_within_sigma: int = 0
    n_fish_beams: int = 0
    n_fish_hit_beams: int = 0
    n_fish_first_beams: int = 0
    n_fish_none_beams: int = 0
    n_hit1_local_beams: int = 0


@dataclasses.dataclass(frozen=True)
class MethodScore:
    """Pooled scores of one method (see the module notes; ``no_return_under_fish`` is the
    fraction of the ``hull_under_fish`` beams without a return)."""

    method: str
    n_pings: int
    pixel_f1: float
    recall: float
    median_error_m: float
    false_return_rate: float
    n_struct_beams: int
    n_empty_beams: int
    recall_1bin: float = math.nan
    median_signed_error_bins: float = math.nan
    sigma_coverage: float = math.nan
    hull_under_fish: float = math.nan
    n_fish_beams: int = 0
    fish_first_under_fish: float = math.nan
    no_return_under_fish: float = math.nan
    recall_1bin_local: float = math.nan

    def as_row(self) -> dict[str, Any]:
        """Plain dict for tables and CSV."""
        return dataclasses.asdict(self)


def _fractional_bins(range_m: NDArray[np.float64], bin_range_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """Ranges (m) as fractional bin indices of the bin-centre table (linear between centres and
    extrapolated with the end spacings); NaN stays NaN."""
    idx = np.arange(bin_range_m.size, dtype=np.float64)
    out = np.interp(range_m, bin_range_m, idx)
    if bin_range_m.size > 1:
        lo, hi = range_m < bin_range_m[0], range_m > bin_range_m[-1]
        out[lo] = (range_m[lo] - bin_range_m[0]) / (bin_range_m[1] - bin_range_m[0])
        out[hi] = idx[-1] + (range_m[hi] - bin_range_m[-1]) / (bin_range_m[-1] - bin_range_m[-2])
    return np.where(np.isfinite(range_m), out, np.nan)


def _pixel_counts(labels: ArrayLike | None, cm: np.ndarray) -> tuple[int, int, int]:
    """True-positive, false-positive and false-negative structure pixels (zeros without labels)."""
    if labels is None:
        return 0, 0, 0
    lab = np.asarray(labels)
    if lab.shape != cm.shape:
        raise InputError(f"labels: shape {lab.shape} does not match truth {cm.shape}")
    pred = lab >= 1
    truth = cm == 1
    return int((pred & truth).sum()), int((pred & ~truth).sum()), int((~pred & truth).sum())


def _positions(rb: np.ndarray, rm: np.ndarray, tb: np.ndarray, truth_range_m: ArrayLike,
               surface_range_m: ArrayLike | None,
               bin_range_m: ArrayLike | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Scored beams, truth ranges and the truth and reported positions in (fractional) bins.

    Against the sub-bin ``surface_range_m`` when given, else against the integer truth bins.
    """
    has = tb >= 0
    if surface_range_m is None:
        return has, np.asarray(truth_range_m, dtype=np.float64), tb.astype(np.float64), rb.astype(np.float64)
    if bin_range_m is None:
        raise InputError("bin_range_m: required with surface_range_m (the geometry's range_m)")
    grid = np.asarray(bin_range_m, dtype=np.float64)
    truth_m = np.asarray(surface_range_m, dtype=np.float64)
    if truth_m.shape != tb.shape:
        raise InputError(f"surface_range_m: shape {truth_m.shape} does not match truth {tb.shape}")
    has = has & np.isfinite(truth_m)
    tpos = _fractional_bins(truth_m, grid)
    rpos = np.where(np.isfinite(rm), _fractional_bins(rm, grid), rb.astype(np.float64))
    return has, truth_m, tpos, rpos


def _sigma_counts(sigma_m: ArrayLike | None, both: np.ndarray, err_m: np.ndarray,
                  shape: tuple[int, ...]) -> tuple[int, int]:
    """Beams scored for sigma coverage and those whose error is within their one sigma."""
    if sigma_m is None:
        return 0, 0
    sg = np.asarray(sigma_m, dtype=np.float64)
    if sg.shape != shape:
        raise InputError(f"sigma_m: shape {sg.shape} does not match truth {shape}")
    scored = both & np.isfinite(sg) & np.isfinite(err_m)
    return int(scored.sum()), int((scored & (err_m <= sg)).sum())


def _fish_beams(cm: np.ndarray, tb: np.ndarray, has: np.ndarray) -> np.ndarray:
    """Beams whose structure has clutter (fish) in front of it in the truth mask."""
    if cm.ndim == 2 and cm.shape[1] == tb.size:
        rows = np.arange(cm.shape[0])[:, None]
        return has & ((cm == 2) & (rows < np.where(tb >= 0, tb, 0)[None, :])).any(axis=0)
    return np.zeros(tb.shape, dtype=bool)


def _on_clutter(cm: np.ndarray, rpos: np.ndarray, beams: np.ndarray, tol_bins: int) -> np.ndarray:
    """Of ``beams``, those whose reported position ``rpos`` (fractional bins) lies within
    ``tol_bins`` of a clutter pixel (class 2) of its beam."""
    out = np.zeros(beams.shape, dtype=bool)
    for j in np.flatnonzero(beams):
        rows = np.flatnonzero(cm[:, j] == 2)
        out[j] = rows.size > 0 and bool((np.abs(rows - rpos[j]) <= tol_bins).any())
    return out


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
    surface_range_m: ArrayLike | None = None,
    bin_range_m: ArrayLike | None = None,
    sigma_m: ArrayLike | None = None,
) -> PingScore:
    """Score one ping's labels and per-beam first returns against truth.

    Parameters
    ----------
    labels : ndarray (n_bins, n_beams) or None
        Predicted labels (>= 1 = structure); ``None`` skips the pixel counts.
    range_bins, range_m : ndarray (n_beams,)
        Reported first-return bin (-1 none) and range (NaN none).
    class_mask : ndarray (n_bins, n_beams)
        Truth classes (1 = structure, 2 = clutter).
    truth_bins, truth_range_m : ndarray (n_beams,)
        Truth first-return bin (-1 none) and range (NaN none); ``truth_bins >= 0`` selects the
        beams with structure.
    tol_bins : int
        Recall tolerance in range bins.
    empty_beams : ndarray of bool (n_beams,), optional
        Beams that see no structure at all (default: beams without a truth first return).  Beams
        that are neither (faint structure below the truth threshold) count for neither recall
        nor false returns.
    surface_range_m : ndarray (n_beams,), optional
        Sub-bin truth (``SimResult.surface_range_m``).  When given, errors are measured against
        it, in fractional bins of ``bin_range_m`` (reported positions from ``range_m``, or
        ``range_bins`` where ``range_m`` is NaN); otherwise against ``truth_bins`` /
        ``truth_range_m`` (integer bins).
    bin_range_m : ndarray (n_bins,), optional
        The geometry's bin ranges (``geometry.range_m``); required with ``surface_range_m``.
    sigma_m : ndarray (n_beams,), optional
        One-sigma uncertainty of each reported range (``BeamRanges.sigma_m``), for the sigma
        coverage.

    Raises
    ------
    InputError
        If shapes disagree or ``surface_range_m`` comes without ``bin_range_m``.
    """
    rb = np.asarray(range_bins, dtype=np.int64)
    tb = np.asarray(truth_bins, dtype=np.int64)
    rm = np.asarray(range_m, dtype=np.float64)
    if rb.shape != tb.shape or rm.shape != tb.shape:
        raise InputError(f"range_bins: shape {rb.shape} does not match truth {tb.shape}")
    cm = np.asarray(class_mask)
    tp, fp, fn = _pixel_counts(labels, cm)
    has, truth_m, tpos, rpos = _positions(rb, rm, tb, truth_range_m, surface_range_m, bin_range_m)
    empty = ~(tb >= 0) if empty_beams is None else (np.asarray(empty_beams, dtype=bool) & ~(tb >= 0))
    rep = rb >= 0
    both = has & rep
    err_bins = np.where(both, rpos - tpos, np.nan)
    hit = both & (np.abs(err_bins) <= tol_bins)
    hit1 = both & (np.abs(err_bins) <= 1.0)
    err_m = np.abs(rm - truth_m)
    n_sigma, n_within = _sigma_counts(sigma_m, both, err_m, tb.shape)
    fish = _fish_beams(cm, tb, has)
    fish_first = _on_clutter(cm, rpos, fish & both & (err_bins < -tol_bins), tol_bins)
    local = local_offset_residuals(err_bins[both])
    return PingScore(tp=tp, fp=fp, fn=fn, n_struct_beams=int(has.sum()), n_hit_beams=int(hit.sum()),
                     n_empty_beams=int(empty.sum()), n_false_beams=int((empty & rep).sum()),
                     errors_m=tuple(float(e) for e in err_m[both]), n_hit1_beams=int(hit1.sum()),
                     errors_bins=tuple(float(e) for e in err_bins[both]), n_sigma_beams=n_sigma,
                     n_within_sigma=n_within, n_fish_beams=int(fish.sum()),
                     n_fish_hit_beams=int((fish & hit).sum()), n_fish_first_beams=int(fish_first.sum()),
                     n_fish_none_beams=int((fish & ~rep).sum()),
                     n_hit1_local_beams=int((np.abs(local) <= 1.0).sum()))


#: Half-width (scored beams) of the running median :func:`local_offset_residuals` takes out.
LOCAL_OFFSET_HALF_BEAMS = 10


def local_offset_residuals(errors_bins: ArrayLike, half_beams: int = LOCAL_OFFSET_HALF_BEAMS) -> NDArray[np.float64]:
    """One ping's signed range errors less their local offset: each error minus the median of the
    errors of the scored beams within ``half_beams`` places of it (in beam order, the window
    truncated at the ends of the ping).

    Parameters
    ----------
    errors_bins : array_like of float
        Signed errors ``reported - truth`` (bins) of one ping's scored beams, in beam order
        (``PingScore.errors_bins``); non-finite values are left out.
    half_beams : int
        Half-width of the running median (scored beams).

    Returns
    -------
    ndarray of float64
        The residuals, one per finite error.

    Examples
    --------
    >>> local_offset_residuals([1.2, 1.0, 1.4, -2.0, 1.1], half_beams=1).round(2).tolist()
    [0.1, -0.2, 0.4, -3.1, 1.55]
    """
    check_integer_argument("half_beams", half_beams, 0)
    e = np.asarray(errors_bins, dtype=np.float64).ravel()
    e = e[np.isfinite(e)]
    out = np.empty_like(e)
    for i in range(e.size):
        out[i] = e[i] - np.median(e[max(0, i - half_beams):i + half_beams + 1])
    return out


def pool_scores(method: str, scores: Iterable[PingScore]) -> MethodScore:
    """Pool per-ping counts into a :class:`MethodScore`."""
    s = list(scores)
    tp = sum(x.tp for x in s)
    fp = sum(x.fp for x in s)
    fn = sum(x.fn for x in s)
    ns = sum(x.n_struct_beams for x in s)
    ne = sum(x.n_empty_beams for x in s)
    nsig = sum(x.n_sigma_beams for x in s)
    nfish = sum(x.n_fish_beams for x in s)
    errs = [e for x in s for e in x.errors_m if math.isfinite(e)]
    errs_b = [e for x in s for e in x.errors_bins if math.isfinite(e)]
    return MethodScore(
        method=method,
        n_pings=len(s),
        pixel_f1=2 * tp / (2 * tp + fp + fn) if (2 * tp + fp + fn) else math.nan,
        recall=sum(x.n_hit_beams for x in s) / ns if ns else math.nan,
        median_error_m=float(np.median(errs)) if errs else math.nan,
        false_return_rate=sum(x.n_false_beams for x in s) / ne if ne else math.nan,
        n_struct_beams=ns,
        n_empty_beams=ne,
        recall_1bin=sum(x.n_hit1_beams for x in s) / ns if ns else math.nan,
        median_signed_error_bins=float(np.median(errs_b)) if errs_b else math.nan,
        sigma_coverage=sum(x.n_within_sigma for x in s) / nsig if nsig else math.nan,
        hull_under_fish=sum(x.n_fish_hit_beams for x in s) / nfish if nfish else math.nan,
        n_fish_beams=nfish,
        fish_first_under_fish=sum(x.n_fish_first_beams for x in s) / nfish if nfish else math.nan,
        no_return_under_fish=sum(x.n_fish_none_beams for x in s) / nfish if nfish else math.nan,
        recall_1bin_local=sum(x.n_hit1_local_beams for x in s) / ns if ns else math.nan,
    )


#: Range rules of the "peer" protocol: the issue's per-beam extraction (first return, rejection of
#: isolated returns) without the default pipeline's component filter, linking, band pooling and
#: leading-edge refinement.
PEER_RANGE_RULES: dict[str, Any] = dict(tracker="rules", min_component_beams=1, min_component_pixels=0, link_beams=0,
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
        f"fixed threshold {d.classify.threshold:g}": b.replace(method="threshold"),
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
    truth: str = "first_return",
) -> list[MethodScore]:
    """The same pipeline on every sonar preset: one row per preset (and per preset and scene).

    Rows are named ``"<preset>"`` and ``"<preset> | <scene>"``; the pings are those of
    :func:`preset_sim_configs` x ``seeds`` x ``scenes`` (scenes scaled to each sonar's window);
    ``truth`` as in :func:`evaluate`.
    """
    from sonarmap.geometry import preset
    from sonarmap.pipeline import PipelineConfig

    cfg = PipelineConfig() if config is None else config
    out: list[MethodScore] = []
    for name in presets:
        geom = preset(name)
        rows = evaluate({name: cfg}, scenes=scenes, sim_configs=preset_sim_configs(geom), seeds=seeds,
                        geometry=geom, per_scene=per_scene, truth=truth)
        out.extend(rows)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m sonarmap.evaluate [--ranges] [--presets NAME,...] [--scenes NAME,...] [--seeds N]
    [--first-seed K] [--config FILE.toml] [-j N]``.

    Without ``--ranges``: the every-sonar table (:func:`evaluate_presets`).  With ``--ranges``:
    the ranges acceptance (:func:`evaluate_ranges`: presets x :data:`RANGES_SCENES`, scored
    against the sub-bin surface truth), its per-preset table and the sloped-hull and
    hull-under-fish figures.  ``--config`` scores another pipeline (a TOML file as for
    ``sonarmap process --config``, :meth:`PipelineConfig.from_toml`); ``--first-seed`` scores
    seeds K .. K+N-1, so a setting can be checked on seeds it was not chosen on.
    """
    import argparse

    ap = argparse.ArgumentParser(prog="python -m sonarmap.evaluate", description=main.__doc__)
    ap.add_argument("--presets", default=",".join(ACCEPTANCE_PRESETS), help="comma-separated preset names")
    ap.add_argument("--scenes", default=None,
                    help="comma-separated scene names (default: the table's own scene set)")
    ap.add_argument("--seeds", type=int, default=3, help="seeds per scene and noise level")
    ap.add_argument("--first-seed", type=int, default=0, help="the first seed (seeds K .. K+N-1)")
    ap.add_argument("--config", default=None,
                    help="pipeline configuration to score (TOML, as for `sonarmap process --config`)")
    ap.add_argument("--ranges", action="store_true", help="the ranges acceptance (sub-bin truth)")
    ap.add_argument("--per-scene", action="store_true", help="with --ranges: also one row per preset and scene")
    ap.add_argument("--noise-free", action="store_true",
                    help="with --ranges: also score the noise-free echoes' half-peak leading edges")
    ap.add_argument("--bound", action="store_true",
                    help="with --ranges: also the Cramér-Rao bound's attainable recalls on the same pings")
    ap.add_argument("--recorded", action="store_true",
                    help="with --ranges: also score the range convention read on the recorded echoes, aligned "
                         "on the truth over 1, 7 and 21 beams")
    ap.add_argument("-j", "--jobs", type=int, default=1,
                    help="with --ranges: processes scoring the scenes in parallel (the same table)")
    args = ap.parse_args(None if argv is None else list(argv))
    presets = [p for p in args.presets.split(",") if p]
    scenes = None if args.scenes is None else [s for s in args.scenes.split(",") if s]
    from sonarmap.simulate.scene import SCENE_NAMES

    unknown = sorted(set(scenes or ()) - set(SCENE_NAMES))
    if unknown:
        ap.error(f"--scenes: unknown scene(s) {', '.join(unknown)}; choose from {', '.join(SCENE_NAMES)}")
    if args.seeds < 1 or args.first_seed < 0 or args.jobs < 1:
        ap.error(f"--seeds and --jobs must be >= 1 and --first-seed >= 0 (got {args.seeds}, {args.jobs}, "
                 f"{args.first_seed})")
    config = None
    if args.config is not None:
        from sonarmap.pipeline import PipelineConfig

        try:
            config = PipelineConfig.from_toml(args.config)
        except InputError as exc:
            ap.error(f"--config: {exc}")
    seeds = tuple(range(args.first_seed, args.first_seed + args.seeds))
    if args.ranges:
        report = evaluate_ranges(config, presets=presets, seeds=seeds,
                                 scenes=RANGES_SCENES if scenes is None else scenes, noise_free=args.noise_free,
                                 bound=args.bound, recorded=args.recorded, jobs=args.jobs)
        print(report.table(per_scene=args.per_scene, noise_free=args.noise_free, bound=args.bound,
                           recorded=args.recorded))
        return 0
    rows = evaluate_presets(config, presets=presets, seeds=seeds,
                            scenes=ACCEPTANCE_SCENES if scenes is None else scenes)
    print(format_table(rows))
    return 0


@functools.lru_cache(maxsize=2)
def _scene_of(scene: str, geometry: Any) -> Any:
    """The named scene built for ``geometry``, once per geometry object: a scene is deterministic
    (its fish use seed 0) and read-only, so every noise level and seed of an evaluation renders
    the same one (building it took a fifth of an evaluation's time).  The cache holds the
    geometry, so its identity (``SonarGeometry`` hashes by identity) is never reused meanwhile."""
    from sonarmap.simulate import scene_from_name

    return scene_from_name(scene, geometry=geometry)


def _simulate(scene: str, geometry: Any, sim_config: Any, seed: int, empty_snr_db: float,
              recording_meta: bool = False) -> tuple[Any, Any]:
    """The simulated ping and its 'no structure at all' beams (no structure pixel >= empty_snr_db)."""
    return _simulate_seeds(scene, geometry, sim_config, (seed,), empty_snr_db, recording_meta)[0]


def _simulate_seeds(scene: str, geometry: Any, sim_config: Any, seeds: Sequence[int], empty_snr_db: float,
                    recording_meta: bool = False) -> list[tuple[Any, Any]]:
    """:func:`_simulate` of each seed, the scene's echo rendered once (the same pings:
    :func:`sonarmap.simulate.simulate_pings`)."""
    from sonarmap.simulate import simulate_pings

    sims = simulate_pings(_scene_of(scene, geometry), geometry, config=sim_config, seeds=seeds,
                          recording_meta=recording_meta)
    if empty_snr_db >= sim_config.truth_snr_db:
        return [(sim, None) for sim in sims]
    return [(sim, ~(sim.structure_peak_snr_db >= empty_snr_db)) for sim in sims]


#: Range truths :func:`evaluate` can score against.
TRUTHS = ("first_return", "surface")


def _score_sim(prod: Any, sim: Any, empty: Any, tol_bins: int, truth: str) -> PingScore:
    """Score a pipeline product against a simulated ping's truth (``truth`` in :data:`TRUTHS`)."""
    ranges = prod.ranges
    surface = sim.surface_range_m if truth == "surface" else None
    return score_ping(prod.labels, ranges.bin, ranges.range_m, sim.class_mask, sim.first_return_bin,
                      sim.first_return_range_m, tol_bins=tol_bins, empty_beams=empty,
                      surface_range_m=surface, bin_range_m=sim.ping.geometry.range_m,
                      sigma_m=getattr(ranges, "sigma_m", None))


def _run(
    configs: Mapping[str, Any], scenes: Sequence[str], sim_configs: Sequence[Any], seeds: Sequence[int],
    geometry: Any, tol_bins: int, empty_snr_db: float, truth: str = "first_return", recording_meta: bool = False,
) -> dict[str, dict[str, list[PingScore]]]:
    """Per method and scene, the scores of every simulated ping."""
    from sonarmap.pipeline import process_ping

    sims = [(scene, sim) for scene in scenes for sc in sim_configs
            for sim in _simulate_seeds(scene, geometry, sc, seeds, empty_snr_db, recording_meta)]
    out: dict[str, dict[str, list[PingScore]]] = {}
    for name, cfg in configs.items():
        per: dict[str, list[PingScore]] = {}
        for scene, (sim, empty) in sims:
            prod = process_ping(sim.ping, cfg, keep_labels=True)
            per.setdefault(scene, []).append(_score_sim(prod, sim, empty, tol_bins, truth))
        out[name] = per
    return out


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
    truth: str = "surface",
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
    truth : {"first_return", "surface"}
        Range truth: ``"first_return"`` the integer first structure bin of the class mask
        (``SimResult.first_return_bin``: the earliest bin whose echo clears the truth threshold,
        the convention of the per-pixel first-return pipeline the existing acceptance tables
        were measured with); ``"surface"`` the sub-bin physical surface
        ``SimResult.surface_range_m`` in fractional bins (the leading-edge convention of
        ``DESIGN.md``; :func:`evaluate_ranges`).

    Returns
    -------
    list of MethodScore

    Raises
    ------
    InputError
        For an unknown ``truth``.
    """
    from sonarmap.geometry import preset

    if truth not in TRUTHS:
        raise InputError(f"truth: one of {', '.join(TRUTHS)}, got {truth!r}")
    geom = preset("didson-hf") if geometry is None else geometry
    cfgs = baseline_configs() if configs is None else dict(configs)
    if sim_configs is None:
        sim_configs = default_sim_configs()
    runs = _run(cfgs, scenes, sim_configs, seeds, geom, tol_bins, empty_snr_db, truth)
    out: list[MethodScore] = []
    for name, per in runs.items():
        out.append(pool_scores(name, [x for v in per.values() for x in v]))
        if per_scene:
            out.extend(pool_scores(f"{name} | {scene}", v) for scene, v in per.items())
    return out


#: Presets and scenes of the ranges acceptance (:func:`evaluate_ranges`).
RANGES_PRESETS = ACCEPTANCE_PRESETS
RANGES_SCENES = ("hull", "hull_slope2", "hull_slope4", "hull_slope8", "curved_hull", "propeller", "seafloor",
                 "fish_over_hull", "fish", "empty")
#: Row suffix of the noise-free leading edges (``evaluate_ranges(noise_free=True)``).
NOISE_FREE = " | noise-free leading edge"
#: Row suffixes of the Cramér-Rao bound (``evaluate_ranges(bound=True)``, :mod:`sonarmap.evaluate.bound`):
#: one beam's samples, and a straight surface over the 7 beams around (the pooled edges' window).
BOUND_BEAM = " | bound, one beam"
BOUND_POOLED = " | bound, 7 beams"
BOUND_POOL_BEAMS = 3
#: Row suffixes of the range convention read on the recorded echoes aligned on the truth
#: (``evaluate_ranges(recorded=True)``, :mod:`sonarmap.evaluate.convention`), by the beams pooled on
#: either side.
RECORDED = {0: " | recorded convention, 1 beam", 3: " | recorded convention, 7 beams",
            10: " | recorded convention, 21 beams"}
#: Sloped-hull scenes (2-8 bins of range change per beam) pooled for the sloped-recall figure.
SLOPED_SCENES = ("hull_slope2", "hull_slope4", "hull_slope8")


@dataclasses.dataclass(frozen=True)
class RangesReport:
    """The ranges acceptance: per-preset (and per preset and scene) scores and two figures.

    Attributes
    ----------
    rows : tuple of MethodScore
        ``"<preset>"`` (all scenes) and ``"<preset> | <scene>"`` rows.
    sloped : MethodScore
        Pooled over every preset's sloped-hull scenes (:data:`SLOPED_SCENES`): its ``recall`` is
        the "sloped (2-8 bins/beam) recall within 3 bins".
    fish_over_hull : MethodScore
        Pooled over every preset's ``fish_over_hull`` pings: its ``hull_under_fish`` is the
        "hull reported under fish" figure.
    """

    rows: tuple[MethodScore, ...]
    sloped: MethodScore
    fish_over_hull: MethodScore

    def table(self, *, per_scene: bool = False, noise_free: bool = False, bound: bool = False,
              recorded: bool = False) -> str:
        """The per-preset markdown table (with ``per_scene``, also the scene rows; with
        ``noise_free``, the noise-free leading-edge rows; with ``bound``, the Cramér-Rao bound's
        rows, per scene too with ``per_scene``; with ``recorded``, the rows of the convention read
        on the recorded echoes) and the figures."""
        rows = [r for r in self.rows if _shown(r.method, per_scene, noise_free, bound, recorded)]
        s, f = self.sloped, self.fish_over_hull
        lines = [format_table(rows), ""]
        # (a figure whose scenes were not evaluated has no beams: left out rather than printed as nan)
        if s.n_struct_beams:
            lines.append(f"sloped (2-8 bins/beam) recall within 3 bins: {s.recall:.3f} (within 1 bin "
                         f"{s.recall_1bin:.3f}, median signed error {s.median_signed_error_bins:+.2f} bins, "
                         f"{s.n_struct_beams} beams)")
        if f.n_fish_beams:
            lines.append(
                f"hull reported under fish (within 3 bins): {f.hull_under_fish:.3f} ({f.n_fish_beams} beams with "
                f"fish in front of the hull; the fish reported first on {f.fish_first_under_fish:.3f}, no return on "
                f"{f.no_return_under_fish:.3f}, another range (more than 3 bins from the hull) on "
                f"{1.0 - f.hull_under_fish - f.fish_first_under_fish - f.no_return_under_fish:.3f})")
        lines += _local_offset_lines(self.rows, per_scene)
        return "\n".join(lines)


def _local_offset_lines(rows: Sequence[MethodScore], per_scene: bool) -> list[str]:
    """The ``recall_1bin_local`` figure of the preset rows (with ``per_scene``, a line of each
    preset's scene rows under it); none when no row has one."""
    # the preset and (per_scene) scene rows the table shows: not the noise-free or bound rows
    shown = [r for r in rows if _shown(r.method, per_scene, False, False) and math.isfinite(r.recall_1bin_local)]
    presets = [r for r in shown if " | " not in r.method]
    if not presets:
        return []
    lines = ["within 1 bin once each ping's local offset is taken out (each signed error less the median of "
             f"the {2 * LOCAL_OFFSET_HALF_BEAMS + 1} scored beams around it): "
             + ", ".join(f"{r.method} {r.recall_1bin_local:.3f}" for r in presets)]
    for p in presets if per_scene else ():
        scenes = [r for r in shown if r.method.startswith(p.method + " | ")]
        if scenes:
            lines.append(f"  {p.method}: " + ", ".join(f"{r.method.split(' | ')[1]} {r.recall_1bin_local:.3f}"
                                                      for r in scenes))
    return lines


def evaluate_ranges(
    config: Any = None, *, presets: Sequence[str] = RANGES_PRESETS, scenes: Sequence[str] = RANGES_SCENES,
    seeds: Sequence[int] = (0,), noise_steps_db: Sequence[float] = (0.0, 6.0), tol_bins: int = 3,
    noise_free: bool = False, bound: bool = False, recorded: bool = False, jobs: int = 1,
) -> RangesReport:
    """The ranges acceptance: one pipeline on every preset x scene, scored on sub-bin truth.

    Pings: :func:`preset_sim_configs` (each preset's own noise floor and +6 dB, truth threshold
    +6 dB; DIDSON with its measured ghosts) x ``seeds`` x ``scenes``, each declaring its pulse
    and (ARIS) log compression as a recording's header would (``simulate_ping(...,
    recording_meta=True)``), so the pipeline measures echoes as on real data.  Scores as in
    :func:`evaluate` (recall within 3 and 1 bins of ``SimResult.surface_range_m``, median signed
    error in bins, false-return rate on empty beams, sigma coverage when the ranges carry
    ``sigma_m``, hull under fish).

    Parameters
    ----------
    config : PipelineConfig, optional
        The pipeline (default ``PipelineConfig()``).
    presets, scenes : sequence of str
        Sonar presets and simulator scenes.
    seeds : sequence of int
        Simulator seeds.
    noise_steps_db : sequence of float
        Receiver-noise steps over each preset's profile.
    tol_bins : int
        Recall tolerance.
    noise_free : bool
        Also score, as ``"<preset> | noise-free leading edge"`` rows, what an ideal detector
        that follows the range convention reports: per beam the half-peak crossing of the first
        peak of the noise-free, unclipped echo (``SimResult.clean`` rendered with
        ``full_scale_db=300``, :func:`sonarmap.simulate.render.leading_edges_m`) of the same
        scenes, noise levels and seeds, without the scenes with fish (which echo comes first is the tracker's
        decision there, not the convention's).  It tells the part of the error that is the
        convention against this truth (the -3 dB footprint) from the part that noise and the
        estimator add.
    bound : bool
        Also the Cramér-Rao bound of the same pings' ranges (:mod:`sonarmap.evaluate.bound`), as
        ``"<preset> | bound, one beam"`` and ``"<preset> | bound, 7 beams"`` rows (and per scene):
        their recalls are those an unbiased detector at the bound would reach
        (:func:`~sonarmap.evaluate.bound.attainable_recall`), the other columns empty.
    recorded : bool
        Also score, as :data:`RECORDED` rows (``"<preset> | recorded convention, 7 beams"``...),
        the range convention read on the same pings' recorded echoes aligned on the truth over 1, 7
        and 21 beams (:func:`sonarmap.evaluate.convention.recorded_edges_bins`), without the scenes
        with fish: what the convention's half-peak crossing itself carries, with no detection or
        alignment error.
    jobs : int
        Processes scoring the presets' scenes in parallel (the same scores as one at a time).

    Returns
    -------
    RangesReport
    """
    from sonarmap.pipeline import PipelineConfig

    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise InputError(f"jobs: must be an integer >= 1 (got {jobs!r})")
    cfg = PipelineConfig() if config is None else config
    # one task per preset and scene (the Oculus-like preset alone takes most of the time)
    tasks = [(cfg, name, scene, tuple(seeds), tuple(noise_steps_db), tol_bins, noise_free, bound, recorded)
             for name in presets for scene in scenes]
    if jobs > 1 and len(tasks) > 1:
        import concurrent.futures
        import multiprocessing

        with concurrent.futures.ProcessPoolExecutor(min(jobs, len(tasks)),
                                                    mp_context=multiprocessing.get_context("spawn")) as pool:
            done = list(pool.map(_scene_ranges, tasks))
    else:
        done = [_scene_ranges(t) for t in tasks]
    extra = ([NOISE_FREE] if noise_free else []) + (list(RECORDED.values()) if recorded else [])
    return _ranges_report(presets, scenes, done, tol_bins, extra)


def _ranges_report(presets: Sequence[str], scenes: Sequence[str], done: Sequence[tuple[Any, Any, Any]],
                   tol_bins: int, extra: Sequence[str]) -> RangesReport:
    """:func:`evaluate_ranges`' report from its tasks' results (``done``: per preset, then per
    scene, what :func:`_scene_ranges` returns); a row per preset for each row suffix of ``extra``
    (:data:`NOISE_FREE`, :data:`RECORDED`'s) and bound rows where the tasks have bounds."""
    rows: list[MethodScore] = []
    sloped: list[PingScore] = []
    fish: list[PingScore] = []
    for k, name in enumerate(presets):
        mine = done[k * len(scenes):(k + 1) * len(scenes)]
        per = {scene: scores for scene, (scores, _, _) in zip(scenes, mine)}
        rows.append(pool_scores(name, [x for v in per.values() for x in v]))
        rows.extend(pool_scores(f"{name} | {scene}", v) for scene, v in per.items())
        rows.extend(pool_scores(f"{name}{suffix}", [x for _, more, _ in mine for x in more.get(suffix, [])])
                    for suffix in extra)
        rows.extend(_bound_rows(name, [b for _, _, bs in mine for b in bs], tol_bins))
        for scene, (_, _, bs) in zip(scenes, mine):
            rows.extend(_bound_rows(f"{name} | {scene}", bs, tol_bins))
        sloped.extend(x for scene in SLOPED_SCENES for x in per.get(scene, []))
        fish.extend(per.get("fish_over_hull", []))
    return RangesReport(rows=tuple(rows), sloped=pool_scores("sloped hulls", sloped),
                        fish_over_hull=pool_scores("fish_over_hull", fish))


def _scene_ranges(task: tuple[Any, ...]) -> tuple[list[PingScore], dict[str, list[PingScore]], list[Any]]:
    """One preset and scene of :func:`evaluate_ranges` (``task``: config, preset name, scene,
    seeds, noise steps, tolerance, noise_free, bound, recorded): its pings' scores, the reference
    edges' by row suffix (:data:`NOISE_FREE` with ``noise_free``, :data:`RECORDED`'s with
    ``recorded``; none for the scenes with fish) and the pings' range bounds
    (:class:`~sonarmap.evaluate.bound.RangeBound`; empty without ``bound``)."""
    from sonarmap.geometry import preset

    cfg, name, scene, seeds, noise_steps_db, tol_bins, noise_free, bound, recorded = task
    geom = preset(name)
    sims = preset_sim_configs(geom, noise_steps_db)
    per = _run({name: cfg}, [scene], sims, seeds, geom, tol_bins, -3.0, "surface", recording_meta=True)[name]
    more: dict[str, list[PingScore]] = {}
    if not scene.startswith("fish"):
        if noise_free:
            more[NOISE_FREE] = _noise_free_scores([scene], sims, seeds, geom, tol_bins)
        if recorded:
            more.update(_recorded_scores(scene, sims, seeds, geom, tol_bins))
    return per.get(scene, []), more, (_bounds(scene, sims, seeds, geom) if bound else [])


def _recorded_scores(scene: str, sim_configs: Sequence[Any], seeds: Sequence[int], geometry: Any,
                     tol_bins: int) -> dict[str, list[PingScore]]:
    """Scores of the range convention read on the recorded echoes aligned on the truth
    (``evaluate_ranges(recorded=True)``), by :data:`RECORDED` row suffix."""
    from sonarmap.evaluate.convention import recorded_edges_bins
    from sonarmap.ranges.measure import pulse_bins

    out: dict[str, list[PingScore]] = {suffix: [] for suffix in RECORDED.values()}
    grid = np.arange(geometry.n_bins, dtype=np.float64)
    for sc in sim_configs:
        for sim, _ in _simulate_seeds(scene, geometry, sc, seeds, -3.0, True):
            pb = pulse_bins(sim.ping)
            for half, suffix in RECORDED.items():
                edge = recorded_edges_bins(sim, half_beams=half, pulse_bins=pb)
                out[suffix].append(_reference_score(sim, np.interp(edge, grid, geometry.range_m, left=np.nan,
                                                                   right=np.nan), geometry, tol_bins))
    return out


def _bounds(scene: str, sim_configs: Sequence[Any], seeds: Sequence[int], geometry: Any) -> list[Any]:
    """The range bounds of the pings :func:`evaluate_ranges` scores (the same configurations and
    seeds), each with its unclipped echo (the ping rendered with full scale at 300 dB, scaled back)."""
    from sonarmap.evaluate.bound import range_bound

    out = []
    for sc in sim_configs:
        for (sim, _), high in zip(_simulate_seeds(scene, geometry, sc, seeds, -3.0, True),
                                  _unclipped_seeds(scene, geometry, sc, seeds), strict=True):
            echo = high.clean.astype(np.float64) * 10.0 ** ((UNCLIPPED_FULL_SCALE_DB - sim.config.full_scale_db) / 10.0)
            out.append(range_bound(sim, echo=echo, pool_beams=BOUND_POOL_BEAMS))
    return out


#: Full scale (dB) of the unclipped renders: far above every echo (the recorded pings clip bright echoes).
UNCLIPPED_FULL_SCALE_DB = 300.0


def _unclipped_seeds(scene: str, geometry: Any, sim_config: Any, seeds: Sequence[int]) -> list[Any]:
    """Each seed's ping of ``scene`` rendered with full scale at :data:`UNCLIPPED_FULL_SCALE_DB` - the
    same echoes, none clipped (``clean`` in intensities ``10^((300 - full_scale_db) / 10)`` times
    smaller than the recorded ping's); the scene's echo rendered once."""
    high = dataclasses.replace(sim_config, full_scale_db=UNCLIPPED_FULL_SCALE_DB)
    return [sim for sim, _ in _simulate_seeds(scene, geometry, high, seeds, -3.0, True)]


def _bound_rows(method: str, bounds: Sequence[Any], tol_bins: int) -> list[MethodScore]:
    """The two bound rows of ``method``'s pings: the recalls (within ``tol_bins`` and 1 bin) an
    unbiased detector at the bound would reach, over the beams with a truth surface (none when
    the pings have none)."""
    from sonarmap.evaluate.bound import attainable_recall

    out = []
    for suffix, field in ((BOUND_BEAM, "sd_bins"), (BOUND_POOLED, "pooled_sd_bins")):
        sd = np.concatenate([getattr(b, field) for b in bounds]) if bounds else np.zeros(0)
        sd = sd[~np.isnan(sd)]
        if sd.size == 0:
            continue
        out.append(MethodScore(method=f"{method}{suffix}", n_pings=len(bounds), pixel_f1=math.nan,
                               recall=attainable_recall(sd, float(tol_bins)), median_error_m=math.nan,
                               false_return_rate=math.nan, n_struct_beams=int(sd.size), n_empty_beams=0,
                               recall_1bin=attainable_recall(sd, 1.0)))
    return out


def _noise_free_scores(scenes: Sequence[str], sim_configs: Sequence[Any], seeds: Sequence[int], geometry: Any,
                       tol_bins: int) -> list[PingScore]:
    """Scores of the noise-free echoes' half-peak leading edges (``evaluate_ranges(noise_free=True)``)."""
    from sonarmap.simulate.render import leading_edges_m

    out = []
    for scene in scenes:
        for sc in sim_configs:
            for sim in _unclipped_seeds(scene, geometry, sc, seeds):
                out.append(_reference_score(sim, leading_edges_m(sim.clean, geometry), geometry, tol_bins))
    return out


def _reference_score(sim: Any, range_m: NDArray[np.float64], geometry: Any, tol_bins: int) -> PingScore:
    """The score of reference edges ``range_m`` (per beam, NaN: none) against ``sim``'s surface
    truth: no detection threshold made them, so no beam is scored for false returns."""
    b = np.where(np.isfinite(range_m), np.searchsorted(geometry.range_m, range_m), -1).astype(np.int64)
    return score_ping(None, b, range_m, sim.class_mask, sim.first_return_bin, sim.first_return_range_m,
                      tol_bins=tol_bins, empty_beams=np.zeros(range_m.size, dtype=bool),
                      surface_range_m=sim.surface_range_m, bin_range_m=geometry.range_m)


def _shown(method: str, per_scene: bool, noise_free: bool, bound: bool, recorded: bool = False) -> bool:
    """Whether :meth:`RangesReport.table` shows the row ``method``."""
    if method.endswith(NOISE_FREE):
        return noise_free
    if method.endswith(tuple(RECORDED.values())):
        return recorded
    if method.endswith((BOUND_BEAM, BOUND_POOLED)):
        return bound and (per_scene or method.count(" | ") == 1)
    return per_scene or " | " not in method


def _fmt(x: float, spec: str = ".3f") -> str:
    return "-" if not math.isfinite(x) else format(x, spec)


def format_table(scores: Sequence[MethodScore]) -> str:
    """Markdown table of scores (``-`` where a figure is undefined, e.g. no sigma)."""
    lines = [
        "| method | pings | pixel F1 | recall (3 bins) | recall (1 bin) | median error (m) | "
        "median signed error (bins) | false-return rate | sigma coverage |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in scores:
        lines.append(
            f"| {s.method} | {s.n_pings} | {_fmt(s.pixel_f1)} | {_fmt(s.recall)} | {_fmt(s.recall_1bin)} | "
            f"{_fmt(s.median_error_m)} | {_fmt(s.median_signed_error_bins, '+.2f')} | "
            f"{_fmt(s.false_return_rate)} | {_fmt(s.sigma_coverage)} |"
        )
    return "\n".join(lines)

