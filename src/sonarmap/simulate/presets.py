"""Sonar profiles: per-sonar rendering defaults of the simulator (gain, loss, floor, receiver).

Every sonar renders through the same sonar equation (:mod:`sonarmap.simulate.render`); what differs
is data: the receiver gain, the net loss left after the sonar's time-varied gain, the reverberation
and noise floor, the receiver mapping (linear with a threshold, or log-compressed), the number of
independent looks averaged per sample, the transmit pulse length, the beams' main-lobe width and
near-field ring-down.
A :class:`SonarProfile` holds those values; :func:`profile_for` picks one from a geometry's name.
The values were fitted to the real recordings in ``../shared/data`` (see ``docs/simulator.md``).

A :class:`~sonarmap.simulate.SimulationConfig` field the caller sets explicitly always wins over
the profile; only the fields left at their defaults take the profile's values.

>>> from sonarmap import preset
>>> profile_for(preset("aris3000-128")).name, profile_for(preset("didson-hf")).name
('aris', 'didson')
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

__all__ = ["SonarProfile", "SONAR_PROFILES", "profile_for"]


@dataclasses.dataclass(frozen=True)
class SonarProfile:
    """Rendering defaults of one family of sonars.

    Parameters
    ----------
    name : str
        Profile name (``"didson"``, ``"aris"``, ``"oculus"``).
    prefixes : tuple of str
        A geometry whose lower-cased name starts with one of these uses the profile.
    values : mapping
        :class:`~sonarmap.simulate.SimulationConfig` field values that replace the defaults.
    calibrated_on : str
        The recording the values were fitted to.
    """

    name: str
    prefixes: tuple[str, ...]
    values: Mapping[str, Any]
    calibrated_on: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "values", MappingProxyType(dict(self.values)))


#: DIDSON (and any sonar no other profile claims): the ``SimulationConfig`` defaults themselves,
#: fitted to the 116 real DIDSON background pings (linear receiver with a threshold: ~62 % zeros).
DIDSON = SonarProfile(
    name="didson",
    prefixes=("didson",),
    values={},
    calibrated_on="didson/background (116 pings, receiver gain 20 dB)",
)

#: ARIS: log-compressed samples (a constant ~0.05 spread at every level), about 6 independent looks
#: per sample, no threshold (no zero pixels), background falling ~3x over a 3-23 m window,
#: rendered at the recording's 24 dB receiver gain (the ARIS presets carry a 0 dB placeholder).
#: Pulse: the recording's 12 us transmit pulse (frame header ``PulseWidth``), ``c tau / 2 = 9 mm``;
#: main lobe from the vendor's beam-width tables (``beam_width_rad=None``).
ARIS = SonarProfile(
    name="aris",
    prefixes=("aris",),
    values={
        "rx_gain_db": 24.0,
        "receiver": "log",
        "dynamic_range_db": 37.0,
        "looks": 6,
        "threshold": 0.0,
        "full_scale_db": 165.35,
        "reverb_db": -70.0,
        "spreading_beta": 0.117,
        "alpha_db_per_m": 0.42,
        "noise_level_db": 111.35,
        "pulse_length_m": 0.009,
    },
    calibrated_on="aris/sample.aris (ARIS 1200 telephoto, 6 frames, receiver gain 24 dB)",
)

#: Oculus: linear samples averaged over ~10 looks (relative spread ~0.3 at every level), no
#: threshold, a dark water column (~0.03) with bright ring-down in the first centimetres.
#: Pulse 6 mm (~2 bins: the real speckle's correlation along range, 0.16 at lag 1 after removing
#: the local level, implies ~2 bins); main lobe 0.55 deg (~2.3 beam spacings: the real seabed's
#: beam-to-beam correlation 0.60 is reproduced, 0.15 with a one-spacing lobe).
OCULUS = SonarProfile(
    name="oculus",
    prefixes=("oculus",),
    values={
        "rx_gain_db": 0.0,
        "receiver": "linear",
        "looks": 10,
        "threshold": 0.0,
        "full_scale_db": 125.7,
        "reverb_db": -87.25,
        "spreading_beta": -0.1,
        "alpha_db_per_m": 0.0,
        "noise_level_db": 95.7,
        "elevation_aperture_rad": math.radians(12.0),
        "pulse_length_m": 0.006,
        "beam_width_rad": math.radians(0.55),
        "ring_down_level": 0.14,
        "ring_down_m": 0.007,
        "gain_assist_saturation": 0.01,
    },
    calibrated_on="oculus/three_pings_8bit.raw (Oculus M750d-like, 3 pings, 2 m range)",
)

#: The profiles by name; :func:`profile_for` tries them in this order.
SONAR_PROFILES: Mapping[str, SonarProfile] = MappingProxyType(
    {p.name: p for p in (ARIS, OCULUS, DIDSON)}
)


def profile_for(geometry: Any) -> SonarProfile:
    """The profile of ``geometry``: by the start of its name, else the DIDSON profile.

    ``"aris*"`` (every ARIS preset and file) -> ``"aris"``; ``"oculus*"`` (the
    ``oculus-m750d-like`` preset and Oculus files) -> ``"oculus"``; anything else, including
    DIDSON geometries and user JSON files, -> ``"didson"`` (the plain ``SimulationConfig``
    defaults).

    Examples
    --------
    >>> from sonarmap import preset
    >>> profile_for(preset("oculus-m750d-like")).values["looks"]
    10
    """
    name = str(getattr(geometry, "name", "")).lower()
    for prof in SONAR_PROFILES.values():
        if any(name.startswith(p) for p in prof.prefixes):
            return prof
    return DIDSON
