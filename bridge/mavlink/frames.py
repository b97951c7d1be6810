"""MAVLink 1 and 2 framing for the real-time control path: find frames in a byte stream, check
their CRC, and check and replay-guard MAVLink 2 signatures.

Pure: bytes in, :class:`Frame` records out; no pymavlink at run time, no I/O, clock or logging.
The real-time loop reads the autopilot's link itself and must not run pymavlink's parser, which
decodes every field of every message into an object, over everything the autopilot sends: it
only needs the few control messages (:mod:`bridge.mavlink.actuators` decodes those payloads).

Wire format (https://mavlink.io/en/guide/serialization.html)
------------------------------------------------------------
::

    MAVLink 1   FE len seq sys comp id                            payload crc_lo crc_hi
    MAVLink 2   FD len incompat compat seq sys comp id0 id1 id2   payload crc_lo crc_hi
                [link_id ts0..ts5 sig0..sig5]   (13 bytes, only when incompat bit 0 is set)

The CRC is CRC-16/MCRF4XX (X.25) over everything after the magic byte up to the payload's end,
followed by the message's CRC_EXTRA byte (a hash of its definition, so two ends that disagree
on a message's fields never accept each other's bytes). MAVLink 2 senders drop trailing zero
bytes of the payload; the receiver zero-extends it to the message's full length. A MAVLink 1
frame has no extension fields, which zero-extension reads as zeros too.

Scanning rules
--------------
- Bytes before a magic byte (0xFE, 0xFD) are junk and counted in ``junk_bytes``.
- A frame of a known message id must pass its CRC. One that fails, and a MAVLink 2 header with
  an incompatibility flag other than "signed" (no frame this codec can read), cost one byte:
  scanning resumes at the next magic byte after the bad frame's own. pymavlink instead skips
  the whole length the bad header claimed, so one corrupted or truncated frame (a serial link
  that dropped bytes) also costs it the good frames that follow within that length; this
  scanner finds those frames, and finds exactly what pymavlink finds when no bad frame hides
  a good one (tests/mavlink/test_frames.py checks both).
- A frame of an unknown message id cannot be checked (no CRC_EXTRA, no length): it is passed
  through unchecked, as pymavlink does, and its claimed length is skipped. A
  magic byte in junk that happens to announce an unknown id therefore hides up to 280 bytes
  after it. ``pass_unknown=False`` treats unknown ids as junk instead (one byte skipped), for a
  reader that only wants the known messages and would rather resynchronise at once.
- The CRC does not cover a signature block: a signed frame damaged there is still a frame
  (:func:`signature_ok` refuses it), and one cut short there takes the next frame's first bytes
  as the rest of its signature, costing that frame.
- At most one partial frame (under 280 bytes) is kept between :meth:`FrameScanner.feed` calls,
  so a stream of junk never grows memory. A frame behind a junk header that claims a long
  frame waits until that length has arrived.
- A datagram (``whole=True``) holds whole frames: nothing is kept from it for the next call.
  A UDP link's datagrams come from anyone who can reach the port, so a frame cut short at the
  end of one must never be completed by the first bytes of the next: a HEARTBEAT that said
  "armed", cut one byte short by one sender, once took its last byte from another's datagram.

The CRC uses the standard library's CRC-16/CCITT (``binascii.crc_hqx``, which is the same
polynomial fed most significant bit first) on bit-reversed bytes: 0.4 µs for a
SERVO_OUTPUT_RAW frame on an x86 server core, against 2.7 µs for a table-driven loop in Python.
"""

from __future__ import annotations

import binascii
import hashlib
import hmac
import re
from collections.abc import Mapping
from dataclasses import dataclass
from types import ModuleType
from typing import Final

from bridge.errors import ConfigError

