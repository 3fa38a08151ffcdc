"""Surface tracking across beams: which echoes are surfaces, decided by one dynamic programme.

Per beam the candidates are the beam's echoes (:mod:`sonarmap.ranges.echoes`) plus "no
return".  A *surface piece* is a sequence of echoes on increasing beams; its cost is

* ``segment_cost`` once (a surface must earn its existence: fish, speckle and side-lobe leaks do
  not carry enough evidence over enough beams),
* per echo ``beam_cost - evidence`` (evidence = the classifier's log-likelihood ratio summed over
  the echo, nats),
* between consecutive echoes ``g`` beams apart, ``slope_cost x |d| / slope_bins`` where ``d`` is
  the change of the leading edge per beam in bins (a Laplace prior on the surface slope), plus
  ``gap_cost`` per skipped beam (faint beams inside a surface are bridged, up to ``max_gap``);
  echoes more than ``jump_bins`` per beam apart are not neighbours, nor are echoes whose bin
  intervals (leading edge to last structure bin) lie more than ``touch_bins`` per beam apart: a
  surface is contiguous across beams (a sloped surface's echoes are as thick as its slope), a
  school of fish is not.

:func:`track_surfaces` finds the set of pieces of least total cost exactly (Viterbi over the
beams, ``O(n_beams x max_gap x K^2)`` for ``K`` echoes per beam), removes their echoes and repeats
for the surfaces behind (``n_surfaces`` passes).  Per beam the nearest tracked echo is the
return; the others are kept as further surfaces.

Each pass gives a beam to one surface only, so where a long, strong surface behind takes a few
beams, the surface in front loses them and its echoes there are left over: no later pass can
start a piece on them alone (``segment_cost``).  A *bridge* restores them: untracked echoes in
front of every tracked echo of their beam that continue a tracked surface beam by beam (each step
a neighbour under the rules above whose evidence pays for its slope) and, within ``bridge_beams``
beams, reach a tracked echo again on the other side, become the beams' returns (a faint stretch
of the slanted target on the real ARIS frames, where the lines behind it took three beams).

A longer stretch, or one with a beam where the surface in front has no echo at all, cannot be
bridged; and when the passes run out (``n_surfaces``) on stronger surfaces behind, a fainter
surface in front may not be tracked at all.  The *front pass* (:func:`front_surfaces`) gives the
first return its meaning back: one more pass of the same dynamic programme over the echoes that
lie wholly in front of their beam's nearest tracked echo; every piece it keeps pays the same
costs as any surface (``segment_cost``, slopes, gaps, the point-target rule), and its echoes become
the beams' returns.  On the real ARIS frames the target's faint end (beams 27-39), which a line
4.5 m behind it won in the first pass, is reported again, whatever local optimum the ping's fit
stopped at.

A surface in front that *ends* on a few beams another surface took is neither: it does not come
back (no bridge) and, over a few beams, cannot pay ``segment_cost`` in the front pass.  The *end
extension* (``extend_beams``, after the front pass; :func:`sonarmap.ranges._kernels.extend_ends`)
continues it: untracked echoes in front of every tracked echo of their beam, chained beam by beam
(each step a neighbour whose evidence pays for its slope, as in a bridge) from a tracked echo
where its surface ends - no tracked echo on the chain's first beam lies within ``touch_bins`` of
its interval, whatever their edges - over beams that all hold a tracked echo behind, and ending
within ``extend_beams`` beams (the next beam holds neither a chained echo nor a tracked neighbour),
become the beams' returns.  On the real ARIS frames where the target's band splits in two, the
lower band's start (in front) takes the 2-3 beams the upper band's faint tail had.

*Point targets* (:func:`point_streaks`).  A point scatterer (a fish) lies at one range, and its
echo reaches every beam whose main lobe points near it: in the image it is a *streak*, flat in
range, as wide as the main lobe at the level where the echo falls to the detection threshold.
With a Gaussian two-way lobe of -3 dB width ``W`` (``SonarGeometry.azimuth_beamwidth_rad``) a
point ``P`` times above the threshold spans at most ``W sqrt(log2 P)``: one or two beams of a
weak fish, 5-10 beams of the clipped fish of the Oculus-like preset (0.55 deg lobe, 2.3 beam
spacings).  A school is such streaks at different ranges side by side, chained by the tracker
into pieces.  A surface extends over many more beams with a range that changes smoothly; where
it is flat over a run of beams (at normal incidence) its echo stays level over the run, far wider
than a point of its strength could be, and it goes on into the next run without a jump in range.

The edge of a clipped echo (one that reaches the receiver's full scale) is the crossing of half
the clip level, not of half its peak: the more the echo exceeds full scale, the earlier on its
rise that crossing lies, so across a clipped point's streak the measured edges drift along the
rise (about 2 bins across the Oculus-like preset's clipped fish), more than a pulse of unknown
length (1 bin) allows.  The half-peak edge of its unclipped signal lies between the measured
edge and the echo's first full-scale row (:func:`clip_rise`, the interval the clipped return's
range sigma is widened by; only when the first peak is the clipped one - a later clipped peak,
a second fish in the same echo, leaves the edge where it is).  In the tests below a clipped
echo's edge is that interval, a run's mean edge the mean of its echoes' intervals, and a
distance between edges the gap between intervals (the plain distance when nothing is clipped).

A flat run - consecutive beams of one piece, each leading edge within ``max(1, pulse_bins / 2)``
bins of the mean of the run before it, split where the peak value dips below ``point_dip`` of
the larger peaks on both sides (a main lobe is unimodal: two fish side by side) - is a *point
streak* when

* at least half of its echoes are point echoes: strong in every pixel (mean log-likelihood
  ratio at least ``point_llr`` nats per structure pixel);
* at both ends the surface does not go on: the piece ends, the next beam has no echo, the run
  was split at a dip, the next echo lies a real range jump away (at least twice the flatness
  tolerance from the run's mean edge: a smooth surface's next edge lies just beyond the
  tolerance, which is where its flat run ended), or it is weaker than
  ``point_dip`` x the run's weakest echo (the streak's own tail, whose half-peak edge its weak
  level moves);
* it is no wider than a point: ``(n - 1) <= point_margin x W sqrt(log2(peak / weakest))`` in
  beams, ``peak`` its strongest echo's peak value (times ``point_over_range_db`` when an echo is
  clipped at full scale: a clipped peak is only a lower bound) and ``weakest`` its weakest one's
  (across a point's streak the echo falls from its peak towards the threshold).

A piece whose leading edges all lie within ``pulse_bins`` of each other is tested as one run (a
fish or two at one range).  A piece whose point streaks hold at least ``point_fraction`` of its
evidence is a point target or a school of them: it is not reported, and its echoes are not
tracked again.  The rule needs the beamwidth: it is off for a geometry without one.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from sonarmap._config import check_booleans, check_integers, coerce_reals, config_error
from sonarmap.errors import InputError
from sonarmap.ranges.echoes import Echoes, _first_runs, _levels_in_range

__all__ = ["TrackConfig", "Tracks", "track_surfaces", "tracks_and_front", "front_surfaces", "point_streaks",
           "clip_rise", "continuation_mask"]


@dataclasses.dataclass(frozen=True)
class TrackConfig:
    """Costs of the surface model (nats; see the module notes).

    Parameters
    ----------
    segment_cost, beam_cost, slope_cost, slope_bins, gap_cost, max_gap, jump_bins, touch_bins
        The surface model's costs and neighbour rules (module notes).
    n_surfaces : int
        Tracking passes (surfaces per beam).
    bridge_beams : int
        Longest bridge over beams another surface took (0 = off).
    extend_beams : int
        Longest end extension of a surface over beams another surface took (0 = off).
    front_pass : bool
        Run the front pass (:func:`front_surfaces`) in the pipeline's range stage.
    point_fraction : float
        A tracked piece whose point streaks (:func:`point_streaks`) hold at least this fraction of
        its evidence is a point target or a school of them, not a surface: it is not reported.
        0 = off (as is the rule for a geometry without ``azimuth_beamwidth_rad``).
    point_llr : float
        A point echo holds at least this mean log-likelihood ratio per structure pixel (nats).
    point_over_range_db : float
        How far above the receiver's full scale a clipped point's true peak may lie (dB).
    point_margin : float
        A point streak may be this factor wider than the main lobe allows (speckle, sampling).
    point_dip : float
        A flat run is split where its peak value falls below this fraction of the larger peaks
        on both sides (two points side by side at one range).
    """

    segment_cost: float = 60.0
    beam_cost: float = 1.0
    slope_cost: float = 1.0
    slope_bins: float = 2.0
    gap_cost: float = 4.0
    max_gap: int = 3
    jump_bins: float = 20.0
    touch_bins: float = 1.0
    n_surfaces: int = 3
    bridge_beams: int = 4
    extend_beams: int = 4
    front_pass: bool = True
    point_fraction: float = 0.6
    point_llr: float = 3.5
    point_over_range_db: float = 30.0
    point_margin: float = 1.25
    point_dip: float = 0.6

    def __post_init__(self) -> None:
        where = "track config: "
        coerce_reals(self, ("segment_cost", "beam_cost", "slope_cost", "slope_bins", "gap_cost", "jump_bins",
                            "touch_bins", "point_fraction", "point_llr", "point_over_range_db", "point_margin",
                            "point_dip"), where, minimum=0)
        if self.slope_bins <= 0:
            raise config_error(where, "slope_bins", "must be > 0", self.slope_bins)
        check_integers(self, (("max_gap", 0), ("n_surfaces", 1), ("bridge_beams", 0), ("extend_beams", 0)), where)
        check_booleans(self, ("front_pass",), where)


@dataclasses.dataclass(frozen=True, eq=False)
class Tracks:
    """Tracked surfaces of one ping.

    Attributes
    ----------
    echo : ndarray of int64, shape (n_surfaces, n_beams)
        Per beam, the echo index of each tracked surface, nearest first; -1 where none.
    """

    echo: NDArray[np.int64]

    @property
    def first(self) -> NDArray[np.int64]:
        """Per beam the nearest tracked echo (-1 none)."""
        return self.echo[0]


def track_surfaces(echoes: Echoes, config: TrackConfig = TrackConfig(), pulse_bins: int = 1) -> Tracks:
    """Track surfaces across beams (see the module notes); the result is sorted by range per beam.

    Pieces that are point targets (:func:`point_streaks`, with ``pulse_bins`` the pulse length in
    bins) are not reported; their echoes are not tracked again."""
    return Tracks(echo=_tracked(echoes, config, pulse_bins, False)[0])


def tracks_and_front(echoes: Echoes, config: TrackConfig = TrackConfig(),
                     pulse_bins: int = 1) -> tuple[Tracks, Tracks]:
    """``(track_surfaces(...), front_surfaces(echoes, track_surfaces(...), ...))`` in one kernel
    call (the front pass and the end extensions); the second is the first object itself when
    neither keeps anything."""
    out, front, hit = _tracked(echoes, config, pulse_bins, True)
    tracks = Tracks(echo=out)
    return tracks, (Tracks(echo=front) if hit else tracks)


def _tracked(echoes: Echoes, config: TrackConfig, pulse_bins: int,
             front: bool) -> tuple[NDArray[np.int64], NDArray[np.int64], bool]:
    """:func:`_kernels.track_surfaces` of ``echoes``: the tracks, (with ``front``) the tracks
    after the front pass, and whether that pass kept anything."""
    import sonarmap.ranges._kernels as _kernels

    if not isinstance(echoes, Echoes):
        raise InputError(f"echoes: expected Echoes, got {type(echoes).__name__}")
    c = config
    on, peak, evidence, width, *point_scalars = _point_options(echoes, c, pulse_bins)
    # the tracker's inputs (_track_inputs) and the tracking in one kernel call
    out, after, hit = _kernels.tracked_echoes(
        *_track_input_args(echoes, c), echoes.beam, int(echoes.n_beams), int(c.n_surfaces), int(c.max_gap),
        float(c.slope_bins), float(c.slope_cost), float(c.jump_bins), float(c.touch_bins), float(c.segment_cost),
        float(c.gap_cost), int(c.bridge_beams), int(c.extend_beams), on, peak, evidence, width, *point_scalars,
        bool(front))
    return out, after, bool(hit)


_NO_FLAGS = np.zeros(0, dtype=np.bool_)
_NO_ROWS = np.zeros(0, dtype=np.int64)


def _track_inputs(echoes: Echoes, config: TrackConfig) -> tuple[NDArray[np.int64], NDArray[np.int64],
                                                                 NDArray[np.float64], NDArray[np.bool_],
                                                                 NDArray[np.float64]]:
    """``(lo, hi, unary, point, rise)``: the echoes' bin intervals (:meth:`Echoes.intervals`), the
    tracker's per-echo cost ``beam_cost - evidence``, the point echoes (mean log-likelihood ratio
    per structure pixel at least ``point_llr``) and :func:`clip_rise`, in one kernel call."""
    import sonarmap.ranges._kernels as _kernels

    return _kernels.track_inputs(*_track_input_args(echoes, config))  # type: ignore[no-any-return]


def _track_input_args(echoes: Echoes, config: TrackConfig) -> tuple:  # type: ignore[type-arg]
    """The arguments of :func:`_kernels.track_inputs` for ``echoes`` under ``config``."""
    e = echoes
    return (np.ascontiguousarray(e.edge_bin, dtype=np.float64), np.ascontiguousarray(e.start_bin, dtype=np.int64),
            np.ascontiguousarray(e.stop_bin, dtype=np.int64), np.ascontiguousarray(e.evidence, dtype=np.float64),
            np.ascontiguousarray(e.n_pixels, dtype=np.int64), np.ascontiguousarray(e.peak_bin, dtype=np.int64),
            _NO_FLAGS if e.clipped is None else np.ascontiguousarray(e.clipped, dtype=np.bool_),
            _NO_ROWS if e.clip_row is None else np.ascontiguousarray(e.clip_row, dtype=np.int64),
            e.clipped is not None, e.clip_row is not None, float(config.beam_cost), float(config.point_llr))


def front_surfaces(echoes: Echoes, tracks: Tracks, config: TrackConfig = TrackConfig(),
                   pulse_bins: int = 1) -> Tracks:
    """The front pass (module notes): surfaces in front of each beam's nearest tracked echo.

    One more pass of the tracking programme over the echoes that lie wholly in front of their
    beam's nearest tracked echo (their bin interval ends before its interval starts; beams without
    a tracked echo take no part); each echo of a piece it keeps becomes its beam's nearest surface,
    the farthest one dropping off when the beam already holds ``n_surfaces``.  Then, with
    ``config.extend_beams``, the end extensions (module notes) of the surfaces so tracked, whose
    echoes become their beams' nearest surfaces likewise.  One kernel
    (:func:`_kernels.front_and_extensions`), which :func:`tracks_and_front` runs inside the
    tracking kernel.

    Parameters
    ----------
    echoes : Echoes
    tracks : Tracks
        :func:`track_surfaces` of ``echoes``.
    config : TrackConfig
    pulse_bins : int
        Pulse length in bins (the point-target rule).

    Returns
    -------
    Tracks
        ``tracks`` itself when neither the pass nor an extension keeps anything.
    """
    import sonarmap.ranges._kernels as _kernels

    if not isinstance(tracks, Tracks) or tracks.echo.ndim != 2 or tracks.echo.shape[1] != echoes.n_beams:
        raise InputError(f"tracks: expected Tracks over {echoes.n_beams} beams")
    if echoes.size == 0:
        return tracks
    lo, hi, unary, point, rise = _track_inputs(echoes, config)
    c = config
    first, count = _kernels.beam_index(echoes.beam, int(echoes.n_beams))
    echo = np.ascontiguousarray(tracks.echo, dtype=np.int64)
    after, hit = _kernels.front_and_extensions(
        first, count, echoes.beam, echo, np.ascontiguousarray(echoes.edge_bin, dtype=np.float64), lo, hi,
        unary, int(c.max_gap), float(c.slope_bins), float(c.slope_cost), float(c.jump_bins),
        float(c.touch_bins), float(c.segment_cost), float(c.gap_cost), int(c.extend_beams),
        *_point_arguments(echoes, c, pulse_bins, (point, rise)))
    return Tracks(echo=after) if hit else tracks


def _point_arguments(echoes: Echoes, config: TrackConfig, pulse_bins: int,
                     point_rise: tuple[NDArray[np.bool_], NDArray[np.float64]] | None = None
                     ) -> tuple:  # type: ignore[type-arg]
    """The point-target arguments of :func:`_kernels.point_pieces` after ``on`` (False: the rule is
    off - no beamwidth or ``point_fraction`` 0), for :func:`_kernels.track_surfaces`
    (``point_rise``: the point echoes and :func:`clip_rise` of :func:`_track_inputs`, when made)."""
    on, peak, evidence, width, *scalars = _point_options(echoes, config, pulse_bins)
    if not on:
        return (False, peak, np.zeros(0, dtype=np.bool_), peak, evidence, width, *scalars)
    point, rise = _track_inputs(echoes, config)[3:] if point_rise is None else point_rise
    return (True, peak, point, rise, evidence, width, *scalars)


def _point_options(echoes: Echoes, config: TrackConfig, pulse_bins: int) -> tuple:  # type: ignore[type-arg]
    """:func:`_point_arguments` without the point echoes and clip rises: ``on``, the peaks, the
    evidence and the beamwidths (empty when off) and the rule's scalars."""
    on = config.point_fraction > 0 and echoes.beamwidth_beams is not None and echoes.size > 0
    pb = max(int(pulse_bins), 1)
    flat = max(1.0, 0.5 * pb)  # a point's edges agree within half a pulse (at least a bin)
    if not on:
        z = np.zeros(0)
        return (False, z, z, z, float(pb), flat, 2.0 * flat, 0.0, 1.0, 0.0, 0.0)
    return (True, np.ascontiguousarray(echoes.peak_value, dtype=np.float64),
            np.ascontiguousarray(echoes.evidence, dtype=np.float64),
            np.ascontiguousarray(echoes.beamwidth_beams, dtype=np.float64), float(pb), flat, 2.0 * flat,
            float(config.point_dip), 10.0 ** (config.point_over_range_db / 10.0), float(config.point_margin),
            float(config.point_fraction))


