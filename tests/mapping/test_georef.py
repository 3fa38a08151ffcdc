"""Georeferenced outputs: local frame <-> projected CRS, LAS/PLY/CSV with a CRS, GeoTIFF rasters and
OctoMap .bt trees (sonarmap.mapping.georef / pointcloud / raster / octomap)."""

from __future__ import annotations

import math
import pickle

import laspy
import numpy as np
import pyproj
import pytest
import rasterio
from plyfile import PlyData
from scipy.spatial.transform import Rotation

from sonarmap.errors import DataFormatError, InputError
from sonarmap.mapping.frames import ned_to_enu
from sonarmap.mapping.georef import GeoReference, utm_epsg
from sonarmap.mapping.occupancy import OccupancyConfig, OccupancyMap
from sonarmap.mapping.octomap import KEY_ORIGIN, octomap_keys, read_octomap_bt, write_octomap_bt
from sonarmap.mapping.pointcloud import read_point_cloud, read_point_cloud_crs, write_point_cloud
from sonarmap.mapping.poses import SensorPoses
from sonarmap.mapping.raster import height_raster, occupancy_raster, read_geotiff, write_geotiff
from sonarmap.mapping.register import PointCloud

LAT0, LON0 = 51.3685, 3.139  # RV Belgica, Belgian coast: UTM zone 31 N, 0.14 deg east of its meridian


@pytest.fixture(scope="module")
def geo() -> GeoReference:
    return GeoReference.from_origin(LAT0, LON0)


def _poses(R, t) -> SensorPoses:
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    n = R.shape[0]
    return SensorPoses(np.arange(n, dtype=np.int64), R, np.asarray(t, np.float64).reshape(n, 3),
                       Rotation.from_matrix(R).as_quat(), np.ones(n, bool))


def _cloud(xyz, frame: str = "ned") -> PointCloud:
    n = len(xyz)
    rng = np.random.default_rng(1)
    return PointCloud(np.asarray(xyz, np.float64), 1_700_000_000_000_000_000 + rng.integers(0, 10**9, n),
                      rng.integers(0, 96, n), rng.uniform(2, 11, n), rng.uniform(0, 1, n), rng.uniform(0, 1, n),
                      np.zeros(n), frame=frame)


# ------------------------------------------------------------------------------ GeoReference
@pytest.mark.slow  # over a second in the fast subset
def test_utm_zone_choice_hemispheres_and_exceptions() -> None:
    assert utm_epsg(LAT0, LON0) == 32631
    assert GeoReference.from_origin(LAT0, LON0).epsg == 32631
    assert utm_epsg(-33.86, 151.21) == 32756  # Sydney: southern hemisphere -> 327xx
    assert GeoReference.from_origin(-8.5, -35.0).epsg == 32725
    assert utm_epsg(60.0, 5.0) == 32632  # south-west Norway is zone 32, not 31
    assert utm_epsg(78.0, 15.0) == 32633  # Svalbard
    assert utm_epsg(85.0, 0.0) == 32661 and utm_epsg(-85.0, 10.0) == 32761  # polar: UPS
    assert utm_epsg(0.0, 180.0) == 32601 and utm_epsg(0.0, -180.0) == 32601
    # away from zone edges and the exceptions, pyproj's own UTM search agrees
    from pyproj.aoi import AreaOfInterest
    from pyproj.database import query_utm_crs_info

    rng = np.random.default_rng(0)
    for lat, lon in zip(rng.uniform(-79, 55, 8), rng.uniform(-179, 179, 8), strict=True):
        lon = math.floor(lon / 6) * 6 + 3.0 + (lon % 1.0)  # inside a zone, >= 2 deg from its edges
        codes = [int(i.code) for i in query_utm_crs_info(
            datum_name="WGS 84", area_of_interest=AreaOfInterest(lon, lat, lon, lat))]
        assert utm_epsg(lat, lon) in codes


