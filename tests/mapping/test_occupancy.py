"""Log-odds occupancy maps with the pD/pFA inverse sensor model (sonarmap.mapping.occupancy)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sonarmap.errors import InputError
from sonarmap.mapping.occupancy import OccupancyConfig, OccupancyMap, SensorModel, voxel_iou, voxelize
from sonarmap.mapping.poses import SensorPoses


def _poses(R, t) -> SensorPoses:
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    n = R.shape[0]
    return SensorPoses(np.arange(n, dtype=np.int64), R, np.asarray(t, np.float64).reshape(n, 3),
                       Rotation.from_matrix(R).as_quat(), np.ones(n, bool))


ID = _poses(np.eye(3), [[0.01, 0.01, 0.01]])


def test_sensor_model_from_pd_pfa_and_fixed() -> None:
    m = SensorModel.from_pd_pfa(0.9, 0.05)
    assert m.l_hit == pytest.approx(math.log(0.9 / 0.05))
    assert m.l_miss == pytest.approx(math.log(0.1 / 0.95))
    f = SensorModel.fixed()
    assert f.l_hit == pytest.approx(math.log(4.0)) and f.l_miss == pytest.approx(math.log(0.3 / 0.7))
    with pytest.raises(InputError, match="pd/pfa"):
        SensorModel.from_pd_pfa(0.1, 0.2)


def test_single_ray_hit_free_and_unknown() -> None:
    m = OccupancyMap(OccupancyConfig(resolution_m=0.1, l_min=-10, l_max=10))
    m.integrate([5.03], [0.0], ID, min_range_m=1.0, max_range_m=8.0, pd=0.9, pfa=0.05)
    lh, lm = math.log(0.9 / 0.05), math.log(0.1 / 0.95)
    x = np.arange(0.05, 8.0, 0.1)
    lo, seen = m.logodds_at(np.stack([x, np.full_like(x, 0.01), np.full_like(x, 0.01)], axis=1))
    before = (x > 1.0) & (x < 5.0)
    assert np.allclose(lo[before], lm, atol=1e-6) and seen[before].all()
    assert lo[50] == pytest.approx(lh, abs=1e-5)  # cell [5.0, 5.1) holds the return
    assert not seen[x < 1.0].any()  # inside the minimum range: unobserved
    assert not seen[x > 5.1].any()  # behind the return: occluded, unobserved
    occ = m.occupied_cells()
    assert occ.tolist() == [[50, 0, 0]]


def test_no_return_carves_to_max_range_and_option_off() -> None:
    m = OccupancyMap(OccupancyConfig(resolution_m=0.1))
    m.integrate([np.nan], [0.0], ID, min_range_m=1.0, max_range_m=3.0, pd=0.9, pfa=0.05)
    assert len(m.observed_cells()) == 21 and len(m.occupied_cells()) == 0
    m2 = OccupancyMap(OccupancyConfig(resolution_m=0.1, free_without_return=False))
    m2.integrate([np.nan], [0.0], ID, min_range_m=1.0, max_range_m=3.0, pd=0.9, pfa=0.05)
    assert len(m2.observed_cells()) == 0


def test_clamping_and_per_ping_pd_pfa() -> None:
    cfg = OccupancyConfig(resolution_m=0.1, l_min=-2.0, l_max=3.5)
    m = OccupancyMap(cfg)
    poses = _poses(np.stack([np.eye(3)] * 20), np.full((20, 3), 0.01))
    m.integrate(np.full((20, 1), 5.03), [0.0], poses, min_range_m=1.0, max_range_m=8.0, pd=0.9, pfa=0.05)
    lo, _ = m.logodds_at([[5.05, 0.01, 0.01], [3.0, 0.01, 0.01]])
    assert lo[0] == pytest.approx(3.5) and lo[1] == pytest.approx(-2.0)
    # a weak detector (pD close to pFA) moves the map less than a strong one
    weak, strong = OccupancyMap(cfg), OccupancyMap(cfg)
    weak.integrate([5.03], [0.0], ID, min_range_m=1.0, max_range_m=8.0, pd=0.6, pfa=0.4)
    strong.integrate([5.03], [0.0], ID, min_range_m=1.0, max_range_m=8.0, pd=0.95, pfa=0.01)
    lw, _ = weak.logodds_at([[5.05, 0.01, 0.01], [3.0, 0.01, 0.01]])
    ls, _ = strong.logodds_at([[5.05, 0.01, 0.01], [3.0, 0.01, 0.01]])
    assert 0 < lw[0] < ls[0] and ls[1] < lw[1] < 0
    # per-ping arrays
    m3 = OccupancyMap(OccupancyConfig(resolution_m=0.1, l_min=-10, l_max=10))
    m3.integrate(np.full((2, 1), 5.03), [0.0], _poses(np.stack([np.eye(3)] * 2), np.full((2, 3), 0.01)),
                 min_range_m=1.0, max_range_m=8.0, pd=[0.9, 0.8], pfa=[0.05, 0.1])
    assert m3.logodds_at([[5.05, 0.01, 0.01]])[0][0] == pytest.approx(math.log(18) + math.log(8), rel=1e-6)


def test_hit_takes_precedence_over_other_beams_miss_in_one_ping() -> None:
    # beam 0 ends at x=3 (hit), beam 1 at the same azimuth continues to 6: the hit cell is not carved
    m = OccupancyMap(OccupancyConfig(resolution_m=0.1, l_min=-10, l_max=10))
    m.integrate([[3.03, 6.03]], [0.0, 0.0], ID, min_range_m=1.0, max_range_m=8.0, pd=0.9, pfa=0.05)
    lo, _ = m.logodds_at([[3.05, 0.01, 0.01], [2.05, 0.01, 0.01]])
    assert lo[0] == pytest.approx(math.log(18), rel=1e-6)  # one hit update, no miss
    assert lo[1] == pytest.approx(math.log(0.1 / 0.95), rel=1e-6)  # crossed by two beams: one update


def test_fixed_model_and_argument_errors() -> None:
    m = OccupancyMap(OccupancyConfig(resolution_m=0.1))
    m.integrate([2.03], [0.0], ID, min_range_m=1.0, max_range_m=3.0, model=SensorModel.fixed(0.8, 0.3))
    assert m.logodds_at([[2.05, 0.01, 0.01]])[0][0] == pytest.approx(math.log(4), rel=1e-6)
    with pytest.raises(InputError, match="pd/pfa"):
        m.integrate([2.0], [0.0], ID, min_range_m=1.0, max_range_m=3.0)
    # uninformative pD/pFA (NaN, or pD <= pFA): skipped and counted, or the fallback model is used
    n_obs = len(m.observed_cells())
    assert m.integrate([[2.53], [2.53]], [0.0], _poses(np.stack([np.eye(3)] * 2), np.full((2, 3), 0.01)),
                       min_range_m=1.0, max_range_m=3.0, pd=[0.1, np.nan], pfa=[0.3, 0.1]) == 0
    assert m.n_uninformative == 2 and len(m.observed_cells()) == n_obs
    m.integrate([2.53], [0.0], ID, min_range_m=1.0, max_range_m=3.0, pd=np.nan, pfa=np.nan,
                model=SensorModel.fixed(0.8, 0.3))
    assert m.logodds_at([[2.55, 0.01, 0.01]])[0][0] == pytest.approx(math.log(4), rel=1e-6)
    with pytest.raises(InputError, match="chunk_size"):
        OccupancyConfig(chunk_size=12)


def test_diagonal_ray_is_6_connected_and_2d_grid() -> None:
    m = OccupancyMap(OccupancyConfig(resolution_m=0.1))
    R = Rotation.from_euler("ZY", [30, -20], degrees=True).as_matrix()
    m.integrate([4.0], [0.0], _poses(R, [0.0, 0.0, 0.0]), min_range_m=0.0, max_range_m=5.0, pd=0.9, pfa=0.05)
    cells = m.observed_cells()
    # Amanatides-Woo visits a face-connected chain from the start cell to the end cell
    end = np.floor(R @ [4.0, 0, 0] / 0.1).astype(int)
    assert (np.abs(end) + 0).sum() + 1 == len(cells)
    assert [0, 0, 0] in cells.tolist() and end.tolist() in cells.tolist()
    g = OccupancyMap(OccupancyConfig(resolution_m=0.1, dims=2))
    g.integrate([[4.0, 4.0]], [0.0, 0.2], _poses(R, [0.0, 0.0, -3.0]), min_range_m=0.0, max_range_m=5.0, pd=0.9, pfa=0.05)
    arr = g.to_array()
    assert arr.logodds.ndim == 2 and (g.observed_cells()[:, 2] == 0).all()
    assert arr.observed.sum() == len(g.observed_cells())
    assert (arr.logodds > 0).sum() == 2  # two hit cells in the plane


@pytest.mark.slow  # over a second in the fast subset
def test_sparse_storage_grows_and_export_matches_lookup() -> None:
    rng = np.random.default_rng(0)
    P, B = 60, 32
    t = rng.uniform(-200, 200, (P, 3))  # pings spread over a large area: far apart chunks
    m = OccupancyMap(OccupancyConfig(resolution_m=0.05, chunk_size=8))
    R = Rotation.random(P, random_state=3).as_matrix()
    r = rng.uniform(3, 9, (P, B))
    m.integrate(r, np.linspace(-0.25, 0.25, B), _poses(R, t), min_range_m=2.0, max_range_m=10.0, pd=0.9, pfa=0.05)
    assert m.n_chunks > 64  # grew past the initial pool
    # bounded memory: proportional to observed chunks, far below a dense grid of the bounding box
    dense_bytes = (400 / 0.05) ** 3 * 8
    assert m.memory_bytes < 1e-4 * dense_bytes
    assert m.memory_bytes < 2 * m.n_chunks * 8**3 * 8 + 64 * m.n_chunks * 8  # pool at most doubled
    occ = m.occupied_cells()
    assert len(occ) >= 0.9 * P * B / 4  # nearby beams may share a cell
    lo, seen = m.logodds_at(m.cell_centers(occ))
    assert seen.all() and (lo > 0).all()
    cloud = m.to_point_cloud()
    assert len(cloud) == len(occ) and (cloud.confidence > 0.5).all()
    with pytest.raises(InputError, match="max_cells"):
        m.to_array(max_cells=10_000)
    small = OccupancyMap(OccupancyConfig(resolution_m=0.05, chunk_size=8, max_chunks=70))
    with pytest.raises(InputError, match="max_chunks"):
        small.integrate(r, np.linspace(-0.25, 0.25, B), _poses(R, t), min_range_m=2.0, max_range_m=10.0, pd=0.9, pfa=0.05)
    # a limit below the initial pool holds too: the map stops at 3 chunks, not at the pool's 64
    tiny = OccupancyMap(OccupancyConfig(resolution_m=0.05, chunk_size=8, max_chunks=3))
    with pytest.raises(InputError, match="more than 3 chunks"):
        tiny.integrate(r, np.linspace(-0.25, 0.25, B), _poses(R, t), min_range_m=2.0, max_range_m=10.0, pd=0.9, pfa=0.05)
    assert tiny.n_chunks <= 3


def test_pd_without_pfa_names_the_missing_one_even_with_a_model() -> None:
    from sonarmap.mapping.occupancy import SensorModel

    m = OccupancyMap(OccupancyConfig(resolution_m=0.1))
    with pytest.raises(InputError, match="^pfa: pd and pfa go together"):
        m.integrate([2.03], [0.0], ID, min_range_m=1.0, max_range_m=3.0, pd=0.9, model=SensorModel(0.85, -0.4))
    with pytest.raises(InputError, match="^pd: pd and pfa go together"):
        m.integrate([2.03], [0.0], ID, min_range_m=1.0, max_range_m=3.0, pfa=0.05)


def test_dense_array_values_and_iou() -> None:
    m = OccupancyMap(OccupancyConfig(resolution_m=0.1))
    m.integrate([2.03], [0.0], ID, min_range_m=1.0, max_range_m=3.0, pd=0.9, pfa=0.05)
    a = m.to_array()
    assert a.logodds.shape == (11, 1, 1) and np.allclose(a.origin_m, [1.0, 0.0, 0.0])
    assert a.probability[-1, 0, 0] == pytest.approx(18 / 19, rel=1e-5)
    assert np.isfinite(a.probability).all()
    pts = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.5, 0.0, 0.0]])
    v = voxelize(pts, 0.1)
    assert len(v) == 2
    assert voxel_iou(v, v[:1]) == pytest.approx(0.5) and voxel_iou(v, [[9, 9, 9]]) == 0.0


def test_cell_and_arc_sensor_model() -> None:
    from sonarmap.mapping.occupancy import pd_pfa_increments

    lh, lm = pd_pfa_increments(0.9, 0.01)  # one bin per cell, one arc cell: the per-pixel model
    assert lh == pytest.approx(math.log(90)) and lm == pytest.approx(math.log(0.1 / 0.99))
    f_cell = 1 - 0.99**3
    lh3, lm3 = pd_pfa_increments(0.9, 0.01, bins_per_cell=3)
    assert lh3 == pytest.approx(math.log(0.9 / f_cell)) and lm3 == pytest.approx(math.log(0.1 / (1 - f_cell)))
    lha, _ = pd_pfa_increments(0.9, 0.01, bins_per_cell=3, n_arc=4)  # hit shared over a 4-cell arc
    assert lha == pytest.approx(math.log(0.9 / (f_cell + (1 - f_cell) * 0.9 * 0.75)))
    assert 0 < lha < lh3
    with pytest.raises(InputError, match="pd/pfa"):
        SensorModel.from_pd_pfa(0.5, 0.3, bins_per_cell=5)  # per cell the detector is no better than chance


def test_range_error_weakens_the_hit_and_arc_hits_may_carry_nothing() -> None:
    from sonarmap.mapping.occupancy import pd_pfa_increments

    f_cell = 1 - 0.99**3
    q = 1 - 1.0 * math.sqrt(2 / math.pi) / 3  # 1-bin range error over a 3-bin cell
    lh, lm = pd_pfa_increments(0.9, 0.01, bins_per_cell=3, range_sigma_bins=1.0)
    assert lh == pytest.approx(math.log(0.9 * q / (f_cell + (1 - f_cell) * 0.9 * 0.5 * (1 - q))))
    assert lm == pytest.approx(math.log(0.1 / (1 - f_cell)))  # the miss is unchanged
    assert 0 < lh < pd_pfa_increments(0.9, 0.01, bins_per_cell=3)[0]
    # a finer cell (fewer bins) loses more of its returns to the neighbours: weaker still
    assert pd_pfa_increments(0.9, 0.01, bins_per_cell=1.5, range_sigma_bins=1.0)[0] < lh
    # an arc of n cells: a free arc cell sees the return (at this range) with probability (1 - 1/n) q
    lha, _ = pd_pfa_increments(0.9, 0.01, bins_per_cell=3, n_arc=4, range_sigma_bins=1.0)
    assert lha == pytest.approx(math.log(0.9 * q / (f_cell + (1 - f_cell) * 0.9 * (0.75 * q + 0.5 * (1 - q)))))


def test_ping_with_uninformative_hits_still_carves_free_space() -> None:
    # 1 bin per cell and a 1.5-bin range error: q = 0.20, the hit carries no information
    # (log(pD q / (pfa + pD (1 - q)/2)) < 0), but the miss does - the ping is integrated with a
    # zero hit increment instead of being dropped
    m = OccupancyMap(OccupancyConfig(resolution_m=0.1, range_sigma_bins=1.5, l_min=-10.0))
    assert m.integrate([2.53], [0.0], ID, min_range_m=1.0, max_range_m=3.0, pd=0.9, pfa=1e-4,
                       range_resolution_m=0.1) == 1
    lo, seen = m.logodds_at([[2.55, 0.01, 0.01], [1.55, 0.01, 0.01]])
    assert seen.all() and lo[0] == 0.0  # the return's cell: observed, unchanged
    assert lo[1] == pytest.approx(math.log(0.1 / (1 - 1e-4)), rel=1e-5)  # free space before it
    assert m.n_uninformative == 0
    with pytest.raises(InputError, match="range_sigma_bins"):
        OccupancyConfig(range_sigma_bins=-1.0)


def test_default_clamps_keep_evidence_that_octomap_clamps_lose() -> None:
    """Three hits then two misses of the pD/pFA model: the default bounds (0.001 / 0.999) keep the
    cell occupied; OctoMap's (0.12 / 0.97) cap the hits at 3.5 and the misses free it."""
    from sonarmap.mapping.occupancy import OCTOMAP_CLAMP_LOGODDS, pd_pfa_increments

    lh, lm = pd_pfa_increments(0.93, 3e-5, bins_per_cell=5.7, range_sigma_bins=1.0)
    assert 2.0 < lh < 3.0 and -3.0 < lm < -2.4  # the increments a simulated DIDSON survey gets
    assert OCTOMAP_CLAMP_LOGODDS == pytest.approx((math.log(0.1192 / 0.8808), math.log(0.971 / 0.029)))
    poses = _poses(np.stack([np.eye(3)] * 5), np.full((5, 3), 0.01))
    ranges = np.array([[5.03]] * 3 + [[5.23]] * 2)  # the last two pings' beams pass the cell at 5.0-5.1
    got = {}
    for name, kw in (("default", {}), ("octomap", dict(zip(("l_min", "l_max"), OCTOMAP_CLAMP_LOGODDS)))):
        m = OccupancyMap(OccupancyConfig(resolution_m=0.1, **kw))
        m.integrate(ranges, [0.0], poses, min_range_m=1.0, max_range_m=8.0, pd=0.93, pfa=3e-5,
                    range_resolution_m=0.1 / 5.7)
        got[name] = float(m.logodds_at([[5.05, 0.01, 0.01]])[0][0])
    l_max = OccupancyConfig().l_max
    assert l_max == pytest.approx(math.log(999)) and 3 * lh > l_max
    assert got["default"] == pytest.approx(l_max + 2 * lm, rel=1e-5) and got["default"] > 0
    assert got["octomap"] == pytest.approx(OCTOMAP_CLAMP_LOGODDS[1] + 2 * lm, rel=1e-5) and got["octomap"] < 0


