"""Seawater absorption against values published with the models."""

from __future__ import annotations

import pytest

from sonarmap.errors import InputError
from sonarmap.preprocess.absorption import absorption_db_per_m

# Francois & Garrison (1982b, JASA 72(6) 1879-1890) check values, dB/km at pH 8, z = 0, as
# tabulated with G. Jimenez Arranz's reference implementation (temperature taken as IPTS-68):
# (T degC, S ppt, f kHz, alpha dB/km)
FG_CHECK = [
    (0, 30, 1, 6.10e-2), (0, 35, 1, 6.40e-2), (10, 35, 1, 6.00e-2),
    (0, 30, 10, 1.12), (0, 35, 10, 1.29), (10, 35, 10, 9.63e-1),
    (0, 30, 100, 21.0), (0, 35, 100, 23.4), (10, 35, 100, 33.6),
]  # fmt: skip


@pytest.mark.parametrize(("t", "s", "f_khz", "ref_db_km"), FG_CHECK)
def test_francois_garrison_published_values(t, s, f_khz, ref_db_km):
    a = absorption_db_per_m(f_khz * 1e3, temperature_c=t, salinity_psu=s, depth_m=0.0, ph=8.0)
    assert a * 1e3 == pytest.approx(ref_db_km, rel=0.01)  # table gives 3 significant digits


def test_ainslie_mccolm_within_10_percent_of_fg():
    # Ainslie & McColm (1998, JASA 103(3) 1671): their formula fits F&G to within 10 % for
    # 100 Hz < f < 1 MHz at T = 10 degC, S = 35, z = 0, pH = 8.
    for f_khz in (0.1, 0.3, 1, 3, 10, 30, 100, 300, 1000):
        fg = absorption_db_per_m(f_khz * 1e3, model="francois-garrison")
        am = absorption_db_per_m(f_khz * 1e3, model="ainslie-mccolm")
        assert am == pytest.approx(fg, rel=0.10), f_khz


def test_didson_frequency_value_and_trends():
    fg = absorption_db_per_m(1.8e6, temperature_c=10.0, salinity_psu=35.0)
    am = absorption_db_per_m(1.8e6, temperature_c=10.0, salinity_psu=35.0, model="ainslie-mccolm")
    # pure-water viscous term dominates: F&G 1.055 dB/m, A&M 1.145 dB/m at 1.8 MHz
    assert fg == pytest.approx(1.055, abs=0.005)
    assert am == pytest.approx(1.145, abs=0.005)
    assert absorption_db_per_m(1.8e6, depth_m=2000.0) < fg  # pressure lowers absorption
    assert absorption_db_per_m(1.8e6, temperature_c=25.0) < fg  # warmer water absorbs less at MHz
    assert absorption_db_per_m(3e3, ph=8.3) > absorption_db_per_m(3e3, ph=7.7)  # boric acid


def test_bad_arguments():
    with pytest.raises(InputError, match="frequency_hz"):
        absorption_db_per_m(-5.0)
    with pytest.raises(InputError, match="temperature_c"):
        absorption_db_per_m(1e6, temperature_c=float("nan"))
    with pytest.raises(InputError, match="model"):
        absorption_db_per_m(1e6, model="thorp")  # type: ignore[arg-type]