def clip_rise(echoes: Echoes) -> NDArray[np.float64]:
    """Per echo, how far the half-peak edge of its unclipped signal may lie behind its measured
    edge (bins): from ``edge_bin`` to its first full-scale row for an echo whose first peak is
    clipped (that row at most a bin behind ``peak_bin``), 0 for another clipped echo or when the
    row is not known, -1 for an echo that is not clipped (module notes, "Point targets")."""
    import sonarmap.ranges._kernels as _kernels

    # only a clipped first peak moves the edge (a later peak may clip: two fish in one echo)
    e = echoes
    return _kernels.clip_rises(  # type: ignore[no-any-return]
        np.ascontiguousarray(e.edge_bin, dtype=np.float64), np.ascontiguousarray(e.peak_bin, dtype=np.int64),
        _NO_FLAGS if e.clipped is None else np.ascontiguousarray(e.clipped, dtype=np.bool_),
        _NO_ROWS if e.clip_row is None else np.ascontiguousarray(e.clip_row, dtype=np.int64),
        e.clipped is not None, e.clip_row is not None)


def point_streaks(echoes: Echoes, chosen: NDArray[np.int64], config: TrackConfig = TrackConfig(),
                  pulse_bins: int = 1, lo: NDArray[np.int64] | None = None,
                  hi: NDArray[np.int64] | None = None) -> NDArray[np.bool_]:
    """Beams of the tracked pieces that are point targets (fish, a school of them), not surfaces.

    See the module notes ("Point targets").  Nothing is returned without
    :attr:`Echoes.beamwidth_beams` (a geometry without ``azimuth_beamwidth_rad``).

    Parameters
    ----------
    echoes : Echoes
    chosen : ndarray of int, shape (n_beams,)
        One tracking pass: per beam the chosen echo (-1 none).
    config : TrackConfig
    pulse_bins : int
        Pulse length in bins.
    lo, hi : ndarray of int, optional
        The echoes' bin intervals (:meth:`Echoes.intervals`).

    Returns
    -------
    ndarray of bool, shape (n_beams,)
        True on the beams of point pieces.

    Examples
    --------
    >>> import numpy as np
    >>> from sonarmap.geometry import SonarGeometry
    >>> from sonarmap.ranges.echoes import find_echoes
    >>> az = np.deg2rad(np.linspace(-3, 3, 25))
    >>> g = SonarGeometry(azimuth_rad=az, range_m=np.linspace(1, 2, 60), azimuth_beamwidth_rad=np.deg2rad(0.5))
    >>> img = np.zeros((60, 25)); img[30:32, 10:15] = 16 * 2.0 ** -(np.arange(-2, 3) ** 2)  # a fish
    >>> e = find_echoes(img > 0, img, g, llr=np.full(img.shape, 4.0))  # 2 beams wide lobes, 12 dB
    >>> chosen = np.full(25, -1); chosen[10:15] = np.arange(5)
    >>> bool(point_streaks(e, chosen)[10:15].all())
    True
    """
    import sonarmap.ranges._kernels as _kernels

    sel = np.ascontiguousarray(chosen, dtype=np.int64)
    if sel.shape != (echoes.n_beams,):
        raise InputError(f"chosen: expected shape ({echoes.n_beams},), got {sel.shape}")
    inputs = _track_inputs(echoes, config)
    on, peak, point, rise, evidence, width, pb, flat, jump, dip, over, margin, fraction = _point_arguments(
        echoes, config, pulse_bins, inputs[3:])
    if not on or not (sel >= 0).any():
        return np.zeros(sel.shape, dtype=bool)
    if lo is None or hi is None:
        lo, hi = inputs[:2]
    return _kernels.point_pieces(  # type: ignore[no-any-return]
        sel, np.ascontiguousarray(echoes.edge_bin, dtype=np.float64), peak, point, rise, evidence, width, lo, hi,
        int(config.max_gap), float(config.jump_bins), float(config.touch_bins), pb, flat, jump, dip, over, margin,
        fraction)


