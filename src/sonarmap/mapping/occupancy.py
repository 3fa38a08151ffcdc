"""Probabilistic occupancy maps (Elfes 1989) in log-odds: a 2-D grid and a sparse 3-D voxel map.

Inverse sensor model from the detector's pD / pFA
-------------------------------------------------
Each beam of a ping is a sequence of pixels classified as object (above the operating threshold)
or not.  Treat the classification of the pixel covering a cell as the measurement ``z`` of that
cell's occupancy ``m``.  At the operating threshold the fitted mixture gives

* ``pD  = P(z = object | m = occupied)``  (detection probability),
* ``pFA = P(z = object | m = free)``      (false-alarm probability).

With a uniform prior the Bayes update of a cell's log-odds ``l = log(P(m) / (1 - P(m)))`` is

* the cell holding the return (``z = object``):  ``l += log(pD / pFA)``,
* cells the beam crossed before the return, or up to the maximum range when there is no return
  (``z = not object``):  ``l += log((1 - pD) / (1 - pFA))``,

and cells behind the return are not updated (occluded).  Given the range-bin size, ``pFA`` is
made per cell (``1 - (1 - pFA)^m`` over the ``m`` bins a ray crosses in a cell), and a hit is
discounted for the range error (the return leaves its surface's cell with probability
``1 - q``) and, with rays over the vertical aperture and ``elevation_ambiguity``, for the ``n``
cells of its elevation arc:
``l_hit = log(pD q / (pFA_cell + (1 - pFA_cell) pD ((1 - 1/n) q + (1 - q)/2)))`` (see
docs/mapping.md).  The pD to use is the pipeline's ``PingProducts.pd_range``, the detection
probability of the range measurement, or per beam ``BeamRanges.p_detect`` where that is finite;
the range error is each return's ``BeamRanges.sigma_m`` where finite, else the constant
``OccupancyConfig.range_sigma_bins``.  Both therefore vary per ray: a beam's ``pD`` sets its
hit and its misses, a return's ``sigma`` sets ``q`` of its hit.  So a confident detector (high
pD, low pFA) moves the map quickly, a poor one slowly, beam by beam - unlike fixed ``P(occ | hit) = 0.8``,
``P(occ | miss) = 0.3`` constants (``l_hit = logit 0.8``, ``l_miss = logit 0.3``), which are
available as :meth:`SensorModel.fixed` for comparison.  Log-odds are clamped to ``[l_min, l_max]``,
by default probabilities ``[0.001, 0.999]`` (``+-6.9``): room for a few pD/pFA updates (``l_hit``
~2.5, ``l_miss`` ~-2.7 on simulated DIDSON surveys) or 5-8 fixed-model updates.  OctoMap's
``[0.12, 0.97]`` (:data:`OCTOMAP_CLAMP_LOGODDS`) suit its weak ``+0.85 / -0.4`` increments and
dynamic scenes; with pD/pFA increments they let each ping overwrite a cell's history (measured in
docs/mapping.md).  Within one ping a cell is updated at most once, and a hit in any beam takes
precedence over misses of other beams crossing it.

Free space starts at the sonar's minimum range (nothing nearer is observed).  Rays lie in the
imaging plane (zero elevation); ``n_elevation > 1`` spreads each beam over the vertical aperture.

Storage
-------
Voxels live in hashed chunks of ``chunk_size**3`` (``chunk_size**2`` for the 2-D grid), created
only where rays pass: memory grows with the observed volume, not with the area's bounding box.
Ray traversal is the Amanatides-Woo voxel walk in a numba kernel
(:mod:`sonarmap.mapping._kernels`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.mapping.poses import SensorPoses
from sonarmap.mapping.register import (
    DEFAULT_APERTURE_RAD,
    PointCloud,
    _as_2d,
    _stack_field,
    elevation_samples,
    range_matrix,
)

__all__ = [
    "SensorModel",
    "pd_pfa_increments",
    "OccupancyConfig",
    "OccupancyMap",
    "OccupancyArray",
    "voxelize",
    "voxel_iou",
    "logit",
    "OCTOMAP_CLAMP_LOGODDS",
]

_P_EPS = 1e-4


def _per_ping(values: ArrayLike, n: int, name: str) -> NDArray[np.float64]:
    """A scalar or one value per ping as float64 ``(n,)``."""
    arr = np.asarray(values, dtype=np.float64)
    try:
        return np.broadcast_to(arr, (n,))
    except ValueError:
        raise InputError(f"{name}: shape {arr.shape} does not broadcast to ({n},) pings") from None


def _per_beam(values: ArrayLike | None, shape: tuple[int, int], name: str) -> NDArray[np.float64]:
    """Per-beam values as float64 ``(n_pings, n_beams)`` (all NaN when None)."""
    return _as_2d(values, shape, name, np.float64, np.nan)


def logit(p: ArrayLike) -> NDArray[np.float64]:
    """``log(p / (1 - p))``."""
    q = np.asarray(p, dtype=np.float64)
    return np.log(q) - np.log1p(-q)


#: OctoMap's clamping thresholds (probabilities 0.1192 and 0.971) as log-odds ``(l_min, l_max)``,
#: for :class:`OccupancyConfig` when a dynamic scene needs a map that forgets quickly.
OCTOMAP_CLAMP_LOGODDS: tuple[float, float] = (float(logit(0.1192)), float(logit(0.971)))


def pd_pfa_increments(
    pd: ArrayLike,
    pfa: ArrayLike,
    *,
    bins_per_cell: ArrayLike = 1.0,
    n_arc: ArrayLike = 1,
    range_sigma_bins: ArrayLike = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Log-odds increments ``(l_hit, l_miss)`` of the pD/pFA inverse sensor model (broadcasting).

    See :meth:`SensorModel.from_pd_pfa`; non-informative inputs give ``l_hit <= 0`` or
    ``l_miss >= 0`` (no error here).
    """
    d = np.clip(np.asarray(pd, dtype=np.float64), _P_EPS, 1 - _P_EPS)
    f = np.clip(np.asarray(pfa, dtype=np.float64), _P_EPS, 1 - _P_EPS)
    m = np.maximum(np.asarray(bins_per_cell, dtype=np.float64), 1.0)
    n = np.maximum(np.asarray(n_arc, dtype=np.float64), 1.0)
    sig = np.maximum(np.asarray(range_sigma_bins, dtype=np.float64), 0.0)
    f_cell = -np.expm1(m * np.log1p(-f))  # 1 - (1 - pfa)^m
    # a return stays in its surface's cell with probability q (Gaussian range error, E|e| =
    # sigma sqrt(2/pi), over a cell m bins long); the rest lands in a neighbour along the ray.
    # A free cell gets the hit when the surface is in another cell of the elevation arc at this
    # range (and stays there), or one cell nearer or farther and is displaced into it.
    q = np.clip(1.0 - sig * math.sqrt(2.0 / math.pi) / m, 0.05, 1.0)
    leak = np.minimum((1.0 - 1.0 / n) * q + 0.5 * (1.0 - q), 1.0)
    l_hit = np.log(d * q) - np.log(f_cell + (1.0 - f_cell) * d * leak)
    l_miss = np.log1p(-d) - np.log1p(-f_cell)
    return l_hit, l_miss


