"""The configuration of the per-ping pipeline: one frozen section per stage.

:class:`PipelineConfig` holds the image conditioning options (``preprocess``, ``normalise``) and
one section per stage of :func:`sonarmap.pipeline.process_ping`:

=================  ==========================  ===================================================
section            class                       stage
=================  ==========================  ===================================================
``fit``            :class:`FitConfig`          the per-ping mixture fit (eq. 8-11) and its gates
``classify``       :class:`ClassifyConfig`     labels: MRF (eq. 17-18, 22), local MAP, threshold,
                                               CFAR
``candidates``     :class:`CandidateConfig`    which structure pixels can carry a return:
                                               component rule, band pooling
``ranges``         :class:`RangeConfig`        per-beam returns: echoes, leading edges, sigma,
                                               surface tracking
=================  ==========================  ===================================================

In a TOML file (``--config``) each section is a table::

    [pipeline]
    normalise = "auto"

    [pipeline.classify]
    beta = 1.5

    [pipeline.ranges]
    edge_fraction = 0.3

Every option name belongs to exactly one section, so a flat table (``beta = 1.5`` at the top, the
form stores written before the sections existed hold) is read too, and
``config.replace(beta=1.5)`` replaces an option of any section by its name.
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from pathlib import Path
from typing import Any, ClassVar

from sonarmap._config import (
    check_booleans,
    check_choice,
    check_integers,
    coerce_reals,
    config_error,
    config_table,
    is_finite_number,
)
from sonarmap.errors import InputError

__all__ = ["PipelineConfig", "FitConfig", "ClassifyConfig", "CandidateConfig", "RangeConfig",
           "METHODS", "SOLVER_NAMES", "SECTIONS"]

METHODS = ("mrf", "map", "threshold", "cfar-ca", "cfar-so", "cfar-go", "cfar-os")
SOLVER_NAMES = ("graphcut", "icm", "anneal", "expansion")
_PREPROCESS_RECIPES = ("paper-table1", "default", "paper-background", "none")


class _Section:
    """Shared (de)serialisation of the sections."""

    SECTION: ClassVar[str] = ""

    @property
    def _where(self) -> str:
        return f"pipeline config: {self.SECTION}."

    def to_dict(self) -> dict[str, Any]:
        """JSON/TOML-compatible dict of the section's options."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}  # type: ignore[arg-type]

    @classmethod
    def from_dict(cls, d: Any) -> Any:
        """Build from a table; unknown keys or bad values raise :class:`InputError` naming the key."""
        return cls(**config_table(d, cls, f"pipeline config: {cls.SECTION}"))


@dataclasses.dataclass(frozen=True)
class FitConfig(_Section):
    """The per-ping intensity model (eq. 8-11) and the gates that refuse an implausible fit.

    Parameters
    ----------
    families : tuple of str
        Mixture families after the zero spike (background first).
    fit_method : str
        ``"em"`` or ``"lsq"``.
    fit_tol : float
        EM relative log-likelihood tolerance.
    n_levels : int
        Quantisation levels of the histogram (and of the level images the classifier labels).
    max_kld, max_object_weight, min_separation : float
        Fit gates (:func:`sonarmap.stats.gates.fit_gates`): a ping whose fit fails one yields no
        returns and carries the gate's name in its flags.
    max_floor_levels : int
        The quantisation floor.  An 8-bit ping whose fit fails the KL-divergence gate is modelled
        again with the lowest ``n = 1, 2, ..`` levels of the image the classifier sees merged into
        the zero level (its level histogram shifted down by ``n`` and refitted; the image shifted
        by ``n`` levels, clamped at 0), up to this many; the first ``n`` whose fit passes every
        gate is used and reported as :attr:`PingProducts.floor_levels`.  A ping that no floor
        explains costs ``max_floor_levels`` further histogram fits.  A background whose bulk lies
        on the bottom two or three levels of the 8-bit grid (the dark water column of an Oculus
        after its automatic gain has lowered the gain for a bright hull) has no shape the grid
        resolves - its histogram falls by 5-30x per level, an exponential of less than one level -
        and the mixture's zero spike then takes it as it takes a thresholded receiver's zeros.
        Pings whose first fit passes (every DIDSON, ARIS, Oculus and Kongsberg recording) are
        unchanged.  0 = off.
    """

    SECTION: ClassVar[str] = "fit"

    families: tuple[str, ...] = ("exponential", "rayleigh")
    fit_method: str = "em"
    fit_tol: float = 1e-6
    n_levels: int = 256
    max_kld: float = 0.05
    max_object_weight: float = 0.5
    min_separation: float = 1.9
    max_floor_levels: int = 4

    def __post_init__(self) -> None:
        w = self._where
        coerce_reals(self, ("fit_tol", "max_kld", "max_object_weight", "min_separation"), w)
        if self.fit_tol <= 0:
            raise config_error(w, "fit_tol", "must be > 0", self.fit_tol)
        check_integers(self, (("n_levels", 2), ("max_floor_levels", 0)), w)
        check_choice(self, "fit_method", ("em", "lsq"), w)
        fams = self.families
        if isinstance(fams, str) or not isinstance(fams, list | tuple) or len(fams) < 2:
            raise config_error(w, "families", "must be a list of at least two family names", fams)
        object.__setattr__(self, "families", tuple(str(f) for f in fams))

    def to_dict(self) -> dict[str, Any]:
        d = super().to_dict()
        d["families"] = list(self.families)
        return d


