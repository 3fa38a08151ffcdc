"""The fused per-ping pipeline and its validated configuration.

``process_ping(ping, config)`` runs, as a pure function of its arguments::

    pre-process (sec. III-IV)  ->  mixture fit (eq. 8-11, 19-21)  ->  classification
    (fixed threshold eq. 14 | local MAP eq. 12-13 | MRF eq. 17-18, 22 | CFAR baselines)
    ->  per-beam ranges (:mod:`sonarmap.ranges`)

and returns a :class:`PingProducts` value.  The default :class:`PipelineConfig` is the most
accurate pipeline measured on the shared DIDSON pings and on simulator truth
(``docs/segmentation.md``): the paper's Table-I pre-processing, an EM fit of the paper's zero
spike + exponential + Rayleigh mixture, an exact graph-cut MRF (4-neighbourhood, ``beta = 2``, range edges x 0.25,
object prior raised to >= 0.2), then first returns from structure components spanning >= 16 beams
or >= 16 bins or holding >= 40 pixels (plus pieces within 4 beams of them), the isolated-return
rule and a leading-edge refinement of up to 8 bins; on the beams that leaves empty, band pooling
(3 bins x 5 beams box mean >= 4x the background mean, >= 40-beam components, strongest pixel per
beam) recovers thin single-look-speckle surface bands.

Images without a zero spike (ARIS, Oculus: anything but a thresholded receiver's output) are
first normalised by their own background level (:mod:`sonarmap.preprocess.normalise`) instead of
the pre-processing recipe, which brings them into the same zero spike + exponential + object
domain; their components must be larger (multi-looked pixels are correlated), band pooling is not
applied and first returns move to the half-peak leading edge of their echo.  A ping whose fit fails
a gate (:mod:`sonarmap.stats.gates`) yields no returns and carries the gate's name.

Degenerate pings (all zero, constant, nothing but background) give no returns, never an error:
their fit flags are carried in :attr:`PingProducts.flags`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap._config import config_table, is_finite_number
from sonarmap.errors import FitError, InputError
from sonarmap.ping import Ping
from sonarmap.ranges import BeamRanges, component_rule, drop_small_components, extract_ranges, half_peak_edges, no_returns

__all__ = ["PipelineConfig", "PingProducts", "process_ping", "classify_image", "pooled_band_pixels", "pooled_band_mask", "pulse_bins", "measurement_image", "METHODS", "SOLVER_NAMES"]

METHODS = ("mrf", "map", "threshold", "cfar-ca", "cfar-so", "cfar-go", "cfar-os")
SOLVER_NAMES = ("graphcut", "icm", "anneal", "expansion")
_PREPROCESS_RECIPES = ("paper-table1", "default", "paper-background", "none")


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Validated configuration of :func:`process_ping` (defaults = the most accurate pipeline).

    Parameters
    ----------
    preprocess : str or PreprocessConfig
        A recipe name (``"paper-table1"``, ``"default"``, ``"paper-background"``, ``"none"``) or an
        explicit :class:`sonarmap.preprocess.pipeline.PreprocessConfig`; applied to images that
        are not normalised (thresholded images such as DIDSON's).
    normalise : str
        ``"auto"``: images without a zero spike (ARIS, Oculus, water column) are normalised by
        their own background level (:mod:`sonarmap.preprocess.normalise`) instead of being
        pre-processed; ``"off"``: always the ``preprocess`` recipe.
    method : str
        ``"mrf"``, ``"map"`` (local MAP), ``"threshold"`` (fixed), or ``"cfar-ca|so|go|os"``.
    solver : str
        MRF solver: ``"graphcut"`` (exact; alpha-expansion for > 2 classes), ``"icm"``,
        ``"anneal"`` (the paper's), ``"expansion"``.
    beta : float
        Potts weight of eq. 22.
    neighbourhood : int
        4 or 8.
    contrast : bool
        Contrast-sensitive pairwise weights.
    range_weight : float
        Factor on the Potts weight along range (anisotropic prior): surfaces are thin in range and
        long across beams; 0.25 keeps 1-3-bin surfaces intact while smoothing across beams.
    object_prior_min : float
        Lower bound on each object class's prior in the MRF unary.  The fitted object weight of
        a ping with a thin, faint surface can be ~0.001 (Table I image 6), which makes the
        posterior reject the surface however clearly it stands out; the Potts prior (not the
        class prior) is then what should suppress speckle.
    speckle_eps : float
        Speckle-robust object likelihood ``(1 - eps) p(y|object) + eps p(y|background)`` in the
        MRF unary (0: the paper's model, where a zero pixel can never be structure).
    grow_prior_min, grow_beta : float
        Hysteresis growth (MRF only; off when ``grow_prior_min`` is 0): a second, more permissive
        cut (object prior raised to ``grow_prior_min``, Potts weight ``grow_beta``) labels faint
        structure, which is kept only where it is 8-connected to the first cut's structure -
        faint low-incidence continuations of a surface are recovered, isolated faint blobs are not.
    families : tuple of str
        Mixture families after the zero spike (background first).
    fit_method : str
        ``"em"`` or ``"lsq"``.
    fit_tol : float
        EM relative log-likelihood tolerance.
    n_levels : int
        Quantisation levels of the histogram.
    threshold : float
        Intensity threshold of ``method="threshold"`` (eq. 14), on the pre-processed image.
    cfar_train, cfar_guard : int
        CFAR training / guard cells along range (total, even); sonar-SLAM: 40 / 10.
    cfar_pfa : float
        CFAR design false-alarm probability (sonar-SLAM: 0.1).
    cfar_two_d : bool
        2-D CFAR window (range x beams).
    range_mode : str
        ``"first"`` or ``"strongest"``.
    min_run : int
        First return: minimum run of consecutive structure bins.
    reject_isolated : bool
        Drop returns without support in neighbouring beams.
    neighbour_beams, max_jump_bins : int
        Support window and range tolerance of the consistency rules.
    min_segment_beams : int
        Drop runs of consistent returns narrower than this many consecutive beams.
    refine_bins, edge_factor : int, float
        Leading-edge refinement of first returns (0 = off): up to ``refine_bins`` bins towards
        the sonar while the local mean intensity is >= ``edge_factor`` x the fitted background
        class's mean intensity.
    min_component_beams, min_component_bins, min_component_pixels : int
        Drop 8-connected structure components spanning fewer than ``min_component_beams`` beams
        *and* fewer than ``min_component_bins`` range bins *and* holding fewer than
        ``min_component_pixels`` pixels (fish, speckle: on the real fish-only pings 1-3 every
        component has <= 25 pixels; a simulated propeller blade seen edge-on, 13-14 beams wide,
        has 55-64).
    link_beams : int
        Keep rejected components within this many beams (and 1 bin) of kept ones.
    normalised_component_beams, normalised_component_bins, normalised_component_pixels : int
        The same three component thresholds for normalised images, whose multi-look box
        correlates neighbouring pixels: i.i.d. exponential speckle of 512 x 96, 2000 x 48 and
        703 x 256 pixels, normalised and segmented, leaves components of at most 65 pixels,
        17 beams and 13 bins (8 seeds each; ``docs/segmentation.md``).
    min_component_extent_m : float
        Drop structure components smaller than this in both cross-range (arc length at their far
        edge) and range extent: fish, particles and interference dashes, whatever the beam count
        (0 = off).
    pool_mode : str
        ``"fill"``: band pooling adds returns on the beams the per-pixel route left empty (its
        returns are kept as they are); ``"fallback"``: only when the per-pixel route found fewer
        than ``pool_min_beams`` returns, on every beam.
    pool_factor, pool_beams, pool_bins, pool_min_beams : float, int, int, int
        Band pooling (off when ``pool_factor`` is 0): the pre-processed image is averaged over a
        box of ``pool_bins`` range bins x ``2 pool_beams + 1`` beams (multi-look across beams),
        thresholded at ``pool_factor`` x the fitted background class's mean intensity, and its
        8-connected components spanning >= ``pool_min_beams`` beams are surfaces; on each of
        their beams the strongest pixel of the component's first run is a structure pixel that
        bypasses the component rule (no leading-edge refinement).  Recovers thin surface bands
        of single-look speckle that the per-pixel model leaves in fragments of 0-5 pixels per
        beam; fish schools and speckle do not span ``pool_min_beams`` beams.  Not applied to
        normalised images, which are multi-looked already.
    edge_fraction : float
        The range convention: a return's range is the first crossing of this fraction of its
        echo's first peak (:mod:`sonarmap.ranges.echoes`).  With ``tracker="rules"`` it applies to
        normalised images only (0 = the first structure pixel).
    tracker : str
        ``"surface"``: per-beam echoes of the candidate structure, tracked across beams by the
        surface model (:mod:`sonarmap.ranges.tracking`); every return is an echo's leading edge
        with a sigma.  ``"rules"``: the previous per-beam rules (isolated-return rule,
        leading-edge refinement, band pooling at the band's peak), kept for comparison.
    track : TrackConfig or dict, optional
        Costs of the surface model (default :class:`sonarmap.ranges.tracking.TrackConfig`).
    pulse_length_m : float, optional
        Transmit pulse length along range (``c tau / 2``); echoes are measured on the image
        smoothed over it.  Default: from the ping (``meta["pulse_width_us"]``, ARIS), else none.
    edge_scan : str
        How the leading-edge crossing is found (:func:`sonarmap.ranges.echoes.find_echoes`):
        ``"back"`` (walk from the first peak towards the sonar to the first bin below the level;
        better on the simulated ARIS pings) or ``"forward"`` (the first bin from in front of the
        echo that reaches the level).
    edge_pool_beams : int
        Leading edges of a tracked surface are measured on the mean of the edge-aligned profiles
        of the ``edge_pool_beams`` beams on either side of each beam on the same surface
        (:func:`sonarmap.ranges.echoes.pooled_edges`: a multi-look along the surface; a single
        beam's speckled echo moves its half-peak crossing by bins).  0 = every beam on its own.
    continue_evidence : float
        Surface continuation (:func:`sonarmap.ranges.tracking.continuation_mask`): a tracked
        surface of >= 5 beams is followed beyond its ends along its slope where, in a window of its
        echo thickness, the pixels' log-likelihood ratio under the ping's fit sums to at least this
        many nats (a faint stretch the component rule left without candidates); those pixels
        become candidates and the surfaces are tracked again.  0 = off.
    sigma_scale : float
        Calibration of the speckle-jitter term of the sigma of a return measured on its own beam
        (``edge_pool_beams=0``, or a surface of fewer than 3 beams;
        :func:`sonarmap.ranges.echoes.range_sigma_m`), fitted on the simulator with the per-beam
        edges: with 1.5, 73 % of the errors of returns on their surface (within 3 bins) lay
        within +-sigma over the four sonar presets.  A return on the wrong echo is not covered by
        its sigma.
    sigma_pool_scale : float
        Sigma of a pooled leading edge (:func:`sonarmap.ranges.echoes.edge_sigma_m`): the mean
        profile's standard error at the crossing over its rise per bin, times this factor
        (neighbouring beams share speckle through the main lobe and their windows overlap),
        fitted on the simulator so that 68 % of the errors lie within +-sigma
        (``docs/segmentation.md``).  Every return's sigma also covers the clipping of its echo
        (:data:`CLIP_LEVEL`: the interval from the crossing to the first sample at full scale).
    log_dynamic_range_db : float, optional
        The raw samples are log-compressed, ``dynamic range`` dB per unit of pixel value (ARIS):
        echoes of normalised images are measured in linear intensity.  Default: the ping's
        ``meta["log_dynamic_range_db"]``, else linear samples.
    max_kld, max_object_weight, min_separation : float
        Fit gates (:func:`sonarmap.stats.gates.fit_gates`): a ping whose fit fails one yields no
        returns and carries the gate's name in its flags.
    max_floor_levels : int
        The quantisation floor.  An 8-bit ping whose fit fails the KL-divergence gate is modelled
        again with the lowest ``n = 1, 2, ..`` levels of the image the classifier sees merged into
        the zero level (its level histogram shifted down by ``n`` and refitted; the image shifted
        by ``n`` levels, clamped at 0), up to this many; the first ``n`` whose fit passes every
        gate is used and reported as :attr:`PingProducts.floor_levels`.  A ping that no floor
        explains costs ``max_floor_levels`` further histogram fits.  A background
        whose bulk lies on the bottom two or three levels of the 8-bit grid (the dark water column
        of an Oculus after its automatic gain has lowered the gain for a bright hull) has no shape
        the grid resolves - its histogram falls by 5-30x per level, an exponential of less than
        one level - and the mixture's zero spike then takes it as it takes a thresholded
        receiver's zeros.  Pings whose first fit passes (every DIDSON, ARIS, Oculus and Kongsberg
        recording) are unchanged.  0 = off.
    """

    preprocess: Any = "paper-table1"
    normalise: str = "auto"
    method: str = "mrf"
    solver: str = "graphcut"
    beta: float = 2.0
    neighbourhood: int = 4
    contrast: bool = False
    range_weight: float = 0.25
    object_prior_min: float = 0.2
    speckle_eps: float = 0.0
    grow_prior_min: float = 0.0
    grow_beta: float = 1.0
    families: tuple[str, ...] = ("exponential", "rayleigh")
    fit_method: str = "em"
    fit_tol: float = 1e-6
    n_levels: int = 256
    threshold: float = 0.3
    cfar_train: int = 40
    cfar_guard: int = 10
    cfar_pfa: float = 0.1
    cfar_two_d: bool = False
    range_mode: str = "first"
    min_run: int = 1
    reject_isolated: bool = True
    neighbour_beams: int = 2
    max_jump_bins: int = 20
    min_segment_beams: int = 1
    min_component_beams: int = 16
    min_component_bins: int = 16
    link_beams: int = 4
    min_component_pixels: int = 40
    normalised_component_beams: int = 24
    normalised_component_bins: int = 24
    normalised_component_pixels: int = 100
    min_component_extent_m: float = 0.02
    refine_bins: int = 8
    edge_factor: float = 4.0
    pool_factor: float = 4.0
    pool_beams: int = 2
    pool_bins: int = 3
    pool_min_beams: int = 40
    pool_mode: str = "fill"
    max_kld: float = 0.05
    max_floor_levels: int = 4
    edge_fraction: float = 0.5
    tracker: str = "surface"
    track: Any = None
    pulse_length_m: float | None = None
    edge_scan: str = "back"
    edge_pool_beams: int = 3
    continue_evidence: float = 10.0
    sigma_scale: float = 1.5
    sigma_pool_scale: float = 5.0
    log_dynamic_range_db: float | None = None
    max_object_weight: float = 0.5
    min_separation: float = 1.9

    def __post_init__(self) -> None:
        self._coerce_stage_configs()
        self._check_choices()
        self._check_reals()
        self._check_integers()

    def _bad(self, key: str, what: str) -> InputError:
        """The error for option ``key`` holding an invalid value."""
        return InputError(f"pipeline config: {key}: {what} (got {getattr(self, key)!r})")

    def _coerce_stage_configs(self) -> None:
        """``preprocess`` and ``track``: a recipe name or a stage config (tables become configs)."""
        from sonarmap.preprocess.pipeline import PreprocessConfig

        pre = self.preprocess
        if isinstance(pre, dict):
            object.__setattr__(self, "preprocess", PreprocessConfig.from_dict(pre))
        elif isinstance(pre, str):
            if pre not in _PREPROCESS_RECIPES:
                raise self._bad("preprocess", f"must be one of {', '.join(_PREPROCESS_RECIPES)} or a table")
        elif not isinstance(pre, PreprocessConfig):
            raise self._bad("preprocess", "must be a recipe name or a preprocess table")
        from sonarmap.ranges.tracking import TrackConfig

        if self.track is None:
            object.__setattr__(self, "track", TrackConfig())
        elif isinstance(self.track, dict):
            object.__setattr__(self, "track", TrackConfig(**config_table(self.track, TrackConfig,
                                                                         "pipeline config: track")))
        elif not isinstance(self.track, TrackConfig):
            raise self._bad("track", "must be a track table")

    def _check_choices(self) -> None:
        """The named choices (tracker, edge scan, normalisation, method, solver) and optional lengths."""
        if self.tracker not in ("surface", "rules"):
            raise self._bad("tracker", "must be 'surface' or 'rules'")
        if self.edge_scan not in ("forward", "back"):
            raise self._bad("edge_scan", "must be 'forward' or 'back'")
        for key, positive in (("log_dynamic_range_db", True), ("pulse_length_m", False)):
            v = getattr(self, key)
            if v is None:
                continue
            if not is_finite_number(v) or (v <= 0 if positive else v < 0):
                raise self._bad(key, "must be a finite number > 0" if positive else "must be a finite number >= 0")
            object.__setattr__(self, key, float(v))
        if self.normalise not in ("auto", "off"):
            raise self._bad("normalise", "must be 'auto' or 'off'")
        if self.method not in METHODS:
            raise self._bad("method", f"must be one of {', '.join(METHODS)}")
        if self.solver not in SOLVER_NAMES:
            raise self._bad("solver", f"must be one of {', '.join(SOLVER_NAMES)}")

    def _check_reals(self) -> None:
        """The real-valued options: finite (stored as float) and within their ranges."""
        for key in ("beta", "fit_tol", "threshold", "cfar_pfa", "object_prior_min", "grow_prior_min",
                    "grow_beta", "speckle_eps", "edge_factor", "range_weight", "pool_factor",
                    "min_component_extent_m", "max_kld", "max_object_weight", "min_separation",
                    "edge_fraction", "sigma_scale", "sigma_pool_scale", "continue_evidence"):
            v = getattr(self, key)
            if not is_finite_number(v):
                raise self._bad(key, "must be a finite number")
            object.__setattr__(self, key, float(v))
        if self.beta < 0:
            raise self._bad("beta", "must be >= 0")
        for key in ("object_prior_min", "grow_prior_min", "speckle_eps"):
            if not 0 <= getattr(self, key) < 0.5:
                raise self._bad(key, "must lie in [0, 0.5)")
        if self.pool_factor < 0:
            raise self._bad("pool_factor", "must be >= 0")
        for key in ("sigma_scale", "sigma_pool_scale", "continue_evidence"):
            if getattr(self, key) < 0:
                raise self._bad(key, "must be >= 0")
        if not 0 <= self.edge_fraction < 1:
            raise self._bad("edge_fraction", "must lie in [0, 1)")
        if self.min_component_extent_m < 0:
            raise self._bad("min_component_extent_m", "must be >= 0")
        if self.grow_beta < 0:
            raise self._bad("grow_beta", "must be >= 0")
        if not 0 <= self.range_weight <= 1:
            raise self._bad("range_weight", "must lie in [0, 1]")
        if self.fit_tol <= 0:
            raise self._bad("fit_tol", "must be > 0")
        if not 0 < self.cfar_pfa < 1:
            raise self._bad("cfar_pfa", "must lie in (0, 1)")

    def _check_integers(self) -> None:
        """The integer and boolean options, the remaining choices and the families."""
        for key, lo in (("neighbourhood", 4), ("n_levels", 2), ("cfar_train", 2), ("cfar_guard", 0),
                        ("min_run", 1), ("neighbour_beams", 1), ("max_jump_bins", 0),
                        ("min_segment_beams", 1), ("min_component_beams", 1),
                        ("min_component_bins", 1), ("min_component_pixels", 0),
                        ("normalised_component_beams", 1), ("normalised_component_bins", 1),
                        ("normalised_component_pixels", 0), ("refine_bins", 0), ("link_beams", 0),
                        ("pool_beams", 0), ("pool_bins", 1), ("pool_min_beams", 1), ("edge_pool_beams", 0),
                        ("max_floor_levels", 0)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise self._bad(key, f"must be an integer >= {lo}")
        if self.neighbourhood not in (4, 8):
            raise self._bad("neighbourhood", "must be 4 or 8")
        if self.cfar_train % 2 or self.cfar_guard % 2:
            raise self._bad("cfar_train" if self.cfar_train % 2 else "cfar_guard", "must be even")
        for key in ("contrast", "cfar_two_d", "reject_isolated"):
            if not isinstance(getattr(self, key), bool):
                raise self._bad(key, "must be true or false")
        if self.pool_mode not in ("fallback", "fill"):
            raise self._bad("pool_mode", "must be 'fallback' or 'fill'")
        if self.fit_method not in ("em", "lsq"):
            raise self._bad("fit_method", "must be 'em' or 'lsq'")
        if self.range_mode not in ("first", "strongest"):
            raise self._bad("range_mode", "must be 'first' or 'strongest'")
        fams = self.families
        if isinstance(fams, str) or not isinstance(fams, list | tuple) or len(fams) < 2:
            raise self._bad("families", "must be a list of at least two family names")
        object.__setattr__(self, "families", tuple(str(f) for f in fams))

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON/TOML-compatible dict; :meth:`from_dict` reads it back."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["families"] = list(self.families)
        if not isinstance(self.preprocess, str):
            d["preprocess"] = self.preprocess.to_dict()
        d["track"] = dataclasses.asdict(self.track)
        for key in ("pulse_length_m", "log_dynamic_range_db"):
            if d[key] is None:
                del d[key]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PipelineConfig:
        """Build from a dict; unknown keys or bad values raise :class:`InputError` naming the key.

        A nested ``{"pipeline": {...}}`` table (TOML) is accepted.
        """
        return cls(**config_table(d, cls, "pipeline config", section="pipeline"))

    @classmethod
    def from_toml(cls, path: str | os.PathLike[str]) -> PipelineConfig:
        """Read a TOML file (top-level keys or a ``[pipeline]`` table)."""
        p = Path(path)
        try:
            d = tomllib.loads(p.read_text(encoding="utf-8"))
        except OSError as exc:
            raise InputError(f"{p}: cannot read pipeline config ({exc.strerror or exc})") from None
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"{p}: invalid TOML ({exc})") from None
        try:
            return cls.from_dict(d)
        except InputError as exc:
            raise InputError(f"{p}: {exc}") from None

    def replace(self, **changes: Any) -> PipelineConfig:
        """Copy with fields replaced (validated)."""
        return dataclasses.replace(self, **changes)

    def preprocess_config(self) -> Any:
        """The :class:`PreprocessConfig` used, or None for ``"none"``."""
        from sonarmap.preprocess.pipeline import PreprocessConfig, recipe

        if isinstance(self.preprocess, PreprocessConfig):
            return self.preprocess
        return None if self.preprocess == "none" else recipe(self.preprocess)


