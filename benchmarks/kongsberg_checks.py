"""Kongsberg EM 2040 (shared RV Belgica recording): detection and registration against the sonar's own.

Usage::

    python benchmarks/kongsberg_checks.py                  # prints the tables of docs/mapping.md
    python benchmarks/kongsberg_checks.py --config my.toml # the same for another pipeline configuration

Two external checks, per head (system serial 2004 = port head, 2031 = starboard head):

* **(b) registration**: sonarmap's world points - placed exactly as ``sonarmap map`` places them
  (:func:`~sonarmap.mapping.navigation.navigation_pose`, the pings' poses as ``SensorPoses``,
  :func:`~sonarmap.mapping.navigation.placed_ranges`, :func:`~sonarmap.mapping.register.register_ranges`)
  - against the sonar's own XYZ 88 soundings of the same beams, in the world frame (the XYZ
  along/across turned by the X datagram's heading from the position fix, depth = XYZ depth + the
  transmit transducer's depth re the water level).  First with the sonar's own detected range per
  beam (``meta["detected_range_m"]``) as the range: that isolates the geometry; then with the
  default pipeline's first return per beam (``process_ping(ping, PipelineConfig())``).
* **(a) detection**: per beam, the pipeline's first return against the sonar's detected range:
  a beam passes when the return lies within 2 samples of it, or within half the range extent of
  the beam's footprint on a flat seabed where that is larger (``r tan(theta) beamwidth / 2``, the
  runtime RX beam width).  A beam without a return fails.  The same for a plain amplitude-peak
  baseline: the argmax of the beam's samples beyond ``BASELINE_MIN_RANGE_M``.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
RECORDING = ROOT.parent / "shared" / "data" / "kongsberg" / "0077_20221109_123655_Belgica.all"

#: Angle bands of (a), degrees from the vertical (|beam pointing angle|); the last is open.
BANDS_DEG: tuple[tuple[float, float], ...] = ((0.0, 15.0), (15.0, 30.0), (30.0, 45.0), (45.0, 90.0))
#: The amplitude-peak baseline ignores the samples nearer than this (the transmit ring-down).
BASELINE_MIN_RANGE_M = 1.0
#: Tolerance of (a): at least this many samples.
TOLERANCE_SAMPLES = 2.0
#: :func:`echo_leading_edge_m` looks for the detected echo's peak this many samples before / after
#: the sonar's detected sample.
EDGE_SEARCH_SAMPLES = (15, 10)


def read_recording(path: Path = RECORDING) -> list[Any]:
    """The recording's pings (the truncated last ping of head 2031 included, its warning muted)."""
    from sonarmap.io import read_pings
    from sonarmap.io._binary import PartialFrameWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PartialFrameWarning)
        return list(read_pings(path))


def beam_ranges(ping: Any, range_m: NDArray[np.float64]) -> Any:
    """A :class:`~sonarmap.ranges.BeamRanges` of ``ping`` with the given per-column ranges."""
    from sonarmap.ranges import BeamRanges

    r = np.asarray(range_m, dtype=np.float64)
    ok = np.isfinite(r)
    step = float(ping.meta["range_per_sample_m"])
    b = np.where(ok, np.rint(np.nan_to_num(r) / step) - ping.meta["start_range_sample"], -1).astype(np.int64)
    return BeamRanges(range_m=r, bin=b, intensity=np.where(ok, 1.0, np.nan).astype(np.float32),
                      confidence=ok.astype(np.float32), azimuth_rad=ping.geometry.azimuth_rad,
                      time_ns=ping.time_ns, source=ping.source)


