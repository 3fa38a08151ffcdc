"""Following a ROS 2 bag (sqlite3 storage) while it is recorded.

``ros2 bag record`` with the sqlite3 storage writes every message as a row of the ``messages``
table of ``<name>_0.db3`` as it goes (in transactions of a few messages), and ``metadata.yaml``
only when the recording ends, so a bag being recorded cannot be opened as a bag yet.
:func:`follow_sqlite_bag` reads the storage file itself: it polls the ``topics`` and ``messages``
tables (read-only) and decodes each new message of the sonar topic as
:func:`sonarmap.io.rosbag.iter_bag_pings` would - the same kinds in the same order of precedence
(ProjectedSonarImage, RawSonarImage, acoustic_msgs/SonarImage, Oculus RawData), the same
decoders, the upstream message definitions.  MCAP storage (the default of newer ROS 2
releases) is not followed: an MCAP file being written has no index to poll.
"""

from __future__ import annotations

import os
import sqlite3
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from sonarmap.errors import DataFormatError, GeometryError, InputError
from sonarmap.geometry import SonarGeometry, as_geometry
from sonarmap.ping import Ping

__all__ = ["follow_sqlite_bag", "sqlite_storage"]

#: Rows read per query.
_BATCH = 64


def sqlite_storage(path: str | os.PathLike[str]) -> Path | None:
    """The sqlite3 storage file of a ROS 2 bag: ``path`` itself (``*.db3``), or the first
    ``*.db3`` in the bag directory ``path``; None if there is none (yet)."""
    p = Path(path)
    if p.suffix == ".db3":
        return p if p.is_file() else None
    if p.is_dir():
        found = sorted(p.glob("*.db3"))
        return found[0] if found else None
    return None


def _connect(db: Path) -> sqlite3.Connection:
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=1.0, check_same_thread=False)
    con.execute("PRAGMA query_only = 1")
    return con


def _pick_topics(rows: list[tuple[int, str, str]], topic: str | None) -> tuple[str, dict[int, tuple[str, str]]]:
    """The kind to read and its topics ``{topic_id: (name, type)}`` (empty: none yet); for
    ProjectedSonarImage also the exact-geometry side channels sonarmap writes beside them."""
    from sonarmap.io.rosbag import _GEOMETRY_SUFFIX, _KINDS

    for kind, types in _KINDS:
        chosen = {i: (name, typ) for i, name, typ in rows if typ in types and (topic is None or name == topic)}
        if chosen:
            if kind == "projected":
                side = {n + _GEOMETRY_SUFFIX for n, _t in chosen.values()}
                side |= {n.rstrip("/") + _GEOMETRY_SUFFIX for n, _t in chosen.values()}
                chosen.update({i: (name, typ) for i, name, typ in rows
                               if name in side and typ == "std_msgs/msg/String"})
            return kind, chosen
    return "", {}