__all__ = [
    "FRAME_MAX_LEN",
    "MAGIC_V1",
    "MAGIC_V2",
    "SIGNING_EPOCH_UNIX_S",
    "Frame",
    "FrameScanner",
    "ReplayGuard",
    "crc_x25",
    "frame_crc",
    "signature_ok",
    "signing_timestamp",
]

MAGIC_V1: Final = 0xFE
MAGIC_V2: Final = 0xFD
_HEADER_V1: Final = 6  # magic len seq sys comp id
_HEADER_V2: Final = 10  # magic len incompat compat seq sys comp id0 id1 id2
_CRC_LEN: Final = 2
_IFLAG_SIGNED: Final = 0x01
_SIGNATURE_BLOCK: Final = 13  # link id, 6-byte timestamp, 6-byte signature
_SIGNATURE_LEN: Final = 6
FRAME_MAX_LEN: Final = _HEADER_V2 + 255 + _CRC_LEN + _SIGNATURE_BLOCK
"""280: the longest frame, a signed MAVLink 2 frame with a 255-byte payload."""
SIGNING_EPOCH_UNIX_S: Final = 1_420_070_400
"""Signing timestamps count 10 µs units since 2015-01-01T00:00:00Z, this many s after 1970."""
_SIGNING_UNIT_NS: Final = 10_000
# The signing spec: a stream not seen before is refused when its timestamp is more than one
# minute (6 000 000 units of 10 µs) behind our own.
_NEW_STREAM_MAX_AGE: Final = 6_000_000
_KEY_LEN: Final = 32

_MAGIC: Final = re.compile(b"[\xfd\xfe]")
_ZEROS: Final = bytes(255)  # zero-extension source: a payload is never longer than 255

# MCRF4XX is CRC-16/CCITT (polynomial 0x1021, initial 0xFFFF) computed least significant bit
# first. Feeding bit-reversed bytes to the most-significant-bit-first binascii.crc_hqx and
# reversing its 16-bit result gives the same CRC at C speed.
_REVERSED: Final = bytes(int(f"{i:08b}"[::-1], 2) for i in range(256))
_CRC_INIT: Final = 0xFFFF


def crc_x25(data: bytes | bytearray, crc: int = _CRC_INIT) -> int:
    """CRC-16/MCRF4XX (the MAVLink "X.25" CRC) of ``data``, continuing from ``crc``."""
    crc = (_REVERSED[crc & 0xFF] << 8) | _REVERSED[crc >> 8]
    crc = binascii.crc_hqx(data.translate(_REVERSED), crc)
    return (_REVERSED[crc & 0xFF] << 8) | _REVERSED[crc >> 8]


def frame_crc(body: bytes | bytearray, crc_extra: int) -> int:
    """The CRC a frame carries: over ``body`` (the frame from the byte after the magic to the
    end of the payload), then the message's CRC_EXTRA byte."""
    crc = binascii.crc_hqx(body.translate(_REVERSED), _CRC_INIT)
    crc = binascii.crc_hqx(_REVERSED[crc_extra : crc_extra + 1], crc)
    return (_REVERSED[crc & 0xFF] << 8) | _REVERSED[crc >> 8]


@dataclass(frozen=True, slots=True)
class Frame:
    """One MAVLink frame as found on the wire. Not checked when built: the scanner builds them,
    once per frame, and has checked what it puts in."""

    msg_id: int
    sys_id: int
    comp_id: int
    seq: int
    payload: bytes
    """Zero-extended to the message's full length (MAVLink 2 truncation, MAVLink 1 without
    extensions) when the id is known; a longer payload (a newer sender's extra extension
    fields) is kept whole. An unknown id's payload is as sent."""
    version: int
    """1 or 2."""
    signed: bool
    raw: bytes
    """The whole frame as on the wire, signature block included."""
    link_id: int | None = None
    """Signed frames only: the sender's link id."""
    signature_timestamp: int | None = None
    """Signed frames only: 10 µs units since 2015-01-01 (see :func:`signing_timestamp`)."""