def register_as_cli(pings: Sequence[Any], ranges: Sequence[Any], georef: Any, *,
                    footprint_edge: bool = True) -> list[Any]:
    """Each ping's ranges registered as ``sonarmap map`` registers them (one cloud per ping).

    The same calls as the CLI without ``--poses``: the pose from
    :func:`~sonarmap.mapping.navigation.navigation_pose`, the ``SensorPoses`` from
    :func:`~sonarmap.mapping.navigation.ping_sensor_poses`, the ranges through
    :func:`~sonarmap.mapping.navigation.placed_ranges`, then :func:`register_ranges` with the
    geometry's beamwidth: a return at the near edge of its beam's footprint (its leading edge's
    place), or with ``footprint_edge=False`` on the beam's axis (``--beam-axis``).
    """
    from sonarmap.mapping.navigation import navigation_pose, ping_sensor_poses, placed_ranges
    from sonarmap.mapping.register import RegistrationConfig, register_ranges

    cfg = RegistrationConfig(footprint_edge=footprint_edge)
    out = []
    for ping, br in zip(pings, ranges, strict=True):
        placed = ping.replace(pose=navigation_pose(ping, georef))
        sp = ping_sensor_poses([placed]).with_extrinsics(None)
        out.append(register_ranges([placed_ranges(placed, br)], sp, config=cfg,
                                   azimuth_beamwidth_rad=ping.geometry.azimuth_beamwidth_rad))
    return out


def register_on_the_axis(pings: Sequence[Any], ranges: Sequence[Any], georef: Any) -> list[Any]:
    """:func:`register_as_cli` on the beams' axes: for the sonar's own detections, which are
    beam-centre estimates (amplitude or phase centre of the echo), not leading edges."""
    return register_as_cli(pings, ranges, georef, footprint_edge=False)


def register_on_the_cone(pings: Sequence[Any], ranges: Sequence[Any], georef: Any) -> list[Any]:
    """Like :func:`register_as_cli` but along the transmit cone's directions
    (:meth:`~sonarmap.mapping.navigation.KongsbergPlacement.cone_directions`) instead of the
    sensor's imaging plane: what the planar registration gives up (a diagnostic)."""
    from scipy.spatial.transform import Rotation

    from sonarmap.mapping.navigation import kongsberg_placement, kongsberg_pose, placed_ranges
    from sonarmap.mapping.register import PointCloud

    out = []
    for ping, br in zip(pings, ranges, strict=True):
        k = kongsberg_placement(ping)
        pose = kongsberg_pose(ping, georef)
        yaw = Rotation.from_quat(pose.orientation_xyzw).as_matrix() @ k.rotation.T
        r = np.asarray(placed_ranges(ping, br).range_m)
        keep = np.flatnonzero(np.isfinite(r))
        d = k.cone_directions(np.asarray(ping.geometry.azimuth_rad)[keep])
        xyz = pose.position_m + (r[keep, None] * d) @ yaw.T
        n = keep.size
        out.append(PointCloud(xyz, np.full(n, ping.time_ns), keep, r[keep], np.ones(n), np.ones(n), np.zeros(n)))
    return out


