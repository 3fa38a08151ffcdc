"""Markov-random-field segmentation of sonar images (paper section V.C, eq. 17-18 and 22).

The lattice is the image itself: one site per (range bin, beam), labels ``0 .. n_labels-1``
(``0`` = background / free space, ``1`` = structure, further labels e.g. clutter such as fish).
The energy minimised by every solver is

.. math::

    E(x) = \\sum_p U_p(x_p) + \\sum_{(p,q)\\in\\mathcal N} w_{pq}\\,[x_p \\ne x_q]

with the unary term ``U_p(k) = -log p(y_p | k) - log pi_k`` (negative log posterior of the fitted
mixture, eq. 17-18, up to a per-pixel constant) and the Potts pairwise term of eq. 22 with weight
``w_pq = beta`` (4-neighbourhood; ``beta / sqrt(2)`` on diagonals of the 8-neighbourhood),
optionally contrast-sensitive, ``w_pq = beta exp(-(y_p - y_q)^2 / (2 <(y_p - y_q)^2>))``.

Solvers
-------
``graphcut``
    Exact binary MAP by s-t minimum cut (PyMaxflow).  Before the cut the problem is reduced
    exactly: a pixel whose unary margin exceeds the total weight of its free edges has the same
    label in every minimiser (persistency) and is fixed; this is propagated to neighbours, and with
    uniform 4-neighbourhood weights followed by the same argument on whole runs of free pixels
    along the beams (chains solved by dynamic programming, the free neighbours in the adjacent
    range bins bounded), then on ladders of two adjacent range bins (the same, with the edges
    between the two bins exact).  Only the remaining pixels enter the graph (about 0.5 % of an
    Oculus ping, 0.01 % of a DIDSON one), which makes the exact solve many times faster than
    cutting the full lattice.
``expansion``
    alpha-expansion (Boykov, Veksler & Zabih 2001) for ``n_labels > 2``; each move is an exact cut;
    the result is within a factor 2 of the optimum for Potts energies.
``icm``
    Iterated conditional modes (Besag 1986), numba kernel; a local minimum.
``anneal``
    Simulated annealing with a Gibbs sampler (Geman & Geman 1984), the solver of the paper; the
    schedule is geometric, ``T_k = T0 (T1/T0)^(k/(n-1))`` with ``T0 = 4``, ``T1 = 0.05``,
    ``n = 60`` sweeps by default, followed by ICM sweeps at zero temperature.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import threading
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError

__all__ = [
    "MRFResult",
    "AnnealSchedule",
    "pairwise_weights",
    "energy",
    "unary_from_log_likelihood",
    "unary_from_fit",
    "solve",
    "solve_graphcut",
    "solve_graphcut_levels",
    "solve_expansion",
    "solve_icm",
    "solve_anneal",
    "segment_mrf",
    "SOLVERS",
]

SOLVERS = ("graphcut", "expansion", "icm", "anneal")
Solver = Literal["graphcut", "expansion", "icm", "anneal"]


@dataclasses.dataclass(frozen=True, eq=False)
class MRFResult:
    """Result of an MRF solve.

    Attributes
    ----------
    labels : ndarray of uint8, shape (n_bins, n_beams)
        The labelling.
    energy : float
        Its energy ``E(x)`` (unary + pairwise), the quantity every solver minimises.
    solver : str
        ``"graphcut"``, ``"expansion"``, ``"icm"`` or ``"anneal"``.
    beta : float
        Potts weight.
    neighbourhood : int
        4 or 8.
    n_iterations : int
        Sweeps (ICM, annealing) or expansion cycles; 1 for a single cut.
    n_free : int
        Pixels left in the graph after the exact reduction (graph cut only; else all pixels).
    exact : bool
        Whether ``labels`` is a proven global minimiser (binary graph cut).
    """

    labels: NDArray[np.uint8]
    energy: float
    solver: str
    beta: float
    neighbourhood: int
    n_iterations: int = 1
    n_free: int = 0
    exact: bool = False

    @property
    def n_labels_used(self) -> int:
        """Number of distinct labels in the result."""
        return int(np.unique(self.labels).size)


@dataclasses.dataclass(frozen=True)
class AnnealSchedule:
    """Geometric cooling schedule of :func:`solve_anneal`.

    ``T_k = t_start (t_end / t_start)^(k / (n_sweeps - 1))``, one Gibbs sweep per temperature,
    then up to ``icm_sweeps`` zero-temperature (ICM) sweeps.
    """

    t_start: float = 4.0
    t_end: float = 0.05
    n_sweeps: int = 60
    icm_sweeps: int = 10

    def __post_init__(self) -> None:
        if not (self.t_start > 0 and self.t_end > 0):
            raise InputError("schedule: temperatures must be positive")
        if self.n_sweeps < 1 or self.icm_sweeps < 0:
            raise InputError("schedule: n_sweeps must be >= 1 and icm_sweeps >= 0")

    def temperatures(self) -> NDArray[np.float64]:
        """The temperature of every sweep."""
        if self.n_sweeps == 1:
            return np.array([self.t_end])
        k = np.arange(self.n_sweeps) / (self.n_sweeps - 1)
        return self.t_start * (self.t_end / self.t_start) ** k


# ----------------------------------------------------------------------------- model pieces


def _check_unary(unary: ArrayLike) -> NDArray[np.float64]:
    u = np.asarray(unary)
    if u.ndim != 3 or u.shape[0] < 2 or u.shape[1] < 1 or u.shape[2] < 1:
        raise InputError(f"unary: expected shape (n_labels >= 2, n_bins, n_beams), got {u.shape}")
    u = np.ascontiguousarray(u, dtype=np.float64)
    if not np.isfinite(u).all():
        raise InputError("unary: contains NaN or infinite costs (clip log-probabilities first)")
    return u


def _check_beta(beta: float) -> float:
    b = float(beta)
    if not math.isfinite(b) or b < 0:
        raise InputError(f"beta: must be finite and >= 0 (got {beta})")
    return b


def pairwise_weights(
    shape: tuple[int, int],
    *,
    beta: float,
    neighbourhood: int = 4,
    image: ArrayLike | None = None,
    contrast: bool = False,
    range_weight: float = 1.0,
) -> NDArray[np.float64]:
    """Potts edge weights of the lattice (eq. 22), optionally contrast-sensitive and anisotropic.

    Parameters
    ----------
    shape : (n_bins, n_beams)
        Lattice shape.
    beta : float
        Potts weight ``beta >= 0``.
    neighbourhood : {4, 8}
        4: range and beam neighbours; 8: also diagonals, weighted ``1/sqrt(2)``.
    image : ndarray, shape (n_bins, n_beams), optional
        Intensities, required when ``contrast`` is true.
    contrast : bool
        Multiply each weight by ``exp(-(y_p - y_q)^2 / (2 s))``, ``s`` the mean squared difference
        over all edges (Boykov & Jolly 2001), so boundaries prefer intensity edges.
    range_weight : float
        Factor on the edges along range (between bins of one beam).  Surfaces are thin in range
        and long across beams, so ``range_weight < 1`` keeps a 1-3-bin surface from paying the
        full ``2 beta`` per pixel for its range boundaries while keeping the smoothing across beams.

    Returns
    -------
    ndarray, shape (2 or 4, n_bins, n_beams)
        ``w[d, i, j]`` is the weight of the edge from ``(i, j)`` to ``(i, j) + offset[d]`` with
        offsets (1, 0), (0, 1), (1, 1), (1, -1); zero where the partner is outside the lattice.
    """
    beta = _check_beta(beta)
    if neighbourhood not in (4, 8):
        raise InputError(f"neighbourhood: must be 4 or 8 (got {neighbourhood})")
    h, w = int(shape[0]), int(shape[1])
    rw = float(range_weight)
    if not math.isfinite(rw) or rw < 0:
        raise InputError(f"range_weight: must be finite and >= 0 (got {range_weight})")
    if not contrast:
        return _uniform(h, w, neighbourhood, beta, rw)[0]
    base = _base_weights(h, w, neighbourhood).copy()
    base[0] *= rw
    if image is None:
        raise InputError("image: required for contrast-sensitive weights")
    y = np.asarray(image, dtype=np.float64)
    if y.shape != (h, w):
        raise InputError(f"image: shape {y.shape} does not match lattice {(h, w)}")
    diffs = np.zeros_like(base)
    diffs[0, :-1, :] = y[1:, :] - y[:-1, :]
    diffs[1, :, :-1] = y[:, 1:] - y[:, :-1]
    if neighbourhood == 8:
        diffs[2, :-1, :-1] = y[1:, 1:] - y[:-1, :-1]
        diffs[3, :-1, 1:] = y[1:, :-1] - y[:-1, 1:]
    sq = diffs * diffs
    mask = base > 0
    s = float(sq[mask].mean()) if mask.any() else 0.0
    if s <= 0:
        return base * beta
    return base * beta * np.exp(-sq / (2.0 * s))


@functools.lru_cache(maxsize=16)
def _base_weights(h: int, w: int, neighbourhood: int) -> NDArray[np.float64]:
    n_dirs = 2 if neighbourhood == 4 else 4
    out = np.zeros((n_dirs, h, w))
    out[0, :-1, :] = 1.0
    out[1, :, :-1] = 1.0
    if n_dirs == 4:
        out[2, :-1, :-1] = 1.0 / math.sqrt(2.0)
        out[3, :-1, 1:] = 1.0 / math.sqrt(2.0)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=32)
def _uniform(h: int, w: int, neighbourhood: int, beta: float, range_weight: float = 1.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Uniform Potts weights and their per-pixel totals, cached (reused across equal pings)."""
    wt = _base_weights(h, w, neighbourhood) * beta
    wt[0] *= range_weight
    wt.setflags(write=False)
    tot = _total_weight(wt)
    tot.setflags(write=False)
    return wt, tot


