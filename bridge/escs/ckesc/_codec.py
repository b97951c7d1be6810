"""CKESC decoding and encoding of whole frames, and the throttle hot path."""

from __future__ import annotations

from collections.abc import Container, Sequence
from typing import Final

import can

from bridge.errors import (
    DlcError,
    NotExtendedIdError,
    TailByteError,
    UnknownTypeError,
    ValueRangeError,
)
from bridge.escs.ckesc import _services  # noqa: F401 - registers the service types
from bridge.escs.ckesc._frame import (
    _CODECS_BY_RECORD,
    _MESSAGE_CODECS,
    _SERVICE_CODECS,
    CkescFrame,
    _Codec,
)
from bridge.escs.ckesc._messages import (
    _bits_10b,
    _bits_12b,
    _bits_14b,
    _count_error,
)
from bridge.escs.ckesc._records import (
    CkescMessage,
)
from bridge.escs.ckesc._wire import (
    _NODE,
    _PRIORITY,
    _TRANSFER_ID,
    CHANNELS_PER_GROUP,
    HOST_NODE_ID,
    MAX_CHANNELS,
    MAX_GROUP,
    MESSAGE_TYPE_RANGE,
    SERVICE_SET_ID,
    SERVICE_TYPE_RANGE,
    TYPE_RAW_COMMAND_10B,
    TYPE_RAW_COMMAND_12B,
    TYPE_RAW_COMMAND_14B,
    _field,
)
from bridge.escs.uavcan_v0 import MAX_NODE_ID, PRIORITY_HIGHEST, message_id, tail_byte


def _codec_of(message: CkescMessage) -> _Codec:
    codec = _CODECS_BY_RECORD.get(type(message))
    if codec is None:
        raise TypeError(f"not a CKESC record: {message!r}")
    return codec


# --------------------------------------------------------------------------------------------
# Decoding and encoding


def decode(msg: can.Message, esc_nodes: Container[int] | None = None) -> CkescFrame | None:
    """Decode one CAN frame into a :class:`CkescFrame`, or ``None`` if it is not CKESC's.

    Not ours: a message type outside 20000..20999 or a service type outside 200..255. Another
    vendor's DroneCAN messages reuse CKESC's type IDs (20050, 20101), so pass ``esc_nodes``
    (our ESCs' node IDs) on a shared bus: then a frame an ESC sends (telemetry, answers, acks,
    service responses) from a node not in ``esc_nodes``, a frame the host sends (RawCommand,
    requests) from a node other than 0, or a service exchange with an ESC not in ``esc_nodes``
    (Set ID excepted: its destination is ignored) is not ours either. Those checks come before
    the DLC check, so a foreign frame never raises.

    Raises:
        NotExtendedIdError: an 11-bit ID, a remote (RTR) frame or an error frame.
        UnknownTypeError: a type in CKESC's ranges that CKESC does not define (or whose payload
            the vendor never specified: services 223, 224, a response to 222).
        DlcError: the data length does not match the type.
        TailByteError: the tail byte is not ``0xC0 | transfer_id`` (for MSG_EXP12: not
            0xC1..0xC4); RawCommand_10b has no tail byte.
        FrameError: a Maintenance Information response whose option byte is not 0..2.
    """
    if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
        raise NotExtendedIdError(_not_a_data_frame(msg))
    can_id: int = msg.arbitration_id
    source = can_id & 0x7F
    destination: int | None
    if can_id & 0x80:
        type_id = can_id >> 16 & 0xFF
        destination = can_id >> 8 & 0x7F
        codec = _SERVICE_CODECS.get(type_id << 1 | (can_id >> 15 & 1))
        if codec is None:
            if type_id in SERVICE_TYPE_RANGE:
                kind = "request" if can_id & 0x8000 else "response"
                raise UnknownTypeError(
                    f"service type {type_id} {kind} is in CKESC's range 200..255 but not defined"
                )
            return None
        if esc_nodes is not None:
            host, esc = (source, destination) if codec.from_host else (destination, source)
            if host != HOST_NODE_ID or (esc not in esc_nodes and type_id != SERVICE_SET_ID):
                return None
    else:
        type_id = can_id >> 8 & 0xFFFF
        destination = None
        codec = _MESSAGE_CODECS.get(type_id << 1 | (source != HOST_NODE_ID))
        if codec is None:
            if type_id in MESSAGE_TYPE_RANGE:
                raise UnknownTypeError(
                    f"message type {type_id} is in CKESC's range 20000..20999 but not defined"
                )
            return None
        if esc_nodes is not None and (
            source != HOST_NODE_ID if codec.from_host else source not in esc_nodes
        ):
            return None
    data = msg.data
    if len(data) != codec.dlc:
        raise DlcError(f"{codec.name}: DLC {len(data)}, expected {codec.dlc}")
    if codec.has_transfer_id:
        tail = data[-1]
        if tail & 0xE0 != 0xC0:
            raise TailByteError(
                f"{codec.name}: tail byte 0x{tail:02X} is not a single-frame transfer"
                " (expected 0xC0..0xDF: start and end set, toggle clear)"
            )
        transfer_id: int | None = tail & 0x1F
    else:
        transfer_id = None
    return CkescFrame(can_id >> 24 & 0x1F, source, destination, transfer_id, codec.unpack(data))