def sonar_xyz_world(ping: Any, georef: Any) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The sonar's XYZ 88 soundings of ``ping`` in ``georef``'s local NED frame, per image column.

    XYZ along/across are from the position fix's point (the active positioning system's antenna)
    in the heading frame of the X datagram's heading; depth is re the transmit transducer, whose
    depth re the water level the datagram gives.  Returns ``(n_beams, 3)`` points and the valid mask.
    """
    m = ping.meta
    fix = georef.geodetic_to_local(m["latitude_deg"], m["longitude_deg"], 0.0, frame="ned").reshape(-1)
    h = math.radians(m["xyz_heading_deg"])
    al, ac = m["xyz_along_m"], m["xyz_across_m"]
    north = fix[0] + al * math.cos(h) - ac * math.sin(h)
    east = fix[1] + al * math.sin(h) + ac * math.cos(h)
    depth = m["xyz_depth_m"] + m["xyz_tx_depth_m"]
    valid = np.asarray(m["xyz_valid"], bool) & np.isfinite(north) & np.isfinite(depth)
    return np.column_stack([north, east, depth]), valid


@dataclasses.dataclass(frozen=True)
class Registration:
    """Beam-matched differences of sonarmap's points from the sonar's XYZ (one head or all)."""

    name: str
    n_points: int
    median_m: float
    p95_m: float
    max_m: float
    mean_along_m: float
    mean_across_m: float
    mean_down_m: float
    mean_range_diff_m: float  # sonarmap's range - the sonar's detected range, mean
    # distance to the seabed profile through the sonar's soundings (profile_distances)
    surface_median_m: float = math.nan  # of |d|
    surface_p95_m: float = math.nan  # of |d|
    surface_mean_m: float = math.nan  # signed, + = deeper than the profile

    def row(self) -> str:
        return (f"| {self.name} | {self.n_points} | {self.median_m:.3f} | {self.p95_m:.3f} | {self.max_m:.3f} | "
                f"{self.mean_along_m:+.3f} | {self.mean_across_m:+.3f} | {self.mean_down_m:+.3f} | "
                f"{self.mean_range_diff_m:+.3f} | {self.surface_median_m:.3f} | {self.surface_p95_m:.3f} | "
                f"{self.surface_mean_m:+.3f} |")


def registration_errors(pings: Sequence[Any], ranges: Sequence[Any], georef: Any, *,
                        register: Any = register_as_cli) -> list[dict[str, Any]]:
    """Per ping with an XYZ datagram: sonarmap's point minus the sonar's, beam-matched.

    Each entry: ``serial``, ``counter``, ``error`` (n, 3) in the heading frame (along, across,
    down; the X datagram's heading), ``distance`` (n,), ``surface`` (n,: signed distance to the
    seabed profile through the sonar's soundings, :func:`profile_distances`), ``range_diff`` (n,),
    ``angle_deg`` (n,).
    ``register(pings, ranges, georef)`` makes the points (default: as ``sonarmap map``).
    """
    clouds = register(pings, ranges, georef)
    out = []
    for ping, br, cloud in zip(pings, ranges, clouds, strict=True):
        if "xyz_along_m" not in ping.meta:
            continue
        ref, valid = sonar_xyz_world(ping, georef)
        ours = np.full_like(ref, np.nan)
        ours[cloud.beam] = cloud.xyz_m
        keep = valid & np.isfinite(ours[:, 0])
        d = ours[keep] - ref[keep]
        h = math.radians(ping.meta["xyz_heading_deg"])
        along = d[:, 0] * math.cos(h) + d[:, 1] * math.sin(h)
        across = -d[:, 0] * math.sin(h) + d[:, 1] * math.cos(h)
        out.append({
            "serial": ping.meta["system_serial"], "counter": ping.meta["ping_counter"],
            "attitude_gap_s": ping.meta.get("attitude_gap_s", math.nan),
            "error": np.column_stack([along, across, d[:, 2]]), "distance": np.linalg.norm(d, axis=1),
            "surface": profile_distances(ours[keep], ref, valid, h),
            "range_diff": (np.asarray(br.range_m) - ping.meta["detected_range_m"])[keep],
            "angle_deg": np.abs(ping.meta["beam_pointing_angle_deg"])[keep],
        })
    return out


def profile_distances(points: NDArray[np.float64], ref: NDArray[np.float64], valid: NDArray[np.bool_],
                      heading_rad: float) -> NDArray[np.float64]:
    """Signed distance (+ = deeper) of world ``points`` (n, 3) to the seabed profile through the
    sonar's soundings ``ref`` (n_beams, 3) of the same ping, in the across-track plane.

    The soundings' valid points, in order of their across-track coordinate (heading frame), are
    joined into a polyline in (across, down); each point's distance is to its nearest segment, NaN
    for points outside the profile's across-track span.  The along-track coordinate is left out
    (the swath is a line across track to a few cm, 0.19 m at 60 deg: the transmit cone).
    """
    c, s = math.cos(heading_rad), math.sin(heading_rad)

    def across_down(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.column_stack([-p[:, 0] * s + p[:, 1] * c, p[:, 2]])

    prof = across_down(ref[valid])
    prof = prof[np.argsort(prof[:, 0])]
    q = across_down(points)
    out = np.full(q.shape[0], np.nan)
    if prof.shape[0] < 2:
        return out
    a, b = prof[:-1], prof[1:]
    ab = b - a
    t = np.clip(np.einsum("psk,sk->ps", q[:, None, :] - a[None], ab) / np.einsum("sk,sk->s", ab, ab), 0.0, 1.0)
    foot = a[None] + t[..., None] * ab[None]
    d = np.linalg.norm(q[:, None, :] - foot, axis=2)
    k = np.argmin(d, axis=1)
    inside = (q[:, 0] >= prof[0, 0]) & (q[:, 0] <= prof[-1, 0])
    below = q[:, 1] >= foot[np.arange(q.shape[0]), k, 1]
    out[inside] = np.where(below, 1.0, -1.0)[inside] * d[np.arange(q.shape[0]), k][inside]
    return out


def summarize_registration(name: str, entries: Sequence[dict[str, Any]]) -> Registration:
    """Median / p95 / max 3-D distance and the mean error per axis of ``entries``."""
    if not entries:
        return Registration(name, 0, *(math.nan,) * 7)
    dist = np.concatenate([e["distance"] for e in entries])
    err = np.concatenate([e["error"] for e in entries])
    rd = np.concatenate([e["range_diff"] for e in entries])
    if dist.size == 0:
        return Registration(name, 0, *(math.nan,) * 7)
    surf = np.concatenate([e["surface"] for e in entries])
    surf = surf[np.isfinite(surf)]
    return Registration(name, int(dist.size), float(np.median(dist)), float(np.percentile(dist, 95)),
                        float(dist.max()), *(float(v) for v in err.mean(axis=0)), float(np.nanmean(rd)),
                        *((float(np.median(np.abs(surf))), float(np.percentile(np.abs(surf), 95)), float(surf.mean()))
                          if surf.size else (math.nan,) * 3))


def detected_ranges(pings: Sequence[Any]) -> list[Any]:
    """The sonar's own detected range per beam (the water-column datagram's) as BeamRanges."""
    return [beam_ranges(p, p.meta["detected_range_m"]) for p in pings]


def travel_time_ranges(pings: Sequence[Any]) -> list[Any]:
    """The sonar's detection as the raw range datagram's two-way travel time, ``c t / 2``: the
    water-column detected range is that time in whole water-column samples."""
    return [beam_ranges(p, p.meta["raw_twtt_s"] * p.meta["sound_speed_m_s"] / 2.0) for p in pings]


def pipeline_ranges(pings: Sequence[Any], config: Any = None) -> list[Any]:
    """The pipeline's first return per beam (``config``, default ``PipelineConfig()``)."""
    from sonarmap.pipeline import PipelineConfig, process_ping

    cfg = PipelineConfig() if config is None else config
    return [process_ping(p, cfg).ranges for p in pings]


