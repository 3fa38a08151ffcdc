"""Sonar geometry: beams, range bins, beam pattern, taper and acoustic constants.

Conventions
-----------
* Images are ``(n_bins, n_beams)``: row ``i`` is range bin ``i`` (row 0 nearest), column ``j`` is
  beam ``j`` with azimuth increasing with ``j``.
* ``azimuth_rad`` is measured in the sonar's horizontal (imaging) plane from its forward axis,
  **positive to starboard** (clockwise seen from above), i.e. the forward-right-down (FRD) body
  convention of marine robotics.  A point at range ``r`` and azimuth ``a`` (zero elevation) is at
  ``x = r cos a`` (forward), ``y = r sin a`` (right).  Readers of formats with other conventions
  (ARIS: beam 0 right-most; ROS: y to port) convert at the boundary.
* Range bin ``i`` of a window ``[min_range, max_range)`` with ``n`` bins lies at
  ``min_range + i * (max_range - min_range) / n`` - the convention of the DIDSON PNG+JSON data
  (row 0 = ``min_range``) and of ARIS (``start + i * period``).  An explicit, possibly non-uniform
  table can be given instead.
* Per-beam azimuths are always a table; they are only assumed uniform over ``fov`` when no table
  exists, with a :class:`GeometryWarning`.

The JSON format is that of the paper authors' data (``min_range``, ``max_range``, ``fov``,
``num_beams``, ``num_bins``, ``noise``, ``rx_gain``, ``psf``, ``taper``, optional ``azimuths``),
extended with optional ``ranges``, ``frequency``, ``sound_speed``, ``name``.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import json
import math
import os
import threading
import warnings
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap._atomic import atomic_write_text
from sonarmap.errors import GeometryError, SonarmapWarning

__all__ = [
    "plausible_elevation_beamwidth",
    "SonarGeometry",
    "GeometryWarning",
    "load_geometry",
    "save_geometry",
    "geometry_from_dict",
    "geometry_from_json_bytes",
    "geometry_from_sidecar_bytes",
    "geometry_summary",
    "preset",
    "preset_names",
    "uniform_azimuths",
    "MAX_BEAMS",
    "MAX_BINS",
    "MAX_RANGE_M",
    "SINGLE_BEAM_WIDTH_RAD",
    "oculus_azimuth_beamwidth_rad",
    "ARIS_LENS",
]

#: Largest beam count accepted, from files and in the constructor (imaging sonars have <= 1024).
MAX_BEAMS = 4096
#: Largest range-bin count accepted (ARIS records at most a few thousand samples per beam).
MAX_BINS = 65536
#: Largest range in metres accepted: the slant range of a full-ocean-depth multibeam (11 km deep,
#: beams to 60 degrees) is ~22 km; imaging-sonar readers apply their own, much tighter window limit.
MAX_RANGE_M = 25_000.0
#: Field of view (= beam width) given to a single-beam geometry built without ``fov_rad``: one
#: azimuth says nothing about the beam's width, so a nominal 1 degree is assumed, with a
#: :class:`GeometryWarning`.  Pass ``fov_rad`` to state the real width.
SINGLE_BEAM_WIDTH_RAD = math.radians(1.0)

_TWO_PI = 2.0 * math.pi
#: Geometry JSON files up to this size are parsed once and cached by content.
_CACHE_MAX_BYTES = 1024 * 1024


class GeometryWarning(SonarmapWarning):
    """A geometry had to be completed by assumption (e.g. uniform azimuths)."""


def _describe(value: object) -> str:
    """A short one-line description of a (possibly huge or nested) value for an error message."""
    if value is None or isinstance(value, bool | np.bool_):
        return repr(bool(value)) if value is not None else "null"
    if isinstance(value, np.integer | np.floating):
        value = value.item()
    if isinstance(value, int):
        bits = value.bit_length()
        return str(value) if bits <= 64 else f"an integer of about {int(bits * 0.30103) + 1} digits"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return repr(value) if len(value) <= 40 else repr(value[:37]) + "..."
    if isinstance(value, list | tuple):
        return f"a {type(value).__name__} of {len(value)} items"
    if isinstance(value, Mapping):
        return f"an object with {len(value)} keys"
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape} and dtype {value.dtype}"
    return f"a {type(value).__name__}"


def _real(value: object, what: str) -> float:
    """``value`` as a finite float; bools, strings, containers and NaN/inf are refused.

    Raises
    ------
    GeometryError
        ``"<what> must be a number, got ..."`` or ``"<what> must be finite, got ..."``.
    """
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | float | np.integer | np.floating):
        raise GeometryError(f"{what} must be a number, got {_describe(value)}")
    try:
        out = float(value)
    except OverflowError:
        raise GeometryError(f"{what} must be a finite number, got {_describe(value)}") from None
    if not math.isfinite(out):
        raise GeometryError(f"{what} must be finite, got {out!r}")
    return out


def _count(value: object, what: str, maximum: int) -> int:
    """``value`` as an integer count in ``1..maximum`` (integral floats such as ``512.0`` pass).

    Raises
    ------
    GeometryError
        If ``value`` is a bool, not a number, not integral, not finite or out of range.
    """
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | float | np.integer | np.floating):
        raise GeometryError(f"{what} must be an integer, got {_describe(value)}")
    if isinstance(value, float | np.floating) and not (math.isfinite(value) and float(value).is_integer()):
        raise GeometryError(f"{what} must be an integer, got {_describe(value)}")
    n = int(value)
    if not 1 <= n <= maximum:
        raise GeometryError(f"{what} must be between 1 and {maximum}, got {_describe(value)}")
    return n


def _real_list(value: object, what: str, max_len: int) -> NDArray[np.float64]:
    """A non-empty list of at most ``max_len`` finite numbers (no bools, strings or nesting).

    Raises
    ------
    GeometryError
        Naming the first offending entry.
    """
    if isinstance(value, np.ndarray):
        if value.ndim != 1 or value.dtype.kind not in "iuf":
            raise GeometryError(f"{what} must be a list of numbers, got {_describe(value)}")
        items: list[Any] = value.tolist()
    elif isinstance(value, list | tuple):
        items = list(value)
    else:
        raise GeometryError(f"{what} must be a list of numbers, got {_describe(value)}")
    if not 1 <= len(items) <= max_len:
        raise GeometryError(f"{what} must have 1 to {max_len} entries, got {len(items)}")
    return np.array([_real(v, f"{what} entry {i}") for i, v in enumerate(items)], dtype=np.float64)


def _frozen_array(
    values: ArrayLike, name: str, *, ndim: int = 1, max_size: int | None = None
) -> NDArray[np.float64]:
    try:
        raw = np.asarray(values)
        if raw.dtype.kind not in "iufO":
            raise TypeError(f"dtype {raw.dtype}")
        arr = np.array(raw, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise GeometryError(f"{name}: not a numeric array ({exc})") from None
    if arr.ndim != ndim:
        raise GeometryError(f"{name}: expected {ndim}-D array, got shape {arr.shape}")
    if max_size is not None and arr.size > max_size:
        raise GeometryError(f"{name}: {arr.size} entries, more than the {max_size} supported")
    if not np.all(np.isfinite(arr)):
        raise GeometryError(f"{name}: contains NaN or infinite values")
    arr.setflags(write=False)
    return arr


def uniform_azimuths(n_beams: int, fov_rad: float) -> NDArray[np.float64]:
    """Beam centres uniformly spread over ``fov_rad``, centred on zero.

    Each beam covers ``fov/n``; centres are at ``-fov/2 + (j + 1/2) fov/n``.

    Parameters
    ----------
    n_beams : int
        Number of beams, ``1..MAX_BEAMS``.
    fov_rad : float
        Field of view in radians, in ``(0, 2 pi]``.

    Returns
    -------
    ndarray, shape (n_beams,)
        Beam centre azimuths in radians.

    Raises
    ------
    GeometryError
        If ``n_beams`` is not an integer in range or ``fov_rad`` is not a finite angle in range.
    """
    n = _count(n_beams, "num_beams", MAX_BEAMS)
    fov = _real(fov_rad, "fov")
    if not 0.0 < fov <= _TWO_PI:
        raise GeometryError(f"fov must be in (0, 2 pi] rad, got {fov!r}")
    step = fov / n
    return -fov / 2 + (np.arange(n) + 0.5) * step


def _checked_axes(
    azimuth_rad: ArrayLike, range_m: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Frozen float64 copies of a geometry's azimuth and range tables, checked (non-empty, strictly
    increasing, azimuths in (-pi, pi), ranges in ``[0, MAX_RANGE_M]``)."""
    az = _frozen_array(azimuth_rad, "azimuth_rad", max_size=MAX_BEAMS)
    rng = _frozen_array(range_m, "range_m", max_size=MAX_BINS)
    if az.size < 1:
        raise GeometryError("azimuth_rad: at least one beam is required")
    if rng.size < 1:
        raise GeometryError("range_m: at least one range bin is required")
    if az.size > 1 and np.any(np.diff(az) <= 0):
        raise GeometryError("azimuth_rad: beam azimuths must be strictly increasing")
    if np.any(np.abs(az) >= math.pi):
        raise GeometryError("azimuth_rad: azimuths must lie in (-pi, pi)")
    if rng.size > 1 and np.any(np.diff(rng) <= 0):
        raise GeometryError("range_m: range bins must be strictly increasing")
    if rng[0] < 0:
        raise GeometryError(f"range_m: ranges must be non-negative (first is {rng[0]})")
    if rng[-1] > MAX_RANGE_M:
        raise GeometryError(f"range_m: ranges must be at most {MAX_RANGE_M:g} m (last is {rng[-1]:g})")
    return az, rng


