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
import functools
import math
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from sonarmap.classify.segment import decision_rates, segment
from sonarmap.config import METHODS, SOLVER_NAMES, PipelineConfig
from sonarmap.errors import InputError
from sonarmap.ping import Ping
from sonarmap.preprocess.crosstalk import remove_crosstalk
from sonarmap.preprocess.normalise import RecordingBackground, condition_image, estimate_background_levels, on_8bit_grid
from sonarmap.preprocess.pipeline import preprocess_finite, preprocess_image
from sonarmap.ranges import BeamRanges, no_returns
from sonarmap.ranges.candidates import candidate_mask, pooled_band_mask, pooled_band_pixels
from sonarmap.ranges.measure import background_mean, rule_ranges, surface_ranges
from sonarmap.stats.model import failed_gates, fit_counts, fit_levels

__all__ = ["PipelineConfig", "PingProducts", "process_ping", "measurement_image", "classify_image", "pooled_band_pixels", "pooled_band_mask", "METHODS", "SOLVER_NAMES"]


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

    @classmethod
    def _of(cls, **fields: Any) -> PingProducts:
        """The products with every field given, built without the frozen dataclass
        ``__init__``'s per-field ``object.__setattr__`` (one per ping)."""
        products = object.__new__(cls)
        products.__dict__.update(fields)
        return products

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
    return failed_gates(fit, config.fit)