@dataclasses.dataclass(frozen=True)
class ClassifyConfig(_Section):
    """Per-pixel labels: the MRF (eq. 17-18, 22; the default), local MAP (eq. 12-13), a fixed
    threshold (eq. 14) or the CFAR baselines.

    Parameters
    ----------
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
    threshold : float
        Intensity threshold of ``method="threshold"`` (eq. 14), on the pre-processed image.
    cfar_train, cfar_guard : int
        CFAR training / guard cells along range (total, even); sonar-SLAM: 40 / 10.
    cfar_pfa : float
        CFAR design false-alarm probability (sonar-SLAM: 0.1).
    cfar_two_d : bool
        2-D CFAR window (range x beams).
    """

    SECTION: ClassVar[str] = "classify"

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
    threshold: float = 0.3
    cfar_train: int = 40
    cfar_guard: int = 10
    cfar_pfa: float = 0.1
    cfar_two_d: bool = False

    def __post_init__(self) -> None:
        w = self._where
        check_choice(self, "method", METHODS, w)
        check_choice(self, "solver", SOLVER_NAMES, w)
        coerce_reals(self, ("threshold", "cfar_pfa"), w)
        coerce_reals(self, ("beta", "grow_beta"), w, minimum=0)
        coerce_reals(self, ("object_prior_min", "grow_prior_min", "speckle_eps", "range_weight"), w)
        for key in ("object_prior_min", "grow_prior_min", "speckle_eps"):
            if not 0 <= getattr(self, key) < 0.5:
                raise config_error(w, key, "must lie in [0, 0.5)", getattr(self, key))
        if not 0 <= self.range_weight <= 1:
            raise config_error(w, "range_weight", "must lie in [0, 1]", self.range_weight)
        if not 0 < self.cfar_pfa < 1:
            raise config_error(w, "cfar_pfa", "must lie in (0, 1)", self.cfar_pfa)
        check_integers(self, (("neighbourhood", 4), ("cfar_train", 2), ("cfar_guard", 0)), w)
        if self.neighbourhood not in (4, 8):
            raise config_error(w, "neighbourhood", "must be 4 or 8", self.neighbourhood)
        for key in ("cfar_train", "cfar_guard"):
            if getattr(self, key) % 2:
                raise config_error(w, key, "must be even", getattr(self, key))
        check_booleans(self, ("contrast", "cfar_two_d"), w)


