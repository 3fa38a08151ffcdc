"""The quantisation floor: a background on the bottom levels of the 8-bit grid (the dark water
column of an Oculus whose automatic gain lowered the gain for a bright hull) is merged into the
zero level instead of failing the KL-divergence gate."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap import preset
from sonarmap.evaluate import preset_sim_configs
from sonarmap.pipeline import PipelineConfig, process_ping
from sonarmap.simulate import scene_from_name, simulate_ping


@pytest.fixture(scope="module")
def dark_hull():
    g = preset("oculus-m750d-like")
    return simulate_ping(scene_from_name("hull_slope2", geometry=g), g, config=preset_sim_configs(g)[0], seed=0)


@pytest.mark.slow  # the dark_hull fixture renders a simulated ping (~4 s)
def test_the_dark_background_sits_on_the_bottom_levels(dark_hull):
    # the premise: the gain assist lowered the gain, the background lives on levels 0-2
    assert dark_hull.ping.meta["gain_assist_db"] >= 6
    lv = np.rint(dark_hull.ping.image * 255).astype(int)
    h = np.bincount(lv.ravel(), minlength=256) / lv.size
    assert h[:3].sum() > 0.75 and h[1] > 10 * h[2]


@pytest.mark.slow  # the dark_hull fixture renders a simulated ping (~4 s)
def test_without_the_floor_the_ping_is_refused(dark_hull):
    out = process_ping(dark_hull.ping, PipelineConfig().replace(max_floor_levels=0))
    assert "kld" in out.gates and out.ranges.n_returns == 0 and out.floor_levels == 0


@pytest.mark.slow  # the dark_hull fixture renders a simulated ping (~4 s)
def test_with_the_floor_the_hull_is_found_at_its_range(dark_hull):
    out = process_ping(dark_hull.ping, PipelineConfig())
    assert out.gates == () and out.floor_levels >= 1
    g = dark_hull.ping.geometry
    truth = dark_hull.surface_range_m
    has = np.isfinite(truth)
    dr = abs(g.range_resolution_m)
    err = (out.ranges.range_m - truth)[has] / dr
    # returns on >= 90 % of the hull's beams, most within 3 bins of the physical surface
    assert np.isfinite(err).mean() >= 0.9
    assert np.mean(np.abs(err[np.isfinite(err)]) <= 3) >= 0.5
    # and no return on a beam without the hull
    assert not np.isfinite(out.ranges.range_m[~has]).any() or np.isfinite(out.ranges.range_m[~has]).mean() < 0.05


def test_a_ping_whose_fit_passes_is_modelled_as_recorded():
    g = preset("oculus-m750d-like")
    sim = simulate_ping(scene_from_name("propeller", geometry=g), g, config=preset_sim_configs(g)[0], seed=0)
    a = process_ping(sim.ping, PipelineConfig())
    b = process_ping(sim.ping, PipelineConfig().replace(max_floor_levels=0))
    assert a.floor_levels == 0
    np.testing.assert_array_equal(a.ranges.range_m, b.ranges.range_m)


@pytest.mark.parametrize("make", [
    lambda r: r.rayleigh(2.0 / 255, (512, 96)),
    lambda r: r.exponential(1.5 / 255, (512, 96)),
    lambda r: r.gamma(10.0, 0.15 / 255, (703, 256)),
])
def test_dark_noise_stays_without_returns(make):
    # speckle on the bottom levels: the floor must not turn it into a surface
    rng = np.random.default_rng(3)
    img = np.clip(np.rint(make(rng) * 255), 0, 255).astype(np.float32) / 255
    from sonarmap.geometry import SonarGeometry
    from sonarmap.ping import Ping

    n, m = img.shape
    geom = SonarGeometry(range_m=np.linspace(1.0, 10.0, n), azimuth_rad=np.linspace(-0.4, 0.4, m))
    out = process_ping(Ping(image=img, geometry=geom), PipelineConfig())
    assert out.ranges.n_returns == 0


def test_max_floor_levels_is_validated():
    from sonarmap.errors import InputError

    with pytest.raises(InputError, match="max_floor_levels"):
        PipelineConfig().replace(max_floor_levels=-1)


def test_report_summarises_the_floor():
    import xarray as xr

    from sonarmap.report import _floor_summary

    assert _floor_summary(xr.Dataset({"floor_levels": ("ping_time", np.array([0, 1, 1, 0]))})) == \
        "2 of 4 pings with their lowest 1 level merged into the zero level"
    assert "1-3 levels" in _floor_summary(xr.Dataset({"floor_levels": ("ping_time", np.array([1, 3]))}))
    assert _floor_summary(xr.Dataset({"floor_levels": ("ping_time", np.zeros(3, int))})).startswith("none")
    assert _floor_summary(xr.Dataset({"kld": ("ping_time", np.zeros(3))})).startswith("not recorded")