_NOT_UNIFORM = np.empty(0)


def _uniform_pair(wt: NDArray[np.float64]) -> NDArray[np.float64]:
    """``[w_range, w_beam]`` of a uniform 4-neighbourhood weight array from :func:`_uniform` (the
    weight of every interior edge along range / across beams), for the reduction kernel."""
    h, w = wt.shape[1:]
    if wt.shape[0] != 2 or h < 3 or w < 3:
        return _NOT_UNIFORM
    return np.array([wt[0, 1, 1], wt[1, 1, 1]])


def _total_weight(wt: NDArray[np.float64]) -> NDArray[np.float64]:
    """Sum of the weights of the edges at each pixel, shape (n_bins, n_beams)."""
    tot = wt.sum(axis=0)
    tot[1:, :] += wt[0, :-1, :]
    tot[:, 1:] += wt[1, :, :-1]
    if wt.shape[0] == 4:
        tot[1:, 1:] += wt[2, :-1, :-1]
        tot[1:, :-1] += wt[3, :-1, 1:]
    return tot


def _weights_for(
    unary: NDArray[np.float64],
    beta: float,
    neighbourhood: int,
    weights: ArrayLike | None,
) -> NDArray[np.float64]:
    h, w = unary.shape[1:]
    if weights is None:
        return np.ascontiguousarray(pairwise_weights((h, w), beta=beta, neighbourhood=neighbourhood))
    wt = np.ascontiguousarray(weights, dtype=np.float64)
    if wt.ndim != 3 or wt.shape[0] not in (2, 4) or wt.shape[1:] != (h, w):
        raise InputError(f"weights: expected shape (2 or 4, {h}, {w}), got {wt.shape}")
    if not np.isfinite(wt).all() or (wt < 0).any():
        raise InputError("weights: must be finite and non-negative")
    return wt