def test_crs_override_forms_and_rejections() -> None:
    for crs in (25831, "EPSG:25831", pyproj.CRS.from_epsg(25831), pyproj.CRS.from_epsg(25831).to_wkt()):
        assert GeoReference.from_origin(LAT0, LON0, crs=crs).epsg == 25831
    g = GeoReference.from_origin(LAT0, LON0, crs=3006)  # SWEREF99 TM: northing-first axis order
    e, n, _ = g.to_projected([0.0, 0.0, 0.0])
    ref = pyproj.Transformer.from_crs(4326, 3006, always_xy=True).transform(LON0, LAT0)
    assert (e, n) == pytest.approx(ref, abs=1e-6) and abs(e) < 1e6 < n  # always (easting, northing)
    with pytest.raises(InputError, match="not a projected CRS"):
        GeoReference.from_origin(LAT0, LON0, crs="EPSG:4326")
    with pytest.raises(InputError, match="metres"):
        GeoReference.from_origin(LAT0, LON0, crs=2263)  # US survey feet
    with pytest.raises(InputError, match="cannot interpret"):
        GeoReference.from_origin(LAT0, LON0, crs="EPSG:99999999")
    with pytest.raises(InputError, match="lat_deg"):
        GeoReference.from_origin(91.0, LON0)
    with pytest.raises(InputError, match="lat_deg"):
        GeoReference.from_origin(math.nan, LON0)
    with pytest.raises(InputError, match="height_m"):
        GeoReference.from_origin(LAT0, LON0, math.inf)


def test_round_trip_local_projected_local_within_1mm_over_1km(geo: GeoReference) -> None:
    rng = np.random.default_rng(2)
    p = np.c_[rng.uniform(-500, 500, (5000, 2)), rng.uniform(-5, 60, 5000)]
    for frame in ("ned", "enu"):
        proj = geo.to_projected(p, frame)
        assert proj.dtype == np.float64 and proj.shape == p.shape
        back = geo.from_projected(proj, frame)
        assert np.abs(back - p).max() < 1e-3
        assert np.abs(back - p).max() < 1e-6  # in fact exact to float64 round-off
    # the two local frames describe the same points
    assert np.allclose(geo.to_projected(p, "ned"), geo.to_projected(ned_to_enu(p), "enu"), rtol=0, atol=1e-7)
    # and geodetic round trip
    lat, lon, h = geo.local_to_geodetic(p[:100])
    assert np.abs(geo.geodetic_to_local(lat, lon, h) - p[:100]).max() < 1e-6
    with pytest.raises(InputError, match="NaN"):
        geo.to_projected([[0.0, math.nan, 0.0]])
    with pytest.raises(InputError, match="frame"):
        geo.to_projected([[0.0, 0.0, 0.0]], "nwu")


def test_convergence_and_scale_are_not_a_flat_offset(geo: GeoReference) -> None:
    o = geo.to_projected([0.0, 0.0, 0.0])
    d = geo.to_projected([100.0, 0.0, 0.0], "ned") - o  # 100 m true north
    assert abs(d[1] - 100.0) > 1e-3 and abs(d[0]) > 0.1  # not +100 m northing, and a sideways step
    angle = math.atan2(d[0], d[1])  # grid azimuth of true north
    assert 0 < abs(angle) < 0.01
    factors = pyproj.Proj(geo.crs).get_factors(LON0, LAT0)
    gamma = math.radians(factors.meridian_convergence)
    assert angle == pytest.approx(-gamma, abs=1e-6) and geo.grid_convergence_rad == pytest.approx(gamma, abs=1e-6)
    assert math.hypot(d[0], d[1]) == pytest.approx(100 * factors.meridional_scale, abs=1e-4)
    assert geo.scale_factor == pytest.approx(factors.meridional_scale, abs=1e-6)
    assert d[2] == pytest.approx(100.0**2 / (2 * 6.37e6), rel=0.01)  # the tangent plane rises above the ellipsoid


