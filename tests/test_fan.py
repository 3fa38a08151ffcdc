"""Fan rendering honours the per-beam azimuth table and range bins."""

from __future__ import annotations

import numpy as np
import pytest

from sonarmap.errors import GeometryError, InputError
from sonarmap.fan import fan_extent_m, fan_image, polar_to_xy, xy_to_polar
from sonarmap.geometry import SonarGeometry, preset


@pytest.mark.parametrize("name", ["didson-hf", "aris3000-128", "aris-telephoto-48"])
@pytest.mark.parametrize("bin_beam", [(100, 5), (400, 90), (10, 47)])
def test_point_lands_on_right_pixel(name: str, bin_beam: tuple[int, int]) -> None:
    g = preset(name)
    i, j = bin_beam
    i = min(i, g.n_bins - 1)
    j = min(j, g.n_beams - 1)
    img = np.zeros(g.shape, np.float32)
    img[i, j] = 1.0
    res = 0.01
    fan = fan_image(img, g, resolution_m=res)
    x, y = polar_to_xy(g.range_m[i], g.azimuth_rad[j])
    row, col = fan.pixel_of(float(x), float(y))
    peak = np.unravel_index(np.nanargmax(fan.image), fan.image.shape)
    # the brightest fan pixel is the one holding the true point, or its immediate neighbour
    assert max(abs(peak[0] - row), abs(peak[1] - col)) <= 1
    assert fan.image[row, col] >= 0.5 * fan.image[peak]
    # and its metric position is the target's range/azimuth to within one pixel
    r, a = xy_to_polar(fan.x_m[peak[0]], fan.y_m[peak[1]])
    assert abs(r - g.range_m[i]) <= res
    assert abs(a - g.azimuth_rad[j]) <= res * np.sqrt(2) / g.range_m[i]


def test_nonuniform_table_is_honoured() -> None:
    """Same beam index, two azimuth tables -> the target moves to the table's azimuth."""
    g = preset("didson-hf")
    uni = g.replace(azimuth_rad=np.linspace(g.azimuth_rad[0], g.azimuth_rad[-1], g.n_beams))
    img = np.zeros(g.shape, np.float32)
    img[300, 20] = 1.0
    for geom in (g, uni):
        fan = fan_image(img, geom, resolution_m=0.01)
        peak = np.unravel_index(np.nanargmax(fan.image), fan.image.shape)
        _, a = xy_to_polar(fan.x_m[peak[0]], fan.y_m[peak[1]])
        assert a == pytest.approx(geom.azimuth_rad[20], abs=2e-3)
    assert abs(g.azimuth_rad[20] - uni.azimuth_rad[20]) > 5e-3


def test_outside_fan_is_nan_and_extent() -> None:
    g = preset("didson-hf")
    fan = fan_image(np.ones(g.shape, np.float32), g)
    assert np.isnan(fan.image[0, 0])  # near corner is outside the fan
    inside = np.isfinite(fan.image)
    assert np.allclose(fan.image[inside], 1.0)
    x0, x1, y0, y1 = fan_extent_m(g)
    assert x1 == pytest.approx(g.range_m[-1] + g.range_resolution_m / 2)
    assert y0 < 0 < y1 and abs(y0) > abs(y1)  # DIDSON table reaches further to port (-14.7 vs 14.1)
    left, right, bottom, top = fan.extent_m
    assert left <= y0 + fan.resolution_m and top >= x1 - fan.resolution_m


def test_bad_input() -> None:
    g = preset("didson-hf")
    with pytest.raises(GeometryError):
        fan_image(np.zeros((5, 5)), g)
    with pytest.raises(InputError, match="resolution_m"):
        fan_image(np.zeros(g.shape), g, resolution_m=-1)
    one = SonarGeometry(azimuth_rad=[0.0], range_m=[1.0, 2.0])
    assert fan_image(np.ones((2, 1)), one, resolution_m=0.05).image.size > 0


@pytest.mark.parametrize("range_m,azimuth_deg", [(4.0, -10.0), (6.3, 2.0), (9.5, 12.0)])
def test_simulated_point_target_lands_on_right_fan_pixel(range_m: float, azimuth_deg: float) -> None:
    """Simulator -> polar ping -> fan: the brightest fan pixel is at the target's (x, y)."""
    from sonarmap.simulate import SimulationConfig, point_target, simulate_ping

    g = preset("didson-hf")
    az = np.deg2rad(azimuth_deg)
    res = simulate_ping(point_target(range_m, az, ts_db=-45.0), g,
                        config=SimulationConfig(speckle=False), seed=3)
    i, j = int(res.first_return_bin.max()), int(np.argmax(res.first_return_bin >= 0))
    assert i == g.bin_of_range(range_m) and j == g.beam_of_azimuth(az)  # truth is where we put it
    # the taper darkens outer beams below their +-8-beam ghosts, so compare taper-corrected levels
    img = res.ping.image / g.taper[None, :].astype(np.float32)
    fan = fan_image(img, g, resolution_m=0.01)
    peak = np.unravel_index(np.nanargmax(fan.image), fan.image.shape)
    x, y = polar_to_xy(range_m, az)
    assert abs(fan.x_m[peak[0]] - x) <= g.range_resolution_m
    # one beam spacing at this azimuth, in metres across track
    spacing = float(np.diff(g.azimuth_rad)[min(j, g.n_beams - 2)])
    assert abs(fan.y_m[peak[1]] - y) <= range_m * spacing


def test_too_fine_a_resolution_is_refused_before_allocating() -> None:
    """A resolution giving more than MAX_FAN_PIXELS pixels is an InputError naming the finest one
    allowed (a 1e-9 m resolution raised MemoryError while building the look-up table before)."""
    from sonarmap.fan import MAX_FAN_PIXELS, check_fan_resolution

    g = preset("aris-telephoto-48")
    img = np.zeros(g.shape, np.float32)
    with pytest.raises(InputError, match=r"give at least 0\.\d+ m") as exc:
        fan_image(img, g, resolution_m=1e-9)
    finest = float(str(exc.value).rsplit("at least ", 1)[1].split()[0])
    x0, x1, y0, y1 = fan_extent_m(g)
    assert np.ceil((x1 - x0) / finest) * np.ceil((y1 - y0) / finest) <= MAX_FAN_PIXELS
    assert check_fan_resolution(g, finest) == finest
    with pytest.raises(InputError, match="positive"):
        check_fan_resolution(g, 0.0)