@dataclasses.dataclass(frozen=True)
class CandidateConfig(_Section):
    """Which structure pixels can carry a return: the component rule (rule 0) and band pooling.

    Parameters
    ----------
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
    pool_factor, pool_beams, pool_bins, pool_min_beams : float, int, int, int
        Band pooling (off when ``pool_factor`` is 0): the pre-processed image is averaged over a
        box of ``pool_bins`` range bins x ``2 pool_beams + 1`` beams (multi-look across beams),
        thresholded at ``pool_factor`` x the fitted background class's mean intensity, and its
        8-connected components spanning >= ``pool_min_beams`` beams are surfaces.  Recovers thin
        surface bands of single-look speckle that the per-pixel model leaves in fragments of 0-5
        pixels per beam; fish schools and speckle do not span ``pool_min_beams`` beams.  Not
        applied to normalised images, which are multi-looked already.
    pool_mode : str
        ``"fill"``: band pooling adds candidates on the beams the per-pixel route left empty;
        ``"fallback"``: only when the per-pixel route found fewer than ``pool_min_beams``
        returns, on every beam (``tracker="rules"``; there the strongest pixel of each band
        beam's first run bypasses the component rule).
    """

    SECTION: ClassVar[str] = "candidates"

    min_component_beams: int = 16
    min_component_bins: int = 16
    link_beams: int = 4
    min_component_pixels: int = 40
    normalised_component_beams: int = 24
    normalised_component_bins: int = 24
    normalised_component_pixels: int = 100
    min_component_extent_m: float = 0.02
    pool_factor: float = 4.0
    pool_beams: int = 2
    pool_bins: int = 3
    pool_min_beams: int = 40
    pool_mode: str = "fill"

    def __post_init__(self) -> None:
        w = self._where
        coerce_reals(self, ("pool_factor", "min_component_extent_m"), w, minimum=0)
        check_integers(self, (("min_component_beams", 1), ("min_component_bins", 1), ("min_component_pixels", 0),
                              ("normalised_component_beams", 1), ("normalised_component_bins", 1),
                              ("normalised_component_pixels", 0), ("link_beams", 0), ("pool_beams", 0),
                              ("pool_bins", 1), ("pool_min_beams", 1)), w)
        check_choice(self, "pool_mode", ("fallback", "fill"), w)


@dataclasses.dataclass(frozen=True)
class RangeConfig(_Section):
    """Per-beam returns (sec. V and the range convention): echoes, their leading edges and sigma,
    surface tracking across beams.

    Parameters
    ----------
    range_mode : str
        ``"first"`` or ``"strongest"``.
    tracker : str
        ``"surface"``: per-beam echoes of the candidate structure, tracked across beams by the
        surface model (:mod:`sonarmap.ranges.tracking`); every return is an echo's leading edge
        with a sigma.  ``"rules"``: the previous per-beam rules (isolated-return rule,
        leading-edge refinement, band pooling at the band's peak), kept for comparison.
    track : TrackConfig or dict, optional
        Costs of the surface model (default :class:`sonarmap.ranges.tracking.TrackConfig`).
    edge_fraction : float
        The range convention: a return's range is the first crossing of this fraction of its
        echo's first peak (:mod:`sonarmap.ranges.echoes`).  With ``tracker="rules"`` it applies to
        normalised images only (0 = the first structure pixel).
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
    pulse_length_m : float, optional
        Transmit pulse length along range (``c tau / 2``); echoes are measured on the image
        smoothed over it.  Default: from the ping (``meta["pulse_width_us"]``, ARIS), else none.
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
    min_run : int
        ``tracker="rules"``, first return: minimum run of consecutive structure bins.
    reject_isolated : bool
        ``tracker="rules"``: drop returns without support in neighbouring beams.
    neighbour_beams, max_jump_bins : int
        ``tracker="rules"``: support window and range tolerance of the consistency rules.
    min_segment_beams : int
        ``tracker="rules"``: drop runs of consistent returns narrower than this many consecutive
        beams.
    refine_bins, edge_factor : int, float
        ``tracker="rules"``: leading-edge refinement of first returns (0 = off): up to
        ``refine_bins`` bins towards the sonar while the local mean intensity is >=
        ``edge_factor`` x the fitted background class's mean intensity.
    """

    SECTION: ClassVar[str] = "ranges"

    range_mode: str = "first"
    tracker: str = "surface"
    track: Any = None
    edge_fraction: float = 0.5
    edge_scan: str = "back"
    edge_pool_beams: int = 3
    pulse_length_m: float | None = None
    continue_evidence: float = 10.0
    sigma_scale: float = 1.5
    sigma_pool_scale: float = 5.0
    log_dynamic_range_db: float | None = None
    min_run: int = 1
    reject_isolated: bool = True
    neighbour_beams: int = 2
    max_jump_bins: int = 20
    min_segment_beams: int = 1
    refine_bins: int = 8
    edge_factor: float = 4.0

    def __post_init__(self) -> None:
        from sonarmap.ranges.tracking import TrackConfig

        w = self._where
        if self.track is None:
            object.__setattr__(self, "track", TrackConfig())
        elif isinstance(self.track, dict):
            object.__setattr__(self, "track", TrackConfig(**config_table(self.track, TrackConfig,
                                                                         "pipeline config: ranges.track")))
        elif not isinstance(self.track, TrackConfig):
            raise config_error(w, "track", "must be a track table", self.track)
        check_choice(self, "tracker", ("surface", "rules"), w)
        check_choice(self, "edge_scan", ("forward", "back"), w)
        check_choice(self, "range_mode", ("first", "strongest"), w)
        for key, positive in (("log_dynamic_range_db", True), ("pulse_length_m", False)):
            v = getattr(self, key)
            if v is None:
                continue
            if not is_finite_number(v) or (v <= 0 if positive else v < 0):
                raise config_error(w, key, "must be a finite number > 0" if positive
                                   else "must be a finite number >= 0", v)
            object.__setattr__(self, key, float(v))
        coerce_reals(self, ("edge_factor",), w)
        coerce_reals(self, ("sigma_scale", "sigma_pool_scale", "continue_evidence"), w, minimum=0)
        coerce_reals(self, ("edge_fraction",), w)
        if not 0 <= self.edge_fraction < 1:
            raise config_error(w, "edge_fraction", "must lie in [0, 1)", self.edge_fraction)
        check_integers(self, (("min_run", 1), ("neighbour_beams", 1), ("max_jump_bins", 0),
                              ("min_segment_beams", 1), ("refine_bins", 0), ("edge_pool_beams", 0)), w)
        check_booleans(self, ("reject_isolated",), w)

    def to_dict(self) -> dict[str, Any]:
        d = super().to_dict()
        d["track"] = dataclasses.asdict(self.track)
        for key in ("pulse_length_m", "log_dynamic_range_db"):
            if d[key] is None:
                del d[key]
        return d