def energy(
    labels: ArrayLike,
    unary: ArrayLike,
    beta: float | None = None,
    *,
    neighbourhood: int = 4,
    weights: ArrayLike | None = None,
) -> float:
    """Energy ``E(x) = sum_p U_p(x_p) + sum_pq w_pq [x_p != x_q]`` of a labelling.

    Give either ``beta`` (+ ``neighbourhood``) or explicit ``weights`` from
    :func:`pairwise_weights`.
    """
    u = _check_unary(unary)
    lab = np.asarray(labels)
    if lab.shape != u.shape[1:]:
        raise InputError(f"labels: shape {lab.shape} does not match unary {u.shape[1:]}")
    if weights is None and beta is None:
        raise InputError("beta: give beta or weights")
    wt = _weights_for(u, 0.0 if beta is None else _check_beta(beta), neighbourhood, weights)
    if lab.size and (lab.min() < 0 or lab.max() >= u.shape[0]):
        raise InputError(f"labels: values must lie in [0, {u.shape[0] - 1}]")
    return _energy(u, wt, lab)


def _flat_levels(h: int, w: int) -> NDArray[np.int64]:
    return _flat_levels_cached(h, w)


@functools.lru_cache(maxsize=8)
def _flat_levels_cached(h: int, w: int) -> NDArray[np.int64]:
    a = np.arange(h * w, dtype=np.int64).reshape(h, w)
    a.setflags(write=False)
    return a


def _energy(u: NDArray[np.float64], wt: NDArray[np.float64], labels: NDArray[Any]) -> float:
    from sonarmap.classify._kernels import energy_lut

    h, w = u.shape[1:]
    lab = np.ascontiguousarray(labels, dtype=np.uint8)  # one compiled specialisation
    return float(energy_lut(_flat_levels(h, w), u.reshape(u.shape[0], -1), wt, lab))


def unary_from_log_likelihood(
    levels: ArrayLike,
    class_log_pmf: ArrayLike,
    class_log_prior: ArrayLike | None = None,
    *,
    floor: float = -50.0,
) -> NDArray[np.float32]:
    """Unary costs ``-log p(y|k) - log pi_k`` from per-level class log-pmfs (eq. 17-18).

    Parameters
    ----------
    levels : int ndarray, shape (n_bins, n_beams)
        Quantisation level index of each pixel.
    class_log_pmf : ndarray, shape (n_classes, n_levels)
        ``log p(level | class)``.
    class_log_prior : ndarray, shape (n_classes,), optional
        ``log pi_k``; uniform if omitted.
    floor : float
        Log-probabilities are clipped below at ``floor`` so impossible levels cost a large
        finite amount (a pmf of exactly zero would otherwise make the energy infinite).

    Returns
    -------
    ndarray of float32, shape (n_classes, n_bins, n_beams)
        Costs shifted so the smallest label cost of each level is zero.
    """
    from sonarmap.classify.segment import level_costs

    cost = level_costs(class_log_pmf, class_log_prior, floor=floor)
    lev = np.asarray(levels)
    if lev.dtype.kind not in "iu":
        raise InputError(f"levels: expected integer level indices, got {lev.dtype}")
    if lev.size and (lev.min() < 0 or lev.max() >= cost.shape[1]):
        raise InputError(f"levels: values must lie in [0, {cost.shape[1] - 1}]")
    return np.ascontiguousarray(cost.astype(np.float32)[:, lev])


