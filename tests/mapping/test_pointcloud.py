"""Point-cloud files read back with identical coordinates (sonarmap.mapping.pointcloud)."""

from __future__ import annotations

import laspy
import numpy as np
import pytest
from plyfile import PlyData

from sonarmap.errors import InputError
from sonarmap.mapping.pointcloud import read_point_cloud, write_point_cloud
from sonarmap.mapping.register import PointCloud


@pytest.fixture()
def cloud() -> PointCloud:
    rng = np.random.default_rng(7)
    n = 1000
    xyz = rng.normal(size=(n, 3)) * [20, 20, 3] + [100, -50, 10]
    return PointCloud(
        xyz, 1_700_000_000_000_000_000 + rng.integers(0, 10**9, n), rng.integers(0, 96, n),
        rng.uniform(2, 11, n), rng.uniform(0, 1, n), rng.uniform(0, 1, n), rng.uniform(-0.1, 0.1, n),
    )


def test_ply_binary_float32_round_trip(cloud: PointCloud, tmp_path) -> None:
    path = tmp_path / "c.ply"
    assert write_point_cloud(cloud, path) == "ply"
    ply = PlyData.read(str(path))
    assert not ply.text and ply["vertex"]["x"].dtype == np.float32
    v = ply["vertex"]
    xyz32 = cloud.xyz_m.astype(np.float32)
    assert np.array_equal(v["x"], xyz32[:, 0]) and np.array_equal(v["y"], xyz32[:, 1])
    assert np.array_equal(v["z"], xyz32[:, 2])
    assert np.array_equal(v["beam"], cloud.beam) and np.array_equal(v["range"], cloud.range_m)
    back = read_point_cloud(path)
    assert np.array_equal(back.xyz_m, xyz32.astype(np.float64))
    assert np.array_equal(back.confidence, cloud.confidence)
    assert np.array_equal(back.time_ns, cloud.time_ns)  # seconds after an offset stamp: exact


def test_ply_enu_frame(cloud: PointCloud, tmp_path) -> None:
    path = tmp_path / "enu.ply"
    write_point_cloud(cloud, path, frame="enu")
    back = read_point_cloud(path)
    assert back.frame == "enu"
    assert np.allclose(back.to_frame("ned").xyz_m, cloud.xyz_m, atol=1e-4)


def test_las14_round_trip(cloud: PointCloud, tmp_path) -> None:
    path = tmp_path / "c.las"
    assert write_point_cloud(cloud, path) == "las"
    las = laspy.read(str(path))
    assert str(las.header.version) == "1.4" and las.header.point_format.id == 6
    scale = las.header.scales
    q = np.rint((cloud.xyz_m - las.header.offsets) / scale) * scale + las.header.offsets
    got = np.stack([las.x, las.y, las.z], axis=1)
    assert np.array_equal(np.asarray(las.X), np.rint((cloud.xyz_m[:, 0] - las.header.offsets[0]) / scale[0]).astype(np.int32))
    assert np.allclose(got, q, rtol=0, atol=1e-9)
    assert np.max(np.abs(got - cloud.xyz_m)) <= scale[0] / 2 + 1e-12
    back = read_point_cloud(path)
    assert np.array_equal(back.xyz_m, got)
    assert np.array_equal(back.time_ns, cloud.time_ns) and np.array_equal(back.beam, cloud.beam)
    assert np.array_equal(back.range_m, cloud.range_m)


def test_csv_exact_round_trip(cloud: PointCloud, tmp_path) -> None:
    path = tmp_path / "c.csv"
    write_point_cloud(cloud, path)
    back = read_point_cloud(path)
    assert np.array_equal(back.xyz_m, cloud.xyz_m)
    assert np.array_equal(back.time_ns, cloud.time_ns)
    assert np.array_equal(back.intensity, cloud.intensity) and np.array_equal(back.beam, cloud.beam)


def test_empty_cloud_and_bad_format(tmp_path) -> None:
    empty = PointCloud.empty()
    for sfx in ("ply", "las", "csv"):
        write_point_cloud(empty, tmp_path / f"e.{sfx}")
        assert len(read_point_cloud(tmp_path / f"e.{sfx}")) == 0
    with pytest.raises(InputError, match="suffix"):
        write_point_cloud(empty, tmp_path / "e.xyz")
    with pytest.raises(InputError, match="format"):
        write_point_cloud(empty, tmp_path / "e.ply", format="obj")


