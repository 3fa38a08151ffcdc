"""Constant-false-alarm-rate (CFAR) detectors: the peers' baselines.

Four detectors, each 1-D along range within every beam (the usual sonar/radar choice, and the
one of the sonar-SLAM peer) or 2-D over a rectangular window of range bins x beams:

``ca``  cell averaging: noise level ``Z`` = mean of all ``N`` training cells.
``so``  smallest-of: ``Z`` = the smaller of the leading (nearer) and lagging (farther) half means.
``go``  greatest-of: ``Z`` = the larger of the two half means.
``os``  ordered statistic: ``Z`` = the ``k``-th smallest training cell (Rohling 1983).

A cell under test ``y`` is a detection when ``y > alpha Z``.  The scale ``alpha`` follows from
the design false-alarm probability ``pfa`` for exponentially distributed (square-law) noise of
unknown level, which is what the background of the DIDSON intensities follows (paper eq. 19):

* CA: ``pfa = (1 + alpha/N)^(-N)``  =>  ``alpha = N (pfa^(-1/N) - 1)`` (closed form).
* SO, GO with ``n = N/2`` cells per half (Weiss 1982; Gandhi & Kassam 1988)::

      P_SO(alpha) = 2 sum_{k=0}^{n-1} C(n-1+k, k) (2 + alpha/n)^(-(n+k))
      P_GO(alpha) = 2 (1 + alpha/n)^(-n) - P_SO(alpha)

  (``Z`` the mean of a half); ``alpha`` is found by Brent's method (both are monotone).
* OS: ``pfa = prod_{i=0}^{k-1} (N - i) / (N - i + alpha)`` (``Z`` the k-th of N), solved the same way.

Guard cells on each side of the cell under test are excluded.  Near the ends of a beam the window
is truncated: CA uses the mean of the cells that exist, SO/GO fall back to the one half that
exists, OS takes the same quantile ``k/N`` of the available cells; ``alpha`` is kept at its design
value (so the false-alarm rate rises slightly at the ends).  Images containing zero noise level
(``Z = 0``) only detect cells strictly above zero.

The sonar-SLAM peer (McConnell et al., "bruce_slam") uses SO-CFAR, 40 training and 10 guard
cells, ``pfa = 0.1``: :data:`SONAR_SLAM`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.ping import as_image

__all__ = ["CFARConfig", "CFARResult", "SONAR_SLAM", "cfar", "cfar_alpha", "cfar_pfa", "CFAR_METHODS"]

CFAR_METHODS = ("ca", "so", "go", "os")
Method = Literal["ca", "so", "go", "os"]


@dataclasses.dataclass(frozen=True)
class CFARConfig:
    """CFAR detector settings.

    Attributes
    ----------
    method : {"ca", "so", "go", "os"}
    n_train : int
        Training cells ``N`` in total (half before, half after the cell; even).  For 2-D, the
        number of training *range* cells; the window spans ``2 * beam_train + 1`` beams.
    n_guard : int
        Guard cells in total (half each side; even).
    pfa : float
        Design probability of false alarm in (0, 1).
    rank : int, optional
        OS only: the order ``k`` (1-based) of the statistic; default ``round(3N/4)``.
    two_d : bool
        2-D window over beams as well.
    beam_train, beam_guard : int
        2-D only: training / guard beams on each side.
    """

    method: Method = "ca"
    n_train: int = 40
    n_guard: int = 10
    pfa: float = 0.1
    rank: int | None = None
    two_d: bool = False
    beam_train: int = 2
    beam_guard: int = 1

    def __post_init__(self) -> None:
        if self.method not in CFAR_METHODS:
            raise InputError(f"method: must be one of {', '.join(CFAR_METHODS)} (got {self.method!r})")
        if self.n_train < 2 or self.n_train % 2:
            raise InputError(f"n_train: must be an even number >= 2 (got {self.n_train})")
        if self.n_guard < 0 or self.n_guard % 2:
            raise InputError(f"n_guard: must be an even number >= 0 (got {self.n_guard})")
        if not 0.0 < self.pfa < 1.0:
            raise InputError(f"pfa: must lie in (0, 1) (got {self.pfa})")
        if self.rank is not None and not 1 <= self.rank <= self.n_train:
            raise InputError(f"rank: must lie in [1, n_train] (got {self.rank})")
        if self.beam_train < 0 or self.beam_guard < 0:
            raise InputError("beam_train/beam_guard: must be >= 0")

    @property
    def k(self) -> int:
        """OS rank (1-based)."""
        return self.rank if self.rank is not None else max(1, round(0.75 * self.n_train))

    @property
    def n_cells(self) -> int:
        """Training cells in the window (2-D: range x beam annulus)."""
        if not self.two_d:
            return self.n_train
        full = (self.n_train + self.n_guard + 1) * (2 * self.beam_train + 2 * self.beam_guard + 1)
        guard = (self.n_guard + 1) * (2 * self.beam_guard + 1)
        return full - guard


#: The sonar-SLAM peer's detector (SO-CFAR, 40 training, 10 guard, pFA 0.1).
SONAR_SLAM = CFARConfig(method="so", n_train=40, n_guard=10, pfa=0.1)


@dataclasses.dataclass(frozen=True, eq=False)
class CFARResult:
    """Detections of a CFAR detector.

    Attributes
    ----------
    mask : ndarray of bool, shape (n_bins, n_beams)
    threshold : ndarray of float32, shape (n_bins, n_beams)
        ``alpha * Z`` per cell.
    alpha : float
    config : CFARConfig
    """

    mask: NDArray[np.bool_]
    threshold: NDArray[np.float32]
    alpha: float
    config: CFARConfig

    @property
    def labels(self) -> NDArray[np.uint8]:
        """``mask`` as 0/1 labels."""
        return self.mask.astype(np.uint8)


def _p_so(alpha: float, n: int) -> float:
    t = 2.0 + alpha / n
    return 2.0 * sum(math.comb(n - 1 + k, k) * t ** (-(n + k)) for k in range(n))


def cfar_pfa(alpha: float, *, method: Method, n_train: int, rank: int | None = None) -> float:
    """False-alarm probability of a threshold scale ``alpha`` in exponential noise."""
    n_train = int(n_train)
    if method == "ca":
        return (1.0 + alpha / n_train) ** (-n_train)
    if method in ("so", "go"):
        n = n_train // 2
        pso = _p_so(alpha, n)
        return pso if method == "so" else 2.0 * (1.0 + alpha / n) ** (-n) - pso
    if method == "os":
        k = rank if rank is not None else max(1, round(0.75 * n_train))
        return math.prod((n_train - i) / (n_train - i + alpha) for i in range(k))
    raise InputError(f"method: must be one of {', '.join(CFAR_METHODS)} (got {method!r})")


@functools.lru_cache(maxsize=256)
def cfar_alpha(pfa: float, *, method: Method, n_train: int, rank: int | None = None) -> float:
    """Threshold scale ``alpha`` giving design ``pfa`` in exponential noise (see module notes)."""
    if not 0.0 < pfa < 1.0:
        raise InputError(f"pfa: must lie in (0, 1) (got {pfa})")
    if method == "ca":
        return n_train * (pfa ** (-1.0 / n_train) - 1.0)
    from scipy.optimize import brentq

    hi = 1.0
    while cfar_pfa(hi, method=method, n_train=n_train, rank=rank) > pfa:
        hi *= 2.0
        if hi > 1e12:  # pragma: no cover - pfa unreachable
            raise InputError(f"pfa: {pfa} is not reachable with this window")
    return float(brentq(lambda a: cfar_pfa(a, method=method, n_train=n_train, rank=rank) - pfa,
                        0.0, hi, xtol=1e-12, rtol=1e-12))


def _window_sums_1d(y: NDArray[np.float64], n_half: int, g_half: int) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Per cell: sum and count of the leading (nearer) and lagging (farther) training cells."""
    h = y.shape[0]
    c = np.zeros((h + 1,) + y.shape[1:])
    np.cumsum(y, axis=0, out=c[1:])
    idx = np.arange(h)
    lo0 = np.clip(idx - g_half - n_half, 0, h)
    lo1 = np.clip(idx - g_half, 0, h)
    hi0 = np.clip(idx + g_half + 1, 0, h)
    hi1 = np.clip(idx + g_half + 1 + n_half, 0, h)
    lead = c[lo1] - c[lo0]
    lag = c[hi1] - c[hi0]
    nlead = (lo1 - lo0).astype(np.float64)
    nlag = (hi1 - hi0).astype(np.float64)
    shape = (h,) + (1,) * (y.ndim - 1)
    return lead, nlead.reshape(shape), lag, nlag.reshape(shape)


