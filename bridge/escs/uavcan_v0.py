"""UAVCAN v0 framing on classic CAN, shared by the two families that use it: CKESC (vendor
types) and standard DroneCAN. The CAN ID's fields, transfer ID counters, tail bytes, the
transfer CRC, splitting a payload into frames and putting frames back together. Pure: no I/O,
clock or logging; no family is imported here (docs/protocols.md §2; the DSDL's
``uavcan.protocol`` and libcanard for the multi-frame rules).

The CAN ID (29 bits). A message (broadcast) frame's is priority (5 bits) · type ID (16) · 0 ·
source node (7); a service frame's is priority · service type (8) · request flag · destination
node (7) · 1 · source node. Node IDs 126 and 127 are reserved (CKESC's document; DroneCAN
leaves them to maintenance tools), so the ID builders take 0..0x7D.

A transfer is one serialized message. Each of its frames ends in a tail byte: start of
transfer (bit 7), end of transfer (bit 6), toggle (bit 5: 0 in the first frame, then
alternating), transfer ID (bits 4..0, the same in every frame). A payload of up to 7 bytes is one
frame (start = end = 1). A longer one is preceded by the transfer CRC, two bytes little-endian,
and cut into 7-byte pieces. The CRC is CRC-16/CCITT-FALSE (polynomial 0x1021, initial 0xFFFF)
over the data type signature (8 bytes, little-endian) and then the payload, so a transfer of one
type never passes for another. (CKESC's types are all single-frame: it uses the ID helpers and
:func:`tail_byte` only; the multi-frame part serves DroneCAN, whose name its errors carry.)

Decisions (libcanard's, which ArduPilot and most DroneCAN ESCs run):

- A receiver keeps one transfer in progress per session: the CAN ID without its priority
  bits (type, source node, and for services the destination). A start frame begins a new one,
  whatever was in progress; a frame that does not continue the one in progress (wrong transfer
  ID, toggle, or no start) ends it as an error, and is dropped. No clock: a transfer cut off
  midway is forgotten when the same sender's next transfer starts.
- A completed multi-frame transfer whose CRC does not match is an error; its payload is lost.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Final

from bridge.errors import CrcError, DlcError, FrameError, TailByteError, ValueRangeError

PRIORITY_HIGHEST: Final = 0
PRIORITY_HIGH: Final = 8
PRIORITY_MEDIUM: Final = 16
PRIORITY_LOW: Final = 24
PRIORITY_LOWEST: Final = 31
"""The five named priority levels (libcanard's ``CANARD_TRANSFER_PRIORITY_*``; CKESC's
document uses the same); any of 0..31 is valid, lower wins arbitration."""
MAX_NODE_ID: Final = 0x7D
"""Highest usable node ID (0x7E and 0x7F are reserved)."""
START_OF_TRANSFER: Final = 0x80
END_OF_TRANSFER: Final = 0x40
TOGGLE: Final = 0x20
TRANSFER_ID_MASK: Final = 0x1F
MAX_TRANSFER_ID: Final = 31
FRAME_PAYLOAD: Final = 7
"""Payload bytes per classic CAN frame (the eighth is the tail byte)."""
SESSION_MASK: Final = (1 << 24) - 1
"""The CAN ID bits that name a transfer's session: all but the 5 priority bits."""


_PRIORITY: Final = range(PRIORITY_LOWEST + 1)
_TYPE_ID: Final = range(0x1_0000)
_SERVICE_TYPE: Final = range(0x100)
_NODE: Final = range(MAX_NODE_ID + 1)

# --------------------------------------------------------------------------------------------
# CAN ID, tail byte, transfer IDs


def _check(what: str, value: object, allowed: range) -> int:
    """``value`` as an int if it is in ``allowed``; else ValueRangeError naming it all."""
    if isinstance(value, int) and value in allowed:
        return int(value)
    raise ValueRangeError(f"{what} = {value!r} is not in {allowed.start}..{allowed.stop - 1}")


@dataclass(frozen=True, slots=True)
class CanId:
    """The fields of a UAVCAN v0 CAN ID (docs/protocols.md §2.1).

    ``type_id`` is the message type ID (16 bits) or the service type ID (8 bits);
    ``destination_node`` and ``is_request`` are ``None`` for message frames.
    """

    priority: int
    is_service: bool
    type_id: int
    source_node: int
    destination_node: int | None
    is_request: bool | None


def message_id(priority: int, type_id: int, source_node: int) -> int:
    """The 29-bit CAN ID of a message (broadcast) frame.

    Raises:
        ValueRangeError: priority outside 0..31, type_id outside 0..65535, or source_node
            outside 0..0x7D.
    """
    return (
        _check("priority", priority, _PRIORITY) << 24
        | _check("type_id", type_id, _TYPE_ID) << 8
        | _check("source_node", source_node, _NODE)
    )