def amplitude_peak_m(ping: Any, min_range_m: float = BASELINE_MIN_RANGE_M) -> NDArray[np.float64]:
    """The baseline: the range of each beam's largest sample beyond ``min_range_m``."""
    img = np.array(ping.image, dtype=np.float32, copy=True)
    rng = np.asarray(ping.geometry.range_m, dtype=np.float64)
    img[rng < min_range_m, :] = -np.inf
    return rng[np.argmax(img, axis=0)]


def echo_leading_edge_m(ping: Any, before: int = EDGE_SEARCH_SAMPLES[0],
                        after: int = EDGE_SEARCH_SAMPLES[1]) -> NDArray[np.float64]:
    """The range convention applied to the echo the sonar detected: per beam, the first crossing
    of half the echo's peak (the largest sample from ``before`` samples in front of the detected
    sample to ``after`` behind it), walking back from the peak on the raw samples, linearly
    interpolated; NaN where the sonar has no detection.  An oracle: it is told where the echo is."""
    img = np.asarray(ping.image, dtype=np.float64)
    rng = np.asarray(ping.geometry.range_m, dtype=np.float64)
    det = np.asarray(ping.meta["detected_bin"])
    out = np.full(img.shape[1], np.nan)
    for b in np.flatnonzero((det >= 0) & np.isfinite(np.asarray(ping.meta["detected_range_m"], dtype=np.float64))):
        lo, hi = max(int(det[b]) - before, 0), min(int(det[b]) + after + 1, img.shape[0])
        col = img[:, b]
        k = lo + int(np.argmax(col[lo:hi]))
        half = 0.5 * col[k]
        j = k
        while j > 0 and col[j - 1] >= half:
            j -= 1
        x = (j - 1) + (half - col[j - 1]) / (col[j] - col[j - 1]) if j > 0 else 0.0
        out[b] = rng[0] + x * (rng[1] - rng[0])
    return out


