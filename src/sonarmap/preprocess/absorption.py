"""Sound absorption in seawater (the ``alpha`` of the channel model, eq. 6-7).

Two published models, both returning the one-way absorption coefficient in dB/m:

* ``"francois-garrison"``: Francois & Garrison (1982), "Sound absorption based on ocean
  measurements. Part I: Pure water and magnesium sulfate contributions", JASA 72(3) 896-907, and
  "Part II: Boric acid contribution and equation for total absorption", JASA 72(6) 1879-1890.
  Boric acid, MgSO4 and pure-water terms with temperature, salinity, depth, pH and sound speed.
  Stated validity 200 Hz - 1 MHz (the pure-water term, which dominates above ~500 kHz, is the
  usual extrapolation for imaging sonars at 1-3 MHz).
* ``"ainslie-mccolm"``: Ainslie & McColm (1998), "A simplified formula for viscous and chemical
  absorption in sea water", JASA 103(3) 1671-1672; fits Francois-Garrison to within 10 % for
  100 Hz - 1 MHz.

For the DIDSON at 1.8 MHz, 10 degC, 35 PSU, surface, both give about 1.0-1.1 dB/m (the pure-water
viscous term ``~ f**2`` dominates).
"""

from __future__ import annotations

import math
from typing import Literal

from sonarmap.errors import InputError

__all__ = ["absorption_db_per_m", "sound_speed_francois_garrison", "MODELS"]

MODELS = ("francois-garrison", "ainslie-mccolm")


def sound_speed_francois_garrison(
    temperature_c: float, salinity_psu: float, depth_m: float
) -> float:
    """Sound speed used inside the Francois-Garrison formula: ``1412 + 3.21 T + 1.19 S + 0.0167 z``."""
    return 1412.0 + 3.21 * temperature_c + 1.19 * salinity_psu + 0.0167 * depth_m


def _check(name: str, value: float, lo: float, hi: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: not a number ({value!r})") from None
    if not math.isfinite(v) or not lo <= v <= hi:
        raise InputError(f"{name}: {v} is outside the supported range [{lo}, {hi}]")
    return v


def _francois_garrison_db_per_km(
    f_khz: float, t: float, s: float, z: float, ph: float, c: float
) -> float:
    tk = t + 273.0
    # Boric acid
    a1 = 8.86 / c * 10.0 ** (0.78 * ph - 5.0)
    p1 = 1.0
    f1 = 2.8 * math.sqrt(s / 35.0) * 10.0 ** (4.0 - 1245.0 / tk)
    # Magnesium sulphate
    a2 = 21.44 * s / c * (1.0 + 0.025 * t)
    p2 = 1.0 - 1.37e-4 * z + 6.2e-9 * z * z
    f2 = 8.17 * 10.0 ** (8.0 - 1990.0 / tk) / (1.0 + 0.0018 * (s - 35.0))
    # Pure water
    p3 = 1.0 - 3.83e-5 * z + 4.9e-10 * z * z
    if t <= 20.0:
        a3 = 4.937e-4 - 2.59e-5 * t + 9.11e-7 * t**2 - 1.50e-8 * t**3
    else:
        a3 = 3.964e-4 - 1.146e-5 * t + 1.45e-7 * t**2 - 6.5e-10 * t**3
    f2s = f_khz * f_khz
    return (
        a1 * p1 * f1 * f2s / (f2s + f1 * f1)
        + a2 * p2 * f2 * f2s / (f2s + f2 * f2)
        + a3 * p3 * f2s
    )


def _ainslie_mccolm_db_per_km(f_khz: float, t: float, s: float, z: float, ph: float) -> float:
    zk = z / 1000.0
    f1 = 0.78 * math.sqrt(s / 35.0) * math.exp(t / 26.0)
    f2 = 42.0 * math.exp(t / 17.0)
    f2s = f_khz * f_khz
    boric = 0.106 * f1 * f2s / (f1 * f1 + f2s) * math.exp((ph - 8.0) / 0.56)
    mgso4 = 0.52 * (1.0 + t / 43.0) * (s / 35.0) * f2 * f2s / (f2 * f2 + f2s) * math.exp(-zk / 6.0)
    water = 0.00049 * f2s * math.exp(-(t / 27.0 + zk / 17.0))
    return boric + mgso4 + water


def absorption_db_per_m(
    frequency_hz: float,
    *,
    temperature_c: float = 10.0,
    salinity_psu: float = 35.0,
    depth_m: float = 0.0,
    ph: float = 8.0,
    model: Literal["francois-garrison", "ainslie-mccolm"] = "francois-garrison",
    sound_speed_m_s: float | None = None,
) -> float:
    """One-way absorption coefficient of seawater in dB/m.

    Parameters
    ----------
    frequency_hz : float
        Acoustic frequency in Hz (> 0).
    temperature_c : float
        Temperature in degrees Celsius (-6 to 40).
    salinity_psu : float
        Salinity in PSU (= ppt; 0 to 50).
    depth_m : float
        Depth in metres (0 to 12000).
    ph : float
        pH (6 to 9.5).
    model : {"francois-garrison", "ainslie-mccolm"}
    sound_speed_m_s : float, optional
        Francois-Garrison only: sound speed; defaults to their formula
        (:func:`sound_speed_francois_garrison`).

    Returns
    -------
    float
        ``alpha`` in dB/m; the two-way loss over range ``r`` is ``2 alpha r`` (``k2 = 2 alpha``,
        eq. 7 of Teixeira et al. 2018).

    Raises
    ------
    InputError
        Non-finite or out-of-range arguments (the message names the argument), unknown model.
    """
    f = _check("frequency_hz", frequency_hz, 1e-9, 1e8)
    if f <= 0:
        raise InputError(f"frequency_hz: must be positive (got {f})")
    t = _check("temperature_c", temperature_c, -6.0, 40.0)
    s = _check("salinity_psu", salinity_psu, 0.0, 50.0)
    z = _check("depth_m", depth_m, 0.0, 12000.0)
    p = _check("ph", ph, 6.0, 9.5)
    f_khz = f / 1000.0
    if model == "francois-garrison":
        if sound_speed_m_s is None:
            c = sound_speed_francois_garrison(t, s, z)
        else:
            c = _check("sound_speed_m_s", sound_speed_m_s, 1300.0, 1700.0)
        return _francois_garrison_db_per_km(f_khz, t, s, z, p, c) / 1000.0
    if model == "ainslie-mccolm":
        if sound_speed_m_s is not None:
            raise InputError("sound_speed_m_s: only used by model='francois-garrison'")
        return _ainslie_mccolm_db_per_km(f_khz, t, s, z, p) / 1000.0
    raise InputError(f"model: must be one of {', '.join(MODELS)}, got {model!r}")
