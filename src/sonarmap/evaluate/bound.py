"""What a simulated ping's samples can say about its ranges: the Cramér-Rao bound of a leading edge.

The simulator draws each pixel's intensity around its expected value ``mu(r) = a e(r - s) +
b(r)``: the echo ``e`` (:attr:`SimResult.clean`, or the unclipped echo) moved by the surface's
range ``s`` and scaled by its unknown level ``a`` (1 at the truth), over the background ``b``
(:func:`sonarmap.simulate.background_mean_image`).  Single-look speckle makes the intensity
exponential with that mean, ``L`` looks a gamma of shape ``L``; the receiver records every sample
at or above full scale ``c`` as full scale (:func:`sonarmap.simulate.level_intensity` of 1).  A
sample so censored tells about its mean ``F_L(c / mu) / mu^2`` (``F_L``: :func:`censored_information`,
``L`` without clipping, ``1 - exp(-c / mu)`` for one look), and one beam's samples about
``(s, a)`` the 2 x 2 Fisher information

    J = sum_r F_L(c / mu) / mu^2 * g g^T,     g = (-a e'(r - s), e(r - s)),

whose information about ``s`` with ``a`` unknown is ``J_ss - J_sa^2 / J_aa`` (bins^-2): no
unbiased estimator of the range from that beam's samples has a standard deviation below its
inverse square root.  Surfaces are smooth across neighbouring beams: on a straight surface over
the ``2 k + 1`` beams around (its range and slope unknown, each beam's level its own) the beams'
own bounds combine by generalised least squares into the bound at the middle beam - with the
correlation of neighbouring beams' speckle, which the simulator's main lobe shares among them
(:func:`beam_correlation`: on the Oculus-like fan, whose beams are twice as wide as their
spacing, 0.74 between neighbours; independent beams would overstate what 7 of them know).

The bound is optimistic - what the samples hold, not what a detector reaches:

- the echo's shape along the beam is known (its level is not); a detector must also find the
  shape, and the half-peak convention of ``docs/DESIGN.md`` reads the level from the noisy
  echo itself;
- the receiver's threshold and 8-bit quantisation are ignored (each only loses information);
- with ``pool_beams`` the surface is straight across the window, and the beams' estimates are
  combined linearly (the best such combination of efficient per-beam estimates).

So a recall above the bound's attainable recall (:func:`attainable_recall`) cannot be reached on
those pings by any unbiased detector of one beam (or of the window); a detector far below it
leaves information unused.  :func:`oracle_shifts` is such a detector, given what the bound
assumes known: the maximum-likelihood shift of the expected echo on the recorded 8-bit samples
(threshold and quantisation included) - it reaches the bound on the simulator's pings.  ``python -m sonarmap.evaluate --ranges --bound`` prints it beside
the pipeline's scores.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap._config import check_integer_argument
from sonarmap.errors import InputError

__all__ = ["RangeBound", "censored_information", "shift_information", "beam_correlation", "range_bound",
           "attainable_recall", "oracle_shifts"]


@dataclasses.dataclass(frozen=True)
class RangeBound:
    """The Cramér-Rao bound of each beam's range (bins) on one simulated ping.

    Attributes
    ----------
    sd_bins : ndarray, shape (n_beams,)
        ``1 / sqrt(J)`` of the beam's own samples; NaN on beams without a truth surface.
    pooled_sd_bins : ndarray, shape (n_beams,)
        The same for a straight surface over the ``2 pool_beams + 1`` beams around (clipped at
        the fan's edges): the generalised-least-squares line's standard error at the beam, from
        the beams' own bounds and their speckle's correlation; NaN on beams without a truth
        surface.
    pool_beams : int
        Beams on either side in ``pooled_sd_bins``.
    """

    sd_bins: NDArray[np.float64]
    pooled_sd_bins: NDArray[np.float64]
    pool_beams: int


def censored_information(t: ArrayLike, looks: int = 1) -> NDArray[np.float64]:
    """``F_L(t)``: the Fisher information about its mean ``mu`` of one speckled sample censored at
    full scale, times ``mu^2``, for ``t = c / mu`` (``c`` the full-scale intensity).

    The sample is the mean of ``looks`` exponential intensities (a gamma of shape ``L``); at or
    above ``c`` only the fact is recorded.  ``F_L(inf) = L`` (no clipping); for one look
    ``F_1(t) = 1 - exp(-t)``; in general ``L^2 E[(U - 1)^2; U < t] + t^2 f(t)^2 / P(U >= t)`` for
    ``U`` the sample over its mean (density ``f``).

    Parameters
    ----------
    t : array_like
        Full scale over the expected intensity (>= 0; ``inf``: never clipped).
    looks : int
        Looks averaged per pixel (>= 1).

    Returns
    -------
    ndarray of float64, the shape of ``t``

    Examples
    --------
    >>> censored_information([np.inf, 1.0, 0.0]).round(4).tolist()   # 1 - exp(-t)
    [1.0, 0.6321, 0.0]
    >>> round(float(censored_information(np.inf, looks=6)), 9)
    6.0
    """
    from scipy.special import gammainc, gammaincc, gammaln

    check_integer_argument("looks", looks, 1)
    tt = np.asarray(t, dtype=np.float64)
    if np.isnan(tt).any() or (tt < 0).any():
        raise InputError("t: full scale over the expected intensity must be >= 0")
    L = float(looks)
    x = L * tt
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inner = (L + 1.0) / L * gammainc(L + 2.0, x) - 2.0 * gammainc(L + 1.0, x) + gammainc(L, x)
        log_f = L * math.log(L) + (L - 1.0) * np.log(tt) - x - gammaln(L)
        surv = gammaincc(L, x)
        tail = np.where((tt > 0) & np.isfinite(tt) & (surv > 0),
                        np.exp(2.0 * np.log(tt) + 2.0 * log_f - np.log(surv)), 0.0)
    return np.asarray(L * L * np.maximum(inner, 0.0) + tail, dtype=np.float64)


def shift_information(echo: ArrayLike, background: ArrayLike, looks: int = 1, *,
                      full_scale: float = math.inf, level_known: bool = False) -> NDArray[np.float64]:
    """Per beam, the Fisher information (bins^-2) of the samples about a shift of the echo along range.

    Parameters
    ----------
    echo : array_like, shape (n_bins, n_beams)
        The expected echo intensity (linear); its derivative along range is taken by central
        differences (one-sided at the ends).
    background : array_like, shape (n_bins, n_beams) or (n_bins,)
        The expected background intensity the speckle is drawn around (> 0).
    looks : int
        Independent looks averaged per pixel (1: exponential intensity).
    full_scale : float
        Intensity at and above which samples are recorded as full scale (default: never).
    level_known : bool
        Whether the echo's level is known; by default it is a second unknown (the information
        about the shift is then what remains after estimating it).

    Returns
    -------
    ndarray of float64, shape (n_beams,)

    Raises
    ------
    InputError
        If the shapes disagree, the arrays hold non-finite values, the background or full scale
        is not positive or ``looks < 1``.

    Examples
    --------
    An echo rising by its own level per bin over a flat background of 1, its level known: each
    rising bin adds ``(slope / mu)^2``.

    >>> import numpy as np
    >>> echo = np.array([[0.0], [0.0], [1.0], [2.0], [2.0]])
    >>> float(shift_information(echo, np.ones(5), level_known=True)[0])   # slopes .5, 1, .5 over mu 1, 2, 3
    0.5277777777777778
    """
    e = np.asarray(echo, dtype=np.float64)
    bg = np.asarray(background, dtype=np.float64)
    if e.ndim != 2 or e.shape[0] < 2:
        raise InputError(f"echo: expected shape (n_bins >= 2, n_beams), got {e.shape}")
    if bg.ndim == 1:
        bg = bg[:, None]
    if bg.ndim != 2 or bg.shape[0] != e.shape[0] or bg.shape[1] not in (1, e.shape[1]):
        raise InputError(f"background: shape {np.asarray(background).shape} does not match echo {e.shape}")
    if not (np.isfinite(e).all() and np.isfinite(bg).all()):
        raise InputError("echo, background: must be finite")
    if not (bg > 0).all():
        raise InputError("background: the expected background intensity must be > 0 everywhere")
    if not (isinstance(full_scale, int | float | np.floating) and full_scale > 0):
        raise InputError(f"full_scale: must be a positive intensity, got {full_scale!r}")
    e = np.maximum(e, 0.0)
    slope = np.gradient(e, axis=0)
    mu = e + bg
    w = censored_information(float(full_scale) / mu, looks) / mu**2
    j_ss = np.sum(w * slope * slope, axis=0)
    if level_known:
        return j_ss
    j_aa = np.sum(w * e * e, axis=0)
    j_sa = np.sum(w * slope * e, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(j_aa > 0, j_ss - j_sa * j_sa / j_aa, 0.0)
    return np.maximum(out, 0.0)


def beam_correlation(geometry: Any, config: Any, max_lag: int) -> NDArray[np.float64]:
    """Correlation of the speckled intensity of two beams ``d = 0 .. max_lag`` apart on an echo.

    The simulator's coherent main lobe (:func:`sonarmap.simulate.main_lobe_taps`, unit-sum taps
    ``t``) gives beam ``j`` the field ``sum_k sqrt(t[j - k]) a_k z_k`` of the azimuth cells'
    amplitudes ``a_k`` and circular Gaussian ``z_k``: on an even surface two beams ``d`` apart
    share the amplitude correlation ``g_d = sum_k sqrt(t_k t_{k+d})``, and their intensities
    ``g_d^2`` (any number of looks).  Zero at ``d > 0`` without speckle or with incoherent ghosts.
    The background's own speckle is independent between beams, so on a faint echo the correlation
    is lower: this is its upper end.

    Parameters
    ----------
    geometry : SonarGeometry
    config : SimulationConfig
    max_lag : int

    Returns
    -------
    ndarray of float64, shape (max_lag + 1,)
        ``[1, rho_1, ..., rho_max_lag]``.

    Examples
    --------
    >>> from sonarmap import preset
    >>> from sonarmap.simulate import simulation_config_for
    >>> g = preset("oculus-m750d-like")
    >>> beam_correlation(g, simulation_config_for(g), 2).round(2).tolist()
    [1.0, 0.78, 0.36]
    """
    from sonarmap.simulate import main_lobe_taps

    check_integer_argument("max_lag", max_lag, 0)
    rho = np.zeros(int(max_lag) + 1)
    rho[0] = 1.0
    config = config.resolved(geometry)
    taps = main_lobe_taps(geometry, config) if config.speckle and config.ghosts == "coherent" else None
    if taps is None:
        return rho
    a = np.sqrt(taps / taps.sum())
    for d in range(1, min(int(max_lag), a.size - 1) + 1):
        rho[d] = float(np.dot(a[:-d], a[d:])) ** 2
    return rho


def _pooled_sd(info: NDArray[np.float64], k: int, rho: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per beam, the standard error at the beam of the generalised-least-squares line through the
    estimates of the ``2 k + 1`` beams around (variances ``1 / info``, correlation ``rho`` by lag);
    beams without information are left out, ``inf`` where fewer than two remain (the beam's own
    bound where it is the one)."""
    m = info.size
    out = np.full(m, np.inf)
    for j in range(m):
        idx = np.array([i for i in range(max(0, j - k), min(m, j + k + 1)) if info[i] > 0], dtype=np.int64)
        if idx.size < 2:
            if idx.size == 1 and idx[0] == j:
                out[j] = 1.0 / math.sqrt(info[j])
            continue
        sd = 1.0 / np.sqrt(info[idx])
        lag = np.abs(idx[:, None] - idx[None, :])
        cov = sd[:, None] * sd[None, :] * np.where(lag < rho.size, rho[np.minimum(lag, rho.size - 1)], 0.0)
        x = np.stack([np.ones(idx.size), (idx - j).astype(np.float64)], axis=1)
        try:
            m_inv = np.linalg.inv(x.T @ np.linalg.solve(cov, x))
        except np.linalg.LinAlgError:
            continue
        out[j] = math.sqrt(max(float(m_inv[0, 0]), 0.0))
    return out