def _checked_window(window: Any) -> tuple[float, float]:
    """A ``(min_range, max_range)`` window as floats with ``0 <= min < max <= MAX_RANGE_M``."""
    try:
        lo_v, hi_v = window
    except (TypeError, ValueError):
        raise GeometryError(
            f"window: must be a (min_range, max_range) pair, got {_describe(window)}"
        ) from None
    lo, hi = _real(lo_v, "window min_range"), _real(hi_v, "window max_range")
    if not 0 <= lo < hi <= MAX_RANGE_M:
        raise GeometryError(
            f"window: need 0 <= min_range < max_range <= {MAX_RANGE_M:g} m, got ({lo}, {hi})"
        )
    return lo, hi


@dataclasses.dataclass(frozen=True, eq=False)
class SonarGeometry:
    """Geometry and acoustic constants of a multibeam imaging sonar.

    Parameters
    ----------
    azimuth_rad : array_like, shape (n_beams,)
        Beam centre azimuths in radians, strictly increasing (positive to starboard).
    range_m : array_like, shape (n_bins,)
        Range of each bin in metres, strictly increasing, positive.
    psf : array_like, shape (n_beams,), optional
        Beam pattern across beams (the ``h`` of eq. 2), centred at index ``n_beams // 2``.  Defaults
        to a unit impulse (no cross-beam spreading).  Normalised to unit sum on construction.
    taper : array_like, shape (n_beams,), optional
        Per-beam gain ``k(theta)`` (eq. 5); defaults to ones.
    noise : float
        Inverse signal-to-noise ratio ``1/SNR`` used by Wiener deconvolution (eq. 4).
    fov_rad : float, optional
        Horizontal field of view in ``(0, 2 pi]``; defaults to the azimuth span plus one mean beam
        spacing.  For a single beam it is that beam's width; without it
        :data:`SINGLE_BEAM_WIDTH_RAD` is assumed with a :class:`GeometryWarning`.
    frequency_hz, sound_speed_m_s, rx_gain_db : float
        Operating frequency, sound speed and receiver gain.
    name : str
        Human-readable identifier (preset name or file stem).
    azimuth_source : str
        Where the azimuth table came from: ``"table"``, ``"preset:<name>"`` or ``"uniform"``.
    window : tuple of float, optional
        ``(min_range, max_range)`` window the bins were derived from, kept for lossless JSON output.
    elevation_beamwidth_rad : float, optional
        Full -3 dB width of the beams across the fan's plane (the vertical aperture of an imaging
        sonar, the along-track transmit beamwidth of a swath multibeam), in ``(0, pi]``; ``None``
        when the recording and the sonar model do not say it.  Written to ROS ``PingInfo``
        ``tx_beamwidths``; not used by the per-ping processing.
    azimuth_beamwidth_rad : float or array_like of shape (n_beams,), optional
        Full width of each beam's main lobe in the fan's plane (azimuth) at the **two-way -3 dB**
        level: the angle over which a point scatterer's echo - transmit times receive pattern, in
        intensity (power) - stays within half of its on-axis value.  With a Gaussian main lobe a
        point target ``P`` times above the detection threshold is seen in every beam within
        ``azimuth_beamwidth_rad x sqrt(log2(P)) / 2`` of it.  (A one-way -3 dB width ``w1`` is a
        two-way width of ``w1 / sqrt(2)``.)  A scalar applies to every beam; stored per beam
        (read-only float64) or ``None`` when unknown.  Used by the range stage's point-target
        rule (:func:`sonarmap.ranges.tracking.point_streaks`); written as ``azimuth_beamwidth``.

    Raises
    ------
    GeometryError
        If a field has the wrong type, contains NaN/inf, or is out of range: at most
        :data:`MAX_BEAMS` beams and :data:`MAX_BINS` bins, ranges in ``[0, MAX_RANGE_M]``,
        azimuths strictly increasing in ``(-pi, pi)``, ``psf``/``taper`` of one entry per beam.
    """

    azimuth_rad: NDArray[np.float64]
    range_m: NDArray[np.float64]
    psf: NDArray[np.float64] | None = None
    taper: NDArray[np.float64] | None = None
    noise: float = 1e-2
    fov_rad: float | None = None
    frequency_hz: float = 1.8e6
    sound_speed_m_s: float = 1500.0
    rx_gain_db: float = 0.0
    name: str = "sonar"
    azimuth_source: str = "table"
    window: tuple[float, float] | None = None
    psf_raw: NDArray[np.float64] | None = dataclasses.field(default=None, repr=False)
    elevation_beamwidth_rad: float | None = None
    azimuth_beamwidth_rad: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        az, rng = _checked_axes(self.azimuth_rad, self.range_m)
        object.__setattr__(self, "azimuth_rad", az)
        object.__setattr__(self, "range_m", rng)
        self._set_beam_tables(az.size)
        for field in ("noise", "frequency_hz", "sound_speed_m_s", "rx_gain_db"):
            object.__setattr__(self, field, _real(getattr(self, field), field))
        if self.noise < 0:
            raise GeometryError(f"noise: 1/SNR must be >= 0 (got {self.noise})")
        if self.frequency_hz <= 0:
            raise GeometryError(f"frequency_hz: must be positive (got {self.frequency_hz})")
        if not 1300.0 <= self.sound_speed_m_s <= 1700.0:
            raise GeometryError(
                f"sound_speed_m_s: {self.sound_speed_m_s} is outside 1300-1700 m/s (water)"
            )
        object.__setattr__(self, "fov_rad", self._checked_fov(az))
        if self.elevation_beamwidth_rad is not None:
            object.__setattr__(self, "elevation_beamwidth_rad",
                               _checked_elevation_beamwidth(self.elevation_beamwidth_rad))
        if self.azimuth_beamwidth_rad is not None:
            object.__setattr__(self, "azimuth_beamwidth_rad",
                               _checked_azimuth_beamwidth(self.azimuth_beamwidth_rad, az.size))
        if self.window is not None:
            object.__setattr__(self, "window", _checked_window(self.window))

    def _set_beam_tables(self, n: int) -> None:
        """Freeze ``psf``, ``taper`` and ``psf_raw`` (one entry per beam of ``n``), keep the raw beam
        pattern and normalise ``psf`` to unit sum; ``taper`` gains must be positive."""
        for field in ("psf", "taper", "psf_raw"):
            val = getattr(self, field)
            if val is None:
                continue
            arr = _frozen_array(val, field, max_size=MAX_BEAMS)
            if arr.size != n:
                raise GeometryError(f"{field}: length {arr.size} does not match {n} beams")
            object.__setattr__(self, field, arr)
        if self.psf is not None:
            if np.any(self.psf < 0):
                raise GeometryError("psf: beam pattern must be non-negative")
            with np.errstate(over="ignore"):
                total = float(self.psf.sum())
            if not 0 < total < math.inf:
                raise GeometryError("psf: beam pattern sums to zero" if total <= 0 else "psf: sum overflows")
            if self.psf_raw is None:
                object.__setattr__(self, "psf_raw", self.psf)
            if not math.isclose(total, 1.0, rel_tol=1e-12):
                object.__setattr__(self, "psf", _frozen_array(self.psf / total, "psf"))
        if self.taper is not None and np.any(self.taper <= 0):
            raise GeometryError("taper: per-beam gains must be positive")

    def _checked_fov(self, az: NDArray[np.float64]) -> float:
        """``fov_rad`` checked to lie in (0, 2 pi]; when None, the azimuth span plus one mean beam
        spacing (capped at 2 pi), or :data:`SINGLE_BEAM_WIDTH_RAD` with a warning for one beam."""
        if self.fov_rad is not None:
            fov = _real(self.fov_rad, "fov_rad")
            if not 0 < fov <= _TWO_PI:
                raise GeometryError(f"fov_rad: must be in (0, 2 pi] (got {fov})")
            return fov
        if az.size > 1:
            fov = float(az[-1] - az[0] + np.mean(np.diff(az)))
        else:
            # one azimuth says nothing about the beam's width; never write an fov of 0
            warnings.warn(
                f"geometry '{self.name}': a single beam without fov_rad; assuming a "
                f"{math.degrees(SINGLE_BEAM_WIDTH_RAD):g} deg beam width",
                GeometryWarning,
                stacklevel=4,  # past this method, __post_init__ and __init__: the constructor's caller
            )
            fov = SINGLE_BEAM_WIDTH_RAD
        return min(fov, _TWO_PI)

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def from_window(
        cls,
        *,
        min_range_m: float,
        max_range_m: float,
        n_bins: int,
        azimuth_rad: ArrayLike | None = None,
        n_beams: int | None = None,
        fov_rad: float | None = None,
        **kwargs: Any,
    ) -> SonarGeometry:
        """Build a geometry from a range window and either an azimuth table or ``n_beams``+``fov``.

        Bins are placed at ``min + i (max - min) / n_bins`` (row 0 = ``min_range_m``).
        """
        lo = _real(min_range_m, "min_range")
        hi = _real(max_range_m, "max_range")
        if lo < 0:
            raise GeometryError(f"min_range: must be >= 0 (got {lo})")
        if hi > MAX_RANGE_M:
            raise GeometryError(f"max_range: must be at most {MAX_RANGE_M:g} m (got {hi:g})")
        if hi <= lo:
            raise GeometryError(f"max_range ({hi}) must exceed min_range ({lo})")
        n_bins = _count(n_bins, "num_bins", MAX_BINS)  # bounded before anything is allocated
        step = (hi - lo) / n_bins
        ranges = lo + np.arange(n_bins) * step
        if azimuth_rad is None:
            if n_beams is None or fov_rad is None:
                raise GeometryError("need azimuth_rad, or both n_beams and fov_rad")
            azimuth_rad = uniform_azimuths(n_beams, fov_rad)
            kwargs.setdefault("azimuth_source", "uniform")
        return cls(
            azimuth_rad=azimuth_rad,
            range_m=ranges,
            fov_rad=fov_rad,
            window=(lo, hi),
            **kwargs,
        )

    def replace(self, **changes: Any) -> SonarGeometry:
        """Return a copy with fields replaced (``dataclasses.replace``).

        A new ``psf`` drops the raw beam pattern, a new ``range_m`` the window; new azimuths of
        another beam count keep ``azimuth_beamwidth_rad`` only when it is one width for all beams.
        """
        if "psf" in changes and "psf_raw" not in changes:
            changes["psf_raw"] = None
        if "range_m" in changes and "window" not in changes:
            changes["window"] = None
        bw = self.azimuth_beamwidth_rad
        if "azimuth_rad" in changes and "azimuth_beamwidth_rad" not in changes and bw is not None \
                and np.size(changes["azimuth_rad"]) != bw.size:
            # other beams: one width for all carries over, a per-beam table does not
            changes["azimuth_beamwidth_rad"] = float(bw[0]) if np.all(bw == bw[0]) else None
        return dataclasses.replace(self, **changes)

    # ------------------------------------------------------------------ derived quantities
    @functools.cached_property
    def n_beams(self) -> int:
        """Number of beams (image columns)."""
        return int(self.azimuth_rad.size)

    @functools.cached_property
    def n_bins(self) -> int:
        """Number of range bins (image rows)."""
        return int(self.range_m.size)

    @functools.cached_property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(n_bins, n_beams)``."""
        return (self.n_bins, self.n_beams)

    @property
    def min_range_m(self) -> float:
        """Window start: range of row 0 (or the recorded window start)."""
        return self.window[0] if self.window is not None else float(self.range_m[0])

    @property
    def max_range_m(self) -> float:
        """Window end (``range of last row + one bin`` for uniform bins)."""
        if self.window is not None:
            return self.window[1]
        return float(self.range_m[-1] + self.range_resolution_m)

    @functools.cached_property
    def range_resolution_m(self) -> float:
        """Mean range-bin spacing in metres."""
        if self.n_bins > 1:
            return float((self.range_m[-1] - self.range_m[0]) / (self.n_bins - 1))
        if self.window is not None:
            return self.window[1] - self.window[0]
        return 0.0

    @property
    def uniform_range(self) -> bool:
        """Whether the range bins are evenly spaced (to 1e-9 relative)."""
        if self.n_bins < 3:
            return True
        d = np.diff(self.range_m)
        return bool(np.allclose(d, d.mean(), rtol=1e-9, atol=1e-12))

    @property
    def wavelength_m(self) -> float:
        """Acoustic wavelength ``c / f``."""
        return self.sound_speed_m_s / self.frequency_hz

    @functools.cached_property
    def key(self) -> str:
        """Stable content hash, used to cache per-geometry work (e.g. Wiener filters)."""
        h = hashlib.blake2b(digest_size=16)
        for arr in (self.azimuth_rad, self.range_m, self.psf, self.taper):
            h.update(b"-" if arr is None else arr.tobytes())
        h.update(
            repr(
                (self.noise, self.fov_rad, self.frequency_hz, self.sound_speed_m_s, self.rx_gain_db)
            ).encode()
        )
        if self.elevation_beamwidth_rad is not None:  # keys of geometries without it stay as they were
            h.update(repr(self.elevation_beamwidth_rad).encode())
        if self.azimuth_beamwidth_rad is not None:  # likewise
            h.update(b"azimuth_beamwidth" + self.azimuth_beamwidth_rad.tobytes())
        return h.hexdigest()

    def __eq__(self, other: object) -> bool:
        if self is other:
            return True
        if not isinstance(other, SonarGeometry):
            return NotImplemented
        return self.key == other.key and self.name == other.name

    def __hash__(self) -> int:
        return hash(self.key)

    def bin_of_range(self, range_m: ArrayLike) -> NDArray[np.intp]:
        """Index of the bin whose range is nearest to ``range_m`` (clipped to the window)."""
        r = np.asarray(range_m, dtype=np.float64)
        idx = np.searchsorted(self.range_m, r)
        idx = np.clip(idx, 1, self.n_bins - 1) if self.n_bins > 1 else np.zeros_like(idx)
        if self.n_bins > 1:
            left = self.range_m[idx - 1]
            right = self.range_m[idx]
            idx = np.where(np.abs(r - left) <= np.abs(right - r), idx - 1, idx)
        return idx.astype(np.intp)

    def beam_of_azimuth(self, azimuth_rad: ArrayLike) -> NDArray[np.intp]:
        """Index of the beam whose centre azimuth is nearest to ``azimuth_rad``."""
        a = np.asarray(azimuth_rad, dtype=np.float64)
        return np.abs(a[..., None] - self.azimuth_rad).argmin(axis=-1).astype(np.intp)

    def check_image(self, image: NDArray[Any], name: str = "image") -> None:
        """Raise :class:`GeometryError` if ``image`` does not have shape ``(n_bins, n_beams)``."""
        if image.shape != self.shape:
            raise GeometryError(
                f"{name}: shape {image.shape} does not match geometry '{self.name}' "
                f"(n_bins, n_beams) = {self.shape}"
            )

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible dict in the DIDSON PNG+JSON format (extended)."""
        d: dict[str, Any] = {
            "name": self.name,
            "fov": self.fov_rad,
            "num_beams": self.n_beams,
            "num_bins": self.n_bins,
            "min_range": self.min_range_m,
            "max_range": self.max_range_m,
            "noise": self.noise,
            "rx_gain": self.rx_gain_db,
            "frequency": self.frequency_hz,
            "sound_speed": self.sound_speed_m_s,
            "azimuths": self.azimuth_rad.tolist(),
        }
        if self.window is None:
            d["ranges"] = self.range_m.tolist()
        if self.psf_raw is not None:
            d["psf"] = self.psf_raw.tolist()
        if self.taper is not None:
            d["taper"] = self.taper.tolist()
        if self.elevation_beamwidth_rad is not None:
            d["elevation_beamwidth"] = self.elevation_beamwidth_rad
        bw = self.azimuth_beamwidth_rad
        if bw is not None:
            d["azimuth_beamwidth"] = float(bw[0]) if np.all(bw == bw[0]) else bw.tolist()
        return d