def unary_from_fit(image: ArrayLike, fit: Any, *, n_levels: int = 256, floor: float = -50.0) -> NDArray[np.float32]:
    """Unary costs of an image under a fitted mixture (``sonarmap.stats.mixture.MixtureFit``).

    Uses ``fit.decision_log_pmf()`` and ``fit.class_prior()``; levels from
    ``sonarmap.stats.mixture.quantize``.
    """
    from sonarmap.stats.mixture import quantize

    levels = quantize(np.asarray(image, dtype=np.float32), n_levels=n_levels)
    lpmf = np.asarray(fit.decision_log_pmf(), dtype=np.float64)
    with np.errstate(divide="ignore"):
        lprior = np.log(np.asarray(fit.class_prior(), dtype=np.float64))
    return unary_from_log_likelihood(levels, lpmf, lprior, floor=floor)


# ----------------------------------------------------------------------------- solvers


def _graph(n_nodes: int, n_edges: int) -> Any:
    import maxflow

    return maxflow.GraphFloat(max(n_nodes, 1), max(n_edges, 1))


def _cut(c_margin: NDArray[np.float64], ei: NDArray[np.int64], ej: NDArray[np.int64],
         cap: NDArray[np.float64], rcap: NDArray[np.float64] | None = None) -> tuple[NDArray[np.bool_], float]:
    """Min cut with per-node margin ``c0 - c1`` (positive favours 1); returns (x, flow)."""
    n = c_margin.size
    g = _graph(n, ei.size)
    nodes = g.add_nodes(n)
    if ei.size:
        g.add_edges(ei, ej, cap, cap if rcap is None else rcap)
    # label 1 = sink segment, which cuts the source edge: source capacity = cost of label 1
    g.add_grid_tedges(np.asarray(nodes), np.maximum(-c_margin, 0.0), np.maximum(c_margin, 0.0))
    flow = g.maxflow()
    return g.get_grid_segments(np.asarray(nodes)), float(flow)


@functools.lru_cache(maxsize=8)
def _lattice_edges(h: int, w: int, n_dirs: int) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.intp]]:
    """Edge endpoint indices of the full lattice (cached per shape: reused across pings)."""
    from sonarmap.classify._kernels import DI, DJ

    idx = np.arange(h * w, dtype=np.int64).reshape(h, w)
    eis, ejs, sel = [], [], []
    flat = np.arange(n_dirs * h * w).reshape(n_dirs, h, w)
    for d in range(n_dirs):
        di, dj = int(DI[d]), int(DJ[d])
        i0, i1 = 0, h - di
        j0, j1 = max(0, -dj), w - max(0, dj)
        eis.append(idx[i0:i1, j0:j1].ravel())
        ejs.append(idx[i0 + di:i1 + di, j0 + dj:j1 + dj].ravel())
        sel.append(flat[d, i0:i1, j0:j1].ravel())
    out = (np.concatenate(eis), np.concatenate(ejs), np.concatenate(sel))
    for a in out:
        a.setflags(write=False)
    return out


class _Workspace(threading.local):
    """Per-thread work arrays of the graph-cut reduction, reused across pings of equal shape."""

    def __init__(self) -> None:
        self.arrays: dict[tuple[int, int], tuple[NDArray[Any], ...]] = {}

    def get(self, h: int, w: int) -> tuple[NDArray[Any], ...]:
        """``(node, stack)`` of :func:`sonarmap.classify._kernels.free_graph` and the reductions
        (nothing returned lives in them: the labels are a fresh array)."""
        key = (h, w)
        arr = self.arrays.get(key)
        if arr is None:
            if len(self.arrays) > 4:
                self.arrays.clear()
            arr = (
                np.empty((h, w), dtype=np.int64),
                np.empty(h * w + 1, dtype=np.int64),
            )
            self.arrays[key] = arr
        return arr


_WORK = _Workspace()


