"""Leading edges along a tracked surface: each beam's edge combined with what its neighbours say.

A surface seen by neighbouring beams is continuous: where one beam's leading edge is noisy (a
speckled, slowly rising echo), the edges of the beams around it predict where it should lie.
:func:`smooth_surface_edges` combines the two per beam, weighting each by its uncertainty:

* the **prediction** ``p_j``: a weighted least-squares quadratic in the beam index through the
  edges of the beams within ``half_beams`` of ``j`` on the same surface run, *without* beam ``j``
  itself (leave-one-out), with tricube weights over the window times ``1 / sigma_i^2``;
* its **variance** ``v_j = sum_i l_i^2 (sigma_i^2 + rho) + rho``, with ``l_i`` the quadratic's
  weights at ``j`` and ``rho`` the surface's roughness about the quadratic - the neighbours'
  weighted residual variance (over its degrees of freedom) beyond what their sigmas explain.  A
  surface with real structure at the scale of a few beams (a steep line sampled beam by beam, a
  step within a run) has a large ``rho``, so its beams keep their own edges;
* the **combination** ``e_j + k (p_j - e_j)``, ``k = sigma_j^2 / (sigma_j^2 + v_j)``: a precise
  edge (a bright, sharp rise) barely moves, a noisy one moves most of the way to its neighbours'
  prediction.

The sigma shrinks by the beam-to-beam scatter the combination removes,
``sigma_j^2 - k min(s^2, sigma_j^2)`` with ``s^2`` the neighbours' residual variance (never below
half of sigma): an error the neighbours share - a bias of the whole surface - is not averaged
away, and stays in the sigma.  An echo given a ``trust`` factor ``t_j > 1`` weighs, enters
``v`` and is combined with ``t_j sigma_j``; its sigma update keeps the gain of ``sigma_j`` itself
against the same ``v_j``.

Only first returns of runs of at least ``min_beams`` beams are combined (the pipeline's
``RangeConfig.edge_smooth_beams`` / ``edge_smooth_min_beams``).  Measured on the simulator
(``docs/ranges.md``, "Smoothing along the surface") and on the Kongsberg swath against the
sonar's own detections (``benchmarks/kongsberg_checks.py``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ranges.echoes import Echoes

__all__ = ["smooth_surface_edges", "SIGMA_MIN_BINS", "window_in_beamwidths"]

#: Sigmas below this many bins are taken as this in the weights (a sigma of a few hundredths of a
#: bin would otherwise pin a beam's own edge and dominate its neighbours' predictions).
SIGMA_MIN_BINS = 0.3


def window_in_beamwidths(half_beams: int, beamwidth_beams: ArrayLike | None) -> int:
    """The half window of :func:`smooth_surface_edges` for a fan whose beams overlap.

    ``half_beams`` counts beams of a fan whose beams are at most one spacing wide.  Neighbouring
    beams that overlap see the same scatterers, so their edges' errors are correlated over about
    a beamwidth and a window of ``half_beams`` beams holds fewer independent edges: the window is
    widened to ``half_beams`` x the median beamwidth in beam spacings (``Echoes.beamwidth_beams``)
    where that exceeds 1 (the Oculus M750d-like fan, 2.4: the default 16 -> 38 beams; the
    Kongsberg EM2040's 2.7: 43), unchanged otherwise (DIDSON, ARIS) or when the geometry gives no
    beamwidth.

    Examples
    --------
    >>> window_in_beamwidths(8, [2.39, 2.4, 2.38]), window_in_beamwidths(8, [0.5, 0.5]), window_in_beamwidths(8, None)
    (19, 8, 8)
    """
    if half_beams <= 0 or beamwidth_beams is None:
        return int(half_beams)
    bw = np.asarray(beamwidth_beams, dtype=np.float64)
    bw = np.sort(bw[np.isfinite(bw)])
    if not bw.size:
        return int(half_beams)
    # np.median's value from the sorted beamwidths (np.median's Python layers cost ~15-70 us a call
    # in a ping's processing): the middle one, or the mean of the two middle ones
    h = bw.size // 2
    median = float(bw[h]) if bw.size % 2 else float((bw[h - 1] + bw[h]) / 2)
    return int(round(half_beams * max(1.0, median)))


def smooth_surface_edges(echoes: Echoes, first: ArrayLike, geometry: SonarGeometry, *, half_beams: int = 8,
                         min_beams: int = 7, touch_bins: float = 1.0, trust: ArrayLike | None = None) -> Echoes:
    """Combine each return's leading edge with the prediction from its neighbours on its surface.

    Parameters
    ----------
    echoes : Echoes
        The ping's echoes with their leading edges and sigmas (after
        :func:`sonarmap.ranges.echoes.pooled_edges` / :func:`sonarmap.ranges.template.template_edges`).
    first : array_like of int, shape (n_beams,)
        Per beam the echo index of its return (-1: none), ``Tracks.first``.
    geometry : SonarGeometry
        The ping's geometry (bin spacing, ranges).
    half_beams : int
        Beams on either side of each beam in its prediction (>= 2).
    min_beams : int
        Shortest run of returns (beams whose echoes touch, :func:`sonarmap.ranges.echoes.pooled_edges`'
        runs) that is combined (>= 5).
    touch_bins : float
        Echo intervals this close belong to one run (``TrackConfig.touch_bins``).
    trust : array_like of float, shape (n_echoes,), optional
        Per echo, a factor (>= 1) on its sigma inside the combination only: the echo weighs in
        its neighbours' predictions, and is pulled towards its own, as if its sigma were that
        many times larger; its reported sigma is shrunk from its own value, by the gain its own
        sigma would have against the same prediction (the factor says how far to lean on the
        neighbours, not that the edge became more precise; ``RangeConfig.sigma_template_smooth_scale``
        on the template-measured edges, ``edge_template_anchor_trust``).  Default: 1 for every
        echo.

    Returns
    -------
    Echoes
        ``echoes`` with the returns' ``edge_bin``, ``edge_range_m`` and ``sigma_m`` replaced where
        combined; every other field unchanged.

    Raises
    ------
    InputError
        If an option is out of range or ``first`` has not one entry per beam.
    """
    import sonarmap.ranges._smoothing_kernels as _sk

    sel = np.asarray(first, dtype=np.int64)
    for key, v, lo in (("half_beams", half_beams, 2), ("min_beams", min_beams, 5)):
        if isinstance(v, bool) or int(v) != v or v < lo:
            raise InputError(f"{key}: must be an integer >= {lo} (got {v!r})")
    if sel.shape != (echoes.n_beams,):
        raise InputError(f"first: expected one echo index per beam ({echoes.n_beams}), got shape {sel.shape}")
    if not echoes.size:
        return echoes
    if trust is not None:
        trust = np.ascontiguousarray(trust, dtype=np.float64)
        if trust.shape != (echoes.size,) or not np.all(trust >= 1.0):  # (NaN fails too)
            raise InputError(f"trust: expected one factor >= 1 per echo ({echoes.size}), got shape {trust.shape}"
                             + ("" if trust.shape != (echoes.size,) else " with a value below 1 or NaN"))
    bin_m = abs(geometry.range_resolution_m) or 1.0  # (the bin the sigmas were formed with)
    # the first runs, the combination and the moved returns' fields in one kernel (a beam without
    # a return, or none at all, moves nothing)
    n_moved, eb, er, sg = _sk.smoothed_echo_edges(
        np.ascontiguousarray(sel), echoes.edge_bin, echoes.edge_range_m, echoes.sigma_m, echoes.start_bin,
        echoes.stop_bin, float(touch_bins), int(half_beams), int(min_beams), SIGMA_MIN_BINS, bin_m,
        np.ascontiguousarray(geometry.range_m, dtype=np.float64),
        np.ones(echoes.size) if trust is None else trust)
    if not n_moved:
        return echoes
    return echoes.replaced(edge_bin=eb, edge_range_m=er, sigma_m=sg)
