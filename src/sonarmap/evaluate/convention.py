"""The range convention read on a simulated ping's recorded echoes, where the truth is known.

``docs/DESIGN.md`` defines a return's range on the echo as recorded: the first crossing of half
the echo's first peak, after smoothing along range over the pulse.  On speckled echoes that
crossing is itself a random quantity: the recorded echo's peak and flank are a few random samples,
however well a detector finds the echo.  :func:`recorded_edges_bins` measures how far it lies from
the physical surface when nothing else can go wrong: each beam's recorded samples are taken at
offsets from its *true* surface range, averaged over the ``2 half_beams + 1`` beams around (every
one aligned exactly, the multi-look a detector can at best pool), the background level in front of
the surface taken away, smoothed over ``max(pulse, 3)`` bins along range, and the convention's
crossing read on that profile.  No detection, association or alignment error enters: the spread
of these edges about the truth is the convention's own on the recorded echo.

It sits beside :mod:`sonarmap.evaluate.bound`: the Cramér-Rao bound says what the samples hold
about the surface's range *given the echo's expected shape*; this oracle says what the
convention's half-peak crossing, read on the same samples, carries.  ``python -m
sonarmap.evaluate --ranges --recorded`` prints its rows beside the pipeline's scores.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarmap._config import check_integer_argument
from sonarmap.errors import InputError

__all__ = ["recorded_edges_bins", "RECORDED_FRONT_BINS", "RECORDED_DEPTH_BINS"]

#: Bins in front of the true surface in each aligned profile (the first third is the background
#: level taken away).
RECORDED_FRONT_BINS = 18
#: Bins behind the true surface in each aligned profile (the echo's first peak is searched there).
RECORDED_DEPTH_BINS = 48
#: The front third of a profile: its background level (taken away), not searched for the peak.
_LEAD_BINS = RECORDED_FRONT_BINS // 3


def recorded_edges_bins(sim: Any, *, half_beams: int = 3, fraction: float = 0.5,
                        pulse_bins: int = 1) -> NDArray[np.float64]:
    """Per beam, the range convention's leading edge read on the recorded echoes aligned on the truth.

    Parameters
    ----------
    sim : SimResult
        A simulated ping with its sub-bin surface truth (``surface_range_m``).
    half_beams : int
        Beams on either side whose recorded echoes (each aligned on its own true range) are
        averaged with the beam's (0: the beam alone); beams without a truth surface are left out.
    fraction : float
        The convention's fraction of the first peak, in (0, 1).
    pulse_bins : int
        The pulse length in bins (the profile is smoothed over ``max(pulse_bins, 3)`` bins).

    Returns
    -------
    ndarray of float64, shape (n_beams,)
        The edge in fractional bins (the truth's units; NaN on beams without a truth surface or
        whose profile has no crossing).  ``edge - truth`` is the convention's error there.

    Examples
    --------
    >>> import dataclasses
    >>> from sonarmap import preset
    >>> from sonarmap.evaluate import preset_sim_configs
    >>> from sonarmap.simulate import scene_from_name, simulate_ping
    >>> g = preset("didson-hf")
    >>> quiet = dataclasses.replace(preset_sim_configs(g)[0], speckle=False)
    >>> sim = simulate_ping(scene_from_name("hull", geometry=g), g, config=quiet, seed=0)
    >>> truth = np.interp(sim.surface_range_m, g.range_m, np.arange(g.n_bins))
    >>> e = recorded_edges_bins(sim, half_beams=0)
    >>> bool(np.nanmax(np.abs(e - truth)) < 0.5)     # without speckle: on the surface
    True
    """
    check_integer_argument("half_beams", half_beams, 0)
    check_integer_argument("pulse_bins", pulse_bins, 1)
    if not 0.0 < float(fraction) < 1.0:
        raise InputError(f"fraction: must lie in (0, 1) (got {fraction})")
    truth_m = getattr(sim, "surface_range_m", None)
    if truth_m is None:
        raise InputError("sim: the simulated ping carries no surface truth (surface_range_m)")
    geom = sim.ping.geometry
    bins = np.arange(geom.n_bins, dtype=np.float64)
    truth = np.where(np.isfinite(truth_m), np.interp(truth_m, geom.range_m, bins), np.nan)
    profiles = _aligned_profiles(_recorded_intensity(sim), truth)
    out = np.full(truth.size, np.nan)
    has = np.flatnonzero(np.isfinite(truth))
    width = max(int(pulse_bins), 3)
    box = np.ones(width) / width
    for k, j in enumerate(has):
        mean = profiles[has[max(k - half_beams, 0): k + half_beams + 1]].mean(axis=0)
        mean = mean - mean[:_LEAD_BINS].mean()
        out[j] = truth[j] + _crossing(np.convolve(mean, box, mode="same"), float(fraction)) - RECORDED_FRONT_BINS
    return out


def _recorded_intensity(sim: Any) -> NDArray[np.float64]:
    """The recorded ping as received intensity: the receiver's mapping undone
    (:func:`sonarmap.simulate.level_intensity`; samples at full scale stay there)."""
    from sonarmap.simulate.render import level_intensity

    return level_intensity(sim.config, np.asarray(sim.ping.image, dtype=np.float64))


def _aligned_profiles(intensity: NDArray[np.float64], truth: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per beam, its column sampled (linearly) at offsets ``-RECORDED_FRONT_BINS ..
    RECORDED_DEPTH_BINS`` from its true range (NaN rows for beams without one; the column's end
    values beyond the image)."""
    offsets = np.arange(-RECORDED_FRONT_BINS, RECORDED_DEPTH_BINS + 1, dtype=np.float64)
    rows = np.arange(intensity.shape[0], dtype=np.float64)
    out = np.full((truth.size, offsets.size), np.nan)
    for j in np.flatnonzero(np.isfinite(truth)):
        out[j] = np.interp(truth[j] + offsets, rows, intensity[:, j])
    return out


def _crossing(profile: NDArray[np.float64], fraction: float) -> float:
    """The convention's crossing (fractional index) on ``profile``: the first peak behind the
    front third (:func:`sonarmap.simulate.render.first_peak_crossing`), NaN without one."""
    from sonarmap.simulate.render import first_peak_crossing

    x = first_peak_crossing(profile[_LEAD_BINS:], fraction)
    return _LEAD_BINS + x if math.isfinite(x) else math.nan
