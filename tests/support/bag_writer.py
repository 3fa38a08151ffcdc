"""Bags written with rosbags' own writers (independent of sonarmap's), for the ROS reader tests."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def bag_path(tmp_path: Path, version: int, name: str = "b") -> Path:
    """``NAME.bag`` (ROS 1) or the directory ``NAME_bag`` (ROS 2) under ``tmp_path``."""
    return tmp_path / (f"{name}.bag" if version == 1 else f"{name}_bag")


def write_bag_items(path: Path, version: int, items: list[tuple[str, str, Any, int]], store: Any | None = None) -> None:
    """Write ``(topic, msgtype, message, time_ns)`` items with rosbags' Writer (default store:
    :func:`sonarmap.io.rosbag.typestore`)."""
    if store is None:
        from sonarmap.io.rosbag import typestore

        store = typestore(version)
    if version == 1:
        from rosbags.rosbag1 import Writer as W1

        writer: Any = W1(path)
        serialize = store.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer as W2

        writer = W2(path, version=9)
        serialize = store.serialize_cdr
    with writer:
        conns: dict[str, Any] = {}
        for topic, msgtype, msg, t in items:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(conns[topic], t, bytes(serialize(msg, msgtype)))