#: Propagation sweeps of the single-pixel persistency reduction after its first raster pass, and
#: passes of the chain reduction (:func:`sonarmap.classify._kernels.reduce_chains`) that replaces
#: the sweeps with uniform 4-neighbourhood weights (the pipeline's).  Both only fix pixels whose
#: label is the same in every minimiser, and the cut solves the rest exactly, so the caps move work
#: between reduction and cut without changing the minimiser.  Two sweeps gave identical labels on
#: every real DIDSON, ARIS and Oculus ping while cutting the Oculus MRF by more than half; the
#: chains decide most of what the single-pixel test leaves (Oculus: ~35000 free pixels after 2
#: sweeps, ~3000 after the chains), and with them no sweep and a few chain passes were fastest on
#: the same pings (identical labels again).  3 passes: on 4096 x 512 simulated pings the first
#: pass leaves ~47000 of ~200000 free pixels, the next two ~36000, and passes 4-6 fixed ~3000,
#: ~1900 and ~1200 more at 0.15-0.25 ms each, more than the ladders and the cut then spend on
#: them (the MRF 7.7-8.1 -> 7.5-7.6 ms); the real pings' MRF the same within 1 %.
_REDUCTION_SWEEPS = 2
_CHAIN_PASSES = 3
#: Passes of the ladder reduction (:func:`sonarmap.classify._ladders.reduce_ladders`) after the
#: chains: pairs of adjacent range bins solved exactly, their free neighbours bounded; exact
#: again, so only the time moves.  One pass leaves ~40 % of what the chains left (Oculus: ~2000
#: -> ~850 free pixels, 4096 x 512 sim pings ~27000 -> ~12500) and costs less than the cut it
#: saves (PyMaxflow's time per node grows with the pieces' size); a second pass fixes a fifth of
#: the rest at half the first pass's cost, about what it saves.
_LADDER_PASSES = 1
#: Chain passes after the ladders: the pixels the ladders fixed decide a quarter of the rest
#: (Oculus ~850 -> ~620 free pixels) for a few microseconds.
_CHAIN_PASSES_AFTER = 3
#: Rounds of ladder and chain passes where the chains left at least ``_LADDER_ROUNDS_MIN`` free
#: pixels (large images, whose pieces are large: PyMaxflow's time per node grows with them); a
#: second round leaves a fifth less (4096 x 512 sim pings: ~10500 -> ~8300 free pixels, 0.2-1.1
#: ms faster), on the real pings (<= ~4000 free pixels) it costs more than it saves.
_LADDER_ROUNDS = 2
_LADDER_ROUNDS_MIN = 8000
#: Largest level table for which the first reduction pass reads a per-level outcome table
#: (:func:`sonarmap.classify._kernels.reduce_uniform4`) instead of testing every pixel; a general
#: unary (one level per pixel) keeps the pixel test.
_TABLE_LEVELS = 1024


def _read_only(a: NDArray[Any]) -> NDArray[Any]:
    """``a`` itself when read-only, else a read-only view of it (no copy)."""
    if not a.flags.writeable:
        return a
    v = a.view()
    v.setflags(write=False)
    return v


def _graphcut_lut(
    levels: NDArray[Any],
    cost_lut: NDArray[np.float64],
    wt: NDArray[np.float64],
    wtot: NDArray[np.float64] | None,
    with_energy: bool = True,
    uniform: bool = False,
) -> tuple[NDArray[np.uint8], float, int]:
    """Exact binary cut with unary ``cost_lut[label, levels]``; returns (labels, energy, n_free).

    ``with_energy=False`` skips the energy evaluation (a full lattice pass) and returns NaN for it.
    ``uniform=True`` promises that ``wt`` comes from :func:`_uniform` (all interior edges along a
    direction have one weight), so the reduction reads scalars instead of ``wt`` inside the lattice
    and, for a 4-neighbourhood, the chain reduction replaces the single-pixel sweeps.
    """
    import sonarmap.classify._kernels as _ck
    import sonarmap.classify._ladders as _ladders

    h, w = levels.shape
    if wtot is None:
        wtot = _total_weight(wt)
    # read-only views of the inputs the kernels only read: numba compiles a kernel once per
    # argument type, and a read-only array is another type than a writable one (callers pass both)
    levels, wt, wtot = _read_only(levels), _read_only(wt), _read_only(wtot)
    node, stack = _WORK.get(h, w)
    # the reductions' pixel states (0, 1, or -1 free) become the labels once the cut has set the
    # free pixels: a fresh array, so no lattice pass copies them out of a work array
    fixed = np.empty((h, w), dtype=np.int8)
    margin_lut = np.ascontiguousarray(cost_lut[0] - cost_lut[1])
    # uniform 4-neighbourhood (the pipeline's): the chain reduction replaces the sweeps
    chains = uniform and wt.shape[0] == 2 and h >= 3 and w >= 3 and _CHAIN_PASSES > 0
    wr, wb = (float(wt[0, 1, 1]), float(wt[1, 1, 1])) if chains else (0.0, 0.0)
    if chains and margin_lut.size <= _TABLE_LEVELS:
        n_free = _ck.reduce_uniform4(levels, margin_lut, wt, wtot, fixed, stack, wr, wb)
    else:
        pair = _uniform_pair(wt) if uniform else _NOT_UNIFORM
        n_free = _ck.reduce_binary(levels, margin_lut, wt, wtot, fixed, stack, pair, 0 if chains else _REDUCTION_SWEEPS)
    if n_free and chains:
        n_free = _ck.reduce_chains(levels, margin_lut, fixed, stack, n_free, wr, wb, _CHAIN_PASSES)
        for _ in range(_LADDER_ROUNDS if n_free >= _LADDER_ROUNDS_MIN else 1):
            if not (n_free and _LADDER_PASSES > 0):
                break
            n_free = _ladders.reduce_ladders(levels, margin_lut, fixed, stack, n_free, wr, wb, _LADDER_PASSES)
            if n_free and _CHAIN_PASSES_AFTER > 0:
                n_free = _ck.reduce_chains(levels, margin_lut, fixed, stack, n_free, wr, wb, _CHAIN_PASSES_AFTER)
    if n_free:
        # uniform 4-neighbourhood: the graph from the scalar weights, without the node map
        m_eff, ei, ej, ew = (_ck.free_graph4(levels, margin_lut, fixed, stack, n_free, wr, wb) if chains
                                 else _ck.free_graph(levels, margin_lut, wt, fixed, node, stack, n_free))
        fixed.reshape(-1)[stack[:n_free]] = _cut(m_eff, ei, ej, ew)[0]
    labels = fixed.view(np.uint8)
    e = float(_ck.energy_lut(levels, cost_lut, wt, labels)) if with_energy else math.nan
    return labels, e, int(n_free)