#: :func:`continuation_mask`'s default ``min_run``, ``max_beams``, ``window_bins`` and ``max_misses``
#: (the pipeline's range stage walks with them).
CONTINUE_MIN_RUN, CONTINUE_MAX_BEAMS, CONTINUE_WINDOW_BINS, CONTINUE_MAX_MISSES = 5, 16, 3.0, 2


def continuation_mask(echoes: Echoes, first: NDArray[np.int64], levels: NDArray[np.integer],
                      level_evidence: NDArray[np.float64], *, min_run: int = CONTINUE_MIN_RUN,
                      max_beams: int = CONTINUE_MAX_BEAMS, window_bins: float = CONTINUE_WINDOW_BINS,
                      min_evidence: float = 10.0, max_misses: int = CONTINUE_MAX_MISSES,
                      touch_bins: float = 1.0) -> NDArray[np.bool_]:
    """Pixels that continue a tracked surface beyond its ends where the classifier left it.

    A surface's faint part (its far end, a stretch under a weaker echo) may have no classifier
    structure pixel that survives the component rule, although its pixels are more likely
    structure than background.  From each end of a run of at least ``min_run`` tracked beams
    (:func:`sonarmap.ranges.echoes.surface_runs`), the leading edge is extrapolated beam by beam
    along the run's slope (Theil-Sen over its last 10 beams); in each beam the window of the
    run's echo thickness (2-16 bins) whose summed per-pixel log-likelihood ratio
    (``level_evidence[levels]``, nats) is largest within ``max(window_bins, thickness / 2)`` (+ a
    bin per beam of extrapolation) of the prediction is a continuation when that sum reaches
    ``min_evidence``: its pixels are returned, and the prediction restarts from it.  The walk
    stops at ``max_misses`` beams in a row without one, at another return near the prediction,
    or after ``max_beams`` beams.  A beam the walk missed and passed is searched again, once the
    walk finds the next beam, within ``max(window_bins, thickness / 2)`` of the line between the two
    beams found around it (a step in the surface puts the extrapolated window beside the echo).
    The pixels are candidates only: the tracker decides whether they are part of the surface.

    Parameters
    ----------
    echoes : Echoes
    first : ndarray of int, shape (n_beams,)
        The tracked return's echo per beam (``Tracks.first``).
    levels : ndarray of int, shape (n_bins, n_beams)
        The quantised image the classifier saw.
    level_evidence : ndarray of float
        Log-likelihood ratio structure : background per level
        (:func:`sonarmap.ranges.echoes.level_llr`).

    Returns
    -------
    ndarray of bool, shape (n_bins, n_beams)
    """
    return _continuation_pixels(echoes, first, levels, level_evidence, min_run=min_run, max_beams=max_beams,
                                window_bins=window_bins, min_evidence=min_evidence, max_misses=max_misses,
                                touch_bins=touch_bins)[0]