@dataclasses.dataclass(frozen=True, eq=False)
class PingProducts:
    """Everything the per-ping pipeline produces.

    Attributes
    ----------
    time_ns, source
        From the ping.
    fit : MixtureFit or None
        The fitted mixture (None if it could not be computed, e.g. an all-zero ping).
    kld : float
        KL divergence of the fit (eq. 11); NaN without a fit.
    flags : tuple of str
        Fit flags plus pipeline flags (``"no_fit"``, ``"no_returns"``).
    ranges : BeamRanges
        Per-beam returns.
    labels : ndarray of uint8 or None
        Label image (only with ``keep_labels=True``).
    pd, pfa : float
        Detection and false-alarm probabilities of the per-pixel decision under the fitted model
        (eq. 15-16): for the MRF those of its unary's per-pixel decision (object prior raised to
        ``object_prior_min``), for MAP those of the local MAP rule, for the fixed threshold those
        of the threshold; CFAR reports its design pFA and NaN pD.
    method : str
        Classification method.
    pd_range : float
        Detection probability of the ping's *range measurement*, the input of the occupancy
        map's pD/pFA model: ``pd`` times the fraction of the beams with any classifier detection
        (or a return) that kept a return, i.e. the chance that a surface in a beam is both
        detected per pixel and reported as the beam's return.  A ping whose detections were all
        rejected by the range rules (echoes too weak to form a surface: aeration, dropouts) gets
        0, so the map learns nothing from its empty beams.  NaN without a fit or a finite
        ``pd`` (CFAR).
    background : BackgroundLevel or None
        What the background normalisation estimated (:mod:`sonarmap.preprocess.normalise`);
        ``applied`` is False for thresholded images.
    gates : tuple of str
        Fit gates the ping failed (:data:`sonarmap.stats.gates.GATE_DESCRIPTIONS`); a gated ping
        has no returns.  Also part of ``flags``.
    image : ndarray of float32 or None
        The image the classifier saw (normalised or pre-processed; only with ``keep_labels=True``).
    floor_levels : int
        Levels of the classifier's image merged into its zero level before it was modelled (the
        quantisation floor, :attr:`PipelineConfig.max_floor_levels`); 0 for an image modelled as
        it came.
    input_gain_db : float
        The automatic input gain applied after the sidelobe suppression
        (:func:`sonarmap.preprocess.normalise.input_gain` and ``suppress_sidelobes``); 0 for 8-bit
        images.  The ranges' ``intensity`` is in the gained units.
    """

    time_ns: int
    source: str
    fit: Any
    kld: float
    flags: tuple[str, ...]
    ranges: BeamRanges
    labels: NDArray[np.uint8] | None
    pd: float
    pfa: float
    method: str = "mrf"
    pd_range: float = math.nan
    background: Any = None
    gates: tuple[str, ...] = ()
    image: NDArray[np.float32] | None = None
    input_gain_db: float = 0.0
    floor_levels: int = 0

    @property
    def flagged(self) -> bool:
        """True when the model cannot explain the ping (a gate of
        :data:`sonarmap.stats.gates.IMPLAUSIBLE`); such a ping has no returns."""
        from sonarmap.stats.gates import IMPLAUSIBLE

        return bool(set(self.gates) & IMPLAUSIBLE)


