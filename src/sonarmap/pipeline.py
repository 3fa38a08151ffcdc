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
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap._config import is_finite_number
from sonarmap.config import METHODS, SOLVER_NAMES, PipelineConfig
from sonarmap.errors import InputError
from sonarmap.ping import Ping
from sonarmap.ranges import BeamRanges, extract_ranges, half_peak_edges, no_returns
from sonarmap.ranges.candidates import candidate_mask, pooled_band_mask, pooled_band_pixels

__all__ = ["PipelineConfig", "PingProducts", "process_ping", "classify_image", "pooled_band_pixels", "pooled_band_mask", "pulse_bins", "measurement_image", "METHODS", "SOLVER_NAMES"]



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
        quantisation floor, :attr:`PipelineConfig.fit.max_floor_levels`); 0 for an image modelled as
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
    if config.classify.method.startswith("cfar-"):
        return frozenset()
    from sonarmap.stats.model import failed_gates

    return failed_gates(fit, config.fit)


def _classify(image: NDArray[np.float32], config: PipelineConfig, gate: bool = False, *,
              levels: NDArray[Any] | None = None, fit: Any = None
              ) -> tuple[NDArray[np.uint8], Any, float, float, NDArray[Any], frozenset[str]]:
    """:func:`classify_image` plus the quantised levels it classified and the fit gates the fit
    fails (:func:`_gates`; only with ``gate=True``, which also skips the labelling of a gated
    ping: its labels are all background).  ``levels`` and ``fit``, when given, are the image's
    levels and their fit (not recomputed)."""
    from sonarmap.classify.segment import decision_rates, segment
    from sonarmap.stats.mixture import quantize
    from sonarmap.stats.model import fit_levels

    if levels is None or fit is None:
        # the intensity model (eq. 8-11): quantised levels and their mixture fit
        levels = quantize(image, config.fit.n_levels)
        fit = fit_levels(levels, config.fit)
    gates = _gates(fit, config) if gate else frozenset()
    if gates:
        pd, pfa = decision_rates(fit, config.classify)
        return np.zeros(image.shape, dtype=np.uint8), fit, pd, pfa, levels, gates
    # classification (eq. 12-18, 22)
    seg = segment(image, fit, config.classify, levels=levels, n_levels=config.fit.n_levels)
    return seg.labels, fit, seg.pd, seg.pfa, levels, gates


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
            method=config.classify.method, pd_range=pd_range, background=m.background, gates=gates,
            image=m.image if keep_labels else None, input_gain_db=gain_db, floor_levels=m.floor)

    def no_return_products(flags: set[str], pd: float, pfa: float, gates: tuple[str, ...] = ()) -> PingProducts:
        return products(no_returns(geom, time_ns=ping.time_ns, source=ping.source, mode=config.ranges.range_mode),
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
    mask = candidate_mask(labels, geom, config.candidates, normalised=m.normalised is not None)
    thickness = None
    if config.ranges.tracker == "surface":
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
    into the zero level (:attr:`PipelineConfig.fit.max_floor_levels`); the first floor whose fit passes
    every gate is kept, else the ping as recorded.
    """
    from sonarmap.preprocess.normalise import on_8bit_grid
    from sonarmap.stats.model import fit_counts

    m = _model_image(raw, geom, config, reference)
    if not (m.classified is not None and "kld" in m.classified[5] and config.fit.max_floor_levels > 0
            and config.fit.n_levels == 256 and on_8bit_grid(raw)):
        return m
    # a background on the bottom levels of the 8-bit grid: merge them into the zero level - a
    # shift of the level histogram, refitted (no pass over the image until one passes)
    levels = m.classified[4]
    counts = np.asarray(m.classified[1].counts, dtype=np.float64)  # the refused fit's level histogram
    for n in range(1, config.fit.max_floor_levels + 1):
        merged = np.zeros_like(counts)
        merged[0] = counts[: n + 1].sum()
        merged[1:counts.size - n] = counts[n + 1:]
        fit = fit_counts(merged, config.fit)
        if fit is None or _gates(fit, config):
            continue
        image = np.maximum(m.image - np.float32(n / (config.fit.n_levels - 1)), np.float32(0.0))
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
    if not (usable or (config.ranges.refine_bins > 0 and fit is not None)):
        return None, None
    bg = float(np.asarray(fit.class_pmf())[0] @ np.asarray(fit.levels))
    return (bg if usable else None), (config.ranges.edge_factor * bg if config.ranges.refine_bins > 0 else None)


def _rule_ranges(ping: Ping, image: NDArray[np.float32], labels: NDArray[np.uint8], mask: NDArray[np.bool_],
                 config: PipelineConfig, normalised: bool, bg_mean: float | None, edge: float | None) -> BeamRanges:
    """The per-beam rules (``tracker="rules"``): first runs, the isolated-return rule, leading-edge
    refinement, band pooling; half-peak edges on normalised images."""
    geom = ping.geometry

    def _ranges(accepted: NDArray[np.bool_] | None) -> BeamRanges:
        return extract_ranges(
            mask, image, geom, mode=config.ranges.range_mode,  # type: ignore[arg-type]
            min_run=config.ranges.min_run, reject_isolated=config.ranges.reject_isolated,
            neighbour_beams=config.ranges.neighbour_beams, max_jump_bins=config.ranges.max_jump_bins,
            min_segment_beams=config.ranges.min_segment_beams,
            refine_bins=config.ranges.refine_bins if not normalised else 0, edge_level=edge, accepted=accepted,
            time_ns=ping.time_ns,
            source=ping.source,
        )

    ranges = _ranges(None)
    # band pooling: "fallback" only when the per-pixel route found less than one wide surface,
    # "fill" on the beams it left without a return
    fallback = ranges.n_returns < config.candidates.pool_min_beams
    n_beams = ranges.bin.size
    # band pooling multi-looks single-look speckle; a normalised image is multi-looked already
    if (config.candidates.pool_factor > 0 and bg_mean is not None and bg_mean > 0 and not normalised
            and (fallback or (config.candidates.pool_mode == "fill" and ranges.n_returns < n_beams))):
        accepted = pooled_band_pixels(image, config.candidates.pool_factor * bg_mean, pool_beams=config.candidates.pool_beams,
                                      pool_bins=config.candidates.pool_bins, min_beams=config.candidates.pool_min_beams,
                                      beams=None if fallback else ranges.bin < 0)
        if accepted is not None:
            ranges = _ranges(accepted)
    if normalised and config.ranges.edge_fraction > 0:
        # the range convention: the leading edge of the echo (a fraction of its first peak)
        ranges = half_peak_edges(ranges, image, labels >= 1, geom, fraction=config.ranges.edge_fraction)
    return ranges


def _meta_number(ping: Ping, key: str, default: float | None = None) -> float | None:
    """``ping.meta[key]`` as a float: ``default`` when absent, None when it is not a finite number."""
    meta = ping.meta if isinstance(ping.meta, dict) else {}
    if key not in meta:
        return default
    v = meta[key]
    return float(v) if is_finite_number(v) else None


def pulse_bins(ping: Ping, config: PipelineConfig) -> int:
    """The pulse length in range bins (>= 1): ``config.ranges.pulse_length_m``, else the ping's
    ``meta["pulse_width_us"]`` at its sound speed (``meta["sound_speed_m_s"]``, default 1500 m/s)."""
    length = config.ranges.pulse_length_m
    if length is None:
        us = _meta_number(ping, "pulse_width_us")
        c = _meta_number(ping, "sound_speed_m_s", 1500.0)
        ok = us is not None and 0 < us < 1e5 and c is not None and 1300 <= c <= 1700
        length = us * 1e-6 * c / 2.0 if ok else 0.0  # type: ignore[operator]
    dr = abs(ping.geometry.range_resolution_m)
    return max(1, int(round(length / dr))) if dr > 0 else 1


def _log_range_db(ping: Ping, config: PipelineConfig) -> float | None:
    """dB per unit of raw pixel value of log-compressed samples (None: linear samples)."""
    if config.ranges.log_dynamic_range_db is not None:
        return config.ranges.log_dynamic_range_db
    v = _meta_number(ping, "log_dynamic_range_db")
    return v if v is not None and 0 < v < 1000 else None


def measurement_image(ping: Ping, background: Any, config: PipelineConfig = PipelineConfig(), *,
                      rows: tuple[int, int] | None = None) -> NDArray[np.float64]:
    """The image a normalised ping's echoes are measured on: echo intensity above the background,
    in units of the background level, linear in intensity.

    ``ratio = raw / b`` for linear samples, ``10^(D (raw - b) / 10)`` for log-compressed ones
    (``D`` dB per unit, :attr:`PipelineConfig.ranges.log_dynamic_range_db`), with ``b`` the estimated
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
    if (config.candidates.pool_factor > 0 and bg_mean is not None and bg_mean > 0 and not normalised
            and config.classify.method in ("mrf", "map", "threshold") and not mask.any(axis=0).all()):
        band = pooled_band_mask(image, config.candidates.pool_factor * bg_mean, pool_beams=config.candidates.pool_beams,
                                pool_bins=config.candidates.pool_bins, min_beams=config.candidates.pool_min_beams)
        if band is not None:
            cand = cand | band
    if not cand.any():
        return (no_returns(geom, time_ns=ping.time_ns, source=ping.source, mode=config.ranges.range_mode),
                np.zeros(geom.n_beams, dtype=np.int64))
    llr_lut = level_llr(fit) if fit is not None and len(fit.class_names) >= 2 else None
    lut = np.maximum(llr_lut, 0.0) if llr_lut is not None else np.ones(int(levels.max()) + 1)
    fraction = config.ranges.edge_fraction if config.ranges.edge_fraction > 0 else 0.5
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
                             pulse_bins=pb, fraction=fraction, background=bg, scan=config.ranges.edge_scan,
                             sigma_scale=config.ranges.sigma_scale)
        return meas, bg, echoes, track_surfaces(echoes, config.ranges.track)

    meas, bg, echoes, tracks = measure(cand)
    if config.ranges.continue_evidence > 0 and llr_lut is not None:
        # a surface's faint stretch that the component rule left without candidates: pixels along
        # its extrapolation where their likelihood ratio says structure, for the tracker to judge
        extra = continuation_mask(echoes, tracks.first, levels, llr_lut, min_evidence=config.ranges.continue_evidence,
                                  touch_bins=config.ranges.track.touch_bins) & ~cand
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
    if config.ranges.edge_pool_beams > 0 and config.ranges.range_mode == "first":
        # the pooled profile is smoothed over at least 3 bins along range in all (a single-look
        # profile's maximum is otherwise a speckle spike)
        echoes = pooled_edges(echoes, sel, meas, geom, pulse_bins=pb, half_beams=config.ranges.edge_pool_beams,
                              smooth_bins=3 if pb < 3 else 1, fraction=fraction,
                              touch_bins=config.ranges.track.touch_bins, sigma_scale=config.ranges.sigma_pool_scale)
    if echoes.size and (sel >= 0).any():
        echoes = _clipped_echo_sigma(echoes, sel, ping.image, geom)
    thickness = np.where(sel >= 0, (echoes.stop_bin - echoes.start_bin)[np.maximum(sel, 0)] if echoes.size else 0, 0)
    return (ranges_from_tracks(echoes, tracks, geom, image, mode=config.ranges.range_mode,  # type: ignore[arg-type]
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
