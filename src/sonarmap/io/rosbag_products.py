"""sonarmap products as ROS 1 / ROS 2 bags: ranges as ``marine_acoustic_msgs/SonarRanges``, point
clouds as ``sensor_msgs/PointCloud2``.

Both writers emit one message per ping, stamped (header and bag record time) with the ping's time
in integer nanoseconds, and replace the output atomically (like :func:`sonarmap.io.rosbag.write_bag`).

``SonarRanges`` (one per ping, ``header.frame_id`` the sonar's frame)
    ``ranges[j]`` is beam ``j``'s range (``BeamRanges.range_m``, float32); ``beam_unit_vec[j]`` is
    ``(0, -sin a, cos a)`` for its azimuth ``a`` - the same convention as the
    ``beam_directions`` that :func:`~sonarmap.io.rosbag.write_bag` writes (z forward, x up, y to
    port; see :mod:`sonarmap.io.rosbag`); ``intensities[j]`` the echo's strength (image intensity at its first peak);
    ``flags[j].flag`` ``DETECT_OK`` (0) for a beam with a return and ``DETECT_BAD_FILTER`` (2, "bad
    by an automated filter applied during processing") for a beam without one, whose range and
    intensity are NaN.  ``transmit_delays`` is empty (not reported); ``ping_info`` has the
    geometry's frequency, sound speed and beam widths (:func:`~sonarmap.io.rosbag.beamwidths`).
``PointCloud2`` (one per ping, ``height`` 1, little-endian, ``is_dense`` when every point is finite)
    Fields ``x``, ``y``, ``z`` (float32, or float64 with ``xyz_dtype="float64"`` - projected
    coordinates need it), ``intensity`` (float32), ``range`` (float32, m), ``beam`` (uint16) and
    ``time`` (float32, seconds after ``header.stamp``: every point of a sonarmap ping has the ping's
    time, so 0).  Coordinates are the cloud's own (``PointCloud.frame``); ``frame_id`` defaults to
    ``map`` for ENU clouds and ``map_ned`` for NED ones (REP 103 / REP 105 naming).
Occupancy maps (:func:`write_occupancy_bag`)
    One ``PointCloud2`` of the occupied cell centres stamped with the last ping's time, fields
    ``x``, ``y``, ``z``, ``p_occupied`` and ``log_odds`` (float32): the occupancy schema of the
    PLY / CSV outputs.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import Any

import numpy as np

from sonarmap.errors import InputError
from sonarmap.geometry import SonarGeometry
from sonarmap.io.rosbag_msgs import DETECT_BAD_FILTER, DETECT_OK, DETECTION_FLAG, POINTCLOUD2, SONAR_RANGES

__all__ = ["write_ranges_bag", "RangesBagWriter", "write_points_bag", "write_occupancy_bag", "POINT_FIELDS", "OCCUPANCY_FIELDS"]

#: PointField datatypes (sensor_msgs/PointField constants).
_UINT16, _FLOAT32, _FLOAT64 = 4, 7, 8

#: Fields of the written PointCloud2 after x, y, z: (name, PointField datatype, numpy dtype).
POINT_FIELDS = (("intensity", _FLOAT32, "<f4"), ("range", _FLOAT32, "<f4"), ("beam", _UINT16, "<u2"),
                ("time", _FLOAT32, "<f4"))


def write_ranges_bag(
    ranges: Iterable[tuple[SonarGeometry, Any]],
    path: str | os.PathLike[str],
    *,
    version: int = 2,
    topic: str = "/sonar/ranges",
    frame_id: str = "sonar",
) -> int:
    """Write per-ping ranges as ``marine_acoustic_msgs/SonarRanges``; returns the message count.

    Parameters
    ----------
    ranges : iterable of (SonarGeometry, BeamRanges)
        Each ping's geometry and its ranges (``BeamRanges.time_ns`` is the stamp).
    path : path-like
        ROS 1: the ``.bag`` file; ROS 2: the bag directory.  Replaced atomically.
    version : {1, 2}
    topic, frame_id : str
        Topic of the messages and their ``header.frame_id``.

    Returns
    -------
    int
        Number of SonarRanges messages (pings) written.

    Raises
    ------
    InputError
        Bad ``version``, or ranges whose beam count differs from their geometry's.

    Notes
    -----
    Field mapping: see the module notes.

    Examples
    --------
    >>> from sonarmap.pipeline import process_ping                      # doctest: +SKIP
    >>> items = ((p.geometry, process_ping(p).ranges) for p in pings)   # doctest: +SKIP
    >>> write_ranges_bag(items, "ranges.bag", version=1)                 # doctest: +SKIP
    """
    with RangesBagWriter(path, version=version, topic=topic, frame_id=frame_id) as out:
        for geometry, r in ranges:
            out.write(geometry, r)
        return out.n_written


class RangesBagWriter:
    """Write ``SonarRanges`` one ping at a time (what :func:`write_ranges_bag` and the live bag
    sink use); the bag appears at ``path`` when :meth:`close` succeeds (written beside it until
    then), and an exception inside a ``with`` block leaves nothing at ``path``.

    Parameters
    ----------
    path : path-like
        ROS 1: the ``.bag`` file; ROS 2: the bag directory.
    version : {1, 2}
    topic, frame_id : str
        Topic of the messages and their ``header.frame_id``.
    """

    def __init__(self, path: str | os.PathLike[str], *, version: int = 2, topic: str = "/sonar/ranges",
                 frame_id: str = "sonar") -> None:
        from sonarmap.io.rosbag import bag_writer

        self.version = version
        self.frame_id = frame_id
        self.n_written = 0
        self._cm = bag_writer(path, version)
        self._writer, self._serialize, self._store = self._cm.__enter__()
        try:
            self._conn = self._writer.add_connection(topic, SONAR_RANGES, typestore=self._store)
        except BaseException as exc:
            self._cm.__exit__(type(exc), exc, exc.__traceback__)
            raise
        self._open = True

    def write(self, geometry: SonarGeometry, r: Any) -> None:
        """Append one ping's ranges (stamped with ``r.time_ns``)."""
        from sonarmap.io.rosbag import beam_vectors, header, ping_info

        if r.n_beams != geometry.n_beams:
            raise InputError(f"ranges: {r.n_beams} beams for a geometry of {geometry.n_beams} (ping {self.n_written})")
        store, T = self._store, self._store.types
        hit = np.asarray(r.bin) >= 0
        rng = np.where(hit, np.asarray(r.range_m, dtype=np.float64), np.nan).astype(np.float32)
        inten = np.where(hit, np.asarray(r.intensity, dtype=np.float64), np.nan).astype(np.float32)
        t_ns = int(r.time_ns)
        flag_t = T[DETECTION_FLAG]
        msg = T[SONAR_RANGES](
            header=header(store, self.version, t_ns, self.frame_id, self.n_written),
            ping_info=ping_info(geometry, store),
            flags=[flag_t(flag=DETECT_OK if h else DETECT_BAD_FILTER) for h in hit],
            transmit_delays=np.zeros(0, np.float32),
            intensities=inten,
            beam_unit_vec=beam_vectors(np.asarray(r.azimuth_rad, dtype=np.float64), store),
            ranges=rng,
        )
        self._writer.write(self._conn, t_ns, self._serialize(msg, SONAR_RANGES))
        self.n_written += 1

    def close(self, error: BaseException | None = None) -> None:
        """Finish the bag and move it onto ``path`` (with ``error``: discard it)."""
        if not self._open:
            return
        self._open = False
        if error is None:
            self._cm.__exit__(None, None, None)
        else:
            self._cm.__exit__(type(error), error, error.__traceback__)

    def __enter__(self) -> RangesBagWriter:
        return self

    def __exit__(self, exc_type: Any, exc: BaseException | None, tb: Any) -> None:
        self.close(exc)