def follow_sqlite_bag(
    path: str | os.PathLike[str],
    *,
    stopped: Callable[[], bool] = lambda: False,
    sleep: Callable[[float], Any] = time.sleep,
    poll_s: float = 0.05,
    idle_timeout_s: float = 5.0,
    wait_s: float = 5.0,
    topic: str | None = None,
    geometry: SonarGeometry | str | os.PathLike[str] | None = None,
    handedness: str = "auto",
) -> Iterator[Ping]:
    """Yield the sonar pings of a ROS 2 sqlite3 bag as they are recorded (module notes).

    Parameters
    ----------
    path : path-like
        The bag directory being recorded, or its ``.db3`` file.
    stopped : callable
        Returns True when the caller wants the iteration to end.
    sleep : callable
        Waits the given seconds (the live source's interruptible sleep).
    poll_s : float
        Polling interval.
    idle_timeout_s : float
        End after this long without a new message (0: never).
    wait_s : float
        How long to wait for the storage file and a sonar topic to appear.
    topic, geometry, handedness
        As in :func:`sonarmap.io.rosbag.iter_bag_pings`.

    Raises
    ------
    DataFormatError
        No storage file or no sonar topic within ``wait_s``, or a message that does not decode.
    """
    from sonarmap.io.rosbag import HANDEDNESS, _ping_from_msg, add_exact_geometry, typestore, warn_guessed_handedness
    from sonarmap.io.rosbag_sources import OculusRawStreams, ping_from_legacy_image, ping_from_raw_sonar_image

    if handedness not in HANDEDNESS:
        raise InputError(f"handedness: choose from {', '.join(HANDEDNESS)} (got {handedness!r})")
    override = None if geometry is None else as_geometry(geometry)
    root = Path(path)
    t0 = time.monotonic()
    db = sqlite_storage(root)
    while db is None:
        if stopped():
            return
        if time.monotonic() - t0 > wait_s:
            raise DataFormatError("no ROS 2 sqlite3 storage file (*.db3) appeared", root)
        sleep(poll_s)
        db = sqlite_storage(root)
    store = typestore(2)
    con: sqlite3.Connection | None = None
    kind, topics = "", {}
    last_id = 0
    index: dict[str, int] = {}
    streams = OculusRawStreams(root, override)
    warned: set[str] = set()
    exact: dict[bytes, SonarGeometry] = {}
    last_new = time.monotonic()
    try:
        while not stopped():
            try:
                if con is None:
                    con = _connect(db)
                if not topics:
                    rows = con.execute("SELECT id, name, type FROM topics").fetchall()
                    kind, topics = _pick_topics([(int(i), str(n), str(t)) for i, n, t in rows], topic)
                    if not topics:
                        if time.monotonic() - t0 > wait_s:
                            seen = ", ".join(f"{n} ({t})" for _i, n, t in rows) or "no topics"
                            raise DataFormatError(f"no sonar topic to follow (the bag has {seen})", db)
                        sleep(poll_s)
                        continue
                marks = ",".join("?" * len(topics))
                batch = con.execute(
                    f"SELECT id, topic_id, data FROM messages WHERE id > ? AND topic_id IN ({marks}) "  # noqa: S608
                    "ORDER BY id LIMIT ?", (last_id, *topics, _BATCH)).fetchall()
            except sqlite3.OperationalError as exc:  # locked by the recorder, or not created yet
                if "no such table" in str(exc) and time.monotonic() - t0 > wait_s:
                    raise DataFormatError(f"not a ROS 2 sqlite3 bag: {exc}", db) from None
                if con is not None and "no such table" in str(exc):
                    con.close()
                    con = None
                sleep(poll_s)
                continue
            except sqlite3.DatabaseError as exc:
                raise DataFormatError(f"cannot read the bag's storage: {exc}", db) from None
            if not batch:
                if idle_timeout_s and time.monotonic() - last_new > idle_timeout_s:
                    break
                sleep(poll_s)
                continue
            last_new = time.monotonic()
            for row_id, topic_id, data in batch:
                last_id = int(row_id)
                name, msgtype = topics[int(topic_id)]
                i = index.get(name, 0)
                index[name] = i + 1
                try:
                    msg = store.deserialize_cdr(bytes(data), msgtype)
                except Exception as exc:  # noqa: BLE001
                    raise DataFormatError(f"corrupt message {i} on {name}: {type(exc).__name__}: {exc}", db) from None
                try:
                    if msgtype == "std_msgs/msg/String":  # a geometry side channel
                        index[name] = i
                        add_exact_geometry(exact, msg.data, root)
                        continue
                    if kind == "projected":
                        ping, guessed = _ping_from_msg(msg, root, name, i, override, exact, handedness)
                        if guessed and name not in warned:
                            warned.add(name)
                            warn_guessed_handedness(root, name)
                        yield ping
                    elif kind in ("raw_image", "legacy_image"):
                        decode = ping_from_raw_sonar_image if kind == "raw_image" else ping_from_legacy_image
                        yield decode(msg, root, name, i, override)
                    else:  # Oculus RawData: the topic's incoming byte stream
                        yield from streams.pings(name, i, msg)
                except (ValueError, GeometryError) as exc:
                    raise DataFormatError(f"message {i} on {name}: {exc}", db) from None
                if stopped():
                    break
        streams.finish()
    finally:
        if con is not None:
            con.close()