@dataclasses.dataclass(frozen=True)
class SensorModel:
    """Log-odds increments of the inverse sensor model.

    Parameters
    ----------
    l_hit : float
        Added to the cell holding a return (> 0).
    l_miss : float
        Added to cells crossed by the beam before its return (< 0).
    """

    l_hit: float
    l_miss: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.l_hit) and self.l_hit > 0):
            raise InputError(f"l_hit: must be a positive finite log-odds increment, got {self.l_hit}")
        if not (math.isfinite(self.l_miss) and self.l_miss < 0):
            raise InputError(f"l_miss: must be a negative finite log-odds increment, got {self.l_miss}")

    @classmethod
    def from_pd_pfa(
        cls, pd: float, pfa: float, *, bins_per_cell: float = 1.0, n_arc: int = 1, range_sigma_bins: float = 0.0
    ) -> SensorModel:
        """Inverse sensor model from the detector's pD and per-pixel pFA (see the module notes).

        ``pfa_cell = 1 - (1 - pfa) ** bins_per_cell`` (a ray crosses ``bins_per_cell`` range bins
        in one cell); ``l_miss = log((1 - pD) / (1 - pfa_cell))``;
        ``l_hit = log(pD q / (pfa_cell + (1 - pfa_cell) pD ((1 - 1/n_arc) q + (1 - q)/2)))``: with
        a range error of ``range_sigma_bins`` (Gaussian) a return stays in its surface's cell with
        probability ``q = 1 - range_sigma_bins sqrt(2/pi) / bins_per_cell`` and otherwise lands
        in one of the two neighbours along the ray; with ``n_arc`` cells on the return's
        elevation arc, a free cell also sees the return when the surface is in one of the other
        arc cells.  ``n_arc = bins_per_cell = 1``, ``range_sigma_bins = 0``
        give ``log(pD / pFA)`` and ``log((1 - pD) / (1 - pFA))``.  Probabilities are clipped to
        ``[1e-4, 1 - 1e-4]``.

        Raises
        ------
        InputError
            If the increments are not informative (``l_hit <= 0`` or ``l_miss >= 0``).
        """
        lh, lm = pd_pfa_increments(pd, pfa, bins_per_cell=bins_per_cell, n_arc=n_arc, range_sigma_bins=range_sigma_bins)
        if not (float(lh) > 0 and float(lm) < 0):
            raise InputError(
                f"pd/pfa: detection probability ({pd}) must exceed the false-alarm probability ({pfa}) "
                f"per cell ({bins_per_cell} bins) and arc ({n_arc} cells)"
            )
        return cls(float(lh), float(lm))

    @classmethod
    def fixed(cls, p_hit: float = 0.8, p_miss: float = 0.3) -> SensorModel:
        """Constant model ``P(occ | hit) = p_hit``, ``P(occ | miss) = p_miss`` (a common default)."""
        if not 0.5 < p_hit < 1 or not 0 < p_miss < 0.5:
            raise InputError(f"p_hit/p_miss: need 0.5 < p_hit < 1 and 0 < p_miss < 0.5, got {p_hit}, {p_miss}")
        return cls(float(logit(p_hit)), float(logit(p_miss)))