def test_geodetic_navigation_to_local_positions_matches_geodesics(geo: GeoReference) -> None:
    assert np.allclose(geo.geodetic_to_local(LAT0, LON0, -5.0), [[0.0, 0.0, 5.0]], atol=1e-8)
    geod = pyproj.Geod(ellps="WGS84")
    rng = np.random.default_rng(3)
    lat = LAT0 + rng.uniform(-0.008, 0.008, 50)  # within ~900 m
    lon = LON0 + rng.uniform(-0.012, 0.012, 50)
    local = geo.geodetic_to_local(lat, lon, np.zeros(50), frame="ned")
    az, _, dist = geod.inv(np.full(50, LON0), np.full(50, LAT0), lon, lat)
    assert np.allclose(np.hypot(local[:, 0], local[:, 1]), dist, rtol=0, atol=1e-3)
    assert np.allclose(np.arctan2(local[:, 1], local[:, 0]), np.radians(az), rtol=0, atol=1e-6)
    enu = geo.geodetic_to_local(lat, lon, np.zeros(50), frame="enu")
    assert np.allclose(enu, ned_to_enu(local), atol=1e-9)
    with pytest.raises(InputError, match="lat_deg"):
        geo.geodetic_to_local([95.0], [LON0], [0.0])


def test_georeference_is_a_value(geo: GeoReference) -> None:
    geo.to_projected([1.0, 2.0, 3.0])  # build the cached transformers
    back = pickle.loads(pickle.dumps(geo))
    assert back == geo and hash(back) == hash(geo)
    assert np.array_equal(back.to_projected([1.0, 2.0, 3.0]), geo.to_projected([1.0, 2.0, 3.0]))
    assert "EPSG:32631" in geo.summary()


# ------------------------------------------------------------------------------ point clouds
@pytest.fixture(scope="module")
def survey_cloud() -> PointCloud:
    rng = np.random.default_rng(4)
    xyz = np.c_[rng.uniform(-500, 500, (2000, 2)), rng.uniform(5, 30, 2000)]  # NED, 1 km square
    return _cloud(xyz)


def test_las_with_crs_read_back_by_laspy_and_pyproj(geo: GeoReference, survey_cloud: PointCloud, tmp_path) -> None:
    path = tmp_path / "survey.las"
    assert write_point_cloud(survey_cloud, path, georef=geo) == "las"
    las = laspy.read(str(path))
    crs = las.header.parse_crs()
    assert crs is not None and crs == pyproj.CRS.from_epsg(32631) and crs.to_epsg() == 32631
    assert las.header.global_encoding.wkt
    assert np.allclose(las.header.scales, 1e-3)
    got = np.stack([las.x, las.y, las.z], axis=1)
    want = geo.to_projected(survey_cloud.xyz_m, "ned")
    assert np.abs(got - want).max() <= 5e-4 + 1e-9  # mm quanta
    assert 5.6e6 < got[:, 1].min()  # UTM northings, not local metres
    assert np.all(got[:, 2] < 0)  # z is height (up): the seabed points are below the origin
    back = read_point_cloud(path)
    assert back.frame == "enu" and np.array_equal(back.time_ns, survey_cloud.time_ns)
    assert read_point_cloud_crs(path) == crs
    # an EPSG override is what ends up in the file
    g2 = GeoReference.from_origin(LAT0, LON0, crs="EPSG:25831")
    write_point_cloud(survey_cloud, tmp_path / "etrs.las", georef=g2)
    assert laspy.read(str(tmp_path / "etrs.las")).header.parse_crs().to_epsg() == 25831


def test_ply_and_csv_record_the_crs_and_keep_full_precision(
    geo: GeoReference, survey_cloud: PointCloud, tmp_path
) -> None:
    want = geo.to_projected(survey_cloud.xyz_m, "ned")
    ply_path = tmp_path / "survey.ply"
    write_point_cloud(survey_cloud, ply_path, georef=geo)
    ply = PlyData.read(str(ply_path))
    assert "crs EPSG:32631" in ply.comments
    wkt = [c for c in ply.comments if c.startswith("crs_wkt ")]
    assert len(wkt) == 1 and pyproj.CRS.from_wkt(wkt[0][8:]) == geo.crs
    assert ply["vertex"]["x"].dtype == np.float64
    assert np.array_equal(read_point_cloud(ply_path).xyz_m, want)  # float32 would lose ~0.3 m here
    assert read_point_cloud_crs(ply_path).to_epsg() == 32631

    import pandas as pd

    csv_path = tmp_path / "survey.csv"
    write_point_cloud(survey_cloud, csv_path, georef=geo)
    df = pd.read_csv(csv_path, comment="#")
    assert list(df.columns[:3]) == ["x", "y", "z"] and len(df) == len(survey_cloud)
    assert np.array_equal(df[["x", "y", "z"]].to_numpy(), want)
    assert read_point_cloud_crs(csv_path) == geo.crs
    assert np.array_equal(read_point_cloud(csv_path).xyz_m, want)


