"""Ping sources of a live run: an Oculus sonar over TCP, a growing recording, a replayed recording.

Each source is an iterable of :class:`sonarmap.ping.Ping` that ends when the source is exhausted
or :meth:`~PingSource.stop` is called (from any thread), and exposes counters the live loop
reports: ``malformed`` (damaged packets skipped), ``reconnects`` and a one-line ``warnings``
list (each kind of problem reported once).

* :class:`OculusTcpSource` - connects to an Oculus, sends the fire message, decodes
  ``SimplePingResult`` messages (ping time: the wall clock when the message was received,
  ``meta["time_source"] = "receive"``), resynchronises after damaged data and reconnects with
  bounded exponential backoff after a disconnect.
* :class:`FollowSource` - follows a recording that is being written (ARIS ``.aris``, ViewPoint
  ``.oculus`` v1 log, raw Oculus capture): every complete new frame is read once, and the
  source ends after ``idle_timeout_s`` without growth.
* :class:`ReplaySource` - replays any recording :func:`sonarmap.io.read_pings` reads, at its
  own ping times (scaled by ``speed``) or at a fixed rate.
"""

from __future__ import annotations

import math
import os
import socket
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from sonarmap.errors import DataFormatError, InputError, SonarmapError, SonarmapWarning
from sonarmap.live.protocol import DEFAULT_PORT, FireSettings, MessageFramer, encode_fire_message
from sonarmap.ping import Ping

__all__ = ["PingSource", "SourceError", "OculusTcpSource", "FollowSource", "ReplaySource", "open_source",
           "parse_tcp_url", "FOLLOW_FORMATS"]

#: Formats :class:`FollowSource` can follow.
FOLLOW_FORMATS = ("aris", "oculus")


class SourceError(SonarmapError, OSError):
    """A source that cannot deliver pings any more (cannot connect, file vanished)."""


def _positive(value: float | None, name: str, *, allow_zero: bool = False, allow_none: bool = False) -> float | None:
    if value is None and allow_none:
        return None
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise InputError(f"{name}: must be a {'non-negative' if allow_zero else 'positive'} number, got {value!r}")
    return v


class PingSource:
    """Base of the live sources: a stop flag, counters and once-only warnings."""

    #: Short description for the status line and the store's ``inputs`` attribute.
    name: str = ""

    def __init__(self) -> None:
        self._stop = threading.Event()
        self.malformed = 0
        self.reconnects = 0
        self.warnings: list[str] = []
        self._warned: set[str] = set()

    def stop(self) -> None:
        """Ask the source to end its iteration soon (thread-safe)."""
        self._stop.set()

    @property
    def stopped(self) -> bool:
        """Whether :meth:`stop` was called."""
        return self._stop.is_set()

    def _warn(self, kind: str, message: str) -> None:
        """Record ``message`` the first time a problem of ``kind`` happens."""
        if kind not in self._warned:
            self._warned.add(kind)
            self.warnings.append(message)
            warnings.warn(message, LiveWarning, stacklevel=2)

    def _sleep(self, seconds: float) -> bool:
        """Sleep, waking early when stopped; True if the source was stopped."""
        return self._stop.wait(max(0.0, seconds))

    def __iter__(self) -> Iterator[Ping]:  # pragma: no cover - abstract
        raise NotImplementedError


class LiveWarning(SonarmapWarning):
    """A problem a live source recovered from (damaged packets, reconnects)."""