def _not_a_data_frame(msg: can.Message) -> str:
    if msg.is_error_frame:
        return "error frame: CKESC uses 29-bit data frames only"
    if msg.is_remote_frame:
        return f"remote (RTR) frame 0x{msg.arbitration_id:X}: CKESC uses 29-bit data frames only"
    return f"11-bit ID 0x{msg.arbitration_id:03X}: CKESC uses 29-bit IDs only"


def encode(frame: CkescFrame) -> can.Message:
    """Encode a frame, checking every value against the protocol's range.

    Raises:
        ValueRangeError: a field of the frame or its record is out of range (the message names
            the field, the value and the range), a message frame has a destination, a service
            frame lacks one, ``transfer_id`` is missing (or given for RawCommand_10b and
            MSG_EXP12, which have none), or the source does not fit the record's direction:
            CANTest, MSGControl and GET_ESC_ID requests come from node 0, their answers from
            an ESC (1..0x7D).
        TypeError: ``frame.message`` is not a CKESC record.
    """
    codec = _codec_of(frame.message)
    priority = _field(frame, "priority", _PRIORITY)
    source = _field(frame, "source_node", _NODE)
    if codec.service:
        destination = _field(frame, "destination_node", _NODE)
        can_id = priority << 24 | codec.type_id << 16 | destination << 8 | 0x80 | source
        if codec.from_host:
            can_id |= 0x8000
    else:
        if frame.destination_node is not None:
            raise ValueRangeError(
                f"{codec.name} is a message (broadcast) frame: CkescFrame.destination_node"
                f" = {frame.destination_node!r}, expected None"
            )
        # decode() tells a request from its answer by the source: make sure it will.
        if _MESSAGE_CODECS[codec.type_id << 1 | (source != HOST_NODE_ID)] is not codec:
            sender = "the host (node 0)" if codec.from_host else "an ESC (node 1..0x7D)"
            raise ValueRangeError(
                f"{codec.name} is sent by {sender}: CkescFrame.source_node = {source}"
            )
        can_id = priority << 24 | codec.type_id << 8 | source
    data = codec.pack(frame.message)
    if codec.has_transfer_id:
        data += bytes((0xC0 | _field(frame, "transfer_id", _TRANSFER_ID),))
    elif frame.transfer_id is not None:
        raise ValueRangeError(
            f"{codec.name} carries no transfer ID: CkescFrame.transfer_id"
            f" = {frame.transfer_id!r}, expected None"
        )
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=True)


def default_priority(message: CkescMessage) -> int:
    """The priority the seed gives the record's frame type (docs/protocols.md §3.2, §3.6).

    Raises:
        TypeError: ``message`` is not a CKESC record.
    """
    return _codec_of(message).priority


