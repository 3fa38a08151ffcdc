"""Map accuracy of a simulated survey against its truth: registration error, coverage, voxel IoU.

The simulated surveys themselves are :mod:`sonarmap.simulate.survey`; this module scores what
the pipeline and the mapping stage made of them (registered points against the analytic surface,
occupancy maps of each sensor model against the truth voxels).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.simulate.survey import SimSurvey, surface_distance

__all__ = [
    "RegistrationAccuracy",
    "registration_accuracy",
    "truth_voxels",
    "SurveyEvaluation",
    "SURVEY_MODELS",
    "evaluate_survey",
]


@dataclasses.dataclass(frozen=True)
class RegistrationAccuracy:
    """Registered points against the true surface.

    Attributes
    ----------
    rms_m : float
        RMS distance of the registered points to the true surface.
    rms_bins : float
        ``rms_m`` in range bins.
    p95_m : float
        95th percentile of the distances.
    coverage : float
        Fraction of the visible surface (truth returns) with a registered point within
        ``tolerance_m``.
    tolerance_m : float
    n_points, n_visible : int
    """

    rms_m: float
    rms_bins: float
    p95_m: float
    coverage: float
    tolerance_m: float
    n_points: int
    n_visible: int


def registration_accuracy(survey: SimSurvey, points_m: ArrayLike, *, tolerance_m: float | None = None) -> RegistrationAccuracy:
    """Accuracy and coverage of registered world points against a survey's truth.

    ``tolerance_m`` defaults to 3 range bins (about the beam spacing at the survey's standoff).
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    dr = survey.geometry.range_resolution_m
    tol = 3 * dr if tolerance_m is None else float(tolerance_m)
    vis = survey.visible_points_m
    if p.shape[0] == 0:
        return RegistrationAccuracy(float("nan"), float("nan"), float("nan"), 0.0, tol, 0, int(vis.shape[0]))
    d = surface_distance(survey.surface, p)
    rms = float(np.sqrt(np.mean(d**2)))
    dist, _ = cKDTree(p).query(vis, k=1, distance_upper_bound=tol)
    cov = float(np.mean(np.isfinite(dist))) if vis.shape[0] else float("nan")
    return RegistrationAccuracy(rms, rms / dr, float(np.percentile(d, 95)), cov, tol, int(p.shape[0]), int(vis.shape[0]))


def truth_voxels(survey: SimSurvey, resolution_m: float, *, dims: int = 3) -> NDArray[np.int64]:
    """Cells (n, 3) holding the visible true surface: the occupied cells an ideal map would have."""
    from sonarmap.mapping.occupancy import voxelize

    return voxelize(survey.visible_points_m, resolution_m, dims=dims)


# ============================================================================ end-to-end evaluation
@dataclasses.dataclass(frozen=True)
class SurveyEvaluation:
    """Pipeline + mapping against a simulated survey's truth.

    Attributes
    ----------
    accuracy : RegistrationAccuracy
        Registered points of the pipeline's ranges.
    iou : dict
        ``{(resolution_m, model): IoU}`` for the models of :data:`SURVEY_MODELS` evaluated.
    mean_pd, mean_pfa : float
        Mean of the pings' range-measurement pD (``pd_range``, over pings where it is defined)
        and per-pixel pFA.
    """

    accuracy: RegistrationAccuracy
    iou: dict[tuple[float, str], float]
    mean_pd: float
    mean_pfa: float


#: Sensor models :func:`evaluate_survey` can compare.
SURVEY_MODELS = (
    "pd/pfa", "fixed 0.8/0.3", "fixed 0.8/0.3, OctoMap clamps", "pd/pfa per pixel", "fixed, pings with returns",
)


def _model_setups(pd: np.ndarray, pd_range: np.ndarray, pfa: np.ndarray, ranges: Sequence[Any],
                  range_resolution_m: float) -> dict[str, tuple[NDArray[np.bool_], dict[str, Any], dict[str, float]]]:
    """Per sensor model of :func:`evaluate_survey`: the pings integrated, the ``integrate()``
    keywords and the :class:`OccupancyConfig` overrides."""
    from sonarmap.mapping.occupancy import OCTOMAP_CLAMP_LOGODDS, SensorModel

    fixed = SensorModel.fixed(0.8, 0.3)
    every = np.ones(len(ranges), dtype=bool)
    with_returns = np.array([r.n_returns > 0 for r in ranges])
    octomap = dict(zip(("l_min", "l_max"), OCTOMAP_CLAMP_LOGODDS, strict=True))
    return {
        "pd/pfa": (every, {"pd": pd_range, "pfa": pfa, "range_resolution_m": range_resolution_m}, {}),
        "fixed 0.8/0.3": (every, {"model": fixed}, {}),
        "fixed 0.8/0.3, OctoMap clamps": (every, {"model": fixed}, octomap),
        "pd/pfa per pixel": (every, {"pd": pd, "pfa": pfa, "range_resolution_m": range_resolution_m,
                                     "use_p_detect": False}, {}),
        "fixed, pings with returns": (with_returns, {"model": fixed}, {}),
    }


def evaluate_survey(
    survey: SimSurvey,
    *,
    pipeline_config: Any = None,
    resolutions_m: tuple[float, ...] = (0.05, 0.1),
    products: list[Any] | None = None,
    n_elevation: int = 1,
    elevation_ambiguity: bool = False,
    models: tuple[str, ...] = ("pd/pfa", "fixed 0.8/0.3", "fixed 0.8/0.3, OctoMap clamps"),
    registration: Any = None,
) -> SurveyEvaluation:
    """Run the per-ping pipeline on a rendered survey, register and map, and score against truth.

    Registration uses the true sensor poses, so the errors measured are those of the ranges and
    of the zero-elevation assumption; ``registration`` (a
    :class:`~sonarmap.mapping.register.RegistrationConfig`, default ``RegistrationConfig()``) says
    how, with the survey geometry's beamwidth for the footprint edge.  Occupancy IoU compares the occupied cells with
    :func:`truth_voxels` for each resolution and sensor model (:data:`SURVEY_MODELS`):

    * ``"pd/pfa"``: the pD/pFA-driven inverse sensor model with each ping's range-measurement
      ``pd_range`` (each beam's ``BeamRanges.p_detect`` where finite) and per-pixel pFA (turned
      into a per-cell one, range error ``BeamRanges.sigma_m`` where finite, else
      ``OccupancyConfig.range_sigma_bins``; ``n_elevation`` rays spanning the renderer's
      vertical aperture, hits discounted for the arc when ``elevation_ambiguity``); pings with
      ``pd_range = 0`` (every detection rejected by the range rules) or NaN are not integrated;
    * ``"fixed 0.8/0.3"``: ``P(occ|hit) = 0.8``, ``P(occ|miss) = 0.3`` for every ping (a peer's
      constants);
    * ``"fixed 0.8/0.3, OctoMap clamps"``: the same constants with the log-odds clamped to
      OctoMap's ``[0.12, 0.97]`` (:data:`~sonarmap.mapping.occupancy.OCTOMAP_CLAMP_LOGODDS`), as
      a peer running OctoMap would; every other model uses :class:`OccupancyConfig`'s defaults;
    * ``"pd/pfa per pixel"``: as ``"pd/pfa"`` with the per-pixel local-MAP ``pd`` on every beam
      (``p_detect`` ignored; ablation);
    * ``"fixed, pings with returns"``: the constants, skipping pings without any return
      (a heuristic guard, ablation).
    """
    from sonarmap.mapping.occupancy import OccupancyConfig, OccupancyMap, voxel_iou
    from sonarmap.mapping.register import register_ranges

    unknown = set(models) - set(SURVEY_MODELS)
    if unknown:
        raise InputError(f"models: unknown {sorted(unknown)}; choose from {SURVEY_MODELS}")
    if products is None:
        from sonarmap.pipeline import PipelineConfig, process_ping

        cfg = pipeline_config if pipeline_config is not None else PipelineConfig()
        products = [process_ping(p, cfg) for p in survey.pings]
    ranges = [p.ranges for p in products]
    cloud = register_ranges(ranges, survey.poses, azimuth_beamwidth_rad=survey.geometry.azimuth_beamwidth_rad,
                            config=registration)
    acc = registration_accuracy(survey, cloud.xyz_m)
    pd_range = np.array([float(p.pd_range) for p in products])
    pfa = np.array([float(p.pfa) for p in products])
    g = survey.geometry
    aperture = survey.sim_truth[0].config.elevation_aperture_rad if survey.sim_truth else math.radians(1.0)
    pd = np.array([float(p.pd) for p in products])
    setups = _model_setups(pd, pd_range, pfa, ranges, g.range_resolution_m)
    iou: dict[tuple[float, str], float] = {}
    for res in resolutions_m:
        truth = truth_voxels(survey, res)
        for name in models:
            sel, kw, overrides = setups[name]
            kw = {k: v[sel] if isinstance(v, np.ndarray) else v for k, v in kw.items()}
            m = OccupancyMap(OccupancyConfig(resolution_m=res, n_elevation=n_elevation, vertical_aperture_rad=aperture,
                                             elevation_ambiguity=elevation_ambiguity, **overrides))
            m.integrate_ranges([r for r, k in zip(ranges, sel, strict=True) if k], survey.poses.select(sel),
                               min_range_m=g.min_range_m, max_range_m=g.max_range_m, **kw)
            iou[(res, name)] = voxel_iou(m.occupied_cells(), truth)
    return SurveyEvaluation(acc, iou, float(np.nanmean(pd_range)), float(np.nanmean(pfa)))
