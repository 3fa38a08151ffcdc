"""Echoes along each beam and the range convention: leading edge, peak and uncertainty.

An *echo* is a run of classifier structure pixels along one beam (runs separated by at most
``max_gap`` background bins are one echo: speckle fades inside a surface echo).  Its range is
measured on the image smoothed along range over the pulse length (``DESIGN.md``, "Range
convention"):

* **first peak** ``p``: the first local maximum inside the echo that reaches ``peak_rel`` (0.5)
  of the echo's maximum (a weak halo or speck in front of the surface is not the peak);
* **leading edge**: walking from ``p`` towards the sonar, the first crossing of
  ``fraction x value(p)`` (default 0.5, "half peak"), linearly interpolated between the two bins
  around it (sub-bin).  The walk may leave the echo by up to ``back`` bins: the rising flank of
  an echo is often below the classifier's threshold;
* **strongest**: the range of ``p``;
* **sigma** (:func:`range_sigma_m`): the quantisation of the bin grid and the timing jitter of
  the crossing, ``sigma_v / slope``, where ``slope`` is the image's rise per bin at the crossing
  and ``sigma_v`` the fluctuation of the smoothed image there (speckle of the echo at the
  crossing level plus background), added in quadrature with a pulse term.

A single beam's echo is a few speckled samples: its first peak is a speckle spike as often as
the echo's own level, and the leading edge then moves by several bins (single-look DIDSON
samples put the half-peak crossing of a hull 2 bins late on the median).  The echoes of a
tracked surface are therefore measured together (:func:`pooled_edges`): per beam, the profiles
of the neighbouring beams of the same surface, aligned on their edges, are averaged (a
multi-look along the surface) and the leading edge is the half-peak crossing of that mean
profile.  The same convention, measured on more looks.

Every return the pipeline reports is one echo's leading edge (or peak with
``range_mode="strongest"``).
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry

__all__ = ["Echoes", "find_echoes", "spliced_echoes", "pooled_edges", "surface_runs", "range_sigma_m", "edge_sigma_m", "smooth_along_range", "level_llr",
           "beamwidth_in_beams"]


@dataclasses.dataclass(frozen=True, eq=False)
class Echoes:
    """The echoes of one ping, sorted by beam and then by range (flat arrays, one entry per echo).

    Attributes
    ----------
    beam : ndarray of int64
        Beam index.
    start_bin, stop_bin : ndarray of int64
        First and one-past-last structure bin of the echo.
    peak_bin : ndarray of int64
        The echo's first peak (see the module notes).
    peak_value : ndarray of float64
        Smoothed image value at the peak.
    edge_bin : ndarray of float64
        Fractional bin index of the leading edge (half-peak crossing).
    edge_range_m, peak_range_m : ndarray of float64
        Ranges of the leading edge (interpolated on ``geometry.range_m``) and of the peak.
    slope : ndarray of float64
        Rise of the smoothed image per bin at the crossing.
    evidence : ndarray of float64
        Sum of the per-pixel log-likelihood ratio (structure vs background, nats) over the echo's
        structure pixels.
    n_pixels : ndarray of int64
        Structure pixels in the echo.
    sigma_m : ndarray of float64
        One-sigma uncertainty of ``edge_range_m`` (:func:`range_sigma_m`).
    n_beams : int
        Beams of the ping.
    clipped : ndarray of bool, optional
        Whether the echo reaches the receiver's full scale (its peak is then a lower bound); None:
        not known (see :func:`sonarmap.ranges.measure.surface_ranges`).
    clip_row : ndarray of int64, optional
        The echo's first full-scale row (-1: not clipped); None: not known.  The half-peak edge
        of a clipped echo's unclipped signal lies between ``edge_bin`` and this row.
    beamwidth_beams : ndarray of float64, optional
        Per beam, the geometry's two-way azimuth beamwidth in units of the local beam spacing
        (``SonarGeometry.azimuth_beamwidth_rad``); None when the geometry does not give it.
    clip_fitted : ndarray of bool, optional
        Whether the echo's leading edge is that of a Gaussian fitted to its clipped peak
        (:func:`pooled_edges` with ``clip``); None: none is.
    smooth_trust : ndarray of float64, optional
        Per echo, how many times larger than its sigma the smoothing along the surface may take
        it (>= 1; ``RangeConfig.edge_template_anchor_trust``): set by
        :func:`sonarmap.ranges.template.template_edges` to the sigma the edge would have if its
        anchor were as uncertain as the incoming edges it reads (the median of their squared
        ``sigma_m`` over the anchor's beams, counted like the offsets) where that is larger, over
        its sigma (1 where not measured), when asked to (``anchor_trust``); None: not set.
    """

    beam: NDArray[np.int64]
    start_bin: NDArray[np.int64]
    stop_bin: NDArray[np.int64]
    peak_bin: NDArray[np.int64]
    peak_value: NDArray[np.float64]
    edge_bin: NDArray[np.float64]
    edge_range_m: NDArray[np.float64]
    peak_range_m: NDArray[np.float64]
    slope: NDArray[np.float64]
    evidence: NDArray[np.float64]
    n_pixels: NDArray[np.int64]
    sigma_m: NDArray[np.float64]
    n_beams: int
    clipped: NDArray[np.bool_] | None = None
    clip_row: NDArray[np.int64] | None = None
    beamwidth_beams: NDArray[np.float64] | None = None
    clip_fitted: NDArray[np.bool_] | None = None
    smooth_trust: NDArray[np.float64] | None = None

    @classmethod
    def _of(cls, **fields: object) -> Echoes:
        """The echoes of ``fields`` (every field without a default), the optional ones None, built
        without the frozen dataclass ``__init__``'s per-field ``object.__setattr__``."""
        new = object.__new__(cls)
        new.__dict__.update(_NO_OPTIONAL)
        new.__dict__.update(fields)
        return new

    @property
    def size(self) -> int:
        """Number of echoes."""
        return int(self.beam.size)

    def intervals(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """``(lo, hi)``: each echo's bin interval, from its leading edge (or first structure bin,
        whichever is nearer) to its last structure bin - what surfaces touch across beams by."""
        return np.minimum(self.start_bin, np.floor(self.edge_bin).astype(np.int64)), self.stop_bin - 1

    def replaced(self, **changes: NDArray[np.generic]) -> Echoes:
        """A copy with the arrays ``changes`` replaced (``dataclasses.replace`` without its
        per-call field introspection: the echoes of a ping are rebuilt several times)."""
        if not changes.keys() <= self.__dataclass_fields__.keys():
            raise TypeError(f"Echoes has no fields {sorted(changes.keys() - self.__dataclass_fields__.keys())}")
        new = object.__new__(Echoes)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new

    def per_beam(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """``(first, count)``: the echoes of beam ``j`` are ``first[j] : first[j] + count[j]``."""
        count = np.bincount(self.beam, minlength=self.n_beams).astype(np.int64)
        first = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64)
        return first, count


#: The optional fields of :class:`Echoes`, unset.
_NO_OPTIONAL = {"clipped": None, "clip_row": None, "beamwidth_beams": None, "clip_fitted": None,
                "smooth_trust": None}


def smooth_along_range(image: ArrayLike, pulse_bins: int) -> NDArray[np.float64]:
    """The image averaged along range over ``pulse_bins`` bins (centred box; unchanged below 2)."""
    img = np.asarray(image, dtype=np.float64)
    if pulse_bins < 2 or img.shape[0] < 2:
        return np.ascontiguousarray(img)
    if img.ndim == 2:
        from sonarmap.ranges._kernels import smooth_rows

        # = uniform_filter1d(img, size=pulse_bins, axis=0, mode="nearest"), bit for bit, ~10x faster
        return smooth_rows(np.ascontiguousarray(img), int(pulse_bins))
    from scipy.ndimage import uniform_filter1d

    return np.ascontiguousarray(uniform_filter1d(img, size=int(pulse_bins), axis=0, mode="nearest"))


def level_llr(fit: object, *, clip: float = 4.0) -> NDArray[np.float64]:
    """Per quantised level, the log-likelihood ratio ``log p(y|structure) - log p(y|background)``
    (nats) under a fitted mixture (eq. 8-10; the best object class), clipped to ``[-clip, clip]``."""
    import sonarmap.ranges._kernels as _rk

    lp = np.ascontiguousarray(fit.decision_log_pmf(copy=False), dtype=np.float64)  # type: ignore[attr-defined]
    if lp.shape[0] < 2:
        return np.zeros(lp.shape[1])
    return _rk.llr_table(lp, float(clip))


def range_sigma_m(edge_value: ArrayLike, slope: ArrayLike, bin_m: float, *, looks: ArrayLike = 1.0,
                  background: float = 0.0, pulse_m: float = 0.0, scale: float = 1.0) -> NDArray[np.float64]:
    """One-sigma uncertainty of a leading-edge range (metres).

    ``sigma^2 = bin^2 / 12 + (scale bin sigma_v / slope)^2 + (pulse / sqrt(12))^2`` with
    ``sigma_v = sqrt(2) (edge_value + background) / sqrt(looks)``: the crossing of a speckled echo
    moves by the image's fluctuation at the crossing level divided by its rise per bin - the
    sample at the crossing and the peak that sets the level fluctuate alike, hence ``sqrt(2)`` -
    and the bin grid and the pulse's own extent add their uniform spreads.  ``scale`` calibrates
    the jitter term (the pipeline's value is fitted on the simulator, ``docs/ranges.md``).

    Parameters
    ----------
    edge_value : array_like
        Image value at the crossing (``fraction`` x the peak).
    slope : array_like
        Rise of the image per bin at the crossing (> 0).
    bin_m : float
        Range bin spacing.
    looks : float or array_like
        Effective independent looks of the smoothed image (1: single-look speckle), per value or
        one for all.
    background : float
        Mean background level of the image.
    pulse_m : float
        Pulse length along range.
    """
    v = np.asarray(edge_value, dtype=np.float64)
    n_looks = np.maximum(np.asarray(looks, dtype=np.float64), 1.0)
    sig_v = math.sqrt(2.0) * (np.abs(v) + max(float(background), 0.0)) / np.sqrt(n_looks)
    return edge_sigma_m(sig_v, slope, bin_m, pulse_m=pulse_m, scale=scale)


def edge_sigma_m(noise: ArrayLike, slope: ArrayLike, bin_m: float, *, pulse_m: float = 0.0,
                 scale: float = 1.0) -> NDArray[np.float64]:
    """One-sigma uncertainty of a crossing (metres) from the image's noise at it.

    ``sigma^2 = bin^2 / 12 + (scale bin noise / slope)^2 + (pulse / sqrt(12))^2``: the timing
    jitter of a crossing is the noise of the profile there over its rise per bin (at most 8
    bins), plus the bin grid's and the pulse's uniform spreads (:func:`range_sigma_m` models
    ``noise`` from speckle looks; :func:`pooled_edges` measures it across the pooled beams).
    """
    from sonarmap.ranges._kernels import edge_sigmas

    # never more than ~8 bins uncertain (also where the noise is unknown)
    nz, s = np.broadcast_arrays(np.asarray(noise, dtype=np.float64), np.asarray(slope, dtype=np.float64))
    out = edge_sigmas(np.ascontiguousarray(nz).ravel(), np.ascontiguousarray(s).ravel(), float(bin_m),
                      float(bin_m**2 / 12.0), float((pulse_m**2) / 12.0), float(scale))
    return out.reshape(nz.shape)


def _check_edge_options(fraction: float, peak_rel: float, scan: str) -> None:
    """The leading-edge options of :func:`find_echoes` are in range."""
    if not 0 < fraction < 1:
        raise InputError(f"fraction: must lie in (0, 1) (got {fraction})")
    if scan not in ("back", "forward"):
        raise InputError(f"scan: must be 'back' or 'forward' (got {scan!r})")
    if not 0 < peak_rel <= 1:
        raise InputError(f"peak_rel: must lie in (0, 1] (got {peak_rel})")


def _levels_in_range(code: np.ndarray, size: int) -> bool:
    """Every value of the integer array ``code`` lies in ``[0, size)`` (no scan when its dtype
    cannot hold any other: 8-bit levels and a 256-entry table)."""
    if code.dtype.kind == "u" and (1 << 8 * code.dtype.itemsize) - 1 < size:  # np.iinfo(dtype).max
        return True
    return not code.size or (int(code.min()) >= 0 and int(code.max()) < size)


def _evidence_table(m: np.ndarray, llr: ArrayLike | None, levels: ArrayLike | None,
                    level_evidence: ArrayLike | None) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel codes and the evidence table they index, from ``levels`` + ``level_evidence`` or ``llr``.

    With ``llr`` (default: 1 per pixel) every pixel is its own code.
    """
    if levels is not None and level_evidence is not None:
        code = np.ascontiguousarray(levels)
        lut = np.ascontiguousarray(level_evidence, dtype=np.float64)
        if code.shape != m.shape:
            raise InputError(f"levels: shape {code.shape} does not match mask {m.shape}")
        if not _levels_in_range(code, lut.size):
            raise InputError(f"levels: values must lie in [0, {lut.size})")
        return code, lut
    ev = np.ones(m.shape) if llr is None else np.asarray(llr, dtype=np.float64)
    if ev.shape != m.shape:
        raise InputError(f"llr: shape {ev.shape} does not match mask {m.shape}")
    return np.arange(ev.size, dtype=np.int64).reshape(ev.shape), np.ascontiguousarray(ev.ravel())


def _boost_pixels(boost: ArrayLike | None, shape: tuple[int, ...]) -> NDArray[np.bool_]:
    """:func:`find_echoes`' ``boost`` as a C-contiguous boolean image (shape (1, 1): none)."""
    if boost is None:
        return np.zeros((1, 1), dtype=bool)
    bst = np.ascontiguousarray(boost, dtype=bool)
    if bst.shape != shape:
        raise InputError(f"boost: shape {bst.shape} does not match mask {shape}")
    return bst


def find_echoes(
    mask: ArrayLike,
    image: ArrayLike,
    geometry: SonarGeometry,
    *,
    llr: ArrayLike | None = None,
    levels: ArrayLike | None = None,
    level_evidence: ArrayLike | None = None,
    boost: ArrayLike | None = None,
    boost_min: float = 1.0,
    pulse_bins: int = 1,
    fraction: float = 0.5,
    peak_rel: float = 0.5,
    max_gap: int | None = None,
    back: int | None = None,
    looks: float = 1.0,
    background: float = 0.0,
    scan: str = "back",
    sigma_scale: float = 1.0,
    columns: NDArray[np.int64] | None = None,
    rows: tuple[int, int] | None = None,
) -> Echoes:
    """Find the echoes of a ping (see the module notes).

    Parameters
    ----------
    mask : ndarray of bool, shape (n_bins, n_beams)
        Classifier structure pixels.
    image : ndarray, shape (n_bins, n_beams)
        The image the classifier saw; smoothed along range over ``pulse_bins`` before measuring.
    geometry : SonarGeometry
    llr : ndarray, shape (n_bins, n_beams), optional
        Per-pixel evidence (e.g. :func:`level_llr` looked up at every pixel); default 1 per
        structure pixel.
    levels, level_evidence : ndarray, optional
        Instead of ``llr``: the quantised image and the evidence per level (:func:`level_llr`),
        looked up only at structure pixels.
    boost, boost_min : ndarray of bool, float
        Pixels whose evidence is at least ``boost_min`` (e.g. pooled band pixels).
    pulse_bins : int
        Pulse length in bins (smoothing box; < 2 = none).
    fraction : float
        Leading-edge fraction of the first peak (0.5 = half peak).
    peak_rel : float
        The first peak is the first local maximum reaching this fraction of the echo's maximum.
    max_gap : int, optional
        Background bins bridged inside one echo (default ``max(2, pulse_bins)``).
    back : int, optional
        Bins the leading-edge walk may go in front of the echo (default ``pulse_bins + 2``).
    looks, background, sigma_scale : float
        Speckle looks, background mean of ``image`` and jitter calibration for
        :func:`range_sigma_m`.
    scan : {"back", "forward"}
        How the crossing is found: walking from the peak towards the sonar to the first bin below
        the level (``"back"``), or from ``back`` bins in front of the echo to the first bin that
        reaches it (``"forward"``: a speckle dip on the rising flank does not stop it).
    columns, rows : ndarray of int64, (int, int), optional
        Only the echoes of the beams ``columns`` (ascending; a beam's echoes depend on its own
        column only: :func:`spliced_echoes`); the rows holding the ``mask`` pixels (default all).
    """
    m = np.ascontiguousarray(mask, dtype=bool)
    geometry.check_image(m, "mask")
    img = smooth_along_range(image, pulse_bins)
    geometry.check_image(img, "image")
    _check_edge_options(fraction, peak_rel, scan)
    code, lut = _evidence_table(m, llr, levels, level_evidence)
    gap = max(2, int(pulse_bins)) if max_gap is None else int(max_gap)
    bk = int(pulse_bins) + 2 if back is None else int(back)
    return _echoes_of(m, img, code, lut, _boost_pixels(boost, m.shape), geometry,
                      (float(boost_min), gap, float(fraction), float(peak_rel), bk, scan == "forward"),
                      (int(pulse_bins), float(looks), float(background), float(sigma_scale)), columns, rows)


def _echoes_of(m: NDArray[np.bool_], img: NDArray[np.float64], code: NDArray[np.integer], lut: NDArray[np.float64],
               boost: NDArray[np.bool_], geometry: SonarGeometry, walk: tuple[float, int, float, float, int, bool],
               sigma: tuple[int, float, float, float], columns: NDArray[np.int64] | None,
               rows: tuple[int, int] | None) -> Echoes:
    """:func:`find_echoes` of its checked arrays: the C-contiguous mask, smoothed float64 image,
    per-pixel codes and their evidence table, the boost pixels (:func:`_boost_pixels`), ``walk``
    = ``(boost_min, max_gap, fraction, peak_rel, back, forward)`` and ``sigma`` = ``(pulse_bins,
    looks, background, sigma_scale)`` (the pipeline's range stage calls it with arrays it made)."""
    import sonarmap.ranges._kernels as _kernels

    cols = _ALL_COLUMNS if columns is None else np.ascontiguousarray(columns, dtype=np.int64)
    r0, r1 = (0, m.shape[0]) if rows is None else (int(rows[0]), int(rows[1]))
    beam, start, stop, peak, pval, edge, slope, evid, npx, edge_r, sig, peak_r = _kernels.measured_echoes(
        m, img, code, lut, boost, *walk, cols, columns is None, r0, r1,
        *_range_arguments(geometry, sigma[0], *sigma[1:]))
    return Echoes._of(beam=beam, start_bin=start, stop_bin=stop, peak_bin=peak, peak_value=pval, edge_bin=edge,
                      edge_range_m=edge_r, peak_range_m=peak_r, slope=slope, evidence=evid, n_pixels=npx,
                      sigma_m=sig, n_beams=int(m.shape[1]), beamwidth_beams=beamwidth_in_beams(geometry))


_ALL_COLUMNS = np.zeros(0, dtype=np.int64)


def spliced_echoes(echoes: Echoes, new: Echoes, columns: NDArray[np.int64]) -> Echoes:
    """``echoes`` with the echoes of the beams ``columns`` replaced by ``new`` (the echoes of those
    beams only, e.g. :func:`find_echoes` with ``columns``), sorted by beam as :func:`find_echoes`
    sorts them; the per-echo fields of both (``clipped`` and ``clip_row`` too when both have them)."""
    fast = _spliced_in_kernel(echoes, new, columns)
    if fast is not None:
        return fast
    keep = np.ones(echoes.n_beams, dtype=bool)
    keep[columns] = False
    old = np.flatnonzero(keep[echoes.beam])
    order = np.argsort(np.concatenate([echoes.beam[old], new.beam]), kind="stable")
    # each field's result as one gather from the two fields side by side
    take = np.concatenate([old, np.arange(echoes.size, echoes.size + new.size)])[order]
    fields = ["beam", "start_bin", "stop_bin", "peak_bin", "peak_value", "edge_bin", "edge_range_m", "peak_range_m",
              "slope", "evidence", "n_pixels", "sigma_m"]
    gone = {}
    for f in ("clipped", "clip_row"):
        if getattr(echoes, f) is not None and getattr(new, f) is not None:
            fields.append(f)
        elif getattr(echoes, f) is not None:
            gone[f] = None
    out = echoes.replaced(**{f: np.concatenate([getattr(echoes, f), getattr(new, f)])[take] for f in fields})
    return out.replaced(**gone) if gone else out  # type: ignore[arg-type]


#: The per-echo fields :func:`_spliced_in_kernel` passes, in the kernel's order, and their dtypes.
_SPLICED = (("beam", np.int64), ("start_bin", np.int64), ("stop_bin", np.int64), ("peak_bin", np.int64),
            ("n_pixels", np.int64), ("clip_row", np.int64), ("peak_value", np.float64), ("edge_bin", np.float64),
            ("edge_range_m", np.float64), ("peak_range_m", np.float64), ("slope", np.float64),
            ("evidence", np.float64), ("sigma_m", np.float64), ("clipped", np.bool_))


def _spliced_in_kernel(echoes: Echoes, new: Echoes, columns: NDArray[np.int64]) -> Echoes | None:
    """:func:`spliced_echoes` in one kernel call (:func:`_kernels.spliced_fields`) when every field
    of both is there as a 1-D array of its dtype (the range stage's echoes, ``clipped`` and
    ``clip_row`` set) and ``columns`` are beams; None otherwise."""
    import sonarmap.ranges._kernels as _kernels

    args = []
    for e in (echoes, new):
        for name, dtype in _SPLICED:
            a = getattr(e, name)
            if not (isinstance(a, np.ndarray) and a.dtype == dtype and a.ndim == 1):
                return None
            args.append(a)
    cols = np.asarray(columns)
    if cols.dtype.kind not in "iu" or cols.ndim != 1 or (cols.size and not 0 <= cols.min() <= cols.max() < echoes.n_beams):
        return None
    out = _kernels.spliced_fields(np.ascontiguousarray(cols, dtype=np.int64), int(echoes.n_beams), *args)
    return echoes.replaced(**{name: a for (name, _), a in zip(_SPLICED, out)})


def beamwidth_in_beams(geometry: SonarGeometry) -> NDArray[np.float64] | None:
    """Per beam, ``geometry.azimuth_beamwidth_rad`` over the local beam spacing (the mean gap to
    the neighbouring beams); None without a beamwidth or with fewer than two beams."""
    bw = getattr(geometry, "azimuth_beamwidth_rad", None)
    if bw is None or geometry.n_beams < 2:
        return None
    az = np.asarray(geometry.azimuth_rad, dtype=np.float64)
    # a geometry's arrays are read-only: its beamwidths are computed once per geometry object
    frozen = not az.flags.writeable and not (isinstance(bw, np.ndarray) and bw.flags.writeable)
    known = _BEAMWIDTHS.get(geometry) if frozen else None
    if known is not None:
        return known.copy()
    out = np.asarray(bw, dtype=np.float64) / np.abs(np.gradient(az))
    if frozen:
        _BEAMWIDTHS[geometry] = out.copy()
    return out


#: :func:`beamwidth_in_beams` per geometry (with read-only arrays), while the geometry lives.
_BEAMWIDTHS: weakref.WeakKeyDictionary[SonarGeometry, NDArray[np.float64]] = weakref.WeakKeyDictionary()


def _bin_and_pulse_m(geometry: SonarGeometry, pulse_bins: int) -> tuple[float, float]:
    """``(bin, pulse)`` lengths (m) that a leading edge's sigma adds as uniform spreads: the range
    bin, and the pulse where it spans at least 2 bins (shorter, it is inside the bin's spread)."""
    bin_m = abs(geometry.range_resolution_m)
    return bin_m, (int(pulse_bins) * bin_m if pulse_bins >= 2 else 0.0)


def _edge_spreads(geometry: SonarGeometry, pulse_bins: int) -> tuple[float, float, float]:
    """``(bin, bin^2 / 12, pulse^2 / 12)`` of :func:`_bin_and_pulse_m`: the bin and the two
    uniform spreads' variances the sigma kernels add (:func:`edge_sigma_m`)."""
    bin_m, pulse_m = _bin_and_pulse_m(geometry, pulse_bins)
    return bin_m, bin_m**2 / 12.0, (pulse_m**2) / 12.0


def _range_arguments(geometry: SonarGeometry, pulse_bins: int, looks: float, background: float,
                     sigma_scale: float) -> tuple[Any, ...]:
    """The arguments of :func:`_kernels.measured_echoes` from ``range_m`` on: the edges' ranges
    (``np.interp`` on the bins) and :func:`range_sigma_m`'s sigmas at the walk's fraction of the
    peaks (:func:`_kernels.echo_ranges`)."""
    sqrt_looks = math.sqrt(max(float(looks * max(int(pulse_bins), 1)), 1.0))  # NaN stays NaN, as np.maximum
    return (np.ascontiguousarray(geometry.range_m, dtype=np.float64), math.sqrt(2.0), max(float(background), 0.0),
            sqrt_looks, *_edge_spreads(geometry, pulse_bins), float(sigma_scale))


def surface_runs(echoes: Echoes, first: ArrayLike, touch_bins: float = 1.0) -> NDArray[np.int64]:
    """Label the runs of consecutive beams whose returns are one surface (-1 where no return).

    Beams ``j`` and ``j + 1`` belong to one run when both have a return and the bin intervals of
    their echoes (leading edge to last structure bin) lie within ``touch_bins`` of each other -
    the contiguity rule of :func:`sonarmap.ranges.tracking.track_surfaces`.
    """
    import sonarmap.ranges._kernels as _kernels

    sel = np.asarray(first, dtype=np.int64)
    if sel.shape != (echoes.n_beams,):
        raise InputError(f"first: expected shape ({echoes.n_beams},), got {sel.shape}")
    return _first_runs(echoes, sel, touch_bins)[2]


def _first_intervals(echoes: Echoes, sel: NDArray[np.int64]) -> tuple[NDArray[np.float64], ...]:
    """Per beam the edge (NaN: none), bin interval and stop of the echo ``sel`` picks."""
    import sonarmap.ranges._kernels as _kernels

    if echoes.size == 0:
        z = np.zeros(sel.shape)
        return np.full(sel.shape, np.nan), z, z, z
    return _kernels.first_intervals(np.ascontiguousarray(sel, dtype=np.int64), echoes.edge_bin, echoes.start_bin,
                                    echoes.stop_bin)


def _first_runs(echoes: Echoes, sel: NDArray[np.int64], touch_bins: float
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """``(edge, stop, run)``: :func:`_first_intervals`' edge and stop per beam and the runs of
    beams whose intervals touch (:func:`surface_runs`), in one kernel call."""
    import sonarmap.ranges._kernels as _kernels

    if echoes.size == 0:
        edge, lo, hi, stop = _first_intervals(echoes, sel)
        return edge, stop, _kernels.surface_runs(edge, lo, hi, float(touch_bins))
    return _kernels.first_interval_runs(np.ascontiguousarray(sel, dtype=np.int64), echoes.edge_bin, echoes.start_bin,  # type: ignore[no-any-return]
                               echoes.stop_bin, float(touch_bins))


#: ``pooled_kept_edges``' clip argument without clipping: float32 like the raw image the pipeline
#: passes when an echo clips, so that both calls share one compiled specialisation of the kernel
#: (each costs ~15-20 s to compile on a fresh cache).
_NO_CLIP = np.zeros((0, 0), dtype=np.float32)


def _mask_as_samples(clip: ArrayLike) -> NDArray[np.float32]:
    """A mask of clipped samples as ``pooled_kept_edges``' clip argument: float32, 1 where clipped
    (at the level 1.0 :func:`_pooled` passes with it), so that a mask shares the compiled
    specialisation of the raw float32 image the pipeline passes - the kernel only compares its
    samples with the level - instead of compiling one more (~15 s on a fresh cache)."""
    return np.asarray(clip, dtype=bool).astype(np.float32)


#: :func:`pooled_edges`' default ``front_bins``, ``max_bins``, ``n_iter`` and ``fit_front_bins``
#: (the pipeline's range stage pools with them).
POOL_FRONT_BINS, POOL_MAX_BINS, POOL_N_ITER, POOL_FIT_FRONT_BINS = 6, 200, 2, 16
#: Default ``flank_bins`` of :func:`pooled_edges` (and of ``PipelineConfig.ranges.edge_pool_flank_bins``).
POOL_FLANK_BINS = 6
#: Default ``peak_bins`` of :func:`pooled_edges` (and of ``PipelineConfig.ranges.edge_pool_peak_bins``).
POOL_PEAK_BINS = 2
#: Default ``lead_bins`` of :func:`pooled_edges` (and of ``PipelineConfig.ranges.edge_pool_lead_bins``):
#: ``POOL_N_ITER`` alignment rounds of ``POOL_FRONT_BINS`` each, the furthest the pooling moves an edge.
POOL_LEAD_BINS = POOL_N_ITER * POOL_FRONT_BINS


def pooled_edges(
    echoes: Echoes,
    first: ArrayLike,
    image: ArrayLike,
    geometry: SonarGeometry,
    *,
    pulse_bins: int = 1,
    half_beams: int = 3,
    front_bins: int = POOL_FRONT_BINS, max_bins: int = POOL_MAX_BINS, smooth_bins: int = 3,
    fraction: float = 0.5,
    n_iter: int = POOL_N_ITER,
    touch_bins: float = 1.0,
    sigma_scale: float = 1.0,
    clip: NDArray[np.bool_] | None = None,
    fit_front_bins: int = POOL_FIT_FRONT_BINS, fit_sigma_scale: float | None = None,
    scan: str = "forward",
    flank_bins: int = POOL_FLANK_BINS, lead_bins: int = POOL_LEAD_BINS, align_beams: int = 0,
    peak_bins: int = POOL_PEAK_BINS, min_slope: float = 0.0, jitter_floor: float = 0.0,
) -> Echoes:
    """Leading edges of a tracked surface measured on a multi-look along the surface.

    For every beam ``j`` with a return (``first[j]``, an echo index), the beams ``j - half_beams
    .. j + half_beams`` of the same surface (:func:`surface_runs`) are aligned on the running
    median of their current edges and their columns (smoothed along range over ``pulse_bins``)
    averaged at offsets ``-front_bins`` to the window's median echo depth (3 .. ``max_bins``
    bins).  The leading edge is the crossing of ``fraction`` x that mean profile's peak (smoothed
    over ``smooth_bins``), interpolated (:func:`find_echoes`' convention): with ``scan="forward"``
    (default) the first bin from the profile's front that reaches the level, with ``"back"`` the
    walk from the peak towards the sonar (it stops at a dip inside a deep echo: the real Oculus
    seabed's returns 14 cm behind its front on 6 beams of ping 0).  ``n_iter`` rounds re-align on
    the new edges.  Runs of fewer than 3 beams keep their own edges.

    Parameters
    ----------
    echoes : Echoes
        The ping's echoes (:func:`find_echoes`).
    first : array_like of int, shape (n_beams,)
        Per beam the echo index of its return (-1 none): ``Tracks.first``.
    image, geometry, pulse_bins, fraction : ndarray (n_bins, n_beams), SonarGeometry, int, float
        The image the echoes were measured on, its geometry; the others as in :func:`find_echoes`.
    sigma_scale : float
        Calibration of :func:`edge_sigma_m`'s jitter term (``PipelineConfig.ranges.sigma_pool_scale``).
    clip : ndarray of bool, shape (n_bins, n_beams), optional
        The raw samples at full scale (``>= sonarmap.ranges.measure.CLIP_LEVEL``): a clipped pooled
        peak's edge is the crossing of a Gaussian fitted to the log of the unclipped bins of both
        flanks, the rising one down to 5 % of the clipped maximum, at most ``fit_front_bins`` in
        front of the alignment; its sigma the fit's standard error x ``fit_sigma_scale`` (default
        ``sigma_scale``).
    half_beams, front_bins, max_bins, smooth_bins, n_iter, touch_bins, scan
        The pooling window; ``scan``: ``"forward"`` or ``"back"`` (see above).
    flank_bins : int
        An unclipped profile's crossing is that of the least-squares line through its rising flank
        (20-80 % of the peak, at most ``flank_bins`` either side of the crossing), not of the two
        samples around it (0, fewer than 3 flank samples or a line that does not rise: those two).
    lead_bins, align_beams : int
        A pooled edge is kept within ``pulse_bins + lead_bins`` in front of the beam's first
        structure bin and not behind its echo's end.  > 0: the pooling starts from each edge on its
        surface's Theil-Sen line over ``align_beams`` beams either side (0, default: its own edge).
    peak_bins : int
        > 0: the peak's height is the parabola's through the samples up to ``peak_bins`` either side
        of the largest, on echoes >= ``6 peak_bins`` deep (``_kernels._peak_level``); 0: the largest.
    min_slope, jitter_floor : float
        > 0 (0, the default: off): the alignment follows each window's slope from ``min_slope`` bins
        per beam; a pooled edge's jitter is at least ``jitter_floor`` x its neighbours' median.

    Returns
    -------
    Echoes
        ``echoes`` with the returns' ``edge_bin``, ``edge_range_m``, ``slope``, ``sigma_m`` replaced
        (and ``clip_fitted`` marking the echoes whose edge is that of a fitted clipped echo).
    """
    sel = np.asarray(first, dtype=np.int64)
    fit_scale = float(sigma_scale if fit_sigma_scale is None else fit_sigma_scale)
    window = (half_beams, front_bins, max_bins, smooth_bins, n_iter, fit_front_bins)
    _check_pooling(echoes, sel, window, fraction, clip, np.shape(image), (fit_scale, min_slope, jitter_floor),
                   (flank_bins, lead_bins, align_beams, peak_bins), scan)
    return _pooled(echoes, sel, image, geometry, pulse_bins, window, (fraction, touch_bins),
                   (sigma_scale, fit_scale), clip, forward=scan == "forward", flank_bins=int(flank_bins),
                   lead_bins=int(lead_bins), align_beams=int(align_beams), peak_bins=int(peak_bins),
                   min_slope=float(min_slope), jitter_floor=float(jitter_floor))


def _pooled(echoes: Echoes, sel: NDArray[np.int64], image: ArrayLike, geometry: SonarGeometry, pulse_bins: int,
            window: tuple[int, int, int, int, int, int], fraction_touch: tuple[float, float],
            scales: tuple[float, float], clip: NDArray[Any] | None, *, forward: bool = True,
            clip_level: float | None = None, flank_bins: int = POOL_FLANK_BINS,
            lead_bins: int = POOL_LEAD_BINS, align_beams: int = 0, peak_bins: int = POOL_PEAK_BINS,
            jitter_floor: float = 0.0, min_slope: float = 0.0) -> Echoes:
    """:func:`pooled_edges` of checked options (:func:`_check_pooling`: ``window`` = ``(half_beams,
    front_bins, max_bins, smooth_bins, n_iter, fit_front_bins)``, ``scales`` = ``(sigma_scale,
    fit_sigma_scale)``; the pipeline's range stage calls it with its validated configuration).
    With ``clip_level``, ``clip`` is the raw image (C-contiguous, the image's shape), clipped at
    and above that level (:func:`sonarmap.ranges.measure.full_scale_mask`'s samples), else the
    mask of the clipped samples; ``align_beams``, ``peak_bins``: as :func:`pooled_edges`' (checked);
    ``jitter_floor`` > 0: :func:`~sonarmap.ranges._kernels.floor_jitter` of the pooled edges
    (``PipelineConfig.ranges.sigma_pool_floor``); ``min_slope`` > 0: the alignment follows the
    window's slope from that many bins per beam (``PipelineConfig.ranges.edge_pool_follow_slope``)."""
    import sonarmap.ranges._kernels as _kernels

    half_beams, front_bins, max_bins, smooth_bins, n_iter, fit_front_bins = window
    fraction, touch_bins = fraction_touch
    if half_beams == 0 or echoes.size == 0:
        return echoes  # (without echoes no beam is in a run)
    # the image in float64 (pooled_edges reads its samples as float64: the same values)
    img = np.ascontiguousarray(image, dtype=np.float64)
    if img.shape != geometry.shape:  # an error where some return is in a run, as the image is then read
        if _first_runs(echoes, sel, touch_bins)[2].max(initial=-1) < 0:
            return echoes
        geometry.check_image(img, "image")
    start = _line_aligned(echoes, sel, touch_bins, align_beams) if align_beams > 0 else echoes.edge_bin
    # the runs, the smoothing along range, pooled_edges and kept_edges (the kept pooled edges
    # given to their echoes) in one kernel call
    n_kept, eb, er, sl, sig, marked, n_marked = _kernels.pooled_kept_edges(
        np.ascontiguousarray(sel, dtype=np.int64), start, echoes.start_bin, echoes.stop_bin,
        float(touch_bins), img, int(pulse_bins), int(half_beams), int(front_bins), int(max_bins),
        int(smooth_bins) | 1, float(fraction), int(n_iter), _NO_CLIP if clip is None else
        clip if clip_level is not None else _mask_as_samples(clip),
        1.0 if clip_level is None else float(clip_level), int(fit_front_bins), bool(forward), int(flank_bins),
        int(peak_bins), int(pulse_bins) + int(lead_bins),
        echoes.edge_range_m, echoes.slope, echoes.sigma_m, np.ascontiguousarray(geometry.range_m, dtype=np.float64),
        *_edge_spreads(geometry, pulse_bins), float(scales[0]), float(scales[1]), float(jitter_floor),
        float(min_slope))
    if start is not echoes.edge_bin and n_kept:
        # a return whose pooled edge was not kept keeps its own edge (kept_edges gave it the start)
        own = (eb == start) & (start != echoes.edge_bin)
        eb[own] = echoes.edge_bin[own]
    return _edges_kept(echoes, n_kept, (eb, er, sl, sig), marked, n_marked)


def _line_aligned(echoes: Echoes, sel: NDArray[np.int64], touch_bins: float, half_beams: int) -> NDArray[np.float64]:
    """The echoes' ``edge_bin`` with each return's (``sel``) replaced by its edge on its surface's
    local line (:func:`~sonarmap.ranges._alignment_kernels.line_aligned_edges` over
    ``half_beams`` on either side, the surfaces :func:`_first_runs`' with ``touch_bins``)."""
    from sonarmap.ranges._alignment_kernels import line_aligned_edges

    s = np.ascontiguousarray(sel, dtype=np.int64)
    edge, _, run = _first_runs(echoes, s, touch_bins)
    aligned = line_aligned_edges(edge, run, np.int64(half_beams))
    out = echoes.edge_bin.copy()
    ok = s >= 0
    out[s[ok]] = aligned[ok]
    return out


def _check_pooling(echoes: Echoes, sel: np.ndarray, window: tuple[int, int, int, int, int, int], fraction: float,
                   clip: NDArray[np.bool_] | None, shape: tuple[int, ...], floats: tuple[float, float, float],
                   flank_lead_align: tuple[int, int, int, int], scan: str) -> None:
    """The options of :func:`pooled_edges` (``window``: half_beams, front_bins, max_bins,
    smooth_bins, n_iter, fit_front_bins; ``floats``: its fit_sigma_scale, min_slope and
    jitter_floor; ``flank_lead_align``: its flank_bins, lead_bins, align_beams and peak_bins;
    ``scan``) are valid, ``first`` has a value per beam and ``clip`` the image's shape."""
    for key, v in zip(("fit_sigma_scale", "min_slope", "jitter_floor"), floats):
        if isinstance(v, bool) or not isinstance(v, int | float | np.number) or not (math.isfinite(v) and v >= 0):
            raise InputError(f"{key}: must be a finite number >= 0 (got {v!r})")
    keys = ("half_beams", "front_bins", "max_bins", "smooth_bins", "n_iter", "fit_front_bins", "flank_bins",
            "lead_bins", "align_beams", "peak_bins")
    for key, v, lo in zip(keys, (*window, *flank_lead_align), (0, 0, 3, 1, 1, 0, 0, 0, 0, 0)):
        if isinstance(v, bool) or int(v) != v or v < lo:
            raise InputError(f"{key}: must be an integer >= {lo} (got {v!r})")
    if not 0 < fraction < 1:
        raise InputError(f"fraction: must lie in (0, 1) (got {fraction})")
    if scan not in ("forward", "back"):
        raise InputError(f"scan: must be 'forward' or 'back' (got {scan!r})")
    if sel.shape != (echoes.n_beams,):
        raise InputError(f"first: expected shape ({echoes.n_beams},), got {sel.shape}")
    if clip is not None and np.shape(clip) != shape:
        raise InputError(f"clip: expected the image's shape {shape}, got {np.shape(clip)}")


def _edges_kept(echoes: Echoes, n_kept: int, fields: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                marked: np.ndarray, n_marked: int) -> Echoes:
    """``echoes`` with the pooled leading edges kept (:func:`_kernels.kept_edges`: their number,
    the echoes' new ``edge_bin``, ``edge_range_m``, ``slope`` and ``sigma_m``, the echoes whose
    kept edge is that of a fitted clipped echo and their number).  A pooled edge is kept where it
    belongs to the beam's own echo: within find_echoes' walk in front of its first structure bin
    and before its last (else a neighbouring surface pulled it)."""
    if not n_kept:
        return echoes
    eb, er, sl, sig = fields
    if n_marked:
        return echoes.replaced(edge_bin=eb, edge_range_m=er, slope=sl, sigma_m=sig, clip_fitted=marked)
    return echoes.replaced(edge_bin=eb, edge_range_m=er, slope=sl, sigma_m=sig)
