"""Scenes for the simulator: surface samples in the sonar frame.

A :class:`Scene` is a set of small surface patches (or point scatterers), each with a position, a
unit normal, a backscatter coefficient, a class label and an area, all expressed in the **sonar
frame** of :mod:`sonarmap.geometry`: ``x`` forward, ``y`` starboard, ``z`` down, metres.  A sample
at ``p`` is seen at range ``|p|``, azimuth ``atan2(y, x)`` and elevation ``atan2(z, hypot(x, y))``.

Target strength of one sample (the ``TS`` of the active sonar equation, eq. 6 of Teixeira et al.)::

    sigma_i = reflectivity_i * patch_area_m2_i * |cos(incidence_i)| ** incidence_exponent

``reflectivity`` is linear (backscattering coefficient per square metre for surfaces, so that
``10 log10(reflectivity)`` is the Lambert parameter mu in dB).  A sample whose normal is the zero
vector is an isotropic point scatterer (fish): its cross-section ``reflectivity * patch_area_m2``
(use ``patch_area_m2 = 1`` and ``reflectivity = 10 ** (TS / 10)``) has no incidence dependence.

Surfaces are sampled on grids of spacing ``spacing_m`` (default 1.2 cm: finer than the DIDSON's
1.76 cm range bins and its ~7 cm beam spacing at 11 m) and cropped to a generous view cone
(:class:`View`) so scenes stay small (tens of thousands of samples).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError

__all__ = [
    "Scene",
    "View",
    "STRUCTURE",
    "CLUTTER",
    "SCENE_NAMES",
    "scene_from_name",
    "scene_scale_for",
    "view_for",
    "SCENE_REFERENCE_RANGE_M",
    "SLOPED_HULL_INCIDENCE_DEG",
    "sloped_hull",
    "sloped_hull_yaw_deg",
    "plane_patch",
    "planar_hull",
    "curved_hull",
    "seafloor",
    "propeller",
    "rudder",
    "fish_school",
    "point_target",
    "empty_scene",
]

#: Label of structure samples (hull, seafloor, propeller, rudder, targets).
STRUCTURE = 1
#: Label of clutter samples (fish, debris).
CLUTTER = 2

_DEFAULT_SPACING_M = 0.012

#: The per-sample arrays of a :class:`Scene` (one row per sample), in field order.
_SAMPLE_FIELDS = ("points_m", "normals", "reflectivity", "labels", "patch_area_m2")


def _db(x_db: float) -> float:
    return float(10.0 ** (x_db / 10.0))


@dataclasses.dataclass(frozen=True)
class View:
    """View cone used to crop sampled surfaces (sonar frame); generous defaults for DIDSON/ARIS.

    Parameters
    ----------
    max_range_m : float
        Samples farther than this are dropped.
    half_azimuth_rad : float
        Samples with ``|azimuth|`` above this are dropped (default 20 deg; DIDSON spans +-14.7).
    half_elevation_rad : float
        Samples with ``|elevation|`` above this are dropped (default 4 deg, four times the default
        1 deg vertical aperture of :class:`~sonarmap.simulate.SimulationConfig`; raise it when
        simulating a wider vertical beam, e.g. 14 deg without the concentrator lens).
    """

    max_range_m: float = 15.0
    half_azimuth_rad: float = math.radians(20.0)
    half_elevation_rad: float = math.radians(4.0)


def _as_array(values: ArrayLike, name: str, shape_tail: tuple[int, ...], dtype: type) -> NDArray:
    try:
        arr = np.array(values, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not a numeric array ({exc})") from None
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        want = "(N, " + ", ".join(str(s) for s in shape_tail) + ")" if shape_tail else "(N,)"
        raise InputError(f"{name}: expected shape {want}, got {arr.shape}")
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or infinite values")
    return arr


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """Surface samples in the sonar frame (x forward, y starboard, z down; metres).

    Parameters
    ----------
    points_m : array_like, shape (N, 3)
        Sample positions.
    normals : array_like, shape (N, 3)
        Unit surface normals (sign irrelevant: surfaces are two-sided); the zero vector marks an
        isotropic point scatterer.
    reflectivity : array_like, shape (N,)
        Linear backscattering coefficient (per m^2 for surfaces), >= 0.
    labels : array_like, shape (N,), uint8
        :data:`STRUCTURE` (1) or :data:`CLUTTER` (2).
    patch_area_m2 : array_like, shape (N,)
        Area represented by each sample (1 for point scatterers), >= 0.
    name : str
        Scene name (recorded in the truth files).

    Raises
    ------
    InputError
        Naming the argument, for wrong shapes, NaN/inf, non-unit normals, negative values or
        unknown labels.
    """

    points_m: NDArray[np.float64]
    normals: NDArray[np.float64]
    reflectivity: NDArray[np.float64]
    labels: NDArray[np.uint8]
    patch_area_m2: NDArray[np.float64]
    name: str = ""

    def __post_init__(self) -> None:
        pts = _as_array(self.points_m, "points_m", (3,), np.float64)
        nrm = _as_array(self.normals, "normals", (3,), np.float64)
        refl = _as_array(self.reflectivity, "reflectivity", (), np.float64)
        area = _as_array(self.patch_area_m2, "patch_area_m2", (), np.float64)
        lab_raw = _as_array(self.labels, "labels", (), np.float64)
        n = pts.shape[0]
        for name, arr in (("normals", nrm), ("reflectivity", refl), ("labels", lab_raw),
                          ("patch_area_m2", area)):
            if arr.shape[0] != n:
                raise InputError(f"{name}: has {arr.shape[0]} samples but points_m has {n}")
        norm = np.linalg.norm(nrm, axis=1)
        bad = (np.abs(norm - 1.0) > 1e-3) & (norm != 0.0)
        if np.any(bad):
            raise InputError(
                f"normals: {int(bad.sum())} normals are neither unit length nor zero "
                f"(first norm {norm[bad][0]:.4g})"
            )
        if np.any(refl < 0):
            raise InputError("reflectivity: must be >= 0 (linear backscatter coefficient)")
        if np.any(area < 0):
            raise InputError("patch_area_m2: must be >= 0")
        if not np.all(np.isin(lab_raw, (STRUCTURE, CLUTTER))):
            raise InputError(f"labels: must be {STRUCTURE} (structure) or {CLUTTER} (clutter)")
        lab = lab_raw.astype(np.uint8)
        nrm = np.where(norm[:, None] > 0, nrm / np.where(norm > 0, norm, 1.0)[:, None], 0.0)
        for arr in (pts, nrm, refl, area, lab):
            arr.setflags(write=False)
        object.__setattr__(self, "points_m", pts)
        object.__setattr__(self, "normals", nrm)
        object.__setattr__(self, "reflectivity", refl)
        object.__setattr__(self, "patch_area_m2", area)
        object.__setattr__(self, "labels", lab)
        object.__setattr__(self, "name", str(self.name))

    def __len__(self) -> int:
        return int(self.points_m.shape[0])

    @classmethod
    def concat(cls, *scenes: Scene, name: str | None = None) -> Scene:
        """All samples of ``scenes`` in one scene; the name joins theirs with ``+``."""
        if not scenes:
            return empty_scene()
        for i, s in enumerate(scenes):
            if not isinstance(s, Scene):
                raise InputError(f"scenes[{i}]: expected Scene, got {type(s).__name__}")
        return cls(
            **{f: np.concatenate([getattr(s, f) for s in scenes]) for f in _SAMPLE_FIELDS},
            name=name if name is not None else "+".join(s.name for s in scenes if s.name),
        )

    def transformed(self, rotation_matrix: ArrayLike, translation: ArrayLike) -> Scene:
        """The scene in another frame: ``p' = R p + t``, ``n' = R n``.

        To express world-frame surfaces in the sonar frame of a sensor with world pose
        ``(R_ws, t_ws)`` (sensor-to-world), pass ``R = R_ws.T`` and ``t = -R_ws.T @ t_ws``.

        Raises
        ------
        InputError
            If ``rotation_matrix`` is not a 3x3 rotation or ``translation`` not a finite 3-vector.
        """
        rot = np.asarray(rotation_matrix, dtype=np.float64)
        t = np.asarray(translation, dtype=np.float64).reshape(-1)
        if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
            raise InputError(f"rotation_matrix: expected a finite 3x3 matrix, got shape {rot.shape}")
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
            raise InputError("rotation_matrix: not a proper rotation (R R^T != I or det < 0)")
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise InputError(f"translation: expected a finite 3-vector, got shape {t.shape}")
        return dataclasses.replace(self, points_m=self.points_m @ rot.T + t, normals=self.normals @ rot.T)

    def cropped(self, view: View = View()) -> Scene:
        """Only the samples inside ``view`` (see :class:`View`)."""
        p = self.points_m
        r = np.linalg.norm(p, axis=1)
        az = np.arctan2(p[:, 1], p[:, 0])
        el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
        keep = (
            (r <= view.max_range_m)
            & (np.abs(az) <= view.half_azimuth_rad)
            & (np.abs(el) <= view.half_elevation_rad)
            & (p[:, 0] > 0)
        )
        return self.subset(keep)

    def scaled(self, factor: float) -> Scene:
        """A geometrically similar scene: positions times ``factor``, patch areas times ``factor**2``.

        Normals and reflectivities are unchanged, so target strengths scale with the areas (a
        smaller copy of the same surfaces, e.g. to put a named scene inside a short-range window).

        Raises
        ------
        InputError
            If ``factor`` is not a positive finite number.
        """
        f = float(factor)
        if not (math.isfinite(f) and f > 0):
            raise InputError(f"factor: must be a positive finite number (got {factor})")
        return dataclasses.replace(self, points_m=self.points_m * f, patch_area_m2=self.patch_area_m2 * (f * f))

    def subset(self, mask: NDArray[np.bool_]) -> Scene:
        """The samples selected by a boolean mask or index array."""
        return dataclasses.replace(self, **{f: getattr(self, f)[mask] for f in _SAMPLE_FIELDS})


# ---------------------------------------------------------------------- generic samplers


def empty_scene(name: str = "empty") -> Scene:
    """A scene with no samples (open water: the image is background only)."""
    z3 = np.zeros((0, 3))
    z = np.zeros(0)
    return Scene(z3, z3, z, np.zeros(0, np.uint8), z, name=name)


def _unit(v: ArrayLike) -> NDArray[np.float64]:
    a = np.asarray(v, dtype=np.float64)
    return a / np.linalg.norm(a)


def _uniform_scene(
    points_m: NDArray[np.float64],
    normals: ArrayLike,
    *,
    reflectivity: float,
    label: int,
    patch_area_m2: float,
    name: str,
) -> Scene:
    """Samples at ``points_m`` that share one linear ``reflectivity``, ``label`` and patch area.

    ``normals`` is one normal for all (shape (3,)) or one per sample (shape (N, 3)).
    """
    m = points_m.shape[0]
    return Scene(
        points_m=points_m,
        normals=np.broadcast_to(normals, (m, 3)),
        reflectivity=np.full(m, reflectivity),
        labels=np.full(m, label, np.uint8),
        patch_area_m2=np.full(m, patch_area_m2),
        name=name,
    )


def _half_span_m(view: View) -> float:
    """Half the across-fan extent a surface needs to fill ``view`` at its maximum range (with margin)."""
    return 1.3 * view.max_range_m * math.tan(view.half_azimuth_rad)


def _half_height_m(range_m: float, incidence_rad: float, view: View) -> float:
    """Half the extent, along its tilt, of a plate at ``range_m`` and incidence that fills the
    vertical aperture of ``view`` (with margin)."""
    return 2.0 * range_m * math.tan(view.half_elevation_rad) / max(math.cos(incidence_rad), 0.05) + 0.2


def _rot_y(angle: float) -> NDArray[np.float64]:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(angle: float) -> NDArray[np.float64]:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(angle: float) -> NDArray[np.float64]:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def plane_patch(
    origin_m: ArrayLike,
    u_axis: ArrayLike,
    v_axis: ArrayLike,
    *,
    u_extent_m: tuple[float, float],
    v_extent_m: tuple[float, float],
    spacing_m: float = _DEFAULT_SPACING_M,
    reflectivity_db: float = -20.0,
    label: int = STRUCTURE,
    name: str = "plane",
    view: View | None = View(),
) -> Scene:
    """A planar rectangle ``origin + u * u_axis + v * v_axis`` sampled on a regular grid.

    ``u_axis`` and ``v_axis`` are orthogonalised and normalised; the normal is ``u x v``.  Each
    sample represents ``spacing_m ** 2`` of surface.  The result is cropped to ``view`` (pass
    ``None`` to keep everything).
    """
    if not spacing_m > 0:
        raise InputError(f"spacing_m: must be positive (got {spacing_m})")
    o = np.asarray(origin_m, dtype=np.float64)
    u = _unit(u_axis)
    v = np.asarray(v_axis, dtype=np.float64)
    v = _unit(v - (v @ u) * u)
    n = np.cross(u, v)
    us = np.arange(u_extent_m[0] + spacing_m / 2, u_extent_m[1], spacing_m)
    vs = np.arange(v_extent_m[0] + spacing_m / 2, v_extent_m[1], spacing_m)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    pts = o + uu.reshape(-1, 1) * u + vv.reshape(-1, 1) * v
    scene = _uniform_scene(pts, n, reflectivity=_db(reflectivity_db), label=label,
                           patch_area_m2=spacing_m**2, name=name)
    return scene.cropped(view) if view is not None else scene


# ---------------------------------------------------------------------- named structures


def planar_hull(
    range_m: float = 6.5,
    *,
    incidence_deg: float = 60.0,
    yaw_deg: float = 0.0,
    reflectivity_db: float = -12.0,
    spacing_m: float = _DEFAULT_SPACING_M,
    view: View = View(),
) -> Scene:
    """A flat hull plate crossing the sonar's forward axis at ``range_m``.

    The plate is tilted in the vertical plane so the forward ray meets it at ``incidence_deg``
    from its normal (the HAUV looks obliquely at the hull), then yawed by ``yaw_deg`` about the
    sonar's z axis (a non-zero yaw makes the hull band slope across beams).  It appears as a band
    at about ``range_m / cos(azimuth)`` whose thickness grows with incidence and elevation aperture.
    """
    inc = math.radians(incidence_deg)
    normal = np.array([-math.cos(inc), 0.0, -math.sin(inc)])
    u = np.array([0.0, 1.0, 0.0])
    v = np.cross(normal, u)
    rot = _rot_z(math.radians(yaw_deg))
    origin = np.array([range_m, 0.0, 0.0])
    half_u = _half_span_m(view) + 0.5
    half_v = _half_height_m(range_m, inc, view)
    s = plane_patch(
        origin,
        rot @ u,
        rot @ v,
        u_extent_m=(-half_u, half_u),
        v_extent_m=(-half_v, half_v),
        spacing_m=spacing_m,
        reflectivity_db=reflectivity_db,
        name="hull",
        view=view,
    )
    return s


def curved_hull(
    range_m: float = 6.0,
    *,
    radius_m: float = 3.0,
    incidence_deg: float = 55.0,
    reflectivity_db: float = -12.0,
    spacing_m: float = _DEFAULT_SPACING_M,
    view: View = View(),
) -> Scene:
    """A cylindrical hull section (bilge-like), convex towards the sonar.

    The cylinder's axis is vertical, tilted by ``incidence_deg`` about the sonar's y axis; the
    nearest generator crosses the forward axis at ``range_m``.  Off-centre beams see the surface at
    growing incidence, so returns fade towards the fan edges (Lambert ``cos^2``) and the band bends
    away in range.
    """
    inc = math.radians(incidence_deg)
    half_psi = min(math.pi / 2, _half_span_m(view) / radius_m)
    dpsi = spacing_m / radius_m
    psi = np.arange(-half_psi + dpsi / 2, half_psi, dpsi)
    half_t = _half_height_m(range_m, inc, view)
    t = np.arange(-half_t + spacing_m / 2, half_t, spacing_m)
    pp, tt = np.meshgrid(psi, t, indexing="ij")
    pp = pp.reshape(-1)
    tt = tt.reshape(-1)
    # Cylinder with axis along z through (range + R, 0, 0); surface towards the sonar.
    normal0 = np.stack([-np.cos(pp), np.sin(pp), np.zeros_like(pp)], axis=1)
    pts0 = np.array([range_m + radius_m, 0.0, 0.0]) + radius_m * normal0
    pts0[:, 2] = tt
    # Tilt about the y axis through the nearest point so the forward ray meets it at `inc`.
    rot = _rot_y(-inc)
    pivot = np.array([range_m, 0.0, 0.0])
    pts = (pts0 - pivot) @ rot.T + pivot
    nrm = normal0 @ rot.T
    s = _uniform_scene(pts, nrm, reflectivity=_db(reflectivity_db), label=STRUCTURE,
                       patch_area_m2=spacing_m * (dpsi * radius_m), name="curved_hull")
    return s.cropped(view)


def seafloor(
    height_m: float = 2.5,
    *,
    pitch_deg: float = 20.0,
    reflectivity_db: float = -20.0,
    spacing_m: float = _DEFAULT_SPACING_M,
    view: View = View(),
) -> Scene:
    """A flat seafloor ``height_m`` below a sonar pitched down by ``pitch_deg``.

    The forward ray meets the floor at range ``height_m / sin(pitch)`` (about 7.3 m by default),
    at grazing angle ``pitch``.  Default ``reflectivity_db`` -20 dB (Lambert mu; Mackenzie's
    classic -27 dB for sediment at 24 kHz, rougher at MHz frequencies).
    """
    p = math.radians(pitch_deg)
    if not 0 < p < math.pi / 2:
        raise InputError(f"pitch_deg: must be in (0, 90) (got {pitch_deg})")
    normal = np.array([-math.sin(p), 0.0, -math.cos(p)])
    r0 = height_m / math.sin(p)
    u = np.array([0.0, 1.0, 0.0])
    v = np.cross(normal, u)
    half_u = _half_span_m(view) + 0.5
    # Along-look extent: elevation +-e maps to ranges h / sin(p +- e) on the floor.
    e = view.half_elevation_rad
    near = height_m / math.tan(min(p + e, math.radians(89.0)))
    far = height_m / math.tan(max(p - e, math.radians(0.5)))
    ground0 = height_m / math.tan(p)
    lo = (near - ground0) / math.cos(p) * 1.05 - 0.1
    hi = min((far - ground0) / math.cos(p) * 1.05 + 0.1, view.max_range_m)
    # v points along the look direction on the floor; orient it forward.
    if v[0] < 0:
        v = -v
    return plane_patch(
        np.array([r0, 0.0, 0.0]),
        u,
        v,
        u_extent_m=(-half_u, half_u),
        v_extent_m=(lo, hi),
        spacing_m=spacing_m,
        reflectivity_db=reflectivity_db,
        name="seafloor",
        view=view,
    )


def rudder(
    range_m: float = 6.3,
    *,
    azimuth_deg: float = 2.0,
    width_m: float = 0.8,
    height_m: float = 2.0,
    yaw_deg: float = 20.0,
    reflectivity_db: float = -10.0,
    spacing_m: float = _DEFAULT_SPACING_M,
    view: View = View(),
) -> Scene:
    """A rudder-like vertical plate of ``width_m`` x ``height_m`` centred at range/azimuth.

    Its normal faces the sonar, yawed by ``yaw_deg``; it is seen as a short, bright segment a few
    degrees wide (the paper's test image 6).
    """
    az = math.radians(azimuth_deg)
    centre = range_m * np.array([math.cos(az), math.sin(az), 0.0])
    rot = _rot_z(az + math.radians(yaw_deg))
    u = rot @ np.array([0.0, 1.0, 0.0])
    v = np.array([0.0, 0.0, 1.0])
    s = plane_patch(
        centre,
        u,
        v,
        u_extent_m=(-width_m / 2, width_m / 2),
        v_extent_m=(-height_m / 2, height_m / 2),
        spacing_m=spacing_m,
        reflectivity_db=reflectivity_db,
        name="rudder",
        view=view,
    )
    return s


def propeller(
    range_m: float = 4.5,
    *,
    n_blades: int = 4,
    radius_m: float = 1.1,
    hub_radius_m: float = 0.18,
    blade_pitch_deg: float = 35.0,
    phase_deg: float = 20.0,
    reflectivity_db: float = -8.0,
    spacing_m: float = _DEFAULT_SPACING_M,
    view: View = View(),
) -> Scene:
    """A propeller-like structure: a hub cylinder and twisted blades, disc facing the sonar.

    The shaft lies along the forward axis with the hub face at ``range_m``.  Blades are plates
    from the hub to ``radius_m`` (chord tapering from 0.45 to 0.25 m), pitched by
    ``blade_pitch_deg`` about their span axis, so they spread over range as in the paper's image 7.
    """
    if n_blades < 1:
        raise InputError(f"n_blades: must be >= 1 (got {n_blades})")
    parts: list[Scene] = []
    refl = _db(reflectivity_db)
    # Hub: cylinder along x, 0.6 m long.
    dpsi = spacing_m / hub_radius_m
    psi = np.arange(0, 2 * math.pi, dpsi)
    xs = np.arange(spacing_m / 2, 0.6, spacing_m)
    pp, xx = np.meshgrid(psi, xs, indexing="ij")
    nrm = np.stack([np.zeros(pp.size), np.cos(pp).ravel(), np.sin(pp).ravel()], axis=1)
    pts = np.stack([range_m + xx.ravel(), np.zeros(pp.size), np.zeros(pp.size)], axis=1)
    pts += hub_radius_m * nrm
    parts.append(_uniform_scene(pts, nrm, reflectivity=refl, label=STRUCTURE,
                                patch_area_m2=spacing_m * dpsi * hub_radius_m, name="propeller"))
    # Blades.
    spans = np.arange(hub_radius_m + spacing_m / 2, radius_m, spacing_m)
    for k in range(n_blades):
        ang = math.radians(phase_deg) + 2 * math.pi * k / n_blades
        span_dir = np.array([0.0, math.cos(ang), math.sin(ang)])
        chord0 = np.cross(span_dir, np.array([1.0, 0.0, 0.0]))  # in the disc plane
        pitch = math.radians(blade_pitch_deg)
        chord_dir = math.cos(pitch) * chord0 + math.sin(pitch) * np.array([1.0, 0.0, 0.0])
        normal = _unit(np.cross(span_dir, chord_dir))
        pts_b: list[NDArray[np.float64]] = []
        for s_ in spans:
            frac = (s_ - hub_radius_m) / (radius_m - hub_radius_m)
            chord = 0.45 - 0.2 * frac
            cs = np.arange(-chord / 2 + spacing_m / 2, chord / 2, spacing_m)
            pts_b.append(
                np.array([range_m + 0.3, 0.0, 0.0]) + s_ * span_dir + cs[:, None] * chord_dir
            )
        parts.append(_uniform_scene(np.concatenate(pts_b), normal, reflectivity=refl, label=STRUCTURE,
                                    patch_area_m2=spacing_m**2, name="propeller"))
    return Scene.concat(*parts, name="propeller").cropped(view)


def fish_school(
    range_m: float = 4.5,
    *,
    azimuth_deg: float = -4.0,
    n_fish: int = 40,
    radius_m: float = 0.6,
    ts_db: tuple[float, float] = (-48.0, -36.0),
    rng: int | np.random.Generator | None = 0,
    view: View = View(),
) -> Scene:
    """A school of ``n_fish`` isotropic point scatterers (label :data:`CLUTTER`).

    Fish are uniform in an ellipsoid of horizontal radius ``radius_m`` (vertical radius a quarter
    of it) centred at range/azimuth, with target strengths uniform in ``ts_db`` (dB re 1 m^2; fish
    of 10-30 cm at MHz frequencies).
    """
    gen = np.random.default_rng(rng)
    if n_fish < 0:
        raise InputError(f"n_fish: must be >= 0 (got {n_fish})")
    az = math.radians(azimuth_deg)
    centre = range_m * np.array([math.cos(az), math.sin(az), 0.0])
    d = gen.normal(size=(n_fish, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rad = radius_m * gen.uniform(size=(n_fish, 1)) ** (1 / 3)
    pts = centre + d * rad * np.array([1.0, 1.0, 0.25])
    ts = gen.uniform(ts_db[0], ts_db[1], size=n_fish)
    s = Scene(
        points_m=pts,
        normals=np.zeros((n_fish, 3)),
        reflectivity=10.0 ** (ts / 10.0),
        labels=np.full(n_fish, CLUTTER, np.uint8),
        patch_area_m2=np.ones(n_fish),
        name="fish",
    )
    return s.cropped(view)


def point_target(
    range_m: float,
    azimuth_rad: float,
    *,
    elevation_rad: float = 0.0,
    ts_db: float = -40.0,
    label: int = STRUCTURE,
) -> Scene:
    """A single isotropic scatterer at ``(range, azimuth, elevation)`` with target strength ``ts_db``.

    Its sonar-frame position is ``r (cos e cos a, cos e sin a, sin e)``; it lands in the bin
    nearest ``range_m`` and the beam nearest ``azimuth_rad``.
    """
    for nm, val in (("range_m", range_m), ("azimuth_rad", azimuth_rad), ("elevation_rad", elevation_rad)):
        if not math.isfinite(val):
            raise InputError(f"{nm}: must be finite (got {val})")
    if range_m <= 0:
        raise InputError(f"range_m: must be positive (got {range_m})")
    ce = math.cos(elevation_rad)
    p = range_m * np.array(
        [[ce * math.cos(azimuth_rad), ce * math.sin(azimuth_rad), math.sin(elevation_rad)]]
    )
    return Scene(p, np.zeros((1, 3)), np.array([_db(ts_db)]), np.array([label], np.uint8),
                 np.ones(1), name="point")


# ---------------------------------------------------------------------- named scenes


#: Range the named scenes are laid out around (the centre of the DIDSON's 2.25-11.25 m window).
SCENE_REFERENCE_RANGE_M = 6.75

#: Vertical incidence of the sloped hull plates (``hull_slope*``): a thin band (~4 DIDSON bins),
#: like the real DIDSON test ping 5's diagonal hull line.
SLOPED_HULL_INCIDENCE_DEG = 30.0


def _default_geometry(geometry: Any) -> Any:
    """``geometry``, or the ``didson-hf`` preset for None (the sloped hulls' default sonar)."""
    if geometry is None:
        from sonarmap.geometry import preset

        geometry = preset("didson-hf")
    return geometry


def sloped_hull_yaw_deg(bins_per_beam: float, geometry: Any = None, *, range_m: float | None = None) -> float:
    """Yaw of :func:`planar_hull` whose band changes range by ``bins_per_beam`` bins per beam.

    At the band's centre (azimuth 0, range ``range_m``) a plate yawed by ``psi`` has
    ``dr / dtheta = range tan(psi)``, so ``tan(psi) = bins_per_beam * bin / (range * dtheta)``
    with ``bin`` the geometry's range-bin spacing and ``dtheta`` its beam spacing at azimuth 0.

    Parameters
    ----------
    bins_per_beam : float
        Slope of the band across beams, >= 0.
    geometry : SonarGeometry, optional
        The sonar (default the ``didson-hf`` preset).
    range_m : float, optional
        Range of the band's centre; default :data:`SCENE_REFERENCE_RANGE_M` times
        :func:`scene_scale_for` (where the named scenes put it for ``geometry``).

    Returns
    -------
    float
        Yaw in degrees (0 for a flat band).

    Examples
    --------
    >>> round(sloped_hull_yaw_deg(4.0), 1)
    58.2
    """
    geometry = _default_geometry(geometry)
    if not (math.isfinite(bins_per_beam) and bins_per_beam >= 0):
        raise InputError(f"bins_per_beam: must be a finite number >= 0 (got {bins_per_beam})")
    r = SCENE_REFERENCE_RANGE_M * scene_scale_for(geometry) if range_m is None else float(range_m)
    az = np.asarray(geometry.azimuth_rad, dtype=np.float64)
    # local beam spacing at azimuth 0 (the DIDSON and Oculus tables are not uniform)
    dtheta = float(np.interp(0.0, az, np.gradient(az))) if az.size > 1 else 1.0
    return math.degrees(math.atan(bins_per_beam * float(geometry.range_resolution_m) / (r * dtheta)))


def sloped_hull(
    bins_per_beam: float,
    geometry: Any = None,
    *,
    range_m: float = SCENE_REFERENCE_RANGE_M,
    incidence_deg: float = SLOPED_HULL_INCIDENCE_DEG,
    scale: float | None = None,
    view: View = View(),
) -> Scene:
    """A :func:`planar_hull` yawed so its band slopes ``bins_per_beam`` bins per beam.

    The yaw comes from :func:`sloped_hull_yaw_deg` at the plate's range after the named scenes'
    scaling (``scale``, default :func:`scene_scale_for` of ``geometry``).  The reflectivity is
    raised by the Lambert loss of the yaw and the tilt, so every slope echoes as brightly as
    the flat ``hull`` (60 deg incidence, -12 dB): ``-12 + 10 log10(cos^2 60 / (cos incidence cos
    yaw)^2)`` dB.  The result is *not* scaled (:func:`scene_from_name` does that).
    """
    geometry = _default_geometry(geometry)
    f = scene_scale_for(geometry) if scale is None else float(scale)
    yaw = sloped_hull_yaw_deg(bins_per_beam, geometry, range_m=range_m * f)
    cos_total = math.cos(math.radians(incidence_deg)) * math.cos(math.radians(yaw))
    refl = -12.0 + 10.0 * math.log10(math.cos(math.radians(60.0)) ** 2 / cos_total**2)
    hull = planar_hull(range_m, incidence_deg=incidence_deg, yaw_deg=yaw, reflectivity_db=refl, view=view)
    return dataclasses.replace(hull, name=f"hull_slope{bins_per_beam:g}")


def _hull(gen: np.random.Generator, view: View, geometry: Any) -> Scene:
    return planar_hull(view=view)


def _fish_over_hull(gen: np.random.Generator, view: View, geometry: Any) -> Scene:
    hull = planar_hull(8.0, incidence_deg=55.0, view=view)
    fish = fish_school(4.0, azimuth_deg=3.0, n_fish=40, rng=gen, view=view)
    return Scene.concat(hull, fish, name="fish_over_hull")


_BUILDERS: dict[str, Callable[[np.random.Generator, View, Any], Scene]] = {
    "hull": _hull,
    "hull_oblique": lambda g, v, geo: Scene.concat(planar_hull(7.0, yaw_deg=20.0, view=v), name="hull_oblique"),
    "hull_slope2": lambda g, v, geo: sloped_hull(2.0, geo, view=v),
    "hull_slope4": lambda g, v, geo: sloped_hull(4.0, geo, view=v),
    "hull_slope8": lambda g, v, geo: sloped_hull(8.0, geo, view=v),
    "curved_hull": lambda g, v, geo: curved_hull(view=v),
    "propeller": lambda g, v, geo: propeller(view=v),
    "rudder": lambda g, v, geo: rudder(view=v),
    "seafloor": lambda g, v, geo: seafloor(view=v),
    "fish": lambda g, v, geo: fish_school(rng=g, view=v),
    "fish_over_hull": _fish_over_hull,
    "fish_over_seafloor": lambda g, v, geo: Scene.concat(
        seafloor(view=v), fish_school(3.5, azimuth_deg=-6.0, rng=g, view=v), name="fish_over_seafloor"
    ),
    "empty": lambda g, v, geo: empty_scene(),
}

#: Names accepted by :func:`scene_from_name`.
SCENE_NAMES: tuple[str, ...] = tuple(_BUILDERS)


def scene_scale_for(geometry: Any) -> float:
    """Factor :func:`scene_from_name` scales the named scenes by for ``geometry``'s range window.

    1 when the window contains :data:`SCENE_REFERENCE_RANGE_M` (DIDSON, ARIS), else the window's
    centre over that range (e.g. 0.148 for the 0-2 m Oculus window: the hull plate then crosses the axis at 0.96 m).
    """
    lo, hi = float(geometry.min_range_m), float(geometry.max_range_m)
    if lo <= SCENE_REFERENCE_RANGE_M <= hi:
        return 1.0
    return 0.5 * (lo + hi) / SCENE_REFERENCE_RANGE_M


def view_for(geometry: Any) -> View:
    """The :class:`View` :func:`scene_from_name` crops to for ``geometry`` (before scaling).

    The default view, widened to the geometry's fan (``fov / 2 + 2 deg``) and to twice its sonar
    profile's vertical aperture (:mod:`sonarmap.simulate.presets`) where those exceed 20 / 4 deg;
    the default view itself for DIDSON and ARIS.  Twice the aperture (the two-way -3 dB width of
    the Gaussian elevation pattern) keeps every sample whose two-way weight is above -48 dB, as the
    default view does for the default 1 deg aperture: a crop at the aperture itself (-12 dB) cuts a
    grazing surface's near part off, and its echo starts with a step (the seafloor on the 12 deg
    Oculus-like preset: to ~45 % of its peak at once).
    """
    from sonarmap.simulate.presets import profile_for

    base = View()
    fov = geometry.fov_rad
    if fov is None:
        fov = float(geometry.azimuth_rad[-1] - geometry.azimuth_rad[0])
    half_az = max(base.half_azimuth_rad, 0.5 * float(fov) + math.radians(2.0))
    aperture = float(profile_for(geometry).values.get("elevation_aperture_rad", 0.0))
    half_el = max(base.half_elevation_rad, 2.0 * aperture)
    if half_az == base.half_azimuth_rad and half_el == base.half_elevation_rad:
        return base
    return View(max_range_m=base.max_range_m, half_azimuth_rad=min(half_az, math.radians(80.0)),
                half_elevation_rad=min(half_el, math.radians(60.0)))


def scene_from_name(
    name: str,
    rng_or_seed: int | np.random.Generator | None = 0,
    *,
    geometry: Any = None,
    view: View | None = None,
) -> Scene:
    """Build a named scene (see :data:`SCENE_NAMES`); random parts (fish) use ``rng_or_seed``.

    Parameters
    ----------
    name : str
        One of :data:`SCENE_NAMES`.
    rng_or_seed : int or numpy.random.Generator or None
        Randomness of the random parts.
    geometry : SonarGeometry, optional
        Build the scene for this sonar: cropped to :func:`view_for` (its fan and vertical beam)
        and scaled by :func:`scene_scale_for` to lie inside its range window.  Unchanged for
        DIDSON and ARIS geometries; the Oculus-like preset gets a smaller, wider scene.
    view : View, optional
        Crop to this view instead (in the unscaled scene's frame); default ``View()`` or, with
        ``geometry``, :func:`view_for`.

    Raises
    ------
    InputError
        If ``name`` is unknown (the message lists the valid names).

    Examples
    --------
    >>> from sonarmap import preset
    >>> from sonarmap import preset
    >>> round(scene_scale_for(preset("oculus-m750d-like")), 3)
    0.148
    >>> len(scene_from_name("hull", geometry=preset("didson-hf"))) == len(scene_from_name("hull"))
    True
    """
    if name not in _BUILDERS:
        raise InputError(f"scene: unknown scene '{name}'; choose from {', '.join(SCENE_NAMES)}")
    gen = np.random.default_rng(rng_or_seed)
    if view is None:
        view = View() if geometry is None else view_for(geometry)
    elif not isinstance(view, View):
        raise InputError(f"view: expected a View, got {type(view).__name__}")
    scene = _BUILDERS[name](gen, view, geometry)
    if geometry is not None:
        factor = scene_scale_for(geometry)
        if factor != 1.0:
            scene = scene.scaled(factor)
    return dataclasses.replace(scene, name=name)