def test_elevation_arc_discount_is_an_option() -> None:
    """n_elevation rays over a wide aperture: by default every ray's hit counts in full (the
    surface spans the aperture); with elevation_ambiguity the hit is shared over the arc's cells."""
    from sonarmap.mapping.occupancy import pd_pfa_increments

    dr = 0.1 / 3
    vals = {}
    for amb in (False, True):
        m = OccupancyMap(OccupancyConfig(resolution_m=0.1, n_elevation=3, vertical_aperture_rad=math.radians(6),
                                         elevation_ambiguity=amb))
        m.integrate([4.03], [0.0], ID, min_range_m=1.0, max_range_m=8.0, pd=0.9, pfa=1e-4, range_resolution_m=dr)
        vals[amb] = float(m.logodds_at([[4.05, 0.01, 0.01]])[0][0])  # the centre ray's hit cell
    full, _ = pd_pfa_increments(0.9, 1e-4, bins_per_cell=3, range_sigma_bins=1.0)
    n_arc = math.ceil(4.03 * math.radians(6) / 0.1)  # 5 cells, capped at n_elevation = 3
    shared, _ = pd_pfa_increments(0.9, 1e-4, bins_per_cell=3, n_arc=3, range_sigma_bins=1.0)
    assert n_arc > 3 and vals[False] == pytest.approx(full, rel=1e-5)
    assert vals[True] == pytest.approx(shared, rel=1e-5) and 0 < shared < full