#: The sections of :class:`PipelineConfig`, by name.
SECTIONS: dict[str, type[_Section]] = {c.SECTION: c for c in (FitConfig, ClassifyConfig, CandidateConfig, RangeConfig)}

#: Each option name of a section -> its section (every name belongs to exactly one).
_OPTION_SECTION: dict[str, str] = {f.name: name for name, cls in SECTIONS.items() for f in dataclasses.fields(cls)}


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Validated configuration of :func:`sonarmap.pipeline.process_ping` (defaults = the most
    accurate pipeline, the same for every sonar).

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
    fit : FitConfig
        The mixture fit and its gates.
    classify : ClassifyConfig
        The labelling method and its parameters.
    candidates : CandidateConfig
        The component rule and band pooling.
    ranges : RangeConfig
        Echoes, leading edges, sigma and surface tracking.

    A section may be given as a dict (a TOML table).

    Examples
    --------
    >>> cfg = PipelineConfig().replace(beta=1.5, edge_fraction=0.3)
    >>> cfg.classify.beta, cfg.ranges.edge_fraction
    (1.5, 0.3)
    >>> PipelineConfig.from_dict({"classify": {"method": "map"}}).classify.method
    'map'
    """

    preprocess: Any = "paper-table1"
    normalise: str = "auto"
    fit: FitConfig = dataclasses.field(default_factory=FitConfig)
    classify: ClassifyConfig = dataclasses.field(default_factory=ClassifyConfig)
    candidates: CandidateConfig = dataclasses.field(default_factory=CandidateConfig)
    ranges: RangeConfig = dataclasses.field(default_factory=RangeConfig)

    def __post_init__(self) -> None:
        from sonarmap.preprocess.pipeline import PreprocessConfig

        where = "pipeline config: "
        pre = self.preprocess
        if isinstance(pre, dict):
            object.__setattr__(self, "preprocess", PreprocessConfig.from_dict(pre))
        elif isinstance(pre, str):
            if pre not in _PREPROCESS_RECIPES:
                raise config_error(where, "preprocess", f"must be one of {', '.join(_PREPROCESS_RECIPES)} or a table",
                                   pre)
        elif not isinstance(pre, PreprocessConfig):
            raise config_error(where, "preprocess", "must be a recipe name or a preprocess table", pre)
        check_choice(self, "normalise", ("auto", "off"), where)
        for name, cls in SECTIONS.items():
            v = getattr(self, name)
            if isinstance(v, dict):
                object.__setattr__(self, name, cls.from_dict(v))
            elif not isinstance(v, cls):
                raise config_error(where, name, f"must be a {cls.__name__} or a table", v)

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON/TOML-compatible nested dict (a table per section); :meth:`from_dict` reads it back."""
        d: dict[str, Any] = {"preprocess": self.preprocess if isinstance(self.preprocess, str)
                             else self.preprocess.to_dict(), "normalise": self.normalise}
        for name in SECTIONS:
            d[name] = getattr(self, name).to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PipelineConfig:
        """Build from a dict: section tables, and/or options by name at the top level (flat).

        A ``{"pipeline": {...}}`` table (TOML) is unwrapped.  Unknown keys, an option given both
        flat and in its section, or bad values raise :class:`InputError` naming the key.
        """
        if not isinstance(d, dict):
            raise InputError(f"pipeline config: expected a table, got {type(d).__name__}")
        if set(d) == {"pipeline"} and isinstance(d["pipeline"], dict):
            d = d["pipeline"]
        top = {"preprocess", "normalise", *SECTIONS}
        kwargs: dict[str, Any] = {}
        sections: dict[str, dict[str, Any]] = {name: {} for name in SECTIONS}
        for key, value in d.items():
            if key in SECTIONS:
                table = config_table(value, SECTIONS[key], f"pipeline config: {key}")
                for k, v in table.items():
                    if k in sections[key]:
                        raise InputError(f"pipeline config: {key}.{k}: given twice (at the top and in [{key}])")
                    sections[key][k] = v
            elif key in top:
                kwargs[key] = value
            elif key in _OPTION_SECTION:
                name = _OPTION_SECTION[key]
                if key in sections[name]:
                    raise InputError(f"pipeline config: {name}.{key}: given twice (at the top and in [{name}])")
                sections[name][key] = value
            else:
                valid = sorted(top | set(_OPTION_SECTION))
                raise InputError(f"pipeline config: unknown key '{key}' (valid: {', '.join(valid)})")
        for name, table in sections.items():
            kwargs[name] = SECTIONS[name](**table)
        return cls(**kwargs)

    @classmethod
    def from_toml(cls, path: str | os.PathLike[str]) -> PipelineConfig:
        """Read a TOML file (top-level keys, a ``[pipeline]`` table and/or its section tables)."""
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
        """Copy with options replaced (validated): ``preprocess``, ``normalise``, a whole section,
        or any section's option by its name (``replace(beta=1.5)`` sets ``classify.beta``)."""
        top: dict[str, Any] = {}
        per_section: dict[str, dict[str, Any]] = {}
        for key, value in changes.items():
            if key in ("preprocess", "normalise") or key in SECTIONS:
                top[key] = value
            elif key in _OPTION_SECTION:
                per_section.setdefault(_OPTION_SECTION[key], {})[key] = value
            else:
                raise InputError(f"pipeline config: unknown option '{key}'")
        for name, opts in per_section.items():
            base = top.get(name, getattr(self, name))
            if isinstance(base, dict):
                base = SECTIONS[name].from_dict(base)
            top[name] = dataclasses.replace(base, **opts)
        return dataclasses.replace(self, **top)

    def option(self, name: str) -> Any:
        """The value of an option by its name (``option("beta")`` is ``classify.beta``)."""
        if name in ("preprocess", "normalise") or name in SECTIONS:
            return getattr(self, name)
        if name not in _OPTION_SECTION:
            raise InputError(f"pipeline config: unknown option '{name}'")
        return getattr(getattr(self, _OPTION_SECTION[name]), name)

    def preprocess_config(self) -> Any:
        """The :class:`PreprocessConfig` used, or None for ``"none"``."""
        from sonarmap.preprocess.pipeline import PreprocessConfig, recipe

        if isinstance(self.preprocess, PreprocessConfig):
            return self.preprocess
        return None if self.preprocess == "none" else recipe(self.preprocess)