# ---------------------------------------------------------------------------- TCP
def parse_tcp_url(url: str) -> tuple[str, int]:
    """``tcp://HOST[:PORT]`` or ``oculus://HOST[:PORT]`` -> ``(host, port)`` (default port 52100).

    Raises
    ------
    InputError
        If ``url`` is not of that form or the port is not 1-65535.

    Examples
    --------
    >>> parse_tcp_url("oculus://192.168.2.3")
    ('192.168.2.3', 52100)
    """
    for scheme in ("tcp://", "oculus://"):
        if url.startswith(scheme):
            rest = url[len(scheme):].rstrip("/")
            break
    else:
        raise InputError(f"source: {url!r} is not tcp://HOST[:PORT] or oculus://HOST[:PORT]")
    host, port = rest, DEFAULT_PORT
    if rest.startswith("["):  # [IPv6]:port
        end = rest.find("]")
        host, tail = rest[1:end], rest[end + 1:]
        if tail.startswith(":"):
            port = _port(tail[1:], url)
    elif rest.count(":") == 1:
        host, p = rest.split(":")
        port = _port(p, url)
    if not host:
        raise InputError(f"source: {url!r} has no host")
    return host, port


def _port(text: str, url: str) -> int:
    if not text.isdigit() or not 0 < int(text) < 65536:
        raise InputError(f"source: {url!r} has an invalid port {text!r} (expected 1-65535)")
    return int(text)


class OculusTcpSource(PingSource):
    """Pings from an Oculus sonar (or :class:`sonarmap.live.server.ReplayServer`) over TCP.

    Parameters
    ----------
    host : str
    port : int
        Data port (52100).
    fire : FireSettings or None
        Sent after every (re)connection; None sends nothing.
    connect_timeout_s : float
        Timeout of one connection attempt.
    read_timeout_s : float
        A connection silent this long is considered lost (reconnect).
    backoff_s, max_backoff_s : float
        First wait before reconnecting, doubled after every failed attempt up to
        ``max_backoff_s``; reset by a received message.
    max_retries : int or None
        Give up (:class:`SourceError`) after this many consecutive failed connection attempts
        (None: never).

    Examples
    --------
    >>> src = OculusTcpSource("192.168.2.3")                # doctest: +SKIP
    >>> for ping in src:                                    # doctest: +SKIP
    ...     print(ping.time_ns, ping.shape)
    """

    def __init__(self, host: str, port: int = DEFAULT_PORT, *, fire: FireSettings | None = FireSettings(),
                 connect_timeout_s: float = 2.0, read_timeout_s: float = 5.0, backoff_s: float = 0.1,
                 max_backoff_s: float = 2.0, max_retries: int | None = 20) -> None:
        super().__init__()
        if not isinstance(host, str) or not host:
            raise InputError(f"host: expected a host name or address, got {host!r}")
        if isinstance(port, bool) or not isinstance(port, int) or not 0 < port < 65536:
            raise InputError(f"port: must be an integer 1-65535, got {port!r}")
        self.host, self.port = host, int(port)
        self.fire = fire
        self.connect_timeout_s = float(_positive(connect_timeout_s, "connect_timeout_s"))  # type: ignore[arg-type]
        self.read_timeout_s = float(_positive(read_timeout_s, "read_timeout_s"))  # type: ignore[arg-type]
        self.backoff_s = float(_positive(backoff_s, "backoff_s"))  # type: ignore[arg-type]
        self.max_backoff_s = float(_positive(max_backoff_s, "max_backoff_s"))  # type: ignore[arg-type]
        if max_retries is not None and (isinstance(max_retries, bool) or not isinstance(max_retries, int)
                                        or max_retries < 0):
            raise InputError(f"max_retries: must be a non-negative integer or None, got {max_retries!r}")
        self.max_retries = max_retries
        self.name = f"tcp://{host}:{self.port}"
        self.framer = MessageFramer()
        self.n_messages = 0
        self._sock: socket.socket | None = None

    def stop(self) -> None:
        super().stop()
        sock = self._sock
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    @property
    def malformed(self) -> int:  # type: ignore[override]
        return self.framer.malformed if hasattr(self, "framer") else 0

    @malformed.setter
    def malformed(self, value: int) -> None:
        pass  # counted by the framer

    def _connect(self) -> socket.socket | None:
        """Connect (with retries and backoff); None when stopped."""
        failures = 0
        delay = self.backoff_s
        last = ""
        while not self.stopped:
            try:
                sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
                sock.settimeout(min(0.25, self.read_timeout_s))
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                if self.fire is not None:
                    sock.sendall(encode_fire_message(self.fire))
                return sock
            except OSError as exc:
                failures += 1
                last = exc.strerror or str(exc) or type(exc).__name__
                if self.max_retries is not None and failures > self.max_retries:
                    raise SourceError(f"{self.name}: cannot connect after {failures} attempts ({last})") from None
                tries = "" if self.max_retries is None else f", up to {self.max_retries} more times"
                self._warn("connect", f"{self.name}: cannot connect ({last}); retrying{tries}")
                if self._sleep(delay):
                    return None
                delay = min(self.max_backoff_s, delay * 2)
        return None

    def __iter__(self) -> Iterator[Ping]:
        from sonarmap.io.oculus import MSG_SIMPLE_PING_RESULT, decode_simple_ping

        first = True
        i = 0
        while not self.stopped:
            sock = self._connect()
            if sock is None:
                return
            if not first:
                self.reconnects += 1
            first = False
            self._sock = sock
            self.framer.reset()
            silent_since = time.monotonic()
            try:
                while not self.stopped:
                    try:
                        data = sock.recv(1 << 20)
                    except TimeoutError:
                        if time.monotonic() - silent_since > self.read_timeout_s:
                            self._warn("silent", f"{self.name}: no data for {self.read_timeout_s:g} s; reconnecting")
                            break
                        continue
                    except OSError:
                        break
                    if not data:
                        break
                    silent_since = time.monotonic()
                    before = self.framer.malformed
                    for msg_id, msg in self.framer.feed(data):
                        self.n_messages += 1
                        if msg_id != MSG_SIMPLE_PING_RESULT:
                            continue
                        t = time.time_ns()
                        try:
                            ping = decode_simple_ping(msg, path=self.name, offset=0, time_ns=t,
                                                      source=f"{self.name}#{i}")
                        except (DataFormatError, InputError, ValueError) as exc:
                            self.framer.count_malformed()
                            self._warn("decode", f"{self.name}: skipping a damaged SimplePingResult ({exc})")
                            continue
                        ping.meta["time_source"] = "receive"
                        i += 1
                        yield ping
                        if self.stopped:
                            return
                    if self.framer.malformed > before:
                        self._warn("framing", f"{self.name}: damaged data in the stream; resynchronised on "
                                              "the next message header")
            finally:
                self._sock = None
                try:
                    sock.close()
                except OSError:
                    pass
            if not self.stopped:
                self._warn("disconnect", f"{self.name}: connection lost; reconnecting")


