"""Simulated surveys: a vehicle trajectory past a known surface, with pings, poses and truth.

Two scenes (world NED, metres):

* ``"hull"`` - a ship-hull side: the surface ``y = f(x, z)`` east of the vehicle, curved in depth
  (bilge) with a few smooth bumps (anodes, weld seams); the vehicle runs north along it at
  ``standoff_m`` with the sonar looking starboard and its imaging plane vertical (a profiling
  configuration, the HAUV's hull-inspection setup).
* ``"seafloor"`` - terrain ``z = h(x, y)`` below the vehicle (sand ripples across track, a gentle
  along-track slope, a few mounds) with the sonar looking down, imaging plane across track.

In both, the true surface's normals lie (nearly) in the imaging plane, so the zero-elevation
(profiling) assumption of :mod:`sonarmap.mapping.register` holds up to the small bumps and the
vehicle's attitude wobble - which is what lets map accuracy be measured in range bins.

Each ping is rendered by :func:`sonarmap.simulate.simulate_ping` from the surface samples near the
ping's imaging plane, transformed into the sensor frame (``Scene.transformed``).  Truth per beam
is the zero-elevation ray's first intersection with the analytic surface.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry, as_geometry
from sonarmap.mapping.poses import Extrinsics, SensorPoses, Trajectory, sensor_poses
from sonarmap.ping import Ping

__all__ = [
    "SurveyConfig",
    "SimSurvey",
    "HullSurface",
    "SeafloorSurface",
    "simulate_survey",
    "truth_ranges",
    "dropout_losses_db",
]

SurveyKind = Literal["hull", "seafloor"]
T0_NS = 1_700_000_000_000_000_000


# ============================================================================ analytic surfaces
@dataclasses.dataclass(frozen=True)
class HullSurface:
    """Hull side ``y = y0 + c (z - zc)^2 + sum of Gaussian bumps`` (world NED; water at smaller y)."""

    y0_m: float = 6.0
    zc_m: float = 2.0
    curvature_1_m: float = 0.04
    bumps: tuple[tuple[float, float, float, float], ...] = ()  # (x, z, height (toward -y), sigma)

    def height(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        """``y`` of the surface at ``x = u``, ``z = v``."""
        y = self.y0_m + self.curvature_1_m * (v - self.zc_m) ** 2
        for bx, bz, a, s in self.bumps:
            y = y - a * np.exp(-((u - bx) ** 2 + (v - bz) ** 2) / (2 * s * s))
        return y

    def signed(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Negative in the water, positive inside the hull."""
        return p[..., 1] - self.height(p[..., 0], p[..., 2])

    def gradient(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Gradient of :meth:`signed` (points into the hull)."""
        u, v = p[..., 0], p[..., 2]
        gu = np.zeros_like(u)
        gv = 2 * self.curvature_1_m * (v - self.zc_m)
        for bx, bz, a, s in self.bumps:
            e = a * np.exp(-((u - bx) ** 2 + (v - bz) ** 2) / (2 * s * s))
            gu = gu + e * (u - bx) / (s * s)
            gv = gv + e * (v - bz) / (s * s)
        return np.stack([-gu, np.ones_like(u), -gv], axis=-1)

    def point(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        """Surface point at parameters ``(u, v) = (x, z)``."""
        return np.stack([u, self.height(u, v), v], axis=-1)


@dataclasses.dataclass(frozen=True)
class SeafloorSurface:
    """Seafloor ``z = z0 + ripples(y) + slope x + mounds`` (world NED; water at smaller z)."""

    z0_m: float = 6.0
    ripple_amp_m: float = 0.06
    ripple_wavelength_m: float = 0.7
    slope: float = 0.02
    bumps: tuple[tuple[float, float, float, float], ...] = ()  # (x, y, height (up), sigma)

    def height(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        """``z`` of the seafloor at ``x = u``, ``y = v``."""
        z = self.z0_m + self.ripple_amp_m * np.sin(2 * np.pi * v / self.ripple_wavelength_m) + self.slope * u
        for bx, by, a, s in self.bumps:
            z = z - a * np.exp(-((u - bx) ** 2 + (v - by) ** 2) / (2 * s * s))
        return z

    def signed(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Negative in the water, positive below the seafloor."""
        return p[..., 2] - self.height(p[..., 0], p[..., 1])

    def gradient(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Gradient of :meth:`signed` (points into the ground)."""
        u, v = p[..., 0], p[..., 1]
        k = 2 * np.pi / self.ripple_wavelength_m
        gu = np.full_like(u, self.slope)
        gv = self.ripple_amp_m * k * np.cos(k * v)
        for bx, by, a, s in self.bumps:
            e = a * np.exp(-((u - bx) ** 2 + (v - by) ** 2) / (2 * s * s))
            gu = gu + e * (u - bx) / (s * s)
            gv = gv + e * (v - by) / (s * s)
        return np.stack([-gu, -gv, np.ones_like(u)], axis=-1)

    def point(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        """Surface point at parameters ``(u, v) = (x, y)``."""
        return np.stack([u, v, self.height(u, v)], axis=-1)


Surface = HullSurface | SeafloorSurface


def surface_distance(surface: Surface, points: ArrayLike) -> NDArray[np.float64]:
    """First-order distance ``|F(p)| / |grad F(p)|`` of points to the surface (exact for planes)."""
    p = np.asarray(points, dtype=np.float64)
    return np.abs(surface.signed(p)) / np.linalg.norm(surface.gradient(p), axis=-1)


# ============================================================================ configuration
@dataclasses.dataclass(frozen=True)
class SurveyConfig:
    """A simulated survey.

    Parameters
    ----------
    kind : {"hull", "seafloor"}
        Which scene.
    n_pings : int
        Number of pings.
    ping_rate_hz : float
        Ping rate; with ``speed_m_s`` it sets the along-track ping spacing.
    speed_m_s : float
        Vehicle speed (north).
    standoff_m : float
        Distance from the sonar to the surface (hull: horizontal; seafloor: altitude).
    nav_rate_hz : float
        Rate of the navigation (trajectory) samples; ping times fall between them.
    wobble_deg : float
        Amplitude of the vehicle's roll/pitch/yaw oscillation.
    sample_spacing_m : float
        Surface sample spacing for rendering (finer than a range bin).
    geometry : SonarGeometry or str
        The sonar (preset name, JSON path or object).
    seed : int
        Seeds the renderer's noise (ping ``i`` uses ``seed + i``).
    reflectivity_db : float
        Surface backscatter strength.
    dropout_fraction : float
        Fraction of pings whose echoes are attenuated (aeration: bubble sweeps from thrusters or
        the ship's wake, which blank hull-inspection sonar frames intermittently), chosen at
        random from ``seed``.
    dropout_db : (float, float)
        Range of the two-way attenuation of those pings, drawn uniformly.
    """

    kind: SurveyKind = "hull"
    n_pings: int = 50
    ping_rate_hz: float = 5.0
    speed_m_s: float = 0.5
    standoff_m: float = 6.0
    nav_rate_hz: float = 20.0
    wobble_deg: float = 1.0
    sample_spacing_m: float = 0.01
    geometry: Any = "didson-hf"
    seed: int = 0
    reflectivity_db: float = -20.0
    dropout_fraction: float = 0.0
    dropout_db: tuple[float, float] = (6.0, 15.0)

    def __post_init__(self) -> None:
        if not 0.0 <= self.dropout_fraction <= 1.0:
            raise InputError(f"dropout_fraction: must lie in [0, 1], got {self.dropout_fraction}")
        lo_db, hi_db = self.dropout_db
        if not 0.0 <= lo_db <= hi_db:
            raise InputError(f"dropout_db: need 0 <= low <= high, got {self.dropout_db}")
        if self.kind not in ("hull", "seafloor"):
            raise InputError(f"kind: must be 'hull' or 'seafloor', got {self.kind!r}")
        if self.n_pings < 1:
            raise InputError(f"n_pings: must be >= 1, got {self.n_pings}")
        for name in ("ping_rate_hz", "nav_rate_hz", "sample_spacing_m", "standoff_m"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name}: must be positive, got {getattr(self, name)}")


@dataclasses.dataclass(frozen=True, eq=False)
class SimSurvey:
    """A simulated survey with its ground truth.

    Attributes
    ----------
    pings : list of Ping
        Rendered pings (``pose`` = the vehicle pose at the ping); empty when not rendered.
    trajectory : Trajectory
        Navigation samples (world NED, body FRD) at ``nav_rate_hz``.
    extrinsics : Extrinsics
        The sonar mounting.
    poses : SensorPoses
        True sensor -> world transforms at the ping times.
    ping_times_ns : ndarray of int64, shape (n_pings,)
    geometry : SonarGeometry
    surface : HullSurface or SeafloorSurface
        The analytic truth surface.
    surface_points_m, surface_normals : ndarray, shape (n, 3)
        World surface samples (normals point into the water).
    truth_range_m : ndarray, shape (n_pings, n_beams)
        Zero-elevation first intersection of each beam with the surface (NaN = none in window).
    sim_truth : list
        The renderer's per-ping :class:`SimResult` (without ``ping``) when rendered.
    config : SurveyConfig
    """

    pings: list[Ping]
    trajectory: Trajectory
    extrinsics: Extrinsics
    poses: SensorPoses
    ping_times_ns: NDArray[np.int64]
    geometry: SonarGeometry
    surface: Any
    surface_points_m: NDArray[np.float64]
    surface_normals: NDArray[np.float64]
    truth_range_m: NDArray[np.float64]
    sim_truth: list[Any]
    config: SurveyConfig

    @property
    def visible_points_m(self) -> NDArray[np.float64]:
        """World points of the truth returns (visible surface), shape (n, 3)."""
        return _ray_points(self.truth_range_m, self.geometry.azimuth_rad, self.poses)

    def write(self, directory: str | os.PathLike[str], *, bit_depth: int = 8) -> Path:
        """Write pings (PNG + JSON), ``poses.csv``, ``mount.json`` and ``truth.npz``; returns the dir."""
        from sonarmap._atomic import atomic_path, make_output_dir
        from sonarmap.io.pngjson import write_png_ping
        from sonarmap.mapping.poses import save_extrinsics, write_trajectory_csv

        d = Path(directory)
        make_output_dir(d / "pings")
        for ping in self.pings:
            write_png_ping(ping, d / "pings", bit_depth=bit_depth)
        write_trajectory_csv(self.trajectory, d / "poses.csv")
        save_extrinsics(self.extrinsics, d / "mount.json")
        with atomic_path(d / "truth.npz") as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                ping_time_ns=self.ping_times_ns,
                truth_range_m=self.truth_range_m,
                visible_points_m=self.visible_points_m,
                surface_points_m=self.surface_points_m,
                surface_normals=self.surface_normals,
            )
        return d


# ============================================================================ construction
def _scene_surface(cfg: SurveyConfig, x_lo: float, x_hi: float) -> Surface:
    rng = np.random.default_rng(cfg.seed + 12345)
    n_b = max(2, int((x_hi - x_lo) / 2.0))
    if cfg.kind == "hull":
        bx = rng.uniform(x_lo + 1, x_hi - 1, n_b)
        bz = rng.uniform(1.2, 2.8, n_b)
        bumps = tuple((float(a), float(b), 0.08, 0.2) for a, b in zip(bx, bz, strict=True))
        return HullSurface(y0_m=cfg.standoff_m, zc_m=2.0, bumps=bumps)
    bx = rng.uniform(x_lo + 1, x_hi - 1, n_b)
    by = rng.uniform(-1.0, 1.0, n_b)
    bumps = tuple((float(a), float(b), 0.15, 0.3) for a, b in zip(bx, by, strict=True))
    return SeafloorSurface(z0_m=2.0 + cfg.standoff_m, bumps=bumps)


def _mount(kind: str) -> Extrinsics:
    if kind == "hull":
        # boresight east (starboard), azimuth (+y_s) downward: imaging plane vertical, across track
        R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    else:
        # boresight down, +y_s to starboard: imaging plane vertical, across track
        R = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    from scipy.spatial.transform import Rotation

    return Extrinsics(np.array([0.3, 0.0, 0.2]), Rotation.from_matrix(R).as_quat())


def _trajectory(cfg: SurveyConfig) -> tuple[Trajectory, NDArray[np.int64]]:
    from scipy.spatial.transform import Rotation

    dt_ping = 1e9 / cfg.ping_rate_hz
    ping_t = T0_NS + np.rint(np.arange(cfg.n_pings) * dt_ping + 0.37 * 1e9 / cfg.nav_rate_hz).astype(np.int64)
    span = ping_t[-1] - T0_NS + 2 * 1e9 / cfg.nav_rate_hz
    n_nav = int(math.ceil(span * cfg.nav_rate_hz / 1e9)) + 1
    nav_t = T0_NS + np.rint(np.arange(n_nav) * 1e9 / cfg.nav_rate_hz).astype(np.int64)
    ts = (nav_t - T0_NS) * 1e-9
    pos = np.zeros((n_nav, 3))
    pos[:, 0] = cfg.speed_m_s * ts
    pos[:, 1] = 0.02 * np.sin(2 * np.pi * ts / 7.0)
    pos[:, 2] = 2.0 + 0.02 * np.sin(2 * np.pi * ts / 5.0)
    w = math.radians(cfg.wobble_deg)
    ypr = np.stack([w * np.sin(2 * np.pi * ts / 6.0), w * np.sin(2 * np.pi * ts / 4.0 + 1), w * np.sin(2 * np.pi * ts / 3.0)], axis=1)
    q = Rotation.from_euler("ZYX", ypr).as_quat()
    return Trajectory(nav_t, pos, q, source="simulated"), ping_t


def _surface_samples(
    surface: Surface, cfg: SurveyConfig, x_lo: float, x_hi: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    h = cfg.sample_spacing_m
    u = np.arange(x_lo, x_hi, h) + h / 2
    if cfg.kind == "hull":
        v = np.arange(-0.5, 4.5, h) + h / 2  # depth z
    else:
        half = cfg.standoff_m * 0.35 + 0.5
        v = np.arange(-half, half, h) + h / 2  # east y
    U, V = np.meshgrid(u, v, indexing="ij")
    P = surface.point(U.ravel(), V.ravel())
    G = surface.gradient(P)
    gn = np.linalg.norm(G, axis=1)
    normals = -G / gn[:, None]  # into the water
    # area element of the graph surface: |grad F| / |dF/d(height axis)| * h^2 (dF/d height = 1)
    area = gn * h * h
    return P, normals, area


def dropout_losses_db(config: SurveyConfig) -> NDArray[np.float64]:
    """Per-ping echo attenuation (dB, 0 for unaffected pings) of a survey's dropouts."""
    rng = np.random.default_rng(config.seed + 4242)
    hit = rng.random(config.n_pings) < config.dropout_fraction
    loss = rng.uniform(config.dropout_db[0], config.dropout_db[1], config.n_pings)
    return np.where(hit, loss, 0.0)


def _ray_points(range_m: NDArray[np.float64], azimuth_rad: NDArray[np.float64], poses: SensorPoses) -> NDArray[np.float64]:
    d = np.stack([np.cos(azimuth_rad), np.sin(azimuth_rad), np.zeros_like(azimuth_rad)], axis=1)
    ok = np.isfinite(range_m)
    pts = poses.translation_m[:, None, :] + range_m[:, :, None] * np.einsum("pij,bj->pbi", poses.rotation, d)
    return pts[ok]


def truth_ranges(
    surface: Surface,
    poses: SensorPoses,
    geometry: SonarGeometry,
    *,
    step_m: float = 0.02,
    elevation_rad: float = 0.0,
) -> NDArray[np.float64]:
    """First intersection range of each beam's ray (at ``elevation_rad``) with the surface.

    Marches ``[min_range, max_range]`` in ``step_m`` steps for the first water -> surface sign
    change, then bisects to 1e-7 m.  NaN where no intersection lies in the window.

    Returns
    -------
    ndarray, shape (n_pings, n_beams)
    """
    az = geometry.azimuth_rad
    ce, se = math.cos(elevation_rad), math.sin(elevation_rad)
    d_s = np.stack([np.cos(az) * ce, np.sin(az) * ce, np.full_like(az, se)], axis=1)
    d_w = np.einsum("pij,bj->pbi", poses.rotation, d_s)  # (P, B, 3)
    o = poses.translation_m[:, None, :]
    s = np.arange(geometry.min_range_m, geometry.max_range_m + step_m, step_m)
    P, B = d_w.shape[:2]
    out = np.full((P, B), np.nan)
    for p in range(P):  # bounded memory: (B, n_steps, 3) per ping
        pts = o[p][:, None, :] + s[None, :, None] * d_w[p][:, None, :]
        f = surface.signed(pts)
        cross = (f[:, :-1] < 0) & (f[:, 1:] >= 0)
        has = cross.any(axis=1)
        if not has.any():
            continue
        k = cross.argmax(axis=1)
        lo, hi = s[k], s[k + 1]
        dd = d_w[p]
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            fm = surface.signed(o[p] + mid[:, None] * dd)
            inside = fm >= 0
            hi = np.where(inside, mid, hi)
            lo = np.where(inside, lo, mid)
        r = 0.5 * (lo + hi)
        ok = has & (r >= geometry.min_range_m) & (r < geometry.max_range_m)
        out[p, ok] = r[ok]
    return out


def _plane_samples(pts: np.ndarray, xs: np.ndarray, R_ws: np.ndarray, t_ws: np.ndarray, *, r_cut: float,
                   tan_el: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Surface samples a ping can see: sensor-frame points and their indices into ``pts``.

    The samples within the vertical aperture (``tan_el``, plus one sample spacing ``h``) of the
    ping's imaging plane (normal = sensor z), in front of the sonar and within ``r_cut``; searched
    in the slab of x (``xs``, increasing) that the plane, nearly across track, can reach.
    """
    n = R_ws[:, 2]
    d_max = r_cut * tan_el + h
    nx = abs(float(n[0]))
    half = (d_max + r_cut * math.sqrt(max(0.0, 1.0 - nx * nx))) / max(nx, 1e-3)
    lo, hi = np.searchsorted(xs, [t_ws[0] - half, t_ws[0] + half])
    dist = pts[lo:hi] @ n - float(n @ t_ws)
    near = lo + np.flatnonzero(np.abs(dist) <= d_max)
    ps = (pts[near] - t_ws) @ R_ws  # world -> sensor: R_ws^T (p - t)
    rho = np.hypot(ps[:, 0], ps[:, 1])
    keep = (np.abs(ps[:, 2]) <= rho * tan_el + h) & (np.hypot(rho, ps[:, 2]) <= r_cut) & (ps[:, 0] > 0)
    return ps[keep], near[keep]


def simulate_survey(
    config: SurveyConfig | None = None,
    *,
    render: bool = True,
    sim_config: Any = None,
    **overrides: Any,
) -> SimSurvey:
    """Simulate a survey: trajectory, surface, truth ranges and (optionally) rendered pings.

    Parameters
    ----------
    config : SurveyConfig, optional
        Survey parameters; keyword ``overrides`` replace its fields.
    render : bool
        Render pings with :func:`sonarmap.simulate.simulate_ping` (False: truth only, fast).
    sim_config : SimulationConfig, optional
        Renderer options (defaults to the simulator's).

    Returns
    -------
    SimSurvey
    """
    cfg = dataclasses.replace(config or SurveyConfig(), **overrides) if overrides else (config or SurveyConfig())
    geometry = as_geometry(cfg.geometry)
    traj, ping_t = _trajectory(cfg)
    ext = _mount(cfg.kind)
    poses = sensor_poses(traj, ping_t, extrinsics=ext)
    vehicle = traj.interpolate(ping_t)
    x0 = float(poses.translation_m[:, 0].min())
    x1 = float(poses.translation_m[:, 0].max())
    half_ap = geometry.max_range_m * math.tan(math.radians(9.0))  # aperture (7 deg) + wobble margin
    x_lo, x_hi = x0 - half_ap - 0.3, x1 + half_ap + 0.3
    surface = _scene_surface(cfg, x_lo, x_hi)
    pts, normals, area = _surface_samples(surface, cfg, x_lo, x_hi)
    truth = truth_ranges(surface, poses, geometry)
    pings: list[Ping] = []
    sims: list[Any] = []
    if render:
        from sonarmap.ping import Pose
        from sonarmap.simulate import Scene, SimulationConfig, simulate_ping

        scfg = sim_config if sim_config is not None else SimulationConfig(beam_pattern="measured")
        loss_db = dropout_losses_db(cfg)
        # samples farther out of the imaging plane than this contribute nothing (Gaussian pattern:
        # weight exp(-4 ln2 2.5^2) = 3e-8 at 2.5 apertures; box pattern: half the aperture)
        w = scfg.elevation_aperture_rad
        half_el = 2.5 * w if scfg.elevation_pattern == "gaussian" else 0.5 * w
        tan_el = math.tan(half_el)
        r_cut = geometry.max_range_m + 0.05
        h = cfg.sample_spacing_m
        xs = pts[:, 0]  # samples are generated in increasing x (u-major grid)

        for i in range(cfg.n_pings):
            R_ws = poses.rotation[i]
            ps, sel = _plane_samples(pts, xs, R_ws, poses.translation_m[i], r_cut=r_cut, tan_el=tan_el, h=h)
            scene = Scene(
                points_m=ps,
                normals=normals[sel] @ R_ws,
                reflectivity=np.full(sel.size, 10.0 ** ((cfg.reflectivity_db - loss_db[i]) / 10.0)),
                labels=np.ones(sel.size, dtype=np.uint8),
                patch_area_m2=area[sel],
                name=f"survey-{cfg.kind}",
            )
            res = simulate_ping(scene, geometry, config=scfg, seed=cfg.seed + i, time_ns=int(ping_t[i]))
            pose = Pose(vehicle.translation_m[i], vehicle.orientation_xyzw[i], "ned")
            pings.append(res.ping.replace(pose=pose, source=f"sim:{cfg.kind}#{i}"))
            sims.append(dataclasses.replace(res, ping=None) if dataclasses.is_dataclass(res) else res)
    return SimSurvey(
        pings=pings, trajectory=traj, extrinsics=ext, poses=poses, ping_times_ns=ping_t, geometry=geometry,
        surface=surface, surface_points_m=pts, surface_normals=normals, truth_range_m=truth, sim_truth=sims,
        config=cfg,
    )