class FrameScanner:
    """Finds MAVLink 1 and 2 frames in a byte stream (see the module docstring for the rules).

    Frames of known ids (``crc_extras``) are CRC-checked; frames of unknown ids are passed
    through unchecked (or skipped as junk with ``pass_unknown=False``). Signatures are not
    checked here: see :func:`signature_ok` and :class:`ReplayGuard`.

    Counters, updated in place: ``frames`` (returned), ``unknown`` (of those, unknown ids passed
    through unchecked), ``bad_crc`` (known ids that failed the CRC), ``bad_flags`` (MAVLink 2
    headers with an incompatibility flag other than "signed"), ``junk_bytes`` (bytes skipped
    while resynchronising, the first byte of each bad frame included).
    """

    def __init__(
        self,
        crc_extras: Mapping[int, int],
        lengths: Mapping[int, int],
        *,
        pass_unknown: bool = True,
    ) -> None:
        """``crc_extras`` and ``lengths``: message id -> CRC_EXTRA and full payload length
        (extensions included), for the same ids.

        Raises:
            ConfigError: the two tables name different ids, or a value is out of its range.
        """
        if crc_extras.keys() != lengths.keys():
            differ = sorted(crc_extras.keys() ^ lengths.keys())
            raise ConfigError(
                f"MAVLink ids {differ[:10]} have a CRC_EXTRA or a length but not both; "
                "expected both tables to name the same ids"
            )
        for msg_id in crc_extras:
            if not 0 <= msg_id <= 0xFFFFFF:
                raise ConfigError(f"MAVLink message id {msg_id}: expected 0..16777215")
            if not 0 <= crc_extras[msg_id] <= 0xFF or not 0 <= lengths[msg_id] <= 255:
                raise ConfigError(
                    f"MAVLink message {msg_id}: CRC_EXTRA {crc_extras[msg_id]} and length "
                    f"{lengths[msg_id]}: expected 0..255 each"
                )
        self._crc_extras: dict[int, int] = dict(crc_extras)
        self._lengths: dict[int, int] = dict(lengths)
        self._pass_unknown = pass_unknown
        self._pending = b""
        self.frames = 0
        self.unknown = 0
        self.bad_crc = 0
        self.bad_flags = 0
        self.junk_bytes = 0

    @classmethod
    def for_dialect(cls, dialect: ModuleType, *, pass_unknown: bool = True) -> FrameScanner:
        """A scanner that knows every message of a pymavlink dialect module (e.g. the one
        :func:`bridge.mavlink.load_dialect` returns), read from its ``mavlink_map``."""
        messages = dialect.mavlink_map
        return cls(
            {msg_id: int(m.crc_extra) for msg_id, m in messages.items()},
            {msg_id: int(m.unpacker.size) for msg_id, m in messages.items()},
            pass_unknown=pass_unknown,
        )

    @property
    def pending(self) -> int:
        """Bytes of a partial frame held for the next :meth:`feed` (under 280)."""
        return len(self._pending)

    def reset(self) -> None:
        """Drop the partial frame, if any (the stream was reopened); counters are kept."""
        self._pending = b""

    def feed(self, data: bytes | bytearray, *, whole: bool = False) -> list[Frame]:
        """The frames completed by ``data``, in stream order. A partial frame at the end is
        kept for the next call.

        ``whole``: ``data`` is one datagram, which ends at a frame boundary (pymavlink,
        mavlink-router, ArduPilot and PX4 put whole frames in each). Then nothing is kept: a
        frame still incomplete at the end cannot be one, costs one byte like a bad CRC, and the
        frames behind its first byte are found now. A sender that cuts the byte stream anywhere
        (a serial-to-UDP converter) loses the frames it splits between two datagrams.
        """
        stream = self._pending + data if self._pending else bytes(data)
        end = len(stream)
        crc_extras = self._crc_extras
        found: list[Frame] = []
        pos = 0
        while pos < end:
            magic = stream[pos]
            if magic != MAGIC_V2 and magic != MAGIC_V1:
                match = _MAGIC.search(stream, pos)
                if match is None:
                    self.junk_bytes += end - pos
                    pos = end
                    break
                self.junk_bytes += match.start() - pos
                pos = match.start()
                magic = stream[pos]
            available = end - pos
            if magic == MAGIC_V2:
                if available < 3:
                    size = _HEADER_V2 + _CRC_LEN  # at least; incomplete either way
                else:
                    length = stream[pos + 1]
                    flags = stream[pos + 2]
                    if flags & ~_IFLAG_SIGNED:
                        self.bad_flags += 1
                        self.junk_bytes += 1
                        pos += 1
                        continue
                    header = _HEADER_V2
                    size = _HEADER_V2 + length + _CRC_LEN + (_SIGNATURE_BLOCK if flags else 0)
            else:
                if available < 2:
                    size = _HEADER_V1 + _CRC_LEN
                else:
                    length = stream[pos + 1]
                    flags = 0
                    header = _HEADER_V1
                    size = _HEADER_V1 + length + _CRC_LEN
            if available < size:
                if not whole:
                    break
                self.junk_bytes += 1
                pos += 1
                continue
            if magic == MAGIC_V2:
                msg_id = stream[pos + 7] | stream[pos + 8] << 8 | stream[pos + 9] << 16
            else:
                msg_id = stream[pos + 5]
            payload_end = pos + header + length
            crc_extra = crc_extras.get(msg_id)
            if crc_extra is None:
                if not self._pass_unknown:
                    self.junk_bytes += 1
                    pos += 1
                    continue
                self.unknown += 1
                payload = stream[pos + header : payload_end]
            else:
                crc = stream[payload_end] | stream[payload_end + 1] << 8
                if frame_crc(stream[pos + 1 : payload_end], crc_extra) != crc:
                    self.bad_crc += 1
                    self.junk_bytes += 1
                    pos += 1
                    continue
                payload = stream[pos + header : payload_end]
                missing = self._lengths[msg_id] - length
                if missing > 0:
                    payload += _ZEROS[:missing]
            if magic == MAGIC_V2:
                link_id: int | None = None
                signature_timestamp: int | None = None
                if flags:  # signed: the link id and timestamp open the block after the CRC
                    at = payload_end + _CRC_LEN
                    link_id = stream[at]
                    signature_timestamp = int.from_bytes(stream[at + 1 : at + 7], "little")
                frame = Frame(
                    msg_id,
                    stream[pos + 5],
                    stream[pos + 6],
                    stream[pos + 4],
                    payload,
                    2,
                    bool(flags),
                    stream[pos : pos + size],
                    link_id,
                    signature_timestamp,
                )
            else:
                frame = Frame(
                    msg_id,
                    stream[pos + 3],
                    stream[pos + 4],
                    stream[pos + 2],
                    payload,
                    1,
                    False,
                    stream[pos : pos + size],
                )
            found.append(frame)
            pos += size
        self.frames += len(found)
        self._pending = stream[pos:] if pos < end else b""
        return found


