"""Output files other tools read as is: the ranges CSV (pandas, stdout), point clouds with absolute
times (PLY seconds, LAS adjusted standard GPS time), the map CSV (header first), the occupancy
schema, and unique non-1970 times for clockless Oculus captures."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import laspy
import numpy as np
import pandas as pd
import pytest
from laspy.header import GpsTimeType
from plyfile import PlyData

from sonarmap.errors import InputError
from sonarmap.mapping.occupancy import OccupancyConfig, OccupancyMap
from sonarmap.mapping.pointcloud import (
    cloud_kind,
    csv_sidecar,
    gps_adjusted_to_unix_ns,
    read_point_cloud,
    read_point_cloud_crs,
    unix_ns_to_gps_adjusted,
    write_point_cloud,
)
from sonarmap.mapping.register import PointCloud

#: 2016-07-19T14:03:05.250000000Z (a DIDSON-era time, 17 leap seconds after the GPS epoch).
T_2016 = 1_468_936_985_250_000_000


def _unix_ns(iso: str) -> int:
    return int(np.datetime64(iso, "ns").astype(np.int64))


# ---------------------------------------------------------------------- ranges CSV
def test_ranges_csv_reads_with_pandas_as_is(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    from sonarmap.cli import main
    from sonarmap.ranges.csv_rows import CSV_HEADER
    from sonarmap.io import read_pings

    pings = [test_ping_paths[4], test_ping_paths[5]]
    out = tmp_path / "r.csv"
    assert main(["ranges", *map(str, pings), "-o", str(out)]) == 0
    assert out.read_text().splitlines()[0] == ",".join(CSV_HEADER)
    df = pd.read_csv(out, parse_dates=["time"])
    assert tuple(df.columns) == CSV_HEADER and len(df) == 2 * 96
    assert str(df["time"].dtype) == "datetime64[ns, UTC]" and df["time_ns"].dtype == np.int64
    want = [p.time_ns for p in read_pings([str(p) for p in pings])]
    assert want[0] > _unix_ns("2000-01-01")  # a real clock, not 1970
    assert df["time_ns"].tolist() == [want[0]] * 96 + [want[1]] * 96
    assert (df["time"].astype("int64") == df["time_ns"]).all()  # ISO text parses to the same ns
    assert all(t.endswith("Z") and len(t) == len("2016-07-19T14:03:05.250000000Z")
               for t in pd.read_csv(out)["time"])


def test_ranges_time_column_format() -> None:
    from sonarmap.ranges.csv_rows import iso_time, write_ranges_rows
    from sonarmap.ranges import BeamRanges

    assert iso_time(T_2016) == "2016-07-19T14:03:05.250000000Z"
    assert iso_time(T_2016 + 7) == "2016-07-19T14:03:05.250000007Z"
    r = BeamRanges(range_m=np.array([4.0, np.nan]), bin=np.array([100, -1]), intensity=np.ones(2, np.float32),
                   confidence=np.ones(2, np.float32), azimuth_rad=np.array([-0.1, 0.1]))
    buf = io.StringIO()
    write_ranges_rows(csv.writer(buf), "p.png", r, time_ns=T_2016)
    rows = list(csv.reader(io.StringIO(buf.getvalue())))
    assert [row[-2:] for row in rows] == [["2016-07-19T14:03:05.250000000Z", str(T_2016)]] * 2


def test_ranges_dash_streams_to_stdout(tmp_path: Path, test_ping_paths: list[Path], capsys: pytest.CaptureFixture[str],
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from sonarmap.cli import main

    ping = str(test_ping_paths[4])
    monkeypatch.chdir(tmp_path)
    assert main(["ranges", ping, "-o", str(tmp_path / "r.csv")]) == 0
    capsys.readouterr()
    assert main(["ranges", ping, "-o", "-"]) == 0
    cap = capsys.readouterr()
    assert not (tmp_path / "-").exists()
    assert cap.out.replace("\r\n", "\n") == (tmp_path / "r.csv").read_text().replace("\r\n", "\n")
    assert "rows" in cap.err and "-> stdout" in cap.err and "rows" not in cap.out  # messages on stderr
    assert len(pd.read_csv(io.StringIO(cap.out))) == 96


# ---------------------------------------------------------------------- point clouds
@pytest.fixture()
def cloud() -> PointCloud:
    rng = np.random.default_rng(3)
    n = 200
    t = T_2016 + np.sort(rng.integers(0, 600 * 10**9, n))
    return PointCloud(
        rng.normal(size=(n, 3)) * 10, t, rng.integers(0, 96, n), rng.uniform(1, 10, n), rng.uniform(0, 1, n),
        rng.uniform(0, 1, n), np.zeros(n), sigma_m=rng.uniform(0.01, 0.05, n),
    )


def test_map_csv_reads_with_pandas_as_is(cloud: PointCloud, tmp_path: Path) -> None:
    path = tmp_path / "map.csv"
    write_point_cloud(cloud, path, frame="enu")
    assert path.read_text().splitlines()[0] == "x,y,z,time_ns,beam,range_m,intensity,confidence,elevation_rad,sigma_m"
    df = pd.read_csv(path)
    assert len(df) == len(cloud) and df["time_ns"].dtype == np.int64
    assert np.array_equal(df["time_ns"].to_numpy(), cloud.time_ns)
    assert np.array_equal(df[["x", "y", "z"]].to_numpy(), cloud.to_frame("enu").xyz_m)
    side = json.loads(csv_sidecar(path).read_text())
    assert side["frame"] == "enu" and side["kind"] == "points" and side["columns"] == list(df.columns)
    back = read_point_cloud(path)
    assert back.frame == "enu" and np.array_equal(back.time_ns, cloud.time_ns)
    # files of earlier versions (comment lines before the header) still read
    old = tmp_path / "old.csv"
    old.write_text("# sonarmap point cloud\n# frame: enu\nx,y,z,time_ns\n1.5,2,3,7\n")
    b = read_point_cloud(old)
    assert b.frame == "enu" and b.time_ns.tolist() == [7] and b.xyz_m.tolist() == [[1.5, 2.0, 3.0]]


def test_georeferenced_map_csv_has_its_crs_in_the_sidecar(cloud: PointCloud, tmp_path: Path) -> None:
    import pyproj

    from sonarmap.mapping.georef import GeoReference

    g = GeoReference.from_origin(51.3685, 3.139)
    path = tmp_path / "geo.csv"
    write_point_cloud(cloud, path, georef=g)
    df = pd.read_csv(path)
    assert np.array_equal(df[["x", "y", "z"]].to_numpy(), g.to_projected(cloud.xyz_m, "ned"))
    side = json.loads(csv_sidecar(path).read_text())
    assert side["crs"] == "EPSG:32631" and side["georef_origin_deg"][:2] == [51.3685, 3.139]
    assert read_point_cloud_crs(path) == pyproj.CRS.from_epsg(32631)
    write_point_cloud(cloud, path)  # rewritten without a CRS: the sidecar says so
    assert read_point_cloud_crs(path) is None


def test_ply_time_is_absolute_unix_seconds(cloud: PointCloud, tmp_path: Path) -> None:
    path = tmp_path / "c.ply"
    write_point_cloud(cloud, path)
    ply = PlyData.read(str(path))
    assert not any(c.startswith("time_offset_ns") for c in ply.comments)
    v = ply["vertex"]
    assert v["time"].dtype == np.float64
    want_s = cloud.time_ns // 10**9 + (cloud.time_ns % 10**9) * 1e-9
    assert np.abs(v["time"] - want_s).max() < 0.25e-6  # float64 seconds: sub-microsecond
    assert v["time"].min() == pytest.approx(T_2016 * 1e-9, abs=600)  # 2016, not seconds after the first ping
    assert np.array_equal(read_point_cloud(path).time_ns, cloud.time_ns)  # + the residual: exact


# (UTC date of the leap second, GPS - UTC from then on): IERS Bulletin C
LEAPS = [("1981-07-01", 1), ("1982-07-01", 2), ("1983-07-01", 3), ("1985-07-01", 4), ("1988-01-01", 5),
         ("1990-01-01", 6), ("1991-01-01", 7), ("1992-07-01", 8), ("1993-07-01", 9), ("1994-07-01", 10),
         ("1996-01-01", 11), ("1997-07-01", 12), ("1999-01-01", 13), ("2006-01-01", 14), ("2009-01-01", 15),
         ("2012-07-01", 16), ("2015-07-01", 17), ("2017-01-01", 18)]


def test_gps_time_accounts_for_every_leap_second() -> None:
    gps_epoch = _unix_ns("1980-01-06")
    for date, n in LEAPS:
        t = _unix_ns(date)
        before, after = np.array([t - 10**9]), np.array([t])
        assert unix_ns_to_gps_adjusted(after)[0] == (t - gps_epoch) / 1e9 + n - 1e9
        assert unix_ns_to_gps_adjusted(before)[0] == (t - 10**9 - gps_epoch) / 1e9 + n - 1 - 1e9
        for x in (before, after):
            assert gps_adjusted_to_unix_ns(unix_ns_to_gps_adjusted(x))[0] == x[0]
    # GPS week 1930 starts 2017-01-01T00:00:00 GPS, 18 s before the UTC midnight
    assert unix_ns_to_gps_adjusted(np.array([_unix_ns("2017-01-01")]))[0] == 1930 * 604800 + 18 - 1e9
    assert unix_ns_to_gps_adjusted(np.array([T_2016]))[0] == 1_468_936_985.25 - 315_964_800 + 17 - 1e9


def test_las_gps_time_is_adjusted_standard(cloud: PointCloud, tmp_path: Path) -> None:
    path = tmp_path / "c.las"
    one = cloud.select(np.array([0]))
    one = PointCloud(one.xyz_m, [T_2016], one.beam, one.range_m, one.intensity, one.confidence, one.elevation_rad)
    write_point_cloud(one, path)
    las = laspy.read(str(path))
    assert las.header.global_encoding.gps_time_type == GpsTimeType.STANDARD
    assert float(las.gps_time[0]) == pytest.approx(152_972_202.25, abs=1e-6)  # 2016-07-19T14:03:05.25Z
    write_point_cloud(cloud, path)
    las = laspy.read(str(path))
    assert np.abs(las.gps_time - unix_ns_to_gps_adjusted(cloud.time_ns)).max() == 0
    assert np.array_equal(read_point_cloud(path).time_ns, cloud.time_ns)
    # another tool's LAS without the time_ns extra bytes: gps_time converted back to Unix time
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.global_encoding.gps_time_type = GpsTimeType.STANDARD
    plain = laspy.LasData(hdr)
    plain.x, plain.y, plain.z = cloud.xyz_m.T
    plain.gps_time = unix_ns_to_gps_adjusted(cloud.time_ns)
    plain.write(str(tmp_path / "plain.las"))
    t = read_point_cloud(tmp_path / "plain.las").time_ns
    assert np.abs(t - cloud.time_ns).max() < 100  # float64 adjusted GPS seconds: ~30 ns


def _occupancy_map() -> OccupancyMap:
    m = OccupancyMap(OccupancyConfig(resolution_m=0.25, dims=3))
    az = np.linspace(-0.3, 0.3, 21)
    r = np.full((1, 21), 4.0)
    from sonarmap.mapping.poses import SensorPoses

    poses = SensorPoses(np.zeros(1, np.int64), np.eye(3)[None], np.array([[0.0, 0.0, 2.0]]),
                        np.array([[0.0, 0.0, 0.0, 1.0]]), np.ones(1, bool))
    for _ in range(2):
        m.integrate(r, az, poses, min_range_m=0.5, max_range_m=6.0, pd=0.9, pfa=0.05)
    return m


def test_occupancy_files_have_their_own_schema(tmp_path: Path) -> None:
    m = _occupancy_map()
    cells = m.to_point_cloud()
    assert len(cells) > 0 and cloud_kind(cells) == "occupancy"
    lo_map, seen = m.logodds_at(cells.xyz_m)
    assert seen.all()
    write_point_cloud(cells, tmp_path / "occ.ply")
    ply = PlyData.read(str(tmp_path / "occ.ply"))
    v = ply["vertex"]
    assert v.data.dtype.names == ("x", "y", "z", "p_occupied", "log_odds") and "kind occupancy" in ply.comments
    assert np.array_equal(v["p_occupied"], cells.confidence)
    assert np.allclose(v["log_odds"], lo_map, atol=1e-4) and np.all(v["log_odds"] > 0)
    write_point_cloud(cells, tmp_path / "occ.csv")
    df = pd.read_csv(tmp_path / "occ.csv")
    assert list(df.columns) == ["x", "y", "z", "p_occupied", "log_odds"]
    assert np.allclose(df["p_occupied"], 1 / (1 + np.exp(-df["log_odds"])), atol=1e-6)
    write_point_cloud(cells, tmp_path / "occ.las")
    las = laspy.read(str(tmp_path / "occ.las"))
    assert {"p_occupied", "log_odds"} <= set(las.point_format.extra_dimension_names)
    assert "time_ns" not in set(las.point_format.dimension_names)
    for sfx in ("ply", "csv", "las"):  # read back as to_point_cloud makes it
        back = read_point_cloud(tmp_path / f"occ.{sfx}")
        assert np.array_equal(back.confidence, cells.confidence) and cloud_kind(back) == "occupancy"
    # explicit kind: the point schema on request; a cloud of returns is never taken for a map
    write_point_cloud(cells, tmp_path / "pts.ply", kind="points")
    assert "p_occupied" not in PlyData.read(str(tmp_path / "pts.ply"))["vertex"].data.dtype.names
    with pytest.raises(InputError, match="kind"):
        write_point_cloud(cells, tmp_path / "x.ply", kind="voxels")
    assert cloud_kind(PointCloud.empty()) == "points"
    k = len(cells)
    plain = PointCloud(cells.xyz_m, np.zeros(k, np.int64), np.full(k, -1), np.full(k, np.nan), np.ones(k), np.ones(k),
                       np.zeros(k))
    assert cloud_kind(plain) == "points"  # x, y, z only (another tool's file): confidence 1 is not a probability


def test_cli_map_grid_writes_the_occupancy_schema(tmp_path: Path, test_ping_paths: list[Path]) -> None:
    from sonarmap.cli import main
    from sonarmap.io.pngjson import time_ns_from_stem

    paths = [test_ping_paths[i] for i in (4, 5, 9)]
    ts = [time_ns_from_stem(p.stem) for p in paths]
    poses = tmp_path / "poses.csv"
    poses.write_text(f"time_ns,x,y,z,qx,qy,qz,qw\n{ts[0] - 10**9},0,0,2,0,0,0,1\n{ts[-1] + 10**9},0,0,2,0,0,0,1\n")
    out = tmp_path / "grid.ply"
    assert main(["map", *map(str, paths), "--poses", str(poses), "-o", str(out), "--grid", "0.1", "-q"]) == 0
    names = PlyData.read(str(out))["vertex"].data.dtype.names
    assert names == ("x", "y", "z", "p_occupied", "log_odds")
    pts = tmp_path / "pts.csv"
    assert main(["map", *map(str, paths), "--poses", str(poses), "-o", str(pts), "-q"]) == 0
    df = pd.read_csv(pts)
    assert "time_ns" in df.columns and set(df["time_ns"]) <= set(ts)


# ---------------------------------------------------------------------- Oculus clock
def test_oculus_raw_capture_times_are_unique_and_not_1970(data_dir: Path) -> None:
    from sonarmap.io import oculus, read_pings

    p = data_dir / "oculus" / "three_pings_8bit.raw"
    pings = list(read_pings(p))
    t = [x.time_ns for x in pings]
    mtime = p.stat().st_mtime_ns
    assert t == [mtime, mtime + 100_000_000, mtime + 200_000_000]  # file time + order, 0.1 s apart
    assert len(set(t)) == 3 and min(t) > _unix_ns("2000-01-01")
    assert all(x.meta["time_source"] == "file_mtime+order" for x in pings)
    t0 = T_2016
    given = list(read_pings(p, start_time_ns=t0, rate_hz=16.0))
    assert [x.time_ns for x in given] == [t0, t0 + 62_500_000, t0 + 125_000_000]
    assert given[0].meta["time_source"] == "start_time_ns+rate_hz"
    only_start = list(oculus.iter_pings(p, start_time_ns=t0))
    assert [x.time_ns for x in only_start] == [t0, t0 + 10**8, t0 + 2 * 10**8]
    assert only_start[2].meta["time_source"] == "start_time_ns+order"
    s = oculus.summary(p)
    assert s["time_source"] == "file_mtime+order" and s["ping_interval_s"] == pytest.approx(0.1)
    assert s["duration_s"] == pytest.approx(0.2)
    for bad in ({"rate_hz": 0.0}, {"rate_hz": float("nan")}, {"start_time_ns": -5}, {"start_time_ns": 1.5e18}):
        with pytest.raises(InputError, match=next(iter(bad))):
            list(read_pings(p, **bad))


def test_oculus_times_make_a_unique_ping_time_index(data_dir: Path) -> None:
    import xarray as xr

    from sonarmap.io import read_pings

    pings = list(read_pings(data_dir / "oculus" / "three_pings_8bit.raw"))
    ds = xr.Dataset(coords={"ping_time": np.array([x.datetime64 for x in pings])})
    assert ds.indexes["ping_time"].is_unique
    assert ds.sel(ping_time=pings[1].datetime64).sizes.get("ping_time", 0) == 0  # one ping, a scalar selection


@pytest.mark.parametrize("cmd", ["ranges", "fit", "segment"])
def test_an_output_of_the_wrong_kind_fails_before_any_ping_is_processed(
        cmd: str, test_ping_paths: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Before: 'sonarmap ranges X -o DIR' processed every ping, then failed ('DIR: cannot write: Is a
    directory'); 'sonarmap segment X -o FILE' said '[Errno 17] File exists: ...'. Now one line
    naming the output, before the progress bar."""
    from sonarmap.cli import main

    afile = tmp_path / "afile"
    afile.write_text("x")
    out = afile if cmd == "segment" else tmp_path
    assert main([cmd, str(test_ping_paths[0]), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "━" not in err and "Errno" not in err
    assert (f"{afile}: exists and is not a directory" if cmd == "segment" else f"{tmp_path}: is a directory") in err
