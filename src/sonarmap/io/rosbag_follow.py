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

import dataclasses
import os
import sqlite3
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

from sonarmap.errors import DataFormatError, GeometryError
from sonarmap.geometry import SonarGeometry
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
    from sonarmap.io.rosbag import _ping_from_msg, _reading_options, warn_guessed_handedness

    override = _reading_options(geometry, handedness)
    root = Path(path)
    t0 = time.monotonic()
    db = _wait_for_storage(root, t0, wait_s, stopped, sleep, poll_s)
    if db is None:
        return
    follower = _Follower(db, root, t0, wait_s, topic, override)
    warned: set[str] = set()
    # The rows are decoded here, not in a helper generator, so that the warnings of
    # warn_guessed_handedness and of the Oculus byte streams (stacklevel=3) point at our caller.
    try:
        for batch in follower.batches(stopped, sleep, poll_s, idle_timeout_s):
            for row_id, topic_id, data in batch:
                name, i, msg = follower.message(row_id, topic_id, data)
                if msg is None:  # a geometry side channel, recorded
                    continue
                try:
                    if follower.kind == "projected":
                        ping, guessed = _ping_from_msg(msg, root, name, i, override, follower.exact, handedness)
                        if guessed and name not in warned:
                            warned.add(name)
                            warn_guessed_handedness(root, name)
                        yield ping
                    else:
                        yield from follower.other_pings(msg, name, i)
                except (ValueError, GeometryError) as exc:
                    raise DataFormatError(f"message {i} on {name}: {exc}", db) from None
                if stopped():
                    break
        follower.streams.finish()
    finally:
        follower.close()


def _wait_for_storage(
    root: Path, t0: float, wait_s: float, stopped: Callable[[], bool], sleep: Callable[[float], Any],
    poll_s: float,
) -> Path | None:
    """The storage file of the bag ``root`` once it exists (None if ``stopped()`` first); a
    DataFormatError if none appeared ``wait_s`` after ``t0``."""
    db = sqlite_storage(root)
    while db is None:
        if stopped():
            return None
        if time.monotonic() - t0 > wait_s:
            raise DataFormatError("no ROS 2 sqlite3 storage file (*.db3) appeared", root)
        sleep(poll_s)
        db = sqlite_storage(root)
    return db


@dataclasses.dataclass
class _Follower:
    """A bag's storage file being followed: its connection, the sonar topics chosen, the last row
    read and the decoding state (message indices, exact geometries, Oculus byte streams)."""

    db: Path
    root: Path
    t0: float
    wait_s: float
    topic: str | None
    override: SonarGeometry | None
    store: Any = dataclasses.field(init=False)
    con: sqlite3.Connection | None = None
    kind: str = ""
    topics: dict[int, tuple[str, str]] = dataclasses.field(default_factory=dict)
    last_id: int = 0
    index: dict[str, int] = dataclasses.field(default_factory=dict)
    streams: Any = dataclasses.field(init=False)
    exact: dict[bytes, SonarGeometry] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        from sonarmap.io.rosbag import typestore
        from sonarmap.io.rosbag_sources import OculusRawStreams

        self.store = typestore(2)
        self.streams = OculusRawStreams(self.root, self.override)

    def batches(
        self, stopped: Callable[[], bool], sleep: Callable[[float], Any], poll_s: float, idle_timeout_s: float
    ) -> Iterator[list[tuple[Any, Any, Any]]]:
        """The batches of new rows, polled every ``poll_s`` until ``stopped()`` or until
        ``idle_timeout_s`` (0: never) pass without one."""
        last_new = time.monotonic()
        while not stopped():
            batch = self._poll(sleep, poll_s)
            if batch is None:  # waited for the storage or a sonar topic
                continue
            if not batch:
                if idle_timeout_s and time.monotonic() - last_new > idle_timeout_s:
                    return
                sleep(poll_s)
                continue
            last_new = time.monotonic()
            yield batch

    def _poll(self, sleep: Callable[[float], Any], poll_s: float) -> list[tuple[Any, Any, Any]] | None:
        """The next rows ``(id, topic_id, data)`` of the sonar topics (``[]``: none yet), or None
        after a ``sleep(poll_s)`` while the storage is locked or has no tables or sonar topic yet."""
        try:
            if self.con is None:
                self.con = _connect(self.db)
            if not self.topics:
                rows = self.con.execute("SELECT id, name, type FROM topics").fetchall()
                self.kind, self.topics = _pick_topics([(int(i), str(n), str(t)) for i, n, t in rows], self.topic)
                if not self.topics:
                    if time.monotonic() - self.t0 > self.wait_s:
                        seen = ", ".join(f"{n} ({t})" for _i, n, t in rows) or "no topics"
                        raise DataFormatError(f"no sonar topic to follow (the bag has {seen})", self.db)
                    sleep(poll_s)
                    return None
            marks = ",".join("?" * len(self.topics))
            return self.con.execute(
                f"SELECT id, topic_id, data FROM messages WHERE id > ? AND topic_id IN ({marks}) "  # noqa: S608
                "ORDER BY id LIMIT ?", (self.last_id, *self.topics, _BATCH)).fetchall()
        except sqlite3.OperationalError as exc:  # locked by the recorder, or not created yet
            if "no such table" in str(exc) and time.monotonic() - self.t0 > self.wait_s:
                raise DataFormatError(f"not a ROS 2 sqlite3 bag: {exc}", self.db) from None
            if self.con is not None and "no such table" in str(exc):
                self.con.close()
                self.con = None
            sleep(poll_s)
            return None
        except sqlite3.DatabaseError as exc:
            raise DataFormatError(f"cannot read the bag's storage: {exc}", self.db) from None

    def message(self, row_id: Any, topic_id: Any, data: Any) -> tuple[str, int, Any]:
        """``(topic, message index on it, message)`` of a row, deserialised; a geometry side-channel
        message is added to the exact geometries instead and given as None."""
        from sonarmap.io.rosbag import add_exact_geometry

        self.last_id = int(row_id)
        name, msgtype = self.topics[int(topic_id)]
        i = self.index.get(name, 0)
        self.index[name] = i + 1
        try:
            msg = self.store.deserialize_cdr(bytes(data), msgtype)
        except Exception as exc:  # noqa: BLE001
            raise DataFormatError(f"corrupt message {i} on {name}: {type(exc).__name__}: {exc}", self.db) from None
        if msgtype == "std_msgs/msg/String":  # a geometry side channel
            self.index[name] = i
            add_exact_geometry(self.exact, msg.data, self.root)
            return name, i, None
        return name, i, msg

    def other_pings(self, msg: Any, name: str, i: int) -> Iterable[Ping]:
        """The ping of a RawSonarImage or acoustic_msgs/SonarImage message, or (lazily) those an Oculus
        RawData message completes in its topic's byte stream."""
        from sonarmap.io.rosbag_sources import ping_from_legacy_image, ping_from_raw_sonar_image

        if self.kind in ("raw_image", "legacy_image"):
            decode = ping_from_raw_sonar_image if self.kind == "raw_image" else ping_from_legacy_image
            return (decode(msg, self.root, name, i, self.override),)
        return self.streams.pings(name, i, msg)  # Oculus RawData: the topic's incoming byte stream

    def close(self) -> None:
        """Close the connection to the storage file, if open."""
        if self.con is not None:
            self.con.close()