def signing_timestamp(unix_ns: int) -> int:
    """A wall-clock time (``time.time_ns()``) as a MAVLink signing timestamp: 10 µs units
    since 2015-01-01T00:00:00Z."""
    return max(0, (unix_ns - SIGNING_EPOCH_UNIX_S * 1_000_000_000) // _SIGNING_UNIT_NS)


def signature_ok(frame: Frame, key: bytes) -> bool:
    """True when ``frame`` is signed and its signature matches ``key``: the first 6 bytes of
    SHA-256 over the key and the frame up to and including the link id and timestamp, compared
    in constant time. The timestamp is not judged here (see :class:`ReplayGuard`)."""
    if not frame.signed:
        return False
    raw = frame.raw
    digest = hashlib.sha256(key + raw[:-_SIGNATURE_LEN]).digest()
    return hmac.compare_digest(digest[:_SIGNATURE_LEN], raw[-_SIGNATURE_LEN:])


class ReplayGuard:
    """Accepts signed frames with a valid signature that are not replays, as the MAVLink
    signing spec says (https://mavlink.io/en/guide/message_signing.html).

    A stream is one (link id, system id, component id). A frame is accepted when it is signed,
    its signature matches the key, and its timestamp is newer than the last accepted one of
    its stream; the first frame of a stream is accepted when its timestamp is at most one
    minute behind :attr:`timestamp`, our own signing timestamp. The signature is checked
    before anything else, so a forged frame never touches the replay state (a forged far-future
    timestamp cannot lock the genuine stream out). Every accepted timestamp raises
    :attr:`timestamp`; the caller raises it from its own clock with :meth:`advance`.

    Rules of the spec not done here: unsigned and badly signed frames are never accepted (the
    spec lets a system accept some, e.g. RADIO_STATUS: that is the caller's choice, before or
    instead of this guard); persisting the timestamp across restarts and taking it from GPS is
    the caller's. The spec's "older than the previous packet" is read as "not newer": an equal
    timestamp is the same frame again, and the C library and pymavlink refuse it too. At most
    ``max_streams`` streams are remembered (the C library keeps 16); a new stream beyond them
    is refused, counted in ``too_many_streams``. Only correctly signed frames open a stream, so
    only key holders can fill the table.

    Counters: ``accepted``, ``unsigned``, ``bad_signature``, ``replayed`` (not newer than its
    stream's last), ``too_old`` (a new stream more than a minute behind), ``too_many_streams``.
    """

    def __init__(self, key: bytes, timestamp: int = 0, max_streams: int = 64) -> None:
        """``key``: the 32-byte secret. ``timestamp``: our signing timestamp now (see
        :func:`signing_timestamp`).

        Raises:
            ConfigError: the key is not 32 bytes, or max_streams is below 1.
        """
        if len(key) != _KEY_LEN:
            raise ConfigError(f"MAVLink signing key of {len(key)} bytes: expected {_KEY_LEN}")
        if max_streams < 1:
            raise ConfigError(f"max_streams={max_streams}: expected at least 1")
        self._key = bytes(key)
        self._streams: dict[int, int] = {}  # link << 16 | sys << 8 | comp -> last timestamp
        self._max_streams = max_streams
        self.timestamp = timestamp
        """Our signing timestamp: the newest of :meth:`advance` and every accepted frame's."""
        self.accepted = 0
        self.unsigned = 0
        self.bad_signature = 0
        self.replayed = 0
        self.too_old = 0
        self.too_many_streams = 0

    def advance(self, timestamp: int) -> None:
        """Raise :attr:`timestamp` to ``timestamp`` (the caller's clock); never lowers it."""
        if timestamp > self.timestamp:
            self.timestamp = timestamp

    def accept(self, frame: Frame) -> bool:
        """True when ``frame`` is signed with the key and is not a replay; then its stream
        remembers its timestamp."""
        stamp = frame.signature_timestamp
        link = frame.link_id
        if stamp is None or link is None:
            self.unsigned += 1
            return False
        if not signature_ok(frame, self._key):
            self.bad_signature += 1
            return False
        stream = link << 16 | frame.sys_id << 8 | frame.comp_id
        last = self._streams.get(stream)
        if last is None:
            if stamp + _NEW_STREAM_MAX_AGE < self.timestamp:
                self.too_old += 1
                return False
            if len(self._streams) >= self._max_streams:
                self.too_many_streams += 1
                return False
        elif stamp <= last:
            self.replayed += 1
            return False
        self._streams[stream] = stamp
        if stamp > self.timestamp:
            self.timestamp = stamp
        self.accepted += 1
        return True
