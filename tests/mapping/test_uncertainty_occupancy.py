"""Per-return range sigma and per-beam pD in the occupancy map's inverse sensor model, and sigma in
registered point clouds (sonarmap.mapping.occupancy / register / pointcloud)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sonarmap.mapping.occupancy import OccupancyConfig, OccupancyMap, SensorModel, pd_pfa_increments
from sonarmap.ranges import BeamRanges

DR = 0.0625  # a power-of-two bin size: sigma_m / DR is exact
RES = 0.25  # 4 bins per cell


from test_occupancy import ID, _poses  # noqa: E402  (the same pose helpers)


def _scene(seed: int, P: int = 12, B: int = 24):
    rng = np.random.default_rng(seed)
    r = rng.uniform(2, 9, (P, B))
    r[rng.random((P, B)) < 0.2] = np.nan
    az = np.linspace(-0.3, 0.3, B)
    R = Rotation.from_euler("ZYX", rng.normal(0, 0.1, (P, 3))).as_matrix()
    t = np.cumsum(rng.normal(0, 0.05, (P, 3)), axis=0)
    pd = rng.uniform(0.5, 0.98, P)
    pd[3], pd[5] = np.nan, 0.0  # a CFAR ping (no pD) and a ping whose detections were all rejected
    pfa = rng.uniform(1e-5, 0.05, P)
    return r, az, _poses(R, t), pd, pfa


def _grid(m: OccupancyMap):
    a = m.to_array()
    return a.logodds, a.observed, a.origin_m, m.n_pings, m.n_uninformative


def _same(a, b) -> None:
    for x, y in zip(a, b, strict=True):
        assert np.array_equal(x, y)


@pytest.mark.parametrize("cfg, kw", [
    ({"resolution_m": 0.1}, {"range_resolution_m": DR}),
    ({"resolution_m": 0.1, "dims": 2}, {"range_resolution_m": DR}),
    ({"resolution_m": 0.1, "n_elevation": 3, "elevation_ambiguity": True}, {"range_resolution_m": DR}),
    ({"resolution_m": 0.1}, {}),
    ({"resolution_m": 0.1}, {"range_resolution_m": DR, "model": SensorModel.fixed()}),
])
def test_nan_sigma_and_p_detect_give_the_per_ping_map(cfg, kw) -> None:
    """All-NaN sigma_m / p_detect (what the pipeline reports until it estimates them): the map is
    exactly the per-ping model's; a finite sigma equal to the constant and a p_detect equal to the
    ping's pd give the same map too."""
    r, az, poses, pd, pfa = _scene(1)
    common = dict(min_range_m=1.0, max_range_m=10.0, pd=pd, pfa=pfa, **kw)
    ref = OccupancyMap(OccupancyConfig(**cfg))
    ref.integrate(r, az, poses, **common)
    nan = OccupancyMap(OccupancyConfig(**cfg))
    nan.integrate(r, az, poses, sigma_m=np.full(r.shape, np.nan), p_detect=np.full(r.shape, np.nan), **common)
    _same(_grid(ref), _grid(nan))
    if "range_resolution_m" in kw:
        same = OccupancyMap(OccupancyConfig(**cfg))  # range_sigma_bins = 1 bin = DR metres
        same.integrate(r, az, poses, sigma_m=np.where(np.isfinite(r), DR, np.nan),
                       p_detect=np.broadcast_to(pd[:, None], r.shape), **common)
        _same(_grid(ref), _grid(same))
    # integrate_ranges with default BeamRanges (NaN sigma / p_detect) is the same map again
    brs = [BeamRanges(range_m=row, bin=np.where(np.isfinite(row), 1, -1), intensity=np.ones(row.size, np.float32),
                      confidence=np.ones(row.size, np.float32), azimuth_rad=az) for row in r]
    via = OccupancyMap(OccupancyConfig(**cfg))
    via.integrate_ranges(brs, poses, **common)
    _same(_grid(ref), _grid(via))


def _cell(m: OccupancyMap, x: float, az: float = 0.0) -> tuple[float, bool]:
    lo, seen = m.logodds_at([[0.01 + x * math.cos(az), 0.01 + x * math.sin(az), 0.01]])
    return float(lo[0]), bool(seen[0])