def service_id(
    priority: int, service_type: int, is_request: bool, destination_node: int, source_node: int
) -> int:
    """The 29-bit CAN ID of a service request or response frame.

    Raises:
        ValueRangeError: priority outside 0..31, service_type outside 0..255, or a node ID
            outside 0..0x7D.
    """
    return (
        _check("priority", priority, _PRIORITY) << 24
        | _check("service_type", service_type, _SERVICE_TYPE) << 16
        | (0x8000 if is_request else 0)
        | _check("destination_node", destination_node, _NODE) << 8
        | 0x80
        | _check("source_node", source_node, _NODE)
    )


def parse_id(arbitration_id: int) -> CanId:
    """Split a 29-bit CAN ID into its UAVCAN v0 fields.

    Raises:
        ValueRangeError: arbitration_id is not a 29-bit value.
    """
    can_id = _check("arbitration_id", arbitration_id, range(1 << 29))
    priority = can_id >> 24
    source = can_id & 0x7F
    if can_id & 0x80:
        return CanId(
            priority,
            True,
            (can_id >> 16) & 0xFF,
            source,
            (can_id >> 8) & 0x7F,
            bool(can_id & 0x8000),
        )
    return CanId(priority, False, (can_id >> 8) & 0xFFFF, source, None, None)


def tail_byte(transfer_id: int) -> int:
    """The tail byte of a single-frame transfer: start = end = 1, toggle = 0, the transfer ID.

    Raises:
        ValueRangeError: transfer_id outside 0..31.
    """
    if 0 <= transfer_id <= MAX_TRANSFER_ID:
        return 0xC0 | transfer_id
    raise ValueRangeError(f"transfer_id = {transfer_id!r} is not in 0..{MAX_TRANSFER_ID}")


class TransferIds:
    """Transfer ID counters of one sender: each type ID counts 0..31 and wraps on its own.

    Message and service type IDs share the map: CKESC's (20000.. and ..255) never collide, nor
    do the DroneCAN message types the bridge sends.
    """

    __slots__ = ("_next",)

    def __init__(self) -> None:
        self._next: dict[int, int] = {}

    def next(self, type_id: int) -> int:
        """The transfer ID for the next frame of ``type_id`` (0 for its first frame)."""
        transfer_id = self._next.get(type_id, 0)
        self._next[type_id] = (transfer_id + 1) & MAX_TRANSFER_ID
        return transfer_id


# --------------------------------------------------------------------------------------------
# Transfers: the CRC, split, reassembly


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = (crc << 1 ^ 0x1021 if crc & 0x8000 else crc << 1) & 0xFFFF
        table.append(crc)
    return tuple(table)


_CRC_TABLE: Final = _crc_table()