@dataclasses.dataclass(frozen=True)
class OccupancyConfig:
    """Options of :class:`OccupancyMap`.

    Parameters
    ----------
    resolution_m : float
        Cell edge length.
    dims : {2, 3}
        2 = grid in the world's horizontal (x, y) plane (rays projected onto it), 3 = voxels.
    chunk_size : int
        Cells per chunk edge (power of two, 2-256).
    l_min, l_max : float
        Log-odds clamping bounds; default probabilities 0.001 / 0.999, for static scenes (hulls,
        seafloor, structures): they leave room for a few pD/pFA updates so the map integrates
        evidence over the pings that see a cell.  Bounds narrower than ``l_hit`` / ``l_miss``
        make the last ping decide a cell; :data:`OCTOMAP_CLAMP_LOGODDS` are OctoMap's, for
        dynamic scenes.
    occupied_logodds : float
        Cells with log-odds above this are occupied (0 = probability 0.5).
    n_elevation : int
        Rays per beam across the vertical aperture (1 = imaging plane only).
    vertical_aperture_rad : float
        Vertical aperture spread over when ``n_elevation > 1``.
    elevation_ambiguity : bool
        With ``n_elevation > 1`` and the pD/pFA model: discount each hit for the ``n_arc`` cells
        its elevation arc spans, as if only one of them held the surface (a surface oblique to
        the vertical aperture, whose return could come from any elevation).  Default False: the
        surface spans the aperture at the return's range, so every ray of the arc hits it - the
        profiling geometry that the zero-elevation registration assumes (docs/mapping.md
        measures both).
    free_without_return : bool
        Carve free space to the maximum range along beams without a return.
    range_sigma_bins : float
        1-sigma range error of a return, in range bins, used by the pD/pFA model when
        ``range_resolution_m`` is given and the return has no finite ``sigma_m`` of its own: a
        return leaves its surface's cell for a neighbour along the ray with probability
        ``sigma sqrt(2/pi) / bins_per_cell``, which weakens the hit.
    max_chunks : int, optional
        Upper bound on allocated chunks (memory ~ ``8 * chunk_size**3`` bytes each); exceeding it
        raises :class:`InputError`.
    """

    resolution_m: float = 0.05
    dims: int = 3
    chunk_size: int = 16
    l_min: float = float(logit(0.001))
    l_max: float = float(logit(0.999))
    occupied_logodds: float = 0.0
    n_elevation: int = 1
    vertical_aperture_rad: float = DEFAULT_APERTURE_RAD
    elevation_ambiguity: bool = False
    free_without_return: bool = True
    range_sigma_bins: float = 1.0
    max_chunks: int | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution_m) and self.resolution_m > 0):
            raise InputError(f"resolution_m: must be positive, got {self.resolution_m}")
        if self.dims not in (2, 3):
            raise InputError(f"dims: must be 2 or 3, got {self.dims}")
        cs = int(self.chunk_size)
        if cs != self.chunk_size or cs < 2 or cs > 256 or cs & (cs - 1):
            raise InputError(f"chunk_size: must be a power of two in [2, 256], got {self.chunk_size}")
        if not self.l_min < self.occupied_logodds < self.l_max:
            raise InputError(f"l_min < occupied_logodds < l_max violated ({self.l_min}, {self.occupied_logodds}, {self.l_max})")
        if int(self.n_elevation) != self.n_elevation or self.n_elevation < 1:
            raise InputError(f"n_elevation: must be a positive integer, got {self.n_elevation}")
        if not (math.isfinite(self.range_sigma_bins) and self.range_sigma_bins >= 0):
            raise InputError(f"range_sigma_bins: must be finite and >= 0, got {self.range_sigma_bins}")
        if self.max_chunks is not None and self.max_chunks < 1:
            raise InputError(f"max_chunks: must be positive, got {self.max_chunks}")