def test_files_without_georef_have_no_crs_and_frame_conflicts_are_refused(
    geo: GeoReference, survey_cloud: PointCloud, tmp_path
) -> None:
    for sfx in ("las", "ply", "csv"):
        write_point_cloud(survey_cloud, tmp_path / f"local.{sfx}")
        assert read_point_cloud_crs(tmp_path / f"local.{sfx}") is None
    with pytest.raises(InputError, match="frame"):
        write_point_cloud(survey_cloud, tmp_path / "x.las", georef=geo, frame="ned")
    write_point_cloud(survey_cloud, tmp_path / "enu.las", georef=geo, frame="enu")  # the projected axes: fine
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\ncomment crs_wkt NOT A CRS\nelement vertex 0\n"
                    b"property float x\nend_header\n")
    with pytest.raises(DataFormatError, match="CRS"):
        read_point_cloud_crs(bad)


# ------------------------------------------------------------------------------ GeoTIFF
def _far_map(res: float, dims: int = 3) -> tuple[OccupancyMap, np.ndarray]:
    """A fan of rays from a sonar 800 m north, 600 m east of the origin; hits 6 m ahead."""
    m = OccupancyMap(OccupancyConfig(resolution_m=res, dims=dims))
    t = np.array([[800.02, 600.03, 4.0]])
    az = np.linspace(-0.3, 0.3, 41)
    r = np.full((1, 41), 6.0)
    r[0, :10] = np.nan  # beams without a return: free to the maximum range
    for _ in range(3):
        m.integrate(r, az, _poses(np.eye(3), t), min_range_m=1.0, max_range_m=8.0, pd=0.9, pfa=0.05)
    hit = t[0] + 6.0 * np.array([math.cos(az[30]), math.sin(az[30]), 0.0])
    return m, hit


def test_occupancy_geotiff_crs_transform_and_nodata(geo: GeoReference, tmp_path) -> None:
    res = 0.25
    m, hit = _far_map(res)
    raster = occupancy_raster(m, georef=geo)
    path = tmp_path / "occupancy.tif"
    write_geotiff(path, raster)
    with rasterio.open(path) as src:
        assert src.crs == rasterio.crs.CRS.from_epsg(32631) and src.crs.to_epsg() == 32631
        assert src.count == 1 and src.descriptions == ("occupancy",) and math.isnan(src.nodata)
        assert src.transform.b == 0 and src.transform.d == 0 and src.transform.e < 0  # north-up
        band = src.read(1)
        E, N, _ = geo.to_projected(m.cell_centers(np.floor(hit / res)), "ned")
        row, col = src.index(E, N)
        cx, cy = src.xy(row, col)
        assert abs(cx - E) <= res / 2 and abs(cy - N) <= res / 2
        assert band[row, col] > 0.99  # the hit cell, where the projection puts it
        # a flat offset (no convergence, no scale factor) would be ~1.9 m = 7 pixels off
        o = geo.to_projected([0.0, 0.0, 0.0])
        naive = src.index(o[0] + hit[1], o[1] + hit[0])
        assert math.hypot(naive[0] - row, naive[1] - col) > 4
    occupied = band > 0.5
    assert 0 < occupied.sum() < 3 * len(m.occupied_cells())  # only the hit arc
    # unobserved pixels are nodata, observed free space is low probability
    assert np.isnan(band).mean() > 0.3
    free = band[np.isfinite(band) & ~occupied]
    assert free.size > 0 and free.max() < 0.1
    # resampling keeps the number of observed columns (to within the edge pixels of a rotated grid)
    cols = {tuple(c) for c in m.observed_cells()[:, :2]}
    assert abs(np.isfinite(band).sum() - len(cols)) < 0.1 * len(cols)
    back = read_geotiff(path)
    assert back.band_names == ("occupancy",) and np.array_equal(back.data, raster.data, equal_nan=True)