# ---------------------------------------------------------------------- JSON I/O

_KNOWN_KEYS = {
    "name", "fov", "num_beams", "num_bins", "min_range", "max_range", "noise", "rx_gain",
    "frequency", "sound_speed", "azimuths", "ranges", "psf", "taper", "elevation_beamwidth",
    "azimuth_beamwidth",
}  # fmt: skip

_MAX_NAME_CHARS = 256


def _field(d: Mapping[str, Any], key: str, source: str) -> Any:
    """``d[key]``; a :class:`GeometryError` naming ``source`` if the field is missing."""
    if key not in d:
        raise GeometryError(f"{source}: missing field '{key}'")
    return d[key]


def _number_field(d: Mapping[str, Any], key: str, source: str, default: float | None = None) -> float:
    """Field ``key`` as a finite float: required without a ``default``, else ``default`` if absent."""
    val = _field(d, key, source) if default is None else d.get(key, default)
    return _real(val, f"field '{key}'")


def _list_field(d: Mapping[str, Any], key: str, max_len: int) -> NDArray[np.float64] | None:
    """Optional field ``key`` as a list of 1 to ``max_len`` finite numbers (None if absent or null)."""
    val = d.get(key)
    return None if val is None else _real_list(val, f"field '{key}'", max_len)


def _optional_count(d: Mapping[str, Any], key: str, maximum: int) -> int | None:
    """Optional field ``key`` as an integer count in ``1..maximum`` (None if absent or null)."""
    return None if d.get(key) is None else _count(d[key], f"field '{key}'", maximum)


