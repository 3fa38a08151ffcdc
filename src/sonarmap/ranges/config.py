"""Configuration of the candidate and range stages (sections of :class:`sonarmap.config.PipelineConfig`)."""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

from sonarmap._config import (
    ConfigSection,
    check_booleans,
    check_choice,
    check_integers,
    coerce_reals,
    config_error,
    config_table,
    is_finite_number,
)
# the pooling's defaults, one source for the function (pooled_edges) and the pipeline's section
from sonarmap.ranges.echoes import POOL_FLANK_BINS, POOL_LEAD_BINS, POOL_PEAK_BINS

__all__ = ["CandidateConfig", "RangeConfig"]


@dataclasses.dataclass(frozen=True)
class CandidateConfig(ConfigSection):
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
        17 beams and 13 bins (8 seeds each; ``docs/ranges.md``).
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
    pool_link_beams, pool_link_bins : int, float
        With the surface tracker, a pooled band shorter than ``pool_min_beams`` is kept too when
        it continues a kept band across beams
        (:func:`sonarmap.ranges.candidates.continued_bands`): within ``pool_link_beams`` beams of
        it and ``pool_link_bins`` bins per beam from it in range, mostly on beams it does not
        hold (``pool_link_beams`` 0 = off).  A rippled seafloor's band breaks into short pieces
        at its steep flanks.
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
    pool_link_beams: int = 4
    pool_link_bins: float = 2.0
    pool_mode: str = "fill"

    def __post_init__(self) -> None:
        w = self._where
        coerce_reals(self, ("pool_factor", "min_component_extent_m", "pool_link_bins"), w, minimum=0)
        check_integers(self, (("min_component_beams", 1), ("min_component_bins", 1), ("min_component_pixels", 0),
                              ("normalised_component_beams", 1), ("normalised_component_bins", 1),
                              ("normalised_component_pixels", 0), ("link_beams", 0), ("pool_beams", 0),
                              ("pool_bins", 1), ("pool_min_beams", 1), ("pool_link_beams", 0)), w)
        check_choice(self, "pool_mode", ("fallback", "fill"), w)