def tolerance_m(ping: Any) -> NDArray[np.float64]:
    """Per beam: max(2 samples, half the flat-seabed footprint's range extent at the detection)."""
    m = ping.meta
    theta = np.radians(np.abs(np.asarray(m["beam_pointing_angle_deg"], dtype=np.float64)))
    width = math.radians(float(m["runtime_rx_beamwidth_deg"]))
    footprint = np.asarray(m["detected_range_m"]) * np.tan(theta) * width
    return np.maximum(TOLERANCE_SAMPLES * float(m["range_per_sample_m"]), 0.5 * footprint)


def band_name(lo: float, hi: float) -> str:
    """A beam-angle band as the tables name it: ``"15-30°"``, ``"≥ 45°"``, ``"all angles"``."""
    if (lo, hi) == (0.0, 90.0):
        return "all angles"
    return f"{lo:.0f}-{hi:.0f}°" if hi < 90 else f"≥ {lo:.0f}°"


@dataclasses.dataclass(frozen=True)
class Detection:
    """(a) for one head and angle band."""

    serial: int
    band: tuple[float, float]
    n_beams: int
    n_returns: int
    sonarmap_pass: int
    sonarmap_early: int  # returns before the detection by more than the tolerance
    sidelobe_arc: int  # ... of which within 3 samples of the ping's nadir (minimum) range
    peak_pass: int
    edge_pass: int  # the range convention at the sonar's detection (echo_leading_edge_m) passes
    sonarmap_edge_pass: int  # sonarmap's return within TOLERANCE_SAMPLES of that leading edge
    level_db: float  # median sample level at the sonar's detection (the file's dB, TVG applied)

    @property
    def sonarmap_fraction(self) -> float:
        return self.sonarmap_pass / self.n_beams if self.n_beams else math.nan

    @property
    def peak_fraction(self) -> float:
        return self.peak_pass / self.n_beams if self.n_beams else math.nan

    def row(self) -> str:
        lo, hi = self.band
        band = band_name(lo, hi)
        head = "both" if self.serial < 0 else str(self.serial)
        within = f"{self.sonarmap_pass / self.n_returns:.3f}" if self.n_returns else "-"
        frac = (lambda n: f"{n / self.n_beams:.3f}") if self.n_beams else (lambda n: "-")
        return (f"| {head} | {band} | {self.n_beams} | {self.level_db:.1f} | {self.n_returns} | "
                f"{self.sonarmap_fraction:.3f} | {within} | {self.sonarmap_early} ({self.sidelobe_arc}) | "
                f"{self.peak_fraction:.3f} | {frac(self.edge_pass)} | {frac(self.sonarmap_edge_pass)} |")