def _checked_name(name: object) -> str:
    """``name`` if it is a printable string of at most ``_MAX_NAME_CHARS`` characters."""
    if not isinstance(name, str) or len(name) > _MAX_NAME_CHARS or not name.isprintable():
        raise GeometryError(
            f"field 'name' must be a printable string of at most {_MAX_NAME_CHARS} characters, "
            f"got {_describe(name)}"
        )
    return name


def plausible_elevation_beamwidth(value_rad: float | None) -> float | None:
    """``value_rad`` if it is a width across the fan a sonar can have - finite, in (0, pi] rad -
    else None (what a reader does with a width its file or message reports)."""
    if value_rad is None:
        return None
    v = float(value_rad)
    return v if 0.0 < v <= math.pi else None  # NaN fails both comparisons


def _checked_elevation_beamwidth(value: object) -> float:
    """``value`` as a beamwidth in (0, pi] rad."""
    bw = _real(value, "elevation_beamwidth_rad")
    if plausible_elevation_beamwidth(bw) is None:
        raise GeometryError(f"elevation_beamwidth_rad: must be in (0, pi] rad (got {bw})")
    return bw


def _checked_azimuth_beamwidth(value: object, n_beams: int) -> NDArray[np.float64]:
    """``value`` (a number or one number per beam) as a read-only per-beam array of widths in
    (0, pi] rad."""
    if isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool | np.bool_):
        arr = np.full(n_beams, _real(value, "azimuth_beamwidth_rad"))
    else:
        arr = np.array(_frozen_array(value, "azimuth_beamwidth_rad", max_size=MAX_BEAMS))
        if arr.size != n_beams:
            raise GeometryError(f"azimuth_beamwidth_rad: length {arr.size} does not match {n_beams} beams")
    if not np.all((arr > 0) & (arr <= math.pi)):
        raise GeometryError("azimuth_beamwidth_rad: widths must be in (0, pi] rad")
    arr.setflags(write=False)
    return arr


