"""Frames, trajectories, interpolation and extrinsics (sonarmap.mapping.frames / poses)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sonarmap.errors import DataFormatError, InputError
from sonarmap.mapping import frames
from sonarmap.mapping.poses import (
    Extrinsics,
    Trajectory,
    load_extrinsics,
    parse_time_s,
    read_trajectory_csv,
    save_extrinsics,
    sensor_poses,
    write_trajectory_csv,
)
from sonarmap.ping import Pose

T0 = 1_700_000_000_000_000_000


def _random_traj(rng: np.random.Generator, n: int = 20) -> Trajectory:
    t = T0 + np.cumsum(rng.integers(50_000_000, 150_000_000, n))
    return Trajectory(t, rng.normal(size=(n, 3)) * 10, Rotation.random(n, random_state=1).as_quat())


def test_enu_ned_point_conversion_both_ways() -> None:
    p_enu = np.array([1.0, 2.0, 3.0])  # 1 m east, 2 m north, 3 m up
    assert np.array_equal(frames.enu_to_ned(p_enu), [2.0, 1.0, -3.0])
    assert np.array_equal(frames.ned_to_enu([2.0, 1.0, -3.0]), p_enu)
    assert np.array_equal(frames.flu_to_frd([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0])
    assert np.array_equal(frames.frd_to_flu([1.0, -2.0, -3.0]), [1.0, 2.0, 3.0])


def test_ros_pose_facing_east_is_heading_90_in_ned() -> None:
    # REP-103: identity orientation = body x along ENU x = east.
    p, q = frames.pose_enu_flu_to_ned_frd([10.0, 20.0, -5.0], [0, 0, 0, 1])
    assert np.allclose(p, [20.0, 10.0, 5.0])
    R = Rotation.from_quat(q)
    assert np.allclose(R.apply([1, 0, 0]), [0, 1, 0])  # forward -> east
    assert np.allclose(R.apply([0, 1, 0]), [-1, 0, 0])  # starboard -> south
    assert np.allclose(R.apply([0, 0, 1]), [0, 0, 1])  # down -> down
    yaw, pitch, roll = R.as_euler("ZYX", degrees=True)
    assert yaw == pytest.approx(90.0) and abs(pitch) < 1e-9 and abs(roll) < 1e-9


def test_pose_conversion_round_trip_both_ways() -> None:
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(50, 3))
    q = Rotation.random(50, random_state=2).as_quat()
    p2, q2 = frames.pose_ned_frd_to_enu_flu(*frames.pose_enu_flu_to_ned_frd(pos, q))
    assert np.allclose(p2, pos, atol=1e-12)
    assert np.allclose(Rotation.from_quat(q2).as_matrix(), Rotation.from_quat(q).as_matrix(), atol=1e-12)
    # A point expressed in ENU/FLU maps to the same physical point through NED/FRD.
    body_flu = rng.normal(size=(50, 3))
    world_enu = Rotation.from_quat(q).apply(body_flu) + pos
    pn, qn = frames.pose_enu_flu_to_ned_frd(pos, q)
    world_ned = Rotation.from_quat(qn).apply(frames.flu_to_frd(body_flu)) + pn
    assert np.allclose(frames.ned_to_enu(world_ned), world_enu, atol=1e-12)


def test_sensor_body_world_round_trip_1e9() -> None:
    rng = np.random.default_rng(3)
    traj = _random_traj(rng)
    ext = Extrinsics.from_rpy_deg([0.4, -0.1, 0.25], 90.0, 20.0, 90.0)
    times = np.sort(rng.integers(traj.span_ns[0], traj.span_ns[1], 30))
    sp = sensor_poses(traj, times, extrinsics=ext)
    bp = traj.interpolate(times)
    p_s = rng.normal(size=(30, 3)) * 8
    p_b = frames.transform_points(ext.rotation, ext.translation_m, p_s)
    p_w = frames.transform_points(bp.rotation, bp.translation_m, p_b)
    assert np.allclose(frames.transform_points(sp.rotation, sp.translation_m, p_s), p_w, atol=1e-9)
    Rbw, tbw = frames.invert_transform(bp.rotation, bp.translation_m)
    Rsb, tsb = frames.invert_transform(ext.rotation, ext.translation_m)
    back = frames.transform_points(Rsb, tsb, frames.transform_points(Rbw, tbw, p_w))
    assert np.max(np.abs(back - p_s)) < 1e-9


def test_interpolation_at_and_between_stamps() -> None:
    t = T0 + np.array([0, 1_000_000_000, 3_000_000_000])
    pos = np.array([[0.0, 0, 0], [1.0, 2.0, 0], [1.0, 2.0, 4.0]])
    q = Rotation.from_euler("z", [[0], [90], [90]], degrees=True).as_quat()
    traj = Trajectory(t, pos, q)
    at = traj.interpolate(t)
    assert np.allclose(at.translation_m, pos, atol=1e-12)
    assert np.allclose(at.rotation, Rotation.from_quat(q).as_matrix(), atol=1e-12)
    mid = traj.interpolate([T0 + 500_000_000, T0 + 2_500_000_000])
    assert np.allclose(mid.translation_m, [[0.5, 1.0, 0], [1.0, 2.0, 3.0]], atol=1e-12)
    yaw = Rotation.from_matrix(mid.rotation).as_euler("ZYX", degrees=True)[:, 0]
    assert yaw == pytest.approx([45.0, 90.0], abs=1e-9)  # Slerp: half of 90 degrees


def test_outside_span_error_or_skip_with_count() -> None:
    traj = Trajectory(T0 + np.array([0, 10]), np.zeros((2, 3)), np.tile([0, 0, 0, 1.0], (2, 1)))
    times = T0 + np.array([-5, 0, 5, 11, 20])
    with pytest.raises(InputError, match="3 of 5 ping time"):
        traj.interpolate(times)
    sp = traj.interpolate(times, outside="skip")
    assert sp.n_skipped == 3 and sp.valid.tolist() == [False, True, True, False, False]
    assert np.isnan(sp.translation_m[0]).all() and np.isfinite(sp.translation_m[1]).all()
    assert traj.interpolate(times, outside="skip", tolerance_ns=1).n_skipped == 2
    assert traj.interpolate(times, outside="skip", tolerance_ns=10).n_skipped == 0
    with pytest.raises(InputError, match="outside"):
        traj.interpolate(times, outside="clamp")  # type: ignore[arg-type]


def test_trajectory_csv_round_trip_ned_and_enu(tmp_path) -> None:
    rng = np.random.default_rng(4)
    traj = _random_traj(rng, 12)
    for frame in ("ned", "enu"):
        path = tmp_path / f"traj_{frame}.csv"
        write_trajectory_csv(traj, path, frame=frame)
        back = read_trajectory_csv(path)
        assert np.array_equal(back.time_ns, traj.time_ns)
        assert np.allclose(back.position_m, traj.position_m, atol=1e-12)
        assert np.allclose(
            Rotation.from_quat(back.orientation_xyzw).as_matrix(),
            Rotation.from_quat(traj.orientation_xyzw).as_matrix(),
            atol=1e-12,
        )
    # the frame argument overrides the comment: reading ENU data as NED swaps x and y
    forced = read_trajectory_csv(tmp_path / "traj_enu.csv", frame="ned")
    assert np.allclose(forced.position_m[:, 0], traj.position_m[:, 1])


def test_trajectory_csv_time_s_exact_and_errors(tmp_path) -> None:
    p = tmp_path / "t.csv"
    p.write_text("time_s,x,y,z,qx,qy,qz,qw,extra\n1700000000.000000001,0,0,0,0,0,0,1,a\n1700000000.5,1,0,0,0,0,0,2,b\n")
    tr = read_trajectory_csv(p)
    assert tr.time_ns.tolist() == [1_700_000_000_000_000_001, 1_700_000_000_500_000_000]
    assert np.allclose(tr.orientation_xyzw[1], [0, 0, 0, 1])  # normalised
    assert parse_time_s("12.3456789019") == 12_345_678_902
    bad = tmp_path / "bad.csv"
    bad.write_text("time_ns,x,y,qx,qy,qz,qw\n1,0,0,0,0,0,1\n")
    with pytest.raises(DataFormatError, match="missing column.*z"):
        read_trajectory_csv(bad)
    dup = tmp_path / "dup.csv"
    dup.write_text("time_ns,x,y,z,qx,qy,qz,qw\n5,0,0,0,0,0,0,1\n5,1,0,0,0,0,0,1\n")
    with pytest.raises(DataFormatError, match="duplicate"):
        read_trajectory_csv(dup)
    nonnum = tmp_path / "nn.csv"
    nonnum.write_text("time_ns,x,y,z,qx,qy,qz,qw\n5,0,zz,0,0,0,0,1\n")
    with pytest.raises(DataFormatError, match="row 2"):
        read_trajectory_csv(nonnum)


def test_unsorted_rows_are_sorted() -> None:
    tr = Trajectory(np.array([3, 1, 2]), np.array([[3.0, 0, 0], [1, 0, 0], [2, 0, 0]]), np.tile([0, 0, 0, 1.0], (3, 1)))
    assert tr.time_ns.tolist() == [1, 2, 3] and tr.position_m[:, 0].tolist() == [1, 2, 3]


def test_from_poses_converts_enu() -> None:
    poses = [Pose([1.0, 2.0, 3.0], [0, 0, 0, 1], "enu"), Pose([2.0, 1.0, -3.0], [0, 0, 0, 1], "ned")]
    tr = Trajectory.from_poses([0, 1], poses)
    assert np.allclose(tr.position_m, [[2.0, 1.0, -3.0], [2.0, 1.0, -3.0]])


def test_extrinsics_json_quaternion_rpy_and_flu(tmp_path) -> None:
    ext = Extrinsics.from_rpy_deg([0.5, 0.0, 0.3], 10.0, -20.0, 30.0)
    path = tmp_path / "mount.json"
    save_extrinsics(ext, path)
    back = load_extrinsics(path)
    assert np.allclose(back.rotation, ext.rotation, atol=1e-12)
    assert np.allclose(back.translation_m, [0.5, 0.0, 0.3])
    rpy = tmp_path / "rpy.json"
    rpy.write_text(json.dumps({"translation_m": [0.5, 0, 0.3], "rotation_rpy_deg": [10, -20, 30]}))
    assert np.allclose(load_extrinsics(rpy).rotation, ext.rotation, atol=1e-12)
    # FLU: a sensor 0.2 m to the left and 0.1 m up of the body origin, pointing left
    flu = tmp_path / "flu.json"
    q_left = Rotation.from_euler("z", 90, degrees=True).as_quat().tolist()
    flu.write_text(json.dumps({"frame": "flu", "translation_m": [0, 0.2, 0.1], "rotation_xyzw": q_left}))
    e = load_extrinsics(flu)
    assert np.allclose(e.translation_m, [0, -0.2, -0.1])
    assert np.allclose(e.rotation @ [1, 0, 0], [0, -1, 0], atol=1e-12)  # boresight to port (-y in FRD)
    badj = tmp_path / "bad.json"
    badj.write_text('{"translation_m": [1, 2]}')
    with pytest.raises(DataFormatError, match="translation_m"):
        load_extrinsics(badj)
    with pytest.raises(DataFormatError, match="cannot read"):
        load_extrinsics(tmp_path / "missing.json")


@pytest.mark.parametrize(("content", "message"), [(b'{"translation": [0, 0', "invalid JSON at line 1"),
                                                  (b'{"name": "\xff"}', "not UTF-8 text"),
                                                  (b"[" * 100_000, "nested too deeply")])
def test_bad_extrinsics_json_is_one_named_error(tmp_path, content, message) -> None:
    path = tmp_path / "mount.json"
    path.write_bytes(content)
    with pytest.raises(DataFormatError, match=message) as exc:
        load_extrinsics(path)
    assert "mount.json" in str(exc.value)
