"""A loopback Oculus replay server for tests and demos.

:class:`ReplayServer` listens on TCP, accepts one client at a time, waits for its fire message
(or carries on without one after ``fire_timeout_s``) and streams the ``SimplePingResult``
messages of a raw Oculus capture (cycled) at ``rate_hz``, bounded by ``count`` messages and
``duration_s`` seconds.  Each sent message carries a sequential ``pingId`` (0, 1, 2, ...), so
a client can tell exactly which pings it received.  For tests it can inject damage
(``corrupt_every``: every n-th message is preceded by garbage bytes, sent with a broken magic,
or sent with an inconsistent image size, in turn) and be stopped and started again on the same
port.

From the command line::

    python -m sonarmap.live.server capture.raw --rate 40 --port 0 --count 400 --duration 10

prints ``listening on 127.0.0.1:PORT`` and serves until the count or duration is reached.
"""

from __future__ import annotations

import argparse
import math
import os
import socket
import struct
import sys
import threading
import time
from pathlib import Path
from types import TracebackType

from sonarmap.errors import DataFormatError, InputError
from sonarmap.io.oculus import FIRE_V1, HEADER, MSG_SIMPLE_PING_RESULT, OCULUS_ID
from sonarmap.live.protocol import MSG_SIMPLE_FIRE, FireSettings, decode_fire_message

__all__ = ["ReplayServer", "read_capture_messages", "CORRUPTIONS", "main"]

#: Kinds of damage :class:`ReplayServer` injects, in turn.
CORRUPTIONS = ("garbage", "bad_magic", "bad_image_size")
_PING_ID_OFFSET = HEADER.size + FIRE_V1.size  # first field of the v1 ping block
_IMAGE_SIZE_OFFSET = HEADER.size + FIRE_V1.size + struct.calcsize("<IIddddIBdHHI")