def _fit(levels: NDArray[Any], config: PipelineConfig) -> Any:
    if levels.ndim == 2 and levels.dtype.kind == "u":
        from sonarmap._pipeline_kernels import level_counts

        counts = level_counts(levels, int(config.n_levels))
    else:
        counts = np.bincount(levels.ravel(), minlength=config.n_levels).astype(np.float64)
    return _fit_counts(counts, config)


def _fit_counts(counts: NDArray[np.float64], config: PipelineConfig) -> Any:
    """The per-ping mixture fit of a level histogram (None when it cannot be computed)."""
    from sonarmap.stats.mixture import fit_mixture

    try:
        return fit_mixture(counts, families=config.families, method=config.fit_method,  # type: ignore[arg-type]
                           n_levels=config.n_levels, tol=config.fit_tol)
    except FitError:
        return None


def _class_prior(fit: Any, prior_min: float) -> NDArray[np.float64]:
    """Fitted class priors with every object class raised to at least ``prior_min``."""
    prior = np.asarray(fit.class_prior(), dtype=np.float64).copy()
    if prior_min > 0 and prior.size > 1:
        prior[1:] = np.maximum(prior[1:], prior_min)
        prior[0] = max(1.0 - prior[1:].sum(), 1e-12)
    return prior


def _cost_lut(fit: Any, prior_min: float = 0.0, speckle_eps: float = 0.0, floor: float = -50.0) -> NDArray[np.float64]:
    """``-log p(level|k) - log pi_k`` per class and level (eq. 17-18), clipped, min-shifted.

    With ``speckle_eps > 0`` every object class's pmf is replaced by
    ``(1 - eps) p(y|k) + eps p(y|background)``: a structure pixel may fade into the background's
    range (speckle, the receiver threshold's zeros), so a dark pixel costs structure at most
    ``-log eps`` instead of an unbounded amount.
    """
    lp = np.asarray(fit.class_log_pmf(), dtype=np.float64)
    if speckle_eps > 0 and lp.shape[0] > 1:
        with np.errstate(divide="ignore"):
            lp[1:] = np.logaddexp(np.log1p(-speckle_eps) + lp[1:], math.log(speckle_eps) + lp[0])
    with np.errstate(divide="ignore"):
        lp = lp + np.log(_class_prior(fit, prior_min))[:, None]
    lp = np.nan_to_num(lp, nan=floor, neginf=floor, posinf=0.0)
    cost = -np.maximum(lp, floor)
    return cost - cost.min(axis=0, keepdims=True)