def _optional_azimuth_beamwidth(d: Mapping[str, Any], source: str) -> float | NDArray[np.float64] | None:
    """Optional field ``azimuth_beamwidth``: a number or a list of one per beam (None if absent)."""
    val = d.get("azimuth_beamwidth")
    if val is None:
        return None
    if isinstance(val, list | tuple | np.ndarray):
        return _real_list(val, "field 'azimuth_beamwidth'", MAX_BEAMS)
    return _number_field(d, "azimuth_beamwidth", source)


def _optional_fov(d: Mapping[str, Any], source: str) -> float | None:
    """Optional field ``fov`` in (0, 2 pi] rad (None if absent or null)."""
    if d.get("fov") is None:
        return None
    fov = _number_field(d, "fov", source)
    if not 0.0 < fov <= _TWO_PI:
        raise GeometryError(f"field 'fov' must be in (0, 2 pi] rad, got {fov!r}")
    return fov


def _geometry_kwargs(d: Mapping[str, Any], source: str, name: str) -> dict[str, Any]:
    """The :class:`SonarGeometry` arguments of the acoustic constants, beam pattern and taper fields
    (defaults for the absent ones) and ``name``."""
    return {
        "noise": _number_field(d, "noise", source, 1e-2),
        "rx_gain_db": _number_field(d, "rx_gain", source, 0.0),
        "frequency_hz": _number_field(d, "frequency", source, 1.8e6),
        "sound_speed_m_s": _number_field(d, "sound_speed", source, 1500.0),
        "psf": _list_field(d, "psf", MAX_BEAMS),
        "taper": _list_field(d, "taper", MAX_BEAMS),
        "elevation_beamwidth_rad": (None if d.get("elevation_beamwidth") is None
                                    else _number_field(d, "elevation_beamwidth", source)),
        "azimuth_beamwidth_rad": _optional_azimuth_beamwidth(d, source),
        "name": name,
    }