@pytest.mark.parametrize("z_chunks", [-(2**20) - 1, 2**20, -(2**20) + 1, 2**20 - 1])
def test_a_ray_without_a_return_outside_the_packable_extent_is_refused(z_chunks: int) -> None:
    """Free space only (no hit): the walk's first chunk used to be range-checked only when its
    packed key differed from the last one - the key of chunk z = -2**20 - 1 is -1, the table's
    EMPTY marker, so it was written at a negative pool row (memory corruption).  Every chunk at
    or beyond +-(2**20 - 1) is refused with the extent error, before any voxel is written."""
    m = OccupancyMap(OccupancyConfig(resolution_m=1.0, chunk_size=2))
    z = (z_chunks * 2 + 0.5) * 1.0  # the sensor inside chunk z_chunks (2 cells per chunk)
    with pytest.raises(InputError, match="representable map extent"):
        m.integrate([np.nan], [0.0], _poses(np.eye(3), [[0.5, 0.5, z]]), min_range_m=0.5, max_range_m=3.0,
                    pd=0.9, pfa=0.05)
    assert len(m.observed_cells()) == 0


def test_rays_just_inside_the_packable_extent_are_mapped() -> None:
    m = OccupancyMap(OccupancyConfig(resolution_m=1.0, chunk_size=2))
    z = ((2**20 - 2) * 2 + 0.5) * 1.0  # the last chunk inside the limit
    m.integrate([2.2], [0.0], _poses(np.eye(3), [[0.5, 0.5, z]]), min_range_m=0.5, max_range_m=3.0, pd=0.9, pfa=0.05)
    assert m.occupied_cells().tolist() == [[2, 0, 2**21 - 4]]
