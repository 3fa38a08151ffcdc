"""Pre-processing pipeline: config, recipes, fast path, metadata, CLI, real data."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sonarmap.errors import GeometryError, InputError
from sonarmap.geometry import preset
from sonarmap.io import read_ping, read_pings
from sonarmap.ping import Ping
from sonarmap.preprocess.deconvolution import deconvolve
from sonarmap.preprocess.gain import RadialGain, apply_radial_gain, correct_taper
from sonarmap.preprocess.pipeline import PreprocessConfig, load_config, preprocess, preprocess_image


@pytest.mark.parametrize("edge", ["pad", "truncated", "circular"])
def test_steps_in_stated_order_equal_the_individual_functions(edge):
    g = preset("didson-hf")
    img = np.random.default_rng(0).random(g.shape).astype(np.float32)
    gain = RadialGain(k1=20.0, k2=2.1, k3=-10.0)
    # Default: taper first (it is a receive gain after the beam pattern), then deconvolve.
    cfg = PreprocessConfig(noise=0.01, edge=edge, clip_negative=True, radial_gain=gain)
    assert cfg.taper_order == "before-deconvolution"
    ref = deconvolve(correct_taper(img, g.taper), g, noise=0.01, edge=edge)
    ref = apply_radial_gain(ref, g, gain)
    out = preprocess_image(img, g, cfg)
    np.testing.assert_allclose(out, np.maximum(ref, 0), rtol=1e-3, atol=1e-3)
    # The paper's order: deconvolve, then taper.
    after = cfg.replace(taper_order="after_deconvolution")  # underscores accepted
    assert after.taper_order == "after-deconvolution"
    ref_a = apply_radial_gain(correct_taper(deconvolve(img, g, noise=0.01, edge=edge), g.taper), g, gain)
    out_a = preprocess_image(img, g, after)
    np.testing.assert_allclose(out_a, np.maximum(ref_a, 0), rtol=1e-3, atol=1e-3)
    # The two orders really differ (the taper does not commute with the beam-axis filter).
    assert np.abs(out - out_a).max() > 100 * 1e-3
    none = PreprocessConfig(deconvolve=False, taper=False, clip_negative=False)
    np.testing.assert_array_equal(preprocess_image(img, g, none), img)


def test_taper_order_recorded_in_metadata_and_recipes():
    g = preset("didson-hf")
    ping = Ping(np.random.default_rng(2).random(g.shape).astype(np.float32), g)
    rec = preprocess(ping).meta["preprocess"]
    assert rec["taper_order"] == "before-deconvolution" == rec["config"]["taper_order"]
    assert rec["steps"] == ["taper", "deconvolve", "clip_negative"]
    assert rec["order"][:2] == ["taper", "deconvolve"]
    assert PreprocessConfig.paper_table1().taper_order == "after-deconvolution"
    assert PreprocessConfig.paper_background().taper_order == "after-deconvolution"
    rec = preprocess(ping, PreprocessConfig.paper_table1()).meta["preprocess"]
    assert rec["taper_order"] == "after-deconvolution" and rec["order"][:2] == ["deconvolve", "taper"]
    with pytest.raises(InputError, match="taper_order"):
        PreprocessConfig(taper_order="first")
    cfg = PreprocessConfig(taper_order="after-deconvolution")
    assert PreprocessConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


def test_normalisation_and_metadata():
    g = preset("didson-hf")
    img = np.random.default_rng(1).random(g.shape).astype(np.float32) * 0.5
    ping = Ping(img, g, source="x.png")
    out = preprocess(ping, PreprocessConfig.paper_table1())
    assert out.image.dtype == np.float32 and out.image is not ping.image
    assert out.image.min() == pytest.approx(0.0, abs=1e-7)
    assert out.image.max() == pytest.approx(img.max(), rel=1e-6)
    rec = out.meta["preprocess"]
    assert rec["steps"] == ["deconvolve", "taper", "clip_negative", "normalise:min-max"]
    assert rec["noise"] == 1e-3 and rec["config"]["edge"] == "circular"
    assert "preprocess" not in ping.meta  # input untouched
    bg = preprocess(ping, PreprocessConfig.paper_background())
    assert bg.meta["preprocess"]["noise"] == g.noise  # per-ping 1/SNR


@pytest.mark.parametrize("subtract_min", [True, False])
@pytest.mark.parametrize("with_nan", [False, True])
def test_clip_rescale_is_numpys_clip_and_normalisation_bit_for_bit(subtract_min, with_nan):
    from sonarmap.preprocess._kernels import clip_rescale

    rng = np.random.default_rng(3)
    out = (rng.standard_normal((64, 24)) * 0.3).astype(np.float32)
    out[5, 5] = -0.0
    if with_nan:
        out[7, 3] = np.nan
    top = 0.7
    expected = np.maximum(out, 0.0)
    if subtract_min:
        expected -= expected.min()
    o_max = float(expected.max())
    if o_max > 0:
        expected *= np.float32(top / o_max)
    got = out.copy()
    if not clip_rescale(got, top, subtract_min):  # NaN: only clipped, the caller goes numpy's way
        assert with_nan
        np.testing.assert_array_equal(got.view(np.uint32), np.maximum(out, 0.0).view(np.uint32))
        return
    assert not with_nan
    np.testing.assert_array_equal(got.view(np.uint32), expected.view(np.uint32))


def test_config_round_trip_and_validation(tmp_path):
    cfg = PreprocessConfig(noise=0.02, radial_gain=RadialGain(k1=20, k2=2), taper_values=(1.0,) * 96)
    assert PreprocessConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    for bad, key in (({"nosie": 1}, "nosie"), ({"edge": "wrap"}, "edge"), ({"noise": "x"}, "noise"),
                     ({"radial_gain": {"k1": 1, "kk": 2}}, "kk"), ({"taper": "yes"}, "taper")):
        with pytest.raises(InputError, match=key):
            PreprocessConfig.from_dict(bad)
    toml = tmp_path / "c.toml"
    toml.write_text('[preprocess]\nnoise = 0.005\nedge = "pad"\n[preprocess.radial_gain]\nk1 = 20.0\nk2 = 2.0\n')
    loaded = load_config(toml)
    assert loaded.noise == 0.005 and loaded.radial_gain == RadialGain(k1=20.0, k2=2.0)
    bad = tmp_path / "b.json"
    bad.write_text('{"noise": 0.1, "colour": 1}')
    with pytest.raises(InputError, match="colour"):
        load_config(bad)


def test_bad_input():
    g = preset("didson-hf")
    with pytest.raises(GeometryError, match="shape"):
        preprocess_image(np.ones((10, 96)), g)
    img = np.ones(g.shape, np.float32)
    img[1, 1] = np.inf
    with pytest.raises(InputError, match="NaN or infinite"):
        preprocess_image(img, g)
    with pytest.raises(GeometryError, match="taper: length 3"):
        preprocess_image(np.ones(g.shape), g, PreprocessConfig(taper_values=(1.0, 1.0, 1.0)))


def test_paper_background_recipe_on_real_data(didson_dir):
    # The authors' deconvolution (circular, 1/SNR 0.01, clip, rescale) leaves 31.1 % non-zero
    # pixels over the 116 background pings: the paper's pi_B = 0.312 (eq. 19).
    cfg = PreprocessConfig.paper_background()
    imgs = [preprocess_image(p.image, p.geometry, cfg) for p in read_pings(didson_dir / "background")]
    frac = np.mean([np.count_nonzero(i) / i.size for i in imgs])
    assert frac == pytest.approx(0.312, abs=0.002)


@pytest.mark.slow
def test_cli_preprocess_writes_pings_and_figure(tmp_path, test_ping_paths):
    from sonarmap.cli import main

    out = tmp_path / "out"
    fig = tmp_path / "fig.png"
    code = main(["preprocess", str(test_ping_paths[4]), str(test_ping_paths[5]), "-o", str(out),
                 "--recipe", "paper-table1", "--figure", str(fig)])
    assert code == 0
    assert fig.stat().st_size > 10_000
    jsons = sorted(out.glob("*.json"))
    assert len(jsons) == 2
    meta = json.loads(jsons[0].read_text())
    assert meta["preprocess"]["config"]["name"] == "paper-table1"
    back = read_ping(sorted(out.glob("*_raw.png"))[0])
    direct = preprocess(read_ping(test_ping_paths[4]), PreprocessConfig.paper_table1())
    np.testing.assert_allclose(back.image, direct.image, atol=1.0 / 65535 + 1e-6)  # 16-bit
    assert main(["preprocess", str(test_ping_paths[0]), "-o", str(out), "--recipe", "nope"]) == 2  # usage error


def test_plan_is_cached_by_geometry_content_not_name() -> None:
    from sonarmap.preprocess import pipeline as pp

    g = preset("didson-hf").replace(noise=0.0217)  # a content no other test plans
    img = np.random.default_rng(3).random(g.shape, dtype=np.float32)
    first = pp.preprocess_image(img, g)
    hits = pp._plan_cached.cache_info().hits
    renamed = g.replace(name="1500000000100000")  # as the reader names each ping's geometry
    np.testing.assert_array_equal(pp.preprocess_image(img, renamed), first)
    assert pp._plan_cached.cache_info().hits == hits + 1