def test_local_grid_geotiff_and_2d_map(geo: GeoReference, tmp_path) -> None:
    m, hit = _far_map(0.5, dims=2)
    arr = m.to_array()
    path = tmp_path / "grid.tif"
    written = write_geotiff(path, arr.probability, georef=geo, origin_m=arr.origin_m, resolution_m=0.5,
                            frame="ned", nodata=-1.0, band_names=("p",))
    with rasterio.open(path) as src:
        assert src.nodata == -1.0 and src.crs.to_epsg() == 32631
        band = src.read(1)
        E, N, _ = geo.to_projected([hit[0], hit[1], 0.0], "ned")
        assert band[src.index(E, N)] > 0.9
        assert (band == -1.0).any() and not np.isnan(band).any()
    assert np.array_equal(occupancy_raster(m, georef=geo, nodata=-1.0).data, written.data)
    with pytest.raises(InputError, match="georef"):
        write_geotiff(path, arr.probability)


def test_bathymetry_grid_in_projected_coordinates(geo: GeoReference, tmp_path) -> None:
    rng = np.random.default_rng(5)
    n = 20000
    xy = np.c_[rng.uniform(900, 940, n), rng.uniform(-320, -280, n)]
    xy = xy[~((np.abs(xy[:, 0] - 915) < 5) & (np.abs(xy[:, 1] + 305) < 5))]  # a 10 m hole in the coverage
    n = len(xy)
    z = 18.0 + 0.05 * (xy[:, 0] - 900)  # a seabed sloping down to the north
    cloud = _cloud(np.c_[xy, z])
    res = 2.0
    r = height_raster(cloud, georef=geo, resolution_m=res)
    assert r.band_names == ("shallowest", "mean", "deepest", "count")
    assert r.transform[2] % res == 0 and r.transform[5] % res == 0  # pixel edges on multiples of res
    assert r.band("count").sum() == n
    path = tmp_path / "bathy.tif"
    write_geotiff(path, r)
    proj = geo.to_projected(cloud.xyz_m, "ned")
    depth = geo.height0_m - proj[:, 2]
    assert np.abs(depth - z).max() < 0.1  # depth ~ NED z, minus the Earth's curvature over ~1 km
    with rasterio.open(path) as src:
        assert src.crs.to_epsg() == 32631 and src.count == 4
        assert src.tags(1)["units"] == "m" and "positive down" in src.tags(1)["meaning"]
        data = src.read()
        k = 123
        row, col = src.index(proj[k, 0], proj[k, 1])
        inside = ((np.floor((src.transform.f - proj[:, 1]) / res) == row)
                  & (np.floor((proj[:, 0] - src.transform.c) / res) == col))
        assert data[3, row, col] == inside.sum() > 0
        assert data[0, row, col] == pytest.approx(depth[inside].min(), abs=1e-4)
        assert data[1, row, col] == pytest.approx(depth[inside].mean(), abs=1e-4)
        assert data[2, row, col] == pytest.approx(depth[inside].max(), abs=1e-4)
        empty = data[3] == 0
        assert empty.sum() >= 9 and np.isnan(data[:3, empty]).all()  # the hole is nodata
        assert np.isfinite(data[:3, ~empty]).all()
    h = height_raster(cloud, georef=geo, resolution_m=res, vertical="height")
    assert np.allclose(h.band("shallowest"), -r.band("shallowest"), equal_nan=True, atol=1e-4)
    with pytest.raises(InputError, match="no points"):
        height_raster(PointCloud.empty(), georef=geo, resolution_m=1.0)