@dataclasses.dataclass(frozen=True)
class RangeConfig(ConfigSection):
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
    edge_image : str
        The image the echoes of a ping that is pre-processed rather than normalised (the DIDSON's
        thresholded 8-bit output) are measured on: ``"undeconvolved"`` (default: the same
        pre-processing without the beam-pattern deconvolution) or ``"classified"`` (the image the
        classifier saw).  The classifier keeps the deconvolved image, which removes the ghosts at
        the same range; the edges do not, because that deconvolution moves them: the DIDSON's
        stated beam pattern puts 57 % / 46 % / 39 % of the main beam at +-8 / 16 / 24 beams, the
        real DIDSON ping 5 shows 3.1 % / 0.7 % / 0.5 %
        (:data:`sonarmap.simulate.render.MEASURED_DIDSON_GHOSTS`), so where a surface's range
        changes across beams the deconvolution subtracts from each beam's rising flank ghosts its
        neighbours' peaks do not cast, and the front of the echo is clipped away (a noise-free
        simulated DIDSON hull: per beam, half-peak crossings a median 1.96 bins late on the
        deconvolved image, 0.10 bin early on the recorded one; ``docs/ranges.md``, "The
        image the edges are measured on").  The cost: the deconvolution also removed a band at
        a bright echo's range across the fan (crosstalk), into which a few edges on steep
        flanks beside it would move (real DIDSON ping 9: 11 of 87) without ``edge_crosstalk``.
        Ignored with ``tracker="rules"`` and for normalised pings (their echoes are measured on
        the recorded samples over the background level).
    edge_crosstalk : bool
        With ``edge_image="undeconvolved"``: subtract from each range row of that image the
        level lit across the fan beyond the water column (crosstalk at a bright echo's range,
        :mod:`sonarmap.preprocess.crosstalk`), estimated on the beams whose first structure lies
        behind the row (default True).  On the real DIDSON test pings it moves the edges of
        ping 9's steep flanks (beams 45-53, 67-80) and of pings 4 and 8 where the band crosses the
        hull back onto the echo's front; the simulator, without crosstalk, is unchanged within
        0.003 (``docs/ranges.md``, "The image the edges are measured on").
    edge_pool_beams : int
        Leading edges of a tracked surface are measured on the mean of the edge-aligned profiles
        of the ``edge_pool_beams`` beams on either side of each beam on the same surface
        (:func:`sonarmap.ranges.echoes.pooled_edges`: a multi-look along the surface; a single
        beam's speckled echo moves its half-peak crossing by bins).  0 = every beam on its own.
    edge_pool_scan : str
        How the crossing is found on the pooled mean profile: ``"forward"`` (default: the first
        bin from the profile's front that reaches the level - the range convention's first
        crossing) or ``"back"`` (walk from the profile's peak towards the sonar to the first bin
        below it, as ``edge_scan`` does on a single beam, where a speckle spike in front would
        otherwise be the crossing; on a deep mean profile that walk stops at a dip inside the
        echo, behind its front).
    edge_pool_flank_bins : int
        The pooled crossing of an unclipped echo is that of the least-squares line through the
        mean profile's rising flank - its samples between 20 % and 80 % of the peak, at most this
        many either side of the crossing - instead of the two samples around it: a slow,
        speckled rise (the Oculus hulls' echoes rise over 35-100 bins) is measured with all its
        samples, and its sigma with the echo's rise rather than a speckle step's.  Default 6;
        0 = the two samples (``docs/ranges.md``, "Pooled edges").
    edge_pool_peak_bins : int
        > 0: the height of the pooled profile's first peak, which sets the level
        ``edge_fraction`` x peak, is the maximum of the least-squares parabola through the
        profile's samples up to this many bins either side of its largest one (on echoes at least
        6 times this many bins deep), not that largest sample - the sample the speckle raised
        most, which lies above the echo's peak and puts the crossing late on the rise.  Default
        2; 0 = the largest sample (``docs/ranges.md``, "Pooled edges").
    edge_pool_lead_bins : int
        A pooled edge is kept when it lies at most the pulse length plus this many bins in front
        of the beam's first structure bin (and not behind its echo's end); else the beam keeps its
        own edge.  Where the classifier labels only the bright core of a faint or grazing echo
        (the faint end of a surface, a fan edge), the echo's half-peak crossing lies well in front
        of that bin, and the pooled edge finds it there.  Default 12: what the pooling's two
        alignment rounds, 6 bins in front of the alignment each, can move an edge.  It trusts the
        crosstalk removal: where that misses a band lit across the fan in front of a surface (the
        real DIDSON ping 8 classified by ICM), the edges slide onto the band; 2 keeps them on the
        labelled echo there (``docs/ranges.md``, "Pooled edges").
    edge_pool_align_beams : int
        The pooling starts from each beam's edge on the surface's local line - the Theil-Sen line
        through the edges of the beams of its surface within this many on either side - instead
        of the beam's own edge (0, default: off).  A single-look edge found far behind a slowly
        rising echo (the speckled ramp below the detection level) then no longer drags its
        neighbours' multi-look with it (``docs/ranges.md``, "Leading edges": "Pooling from the
        surface's line", measured with 3).
    edge_pool_follow_slope : float
        > 0: each pooling round aligns a window's beams on the median of their edges along the
        window's Theil-Sen slope where that slope is at least this many bins per beam (none below
        half of it, a share in between: :func:`sonarmap.ranges._kernels._sloped_median`), not on
        their plain running median - which on a surface steeper than the edges' scatter is each
        beam's own edge, its noise kept, so the pooled profile is smeared and its half-peak
        crossing early.  Default 0 = off (``docs/ranges.md``, "Options": what 2 changes).
    pulse_length_m : float, optional
        Transmit pulse length along range (``c tau / 2``); echoes are measured on the image
        smoothed over it.  Default: from the ping - its effective length ``1 / B`` where the file
        gives the transmit bandwidth ``B`` (``meta["effective_pulse_us"]``, Kongsberg), else its
        ``meta["pulse_width_us"]`` (ARIS) - else none.
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
        (``docs/ranges.md``).  Every return's sigma also covers the clipping of its echo
        (the interval from the crossing to the first sample at the ping's full scale,
        :func:`sonarmap.ranges.measure.full_scale_level`).
    sigma_pool_floor : float
        > 0: a pooled edge's jitter (the profile's standard error over its rise, bins) is at least
        this fraction of the median jitter of the pooled edges of its surface within twice
        ``edge_pool_beams`` on either side (:func:`sonarmap.ranges._kernels.floor_jitter`): the
        rise at one crossing is itself noisy, and an edge given a small sigma by one steep speckle
        step would outweigh its neighbours in the smoothing along the surface.  Default 0.5;
        0 = off (``docs/ranges.md``, "Uncertainty").
    sigma_fit_scale : float
        Sigma of a clipped echo's fitted leading edge (a Gaussian fitted to the unclipped flanks
        of the pooled profile, :func:`sonarmap.ranges.echoes.pooled_edges`): the fit's standard
        error times this factor; such a return's sigma no longer adds the clipping interval.
        ``sigma_pool_scale``, ``sigma_fit_scale`` and ``sigma_template_scale`` are fitted together
        on the simulator (every preset, seeds 0-2 and 3-5) so that about 68 % of the errors of all
        returns lie within +-sigma (``docs/ranges.md``, "Uncertainty").
    edge_template_beams : int
        Leading edges of surfaces of at least ``edge_template_min_beams`` beams are measured
        against the surface's own echo template, the mean of the ``edge_template_beams`` beams on
        either side aligned on the surface's local course
        (:func:`sonarmap.ranges.template.template_edges`): every sample of the rise informs the
        edge.  0 = off (the pooled or per-beam edges are kept).
    edge_template_min_beams : int
        Shortest surface measured against a template (shorter runs - propeller blades, small
        objects - change their echo's shape within a template's width).
    edge_template_anchor_beams : int
        The template edges keep their relative positions and take their level from the edges
        they replace: each moves by the median of (edge before - template edge) over the
        template-measured beams within this many beams of it.  0 = the template's own half-peak
        crossing is the edge (noisier; on the real Kongsberg swath a median 2 samples early on
        the oblique beams).
    sigma_template_scale : float
        Sigma of a template-measured edge: the standard error of the template's position
        (its sandwich variance: the scatter of the beams' scores over the squared Fisher
        information), of its crossing and of the anchor's median, in quadrature, times this
        factor (``docs/ranges.md``, "Template edges").
        The anchor's median is taken over pooled edges whose windows (``2 edge_pool_beams + 1``
        beams) overlap: ``c`` of them count as ``c / (2 edge_pool_beams + 1)`` independent ones.
        Fitted on the simulator (seeds 0-8, every preset): the factor that puts every preset's
        share of returns within +-sigma inside 0.68 +- 0.05 over the nine seeds (seeds 9-11 held
        out; ``docs/ranges.md``, "Uncertainty").
    edge_template_anchor_trust : bool
        Whether the smoothing along the surface (``edge_smooth_beams``) weighs a template edge as
        if its anchor were as uncertain as the pooled edges it reads (their own sigmas, where that
        is more than the scatter of the offsets says: ``Echoes.smooth_trust``); the sigma it
        reports is shrunk as its own sigma would be against the same prediction.  Where a run of
        pooled edges is late together (single-look edges far behind a slowly rising echo drag their
        windows), the anchor's scatter is small but the pooled sigmas are large, and the smoothing
        then leans on the neighbours.  Default False (docs/ranges.md, "Template edges trusted as
        their anchor").
    sigma_template_smooth_scale : float
        How much less the smoothing along the surface (``edge_smooth_beams``) trusts a
        template-measured edge than its sigma says: inside the smoothing such an edge weighs, and
        is pulled towards its neighbours' prediction, as if its sigma were this many times larger;
        the sigma it reports is shrunk as its own sigma would be against the same prediction.
        Default 1.0 (the template sigma as is).  A template edge's errors are heavier-tailed than
        its sigma where single-look speckle fades the front of the echo on a few neighbouring
        beams (the template's 3-beam fit follows the fade: simulated DIDSON flat hull, 3-4 bins
        late on 6 beams with sigmas of 0.5 bin); 2.0 pulls such edges back on smooth surfaces
        (hulls) but flattens relief at the window's scale (the simulated rippled seafloor survey
        registers at 0.56 instead of 0.47 bins RMS) - ``docs/ranges.md``, "Smoothing along the
        surface".  At least 1.
    edge_smooth_beams : int
        Each first return's leading edge is combined with the prediction of the edges within this
        many beams on either side on its surface (a leave-one-out local quadratic across beams),
        weighted by their sigmas and by the surface's roughness
        (:func:`sonarmap.ranges.smoothing.smooth_surface_edges`): a noisy edge moves towards its
        neighbours, a precise one stays.  Counted in beams of a fan whose beams are at most one
        spacing wide; a fan of overlapping beams (the geometry's ``azimuth_beamwidth_rad`` wider
        than the beam spacing) takes that many beamwidths
        (:func:`sonarmap.ranges.smoothing.window_in_beamwidths`).  0 = off; else >= 2.  The
        default 16 was chosen over 8, 12 and 24 on the simulator's held-out seeds and the Kongsberg
        swath's own detections (``docs/ranges.md``, "Smoothing along the surface").
    edge_smooth_min_beams : int
        Shortest run of returns combined (>= 5).
    surface_min_z : float
        A first return's surface on a normalised ping is kept only when its echo stands at least
        this many robust standard deviations (scaled MAD) above the same surface moved into the
        water column in front of it (:func:`sonarmap.ranges.significance.surface_significance`);
        the beams of a dropped surface report no first return.  0 = off.
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
    edge_image: str = "undeconvolved"
    edge_crosstalk: bool = True
    edge_pool_beams: int = 3
    edge_pool_scan: str = "forward"
    edge_pool_flank_bins: int = POOL_FLANK_BINS
    edge_pool_peak_bins: int = POOL_PEAK_BINS
    edge_pool_lead_bins: int = POOL_LEAD_BINS
    edge_pool_align_beams: int = 0
    edge_pool_follow_slope: float = 0.0
    pulse_length_m: float | None = None
    continue_evidence: float = 10.0
    sigma_scale: float = 1.5
    sigma_pool_scale: float = 5.0
    sigma_fit_scale: float = 4.0
    sigma_pool_floor: float = 0.5
    edge_template_beams: int = 5
    edge_template_min_beams: int = 30
    edge_template_anchor_beams: int = 10
    sigma_template_scale: float = 0.8
    edge_template_anchor_trust: bool = False
    sigma_template_smooth_scale: float = 1.0
    edge_smooth_beams: int = 16
    edge_smooth_min_beams: int = 7
    surface_min_z: float = 3.5
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
        check_choice(self, "edge_image", ("undeconvolved", "classified"), w)
        check_booleans(self, ("edge_crosstalk", "edge_template_anchor_trust"), w)
        check_choice(self, "edge_pool_scan", ("forward", "back"), w)
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
        coerce_reals(self, ("sigma_scale", "sigma_pool_scale", "sigma_fit_scale", "sigma_template_scale",
                            "sigma_pool_floor", "continue_evidence", "surface_min_z", "edge_pool_follow_slope"), w,
                     minimum=0)
        coerce_reals(self, ("edge_fraction",), w)
        coerce_reals(self, ("sigma_template_smooth_scale",), w, minimum=1)
        if not 0 <= self.edge_fraction < 1:
            raise config_error(w, "edge_fraction", "must lie in [0, 1)", self.edge_fraction)
        check_integers(self, (("min_run", 1), ("neighbour_beams", 1), ("max_jump_bins", 0),
                              ("min_segment_beams", 1), ("refine_bins", 0), ("edge_pool_beams", 0),
                              ("edge_pool_flank_bins", 0), ("edge_pool_peak_bins", 0), ("edge_pool_lead_bins", 0),
                              ("edge_pool_align_beams", 0),
                              ("edge_template_beams", 0), ("edge_template_min_beams", 3),
                              ("edge_template_anchor_beams", 0), ("edge_smooth_beams", 0),
                              ("edge_smooth_min_beams", 5)), w)
        if self.edge_smooth_beams == 1:
            raise config_error(w, "edge_smooth_beams", "must be 0 (off) or >= 2", self.edge_smooth_beams)
        check_booleans(self, ("reject_isolated",), w)

    def to_dict(self) -> dict[str, Any]:
        d = super().to_dict()
        d["track"] = dataclasses.asdict(self.track)
        for key in ("pulse_length_m", "log_dynamic_range_db"):
            if d[key] is None:
                del d[key]
        return d