def graphcut_levels_labels(
    levels: NDArray[Any],
    cost_lut: NDArray[np.float64],
    *,
    beta: float,
    neighbourhood: int = 4,
    range_weight: float = 1.0,
) -> NDArray[np.uint8]:
    """Labels of :func:`solve_graphcut_levels` without the energy (the per-ping pipeline's path).

    Same labelling; skips the energy evaluation and, for ``uint8`` levels with a >= 256-entry
    table, the level range check (every level is a valid index).
    """
    lev = np.asarray(levels)
    lut = np.ascontiguousarray(cost_lut, dtype=np.float64)
    if not (_table_cut_applies(lev, lut, neighbourhood) and math.isfinite(float(lut.sum()))):
        return solve_graphcut_levels(levels, cost_lut, beta=beta, neighbourhood=neighbourhood,
                                     range_weight=range_weight).labels
    return _table_cut(lev, lut, _check_beta(beta), neighbourhood, float(range_weight))


def _table_cut_applies(lev: NDArray[Any], lut: NDArray[np.float64], neighbourhood: int) -> bool:
    """Whether :func:`_table_cut` takes these levels and table (the finiteness of the table aside)."""
    return (lev.ndim == 2 and lev.dtype == np.uint8 and lut.ndim == 2 and lut.shape[0] == 2 and lut.shape[1] >= 256
            and neighbourhood in (4, 8))


def _table_cut(lev: NDArray[np.uint8], lut: NDArray[np.float64], beta: float, neighbourhood: int,
               range_weight: float) -> NDArray[np.uint8]:
    """:func:`graphcut_levels_labels` of checked arguments (:func:`_table_cut_applies`, a finite
    C-contiguous float64 table, a finite ``beta >= 0``): the classification stage calls it with
    the finite tables of :func:`sonarmap.classify.segment.level_costs`."""
    h, w = lev.shape
    wt, wtot = _uniform(h, w, neighbourhood, beta, range_weight)
    return _graphcut_lut(np.ascontiguousarray(lev), lut, wt, wtot, with_energy=False, uniform=True)[0]


def solve_graphcut_levels(
    levels: ArrayLike,
    cost_lut: ArrayLike,
    *,
    beta: float = 1.0,
    neighbourhood: int = 4,
    weights: ArrayLike | None = None,
    range_weight: float = 1.0,
) -> MRFResult:
    """Exact binary graph cut when the unary depends on a pixel only through its level.

    ``unary[k, i, j] = cost_lut[k, levels[i, j]]`` (e.g. the negative log posterior of a fitted
    mixture on 256 quantisation levels); never materialises the ``(2, n_bins, n_beams)`` unary,
    which is what makes the per-ping pipeline fast.  Same result as :func:`solve_graphcut`.
    """
    lev = np.asarray(levels)
    if lev.ndim != 2 or lev.dtype.kind not in "iu":
        raise InputError(f"levels: expected a 2-D integer array, got {lev.dtype} {lev.shape}")
    lut = np.ascontiguousarray(cost_lut, dtype=np.float64)
    if lut.ndim != 2 or lut.shape[0] != 2:
        raise InputError(f"cost_lut: expected shape (2, n_levels), got {lut.shape}")
    if not np.isfinite(lut).all():
        raise InputError("cost_lut: contains NaN or infinite costs")
    if lev.size and (lev.min() < 0 or lev.max() >= lut.shape[1]):
        raise InputError(f"levels: values must lie in [0, {lut.shape[1] - 1}]")
    beta = _check_beta(beta)
    h, w = lev.shape
    if weights is None:
        if neighbourhood not in (4, 8):
            raise InputError(f"neighbourhood: must be 4 or 8 (got {neighbourhood})")
        wt, wtot = _uniform(h, w, neighbourhood, beta, float(range_weight))
    else:
        wt = _weights_for(np.empty((2, h, w)), beta, neighbourhood, weights)
        wtot = None
    labels, e, n_free = _graphcut_lut(np.ascontiguousarray(lev), lut, wt, wtot, uniform=weights is None)
    return MRFResult(labels=labels, energy=e, solver="graphcut", beta=beta,
                     neighbourhood=4 if wt.shape[0] == 2 else 8, n_iterations=1, n_free=n_free,
                     exact=True)