def _model_pd_pfa(fit: Any, lut: NDArray[Any]) -> tuple[float, float]:
    pmf = np.asarray(fit.class_pmf())
    det = np.asarray(lut) != 0
    pfa = float(pmf[0][det].sum())
    pd = float((pmf[1:][:, det].sum(axis=1) * np.asarray(fit.class_prior())[1:]).sum()
               / max(float(np.asarray(fit.class_prior())[1:].sum()), 1e-300))
    return min(pd, 1.0), min(pfa, 1.0)


def classify_image(image: NDArray[np.float32], config: PipelineConfig = PipelineConfig()) -> tuple[NDArray[np.uint8], Any, float, float]:
    """Label a pre-processed image: returns ``(labels, fit, pd, pfa)`` (see :class:`PingProducts`).

    Labels: 0 background, >= 1 structure classes.  A ping whose fit is missing or flagged
    ``"no_object"`` / ``"all_zero"`` / ``"degenerate"`` is all background for the fit-based
    methods.
    """
    labels, fit, pd, pfa, _, _ = _classify(image, config)
    return labels, fit, pd, pfa


def _gates(fit: Any, config: PipelineConfig) -> frozenset[str]:
    """The fit gates ``fit`` fails under ``config`` (none for CFAR or without a fit)."""
    if fit is None or config.method.startswith("cfar-"):
        return frozenset()
    from sonarmap.stats.gates import fit_gates

    return fit_gates(fit, max_kld=config.max_kld, max_object_weight=config.max_object_weight,
                     min_separation=config.min_separation)