# ---------------------------------------------------------------------- `sonarmap map`
def _cli_inputs(tmp_path, test_ping_paths, *, span_pad_ns: int = 10**9):
    from sonarmap.io.pngjson import time_ns_from_stem

    paths = [test_ping_paths[i] for i in (4, 5, 9)]  # three pings with returns
    ts = [time_ns_from_stem(p.stem) for p in paths]
    poses = tmp_path / "poses.csv"
    poses.write_text(
        "# frame: ned\ntime_ns,x,y,z,qx,qy,qz,qw\n"
        f"{ts[0] - span_pad_ns},0,0,2,0,0,0,1\n{ts[-1] + span_pad_ns},0,0,2,0,0,0,1\n"
    )
    return paths, ts, poses


def test_cli_map_registers_pipeline_returns(tmp_path, test_ping_paths, capsys) -> None:
    from sonarmap.cli import main
    from sonarmap.io.pngjson import read_png_ping
    from sonarmap.pipeline import process_ping

    paths, ts, poses = _cli_inputs(tmp_path, test_ping_paths)
    mount = tmp_path / "mount.json"
    mount.write_text('{"translation_m": [0.5, 0.0, 0.0], "rotation_xyzw": [0, 0, 0, 1]}')
    out = tmp_path / "map.ply"
    args = ["map", *map(str, paths), "--poses", str(poses), "--extrinsics", str(mount), "-o", str(out), "-q"]
    assert main(args) == 0
    cloud = read_point_cloud(out)
    prods = [process_ping(read_png_ping(p)) for p in paths]
    assert len(cloud) == sum(p.ranges.n_returns for p in prods) > 0
    # sensor at (0.5, 0, 2) looking north: distance to it equals the measured range
    d = np.linalg.norm(cloud.xyz_m - [0.5, 0.0, 2.0], axis=1)
    assert np.allclose(d, cloud.range_m, atol=1e-5)
    assert set(cloud.time_ns.tolist()) <= set(ts)
    # occupancy grid: occupied cells + dense array
    grid = tmp_path / "grid.las"
    arr = tmp_path / "grid.npz"
    assert main(["map", *map(str, paths), "--poses", str(poses), "-o", str(grid), "--grid", "0.1",
                 "--grid-array", str(arr), "-q"]) == 0
    occ = read_point_cloud(grid)
    z = np.load(arr)
    assert len(occ) > 0 and (z["logodds"][z["observed"]] > 0).sum() == len(occ)
    lo, hi = float(np.log(0.1192 / 0.8808)), float(np.log(0.971 / 0.029))
    default = z["logodds"][z["observed"]]
    assert default.min() < lo - 0.5 or default.max() > hi + 0.5  # the default clamps are wider
    # --clamp: OctoMap's bounds cap the map; a malformed value is a usage error
    assert main(["map", *map(str, paths), "--poses", str(poses), "-o", str(grid), "--grid", "0.1",
                 "--grid-array", str(arr), "--clamp", "0.1192,0.971", "-q"]) == 0
    z = np.load(arr)
    octo = z["logodds"][z["observed"]]
    assert octo.min() >= lo - 1e-5 and octo.max() <= hi + 1e-5 and octo.size == default.size
    assert main(["map", *map(str, paths), "--poses", str(poses), "-o", str(grid), "--grid", "0.1",
                 "--clamp", "0.6,0.9", "-q"]) != 0
    # --spread with --grid: rays over the vertical aperture observe cells above and below the plane
    assert main(["map", *map(str, paths), "--poses", str(poses), "-o", str(grid), "--grid", "0.1",
                 "--grid-array", str(arr), "--spread", "3", "-q"]) == 0
    spread = np.load(arr)
    assert spread["observed"].sum() > 2 * default.size and spread["logodds"].shape[2] > 1
    assert main(["map", *map(str, paths), "--poses", str(poses), "-o", str(grid), "--grid", "0.1",
                 "--min-confidence", "0.5", "-q"]) != 0


def test_cli_map_outside_trajectory_error_or_skip(tmp_path, test_ping_paths, capsys) -> None:
    from sonarmap.cli import main

    paths, ts, _ = _cli_inputs(tmp_path, test_ping_paths)
    short = tmp_path / "short.csv"
    short.write_text(f"time_ns,x,y,z,qx,qy,qz,qw\n{ts[0] - 10},0,0,0,0,0,0,1\n{ts[1] + 10},1,0,0,0,0,0,1\n")
    out = tmp_path / "m.csv"
    assert main(["map", *map(str, paths), "--poses", str(short), "-o", str(out), "-q"]) == 1
    err = capsys.readouterr().err
    assert "outside the trajectory span" in err and err.count("\n") == 1
    assert err.startswith(f"sonarmap: error: {short}: 1 of 3 ping time(s)") and "--outside skip" in err, err
    assert main(["map", *map(str, paths), "--poses", str(short), "-o", str(out), "--outside", "skip"]) == 0
    assert "1 skipped outside the trajectory" in capsys.readouterr().err
    assert set(read_point_cloud(out).time_ns.tolist()) <= set(ts[:2])