def _default_azimuths(
    n_beams: int | None, fov: float | None, source: str
) -> tuple[NDArray[np.float64], str]:
    """Azimuths and their ``azimuth_source`` for a dict without ``azimuths``: those of the preset with
    this beam count and fov, else uniform over ``fov`` with a :class:`GeometryWarning`."""
    if n_beams is None or fov is None:
        raise GeometryError("need 'azimuths', or 'num_beams' and 'fov'")
    match = _matching_preset(n_beams, fov)
    if match is not None:
        return match.azimuth_rad, f"preset:{match.name}"
    warnings.warn(
        f"{source}: no azimuth table; assuming {n_beams} beams uniform "
        f"over fov={fov:.4f} rad",
        GeometryWarning,
        stacklevel=4,  # past this helper, geometry_from_dict and its caller (e.g. load_geometry)
    )
    return uniform_azimuths(n_beams, fov), "uniform"


def geometry_from_dict(
    d: Mapping[str, Any], *, source: str = "<dict>", default_name: str = "sonar"
) -> SonarGeometry:
    """Build a :class:`SonarGeometry` from a dict in the (extended) DIDSON JSON format.

    When ``azimuths`` is absent the beams are taken from a preset whose beam count and field of
    view match (e.g. the DIDSON's measured table), else spread uniformly over ``fov`` with a
    :class:`GeometryWarning`.

    Every field is checked before anything is allocated: numbers must be finite numbers (not
    bools or strings), ``num_beams`` an integer in ``1..MAX_BEAMS``, ``num_bins`` an integer in
    ``1..MAX_BINS``, ``0 <= min_range < max_range <= MAX_RANGE_M``, ``fov`` in ``(0, 2 pi]``,
    ``elevation_beamwidth`` in ``(0, pi]`` rad, ``azimuths`` / ``psf`` / ``taper`` lists of one
    finite number per beam, ``ranges`` a list of ``num_bins`` finite numbers, ``noise >= 0``, ``name`` a short printable string.  Unknown keys
    are ignored; ``null`` counts as absent for the optional fields.

    Parameters
    ----------
    d : mapping
        The decoded JSON object.
    source : str
        Prefix of error messages (the file name).
    default_name : str
        Geometry name when ``d`` has no ``name``.

    Returns
    -------
    SonarGeometry
        The validated geometry.

    Raises
    ------
    GeometryError
        With ``source`` in the message, when fields are missing, of the wrong type, out of range
        or inconsistent.
    """
    if not isinstance(d, Mapping):
        raise GeometryError(f"{source}: geometry JSON must be an object, got {type(d).__name__}")
    try:
        name = _checked_name(d.get("name", default_name))
        fov = _optional_fov(d, source)
        n_beams = _optional_count(d, "num_beams", MAX_BEAMS)
        n_bins = _optional_count(d, "num_bins", MAX_BINS)
        azimuths = _list_field(d, "azimuths", MAX_BEAMS)
        if azimuths is not None and n_beams is not None and azimuths.size != n_beams:
            raise GeometryError(f"'azimuths' has {azimuths.size} entries but num_beams is {n_beams}")
        kwargs = _geometry_kwargs(d, source, name)
        if azimuths is None:
            azimuths, kwargs["azimuth_source"] = _default_azimuths(n_beams, fov, source)
        ranges = _list_field(d, "ranges", MAX_BINS)
        if ranges is not None:
            if n_bins is not None and ranges.size != n_bins:
                raise GeometryError(f"'ranges' has {ranges.size} entries but num_bins is {n_bins}")
            return SonarGeometry(azimuth_rad=azimuths, range_m=ranges, fov_rad=fov, **kwargs)
        if n_bins is None:
            _field(d, "num_bins", source)
            raise GeometryError("field 'num_bins' must be an integer, got null")
        return SonarGeometry.from_window(
            min_range_m=_number_field(d, "min_range", source),
            max_range_m=_number_field(d, "max_range", source),
            n_bins=n_bins,
            azimuth_rad=azimuths,
            fov_rad=fov,
            **kwargs,
        )
    except GeometryError as exc:
        msg = str(exc)
        if not msg.startswith(source):
            raise GeometryError(f"{source}: {msg}") from None
        raise


def _parse_geometry_json(data: bytes, source: str, default_name: str) -> SonarGeometry:
    from sonarmap._files import parse_json  # lazily, as the file reads below: `import sonarmap` stays light

    return geometry_from_dict(parse_json(data, source), source=source, default_name=default_name)


_cached_geometry_json = functools.lru_cache(maxsize=64)(_parse_geometry_json)


@dataclasses.dataclass(frozen=True)
class _Template:
    """The validated geometry of one JSON content, for every file that holds that content."""

    geometry: SonarGeometry
    #: The JSON has its own ``name``; else each file's geometry is named after the file.
    named: bool


#: Validated geometries by JSON content (at most ``_TEMPLATES_MAX``, oldest dropped first); ``None``
#: for a content that is parsed per file (its geometry warns, naming the file).  A survey's
#: sidecars are one content under thousands of file names: it is decoded and validated once.
_templates: dict[bytes, _Template | None] = {}
_templates_lock = threading.Lock()
_TEMPLATES_MAX = 64


def _template_of(data: bytes, geometry: SonarGeometry) -> _Template | None:
    """The template of ``data`` (already parsed into ``geometry`` without error), or ``None`` if
    parsing it warns: uniform azimuths (no table) or a single beam (without ``fov``), whose
    warnings name the file, so such contents are parsed for every file as before."""
    if geometry.azimuth_source == "uniform" or geometry.n_beams < 2:
        return None
    d = json.loads(data)
    return _Template(geometry, isinstance(d, Mapping) and "name" in d)


def _renamed(geometry: SonarGeometry, name: str, source: str) -> SonarGeometry:
    """``geometry`` under the (checked) ``name``: a shallow copy sharing its read-only arrays and its
    content ``key`` (which does not depend on the name), not validated again."""
    try:
        name = _checked_name(name)
    except GeometryError as exc:
        raise GeometryError(f"{source}: {exc}") from None
    out = copy.copy(geometry)
    object.__setattr__(out, "name", name)
    return out


def geometry_from_json_bytes(data: bytes, source: str, default_name: str) -> SonarGeometry:
    """Parse and validate geometry JSON bytes; results of small files are cached by content.

    Files of the same content (a survey's sidecars) are parsed and validated once; each gets the
    same geometry, named after ``default_name`` when the JSON has no ``name`` (exactly what parsing
    the file would give).  A content that warns when parsed is parsed for every file, so every
    file's warning names it.

    Raises
    ------
    DataFormatError
        If ``data`` is not JSON (bad syntax, not UTF-8, nested too deeply, oversized integers).
    GeometryError
        If the fields are missing, out of range or inconsistent.
    """
    if len(data) > _CACHE_MAX_BYTES:  # do not pin large files in the cache
        return _parse_geometry_json(data, source, default_name)
    if data not in _templates:
        geometry = _cached_geometry_json(data, source, default_name)
        template = _template_of(data, geometry)
        with _templates_lock:
            while len(_templates) >= _TEMPLATES_MAX:
                del _templates[next(iter(_templates))]
            _templates[data] = template
        return geometry
    template = _templates.get(data)
    if template is None:
        return _cached_geometry_json(data, source, default_name)
    if template.named or template.geometry.name == default_name:
        return template.geometry
    return _renamed(template.geometry, default_name, source)


