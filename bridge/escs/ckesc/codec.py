"""CKESC frames: the envelope (:class:`CkescFrame`), decoding and encoding of whole frames
through the type table of :mod:`~bridge.escs.ckesc.messages` and
:mod:`~bridge.escs.ckesc.services`, and the throttle hot path. Pure: no I/O, clock or logging."""

from __future__ import annotations

from collections.abc import Container, Sequence
from dataclasses import dataclass
from typing import Final

import can

from bridge.errors import (
    DlcError,
    NotExtendedIdError,
    TailByteError,
    UnknownTypeError,
    ValueRangeError,
)
from bridge.escs.ckesc import layout, records
from bridge.escs.ckesc.layout import TypeCodec
from bridge.escs.ckesc.messages import MESSAGE_TYPES, bits_10b, bits_12b, bits_14b
from bridge.escs.ckesc.services import SERVICE_TYPES
from bridge.escs.uavcan_v0 import (
    MAX_NODE_ID,
    PRIORITY_HIGHEST,
    message_id,
    service_id,
    tail_byte,
)

# The type table, keyed by plain ints so that a look-up allocates nothing. Messages:
# ``type_id << 1 | (source != host)``; a type sent one way only answers both keys, a type sent
# both ways has a row per direction. Services: ``service_type << 1 | is_request``.
_BY_RECORD: Final[dict[type, TypeCodec]] = {}
_MESSAGE_CODECS: Final[dict[int, TypeCodec]] = {}
_SERVICE_CODECS: Final[dict[int, TypeCodec]] = {}
for _row in MESSAGE_TYPES:
    _BY_RECORD[_row.record] = _row
    _MESSAGE_CODECS[_row.type_id << 1 | (not _row.from_host)] = _row
    _MESSAGE_CODECS.setdefault(_row.type_id << 1 | _row.from_host, _row)
for _row in SERVICE_TYPES:
    _BY_RECORD[_row.record] = _row
    _SERVICE_CODECS.setdefault(_row.type_id << 1 | _row.from_host, _row)


@dataclass(frozen=True, slots=True)
class CkescFrame:
    """One CKESC frame: the CAN ID's fields around a payload record.

    ``destination_node`` is ``None`` for message (broadcast) frames; ``transfer_id`` is
    ``None`` for RawCommand_10b (no tail byte) and MSG_EXP12 (whose tail holds the record kind).
    """

    priority: int
    source_node: int
    destination_node: int | None
    transfer_id: int | None
    message: records.CkescMessage

    @property
    def node_id(self) -> int:
        """The ESC this frame is from or to: a request's destination, else the source."""
        if self.destination_node is not None and _BY_RECORD[type(self.message)].from_host:
            return self.destination_node
        return self.source_node


def _codec_of(message: records.CkescMessage) -> TypeCodec:
    codec = _BY_RECORD.get(type(message))
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
            if type_id in records.SERVICE_TYPE_RANGE:
                kind = "request" if can_id & 0x8000 else "response"
                raise UnknownTypeError(
                    f"service type {type_id} {kind} is in CKESC's range 200..255 but not defined"
                )
            return None
        if esc_nodes is not None:
            host, esc = (source, destination) if codec.from_host else (destination, source)
            if host != records.HOST_NODE_ID or (
                esc not in esc_nodes and type_id != records.SERVICE_SET_ID
            ):
                return None
    else:
        type_id = can_id >> 8 & 0xFFFF
        destination = None
        codec = _MESSAGE_CODECS.get(type_id << 1 | (source != records.HOST_NODE_ID))
        if codec is None:
            if type_id in records.MESSAGE_TYPE_RANGE:
                raise UnknownTypeError(
                    f"message type {type_id} is in CKESC's range 20000..20999 but not defined"
                )
            return None
        if esc_nodes is not None and (
            source != records.HOST_NODE_ID if codec.from_host else source not in esc_nodes
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
    priority = layout.field_value(frame, "priority", layout.PRIORITY)
    source = layout.field_value(frame, "source_node", layout.NODE)
    if codec.service:
        destination = layout.field_value(frame, "destination_node", layout.NODE)
        can_id = service_id(priority, codec.type_id, codec.from_host, destination, source)
    else:
        if frame.destination_node is not None:
            raise ValueRangeError(
                f"{codec.name} is a message (broadcast) frame: CkescFrame.destination_node"
                f" = {frame.destination_node!r}, expected None"
            )
        # decode() tells a request from its answer by the source: make sure it will.
        if _MESSAGE_CODECS[codec.type_id << 1 | (source != records.HOST_NODE_ID)] is not codec:
            sender = "the host (node 0)" if codec.from_host else "an ESC (node 1..0x7D)"
            raise ValueRangeError(
                f"{codec.name} is sent by {sender}: CkescFrame.source_node = {source}"
            )
        can_id = message_id(priority, codec.type_id, source)
    data = codec.pack(frame.message)
    if codec.has_transfer_id:
        data += bytes((0xC0 | layout.field_value(frame, "transfer_id", layout.TRANSFER_ID),))
    elif frame.transfer_id is not None:
        raise ValueRangeError(
            f"{codec.name} carries no transfer ID: CkescFrame.transfer_id"
            f" = {frame.transfer_id!r}, expected None"
        )
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=True)


