"""Returns registered at the near edge of their beam's footprint (sonarmap.mapping.footprint)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sonarmap.errors import InputError
from sonarmap.mapping.footprint import across_beam_slope, footprint_azimuths
from sonarmap.mapping.poses import SensorPoses
from sonarmap.mapping.register import RegistrationConfig, register_ranges, register_returns
from sonarmap.ranges import BeamRanges

W = math.radians(0.3)  # two-way -3 dB beamwidth (DIDSON HF)
AZ = np.radians(np.linspace(-14.0, 14.0, 96))


def _identity_poses(n: int = 1) -> SensorPoses:
    R = np.repeat(np.eye(3)[None], n, axis=0)
    return SensorPoses(np.arange(n, dtype=np.int64), R, np.zeros((n, 3)), Rotation.from_matrix(R).as_quat(),
                       np.ones(n, bool))


def _plane_range(az: np.ndarray, d: float, tilt: float) -> np.ndarray:
    """Range along azimuth ``az`` to the line ``p . (cos tilt, sin tilt) = d`` of the imaging plane."""
    return d / np.cos(az - tilt)


def _plane_distance(xyz: np.ndarray, d: float, tilt: float) -> np.ndarray:
    return np.abs(xyz[:, 0] * math.cos(tilt) + xyz[:, 1] * math.sin(tilt) - d)


@pytest.mark.parametrize("tilt_deg", [-40.0, -20.0, 25.0, 50.0])
def test_inclined_plane_points_land_on_it(tilt_deg: float) -> None:
    """Each beam reports the leading edge: the plane's nearest point in its -3 dB footprint."""
    tilt = math.radians(tilt_deg)
    d = 5.0
    # the nearest point of the footprint [az - W/2, az + W/2] (the plane is monotonic across it)
    r = np.minimum(_plane_range(AZ - W / 2, d, tilt), _plane_range(AZ + W / 2, d, tilt))
    poses = _identity_poses()
    edge = register_returns(r[None], AZ, poses, azimuth_beamwidth_rad=W)
    axis = register_returns(r[None], AZ, poses, azimuth_beamwidth_rad=W,
                            config=RegistrationConfig(footprint_edge=False))
    assert _plane_distance(edge.xyz_m, d, tilt).max() < 1e-9
    # on the axes every point lies in front of the plane by |dr/dtheta| W / 2 (several mm here)
    assert _plane_distance(axis.xyz_m, d, tilt).min() > 1e-3
    # the same without a beamwidth: on the axes
    assert np.array_equal(register_returns(r[None], AZ, poses).xyz_m, axis.xyz_m)


def test_flat_surface_at_normal_incidence_is_unchanged() -> None:
    r = np.full((2, AZ.size), 6.0)  # a circle about the sonar: every beam at normal incidence
    poses = _identity_poses(2)
    edge = register_returns(r, AZ, poses, azimuth_beamwidth_rad=W)
    axis = register_returns(r, AZ, poses, config=RegistrationConfig(footprint_edge=False))
    assert np.array_equal(edge.xyz_m, axis.xyz_m)
    assert np.array_equal(footprint_azimuths(r, AZ, W), np.broadcast_to(AZ, r.shape))


def test_side_follows_the_slope() -> None:
    az = np.radians([-1.0, -0.5, 0.0, 0.5, 1.0])
    rising = 5.0 + 0.2 * np.degrees(az)
    assert np.allclose(footprint_azimuths(rising, az, W), az - W / 2)  # the surface is nearer to port
    assert np.allclose(footprint_azimuths(rising[::-1].copy(), az, W), az + W / 2)
    assert np.allclose(footprint_azimuths(rising, az, W, fraction=0.25), az - W / 4)
    assert np.array_equal(footprint_azimuths(rising, az, W, fraction=0.0), az)


def test_unknown_slope_or_beamwidth_keeps_the_axis() -> None:
    az = np.radians([-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5])
    r = np.array([np.nan, 5.0, np.nan, np.nan, 6.0, 6.1, 6.2])
    new = footprint_azimuths(r, az, W, half_beams=1)
    assert new[1] == az[1]  # isolated return
    assert new[4] == az[4] - W / 2 and new[6] == az[6] - W / 2  # one-sided neighbours suffice
    assert new[0] == az[0] and new[2] == az[2]  # no return
    widths = np.full(az.size, W)
    widths[5] = np.nan
    assert footprint_azimuths(r, az, widths)[5] == az[5]


def test_a_jump_to_another_surface_is_not_a_slope() -> None:
    az = np.radians(np.linspace(-2.0, 2.0, 9))
    r = 5.0 + 0.3 * np.degrees(az)
    r_jump = r.copy()
    r_jump[4] += 2.0  # a surface 2 m behind: steeper than 80 deg incidence from both neighbours
    s, s_jump = across_beam_slope(r, az), across_beam_slope(r_jump, az)
    assert np.isnan(s_jump[4])
    assert np.allclose(s_jump[[0, 1, 7, 8]], s[[0, 1, 7, 8]])  # neighbours beyond the window's reach
    assert np.all(s_jump[[2, 3, 5, 6]] > 0)  # still the plane's side, from the beams on it


def test_register_ranges_takes_a_width_per_ping() -> None:
    rising = 5.0 + 0.2 * np.degrees(AZ)
    brs = [BeamRanges(range_m=rising, bin=np.arange(AZ.size), intensity=np.ones(AZ.size, np.float32),
                      confidence=np.ones(AZ.size, np.float32), azimuth_rad=AZ) for _ in range(2)]
    poses = _identity_poses(2)
    axis = register_ranges(brs, poses)
    both = register_ranges(brs, poses, azimuth_beamwidth_rad=W)
    one = register_ranges(brs, poses, azimuth_beamwidth_rad=[W, None])
    per_beam = register_ranges(brs, poses, azimuth_beamwidth_rad=np.full(AZ.size, W))
    n = AZ.size
    assert np.array_equal(one.xyz_m[:n], both.xyz_m[:n]) and np.array_equal(one.xyz_m[n:], axis.xyz_m[n:])
    assert np.array_equal(per_beam.xyz_m, both.xyz_m)
    assert not np.allclose(both.xyz_m, axis.xyz_m)
    with pytest.raises(InputError, match="azimuth_beamwidth_rad"):
        register_ranges(brs, poses, azimuth_beamwidth_rad=[W])
    with pytest.raises(InputError, match="footprint_fraction"):
        RegistrationConfig(footprint_fraction=1.5)