# ---------------------------------------------------------------------------- follow
class FollowSource(PingSource):
    """Follow a recording while it is written: each complete new frame is yielded once.

    The file size is polled every ``poll_s``; when it grew, the frames that are now complete are
    read (a frame being written is read once it is whole).  Supported: ARIS ``.aris``, ViewPoint
    ``.oculus`` v1 logs and raw Oculus captures (:data:`FOLLOW_FORMATS`), and a ROS 2 bag being
    recorded with the sqlite3 storage - its directory or its ``.db3`` file - whose new messages
    are polled from the storage file (:func:`sonarmap.io.rosbag_follow.follow_sqlite_bag`).

    Parameters
    ----------
    path : path-like
    poll_s : float
        Polling interval.
    idle_timeout_s : float
        End after this long without growth (0: never; stop with :meth:`stop`).
    wait_s : float
        How long to wait for the file to appear / hold a header (0: it must exist).
    geometry : optional
        Geometry override for the reader.

    Raises
    ------
    InputError
        On invalid arguments.
    DataFormatError
        If the file is not of a followable format.
    """

    def __init__(self, path: str | os.PathLike[str], *, poll_s: float = 0.01, idle_timeout_s: float = 5.0,
                 wait_s: float = 5.0, geometry: Any = None) -> None:
        super().__init__()
        self.path = Path(os.path.abspath(path))
        self.poll_s = float(_positive(poll_s, "poll_s"))  # type: ignore[arg-type]
        self.idle_timeout_s = float(_positive(idle_timeout_s, "idle_timeout_s", allow_zero=True))  # type: ignore[arg-type]
        self.wait_s = float(_positive(wait_s, "wait_s", allow_zero=True))  # type: ignore[arg-type]
        self.geometry = geometry
        self.name = str(self.path)
        self.format: str | None = None
        self._start_ns: int | None = None

    def _open(self) -> Any:
        """The reader over the file's current content (warnings about a partial last frame off)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if self.format == "aris":
                from sonarmap.io.aris import ArisFile

                return ArisFile(self.path, geometry=self.geometry)
            from sonarmap.io.oculus import OculusFile

            f = OculusFile(self.path, geometry=self.geometry, start_time_ns=self._start_ns)
            return f

    def _detect(self) -> bool:
        """Detect the format once the file has a header; False if not yet."""
        from sonarmap.io import detect_format

        try:
            if self.path.stat().st_size < 64:
                return False
        except FileNotFoundError:
            return False
        fmt = detect_format(self.path)
        if fmt not in FOLLOW_FORMATS:
            raise DataFormatError(f"cannot follow a {fmt} recording while it is written (followable: "
                                  f"{', '.join(FOLLOW_FORMATS)})", self.path)
        self.format = fmt
        if fmt == "oculus":
            self._start_ns = time.time_ns()
        return True

    def _is_bag(self) -> bool:
        return self.path.is_dir() or self.path.suffix == ".db3"

    def __iter__(self) -> Iterator[Ping]:
        if self._is_bag():
            from sonarmap.io.rosbag_follow import follow_sqlite_bag

            self.format = "rosbag2-sqlite3"
            yield from follow_sqlite_bag(self.path, stopped=lambda: self.stopped, sleep=self._sleep,
                                         poll_s=self.poll_s, idle_timeout_s=self.idle_timeout_s, wait_s=self.wait_s,
                                         geometry=self.geometry)
            return
        t0 = time.monotonic()
        while not self._detect():
            if self.stopped:
                return
            if time.monotonic() - t0 > self.wait_s:
                if not self.path.exists():
                    raise DataFormatError("file not found", self.path)
                raise DataFormatError("file holds no header yet", self.path)
            self._sleep(self.poll_s)
        done = 0
        size = -1
        last_growth = time.monotonic()
        while not self.stopped:
            try:
                st = os.stat(self.path)
            except FileNotFoundError:
                raise SourceError(f"{self.path}: the followed file was removed") from None
            if st.st_size != size:
                size = st.st_size
                last_growth = time.monotonic()
                try:
                    f = self._open()
                except DataFormatError as exc:
                    self._warn("read", f"{self.path}: cannot read the new data yet ({exc}); retrying")
                    f = None
                if f is not None:
                    try:
                        n = len(f)  # complete frames / messages only
                        while done < n and not self.stopped:
                            ping = f[done]
                            done += 1
                            yield ping
                    finally:
                        f.close()
                continue  # look again at once: more may have arrived while processing
            if self.idle_timeout_s and time.monotonic() - last_growth > self.idle_timeout_s:
                return
            self._sleep(self.poll_s)


# ---------------------------------------------------------------------------- replay
class ReplaySource(PingSource):
    """Replay a recording in real time: at its own ping times (scaled by ``speed``) or at ``rate_hz``.

    Pings keep their recorded times and sources (a replay's products equal a batch run's).

    Parameters
    ----------
    path : path-like
        Anything :func:`sonarmap.io.read_pings` reads (files, directories, globs).
    rate_hz : float, optional
        Fixed ping rate (overrides the recorded times).
    speed : float
        Time-scale factor on the recorded intervals (2: twice as fast).
    loop : bool
        Start again after the last ping (until stopped); the times of a repeated loop are shifted
        by the recording's span plus one mean ping interval, so they keep increasing.
    geometry : optional
        Geometry override for the reader.
    """

    def __init__(self, path: str | os.PathLike[str] | list[str], *, rate_hz: float | None = None,
                 speed: float = 1.0, loop: bool = False, geometry: Any = None) -> None:
        super().__init__()
        self.rate_hz = _positive(rate_hz, "rate_hz", allow_none=True)
        self.speed = float(_positive(speed, "speed"))  # type: ignore[arg-type]
        self.loop = bool(loop)
        paths = [path] if isinstance(path, str | os.PathLike) else list(path)
        self.paths = [os.path.abspath(p) if os.path.exists(p) else str(p) for p in paths]
        self.geometry = geometry
        self.name = ",".join(self.paths)
        self.n_late = 0

    def __iter__(self) -> Iterator[Ping]:
        from sonarmap.io import read_pings

        start = time.monotonic()
        k = 0  # pings delivered so far
        loops = 0
        shift_ns = 0  # added to the times of a repeated loop, so that times keep increasing
        t_first: int | None = None
        period_ns = 0
        while not self.stopped:
            n = 0
            t_last = 0
            for ping in read_pings(self.paths, geometry=self.geometry):
                if t_first is None:
                    t_first = ping.time_ns
                t_last = ping.time_ns
                n += 1
                t = ping.time_ns - t_first + loops * period_ns
                due = start + (k / self.rate_hz if self.rate_hz is not None else max(0.0, t * 1e-9) / self.speed)
                wait = due - time.monotonic()
                if wait > 0 and self._sleep(wait):
                    return
                if wait < -0.05:
                    self.n_late += 1
                k += 1
                yield ping if not shift_ns else ping.replace(time_ns=ping.time_ns + shift_ns)
                if self.stopped:
                    return
            if n == 0:
                raise DataFormatError("no pings to replay", self.name)
            if not self.loop:
                return
            if loops == 0:  # a loop lasts the recording's span plus one mean ping interval
                span = t_last - (t_first or 0)
                period_ns = span + (span // (n - 1) if n > 1 else 100_000_000)
            loops += 1
            shift_ns = loops * period_ns


def open_source(spec: str, *, follow: bool = False, replay: bool = False, rate_hz: float | None = None,
                speed: float = 1.0, loop: bool = False, idle_timeout_s: float = 5.0, geometry: Any = None,
                **tcp: Any) -> PingSource:
    """The source named by ``spec``: ``tcp://HOST[:PORT]`` / ``oculus://HOST[:PORT]``, or a file.

    A file needs ``follow=True`` (:class:`FollowSource`) or ``replay=True`` (:class:`ReplaySource`).

    Raises
    ------
    InputError
        If ``spec`` and the flags do not name one source.
    """
    if spec.startswith(("tcp://", "oculus://")):
        if follow or replay:
            raise InputError("source: --follow / --replay apply to files, not to tcp:// sources")
        host, port = parse_tcp_url(spec)
        return OculusTcpSource(host, port, **tcp)
    if "://" in spec:
        raise InputError(f"source: unknown scheme in {spec!r} (expected tcp:// or oculus://, or a file)")
    if follow and replay:
        raise InputError("source: give either --follow or --replay, not both")
    if follow:
        return FollowSource(spec, idle_timeout_s=idle_timeout_s, geometry=geometry)
    if replay:
        if not os.path.exists(spec) and not any(c in spec for c in "*?["):
            raise DataFormatError("file not found", spec)
        return ReplaySource(spec, rate_hz=rate_hz, speed=speed, loop=loop, geometry=geometry)
    raise InputError(f"source: {spec!r} is a file; give --follow (a file being written) or --replay")
