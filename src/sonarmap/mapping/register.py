"""Registration: per-beam ranges + sensor poses -> 3-D points in the world (NED) frame.

A 2-D imaging sonar measures range and azimuth but integrates over its vertical (elevation)
aperture.  Under the *zero-elevation* (profiling) assumption every return is placed in the
sensor's imaging plane, ``p_s = r (cos a, sin a, 0)``, at the azimuth ``a`` where it was
measured: the near edge of its beam's footprint on a surface inclined across the beams, else the
beam's axis (:mod:`sonarmap.mapping.footprint`; given the beams' width).  Optionally each return
is *spread* over the vertical aperture as ``n_elevation`` points at elevations
``linspace(-aperture/2, aperture/2)`` (useful for occupancy carving and for visualising the
elevation ambiguity).  World points are ``p_w = R_ws p_s + t_ws`` with the sensor -> world
transforms of :func:`sonarmap.mapping.poses.sensor_poses`.

Everything is vectorised over ``(ping, beam, elevation)``; 1 M returns register in a few tens of
milliseconds.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarmap.errors import InputError
from sonarmap.mapping.footprint import FOOTPRINT_EDGE_FRACTION, footprint_azimuths
from sonarmap.mapping.poses import SensorPoses

__all__ = ["RegistrationConfig", "PointCloud", "register_returns", "register_ranges", "elevation_samples"]

#: DIDSON / ARIS vertical beam width (the lens's elevation aperture), radians.
DEFAULT_APERTURE_RAD = math.radians(14.0)


@dataclasses.dataclass(frozen=True)
class RegistrationConfig:
    """Options of :func:`register_returns`.

    Parameters
    ----------
    n_elevation : int
        Points per return across the vertical aperture; 1 = zero-elevation assumption.
    vertical_aperture_rad : float
        Full vertical aperture spread over when ``n_elevation > 1`` (DIDSON/ARIS: 14 degrees).
    min_confidence : float
        Returns with a lower confidence are dropped.
    footprint_edge : bool
        Place each return at the near edge of its beam's footprint
        (:func:`sonarmap.mapping.footprint.footprint_azimuths`) where the beamwidth is given;
        False: on the beam's axis.
    footprint_fraction : float
        Offset of that edge from the axis in two-way -3 dB beamwidths (1/2: the -3 dB edge).
    """

    n_elevation: int = 1
    vertical_aperture_rad: float = DEFAULT_APERTURE_RAD
    min_confidence: float = 0.0
    footprint_edge: bool = True
    footprint_fraction: float = FOOTPRINT_EDGE_FRACTION

    def __post_init__(self) -> None:
        if int(self.n_elevation) != self.n_elevation or self.n_elevation < 1:
            raise InputError(f"n_elevation: must be a positive integer, got {self.n_elevation}")
        if not 0.0 <= self.vertical_aperture_rad < math.pi:
            raise InputError(f"vertical_aperture_rad: must be in [0, pi), got {self.vertical_aperture_rad}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise InputError(f"min_confidence: must be in [0, 1], got {self.min_confidence}")
        if not 0.0 <= self.footprint_fraction <= 1.0:
            raise InputError(f"footprint_fraction: must be in [0, 1], got {self.footprint_fraction}")


def elevation_samples(n_elevation: int, aperture_rad: float) -> NDArray[np.float64]:
    """Elevations of the spread points: ``[0]`` for one, else ``linspace(-a/2, a/2, n)``."""
    if n_elevation == 1:
        return np.zeros(1)
    return np.linspace(-aperture_rad / 2, aperture_rad / 2, n_elevation)


@dataclasses.dataclass(frozen=True, eq=False)
class PointCloud:
    """Registered returns.  All arrays have length ``n`` (one row per point).

    Parameters
    ----------
    xyz_m : ndarray, shape (n, 3), float64
        World coordinates (NED unless ``frame`` says otherwise), metres.
    time_ns : ndarray, shape (n,), int64
        Ping time of each point.
    beam : ndarray, shape (n,), int32
        Beam (image column) index.
    range_m : ndarray, shape (n,), float32
        Measured range.
    intensity : ndarray, shape (n,), float32
        Return intensity.
    confidence : ndarray, shape (n,), float32
        Return confidence in [0, 1].
    elevation_rad : ndarray, shape (n,), float32
        Assumed elevation (0 under the profiling assumption).
    frame : str
        ``"ned"`` (default) or ``"enu"``.
    sigma_m : ndarray, shape (n,), float32, optional
        One-sigma range uncertainty of the return (``BeamRanges.sigma_m``); NaN (the default)
        where unknown.
    """

    xyz_m: NDArray[np.float64]
    time_ns: NDArray[np.int64]
    beam: NDArray[np.int32]
    range_m: NDArray[np.float32]
    intensity: NDArray[np.float32]
    confidence: NDArray[np.float32]
    elevation_rad: NDArray[np.float32]
    frame: str = "ned"
    sigma_m: NDArray[np.float32] | None = None

    def __post_init__(self) -> None:
        xyz = np.asarray(self.xyz_m, dtype=np.float64).reshape(-1, 3)
        n = xyz.shape[0]
        object.__setattr__(self, "xyz_m", xyz)
        if self.sigma_m is None:
            object.__setattr__(self, "sigma_m", np.full(n, np.nan, dtype=np.float32))
        for name, dt in _ATTRS.items():
            arr = np.asarray(getattr(self, name), dtype=dt).reshape(-1)
            if arr.size != n:
                raise InputError(f"{name}: length {arr.size} does not match {n} points")
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return int(self.xyz_m.shape[0])

    @classmethod
    def empty(cls, frame: str = "ned") -> PointCloud:
        """A cloud with no points."""
        return cls(np.zeros((0, 3)), **{k: np.zeros(0, dt) for k, dt in _ATTRS.items()}, frame=frame)

    @classmethod
    def concat(cls, clouds: Sequence[PointCloud]) -> PointCloud:
        """Concatenate clouds in the same frame."""
        clouds = list(clouds)
        if not clouds:
            return cls.empty()
        frames = {c.frame for c in clouds}
        if len(frames) > 1:
            raise InputError(f"clouds: cannot concatenate frames {sorted(frames)}")
        return cls(
            np.concatenate([c.xyz_m for c in clouds]),
            **{k: np.concatenate([getattr(c, k) for c in clouds]) for k in _ATTRS},
            frame=clouds[0].frame,
        )

    def select(self, index: ArrayLike) -> PointCloud:
        """Subset by boolean mask or indices."""
        k = np.asarray(index)
        return PointCloud(self.xyz_m[k], **{a: getattr(self, a)[k] for a in _ATTRS}, frame=self.frame)

    def to_frame(self, frame: str) -> PointCloud:
        """The same points with coordinates in ``"ned"`` or ``"enu"``."""
        from sonarmap.mapping.frames import enu_to_ned, world_frame

        fr = world_frame(frame)
        if fr == self.frame:
            return self
        return dataclasses.replace(self, xyz_m=enu_to_ned(self.xyz_m), frame=fr)

    def attributes(self) -> dict[str, NDArray[Any]]:
        """The per-point attributes by name."""
        return {k: getattr(self, k) for k in _ATTRS}


_ATTRS: dict[str, Any] = {
    "time_ns": np.int64,
    "beam": np.int32,
    "range_m": np.float32,
    "intensity": np.float32,
    "confidence": np.float32,
    "elevation_rad": np.float32,
    "sigma_m": np.float32,
}


def range_matrix(range_m: ArrayLike, poses: Sequence[Any] | SensorPoses) -> NDArray[np.float64]:
    """Per-beam ranges as a float64 ``(n_pings, n_beams)`` array checked against one pose per ping.

    A single ping's ``(n_beams,)`` ranges become one row.  Raises :class:`InputError` naming the
    argument on a wrong shape or a pose count that differs from the ping count.
    """
    r = np.asarray(range_m, dtype=np.float64)
    if r.ndim == 1:
        r = r[None, :]
    if r.ndim != 2:
        raise InputError(f"range_m: expected (n_pings, n_beams), got shape {r.shape}")
    if len(poses) != r.shape[0]:
        raise InputError(f"poses: {len(poses)} poses for {r.shape[0]} pings")
    return r


def _as_2d(values: ArrayLike | None, shape: tuple[int, int], name: str, dtype: Any, fill: float) -> NDArray[Any]:
    if values is None:
        return np.full(shape, fill, dtype=dtype)
    arr = np.asarray(values, dtype=dtype)
    try:
        return np.broadcast_to(arr, shape)
    except ValueError:
        raise InputError(f"{name}: shape {arr.shape} does not broadcast to (n_pings, n_beams) {shape}") from None


def register_returns(
    range_m: ArrayLike,
    azimuth_rad: ArrayLike,
    poses: SensorPoses,
    *,
    intensity: ArrayLike | None = None,
    confidence: ArrayLike | None = None,
    sigma_m: ArrayLike | None = None,
    azimuth_beamwidth_rad: ArrayLike | None = None,
    config: RegistrationConfig | None = None,
) -> PointCloud:
    """Register a batch of per-beam ranges into world points.

    Parameters
    ----------
    range_m : array_like, shape (n_pings, n_beams)
        Ranges; NaN (or non-positive) = no return.
    azimuth_rad : array_like, shape (n_beams,) or (n_pings, n_beams)
        Beam azimuths (positive to starboard).
    poses : SensorPoses
        Sensor -> world transforms, one per ping (invalid poses drop their pings' returns).
    intensity, confidence : array_like, shape (n_pings, n_beams), optional
        Per-return attributes (default 1).
    sigma_m : array_like, shape (n_pings, n_beams), optional
        One-sigma range uncertainty per return (default NaN: unknown).
    azimuth_beamwidth_rad : array_like, broadcastable to (n_pings, n_beams), optional
        Each beam's two-way -3 dB width in the fan's plane
        (:attr:`~sonarmap.geometry.SonarGeometry.azimuth_beamwidth_rad`).  With
        ``config.footprint_edge`` a return is placed at the near edge of its beam's footprint
        (:func:`~sonarmap.mapping.footprint.footprint_azimuths`: the leading edge's range was
        measured there); None or NaN: on the beam's axis.
    config : RegistrationConfig, optional

    Returns
    -------
    PointCloud
        Points ordered by ping, then beam, then elevation sample.
    """
    cfg = config or RegistrationConfig()
    r = range_matrix(range_m, poses)
    P, B = r.shape
    az = _as_2d(azimuth_rad, (P, B), "azimuth_rad", np.float64, 0.0)
    inten = _as_2d(intensity, (P, B), "intensity", np.float32, 1.0)
    conf = _as_2d(confidence, (P, B), "confidence", np.float32, 1.0)
    sig = _as_2d(sigma_m, (P, B), "sigma_m", np.float32, np.nan)
    keep = np.isfinite(r) & (r > 0) & poses.valid[:, None]
    if cfg.min_confidence > 0:
        keep &= conf >= cfg.min_confidence
    elev = elevation_samples(cfg.n_elevation, cfg.vertical_aperture_rad)
    E = elev.size
    a_in = np.asarray(azimuth_rad, dtype=np.float64)
    a_small = a_in if a_in.ndim == 1 else az  # cos/sin per beam when the table is shared
    if cfg.footprint_edge and azimuth_beamwidth_rad is not None:
        bw = _as_2d(azimuth_beamwidth_rad, (P, B), "azimuth_beamwidth_rad", np.float64, np.nan)
        a_small = footprint_azimuths(r, a_small, bw, fraction=cfg.footprint_fraction)
    xyz = _world_points(r, a_small, keep, poses, elev)
    bi = np.broadcast_to(np.arange(B, dtype=np.int32), (P, B))[keep]
    rr = r[keep]
    n_keep = rr.size

    def rep(v: NDArray[Any]) -> NDArray[Any]:
        return np.repeat(v, E) if E > 1 else v

    return PointCloud(
        xyz,
        rep(np.broadcast_to(poses.time_ns[:, None], (P, B))[keep]),
        rep(bi),
        rep(rr.astype(np.float32)),
        rep(inten[keep]),
        rep(conf[keep]),
        np.tile(elev.astype(np.float32), n_keep) if E > 1 else np.zeros(n_keep, np.float32),
        sigma_m=rep(sig[keep]),
    )


def _world_points(r: NDArray[np.float64], azimuth_rad: NDArray[np.float64], keep: NDArray[np.bool_],
                  poses: SensorPoses, elev: NDArray[np.float64]) -> NDArray[np.float64]:
    """World points ``(n_keep * n_elevation, 3)`` of the kept returns of ranges ``r`` (n_pings, n_beams)
    at azimuths ``azimuth_rad`` (per beam, or per ping and beam), ordered by ping, beam, elevation."""
    R = poses.rotation
    t = poses.translation_m
    E = elev.size
    # Work in the dense (ping, beam) layout with per-ping rotation columns broadcast (no gathers),
    # then keep the valid returns.
    with np.errstate(invalid="ignore"):
        xs = r * np.cos(azimuth_rad)
        ys = r * np.sin(azimuth_rad)
    flat = keep.ravel()
    n_keep = int(flat.sum())
    if E == 1:
        xyz = np.empty((n_keep, 3))
        for k in range(3):
            xyz[:, k] = (R[:, k, 0, None] * xs + R[:, k, 1, None] * ys + t[:, k, None]).ravel()[flat]
        return xyz
    ce, se = np.cos(elev), np.sin(elev)
    xyz = np.empty((n_keep, E, 3))
    for k in range(3):
        base = (R[:, k, 0, None] * xs + R[:, k, 1, None] * ys).ravel()[flat]
        zterm = (R[:, k, 2, None] * r).ravel()[flat]
        xyz[:, :, k] = base[:, None] * ce + zterm[:, None] * se + np.repeat(t[:, k], keep.sum(axis=1))[:, None]
    return xyz.reshape(-1, 3)


def _stack_field(ranges: Sequence[Any], name: str) -> NDArray[np.float64] | None:
    """The per-beam field ``name`` of each of ``ranges`` stacked into float64 (n_pings, n_beams),
    or None if one of them has none (``BeamRanges`` from before the field existed, duck types)."""
    vals = [getattr(br, name, None) for br in ranges]
    if any(v is None for v in vals):
        return None
    return np.stack([np.asarray(v, dtype=np.float64) for v in vals])


def register_ranges(
    ranges: Sequence[Any],
    poses: SensorPoses,
    *,
    config: RegistrationConfig | None = None,
    azimuth_beamwidth_rad: ArrayLike | Sequence[ArrayLike | None] | None = None,
) -> PointCloud:
    """Register a sequence of :class:`sonarmap.ranges.BeamRanges` (one per ping).

    Pings with equal beam counts are stacked and registered in one vectorised call.

    Parameters
    ----------
    ranges : sequence of BeamRanges
        Each with ``range_m``, ``azimuth_rad``, ``intensity``, ``confidence`` (and ``sigma_m``,
        carried to the points when present) of shape (n_beams,).
    poses : SensorPoses
        One sensor pose per element of ``ranges``.
    config : RegistrationConfig, optional
    azimuth_beamwidth_rad : float, array_like of shape (n_beams,), list or tuple, optional
        The beams' two-way -3 dB width in the fan's plane
        (:attr:`~sonarmap.geometry.SonarGeometry.azimuth_beamwidth_rad` of the pings' geometry):
        one width or one per beam for every ping, or a list with one entry per ping (a width, one
        per beam, or None); None or NaN: unknown (the returns stay on their beams' axes).  See
        :func:`register_returns`.
    """
    ranges = list(ranges)
    if len(ranges) != len(poses):
        raise InputError(f"poses: {len(poses)} poses for {len(ranges)} pings")
    if not ranges:
        return PointCloud.empty()
    widths = _per_ping_widths(azimuth_beamwidth_rad, ranges)
    sizes = {np.asarray(br.range_m).size for br in ranges}
    if len(sizes) == 1:
        return register_returns(
            np.stack([br.range_m for br in ranges]),
            np.stack([br.azimuth_rad for br in ranges]),
            poses,
            intensity=np.stack([br.intensity for br in ranges]),
            confidence=np.stack([br.confidence for br in ranges]),
            sigma_m=_stack_field(ranges, "sigma_m"),
            azimuth_beamwidth_rad=None if widths is None else np.stack(widths),
            config=config,
        )
    return PointCloud.concat(
        [
            register_returns(
                br.range_m, br.azimuth_rad, poses.select([i]),
                intensity=br.intensity, confidence=br.confidence, sigma_m=_stack_field([br], "sigma_m"),
                azimuth_beamwidth_rad=None if widths is None else widths[i],
                config=config,
            )
            for i, br in enumerate(ranges)
        ]
    )


def _per_ping_widths(widths: Any, ranges: Sequence[Any]) -> list[NDArray[np.float64]] | None:
    """``register_ranges``'s beamwidths as one float64 (n_beams,) array per ping (NaN: unknown),
    or None when none are given."""
    if widths is None:
        return None
    n = len(ranges)
    per_ping = list(widths) if isinstance(widths, (list, tuple)) else [widths] * n
    if len(per_ping) != n:
        raise InputError(f"azimuth_beamwidth_rad: {len(per_ping)} entries for {n} pings")
    out = []
    for w, br in zip(per_ping, ranges, strict=True):
        b = np.asarray(br.range_m).size
        arr = np.full(b, np.nan) if w is None else np.asarray(w, dtype=np.float64)
        try:
            out.append(np.broadcast_to(arr, (b,)))
        except ValueError:
            raise InputError(f"azimuth_beamwidth_rad: shape {arr.shape} does not match {b} beams") from None
    return out