def read_capture_messages(path: str | os.PathLike[str]) -> list[bytes]:
    """The ``SimplePingResult`` messages of a raw Oculus capture, in order.

    Raises
    ------
    DataFormatError
        If the file is not a raw capture or holds no ping.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise DataFormatError(f"cannot read: {exc.strerror or exc}", p) from None
    out, o = [], 0
    while o + HEADER.size <= len(data):
        oid, _s, _d, msg_id, _v, payload, _sp = HEADER.unpack_from(data, o)
        if oid != OCULUS_ID:
            raise DataFormatError(f"bad Oculus message id 0x{oid:04X}; not a raw capture", p, o)
        end = o + HEADER.size + payload
        if end > len(data):
            break
        if msg_id == MSG_SIMPLE_PING_RESULT:
            out.append(data[o:end])
        o = end
    if not out:
        raise DataFormatError("no SimplePingResult message (not a raw Oculus capture?)", p)
    return out


class ReplayServer:
    """Serve a raw Oculus capture over TCP like a sonar (runs in a background thread).

    Parameters
    ----------
    path : path-like
        Raw capture (``SimplePingResult`` messages, e.g. liboculus's ``three_pings_8bit.raw``).
    rate_hz : float
        Messages per second.
    host, port : str, int
        Where to listen (port 0: any free port; see :attr:`port`).
    count : int, optional
        Stop after this many messages in total (over all clients).
    duration_s : float, optional
        Stop this long after the first client connected.
    fire_timeout_s : float
        How long to wait for the client's fire message before streaming anyway.
    corrupt_every : int, optional
        Every n-th message is damaged (:data:`CORRUPTIONS`, in turn); the damaged ones are not
        counted in :attr:`sent_valid`.

    Attributes
    ----------
    sent, sent_valid, corrupted : int
        Messages sent; of them undamaged ping messages; damaged ones.
    fire : FireSettings or None
        The last fire message received.

    Examples
    --------
    >>> with ReplayServer("three_pings_8bit.raw", rate_hz=40, count=100) as srv:  # doctest: +SKIP
    ...     print(srv.port)
    """

    def __init__(self, path: str | os.PathLike[str], *, rate_hz: float = 40.0, host: str = "127.0.0.1",
                 port: int = 0, count: int | None = None, duration_s: float | None = None,
                 fire_timeout_s: float = 0.5, corrupt_every: int | None = None) -> None:
        try:
            r = float(rate_hz)
        except (TypeError, ValueError):
            raise InputError(f"rate_hz: expected a number, got {rate_hz!r}") from None
        if not (math.isfinite(r) and 0 < r <= 10_000):
            raise InputError(f"rate_hz: must be in (0, 10000] messages per second, got {rate_hz!r}")
        if count is not None and (isinstance(count, bool) or not isinstance(count, int) or count < 0):
            raise InputError(f"count: must be a non-negative integer, got {count!r}")
        if duration_s is not None and not (isinstance(duration_s, int | float) and duration_s > 0):
            raise InputError(f"duration_s: must be a positive number, got {duration_s!r}")
        if corrupt_every is not None and (isinstance(corrupt_every, bool) or not isinstance(corrupt_every, int)
                                          or corrupt_every < 1):
            raise InputError(f"corrupt_every: must be a positive integer, got {corrupt_every!r}")
        self.messages = read_capture_messages(path)
        self.rate_hz = r
        self.host = host
        self._port = int(port)
        self.count = count
        self.duration_s = duration_s
        self.fire_timeout_s = float(fire_timeout_s)
        self.corrupt_every = corrupt_every
        self.sent = self.sent_valid = self.corrupted = self.clients = 0
        self.fire: FireSettings | None = None
        self.done = threading.Event()
        self._stop = threading.Event()
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._t_first: float | None = None

    # ------------------------------------------------------------------ control
    @property
    def port(self) -> int:
        """The bound port (after :meth:`start`)."""
        return self._port

    @property
    def url(self) -> str:
        """``tcp://host:port`` of the server."""
        return f"tcp://{self.host}:{self._port}"

    def start(self) -> ReplayServer:
        """Listen (again, on the same port after a :meth:`stop`) and serve in a thread."""
        if self._thread is not None and self._thread.is_alive():
            return self
        self._stop.clear()
        self.done.clear()
        ls = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        ls.bind((self.host, self._port))
        ls.listen(1)
        ls.settimeout(0.1)
        self._port = ls.getsockname()[1]
        self._listener = ls
        self._thread = threading.Thread(target=self._serve, name="sonarmap-replay-server", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Close the connection and the listening socket (like a sonar switched off)."""
        self._stop.set()
        for s in (self._client, self._listener):
            if s is not None:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
        if self._thread is not None:
            self._thread.join(5)
        self._thread = None

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the count or duration is reached; True if it was."""
        return self.done.wait(timeout)

    def __enter__(self) -> ReplayServer:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    # ------------------------------------------------------------------ serving
    def _finished(self) -> bool:
        if self.count is not None and self.sent >= self.count:
            return True
        return (self.duration_s is not None and self._t_first is not None
                and time.monotonic() - self._t_first >= self.duration_s)

    def _serve(self) -> None:
        ls = self._listener
        assert ls is not None
        try:
            while not self._stop.is_set() and not self._finished():
                try:
                    conn, _ = ls.accept()
                except TimeoutError:
                    continue
                except OSError:
                    break
                self.clients += 1
                self._client = conn
                try:
                    self._stream(conn)
                except OSError:
                    pass  # the client went away: accept the next one
                finally:
                    self._client = None
                    try:
                        conn.close()
                    except OSError:
                        pass
        finally:
            try:
                ls.close()
            except OSError:
                pass
            self._listener = None
            if self._finished():
                self.done.set()

    def _await_fire(self, conn: socket.socket) -> None:
        conn.settimeout(self.fire_timeout_s)
        buf = b""
        try:
            while len(buf) < HEADER.size + FIRE_V1.size:
                chunk = conn.recv(4096)
                if not chunk:
                    break
                buf += chunk
        except (TimeoutError, OSError):
            pass
        if len(buf) >= HEADER.size and HEADER.unpack_from(buf, 0)[3] == MSG_SIMPLE_FIRE:
            try:
                self.fire = decode_fire_message(buf)
            except InputError:
                pass
        conn.settimeout(None)

    def _message(self, i: int) -> tuple[bytes, bool]:
        """Message ``i`` (with pingId ``i``), damaged when it is its turn; (bytes, valid)."""
        msg = bytearray(self.messages[i % len(self.messages)])
        struct.pack_into("<I", msg, _PING_ID_OFFSET, i & 0xFFFFFFFF)
        if self.corrupt_every is None or (i + 1) % self.corrupt_every:
            return bytes(msg), True
        kind = CORRUPTIONS[self.corrupted % len(CORRUPTIONS)]
        self.corrupted += 1
        if kind == "garbage":  # junk between messages; the message itself arrives intact
            junk = bytes((j * 37 + 11) % 251 for j in range(997)).replace(b"SO", b"S_")
            return junk + bytes(msg), True
        if kind == "bad_magic":
            msg[0:2] = b"XX"
        else:  # "bad_image_size": the framing holds, the message does not decode
            (img,) = struct.unpack_from("<I", msg, _IMAGE_SIZE_OFFSET)
            struct.pack_into("<I", msg, _IMAGE_SIZE_OFFSET, img + 7)
        return bytes(msg), False

    def _stream(self, conn: socket.socket) -> None:
        self._await_fire(conn)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if self._t_first is None:
            self._t_first = time.monotonic()
        t0 = time.monotonic()
        k = 0
        while not self._stop.is_set() and not self._finished():
            due = t0 + k / self.rate_hz
            wait = due - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                return
            data, valid = self._message(self.sent)
            conn.sendall(data)
            self.sent += 1
            self.sent_valid += int(valid)
            k += 1
        if self._finished():
            self.done.set()


def main(argv: list[str] | None = None) -> int:
    """``python -m sonarmap.live.server FILE --rate HZ --port P --count N --duration S``."""
    ap = argparse.ArgumentParser(prog="python -m sonarmap.live.server",
                                 description="Serve a raw Oculus capture over TCP like a sonar.")
    ap.add_argument("file", help="raw Oculus capture (SimplePingResult messages)")
    ap.add_argument("--rate", type=float, default=40.0, help="messages per second (default 40)")
    ap.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    ap.add_argument("--port", type=int, default=52100, help="port (0: any free port; default 52100)")
    ap.add_argument("--count", type=int, default=None, help="stop after this many messages")
    ap.add_argument("--duration", type=float, default=None, help="stop this many seconds after the first client")
    ap.add_argument("--corrupt-every", type=int, default=None, help="damage every n-th message (tests)")
    args = ap.parse_args(argv)
    try:
        srv = ReplayServer(args.file, rate_hz=args.rate, host=args.host, port=args.port, count=args.count,
                           duration_s=args.duration, corrupt_every=args.corrupt_every)
        srv.start()
    except (InputError, DataFormatError, OSError) as exc:
        print(f"sonarmap.live.server: error: {exc}", file=sys.stderr)
        return 1
    print(f"listening on {srv.host}:{srv.port}", flush=True)
    try:
        while not srv.wait(0.2):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        srv.stop()
    print(f"sent {srv.sent} messages ({srv.corrupted} damaged) to {srv.clients} client(s)", file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