def detection_table(pings: Sequence[Any], ranges: Sequence[Any],
                    bands: Sequence[tuple[float, float]] = BANDS_DEG) -> list[Detection]:
    """(a) per head and angle band, then per head over all bands, then everything (serial -1)."""
    from sonarmap.io.kongsberg import image_to_db

    rows: dict[tuple[int, tuple[float, float]], list[NDArray[Any]]] = {}
    levels: dict[tuple[int, tuple[float, float]], list[NDArray[Any]]] = {}
    for ping, br in zip(pings, ranges, strict=True):
        m = ping.meta
        det = np.asarray(m["detected_range_m"], dtype=np.float64)
        ok = np.isfinite(det)
        r = np.asarray(br.range_m, dtype=np.float64)
        tol = tolerance_m(ping)
        step = float(m["range_per_sample_m"])
        passed = np.abs(r - det) <= tol  # NaN (no return) fails
        early = r < det - tol
        nadir = np.nanmin(det)
        arc = early & (np.abs(r - nadir) <= 3 * step)
        peak = np.abs(amplitude_peak_m(ping) - det) <= tol
        edge = echo_leading_edge_m(ping)
        edge_pass = np.abs(edge - det) <= tol
        on_edge = np.abs(r - edge) <= TOLERANCE_SAMPLES * step
        ang = np.abs(np.asarray(m["beam_pointing_angle_deg"], dtype=np.float64))
        stack = np.vstack([ok, np.isfinite(r), passed, early, arc, peak, edge_pass, on_edge]).astype(np.int64)
        row = np.asarray(m["detected_bin"])
        cols = np.arange(row.size)
        db = np.where(row >= 0, image_to_db(ping.image[np.clip(row, 0, None), cols]), np.nan)
        for band in bands:
            sel = ok & (ang >= band[0]) & (ang < band[1])
            for key in ((int(m["system_serial"]), band), (int(m["system_serial"]), (0.0, 90.0)),
                        (-1, band), (-1, (0.0, 90.0))):
                rows.setdefault(key, []).append(stack[:, sel].sum(axis=1))
                levels.setdefault(key, []).append(db[sel])
    out = []
    for (serial, band), parts in sorted(rows.items(), key=lambda kv: (kv[0][0] < 0, kv[0][0], kv[0][1] == (0.0, 90.0),
                                                                     kv[0][1])):
        tot = np.sum(parts, axis=0)
        lv = np.concatenate(levels[(serial, band)])
        out.append(Detection(serial, band, *(int(v) for v in tot),
                             level_db=float(np.nanmedian(lv)) if np.isfinite(lv).any() else math.nan))
    return out


def transmit_fan_fit(pings: Sequence[Any]) -> list[dict[str, float]]:
    """Evidence for the transmit geometry: per ping counter, both heads' XYZ soundings fitted as
    ``along = x0 + r sin(s) + across sin(q)`` (``r`` the sounding's distance in the across-down
    plane).  A steered line array's cone gives ``s = -tau`` for a tilt towards the array's +x
    (aft: the TX array is mounted with heading 180.52); a plane would give ``s = 0``."""
    by: dict[int, list[Any]] = {}
    for p in pings:
        if "xyz_along_m" in p.meta:
            by.setdefault(int(p.meta["ping_counter"]), []).append(p.meta)
    out = []
    for counter, metas in sorted(by.items()):
        al, ac, dp = (np.concatenate([m[k][m["xyz_valid"]] for m in metas])
                      for k in ("xyz_along_m", "xyz_across_m", "xyz_depth_m"))
        A = np.column_stack([np.ones(al.size), np.hypot(ac, dp), ac])
        coef, *_ = np.linalg.lstsq(A, al, rcond=None)
        out.append({"counter": counter, "pitch_deg": float(metas[0]["pitch_deg"]),
                    "attitude_gap_s": float(metas[0].get("attitude_gap_s", math.nan)), "x0_m": float(coef[0]),
                    "s_deg": math.degrees(math.asin(coef[1])), "q_deg": math.degrees(math.asin(coef[2])),
                    "rms_m": float(np.sqrt(np.mean((A @ coef - al) ** 2)))})
    return out


def sound_speed_profiles(path: Path = RECORDING) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """The ``U`` (sound speed profile) datagrams of an ``.all``: (depth m, sound speed m/s) each."""
    raw = path.read_bytes()
    out = []
    off = 0
    while off + 24 <= len(raw):
        n = int.from_bytes(raw[off:off + 4], "little")
        if raw[off + 5] == 0x55 and n >= 16 + 12 + 3:
            body = raw[off + 20:off + 4 + n - 3]
            count, res_cm = np.frombuffer(body[8:12], "<u2")
            e = np.frombuffer(body[12:12 + 8 * int(count)], "<u4").reshape(-1, 2)
            out.append((e[:, 0] * float(res_cm) / 100.0, e[:, 1] / 10.0))
        off += 4 + n
    return out