# ------------------------------------------------------------------------------ OctoMap
def test_bt_bytes_follow_the_octomap_format(tmp_path) -> None:
    """One occupied NED voxel (0, 0, 0) = ENU voxel (0, 0, -1): keys (32768, 32768, 32767)."""
    m = OccupancyMap(OccupancyConfig(resolution_m=0.1, l_min=-10, l_max=10))
    # a ray along +x from (-0.95, 0.05, 0.05) hits at 1.0 m: occupied (0, 0, 0), free behind it
    m.integrate([1.0], [0.0], _poses(np.eye(3), [[-0.95, 0.05, 0.05]]), min_range_m=0.96, max_range_m=2.0,
                pd=0.9, pfa=0.05)
    assert m.occupied_cells().tolist() == [[0, 0, 0]] and len(m.observed_cells()) == 1
    info = write_octomap_bt(tmp_path / "one.bt", m)
    raw = (tmp_path / "one.bt").read_bytes()
    head, data = raw.split(b"data\n", 1)
    assert head.startswith(b"# Octomap OcTree binary file\n") and b"\nid OcTree\nsize 17\nres 0.1\n" in head + b"\n"
    # root: child 3 (x and y keys >= 32768, z below) is inner -> bits 6-7 = 11; then 14 inner
    # nodes with child 4 (z bit set) inner, and the last with child 4 an occupied leaf (field 2)
    assert data == b"\xc0\x00" + b"\x00\x03" * 14 + b"\x00\x02"
    assert info.n_nodes == 17 and info.n_occupied_voxels == 1 and info.n_free_voxels == 0
    leaves = read_octomap_bt(tmp_path / "one.bt")
    assert leaves.key_min.tolist() == [[32768, 32768, 32767]] and leaves.occupied.tolist() == [True]
    assert np.allclose(leaves.centers_m, [[0.05, 0.05, -0.05]])  # the NED cell centre (0.05, 0.05, 0.05) in ENU
    write_octomap_bt(tmp_path / "ned.bt", m, frame="ned")
    assert read_octomap_bt(tmp_path / "ned.bt").key_min.tolist() == [[32768, 32768, 32768]]


def test_bt_pruning_and_errors(tmp_path) -> None:
    from sonarmap.mapping.occupancy import OccupancyArray

    lo = np.full((4, 2, 2), 3.0, np.float32)
    lo[2:] = -3.0  # an aligned 2x2x2 occupied block and a 2x2x2 free block
    arr = OccupancyArray(lo, np.ones(lo.shape, bool), np.array([0.0, 0.0, 0.0]), 0.2)
    info = write_octomap_bt(tmp_path / "block.bt", arr, frame="ned")
    leaves = read_octomap_bt(tmp_path / "block.bt")
    assert leaves.size_voxels.tolist() == [2, 2] and info.n_leaves == 2  # each block is one pruned leaf
    assert info.n_nodes == 1 + 14 + 2 == leaves.n_nodes  # root, inner nodes at depths 1-14, 2 leaves at depth 15
    assert {tuple(v) for v in leaves.voxels(True)} == {(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)}
    assert len(leaves.voxels(False)) == 8
    with pytest.raises(InputError, match="3-D"):
        write_octomap_bt(tmp_path / "x.bt", OccupancyMap(OccupancyConfig(dims=2)))
    with pytest.raises(InputError, match="32768"):
        octomap_keys(np.array([[40000, 0, 0]]))
    raw = (tmp_path / "block.bt").read_bytes()
    assert b"\nsize 17\n" in raw
    for broken in (raw[:-2], raw + b"\x00\x00", raw.replace(b"size 17", b"size 18"), b"not a tree"):
        (tmp_path / "broken.bt").write_bytes(broken)
        with pytest.raises(DataFormatError):
            read_octomap_bt(tmp_path / "broken.bt")
    empty = write_octomap_bt(tmp_path / "empty.bt", OccupancyMap())
    assert empty.n_nodes == 0 and len(read_octomap_bt(tmp_path / "empty.bt").occupied) == 0