def _pointcloud2(store: Any, version: int, xyz: np.ndarray, columns: Iterable[tuple[str, int, str, np.ndarray]],
                 t_ns: int, frame_id: str, xyz_dtype: str, seq: int) -> Any:
    """A PointCloud2 of the points ``xyz (n, 3)`` with further ``(name, PointField datatype,
    numpy dtype, values)`` columns, packed without padding."""
    from sonarmap.io.rosbag import header

    T = store.types
    cols = list(columns)
    xyz_np = "<f4" if xyz_dtype == "float32" else "<f8"
    xyz_code = _FLOAT32 if xyz_dtype == "float32" else _FLOAT64
    names = ["x", "y", "z"] + [c[0] for c in cols]
    dt = np.dtype({"names": names, "formats": [xyz_np] * 3 + [c[2] for c in cols]})  # packed
    n = int(xyz.shape[0])
    rec = np.zeros(n, dtype=dt)
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for name, _, _, values in cols:
        rec[name] = values
    field_t = T["sensor_msgs/msg/PointField"]
    fields = [field_t(name=nm, offset=int(dt.fields[nm][1]), datatype=code, count=1)
              for nm, code in zip(names, [xyz_code] * 3 + [c[1] for c in cols])]
    finite = bool(np.all(np.isfinite(xyz))) if n else True
    return T[POINTCLOUD2](
        header=header(store, version, t_ns, frame_id, seq),
        height=1, width=n, fields=fields, is_bigendian=False,
        point_step=int(dt.itemsize), row_step=int(dt.itemsize * n),
        data=np.frombuffer(rec.tobytes(), dtype=np.uint8), is_dense=finite,
    )


