"""Mapping speed: registration of 1 M returns; occupancy updates of DIDSON-size pings at 0.05 m.

Registration baseline: a per-ping Python loop (``R @ p + t`` per ping), as lab scripts do, timed
in the same process.  Occupancy: a fresh sparse voxel map per call (so chunk allocation and hash
growth are included), 96 beams over 2.25-11.25 m (rays ~9 m: 20 % of beams have no return and
carve to the maximum range), a vehicle moving 2 cm per ping; the target is 500 pings/s = 2 ms/ping.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from run import timeit

from sonarmap.geometry import preset
from sonarmap.mapping.occupancy import OccupancyConfig, OccupancyMap
from sonarmap.mapping.poses import Extrinsics, Trajectory, sensor_poses
from sonarmap.mapping.register import register_returns


def _survey(n_pings: int, seed: int = 0) -> tuple[Any, Any, Any]:
    g = preset("didson-hf")
    rng = np.random.default_rng(seed)
    t = 1_700_000_000_000_000_000 + np.arange(n_pings, dtype=np.int64) * 100_000_000
    pos = np.zeros((n_pings, 3))
    pos[:, 0] = np.arange(n_pings) * 0.02
    pos[:, 2] = 2.0
    yaw = np.deg2rad(rng.normal(0, 2, n_pings))
    from scipy.spatial.transform import Rotation

    q = Rotation.from_euler("z", yaw[:, None]).as_quat()
    traj = Trajectory(t, pos, q)
    ext = Extrinsics.from_rpy_deg([0.3, 0.0, 0.2], 90.0, 0.0, 90.0)  # profiling the starboard side
    poses = sensor_poses(traj, t, extrinsics=ext)
    r = rng.uniform(5.0, 9.0, (n_pings, g.n_beams))
    r[rng.random(r.shape) < 0.2] = np.nan
    return g, r, poses


def run(quick: bool = False) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    # ---- registration of 1 M returns
    n_pings = math.ceil(1_000_000 / 96)
    g, r, poses = _survey(n_pings)
    r = np.where(np.isfinite(r), r, 7.0)  # every beam a return: 1 M points
    r_full = r.reshape(-1)[:1_000_000]
    assert r_full.size == 1_000_000
    inten = np.ones_like(r, dtype=np.float32)
    rep = 3 if quick else 10
    t_reg = timeit(lambda: register_returns(r, g.azimuth_rad, poses, intensity=inten, confidence=inten),
                   repeat=rep, warmup=1)
    ca, sa = np.cos(g.azimuth_rad), np.sin(g.azimuth_rad)

    def baseline() -> Any:
        out = []
        for p in range(n_pings):
            ps = np.stack([r[p] * ca, r[p] * sa, np.zeros_like(ca)], axis=1)
            out.append(ps @ poses.rotation[p].T + poses.translation_m[p])
        return np.concatenate(out)

    t_base = timeit(baseline, repeat=1 if quick else 3, warmup=1)
    rows.append({"benchmark": "mapping", "case": f"register {r.size / 1e6:.2f} M returns (zero elevation)",
                 "median_ms": t_reg, "target_ms": 200.0, "baseline": "per-ping loop", "baseline_ms": t_base})
    t_edge = timeit(lambda: register_returns(r, g.azimuth_rad, poses, intensity=inten, confidence=inten,
                                             azimuth_beamwidth_rad=g.azimuth_beamwidth_rad), repeat=rep, warmup=1)
    rows.append({"benchmark": "mapping", "case": f"register {r.size / 1e6:.2f} M returns at the footprint edge",
                 "median_ms": t_edge, "target_ms": 200.0, "baseline": "on the beams' axes", "baseline_ms": t_reg})
    # ---- occupancy updates
    n_occ = 100 if quick else 400
    g, r, poses = _survey(n_occ, seed=1)
    for dims in (3, 2):
        cfg = OccupancyConfig(resolution_m=0.05, dims=dims)

        def integrate(cfg: OccupancyConfig = cfg) -> None:
            m = OccupancyMap(cfg)
            m.integrate(r, g.azimuth_rad, poses, min_range_m=g.min_range_m, max_range_m=g.max_range_m,
                        pd=0.9, pfa=0.05)

        t_occ = timeit(integrate, repeat=3 if quick else 7, warmup=1)
        per_ping = t_occ / n_occ
        rows.append({"benchmark": "mapping",
                     "case": f"occupancy {dims}-D 0.05 m, per DIDSON ping (batch {n_occ})",
                     "median_ms": per_ping, "target_ms": 2.0,
                     "note": f"{1e3 / per_ping:.0f} pings/s"})
    return rows