@pytest.fixture(scope="module")
def survey_map() -> OccupancyMap:
    rng = np.random.default_rng(6)
    P, B = 30, 48
    R = Rotation.from_euler("ZYX", rng.normal(0, 0.3, (P, 3))).as_matrix()
    t = np.cumsum(rng.normal(0, 0.3, (P, 3)), axis=0)
    r = rng.uniform(2, 9, (P, B))
    r[rng.random((P, B)) < 0.2] = np.nan
    m = OccupancyMap(OccupancyConfig(resolution_m=0.1, n_elevation=3))
    m.integrate(r, np.linspace(-0.4, 0.4, B), _poses(R, t), min_range_m=1.0, max_range_m=10.0, pd=0.9, pfa=0.05)
    return m


@pytest.mark.slow
def test_bt_round_trip_of_a_survey_map(survey_map: OccupancyMap, tmp_path) -> None:
    path = tmp_path / "survey.bt"
    info = write_octomap_bt(path, survey_map)
    leaves = read_octomap_bt(path)
    assert leaves.n_nodes == info.n_nodes and leaves.resolution_m == 0.1
    occ = {tuple(v) for v in octomap_keys(survey_map.occupied_cells()) - KEY_ORIGIN}
    obs = {tuple(v) for v in octomap_keys(survey_map.observed_cells()) - KEY_ORIGIN}
    assert len(occ) == info.n_occupied_voxels > 100
    assert {tuple(v) for v in leaves.voxels(True)} == occ
    assert {tuple(v) for v in leaves.voxels(False)} == obs - occ
    assert info.n_leaves < len(obs)  # pruning merged free space
    # positions: an occupied NED cell centre, converted to ENU, is inside its leaf
    c_ned = survey_map.cell_centers(survey_map.occupied_cells()[:1])[0]
    c_enu = np.array([c_ned[1], c_ned[0], -c_ned[2]])
    k = np.floor(c_enu / 0.1).astype(np.int64) + KEY_ORIGIN
    inside = np.all((leaves.key_min <= k) & (k < leaves.key_min + leaves.size_voxels[:, None]), axis=1)
    assert inside.sum() == 1 and leaves.occupied[inside][0]


@pytest.mark.slow
def test_bt_is_read_by_the_octomap_library(survey_map: OccupancyMap, tmp_path) -> None:
    octomap = pytest.importorskip("octomap", reason="octomap-python (the OctoMap C++ library's binding) not installed")
    path = tmp_path / "survey.bt"
    info = write_octomap_bt(path, survey_map)
    tree = octomap.OcTree(0.1)
    assert tree.readBinary(str(path).encode())
    assert tree.size() == info.n_nodes and tree.getNumLeafNodes() == info.n_leaves
    occ_enu = octomap_keys(survey_map.occupied_cells()) - KEY_ORIGIN
    assert (tree.getLabels((occ_enu + 0.5) * 0.1) == 1).all()  # 1 = occupied
    obs = octomap_keys(survey_map.observed_cells()) - KEY_ORIGIN
    free = np.array(sorted({tuple(v) for v in obs} - {tuple(v) for v in occ_enu}))
    assert (tree.getLabels((free + 0.5) * 0.1) == 0).all()  # 0 = free
    # OctoMap's own writer produces the same node stream from what it read
    tree.writeBinary(str(tmp_path / "again.bt").encode())
    ours = path.read_bytes().split(b"data\n", 1)[1]
    theirs = (tmp_path / "again.bt").read_bytes().split(b"data\n", 1)[1]
    assert ours == theirs
    # and our reader reads a tree OctoMap built itself
    t2 = octomap.OcTree(0.2)
    t2.insertPointCloud(np.array([[3.0, 0.1, 0.1], [0.1, 2.0, -1.0]]), np.array([0.0, 0.0, 0.0]))
    t2.writeBinary(str(tmp_path / "native.bt").encode())
    leaves = read_octomap_bt(tmp_path / "native.bt")
    assert leaves.n_nodes == t2.size()
    assert {tuple(v) for v in leaves.voxels(True)} == {(15, 0, 0), (0, 10, -5)}
