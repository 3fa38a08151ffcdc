"""SonarGeometry: validation, JSON round trip, presets."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import sonarmap
from sonarmap.errors import DataFormatError, GeometryError, SonarmapError
from sonarmap.geometry import (
    GeometryWarning,
    SonarGeometry,
    geometry_from_dict,
    geometry_from_json_bytes,
    load_geometry,
    preset,
    preset_names,
    save_geometry,
)


def test_didson_preset_measured_azimuths(didson_dir: Path) -> None:
    g = preset("didson-hf")
    ref = json.loads((didson_dir / "didson.json").read_text())
    assert g.shape == (512, 96)
    np.testing.assert_array_equal(g.azimuth_rad, np.asarray(ref["azimuths"]))
    assert np.rad2deg(g.azimuth_rad[0]) == pytest.approx(-14.7177, abs=1e-3)
    assert np.rad2deg(g.azimuth_rad[-1]) == pytest.approx(14.0942, abs=1e-3)
    # measured table is not uniform: spacing varies by > 50 %
    d = np.diff(g.azimuth_rad)
    assert d.max() / d.min() > 1.5
    assert g.range_m[0] == 2.25 and g.max_range_m == 11.25
    assert g.range_resolution_m == pytest.approx(9.0 / 512)
    assert g.psf is not None and g.psf.sum() == pytest.approx(1.0)
    assert np.count_nonzero(g.psf) == 12 and g.psf.argmax() == 48


@pytest.mark.parametrize(
    "name,beams,half_fov_deg",
    [("aris1800-48", 48, 13.57), ("aris1800-96", 96, 13.9), ("aris3000-64", 64, 14.9),
     ("aris3000-128", 128, 15.0), ("aris-telephoto-48", 48, 7.34), ("aris-telephoto-96", 96, 7.42)],
)
def test_aris_presets_from_vendor_tables(name: str, beams: int, half_fov_deg: float, data_dir: Path) -> None:
    g = preset(name)
    assert g.n_beams == beams
    assert np.all(np.diff(g.azimuth_rad) > 0)
    assert np.abs(np.rad2deg(g.azimuth_rad)).max() == pytest.approx(half_fov_deg, abs=0.03)
    # vendor beam 0 (right-most, most negative vendor angle) is our last column, sign flipped
    src = {"aris1800-48": "ARIS1800_1200_48", "aris1800-96": "ARIS1800_96", "aris3000-64": "ARIS3000_64",
           "aris3000-128": "ARIS3000_128", "aris-telephoto-48": "ARIS_Telephoto_48",
           "aris-telephoto-96": "ARIS_Telephoto_96"}[name]
    text = (data_dir / "aris" / f"BeamWidths_{src}.h").read_text()
    first = text.split("DEFINE_BEAMWIDTH3(0,")[1].split(",")[0]
    assert np.rad2deg(g.azimuth_rad[-1]) == pytest.approx(-float(first), abs=1e-9)


def test_preset_names_and_unknown() -> None:
    assert "didson-hf" in preset_names() and len(preset_names()) == 8
    assert "oculus-m750d-like" in preset_names()
    with pytest.raises(GeometryError, match="unknown preset 'nope'.*didson-hf"):
        preset("nope")


def test_json_round_trip_lossless(tmp_path: Path, didson_dir: Path) -> None:
    for src in [preset("didson-hf"), load_geometry(didson_dir / "didson.json"), preset("aris3000-128")]:
        out = tmp_path / "g.json"
        save_geometry(src, out)
        back = load_geometry(out)
        assert back == src
        for f in ("azimuth_rad", "range_m", "psf", "taper", "psf_raw"):
            a, b = getattr(src, f), getattr(back, f)
            assert (a is None and b is None) or np.array_equal(a, b), f
        for f in ("noise", "fov_rad", "frequency_hz", "sound_speed_m_s", "rx_gain_db", "window", "name",
                  "elevation_beamwidth_rad"):
            assert getattr(src, f) == getattr(back, f), f
        a, b = src.azimuth_beamwidth_rad, back.azimuth_beamwidth_rad
        assert (a is None and b is None) or np.array_equal(a, b)


def test_elevation_beamwidth_field(tmp_path: Path) -> None:
    std, tele = preset("aris1800-96"), preset("aris-telephoto-48")
    assert std.elevation_beamwidth_rad == pytest.approx(np.deg2rad(14.0))
    assert tele.elevation_beamwidth_rad is None and preset("didson-hf").elevation_beamwidth_rad is None
    assert "elevation_beamwidth" in std.to_dict() and "elevation_beamwidth" not in tele.to_dict()
    narrow = std.replace(elevation_beamwidth_rad=np.deg2rad(3.0))
    assert narrow != std and narrow.key != std.key  # a different sonar, never merged in a store
    d = std.to_dict()
    for bad, msg in ((0.0, r"\(0, pi\]"), (4.0, r"\(0, pi\]"), ("wide", "elevation_beamwidth"),
                     (float("nan"), "elevation_beamwidth")):
        with pytest.raises(GeometryError, match=msg):
            geometry_from_dict({**d, "elevation_beamwidth": bad}, source="g.json")
    assert geometry_from_dict({**d, "elevation_beamwidth": None}).elevation_beamwidth_rad is None


def test_azimuth_beamwidth_field(tmp_path: Path) -> None:
    aris, ocu, did = preset("aris3000-128"), preset("oculus-m750d-like"), preset("didson-hf")
    assert aris.azimuth_beamwidth_rad.shape == (128,)
    assert np.median(aris.azimuth_beamwidth_rad / np.gradient(aris.azimuth_rad)) == pytest.approx(1.0, abs=0.1)
    assert np.allclose(ocu.azimuth_beamwidth_rad, np.deg2rad(0.55))
    assert np.allclose(did.azimuth_beamwidth_rad, np.deg2rad(0.3))
    assert did.to_dict()["azimuth_beamwidth"] == pytest.approx(np.deg2rad(0.3))  # one number: all equal
    for src in (aris, did):
        save_geometry(src, tmp_path / "g.json")
        back = load_geometry(tmp_path / "g.json")
        assert back == src and np.array_equal(back.azimuth_beamwidth_rad, src.azimuth_beamwidth_rad)
    # a file without it (every file written before it existed) still loads, as before
    d = did.to_dict()
    del d["azimuth_beamwidth"]
    old = geometry_from_dict(d)
    assert old.azimuth_beamwidth_rad is None and "azimuth_beamwidth" not in old.to_dict()
    assert old.key == did.replace(azimuth_beamwidth_rad=None).key != did.key
    assert geometry_from_dict({**d, "azimuth_beamwidth": None}).azimuth_beamwidth_rad is None
    for bad, msg in ((0.0, r"\(0, pi\]"), (4.0, r"\(0, pi\]"), ("wide", "azimuth_beamwidth"),
                     ([0.01] * 3, "does not match"), ([0.01] * 95 + [float("nan")], "azimuth_beamwidth")):
        with pytest.raises(GeometryError, match=msg):
            geometry_from_dict({**d, "azimuth_beamwidth": bad}, source="g.json")


def test_azimuth_beamwidth_follows_a_new_beam_count() -> None:
    ocu, aris = preset("oculus-m750d-like"), preset("aris3000-128")
    few = ocu.replace(azimuth_rad=np.linspace(-0.5, 0.5, 16))
    assert np.allclose(few.azimuth_beamwidth_rad, np.deg2rad(0.55)) and few.azimuth_beamwidth_rad.shape == (16,)
    assert aris.replace(azimuth_rad=np.linspace(-0.2, 0.2, 64)).azimuth_beamwidth_rad is None  # a table
    assert np.array_equal(aris.replace(azimuth_rad=aris.azimuth_rad * 0.9).azimuth_beamwidth_rad,
                          aris.azimuth_beamwidth_rad)


def test_oculus_default_azimuth_beamwidth_by_frequency() -> None:
    from sonarmap.geometry import oculus_azimuth_beamwidth_rad

    assert [round(np.rad2deg(oculus_azimuth_beamwidth_rad(f)), 2) for f in (7.5e5, 1.2e6, 2.1e6)] == [1.0, 0.6, 0.55]


def test_explicit_nonuniform_range_table_round_trip(tmp_path: Path) -> None:
    r = np.array([1.0, 1.1, 1.3, 1.7, 2.5])
    g = SonarGeometry(azimuth_rad=[-0.1, 0.0, 0.2], range_m=r, name="odd")
    assert not g.uniform_range
    save_geometry(g, tmp_path / "odd.json")
    back = load_geometry(tmp_path / "odd.json")
    np.testing.assert_array_equal(back.range_m, r)
    np.testing.assert_array_equal(back.azimuth_rad, [-0.1, 0.0, 0.2])


def test_missing_azimuths_fall_back_to_uniform_with_warning() -> None:
    d = {"fov": 0.5, "num_beams": 10, "num_bins": 20, "min_range": 1.0, "max_range": 3.0}
    with pytest.warns(GeometryWarning, match="uniform"):
        g = geometry_from_dict(d, source="x.json")
    assert g.azimuth_source == "uniform"
    assert np.allclose(np.diff(g.azimuth_rad), 0.05)
    assert g.azimuth_rad[0] == pytest.approx(-0.225)


def test_missing_azimuths_matching_didson_uses_measured_table(didson_dir: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g = load_geometry(didson_dir / "test" / "1468966347175925.json")
    assert g.azimuth_source == "preset:didson-hf"
    np.testing.assert_array_equal(g.azimuth_rad, preset("didson-hf").azimuth_rad)
    assert g.noise == 0.01  # the per-ping value, not the preset's


def test_malformed_json_names_file_line_column(data_dir: Path) -> None:
    path = data_dir / "mb2250" / "mb2250.json"
    with pytest.raises(DataFormatError) as ei:
        load_geometry(path)
    msg = str(ei.value)
    assert str(path) in msg and "line 3 column 3" in msg
    assert isinstance(ei.value, OSError) and isinstance(ei.value, SonarmapError)


@pytest.mark.parametrize(
    "change,match",
    [
        ({"psf": [1.0, 2.0]}, "psf: length 2 does not match 3 beams"),
        ({"taper": [1.0, 0.0, 1.0]}, "taper: per-beam gains must be positive"),
        ({"azimuth_rad": [0.1, 0.0, 0.2]}, "strictly increasing"),
        ({"azimuth_rad": [0.0, np.nan, 0.2]}, "NaN"),
        ({"range_m": [2.0, 1.0]}, "range_m: range bins must be strictly increasing"),
        ({"noise": -1.0}, "noise"),
        ({"sound_speed_m_s": 340.0}, "sound_speed_m_s"),
        ({"psf": [-1.0, 2.0, 0.0]}, "non-negative"),
    ],
)
def test_validation_errors(change: dict, match: str) -> None:
    kw = {"azimuth_rad": [-0.1, 0.0, 0.1], "range_m": [1.0, 2.0]}
    kw.update(change)
    with pytest.raises(GeometryError, match=match):
        SonarGeometry(**kw)
    with pytest.raises(ValueError):  # also a builtin ValueError
        SonarGeometry(**kw)


def test_missing_field_and_wrong_type_named() -> None:
    with pytest.raises(GeometryError, match="a.json: missing field 'min_range'"):
        geometry_from_dict({"azimuths": [0.0], "num_bins": 3, "max_range": 2.0}, source="a.json")
    with pytest.raises(GeometryError, match="'noise' must be a number"):
        geometry_from_dict({"azimuths": [0.0], "num_bins": 3, "min_range": 1.0, "max_range": 2.0,
                            "noise": "x"}, source="a.json")
    with pytest.raises(GeometryError, match="'azimuths' has 1 entries but num_beams is 2"):
        geometry_from_dict({"azimuths": [0.0], "num_beams": 2, "num_bins": 3, "min_range": 1.0,
                            "max_range": 2.0}, source="a.json")


def test_bin_and_beam_lookup() -> None:
    g = preset("didson-hf")
    assert g.bin_of_range(2.25) == 0
    assert g.bin_of_range(g.range_m[100] + 0.4 * g.range_resolution_m) == 100
    assert g.bin_of_range(g.range_m[100] + 0.6 * g.range_resolution_m) == 101
    assert g.beam_of_azimuth(g.azimuth_rad[37] + 1e-4) == 37


def test_geometry_hash_and_immutability() -> None:
    g = preset("didson-hf")
    assert hash(g) == hash(preset("didson-hf").replace())
    assert g != g.replace(noise=0.5)
    with pytest.raises(ValueError):
        g.azimuth_rad[0] = 1.0  # read-only arrays
    with pytest.raises(AttributeError):
        g.noise = 3.0  # type: ignore[misc]


def test_public_api_exports() -> None:
    assert sonarmap.SonarGeometry is SonarGeometry
    assert issubclass(sonarmap.InputError, ValueError)
    assert issubclass(sonarmap.DataFormatError, OSError)


def test_json_of_one_content_is_validated_once_and_named_per_file(monkeypatch: pytest.MonkeyPatch) -> None:
    import sonarmap.geometry as geometry_module

    calls: list[str] = []
    real = geometry_module.geometry_from_dict

    def counting(d: Any, **kw: Any) -> SonarGeometry:
        calls.append(kw["source"])
        return real(d, **kw)

    monkeypatch.setattr(geometry_module, "geometry_from_dict", counting)
    d = {"num_beams": 4, "num_bins": 8, "min_range": 1.0, "max_range": 3.0, "fov": 0.4,
         "azimuths": [-0.15, -0.05, 0.05, 0.15], "psf": [0.0, 0.5, 1.0, 0.5]}
    data = json.dumps(d).encode()
    a = geometry_from_json_bytes(data, "a.json", "1500000000000000")
    b = geometry_from_json_bytes(data, "b.json", "1500000000100000")
    assert calls == ["a.json"]  # the second file's content was not decoded or validated again
    assert (a.name, b.name) == ("1500000000000000", "1500000000100000")
    assert a.key == b.key and a != b  # same content, each named after its own file
    parsed = geometry_from_dict(d, source="b.json", default_name="1500000000100000")
    assert b == parsed and b.key == parsed.key
    for field in ("azimuth_rad", "range_m", "psf", "psf_raw", "taper"):
        np.testing.assert_array_equal(getattr(b, field), getattr(parsed, field))
    assert (b.fov_rad, b.window, b.azimuth_source) == (parsed.fov_rad, parsed.window, parsed.azimuth_source)
    # a name in the JSON names every file's geometry
    named = json.dumps({**d, "name": "hull"}).encode()
    assert geometry_from_json_bytes(named, "c.json", "1").name == "hull"
    assert geometry_from_json_bytes(named, "d.json", "2").name == "hull"
    # a file name that is not a valid geometry name is refused as when parsing, naming the file
    with pytest.raises(GeometryError, match=r"^e\.json: field 'name'"):
        geometry_from_json_bytes(data, "e.json", "bad\nname")


def test_json_content_that_warns_warns_for_every_file() -> None:
    data = json.dumps({"fov": 0.5, "num_beams": 10, "num_bins": 20, "min_range": 1.0,
                       "max_range": 3.0, "noise": 0.0123}).encode()
    for source in ("w1.json", "w2.json"):
        with pytest.warns(GeometryWarning, match=source):
            g = geometry_from_json_bytes(data, source, source[:2])
        assert g.azimuth_source == "uniform" and g.name == source[:2]
