"""The sonar-equation renderer: scene -> synthetic ping + truth.

Processing order (each step documented in ``docs/simulator.md``)::

    per-pixel echo energy  E[i, j]  = sum over samples in (bin i, beam j) of
                                      reflectivity * area * |cos inc|^p * b(elevation)
    beam pattern           E' = E (*) psf        linear convolution across beams (eq. 2)
    taper                  E'' = k(theta_j) E'   per-beam gain (eq. 5)
    channel                m = E'' 10^((SL + G - FS - TL(r)) / 10),
                           TL(r) = 20 beta log10 r + 2 alpha r      (eqs. 6-7: k1 = 20 beta, k2 = 2 alpha)
    background             m_bg = k(theta_j) 10^((SL + G - FS + RV - TL(r)) / 10)
                           (volume reverberation: through taper and channel exactly like echoes)
    speckle + noise        A = sqrt(m + m_bg) z1 + sqrt(n) z2,  z ~ CN(0, 1);  I = |A|^2
                           (Rayleigh amplitude; I is exponential with mean m + m_bg + n),
                           averaged over ``looks`` independent draws (gamma with shape looks)
    receiver mapping       linear: p = clip(I - threshold, 0, 1)
                           log:    p = clip(1 + 10 log10(I) / D - threshold, 0, 1)
    quantisation           q = floor(255 p) / 255

``SL`` source level, ``G`` receiver gain (``geometry.rx_gain_db`` unless overridden), ``FS`` the
full-scale level (received level that maps to pixel 1), ``RV`` the per-pixel volume backscatter,
``n`` the receiver noise power, ``D`` the log receiver's dynamic range.  The defaults were fitted
to the 116 real DIDSON background pings; other sonars take their defaults from a sonar profile
(:mod:`sonarmap.simulate.presets`, chosen from the geometry's name) for every field the caller does
not set (see ``docs/simulator.md``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ping import Ping
from sonarmap.simulate.scene import CLUTTER, STRUCTURE, Scene

__all__ = [
    "SimulationConfig",
    "simulation_config_for",
    "SimResult",
    "SimulationFiles",
    "simulate_ping",
    "transmission_loss_db",
    "channel_gain",
    "expected_background_level",
    "expected_background_image",
    "seawater_absorption_db_per_m",
    "write_simulation",
    "read_truth",
]


def seawater_absorption_db_per_m(
    frequency_hz: float = 1.8e6,
    *,
    temperature_c: float = 15.0,
    salinity_psu: float = 35.0,
    depth_m: float = 5.0,
    ph: float = 8.0,
) -> float:
    """One-way absorption of sea water (Ainslie & McColm 1998, JASA 103(3)), in dB/m.

    About 1 dB/m at 1.8 MHz and 15 deg C.  Not the simulator default: DIDSON images are recorded
    after the sonar's own time-varied gain, so the *net* loss left in the image is much smaller
    (see :class:`SimulationConfig`).
    """
    f = frequency_hz / 1e3  # kHz
    z = depth_m / 1e3  # km
    f1 = 0.78 * math.sqrt(salinity_psu / 35.0) * math.exp(temperature_c / 26.0)
    f2 = 42.0 * math.exp(temperature_c / 17.0)
    boric = 0.106 * f1 * f * f / (f1 * f1 + f * f) * math.exp((ph - 8.0) / 0.56)
    mgso4 = (
        0.52 * (1 + temperature_c / 43.0) * (salinity_psu / 35.0)
        * f2 * f * f / (f2 * f2 + f * f) * math.exp(-z / 6.0)
    )
    water = 0.00049 * f * f * math.exp(-(temperature_c / 27.0 + z / 17.0))
    return (boric + mgso4 + water) / 1e3


@dataclasses.dataclass(frozen=True)
class SimulationConfig:
    """Parameters of the sonar equation, the sensor and the receiver (all levels in dB).

    Parameters
    ----------
    source_level_db : float
        Source level SL (dB re 1 uPa at 1 m).
    spreading_beta : float
        One-way spreading exponent beta; two-way loss ``20 beta log10 r + 2 alpha r`` dB (eqs. 6-7,
        ``k1 = 20 beta``, ``k2 = 2 alpha``).  This is the *net* loss remaining in the recorded
        image after the DIDSON's internal time-varied gain, fitted to the real background pings.
    alpha_db_per_m : float
        One-way net absorption alpha (dB/m); see :func:`seawater_absorption_db_per_m` for the raw
        physical value (~1 dB/m at 1.8 MHz) when simulating a sonar without TVG.
    elevation_aperture_rad : float
        Full width of the two-way vertical beam pattern at -3 dB (default 1 deg: the concentrator
        lens narrows the DIDSON's 14 deg vertical beam; 1 deg gives the 5-10-bin hull bands of the
        paper's test images 4, 5, 8, 9).
    elevation_pattern : {"gaussian", "uniform"}
        Vertical two-way power pattern ``b(e) = exp(-4 ln2 (e / width)^2)`` or a box of the width.
    incidence_exponent : float
        Lambert's law exponent p: surface samples scatter ``|cos(incidence)|^p`` (p = 2).
    reverb_db : float
        Volume reverberation per pixel (dB re 1 m^2 equivalent target strength) - the open-water
        background that passes through taper and channel loss like echoes.
    noise_level_db : float
        Receiver noise power (dB re 1 uPa^2), added after the channel (not tapered).
    rx_gain_db : float or None
        Receiver gain; ``None`` uses ``geometry.rx_gain_db`` (20 dB for the DIDSON data).
    full_scale_db : float
        Received level after gain (dB re 1 uPa^2) that maps to pixel value 1.
    threshold : float
        Noise floor subtracted in the receiver mapping ``p = clip(I - threshold, 0, 1)``, in
        full-scale units; with quantisation it produces the zero spike of real DIDSON data.
    speckle : bool
        Apply Rayleigh fading to echoes and reverberation (``False``: use their expected value).
    ghosts : {"coherent", "incoherent"}
        How the beam pattern meets speckle.  ``"coherent"`` (default, physical): each direction's
        echo is a complex Gaussian field, and beam ``j`` receives ``sum_k sqrt(psf[j - k]) a_k`` -
        the ghost of a direction is a scaled copy of *its* echo, speckle included (the same
        scatterers seen through a sidelobe / the DIDSON's channel cross-talk).  ``"incoherent"``
        (the previous model): the blurred *expected* intensity receives independent speckle on
        every beam, so a ghost fades independently of its source and no deconvolution of a single
        ping can remove it.  Both have the same expected image.
    beam_pattern : {"geometry", "measured"}
        Across-beam pattern the image is rendered with.  ``"geometry"``: the sonar's stated PSF
        (``geometry.psf``; for the DIDSON the authors' 12-tap pattern, whose ghosts at +-8 beams
        are 57 % of the main beam).  ``"measured"``: the ghost taps measured on the real DIDSON
        test ping 5 (:data:`MEASURED_DIDSON_GHOSTS`: 3.1 % at +-8 beams, 0.7 / 0.5 % at +-16 / +-24), placed
        on the geometry PSF's tap grid - what the recorded images actually show.  Pre-processing
        still deconvolves with ``geometry.psf``, as on real data.
    quantization : {"floor", "round"}
        8-bit quantisation rule (ADC truncation by default).
    truth_snr_db : float
        A pixel belongs to a class in the truth mask when that class's *unblurred* expected echo
        intensity is at least this many dB relative to the expected background intensity
        (reverberation + noise) at the pixel (default -3 dB, i.e. half the noise floor).
    receiver : {"linear", "log"}
        Receiver mapping from intensity ``I`` (full-scale units) to the pixel value before
        quantisation: ``"linear"`` ``p = clip(I - threshold, 0, 1)`` (DIDSON, Oculus) or
        ``"log"`` ``p = clip(1 + 10 log10(I) / dynamic_range_db - threshold, 0, 1)`` (ARIS: full
        scale maps to 1, ``dynamic_range_db`` below it to 0).
    dynamic_range_db : float
        Input range of the log receiver mapped onto [0, 1] (unused by ``"linear"``).
    looks : int
        Independent speckle draws averaged per pixel (intensity gamma-distributed with this shape;
        1: single-look exponential speckle, as the DIDSON).
    range_resolution_m : float
        Range resolution of the pulse: the expected echo is averaged along range over a box of
        ``round(range_resolution_m / bin spacing)`` bins when that is 2 or more (0: none).
    ring_down_level : float
        Near-field ring-down of the transducer, in full-scale intensity at range 0; it decays as
        ``exp(-r / ring_down_m)``, is not tapered and fades like reverberation (0: none).
    ring_down_m : float
        Decay length of the ring-down.

    Notes
    -----
    Sonar profiles (:mod:`sonarmap.simulate.presets`) give other sonars their own defaults for
    gain, loss, floor and receiver.  A field passed to the constructor (or to :meth:`replace`) is
    *explicit* and always used as given; the others take the profile's value when the config
    meets a geometry (:meth:`resolved`, which :func:`simulate_ping` calls).  For DIDSON and any
    geometry no profile claims, the defaults above are used unchanged.
    ``rx_gain_db=None`` passed explicitly means the geometry's gain.

    Examples
    --------
    >>> from sonarmap import preset
    >>> SimulationConfig(looks=3).resolved(preset("aris3000-128")).receiver
    'log'
    >>> SimulationConfig(looks=3).resolved(preset("aris3000-128")).looks
    3
    >>> SimulationConfig().resolved(preset("didson-hf")) == SimulationConfig()
    True
    """

    source_level_db: float = 200.0
    spreading_beta: float = 0.07
    alpha_db_per_m: float = 0.1
    elevation_aperture_rad: float = math.radians(1.0)
    elevation_pattern: Literal["gaussian", "uniform"] = "gaussian"
    incidence_exponent: float = 2.0
    reverb_db: float = -62.54
    noise_level_db: float = 80.0
    rx_gain_db: float | None = None
    full_scale_db: float = 170.0
    threshold: float = 0.01218
    speckle: bool = True
    quantization: Literal["floor", "round"] = "floor"
    truth_snr_db: float = -3.0
    ghosts: Literal["coherent", "incoherent"] = "coherent"
    beam_pattern: Literal["geometry", "measured"] = "geometry"
    receiver: Literal["linear", "log"] = "linear"
    dynamic_range_db: float = 40.0
    looks: int = 1
    range_resolution_m: float = 0.0
    ring_down_level: float = 0.0
    ring_down_m: float = 0.005

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            val = getattr(self, f.name)
            if isinstance(val, float | int) and not isinstance(val, bool):
                if not math.isfinite(float(val)):
                    raise InputError(f"config.{f.name}: must be finite (got {val})")
        if not self.elevation_aperture_rad > 0:
            raise InputError(
                f"config.elevation_aperture_rad: must be positive (got {self.elevation_aperture_rad})"
            )
        if self.elevation_pattern not in ("gaussian", "uniform"):
            raise InputError(f"config.elevation_pattern: 'gaussian' or 'uniform', got {self.elevation_pattern!r}")
        if self.ghosts not in ("coherent", "incoherent"):
            raise InputError(f"config.ghosts: 'coherent' or 'incoherent', got {self.ghosts!r}")
        if self.beam_pattern not in ("geometry", "measured"):
            raise InputError(f"config.beam_pattern: 'geometry' or 'measured', got {self.beam_pattern!r}")
        if self.quantization not in ("floor", "round"):
            raise InputError(f"config.quantization: 'floor' or 'round', got {self.quantization!r}")
        if not 0 <= self.threshold < 1:
            raise InputError(f"config.threshold: must be in [0, 1) (got {self.threshold})")
        if self.incidence_exponent < 0:
            raise InputError(f"config.incidence_exponent: must be >= 0 (got {self.incidence_exponent})")
        if self.receiver not in ("linear", "log"):
            raise InputError(f"config.receiver: 'linear' or 'log', got {self.receiver!r}")
        if not self.dynamic_range_db > 0:
            raise InputError(f"config.dynamic_range_db: must be positive (got {self.dynamic_range_db})")
        if isinstance(self.looks, bool) or not isinstance(self.looks, int | np.integer) or self.looks < 1:
            raise InputError(f"config.looks: must be an integer >= 1 (got {self.looks!r})")
        object.__setattr__(self, "looks", int(self.looks))
        if self.range_resolution_m < 0:
            raise InputError(f"config.range_resolution_m: must be >= 0 (got {self.range_resolution_m})")
        if self.ring_down_level < 0:
            raise InputError(f"config.ring_down_level: must be >= 0 (got {self.ring_down_level})")
        if not self.ring_down_m > 0:
            raise InputError(f"config.ring_down_m: must be positive (got {self.ring_down_m})")

    @property
    def explicit_fields(self) -> frozenset[str]:
        """Names of the fields set by the caller (never replaced by a sonar profile)."""
        return self.__dict__.get("_explicit", frozenset())

    def replace(self, **changes: Any) -> SimulationConfig:
        """A copy with fields replaced; the replaced fields become explicit."""
        new = dataclasses.replace(self, **changes)
        object.__setattr__(new, "_explicit", self.explicit_fields | frozenset(changes))
        return new

    def resolved(self, geometry: SonarGeometry) -> SimulationConfig:
        """This config with the sonar profile of ``geometry`` filling every non-explicit field.

        Returns ``self`` when the profile changes nothing (DIDSON and unknown sonars); otherwise a
        config whose fields are all explicit (resolving it again, for any geometry, is a no-op).
        """
        from sonarmap.simulate.presets import profile_for

        prof = profile_for(geometry)
        changes = {k: v for k, v in prof.values.items() if k not in self.explicit_fields}
        if not changes:
            return self
        new = dataclasses.replace(self, **changes)
        object.__setattr__(new, "_explicit", frozenset(f.name for f in dataclasses.fields(self)))
        return new

    @classmethod
    def for_geometry(cls, geometry: SonarGeometry, **changes: Any) -> SimulationConfig:
        """The defaults of ``geometry``'s sonar profile with ``changes`` applied (see
        :func:`simulation_config_for`)."""
        out = cls(**changes).resolved(geometry)
        # a fresh object: mark it fully specified so it renders the same for any geometry
        object.__setattr__(out, "_explicit", frozenset(f.name for f in dataclasses.fields(cls)))
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible dict of the parameters."""
        return dataclasses.asdict(self)


def _track_explicit_fields(cls: type[SimulationConfig]) -> type[SimulationConfig]:
    """Record which fields each constructor call set (for :meth:`SimulationConfig.resolved`)."""
    init = cls.__init__
    names = tuple(f.name for f in dataclasses.fields(cls) if f.init)

    @functools.wraps(init)
    def __init__(self: SimulationConfig, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        object.__setattr__(self, "_explicit", frozenset(names[: len(args)]) | frozenset(kwargs))

    cls.__init__ = __init__  # type: ignore[method-assign]
    return cls


_track_explicit_fields(SimulationConfig)


def simulation_config_for(geometry: SonarGeometry, **changes: Any) -> SimulationConfig:
    """The rendering defaults of ``geometry``'s sonar profile, with ``changes`` applied.

    Parameters
    ----------
    geometry : SonarGeometry
        The profile is chosen from ``geometry.name`` (:func:`sonarmap.simulate.presets.profile_for`:
        ``aris*`` -> ARIS, ``oculus*`` -> Oculus, anything else -> the DIDSON defaults).
    **changes
        :class:`SimulationConfig` fields to set explicitly (they override the profile).

    Returns
    -------
    SimulationConfig
        Fully specified (every field explicit).

    Examples
    --------
    >>> from sonarmap import preset
    >>> cfg = simulation_config_for(preset("aris-telephoto-48"), speckle=False)
    >>> cfg.receiver, cfg.rx_gain_db, cfg.speckle
    ('log', 24.0, False)
    >>> simulation_config_for(preset("didson-hf")) == SimulationConfig()
    True
    """
    if not isinstance(geometry, SonarGeometry):
        raise InputError(f"geometry: expected a SonarGeometry, got {type(geometry).__name__}")
    return SimulationConfig.for_geometry(geometry, **changes)


@dataclasses.dataclass(frozen=True, eq=False)
class SimResult:
    """A simulated ping and its truth.

    Attributes
    ----------
    ping : Ping
        The recorded image (float32 in [0, 1], multiples of 1/255), geometry and time.
    clean : ndarray, shape (n_bins, n_beams), float32
        Expected echo intensity of the scene (through beam pattern, taper, channel and gain; no
        reverberation, noise, speckle, threshold or quantisation), clipped to [0, 1].
    class_mask : ndarray, shape (n_bins, n_beams), uint8
        0 background, 1 structure, 2 clutter (see ``SimulationConfig.truth_snr_db``); built from
        the unblurred scene, so PSF ghosts are background.  Where both classes qualify, the larger
        expected intensity wins.
    first_return_bin : ndarray, shape (n_beams,), int64
        First structure row of each beam in ``class_mask``; -1 where none.
    first_return_range_m : ndarray, shape (n_beams,), float64
        ``geometry.range_m[first_return_bin]``; NaN where none.
    config : SimulationConfig
    scene_name : str
    seed : int or None
        The integer seed when one was given.
    unblurred : ndarray, shape (n_bins, n_beams), float32
        Like ``clean`` but before the beam pattern (the ideal image deconvolution aims at).
    structure_peak_snr_db : ndarray, shape (n_beams,), float64
        Per beam, the highest structure-to-background ratio (dB, unblurred) of a pixel where
        structure is not outshone by clutter; ``-inf`` where none.  A beam has structure in the
        class mask at a truth threshold ``t`` exactly when this is ``>= t``, so callers can ask
        about another threshold without rendering again.
    """

    ping: Ping
    clean: NDArray[np.float32]
    class_mask: NDArray[np.uint8]
    first_return_bin: NDArray[np.int64]
    first_return_range_m: NDArray[np.float64]
    config: SimulationConfig
    scene_name: str
    seed: int | None = None
    unblurred: NDArray[np.float32] | None = None
    structure_peak_snr_db: NDArray[np.float64] | None = None


# ---------------------------------------------------------------------- channel quantities


def transmission_loss_db(range_m: NDArray[np.float64] | float, config: SimulationConfig) -> NDArray[np.float64]:
    """Two-way loss ``20 beta log10 r + 2 alpha r`` in dB (eqs. 6-7); ranges below 1 cm are clamped.

    ``config`` is used as given (resolve it for a geometry first: :meth:`SimulationConfig.resolved`).
    """
    r = np.maximum(np.asarray(range_m, dtype=np.float64), 0.01)
    return 20.0 * config.spreading_beta * np.log10(r) + 2.0 * config.alpha_db_per_m * r


def _rx_gain(geometry: SonarGeometry, config: SimulationConfig) -> float:
    return geometry.rx_gain_db if config.rx_gain_db is None else float(config.rx_gain_db)


def channel_gain(geometry: SonarGeometry, config: SimulationConfig = SimulationConfig()) -> NDArray[np.float64]:
    """Per-bin factor from target strength (linear, m^2) to full-scale intensity, shape (n_bins,).

    ``10 ** ((SL + G - FS - TL(r)) / 10)``; the taper is *not* included.  ``config`` is
    resolved for ``geometry`` (its sonar profile fills the fields not set explicitly).
    """
    config = config.resolved(geometry)
    offset = config.source_level_db + _rx_gain(geometry, config) - config.full_scale_db
    return 10.0 ** ((offset - transmission_loss_db(geometry.range_m, config)) / 10.0)


def _noise_power(geometry: SonarGeometry, config: SimulationConfig) -> float:
    return float(10.0 ** ((config.noise_level_db + _rx_gain(geometry, config) - config.full_scale_db) / 10.0))


def expected_background_level(
    geometry: SonarGeometry, config: SimulationConfig = SimulationConfig()
) -> NDArray[np.float64]:
    """Mean background intensity per bin for a beam of unit taper, before threshold, shape (n_bins,).

    ``channel_gain(r) * 10^(reverb_db/10) + noise`` (+ the ring-down, where a profile has one):
    multiply the first term by ``geometry.taper[j]`` (the noise term is tiny by default) for beam
    ``j``.  After a radial gain ``1 / channel_gain`` it is flat.
    """
    config = config.resolved(geometry)
    out = channel_gain(geometry, config) * 10.0 ** (config.reverb_db / 10.0) + _noise_power(geometry, config)
    if config.ring_down_level > 0:
        out = out + _ring_down(geometry, config)
    return out


def _ring_down(geometry: SonarGeometry, config: SimulationConfig) -> NDArray[np.float64]:
    return config.ring_down_level * np.exp(-np.asarray(geometry.range_m) / config.ring_down_m)


def _taper(geometry: SonarGeometry) -> NDArray[np.float64]:
    return np.ones(geometry.n_beams) if geometry.taper is None else np.asarray(geometry.taper)


def _background_mean(geometry: SonarGeometry, config: SimulationConfig) -> NDArray[np.float64]:
    rv = channel_gain(geometry, config) * 10.0 ** (config.reverb_db / 10.0)
    out = rv[:, None] * _taper(geometry)[None, :] + _noise_power(geometry, config)
    if config.ring_down_level > 0:
        out = out + _ring_down(geometry, config)[:, None]
    return out


def _level_thresholds(config: SimulationConfig, ks: NDArray[np.float64]) -> NDArray[np.float64]:
    """Intensity at which the receiver mapping reaches the pixel values ``ks`` (in [0, 1])."""
    if config.receiver == "log":
        return 10.0 ** ((ks + config.threshold - 1.0) * config.dynamic_range_db / 10.0)
    return config.threshold + ks


def _exceedance(x: NDArray[np.float64], mean: NDArray[np.float64], looks: int) -> NDArray[np.float64]:
    """``P(I >= x)`` for ``I`` the average of ``looks`` exponentials of mean ``mean``."""
    if looks == 1:
        return np.exp(-x / mean)
    from scipy.special import gammaincc

    return gammaincc(looks, looks * x / mean)


def expected_background_image(
    geometry: SonarGeometry, config: SimulationConfig = SimulationConfig()
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Expected recorded pixel value and probability of a zero pixel in open water.

    Exact for the model: ``I`` is exponential with mean ``mu = m_bg + n``, so
    ``P(q >= k/255) = exp(-(threshold + k/255) / mu)`` (floor quantisation, linear receiver) and
    ``E[q] = sum_k P(q >= k/255) / 255``.  With ``looks`` L > 1 the exponential becomes a gamma
    distribution of shape L (``scipy.special.gammaincc``); the log receiver reaches level ``k``
    at ``I = 10^((k/255 + threshold - 1) D / 10)``.  ``config`` is resolved for ``geometry``.

    Returns
    -------
    mean, p_zero : ndarray, shape (n_bins, n_beams)
    """
    config = config.resolved(geometry)
    mu_full = _background_mean(geometry, config)
    # every pixel with the same mean has the same distribution: evaluate each level once
    mu, inverse = np.unique(mu_full, return_inverse=True)
    shift = 0.5 if config.quantization == "round" else 0.0
    ks = (np.arange(1, 256) - shift) / 255.0
    x = _level_thresholds(config, ks)
    if config.speckle:
        exceed = _exceedance(x, mu[..., None], config.looks)
    else:  # deterministic reverberation; receiver noise still exponential (gamma with looks)
        rv = mu - _noise_power(geometry, config)
        n = _noise_power(geometry, config)
        need = np.maximum(x - rv[..., None], 0.0)
        exceed = _exceedance(need, n, config.looks)
    mean = exceed.sum(axis=-1) / 255.0
    p_zero = 1.0 - exceed[..., 0]
    shape = mu_full.shape
    return mean[inverse].reshape(shape), p_zero[inverse].reshape(shape)


# ---------------------------------------------------------------------- rendering


def _edges(centres: NDArray[np.float64]) -> NDArray[np.float64]:
    """Bin edges at midpoints, extended by half a spacing at both ends."""
    if centres.size == 1:
        return np.array([-np.inf, np.inf])
    mid = 0.5 * (centres[1:] + centres[:-1])
    lo = centres[0] - (mid[0] - centres[0])
    hi = centres[-1] + (centres[-1] - mid[-1])
    return np.concatenate([[lo], mid, [hi]])


def _beam_pattern(image: NDArray[np.float64], psf: NDArray[np.float64] | None, *,
                  amplitude: bool = False) -> NDArray[np.float64]:
    """Linear (zero-padded) convolution across beams with ``psf`` centred at ``n // 2``.

    ``amplitude=True`` convolves with ``sqrt(psf)`` (a field, whose intensity the psf blurs).

    ``out[:, j] = sum_k image[:, k] psf[c + j - k]``; only the non-zero taps are visited, so the
    DIDSON's 12-tap pattern costs 12 shifted additions and introduces no FFT round-off.
    """
    if psf is None:
        return image
    n = image.shape[1]
    c = n // 2
    out = np.zeros_like(image)
    for idx in np.flatnonzero(psf):
        d = int(idx) - c  # output beam = input beam + d
        w = math.sqrt(float(psf[idx])) if amplitude else float(psf[idx])
        if d >= 0:
            if d < n:
                out[:, d:] += w * image[:, : n - d]
        elif -d < n:
            out[:, : n + d] += w * image[:, -d:]
    return out


def _elevation_weight(el: NDArray[np.float64], config: SimulationConfig) -> NDArray[np.float64]:
    w = config.elevation_aperture_rad
    if config.elevation_pattern == "uniform":
        return (np.abs(el) <= w / 2).astype(np.float64)
    return np.exp(-4.0 * math.log(2.0) * (el / w) ** 2)


def _accumulate(
    scene: Scene, geometry: SonarGeometry, config: SimulationConfig
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unblurred per-pixel echo energy (linear m^2) for structure and clutter, each (n_bins, n_beams)."""
    nb, nbeam = geometry.shape
    size = nb * nbeam
    if len(scene) == 0:
        z = np.zeros((nb, nbeam))
        return z, z.copy()
    p = scene.points_m
    x, y, zc = p[:, 0], p[:, 1], p[:, 2]
    rho = np.hypot(x, y)
    r = np.hypot(rho, zc)
    az = np.arctan2(y, x)
    el = np.arctan2(zc, rho)
    r_edges = _edges(geometry.range_m)
    a_edges = _edges(geometry.azimuth_rad)
    bi = np.searchsorted(r_edges, r, side="right") - 1
    bj = np.searchsorted(a_edges, az, side="right") - 1
    inside = (bi >= 0) & (bi < nb) & (bj >= 0) & (bj < nbeam) & (r > 0)
    nrm = scene.normals
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_inc = np.abs(np.einsum("ij,ij->i", nrm, p)) / r
    isotropic = ~np.any(nrm != 0, axis=1)
    g = np.where(isotropic, 1.0, np.nan_to_num(cos_inc) ** config.incidence_exponent)
    energy = scene.reflectivity * scene.patch_area_m2 * g * _elevation_weight(el, config)
    flat = bi * nbeam + bj
    sel = inside & (energy > 0)
    out = []
    for label in (STRUCTURE, CLUTTER):
        m = sel & (scene.labels == label)
        if np.any(m):
            acc = np.bincount(flat[m], weights=energy[m], minlength=size)
        else:
            acc = np.zeros(size)
        out.append(acc.reshape(nb, nbeam))
    return out[0], out[1]


#: Ghost-to-main-beam intensity ratios at +-8, +-16, +-24 beams measured on the real DIDSON test
#: ping 5 (a clean diagonal hull line) by :func:`sonarmap.simulate.compare.ghost_ratios`;
#: ``python -m sonarmap.simulate.compare --ghosts PING`` reproduces them.  The sonar's stated PSF
#: (``geometry.psf``) implies 0.57 / 0.46 / 0.39.
MEASURED_DIDSON_GHOSTS: tuple[float, ...] = (0.031, 0.007, 0.005)


def render_psf(geometry: SonarGeometry, config: SimulationConfig) -> NDArray[np.float64] | None:
    """The across-beam pattern :func:`simulate_ping` renders with (see ``beam_pattern``)."""
    config = config.resolved(geometry)
    psf = geometry.psf
    if psf is None or config.beam_pattern == "geometry":
        return psf
    p = np.asarray(psf, dtype=np.float64)
    c = p.size // 2
    taps = np.flatnonzero(p)
    offs = np.abs(taps - c)
    step = int(offs[offs > 0].min()) if (offs > 0).any() else 0
    out = np.zeros_like(p)
    out[c] = 1.0
    if step:
        for k, ratio in enumerate(MEASURED_DIDSON_GHOSTS, start=1):
            for idx in (c - k * step, c + k * step):
                if 0 <= idx < p.size and p[idx] > 0:
                    out[idx] = ratio
    return out / out.sum()


def _pulse_smooth(energy: NDArray[np.float64], geometry: SonarGeometry,
                  config: SimulationConfig) -> NDArray[np.float64]:
    """Average ``energy`` along range over the pulse's range resolution (unit-sum box)."""
    if config.range_resolution_m <= 0 or geometry.n_bins < 2:
        return energy
    n = int(round(config.range_resolution_m / geometry.range_resolution_m))
    if n < 2 or not energy.any():
        return energy
    from scipy.ndimage import uniform_filter1d

    return uniform_filter1d(energy, size=n, axis=0, mode="constant")


def _one_look(
    rng: np.random.Generator,
    shape: tuple[int, int],
    config: SimulationConfig,
    psf: NDArray[np.float64] | None,
    a: NDArray[np.float64] | None,
    taper: NDArray[np.float64],
    m_bg: NDArray[np.float64],
    m_scatter: NDArray[np.float64],
    noise: float,
) -> NDArray[np.float64]:
    """One speckle realisation of the received intensity (full-scale units).

    Speckle (Rayleigh amplitude) and additive receiver noise, in the complex amplitude domain;
    ``a`` (the per-direction echo amplitude) is given for coherent ghosts.
    """
    z = rng.standard_normal((4,) + shape)
    z *= math.sqrt(0.5)
    if a is not None:
        # complex echo field per source direction, seen through the pattern's amplitude taps
        zs = rng.standard_normal((2,) + shape)
        zs *= math.sqrt(0.5)
        field_re = _beam_pattern(a * zs[0], psf, amplitude=True)
        field_im = _beam_pattern(a * zs[1], psf, amplitude=True)
        st = np.sqrt(taper)
        amp_bg = np.sqrt(np.maximum(m_bg - noise, 0.0))
        re = st * field_re + amp_bg * z[0] + math.sqrt(noise) * z[2]
        im = st * field_im + amp_bg * z[1] + math.sqrt(noise) * z[3]
        return re * re + im * im
    if config.speckle:
        amp = np.sqrt(m_scatter)
        re = amp * z[0] + math.sqrt(noise) * z[2]
        im = amp * z[1] + math.sqrt(noise) * z[3]
        return re * re + im * im
    return m_scatter + noise * (z[2] ** 2 + z[3] ** 2)


def _validate(scene: Any, geometry: Any, config: Any) -> None:
    if not isinstance(scene, Scene):
        raise InputError(f"scene: expected a Scene, got {type(scene).__name__}")
    if not isinstance(geometry, SonarGeometry):
        raise InputError(f"geometry: expected a SonarGeometry, got {type(geometry).__name__}")
    if not isinstance(config, SimulationConfig):
        raise InputError(f"config: expected a SimulationConfig, got {type(config).__name__}")


def simulate_ping(
    scene: Scene,
    geometry: SonarGeometry,
    *,
    config: SimulationConfig = SimulationConfig(),
    seed: int | np.random.Generator,
    time_ns: int = 0,
) -> SimResult:
    """Render one ping of ``scene`` seen by ``geometry`` through the active sonar equation.

    Parameters
    ----------
    scene : Scene
        Surface samples in the sonar frame.
    geometry : SonarGeometry
        Range bins (``range_m``), beam azimuth table (``azimuth_rad``, may be non-uniform), beam
        pattern ``psf``, ``taper`` and ``rx_gain_db``.
    config : SimulationConfig
        Sonar-equation and receiver parameters; fields not set explicitly take the values of the
        geometry's sonar profile (:meth:`SimulationConfig.resolved`; unchanged for DIDSON).
    seed : int or numpy.random.Generator
        Randomness (speckle, noise); the same integer seed gives identical bytes.
    time_ns : int
        Ping time stamp.

    Returns
    -------
    SimResult
        Its ``config`` is the resolved configuration actually rendered.

    Notes
    -----
    Each sample falls into the bin nearest its range ``|p|`` and the beam nearest its azimuth
    ``atan2(y, x)`` (samples outside the window or fan are dropped), weighted by its target
    strength and the vertical pattern at elevation ``atan2(z, hypot(x, y))``.  Then: beam pattern
    across beams (linear convolution, eq. 2 of Teixeira et al. 2018), taper ``k(theta)`` (eq. 5),
    channel ``SL + G - FS - (20 beta log10 r + 2 alpha r)`` (eqs. 6-7), Rayleigh speckle averaged
    over ``looks``, receiver noise, receiver mapping (linear with threshold, or log) and 8-bit
    quantisation.

    Examples
    --------
    >>> from sonarmap import preset
    >>> from sonarmap.simulate import scene_from_name
    >>> g = preset("aris3000-128")
    >>> res = simulate_ping(scene_from_name("hull", geometry=g), g, seed=0)
    >>> res.config.receiver, bool(res.ping.image.min() > 0)
    ('log', True)
    """
    _validate(scene, geometry, config)
    config = config.resolved(geometry)
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer | np.random.Generator):
        raise InputError(f"seed: expected an int or numpy Generator, got {type(seed).__name__}")
    rng = np.random.default_rng(seed)
    e_struct, e_clutter = _accumulate(scene, geometry, config)
    gain_r = channel_gain(geometry, config)[:, None]
    taper = _taper(geometry)[None, :]
    total = e_struct + e_clutter
    total = _pulse_smooth(total, geometry, config)
    psf = render_psf(geometry, config)
    blurred = _beam_pattern(total, psf)
    m_echo = blurred * taper * gain_r
    m_bg = _background_mean(geometry, config)
    noise = _noise_power(geometry, config)
    shape = geometry.shape
    m_scatter = m_echo + (m_bg - noise)
    coherent = config.speckle and config.ghosts == "coherent" and psf is not None
    a = np.sqrt(total * gain_r) if coherent else None
    intensity = _one_look(rng, shape, config, psf, a, taper, m_bg, m_scatter, noise)
    if config.looks > 1:
        for _ in range(config.looks - 1):
            intensity += _one_look(rng, shape, config, psf, a, taper, m_bg, m_scatter, noise)
        intensity /= config.looks
    if config.receiver == "log":
        with np.errstate(divide="ignore"):
            level = 1.0 + 10.0 * np.log10(intensity) / config.dynamic_range_db
        p = np.clip(level - config.threshold, 0.0, 1.0)
    else:
        p = np.clip(intensity - config.threshold, 0.0, 1.0)
    if config.quantization == "floor":
        q = np.floor(p * 255.0 + 1e-9)
    else:
        q = np.rint(p * 255.0)
    # Same float32 values as the PNG reader produces (k * float32(1/255)), so round trips are exact.
    image = q.astype(np.float32) * np.float32(1.0 / 255.0)
    # Truth from the unblurred scene.
    scale = taper * gain_r
    s_int = e_struct * scale
    c_int = e_clutter * scale
    floor_ = m_bg * 10.0 ** (config.truth_snr_db / 10.0)
    is_s = s_int >= floor_
    is_c = c_int >= floor_
    mask = np.zeros(shape, np.uint8)
    mask[is_s] = STRUCTURE
    mask[is_c & (~is_s | (c_int > s_int))] = CLUTTER
    struct = mask == STRUCTURE
    has = struct.any(axis=0)
    # a pixel is structure at threshold t iff s_int >= floor_t and clutter does not exceed it
    with np.errstate(divide="ignore", invalid="ignore"):
        peak_db = 10.0 * np.log10(np.where(s_int >= c_int, s_int / m_bg, 0.0).max(axis=0))
    first = np.where(has, struct.argmax(axis=0), -1).astype(np.int64)
    first_r = np.where(has, geometry.range_m[np.maximum(first, 0)], np.nan)
    ping = Ping(
        image=image,
        geometry=geometry,
        time_ns=time_ns,
        source="",
        meta={"simulated": scene.name or "scene"},
    )
    int_seed = int(seed) if isinstance(seed, int | np.integer) else None
    return SimResult(
        ping=ping,
        clean=np.clip(m_echo, 0.0, 1.0).astype(np.float32),
        class_mask=mask,
        first_return_bin=first,
        first_return_range_m=first_r,
        config=config,
        scene_name=scene.name,
        seed=int_seed,
        unblurred=np.clip(total * scale, 0.0, 1.0).astype(np.float32),
        structure_peak_snr_db=peak_db.astype(np.float64),
    )


# ---------------------------------------------------------------------- files


@dataclasses.dataclass(frozen=True)
class SimulationFiles:
    """Paths written by :func:`write_simulation`."""

    image: Path
    sidecar: Path
    truth_mask: Path
    truth_json: Path


def write_simulation(result: SimResult, directory: str | os.PathLike[str], stem: str | None = None) -> SimulationFiles:
    """Write ``<stem>_raw.png`` + ``<stem>.json`` (the real data's format) and the truth files.

    ``<stem>_truth.png`` is the class mask as raw 8-bit values (0 background, 1 structure,
    2 clutter); ``<stem>_truth.json`` holds ``first_return_bin``, ``first_return_range_m`` (null
    where none), ``scene``, ``seed``, ``time_ns`` and ``config``.  All files are written atomically.
    ``stem`` defaults to the ping time in microseconds.
    """
    from PIL import Image

    from sonarmap._atomic import atomic_path, atomic_write_text
    from sonarmap.io.pngjson import write_png_ping

    d = Path(directory)
    if stem is None:
        stem = str(result.ping.time_ns // 1000)
    img = write_png_ping(result.ping, d, stem=stem)
    truth_png = d / f"{stem}_truth.png"
    with atomic_path(truth_png) as tmp:
        Image.fromarray(result.class_mask, mode="L").save(tmp, format="PNG")
    truth = {
        "scene": result.scene_name,
        "seed": result.seed,
        "time_ns": result.ping.time_ns,
        "class_values": {"background": 0, "structure": STRUCTURE, "clutter": CLUTTER},
        "first_return_bin": result.first_return_bin.tolist(),
        "first_return_range_m": [
            None if not math.isfinite(v) else float(v) for v in result.first_return_range_m
        ],
        "config": result.config.to_dict(),
    }
    truth_json = d / f"{stem}_truth.json"
    atomic_write_text(truth_json, json.dumps(truth, indent=1) + "\n")
    return SimulationFiles(image=img, sidecar=d / f"{stem}.json", truth_mask=truth_png, truth_json=truth_json)


def read_truth(directory: str | os.PathLike[str], stem: str) -> tuple[NDArray[np.uint8], dict[str, Any]]:
    """Read ``<stem>_truth.png`` and ``<stem>_truth.json`` written by :func:`write_simulation`."""
    from PIL import Image

    from sonarmap.errors import DataFormatError

    d = Path(directory)
    mp = d / f"{stem}_truth.png"
    jp = d / f"{stem}_truth.json"
    try:
        with Image.open(mp) as im:
            mask = np.asarray(im, dtype=np.uint8).copy()
        info = json.loads(jp.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise DataFormatError("truth file not found", exc.filename) from None
    except (OSError, ValueError) as exc:
        raise DataFormatError(f"cannot read truth ({exc})", d / stem) from None
    return mask, info
