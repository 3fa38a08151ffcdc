"""The measurement stage of the per-ping pipeline: per-beam returns of the candidate structure.

The range convention (``DESIGN.md``): a return's range is the leading edge of its echo - the first
crossing of ``edge_fraction`` of the echo's first peak after smoothing along range over the pulse
length - with a sigma.  :func:`surface_ranges` (``tracker="surface"``, the default) finds the
echoes of the candidate pixels (:mod:`sonarmap.ranges.candidates`) on every beam, tracks surfaces
across beams (:mod:`sonarmap.ranges.tracking`) and measures their leading edges on pooled
profiles (:func:`sonarmap.ranges.echoes.pooled_edges`); :func:`rule_ranges` is the previous
per-beam rules tracker.  Normalised pings are measured on :func:`measurement_image` (echo above
the background, linear in intensity).  Called alone with the default
:class:`~sonarmap.ranges.config.RangeConfig` and
:class:`~sonarmap.ranges.config.CandidateConfig` they give what
:func:`sonarmap.pipeline.process_ping` reports.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap._config import is_finite_number
from sonarmap.ping import Ping
from sonarmap.ranges import BeamRanges, extract_ranges, half_peak_edges, no_returns, track_returns
from sonarmap.ranges.candidates import pooled_band_mask, pooled_band_pixels
from sonarmap.ranges.config import CandidateConfig, RangeConfig
from sonarmap.ranges.echoes import (POOL_FIT_FRONT_BINS, POOL_FRONT_BINS, POOL_MAX_BINS, POOL_N_ITER, _boost_pixels,
                                    _echoes_of, _evidence_table, _pooled, level_llr, smooth_along_range,
                                    spliced_echoes)
from sonarmap.ranges.significance import surface_significance
from sonarmap.ranges.tracking import (CONTINUE_MAX_BEAMS, CONTINUE_MAX_MISSES, CONTINUE_MIN_RUN,
                                      CONTINUE_WINDOW_BINS, Tracks, _continuation_inputs, track_surfaces,
                                      tracks_and_front)
from sonarmap.ranges.template import template_edges
from sonarmap.ranges.smoothing import smooth_surface_edges, window_in_beamwidths

__all__ = ["surface_ranges", "rule_ranges", "measurement_image", "pulse_bins", "background_mean",
           "clipped_echo_sigma", "clipped_echoes", "clipped_gaussian_edges", "clip_rows", "CLIP_LEVEL",
           "full_scale_mask",
           "full_scale_level"]


def background_mean(fit: Any, config: RangeConfig = RangeConfig()) -> tuple[float | None, float | None]:
    """The fitted background class's mean intensity (None when the fit has no usable classes) and
    the leading-edge level of the rules tracker (``edge_factor`` x that mean; None when off)."""
    usable = fit is not None and fit.classifiable
    if not (usable or (config.refine_bins > 0 and fit is not None)):
        return None, None
    bg = float(np.asarray(fit.class_pmf(copy=False))[0] @ np.asarray(fit.levels))
    return (bg if usable else None), (config.edge_factor * bg if config.refine_bins > 0 else None)


def rule_ranges(ping: Ping, image: NDArray[np.float32], labels: NDArray[np.uint8], mask: NDArray[np.bool_],
                config: RangeConfig = RangeConfig(), candidates: CandidateConfig = CandidateConfig(), *,
                normalised: bool = False, bg_mean: float | None = None, edge: float | None = None) -> BeamRanges:
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
    fallback = ranges.n_returns < candidates.pool_min_beams
    n_beams = ranges.bin.size
    # band pooling multi-looks single-look speckle; a normalised image is multi-looked already
    if (candidates.pool_factor > 0 and bg_mean is not None and bg_mean > 0 and not normalised
            and (fallback or (candidates.pool_mode == "fill" and ranges.n_returns < n_beams))):
        accepted = pooled_band_pixels(image, candidates.pool_factor * bg_mean, pool_beams=candidates.pool_beams,
                                      pool_bins=candidates.pool_bins, min_beams=candidates.pool_min_beams,
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


def pulse_bins(ping: Ping, config: RangeConfig = RangeConfig()) -> int:
    """The pulse length in range bins (>= 1): ``config.pulse_length_m``, else the ping's
    effective pulse length ``meta["effective_pulse_us"]`` (``1 / B`` of the transmit bandwidth
    ``B``, where the file gives it: Kongsberg), else its ``meta["pulse_width_us"]``, at its sound
    speed (``meta["sound_speed_m_s"]``, default 1500 m/s)."""
    length = config.pulse_length_m
    if length is None:
        us = _meta_number(ping, "effective_pulse_us")
        if us is None:
            us = _meta_number(ping, "pulse_width_us")
        c = _meta_number(ping, "sound_speed_m_s", 1500.0)
        ok = us is not None and 0 < us < 1e5 and c is not None and 1300 <= c <= 1700
        length = us * 1e-6 * c / 2.0 if ok else 0.0  # type: ignore[operator]
    dr = abs(ping.geometry.range_resolution_m)
    return max(1, int(round(length / dr))) if dr > 0 else 1


def _log_range_db(ping: Ping, config: RangeConfig) -> float | None:
    """dB per unit of raw pixel value of log-compressed samples (None: linear samples)."""
    if config.log_dynamic_range_db is not None:
        return config.log_dynamic_range_db
    v = _meta_number(ping, "log_dynamic_range_db")
    return v if v is not None and 0 < v < 1000 else None


def measurement_image(ping: Ping, background: Any, config: RangeConfig = RangeConfig(), *,
                      rows: tuple[int, int] | None = None) -> NDArray[np.float64]:
    """The image a normalised ping's echoes are measured on: echo intensity above the background,
    in units of the background level, linear in intensity.

    ``ratio = raw / b`` for linear samples, ``10^(D (raw - b) / 10)`` for log-compressed ones
    (``D`` dB per unit, :attr:`RangeConfig.log_dynamic_range_db`), with ``b`` the estimated
    background level x beam factor (:mod:`sonarmap.preprocess.normalise`); then
    ``max(ratio - 1, 0)``.  No multi-look: the leading edge keeps the raw range resolution.
    ``rows=(r0, r1)`` computes only those rows (zero elsewhere).
    """
    from sonarmap.ranges._kernels import excess_ratio
    from sonarmap.preprocess.normalise import expand_grid

    raw = np.ascontiguousarray(ping.image, dtype=np.float32)
    level = np.ascontiguousarray(background.level_by_bin, dtype=np.float32)
    full = (np.ones(raw.shape, np.float32) if background.beam_factor is None
            else np.ascontiguousarray(expand_grid(background.beam_factor, raw.shape), dtype=np.float32))
    d = _log_range_db(ping, config)
    r0, r1 = (0, raw.shape[0]) if rows is None else rows
    out = excess_ratio(raw, level, full, float(d) if d is not None else 0.0, int(r0), int(r1))
    if d is not None and d > 0:
        expm1_rows(out, int(r0), int(r1))
    return out


def expm1_rows(out: NDArray[np.float64], r0: int, r1: int) -> None:
    """``out[r0:r1] = exp(out[r0:r1]) - 1`` in place: the log-compressed samples' ratio from the
    exponents the measurement kernels write.  numpy's float64 exp is vectorised on CPUs with
    AVX-512 (~0.6 ns a sample against ~7 ns for the scalar exp in a numba loop; the two then
    differ by at most one unit in the last place on ~5 % of the samples); without AVX-512 it calls
    the same scalar exp as numba (~7 ns, the same bits), ~0.3 ms of an ARIS frame."""
    a, b = max(r0, 0), min(r1, out.shape[0])
    if b > a:
        rows = out[a:b]
        np.exp(rows, out=rows)
        rows -= 1.0


def _continuation(echoes: Any, first: NDArray[np.int64], levels: NDArray[Any], llr_lut: NDArray[np.float64],
                  cand: NDArray[np.bool_], config: RangeConfig) -> tuple[NDArray[np.bool_], NDArray[np.int64],
                                                                        int, int] | None:
    """A surface's faint stretch that the component rule left without candidates: pixels along
    its extrapolation where their likelihood ratio says structure, for the tracker to judge
    (:func:`sonarmap.ranges.tracking.continuation_mask`) - only where it could become the return,
    on a beam without one or whose return lies behind it (None: no such pixel); with the beams
    holding them and their first and one-past-last row."""
    import sonarmap.ranges._kernels as _rk

    code, lut, sel = _continuation_inputs(echoes, first, levels, llr_lut)
    if sel is None:
        return None  # no return to continue
    # _continuation_pixels' kernels and continuation_extra in one call
    hit, extra, cols, r0, r1 = _rk.continuation_pixels(
        np.ascontiguousarray(sel), echoes.edge_bin, echoes.start_bin, echoes.stop_bin, float(config.track.touch_bins),
        code, lut, CONTINUE_MIN_RUN, CONTINUE_MAX_BEAMS, CONTINUE_WINDOW_BINS, float(config.continue_evidence),
        CONTINUE_MAX_MISSES, np.ascontiguousarray(cand))
    return (extra, cols, int(r0), int(r1)) if hit else None


_WORK = threading.local()


def _work_image(shape: tuple[int, int]) -> tuple[NDArray[np.float64], list[int]]:
    """This thread's float64 work image of ``shape`` and ``[lo, hi)``, the rows that may be non-zero
    (a fresh image on the thread's first call of a shape: no page faults per ping; nothing returned
    by :func:`surface_ranges` lives in it)."""
    cached = getattr(_WORK, "image", None)
    if cached is None or cached[0].shape != shape:
        cached = (np.zeros(shape), [0, 0])
        _WORK.image = cached
    return cached


def _measurement_rows(ping: Ping, background: Any, config: RangeConfig, r0: int, r1: int,
                      done: list[Any]) -> NDArray[np.float64]:
    """``measurement_image(ping, background, config, rows=(r0, r1))``, or the image of an earlier
    call when its rows cover these.

    ``done`` is ``[]`` or ``[image, (r0, r1), inputs]`` of the earlier call on the same ping
    (updated in place): a new image reuses the inputs and that image's memory (this thread's
    work image, :func:`_work_image`), computing only the rows it lacks and zeroing those outside
    the new rows (each pixel's value does not depend on the others: the same image, bit for bit).
    The beam factor is interpolated from its block grid on the measured rows only
    (:func:`_kernels.excess_ratio_grid`).
    """
    from sonarmap.preprocess.normalise import grid_weights
    from sonarmap.ranges._kernels import excess_ratio_grid

    n, m = ping.image.shape
    a, b = max(r0, 0), min(r1, n)
    if not done:
        raw = np.ascontiguousarray(ping.image)
        if raw.dtype.kind not in "fiu":
            raw = np.ascontiguousarray(raw, dtype=np.float32)
        level = np.ascontiguousarray(background.level_by_bin, dtype=np.float32)
        grid = (np.ones((0, 1), np.float32) if background.beam_factor is None
                else np.ascontiguousarray(background.beam_factor, dtype=np.float32))
        d = _log_range_db(ping, config)
        out, dirty = _work_image((n, m))
        weights = (*grid_weights(m, grid.shape[1]), *grid_weights(n, max(grid.shape[0], 1)))
        done[:] = [out, (0, 0), (raw, level, grid, *weights, float(d) if d is not None else 0.0), dirty]
    out, (a0, b0), inputs, dirty = done
    if done[1] != (0, 0) and a >= a0 and b <= b0:
        return out
    for lo, hi in ((dirty[0], min(dirty[1], a)), (max(dirty[0], b), dirty[1])):  # rows no longer measured
        if hi > lo:
            out[lo:hi] = 0.0
    dirty[:] = [min(dirty[0], a), max(dirty[1], b)]  # (should a kernel fail half-way)
    for lo, hi in ((a, min(b, a0)), (max(a, b0), b)):  # rows not measured yet (on this ping)
        if hi > lo:
            excess_ratio_grid(*inputs, lo, hi, out)
            if inputs[-1] > 0:  # log-compressed samples: the kernel wrote the exponents
                expm1_rows(out, lo, hi)
    done[1] = (a, b)
    dirty[:] = [a, b]
    return out


def _rows_unseen(first: tuple[int, int], second: tuple[int, int], rows: tuple[int, int], pb: int) -> bool:
    """Whether the measurement image rows ``second`` (a superset of ``first``) differ from
    ``first`` only on rows that no echo of candidates on ``rows`` (first, one-past-last) reads:
    :func:`sonarmap.ranges.echoes.find_echoes` reads from ``back + 1 = pb + 3`` bins in front of
    an echo to one bin past it, smoothed over ``pb`` bins when ``pb >= 2``."""
    lo = rows[0] - pb - 3 - (pb // 2 if pb >= 2 else 0)
    hi = rows[1] + pb + 1
    return (second[0] >= first[0] or lo >= first[0]) and (second[1] <= first[1] or hi <= first[1])


def _with_pooled_bands(mask: NDArray[np.bool_], image: NDArray[np.float32], candidates: CandidateConfig,
                       bg_mean: float | None, pool: bool
                       ) -> tuple[NDArray[np.bool_], NDArray[np.bool_] | None, int, int]:
    """``(candidates, band, r0, r1)``: ``mask`` plus the pooled bands (:func:`pooled_band_mask`;
    ``band`` None when none), and the rows ``r0 .. r1 - 1`` they occupy.  Band pooling recovers
    thin single-look surface bands the per-pixel route leaves in pieces; it is only needed (and
    only run, with ``pool``) where some beam has no candidate at all."""
    import sonarmap.ranges._kernels as _rk

    cand = np.ascontiguousarray(mask, dtype=bool)
    r0, r1, n_cols = _rk.mask_extent(cand)
    if not (pool and candidates.pool_factor > 0 and bg_mean is not None and bg_mean > 0 and n_cols < cand.shape[1]):
        return cand, None, r0, r1
    band = pooled_band_mask(image, candidates.pool_factor * bg_mean, pool_beams=candidates.pool_beams,
                            pool_bins=candidates.pool_bins, min_beams=candidates.pool_min_beams,
                            link_beams=candidates.pool_link_beams, link_bins=candidates.pool_link_bins)
    if band is None:
        return cand, None, r0, r1
    cand, r0, r1 = _rk.union_extent(cand, np.ascontiguousarray(band))
    return cand, band, r0, r1


def surface_ranges(ping: Ping, image: NDArray[np.float32], levels: NDArray[Any], mask: NDArray[np.bool_],
                   fit: Any, config: RangeConfig = RangeConfig(), candidates: CandidateConfig = CandidateConfig(), *,
                   normalised: bool = False, bg_mean: float | None = None, background: Any = None,
                   pool_bands: bool = True,
                   edge_image: Callable[[], tuple[NDArray[np.float32], float] | None] | None = None,
                   image_max: float | None = None) -> tuple[BeamRanges, NDArray[np.int64]]:
    """Echoes of the candidate structure (``mask`` plus pooled bands), tracked across beams; also
    the number of bins each return's echo spans (0 where no return).

    ``edge_image``: returns ``(image, background mean)`` the echoes of a ping that is not
    normalised are measured on instead of ``image`` and ``bg_mean``, or None for ``image``
    itself (``RangeConfig.edge_image``, :func:`sonarmap.pipeline.measurement_image`); called only
    when there is a candidate to measure.  ``image`` still makes the pooled-band candidates.
    ``image_max``: ``ping.image``'s maximum when the caller has it (:func:`full_scale_level`
    then makes no pass for it)."""
    geom = ping.geometry
    cand, band, r0, r1 = _with_pooled_bands(mask, image, candidates, bg_mean,
                                            pool_bands and not normalised)
    if r1 <= r0:
        return (no_returns(geom, time_ns=ping.time_ns, source=ping.source, mode=config.range_mode),
                np.zeros(geom.n_beams, dtype=np.int64))
    llr_lut = level_llr(fit) if fit is not None and len(fit.class_names) >= 2 else None
    lut = np.maximum(llr_lut, 0.0) if llr_lut is not None else np.ones(int(levels.max()) + 1)
    fraction = config.edge_fraction if config.edge_fraction > 0 else 0.5
    pb = pulse_bins(ping, config)
    measured = normalised and background is not None and getattr(background, "level_by_bin", None) is not None

    done: list[Any] = []  # the measurement image, its rows and its inputs, once computed
    # the image the echoes are measured on unless normalised, and its smoothing over the pulse
    # (find_echoes' checks and conversions, made once: it may measure twice)
    on, on_bg = (edge_image() if edge_image is not None and not normalised else None) or (image, bg_mean)
    plain = np.ascontiguousarray(on, dtype=np.float64) if pb < 2 and not measured else on
    smoothed = None if measured else smooth_along_range(plain, pb)
    geom.check_image(cand, "mask")
    code, lut = _evidence_table(cand, None, levels, lut)
    boost = _boost_pixels(band, cand.shape)
    walk = (1.0, max(2, pb), float(fraction), 0.5, pb + 2, config.edge_scan == "forward")
    # the ping's full-scale level, computed once and only when an echo is measured
    full_scale = functools.cache(functools.partial(full_scale_level, ping.image, top=image_max))

    def measure(cand: NDArray[np.bool_], rows: tuple[int, int],
                before: tuple[Any, NDArray[np.int64], tuple[int, int]] | None = None
                ) -> tuple[Any, float, Any, Any, Any]:
        meas, bg = plain, on_bg or 0.0
        if measured:
            # echo intensity above the background, in background units (its mean is 1)
            valid = done[1] if done else (0, 0)
            meas, bg = _measurement_rows(ping, background, config, rows[0] - pb - 4, rows[1] + pb + 4, done), 1.0
            if before is not None and not _rows_unseen(valid, done[1], before[2], pb):
                before = None  # rows the first pass's echoes looked at have changed
        # find_echoes (its default peak_rel, max_gap, back and looks); a pooled band pixel passed
        # a >= pool_factor x background test over the whole box: one nat at least (boost_min),
        # whatever its own (single-look, speckled) value says
        img = smooth_along_range(meas, pb) if smoothed is None else smoothed
        echoes = _echoes_of(cand, img, code, lut, boost, geom, walk, (pb, 1.0, float(bg), float(config.sigma_scale)),
                            None if before is None else before[1], rows)
        if echoes.beamwidth_beams is not None and echoes.size:
            rows = clip_rows(echoes, ping.image, full_scale())
            echoes = echoes.replaced(clipped=rows >= 0, clip_row=rows)
        if before is not None:
            # only the beams with new candidates were measured again (each beam's echoes depend
            # on its own column only)
            echoes = spliced_echoes(before[0], echoes, before[1])
        # the front pass inside the tracking kernel (kept for the last measurement only: the
        # continuation walks on from the passes' own surfaces)
        if config.track.front_pass:
            return meas, bg, echoes, *tracks_and_front(echoes, config.track, pb)
        tracks = track_surfaces(echoes, config.track, pb)
        return meas, bg, echoes, tracks, tracks

    meas, bg, echoes, tracks, fronted = measure(cand, (r0, r1))
    if config.continue_evidence > 0 and llr_lut is not None:
        more = _continuation(echoes, tracks.first, levels, llr_lut, cand, config)
        if more is not None:
            extra, cols, e0, e1 = more
            cand = cand | extra
            meas, bg, echoes, tracks, fronted = measure(cand, (min(r0, e0), max(r1, e1)), (echoes, cols, (r0, r1)))
    return _refined_returns(echoes, fronted, meas, image, ping, config, pb, fraction, full_scale, measured)


def _refined_returns(echoes: Any, tracks: Any, meas: Any, image: NDArray[np.float32], ping: Ping, config: RangeConfig,
                     pb: int, fraction: float, full_scale: Callable[[], float], test: bool = False
                     ) -> tuple[BeamRanges, NDArray[np.int64]]:
    """:func:`surface_ranges` after the tracking: the first returns' edges pooled, measured against
    the template and smoothed along the surface on the measured image ``meas``, clipped echoes'
    sigmas widened (``full_scale()``: the ping's :func:`full_scale_level`), with ``test`` (a
    normalised ping) the surfaces not told apart from their water column dropped, and the returns
    of ``tracks`` (intensities from the classified ``image``)."""
    geom = ping.geometry
    sel = tracks.first
    if config.edge_pool_beams > 0 and config.range_mode == "first":
        echoes = _pooled_returns(echoes, sel, meas, ping, config, pb, fraction, full_scale)
    trust = None  # (per echo, the smoothing's factor on its sigma: None, 1 for every echo)
    if config.edge_template_beams > 0 and config.range_mode == "first" and echoes.size:
        before = echoes
        echoes = _template_pass(echoes, sel, meas, geom, config, fraction, pb)
        if config.sigma_template_smooth_scale != 1.0 and echoes is not before:
            moved = (echoes.edge_bin != before.edge_bin) | (echoes.sigma_m != before.sigma_m)
            trust = np.where(moved, config.sigma_template_smooth_scale, 1.0)
        if config.edge_template_anchor_trust and echoes.smooth_trust is not None:
            trust = echoes.smooth_trust if trust is None else trust * echoes.smooth_trust
    if config.edge_smooth_beams > 0 and config.range_mode == "first" and echoes.size:
        echoes = smooth_surface_edges(echoes, sel, geom,
                                      half_beams=window_in_beamwidths(config.edge_smooth_beams, echoes.beamwidth_beams),
                                      min_beams=config.edge_smooth_min_beams, touch_bins=config.track.touch_bins,
                                      trust=trust)
    if echoes.size:  # (without a return, clipped_echo_sigma's kernel finds nothing: the echoes unchanged)
        echoes = clipped_echo_sigma(echoes, sel, ping.image, geom, level=full_scale())
        if config.range_mode == "first":
            echoes = clipped_gaussian_edges(echoes, sel, ping.image, geom, level=full_scale(),
                                            max_over_db=config.track.point_over_range_db)
    if test and config.surface_min_z > 0 and echoes.size:
        tracks = _significant(echoes, tracks, ping, config)
    return track_returns(echoes, tracks, geom, image, mode=config.range_mode,  # type: ignore[arg-type]
                         time_ns=ping.time_ns, source=ping.source)


def _significant(echoes: Any, tracks: Tracks, ping: Ping, config: RangeConfig) -> Tracks:
    """``tracks`` without the first returns whose surface's significance
    (:func:`sonarmap.ranges.significance.surface_significance`) is below ``config.surface_min_z``
    (those beams report no first return; the surfaces behind stay further surfaces)."""
    z, _ = surface_significance(echoes, tracks.first, ping.image, touch_bins=config.track.touch_bins,
                                jump_bins=config.track.jump_bins)
    drop = z < config.surface_min_z  # (NaN: no return or not tested, kept)
    if not drop.any():
        return tracks
    e = np.array(tracks.echo)
    e[0, drop] = -1
    return Tracks(echo=e)


def _template_pass(echoes: Any, sel: NDArray[np.int64], meas: Any, geom: Any, config: RangeConfig, fraction: float,
                   pb: int) -> Any:
    """Long surfaces' leading edges measured against the surface's echo template
    (:func:`sonarmap.ranges.template.template_edges`; a fitted clipped echo keeps its fit)."""
    return template_edges(echoes, sel, meas, geom, half_template=config.edge_template_beams,
                          min_beams=config.edge_template_min_beams, fraction=fraction,
                          touch_bins=config.track.touch_bins, pulse_bins=pb,
                          sigma_scale=config.sigma_template_scale,
                          anchor_beams=config.edge_template_anchor_beams, skip=echoes.clip_fitted,
                          shared_beams=2 * config.edge_pool_beams + 1,
                          anchor_trust=config.edge_template_anchor_trust)


def _pooled_returns(echoes: Any, sel: NDArray[np.int64], meas: NDArray[Any], ping: Ping, config: RangeConfig,
                    pb: int, fraction: float, full_scale: Callable[[], float]) -> Any:
    """:func:`pooled_edges` of the returns ``sel`` on the measured image ``meas``, with the validated
    ``config`` and the default window; the pooled profile is smoothed over at least 3 bins along
    range in all (a single-look profile's maximum is otherwise a speckle spike), and a clipped
    return (at ``full_scale()``, the ping's :func:`full_scale_level`) is measured by a Gaussian
    fitted to its flanks."""
    clipped = echoes.clipped if echoes.clipped is not None else clipped_echoes(echoes, ping.image, full_scale())
    clip, level = None, None
    if clipped[sel[sel >= 0]].any():
        # full_scale_mask's samples: the kernel tests those of the raw image it reaches against the
        # level (in float64, as the mask compares them), no mask of the whole image is formed
        raw = np.asarray(ping.image)
        if raw.dtype in (np.float32, np.float64) or raw.dtype.kind in "iu":
            clip, level = np.ascontiguousarray(raw), full_scale()
        else:
            clip = full_scale_mask(raw, full_scale())
    window = (config.edge_pool_beams, POOL_FRONT_BINS, POOL_MAX_BINS, 3 if pb < 3 else 1, POOL_N_ITER,
              POOL_FIT_FRONT_BINS)
    return _pooled(echoes, sel, meas, ping.geometry, pb, window, (fraction, config.track.touch_bins),
                   (config.sigma_pool_scale, config.sigma_fit_scale), clip,
                   forward=config.edge_pool_scan == "forward", clip_level=level,
                   flank_bins=config.edge_pool_flank_bins, lead_bins=config.edge_pool_lead_bins,
                   align_beams=config.edge_pool_align_beams, peak_bins=config.edge_pool_peak_bins,
                   jitter_floor=config.sigma_pool_floor, min_slope=config.edge_pool_follow_slope)


#: A raw sample at or above this is at the receiver's full scale (8-bit images: level 255).
CLIP_LEVEL = 254.5 / 255.0
#: The smallest float32 whose float64 value reaches :data:`CLIP_LEVEL` (float32 rounds the level
#: down, 0.998039186 < 0.998039216).
_CLIP_LEVEL_F32 = (np.float32(CLIP_LEVEL) if float(np.float32(CLIP_LEVEL)) >= CLIP_LEVEL
                   else np.nextafter(np.float32(CLIP_LEVEL), np.float32(np.inf)))


#: A ping's maximum is its receiver's full scale when at least this many samples sit on it ...
PILEUP_MIN_SAMPLES = 10
#: ... and at least this many times the mean count per 1/255 step over the
#: :data:`PILEUP_STEPS` steps below it.
PILEUP_FACTOR = 10.0
#: The steps of 1/255 below a ping's maximum that :func:`full_scale_level` compares it with.
PILEUP_STEPS = 8


def full_scale_level(raw: ArrayLike, *, top: float | None = None) -> float:
    """The level at or above which a sample of ``raw`` is at its receiver's full scale.

    Nominally :data:`CLIP_LEVEL` (the 8-bit code 255).  Some receivers saturate below the top
    code: the real Oculus M-series pings (``oculus/three_pings_8bit.raw``) top out at code 254,
    with 1364-1514 samples per ping there (the seabed), 32-63 on each code below and none at 255.
    A saturated receiver piles its samples up at its top value, while the histogram of an
    unsaturated image thins out towards its maximum; so a ping whose maximum ``m`` lies below
    :data:`CLIP_LEVEL` is clipped at ``m`` when at least :data:`PILEUP_MIN_SAMPLES` samples
    equal ``m`` and they are at least :data:`PILEUP_FACTOR` times the mean count per 1/255 step
    over the :data:`PILEUP_STEPS` steps below ``m`` (the real DIDSON and ARIS pings: one to
    three samples on their maximum).  The level is compared in float64 with the samples
    (``m`` itself: float32 samples convert exactly).  ``top``: ``raw``'s maximum when the caller
    has it (no pass over ``raw`` for it).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> img = (np.floor(rng.rayleigh(0.1, (400, 64)) * 255) / 255).astype(np.float32)
    >>> full_scale_level(img) == CLIP_LEVEL
    True
    >>> img[200:210] = np.float32(254 / 255)  # a saturated band at code 254
    >>> full_scale_level(img) == float(np.float32(254 / 255))
    True
    """
    import sonarmap.ranges._kernels as _rk

    a = np.ascontiguousarray(raw)
    if a.size == 0 or a.dtype.kind not in "fiu":
        return CLIP_LEVEL
    top = float(a.max()) if top is None else float(top)
    if not (0.0 < top < CLIP_LEVEL):  # (NaN too)
        return CLIP_LEVEL
    n_top, n_below = _rk.top_counts(a, top, PILEUP_STEPS / 255.0)
    if n_top >= PILEUP_MIN_SAMPLES and n_top >= PILEUP_FACTOR * n_below / PILEUP_STEPS:
        return top
    return CLIP_LEVEL


def full_scale_mask(raw: ArrayLike, level: float = CLIP_LEVEL) -> NDArray[np.bool_]:
    """The samples of ``raw`` at or above ``level`` (default :data:`CLIP_LEVEL`; a ping's own:
    :func:`full_scale_level`), compared in float64 as the range kernels compare them (numpy would
    compare a float32 image with the level rounded to float32, 0.998039186 < 0.998039216: a
    sample at exactly that value would count as clipped here and not in the kernels)."""
    a = np.asarray(raw)
    if a.dtype == np.float32 and level == CLIP_LEVEL:
        return a >= _CLIP_LEVEL_F32  # type: ignore[no-any-return]
    return np.asarray(a, dtype=np.float64) >= level  # type: ignore[no-any-return]


def clipped_gaussian_edges(echoes: Any, sel: NDArray[np.int64], raw: NDArray[Any], geom: Any, *,
                           level: float = CLIP_LEVEL, max_over_db: float = 30.0) -> Any:
    """Move the leading edge of a clipped first peak whose rise is resolved to the half-peak
    crossing of a Gaussian echo through it.

    A clipped echo not measured by the Gaussian fit of :func:`pooled_edges` (too few unclipped
    samples on a flank: the simulator's propeller blades) has its edge ``x`` at half the clip
    level, early on the true echo's rise.  With ``c`` its first full-scale row and ``L`` the
    length of that clipped run, a Gaussian echo ``P exp(-(r - x0)^2 / 2 w^2)`` peaking in the
    middle of the run (``x0 = c + (L - 1) / 2``) crosses full scale at ``c - 0.5`` (between the
    last unclipped sample and the first clipped one) and half of it at ``x``, which fixes ``w``
    and ``P``; its half-peak crossing is ``x0 - sqrt((x0 - x)^2 - (x0 - c + 0.5)^2)``.  Nothing
    moves where that needs a peak more than ``max_over_db`` over full scale (a steep rise into a
    long clipped run: not one Gaussian echo), where the rise from half the clip level to full
    scale spans less than a bin (``c - x < 1``: not resolved by the samples, it says nothing of
    the peak), or where the clipped run is not the echo's first peak (``c`` more than a bin
    behind ``Echoes.peak_bin``).  The move's length over ``sqrt 12`` is added to the sigma, in
    quadrature.  ``level``: the ping's :func:`full_scale_level`; the pipeline passes
    ``TrackConfig.point_over_range_db`` (30 dB) as the bound.  On the simulator's propellers
    (docs/ranges.md, "Clipped echoes") the ARIS returns move from a median 2.5-2.7 bins in
    front of the surface to 1.3; the real recordings have no such echo (none moves).
    """
    import sonarmap.ranges._kernels as _rk

    if echoes.clip_row is None or not echoes.size:
        return echoes
    fitted = echoes.clip_fitted
    n_moved, eb, er, sg = _rk.clipped_gaussian_edges(
        np.ascontiguousarray(raw), np.ascontiguousarray(sel, dtype=np.int64), echoes.edge_bin, echoes.edge_range_m,
        echoes.sigma_m, np.ascontiguousarray(echoes.clip_row, dtype=np.int64), echoes.peak_bin, float(level),
        _NO_FITTED if fitted is None else np.ascontiguousarray(fitted, dtype=np.bool_), fitted is not None,
        10.0 ** (float(max_over_db) / 10.0), np.ascontiguousarray(geom.range_m, dtype=np.float64),
        abs(geom.range_resolution_m))
    if not n_moved:
        return echoes
    return echoes.replaced(edge_bin=eb, edge_range_m=er, sigma_m=sg)


def clipped_echoes(echoes: Any, raw: NDArray[Any], level: float = CLIP_LEVEL) -> NDArray[np.bool_]:
    """Per echo, whether a raw sample of its structure bins reaches the receiver's full scale
    (``level``: :data:`CLIP_LEVEL`, or the ping's :func:`full_scale_level`)."""
    return clip_rows(echoes, raw, level) >= 0


def clip_rows(echoes: Any, raw: NDArray[Any], level: float = CLIP_LEVEL) -> NDArray[np.int64]:
    """Per echo, the first of its structure bins whose raw sample reaches the receiver's full
    scale (``level``: :data:`CLIP_LEVEL`, or the ping's :func:`full_scale_level`); -1 where none
    does."""
    import sonarmap.ranges._kernels as _rk

    # (the kernel clips the bins to the image's rows)
    return _rk.first_clipped_rows(  # type: ignore[no-any-return]
        np.ascontiguousarray(raw), np.ascontiguousarray(echoes.beam),
        np.ascontiguousarray(echoes.start_bin, dtype=np.int64), np.ascontiguousarray(echoes.stop_bin, dtype=np.int64),
        float(level))


_NO_FITTED = np.zeros(0, dtype=np.bool_)


def clipped_echo_sigma(echoes: Any, sel: NDArray[np.int64], raw: NDArray[Any], geom: Any, *,
                       level: float = CLIP_LEVEL) -> Any:
    """Widen the sigma of returns whose echo's first peak reaches the receiver's full scale
    (``level``: :data:`CLIP_LEVEL`, or the ping's :func:`full_scale_level`).

    A clipped first peak is only a lower bound: the half-peak crossing of the true echo lies at
    or behind the crossing measured (half the clipped level) - before the echo's first clipped
    sample when it peaks below twice full scale, inside the clipped run above that.  The spread
    of the interval up to the first clipped sample, ``length / sqrt 12``, is added in quadrature
    to the return's sigma; the range itself is not moved.  Only a full-scale sample between the
    edge and the echo's first peak (``Echoes.peak_bin``) counts: one behind the first peak (a
    speckle spike deeper in the echo) did not set the level the edge is measured at.  On the
    simulator (seeds 0-2, the default pipeline) the returns widened lie within +-sigma on 0.53 of
    the Oculus preset's beams (median sigma 0.85 bins, median error 0.83); widening by every
    full-scale sample of the echo instead covered 0.92 with a median sigma of 7.2 bins for a median
    error of 1.5 (measured with an 8-beam smoothing window).  Returns whose edge is that of a
    Gaussian fitted to the clipped echo's flanks (``Echoes.clip_fitted``, :func:`pooled_edges`)
    keep their sigma: the fit's own standard error is in it.
    """
    import sonarmap.ranges._kernels as _rk

    # (not those whose edge a Gaussian fitted to the clipped peak gave: clip_fitted)
    fitted = echoes.clip_fitted
    e, spread = _rk.clipped_spread(
        np.ascontiguousarray(raw), np.ascontiguousarray(sel, dtype=np.int64), echoes.edge_bin, echoes.peak_bin,
        float(level), abs(geom.range_resolution_m),
        _NO_FITTED if fitted is None else np.ascontiguousarray(fitted, dtype=np.bool_), fitted is not None)
    if not e.size:
        return echoes
    sigma = echoes.sigma_m.copy()
    sigma[e] = np.hypot(sigma[e], spread / math.sqrt(12.0))
    return echoes.replaced(sigma_m=sigma)
