"""Registration of per-beam ranges into world points (sonarmap.mapping.register)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sonarmap.errors import InputError
from sonarmap.mapping.poses import SensorPoses, Trajectory, sensor_poses, Extrinsics
from sonarmap.mapping.register import PointCloud, RegistrationConfig, register_ranges, register_returns
from sonarmap.ranges import BeamRanges


def _poses(R: np.ndarray, t: np.ndarray, times: np.ndarray | None = None) -> SensorPoses:
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    n = R.shape[0]
    times = np.arange(n, dtype=np.int64) if times is None else times
    return SensorPoses(times, R, np.asarray(t, dtype=np.float64).reshape(n, 3),
                       Rotation.from_matrix(R).as_quat(), np.ones(n, bool))


def test_zero_elevation_points_follow_azimuth_convention() -> None:
    az = np.deg2rad([-30.0, 0.0, 30.0])
    cloud = register_returns([[4.0, 5.0, 6.0]], az, _poses(np.eye(3), [0, 0, 0]))
    assert np.allclose(cloud.xyz_m[1], [5, 0, 0])
    assert np.allclose(cloud.xyz_m[2], [6 * math.cos(az[2]), 6 * math.sin(az[2]), 0])
    assert cloud.xyz_m[2, 1] > 0 > cloud.xyz_m[0, 1]  # positive azimuth = starboard = +y
    assert cloud.beam.tolist() == [0, 1, 2]


def test_pose_rotation_and_translation_applied() -> None:
    R = Rotation.from_euler("z", 90, degrees=True).as_matrix()  # sensor facing east
    cloud = register_returns([[5.0]], [0.0], _poses(R, [10, 20, 3]))
    assert np.allclose(cloud.xyz_m, [[10, 25, 3]])


def test_nan_dropped_and_attributes_kept() -> None:
    r = np.array([[5.0, np.nan, 7.0], [np.nan, 2.0, -1.0]])
    inten = np.array([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]], np.float32)
    conf = np.array([[1.0, 0.0, 0.5], [0.0, 0.25, 0.0]], np.float32)
    cloud = register_returns(r, np.zeros(3), _poses(np.stack([np.eye(3)] * 2), np.zeros((2, 3)), np.array([100, 200])),
                             intensity=inten, confidence=conf)
    assert len(cloud) == 3
    assert cloud.time_ns.tolist() == [100, 100, 200]
    assert cloud.beam.tolist() == [0, 2, 1]
    assert cloud.range_m.tolist() == [5.0, 7.0, 2.0]
    assert np.allclose(cloud.intensity, [0.1, 0.3, 0.5]) and np.allclose(cloud.confidence, [1.0, 0.5, 0.25])
    hi = register_returns(r, np.zeros(3), _poses(np.stack([np.eye(3)] * 2), np.zeros((2, 3))),
                          confidence=conf, config=RegistrationConfig(min_confidence=0.5))
    assert hi.range_m.tolist() == [5.0, 7.0]


def test_invalid_pose_drops_its_pings() -> None:
    traj = Trajectory(np.array([0, 10]), np.zeros((2, 3)), np.tile([0, 0, 0, 1.0], (2, 1)))
    ps = sensor_poses(traj, [5, 50], outside="skip")
    cloud = register_returns(np.full((2, 4), 3.0), np.zeros(4), ps)
    assert len(cloud) == 4 and set(cloud.time_ns.tolist()) == {5}


def test_vertical_aperture_spreading() -> None:
    cfg = RegistrationConfig(n_elevation=5, vertical_aperture_rad=math.radians(14))
    cloud = register_returns([[6.0, 8.0]], np.deg2rad([0.0, 10.0]), _poses(np.eye(3), [1, 2, 3]), config=cfg)
    assert len(cloud) == 10
    d = np.linalg.norm(cloud.xyz_m - [1, 2, 3], axis=1)
    assert np.allclose(d, np.repeat([6.0, 8.0], 5))
    assert np.allclose(cloud.elevation_rad[:5], np.deg2rad([-7, -3.5, 0, 3.5, 7]), atol=1e-7)
    assert np.allclose(cloud.xyz_m[4, 2] - 3, 6 * math.sin(math.radians(7)))  # e > 0 is below (z down)
    assert cloud.beam.tolist() == [0] * 5 + [1] * 5


def test_vectorised_matches_per_point_loop() -> None:
    rng = np.random.default_rng(1)
    P, B = 40, 96
    R = Rotation.random(P, random_state=5).as_matrix()
    t = rng.normal(size=(P, 3)) * 50
    az = np.linspace(-0.25, 0.25, B)
    r = rng.uniform(2, 11, (P, B))
    r[rng.random((P, B)) < 0.2] = np.nan
    cloud = register_returns(r, az, _poses(R, t))
    ref = [R[p] @ [r[p, b] * math.cos(az[b]), r[p, b] * math.sin(az[b]), 0] + t[p]
           for p in range(P) for b in range(B) if np.isfinite(r[p, b])]
    assert np.allclose(cloud.xyz_m, np.array(ref), atol=1e-9)


def test_register_ranges_with_beamranges_and_extrinsics() -> None:
    az = np.array([-0.1, 0.0, 0.1])
    brs = [BeamRanges(np.array([3.0, np.nan, 4.0]), np.array([10, -1, 20]), np.array([0.5, np.nan, 0.7], np.float32),
                      np.array([1, 0, 1], np.float32), az, time_ns=t) for t in (0, 10)]
    traj = Trajectory(np.array([0, 10]), np.array([[0.0, 0, 0], [1.0, 0, 0]]), np.tile([0, 0, 0, 1.0], (2, 1)))
    ext = Extrinsics([0.0, 0.0, 0.5], Rotation.from_euler("y", -90, degrees=True).as_quat())  # boresight down
    cloud = register_ranges(brs, sensor_poses(traj, [0, 10], extrinsics=ext))
    assert len(cloud) == 4
    assert np.allclose(cloud.xyz_m[0], [0.0, 3 * math.sin(-0.1), 0.5 + 3 * math.cos(-0.1)], atol=1e-12)
    assert cloud.xyz_m[2, 0] == pytest.approx(1.0)
    with pytest.raises(InputError, match="poses"):
        register_ranges(brs[:1], sensor_poses(traj, [0, 10]))


def test_pointcloud_concat_and_frames() -> None:
    c = register_returns([[5.0, 6.0]], [0.0, 0.1], _poses(np.eye(3), [1, 2, 3]))
    both = PointCloud.concat([c, c])
    assert len(both) == 4
    enu = c.to_frame("enu")
    assert np.allclose(enu.xyz_m[:, 0], c.xyz_m[:, 1]) and np.allclose(enu.xyz_m[:, 2], -c.xyz_m[:, 2])
    with pytest.raises(InputError, match="frames"):
        PointCloud.concat([c, enu])
    with pytest.raises(InputError, match="n_elevation"):
        RegistrationConfig(n_elevation=0)