def cfar(image: ArrayLike, *, config: CFARConfig = CFARConfig()) -> CFARResult:
    """Run a CFAR detector on an image.

    Parameters
    ----------
    image : ndarray, shape (n_bins, n_beams)
        Intensities (square-law; e.g. the raw or pre-processed DIDSON image).
    config : CFARConfig
        Detector, window and design pFA.

    Returns
    -------
    CFARResult
    """
    y = as_image(image).astype(np.float64)
    cfg = config
    n_half, g_half = cfg.n_train // 2, cfg.n_guard // 2
    n_cells = cfg.n_cells
    if cfg.two_d:
        # sum over the beam window first (training + guard beams), then along range as in 1-D
        y_beam = _beam_sum(y, cfg.beam_train + cfg.beam_guard)
        nb_full = _beam_count(y.shape[1], cfg.beam_train + cfg.beam_guard)
        y_guard = _beam_sum(y, cfg.beam_guard)
        nb_guard = _beam_count(y.shape[1], cfg.beam_guard)
    if cfg.method in ("ca", "so", "go"):
        if not cfg.two_d:
            lead, nlead, lag, nlag = _window_sums_1d(y, n_half, g_half)
        else:
            # leading/lagging halves of the range x beam annulus; the guard-range rows of the
            # training beams (beside the cell) are shared equally by both halves
            lead, nlead, lag, nlag = _window_sums_1d(y_beam, n_half, g_half)
            nlead = nlead * nb_full
            nlag = nlag * nb_full
            side = _range_box(y_beam, g_half) - _range_box(y_guard, g_half)
            nside = _range_count(y.shape[0], g_half) * (nb_full - nb_guard)
            lead = lead + 0.5 * side
            lag = lag + 0.5 * side
            nlead = nlead + 0.5 * nside
            nlag = nlag + 0.5 * nside
        with np.errstate(invalid="ignore", divide="ignore"):
            m_lead = np.where(nlead > 0, lead / np.maximum(nlead, 1e-300), np.nan)
            m_lag = np.where(nlag > 0, lag / np.maximum(nlag, 1e-300), np.nan)
        if cfg.method == "ca":
            z = (np.nan_to_num(m_lead) * nlead + np.nan_to_num(m_lag) * nlag) / np.maximum(nlead + nlag, 1)
            alpha = cfar_alpha(cfg.pfa, method="ca", n_train=n_cells)
        else:
            both = np.stack([m_lead, m_lag])
            z = np.nanmin(both, axis=0) if cfg.method == "so" else np.nanmax(both, axis=0)
            z = np.nan_to_num(z)
            n_eff = n_cells if n_cells % 2 == 0 else n_cells + 1
            alpha = cfar_alpha(cfg.pfa, method=cfg.method, n_train=n_eff)
    else:
        from scipy.ndimage import rank_filter

        fp = _os_footprint(cfg)
        k = cfg.k if not cfg.two_d else max(1, round(cfg.k / cfg.n_train * n_cells))
        # rank_filter pads with the reflected image at the ends (same quantile of available cells)
        z = rank_filter(y, rank=k - 1, footprint=fp, mode="reflect")
        alpha = cfar_alpha(cfg.pfa, method="os", n_train=n_cells, rank=k)
    thr = (alpha * z).astype(np.float32)
    mask = y > thr
    return CFARResult(mask=mask, threshold=thr, alpha=float(alpha), config=cfg)