def default_priority(message: records.CkescMessage) -> int:
    """The priority the seed gives the record's frame type (docs/protocols.md §3.2, §3.6).

    Raises:
        TypeError: ``message`` is not a CKESC record.
    """
    return _codec_of(message).priority


def type_id_of(message: records.CkescMessage) -> int:
    """The record's message or service type ID (the key for :meth:`TransferIds.next`).

    Raises:
        TypeError: ``message`` is not a CKESC record.
    """
    return _codec_of(message).type_id


# --------------------------------------------------------------------------------------------
# Throttle hot path: one check per value, one int, one bytes object, one can.Message.

_RAW_14B_ID: Final = message_id(
    PRIORITY_HIGHEST, records.TYPE_RAW_COMMAND_14B, records.HOST_NODE_ID
)
_RAW_12B_ID: Final = message_id(
    PRIORITY_HIGHEST, records.TYPE_RAW_COMMAND_12B, records.HOST_NODE_ID
)
_RAW_10B_ID: Final = message_id(
    PRIORITY_HIGHEST, records.TYPE_RAW_COMMAND_10B, records.HOST_NODE_ID
)


def _source_node(source_node: int) -> int:
    if 0 <= source_node <= MAX_NODE_ID:
        return source_node
    raise ValueRangeError(f"source_node = {source_node!r} is not in 0..{MAX_NODE_ID}")


def encode_raw_12b(
    group: int, throttles: Sequence[int], transfer_id: int, source_node: int = records.HOST_NODE_ID
) -> can.Message:
    """A RawCommand_12b frame for channels 4 * group - 3 .. 4 * group.

    ``throttles`` holds 1..4 values, 0..2000; missing channels are sent as 0 (stopped), the
    only value that is safe for an ESC that happens to follow one of them.

    Raises:
        ValueRangeError: group outside 1..5, no or more than four throttles, a throttle
            outside 0..2000, transfer_id outside 0..31 or source_node outside 0..0x7D. Values
            are never clamped: limiting them is the caller's safety layer.
    """
    if not 1 <= group <= records.MAX_GROUP:
        raise ValueRangeError(f"RawCommand12b group = {group!r} is not in 1..{records.MAX_GROUP}")
    bits = bits_12b(throttles) | group << 48 | tail_byte(transfer_id) << 56
    return can.Message(
        arbitration_id=_RAW_12B_ID | _source_node(source_node),
        data=bits.to_bytes(8, "little"),
        is_extended_id=True,
    )


def encode_raw_14b(
    throttles: Sequence[int], transfer_id: int, source_node: int = records.HOST_NODE_ID
) -> can.Message:
    """A RawCommand_14b frame for channels 1..4 (1..4 values, 0..2000; missing ones are 0).

    Raises:
        ValueRangeError: as :func:`encode_raw_12b`.
    """
    bits = bits_14b(throttles) << 8 | tail_byte(transfer_id)
    return can.Message(
        arbitration_id=_RAW_14B_ID | _source_node(source_node),
        data=bits.to_bytes(8, "big"),
        is_extended_id=True,
    )


def encode_raw_10b(
    throttles: Sequence[int], source_node: int = records.HOST_NODE_ID
) -> can.Message:
    """A RawCommand_10b frame for channels 1..6 (1..6 values, 0..1000; missing ones are 0).

    It has no tail byte, hence no transfer ID.

    Raises:
        ValueRangeError: no or more than six throttles, a throttle outside 0..1000, or
            source_node outside 0..0x7D.
    """
    return can.Message(
        arbitration_id=_RAW_10B_ID | _source_node(source_node),
        data=bits_10b(throttles).to_bytes(8, "little"),
        is_extended_id=True,
    )
