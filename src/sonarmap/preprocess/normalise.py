"""Background normalisation: one background distribution over the whole lattice, for any sonar.

The paper's per-ping model (eq. 19: a zero spike plus an exponential background) describes a
DIDSON's output, whose receiver thresholds the background so that ~60 % of the pixels are zero.
Other sonars deliver the background itself: ARIS raw samples are never zero and their
reverberation falls by ~3x over the window; Oculus images carry the sonar's own gain and a
brighter fan edge.  This module estimates that background level from the data and maps the
image into the domain the paper's model describes, which is what a DIDSON receiver does in
hardware:

1. **Level vs range** ``b(r)``: the lower quartile of each range row across the beams, median
   filtered over 5 bins along range, then smoothed in the log domain over ``n_bins / 16`` bins
   with the rows far above the curve left out together with their flanks, and the curve
   interpolated across rows so left out (a surface across most of a narrow fan - a hull seen
   head-on, a seabed - is not background, and its whole echo would otherwise raise the level
   under its peak and flatten it), except for the leading rows above it: the transmitter's
   ring-down at the start of the window stays background.  Across the rows left out the curve is
   the least-squares quadratic through the kept rows on either side (a straight line between the
   running means beside them is a chord of the convex level: above it under the surface).
   The level may rise at most ``max_rise`` (2x) above its minimum at nearer ranges: reverberation
   and noise fall with range (or stay flat under the sonar's TVG), so a surface that fills most
   beams over a range interval (a seabed) is not taken for background.
2. **Level vs beam** ``f(r, theta)``: the lower quartile of ``y / b(r)`` in blocks of
   ``n_bins / 16`` bins x ``max(16, n_beams / 16)`` beams relative to the median of the
   background blocks (those within twice the blocks' lower quartile), clipped to [0.5, 2] and
   bilinearly interpolated - the beam pattern's taper and range-dependent fan-edge brightening.
   The median of all the blocks would be a surface's when it fills most of them (a seabed on
   every beam behind its front): the water column in front would get a factor of 0.5 and be
   doubled in the measured image.  Each block row is then scaled so that its median across the
   beams is the median filter over 5 block rows of those medians along range: a surface across
   the fan fills one or two block rows and stands out from its neighbours - it is not a beam
   pattern (:func:`_without_range_bands`).
3. **Multi-look**: ``z = y / (b f)`` averaged over ``pool`` = 5 bins x 3 beams (the background of
   a single look is speckle; surfaces are coherent over a few bins and beams).
4. **Receiver threshold**: ``u = g max(z - t, 0)`` with ``t`` the background's 90th percentile
   and ``g`` putting the mean background excess at ``1 / 44.6`` (the DIDSON background scale of
   the paper's Table I, so that its 256-level quantisation resolves the background tail).  Both
   come from the lower half of each row, in the quarter of the rows with the lowest median -
   robust to surfaces on up to half the beams of a row and filling up to 3/4 of the rows - for an
   exponential tail of scale ``s`` above the median: ``q50 - q25 = s ln 1.5``,
   ``t = q50 + s ln 5``, mean excess ``s``.  Where that gain would put more than 1 % of the
   pixels at the top level (targets tens of dB above a weak or coarsely quantised background),
   ``g`` is lowered until 1 % reach it: a mixture cannot describe a clipped histogram.

The result is a zero spike (the pixels under the threshold) plus the excess of the background
over it - exponential for any background whose tail is (gamma, Rayleigh and K speckle all are) -
plus the objects: the paper's mixture, on every sonar.

Images that are already thresholded (>= ``thresholded_fraction`` of the pixels are zero: DIDSON,
many vendor displays) are left alone; the paper's calibrated pre-processing applies to them.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import threading

import numpy as np
from numpy.typing import NDArray

from sonarmap._config import check_field_names
from sonarmap.errors import InputError

__all__ = ["BackgroundLevel", "on_8bit_grid", "RecordingBackground", "estimate_background", "estimate_recording_background",
           "estimate_background_levels", "normalise_image", "BACKGROUND_MEAN", "expand_grid", "grid_weights", "input_gain", "suppress_sidelobes", "condition_image",
           "SIDELOBE_LEVEL_DB", "INPUT_GAIN_QUANTILE", "INPUT_GAIN_BELOW", "MIN_LEVEL_COUNTS"]

#: Mean of the background excess after normalisation (the DIDSON background's 1/lambda, Table I).
BACKGROUND_MEAN = 1.0 / 44.6
_ZERO = 0.5 / 255.0
#: Smallest background level (in 8-bit levels, the median over range of the estimated level) that
#: is normalised.  The level is an order statistic of each row: below 4 levels it moves in steps of
#: 25 % or more between rows, and dividing by it draws bands across the fan that the classifier
#: takes for surfaces (dark Rayleigh speckle of 2 levels gave a "surface" on every beam).  Such an
#: image is left as recorded - its background is the zero spike and the lowest levels of the
#: mixture (``PipelineConfig.fit.max_floor_levels``).  The real recordings' levels: ARIS 75-77, Oculus
#: 11-12 levels.
MIN_LEVEL_COUNTS = 4.0

#: Largest fraction of the normalised pixels at the top level (1.0): above it the gain is lowered.
MAX_SATURATED = 0.01


@dataclasses.dataclass(frozen=True, eq=False)
class BackgroundLevel:
    """What :func:`estimate_background` measured on one ping (or a recording).

    Attributes
    ----------
    applied : bool
        Whether the image is normalised (False for thresholded images and degenerate ones).
    reason : str
        ``"estimated"`` (normalised), ``"thresholded"`` (already has a zero spike: left alone),
        ``"degenerate"`` (the background level is zero or not finite in most rows: no estimate),
        ``"quantised"`` (8-bit data whose background level is below :data:`MIN_LEVEL_COUNTS`
        levels: the grid does not resolve it, left alone like a thresholded image).
    zero_fraction : float
        Fraction of pixels at the zero level of the raw image.
    level_by_bin : ndarray, shape (n_bins,), float32, or None
        Background level ``b(r)`` in raw intensity units.
    beam_factor : ndarray, shape (n_blocks_range, n_blocks_beam), float32, or None
        Block grid of ``f(r, theta)`` (median 1).
    range_dependence_db : float
        ``10 log10`` of the ratio of the 90th to the 10th percentile of ``b(r)``: how much the
        background changes over the window (~0 dB when the sonar applied TVG).
    floor : float
        Threshold ``t`` on the normalised, multi-looked scale.
    gain : float
        Factor ``g`` of the excess.
    """

    applied: bool
    reason: str
    zero_fraction: float
    level_by_bin: NDArray[np.float32] | None = None
    beam_factor: NDArray[np.float32] | None = None
    range_dependence_db: float = math.nan
    floor: float = math.nan
    gain: float = math.nan

    def to_dict(self) -> dict[str, object]:
        """JSON-compatible summary (scalars only)."""
        return {"applied": self.applied, "reason": self.reason, "zero_fraction": self.zero_fraction,
                "range_dependence_db": self.range_dependence_db, "floor": self.floor, "gain": self.gain}


#: Level (dB) under a range row's strongest echo below which an intensity is taken for that
#: echo's sidelobe leakage: receive arrays of multibeams are shaded to sidelobes of -25 to -30 dB.
SIDELOBE_LEVEL_DB = 25.0
#: :func:`input_gain` maps this quantile of the positive intensities to full scale ...
INPUT_GAIN_QUANTILE = 0.999
#: ... when it lies below this fraction of full scale (4 of the 256 quantisation levels).
INPUT_GAIN_BELOW = 4.0 / 256.0


def on_8bit_grid(img: NDArray[np.float32]) -> bool:
    """True when a sample of the image's positive values are all multiples of 1/255 (8-bit data:
    nothing below can change it, so the per-ping cost is one small sample)."""
    flat = img.ravel()
    step = max(flat.size // 4096, 1)
    if flat.dtype == np.float32 or flat.dtype == np.float64:
        import sonarmap.preprocess._kernels as _pk

        return bool(_pk.on_255_grid(flat, step))  # the same test in one pass, stopping at the first miss
    sample = flat[::step]
    pos = sample[sample > 0]
    if pos.size == 0:
        return True
    scaled = pos * np.float32(255.0)
    return bool(np.all(np.abs(scaled - np.rint(scaled)) < 1e-3))


def suppress_sidelobes(image: NDArray[np.floating], level_db: float = SIDELOBE_LEVEL_DB) -> NDArray[np.float32]:
    """Remove the sidelobe leakage of each range row's strongest echo (the paper's ghosting).

    A strong echo at range ``r`` (a multibeam's specular nadir return above all) reaches every beam
    through its sidelobes, at the same range: the arc at the minimum slant range across a
    bathymetric swath, in front of the off-nadir beams' own seabed.  Within a row, an intensity
    more than ``level_db`` under the row's maximum cannot be told from that leakage, so it is
    lowered to at most its beam's median (of the beam's positive intensities: the beam's own
    background, water column for most of its samples).

    8-bit images are never changed: their smallest positive value (1/255 of full scale) lies
    24.1 dB under the largest, inside the 25 dB default.  Only data with more dynamic range
    (Kongsberg water column in linear units, 16-bit or float images) can hold leakage.

    Parameters
    ----------
    image : ndarray, shape (n_bins, n_beams)
        Raw non-negative intensities; 0 means no sample.
    level_db : float
        The receive sidelobe level (dB under the main lobe, positive).

    Returns
    -------
    ndarray of float32
        The image, unchanged where nothing lies ``level_db`` under its row's maximum.
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2 or img.size == 0 or not level_db > 0 or on_8bit_grid(img):
        return img  # (8-bit data holds no value 25 dB under its row's maximum anyway)
    return _suppress_sidelobes(img, level_db)


