"""Cutting a byte stream into Oculus network messages (a TCP stream, a raw capture, the chunks of
ROS ``apl_msgs/RawData`` messages), resynchronising on damage.

The Oculus data stream is a sequence of messages, each a 16-byte header (``oculusId`` 0x4F53,
``b"SO"``, ..., ``payloadSize``) and its payload.  :class:`MessageFramer` takes the bytes in any
pieces and returns the complete messages; bytes that cannot start a message are skipped up to the
next ``b"SO"`` whose header is plausible (a ``SimplePingResult`` must also have an image that
fits in its payload, so a ``b"SO"`` inside image data is not taken for a message).
"""

from __future__ import annotations

import struct

from sonarmap.io import MAX_PING_BYTES
from sonarmap.io.oculus import (
    FIRE_V1,
    FIRE_V2_EXTRA,
    HEADER,
    MSG_SIMPLE_PING_RESULT,
    OCULUS_ID,
    PING_V1,
    PING_V2,
    SIZE_V1,
    SIZE_V2,
)

__all__ = ["MessageFramer"]

#: Largest payload accepted for messages other than pings (status, configuration: a few hundred bytes).
_MAX_OTHER_PAYLOAD = 1 << 16
_MAGIC = struct.pack("<H", OCULUS_ID)  # b"SO"


class MessageFramer:
    """Cut a byte stream into Oculus messages, resynchronising on damage.

    Feed received bytes with :meth:`feed`; it returns the complete messages ``(msg_id, bytes)``
    found so far.  Bytes that cannot start a message are skipped up to the next ``b"SO"``;
    :attr:`malformed` counts such events (one per run of bad bytes).

    Parameters
    ----------
    max_payload : int
        Largest plausible ``payloadSize`` (default 64 MiB, as the file reader's limit).
    """

    def __init__(self, max_payload: int = MAX_PING_BYTES) -> None:
        self.max_payload = int(max_payload)
        self.malformed = 0
        self.skipped_bytes = 0
        self.dropped = 0
        self._buf = bytearray()
        self._in_garbage = False

    @property
    def buffered(self) -> int:
        """Bytes received but not yet part of a complete message."""
        return len(self._buf)

    def reset(self) -> None:
        """Drop buffered bytes (after a reconnect: a partial message never completes)."""
        self._buf.clear()
        self._in_garbage = False

    def _starts_message(self, data: bytes | bytearray | memoryview) -> bool:
        """Whether ``data`` starts with a plausible message header (undecided counts as yes)."""
        if len(data) < HEADER.size:
            return False
        probe = MessageFramer(self.max_payload)
        probe._buf += data
        return probe._plausible(0) is not False

    def _plausible(self, at: int) -> bool | None:
        """Whether a message can start at ``at`` (None: cannot tell yet, wait for more bytes).

        The header must have a small ``msgId`` / ``msgVersion`` and a ``payloadSize`` within
        bounds; a ``SimplePingResult`` must also have an image that fits in its payload (checked
        as soon as its ping fields have arrived), so a ``b"SO"`` inside image data is not taken
        for a message.
        """
        buf = self._buf
        _oid, _s, _d, msg_id, version, payload, _sp = HEADER.unpack_from(buf, at)
        if msg_id >= 0x100 or version >= 16 or payload > self.max_payload:
            return False
        if msg_id != MSG_SIMPLE_PING_RESULT:
            return payload <= _MAX_OTHER_PAYLOAD
        v2 = version == 2
        need = SIZE_V2 if v2 else SIZE_V1
        if payload + HEADER.size < need:
            return False
        if len(buf) - at < need:
            return None
        if v2:
            f = PING_V2.unpack_from(buf, at + HEADER.size + FIRE_V1.size + FIRE_V2_EXTRA.size)
            dsize, n_ranges, n_beams, img_off, img_size = f[10], f[12], f[13], f[18], f[19]
        else:
            f = PING_V1.unpack_from(buf, at + HEADER.size + FIRE_V1.size)
            dsize, n_ranges, n_beams, img_off, img_size = f[7], f[9], f[10], f[11], f[12]
        return (dsize <= 3 and 0 < n_ranges and 0 < n_beams and img_size >= n_ranges * n_beams
                and need + 2 * n_beams <= img_off and img_off + img_size <= HEADER.size + payload)

    def feed(self, data: bytes | bytearray | memoryview, *, boundary: bool = False) -> list[tuple[int, bytes]]:
        """Add received bytes; return the messages completed by them, in order.

        With ``boundary`` the bytes are one received unit that starts a message when it starts
        with a plausible header (a ROS RawData holds what one network read gave): a partial
        message buffered before it then never completes - its missing bytes were lost - and is
        dropped (counted in :attr:`dropped`) instead of being completed with the new message's
        bytes; buffered bytes that are not a message count in :attr:`malformed`.
        """
        buf = self._buf
        if boundary and buf and bytes(data[:2]) == _MAGIC and self._starts_message(data):
            if buf[:2] == _MAGIC:
                self.dropped += 1  # a message whose rest never arrived
            elif not self._in_garbage:
                self.malformed += 1
            self.skipped_bytes += len(buf)
            buf.clear()
            self._in_garbage = False
        buf += data
        out: list[tuple[int, bytes]] = []
        pos = 0
        n = len(buf)
        while n - pos >= HEADER.size:
            ok = buf[pos : pos + 2] == _MAGIC and self._plausible(pos)
            if ok is None:
                break
            if not ok:
                if not self._in_garbage:
                    self.malformed += 1
                    self._in_garbage = True
                nxt = buf.find(_MAGIC, pos + 1)
                new = nxt if nxt >= 0 else max(pos + 1, n - 1)  # keep a trailing b"S"
                self.skipped_bytes += new - pos
                pos = new
                continue
            payload = HEADER.unpack_from(buf, pos)[5]
            end = pos + HEADER.size + payload
            if end > n:
                break
            self._in_garbage = False
            msg_id = HEADER.unpack_from(buf, pos)[3]
            out.append((msg_id, bytes(buf[pos:end])))
            pos = end
        if pos:
            del buf[:pos]
        return out

    def count_malformed(self) -> None:
        """Count one malformed message found after framing (e.g. a ping that does not decode)."""
        self.malformed += 1
