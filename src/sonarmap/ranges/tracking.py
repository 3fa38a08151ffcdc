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
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from sonarmap._config import check_integers, coerce_reals, config_error
from sonarmap.errors import InputError
from sonarmap.ranges.echoes import Echoes

__all__ = ["TrackConfig", "Tracks", "track_surfaces", "continuation_mask"]


@dataclasses.dataclass(frozen=True)
class TrackConfig:
    """Costs of the surface model (nats; see the module notes)."""

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

    def __post_init__(self) -> None:
        where = "track config: "
        coerce_reals(self, ("segment_cost", "beam_cost", "slope_cost", "slope_bins", "gap_cost", "jump_bins",
                            "touch_bins"), where, minimum=0)
        if self.slope_bins <= 0:
            raise config_error(where, "slope_bins", "must be > 0", self.slope_bins)
        check_integers(self, (("max_gap", 0), ("n_surfaces", 1), ("bridge_beams", 0)), where)


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


def track_surfaces(echoes: Echoes, config: TrackConfig = TrackConfig()) -> Tracks:
    """Track surfaces across beams (see the module notes); the result is sorted by range per beam."""
    from sonarmap.ranges import _kernels

    if not isinstance(echoes, Echoes):
        raise InputError(f"echoes: expected Echoes, got {type(echoes).__name__}")
    lo, hi = echoes.intervals()
    c = config
    return Tracks(echo=_kernels.track_surfaces(
        echoes.beam, int(echoes.n_beams), np.ascontiguousarray(echoes.edge_bin, dtype=np.float64), lo, hi,
        c.beam_cost - echoes.evidence, int(c.n_surfaces), int(c.max_gap), float(c.slope_bins), float(c.slope_cost),
        float(c.jump_bins), float(c.touch_bins), float(c.segment_cost), float(c.gap_cost), int(c.bridge_beams)))


def continuation_mask(echoes: Echoes, first: NDArray[np.int64], levels: NDArray[np.integer],
                      level_evidence: NDArray[np.float64], *, min_run: int = 5, max_beams: int = 16,
                      window_bins: float = 3.0, min_evidence: float = 10.0, max_misses: int = 2,
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
    or after ``max_beams`` beams.  The pixels are candidates only: the tracker decides whether
    they are part of the surface.

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
    from sonarmap.ranges import _kernels
    from sonarmap.ranges.echoes import _first_intervals, _levels_in_range

    code = np.ascontiguousarray(levels)
    lut = np.ascontiguousarray(level_evidence, dtype=np.float64)
    if code.ndim != 2 or code.shape[1] != echoes.n_beams:
        raise InputError(f"levels: expected shape (n_bins, {echoes.n_beams}), got {code.shape}")
    if not _levels_in_range(code, lut.size):
        raise InputError(f"levels: values must lie in [0, {lut.size})")
    sel = np.asarray(first, dtype=np.int64)
    if echoes.size == 0 or not (sel >= 0).any():
        return np.zeros(code.shape, dtype=bool)
    edge, lo, hi, stop = _first_intervals(echoes, sel)
    run = _kernels.surface_runs(edge, lo, hi, float(touch_bins))
    return _kernels.continuation_mask(code, lut, edge, stop, run, int(min_run), int(max_beams), float(window_bins),
                                      float(min_evidence), int(max_misses))