def run(path: Path = RECORDING, config: Any = None) -> dict[str, Any]:
    """Everything the docs' tables show: (b) with the detections and with the pipeline, and (a)."""
    from sonarmap.mapping.navigation import navigation_origin

    pings = read_recording(path)
    georef = navigation_origin(pings[0])
    det = detected_ranges(pings)
    pipe = pipeline_ranges(pings, config)
    twtt = travel_time_ranges(pings)
    out: dict[str, Any] = {"pings": pings, "georef": georef}
    for name, ranges, register in (("detections", det, register_on_the_axis), ("pipeline", pipe, register_as_cli),
                                   ("pipeline_axis", pipe, register_on_the_axis),
                                   ("travel_time", twtt, register_on_the_axis),
                                   ("travel_time_cone", twtt, register_on_the_cone)):
        entries = registration_errors(pings, ranges, georef, register=register)
        out[name] = registration_rows(entries)
        out[f"{name}_entries"] = entries
    passed = [_passed_only(p, br) for p, br in zip(pings, pipe, strict=True)]
    out["pipeline_passed"] = registration_rows(registration_errors(pings, passed, georef))
    out["pipeline_passed_axis"] = registration_rows(registration_errors(pings, passed, georef,
                                                                        register=register_on_the_axis))
    out["detection"] = detection_table(pings, pipe)
    out["offsets"] = offsets_by_band(pings, pipe)
    out["fan_fit"] = transmit_fan_fit(pings)
    out["sound_speed_profiles"] = sound_speed_profiles(path)
    return out


def seabed_by_band(entries: Sequence[dict[str, Any]], bands: Sequence[tuple[float, float]] = BANDS_DEG
                   ) -> list[tuple[str, int, float, float]]:
    """Per beam-angle band, then over all: ``(band, points, RMS, mean)`` of the points' signed
    distance to the seabed through the sonar's soundings (m; + = deeper), from
    :func:`registration_errors` entries."""
    surf = np.concatenate([e["surface"] for e in entries]) if entries else np.zeros(0)
    ang = np.concatenate([e["angle_deg"] for e in entries]) if entries else np.zeros(0)
    ok = np.isfinite(surf)
    surf, ang = surf[ok], ang[ok]
    out = []
    for lo, hi in (*bands, (0.0, 90.0)):
        sel = (ang >= lo) & (ang < hi)
        name = band_name(lo, hi)
        v = surf[sel]
        out.append((name, int(v.size), float(np.sqrt(np.mean(v * v))) if v.size else math.nan,
                    float(v.mean()) if v.size else math.nan))
    return out


def offsets_by_band(pings: Sequence[Any], ranges: Sequence[Any], bands: Sequence[tuple[float, float]] = BANDS_DEG
                    ) -> list[tuple[str, float, float]]:
    """Per beam-angle band (both heads): ``(band, median of detection - return, median of
    |return - the single-beam leading edge at the detection|)``, in samples."""
    det_minus, to_edge, ang = [], [], []
    for ping, br in zip(pings, ranges, strict=True):
        r = np.asarray(br.range_m, dtype=np.float64)
        step = float(ping.meta["range_per_sample_m"])
        det_minus.append((np.asarray(ping.meta["detected_range_m"], dtype=np.float64) - r) / step)
        to_edge.append(np.abs(r - echo_leading_edge_m(ping)) / step)
        ang.append(np.abs(np.asarray(ping.meta["beam_pointing_angle_deg"], dtype=np.float64)))
    d, e, a = (np.concatenate(x) for x in (det_minus, to_edge, ang))
    out = []
    for lo, hi in bands:
        sel = (a >= lo) & (a < hi)
        name = band_name(lo, hi)
        out.append((name, float(np.nanmedian(d[sel])), float(np.nanmedian(e[sel]))))
    return out


def registration_rows(entries: Sequence[dict[str, Any]]) -> list[Registration]:
    """Per head, both heads, and both heads on the pings with measured attitude."""
    rows = [summarize_registration(f"head {s}", [e for e in entries if e["serial"] == s])
            for s in sorted({e["serial"] for e in entries})]
    rows.append(summarize_registration("both heads", entries))
    rows.append(summarize_registration("both, measured attitude", [e for e in entries if e["attitude_gap_s"] == 0]))
    return rows