def solve_graphcut(
    unary: ArrayLike,
    *,
    beta: float = 1.0,
    neighbourhood: int = 4,
    weights: ArrayLike | None = None,
    reduce: bool = True,
) -> MRFResult:
    """Exact binary MAP labelling by s-t minimum cut (Greig, Porteous & Seheult 1989).

    Parameters
    ----------
    unary : ndarray, shape (2, n_bins, n_beams)
        Label costs.
    beta, neighbourhood, weights
        Potts weights (see :func:`pairwise_weights`); ``weights`` overrides ``beta``.
    reduce : bool
        Apply the exact persistency reduction before the cut (same result, much faster).
        Without it the full lattice graph is built from cached edge-index arrays.

    Returns
    -------
    MRFResult
        ``exact=True``; ``n_free`` = pixels that entered the graph.
    """
    u = _check_unary(unary)
    if u.shape[0] != 2:
        raise InputError(f"unary: graph cut is binary; got {u.shape[0]} labels (use 'expansion')")
    beta = _check_beta(beta)
    h, w = u.shape[1:]
    uniform = weights is None and neighbourhood in (4, 8)
    if uniform:
        wt, wtot = _uniform(h, w, neighbourhood, beta)
    else:
        wt = _weights_for(u, beta, neighbourhood, weights)
        wtot = None
    if reduce:
        labels, e, n_free = _graphcut_lut(_flat_levels(h, w), u.reshape(2, -1), wt, wtot, uniform=uniform)
    else:
        ei, ej, sel = _lattice_edges(h, w, wt.shape[0])
        cap = wt.ravel()[sel]
        keep = cap > 0
        x, _ = _cut((u[0] - u[1]).ravel(), ei[keep], ej[keep], cap[keep])
        labels = x.reshape(h, w).astype(np.uint8)
        n_free = h * w
        e = _energy(u, wt, labels)
    return MRFResult(
        labels=labels,
        energy=e,
        solver="graphcut",
        beta=beta,
        neighbourhood=4 if wt.shape[0] == 2 else 8,
        n_iterations=1,
        n_free=n_free,
        exact=True,
    )


def _init_labels(u: NDArray[np.float64], init: ArrayLike | None) -> NDArray[np.int32]:
    if init is None:
        return np.ascontiguousarray(u.argmin(axis=0).astype(np.int32))
    lab = np.array(init, dtype=np.int32)
    if lab.shape != u.shape[1:]:
        raise InputError(f"init: shape {lab.shape} does not match unary {u.shape[1:]}")
    if lab.min() < 0 or lab.max() >= u.shape[0]:
        raise InputError(f"init: labels must lie in [0, {u.shape[0] - 1}]")
    return np.ascontiguousarray(lab)


def solve_expansion(
    unary: ArrayLike,
    *,
    beta: float = 1.0,
    neighbourhood: int = 4,
    weights: ArrayLike | None = None,
    init: ArrayLike | None = None,
    max_cycles: int = 5,
) -> MRFResult:
    """alpha-expansion for Potts energies with any number of labels (Boykov et al. 2001).

    Starts from ``init`` (default: the unary minimum) and cycles over labels, accepting each
    exact expansion move that lowers the energy, until a full cycle makes no progress or
    ``max_cycles`` is reached.  For two labels the first move is already the exact optimum.
    """
    from sonarmap.classify._kernels import expansion_arrays

    u = _check_unary(unary)
    beta = _check_beta(beta)
    wt = _weights_for(u, beta, neighbourhood, weights)
    if u.shape[0] == 2 and init is None:
        res = solve_graphcut(u, weights=wt)
        return dataclasses.replace(res, solver="expansion", beta=beta)
    labels = _init_labels(u, init)
    e = _energy(u, wt, labels)
    h, w = u.shape[1:]
    cycles = 0
    for _ in range(max(1, int(max_cycles))):
        cycles += 1
        improved = False
        for alpha in range(u.shape[0]):
            c0, c1, ei, ej, cap = expansion_arrays(u, wt, labels, alpha)
            x, _ = _cut(c0 - c1, ei, ej, cap, np.zeros_like(cap))
            cand = np.where(x.reshape(h, w), np.int32(alpha), labels).astype(np.int32)
            e_new = _energy(u, wt, cand)
            if e_new < e - 1e-9 * max(1.0, abs(e)):
                labels, e, improved = cand, e_new, True
        if not improved:
            break
    return MRFResult(labels=labels.astype(np.uint8), energy=e, solver="expansion", beta=beta,
                     neighbourhood=4 if wt.shape[0] == 2 else 8, n_iterations=cycles,
                     n_free=h * w, exact=u.shape[0] == 2)