def _suppress_sidelobes(img: NDArray[np.float32], level_db: float) -> NDArray[np.float32]:
    """:func:`suppress_sidelobes` of a non-empty 2-D float32 image that is not 8-bit data."""
    rowmax = img.max(axis=1, keepdims=True)
    floor = rowmax * np.float32(10.0 ** (-level_db / 10.0))
    leak = (img > 0) & (img < floor)
    if not leak.any():
        return img
    # each beam's median positive value (the lower middle one; np.nanmedian is 5x slower here)
    srt = np.sort(np.where(img > 0, img, np.inf), axis=0)
    cnt = np.count_nonzero(img > 0, axis=0)
    beam_bg = srt[np.maximum((cnt - 1) // 2, 0), np.arange(img.shape[1])]
    beam_bg = np.where(cnt > 0, beam_bg, 0.0).astype(np.float32)[None, :]
    return np.where(leak, np.minimum(img, beam_bg), img).astype(np.float32)


def input_gain(image: NDArray[np.floating]) -> tuple[NDArray[np.float32], float]:
    """An automatic input gain for images that leave most of the [0, 1] scale empty.

    The per-ping model quantises intensities into 256 levels of [0, 1] (eq. 8-10).  An image that
    is not 8-bit data and whose positive intensities have their 99.9th percentile below
    :data:`INPUT_GAIN_BELOW` of full scale (4 levels) would put nearly every pixel into the first
    few levels: Kongsberg water column, linear re the datagram's +63.5 dB full scale, has that
    percentile near +40 dB, i.e. at 0.005.  Such an image is multiplied by the gain that puts the
    percentile at 1 and clipped there (the brightest 0.1 % saturate), as a receiver's display
    gain would.  Any other image is returned unchanged with gain 0 dB (8-bit images, such as
    every DIDSON, ARIS and Oculus recording, always are).

    Parameters
    ----------
    image : ndarray, shape (n_bins, n_beams)
        Raw intensities, non-negative.

    Returns
    -------
    (ndarray of float32, float)
        The image and the gain applied, in dB (0 when unchanged).
    """
    img = np.asarray(image, dtype=np.float32)
    if img.size == 0 or on_8bit_grid(img):
        return img, 0.0  # 8-bit data: its levels are the sonar's own, keep them
    return _input_gain(img)


def _input_gain(img: NDArray[np.float32]) -> tuple[NDArray[np.float32], float]:
    """:func:`input_gain` of a non-empty float32 image that is not 8-bit data."""
    sample = img.ravel()[:: max(img.size // 65536, 1)]
    pos = sample[sample > 0]
    if pos.size == 0:
        return img, 0.0
    k = int(INPUT_GAIN_QUANTILE * (pos.size - 1))
    top = float(np.partition(pos, k)[k])
    if not 0.0 < top < INPUT_GAIN_BELOW:
        return img, 0.0
    g = 1.0 / top
    return np.minimum(img * np.float32(g), np.float32(1.0)).astype(np.float32), float(10.0 * math.log10(g))


def condition_image(image: NDArray[np.floating]) -> tuple[NDArray[np.float32], float]:
    """:func:`suppress_sidelobes` then :func:`input_gain` with the 8-bit test made once (the
    per-ping pipeline's first step); returns the image and the gain in dB."""
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2 or img.size == 0 or on_8bit_grid(img):
        return img, 0.0
    return _input_gain(_suppress_sidelobes(img, SIDELOBE_LEVEL_DB))


def _finite_zero_fraction(img: NDArray[np.float32]) -> tuple[bool, float]:
    """Whether every pixel of a non-empty 2-D image is finite, and the fraction at the zero level
    of 8-bit data (one pass, no image-sized temporaries)."""
    import sonarmap.preprocess._kernels as _pk

    finite, zeros = _pk.finite_and_zeros(np.ascontiguousarray(img, dtype=np.float32), np.float32(_ZERO))
    return bool(finite), float(zeros) / img.size


class _Work(threading.local):
    """Per-thread float32 work arrays by name and shape: the image-sized temporaries of one ping
    reused by the next (a fresh 0.7 MB Oculus-sized array costs ~180 page faults, ~0.4 ms, on
    every ping).  Nothing returned to a caller lives in them."""

    def __init__(self) -> None:
        self.arrays: dict[tuple[str, tuple[int, ...]], NDArray[np.float32]] = {}

    def get(self, name: str, shape: tuple[int, ...]) -> NDArray[np.float32]:
        key = (name, shape)
        arr = self.arrays.get(key)
        if arr is None:
            if len(self.arrays) >= 16:
                self.arrays.clear()
            arr = self.arrays[key] = np.empty(shape, dtype=np.float32)
        return arr


_WORK = _Work()


_Q10_90 = np.true_divide([10, 90], 100)


def _range_dependence_db(level: NDArray[np.floating]) -> float:
    """``10 log10`` of the 90th over the 10th percentile of a level profile."""
    from sonarmap.preprocess._kernels import percentiles_linear

    if level.size >= 2 and level.dtype in (np.float32, np.float64) and np.all(np.isfinite(level)):
        q10, q90 = percentiles_linear(np.ascontiguousarray(level), _Q10_90)  # = np.percentile(level, [10, 90])
    else:
        q10, q90 = np.percentile(level, [10, 90])
    return float(10 * np.log10(q90 / q10)) if q10 > 0 else math.inf


def _median(x: NDArray[np.floating]) -> float:
    """``float(np.median(x))`` of a non-empty array without NaN, by selection (no Python-level
    overhead of np.median: ~20 us a call)."""
    from sonarmap.preprocess._kernels import median_inplace

    return float(median_inplace(np.array(x).ravel(), x.size))


#: Row length from which np.partition beats np.sort for a row's median and lower quartile (numpy
#: 2.4, AVX-512: np.sort's vectorised kernels sort rows of up to 512 values in one network, 2x
#: faster than partitioning them twice; 640-768 values 10 % faster, 1024 as fast) ...
_PARTITION_MIN = 1024


def _row_quartile(img: NDArray[np.float32]) -> NDArray[np.float32]:
    """The lower quartile of each row of ``max(img, 0)``: by counting the levels of 8-bit data
    (ARIS, Oculus: 2-3x faster than sorting the rows), else by sorting (the same order statistic)."""
    return _row_quartile_grid(img)[0]


def _row_quartile_grid(img: NDArray[np.float32]) -> tuple[NDArray[np.float32], bool]:
    """:func:`_row_quartile` and whether the count found the image to be the readers' 8-bit data
    (every positive value a level times ``float32(1 / 255)``): then ``on_8bit_grid(img)`` is True
    without a test of its own (False: not known)."""
    from sonarmap.preprocess._kernels import row_quartile_scaled

    k = (img.shape[1] - 1) // 4
    out, ok, scaled = row_quartile_scaled(np.ascontiguousarray(img), k)
    if ok:
        return out, bool(scaled)
    rows = np.maximum(img, 0.0)
    rows.sort(axis=1)  # np.sort's vectorised kernels beat np.partition along these short rows
    return rows.take(k, axis=1), False


def _block_factor(img: NDArray[np.float32], level: NDArray[np.float32]) -> NDArray[np.float32]:
    """Step 2: the beam factor grid of ``img / level[:, None]`` (see the module docstring)."""
    from sonarmap.preprocess._kernels import QUARTILE_BUCKETS, block_quartiles

    n, m = img.shape
    br = max(n // 16, 16)
    bc = max(m // 16, 16)
    nr, nc = max(n // br, 1), max(m // bc, 1)
    br, bc = n // nr, m // nc
    # each block's lower quartile, selected exactly in one kernel (the ratio computed on the way,
    # no image-sized temporary)
    k = (br * bc - 1) // 4
    grid = block_quartiles(np.ascontiguousarray(img), np.ascontiguousarray(level, dtype=np.float32), nr, nc, br, bc,
                           k, _WORK.get("blocks", (nc, br * bc)), np.empty((4, QUARTILE_BUCKETS), np.int64)).reshape(nr, nc)
    if not np.all(np.isfinite(grid)):
        return np.ones((nr, nc), dtype=np.float32)
    med = _background_median(grid)
    if not med > 0:
        return np.ones((nr, nc), dtype=np.float32)
    grid = _without_range_bands(grid / med)
    # beam-pattern and fan-edge effects are a few dB; a block-filling surface is not background
    return np.clip(grid, 0.5, 2.0).astype(np.float32)


def _without_range_bands(grid: NDArray[np.float32]) -> NDArray[np.float32]:
    """The beam-factor grid with each block row scaled so that its median across the beams is the
    median filter over 5 block rows (along range) of those medians (grids of at least 5 rows whose
    block rows' medians are all positive; others unchanged).

    A surface that spans the fan at one range (a seabed band, a hull seen head-on) fills one or
    two block rows on every beam: their lower quartiles are those of the surface's echo, 1.15-1.25
    times the background on the simulated ARIS 3000 seafloor (log-compressed samples: +3 dB), and
    the factor would raise the background there - the seafloor's measured profile flattened, its
    half-peak leading edges ~1 bin early.  The level ``b(r)`` carries the dependence on range, so
    a block row whose median stands out from its neighbours' is such a band; the median filter
    removes a bump one or two block rows wide and keeps a step (a seabed that fills the window to
    its end, whose rows the level's rise limit keeps from being background).  The pattern across
    the beams within a block row is kept.  Every block row is filtered, not only those that stand
    out: a hull across the fan raises two block rows by 6 % (simulated ARIS 3000), within the
    few per cent by which the rows' medians scatter on the real ARIS frames (0.95-1.07) - no
    threshold tells them apart, and the median of 5 leaves a row within that scatter of its
    neighbours."""
    from sonarmap.preprocess._kernels import median5

    if grid.shape[0] < 5:
        return grid
    rows = np.median(grid, axis=1).astype(np.float32)
    if not np.all(rows > 0):
        return grid
    return grid * (median5(rows) / rows)[:, None]


#: A block of the beam-factor grid more than this times the grid's lower quartile holds a surface,
#: not background (the factor's own range is [0.5, 2]: beam-pattern effects of a few dB).
BACKGROUND_BLOCK_RATIO = 2.0


def _background_median(grid: NDArray[np.float32]) -> float:
    """The median of the grid's background blocks: those at most :data:`BACKGROUND_BLOCK_RATIO`
    times the grid's lower quartile (its ``(n - 1) // 4``-th smallest value); the median of all
    the blocks where none is above that.

    The level ``b(r)`` makes a background block's value about 1 whatever the range, so the
    background blocks form the grid's lower cluster, and a surface's blocks lie above it however
    many of them there are (up to three quarters of the grid)."""
    flat = grid.ravel()
    k = (flat.size - 1) // 4
    q25 = float(np.partition(flat, k)[k])
    background = flat[flat <= BACKGROUND_BLOCK_RATIO * q25]
    return _median(background if background.size else grid)


@functools.lru_cache(maxsize=64)
def grid_weights(n: int, nb: int) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float32]]:
    """:func:`expand_grid`'s bilinear weights along one axis, ``(i0, i1, f)`` (read-only, cached):
    sample ``k`` of ``n`` lies a fraction ``f[k]`` of the way from block centre ``i0[k]`` to
    ``i1[k]`` of ``nb`` blocks (edges held: ``f`` is 0 or 1 beyond the outer centres)."""
    x = np.clip((np.arange(n) + 0.5) * nb / n - 0.5, 0, nb - 1)
    i0 = np.minimum(x.astype(np.intp), max(nb - 2, 0))
    i1 = np.minimum(i0 + 1, nb - 1)
    f = (x - i0).astype(np.float32)
    for a in (i0, i1, f):
        a.setflags(write=False)
    return i0, i1, f


def expand_grid(grid: NDArray[np.float32], shape: tuple[int, int], *,
                out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """Bilinear interpolation of a block grid to the full lattice (block centres; edges held).

    Separable, from the two neighbouring block centres along each axis, in elementwise float32
    arithmetic: the result does not depend on the BLAS library or its thread count (a product
    with dense interpolation matrices did, in the last bit).  ``out`` (float32, C-contiguous, of
    ``shape``) receives the result when given.
    """
    from sonarmap.preprocess._kernels import interpolate_rows, interpolate_rows_into

    cols, r0, r1, fr = _grid_rows(grid, shape)
    if out is None:
        return interpolate_rows(cols, r0, r1, fr)
    interpolate_rows_into(cols, r0, r1, fr, out)
    return out


def _grid_rows(grid: NDArray[np.float32], shape: tuple[int, int]
               ) -> tuple[NDArray[np.float32], NDArray[np.intp], NDArray[np.intp], NDArray[np.float32]]:
    """:func:`expand_grid`'s first step: ``(cols, r0, r1, fr)``, the grid interpolated across
    the beams (``(n_block_rows, shape[1])``, C-contiguous) and the weights of its rows along range:
    the lattice is ``interpolate_rows(cols, r0, r1, fr)``."""
    from sonarmap.preprocess._kernels import interpolate_rows

    g = np.ascontiguousarray(grid, dtype=np.float32)
    c0, c1, fc = grid_weights(shape[1], g.shape[1])
    cols = interpolate_rows(np.ascontiguousarray(g.T), c0, c1, fc).T  # across beams on the small grid
    return (np.ascontiguousarray(cols), *grid_weights(shape[0], g.shape[0]))


_ONE_BLOCK = np.ones((1, 1), dtype=np.float32)


def estimate_background(
    image: NDArray[np.floating], *, thresholded_fraction: float = 0.2, floor_quantile: float = 0.9,
    pool: tuple[int, int] = (5, 3), max_rise: float = 2.0, reference: RecordingBackground | None = None,
) -> tuple[BackgroundLevel, NDArray[np.float32] | None]:
    """Estimate the background level of one ping and return it with the normalised image.

    Parameters
    ----------
    image : ndarray, shape (n_bins, n_beams)
        Raw intensities (any non-negative scale).
    thresholded_fraction : float
        An image with at least this fraction of zero pixels is taken as already thresholded
        and is not normalised.
    floor_quantile : float
        Quantile of the normalised, multi-looked *background* used as the receiver threshold ``t``
        (``t = q50 + s ln(0.5 / (1 - floor_quantile))`` for an exponential tail of scale ``s``).
    pool : (int, int)
        Multi-look box (range bins, beams).
    max_rise : float
        The level may rise at most this factor above its minimum at nearer ranges (0 = off).
    reference : RecordingBackground, optional
        A recording-level estimate (:func:`estimate_recording_background`, ``sonarmap
        calibrate``): its level and beam factor replace the ping's own (``reason``
        ``"calibration"``); the threshold and gain stay per ping.  Its shape must match.

    Returns
    -------
    (BackgroundLevel, ndarray or None)
        The estimate and the normalised image (float32 in ``[0, 1]``), or None when the image
        is not normalised (``applied`` False).

    Notes
    -----
    Generalises the paper's background model (sec. IV, eq. 19) from a calibrated open-water set
    to the data of the ping itself; see the module docstring.
    """
    return estimate_background_levels(image, thresholded_fraction=thresholded_fraction, floor_quantile=floor_quantile,
                                      pool=pool, max_rise=max_rise, reference=reference)[:2]


def estimate_background_levels(
    image: NDArray[np.floating], *, n_levels: int = 256, thresholded_fraction: float = 0.2, floor_quantile: float = 0.9,
    pool: tuple[int, int] = (5, 3), max_rise: float = 2.0, reference: RecordingBackground | None = None,
) -> tuple[BackgroundLevel, NDArray[np.float32] | None, NDArray[np.uint8] | None]:
    """:func:`estimate_background` and the quantisation levels of the normalised image, made in the
    same pass over it.

    Parameters
    ----------
    image : ndarray, shape (n_bins, n_beams)
        Raw intensities (any non-negative scale).
    n_levels : int
        Quantisation levels (:func:`sonarmap.stats.mixture.quantize`, round binning).
    thresholded_fraction, floor_quantile, pool, max_rise, reference
        As in :func:`estimate_background`.

    Returns
    -------
    (BackgroundLevel, ndarray or None, ndarray of uint8 or None)
        The estimate, the normalised image and ``quantize(normalised, n_levels)`` - None when the
        image is not normalised, for more than 256 levels or where a normalised value is not
        finite (``quantize`` refuses it).
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2 or img.size == 0:
        raise InputError(f"image: expected a non-empty (n_bins, n_beams) array, got shape {img.shape}")
    finite, zero_fraction = _finite_zero_fraction(img)
    if not finite:
        raise InputError("image: contains NaN or infinite values")
    if not 0 < thresholded_fraction <= 1:
        raise InputError(f"thresholded_fraction: must lie in (0, 1], got {thresholded_fraction}")
    if not 0.5 <= floor_quantile < 1:
        raise InputError(f"floor_quantile: must lie in [0.5, 1), got {floor_quantile}")
    n, m = img.shape
    if reference is not None and reference.level_by_bin is not None and (
            reference.level_by_bin.size != n or reference.n_beams != m):  # a thresholded image too
        where = reference.source or "reference"
        raise InputError(f"{where}: a background of {reference.level_by_bin.size} bins x {reference.n_beams} "
                         f"beams does not fit an image of {n} x {m} (calibration of another sonar setting?)")
    if zero_fraction >= thresholded_fraction:
        return BackgroundLevel(False, "thresholded", zero_fraction), None, None
    if reference is not None and reference.level_by_bin is not None:
        return _finish(img, reference.level_by_bin, reference.beam_factor, zero_fraction, floor_quantile, pool,
                       "calibration", n_levels)
    level = _row_level(img, max_rise)
    if level is None:
        return BackgroundLevel(False, "degenerate", zero_fraction), None, None
    if _median(level) * 255.0 < MIN_LEVEL_COUNTS and on_8bit_grid(img):
        return BackgroundLevel(False, "quantised", zero_fraction, level), None, None
    factor = _block_factor(img, level)
    return _finish(img, level, factor, zero_fraction, floor_quantile, pool, "estimated", n_levels)


def _row_level(img: NDArray[np.float32], max_rise: float) -> NDArray[np.float32] | None:
    """Step 1: the background level vs range (None if most rows have a zero level).

    The lower quartile of each row across the beams, median filtered over 5 bins, then smoothed
    along range in the log domain over ``max(n_bins / 16, 15)`` bins with rows far above the
    smooth curve left out (> 2.5 robust sigma, with the contiguous rows > 0.5 sigma above it on
    either side; sigma at least :func:`_sigma_floor`), the curve interpolated across rows whose
    window holds almost none kept, until the rows left out settle, and then bridged by the
    quadratic through the kept rows on either side wherever a window holds a row left out
    (:func:`sonarmap.preprocess._kernels.smooth_log_level`): a surface at one range across most of
    the fan (a hull seen head-on through a narrow fan, a seabed) is not background.  Its flanks
    are left out with it: kept, they raise the curve under the echo's peak (+31 % under a seabed
    echo 2.5x the background, against +9 %), which flattens the echo's measured profile and moves
    its half-peak leading edge towards the sonar (simulated ARIS seafloors: 3.8 bins early).  Rows
    from the first bin on that stay above the curve are the transmitter's ring-down and keep
    their own level.  Finally the level may rise at most ``max_rise`` above its minimum at
    nearer ranges.
    """
    from sonarmap.preprocess._kernels import level_tail, median5, smooth_log_level

    n = img.shape[0]
    # (the count also tells whether the image is the readers' 8-bit data: no on_8bit_grid pass then)
    level, scaled = _row_quartile_grid(img)
    if n >= 5:
        level = median5(level)  # = scipy.ndimage.median_filter(level, size=5, mode="nearest")
    good = level > _ZERO
    n_good = np.count_nonzero(good)
    if n_good < 0.5 * n:
        return None
    if n_good < n:
        level = np.where(good, level, float(np.median(level[good])))
    level = level.astype(np.float64)
    log_level = np.log(level)
    width = max(n // 16, 15)
    smooth = log_level
    above = np.zeros(n, dtype=bool)
    if n > width:
        # rounds of: running means of keep and log_level * keep over width bins (scipy's
        # uniform_filter1d, mode "nearest"), their ratio where keep covers > 5 % of the window
        # (interpolated elsewhere), then the rows > 2.5 robust sigma above it and their flanks
        # left out, until those rows settle
        smooth, above = smooth_log_level(log_level, width, _sigma_floor(level, scaled or on_8bit_grid(img)))
    # ring-down: the leading rows above the curve stay background at their own level; then a
    # surface across most beams (seabed) is no background: the level may rise at most max_rise x
    # above its minimum nearer to the sonar (off for max_rise <= 0)
    # (max_rise in the precision numpy multiplies a float32 array by it: float32 for a Python float)
    rise = np.result_type(max_rise, np.float32).type(max_rise)
    return level_tail(np.exp(smooth), level, above, rise, max_rise > 0)


#: Smallest robust sigma of the log level (natural log) :func:`_row_level` assumes.
LEVEL_SIGMA_FLOOR = 0.02


def _sigma_floor(level: NDArray[np.float64], quantised: bool) -> NDArray[np.float64]:
    """Per row, the smallest sigma of the log level: :data:`LEVEL_SIGMA_FLOOR`, or on 8-bit data
    the log of one quantisation step over the level when larger (a row quartile of 8-bit samples
    moves in steps of 1/255: on a dim background of a few levels one step is 10-40 %, no
    surface)."""
    if not quantised:
        return np.full(level.size, LEVEL_SIGMA_FLOOR)
    return np.maximum(LEVEL_SIGMA_FLOOR, np.log1p((1.0 / 255.0) / level))


def _finish(img: NDArray[np.float32], level: NDArray[np.float32], factor: NDArray[np.float32] | None,
            zero_fraction: float, floor_quantile: float, pool: tuple[int, int], reason: str,
            n_levels: int) -> tuple[BackgroundLevel, NDArray[np.float32] | None, NDArray[np.uint8] | None]:
    """Steps 2-4: divide by level x factor, multi-look, threshold, scale; also the normalised
    image's quantisation levels (:func:`estimate_background_levels`)."""
    from sonarmap.preprocess._kernels import excess_top, pooled_ratio_grid

    n, m = img.shape
    # the factor interpolated from its grid on the way (a grid of one block of 1: no factor, the
    # same bits as dividing by 1)
    cols, r0, r1, fr = _grid_rows(_ONE_BLOCK if factor is None else factor, (n, m))
    z = _WORK.get("z", (n, m))
    pooled_ratio_grid(np.ascontiguousarray(img, dtype=np.float32), np.ascontiguousarray(level, dtype=np.float32),
                      cols, r0, r1, fr, int(min(max(pool[0], 1), n)), int(min(max(pool[1], 1), m)), z,
                      _WORK.get("tmp", (n, m)))
    c50, spread = _background_quartiles(z)
    scale = float(spread) / math.log(1.5)
    if not scale > 0 or not math.isfinite(scale):
        return BackgroundLevel(False, "degenerate", zero_fraction, level, factor), None, None
    t = c50 + math.log(0.5 / (1.0 - floor_quantile)) * scale  # ln 5 at the 0.9 quantile
    g = BACKGROUND_MEAN / scale
    levels = np.empty((n, m), dtype=np.uint8)
    step = np.float32(min(max(n_levels, 1), 256) - 1)
    u, n_top, finite = excess_top(z, np.float32(t), np.float32(g), step, levels)
    if n_top > MAX_SATURATED * u.size:
        # targets far above a weak (or coarsely quantised) background would fill the top level:
        # lower the gain until at most MAX_SATURATED of the pixels reach it (a receiver's gain
        # assist); the background then spans fewer levels, but stays resolved
        top = float(np.quantile(z, 1.0 - MAX_SATURATED))
        if top > t:
            g = min(g, 1.0 / (top - t))
            u, _, finite = excess_top(z, np.float32(t), np.float32(g), step, levels)
    return (BackgroundLevel(True, reason, zero_fraction, level.astype(np.float32), factor,
                            _range_dependence_db(level), t, g), u, levels if finite and 2 <= n_levels <= 256 else None)


def _background_quartiles(z: NDArray[np.float32]) -> tuple[float, float]:
    """``(c50, spread)`` of step 4: the median over the background rows of each row's median
    ``q50`` and of its ``q50 - q25``.

    Only the rows that can be background rows are ordered (:func:`_candidate_rows`): the others'
    medians lie above the threshold that picks the background rows, so they cannot change which
    rows those are, nor their order."""
    n, m = z.shape
    # the background's threshold and scale from the lower half of each row (robust to surfaces
    # on up to half the beams of a row) in the quarter of the rows with the lowest median (robust
    # to surfaces filling up to 3/4 of the rows): exponential tail of scale s above the median:
    # q50 - q25 = s ln(3/2), q90 = q50 + s ln 5
    k25, k50 = (m - 1) // 4, (m - 1) // 2
    # background rows: the quarter of the rows with the lowest median (saturated or surface rows
    # have high medians), the first ones of a stable argsort; their median level and median spread
    n_rows = max(n // 4, 1)
    part = _WORK.get("sorted", (n, m))
    rows = _candidate_rows(z, k50, n_rows)
    if rows is not None:
        found = _row_quartiles(np.take(z, rows, axis=0, out=part[: rows.size]), k25, k50, n_rows)
        if found is not None:
            return found
    np.copyto(part, z)
    found = _row_quartiles(part, k25, k50, n_rows)
    if found is not None:
        return found
    # (overflowing images) the numpy way
    np.copyto(part, z)
    part.sort(axis=1)
    q25, q50 = part[:, k25].astype(np.float64), part[:, k50].astype(np.float64)
    sel = np.argsort(q50, kind="stable")[:n_rows]
    return float(np.median(q50[sel])), float(np.median((q50 - q25)[sel]))


#: :func:`_candidate_rows` takes the median of every ``_SAMPLE_STEP``-th row ...
_SAMPLE_STEP = 8
#: ... from at least this many rows (fewer: every row is ordered).
_SAMPLE_MIN = 8


def _candidate_rows(z: NDArray[np.float32], k50: int, n_rows: int) -> NDArray[np.intp] | None:
    """The rows of ``z`` (ascending) whose median is at most a threshold ``t`` that at least
    ``n_rows`` medians lie under: the ``n_rows`` lowest medians, ties included, are among them.

    ``t`` is a median of a sample of the rows (every :data:`_SAMPLE_STEP`-th), the one a little
    above the share ``n_rows / n`` of them (by 0.05 plus 2.5 standard errors of the sample
    quantile), so that ``t`` rarely falls short; the rows are then found by counting
    (:func:`sonarmap.preprocess._kernels.rows_ranked_at_most`).  None when the sample is small or
    not finite, or ``t`` falls short (then every row is ordered).  About 36 % of the rows are left
    on 4096 x 512 simulated pings (the Oculus pings ~42 %, ARIS ~38 %): step 4's quartiles there
    take 0.9 ms instead of 3.2 with every row partitioned.
    """
    from sonarmap.preprocess._kernels import rows_ranked_at_most

    n = z.shape[0]
    sample = np.sort(z[::_SAMPLE_STEP], axis=1)[:, k50]
    ns = sample.size
    if ns < _SAMPLE_MIN:
        return None
    share = n_rows / n
    share += 0.05 + 2.5 * math.sqrt(share * (1.0 - share) / ns)
    if share >= 1.0:
        return None
    sample.sort()
    t = sample[int(share * ns)]
    if not np.isfinite(t):
        return None
    rows = rows_ranked_at_most(z, t, k50)
    return rows if rows.size >= n_rows else None


def _row_quartiles(part: NDArray[np.float32], k25: int, k50: int, n_rows: int) -> tuple[float, float] | None:
    """:func:`_background_quartiles` over the rows of ``part`` (reordered in place): long rows
    partitioned (:func:`_partitioned_quartiles`), short ones sorted; None when a median or a
    quartile is not finite."""
    from sonarmap.preprocess._kernels import background_rows

    if part.shape[1] >= _PARTITION_MIN:
        return _partitioned_quartiles(part, k25, k50, n_rows)
    part.sort(axis=1)
    q25, q50 = part[:, k25].astype(np.float64), part[:, k50].astype(np.float64)
    if not (np.isfinite(q50).all() and np.isfinite(q25).all()):
        return None
    c50, spread = background_rows(q25, q50, n_rows)
    return float(c50), float(spread)


def _partitioned_quartiles(part: NDArray[np.float32], k25: int, k50: int, n_rows: int) -> tuple[float, float] | None:
    """:func:`_background_quartiles` of long rows: each row partitioned at its median, the lower
    quartile only in the background rows (from the lower part of their partition: the same
    order statistic); None when a median or a quartile is not finite (then by sorting)."""
    part.partition(k50, axis=1)
    q50 = part[:, k50].astype(np.float64)
    if not np.isfinite(q50).all():
        return None
    rows = np.argsort(q50, kind="stable")[:n_rows]
    low = part[rows, : k50 + 1]  # the k50 + 1 smallest values of each background row
    low.partition(k25, axis=1)
    q25 = low[:, k25].astype(np.float64)
    if not np.isfinite(q25).all():
        return None
    sel = q50[rows]
    return _median(sel), _median(sel - q25)


@dataclasses.dataclass(frozen=True, eq=False)
class RecordingBackground:
    """Background level of a whole recording: the median over its pings of each ping's estimate.

    Attributes
    ----------
    n_pings : int
        Pings the estimate is made of.
    n_beams : int
        Beams of the recording's geometry.
    thresholded : bool
        The recording's pings are thresholded (median zero fraction >= 0.2): no level is estimated
        and the paper's calibrated pre-processing applies.
    zero_fraction : float
        Median over the pings of the fraction of zero pixels.
    level_by_bin : ndarray, shape (n_bins,), float32, or None
        Median over the pings of ``b(r)``.
    beam_factor : ndarray, shape (n_blocks_range, n_blocks_beam), float32, or None
        Median over the pings of ``f(r, theta)``.
    range_dependence_db : float
        ``10 log10`` of the 90th over the 10th percentile of ``level_by_bin``.
    ping_spread_db : float
        Median over the range bins of the ping-to-ping spread (inter-quartile range, dB) of
        ``b(r)``: how stable the background is over the recording (NaN for one ping).
    degenerate_pings : int
        Pings whose level could not be estimated (zero in most rows).
    source : str
        Where the estimate came from (the calibration file read by the command line), named in
        the error when it does not fit an image; empty for one estimated in memory.
    """

    n_pings: int
    n_beams: int
    thresholded: bool
    zero_fraction: float
    level_by_bin: NDArray[np.float32] | None = None
    beam_factor: NDArray[np.float32] | None = None
    range_dependence_db: float = math.nan
    ping_spread_db: float = math.nan
    degenerate_pings: int = 0
    source: str = ""

    def beam_profile(self) -> NDArray[np.float32] | None:
        """Per-beam gain implied by the beam factor (its mean over range, median 1): the taper."""
        if self.beam_factor is None or self.level_by_bin is None:
            return None
        full = expand_grid(self.beam_factor, (self.level_by_bin.size, self.n_beams))
        taper = full.mean(axis=0)
        return (taper / float(np.median(taper))).astype(np.float32)

    def to_dict(self) -> dict[str, object]:
        """JSON-compatible dict; :meth:`from_dict` reads it back."""
        return {
            "n_pings": self.n_pings, "n_beams": self.n_beams, "thresholded": self.thresholded,
            "zero_fraction": self.zero_fraction,
            "level_by_bin": None if self.level_by_bin is None else [float(v) for v in self.level_by_bin],
            "beam_factor": None if self.beam_factor is None else [[float(v) for v in row] for row in self.beam_factor],
            "range_dependence_db": None if not math.isfinite(self.range_dependence_db) else self.range_dependence_db,
            "ping_spread_db": None if not math.isfinite(self.ping_spread_db) else self.ping_spread_db,
            "degenerate_pings": self.degenerate_pings,
        }

    @classmethod
    def from_dict(cls, d: dict[str, object], name: str = "background") -> RecordingBackground:
        """Inverse of :meth:`to_dict`; a bad field raises :class:`InputError` naming it."""
        if not isinstance(d, dict):
            raise InputError(f"{name}: expected a table, got {type(d).__name__}")
        check_field_names(d, cls, name)
        try:
            n_pings = int(d["n_pings"])  # type: ignore[call-overload]
            n_beams = int(d["n_beams"])  # type: ignore[call-overload]
            thresholded = bool(d["thresholded"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{name}: missing or bad n_pings / n_beams / thresholded ({exc})") from None
        level = d.get("level_by_bin")
        factor = d.get("beam_factor")
        try:
            lv = None if level is None else np.asarray(level, dtype=np.float32)
            fv = None if factor is None else np.asarray(factor, dtype=np.float32)
        except (TypeError, ValueError):
            raise InputError(f"{name}: level_by_bin / beam_factor must be numeric arrays") from None
        if lv is not None and (lv.ndim != 1 or lv.size == 0 or not np.all(np.isfinite(lv)) or np.any(lv <= 0)):
            raise InputError(f"{name}.level_by_bin: must be a non-empty list of positive numbers")
        if fv is not None and (fv.ndim != 2 or fv.size == 0 or not np.all(np.isfinite(fv)) or np.any(fv <= 0)):
            raise InputError(f"{name}.beam_factor: must be a non-empty 2-D table of positive numbers")

        def num(key: str) -> float:
            v = d.get(key)
            return math.nan if v is None else float(v)  # type: ignore[arg-type]

        return cls(n_pings, n_beams, thresholded, num("zero_fraction"), lv, fv, num("range_dependence_db"),
                   num("ping_spread_db"), int(d.get("degenerate_pings", 0) or 0))  # type: ignore[call-overload]


def estimate_recording_background(
    images: object, *, thresholded_fraction: float = 0.2, max_rise: float = 2.0,
) -> RecordingBackground:
    """Recording-level background: the median over the pings of :func:`estimate_background`'s
    level and beam factor (robust to a target that moves through the window).

    Parameters
    ----------
    images : iterable of ndarray or Ping
        The pings of one recording (one geometry).
    thresholded_fraction, max_rise : float
        As in :func:`estimate_background`.

    Returns
    -------
    RecordingBackground

    Raises
    ------
    InputError
        No pings, mixed shapes, or no ping with an estimable level.
    """
    levels: list[NDArray[np.float32]] = []
    factors: list[NDArray[np.float32]] = []
    zeros: list[float] = []
    shape: tuple[int, int] | None = None
    n = 0
    degenerate = 0
    for item in images:  # type: ignore[attr-defined]
        img = np.asarray(getattr(item, "image", item), dtype=np.float32)
        src = getattr(item, "source", "") or f"ping {n}"
        if img.ndim != 2 or img.size == 0:
            raise InputError(f"{src}: expected a (n_bins, n_beams) image, got shape {img.shape}")
        if shape is None:
            shape = img.shape
        elif img.shape != shape:
            raise InputError(f"{src}: shape {img.shape} differs from the recording's {shape}")
        finite, zero_fraction = _finite_zero_fraction(img)
        if not finite:
            raise InputError(f"{src}: contains NaN or infinite values")
        n += 1
        zeros.append(zero_fraction)
        lv = _row_level(img, max_rise)
        if lv is None:
            degenerate += 1
            continue
        levels.append(lv)
        factors.append(_block_factor(img, lv))
    if n == 0 or shape is None:
        raise InputError("recording: no pings")
    zf = float(np.median(zeros))
    if zf >= thresholded_fraction:
        return RecordingBackground(n, shape[1], True, zf, degenerate_pings=degenerate)
    if not levels:
        raise InputError(f"recording: the background level is zero in most range rows of all {n} pings "
                         "(nothing to estimate)")
    stack = np.stack(levels)
    level = np.median(stack, axis=0).astype(np.float32)
    factor = np.median(np.stack(factors), axis=0).astype(np.float32)
    dep = _range_dependence_db(level)
    spread = math.nan
    if len(levels) > 1:
        db = 10 * np.log10(stack)
        spread = float(np.median(np.subtract(*np.percentile(db, [75, 25], axis=0))))
    return RecordingBackground(n, shape[1], False, zf, level, factor, dep, spread, degenerate)


def normalise_image(image: NDArray[np.floating], **kwargs: object) -> NDArray[np.float32]:
    """The normalised image of :func:`estimate_background` (the input as float32 when not applied)."""
    bg, u = estimate_background(image, **kwargs)  # type: ignore[arg-type]
    return np.asarray(image, dtype=np.float32) if u is None else u