def _classify(image: NDArray[np.float32], config: PipelineConfig, gate: bool = False, *,
              levels: NDArray[Any] | None = None, fit: Any = None
              ) -> tuple[NDArray[np.uint8], Any, float, float, NDArray[Any], frozenset[str]]:
    """:func:`classify_image` plus the quantised levels it classified and the fit gates the fit
    fails (:func:`_gates`; only with ``gate=True``, which also skips the labelling of a gated
    ping: its labels are all background).  ``levels`` and ``fit``, when given, are the image's
    levels and their fit (not recomputed)."""
    import sonarmap.stats.mixture as _mixture  # (scipy: imported with the first ping)

    if levels is None or fit is None:
        # the intensity model (eq. 8-11): quantised levels and the mixture fit of their histogram
        levels, counts = _mixture.quantize_counts(image, config.fit.n_levels)
        fit = fit_counts(counts, config.fit)
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
    _check_arguments(ping, config, background)
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
        return PingProducts._of(
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
    bg_mean, edge = background_mean(fit, config.ranges)
    normalised = m.normalised is not None
    mask = candidate_mask(labels, geom, config.candidates, normalised=normalised)
    thickness = None
    if config.ranges.tracker == "surface":
        ranges, thickness = surface_ranges(
            ping, m.image, levels, mask, fit, config.ranges, config.candidates, normalised=normalised,
            bg_mean=bg_mean, background=m.background, pool_bands=config.classify.method in ("mrf", "map", "threshold"),
            # (the ping's maximum, when the conditioned image is the ping's own: no pass of its own)
            image_max=m.raw_max if raw is ping.image else None,
            # (the edge image is made only when a candidate needs it: none on a ping without structure)
            edge_image=None if normalised else functools.partial(measurement_image, raw, geom, config, labels,
                                                                 m.image, bg_mean))
    else:
        ranges = rule_ranges(ping, m.image, labels, mask, config.ranges, config.candidates, normalised=normalised,
                             bg_mean=bg_mean, edge=edge)
    flags = set(fit.flags) if fit is not None else {"no_fit"}
    n_returns, detecting = _return_counts(labels, ranges)
    if n_returns == 0:
        flags.add("no_returns")
    pd_range = _pd_range(float(pd), flags, n_returns, detecting)
    if thickness is not None:
        ranges = ranges.with_p_detect(_p_detect(float(pd), pd_range, ranges, thickness))
    return products(ranges, flags, labels, pd, pfa, pd_range)


def measurement_image(raw: NDArray[np.float32], geom: Any, config: PipelineConfig, labels: NDArray[np.uint8],
                      image: NDArray[np.float32], bg_mean: float | None) -> tuple[NDArray[np.float32], float] | None:
    """The image the echoes of a pre-processed (not normalised) ping are measured on, and its
    background mean (``RangeConfig.edge_image``; ``surface_ranges(edge_image=...)``).

    Parameters
    ----------
    raw : ndarray, float32, shape (n_bins, n_beams)
        The conditioned ping (:func:`sonarmap.preprocess.normalise.condition_image`).
    geom : SonarGeometry
    config : PipelineConfig
    labels, image : ndarray, shape (n_bins, n_beams)
        The classifier's labels (0 background) and the pre-processed image it saw.
    bg_mean : float or None
        The fitted background class's mean intensity in ``image``.

    Returns
    -------
    (ndarray, float) or None
        The ping's pre-processing without the deconvolution of the beam pattern (when it
        deconvolves and ``config.ranges.edge_image == "undeconvolved"``), less the crosstalk
        lit across the fan (``config.ranges.edge_crosstalk``,
        :func:`sonarmap.preprocess.crosstalk.remove_crosstalk`), and ``bg_mean`` in its units;
        None: the echoes are measured on ``image`` itself.
    """
    pre = config.preprocess_config()
    if config.ranges.edge_image != "undeconvolved" or pre is None or not pre.deconvolve or geom.psf is None:
        return None
    edge = preprocess_finite(raw, geom, _undeconvolved(pre), float(raw.max()))
    if config.ranges.edge_crosstalk:
        # the rows lit across the fan that the deconvolution would have removed
        edge = remove_crosstalk(edge, labels)
    # the background mean of the classified image, in the units of ``edge``: the ratio of the two
    # images' means over the background pixels (every 4th row: the ratio, not every pixel, is
    # wanted)
    bg = labels[::4] == 0
    if not bg.any():
        return edge, 0.0
    a = float(edge[::4][bg].mean())
    b = float(image[::4][bg].mean())
    return edge, (bg_mean * a / b if bg_mean and b > 0 else a)


@functools.lru_cache(maxsize=8)
def _undeconvolved(pre: Any) -> Any:
    """``pre`` without its deconvolution (cached: every ping of a recording asks for it)."""
    return pre.replace(deconvolve=False)


def _check_arguments(ping: Any, config: Any, background: Any) -> None:
    """The types :func:`process_ping` takes (an :class:`InputError` naming the argument)."""
    if not isinstance(ping, Ping):
        raise InputError(f"ping: expected a Ping, got {type(ping).__name__}")
    if not isinstance(config, PipelineConfig):
        raise InputError(f"config: expected a PipelineConfig, got {type(config).__name__}")
    if background is not None and config.normalise == "auto":
        if not isinstance(background, RecordingBackground):
            raise InputError(f"background: expected a RecordingBackground, got {type(background).__name__}")


class _Modelled(NamedTuple):
    """What :func:`_model_ping` made of a ping: the image the classifier saw, the normalised image
    (None when not normalised), the background estimate, ``(labels, fit, pd, pfa, levels, gates)``
    of :func:`_classify` (None for a constant image), the quantisation floor used and the
    conditioned image's maximum (a named tuple: one per ping, without a frozen dataclass's
    per-field ``object.__setattr__``)."""

    image: NDArray[np.float32]
    normalised: NDArray[np.float32] | None
    background: Any
    classified: tuple[Any, ...] | None
    floor: int
    raw_max: float


def _model_ping(raw: NDArray[np.float32], geom: Any, config: PipelineConfig, reference: Any) -> _Modelled:
    """The modelling stage: normalise (or pre-process) the conditioned image, fit, gate, classify.

    An 8-bit ping whose fit fails the ``kld`` gate is modelled again with its lowest levels merged
    into the zero level (:attr:`PipelineConfig.fit.max_floor_levels`); the first floor whose fit passes
    every gate is kept, else the ping as recorded.
    """
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
        return m._replace(image=image, floor=n, classified=_classify(image, config, gate=True, levels=shifted, fit=fit))
    return m


def _model_image(raw: NDArray[np.float32], geom: Any, config: PipelineConfig, reference: Any) -> _Modelled:
    """:func:`_model_ping` of one image, without the quantisation floor."""
    raw_max = float(raw.max())
    constant = _all_equal(raw, raw_max)
    background = None
    normalised = None
    levels = None
    if config.normalise == "auto" and not constant:
        # (the normalised image's quantisation levels come from the same pass)
        background, normalised, levels = estimate_background_levels(raw, n_levels=config.fit.n_levels,
                                                                     reference=reference)
    pre = config.preprocess_config()
    if normalised is not None:
        image = normalised
    elif pre is None or constant:
        image = raw
    elif background is not None:
        # the background estimate has checked that every pixel of ``raw`` is finite
        image = preprocess_finite(raw, geom, pre, raw_max)
    else:
        image = preprocess_image(raw, geom, pre)
    if constant or _flat(image):
        return _Modelled(image, normalised, background, None, 0, raw_max)
    # (levels come only with a normalised image)
    fit = fit_levels(levels, config.fit) if levels is not None else None
    return _Modelled(image, normalised, background, _classify(image, config, gate=True, levels=levels, fit=fit), 0,
                     raw_max)


def _flat(image: NDArray[np.float32]) -> bool:
    """No positive pixel, or one value everywhere (``not np.any(image > 0) or max == min``; for
    an image without NaN ``np.any(image > 0)`` is ``max > 0``, which saves a pass)."""
    hi = float(image.max())
    if math.isnan(hi):
        return not np.any(image > 0)  # NaN compares unequal: max == min is False
    return not hi > 0 or _all_equal(image, hi)


def _all_equal(image: NDArray[Any], hi: float) -> bool:
    """``hi == image.min()`` for ``hi = image.max()`` (False when ``hi`` is NaN): every pixel
    is ``hi``.  A first pixel that is not ``hi`` says no without the pass for the minimum."""
    if math.isnan(hi) or float(image.flat[0]) != hi:
        return False
    return hi == float(image.min())


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
    import sonarmap._pipeline_kernels as _plk

    n = ranges.n_beams
    if not (math.isfinite(pd) and math.isfinite(pd_range)) or pd <= 0:
        return np.full(n, np.nan if not math.isfinite(pd_range) else pd_range, dtype=np.float32)
    # the thickness per beam, the median of the returns' (np.median) on the beams without one
    t, valid, n_valid = _plk.echo_thickness(np.ascontiguousarray(thickness, dtype=np.float64),
                                            np.ascontiguousarray(ranges.bin, dtype=np.int64))
    f = 1.0 - (1.0 - min(pd, 1.0)) ** t
    fv = f[valid] if n_valid else f
    mean = float(fv.sum()) / fv.size  # = fv.mean(): numpy's sum over the count, without its wrapper
    return _plk.scaled_rates(f, float(pd_range), max(mean, 1e-12))  # type: ignore[no-any-return]


def _labelled_columns(labels: NDArray[Any]) -> NDArray[np.bool_]:
    """``labels.any(axis=0)``: the beams holding a labelled pixel (one pass of a kernel for a
    C-contiguous unsigned label image, the classifiers' output)."""
    if labels.ndim == 2 and labels.dtype.kind == "u" and labels.flags.c_contiguous:
        from sonarmap._pipeline_kernels import any_columns

        return any_columns(labels)  # type: ignore[no-any-return]
    return labels.any(axis=0)  # type: ignore[no-any-return]


def _return_counts(labels: NDArray[np.uint8], ranges: BeamRanges) -> tuple[int, int]:
    """``(ranges.n_returns, detecting)``: the beams with a return, and the beams with a labelled
    pixel or a return (one kernel call for the classifiers' labels)."""
    if labels.ndim == 2 and labels.dtype.kind == "u" and labels.flags.c_contiguous and ranges.bin.dtype == np.int64:
        import sonarmap._pipeline_kernels as _plk

        n_returns, detecting = _plk.return_counts(labels, ranges.bin)
        return int(n_returns), int(detecting)
    return ranges.n_returns, int(np.count_nonzero(_labelled_columns(labels) | (ranges.bin >= 0)))  # uint8: >= 1 is != 0


def _pd_range(pd: float, flags: set[str], n_returns: int, detecting: int) -> float:
    """``pd`` times the fraction of detecting beams that kept a return (see ``PingProducts.pd_range``;
    ``n_returns``, ``detecting``: :func:`_return_counts`)."""
    if "no_fit" in flags or not math.isfinite(pd):
        return math.nan
    if detecting == 0:
        return pd
    return pd * n_returns / detecting
