"""Leading edges re-measured against the surface's own echo template.

A surface seen across many beams echoes with nearly the same shape on neighbouring beams: the
same pulse, the same incidence, the same band depth.  :func:`template_edges` uses that.  For
each beam of a long tracked surface it

1. fits a quadratic to the current leading edges of the beams within ``half_template`` of it
   (the surface's local course, which follows a slope and a curve);
2. averages those beams' columns aligned on that course: the *template*, a multi-look of
   ``2 half_template + 1`` beams whose half-peak crossing (the range convention of
   :mod:`sonarmap.ranges.echoes`, on the template smoothed over 3 bins) is the echo's leading edge
   relative to the course;
3. slides the template along range over the beams within ``half_window`` of the beam (each at
   the course's local slope) to the position that best explains their samples - the maximum
   likelihood of single-look (exponential) intensities whose mean is the template, by Fisher
   scoring - on the rows from ``front_bins`` in front of the course to just past the template's
   peak.  The position's variance is the sandwich estimate (the scatter of the beams' scores over
   the squared Fisher information), which holds whatever the intensities' distribution: an echo
   averaged over ``L`` looks (the ARIS and Oculus-like presets render 6 and 10) is placed about
   ``L`` times more precisely than the single-look likelihood says.

The template's own half-peak crossing is noisy (even aligned on the true surface, an 11-beam
template's crossing lies within a bin of it on about 60 % of the simulated DIDSON hull's beams),
while the position it is slid to is precise.  So the beam's edge is that position *anchored* on
the edges the stage started from (:func:`sonarmap.ranges.echoes.pooled_edges`): the template's
relative positions keep their precision, and the median over ``anchor_beams`` beams either side
of (edge before - template edge) sets the range convention's level.  Two rounds: a template
aligned on noisy edges is blurred.  A faint echo (a template peak under ``min_contrast`` times its
level in front of the surface) keeps its edge: through a faint grazing seafloor's template (3-10x
on the simulator's ARIS presets) the crossing lay 3 bins early.

Every sample of the rise and of the peak informs the relative position, not only the two around
one crossing of a speckled profile (``docs/ranges.md``, "Template edges").
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ranges.echoes import Echoes, _edge_spreads


def template_edges(
    echoes: Echoes,
    first: ArrayLike,
    image: ArrayLike,
    geometry: SonarGeometry,
    *,
    half_template: int = 5,
    half_window: int = 1,
    front_bins: int = 8,
    min_beams: int = 30,
    max_bins: int = 60,
    max_shift_bins: float = 4.0,
    n_iter: int = 2,
    min_contrast: float = 12.0,
    fraction: float = 0.5,
    touch_bins: float = 1.0,
    pulse_bins: int = 1,
    sigma_scale: float = 1.0,
    anchor_beams: int = 10,
    skip: ArrayLike | None = None,
    shared_beams: int = 1,
    anchor_trust: bool = False,
) -> Echoes:
    """Leading edges of the returns on long surfaces measured against the surface's echo template.

    See the module notes.  Only surfaces (:func:`sonarmap.ranges.echoes.surface_runs`) of at least ``min_beams`` beams
    are measured (the echo must keep its shape over the template's beams; propeller blades and fish do not).  A beam
    keeps its edge where the template has no crossing, its samples say nothing of the position, or ``skip`` says so.

    Parameters
    ----------
    echoes : Echoes
        The ping's echoes with their current leading edges (e.g. after
        :func:`sonarmap.ranges.echoes.pooled_edges`).
    first : array_like of int, shape (n_beams,)
        Per beam the echo index of its return (-1 none): ``Tracks.first``.
    image, geometry : ndarray (n_bins, n_beams), SonarGeometry
        The image the echoes were measured on (linear intensity) and its geometry.
    half_template, half_window, front_bins : int
        Beams either side averaged into the template; beams either side sharing the beam's
        template position; rows in front of the course that the position is fitted on.
    min_beams, max_bins : int
        Shortest surface measured; longest echo depth (bins) the template's peak is searched over.
    max_shift_bins, n_iter : float, int
        Largest move of the template position from the course; rounds (see the notes).
    min_contrast : float
        Least ratio of the template's peak to its mean level in front of the surface (offsets
        beyond ``front_bins``): a weaker echo keeps its edge (see the notes).
    fraction, touch_bins, pulse_bins
        Convention's fraction of the first peak; :func:`surface_runs`' touch; pulse length (bins).
    sigma_scale, anchor_beams : float, int
        ``sigma^2 = bin^2 / 12 + (scale bin se)^2 + pulse^2 / 12``, ``se^2`` the variances of
        position, crossing and anchor (bins^2); the anchor's half-width (0: the template's own
        crossing is the edge).  ``PipelineConfig.ranges.sigma_template_scale`` and ``.edge_template_anchor_beams``.
    skip, anchor_trust : array_like of bool, shape (n_echoes,), optional; bool
        Echoes whose edge is kept (e.g. the fitted clipped echoes of ``pooled_edges``); whether to
        set ``Echoes.smooth_trust`` too (``RangeConfig.edge_template_anchor_trust``).
    shared_beams : int
        How many neighbouring beams' data each incoming edge was measured on (1: its own beam; a
        pooled edge: its window, ``2 edge_pool_beams + 1``): neighbouring anchor offsets share their
        errors, and the anchor median's variance counts ``c`` of them as ``max(c / shared_beams, 1)``.

    Returns
    -------
    Echoes
        ``echoes``, the measured returns' ``edge_bin``, ``edge_range_m``, ``sigma_m`` replaced.
    """
    sel = np.ascontiguousarray(np.asarray(first, dtype=np.int64))
    _check_template_options(sel, echoes, (half_template, half_window, n_iter, front_bins, min_beams, max_bins,
                                          anchor_beams, shared_beams), max_shift_bins, fraction, sigma_scale,
                            min_contrast)
    img = np.ascontiguousarray(image, dtype=np.float64)
    geometry.check_image(img, "image")
    if echoes.n_beams < min_beams:
        return echoes  # no surface can span min_beams beams
    options = (int(half_template), int(half_window), int(front_bins), int(min_beams), int(max_bins),
               float(max_shift_bins), 6, float(fraction), 3, 24, int(n_iter), float(min_contrast), int(anchor_beams),
               float(shared_beams))
    return _moved_by_template(echoes, sel, img, geometry, (touch_bins, pulse_bins, sigma_scale, bool(anchor_trust)),
                              _skipped_beams(sel, skip), options)


def _moved_by_template(echoes: Echoes, sel: NDArray[np.int64], img: NDArray[np.float64], geometry: SonarGeometry,
                       scalars: tuple[float, int, float, bool], skip_beam: NDArray[np.bool_],
                       options: tuple) -> Echoes:  # type: ignore[type-arg]
    """:func:`template_edges` of checked arguments (``scalars``: touch_bins, pulse_bins,
    sigma_scale, anchor_trust; ``options``: the template kernel's, from half_template on): the runs, the
    template's measurement and the measured returns' fields in one kernel call."""
    import sonarmap.ranges._template_kernels as _template_kernels

    if echoes.size == 0:
        return echoes  # (without echoes no beam is in a run)
    touch_bins, pulse_bins, sigma_scale, anchor_trust = scalars
    n_moved, eb, er, sg, trust = _template_kernels.template_moved_edges(
        sel, echoes.edge_bin, echoes.start_bin, echoes.stop_bin, float(touch_bins), img, skip_beam, *options,
        echoes.edge_range_m, echoes.sigma_m, np.ascontiguousarray(geometry.range_m, dtype=np.float64),
        *_edge_spreads(geometry, pulse_bins), float(sigma_scale), anchor_trust)
    if not n_moved:
        return echoes
    if anchor_trust:
        return echoes.replaced(edge_bin=eb, edge_range_m=er, sigma_m=sg, smooth_trust=trust)
    return echoes.replaced(edge_bin=eb, edge_range_m=er, sigma_m=sg)


def _skipped_beams(sel: NDArray[np.int64], skip: ArrayLike | None) -> NDArray[np.bool_]:
    """Per beam, whether its return (``sel``, -1 none) is one of the echoes ``skip`` marks."""
    skip_beam = np.zeros(sel.size, dtype=np.bool_)
    if skip is not None:
        marks = np.asarray(skip, dtype=bool)
        skip_beam[sel >= 0] = marks[sel[sel >= 0]]
    return skip_beam


def _check_template_options(sel: NDArray[np.int64], echoes: Echoes, ints: tuple[int, ...], max_shift_bins: float,
                            fraction: float, sigma_scale: float, min_contrast: float) -> None:
    """The options of :func:`template_edges` are in range and ``first`` has a value per beam
    (``ints``: half_template, half_window, n_iter, front_bins, min_beams, max_bins, anchor_beams,
    shared_beams)."""
    if sel.shape != (echoes.n_beams,):
        raise InputError(f"first: expected one echo index per beam ({echoes.n_beams}), got shape {sel.shape}")
    values = (*ints, max_shift_bins, fraction, sigma_scale, min_contrast)
    try:
        _checked_template_values(*values)  # (checked once per set of values and types: every ping repeats them)
    except TypeError:  # an unhashable value: checked without the cache (its error, if any, is raised there)
        _check_template_values(*values)


def _check_template_values(half_template: int, half_window: int, n_iter: int, front_bins: int, min_beams: int,
                           max_bins: int, anchor_beams: int, shared_beams: int, max_shift_bins: float, fraction: float,
                           sigma_scale: float, min_contrast: float) -> None:
    """The option values of :func:`_check_template_options` are in range (an :class:`InputError` naming one)."""
    for key, v, lo in (("half_template", half_template, 1), ("half_window", half_window, 0), ("n_iter", n_iter, 1),
                       ("front_bins", front_bins, 1), ("min_beams", min_beams, 3), ("max_bins", max_bins, 3),
                       ("anchor_beams", anchor_beams, 0), ("shared_beams", shared_beams, 1)):
        if isinstance(v, bool) or int(v) != v or v < lo:
            raise InputError(f"{key}: must be an integer >= {lo} (got {v!r})")
    for key, v in (("max_shift_bins", max_shift_bins), ("sigma_scale", sigma_scale), ("min_contrast", min_contrast)):
        if not (math.isfinite(float(v)) and float(v) >= 0):
            raise InputError(f"{key}: must be a finite number >= 0 (got {v!r})")
    if not 0 < fraction < 1:
        raise InputError(f"fraction: must lie in (0, 1) (got {fraction})")


#: :func:`_check_template_values` remembered for the values that passed (keyed by value and type:
#: ``typed`` keeps ``True`` apart from ``1``; a failing check raises and is not remembered).
_checked_template_values = functools.lru_cache(maxsize=32, typed=True)(_check_template_values)