def range_bound(sim: Any, *, echo: ArrayLike | None = None, pool_beams: int = 3) -> RangeBound:
    """The Cramér-Rao bound of the first surface's range on each beam of a simulated ping.

    Parameters
    ----------
    sim : SimResult
        A ping of :func:`sonarmap.simulate.simulate_ping` (its ``config``, ``surface_range_m``
        and any ``ping.meta["gain_assist_db"]``, and its ``clean`` echo unless ``echo`` is given).
    echo : array_like, shape (n_bins, n_beams), optional
        The unclipped expected echo in the units of ``sim.clean`` (e.g. the same ping rendered
        with a far higher ``full_scale_db``, scaled back); by default ``sim.clean``, whose values
        above full scale are cut there (their samples then count as carrying no slope: a bound
        lower in information than the ping's).
    pool_beams : int
        Beams on either side sharing one straight surface in ``pooled_sd_bins``.

    Returns
    -------
    RangeBound

    Raises
    ------
    InputError
        If ``pool_beams`` is negative, ``echo`` has another shape or the ping carries no surface
        truth.

    Notes
    -----
    The information of a beam counts the whole beam: on a beam with a surface behind the first
    one (a hull behind fish, propeller blades behind the hub) the later echo's flanks add to it.
    """
    from sonarmap.simulate import level_intensity

    e, has = _echo_of(sim, echo, pool_beams)
    geometry = sim.ping.geometry
    bg, gain = _before_assist(sim)
    info = shift_information(e, bg, int(sim.config.looks), full_scale=float(level_intensity(sim.config, 1.0)) * gain)
    rho = beam_correlation(geometry, sim.config, 2 * int(pool_beams))
    with np.errstate(divide="ignore"):
        sd = np.where(has, 1.0 / np.sqrt(info), np.nan)
    psd = np.where(has, _pooled_sd(info, int(pool_beams), rho), np.nan)
    return RangeBound(sd_bins=sd, pooled_sd_bins=psd, pool_beams=int(pool_beams))


