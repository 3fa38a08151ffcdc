"""The sonar-equation renderer: scene -> synthetic ping + truth.

Processing order (each step documented in ``docs/simulator.md``)::

    per-pixel echo energy  E[i, j]  = sum over samples of
                                      reflectivity * area * |cos inc|^p * b(elevation)
                                      * P_i(r) * L_j(azimuth)
                           P_i: share of the sample's echo - its patch's range tent through the
                           causal transmit pulse (pulse_envelope) - falling in bin i (sub-bin);
                           L_j: beam j's Gaussian main lobe towards the sample (sub-beam)
    ghost taps             E' = E (*) psf        linear convolution across beams (eq. 2)
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

Truth: the class mask and first-return bin from every sample in its nearest bin and azimuth
cell; the sub-bin physical surface ``SimResult.surface_range_m`` from the nearest structure in
each beam's two-way -3 dB footprint.  :func:`measure_edge_rise`, :func:`first_peak_crossing` and
:func:`leading_edges_m` measure leading edges of real and simulated pings alike.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.ping import Ping
from sonarmap.preprocess.absorption import absorption_db_per_m
from sonarmap.simulate.scene import CLUTTER, STRUCTURE, Scene

__all__ = [
    "SimulationConfig",
    "simulation_config_for",
    "SimResult",
    "SimulationFiles",
    "simulate_ping",
    "simulate_pings",
    "iter_simulated_pings",
    "transmission_loss_db",
    "channel_gain",
    "expected_background_level",
    "expected_background_image",
    "background_mean_image",
    "level_intensity",
    "seawater_absorption_db_per_m",
    "write_simulation",
    "read_truth",
    "pulse_envelope",
    "beam_widths_for",
    "DEFAULT_BEAM_WIDTH_GAPS",
    "main_lobe_taps",
    "ghost_psf",
    "render_psf",
    "MEASURED_DIDSON_GHOSTS",
    "MAX_FURTHER_SURFACES",
    "first_peak_crossing",
    "leading_edges_m",
    "EdgeRise",
    "measure_edge_rise",
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
    (see :class:`SimulationConfig`).  The library's
    :func:`~sonarmap.preprocess.absorption.absorption_db_per_m` (``model="ainslie-mccolm"``) with
    the simulator's defaults; arguments outside its ranges raise :class:`InputError`.
    """
    return absorption_db_per_m(frequency_hz, temperature_c=temperature_c, salinity_psu=salinity_psu,
                               depth_m=depth_m, ph=ph, model="ainslie-mccolm")


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
    pulse_length_m : float
        Length along range of the transmit pulse, ``L = c tau / 2`` (m).  The echo of a point at
        range ``r0`` starts at ``r0`` (causal) and lasts ``L``, with the intensity envelope of
        :func:`pulse_envelope` (raised-cosine rise and fall of ``pulse_rise_m``, flat between);
        each sample's echo energy is split over the bins its envelope overlaps in proportion to
        the envelope's integral over each bin (sub-bin: a surface's echo is not quantised to the
        bin grid).  Energy is conserved (the envelope has unit area).  0: no pulse.  Default
        5 mm (0.28 DIDSON bin, ``tau`` ~7 us): the real DIDSON speckle is almost uncorrelated
        along range and its sharpest echoes rise as fast as the simulator's
        (``docs/simulator.md``).  A surface's half-peak leading edge lags the surface by
        :attr:`leading_edge_delay_m`.
    pulse_rise_m : float or None
        Raised-cosine rise (= fall) length of the envelope, ``0 <= rise <= L / 2``; ``None``: ``L / 2``
        (a Hann-shaped envelope without flat top).  ``0`` gives a rectangular pulse.
    beam_width_rad : float or None
        Two-way -3 dB horizontal width of a beam's main lobe (rad).  The main lobe spreads each
        direction's echo into the neighbouring beams with the Gaussian two-way pattern
        ``exp(-4 ln2 (d dtheta / beam_width)^2)`` at ``d`` beams (``dtheta`` the mean beam
        spacing), convolved with the ghost taps in :func:`render_psf`: a sloped surface then has
        the halo of the neighbouring beams' nearer echoes in front of it.  ``None``: the
        geometry's own beam width (:func:`beam_width_for`: the ARIS beam-width tables, else one
        beam spacing); ``0``: no main-lobe spread (each direction only in its own beam).
    gain_assist_saturation : float
        Automatic gain ("gain assist", as the Oculus sonars apply by default): when more than this
        fraction of the pixels would reach full scale, the receiver gain is lowered in whole-dB
        steps until at most this fraction does (the reduction is in ``ping.meta["gain_assist_db"]``
        and ``SimResult.config.rx_gain_db``).  0 (default): a fixed gain, bright targets saturate.
    range_resolution_m : float
        Deprecated (the centred range box of earlier versions): a value larger than
        ``pulse_length_m`` is used as the pulse length.  Default 0.
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
    pulse_length_m: float = 0.005
    pulse_rise_m: float | None = None
    beam_width_rad: float | None = None
    ring_down_level: float = 0.0
    ring_down_m: float = 0.005
    gain_assist_saturation: float = 0.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            val = getattr(self, f.name)
            if isinstance(val, float | int) and not isinstance(val, bool):
                if not math.isfinite(float(val)):
                    raise InputError(f"config.{f.name}: must be finite (got {val})")
        if not 0.0 <= self.gain_assist_saturation < 1.0:
            raise InputError(f"config.gain_assist_saturation: must lie in [0, 1) (got {self.gain_assist_saturation})")
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
        if self.pulse_length_m < 0:
            raise InputError(f"config.pulse_length_m: must be >= 0 (got {self.pulse_length_m})")
        if self.pulse_rise_m is not None:
            if not math.isfinite(float(self.pulse_rise_m)):
                raise InputError(f"config.pulse_rise_m: must be finite (got {self.pulse_rise_m})")
            if not 0 <= self.pulse_rise_m <= 0.5 * max(self.pulse_length_m, self.range_resolution_m) + 1e-12:
                raise InputError(
                    f"config.pulse_rise_m: must be in [0, pulse_length_m / 2] (got {self.pulse_rise_m})"
                )
        if self.beam_width_rad is not None:
            if not math.isfinite(float(self.beam_width_rad)) or self.beam_width_rad < 0:
                raise InputError(f"config.beam_width_rad: must be >= 0 or None (got {self.beam_width_rad})")
        if self.ring_down_level < 0:
            raise InputError(f"config.ring_down_level: must be >= 0 (got {self.ring_down_level})")
        if not self.ring_down_m > 0:
            raise InputError(f"config.ring_down_m: must be positive (got {self.ring_down_m})")

    @property
    def pulse(self) -> tuple[float, float]:
        """``(length, rise)`` of the rendered pulse envelope in metres.

        The length is ``max(pulse_length_m, range_resolution_m)`` (the deprecated field only ever
        lengthens it); the rise is ``pulse_rise_m``, or half the length when that is ``None``.
        """
        length = max(float(self.pulse_length_m), float(self.range_resolution_m))
        rise = 0.5 * length if self.pulse_rise_m is None else min(float(self.pulse_rise_m), 0.5 * length)
        return length, rise

    @property
    def leading_edge_delay_m(self) -> float:
        """How far the half-peak leading edge of a surface's echo lies behind the surface (m).

        The pulse is causal, so the echo's 0.5-of-first-peak crossing is late by the envelope's
        centroid, half the pulse length (measured on noise-free renders of flat and sloped hulls
        and the seafloor: ``docs/simulator.md``); a point target's by ``rise / 2``.  Subtract it
        from a leading-edge range to compare with ``SimResult.surface_range_m``.
        """
        return 0.5 * self.pulse[0]

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
        Like ``clean`` but before the beam pattern - main lobe and ghosts: each direction's echo
        in its own azimuth cell (through the pulse; the ideal image deconvolution aims at).
    structure_peak_snr_db : ndarray, shape (n_beams,), float64
        Per beam, the highest structure-to-background ratio (dB, unblurred) of a pixel where
        structure is not outshone by clutter; ``-inf`` where none.  A beam has structure in the
        class mask at a truth threshold ``t`` exactly when this is ``>= t``, so callers can ask
        about another threshold without rendering again.
    surface_range_m : ndarray, shape (n_beams,), float64
        Sub-bin physical truth of the first surface: per beam, the nearest range of the structure
        samples in the beam's azimuth cell (and the range window) whose two-way elevation weight
        is >= 0.5 (the beam's -3 dB footprint; a beam whose structure never reaches 0.5 uses half
        its largest weight instead).  It is not quantised to the bin grid: it is the range a
        leading-edge detector (first crossing of 0.5 x the echo's first peak) should report -
        within a quarter bin (plus half the pulse) of the noise-free echo's crossing on the
        DIDSON and ARIS presets; through a wide vertical beam (the Oculus preset's 12 deg) a
        surface's echo rises over tens of bins and that crossing lies 2-10 bins in front of it
        (docs/simulator.md, "Clean-echo crossing vs truth").
        NaN on the beams without truth structure (``first_return_bin == -1``).
    surface_ranges_m : ndarray, shape (k, n_beams), float64
        Further surfaces behind ``surface_range_m`` on each beam, nearest first (like
        ``BeamRanges.other_range_m``): the same rule applied to the footprint samples after a gap
        in range of more than the pulse length plus two bins (e.g. propeller blades behind the
        hub, a hull behind a rudder).  Geometric only (no visibility test); NaN where none;
        ``k`` (at most :data:`MAX_FURTHER_SURFACES`) may be 0.
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
    surface_range_m: NDArray[np.float64] | None = None
    surface_ranges_m: NDArray[np.float64] | None = None


# ---------------------------------------------------------------------- channel quantities


def transmission_loss_db(range_m: NDArray[np.float64] | float, config: SimulationConfig) -> NDArray[np.float64]:
    """Two-way loss ``20 beta log10 r + 2 alpha r`` in dB (eqs. 6-7); ranges below 1 cm are clamped.

    ``config`` is used as given (resolve it for a geometry first: :meth:`SimulationConfig.resolved`).
    """
    r = np.maximum(np.asarray(range_m, dtype=np.float64), 0.01)
    return 20.0 * config.spreading_beta * np.log10(r) + 2.0 * config.alpha_db_per_m * r


def _gain_assist_db(intensity: NDArray[np.float64], config: SimulationConfig) -> float:
    """Whole-dB gain reduction that leaves at most ``config.gain_assist_saturation`` of the pixels
    at full scale (0 when off or when the image does not saturate more than that)."""
    f = config.gain_assist_saturation
    if f <= 0:
        return 0.0
    top = float(np.quantile(intensity, 1.0 - f))
    if config.receiver == "log":
        over_db = 10.0 * math.log10(top) - config.threshold * config.dynamic_range_db if top > 0 else -math.inf
    else:
        over_db = 10.0 * math.log10(top / (1.0 + config.threshold)) if top > 0 else -math.inf
    return float(max(math.ceil(over_db - 1e-9), 0))


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


def background_mean_image(geometry: SonarGeometry, config: SimulationConfig = SimulationConfig()) -> NDArray[np.float64]:
    """Mean received background intensity per pixel, shape (n_bins, n_beams): reverberation
    through each beam's taper and the channel, plus receiver noise (plus the ring-down, where a
    profile has one) - the ``m_bg + n`` a pixel's speckle is drawn around (the expected
    intensity of a pixel is this plus the echo, :attr:`SimResult.clean` before clipping).
    ``config`` is resolved for ``geometry`` first.

    Examples
    --------
    >>> from sonarmap import preset
    >>> background_mean_image(preset("didson-hf")).shape
    (512, 96)
    """
    config = config.resolved(geometry)
    return _background_mean(geometry, config)


def _background_mean(geometry: SonarGeometry, config: SimulationConfig) -> NDArray[np.float64]:
    rv = channel_gain(geometry, config) * 10.0 ** (config.reverb_db / 10.0)
    out = rv[:, None] * _taper(geometry)[None, :] + _noise_power(geometry, config)
    if config.ring_down_level > 0:
        out = out + _ring_down(geometry, config)[:, None]
    return out


def level_intensity(config: SimulationConfig, levels: ArrayLike) -> NDArray[np.float64]:
    """The received intensity (the units of :attr:`SimResult.clean`, after any gain assist) at
    which the receiver reaches the recorded values ``levels`` (in [0, 1]): the inverse of its
    mapping, linear with threshold or log.  At ``1.0``, full scale: samples at or above it are
    recorded as 1.0.

    Examples
    --------
    >>> float(level_intensity(SimulationConfig(receiver="linear", threshold=0.01), 1.0))
    1.01
    """
    return np.asarray(_level_thresholds(config, np.asarray(levels, dtype=np.float64)), dtype=np.float64)


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


# ---------------------------------------------------------------------- transmit pulse


def pulse_envelope(x_m: ArrayLike, length_m: float, rise_m: float | None = None) -> NDArray[np.float64]:
    """Intensity envelope (peak 1) of the echo of a point target, ``x_m`` metres behind it.

    Causal: 0 for ``x < 0`` and ``x > L``; a raised-cosine rise ``(1 - cos(pi x / R)) / 2`` over
    ``0 <= x < R``, 1 over ``R <= x <= L - R`` and the mirrored raised-cosine fall over the last
    ``R``.  ``R = rise_m`` (default ``L / 2``: a Hann-shaped envelope without flat top; ``0``: a
    rectangle).  Its area is ``L - R``; its 10-90 % rise is ``0.59 R``.

    Parameters
    ----------
    x_m : array_like
        Distance behind the target along range (m).
    length_m : float
        Pulse length along range ``L = c tau / 2`` (m), > 0.
    rise_m : float, optional
        Rise (= fall) length, ``0 <= R <= L / 2``.

    Returns
    -------
    ndarray
        The envelope at ``x_m``.

    Examples
    --------
    >>> pulse_envelope([-0.01, 0.0025, 0.005, 0.01, 0.02], 0.01).round(3).tolist()
    [0.0, 0.5, 1.0, 0.0, 0.0]
    """
    x = np.asarray(x_m, dtype=np.float64)
    length = float(length_m)
    rise = 0.5 * length if rise_m is None else float(rise_m)
    if not length > 0 or not 0 <= rise <= 0.5 * length + 1e-15:
        raise InputError(f"length_m/rise_m: need L > 0 and 0 <= R <= L/2 (got {length_m}, {rise_m})")
    out = ((x >= 0) & (x <= length)).astype(np.float64)
    if rise > 0:
        up = (x >= 0) & (x < rise)
        out[up] = 0.5 * (1.0 - np.cos(math.pi * x[up] / rise))
        down = (x > length - rise) & (x <= length)
        out[down] = 0.5 * (1.0 + np.cos(math.pi * (x[down] - (length - rise)) / rise))
    return out


def _pulse_cdf(x: NDArray[np.float64], length: float, rise: float) -> NDArray[np.float64]:
    """Fraction of the unit-area envelope of :func:`pulse_envelope` lying before ``x``."""
    if length <= 0:
        return (x >= 0).astype(np.float64)
    xc = np.clip(x, 0.0, length)
    if rise <= 0:
        return xc / length
    k = rise / math.pi
    flat_end = length - rise
    e = np.where(
        xc < rise,
        0.5 * (xc - k * np.sin(xc / k)),
        np.where(
            xc <= flat_end,
            0.5 * rise + (xc - rise),
            (length - 1.5 * rise) + 0.5 * ((xc - flat_end) + k * np.sin((xc - flat_end) / k)),
        ),
    )
    return e / (length - rise)


class _PulseKernel:
    """CDF of the echo of a patch: the unit-area pulse envelope convolved with a tent.

    A patch of range half-extent ``h`` spreads its echo with the tent ``box(h) * box(h)``
    (half-width ``h``; unlike a box, a row of tents at any spacing below ``h`` sums to an almost
    flat surface).  With ``P`` the pulse's CDF and ``S`` its second antiderivative, the CDF is the
    second difference ``(S(x + h) - 2 S(x) + S(x - h)) / h^2``.
    """

    def __init__(self, length: float, rise: float) -> None:
        self.length = float(length)
        self.rise = float(rise)
        if self.length > 0:
            x = np.linspace(0.0, self.length, 4097)
            p = _pulse_cdf(x, self.length, self.rise)
            dx = np.diff(x)
            q = np.concatenate([[0.0], np.cumsum(0.5 * (p[1:] + p[:-1]) * dx)])
            s2 = np.concatenate([[0.0], np.cumsum(0.5 * (q[1:] + q[:-1]) * dx)])
            self._x, self._q, self._s = x, q, s2

    def _second(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """``S(x)``: the pulse CDF integrated twice (0 before the pulse, quadratic after it)."""
        if self.length <= 0:
            return 0.5 * np.maximum(x, 0.0) ** 2
        # linear interpolation on the uniform table, by index (no search)
        n = self._s.size - 1
        pos = np.clip(x * (n / self.length), 0.0, n)
        i = np.minimum(pos.astype(np.int64), n - 1)
        f = pos - i
        inside = self._s[i] * (1.0 - f) + self._s[i + 1] * f
        u = x - self.length
        after = self._s[-1] + self._q[-1] * u + 0.5 * u * u
        return np.where(u > 0, after, inside)

    def cdf(self, x: NDArray[np.float64], half_width: NDArray[np.float64]) -> NDArray[np.float64]:
        """Fraction of the echo of a patch at ``r`` (tent half-width ``half_width``) before ``r + x``."""
        wide = half_width > 1e-9
        if not wide.any():
            return _pulse_cdf(x, self.length, self.rise)
        h = np.where(wide, half_width, 1.0)
        tent = np.clip((self._second(x + h) - 2.0 * self._second(x) + self._second(x - h)) / (h * h), 0.0, 1.0)
        if wide.all():
            return tent
        return np.where(wide, tent, _pulse_cdf(x, self.length, self.rise))


@dataclasses.dataclass(frozen=True)
class _Samples:
    """Per-sample quantities of a scene seen by a geometry (only samples inside the fan)."""

    r: NDArray[np.float64]
    beam: NDArray[np.int64]
    weight_el: NDArray[np.float64]
    energy: NDArray[np.float64]
    labels: NDArray[np.uint8]
    extent: NDArray[np.float64]
    az: NDArray[np.float64]
    az_extent: NDArray[np.float64]
    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    size: NDArray[np.float64]


def _samples(scene: Scene, geometry: SonarGeometry, config: SimulationConfig) -> _Samples:
    """Range, beam (azimuth cell), two-way elevation weight, echo energy and range extent of
    every sample inside the fan.

    A surface sample stands for a patch of side ``sqrt(patch_area_m2)``; its echo is spread in
    range by a tent of half-width ``side * sin(incidence)`` (``extent``; the patch's range
    extent) and in azimuth by a tent of half-width its across-track extent over ``hypot(x, y)``
    (``az_extent``), so a surface's samples tile it instead of beating against the bin and beam
    grids; point scatterers (zero normal) have no extent.
    """
    if len(scene) == 0:
        z = np.zeros(0)
        z3 = np.zeros((0, 3))
        return _Samples(z, np.zeros(0, np.int64), z, z, np.zeros(0, np.uint8), z, z, z, z3, z3, z)
    p = scene.points_m
    x, y, zc = p[:, 0], p[:, 1], p[:, 2]
    rho = np.hypot(x, y)
    r = np.hypot(rho, zc)
    az = np.arctan2(y, x)
    el = np.arctan2(zc, rho)
    a_edges = _edges(geometry.azimuth_rad)
    bj = np.searchsorted(a_edges, az, side="right") - 1
    nrm = scene.normals
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_inc = np.nan_to_num(np.abs(np.einsum("ij,ij->i", nrm, p)) / r)
    isotropic = ~np.any(nrm != 0, axis=1)
    g = np.where(isotropic, 1.0, cos_inc ** config.incidence_exponent)
    w_el = _elevation_weight(el, config)
    energy = scene.reflectivity * scene.patch_area_m2 * g * w_el
    size = np.where(isotropic, 0.0, np.sqrt(scene.patch_area_m2))
    extent = size * np.sqrt(np.clip(1.0 - cos_inc * cos_inc, 0.0, 1.0))
    # across-track extent: the patch projected on the azimuth direction (-sin az, cos az, 0)
    n_az = -nrm[:, 0] * np.sin(az) + nrm[:, 1] * np.cos(az)
    with np.errstate(invalid="ignore", divide="ignore"):
        az_extent = np.nan_to_num(size * np.sqrt(np.clip(1.0 - n_az * n_az, 0.0, 1.0)) / rho)
    keep = (bj >= 0) & (bj < geometry.n_beams) & (r > 0) & (energy > 0)
    return _Samples(r[keep], bj[keep].astype(np.int64), w_el[keep], energy[keep], scene.labels[keep],
                    extent[keep], az[keep], az_extent[keep], p[keep], nrm[keep], size[keep])


def _accumulate(
    smp: _Samples, geometry: SonarGeometry, labels: tuple[int, ...] = (STRUCTURE, CLUTTER),
) -> list[NDArray[np.float64]]:
    """Per-pixel echo energy (linear m^2) for the truth, one (n_bins, n_beams) image per label:
    each sample in the bin containing its range (the nearest bin centre) and its azimuth cell."""
    nb, nbeam = geometry.shape
    size = nb * nbeam
    r_edges = _edges(geometry.range_m)
    out = []
    for label in labels:
        m = smp.labels == label
        b0 = np.searchsorted(r_edges, smp.r[m], side="right") - 1
        ok = (b0 >= 0) & (b0 < nb)
        acc = np.bincount((b0 * nbeam + smp.beam[m])[ok], weights=smp.energy[m][ok], minlength=size)
        out.append(acc.reshape(nb, nbeam))
    return out


def _azimuth_parts(
    az: NDArray[np.float64], cell: NDArray[np.int64], half_extent: NDArray[np.float64],
    a_edges: NDArray[np.float64], nbeam: int,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """The azimuth cells each patch's tent (half-width ``half_extent``) overlaps:
    (sample index, cell, share), zero shares dropped."""
    step = _min_step(a_edges)
    reach = int(math.ceil(_max(half_extent) / step)) if math.isfinite(step) else 0
    parts = []
    for d in range(-reach, reach + 1):
        beam = cell + d
        cb = np.clip(beam, 0, nbeam - 1)
        frac = _tent_cdf(a_edges[cb + 1] - az, half_extent) - _tent_cdf(a_edges[cb] - az, half_extent)
        parts.append((beam, np.where((beam >= 0) & (beam < nbeam), frac, 0.0)))
    idx, beams, weights = [], [], []
    for beam, w in parts:
        ok = np.flatnonzero(w > 0)
        idx.append(ok)
        beams.append(beam[ok])
        weights.append(w[ok])
    if not idx:
        z = np.zeros(0, np.int64)
        return z, z, np.zeros(0)
    return np.concatenate(idx), np.concatenate(beams), np.concatenate(weights)


def _render_energy(
    smp: _Samples, geometry: SonarGeometry, length: float, rise: float, lobe: _MainLobe | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The echo energy images of the rendering, each (n_bins, n_beams): through the main lobe,
    and in each direction's own azimuth cell (the same as the first without a lobe).

    Each sample's echo - its patch's range tent (:class:`_PulseKernel`) through the unit-area
    envelope of :func:`pulse_envelope` starting at its range (length 0: no pulse) - is integrated
    over every bin it overlaps (``cdf(upper edge - r) - cdf(lower edge - r)``); across beams it is
    received by every beam through that beam's main lobe (:class:`_MainLobe`; the sample's
    azimuth is resolved to 1/``_SUB_DIRECTIONS`` of a beam), or, for the cell image, split over
    the azimuth cells its patch's tent overlaps.
    """
    nb, nbeam = geometry.shape
    size = nb * nbeam
    r_edges = _edges(geometry.range_m)
    a_edges = _edges(geometry.azimuth_rad)
    r_step = _min_step(r_edges)
    kernel = _PulseKernel(length, rise)
    cell_acc = np.zeros(size)
    r, bj, e, ext = smp.r, smp.beam, smp.energy, smp.extent
    if r.size == 0:
        return cell_acc.reshape(nb, nbeam), cell_acc.reshape(nb, nbeam).copy()
    b0 = np.searchsorted(r_edges, r - ext, side="right") - 1
    live = (b0 < nb) & (r + ext + kernel.length >= r_edges[0])
    r, bj, e, ext, b0, az, az_ext = (v[live] for v in (r, bj, e, ext, b0, smp.az, smp.az_extent))
    n_off = 1 + (int(math.ceil((kernel.length + 2.0 * _max(ext)) / r_step)) + 1 if math.isfinite(r_step) else 0)
    # cells: the patch's azimuth tent split over the cells; the lobe: each sample split linearly
    # between the two nearest of _SUB_DIRECTIONS sub-directions per beam, which the beams then
    # receive through their lobes (a sparse sub-direction x beam matrix)
    images = [(cell_acc, _azimuth_parts(az, bj, az_ext, a_edges, nbeam), nbeam)]
    fine = None
    if lobe is not None:
        fine_az, lobe_matrix = lobe.sub_directions(a_edges)
        nfine = fine_az.size
        pos = np.interp(az, fine_az, np.arange(nfine, dtype=np.float64))
        lo_u = np.clip(np.floor(pos).astype(np.int64), 0, nfine - 2)
        frac = np.clip(pos - lo_u, 0.0, 1.0)
        n = az.size
        fine = np.zeros(nb * nfine)
        images.append((fine, (np.concatenate([np.arange(n), np.arange(n)]), np.concatenate([lo_u, lo_u + 1]),
                              np.concatenate([1.0 - frac, frac])), nfine))
    lo_cdf = np.zeros_like(r)
    for k in range(n_off):
        b = b0 + k
        hi_cdf = kernel.cdf(r_edges[np.clip(b + 1, 0, nb)] - r, ext)
        w = e * (hi_cdf - lo_cdf)
        lo_cdf = hi_cdf
        w[(b < 0) | (b >= nb)] = 0.0
        if not (w > 0).any():
            continue
        for acc, (idx, col, wt), ncol in images:
            wk = w[idx] * wt
            ok = wk > 0
            acc += np.bincount((b[idx] * ncol + col)[ok], weights=wk[ok], minlength=acc.size)
    if fine is None:
        return cell_acc.reshape(nb, nbeam), cell_acc.reshape(nb, nbeam)
    lobe_img = np.asarray(lobe_matrix.T @ fine.reshape(nb, -1).T).T
    return np.ascontiguousarray(lobe_img), cell_acc.reshape(nb, nbeam)


def _max(x: NDArray[np.float64]) -> float:
    return float(x.max()) if x.size else 0.0


def _min_step(edges: NDArray[np.float64]) -> float:
    widths = np.diff(edges)
    finite = widths[np.isfinite(widths)]
    return float(finite.min()) if finite.size else math.inf


def _tent_cdf(x: NDArray[np.float64], half_width: NDArray[np.float64]) -> NDArray[np.float64]:
    """CDF of a unit-area tent of half-width ``half_width`` centred at 0 (a step where it is 0)."""
    h = np.where(half_width > 0, half_width, 1.0)
    u = np.clip(x / h, -1.0, 1.0)
    tent = np.where(u < 0, 0.5 * (1.0 + u) ** 2, 1.0 - 0.5 * (1.0 - u) ** 2)
    return np.where(half_width > 0, tent, (x >= 0).astype(np.float64))


#: At most this many further surfaces per beam in :attr:`SimResult.surface_ranges_m`.
MAX_FURTHER_SURFACES = 3

#: Sub-samples per side of a patch when :func:`_surface_truth` refines the footprint's edge.
_TRUTH_SUBSAMPLES = 8


def _tangent_offsets(normals: NDArray[np.float64], size: NDArray[np.float64], k: int) -> NDArray[np.float64]:
    """Offsets (n, k*k, 3) of a k x k grid over each patch (side ``size``, in its tangent plane)."""
    ref = np.where(np.abs(normals[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    a = np.cross(normals, ref)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(normals, a)
    f = (np.arange(k) + 0.5) / k - 0.5
    fu, fv = (g.ravel() for g in np.meshgrid(f, f, indexing="ij"))
    return size[:, None, None] * (fu[None, :, None] * a[:, None, :] + fv[None, :, None] * b[:, None, :])


def _footprint_pairs(
    r: NDArray[np.float64], az: NDArray[np.float64], cell: NDArray[np.int64], w_el: NDArray[np.float64],
    lobe: _MainLobe | None, nbeam: int,
) -> list[tuple[NDArray[np.int64], NDArray[np.float64]]]:
    """(beam, two-way weight) for every sample and each beam whose -3 dB lobe can hold it.

    With a main lobe: ``w_el * pattern_beam(az)`` for the beams within half a lobe width; without
    one, ``w_el`` for the sample's own azimuth cell only.
    """
    if lobe is None:
        return [(cell, w_el)]
    out = []
    for d in range(-lobe.half_reach, lobe.half_reach + 1):
        beam = cell + d
        ok = (beam >= 0) & (beam < nbeam)
        cb = np.clip(beam, 0, nbeam - 1)
        out.append((np.where(ok, beam, -1), np.where(ok, w_el * lobe.pattern(az, cb), 0.0)))
    return out


def _lobe_reach(lobe: _MainLobe | None) -> int:
    """Beams on either side a main lobe reaches (0 without one)."""
    return lobe.half_reach if lobe is not None else 0


def _near_beams(beams: NDArray[np.bool_], lobe: _MainLobe | None) -> NDArray[np.bool_]:
    """Beams within the lobe's reach of a selected beam."""
    reach = _lobe_reach(lobe)
    out = beams.copy()
    for d in range(1, reach + 1):
        out[d:] |= beams[:-d]
        out[:-d] |= beams[d:]
    return out


class _BeamWeights(NamedTuple):
    """(sample index, beam, two-way weight) triples of samples in beams' footprints."""

    sample: NDArray[np.int64]
    beam: NDArray[np.int64]
    weight: NDArray[np.float64]


def _beam_weights(st: _Samples, sel: NDArray[np.bool_], lobe: _MainLobe | None, nbeam: int) -> _BeamWeights:
    """(sample index, beam, two-way weight) of the selected samples, zero weights dropped."""
    idx = np.flatnonzero(sel)
    ii, bb, ww = [], [], []
    for beam, wt in _footprint_pairs(st.r[idx], st.az[idx], st.beam[idx], st.weight_el[idx], lobe, nbeam):
        ok = (beam >= 0) & (wt > 0)
        ii.append(idx[ok])
        bb.append(beam[ok])
        ww.append(wt[ok])
    return _BeamWeights(np.concatenate(ii), np.concatenate(bb), np.concatenate(ww))


class _Footprints(NamedTuple):
    """The structure samples in each beam's footprint and the weight threshold of every beam."""

    sample: NDArray[np.int64]
    beam: NDArray[np.int64]
    threshold: NDArray[np.float64]


def _footprints(st: _Samples, lobe: _MainLobe | None, nbeam: int) -> _Footprints:
    """(sample, beam) pairs whose two-way weight passes the beam's threshold: 0.5, or half the
    beam's largest weight when no sample reaches 0.5."""
    # beams whose footprint reaches 0.5 are settled by the samples at w_el >= 0.5; the others
    # (faint skirts) take half their largest weight over all their samples
    w = st.weight_el
    ii, bb, ww = _beam_weights(st, w >= 0.5, lobe, nbeam)
    wmax = np.zeros(nbeam)
    np.maximum.at(wmax, bb, ww)
    weak = wmax < 0.5
    if weak.any():
        ii2, bb2, ww2 = _beam_weights(st, (w < 0.5) & _near_beams(weak, lobe)[st.beam], lobe, nbeam)
        keep = weak[bb2]
        ii, bb, ww = np.concatenate([ii, ii2[keep]]), np.concatenate([bb, bb2[keep]]), np.concatenate([ww, ww2[keep]])
        np.maximum.at(wmax, bb2[keep], ww2[keep])
    thr = np.where(wmax >= 0.5, 0.5, 0.5 * wmax) * (1.0 - 1e-12)
    ok = ww >= thr[bb]
    return _Footprints(ii[ok], bb[ok], thr)


class _SurfaceStarts(NamedTuple):
    """The near edge of every surface a beam's footprint holds, surfaces ranked by range per beam."""

    beam: NDArray[np.int64]
    range_m: NDArray[np.float64]
    rank: NDArray[np.int64]


def _surface_starts(rp: NDArray[np.float64], bp: NDArray[np.int64], gap_m: float) -> _SurfaceStarts:
    """Split each beam's footprint ranges ``rp`` (beams ``bp``) into surfaces at gaps over ``gap_m``."""
    order = np.lexsort((rp, bp))
    rp, bp = rp[order], bp[order]
    new = np.ones(rp.size, dtype=bool)
    new[1:] = (bp[1:] != bp[:-1]) | (np.diff(rp) > gap_m)
    starts = np.flatnonzero(new)
    sb, sr = bp[starts], rp[starts]
    rank = np.arange(starts.size) - np.searchsorted(sb, sb, side="left")
    return _SurfaceStarts(sb, sr, rank)


def _edge_patches(st: _Samples, first: NDArray[np.float64], thr: NDArray[np.float64], config: SimulationConfig,
                  lobe: _MainLobe | None, nbeam: int) -> NDArray[np.bool_]:
    """Patches that can hold a footprint's near edge: within a patch of the first surface of a
    beam they may reach, with a weight within the elevation margin of its threshold."""
    r, bj, w, size = st.r, st.beam, st.weight_el, st.size
    reach = _lobe_reach(lobe)
    if config.elevation_pattern == "uniform":
        margin = np.ones(r.size)
    else:  # the largest change of the Gaussian elevation weight across a patch
        margin = 1.43 * 0.75 * size / (r * config.elevation_aperture_rad) + 0.02
    # a patch can move beam b's edge when it lies within a patch of b's nearest footprint sample
    cand = np.zeros(r.size, dtype=bool)
    for d in range(-reach - 1, reach + 2):
        b = np.clip(bj + d, 0, nbeam - 1)
        fb = first[b]
        with np.errstate(invalid="ignore"):
            cand |= (r >= fb - 2.0 * size) & (r <= fb + size) & (w >= thr[b] - margin)
    cand &= size > 0
    return cand


def _subsampled_first(st: _Samples, cand: NDArray[np.bool_], first: NDArray[np.float64], thr: NDArray[np.float64],
                      geometry: SonarGeometry, config: SimulationConfig, lobe: _MainLobe | None, gap_m: float
                      ) -> NDArray[np.float64]:
    """Per beam the nearest passing sub-sample of the ``cand`` patches (``_TRUTH_SUBSAMPLES`` per
    side) on its first surface; ``inf`` where none."""
    nbeam = geometry.n_beams
    r_edges = _edges(geometry.range_m)
    a_edges = _edges(geometry.azimuth_rad)
    pts = st.points[cand]
    offs = _tangent_offsets(st.normals[cand], st.size[cand], _TRUTH_SUBSAMPLES)
    sub = (pts[:, None, :] + offs).reshape(-1, 3)
    rho = np.hypot(sub[:, 0], sub[:, 1])
    rs = np.hypot(rho, sub[:, 2])
    azs = np.arctan2(sub[:, 1], sub[:, 0])
    js = np.searchsorted(a_edges, azs, side="right") - 1
    ws = _elevation_weight(np.arctan2(sub[:, 2], rho), config)
    inb = (js >= 0) & (js < nbeam) & (rs >= r_edges[0]) & (rs < r_edges[-1])
    js, rs, ws, azs = js[inb], rs[inb], ws[inb], azs[inb]
    refined = np.full(nbeam, np.inf)
    for beam, wt in _footprint_pairs(rs, azs, js, ws, lobe, nbeam):
        ok = (beam >= 0) & (wt > 0)
        ok[ok] = (wt[ok] >= thr[beam[ok]]) & np.isfinite(first[beam[ok]])
        # only within the first surface (not a further one reached through a gap)
        ok[ok] = rs[ok] <= first[beam[ok]] + gap_m
        np.minimum.at(refined, beam[ok], rs[ok])
    return refined


def _further_surfaces(starts: _SurfaceStarts, nbeam: int) -> NDArray[np.float64]:
    """``surface_ranges_m`` (k, n_beams): the near edges of up to :data:`MAX_FURTHER_SURFACES`
    surfaces behind the first."""
    rank = starts.rank
    k = int(min(MAX_FURTHER_SURFACES, rank.max())) if rank.size else 0
    others = np.full((k, nbeam), np.nan)
    for i in range(1, k + 1):
        sel = rank == i
        others[i - 1, starts.beam[sel]] = starts.range_m[sel]
    return others


def _surface_truth(
    smp: _Samples, geometry: SonarGeometry, config: SimulationConfig, has: NDArray[np.bool_], gap_m: float,
    lobe: _MainLobe | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``surface_range_m`` (n_beams,) and ``surface_ranges_m`` (k, n_beams) - see :class:`SimResult`.

    A structure sample belongs to beam ``j``'s footprint when its two-way weight - elevation
    pattern times beam ``j``'s main lobe towards its azimuth (without a main lobe: elevation
    pattern, in ``j``'s azimuth cell) - is at least 0.5 (or half the beam's largest weight when
    no sample reaches 0.5).  The nearest footprint sample is refined to a fraction of the sample
    spacing: the patches near the footprint's edge are sub-sampled (``_TRUTH_SUBSAMPLES`` per
    side, in their tangent plane) and the nearest passing sub-sample is taken.
    """
    nbeam = geometry.n_beams
    r_edges = _edges(geometry.range_m)
    m = (smp.labels == STRUCTURE) & (smp.r >= r_edges[0]) & (smp.r < r_edges[-1])
    st = _Samples(*(getattr(smp, f.name)[m] for f in dataclasses.fields(_Samples)))
    first = np.full(nbeam, np.nan)
    if st.r.size == 0:
        return first, np.full((0, nbeam), np.nan)
    fp = _footprints(st, lobe, nbeam)
    starts = _surface_starts(st.r[fp.sample], fp.beam, gap_m)
    first[starts.beam[starts.rank == 0]] = starts.range_m[starts.rank == 0]
    # refine the first surface: sub-sample the patches that can hold a footprint's near edge
    cand = _edge_patches(st, first, fp.threshold, config, lobe, nbeam)
    if cand.any():
        refined = _subsampled_first(st, cand, first, fp.threshold, geometry, config, lobe, gap_m)
        better = np.isfinite(refined) & np.isfinite(first)
        first[better] = refined[better]
    others = _further_surfaces(starts, nbeam)
    first[~has] = np.nan
    others[:, ~has] = np.nan
    return first, others


# ---------------------------------------------------------------------- beam pattern


#: Ghost-to-main-beam intensity ratios at +-8, +-16, +-24 beams measured on the real DIDSON test
#: ping 5 (a clean diagonal hull line) by :func:`sonarmap.simulate.compare.ghost_ratios`;
#: ``python -m sonarmap.simulate.compare --ghosts PING`` reproduces them.  The sonar's stated PSF
#: (``geometry.psf``) implies 0.57 / 0.46 / 0.39.
MEASURED_DIDSON_GHOSTS: tuple[float, ...] = (0.031, 0.007, 0.005)

_FOUR_LN2 = 4.0 * math.log(2.0)
#: Sub-directions per beam at which the renderer resolves a sample's azimuth for the main lobe.
_SUB_DIRECTIONS = 8
#: Integral of ``exp(-4 ln2 x^2)`` over x: a Gaussian lobe of -3 dB width W covers 1.0645 W.
_GAUSS_AREA = math.sqrt(math.pi / _FOUR_LN2)


@functools.cache
def _aris_beam_widths() -> dict[str, NDArray[np.float64]]:
    """Preset name -> per-beam two-way beam widths (rad, column order) from the ARIS tables."""
    from importlib import resources

    from sonarmap.geometry import ARIS_LENS

    tables = json.loads(resources.files("sonarmap.data").joinpath("aris_beamwidths.json").read_text("utf-8"))
    out = {}
    for table, (name, _freq) in ARIS_LENS.items():
        t = tables["tables"][table]
        width = np.abs(np.asarray(t["right_deg"], dtype=np.float64) - np.asarray(t["left_deg"], dtype=np.float64))
        arr = np.deg2rad(width[::-1])  # column j is vendor beam n - 1 - j (see sonarmap.geometry)
        arr.setflags(write=False)
        out[name] = arr
    return out


def _local_spacing(geometry: SonarGeometry) -> NDArray[np.float64]:
    """Mean of the gaps to the two neighbouring beams (the one gap at the fan's ends)."""
    az = np.asarray(geometry.azimuth_rad, dtype=np.float64)
    return np.gradient(az) if az.size > 1 else np.zeros(az.size)


def _nearest_gap(geometry: SonarGeometry) -> NDArray[np.float64]:
    """Gap to the nearer neighbouring beam."""
    az = np.asarray(geometry.azimuth_rad, dtype=np.float64)
    if az.size < 2:
        return np.zeros(az.size)
    d = np.diff(az)
    return np.minimum(np.concatenate([d[:1], d]), np.concatenate([d, d[-1:]]))


def beam_widths_for(geometry: SonarGeometry) -> NDArray[np.float64]:
    """Two-way -3 dB horizontal width of each of ``geometry``'s beams (rad), shape (n_beams,).

    ARIS geometries (preset name - also what the ARIS reader names its geometries - and matching
    beam count): the vendor's beam-width tables (``right - left`` of
    ``sonarmap/data/aris_beamwidths.json``; one beam spacing for every model except the
    telephoto lens at 48 beams, whose beams are half a spacing wide).  Any other geometry:
    :data:`DEFAULT_BEAM_WIDTH_GAPS` (0.9) times the gap to the nearer neighbouring beam - about
    one spacing (DIDSON HF: 0.3 deg beams on a table 0.23-0.37 deg apart), narrow enough that
    a neighbour receives at most 2^-4.9 = 3 % of a beam's centre (0 for a single beam).

    Examples
    --------
    >>> from sonarmap import preset
    >>> g = preset("aris3000-128")
    >>> round(float(beam_widths_for(g).mean() / np.diff(g.azimuth_rad).mean()), 2)
    1.0
    """
    name = str(getattr(geometry, "name", "")).lower()
    hit = _aris_beam_widths().get(name)
    if hit is not None and hit.size == geometry.n_beams:
        return hit.copy()
    return DEFAULT_BEAM_WIDTH_GAPS * _nearest_gap(geometry)


#: Default two-way -3 dB beam width of a geometry without a beam-width table, in units of the
#: gap to the nearer neighbouring beam.
DEFAULT_BEAM_WIDTH_GAPS = 0.9


def _beam_widths(geometry: SonarGeometry, config: SimulationConfig) -> NDArray[np.float64]:
    if config.beam_width_rad is None:
        return beam_widths_for(geometry)
    return np.full(geometry.n_beams, float(config.beam_width_rad))


@dataclasses.dataclass(frozen=True)
class _MainLobe:
    """Each beam's Gaussian main lobe at sub-beam resolution.

    Beam ``j`` receives ``k exp(-4 ln2 ((az - theta_j) / W_j)^2)`` of the echo from azimuth
    ``az``, ``W_j`` its two-way -3 dB width and ``k = mean spacing / (1.0645 mean W)`` (one
    constant per geometry) so that an extended surface gives the beams, on average, the echo of
    one beam spacing of it - the level of the azimuth-cell model the profiles were fitted with -
    and a point target on a beam's axis the same level in every beam.
    """

    azimuth: NDArray[np.float64]
    width: NDArray[np.float64]
    gain: NDArray[np.float64]
    reach: int
    half_reach: int

    @classmethod
    def of(cls, geometry: SonarGeometry, config: SimulationConfig) -> _MainLobe | None:
        width = _beam_widths(geometry, config)
        spacing = np.abs(_local_spacing(geometry))
        if geometry.n_beams < 2 or not np.all(width > 0) or not np.all(spacing > 0):
            return None
        reach = int(math.ceil(1.83 * float(width.max()) / float(spacing.min()))) + 1
        half_reach = int(math.ceil(0.5 * float(width.max()) / float(spacing.min()))) + 1
        k = float(spacing.mean()) / (_GAUSS_AREA * float(width.mean()))
        return cls(np.asarray(geometry.azimuth_rad, dtype=np.float64), width,
                   np.full(width.size, k), reach, half_reach)

    def sub_directions(self, a_edges: NDArray[np.float64]) -> tuple[NDArray[np.float64], Any]:
        """Sub-direction azimuths (``_SUB_DIRECTIONS`` per azimuth cell, at equal steps inside it)
        and the sparse (n_sub, n_beams) matrix of each beam's lobe towards each of them."""
        from scipy import sparse

        q = (np.arange(_SUB_DIRECTIONS) + 0.5) / _SUB_DIRECTIONS
        lo, hi = a_edges[:-1], a_edges[1:]
        width = np.where(np.isfinite(hi - lo), hi - lo, 0.0)
        fine = (lo[:, None] + q[None, :] * width[:, None]).ravel()
        if not np.all(np.isfinite(fine)):
            fine = np.repeat(self.azimuth, _SUB_DIRECTIONS)
        n = self.azimuth.size
        rows, cols, vals = [], [], []
        cell = np.repeat(np.arange(n), _SUB_DIRECTIONS)
        for beam, val in self.parts(fine, cell):
            ok = val > 0
            rows.append(np.flatnonzero(ok))
            cols.append(beam[ok])
            vals.append(val[ok])
        mat = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                shape=(fine.size, n))
        return fine, mat

    def pattern(self, az: NDArray[np.float64], beam: NDArray[np.int64]) -> NDArray[np.float64]:
        """Two-way power pattern (peak 1) of ``beam`` towards ``az``."""
        return np.exp(-_FOUR_LN2 * ((az - self.azimuth[beam]) / self.width[beam]) ** 2)

    def parts(self, az: NDArray[np.float64], cell: NDArray[np.int64]
              ) -> list[tuple[NDArray[np.int64], NDArray[np.float64]]]:
        """Per beam offset from each direction's cell: (beam, ``k`` x pattern), cut below 1e-4."""
        n = self.azimuth.size
        out = []
        for d in range(-self.reach, self.reach + 1):
            beam = cell + d
            ok = (beam >= 0) & (beam < n)
            cb = np.clip(beam, 0, n - 1)
            x = (az - self.azimuth[cb]) / self.width[cb]
            val = np.where(ok & (x * x < 4.0 * math.log(10.0) / _FOUR_LN2),
                           self.gain[cb] * np.exp(-_FOUR_LN2 * x * x), 0.0)
            if (val > 0).any():
                out.append((beam, val))
        return out


def main_lobe_taps(geometry: SonarGeometry, config: SimulationConfig) -> NDArray[np.float64] | None:
    """The main lobe on the beam grid, length ``n_beams`` centred at ``n_beams // 2``, unit sum.

    Tap ``d`` is ``exp(-4 ln2 (d dtheta / W)^2)`` with ``W`` the mean beam width
    (:func:`beam_widths_for`, or ``config.beam_width_rad``) and ``dtheta`` the mean spacing: what a
    direction at a beam's centre gives its neighbours.  Taps below 1e-4 of the centre are dropped;
    ``None`` when the width is 0, there is one beam, or no neighbour reaches 1e-4.
    """
    config = config.resolved(geometry)
    n = geometry.n_beams
    az = np.asarray(geometry.azimuth_rad, dtype=np.float64)
    spacing = float(np.diff(az).mean()) if n > 1 else 0.0
    width = float(_beam_widths(geometry, config).mean()) if n else 0.0
    if n < 2 or width <= 0 or spacing <= 0:
        return None
    c = n // 2
    d = np.arange(n) - c
    taps = np.exp(-_FOUR_LN2 * (d * spacing / width) ** 2)
    taps[taps < 1e-4] = 0.0
    if np.count_nonzero(taps) < 2:
        return None
    return taps / taps.sum()


def _centred_convolve(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Convolution of two centred length-n patterns, centred and cut to length n."""
    n = a.size
    return np.convolve(a, b)[n // 2: n // 2 + n]


def ghost_psf(geometry: SonarGeometry, config: SimulationConfig) -> NDArray[np.float64] | None:
    """The ghost taps on the beam grid (``beam_pattern``), unit sum, centred at ``n // 2``.

    ``"geometry"``: the sonar's stated ``geometry.psf`` (the object itself); ``"measured"``:
    :data:`MEASURED_DIDSON_GHOSTS` on that pattern's tap grid.  ``None`` for a geometry without one.
    """
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


def render_psf(geometry: SonarGeometry, config: SimulationConfig) -> NDArray[np.float64] | None:
    """The across-beam pattern of :func:`simulate_ping` on the beam grid, unit sum, centred at ``n // 2``.

    The ghost taps (:func:`ghost_psf`) convolved with the main lobe (:func:`main_lobe_taps`): the
    image of a direction at a beam's centre.  The renderer applies the main lobe at sub-beam
    resolution (a direction between two beams reaches both at half power) and then the ghost
    taps; this is the pattern it amounts to on the grid.  Without a main lobe
    (``beam_width_rad=0``) this is :func:`ghost_psf`; ``None`` when there is neither.
    """
    config = config.resolved(geometry)
    psf = ghost_psf(geometry, config)
    main = main_lobe_taps(geometry, config)
    if main is None:
        return psf
    if psf is None:
        return main
    out = _centred_convolve(np.asarray(psf, dtype=np.float64), main)
    return out / out.sum()


def _one_look(
    rng: np.random.Generator,
    shape: tuple[int, int],
    config: SimulationConfig,
    field: _CoherentField | None,
    taper: NDArray[np.float64],
    m_bg: NDArray[np.float64],
    m_scatter: NDArray[np.float64],
    noise: float,
) -> NDArray[np.float64]:
    """One speckle realisation of the received intensity (full-scale units).

    Speckle (Rayleigh amplitude) and additive receiver noise, in the complex amplitude domain;
    ``field`` (the echo sources and patterns) is given for coherent ghosts.
    """
    z = rng.standard_normal((4,) + shape)
    z *= math.sqrt(0.5)
    if field is not None:
        zs = rng.standard_normal((4,) + shape)
        zs *= math.sqrt(0.5)
        field_re = field.realise(zs[0], zs[2])
        field_im = field.realise(zs[1], zs[3])
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


@dataclasses.dataclass(frozen=True)
class _CoherentField:
    """Complex echo field of one ping's sources, for coherent ghosts and main-lobe overlap.

    The sources are the azimuth cells (``a`` = amplitude of each cell's echo); beam ``j``
    receives ``sum_k sqrt(taps[j - k]) a_k z_k`` through the main lobe on the beam grid
    (neighbouring beams share their sources' speckle), scaled per pixel to the sub-beam expected
    intensity (``scale``; pixels no cell source reaches get an independent field of amplitude
    ``orphan``), then every beam's field goes through the ghost taps ``ghosts`` in amplitude (a
    ghost is a scaled copy of its source beam's echo, speckle included).  The expected intensity
    is the ghost pattern applied to the sub-beam echo.
    """

    a: NDArray[np.float64]
    taps: NDArray[np.float64] | None
    scale: NDArray[np.float64]
    orphan: NDArray[np.float64]
    ghosts: NDArray[np.float64] | None

    def realise(self, z: NDArray[np.float64], z_orphan: NDArray[np.float64]) -> NDArray[np.float64]:
        """One real component of the field, given unit-variance normals per source."""
        f = _beam_pattern(self.a * z, self.taps, amplitude=True) * self.scale + self.orphan * z_orphan
        return _beam_pattern(f, self.ghosts, amplitude=True)


def _validate(scene: Any, geometry: Any, config: Any) -> None:
    if not isinstance(scene, Scene):
        raise InputError(f"scene: expected a Scene, got {type(scene).__name__}")
    if not isinstance(geometry, SonarGeometry):
        raise InputError(f"geometry: expected a SonarGeometry, got {type(geometry).__name__}")
    if not isinstance(config, SimulationConfig):
        raise InputError(f"config: expected a SimulationConfig, got {type(config).__name__}")


def _receive(intensity: NDArray[np.float64], config: SimulationConfig) -> NDArray[np.float32]:
    """The receiver: linear with threshold, or log over ``dynamic_range_db``; then 8-bit
    quantisation to the float32 values the PNG reader produces (``k * float32(1/255)``, so round
    trips are exact)."""
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
    return q.astype(np.float32) * np.float32(1.0 / 255.0)


def _class_truth(s_int: NDArray[np.float64], c_int: NDArray[np.float64], m_bg: Any, config: SimulationConfig
                 ) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
    """The class mask from the unblurred structure and clutter intensities (a class where it is
    ``truth_snr_db`` over the background mean; the larger wins), and per beam the highest
    structure-to-background ratio (dB) of a pixel where clutter does not outshine structure."""
    floor_ = m_bg * 10.0 ** (config.truth_snr_db / 10.0)
    is_s = s_int >= floor_
    is_c = c_int >= floor_
    mask = np.zeros(s_int.shape, np.uint8)
    mask[is_s] = STRUCTURE
    mask[is_c & (~is_s | (c_int > s_int))] = CLUTTER
    # a pixel is structure at threshold t iff s_int >= floor_t and clutter does not exceed it
    with np.errstate(divide="ignore", invalid="ignore"):
        peak_db = 10.0 * np.log10(np.where(s_int >= c_int, s_int / m_bg, 0.0).max(axis=0))
    return mask, peak_db


@dataclasses.dataclass(frozen=True, eq=False)
class _MeanEcho:
    """The expected received intensities of one ping (full-scale units), before speckle.

    Attributes
    ----------
    lobe : _MainLobe or None
        The main lobe the echoes were received through.
    pulse_length_m : float
        Transmit pulse length rendered.
    cells : ndarray (n_bins, n_beams)
        Echo energy of every azimuth cell (each sample in its own cell, no main lobe).
    gain_r : ndarray (n_bins, 1)
        Channel gain per range bin.
    taper : ndarray (1, n_beams)
        Per-beam gain.
    m_echo : ndarray (n_bins, n_beams)
        Mean echo intensity: ghost taps, taper and channel applied.
    m_bg : ndarray
        Mean background (volume reverberation and noise).
    noise : float
        Receiver noise power.
    m_scatter : ndarray (n_bins, n_beams)
        Mean intensity of the speckled part (echo and reverberation).
    field : _CoherentField or None
        The complex echo field for coherent ghosts and main-lobe overlap.
    """

    lobe: _MainLobe | None
    pulse_length_m: float
    cells: NDArray[np.float64]
    gain_r: NDArray[np.float64]
    taper: NDArray[np.float64]
    m_echo: NDArray[np.float64]
    m_bg: NDArray[np.float64]
    noise: float
    m_scatter: NDArray[np.float64]
    field: _CoherentField | None


def _coherent_field(total: NDArray[np.float64], cells: NDArray[np.float64], gain_r: NDArray[np.float64],
                    taps: NDArray[np.float64] | None, ghosts: NDArray[np.float64] | None) -> _CoherentField:
    """The field of the azimuth-cell sources ``cells`` scaled per pixel to the sub-beam expected
    intensity ``total``; pixels no source reaches get an independent (orphan) field."""
    e_tap = _beam_pattern(cells, taps)
    sub = total * gain_r
    with np.errstate(divide="ignore", invalid="ignore"):
        reached = e_tap > 1e-12 * max(float(e_tap.max()), 1e-300)
        scale = np.where(reached, np.sqrt(total / np.where(reached, e_tap, 1.0)), 0.0)
    return _CoherentField(a=np.sqrt(cells * gain_r), taps=taps, scale=scale,
                          orphan=np.sqrt(np.where(reached, 0.0, sub)), ghosts=ghosts)


def _mean_echo(smp: _Samples, geometry: SonarGeometry, config: SimulationConfig) -> _MeanEcho:
    """Render the samples' echoes through pulse, main lobe, ghost taps, taper and channel, and
    the background they are received over."""
    length, rise = config.pulse
    lobe = _MainLobe.of(geometry, config)
    # the image: every sample's echo spread over the bins its patch and pulse envelope overlap,
    # received by every beam through its main lobe; and in its own azimuth cell
    total, cells = _render_energy(smp, geometry, length, rise, lobe)
    gain_r = channel_gain(geometry, config)[:, None]
    taper = _taper(geometry)[None, :]
    ghosts = ghost_psf(geometry, config)
    taps = main_lobe_taps(geometry, config) if lobe is not None else None
    m_echo = _beam_pattern(total, ghosts) * taper * gain_r
    m_bg = _background_mean(geometry, config)
    noise = _noise_power(geometry, config)
    m_scatter = m_echo + (m_bg - noise)
    field = None
    if config.speckle and config.ghosts == "coherent" and (ghosts is not None or taps is not None):
        field = _coherent_field(total, cells, gain_r, taps, ghosts)
    return _MeanEcho(lobe=lobe, pulse_length_m=length, cells=cells, gain_r=gain_r, taper=taper, m_echo=m_echo,
                     m_bg=m_bg, noise=noise, m_scatter=m_scatter, field=field)


def _speckled_intensity(rng: np.random.Generator, shape: tuple[int, int], config: SimulationConfig,
                        echo: _MeanEcho) -> NDArray[np.float64]:
    """The received intensity: :func:`_one_look` averaged over ``config.looks`` looks."""
    look_args = (rng, shape, config, echo.field, echo.taper, echo.m_bg, echo.m_scatter, echo.noise)
    intensity = _one_look(*look_args)
    if config.looks > 1:
        for _ in range(config.looks - 1):
            intensity += _one_look(*look_args)
        intensity /= config.looks
    return intensity


@dataclasses.dataclass(frozen=True, eq=False)
class _PingTruth:
    """The truth of one ping (see the fields of :class:`SimResult` of the same names)."""

    class_mask: NDArray[np.uint8]
    first_return_bin: NDArray[np.int64]
    first_return_range_m: NDArray[np.float64]
    unblurred: NDArray[np.float32]
    structure_peak_snr_db: NDArray[np.float64]
    surface_range_m: NDArray[np.float64]
    surface_ranges_m: NDArray[np.float64]


def _ping_truth(smp: _Samples, geometry: SonarGeometry, config: SimulationConfig, echo: _MeanEcho,
                e_struct: NDArray[np.float64], e_clutter: NDArray[np.float64],
                surfaces: dict[Any, Any] | None = None) -> _PingTruth:
    """Class mask, first returns and surfaces from the unblurred structure and clutter energies
    (every sample in its nearest bin) through the same taper and channel as the echoes.
    ``surfaces``: the surface truths of other pings of the same samples and echo, by
    configuration and beams with structure (the same inputs give the same truth; filled here)."""
    scale = echo.taper * echo.gain_r
    mask, peak_db = _class_truth(e_struct * scale, e_clutter * scale, echo.m_bg, config)
    struct = mask == STRUCTURE
    has = struct.any(axis=0)
    first = np.where(has, struct.argmax(axis=0), -1).astype(np.int64)
    first_r = np.where(has, geometry.range_m[np.maximum(first, 0)], np.nan)
    key = (config, has.tobytes())
    if surfaces is not None and key in surfaces:
        surf, surfs = surfaces[key]
    else:
        surf, surfs = _surface_truth(smp, geometry, config, has,
                                     gap_m=echo.pulse_length_m + 2.0 * geometry.range_resolution_m, lobe=echo.lobe)
        if surfaces is not None:
            surfaces[key] = (surf, surfs)
    return _PingTruth(class_mask=mask, first_return_bin=first, first_return_range_m=first_r,
                      unblurred=np.clip(echo.cells * scale, 0.0, 1.0).astype(np.float32),
                      structure_peak_snr_db=peak_db.astype(np.float64), surface_range_m=surf,
                      surface_ranges_m=surfs)


def _ping_meta(scene: Scene, geometry: SonarGeometry, config: SimulationConfig, assist_db: float,
               pulse_length_m: float, *, recording_meta: bool) -> dict[str, Any]:
    """``ping.meta`` of a simulated ping: the scene, any gain assist and, with ``recording_meta``,
    what a recording's header would declare."""
    meta: dict[str, Any] = {"simulated": scene.name or "scene"}
    if assist_db > 0:
        meta["gain_assist_db"] = assist_db
    if recording_meta:
        meta["pulse_width_us"] = 2e6 * pulse_length_m / geometry.sound_speed_m_s
        meta["sound_speed_m_s"] = geometry.sound_speed_m_s
        if config.receiver == "log":
            meta["log_dynamic_range_db"] = config.dynamic_range_db
    return meta


def _sim_result(ping: Ping, scene: Scene, seed: int | np.random.Generator, config: SimulationConfig,
                echo: _MeanEcho, truth: _PingTruth) -> SimResult:
    """The :class:`SimResult` of a rendered ping, its truth and the configuration rendered."""
    int_seed = int(seed) if isinstance(seed, int | np.integer) else None
    return SimResult(
        ping=ping,
        clean=np.clip(echo.m_echo, 0.0, 1.0).astype(np.float32),
        class_mask=truth.class_mask,
        first_return_bin=truth.first_return_bin,
        first_return_range_m=truth.first_return_range_m,
        config=config,
        scene_name=scene.name,
        seed=int_seed,
        unblurred=truth.unblurred,
        structure_peak_snr_db=truth.structure_peak_snr_db,
        surface_range_m=truth.surface_range_m,
        surface_ranges_m=truth.surface_ranges_m,
    )


def simulate_ping(
    scene: Scene, geometry: SonarGeometry, *, config: SimulationConfig = SimulationConfig(),
    seed: int | np.random.Generator, time_ns: int = 0, recording_meta: bool = False,
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
    recording_meta : bool
        Also declare in ``ping.meta`` what a recording's header would: ``pulse_width_us``
        (``2 L / c``), ``sound_speed_m_s`` and, for a log receiver, ``log_dynamic_range_db`` (as
        the ARIS reader does), so a pipeline reads the simulated ping as it reads a real one.
        Default off: only ``meta["simulated"]``.

    Returns
    -------
    SimResult
        Its ``config`` is the resolved configuration actually rendered.

    Notes
    -----
    Each sample at range ``|p|``, azimuth ``atan2(y, x)`` and elevation ``atan2(z, hypot(x, y))``
    (samples outside the fan are dropped) echoes its target strength times the vertical pattern;
    its echo - the patch's range extent through the causal transmit pulse - is integrated over
    the bins it overlaps, and every beam receives it through its Gaussian main lobe at sub-beam
    resolution (``pulse_length_m``, ``beam_width_rad``).  Then: ghost taps across beams (linear
    convolution, eq. 2 of Teixeira et al. 2018), taper ``k(theta)`` (eq. 5),
    channel ``SL + G - FS - (20 beta log10 r + 2 alpha r)`` (eqs. 6-7), Rayleigh speckle averaged
    over ``looks``, receiver noise, receiver mapping (linear with threshold, or log) and 8-bit
    quantisation.  The truth (class mask, first return) puts every sample in its nearest bin and
    azimuth cell; ``surface_range_m`` is the sub-bin physical surface (see :class:`SimResult`).

    Examples
    --------
    >>> from sonarmap import preset
    >>> from sonarmap.simulate import scene_from_name
    >>> g = preset("aris3000-128")
    >>> res = simulate_ping(scene_from_name("hull", geometry=g), g, seed=0)
    >>> res.config.receiver, bool(res.ping.image.min() > 0)
    ('log', True)
    """
    return simulate_pings(scene, geometry, config=config, seeds=[seed], time_ns=time_ns,
                          recording_meta=recording_meta)[0]


def simulate_pings(
    scene: Scene, geometry: SonarGeometry, *, config: SimulationConfig = SimulationConfig(),
    seeds: Iterable[int | np.random.Generator], time_ns: int | Iterable[int] = 0, recording_meta: bool = False,
) -> list[SimResult]:
    """:func:`simulate_ping` of one scene for each of ``seeds``, in order: the same bytes per seed,
    the scene's echo rendered once.  ``time_ns``: one time stamp for every ping, or one per seed.

    The expected echo (samples, pulse, main lobe, ghosts, channel) and the surface truth do not
    depend on the seed, only the speckle, the noise and what follows from them (a gain assist, the
    receiver, the class truth); an Oculus-like hull renders in ~1.4 s, of which ~0.9 s is the
    expected echo.  ``python -m sonarmap.evaluate`` renders every scene this way.

    Examples
    --------
    >>> from sonarmap import preset
    >>> from sonarmap.simulate import scene_from_name
    >>> g = preset("didson-hf")
    >>> scene = scene_from_name("hull", geometry=g)
    >>> a, b = simulate_pings(scene, g, seeds=[0, 1])
    >>> bool((a.ping.image == simulate_ping(scene, g, seed=0).ping.image).all())
    True
    """
    _validate(scene, geometry, config)
    config = config.resolved(geometry)
    seeds, times = _seeds_and_times(seeds, time_ns)
    if not seeds:
        return []
    smp = _samples(scene, geometry, config)
    # truth: every sample in its nearest bin (no pulse, no beam pattern)
    e_struct, e_clutter = _accumulate(smp, geometry)
    echo = _mean_echo(smp, geometry, config)
    surfaces: dict[Any, Any] = {}
    return [_rendered_ping(scene, geometry, config, seed, (smp, e_struct, e_clutter, echo, surfaces), t,
                           recording_meta) for seed, t in zip(seeds, times, strict=True)]


#: Seeds :func:`iter_simulated_pings` renders per expected echo by default (at most this many
#: whole pings held at a time).
SEEDS_PER_RENDER = 16


def iter_simulated_pings(
    scene: Scene, geometry: SonarGeometry, *, config: SimulationConfig = SimulationConfig(),
    seeds: Iterable[int | np.random.Generator], time_ns: int | Iterable[int] = 0, recording_meta: bool = False,
    batch: int = SEEDS_PER_RENDER,
) -> Iterator[SimResult]:
    """:func:`simulate_pings` of ``seeds`` in batches of ``batch``, yielded one ping at a time: the
    same pings, the scene's echo rendered once per batch, at most ``batch`` whole pings held (a
    long run of seeds does not fill the memory).  The arguments are checked on the call."""
    _validate(scene, geometry, config)
    seeds, times = _seeds_and_times(seeds, time_ns)
    if isinstance(batch, bool) or not isinstance(batch, int | np.integer) or batch < 1:
        raise InputError(f"batch: expected an integer >= 1, got {batch!r}")
    return (res for k in range(0, len(seeds), batch)
            for res in simulate_pings(scene, geometry, config=config, seeds=seeds[k:k + batch],
                                      time_ns=times[k:k + batch], recording_meta=recording_meta))


def _seeds_and_times(seeds: Any, time_ns: Any) -> tuple[list[Any], list[int]]:
    """``seeds`` as a list (each an int or a numpy Generator) and a time stamp per seed (``time_ns``:
    one for all or one per seed); an :class:`InputError` naming the argument otherwise."""
    if isinstance(seeds, int | np.integer | np.random.Generator) or not isinstance(seeds, Iterable):
        raise InputError(f"seeds: expected an iterable of ints or numpy Generators, got {type(seeds).__name__}")
    if not isinstance(time_ns, int | np.integer | Iterable):
        raise InputError(f"time_ns: expected an int or one per seed, got {type(time_ns).__name__}")
    seeds = list(seeds)
    for seed in seeds:
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer | np.random.Generator):
            raise InputError(f"seed: expected an int or numpy Generator, got {type(seed).__name__}")
    times = [int(time_ns)] * len(seeds) if isinstance(time_ns, int | np.integer) else [int(t) for t in time_ns]
    if len(times) != len(seeds):
        raise InputError(f"time_ns: {len(times)} time stamps for {len(seeds)} seeds")
    return seeds, times


def _rendered_ping(scene: Scene, geometry: SonarGeometry, config: SimulationConfig, seed: int | np.random.Generator,
                   rendered: tuple[_Samples, NDArray[np.float64], NDArray[np.float64], _MeanEcho, dict[Any, Any]],
                   time_ns: int, recording_meta: bool) -> SimResult:
    """One seed's ping of :func:`simulate_pings` from the scene's rendered samples, truth energies,
    expected echo and the surface truths found so far."""
    smp, e_struct, e_clutter, echo, surfaces = rendered
    rng = np.random.default_rng(seed)
    intensity = _speckled_intensity(rng, geometry.shape, config, echo)
    assist_db = _gain_assist_db(intensity, config)
    if assist_db > 0:
        intensity *= 10.0 ** (-assist_db / 10.0)
        config = config.replace(rx_gain_db=_rx_gain(geometry, config) - assist_db)
    image = _receive(intensity, config)
    # Truth from the unblurred scene.
    truth = _ping_truth(smp, geometry, config, echo, e_struct, e_clutter, surfaces)
    meta = _ping_meta(scene, geometry, config, assist_db, echo.pulse_length_m, recording_meta=recording_meta)
    ping = Ping(image=image, geometry=geometry, time_ns=time_ns, source="", meta=meta)
    return _sim_result(ping, scene, seed, config, echo, truth)


# ---------------------------------------------------------------------- measuring leading edges


def first_peak_crossing(profile: ArrayLike, fraction: float = 0.5, *, min_peak: float = 0.5) -> float:
    """Fractional index where ``profile`` first crosses ``fraction`` x its first peak.

    The first peak is the first local maximum among the samples reaching ``min_peak`` x the
    profile's maximum (so ripple and faint echoes in front do not count); the crossing is the last
    upward crossing of ``fraction x peak`` before it, interpolated linearly between the two
    samples around it - the leading edge of ``docs/DESIGN`` "Range convention".  NaN when the
    profile has no positive sample or is already above the level at its start.

    Examples
    --------
    >>> first_peak_crossing([0.0, 0.0, 0.2, 0.6, 1.0, 0.7, 0.9])
    2.75
    """
    y = np.asarray(profile, dtype=np.float64)
    if y.size == 0 or not np.isfinite(y).any() or not np.nanmax(y) > 0:
        return math.nan
    y = np.nan_to_num(y, nan=-np.inf)
    k = int(np.argmax(y >= min_peak * y.max()))
    while k + 1 < y.size and y[k + 1] >= y[k]:
        k += 1
    level = fraction * y[k]
    below = np.flatnonzero(y[: k + 1] < level)
    if below.size == 0:
        return math.nan
    i = int(below[-1])
    return float(i + (level - y[i]) / (y[i + 1] - y[i]))


def leading_edges_m(
    image: ArrayLike, geometry: SonarGeometry, *, fraction: float = 0.5, min_peak: float = 0.5,
    background: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Per beam, the range (m) of :func:`first_peak_crossing` of an image column.

    For a noise-free render (``SimResult.clean``; render with a high ``full_scale_db`` so nothing
    clips) this is what an ideal leading-edge detector reports; compare with
    ``SimResult.surface_range_m``.  ``background`` (per bin, per beam or scalar) is subtracted
    first.  NaN where a column has no echo.
    """
    img = np.asarray(image, dtype=np.float64)
    if background is not None:
        img = img - np.asarray(background, dtype=np.float64)
    idx = np.array([first_peak_crossing(img[:, j], fraction, min_peak=min_peak) for j in range(img.shape[1])])
    return np.interp(idx, np.arange(geometry.n_bins), geometry.range_m, left=np.nan, right=np.nan)


@dataclasses.dataclass(frozen=True)
class EdgeRise:
    """Leading edge of the surface echoes in a range window, averaged over beams and pings.

    Attributes
    ----------
    rise_bins : float
        10-90 % rise (bins) of ``profile`` before its first peak (:func:`first_peak_crossing`).
    n_profiles : int
        Beam profiles averaged.
    offsets_bins : ndarray
        Offsets (bins) of ``profile`` from each beam's 50 % crossing.
    profile : ndarray
        Mean background-subtracted linear intensity at those offsets.
    """

    rise_bins: float
    n_profiles: int
    offsets_bins: NDArray[np.float64]
    profile: NDArray[np.float64]


def _linear_intensity(image: NDArray[np.float64], config: SimulationConfig | None) -> NDArray[np.float64]:
    """Undo a log receiver mapping (intensity in full-scale units); linear images unchanged."""
    if config is None or config.receiver != "log":
        return image
    return 10.0 ** ((image + config.threshold - 1.0) * config.dynamic_range_db / 10.0)


def _smooth_edge_positions(pos: NDArray[np.float64], align: str, degree: int, max_jump: float) -> dict[int, float]:
    """Beam -> smoothed edge position (beams with an edge, outliers beyond ``max_jump`` dropped).

    ``"median"``: the running median over 5 edge beams.  ``"poly"``: a robust polynomial in beam
    index per run of edge beams (runs split where more than 3 beams lack an edge; runs of fewer
    than ``2 degree + 3`` beams dropped; outliers rejected and the fit repeated, 3 times).
    """
    idx = np.flatnonzero(np.isfinite(pos))
    out: dict[int, float] = {}
    if idx.size == 0:
        return out
    if align == "median":
        v = pos[idx]
        med = np.array([np.median(v[max(0, k - 2): k + 3]) for k in range(v.size)])
        return {int(j): float(mv) for j, p, mv in zip(idx, v, med, strict=True) if abs(p - mv) <= max_jump}
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 4) + 1)
    for run in runs:
        keep = run
        for _ in range(3):
            if keep.size < 2 * degree + 3:
                keep = keep[:0]
                break
            coef = np.polyfit(keep - run[0], pos[keep], degree)
            fit = np.polyval(coef, run - run[0])
            ok = np.abs(pos[run] - fit) <= max_jump
            if np.array_equal(run[ok], keep):
                break
            keep = run[ok]
        if keep.size:
            coef = np.polyfit(keep - run[0], pos[keep], degree)
            for j in keep:
                out[int(j)] = float(np.polyval(coef, j - run[0]))
    return out


class _ColumnEdges(NamedTuple):
    """Per beam of one image, the background level in front of the window and the edge position."""

    background: NDArray[np.float64]
    #: Fractional bin of each beam's 50 % crossing (NaN without an edge).
    position: NDArray[np.float64]


def _column_edges(img: NDArray[np.float64], smoothed: NDArray[np.float64], lo: int, hi: int, *,
                  background_bins: int, min_snr: float) -> _ColumnEdges:
    """Background (median of the ``background_bins`` rows before row ``lo``) and, in rows
    ``lo:hi`` of the 3 x 3 ``smoothed`` image, the 50 % crossing of every beam's first peak
    that clears the background by ``min_snr`` robust standard deviations."""
    _, m = img.shape
    b0 = max(0, lo - background_bins)
    bg = np.median(img[b0:lo], axis=0) if lo > b0 else np.zeros(m)
    sm = smoothed
    if lo > b0:
        spread = 1.4826 * np.median(np.abs(sm[b0:lo] - np.median(sm[b0:lo], axis=0)), axis=0)
    else:
        spread = np.zeros(m)
    pos = np.full(m, np.nan)
    for j in range(m):
        y = sm[lo:hi, j] - bg[j]
        if y.size < 3 or y.max() <= min_snr * max(spread[j], 1e-6):
            continue
        c = first_peak_crossing(y)
        pos[j] = lo + c
    return _ColumnEdges(bg, pos)


def _edge_profiles(img: NDArray[np.float64], background: NDArray[np.float64], positions: dict[int, float],
                   offs: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """The intensity of every beam of ``positions`` (beam -> edge position) at the offsets ``offs``
    from its edge, less the beam's ``background`` (beams whose offsets leave the image skipped)."""
    n = img.shape[0]
    out = []
    for j, mv in positions.items():
        x = mv + offs
        if x[0] < 0 or x[-1] > n - 1:
            continue
        out.append(np.interp(x, np.arange(n), img[:, j]) - background[j])
    return out


def measure_edge_rise(
    images: Any, geometry: SonarGeometry, *, min_range_m: float, max_range_m: float,
    config: SimulationConfig | None = None, half_bins: int = 25, background_bins: int = 40, min_snr: float = 4.0,
    max_jump_bins: float = 3.0, floor_bins: int = 0, align: Literal["median", "poly"] = "median",
    poly_degree: int = 3,
) -> EdgeRise:
    """10-90 % rise (bins) of the first surface echo in a range window: real and simulated alike.

    Single pings are speckled (a single-look edge is a few random samples), so the edge is
    averaged: per beam, the window's column (background - the median of the ``background_bins``
    rows in front of the window - subtracted) smoothed 3 x 3 locates the 50 % crossing of its
    first peak; a running median over 5 edge beams (``align="median"``) or a robust polynomial in
    beam index (``"poly"``) smooths those positions (the alignment error, not the pulse,
    otherwise dominates a single-look edge), beams more than ``max_jump_bins`` off it are
    dropped, and the *unsmoothed* linear intensity is sampled at
    ``position + offset`` (linear interpolation) and averaged over beams and pings.  The rise of
    that mean edge is :func:`first_peak_crossing` at 0.9 minus at 0.1, measured above the
    background (``floor_bins=0``) or above the mean edge's lowest level over offsets
    ``-floor_bins .. 0`` (for a pedestal: a water column brightening towards a seabed; a halo
    rising over the last few bins stays part of the edge).

    Parameters
    ----------
    images : iterable of ndarray or Ping
        Pings of ``geometry`` (pixel values in [0, 1]).
    geometry : SonarGeometry
    min_range_m, max_range_m : float
        Window holding the surface; the rows just in front of it must be background.
    config : SimulationConfig, optional
        Receiver to undo (a ``"log"`` receiver is linearised); resolve it for the geometry.
    half_bins : int
        Profile offsets ``-half_bins .. half_bins``.
    background_bins : int
        Rows in front of the window used as background.
    min_snr : float
        A beam counts when its smoothed peak exceeds the background by this many robust standard
        deviations of the (smoothed) background rows.
    max_jump_bins : float
        Outlier rejection against the polynomial fit of the edge positions.
    floor_bins : int
        0: the rise is measured above the background; else above the mean edge's minimum over
        offsets ``-floor_bins .. 0``.
    align : {"median", "poly"}
        How the edge positions are smoothed across beams.
    poly_degree : int
        Degree of the ``"poly"`` fit.

    Returns
    -------
    EdgeRise

    Raises
    ------
    InputError
        If no beam holds an edge.
    """
    from scipy.ndimage import uniform_filter

    lo = int(np.searchsorted(geometry.range_m, min_range_m))
    hi = int(np.searchsorted(geometry.range_m, max_range_m))
    offs = np.arange(-half_bins, half_bins + 1, dtype=np.float64)
    acc: list[NDArray[np.float64]] = []
    for item in images:
        img = _linear_intensity(np.asarray(getattr(item, "image", item), dtype=np.float64), config)
        edges = _column_edges(img, uniform_filter(img, size=3, mode="nearest"), lo, hi,
                              background_bins=background_bins, min_snr=min_snr)
        kept = _smooth_edge_positions(edges.position, align, poly_degree, max_jump_bins)
        acc += _edge_profiles(img, edges.background, kept, offs)
    if not acc:
        raise InputError("images: no beam holds a leading edge in the window")
    prof = np.mean(acc, axis=0)
    y = prof - prof[(offs >= -floor_bins) & (offs <= 0)].min() if floor_bins > 0 else prof
    rise = first_peak_crossing(y, 0.9) - first_peak_crossing(y, 0.1)
    return EdgeRise(rise_bins=float(rise), n_profiles=len(acc), offsets_bins=offs, profile=prof)


# ---------------------------------------------------------------------- files


@dataclasses.dataclass(frozen=True)
class SimulationFiles:
    """Paths written by :func:`write_simulation`."""

    image: Path
    sidecar: Path
    truth_mask: Path
    truth_json: Path


def _json_ranges(values: NDArray[np.float64] | None) -> list[float | None] | None:
    """Ranges as a JSON list (null where NaN); ``None`` when absent."""
    if values is None:
        return None
    return [None if not math.isfinite(v) else float(v) for v in np.asarray(values, dtype=np.float64)]


def write_simulation(result: SimResult, directory: str | os.PathLike[str], stem: str | None = None) -> SimulationFiles:
    """Write ``<stem>_raw.png`` + ``<stem>.json`` (the real data's format) and the truth files.

    ``<stem>_truth.png`` is the class mask as raw 8-bit values (0 background, 1 structure,
    2 clutter); ``<stem>_truth.json`` holds ``first_return_bin``, ``first_return_range_m`` (null
    where none), the sub-bin ``surface_range_m`` (null where none) and ``surface_ranges_m`` (one
    list per further surface), ``scene``, ``seed``, ``time_ns`` and ``config``.  All files are written atomically.
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
        "surface_range_m": _json_ranges(result.surface_range_m),
        "surface_ranges_m": [_json_ranges(row) for row in
                             (result.surface_ranges_m if result.surface_ranges_m is not None else ())],
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