def _classify(image: NDArray[np.float32], config: PipelineConfig, gate: bool = False, *,
              levels: NDArray[Any] | None = None, fit: Any = None
              ) -> tuple[NDArray[np.uint8], Any, float, float, NDArray[Any], frozenset[str]]:
    """:func:`classify_image` plus the quantised levels it classified and the fit gates the fit
    fails (:func:`_gates`; only with ``gate=True``, which also skips the labelling of a gated
    ping: its labels are all background).  ``levels`` and ``fit``, when given, are the image's
    levels and their fit (not recomputed)."""
    from sonarmap.stats.mixture import quantize

    method = config.method
    if method.startswith("cfar-"):
        from sonarmap.classify.cfar import CFARConfig, cfar

        cfg = CFARConfig(method=method[5:], n_train=config.cfar_train, n_guard=config.cfar_guard,  # type: ignore[arg-type]
                         pfa=config.cfar_pfa, two_d=config.cfar_two_d)
        res = cfar(image, config=cfg)
        levels = quantize(image, config.n_levels)
        return res.labels, _fit(levels, config), math.nan, config.cfar_pfa, levels, frozenset()
    if levels is None or fit is None:
        levels = quantize(image, config.n_levels)
        fit = _fit(levels, config)
    gates = _gates(fit, config) if gate else frozenset()
    if method == "threshold":
        from sonarmap.classify.threshold import threshold_labels

        labels = threshold_labels(image, config.threshold)
        pd, pfa = math.nan, math.nan
        if fit is not None:
            from sonarmap.stats.roc import pd_pfa_at_threshold

            pd, pfa = pd_pfa_at_threshold(fit, config.threshold)
        return labels, fit, pd, pfa, levels, gates
    if fit is None or fit.flags & {"all_zero", "degenerate"} or len(fit.class_names) < 2:
        return np.zeros(image.shape, dtype=np.uint8), fit, 0.0, 0.0, levels, gates
    from sonarmap.classify.local_map import map_lookup_table

    lut = map_lookup_table(fit)
    pd, pfa = _model_pd_pfa(fit, lut)
    if method == "map":
        return lut[levels], fit, pd, pfa, levels, gates
    cost = _cost_lut(fit, config.object_prior_min, config.speckle_eps)
    # the per-pixel decision of the MRF's own unary (object prior raised to object_prior_min):
    # the fitted prior alone can be so small (a thin surface, 0.001-0.02) that the local MAP rule
    # detects nothing while the MRF reports the surface
    pd, pfa = _model_pd_pfa(fit, np.argmin(cost, axis=0))
    if gates:
        return np.zeros(image.shape, dtype=np.uint8), fit, pd, pfa, levels, gates
    labels = _mrf_labels(image, levels, cost, config.beta, config)
    if config.grow_prior_min > 0:
        from sonarmap.ranges import wide_components

        weak = _mrf_labels(image, levels, _cost_lut(fit, config.grow_prior_min, config.speckle_eps), config.grow_beta, config)
        grown = wide_components((weak >= 1) | (labels >= 1), 1, seeds=labels >= 1)
        labels = np.where(grown & (labels == 0), np.uint8(1), labels).astype(np.uint8)
    return labels, fit, pd, pfa, levels, gates


def _mrf_labels(image: NDArray[np.float32], levels: NDArray[Any], cost: NDArray[np.float64], beta: float,
                config: PipelineConfig) -> NDArray[np.uint8]:
    from sonarmap.classify import mrf

    if config.solver == "graphcut" and cost.shape[0] == 2 and not config.contrast:
        return mrf.graphcut_levels_labels(levels, cost, beta=beta, neighbourhood=config.neighbourhood,
                                          range_weight=config.range_weight)
    from sonarmap._pipeline_kernels import gather_costs

    unary = gather_costs(np.ascontiguousarray(levels), cost)
    wt = mrf.pairwise_weights(image.shape, beta=beta, neighbourhood=config.neighbourhood,
                              image=image, contrast=config.contrast, range_weight=config.range_weight)
    return mrf.solve(unary, solver=config.solver, beta=beta,  # type: ignore[arg-type]
                     neighbourhood=config.neighbourhood, weights=wt).labels


def pooled_band_mask(image: NDArray[np.float32], level: float, *, pool_beams: int = 4, pool_bins: int = 3,
                     min_beams: int = 40) -> NDArray[np.bool_] | None:
    """Band pooling as a mask: pixels of ``image`` averaged over ``pool_bins`` x ``2 pool_beams + 1``
    that reach ``level`` and belong to an 8-connected band spanning >= ``min_beams`` beams (None: none)."""
    from sonarmap._pipeline_kernels import box_mean_f32
    from sonarmap.ranges import rule0

    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2 or img.size == 0:
        from scipy.ndimage import uniform_filter

        pooled = uniform_filter(img, size=(pool_bins, 2 * pool_beams + 1), mode="constant")
    else:
        # = scipy.ndimage.uniform_filter(img, size=(pool_bins, 2 pool_beams + 1), mode="constant")
        pooled = box_mean_f32(np.ascontiguousarray(img), int(pool_bins), 2 * int(pool_beams) + 1)
    band = pooled >= level
    if not band.any():
        return None
    band = rule0(band, min_beams, img.shape[0] + 1, 0)
    return band if band.any() else None


def pooled_band_pixels(image: NDArray[np.float32], level: float, *, pool_beams: int = 4, pool_bins: int = 3,
                       min_beams: int = 40, beams: NDArray[np.bool_] | None = None) -> NDArray[np.bool_] | None:
    """Band pooling (see :class:`PipelineConfig`): one structure pixel per beam of every wide band.

    The bands of :func:`pooled_band_mask`; on each of their beams (only those with ``beams[j]``
    when given) the strongest pixel of the first run of band rows is returned.  None if no band.
    """
    from sonarmap._pipeline_kernels import band_peak_pixels

    band = pooled_band_mask(image, level, pool_beams=pool_beams, pool_bins=pool_bins, min_beams=min_beams)
    if band is None:
        return None
    cols = band.any(axis=0)
    if beams is not None:
        cols &= np.asarray(beams, dtype=bool)
    if not cols.any():
        return None
    return band_peak_pixels(band, np.ascontiguousarray(image, dtype=np.float32), cols)