def test_return_sigma_sets_the_strength_of_its_own_hit() -> None:
    """Two beams of one ping, returns at 5.1 m: the beam with the larger sigma gets a weaker hit
    (the model's q = P(return in its surface's cell) falls, the rest of its probability goes to the
    neighbouring cells along the ray); NaN uses range_sigma_bins; free space is the same."""
    pd, pfa = 0.9, 1e-4
    az = [0.0, 0.4, -0.4]
    sig = np.array([[0.01, 0.12, np.nan]])
    m = OccupancyMap(OccupancyConfig(resolution_m=RES, l_min=-20, l_max=20))
    m.integrate([[5.1, 5.1, 5.1]], az, ID, min_range_m=1.0, max_range_m=8.0, pd=pd, pfa=pfa,
                range_resolution_m=DR, sigma_m=sig)
    m_bins = RES / DR
    want = [pd_pfa_increments(pd, pfa, bins_per_cell=m_bins, range_sigma_bins=s)[0]
            for s in (0.01 / DR, 0.12 / DR, 1.0)]
    got = [_cell(m, 5.1, a)[0] for a in az]
    assert got == pytest.approx(want, rel=1e-5)
    assert got[0] > got[2] > got[1] > 0  # 0.16 bins, 1 bin (the constant), 1.92 bins
    _, l_miss = pd_pfa_increments(pd, pfa, bins_per_cell=m_bins)
    for a in az:  # free space does not depend on sigma
        assert _cell(m, 3.0, a)[0] == pytest.approx(float(l_miss), rel=1e-5)
        assert not _cell(m, 5.6, a)[1]  # behind the return: occluded


def test_return_with_a_large_sigma_leaves_its_cell_unchanged() -> None:
    """sigma >= 0.84 cell: the return's cell is as likely to be a neighbour's surface as its own,
    the hit is clipped to zero, the beam still carves free space up to it."""
    m = OccupancyMap(OccupancyConfig(resolution_m=RES, l_min=-20, l_max=20))
    assert m.integrate([[5.1, 5.1]], [0.0, 0.4], ID, min_range_m=1.0, max_range_m=8.0, pd=0.9, pfa=1e-4,
                       range_resolution_m=DR, sigma_m=[[0.22, 0.25]]) == 1
    for a in (0.0, 0.4):
        lo, seen = _cell(m, 5.1, a)
        assert seen and lo == 0.0
        assert _cell(m, 3.0, a)[0] < 0
    assert m.n_uninformative == 0


def test_sigma_without_a_range_resolution_is_in_cells() -> None:
    """Without range_resolution_m a finite sigma_m still applies (one 'bin' per cell, sigma in
    cells); NaN means no range error, as before."""
    m = OccupancyMap(OccupancyConfig(resolution_m=RES, l_min=-20, l_max=20))
    m.integrate([[5.1, 5.1]], [0.0, 0.4], ID, min_range_m=1.0, max_range_m=8.0, pd=0.9, pfa=0.01,
                sigma_m=[[0.05, np.nan]])
    want = pd_pfa_increments(0.9, 0.01, range_sigma_bins=0.05 / RES)[0]
    assert _cell(m, 5.1, 0.0)[0] == pytest.approx(want, rel=1e-5)
    assert _cell(m, 5.1, 0.4)[0] == pytest.approx(math.log(0.9 / 0.01), rel=1e-5)


def test_beam_p_detect_sets_that_beams_hit_and_free_space() -> None:
    """Per-beam pD: a beam that rarely reports its surface carves free space weakly; NaN uses the
    ping's pd; pD <= pFA leaves the beam out (or gives it the fixed model), not the ping."""
    pd, pfa = 0.9, 0.01
    az = [0.0, 0.4, -0.4]
    p_det = np.array([[0.6, np.nan, 0.005]])
    m = OccupancyMap(OccupancyConfig(resolution_m=RES, l_min=-20, l_max=20))
    assert m.integrate([[5.1, 5.1, 5.1]], az, ID, min_range_m=1.0, max_range_m=8.0, pd=pd, pfa=pfa,
                       p_detect=p_det) == 1
    assert _cell(m, 3.0, 0.0)[0] == pytest.approx(math.log(0.4 / 0.99), rel=1e-5)
    assert _cell(m, 5.1, 0.0)[0] == pytest.approx(math.log(0.6 / 0.01), rel=1e-5)
    assert _cell(m, 3.0, 0.4)[0] == pytest.approx(math.log(0.1 / 0.99), rel=1e-5)
    assert _cell(m, 5.1, 0.4)[0] == pytest.approx(math.log(0.9 / 0.01), rel=1e-5)
    assert not _cell(m, 3.0, -0.4)[1] and not _cell(m, 5.1, -0.4)[1]  # uninformative beam: left out
    assert m.n_uninformative == 0 and m.n_pings == 1
    fx = SensorModel.fixed()
    mf = OccupancyMap(OccupancyConfig(resolution_m=RES, l_min=-20, l_max=20))
    mf.integrate([[5.1, 5.1, 5.1]], az, ID, min_range_m=1.0, max_range_m=8.0, pd=pd, pfa=pfa, p_detect=p_det, model=fx)
    assert _cell(mf, 3.0, -0.4)[0] == pytest.approx(fx.l_miss, rel=1e-6)
    assert _cell(mf, 5.1, -0.4)[0] == pytest.approx(fx.l_hit, rel=1e-6)
    assert _cell(mf, 3.0, 0.0)[0] == pytest.approx(math.log(0.4 / 0.99), rel=1e-5)


