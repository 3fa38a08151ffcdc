"""Per-beam range measurements from a segmentation: first or strongest return, with confidence.

Mapping needs one trustworthy range per beam or an explicit "nothing here": every false range
becomes a false surface.  :func:`extract_ranges` turns a label image (or boolean mask) into a
:class:`BeamRanges`, where "no return" is ``bin == -1`` and ``range_m = NaN``, never a number that
looks like a range.

Rules (applied in this order)
-----------------------------
0. **Narrow components** (``min_component_beams``).  Structure pixels are grouped into
   8-connected components; components spanning fewer than ``min_component_beams`` beams and
   fewer than ``min_component_bins`` range bins are discarded (off by default).  Surfaces (hull,
   seafloor, rudder) extend over many beams, or over many bins when steep; speckle and fish
   appear as blobs a few beams wide and 2-5 bins tall.
   Components within ``link_beams`` beams (and 1 bin) of a kept one are kept as well, so a
   surface broken into pieces by fading survives while isolated blobs do not.
1. **Return per beam.**  ``mode="first"``: the nearest range bin that starts a run of at least
   ``min_run`` consecutive structure bins (a lone speckle pixel in front of the surface is skipped
   when ``min_run > 1``).  ``mode="strongest"``: the structure bin of highest intensity.
2. **Isolated-return rejection** (``reject_isolated``).  A return on beam ``j`` is *supported* by
   beam ``k`` (``0 < |k - j| <= neighbour_beams``) when ``k`` has a return within
   ``max_jump_bins`` range bins.  An unsupported first return is replaced by the beam's next
   return (the next structure run behind it), up to three times, then removed; a pair of
   mutually supporting returns survives.  Surfaces are continuous across beams; isolated
   detections are speckle, fish or side-lobe leaks.
3. **Short-segment rejection** (``min_segment_beams``).  Consecutive beams whose returns differ
   by at most ``max_jump_bins`` form a segment; segments spanning fewer than
   ``min_segment_beams`` beams are removed (off by default).
4. **Leading-edge refinement** (``refine_bins``, first returns only).  The return moves up to
   ``refine_bins`` bins towards the sonar while the mean intensity of the 3 bins x 3 beams box
   centred on the bin above stays >= ``edge_level`` (off by default).
5. **Confidence** of a kept return = the fraction of its existing neighbour beams
   (``|k - j| <= neighbour_beams``) that support it, in [0, 1]; NaN-free, 0 where no return.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry

if TYPE_CHECKING:
    from sonarmap.ranges.echoes import Echoes
    from sonarmap.ranges.tracking import Tracks

__all__ = ["BeamRanges", "extract_ranges", "ranges_from_tracks", "track_returns", "no_returns", "first_return_bins", "wide_components",
           "rule0"]

Mode = Literal["first", "strongest"]


@dataclasses.dataclass(frozen=True, eq=False)
class BeamRanges:
    """One ping's per-beam returns.

    Attributes
    ----------
    range_m : ndarray of float64, shape (n_beams,)
        Range of the return in metres (``geometry.range_m`` of its bin); NaN = no return.
    bin : ndarray of int64, shape (n_beams,)
        0-based range bin of the return; -1 = no return.
    intensity : ndarray of float32, shape (n_beams,)
        Strength of the return's echo: the intensity of the image the classifier saw at the
        echo's first peak (the surface tracker, in either range mode; the per-beam rules: at the
        return's bin); NaN = no return.
    confidence : ndarray of float32, shape (n_beams,)
        Neighbour-beam support in [0, 1] (0 where no return).
    azimuth_rad : ndarray of float64, shape (n_beams,)
        Beam azimuths.
    time_ns : int
        Ping time.
    source : str
        Ping source (file path).
    mode : str
        ``"first"`` or ``"strongest"``.
    sigma_m : ndarray of float64, shape (n_beams,)
        One-sigma uncertainty of ``range_m`` in metres (from the pulse length, the bin size and
        the echo's signal-to-background ratio; :func:`sonarmap.ranges.echoes.range_sigma_m`);
        NaN where there is no return or no estimate.
    p_detect : ndarray of float32, shape (n_beams,)
        Probability that a surface in this beam is detected and reported (the mapping sensor
        model's pD for this beam); NaN where unknown.
    other_range_m : ndarray of float64, shape (n_other, n_beams)
        Leading-edge ranges of further surfaces behind the reported return on each beam (nearest
        first); NaN where none.  ``n_other`` may be 0.
    """

    range_m: NDArray[np.float64]
    bin: NDArray[np.int64]
    intensity: NDArray[np.float32]
    confidence: NDArray[np.float32]
    azimuth_rad: NDArray[np.float64]
    time_ns: int = 0
    source: str = ""
    mode: str = "first"
    sigma_m: NDArray[np.float64] | None = None
    p_detect: NDArray[np.float32] | None = None
    other_range_m: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        n = np.asarray(self.azimuth_rad).shape[0]
        if self.sigma_m is None:
            object.__setattr__(self, "sigma_m", np.full(n, np.nan))
        if self.p_detect is None:
            object.__setattr__(self, "p_detect", np.full(n, np.nan, dtype=np.float32))
        if self.other_range_m is None:
            object.__setattr__(self, "other_range_m", np.full((0, n), np.nan))
        object.__setattr__(self, "sigma_m", np.asarray(self.sigma_m, dtype=np.float64))
        object.__setattr__(self, "p_detect", np.asarray(self.p_detect, dtype=np.float32))
        object.__setattr__(self, "other_range_m", np.asarray(self.other_range_m, dtype=np.float64))
        for name in ("range_m", "bin", "intensity", "confidence", "sigma_m", "p_detect"):
            if np.asarray(getattr(self, name)).shape != (n,):
                raise InputError(f"{name}: expected shape ({n},)")
        if self.other_range_m.ndim != 2 or self.other_range_m.shape[1] != n:
            raise InputError(f"other_range_m: expected shape (n_other, {n}), got {self.other_range_m.shape}")
        b = np.asarray(self.bin)
        if not np.array_equal(b < 0, ~np.isfinite(np.asarray(self.range_m))):
            raise InputError("bin/range_m: no-return beams must have bin -1 and range NaN together")

    @classmethod
    def _checked_already(cls, **fields: object) -> BeamRanges:
        """A :class:`BeamRanges` of ``fields`` that are already of the types, dtypes and shapes
        :meth:`__post_init__` checks and converts to (a kernel's outputs), without running it;
        ``p_detect`` is NaN and every field must be given except it."""
        new = object.__new__(cls)
        new.__dict__.update(fields)
        new.__dict__["p_detect"] = np.full(np.shape(fields["azimuth_rad"])[0], np.nan, dtype=np.float32)
        return new

    def with_p_detect(self, p_detect: ArrayLike) -> BeamRanges:
        """A copy with ``p_detect`` replaced (``dataclasses.replace`` without re-checking the
        other fields, which this object's construction checked already)."""
        p = np.asarray(p_detect, dtype=np.float32)
        if p.shape != self.bin.shape:
            raise InputError(f"p_detect: expected shape {self.bin.shape}, got {p.shape}")
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.__dict__["p_detect"] = p
        return new

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Beams with a return."""
        return self.bin >= 0

    @property
    def n_returns(self) -> int:
        """Number of beams with a return."""
        return int(np.count_nonzero(self.valid))

    @property
    def n_beams(self) -> int:
        """Number of beams."""
        return int(self.bin.size)


def no_returns(geometry: SonarGeometry, *, time_ns: int = 0, source: str = "", mode: str = "first") -> BeamRanges:
    """A :class:`BeamRanges` with no return on any beam."""
    n = geometry.n_beams
    # (of the checked types and shapes by construction: BeamRanges' checks skipped)
    return BeamRanges._checked_already(
        range_m=np.full(n, np.nan), bin=np.full(n, -1, dtype=np.int64),
        intensity=np.full(n, np.nan, dtype=np.float32), confidence=np.zeros(n, dtype=np.float32),
        azimuth_rad=np.asarray(geometry.azimuth_rad, dtype=np.float64), time_ns=int(time_ns),
        source=source, mode=mode, sigma_m=np.full(n, np.nan), other_range_m=np.full((0, n), np.nan),
    )


def first_return_bins(mask: ArrayLike, *, min_run: int = 1) -> NDArray[np.int64]:
    """Per beam, the first bin starting a run of ``min_run`` true bins; -1 if none."""
    from sonarmap.ranges._kernels import first_runs

    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise InputError(f"mask: expected (n_bins, n_beams), got shape {m.shape}")
    if min_run < 1:
        raise InputError(f"min_run: must be >= 1 (got {min_run})")
    return first_runs(m, int(min_run))


def wide_components(
    mask: ArrayLike, min_beams: int, *, min_bins: int | None = None, seeds: ArrayLike | None = None
) -> NDArray[np.bool_]:
    """Keep the 8-connected components of ``mask`` spanning >= ``min_beams`` beams or >= ``min_bins``
    bins (and, if ``seeds`` is given, containing at least one seed pixel: hysteresis growth)."""
    from sonarmap.ranges._kernels import wide_components as kernel

    m = np.ascontiguousarray(mask, dtype=bool)
    if m.ndim != 2:
        raise InputError(f"mask: expected (n_bins, n_beams), got shape {m.shape}")
    sd = m if seeds is None else np.ascontiguousarray(seeds, dtype=bool)
    if sd.shape != m.shape:
        raise InputError(f"seeds: shape {sd.shape} does not match mask {m.shape}")
    return kernel(m, sd, int(min_beams), int(min_bins) if min_bins is not None else 0)


def rule0(mask: NDArray[np.bool_], min_beams: int, min_bins: int | None, link_beams: int,
          min_pixels: int = 0) -> NDArray[np.bool_]:
    """Rule 0 (wide components, then linked pieces) in one kernel: same as :func:`wide_components`
    followed by :func:`_link_components`."""
    return _components(mask, (min_beams, min_bins, link_beams, min_pixels), None, 0.0)


def component_rule(mask: NDArray[np.bool_], min_component_beams: int = 1, min_component_bins: int | None = None,
                   link_beams: int = 0, min_component_pixels: int = 0, *, geometry: SonarGeometry | None = None,
                   min_extent_m: float = 0.0) -> NDArray[np.bool_]:
    """Rule 0 of :func:`extract_ranges` with its parameters (the mask unchanged when it is off),
    then, given ``geometry`` and ``min_extent_m > 0``, :func:`drop_small_components` on the result
    (in the same pass: the components of rule 0's result are the components it kept)."""
    rule_on = min_component_beams > 1 or min_component_pixels > 0
    rule = (min_component_beams, min_component_bins, link_beams, min_component_pixels) if rule_on else None
    if geometry is None or not min_extent_m > 0:
        return _components(mask, rule, None, 0.0) if rule_on else mask
    return _components(mask, rule, geometry, min_extent_m)


def drop_small_components(mask: NDArray[np.bool_], geometry: SonarGeometry, min_extent_m: float) -> NDArray[np.bool_]:
    """Drop the 8-connected components of ``mask`` smaller than ``min_extent_m`` both across range
    (arc length at the component's far edge, one beam spacing included) and along range."""
    m = np.asarray(mask, dtype=bool)
    if not min_extent_m > 0:
        return m
    return _components(m, None, geometry, min_extent_m)


_NO_AXIS = np.zeros(1)


def _components(mask: NDArray[np.bool_], rule: tuple[int, int | None, int, int] | None,
                geometry: SonarGeometry | None, min_extent_m: float) -> NDArray[np.bool_]:
    """The component rules in one kernel (:func:`_kernels.linked_components`): rule 0 with
    ``rule = (min_beams, min_bins, link_beams, min_pixels)`` (None: every component), then the
    metric extent rule when ``geometry`` is given and ``min_extent_m > 0``."""
    import sonarmap.ranges._kernels as _rk

    m = np.ascontiguousarray(mask, dtype=bool)
    if m.ndim != 2:
        raise InputError(f"mask: expected (n_bins, n_beams), got shape {m.shape}")
    beams, bins, link, pixels = rule if rule is not None else (1, None, 0, 0)
    r, az, dr, daz = _NO_AXIS, _NO_AXIS, 0.0, 0.0
    if geometry is not None and min_extent_m > 0:
        r = np.ascontiguousarray(geometry.range_m, dtype=np.float64)
        az = np.ascontiguousarray(geometry.azimuth_rad, dtype=np.float64)
        if r.size < m.shape[0] or az.size < m.shape[1]:
            raise InputError(f"mask: shape {m.shape} exceeds the geometry's {(r.size, az.size)}")
        dr = abs(geometry.range_resolution_m)
        daz = float(abs(az[-1] - az[0]) / (az.size - 1)) if az.size > 1 else 0.0
    return _rk.linked_components(m, int(beams), int(bins) if bins is not None else 0, int(link), 4 if link > 0 else 0,
                                 int(pixels), rule is not None, r, az, float(dr), daz,
                                 float(min_extent_m) if geometry is not None else 0.0)


def half_peak_edges(ranges: BeamRanges, image: ArrayLike, mask: ArrayLike, geometry: SonarGeometry, *,
                    fraction: float = 0.5) -> BeamRanges:
    """Move each first return to the leading edge of its echo: the first crossing of ``fraction``
    of the echo's first peak (the range convention of ``DESIGN.md``).

    From the reported bin, the echo's first peak is the first local maximum of ``image`` along the
    beam within the run of ``mask`` that starts there; the edge is the first bin of that run whose
    value reaches ``fraction`` x the peak, interpolated linearly to sub-bin ``range_m`` (``bin``
    is the bin at or after the crossing).  ``image`` should be smooth along range (the normalised,
    multi-looked image is).  Strongest-mode ranges are returned unchanged.
    """
    if ranges.mode != "first" or ranges.n_returns == 0:
        return ranges
    from sonarmap.ranges._kernels import half_peak_edges as kernel

    img = np.ascontiguousarray(image, dtype=np.float64)
    m = np.ascontiguousarray(mask, dtype=bool)
    if img.shape != m.shape or img.ndim != 2 or img.shape[1] != ranges.n_beams:
        raise InputError(f"image/mask: shapes {img.shape} / {m.shape} do not match {ranges.n_beams} beams")
    r = np.asarray(geometry.range_m, dtype=np.float64)
    b_out, frac = kernel(img, m, np.ascontiguousarray(ranges.bin, dtype=np.int64), float(fraction))
    ok = b_out >= 0
    r_out = np.full(b_out.shape, np.nan)
    prev = np.maximum(b_out - 1, 0)
    r_out[ok] = r[b_out[ok]] - frac[ok] * (r[b_out[ok]] - r[prev[ok]])
    i_out = np.full(b_out.shape, np.nan, dtype=np.float32)
    i_out[ok] = img[b_out[ok], np.flatnonzero(ok)].astype(np.float32)
    return dataclasses.replace(ranges, bin=b_out, range_m=r_out, intensity=i_out)


def _link_components(mask: NDArray[np.bool_], kept: NDArray[np.bool_], gap: int, rounds: int = 4) -> NDArray[np.bool_]:
    """Add components of ``mask`` within ``gap`` beams and 1 bin of ``kept`` ones (chained)."""
    from sonarmap.ranges._kernels import near_mask

    for _ in range(rounds):
        rest = mask & ~kept
        seeds, hit = near_mask(kept, rest, int(gap))
        if not hit:
            break
        kept = kept | wide_components(rest, 1, seeds=seeds)
    return kept


def _support(bins: NDArray[np.int64], neighbour_beams: int, max_jump: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(number of supporting neighbours, number of existing neighbours) per beam."""
    if bins.dtype == np.int64 and bins.ndim == 1:
        from sonarmap.ranges._kernels import support_counts

        return support_counts(bins, int(neighbour_beams), int(max_jump))
    n = bins.size
    sup = np.zeros(n, dtype=np.int64)
    cnt = np.zeros(n, dtype=np.int64)
    valid = bins >= 0
    for off in range(1, neighbour_beams + 1):
        for s in (off, -off):
            lo, hi = max(0, -s), n - max(0, s)
            if hi <= lo:
                continue
            a = bins[lo:hi]
            b = bins[lo + s:hi + s]
            cnt[lo:hi] += 1
            sup[lo:hi] += (valid[lo:hi] & valid[lo + s:hi + s] & (np.abs(a - b) <= max_jump)).astype(np.int64)
    return sup, cnt


def _refine_leading_edge(img: NDArray[np.float32], bins: NDArray[np.int64], k_max: int, level: float) -> NDArray[np.int64]:
    """Move first returns up while the 3-bin x 3-beam box mean above them is >= ``level``."""
    from sonarmap.ranges._kernels import refine_leading_edge

    return refine_leading_edge(np.ascontiguousarray(img, dtype=np.float32), bins, int(k_max), float(level))


def _segments_short(bins: NDArray[np.int64], max_jump: int, min_beams: int) -> NDArray[np.bool_]:
    """Beams whose return lies in a segment shorter than ``min_beams`` beams."""
    n = bins.size
    drop = np.zeros(n, dtype=bool)
    start = 0
    while start < n:
        if bins[start] < 0:
            start += 1
            continue
        end = start + 1
        while end < n and bins[end] >= 0 and abs(int(bins[end]) - int(bins[end - 1])) <= max_jump:
            end += 1
        if end - start < min_beams:
            drop[start:end] = True
        start = end
    return drop


def extract_ranges(
    labels_or_mask: ArrayLike,
    image: ArrayLike,
    geometry: SonarGeometry,
    *,
    mode: Mode = "first",
    structure_label: int = 1,
    min_run: int = 1,
    reject_isolated: bool = True,
    neighbour_beams: int = 2,
    max_jump_bins: int = 8,
    min_segment_beams: int = 1,
    min_component_beams: int = 1,
    min_component_bins: int | None = None,
    link_beams: int = 0,
    min_component_pixels: int = 0,
    refine_bins: int = 0,
    edge_level: float | None = None,
    accepted: ArrayLike | None = None,
    time_ns: int = 0,
    source: str = "",
) -> BeamRanges:
    """Per-beam first or strongest return of structure (see the module notes for the rules).

    Parameters
    ----------
    labels_or_mask : ndarray, shape (n_bins, n_beams)
        Boolean structure mask, or integer labels where ``structure_label`` marks structure.
    image : ndarray, shape (n_bins, n_beams)
        Intensities (for ``"strongest"`` and the reported intensity).
    geometry : SonarGeometry
        Gives metres per bin and beam azimuths.
    mode : {"first", "strongest"}
    structure_label : int
        Label value of structure (ignored for a boolean mask).
    min_run : int
        First return: minimum run of consecutive structure bins.
    reject_isolated, neighbour_beams, max_jump_bins, min_segment_beams
        Consistency rules 2-3.
    min_component_beams, min_component_bins : int
        Rule 0: keep a component spanning >= this many beams, or bins (default: beams only).
    min_component_pixels : int
        Rule 0 also keeps a component of at least this many pixels (0: off) - a compact solid
        target (a propeller blade seen edge-on) narrower than a surface but denser than a fish.
    link_beams : int
        Rule 0b: a rejected component lying within ``link_beams`` beams and 1 bin of a kept
        one is kept too (chained up to 4 times) - a faint surface broken by speckle into pieces.
    refine_bins, edge_level : int, float
        Rule 4 (first returns only): move each first return up (towards the sonar) by up to
        ``refine_bins`` bins while the mean of ``image`` over 3 bins x 3 beams centred on the bin
        above stays >= ``edge_level`` - the leading edge of a speckled surface band, where
        the segmentation's first pixel is often a few bins late.
    accepted : ndarray of bool, shape (n_bins, n_beams), optional
        Structure pixels accepted without rule 0 (added after it; e.g. pooled band detections,
        already validated as wide components); a first return on one is not moved by rule 4.
    time_ns, source
        Copied into the result.  The rules leave a beam without a return as -1 / NaN.

    Returns
    -------
    BeamRanges
    """
    lab, img = np.asarray(labels_or_mask), np.asarray(image, dtype=np.float32)
    geometry.check_image(lab, "labels_or_mask")
    geometry.check_image(img, "image")
    if mode not in ("first", "strongest"):
        raise InputError(f"mode: must be 'first' or 'strongest' (got {mode!r})")
    if min_run < 1 or neighbour_beams < 1 or max_jump_bins < 0 or min_segment_beams < 1:
        raise InputError("min_run, neighbour_beams, min_segment_beams must be >= 1; max_jump_bins >= 0")
    mask = lab if lab.dtype == np.bool_ else (lab == structure_label)
    mask = component_rule(mask, min_component_beams, min_component_bins, link_beams, min_component_pixels)
    mask, acc_only = _with_accepted(mask, accepted, geometry)
    bins = _pick_bins(mask, img, mode, min_run)
    if reject_isolated:
        bins = _reject_isolated(bins, mask, mode, min_run, neighbour_beams, max_jump_bins)
    if min_segment_beams > 1:
        bins = np.where(_segments_short(bins, max_jump_bins, min_segment_beams), -1, bins)
    if refine_bins > 0 and edge_level is not None and mode == "first":
        bins = _refined_unless_accepted(img, bins, refine_bins, float(edge_level), acc_only)
    return _beam_ranges(bins, img, geometry, mode, neighbour_beams, max_jump_bins, time_ns, source)


def _with_accepted(
    mask: np.ndarray, accepted: ArrayLike | None, geometry: SonarGeometry
) -> tuple[np.ndarray, np.ndarray | None]:
    """``mask`` plus the ``accepted`` pixels, and the accepted pixels that rule 0 did not keep."""
    if accepted is None:
        return mask, None
    acc = np.asarray(accepted, dtype=bool)
    geometry.check_image(acc, "accepted")
    return mask | acc, acc & ~mask


def _refined_unless_accepted(
    img: np.ndarray, bins: np.ndarray, refine_bins: int, edge_level: float, acc_only: np.ndarray | None
) -> np.ndarray:
    """Rule 4 on every first return except those on accepted-only pixels."""
    refined = _refine_leading_edge(img, bins, refine_bins, edge_level)
    if acc_only is None:
        return refined
    # accepted (pooled) picks are the band's peak: not moved by the leading-edge rule
    keep = (bins >= 0) & acc_only[np.maximum(bins, 0), np.arange(bins.size)]
    return np.where(keep, bins, refined)


def _pick_bins(mask: np.ndarray, img: np.ndarray, mode: Mode, min_run: int) -> np.ndarray:
    """Per-beam bin of the first run of ``min_run`` structure bins, or of the strongest one (-1: none)."""
    if mode == "first":
        return first_return_bins(mask, min_run=min_run)
    masked = np.where(mask, img, -np.inf)
    bins = masked.argmax(axis=0).astype(np.int64)
    bins[~mask.any(axis=0)] = -1
    return bins


def _reject_isolated(bins: np.ndarray, mask: np.ndarray, mode: Mode, min_run: int,
                     neighbour_beams: int, max_jump_bins: int) -> np.ndarray:
    """Rule 2: drop returns without support from neighbouring beams.

    A rejected first return falls back to the beam's next return (up to 3 times); ``mask`` is
    not modified.
    """
    for attempt in range(4 if mode == "first" else 1):
        sup, _ = _support(bins, neighbour_beams, max_jump_bins)
        bad = (bins >= 0) & (sup == 0)
        if not bad.any():
            break
        if mode != "first" or attempt == 3:
            bins = np.where(bad, -1, bins)
            break
        mask = mask.copy() if attempt == 0 else mask
        for j in np.flatnonzero(bad):
            b = int(bins[j])
            end = b
            while end < mask.shape[0] and mask[end, j]:
                end += 1
            mask[:end, j] = False
        bins = np.where(bad, first_return_bins(np.ascontiguousarray(mask[:, bad]), min_run=min_run)[np.cumsum(bad) - 1], bins)
    return bins


def _beam_ranges(bins: np.ndarray, img: np.ndarray, geometry: SonarGeometry, mode: Mode, neighbour_beams: int,
                 max_jump_bins: int, time_ns: int, source: str) -> BeamRanges:
    """The :class:`BeamRanges` of per-beam bins ``bins`` (-1: no return), with neighbour-support confidence."""
    valid = bins >= 0
    sup, cnt = _support(bins, neighbour_beams, max_jump_bins)
    conf = np.where(valid, sup / np.maximum(cnt, 1), 0.0).astype(np.float32)
    cols = np.arange(bins.size)
    safe = np.where(valid, bins, 0)
    rng = np.where(valid, geometry.range_m[safe], np.nan)
    inten = np.where(valid, img[safe, cols], np.nan).astype(np.float32)
    return BeamRanges(
        range_m=rng.astype(np.float64), bin=bins, intensity=inten, confidence=conf,
        azimuth_rad=np.asarray(geometry.azimuth_rad, dtype=np.float64), time_ns=int(time_ns),
        source=source, mode=mode,
    )


def ranges_from_tracks(echoes: "Echoes", tracks: "Tracks", geometry: SonarGeometry, image: ArrayLike, *,
                       mode: Mode = "first", time_ns: int = 0, source: str = "") -> BeamRanges:
    """The :class:`BeamRanges` of tracked surfaces: per beam the nearest tracked echo's leading
    edge (``mode="first"``) or peak (``"strongest"``), its sigma, the intensity of ``image`` at
    the echo's first peak (either mode: the echo's strength, not the sample on its rise) and the
    surfaces behind it.  ``p_detect`` is left NaN (the pipeline sets it from the ping's model)."""
    return track_returns(echoes, tracks, geometry, image, mode=mode, time_ns=time_ns, source=source)[0]


def track_returns(echoes: "Echoes", tracks: "Tracks", geometry: SonarGeometry, image: ArrayLike, *,
                  mode: Mode = "first", time_ns: int = 0, source: str = "") -> tuple[BeamRanges, NDArray[np.int64]]:
    """:func:`ranges_from_tracks` and the number of bins each return's echo spans (``stop_bin -
    start_bin`` of the nearest tracked echo; 0 where no return), from one kernel pass."""
    import sonarmap.ranges._kernels as _rk

    e = np.ascontiguousarray(tracks.echo, dtype=np.int64)
    if not (e[0] >= 0).any():
        return no_returns(geometry, time_ns=time_ns, source=source, mode=mode), np.zeros(e.shape[1], dtype=np.int64)
    img = np.asarray(image, dtype=np.float32)
    geometry.check_image(img, "image")
    at = echoes.edge_range_m if mode == "first" else echoes.peak_range_m
    rng, b, inten, sigma, other, conf, thick, consistent = _rk.track_ranges(
        e, echoes.edge_bin, echoes.peak_bin, at, echoes.sigma_m, img, mode == "first", echoes.start_bin,
        echoes.stop_bin)
    fields = dict(range_m=rng, bin=b, intensity=inten, confidence=conf,
                  azimuth_rad=np.asarray(geometry.azimuth_rad, dtype=np.float64), time_ns=int(time_ns),
                  source=source, mode=mode, sigma_m=sigma, other_range_m=other)
    if rng.shape != fields["azimuth_rad"].shape or not consistent:  # type: ignore[union-attr]
        return BeamRanges(**fields), thick  # type: ignore[arg-type]  # (raises the constructor's error)
    # the kernel's arrays have BeamRanges' dtypes and shapes
    return BeamRanges._checked_already(**fields), thick