def process_ping(ping: Ping, config: PipelineConfig = PipelineConfig(), *, keep_labels: bool = False,
                 background: Any = None) -> PingProducts:
    """Run the per-ping pipeline (pure function of ``ping``, ``config`` and ``background``).

    Parameters
    ----------
    ping : Ping
        A raw ping.
    config : PipelineConfig
        Pipeline configuration; the default is the most accurate measured pipeline.
    keep_labels : bool
        Keep the label image in the result.
    background : RecordingBackground, optional
        Recording-level background (``sonarmap calibrate``,
        :func:`sonarmap.preprocess.normalise.estimate_recording_background`); without it a
        ping that needs normalisation is normalised by its own background estimate.

    Returns
    -------
    PingProducts
    """
    if not isinstance(ping, Ping):
        raise InputError(f"ping: expected a Ping, got {type(ping).__name__}")
    if not isinstance(config, PipelineConfig):
        raise InputError(f"config: expected a PipelineConfig, got {type(config).__name__}")
    if background is not None and config.normalise == "auto":
        from sonarmap.preprocess.normalise import RecordingBackground

        if not isinstance(background, RecordingBackground):
            raise InputError(f"background: expected a RecordingBackground, got {type(background).__name__}")
    from sonarmap.preprocess.normalise import condition_image

    geom = ping.geometry
    # sidelobe suppression and input gain; 8-bit images (every DIDSON, ARIS and Oculus recording)
    # pass unchanged
    raw, gain_db = condition_image(ping.image)
    # background normalisation or pre-processing (sec. III-IV), mixture fit (eq. 8-11) and its
    # gates, classification (eq. 12-18)
    m = _model_ping(raw, geom, config, background)

    def products(ranges: BeamRanges, flags: set[str], labels: NDArray[np.uint8] | None, pd: float, pfa: float,
                 pd_range: float, gates: tuple[str, ...] = ()) -> PingProducts:
        fit = m.classified[1] if m.classified is not None else None
        return PingProducts(
            time_ns=ping.time_ns, source=ping.source, fit=fit,
            kld=float(fit.kld) if fit is not None else math.nan, flags=tuple(sorted(flags)),
            ranges=ranges, labels=labels if keep_labels else None, pd=float(pd), pfa=float(pfa),
            method=config.method, pd_range=pd_range, background=m.background, gates=gates,
            image=m.image if keep_labels else None, input_gain_db=gain_db, floor_levels=m.floor)

    def no_return_products(flags: set[str], pd: float, pfa: float, gates: tuple[str, ...] = ()) -> PingProducts:
        return products(no_returns(geom, time_ns=ping.time_ns, source=ping.source, mode=config.range_mode),
                        flags | {"no_returns"}, np.zeros(m.image.shape, dtype=np.uint8), pd, pfa, 0.0, gates)

    if m.classified is None:
        # a constant ping (all zero, saturated, a dead sensor) carries no range information
        return no_return_products({"constant_image"}, 0.0, 0.0)
    labels, fit, pd, pfa, levels, gates = m.classified
    if gates:
        # an implausible fit never becomes confident output: no returns, the reasons as flags
        return no_return_products(set(fit.flags) | gates, float(pd), float(pfa), tuple(sorted(gates)))
    # per-beam ranges (sec. V): candidate structure, then echoes tracked across beams
    bg_mean, edge = _background_mean(fit, config)
    mask = _candidate_mask(labels, geom, config, m.normalised is not None)
    thickness = None
    if config.tracker == "surface":
        ranges, thickness = _surface_ranges(ping, m.image, levels, mask, fit, config, m.normalised is not None,
                                            bg_mean, m.background)
    else:
        ranges = _rule_ranges(ping, m.image, labels, mask, config, m.normalised is not None, bg_mean, edge)
    flags = set(fit.flags) if fit is not None else {"no_fit"}
    if ranges.n_returns == 0:
        flags.add("no_returns")
    pd_range = _pd_range(float(pd), labels, ranges, flags)
    if thickness is not None:
        ranges = dataclasses.replace(ranges, p_detect=_p_detect(float(pd), pd_range, ranges, thickness))
    return products(ranges, flags, labels, pd, pfa, pd_range)


@dataclasses.dataclass(frozen=True, eq=False)
class _Modelled:
    """What :func:`_model_ping` made of a ping: the image the classifier saw, the normalised image
    (None when not normalised), the background estimate, ``(labels, fit, pd, pfa, levels, gates)``
    of :func:`_classify` (None for a constant image) and the quantisation floor used."""

    image: NDArray[np.float32]
    normalised: NDArray[np.float32] | None
    background: Any
    classified: tuple[Any, ...] | None
    floor: int


def _model_ping(raw: NDArray[np.float32], geom: Any, config: PipelineConfig, reference: Any) -> _Modelled:
    """The modelling stage: normalise (or pre-process) the conditioned image, fit, gate, classify.

    An 8-bit ping whose fit fails the ``kld`` gate is modelled again with its lowest levels merged
    into the zero level (:attr:`PipelineConfig.max_floor_levels`); the first floor whose fit passes
    every gate is kept, else the ping as recorded.
    """
    from sonarmap.preprocess.normalise import on_8bit_grid

    m = _model_image(raw, geom, config, reference)
    if not (m.classified is not None and "kld" in m.classified[5] and config.max_floor_levels > 0
            and config.n_levels == 256 and on_8bit_grid(raw)):
        return m
    # a background on the bottom levels of the 8-bit grid: merge them into the zero level - a
    # shift of the level histogram, refitted (no pass over the image until one passes)
    levels = m.classified[4]
    counts = np.asarray(m.classified[1].counts, dtype=np.float64)  # the refused fit's level histogram
    for n in range(1, config.max_floor_levels + 1):
        merged = np.zeros_like(counts)
        merged[0] = counts[: n + 1].sum()
        merged[1:counts.size - n] = counts[n + 1:]
        fit = _fit_counts(merged, config)
        if fit is None or _gates(fit, config):
            continue
        image = np.maximum(m.image - np.float32(n / (config.n_levels - 1)), np.float32(0.0))
        shifted = np.maximum(levels.astype(np.int16) - n, 0).astype(levels.dtype)
        return dataclasses.replace(m, image=image, floor=n,
                                   classified=_classify(image, config, gate=True, levels=shifted, fit=fit))
    return m


def _model_image(raw: NDArray[np.float32], geom: Any, config: PipelineConfig, reference: Any) -> _Modelled:
    """:func:`_model_ping` of one image, without the quantisation floor."""
    constant = float(raw.max()) == float(raw.min())
    background = None
    normalised = None
    if config.normalise == "auto" and not constant:
        from sonarmap.preprocess.normalise import estimate_background

        background, normalised = estimate_background(raw, reference=reference)
    pre = config.preprocess_config()
    if normalised is not None:
        image = normalised
    elif pre is None or constant:
        image = raw
    else:
        from sonarmap.preprocess.pipeline import preprocess_image

        image = preprocess_image(raw, geom, pre)
    if constant or not np.any(image > 0) or float(image.max()) == float(image.min()):
        return _Modelled(image, normalised, background, None, 0)
    return _Modelled(image, normalised, background, _classify(image, config, gate=True), 0)


def _background_mean(fit: Any, config: PipelineConfig) -> tuple[float | None, float | None]:
    """The fitted background class's mean intensity (None when the fit has no usable classes) and
    the leading-edge level of the rules tracker (``edge_factor`` x that mean; None when off)."""
    usable = fit is not None and len(fit.class_names) >= 2 and not fit.flags & {"all_zero", "degenerate"}
    if not (usable or (config.refine_bins > 0 and fit is not None)):
        return None, None
    bg = float(np.asarray(fit.class_pmf())[0] @ np.asarray(fit.levels))
    return (bg if usable else None), (config.edge_factor * bg if config.refine_bins > 0 else None)