def test_p_detect_rescues_a_ping_without_pd_and_all_uninformative_beams_skip_it() -> None:
    """A ping whose pd is NaN (CFAR) is mapped on the beams with a finite p_detect; a ping none of
    whose beams is informative is skipped and counted, as before."""
    m = OccupancyMap(OccupancyConfig(resolution_m=RES))
    assert m.integrate([[5.1, 5.1]], [0.0, 0.4], ID, min_range_m=1.0, max_range_m=8.0, pd=np.nan, pfa=0.01,
                       p_detect=[[0.8, np.nan]]) == 1
    assert _cell(m, 3.0, 0.0)[1] and not _cell(m, 3.0, 0.4)[1]
    assert m.integrate([[5.1, 5.1]], [0.0, 0.4], ID, min_range_m=1.0, max_range_m=8.0, pd=np.nan, pfa=0.01,
                       p_detect=[[0.001, np.nan]]) == 0
    assert m.n_uninformative == 1


def test_integrate_ranges_uses_beamranges_fields_unless_told_not_to() -> None:
    n = 3
    br = BeamRanges(range_m=np.full(n, 5.1), bin=np.full(n, 80), intensity=np.ones(n, np.float32),
                    confidence=np.ones(n, np.float32), azimuth_rad=np.array([0.0, 0.4, -0.4]),
                    sigma_m=np.array([0.01, 0.22, np.nan]), p_detect=np.array([0.6, np.nan, np.nan], np.float32))
    kw = dict(min_range_m=1.0, max_range_m=8.0, pd=[0.9], pfa=[1e-4], range_resolution_m=DR)
    m = OccupancyMap(OccupancyConfig(resolution_m=RES, l_min=-20, l_max=20))
    m.integrate_ranges([br], ID, **kw)
    m_bins = RES / DR
    p6 = float(np.float32(0.6))
    assert _cell(m, 5.1, 0.0)[0] == pytest.approx(
        pd_pfa_increments(p6, 1e-4, bins_per_cell=m_bins, range_sigma_bins=0.01 / DR)[0], rel=1e-5)
    assert _cell(m, 3.0, 0.0)[0] == pytest.approx(pd_pfa_increments(p6, 1e-4, bins_per_cell=m_bins)[1], rel=1e-5)
    assert _cell(m, 5.1, 0.4)[0] == 0.0  # sigma 3.5 bins on a 4-bin cell: no information
    off = OccupancyMap(OccupancyConfig(resolution_m=RES, l_min=-20, l_max=20))
    off.integrate_ranges([br], ID, use_sigma=False, use_p_detect=False, **kw)
    plain = OccupancyMap(OccupancyConfig(resolution_m=RES, l_min=-20, l_max=20))
    plain.integrate(br.range_m, br.azimuth_rad, ID, **kw)
    _same(_grid(off), _grid(plain))
    assert _cell(off, 5.1, 0.4)[0] > 0


def test_registered_points_carry_sigma_through_every_format(tmp_path) -> None:
    from sonarmap.mapping.pointcloud import read_point_cloud, write_point_cloud
    from sonarmap.mapping.register import PointCloud, RegistrationConfig, register_ranges

    n = 4
    brs = [BeamRanges(range_m=np.array([4.0, np.nan, 5.0, 6.0]) + k, bin=np.array([10, -1, 20, 30]),
                      intensity=np.ones(n, np.float32), confidence=np.ones(n, np.float32),
                      azimuth_rad=np.linspace(-0.2, 0.2, n), sigma_m=np.array([0.01, np.nan, np.nan, 0.03]) * (k + 1))
           for k in range(2)]
    poses = _poses(np.stack([np.eye(3)] * 2), np.zeros((2, 3)))
    cloud = register_ranges(brs, poses)
    want = np.array([0.01, np.nan, 0.03, 0.02, np.nan, 0.06], np.float32)
    np.testing.assert_array_equal(cloud.sigma_m, want)
    spread = register_ranges(brs, poses, config=RegistrationConfig(n_elevation=3))
    np.testing.assert_array_equal(spread.sigma_m, np.repeat(want, 3))
    both = PointCloud.concat([cloud, cloud.select(np.array([0, 2]))])
    np.testing.assert_array_equal(both.sigma_m, np.concatenate([want, want[[0, 2]]]))
    for sfx in ("ply", "las", "csv"):
        path = tmp_path / f"c.{sfx}"
        write_point_cloud(cloud, path)
        np.testing.assert_array_equal(read_point_cloud(path).sigma_m, want)
    # a cloud file without sigma (written by another tool) reads back with NaN
    (tmp_path / "old.csv").write_text("x,y,z,time_ns,beam,range_m\n1.0,2.0,3.0,5,0,4.0\n", encoding="utf-8")
    assert np.isnan(read_point_cloud(tmp_path / "old.csv").sigma_m).all()