def _beam_sum(y: NDArray[np.float64], half: int) -> NDArray[np.float64]:
    w = y.shape[1]
    c = np.zeros((y.shape[0], w + 1))
    np.cumsum(y, axis=1, out=c[:, 1:])
    j = np.arange(w)
    return c[:, np.clip(j + half + 1, 0, w)] - c[:, np.clip(j - half, 0, w)]


def _beam_count(w: int, half: int) -> NDArray[np.float64]:
    j = np.arange(w)
    return (np.clip(j + half + 1, 0, w) - np.clip(j - half, 0, w)).astype(np.float64)[None, :]


def _range_box(y: NDArray[np.float64], half: int) -> NDArray[np.float64]:
    h = y.shape[0]
    c = np.zeros((h + 1, y.shape[1]))
    np.cumsum(y, axis=0, out=c[1:])
    i = np.arange(h)
    return c[np.clip(i + half + 1, 0, h)] - c[np.clip(i - half, 0, h)]


def _range_count(h: int, half: int) -> NDArray[np.float64]:
    i = np.arange(h)
    return (np.clip(i + half + 1, 0, h) - np.clip(i - half, 0, h)).astype(np.float64)[:, None]


def _os_footprint(cfg: CFARConfig) -> NDArray[np.bool_]:
    n_half, g_half = cfg.n_train // 2, cfg.n_guard // 2
    rows = 2 * (n_half + g_half) + 1
    if not cfg.two_d:
        fp = np.ones((rows, 1), dtype=bool)
        fp[n_half:n_half + 2 * g_half + 1, 0] = False
        return fp
    bt, bg = cfg.beam_train, cfg.beam_guard
    cols = 2 * (bt + bg) + 1
    fp = np.ones((rows, cols), dtype=bool)
    fp[n_half:n_half + 2 * g_half + 1, bt:bt + 2 * bg + 1] = False
    return fp