def _echo_of(sim: Any, echo: ArrayLike | None, pool_beams: int) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The expected echo of :func:`range_bound` and :func:`oracle_shifts` (``echo``, default
    ``sim.clean``) and the beams with a truth surface, with their arguments checked."""
    check_integer_argument("pool_beams", pool_beams, 0)
    truth = getattr(sim, "surface_range_m", None)
    if truth is None:
        raise InputError("sim: carries no surface_range_m (not a simulate_ping result)")
    shape = sim.ping.geometry.shape
    e = np.asarray(sim.clean if echo is None else echo, dtype=np.float64)
    if e.shape != shape:
        raise InputError(f"echo: shape {e.shape} does not match the ping's {shape}")
    return e, np.isfinite(np.asarray(truth, dtype=np.float64))


def _before_assist(sim: Any) -> tuple[NDArray[np.float64], float]:
    """The background image of a simulated ping in the units of its ``clean`` echo - before a
    gain assist scaled the received intensity down - and the factor that scaled it (1 without an
    assist; received intensities times it are in those units).  ``sim.config`` holds the reduced
    receiver gain, which the reverberation and noise scale with (the ring-down does not)."""
    from sonarmap.simulate import background_mean_image

    assist_db = float((sim.ping.meta or {}).get("gain_assist_db", 0.0))
    config = sim.config
    if assist_db > 0:
        config = config.replace(rx_gain_db=float(config.rx_gain_db) + assist_db)
    return background_mean_image(sim.ping.geometry, config), 10.0 ** (assist_db / 10.0)


def attainable_recall(sd_bins: ArrayLike, tol_bins: float) -> float:
    """Mean over beams of ``P(|e| <= tol_bins)`` for unbiased Gaussian errors ``e`` at the bound.

    Parameters
    ----------
    sd_bins : array_like
        Per-beam bounds (NaN entries are left out; ``inf``, a beam without information, counts 0).
    tol_bins : float
        The recall's tolerance (> 0).

    Returns
    -------
    float
        NaN when no beam is finite or infinite.

    Examples
    --------
    >>> round(attainable_recall([1.0, 0.5], 1.0), 4)   # 0.6827 and 0.9545
    0.8186
    """
    if not (isinstance(tol_bins, int | float | np.floating) and tol_bins > 0):
        raise InputError(f"tol_bins: must be a positive number, got {tol_bins!r}")
    sd = np.asarray(sd_bins, dtype=np.float64).ravel()
    sd = sd[~np.isnan(sd)]
    if sd.size == 0:
        return math.nan
    if (sd < 0).any():
        raise InputError("sd_bins: standard deviations must be >= 0")
    with np.errstate(divide="ignore"):
        z = np.where(sd > 0, float(tol_bins) / (sd * math.sqrt(2.0)), np.inf)
    return float(np.mean([math.erf(v) if math.isfinite(v) else 1.0 for v in z]))


def _cell_intensities(image: NDArray[Any], config: Any) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per recorded 8-bit sample, the received intensities ``[lo, hi)`` the simulator's receiver
    (:func:`sonarmap.simulate.render._receive`: rounding or floor to 8 bits, inverted by
    :func:`sonarmap.simulate.level_intensity`) maps to it: from 0 for the lowest value (threshold),
    to infinity for full scale."""
    from sonarmap.simulate import level_intensity

    k = np.rint(np.asarray(image, dtype=np.float64) * 255.0)
    half = 0.0 if config.quantization == "floor" else 0.5
    lo = np.where(k <= 0, 0.0, level_intensity(config, (k - half) / 255.0))
    hi = np.where(k >= 255, np.inf, level_intensity(config, (k + 1.0 - half) / 255.0))
    return lo, hi