def _candidate_mask(labels: NDArray[np.uint8], geom: Any, config: PipelineConfig, normalised: bool) -> NDArray[np.bool_]:
    """Structure pixels in components large enough to be surfaces (rule 0), without the ones
    smaller than ``min_component_extent_m`` both ways."""
    if normalised:
        rule = (config.normalised_component_beams, config.normalised_component_bins,
                config.normalised_component_pixels)
    else:
        rule = (config.min_component_beams, config.min_component_bins, config.min_component_pixels)
    mask = component_rule(labels >= 1, rule[0], rule[1], config.link_beams, rule[2])
    if config.min_component_extent_m > 0:
        mask = drop_small_components(mask, geom, config.min_component_extent_m)
    return mask


def _rule_ranges(ping: Ping, image: NDArray[np.float32], labels: NDArray[np.uint8], mask: NDArray[np.bool_],
                 config: PipelineConfig, normalised: bool, bg_mean: float | None, edge: float | None) -> BeamRanges:
    """The per-beam rules (``tracker="rules"``): first runs, the isolated-return rule, leading-edge
    refinement, band pooling; half-peak edges on normalised images."""
    geom = ping.geometry

    def _ranges(accepted: NDArray[np.bool_] | None) -> BeamRanges:
        return extract_ranges(
            mask, image, geom, mode=config.range_mode,  # type: ignore[arg-type]
            min_run=config.min_run, reject_isolated=config.reject_isolated,
            neighbour_beams=config.neighbour_beams, max_jump_bins=config.max_jump_bins,
            min_segment_beams=config.min_segment_beams,
            refine_bins=config.refine_bins if not normalised else 0, edge_level=edge, accepted=accepted,
            time_ns=ping.time_ns,
            source=ping.source,
        )

    ranges = _ranges(None)
    # band pooling: "fallback" only when the per-pixel route found less than one wide surface,
    # "fill" on the beams it left without a return
    fallback = ranges.n_returns < config.pool_min_beams
    n_beams = ranges.bin.size
    # band pooling multi-looks single-look speckle; a normalised image is multi-looked already
    if (config.pool_factor > 0 and bg_mean is not None and bg_mean > 0 and not normalised
            and (fallback or (config.pool_mode == "fill" and ranges.n_returns < n_beams))):
        accepted = pooled_band_pixels(image, config.pool_factor * bg_mean, pool_beams=config.pool_beams,
                                      pool_bins=config.pool_bins, min_beams=config.pool_min_beams,
                                      beams=None if fallback else ranges.bin < 0)
        if accepted is not None:
            ranges = _ranges(accepted)
    if normalised and config.edge_fraction > 0:
        # the range convention: the leading edge of the echo (a fraction of its first peak)
        ranges = half_peak_edges(ranges, image, labels >= 1, geom, fraction=config.edge_fraction)
    return ranges


def _meta_number(ping: Ping, key: str, default: float | None = None) -> float | None:
    """``ping.meta[key]`` as a float: ``default`` when absent, None when it is not a finite number."""
    meta = ping.meta if isinstance(ping.meta, dict) else {}
    if key not in meta:
        return default
    v = meta[key]
    return float(v) if is_finite_number(v) else None


def pulse_bins(ping: Ping, config: PipelineConfig) -> int:
    """The pulse length in range bins (>= 1): ``config.pulse_length_m``, else the ping's
    ``meta["pulse_width_us"]`` at its sound speed (``meta["sound_speed_m_s"]``, default 1500 m/s)."""
    length = config.pulse_length_m
    if length is None:
        us = _meta_number(ping, "pulse_width_us")
        c = _meta_number(ping, "sound_speed_m_s", 1500.0)
        ok = us is not None and 0 < us < 1e5 and c is not None and 1300 <= c <= 1700
        length = us * 1e-6 * c / 2.0 if ok else 0.0  # type: ignore[operator]
    dr = abs(ping.geometry.range_resolution_m)
    return max(1, int(round(length / dr))) if dr > 0 else 1


def _log_range_db(ping: Ping, config: PipelineConfig) -> float | None:
    """dB per unit of raw pixel value of log-compressed samples (None: linear samples)."""
    if config.log_dynamic_range_db is not None:
        return config.log_dynamic_range_db
    v = _meta_number(ping, "log_dynamic_range_db")
    return v if v is not None and 0 < v < 1000 else None


def measurement_image(ping: Ping, background: Any, config: PipelineConfig = PipelineConfig(), *,
                      rows: tuple[int, int] | None = None) -> NDArray[np.float64]:
    """The image a normalised ping's echoes are measured on: echo intensity above the background,
    in units of the background level, linear in intensity.

    ``ratio = raw / b`` for linear samples, ``10^(D (raw - b) / 10)`` for log-compressed ones
    (``D`` dB per unit, :attr:`PipelineConfig.log_dynamic_range_db`), with ``b`` the estimated
    background level x beam factor (:mod:`sonarmap.preprocess.normalise`); then
    ``max(ratio - 1, 0)``.  No multi-look: the leading edge keeps the raw range resolution.
    ``rows=(r0, r1)`` computes only those rows (zero elsewhere).
    """
    from sonarmap._pipeline_kernels import excess_ratio
    from sonarmap.preprocess.normalise import expand_grid

    raw = np.ascontiguousarray(ping.image, dtype=np.float32)
    level = np.ascontiguousarray(background.level_by_bin, dtype=np.float32)
    full = (np.ones(raw.shape, np.float32) if background.beam_factor is None
            else np.ascontiguousarray(expand_grid(background.beam_factor, raw.shape), dtype=np.float32))
    d = _log_range_db(ping, config)
    r0, r1 = (0, raw.shape[0]) if rows is None else rows
    return excess_ratio(raw, level, full, float(d) if d is not None else 0.0, int(r0), int(r1))