def _passed_only(ping: Any, br: Any) -> Any:
    """``br`` with only the returns that pass (a) (the others NaN)."""
    r = np.asarray(br.range_m, dtype=np.float64)
    ok = np.abs(r - ping.meta["detected_range_m"]) <= tolerance_m(ping)
    return beam_ranges(ping, np.where(ok, r, np.nan))


def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description="Kongsberg EM 2040 detection and registration checks")
    ap.add_argument("--config", default=None,
                    help="pipeline configuration (TOML, as `sonarmap process --config` reads it); default PipelineConfig()")
    args = ap.parse_args(argv)
    config = None
    if args.config is not None:
        from sonarmap.pipeline import PipelineConfig

        config = PipelineConfig.from_toml(args.config)
    res = run(config=config)
    print("Transmit fan: along = x0 + r sin(s) + across sin(q), both heads' XYZ soundings per ping")
    print("| ping | pitch (deg) | attitude gap (s) | x0 (m) | s (deg) | q (deg) | rms (m) |\n|---|---|---|---|---|---|---|")
    for f in res["fan_fit"]:
        print(f"| {f['counter']} | {f['pitch_deg']:+.3f} | {f['attitude_gap_s']:.2f} | {f['x0_m']:.3f} | "
              f"{f['s_deg']:+.3f} | {f['q_deg']:+.3f} | {f['rms_m']:.4f} |")
    for depth, speed in res["sound_speed_profiles"]:
        top = depth <= 30.0
        print(f"\nsound speed profile (U): {depth.size} points; 0-30 m: "
              + ", ".join(f"{d:g} m {c:.1f}" for d, c in zip(depth[top], speed[top])) + " m/s")
    head = ("| | points | median (m) | p95 (m) | max (m) | mean along (m) | mean across (m) | mean down (m) | "
            "mean range - detection (m) | to the seabed: median (m) | p95 (m) | mean, + deeper (m) |"
            "\n|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, title in (("detections", "(b) geometry: the sonar's detected ranges through sonarmap's placement"),
                        ("travel_time", "(b) geometry, the detection as the raw range datagram's travel time"),
                        ("travel_time_cone", "(b) the same on the transmit cone instead of the imaging plane"),
                        ("pipeline", "(b) sonarmap's default pipeline, first return per beam (footprint edge)"),
                        ("pipeline_axis", "(b) the same on the beams' axes (--beam-axis)"),
                        ("pipeline_passed", "(b) the pipeline's returns that pass (a)"),
                        ("pipeline_passed_axis", "(b) the same on the beams' axes")):
        print(f"\n{title}\n{head}")
        for row in res[name]:
            print(row.row())
    print("\n(a) first return vs the sonar's detection (pass: within max(2 samples, half the footprint))")
    print("| head | band | beams | level at detection (dB) | returns | sonarmap pass / beams | pass / returns | "
          "early (on the sidelobe arc) | amplitude peak pass / beams | leading edge at the detection pass / beams | "
          "sonarmap within 2 samples of that edge / beams |\n|---|---|---|---|---|---|---|---|---|---|---|")
    for row in res["detection"]:
        print(row.row())
    print("\n(a) per band, both heads: median detection - return, median |return - the single-beam edge| (samples)")
    print("| band | detection - return | return to the edge |\n|---|---|---|")
    for name, d, e in res["offsets"]:
        print(f"| {name} | {d:+.2f} | {e:.2f} |")
    print("\n(b) the pipeline's points to the seabed per band, both heads: RMS / mean (cm, + deeper)")
    print("| band | points, axis | axis | points, footprint edge | footprint edge |\n|---|---|---|---|---|")
    for ax, fp in zip(seabed_by_band(res["pipeline_axis_entries"]), seabed_by_band(res["pipeline_entries"]),
                      strict=True):
        print(f"| {ax[0]} | {ax[1]} | {100 * ax[2]:.1f} / {100 * ax[3]:+.1f} | {fp[1]} | "
              f"{100 * fp[2]:.1f} / {100 * fp[3]:+.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