def _cloud_message(store: Any, version: int, cloud: Any, idx: np.ndarray, t_ns: int, frame_id: str,
                   xyz_dtype: str, seq: int) -> Any:
    """One PointCloud2 of the points ``idx`` of ``cloud`` (all of the ping at ``t_ns``)."""
    values = {"intensity": cloud.intensity[idx], "range": cloud.range_m[idx],
              "beam": np.clip(cloud.beam[idx], 0, 65535),
              "time": ((cloud.time_ns[idx] - t_ns) * 1e-9).astype(np.float32)}
    return _pointcloud2(store, version, cloud.xyz_m[idx], [(*field, values[field[0]]) for field in POINT_FIELDS],
                        t_ns, frame_id, xyz_dtype, seq)


def write_points_bag(
    clouds: Iterable[Any],
    path: str | os.PathLike[str],
    *,
    version: int = 2,
    topic: str = "/sonarmap/points",
    frame_id: str | None = None,
    xyz_dtype: str = "float32",
) -> int:
    """Write registered points as ``sensor_msgs/PointCloud2``, one message per ping; returns the count.

    Parameters
    ----------
    clouds : iterable of PointCloud
        Registered points (:func:`sonarmap.mapping.register.register_ranges`); the points of one
        ping share its ``time_ns``, and pings are written in the order they first appear.
    path : path-like
        ROS 1: the ``.bag`` file; ROS 2: the bag directory.  Replaced atomically.
    version : {1, 2}
    topic : str
    frame_id : str, optional
        ``header.frame_id``; default ``"map"`` for an ENU cloud, ``"map_ned"`` for a NED one.
    xyz_dtype : {"float32", "float64"}
        Type of ``x``, ``y``, ``z``; float64 keeps projected (UTM) coordinates exact.

    Returns
    -------
    int
        Number of PointCloud2 messages written.

    Raises
    ------
    InputError
        Bad ``version`` or ``xyz_dtype``.

    Examples
    --------
    >>> write_points_bag([cloud], "points.bag", version=1)  # doctest: +SKIP
    """
    if xyz_dtype not in ("float32", "float64"):
        raise InputError(f"xyz_dtype: choose from float32, float64 (got {xyz_dtype!r})")
    from sonarmap.io.rosbag import bag_writer

    n = 0
    with bag_writer(path, version) as (writer, serialize, store):
        conn = writer.add_connection(topic, POINTCLOUD2, typestore=store)
        for cloud in clouds:
            if len(cloud) == 0:
                continue
            fid = frame_id if frame_id is not None else ("map" if cloud.frame == "enu" else "map_ned")
            times = np.asarray(cloud.time_ns, dtype=np.int64)
            uniq, first = np.unique(times, return_index=True)
            for t in uniq[np.argsort(first, kind="stable")]:
                idx = np.flatnonzero(times == t)
                msg = _cloud_message(store, version, cloud, idx, int(t), fid, xyz_dtype, n)
                writer.write(conn, int(t), serialize(msg, POINTCLOUD2))
                n += 1
    return n


