"""Decoding the bag message types read besides ``ProjectedSonarImage`` (see :mod:`sonarmap.io.rosbag`).

``marine_acoustic_msgs/RawSonarImage``
    Rows are the message's samples (``samples_per_beam`` range bins, row 0 the first sample),
    columns its beams.  Sample ``i`` lies at range ``(i + sample0) * sound_speed / (2 *
    sample_rate)`` (the marine_acoustic_msgs README); ``ping_info.sound_speed`` 0 ("unavailable")
    is taken as 1500 m/s (``Ping.meta["sound_speed_assumed"]``).  ``rx_angles`` are the beams'
    azimuths: the receive steering angle, positive toward the frame's +Y, which the sibling
    ``SonarDetections`` message documents as "+ to starboard", i.e. sonarmap's azimuth.
    ``tx_angles`` and ``tx_delays`` are kept in ``Ping.meta``.  The image data are decoded like
    ``ProjectedSonarImage``'s (``SonarImageData``, range-major).
``acoustic_msgs/SonarImage`` (legacy)
    ``azimuth_angles`` (positive to starboard) and ``ranges`` give the geometry directly;
    ``data_size`` 1, 2 or 4 are unsigned 8/16/32-bit samples in ``is_bigendian`` byte order, indexed
    ``intensities[(range * n_beams + beam) * data_size]`` - the order its reference consumer
    (``sonar_image_proc``) and producer (the UW-APL Oculus driver) used, although the last revision
    of the .msg comment calls it "azimuth-major".  ``azimuth_beamwidth``, ``elevation_beamwidth``
    and non-empty ``elevation_angles`` go to ``Ping.meta``.
``apl_msgs/RawData`` (Oculus network capture)
    The UW-APL Oculus driver publishes what it receives from the sonar as RawData (``direction``
    ``DATA_IN``), each header stamped just after reception - usually one whole Oculus network
    message per RawData.  sonarmap reads a topic's incoming RawData as the byte stream they are
    pieces of (:class:`sonarmap.io.oculus_stream.MessageFramer`): a message split over several
    RawData is reassembled, several messages in one RawData are all read, and every
    ``SimplePingResult`` is a ping, decoded by :func:`sonarmap.io.oculus.decode_simple_ping`, at
    the stamp of the RawData that completed it (its last byte's reception).  A RawData that
    starts with a plausible message header while a message is still incomplete means the rest of
    that message was lost: the incomplete one is dropped.  Outgoing data (``DATA_OUT``), other
    Oculus messages and bytes that are not a message are skipped; dropped, undecodable or
    skipped data give one :class:`~sonarmap.errors.SonarmapWarning` per topic.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from sonarmap.errors import DataFormatError, GeometryError, SonarmapWarning
from sonarmap.geometry import SonarGeometry, plausible_elevation_beamwidth
from sonarmap.io.oculus import MSG_SIMPLE_PING_RESULT, decode_simple_ping
from sonarmap.ping import Ping

__all__ = ["ping_from_raw_sonar_image", "ping_from_legacy_image", "incoming_bytes", "OculusRawStreams", "iter_kind", "count_oculus"]

_LEGACY_DTYPES = {1: np.dtype("u1"), 2: np.dtype("u2"), 4: np.dtype("u4")}


def _name(msg: Any, topic: str) -> str:
    return (msg.header.frame_id or topic).strip("/").replace("/", "-") or "sonar"


def _meta(kind: str, topic: str, idx: int, msg: Any) -> dict[str, Any]:
    from sonarmap.io.rosbag import FORMAT

    meta: dict[str, Any] = {"format": FORMAT, "msgtype": kind, "topic": topic, "message_index": idx}
    if hasattr(msg.header, "seq"):
        meta["seq"] = int(msg.header.seq)
    return meta


@functools.lru_cache(maxsize=64)
def _sample_geometry(
    az: bytes, n_samples: int, sample0: int, sound_speed: float, sample_rate: float, frequency: float, name: str,
    elevation_beamwidth_rad: float | None = None, azimuth_beamwidth_rad: float | None = None,
) -> tuple[SonarGeometry, np.ndarray | None]:
    """Geometry of a RawSonarImage (beams sorted by azimuth; the column order if re-sorted)."""
    from sonarmap.io.rosbag import sorted_beam_geometry

    r = (np.arange(n_samples, dtype=np.float64) + sample0) * (sound_speed / (2.0 * sample_rate))
    return sorted_beam_geometry(np.frombuffer(az, dtype=np.float64), r, frequency, sound_speed, name,
                                elevation_beamwidth_rad=elevation_beamwidth_rad,
                                azimuth_beamwidth_rad=azimuth_beamwidth_rad)


def ping_from_raw_sonar_image(
    msg: Any, path: Path, topic: str, idx: int, override: SonarGeometry | None
) -> Ping:
    """One ``marine_acoustic_msgs/RawSonarImage`` -> Ping (see the module notes).

    Raises
    ------
    ValueError, GeometryError
        Inconsistent sizes, a non-positive sample rate, an implausible sound speed or angles.
    """
    from sonarmap.io.rosbag import _decode_image, _stamp_ns, azimuth_from_ping_info, elevation_from_ping_info

    rx = np.asarray(msg.rx_angles, dtype=np.float64).reshape(-1)
    n_samples = int(msg.samples_per_beam)
    if rx.size < 1 or n_samples < 1:
        raise ValueError(f"empty image ({n_samples} samples per beam, {rx.size} rx_angles)")
    if not np.all(np.isfinite(rx)):
        raise ValueError("rx_angles contain NaN/inf")
    fs = float(msg.sample_rate)
    if not (math.isfinite(fs) and fs > 0):
        raise ValueError(f"sample_rate {fs} Hz is not a positive number")
    c = float(msg.ping_info.sound_speed)
    assumed = c == 0.0
    if assumed:
        c = 1500.0
    elif not (math.isfinite(c) and 1300.0 <= c <= 1700.0):
        raise ValueError(f"ping_info.sound_speed {c} m/s is outside 1300-1700 m/s (0 = unavailable)")
    geom, order = _sample_geometry(
        np.ascontiguousarray(rx).tobytes(), n_samples, int(msg.sample0), c, fs,
        float(msg.ping_info.frequency), _name(msg, topic), elevation_from_ping_info(msg.ping_info),
        azimuth_from_ping_info(msg.ping_info),
    )
    image = _decode_image(msg.image, n_samples, rx.size)
    if order is not None:
        image = np.ascontiguousarray(image[:, order])
    meta = _meta("RawSonarImage", topic, idx, msg)
    meta.update(sample_rate_hz=fs, sample0=int(msg.sample0))
    if assumed:
        meta["sound_speed_assumed"] = True
    for field in ("tx_angles", "tx_delays"):
        v = np.asarray(getattr(msg, field, ()), dtype=np.float64).reshape(-1)
        if v.size:
            meta[field] = v if order is None or v.size != rx.size else v[order]
    return Ping(image=image, geometry=override or geom, time_ns=_stamp_ns(msg.header.stamp),
                source=f"{path}#{topic}:{idx}", meta=meta)


def ping_from_legacy_image(msg: Any, path: Path, topic: str, idx: int, override: SonarGeometry | None) -> Ping:
    """One legacy ``acoustic_msgs/SonarImage`` -> Ping (see the module notes).

    Raises
    ------
    ValueError, GeometryError
        Inconsistent sizes, unknown ``data_size``, non-finite angles or ranges.
    """
    from sonarmap.io.rosbag import _message_geometry, _scale_pixels, _stamp_ns, two_way_beamwidth

    az = np.asarray(msg.azimuth_angles, dtype=np.float64).reshape(-1)
    ranges = np.asarray(msg.ranges, dtype=np.float32).reshape(-1)
    if az.size < 1 or ranges.size < 1:
        raise ValueError(f"empty geometry ({az.size} azimuth_angles, {ranges.size} ranges)")
    if not (np.all(np.isfinite(az)) and np.all(np.isfinite(ranges))):
        raise ValueError("azimuth_angles or ranges contain NaN/inf")
    ds = int(msg.data_size)
    dt = _LEGACY_DTYPES.get(ds)
    if dt is None:
        raise ValueError(f"data_size {ds} is not 1, 2 or 4 bytes per sample")
    raw = np.asarray(msg.intensities, dtype=np.uint8).reshape(-1)
    if raw.size != ranges.size * az.size * ds:
        raise ValueError(
            f"intensities have {raw.size} bytes, expected {ranges.size} ranges x {az.size} beams x {ds} bytes"
        )
    geom, order = _message_geometry(
        np.ascontiguousarray(az).tobytes(), ranges.tobytes(), float(msg.frequency), float(msg.sound_speed),
        _name(msg, topic), plausible_elevation_beamwidth(getattr(msg, "elevation_beamwidth", None)),
        two_way_beamwidth(getattr(msg, "azimuth_beamwidth", None)),
    )
    dt = dt.newbyteorder(">" if msg.is_bigendian else "<")
    image = _scale_pixels(raw.view(dt).reshape(ranges.size, az.size))
    if order is not None:
        image = np.ascontiguousarray(image[:, order])
    meta = _meta("SonarImage", topic, idx, msg)
    for field in ("azimuth_beamwidth", "elevation_beamwidth"):
        v = float(getattr(msg, field, 0.0))
        if math.isfinite(v) and v > 0:
            meta[f"{field}_rad"] = v
    el = np.asarray(getattr(msg, "elevation_angles", ()), dtype=np.float64).reshape(-1)
    if el.size:
        meta["elevation_angles_rad"] = el if order is None or el.size != az.size else el[order]
    return Ping(image=image, geometry=override or geom, time_ns=_stamp_ns(msg.header.stamp),
                source=f"{path}#{topic}:{idx}", meta=meta)


def incoming_bytes(msg: Any) -> bytes | None:
    """The bytes of an incoming RawData (None for outgoing data).

    ``direction`` is compared with the message's own ``DATA_IN`` constant (the bag's definition);
    a definition without ``direction`` counts as incoming.
    """
    if hasattr(msg, "direction"):
        data_in = getattr(msg, "DATA_IN", 1)
        if int(msg.direction) != int(data_in):
            return None
    return np.asarray(msg.data, dtype=np.uint8).reshape(-1).tobytes()


def _topic_messages(reader: Any, path: Path, conns: list[Any]) -> Iterator[tuple[Any, int, Any]]:
    """``(connection, index of the message on its topic, deserialized message)`` in time order;
    a message that does not deserialize is a DataFormatError naming its topic and index."""
    from sonarmap.io.rosbag import _guarded

    idx: dict[str, int] = {}
    for conn, _t, raw in _guarded(path, reader.messages(connections=conns)):
        i = idx.get(conn.topic, 0)
        idx[conn.topic] = i + 1
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # noqa: BLE001
            raise DataFormatError(f"corrupt message {i} on {conn.topic}: {type(exc).__name__}: {exc}", path) from None
        yield conn, i, msg


class OculusRawStreams:
    """The Oculus byte streams of RawData topics (module notes): per topic a
    :class:`~sonarmap.io.oculus_stream.MessageFramer`, the pings decoded from it, and one warning
    per topic for undecodable pings (at once) and for lost or skipped data (:meth:`finish`).
    Used by the bag reader and by :mod:`sonarmap.io.rosbag_follow` alike.

    Parameters
    ----------
    path : Path
        The bag (for sources and messages).
    override : SonarGeometry, optional
        Geometry override for the decoded pings.
    """

    def __init__(self, path: Path, override: SonarGeometry | None = None) -> None:
        self.path = path
        self.override = override
        self._framers: dict[str, Any] = {}
        self._bad: set[str] = set()

    def messages(self, topic: str, msg: Any) -> list[bytes]:
        """The SimplePingResult messages that RawData ``msg`` of ``topic`` completes."""
        from sonarmap.io.oculus_stream import MessageFramer

        data = incoming_bytes(msg)
        if not data:
            return []
        framer = self._framers.setdefault(topic, MessageFramer())
        return [whole for msg_id, whole in framer.feed(data, boundary=True) if msg_id == MSG_SIMPLE_PING_RESULT]

    def pings(self, topic: str, index: int, msg: Any) -> Iterator[Ping]:
        """The pings RawData ``msg`` (message ``index`` of ``topic``) completes, at its stamp."""
        from sonarmap.io.rosbag import FORMAT, _stamp_ns

        wholes = self.messages(topic, msg)
        if not wholes:
            return
        try:
            t_ns = _stamp_ns(msg.header.stamp)
        except ValueError as exc:
            raise DataFormatError(f"message {index} on {topic}: {exc}", self.path) from None
        where = f"{self.path}#{topic}:{index}"
        for data in wholes:
            try:
                ping = decode_simple_ping(data, path=where, time_ns=t_ns, geometry=self.override, source=where)
            except DataFormatError as exc:
                if topic not in self._bad:
                    self._bad.add(topic)
                    warnings.warn(f"{self.path}: {topic}: an Oculus SimplePingResult ending in RawData message "
                                  f"{index} does not decode ({exc}); such pings are skipped", SonarmapWarning,
                                  stacklevel=3)
                continue
            ping.meta.update(format=FORMAT, payload_format="oculus", msgtype="RawData", topic=topic,
                             message_index=index, time_source="header_stamp")
            if hasattr(msg.header, "seq"):
                ping.meta["seq"] = int(msg.header.seq)
            yield ping

    def finish(self) -> None:
        """Warn once per topic about data dropped or skipped while framing."""
        for topic, framer in self._framers.items():
            lost = []
            if framer.dropped:
                lost.append(f"{framer.dropped} incomplete message(s) dropped (their rest was never recorded)")
            if framer.malformed:
                lost.append(f"{framer.malformed} run(s) of bytes that are not an Oculus message skipped")
            if framer.buffered:
                lost.append(f"{framer.buffered} bytes of an unfinished last message")
            if lost:
                warnings.warn(f"{self.path}: {topic}: " + "; ".join(lost), SonarmapWarning, stacklevel=3)


def _iter_oculus(reader: Any, path: Path, conns: list[Any], override: SonarGeometry | None) -> Iterator[Ping]:
    streams = OculusRawStreams(path, override)
    for conn, i, msg in _topic_messages(reader, path, conns):
        yield from streams.pings(conn.topic, i, msg)
    streams.finish()


def count_oculus(reader: Any, path: Path, conns: list[Any]) -> dict[str, int]:
    """SimplePingResult messages per topic of RawData connections (scans and frames the messages)."""
    out = {c.topic: 0 for c in conns}
    streams = OculusRawStreams(path)
    for conn, _i, msg in _topic_messages(reader, path, conns):
        out[conn.topic] += len(streams.messages(conn.topic, msg))
    return out


def iter_kind(
    kind: str, reader: Any, path: Path, conns: list[Any], override: SonarGeometry | None
) -> Iterator[Ping]:
    """Pings of connections of one kind (``raw_image``, ``legacy_image`` or ``oculus_raw``), in time order.

    Raises
    ------
    DataFormatError
        A corrupt or inconsistent message (naming the topic and its message index).
    """
    if kind == "oculus_raw":
        yield from _iter_oculus(reader, path, conns, override)
        return
    decode = ping_from_raw_sonar_image if kind == "raw_image" else ping_from_legacy_image
    for conn, i, msg in _topic_messages(reader, path, conns):
        try:
            yield decode(msg, path, conn.topic, i, override)
        except (ValueError, GeometryError) as exc:
            raise DataFormatError(f"message {i} on {conn.topic}: {exc}", path) from None