def _continuation_pixels(echoes: Echoes, first: NDArray[np.int64], levels: NDArray[np.integer],
                         level_evidence: NDArray[np.float64], *, min_run: int = CONTINUE_MIN_RUN,
                         max_beams: int = CONTINUE_MAX_BEAMS, window_bins: float = CONTINUE_WINDOW_BINS,
                         min_evidence: float = 10.0, max_misses: int = CONTINUE_MAX_MISSES,
                         touch_bins: float = 1.0) -> tuple[NDArray[np.bool_], int, int, NDArray[np.int64],
                                                           NDArray[np.int64]]:
    """:func:`continuation_mask` and the first and one-past-last row holding one of its pixels
    (``(n_bins, 0)``: none), overall and per beam (arrays: ``n_bins`` and 0 where none)."""
    import sonarmap.ranges._kernels as _kernels

    code, lut, sel = _continuation_inputs(echoes, first, levels, level_evidence)
    if sel is None:
        n, m = code.shape
        return np.zeros(code.shape, dtype=bool), n, 0, np.full(m, n, np.int64), np.zeros(m, np.int64)
    edge, stop, run = _first_runs(echoes, sel, touch_bins)
    out, r0, r1, col_lo, col_hi = _kernels.continuation_mask(code, lut, edge, stop, run, int(min_run), int(max_beams),
                                                             float(window_bins), float(min_evidence), int(max_misses))
    return out, int(r0), int(r1), col_lo, col_hi


def _continuation_inputs(echoes: Echoes, first: NDArray[np.int64], levels: NDArray[np.integer],
                         level_evidence: NDArray[np.float64]
                         ) -> tuple[NDArray[np.integer], NDArray[np.float64], NDArray[np.int64] | None]:
    """The checked inputs of :func:`continuation_mask`: the C-contiguous levels and evidence table
    (an :class:`InputError` for levels of another shape or outside the table) and the returns
    ``first`` as int64 (None without any return: no continuation)."""
    code = np.ascontiguousarray(levels)
    lut = np.ascontiguousarray(level_evidence, dtype=np.float64)
    if code.ndim != 2 or code.shape[1] != echoes.n_beams:
        raise InputError(f"levels: expected shape (n_bins, {echoes.n_beams}), got {code.shape}")
    if not _levels_in_range(code, lut.size):
        raise InputError(f"levels: values must lie in [0, {lut.size})")
    sel = np.asarray(first, dtype=np.int64)
    if echoes.size == 0 or not (sel >= 0).any():
        return code, lut, None
    return code, lut, sel