#: Fields of the occupancy PointCloud2 after x, y, z (the occupancy schema of PLY / CSV outputs).
OCCUPANCY_FIELDS = (("p_occupied", _FLOAT32, "<f4"), ("log_odds", _FLOAT32, "<f4"))


def write_occupancy_bag(
    xyz_m: np.ndarray,
    p_occupied: np.ndarray,
    log_odds: np.ndarray,
    path: str | os.PathLike[str],
    *,
    stamp_ns: int,
    frame: str = "ned",
    version: int = 2,
    topic: str = "/sonarmap/occupancy",
    frame_id: str | None = None,
    xyz_dtype: str = "float32",
) -> int:
    """Write an occupancy map's occupied cells as one ``sensor_msgs/PointCloud2``; returns 1.

    Parameters
    ----------
    xyz_m : ndarray, shape (n, 3)
        Occupied cell centres (:meth:`~sonarmap.mapping.occupancy.OccupancyMap.to_point_cloud`).
    p_occupied, log_odds : ndarray, shape (n,)
        Each cell's occupancy probability and its log-odds
        (:func:`sonarmap.mapping.pointcloud.occupancy_columns`).
    path : path-like
        ROS 1: the ``.bag`` file; ROS 2: the bag directory.  Replaced atomically.
    stamp_ns : int
        ``header.stamp`` and record time: the time of the last ping the map holds.
    version : {1, 2}
    topic : str
    frame : {"ned", "enu"}
        The frame of ``xyz_m``.
    frame_id : str, optional
        Default ``"map"`` for an ENU cloud, ``"map_ned"`` for a NED one.
    xyz_dtype : {"float32", "float64"}

    Notes
    -----
    Fields ``x``, ``y``, ``z`` (cell centres), ``p_occupied`` (float32) and ``log_odds``
    (float32, ``log(p / (1 - p))``): RViz colours the cells by either.
    """
    if xyz_dtype not in ("float32", "float64"):
        raise InputError(f"xyz_dtype: choose from float32, float64 (got {xyz_dtype!r})")
    from sonarmap.io.rosbag import bag_writer

    xyz = np.asarray(xyz_m, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(p_occupied, dtype=np.float32).ravel()
    lo = np.asarray(log_odds, dtype=np.float32).ravel()
    if p.size != xyz.shape[0] or lo.size != xyz.shape[0]:
        raise InputError(f"p_occupied / log_odds: {p.size} / {lo.size} values for {xyz.shape[0]} cells")
    fid = frame_id if frame_id is not None else ("map" if frame == "enu" else "map_ned")
    with bag_writer(path, version) as (writer, serialize, store):
        conn = writer.add_connection(topic, POINTCLOUD2, typestore=store)
        columns = [(*field, values) for field, values in zip(OCCUPANCY_FIELDS, (p, lo), strict=True)]
        msg = _pointcloud2(store, version, xyz, columns, int(stamp_ns), fid, xyz_dtype, 0)
        writer.write(conn, int(stamp_ns), serialize(msg, POINTCLOUD2))
    return 1

