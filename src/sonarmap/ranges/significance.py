"""Surface significance: is a tracked surface's echo brighter than the water column in front of it?

The classifier and the tracker decide where surfaces are on the normalised image; whether a
faint surface is real is decided here, on the raw samples, against the ping's own data.  A first
return's surface (the run of beams whose echoes touch, :func:`sonarmap.ranges.echoes.surface_runs`;
with ``jump_bins``, as the pipeline passes ``TrackConfig.jump_bins``, also neighbouring beams whose
leading edges lie within ``jump_bins`` of each other - the tracker's neighbour rule without its
contiguity half, so that a surface whose echo steps a few bins is tested whole, not as two pieces)
is compared with itself moved towards the sonar:

* its **statistic** ``S`` is the mean of the raw samples over its beams and the ``d`` samples from
  each beam's leading edge, ``d`` the surface's median echo depth (leading edge to last structure
  bin) clipped to 3-8 bins;
* its **null** is the same statistic with the whole surface shifted ``gap`` to ``gap + window - 1``
  bins towards the sonar: on every one of its beams, samples in front of that beam's first
  return - the water column the pipeline itself judged empty.  The shifted copies keep the
  surface's shape, length and depth, and lie in the same stretch of range, so the null carries
  whatever the data does: correlated samples, log-compressed samples, speckle of any family;
* the background's level changes with range, so the null's trend along the offset is Tukey's
  resistant line through the shifted copies' statistics (slope through the medians of the outer
  thirds, the median intercept), extrapolated to offset 0; ``z = (S - trend(0)) / (1.4826 MAD)``
  with the MAD of the copies about that line.  No background estimate enters: a recording-level
  calibration that absorbed a target which stays in the window (``sonarmap calibrate`` on a
  short recording) cannot hide that target's echo.

A surface with ``z`` below ``RangeConfig.surface_min_z`` (default 3.5) is not told apart from the
water column in front of it, and its returns are dropped: those beams report no first return.
The surfaces tracked behind it are not moved up - a first surface that fails often does so because
a nearer echo the classifier missed lies in its water column, and the surface behind it would be
further still from the true first surface - but stay in the products as further surfaces.
Surfaces of fewer than ``min_beams`` (3) beams - too few samples for the test to tell anything;
pieces of a surface the contiguity rule broke - and those with fewer than ``min_shifts`` offsets
in front (within a few bins of the first range bin) are not tested, and kept.

Why it is needed: after the normaliser's division by the level, the background of log-compressed
samples (ARIS) spreads wider with range - the spread of the raw samples stays about constant while
the level falls 2-3x over the window - so the far rows hold more bright speckle than the
background model expects, which the classifier and tracker can join into a surface (1-3 % of the
simulated empty ARIS pings; a few beams at the far end of the real ARIS frames).  Such surfaces
stand a few MADs at most above their water column, real ones far more (``docs/ranges.md``,
"Surface significance").

Only normalised pings are tested by the pipeline; a pre-processed ping (DIDSON: thresholded, its
water column mostly zeros) keeps its returns.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.ranges.echoes import Echoes

__all__ = ["surface_significance", "SIGNIFICANCE_GAP_BINS", "SIGNIFICANCE_WINDOW_BINS", "SIGNIFICANCE_MIN_SHIFTS",
           "SIGNIFICANCE_DEPTH_BINS", "SIGNIFICANCE_MIN_BEAMS"]

#: The null's offsets start this many bins in front of the surface (past its rising flank and the
#: halo that the main lobe spreads in front of a sloped surface).
SIGNIFICANCE_GAP_BINS = 10
#: ... and span this many offsets: enough for a stable median and MAD of correlated samples
#: (the normalisation's 5-bin multi-look: ~40 independent shifts).
SIGNIFICANCE_WINDOW_BINS = 200
#: A surface with fewer offsets in front of it (it starts within gap + this many bins of the
#: first range bin) is not tested.
SIGNIFICANCE_MIN_SHIFTS = 20
#: Surfaces of fewer beams are not tested.
SIGNIFICANCE_MIN_BEAMS = 3
#: The bins averaged from each leading edge: the surface's median echo depth, clipped to this.
SIGNIFICANCE_DEPTH_BINS = (3, 8)


def surface_significance(echoes: Echoes, first: ArrayLike, raw: ArrayLike, *,
                         touch_bins: float = 1.0, gap_bins: int = SIGNIFICANCE_GAP_BINS,
                         window_bins: int = SIGNIFICANCE_WINDOW_BINS,
                         min_shifts: int = SIGNIFICANCE_MIN_SHIFTS,
                         min_beams: int = SIGNIFICANCE_MIN_BEAMS,
                         jump_bins: float | None = None) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Per beam the significance ``z`` of its first return's surface against its water column.

    Parameters
    ----------
    echoes : Echoes
        The ping's echoes, with the first returns' final leading edges.
    first : array_like of int, shape (n_beams,)
        Per beam the echo index of its first return (-1: none), ``Tracks.first``.
    raw : array_like, shape (n_bins, n_beams)
        The ping's raw samples (linear or log-compressed, any scale).
    touch_bins : float
        The surfaces' contiguity rule (``TrackConfig.touch_bins``).
    gap_bins, window_bins, min_shifts, min_beams : int
        The null's offsets and the shortest surface tested (see the module notes).
    jump_bins : float, optional
        Also join neighbouring returns whose leading edges lie within this many bins into one
        surface (module notes); None: touching echoes only.

    Returns
    -------
    (ndarray of float64, ndarray of int64), each shape (n_beams,)
        ``z`` per beam (the same for all beams of a surface; NaN where the beam has no return or
        its surface was not tested) and the number of offsets the null had.

    Raises
    ------
    InputError
        If a shape or an option is wrong.
    """
    import sonarmap.ranges._significance_kernels as _sk

    img = np.ascontiguousarray(raw)
    if img.dtype.kind not in "fiu":
        img = np.ascontiguousarray(img, dtype=np.float32)
    sel = np.ascontiguousarray(first, dtype=np.int64)
    if img.ndim != 2:
        raise InputError(f"raw: expected (n_bins, n_beams), got shape {img.shape}")
    if sel.shape != (echoes.n_beams,) or img.shape[1] != echoes.n_beams:
        raise InputError(f"first: expected one echo index per beam ({echoes.n_beams}) of a {img.shape[1]}-beam "
                         f"image, got shape {sel.shape}")
    for key, v, lo in (("gap_bins", gap_bins, 1), ("window_bins", window_bins, 2), ("min_shifts", min_shifts, 2),
                         ("min_beams", min_beams, 1)):
        if isinstance(v, bool) or int(v) != v or v < lo:
            raise InputError(f"{key}: must be an integer >= {lo} (got {v!r})")
    if not (math.isfinite(float(touch_bins)) and touch_bins >= 0):
        raise InputError(f"touch_bins: must be a finite number >= 0 (got {touch_bins!r})")
    lo_d, hi_d = SIGNIFICANCE_DEPTH_BINS
    return _sk.surface_z(  # type: ignore[no-any-return]
        img, sel, echoes.edge_bin, echoes.start_bin, echoes.stop_bin, float(touch_bins), lo_d, hi_d, int(gap_bins),
        int(window_bins), int(min_shifts), int(min_beams), -1.0 if jump_bins is None else float(jump_bins))