#: The name of a ping's sidecar geometry that names no sonar and takes no preset's azimuth table.
SIDECAR_DEFAULT_NAME = "sonar"


def geometry_from_sidecar_bytes(data: bytes, source: str) -> SonarGeometry:
    """:func:`geometry_from_json_bytes` for a ping's sidecar JSON (``<ts>.json`` beside its image).

    The geometry is named by the JSON's ``name``; without one, after the preset whose measured
    azimuth table it takes (``didson-hf`` for the DIDSON's sidecars), else
    :data:`SIDECAR_DEFAULT_NAME` - never after the ping's file, whose stem is its time stamp.

    Raises
    ------
    DataFormatError, GeometryError
        As :func:`geometry_from_json_bytes`.
    """
    geometry = geometry_from_json_bytes(data, source, SIDECAR_DEFAULT_NAME)
    if geometry.name == SIDECAR_DEFAULT_NAME and geometry.azimuth_source.startswith("preset:"):
        return _renamed(geometry, geometry.azimuth_source.removeprefix("preset:"), source)
    return geometry


def geometry_summary(geometry: Any) -> dict[str, Any]:
    """Plain-dict summary of a SonarGeometry (shared by ``sonarmap info`` and the formats' summaries)."""
    az = np.rad2deg(geometry.azimuth_rad)
    d = np.diff(az) if az.size > 1 else np.array([0.0])
    uniform = bool(np.allclose(d, d.mean(), rtol=1e-3, atol=1e-6))
    return {
        "name": geometry.name,
        "beams": geometry.n_beams,
        "bins": geometry.n_bins,
        "range_min_m": round(geometry.min_range_m, 6),
        "range_max_m": round(geometry.max_range_m, 6),
        "range_resolution_m": geometry.range_resolution_m,
        "azimuth_min_deg": float(az[0]),
        "azimuth_max_deg": float(az[-1]),
        "fov_deg": float(np.rad2deg(geometry.fov_rad)),
        "beam_spacing_deg": [float(d.min()), float(d.max())],
        "azimuth_table": "uniform" if uniform else "non-uniform",
        "azimuth_source": geometry.azimuth_source,
        "frequency_hz": geometry.frequency_hz,
        "sound_speed_m_s": geometry.sound_speed_m_s,
        "rx_gain_db": geometry.rx_gain_db,
        "noise_inv_snr": geometry.noise,
        "psf": geometry.psf is not None,
        "taper": geometry.taper is not None,
        "elevation_beamwidth_deg": (None if geometry.elevation_beamwidth_rad is None
                                    else float(np.rad2deg(geometry.elevation_beamwidth_rad))),
        "azimuth_beamwidth_deg": _beamwidth_summary(getattr(geometry, "azimuth_beamwidth_rad", None)),
    }


def _beamwidth_summary(width_rad: Any) -> float | list[float] | None:
    """A per-beam width (two-way -3 dB, rad) in degrees: one value when it is the same for every
    beam, else ``[min, max]``; None when unknown."""
    if width_rad is None:
        return None
    w = np.rad2deg(np.asarray(width_rad, dtype=np.float64).reshape(-1))
    if np.allclose(w, w[0], rtol=1e-6, atol=0.0):
        return round(float(w[0]), 6)
    return [round(float(w.min()), 6), round(float(w.max()), 6)]


def load_geometry(path: str | os.PathLike[str]) -> SonarGeometry:
    """Load a geometry JSON file (DIDSON format, extended); results are cached by content.

    Only regular files of at most ``MAX_SIDECAR_BYTES`` are read.

    Raises
    ------
    DataFormatError
        If the file is missing, not a regular file (FIFO, device, directory), too large, cannot be
        read or is not valid JSON (message gives line and column).
    GeometryError
        If fields are missing or inconsistent.
    """
    from sonarmap._files import MAX_SIDECAR_BYTES, read_bytes_bounded

    p = Path(path)
    data = read_bytes_bounded(p, MAX_SIDECAR_BYTES, "geometry JSON")
    return geometry_from_json_bytes(data, str(p), p.stem)


def save_geometry(geometry: SonarGeometry, path: str | os.PathLike[str]) -> None:
    """Write ``geometry`` as JSON atomically; :func:`load_geometry` reads it back losslessly."""
    atomic_write_text(path, json.dumps(geometry.to_dict(), indent=1) + "\n")


# ---------------------------------------------------------------------- presets

#: ARIS lens tables of ``aris_beamwidths.json``: table name -> (preset name, frequency in Hz).
ARIS_LENS = {
    "ARIS1800_1200_48": ("aris1800-48", 1.8e6),
    "ARIS1800_96": ("aris1800-96", 1.8e6),
    "ARIS3000_128": ("aris3000-128", 3.0e6),
    "ARIS3000_64": ("aris3000-64", 3.0e6),
    "ARIS_Telephoto_48": ("aris-telephoto-48", 1.8e6),
    "ARIS_Telephoto_96": ("aris-telephoto-96", 1.8e6),
}
#: Vertical -3 dB beamwidth of the ARIS standard lenses (SoundMetrics: 14 deg on the 1200, 1800
#: and 3000); the telephoto lens's is not in the vendor tables, so those presets leave it unknown.
ARIS_STANDARD_ELEVATION_BEAMWIDTH_RAD = math.radians(14.0)