@dataclasses.dataclass(frozen=True, eq=False)
class OccupancyArray:
    """A dense export of (part of) an occupancy map.

    Parameters
    ----------
    logodds : ndarray, shape (nx, ny[, nz]), float32
        Cell log-odds (0 where unobserved).
    observed : ndarray of bool, same shape
        Whether any ray reached the cell.
    origin_m : ndarray, shape (2,) or (3,)
        World coordinates of the minimum corner of cell ``[0, 0(, 0)]``.
    resolution_m : float
        Cell size.
    """

    logodds: NDArray[np.float32]
    observed: NDArray[np.bool_]
    origin_m: NDArray[np.float64]
    resolution_m: float

    @property
    def probability(self) -> NDArray[np.float32]:
        """Occupancy probability, NaN where unobserved."""
        p = (1.0 / (1.0 + np.exp(-self.logodds.astype(np.float64)))).astype(np.float32)
        p[~self.observed] = np.nan
        return p


def voxelize(points: ArrayLike, resolution_m: float, *, dims: int = 3) -> NDArray[np.int64]:
    """Unique cell indices ``floor(p / resolution)`` of points, shape (n, 3) (z = 0 when 2-D)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ijk = np.floor(p / resolution_m).astype(np.int64)
    if dims == 2:
        ijk[:, 2] = 0
    return np.unique(ijk, axis=0)


def _pack_ijk(ijk: NDArray[np.int64]) -> NDArray[np.int64]:
    o = 1 << 20
    return ((ijk[:, 0] + o) << 42) | ((ijk[:, 1] + o) << 21) | (ijk[:, 2] + o)


def voxel_iou(a_ijk: ArrayLike, b_ijk: ArrayLike) -> float:
    """Intersection over union of two sets of cell indices (n, 3)."""
    a = np.unique(_pack_ijk(np.asarray(a_ijk, dtype=np.int64).reshape(-1, 3)))
    b = np.unique(_pack_ijk(np.asarray(b_ijk, dtype=np.int64).reshape(-1, 3)))
    union = np.union1d(a, b).size
    return float(np.intersect1d(a, b, assume_unique=True).size / union) if union else 1.0


class _Rays(NamedTuple):
    """The rays of a batch of pings as :func:`sonarmap.mapping._kernels.integrate_rays` takes them."""

    starts: NDArray[np.float64]
    """Ray starts (n_rays, 3), in cells (z = 0 for the 2-D grid)."""
    ends: NDArray[np.float64]
    """Ray ends (n_rays, 3): the return, or the maximum range; in cells."""
    hits: NDArray[np.bool_]
    """Whether each ray ends at a return."""
    offsets: NDArray[np.int64]
    """Rays of ping ``i``: ``offsets[i]:offsets[i + 1]``."""
    l_hit: NDArray[np.float32]
    """Per ray, the log-odds increment of its return's cell."""
    l_miss: NDArray[np.float32]
    """Per ray, the log-odds increment of the cells it crosses."""


