"""The Oculus network protocol as far as a live client needs it: the fire message and message framing.

Every message on the sonar's TCP stream (port 52100) starts with the 16-byte
``OculusMessageHeader`` (little endian): ``oculusId`` (0x4F53, the bytes ``b"SO"``),
``srcDeviceId``, ``dstDeviceId``, ``msgId``, ``msgVersion``, ``payloadSize`` (bytes after the
header) and a spare ``uint16``.  A client starts the sonar by sending an
``OculusSimpleFireMessage`` (``msgId`` 0x15): the header followed by ``masterMode``,
``pingRate``, ``networkSpeed``, ``gammaCorrection``, ``flags`` (``uint8`` each) and ``range``,
``gainPercent``, ``speedOfSound``, ``salinity`` (``double`` each) - the same fields
:mod:`sonarmap.io.oculus` reads back from the copy the sonar embeds in every ping
(:data:`sonarmap.io.oculus.FIRE_V1`).  The sonar answers with ``SimplePingResult`` messages
(``msgId`` 0x23, decoded by :func:`sonarmap.io.oculus.decode_simple_ping`) among status
messages, which a client skips.

:class:`MessageFramer` (:mod:`sonarmap.io.oculus_stream`, re-exported here) cuts a byte stream
into messages and resynchronises after damage: a header without the magic, with an absurd ``payloadSize`` or an implausible ``msgId`` /
``msgVersion``, or a ``SimplePingResult`` whose image does not fit in its payload, is skipped up
to the next ``b"SO"``; each such run of bad bytes counts as one malformed event.
"""

from __future__ import annotations

import dataclasses

from sonarmap.errors import InputError
from sonarmap.io.oculus import FIRE_V1, HEADER, MSG_SIMPLE_PING_RESULT, OCULUS_ID
from sonarmap.io.oculus_stream import MessageFramer

__all__ = [
    "DEFAULT_PORT",
    "MSG_SIMPLE_FIRE",
    "MSG_SIMPLE_PING_RESULT",
    "FireSettings",
    "encode_fire_message",
    "decode_fire_message",
    "MessageFramer",
]

#: TCP port of the Oculus data stream.
DEFAULT_PORT = 52100
#: ``msgId`` of ``OculusSimpleFireMessage``.
MSG_SIMPLE_FIRE = 0x15

#: ``flags`` bits of the fire message.
FLAG_RANGE_METERS = 0x01
FLAG_SIMPLE = 0x08
#: The sonar adjusts its gain so that bright targets do not saturate (the shared capture has it set).
FLAG_GAIN_ASSIST = 0x10


@dataclasses.dataclass(frozen=True)
class FireSettings:
    """Settings sent to the sonar in the fire message (defaults: 2 m window, high frequency, gain
    assist on - the flags 0x19 of the shared capture).

    Parameters
    ----------
    master_mode : int
        1 low frequency, 2 high frequency.
    ping_rate : int
        0 normal (10 Hz), 1 high (15 Hz), 2 highest (40 Hz), 3 low (5 Hz), 4 lowest (2 Hz),
        5 standby.
    network_speed : int
        Link speed limit (255: none).
    gamma : int
        Gamma correction (0-255).
    flags : int
        Bit 0 range in metres, bit 1 16-bit data, bit 2 row gains, bit 3 simple ping, bit 4 gain
        assist.
    range_m : float
        Range window (metres when ``flags`` bit 0 is set, else percent).
    gain_percent : float
        Receiver gain (0-100).
    sound_speed_m_s : float
        Speed of sound (0: the sonar's own estimate).
    salinity_ppt : float
        Salinity (parts per thousand) for the sonar's sound-speed estimate.
    """

    master_mode: int = 2
    ping_rate: int = 2
    network_speed: int = 255
    gamma: int = 127
    flags: int = FLAG_RANGE_METERS | FLAG_SIMPLE | FLAG_GAIN_ASSIST
    range_m: float = 2.0
    gain_percent: float = 50.0
    sound_speed_m_s: float = 0.0
    salinity_ppt: float = 0.0

    def __post_init__(self) -> None:
        for name in ("master_mode", "ping_rate", "network_speed", "gamma", "flags"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 255:
                raise InputError(f"{name}: must be an integer 0-255, got {v!r}")
        if not 0 < float(self.range_m) <= 1000:
            raise InputError(f"range_m: must be in (0, 1000], got {self.range_m!r}")
        if not 0 <= float(self.gain_percent) <= 100:
            raise InputError(f"gain_percent: must be in [0, 100], got {self.gain_percent!r}")


def encode_fire_message(settings: FireSettings = FireSettings(), *, src_device: int = 0,
                        dst_device: int = 0, version: int = 1) -> bytes:
    """The ``OculusSimpleFireMessage`` (v1: 16-byte header + 37-byte payload) for ``settings``.

    Examples
    --------
    >>> msg = encode_fire_message()
    >>> len(msg), msg[:2]
    (53, b'SO')
    """
    s = settings
    body = FIRE_V1.pack(s.master_mode, s.ping_rate, s.network_speed, s.gamma, s.flags, float(s.range_m),
                        float(s.gain_percent), float(s.sound_speed_m_s), float(s.salinity_ppt))
    head = HEADER.pack(OCULUS_ID, src_device, dst_device, MSG_SIMPLE_FIRE, version, len(body), 0)
    return head + body


def decode_fire_message(msg: bytes) -> FireSettings:
    """The settings of a fire message (inverse of :func:`encode_fire_message`).

    Raises
    ------
    InputError
        If ``msg`` is not a fire message.
    """
    if len(msg) < HEADER.size + FIRE_V1.size:
        raise InputError(f"fire message: {len(msg)} bytes, need {HEADER.size + FIRE_V1.size}")
    oid, _s, _d, msg_id, _v, _p, _sp = HEADER.unpack_from(msg, 0)
    if oid != OCULUS_ID or msg_id != MSG_SIMPLE_FIRE:
        raise InputError(f"fire message: id 0x{oid:04X} / message 0x{msg_id:02X} is not a simple fire message")
    f = FIRE_V1.unpack_from(msg, HEADER.size)
    return FireSettings(*f[:5], *f[5:])