#: DIDSON 300 high-frequency mode (1.8 MHz): 0.3 deg two-way beams (SoundMetrics' published
#: figure; the beams are 0.23-0.37 deg apart on the measured azimuth table).
DIDSON_HF_AZIMUTH_BEAMWIDTH_RAD = math.radians(0.3)
#: Two-way -3 dB azimuth beamwidth of the Oculus M-series by operating frequency (upper bound of
#: the band in Hz, width in degrees): 1.0 deg at 750 kHz and 0.6 deg at 1.2 MHz (Blueprint's
#: published angular resolution of the M750d / M1200d), 0.55 deg at 2.1 MHz - measured on the
#: 2.1 MHz recording ``oculus/three_pings_8bit.raw`` (the seabed's beam-to-beam correlation,
#: ``docs/simulator.md``; the vendor quotes 0.4 deg for the M1200d's 2.1 MHz mode).
OCULUS_AZIMUTH_BEAMWIDTH_DEG: tuple[tuple[float, float], ...] = ((0.95e6, 1.0), (1.6e6, 0.6), (math.inf, 0.55))


def oculus_azimuth_beamwidth_rad(frequency_hz: float) -> float:
    """The default two-way azimuth beamwidth of an Oculus sonar operating at ``frequency_hz``
    (:data:`OCULUS_AZIMUTH_BEAMWIDTH_DEG`)."""
    for top, deg in OCULUS_AZIMUTH_BEAMWIDTH_DEG:
        if frequency_hz < top:
            return math.radians(deg)
    return math.radians(OCULUS_AZIMUTH_BEAMWIDTH_DEG[-1][1])


def _data_text(name: str) -> str:
    return resources.files("sonarmap.data").joinpath(name).read_text(encoding="utf-8")


@functools.cache
def _presets() -> dict[str, SonarGeometry]:
    out: dict[str, SonarGeometry] = {}
    did = json.loads(_data_text("didson_hf.json"))
    out["didson-hf"] = geometry_from_dict(did, source="preset didson-hf").replace(
        azimuth_beamwidth_rad=DIDSON_HF_AZIMUTH_BEAMWIDTH_RAD)
    tables = json.loads(_data_text("aris_beamwidths.json"))["tables"]
    for table, (name, freq) in ARIS_LENS.items():
        t = tables[table]
        # Vendor order: beam 0 right-most with a negative angle (vendor angles positive to port).
        # Our azimuths are positive to starboard and increase with column, so
        # column j = vendor beam (n-1-j) and azimuth = -vendor angle.
        centre = -np.asarray(t["center_deg"], dtype=np.float64)[::-1]
        left = -np.asarray(t["left_deg"], dtype=np.float64)[::-1]
        right = -np.asarray(t["right_deg"], dtype=np.float64)[::-1]
        fov = float(np.deg2rad(max(left.max(), right.max()) - min(left.min(), right.min())))
        out[name] = SonarGeometry.from_window(
            min_range_m=1.0,
            max_range_m=11.0,
            n_bins=1000,
            azimuth_rad=np.deg2rad(centre),
            fov_rad=fov,
            frequency_hz=freq,
            name=name,
            azimuth_source=f"preset:{name}",
            elevation_beamwidth_rad=None if "telephoto" in name else ARIS_STANDARD_ELEVATION_BEAMWIDTH_RAD,
            azimuth_beamwidth_rad=np.deg2rad(np.abs(right - left)),
        )
    ocu = json.loads(_data_text("oculus_m750d_like.json"))
    az = np.deg2rad(np.asarray(ocu["bearings_centideg"], dtype=np.float64) / 100.0)
    out["oculus-m750d-like"] = SonarGeometry.from_window(
        min_range_m=float(ocu["min_range"]),
        max_range_m=float(ocu["max_range"]),
        n_bins=int(ocu["num_bins"]),
        azimuth_rad=az,
        frequency_hz=float(ocu["frequency"]),
        sound_speed_m_s=float(ocu["sound_speed"]),
        name="oculus-m750d-like",
        azimuth_source="preset:oculus-m750d-like",
        azimuth_beamwidth_rad=oculus_azimuth_beamwidth_rad(float(ocu["frequency"])),
    )
    return out


def preset_names() -> list[str]:
    """Names of the built-in sonar presets."""
    return sorted(_presets())


def preset(name: str, **changes: Any) -> SonarGeometry:
    """A built-in sonar geometry, optionally with fields replaced.

    ``"didson-hf"``: DIDSON 300 high-frequency mode (1.8 MHz, 96 beams, 2.25-11.25 m, 512 bins)
    with the measured beam azimuths, beam pattern and taper of Teixeira et al.  ``"aris*"``: every
    ARIS model/lens/beam count with the vendor's beam-angle tables (SoundMetrics, MIT licence); the
    range window is a placeholder (1-11 m, 1000 bins) that readers replace from the file.
    ``"oculus-m750d-like"``: a Blueprint Oculus M750d in its 2.1 MHz mode as recorded in the
    liboculus test file (256 beams at the recorded bearings over +-30 deg, 703 bins over 0-2 m).

    Raises
    ------
    GeometryError
        If ``name`` is unknown (the message lists the valid names).
    """
    table = _presets()
    if name not in table:
        raise GeometryError(f"unknown preset '{name}'; choose from {', '.join(sorted(table))}")
    geom = table[name]
    return geom.replace(**changes) if changes else geom


def _matching_preset(n_beams: int, fov_rad: float) -> SonarGeometry | None:
    """The preset with this beam count and field of view (to 1e-6 rad), if exactly one matches."""
    hits = [
        g
        for g in _presets().values()
        if g.n_beams == n_beams and abs(float(g.fov_rad or 0.0) - fov_rad) < 1e-6
    ]
    return hits[0] if len(hits) == 1 else None


def as_geometry(spec: SonarGeometry | str | os.PathLike[str]) -> SonarGeometry:
    """Resolve a geometry given as an object, a preset name, or a JSON path.

    Raises
    ------
    GeometryError
        If ``spec`` is of another type, or the JSON file's fields are invalid.
    DataFormatError
        If the JSON file is missing, not a regular file, too large or not valid JSON.
    """
    if isinstance(spec, SonarGeometry):
        return spec
    if not isinstance(spec, str | os.PathLike):
        raise GeometryError(
            f"geometry: expected a SonarGeometry, preset name or JSON path, got {type(spec).__name__}"
        )
    s = str(spec)
    if s in _presets():
        return _presets()[s]
    return load_geometry(s)


def azimuth_span_deg(geometry: SonarGeometry) -> tuple[float, float]:
    """First and last beam azimuths in degrees."""
    return (
        float(np.rad2deg(geometry.azimuth_rad[0])),
        float(np.rad2deg(geometry.azimuth_rad[-1])),
    )