class OccupancyMap:
    """Sparse log-odds occupancy map (2-D grid or 3-D voxels) with hashed chunk storage.

    Parameters
    ----------
    config : OccupancyConfig, optional

    Examples
    --------
    >>> m = OccupancyMap(OccupancyConfig(resolution_m=0.05))
    >>> m.integrate(range_m, azimuth_rad, poses, pd=0.9, pfa=0.02,
    ...             min_range_m=2.25, max_range_m=11.25)              # doctest: +SKIP
    >>> cloud = m.to_point_cloud()                                     # doctest: +SKIP
    """

    def __init__(self, config: OccupancyConfig | None = None) -> None:
        from sonarmap.mapping import _kernels as k

        self.config = config or OccupancyConfig()
        cs = self.config.chunk_size
        b = int(round(math.log2(cs)))
        self._shifts = np.array([b, b, b if self.config.dims == 3 else 0], dtype=np.int64)
        self._vol = 1 << int(self._shifts.sum())
        self._k = k
        mx = self.config.max_chunks
        self._alloc(64 if mx is None else min(64, mx), 256)  # the pool never exceeds max_chunks
        self._next_id = 1
        #: Pings integrated.
        self.n_pings = 0
        #: Pings skipped because the pD/pFA of every beam were missing (NaN) or pD <= pFA and no
        #: fallback model was given.
        self.n_uninformative = 0

    # ------------------------------------------------------------------ storage
    def _alloc(self, n_chunks: int, capacity: int) -> None:
        self._chunk_keys = np.full(n_chunks, -1, dtype=np.int64)
        self._logodds = np.zeros(n_chunks * self._vol, dtype=np.float32)
        self._stamp = np.zeros(n_chunks * self._vol, dtype=np.int32)
        self._keys = np.full(capacity, -1, dtype=np.int64)
        self._slots = np.zeros(capacity, dtype=np.int32)
        self._counts = np.zeros(1, dtype=np.int64)

    def _grow(self) -> None:
        n = int(self._counts[0])
        pool = self._chunk_keys.size
        if n >= pool:
            new = pool * 2
            mx = self.config.max_chunks
            if mx is not None:
                if n >= mx:
                    raise InputError(
                        f"max_chunks: the map needs more than {mx} chunks "
                        f"({self.memory_bytes / 2**20:.0f} MiB); raise max_chunks or coarsen resolution_m"
                    )
                new = min(new, mx)
            keys = np.full(new, -1, dtype=np.int64)
            keys[:n] = self._chunk_keys[:n]
            self._chunk_keys = keys
            lo = np.zeros(new * self._vol, dtype=np.float32)
            lo[: n * self._vol] = self._logodds[: n * self._vol]
            st = np.zeros(new * self._vol, dtype=np.int32)
            st[: n * self._vol] = self._stamp[: n * self._vol]
            self._logodds, self._stamp = lo, st
        cap = self._keys.size
        while cap < 2 * (self._chunk_keys.size + 1):
            cap *= 2
        if cap != self._keys.size:
            self._keys, self._slots = self._k.rebuild_table(self._chunk_keys, n, cap)

    @property
    def n_chunks(self) -> int:
        """Allocated chunks in use."""
        return int(self._counts[0])

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the voxel pools and the hash table."""
        return int(self._logodds.nbytes + self._stamp.nbytes + self._keys.nbytes + self._slots.nbytes + self._chunk_keys.nbytes)

    # ------------------------------------------------------------------ updates
    def integrate(
        self,
        range_m: ArrayLike,
        azimuth_rad: ArrayLike,
        poses: SensorPoses,
        *,
        min_range_m: float | ArrayLike,
        max_range_m: float | ArrayLike,
        pd: float | ArrayLike | None = None,
        pfa: float | ArrayLike | None = None,
        model: SensorModel | None = None,
        range_resolution_m: float | None = None,
        sigma_m: ArrayLike | None = None,
        p_detect: ArrayLike | None = None,
    ) -> int:
        """Integrate a batch of pings.

        Parameters
        ----------
        range_m : array_like, shape (n_pings, n_beams) or (n_beams,)
            First-return range per beam, NaN = no return.
        azimuth_rad : array_like, shape (n_beams,) or (n_pings, n_beams)
        poses : SensorPoses
            Sensor -> world transforms (pings with invalid poses are skipped).
        min_range_m, max_range_m : float or array_like (n_pings,)
            Range window: free space starts at ``min_range_m``; beams without a return are free to
            ``max_range_m``.
        pd, pfa : float or array_like (n_pings,), optional
            Each ping's detection / false-alarm probability at the operating threshold; give
            these or ``model``.  Beams whose pD (``p_detect``, else the ping's ``pd``) or pFA is
            NaN, or has ``pD <= pFA`` (no information), use ``model`` when given, else are
            skipped; pings with no informative beam are counted in :attr:`n_uninformative`.
        model : SensorModel, optional
            A fixed inverse sensor model (used when ``pd``/``pfa`` are not given, and as the
            fallback for uninformative beams and pings).  It ignores ``sigma_m`` and ``p_detect``.
        range_resolution_m : float, optional
            Range-bin size.  When given, ``pfa`` is read as a per-pixel probability and turned
            into a per-cell one over the ``resolution_m / range_resolution_m`` bins a ray crosses
            in a cell, and returns without a finite ``sigma_m`` carry the range error
            ``OccupancyConfig.range_sigma_bins``; with ``n_elevation > 1`` and
            ``elevation_ambiguity`` hits are also discounted for the elevation arc (``n_arc`` =
            cells the arc spans at the ping's median return range).
            Without it, ``pd``/``pfa`` are used as per-cell probabilities directly and returns
            without a finite ``sigma_m`` have no range error.
        sigma_m : array_like, shape like ``range_m``, optional
            One-sigma range error of each return in metres (``BeamRanges.sigma_m``), used for
            that return's hit instead of ``range_sigma_bins``; NaN = no estimate (the fallback).
        p_detect : array_like, shape like ``range_m``, optional
            Per-beam detection probability (``BeamRanges.p_detect``), used for that beam's hit
            and misses instead of the ping's ``pd``; NaN = unknown (the fallback).

        Returns
        -------
        int
            Number of pings integrated.
        """
        r = range_matrix(range_m, poses)
        P, B = r.shape
        az = np.broadcast_to(np.asarray(azimuth_rad, dtype=np.float64), (P, B))
        rmin = np.broadcast_to(np.asarray(min_range_m, dtype=np.float64), (P,))
        rmax = np.broadcast_to(np.asarray(max_range_m, dtype=np.float64), (P,))
        l_hit, l_miss, informative = self._beam_increments(r, pd, pfa, model, range_resolution_m, sigma_m, p_detect)
        ping_informative = informative.any(axis=1)
        self.n_uninformative += int((~ping_informative & poses.valid).sum())
        ok = poses.valid & np.isfinite(rmin) & np.isfinite(rmax) & ping_informative
        if not ok.any():
            return 0
        sel = np.flatnonzero(ok)
        rays = self._rays(r[sel], az[sel], rmin[sel], rmax[sel], poses.rotation[sel], poses.translation_m[sel],
                          l_hit[sel], l_miss[sel], informative[sel])
        ids = np.arange(self._next_id, self._next_id + sel.size, dtype=np.int32)
        self._run(rays.starts, rays.ends, rays.hits, rays.offsets, rays.l_hit, rays.l_miss, ids)
        self._next_id += sel.size
        self.n_pings += sel.size
        return sel.size

    def _beam_increments(
        self,
        r: NDArray[np.float64],
        pd: float | ArrayLike | None,
        pfa: float | ArrayLike | None,
        model: SensorModel | None,
        range_resolution_m: float | None,
        sigma_m: ArrayLike | None,
        p_detect: ArrayLike | None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        """Per-beam ``(l_hit, l_miss, informative)``, each (n_pings, n_beams), of :meth:`integrate`:
        the pD/pFA model (``model`` the fallback of its uninformative beams), or ``model`` alone."""
        P, B = r.shape
        if pd is not None or pfa is not None:
            if pd is None or pfa is None:
                missing = "pfa" if pfa is None else "pd"
                raise InputError(f"{missing}: pd and pfa go together (a model is only the fallback of beams "
                                 "whose pD/pFA are missing); give both, or the model alone")
            l_hit, l_miss, informative = self._increments(
                r, _per_ping(pd, P, "pd"), _per_ping(pfa, P, "pfa"), range_resolution_m,
                _per_beam(sigma_m, (P, B), "sigma_m"), _per_beam(p_detect, (P, B), "p_detect"))
            if model is not None:  # fallback for beams whose pD/pFA are missing or uninformative
                l_hit = np.where(informative, l_hit, model.l_hit)
                l_miss = np.where(informative, l_miss, model.l_miss)
                informative = np.ones((P, B), dtype=bool)
        elif model is not None:
            l_hit = np.full((P, B), model.l_hit)
            l_miss = np.full((P, B), model.l_miss)
            informative = np.ones((P, B), dtype=bool)
        else:
            raise InputError("pd/pfa: give each ping's pD and pFA, or a fixed SensorModel")
        return l_hit, l_miss, informative

    def _rays(
        self,
        r: NDArray[np.float64],
        az: NDArray[np.float64],
        rmin: NDArray[np.float64],
        rmax: NDArray[np.float64],
        R: NDArray[np.float64],
        t: NDArray[np.float64],
        l_hit: NDArray[np.float64],
        l_miss: NDArray[np.float64],
        informative: NDArray[np.bool_],
    ) -> _Rays:
        """The rays of pings with ranges ``r`` (n_pings, n_beams) seen from the sensor poses ``R``,
        ``t``, in cell units, for :meth:`_run` (one per beam and elevation sample that updates the map)."""
        cfg = self.config
        P, B = r.shape
        elev = elevation_samples(cfg.n_elevation, cfg.vertical_aperture_rad)
        E = elev.size
        hit = np.isfinite(r) & (r > 0)
        # rays (P, B, E): direction in the sensor frame, then to the world
        ce, se = np.cos(elev), np.sin(elev)
        d = np.empty((P, B, E, 3))
        d[..., 0] = np.cos(az)[:, :, None] * ce
        d[..., 1] = np.sin(az)[:, :, None] * ce
        d[..., 2] = np.broadcast_to(se, (P, B, E))
        dw = np.einsum("pij,pbej->pbei", R, d)
        rend = np.where(hit, np.clip(r, rmin[:, None], rmax[:, None]), rmax[:, None])
        keep = (hit | cfg.free_without_return) & informative
        starts = t[:, None, None, :] + dw * rmin[:, None, None, None]
        ends = t[:, None, None, :] + dw * rend[:, :, None, None]
        hits = np.broadcast_to(hit[:, :, None], (P, B, E))
        keep3 = np.broadcast_to(keep[:, :, None], (P, B, E))
        counts = keep3.reshape(P, -1).sum(axis=1)
        starts = starts[keep3]
        ends = ends[keep3]
        hits = np.ascontiguousarray(hits[keep3])
        ray_hit = np.broadcast_to(l_hit.astype(np.float32)[:, :, None], (P, B, E))[keep3]
        ray_miss = np.broadcast_to(l_miss.astype(np.float32)[:, :, None], (P, B, E))[keep3]
        inv = 1.0 / cfg.resolution_m
        starts *= inv
        ends *= inv
        if cfg.dims == 2:
            starts[:, 2] = 0.0
            ends[:, 2] = 0.0
        offsets = np.zeros(P + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        return _Rays(starts, ends, hits, offsets, ray_hit, ray_miss)

    def _increments(
        self,
        r: NDArray[np.float64],
        pd: NDArray[np.float64],
        pfa: NDArray[np.float64],
        range_resolution_m: float | None,
        sigma_m: NDArray[np.float64],
        p_detect: NDArray[np.float64],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        """Per-beam ``(l_hit, l_miss, informative)``, each (n_pings, n_beams), of the pD/pFA model.

        A beam's pD is its ``p_detect`` where finite, else its ping's ``pd``; a return's range
        error is its ``sigma_m`` where finite, else ``range_sigma_bins`` bins (with a range-bin
        size) or none.  With all-NaN ``sigma_m`` / ``p_detect`` every beam of a ping gets the
        ping's increments.
        """
        cfg = self.config
        P, B = r.shape
        pdb = np.where(np.isfinite(p_detect), p_detect, pd[:, None])
        pfb = np.broadcast_to(pfa[:, None], (P, B))
        informative = np.isfinite(pdb) & np.isfinite(pfb) & (pdb > pfb)
        if range_resolution_m is None:
            m_bins, bin_m, sig_default = 1.0, cfg.resolution_m, 0.0  # a "bin" is a cell
        else:
            dr = float(range_resolution_m)
            m_bins, bin_m, sig_default = max(1.0, cfg.resolution_m / dr), dr, cfg.range_sigma_bins
        n_arc = np.ones((P, 1))
        if range_resolution_m is not None and cfg.n_elevation > 1 and cfg.elevation_ambiguity:
            hit_r = np.where(np.isfinite(r) & (r > 0), r, np.inf)
            k = (np.isfinite(hit_r)).sum(axis=1)
            srt = np.sort(hit_r, axis=1)
            r_med = np.where(k > 0, srt[np.arange(P), np.maximum(k - 1, 0) // 2], 0.0)
            n_arc = np.clip(np.ceil(r_med * cfg.vertical_aperture_rad / cfg.resolution_m), 1, cfg.n_elevation)[:, None]
        with np.errstate(invalid="ignore"):
            own = np.isfinite(sigma_m) & (sigma_m >= 0)
        sig_bins = np.where(own, np.where(own, sigma_m, 0.0) / bin_m, sig_default)
        l_hit, l_miss = pd_pfa_increments(np.where(informative, pdb, 0.9), np.where(informative, pfb, 0.1),
                                          bins_per_cell=m_bins, n_arc=n_arc, range_sigma_bins=sig_bins)
        # hits that carry no information (an elevation arc as wide as the range error's reach)
        # leave the return's cell unchanged; the beam's free space still counts
        informative &= l_miss < 0
        return np.maximum(l_hit, 0.0), l_miss, informative

    def _run(self, starts: Any, ends: Any, hits: Any, offsets: Any, l_hit: Any, l_miss: Any, ids: Any) -> None:
        first = 0
        while True:
            status = self._k.integrate_rays(
                starts, ends, hits, offsets, l_hit, l_miss, ids, first, self._shifts,
                float(self.config.l_min), float(self.config.l_max),
                self._keys, self._slots, self._chunk_keys, self._counts, self._logodds, self._stamp,
            )
            if status == -1:
                return
            if status == -2:
                raise InputError("poses: a ray leaves the representable map extent (+-2**20 chunks); check units")
            first = int(status)
            self._grow()

    def integrate_ranges(
        self,
        ranges: Sequence[Any],
        poses: SensorPoses,
        *,
        min_range_m: float,
        max_range_m: float,
        pd: ArrayLike | None = None,
        pfa: ArrayLike | None = None,
        model: SensorModel | None = None,
        range_resolution_m: float | None = None,
        use_sigma: bool = True,
        use_p_detect: bool = True,
    ) -> int:
        """Integrate :class:`sonarmap.ranges.BeamRanges` (one per ping, equal beam counts).

        Each return's ``sigma_m`` and each beam's ``p_detect`` feed the pD/pFA model where finite
        (see :meth:`integrate`); ``use_sigma=False`` / ``use_p_detect=False`` ignore them (the
        constant range error, the per-ping ``pd``).
        """
        ranges = list(ranges)
        if not ranges:
            return 0

        return self.integrate(
            np.stack([br.range_m for br in ranges]),
            np.stack([br.azimuth_rad for br in ranges]),
            poses,
            min_range_m=min_range_m,
            max_range_m=max_range_m,
            pd=pd,
            pfa=pfa,
            model=model,
            range_resolution_m=range_resolution_m,
            sigma_m=_stack_field(ranges, "sigma_m") if use_sigma else None,
            p_detect=_stack_field(ranges, "p_detect") if use_p_detect else None,
        )

    # ------------------------------------------------------------------ queries and export
    def _cells(self) -> tuple[NDArray[np.int64], NDArray[np.float32], NDArray[np.bool_]]:
        """All allocated cells: indices (n, 3), log-odds, observed flags."""
        n = self.n_chunks
        if n == 0:
            return np.zeros((0, 3), np.int64), np.zeros(0, np.float32), np.zeros(0, bool)
        coords = self._k.unpack_keys(self._chunk_keys[:n])  # (n, 3) chunk coordinates
        sx, sy, sz = (int(s) for s in self._shifts)
        local = np.arange(self._vol, dtype=np.int64)
        li = local >> (sy + sz)
        lj = (local >> sz) & ((1 << sy) - 1)
        lk = local & ((1 << sz) - 1)
        ijk = np.empty((n, self._vol, 3), dtype=np.int64)
        ijk[:, :, 0] = (coords[:, 0:1] << sx) + li
        ijk[:, :, 1] = (coords[:, 1:2] << sy) + lj
        ijk[:, :, 2] = (coords[:, 2:3] << sz) + lk
        lo = self._logodds[: n * self._vol]
        seen = self._stamp[: n * self._vol] != 0
        return ijk.reshape(-1, 3), lo, seen

    def occupied_cells(self, *, threshold_logodds: float | None = None) -> NDArray[np.int64]:
        """Indices (n, 3) of occupied cells (log-odds above the threshold; z index 0 in 2-D)."""
        thr = self.config.occupied_logodds if threshold_logodds is None else threshold_logodds
        ijk, lo, seen = self._cells()
        return ijk[seen & (lo > thr)]

    def observed_cells(self) -> NDArray[np.int64]:
        """Indices (n, 3) of every cell any ray reached."""
        ijk, _, seen = self._cells()
        return ijk[seen]

    def cell_centers(self, ijk: ArrayLike) -> NDArray[np.float64]:
        """World coordinates of cell centres (z = 0 for the 2-D grid)."""
        c = (np.asarray(ijk, dtype=np.float64) + 0.5) * self.config.resolution_m
        if self.config.dims == 2:
            c[..., 2] = 0.0
        return c

    def logodds_at(self, points: ArrayLike) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """Log-odds and observed flags of the cells containing ``points`` (n, 3)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ijk = np.floor(p / self.config.resolution_m).astype(np.int64)
        if self.config.dims == 2:
            ijk[:, 2] = 0
        out_l = np.zeros(ijk.shape[0], np.float32)
        out_s = np.zeros(ijk.shape[0], bool)
        self._k.lookup(ijk, self._shifts, self._keys, self._slots, self._logodds, self._stamp, out_l, out_s)
        return out_l, out_s

    def to_point_cloud(self, *, threshold_logodds: float | None = None) -> PointCloud:
        """Occupied cell centres as a point cloud (``confidence`` = occupancy probability)."""
        thr = self.config.occupied_logodds if threshold_logodds is None else threshold_logodds
        ijk, lo, seen = self._cells()
        m = seen & (lo > thr)
        prob = (1.0 / (1.0 + np.exp(-lo[m].astype(np.float64)))).astype(np.float32)
        n = int(m.sum())
        return PointCloud(
            self.cell_centers(ijk[m]), np.zeros(n, np.int64), np.full(n, -1, np.int32),
            np.full(n, np.nan, np.float32), prob, prob, np.zeros(n, np.float32),
        )

    def to_array(self, *, max_cells: int = 200_000_000) -> OccupancyArray:
        """Dense log-odds array over the bounding box of the observed cells.

        Raises
        ------
        InputError
            If the box would exceed ``max_cells`` cells (export a sub-region or coarsen instead).
        """
        ijk, lo, seen = self._cells()
        ijk, lo = ijk[seen], lo[seen]
        nd = self.config.dims
        res = self.config.resolution_m
        if ijk.shape[0] == 0:
            shape0 = (0,) * nd
            return OccupancyArray(np.zeros(shape0, np.float32), np.zeros(shape0, bool), np.zeros(nd), res)
        lo_c = ijk.min(axis=0)[:nd]
        hi_c = ijk.max(axis=0)[:nd]
        shape = tuple(int(v) for v in (hi_c - lo_c + 1))
        if math.prod(shape) > max_cells:
            raise InputError(f"max_cells: the dense grid {shape} has more than {max_cells} cells")
        arr = np.zeros(shape, np.float32)
        obs = np.zeros(shape, bool)
        idx = tuple((ijk[:, a] - lo_c[a]) for a in range(nd))
        arr[idx] = lo
        obs[idx] = True
        return OccupancyArray(arr, obs, lo_c.astype(np.float64) * res, res)