def _surface_ranges(ping: Ping, image: NDArray[np.float32], levels: NDArray[Any], mask: NDArray[np.bool_],
                    fit: Any, config: PipelineConfig, normalised: bool,
                    bg_mean: float | None, background: Any = None) -> tuple[BeamRanges, NDArray[np.int64]]:
    """Echoes of the candidate structure (``mask`` plus pooled bands), tracked across beams; also
    the number of bins each return's echo spans (0 where no return)."""
    from sonarmap.ranges import ranges_from_tracks
    from sonarmap.ranges.echoes import find_echoes, level_llr, pooled_edges
    from sonarmap.ranges.tracking import continuation_mask, track_surfaces

    geom = ping.geometry
    cand = mask
    band = None
    # band pooling recovers thin single-look surface bands the per-pixel route leaves in pieces;
    # only needed where some beam has no candidate at all
    if (config.pool_factor > 0 and bg_mean is not None and bg_mean > 0 and not normalised
            and config.method in ("mrf", "map", "threshold") and not mask.any(axis=0).all()):
        band = pooled_band_mask(image, config.pool_factor * bg_mean, pool_beams=config.pool_beams,
                                pool_bins=config.pool_bins, min_beams=config.pool_min_beams)
        if band is not None:
            cand = cand | band
    if not cand.any():
        return (no_returns(geom, time_ns=ping.time_ns, source=ping.source, mode=config.range_mode),
                np.zeros(geom.n_beams, dtype=np.int64))
    llr_lut = level_llr(fit) if fit is not None and len(fit.class_names) >= 2 else None
    lut = np.maximum(llr_lut, 0.0) if llr_lut is not None else np.ones(int(levels.max()) + 1)
    fraction = config.edge_fraction if config.edge_fraction > 0 else 0.5
    pb = pulse_bins(ping, config)
    measured = normalised and background is not None and getattr(background, "level_by_bin", None) is not None

    done: list[Any] = []  # the measurement image and its rows, once computed

    def measure(cand: NDArray[np.bool_]) -> tuple[Any, float, Any, Any]:
        meas, bg = image, bg_mean or 0.0
        if measured:
            # echo intensity above the background, in background units (its mean is 1)
            occupied = np.flatnonzero(cand.any(axis=1))
            pad = pb + 4
            rows = (int(occupied[0]) - pad, int(occupied[-1]) + 1 + pad)
            if not done or rows[0] < done[1][0] or rows[1] > done[1][1]:
                done[:] = [measurement_image(ping, background, config, rows=rows), rows]
            meas, bg = done[0], 1.0
        # a pooled band pixel passed a >= pool_factor x background test over the whole box: one
        # nat at least, whatever its own (single-look, speckled) value says
        echoes = find_echoes(cand, meas, geom, levels=levels, level_evidence=lut, boost=band, boost_min=1.0,
                             pulse_bins=pb, fraction=fraction, background=bg, scan=config.edge_scan,
                             sigma_scale=config.sigma_scale)
        return meas, bg, echoes, track_surfaces(echoes, config.track)

    meas, bg, echoes, tracks = measure(cand)
    if config.continue_evidence > 0 and llr_lut is not None:
        # a surface's faint stretch that the component rule left without candidates: pixels along
        # its extrapolation where their likelihood ratio says structure, for the tracker to judge
        extra = continuation_mask(echoes, tracks.first, levels, llr_lut, min_evidence=config.continue_evidence,
                                  touch_bins=config.track.touch_bins) & ~cand
        if extra.any() and echoes.size:
            # only where it could become the return: a beam without one, or whose return lies behind
            first = tracks.first
            current = np.where(first >= 0, echoes.edge_bin[np.maximum(first, 0)], np.inf)
            top = np.where(extra.any(axis=0), np.argmax(extra, axis=0), extra.shape[0])
            extra &= (top < current)[None, :]
        if extra.any():
            cand = cand | extra
            meas, bg, echoes, tracks = measure(cand)
    sel = tracks.first
    if config.edge_pool_beams > 0 and config.range_mode == "first":
        # the pooled profile is smoothed over at least 3 bins along range in all (a single-look
        # profile's maximum is otherwise a speckle spike)
        echoes = pooled_edges(echoes, sel, meas, geom, pulse_bins=pb, half_beams=config.edge_pool_beams,
                              smooth_bins=3 if pb < 3 else 1, fraction=fraction,
                              touch_bins=config.track.touch_bins, sigma_scale=config.sigma_pool_scale)
    if echoes.size and (sel >= 0).any():
        echoes = _clipped_echo_sigma(echoes, sel, ping.image, geom)
    thickness = np.where(sel >= 0, (echoes.stop_bin - echoes.start_bin)[np.maximum(sel, 0)] if echoes.size else 0, 0)
    return (ranges_from_tracks(echoes, tracks, geom, image, mode=config.range_mode,  # type: ignore[arg-type]
                               time_ns=ping.time_ns, source=ping.source), thickness.astype(np.int64))


#: A raw sample at or above this is at the receiver's full scale (8-bit images: level 255).
CLIP_LEVEL = 254.5 / 255.0


def _clipped_echo_sigma(echoes: Any, sel: NDArray[np.int64], raw: NDArray[Any], geom: Any) -> Any:
    """Widen the sigma of returns whose echo reaches the receiver's full scale.

    A clipped echo's peak is only a lower bound: the half-peak crossing of the true echo lies
    somewhere between the crossing measured (half the clipped level) and the echo's first
    clipped sample.  That interval's uniform spread, ``length / sqrt 12``, is added in
    quadrature to the return's sigma; the range itself is not moved.
    """
    from sonarmap._pipeline_kernels import first_clipped_rows

    img = np.ascontiguousarray(raw)
    idx = np.flatnonzero(sel >= 0)
    e = sel[idx]
    lo = np.clip(np.ceil(echoes.edge_bin[e]).astype(np.int64), 0, img.shape[0] - 1)
    hi = np.clip(echoes.stop_bin[e], 0, img.shape[0])
    first = first_clipped_rows(img, idx, lo, hi, CLIP_LEVEL)  # per return: its echo's first clipped row
    spread = (first - echoes.edge_bin[e]) * abs(geom.range_resolution_m)
    hit = (first >= 0) & (spread > 0)
    if not hit.any():
        return echoes
    sigma = echoes.sigma_m.copy()
    sigma[e[hit]] = np.hypot(sigma[e[hit]], spread[hit] / math.sqrt(12.0))
    return dataclasses.replace(echoes, sigma_m=sigma)


def _p_detect(pd: float, pd_range: float, ranges: BeamRanges, thickness: NDArray[np.int64]) -> NDArray[np.float32]:
    """Per-beam detection probability of a surface (the mapping sensor model's pD).

    The ping's range-measurement pD (``pd_range``: the model's per-pixel pD times the share of
    detecting beams that kept a return) is the rate; it is shared among the beams in proportion to
    ``1 - (1 - pd)^n``, the chance that at least one of the ``n`` bins of the beam's echo is
    detected (eq. 15), so a thick echo (a steep surface) counts as more reliable than a one-bin
    one, and the mean over the ping's returns stays ``pd_range``.  Beams without a return use the
    median echo thickness of the ping's returns (1 bin when there is none).  NaN when the ping has
    no finite ``pd`` (CFAR, no fit).
    """
    n = ranges.n_beams
    if not (math.isfinite(pd) and math.isfinite(pd_range)) or pd <= 0:
        return np.full(n, np.nan if not math.isfinite(pd_range) else pd_range, dtype=np.float32)
    t = np.asarray(thickness, dtype=np.float64)
    fill = float(np.median(t[ranges.valid])) if ranges.n_returns else 1.0
    t = np.where(ranges.valid, np.maximum(t, 1.0), max(fill, 1.0))
    f = 1.0 - (1.0 - min(pd, 1.0)) ** t
    mean = float(f[ranges.valid].mean()) if ranges.n_returns else float(f.mean())
    return np.clip(pd_range * f / max(mean, 1e-12), 0.0, 1.0).astype(np.float32)


def _pd_range(pd: float, labels: NDArray[np.uint8], ranges: BeamRanges, flags: set[str]) -> float:
    """``pd`` times the fraction of detecting beams that kept a return (see ``PingProducts.pd_range``)."""
    if "no_fit" in flags or not math.isfinite(pd):
        return math.nan
    detecting = int(np.count_nonzero((labels >= 1).any(axis=0) | (ranges.bin >= 0)))
    if detecting == 0:
        return pd
    return pd * ranges.n_returns / detecting
