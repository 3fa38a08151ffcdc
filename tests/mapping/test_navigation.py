"""Poses from a recording's own navigation, fixed mounts, and georeferenced ``sonarmap map`` outputs."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from sonarmap.cli import main
from sonarmap.errors import InputError
from sonarmap.mapping.georef import GeoReference
from sonarmap.mapping.navigation import missing_navigation, navigation_origin, navigation_pose, static_pose
from sonarmap.ping import Ping

LAT, LON = 51.3685, 3.139


def _ping(meta: dict) -> Ping:
    from sonarmap.geometry import SonarGeometry

    g = SonarGeometry(azimuth_rad=np.linspace(-0.2, 0.2, 8), range_m=np.linspace(1, 4, 16))
    return Ping(np.zeros((16, 8), np.float32), g, source="x#0", meta=meta)


def test_navigation_pose_position_and_attitude() -> None:
    first = _ping({"latitude_deg": LAT, "longitude_deg": LON, "heading_deg": 0.0})
    g = navigation_origin(first)
    assert g.epsg == 32631
    # 0.001 deg of latitude north (~111.2 m), 4 m deep, heading 90 (east), pitch 5 bow up
    p = _ping({"latitude_deg": LAT + 0.001, "longitude_deg": LON, "depth_m": 4.0, "heading_deg": 90.0,
               "pitch_deg": 5.0, "roll_deg": 0.0})
    pose = navigation_pose(p, g)
    n, e, d = pose.position_m
    assert 111.0 < n < 111.5 and abs(e) < 0.01 and abs(d - 4.0) < 0.01
    from scipy.spatial.transform import Rotation

    fwd = Rotation.from_quat(pose.orientation_xyzw).apply([1.0, 0.0, 0.0])
    # heading 90: forward points east; pitch 5 deg bow up: forward rises (z down is negative)
    assert fwd[1] == pytest.approx(np.cos(np.radians(5)), abs=1e-9)
    assert fwd[2] == pytest.approx(-np.sin(np.radians(5)), abs=1e-9)


def test_missing_navigation_says_what_is_missing() -> None:
    assert missing_navigation(_ping({"latitude_deg": LAT, "longitude_deg": LON, "heading_deg": 1.0})) is None
    why = missing_navigation(_ping({"heading_deg": 0.0}))
    assert why is not None and "latitude" in why and "longitude" in why and "heading" not in why
    with pytest.raises(InputError, match="x#0: no navigation"):
        navigation_pose(_ping({"latitude_deg": float("nan"), "longitude_deg": LON, "heading_deg": 0.0}),
                        GeoReference.from_origin(LAT, LON))
    assert np.allclose(static_pose().position_m, 0) and np.allclose(static_pose().orientation_xyzw, [0, 0, 0, 1])


def _aris_with_navigation(data_dir: Path, tmp_path: Path) -> Path:
    from sonarmap.io.aris import FRAME_HEADER_DTYPE

    raw = bytearray((data_dir / "aris" / "sample.aris").read_bytes())
    frame = 1024 + 48 * 2000
    for k, off in enumerate(range(1024, len(raw), frame)):
        hdr = np.frombuffer(bytes(raw[off : off + 1024]), FRAME_HEADER_DTYPE, count=1).copy()
        hdr["Latitude"] = LAT + k * 1e-5
        hdr["Longitude"] = LON
        hdr["Heading"] = 30.0
        hdr["Depth"] = 2.0
        raw[off : off + 1024] = hdr.tobytes()
    p = tmp_path / "nav.aris"
    p.write_bytes(bytes(raw))
    return p


def test_map_without_pose_fails_before_processing(data_dir: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["map", str(data_dir / "aris" / "sample.aris"), "-o", str(tmp_path / "m.ply")])
    err = capsys.readouterr().err
    assert rc == 1
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "latitude / longitude" in lines[0] and "--static" in lines[0], err
    assert not (tmp_path / "m.ply").exists()


def test_map_uses_the_header_navigation(data_dir: Path, tmp_path: Path) -> None:
    import laspy
    import pyproj
    import rasterio

    src = _aris_with_navigation(data_dir, tmp_path)
    las, tif = tmp_path / "m.las", tmp_path / "m.tif"
    assert main(["map", str(src), "-o", str(las), "--geotiff", str(tif), "-q"]) == 0
    cloud = laspy.read(las)
    crs = cloud.header.parse_crs()
    assert crs is not None and pyproj.CRS(crs).to_epsg() == 32631
    e0, n0 = pyproj.Transformer.from_crs(4326, 32631, always_xy=True).transform(LON, LAT)
    # the ARIS window is 15-23 m ahead; heading 30 deg: the points lie north-north-east of the fix
    de, dn = np.asarray(cloud.x) - e0, np.asarray(cloud.y) - n0
    dist = np.hypot(de, dn)
    assert len(dist) > 100 and 14.0 < np.median(dist) < 24.0
    bearing = np.degrees(np.arctan2(np.median(de), np.median(dn)))
    assert 15.0 < bearing < 45.0
    with rasterio.open(tif) as r:
        assert r.crs.to_epsg() == 32631
        west, north = r.transform.c, r.transform.f
        assert west <= np.asarray(cloud.x).min() + 1.0 and north >= np.asarray(cloud.y).max() - 1.0
        assert abs(west - e0) < 40 and abs(north - n0) < 40


def test_crs_override(data_dir: Path, tmp_path: Path) -> None:
    import laspy

    src = _aris_with_navigation(data_dir, tmp_path)
    las = tmp_path / "m.las"
    assert main(["map", str(src), "-o", str(las), "--crs", "EPSG:25831", "-q"]) == 0
    assert laspy.read(las).header.parse_crs().to_epsg() == 25831


def _static_inputs(data_dir: Path, tmp_path: Path) -> dict[str, Path]:
    from ddf_writer import write_ddf

    from sonarmap.io import read_pings
    from sonarmap.store import write_survey
    from sonarmap.io.rosbag import write_bag

    aris = list(read_pings(data_dir / "aris" / "sample.aris"))[:2]
    out = {
        "aris": data_dir / "aris" / "sample.aris",
        "oculus": data_dir / "oculus" / "three_pings_8bit.raw",
        "pngjson": tmp_path / "didson",
    }
    out["pngjson"].mkdir()
    for png in sorted((data_dir / "didson" / "test").glob("*_raw.png"))[4:6]:
        shutil.copy2(png, out["pngjson"])
        shutil.copy2(png.with_name(png.name.replace("_raw.png", ".json")), out["pngjson"])
    rng = np.random.default_rng(0)
    frames = []
    for _ in range(2):  # speckle with a bright surface across the beams
        f = rng.rayleigh(12.0, (512, 96)).clip(0, 255).astype(np.uint8)
        f[300:304] = 230
        frames.append(f)
    write_ddf(tmp_path / "a.ddf", frames)
    out["ddf"] = tmp_path / "a.ddf"
    write_bag(aris, tmp_path / "a.bag", version=1)
    out["rosbag"] = tmp_path / "a.bag"
    write_survey(aris, tmp_path / "a.zarr")
    out["zarr"] = tmp_path / "a.zarr"
    k = data_dir / "kongsberg" / "0077_20221109_123655_Belgica.all"
    from sonarmap.io import FORMAT_MODULES

    if "kongsberg" in FORMAT_MODULES and (Path(__file__).parents[2] / "src/sonarmap/io/kongsberg.py").exists():
        out["kongsberg"] = k
    return out


@pytest.mark.slow
def test_static_works_on_every_format(data_dir: Path, tmp_path: Path) -> None:
    from plyfile import PlyData

    for name, src in _static_inputs(data_dir, tmp_path).items():
        out = tmp_path / f"{name}.ply"
        assert main(["map", str(src), "-o", str(out), "--static", "-q"]) == 0, name
        ply = PlyData.read(str(out))
        assert ply["vertex"].count > 0, name


def test_static_and_poses_conflict(data_dir: Path, tmp_path: Path) -> None:
    poses = tmp_path / "p.csv"
    poses.write_text("time_s,x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,0,1\n")
    assert main(["map", str(data_dir / "aris" / "sample.aris"), "-o", str(tmp_path / "m.ply"), "--static",
                 "--poses", str(poses)]) == 2


def test_octomap_export_from_cli(data_dir: Path, tmp_path: Path) -> None:
    from sonarmap.mapping.octomap import read_octomap_bt

    bt = tmp_path / "m.bt"
    assert main(["map", str(data_dir / "aris" / "sample.aris"), "-o", str(tmp_path / "m.ply"), "--static",
                 "--grid", "0.2", "--octomap", str(bt), "-q"]) == 0
    tree = read_octomap_bt(bt)
    assert tree.resolution_m == pytest.approx(0.2) and tree.occupied.any() and (~tree.occupied).any()
    assert main(["map", str(data_dir / "aris" / "sample.aris"), "-o", str(tmp_path / "n.ply"), "--static",
                 "--octomap", str(bt)]) == 2


def test_ddf_header_navigation_places_the_map(tmp_path: Path) -> None:
    import laspy
    import pyproj
    from ddf_writer import write_ddf

    from sonarmap.io.ddf import FILE_HEADER_DTYPES, FRAME_HEADER_DTYPES

    rng = np.random.default_rng(0)
    frames = []
    for _ in range(2):
        f = rng.rayleigh(12.0, (512, 96)).clip(0, 255).astype(np.uint8)
        f[300:304] = 230
        frames.append(f)
    p = tmp_path / "nav.ddf"
    write_ddf(p, frames)
    raw = bytearray(p.read_bytes())
    fh, fr = FILE_HEADER_DTYPES[4].itemsize, FRAME_HEADER_DTYPES[4]
    for k in range(2):
        off = fh + k * (fr.itemsize + 512 * 96)
        h = np.frombuffer(bytes(raw[off : off + fr.itemsize]), fr, count=1).copy()
        h["latitude"], h["longitude"], h["heading"] = LAT, LON, 180.0
        raw[off : off + fr.itemsize] = h.tobytes()
    p.write_bytes(bytes(raw))
    las = tmp_path / "m.las"
    assert main(["map", str(p), "-o", str(las), "-q"]) == 0
    cloud = laspy.read(las)
    assert pyproj.CRS(cloud.header.parse_crs()).to_epsg() == 32631
    e0, n0 = pyproj.Transformer.from_crs(4326, 32631, always_xy=True).transform(LON, LAT)
    # heading 180: the fan looks south of the fix
    assert np.median(np.asarray(cloud.y)) < n0 - 1.0 and abs(np.median(np.asarray(cloud.x)) - e0) < 5.0