def crc16(data: bytes | bytearray, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE of ``data``, continuing from ``crc``."""
    table = _CRC_TABLE
    for byte in data:
        crc = (crc << 8 & 0xFF00) ^ table[(crc >> 8) ^ byte]
    return crc


def signature_crc(signature: int) -> int:
    """The transfer CRC's start for a data type: the CRC of its 64-bit signature's bytes,
    little-endian (libcanard's ``crcAddSignature``; ``dronecan``'s ``base_crc``)."""
    return crc16(signature.to_bytes(8, "little"))


def tail(transfer_id: int, start: bool, end: bool, toggle: bool) -> int:
    """A tail byte."""
    return (
        (START_OF_TRANSFER if start else 0)
        | (END_OF_TRANSFER if end else 0)
        | (TOGGLE if toggle else 0)
        | transfer_id
    )


def frames_data(payload: bytes | bytearray, transfer_id: int, crc_start: int) -> list[bytes]:
    """The data bytes of each frame carrying ``payload`` (tail bytes included): one frame up to
    7 bytes, else the transfer CRC (started at ``crc_start``, see :func:`signature_crc`) and
    the payload in 7-byte pieces.

    Raises:
        ValueRangeError: ``transfer_id`` outside 0..31.
    """
    if not 0 <= transfer_id <= MAX_TRANSFER_ID:
        raise ValueRangeError(f"transfer_id = {transfer_id!r} is not in 0..{MAX_TRANSFER_ID}")
    if len(payload) <= FRAME_PAYLOAD:
        return [bytes(payload) + bytes((0xC0 | transfer_id,))]
    crc = crc16(payload, crc_start)
    stream = bytes((crc & 0xFF, crc >> 8)) + bytes(payload)
    pieces = range(0, len(stream), FRAME_PAYLOAD)
    last = len(pieces) - 1
    return [
        stream[offset : offset + FRAME_PAYLOAD]
        + bytes((tail(transfer_id, index == 0, index == last, index % 2 == 1),))
        for index, offset in enumerate(pieces)
    ]


def frame_sizes(payload_bytes: int) -> list[int]:
    """The data length of each frame of a transfer of ``payload_bytes`` (tail bytes included):
    one frame up to 7 bytes, else the CRC's two bytes and the payload in 7-byte pieces."""
    if payload_bytes <= FRAME_PAYLOAD:
        return [payload_bytes + 1]
    stream = payload_bytes + 2
    full, rest = divmod(stream, FRAME_PAYLOAD)
    return [FRAME_PAYLOAD + 1] * full + ([rest + 1] if rest else [])


@dataclass(frozen=True, slots=True)
class Transfer:
    """A complete transfer: the CAN ID of its frames, its transfer ID and its payload (the
    transfer CRC already checked and removed)."""

    arbitration_id: int
    transfer_id: int
    payload: bytes
    frames: int
    """How many frames carried it."""


@dataclass(slots=True)
class _Partial:
    transfer_id: int
    toggle: bool
    data: bytearray


class Reassembler:
    """Frames in, whole transfers out: a small state machine per session (see the module
    docstring). ``crc_starts`` gives, per data type ID, the CRC start of its multi-frame
    transfers (:func:`signature_crc`); ``type_of`` the data type ID a CAN ID carries.

    Counters: ``transfers`` completed, ``errors`` (transfers lost to a bad tail sequence or
    CRC; each also raised once).
    """

    __slots__ = ("_crc_starts", "_partial", "_type_of", "errors", "transfers")

    def __init__(self, crc_starts: Mapping[int, int], type_of: Callable[[int], int]) -> None:
        self._crc_starts = crc_starts
        self._type_of = type_of
        self._partial: dict[int, _Partial] = {}
        self.transfers = 0
        self.errors = 0

    def feed(self, arbitration_id: int, data: bytes | bytearray) -> Transfer | None:
        """Take one frame of a session whose type is in ``crc_starts``; the transfer it
        completes, or None while one is in progress.

        Raises:
            DlcError: a frame without data (no tail byte).
            TailByteError: the frame does not continue the transfer in progress (the
                transfer is dropped), or continues none.
            CrcError: a completed multi-frame transfer with a wrong CRC.
        """
        if not data:
            raise DlcError(f"DroneCAN frame 0x{arbitration_id:08X} has no tail byte")
        tail_byte = data[-1]
        transfer_id = tail_byte & TRANSFER_ID_MASK
        toggle = bool(tail_byte & TOGGLE)
        session = arbitration_id & SESSION_MASK
        if tail_byte & START_OF_TRANSFER:
            self._partial.pop(session, None)
            if toggle:
                self.errors += 1
                raise TailByteError(
                    f"DroneCAN frame 0x{arbitration_id:08X}: tail byte 0x{tail_byte:02X} "
                    "starts a transfer with the toggle bit set"
                )
            if tail_byte & END_OF_TRANSFER:
                self.transfers += 1
                return Transfer(arbitration_id, transfer_id, bytes(data[:-1]), 1)
            if len(data) != FRAME_PAYLOAD + 1:
                self.errors += 1
                raise DlcError(
                    f"DroneCAN frame 0x{arbitration_id:08X}: a first frame of a multi-frame "
                    f"transfer carries 8 bytes, not {len(data)}"
                )
            self._partial[session] = _Partial(transfer_id, True, bytearray(data[:-1]))
            return None
        partial = self._partial.get(session)
        if partial is None or partial.transfer_id != transfer_id or partial.toggle != toggle:
            if partial is not None:
                del self._partial[session]
            self.errors += 1
            expected = (
                "no transfer in progress"
                if partial is None
                else f"transfer ID {partial.transfer_id}, toggle {int(partial.toggle)}"
            )
            raise TailByteError(
                f"DroneCAN frame 0x{arbitration_id:08X}: tail byte 0x{tail_byte:02X} does not "
                f"continue a transfer ({expected})"
            )
        partial.data += data[:-1]
        if not tail_byte & END_OF_TRANSFER:
            if len(data) != FRAME_PAYLOAD + 1:
                del self._partial[session]
                self.errors += 1
                raise DlcError(
                    f"DroneCAN frame 0x{arbitration_id:08X}: a middle frame carries 8 bytes, "
                    f"not {len(data)}"
                )
            partial.toggle = not toggle
            return None
        del self._partial[session]
        stream = partial.data
        if len(stream) < 2:
            self.errors += 1
            raise FrameError(f"DroneCAN transfer 0x{arbitration_id:08X} too short for its CRC")
        payload = bytes(stream[2:])
        sent = stream[0] | stream[1] << 8
        crc_start = self._crc_starts.get(self._type_of(arbitration_id))
        if crc_start is None or crc16(payload, crc_start) != sent:
            self.errors += 1
            raise CrcError(
                f"DroneCAN transfer 0x{arbitration_id:08X} (transfer ID {transfer_id}): CRC "
                f"0x{sent:04X} does not match its {len(payload)} bytes"
            )
        self.transfers += 1
        return Transfer(arbitration_id, transfer_id, payload, -(-len(stream) // FRAME_PAYLOAD))

    def frames_so_far(self, arbitration_id: int) -> int:
        """Frames taken of the transfer in progress in ``arbitration_id``'s session (0: none)."""
        partial = self._partial.get(arbitration_id & SESSION_MASK)
        return 0 if partial is None else len(partial.data) // FRAME_PAYLOAD

    def reset(self) -> None:
        """Forget every transfer in progress (a reopened bus)."""
        self._partial.clear()