def oracle_shifts(sim: Any, *, echo: ArrayLike | None = None, pool_beams: int = 3, max_shift_bins: float = 3.0,
                  step_bins: float = 0.05) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Range errors (bins) of a detector that knows each beam's expected echo: the maximum-likelihood
    shift of the echo on the recorded samples, per beam and shared by the ``2 pool_beams + 1``
    beams around.

    The likelihood is the simulator's own: each recorded 8-bit sample's cell of received intensity
    (:func:`_cell_intensities`) under gamma speckle of the ping's looks around ``echo(r - s) +
    background``.  The shift is searched on a grid of ``step_bins`` within ``+-max_shift_bins`` (an
    error cannot exceed it: on faint echoes the grid's edge flatters the one-beam figure).  What it
    knows - the echo's shape and level - no detector of real data knows; it shows that the bound
    is reached on the recorded pings, threshold and quantisation included.

    Parameters
    ----------
    sim : SimResult
    echo : array_like, optional
        The unclipped expected echo (as for :func:`range_bound`); default ``sim.clean``.
    pool_beams : int
        Beams on either side sharing the shift in the second result.
    max_shift_bins, step_bins : float
        The search grid.

    Returns
    -------
    one_beam, pooled : ndarray of float64
        Per beam with a truth surface (in beam order), the estimated shift of its echo - its
        range error, the echo being at the truth.

    Raises
    ------
    InputError
        If an option is out of range or ``echo`` has another shape.
    """
    from scipy.special import gammainc

    if not (max_shift_bins > 0 and 0 < step_bins <= max_shift_bins):
        raise InputError(f"max_shift_bins, step_bins: need 0 < step_bins <= max_shift_bins, got "
                         f"{max_shift_bins!r}, {step_bins!r}")
    e_all, has = _echo_of(sim, echo, pool_beams)
    geometry = sim.ping.geometry
    bg, gain = _before_assist(sim)
    lo, hi = _cell_intensities(sim.ping.image, sim.config)
    lo, hi = lo * gain, hi * gain  # in the echo's units (before any gain assist)
    looks = float(sim.config.looks)
    shifts = np.arange(-max_shift_bins, max_shift_bins + 0.5 * step_bins, step_bins)
    rows = np.arange(geometry.n_bins, dtype=np.float64)
    beams = np.flatnonzero(has)
    ll = np.zeros((geometry.n_beams, shifts.size))
    for j in beams:
        e = e_all[:, j]
        lit = np.flatnonzero(e > 1e-4 * e.max()) if e.max() > 0 else np.arange(geometry.n_bins)
        r0, r1 = max(int(lit[0]) - 8, 0), min(int(lit[-1]) + 9, geometry.n_bins)
        mu = np.stack([np.interp(rows[r0:r1] - s, rows, e) for s in shifts]) + bg[r0:r1, j]
        # (a full-scale sample's cell is open: P(I >= lo) = 1 - P(I < lo), gammainc(L, inf) = 1)
        p_lo = gammainc(looks, looks * lo[r0:r1, j] / mu)
        p_hi = gammainc(looks, looks * hi[r0:r1, j] / mu)
        ll[j] = np.log(np.maximum(p_hi - p_lo, 1e-300)).sum(axis=1)
    one = shifts[np.argmax(ll[beams], axis=1)]
    pooled = np.array([shifts[np.argmax(ll[max(0, j - pool_beams):j + pool_beams + 1][
        has[max(0, j - pool_beams):j + pool_beams + 1]].sum(axis=0))] for j in beams])
    return one, pooled