def type_id_of(message: CkescMessage) -> int:
    """The record's message or service type ID (the key for :meth:`TransferIds.next`).

    Raises:
        TypeError: ``message`` is not a CKESC record.
    """
    return _codec_of(message).type_id


# --------------------------------------------------------------------------------------------
# Throttle hot path: one check per value, one int, one bytes object, one can.Message.

_RAW_14B_ID: Final = message_id(PRIORITY_HIGHEST, TYPE_RAW_COMMAND_14B, HOST_NODE_ID)
_RAW_12B_ID: Final = message_id(PRIORITY_HIGHEST, TYPE_RAW_COMMAND_12B, HOST_NODE_ID)
_RAW_10B_ID: Final = message_id(PRIORITY_HIGHEST, TYPE_RAW_COMMAND_10B, HOST_NODE_ID)


def _source_node(source_node: int) -> int:
    if 0 <= source_node <= MAX_NODE_ID:
        return source_node
    raise ValueRangeError(f"source_node = {source_node!r} is not in 0..{MAX_NODE_ID}")


def encode_raw_12b(
    group: int, throttles: Sequence[int], transfer_id: int, source_node: int = HOST_NODE_ID
) -> can.Message:
    """A RawCommand_12b frame for channels 4 * group - 3 .. 4 * group.

    ``throttles`` holds 1..4 values, 0..2000; missing channels are sent as 0 (stopped), the
    only value that is safe for an ESC that happens to follow one of them.

    Raises:
        ValueRangeError: group outside 1..5, no or more than four throttles, a throttle
            outside 0..2000, transfer_id outside 0..31 or source_node outside 0..0x7D. Values
            are never clamped: limiting them is the caller's safety layer.
    """
    if not 1 <= group <= MAX_GROUP:
        raise ValueRangeError(f"RawCommand12b group = {group!r} is not in 1..{MAX_GROUP}")
    bits = _bits_12b(throttles) | group << 48 | tail_byte(transfer_id) << 56
    return can.Message(
        arbitration_id=_RAW_12B_ID | _source_node(source_node),
        data=bits.to_bytes(8, "little"),
        is_extended_id=True,
    )


def encode_raw_14b(
    throttles: Sequence[int], transfer_id: int, source_node: int = HOST_NODE_ID
) -> can.Message:
    """A RawCommand_14b frame for channels 1..4 (1..4 values, 0..2000; missing ones are 0).

    Raises:
        ValueRangeError: as :func:`encode_raw_12b`.
    """
    bits = _bits_14b(throttles) << 8 | tail_byte(transfer_id)
    return can.Message(
        arbitration_id=_RAW_14B_ID | _source_node(source_node),
        data=bits.to_bytes(8, "big"),
        is_extended_id=True,
    )


def encode_raw_10b(throttles: Sequence[int], source_node: int = HOST_NODE_ID) -> can.Message:
    """A RawCommand_10b frame for channels 1..6 (1..6 values, 0..1000; missing ones are 0).

    It has no tail byte, hence no transfer ID.

    Raises:
        ValueRangeError: no or more than six throttles, a throttle outside 0..1000, or
            source_node outside 0..0x7D.
    """
    return can.Message(
        arbitration_id=_RAW_10B_ID | _source_node(source_node),
        data=_bits_10b(throttles).to_bytes(8, "little"),
        is_extended_id=True,
    )


def raw_12b_groups(throttles: Sequence[int]) -> list[tuple[int, tuple[int, int, int, int]]]:
    """Split channels 1..n (n = 1..20) into RawCommand_12b ``(group, throttles)`` pairs.

    The last group is padded with 0 (see :func:`encode_raw_12b`); values are not checked here
    but by the encoder.

    Raises:
        ValueRangeError: no throttles or more than 20.
    """
    if not 1 <= len(throttles) <= MAX_CHANNELS:
        raise _count_error("RawCommand12b", throttles, MAX_CHANNELS)
    padded = (*throttles, 0, 0, 0)
    return [
        (1 + start // 4, (padded[start], padded[start + 1], padded[start + 2], padded[start + 3]))
        for start in range(0, len(throttles), CHANNELS_PER_GROUP)
    ]