def solve_icm(
    unary: ArrayLike,
    *,
    beta: float = 1.0,
    neighbourhood: int = 4,
    weights: ArrayLike | None = None,
    init: ArrayLike | None = None,
    max_sweeps: int = 20,
) -> MRFResult:
    """Iterated conditional modes (Besag 1986): greedy raster sweeps to a local minimum."""
    from sonarmap.classify._kernels import icm

    u = _check_unary(unary)
    beta = _check_beta(beta)
    wt = _weights_for(u, beta, neighbourhood, weights)
    labels = _init_labels(u, init)
    sweeps = int(icm(u, wt, labels, int(max_sweeps)))
    return MRFResult(labels=labels.astype(np.uint8), energy=_energy(u, wt, labels), solver="icm", beta=beta,
                     neighbourhood=4 if wt.shape[0] == 2 else 8, n_iterations=sweeps,
                     n_free=labels.size)


def solve_anneal(
    unary: ArrayLike,
    *,
    beta: float = 1.0,
    neighbourhood: int = 4,
    weights: ArrayLike | None = None,
    init: ArrayLike | None = None,
    schedule: AnnealSchedule = AnnealSchedule(),
    seed: int = 0,
) -> MRFResult:
    """Simulated annealing with a Gibbs sampler (the paper's solver; Geman & Geman 1984).

    See :class:`AnnealSchedule` for the cooling schedule.  Deterministic for a given ``seed``.
    """
    from sonarmap.classify._kernels import anneal, icm

    u = _check_unary(unary)
    beta = _check_beta(beta)
    wt = _weights_for(u, beta, neighbourhood, weights)
    labels = _init_labels(u, init)
    anneal(u, wt, labels, schedule.temperatures(), int(seed) & 0x7FFFFFFF)
    sweeps = schedule.n_sweeps
    if schedule.icm_sweeps:
        sweeps += int(icm(u, wt, labels, schedule.icm_sweeps))
    return MRFResult(labels=labels.astype(np.uint8), energy=_energy(u, wt, labels), solver="anneal", beta=beta,
                     neighbourhood=4 if wt.shape[0] == 2 else 8, n_iterations=sweeps,
                     n_free=labels.size)


def solve(
    unary: ArrayLike,
    *,
    solver: Solver = "graphcut",
    beta: float = 1.0,
    neighbourhood: int = 4,
    weights: ArrayLike | None = None,
    **kwargs: Any,
) -> MRFResult:
    """Dispatch to a solver; ``"graphcut"`` with more than two labels uses alpha-expansion."""
    u = _check_unary(unary)
    if solver == "graphcut":
        if u.shape[0] == 2:
            return solve_graphcut(u, beta=beta, neighbourhood=neighbourhood, weights=weights, **kwargs)
        return solve_expansion(u, beta=beta, neighbourhood=neighbourhood, weights=weights, **kwargs)
    if solver == "expansion":
        return solve_expansion(u, beta=beta, neighbourhood=neighbourhood, weights=weights, **kwargs)
    if solver == "icm":
        return solve_icm(u, beta=beta, neighbourhood=neighbourhood, weights=weights, **kwargs)
    if solver == "anneal":
        return solve_anneal(u, beta=beta, neighbourhood=neighbourhood, weights=weights, **kwargs)
    raise InputError(f"solver: must be one of {', '.join(SOLVERS)} (got {solver!r})")


def segment_mrf(
    image: ArrayLike,
    fit: Any,
    *,
    beta: float = 2.0,
    neighbourhood: int = 4,
    contrast: bool = False,
    solver: Solver = "graphcut",
    n_levels: int = 256,
    range_weight: float = 0.25,
    object_prior_min: float = 0.2,
    speckle_eps: float = 0.0,
    **kwargs: Any,
) -> MRFResult:
    """MRF segmentation of a (pre-processed) image under a fitted mixture (eq. 17-18, 22).

    The defaults are the default pipeline's (:class:`sonarmap.classify.config.ClassifyConfig`):
    with them the labels are those of :func:`sonarmap.classify.segment.segment` (the pipeline's
    stage, which solves the same problem on a level lookup table); this function also returns the
    energy and accepts every solver's options.

    Parameters
    ----------
    image : ndarray, shape (n_bins, n_beams)
        Pre-processed intensities in [0, 1].
    fit : MixtureFit
        Fitted mixture giving ``decision_log_pmf()`` and ``class_prior()``.
    beta, neighbourhood, contrast, range_weight
        Pairwise model (see :func:`pairwise_weights`).
    object_prior_min, speckle_eps
        Unary model (see :func:`sonarmap.classify.segment.class_costs`).
    solver, **kwargs
        See :func:`solve`.
    """
    from sonarmap.classify.segment import class_costs
    from sonarmap.stats.mixture import quantize

    img = np.asarray(image, dtype=np.float32)
    levels = quantize(img, n_levels=n_levels)
    cost = class_costs(fit, object_prior_min=object_prior_min, speckle_eps=speckle_eps)
    u = np.ascontiguousarray(cost[:, levels])
    wt = pairwise_weights(img.shape, beta=beta, neighbourhood=neighbourhood, image=img, contrast=contrast,
                          range_weight=range_weight)
    return solve(u, solver=solver, beta=beta, neighbourhood=neighbourhood, weights=wt, **kwargs)
