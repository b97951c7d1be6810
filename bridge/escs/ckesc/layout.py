"""How a CKESC frame type sits on the wire: the value ranges and field checks the packers share,
and a type's row in the codec's table (:class:`TypeCodec`: type ID, sender, DLC, priority,
unpack and pack), which :mod:`~bridge.escs.ckesc.messages` and
:mod:`~bridge.escs.ckesc.services` fill in and :mod:`~bridge.escs.ckesc.codec` looks up. Pure:
no I/O, clock or logging.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final, TypeAlias, TypeVar

from bridge.errors import ValueRangeError
from bridge.escs.ckesc.records import (
    BAUD_RATES_BPS,
    MAX_CHANNELS,
    MAX_GROUP,
    THROTTLE_10B_MAX,
    THROTTLE_MAX,
    CanTestOption,
    CkescMessage,
    ExpandSetCommand,
    MsgControlCommand,
    Rotation,
    SelfTestFault,
    TempRecordKind,
    ThrottleSource,
)
from bridge.escs.uavcan_v0 import (
    MAX_NODE_ID,
    MAX_TRANSFER_ID,
    PRIORITY_HIGHEST,
    PRIORITY_LOW,
    PRIORITY_LOWEST,
    PRIORITY_MEDIUM,
)

# The wire limits and spec ranges the encoders check against (``range`` membership is O(1)).
U8 = range(0x100)
U16 = range(0x1_0000)
U32 = range(0x1_0000_0000)
NIBBLE = range(0x10)
BOOL = range(2)
PRIORITY = range(PRIORITY_LOWEST + 1)
NODE = range(MAX_NODE_ID + 1)
ESC_NODE = range(1, MAX_NODE_ID + 1)
TRANSFER_ID = range(MAX_TRANSFER_ID + 1)
CHANNEL = range(1, MAX_CHANNELS + 1)
GROUP = range(1, MAX_GROUP + 1)
THROTTLE = range(THROTTLE_MAX + 1)
THROTTLE_10B = range(THROTTLE_10B_MAX + 1)
BAUD_CODE = range(len(BAUD_RATES_BPS))
LED_RGB = range(8)
BLINK_HZ = (0, 1, 2, 5)
INTERVAL_MS = range(0, 2 * 0xFF + 1, 2)
INTERVAL_WRITE_MS = range(20, 501, 2)
MAX_CURRENT_A = range(0, 10 * 0xFF + 1, 10)

Allowed: TypeAlias = range | tuple[int, ...]
Buf: TypeAlias = bytes | bytearray


# The parts each Expand Set command accepts (seed 4.4.25's table, reserved entries included).
EXPAND_SET_PARTS: Final[dict[int, Allowed]] = {
    ExpandSetCommand.DIRECTION: range(1, 3),
    ExpandSetCommand.LED: range(4),
    ExpandSetCommand.THROTTLE_INTERFACE: range(1, 7),
    ExpandSetCommand.ACTIVE_FREEWHEELING: range(2),
    ExpandSetCommand.TIMING: range(1, 5),
    ExpandSetCommand.TIMING_2: range(1, 5),
    ExpandSetCommand.LOAD_TYPE: range(1, 5),
    ExpandSetCommand.PROP_LOCK: range(4),
    ExpandSetCommand.STARTUP_ACCELERATION: range(16),
    ExpandSetCommand.SIGNAL_LOSS_RATE: range(16),
    ExpandSetCommand.READ_TEMP_RECORD: (1,),
    ExpandSetCommand.BAUD: BAUD_CODE,
    ExpandSetCommand.SYSTEM: (0x00, 0x10, 0x11),
}

_E = TypeVar("_E", bound=enum.IntEnum)


def _members(enum_type: type[_E]) -> dict[int, _E]:
    """Value → member, for decoding with ``.get(raw, raw)``: unknown values stay plain ints."""
    return {member.value: member for member in enum_type}


SELF_TEST_FAULTS = _members(SelfTestFault)
CAN_TEST_OPTIONS = _members(CanTestOption)
MSG_CONTROL_COMMANDS = _members(MsgControlCommand)
ROTATIONS = _members(Rotation)
THROTTLE_SOURCES = _members(ThrottleSource)
EXPAND_SET_COMMANDS = _members(ExpandSetCommand)
TEMP_RECORD_KINDS = _members(TempRecordKind)

# The values the encoders accept for enumerated fields.
HOST_CAN_TEST_OPTIONS = (CanTestOption.ENTER, CanTestOption.LEAVE)
HOST_MSG_CONTROL_COMMANDS = (
    MsgControlCommand.PAUSE,
    MsgControlCommand.RESUME_MSG,
    MsgControlCommand.RESUME_EXP,
)
ROTATION_VALUES = tuple(Rotation)
THROTTLE_SOURCE_VALUES = tuple(ThrottleSource)
EXPAND_SET_VALUES = tuple(ExpandSetCommand)
TEMP_RECORD_KIND_VALUES = tuple(TempRecordKind)

# --------------------------------------------------------------------------------------------
# Range checks shared by the encoders


def describe(allowed: Allowed) -> str:
    """``allowed`` for an error message: "in 0..31", "in 20..500 in steps of 2", "one of 1, 2"."""
    if isinstance(allowed, tuple):
        return "one of " + ", ".join(
            str(value) if value < 0x100 else hex(value) for value in allowed
        )
    text = f"in {allowed.start}..{allowed.stop - 1}"
    return text if allowed.step == 1 else f"{text} in steps of {allowed.step}"


def check_value(what: str, value: object, allowed: Allowed) -> int:
    """``value`` as an int if it is one of ``allowed``; else ValueRangeError naming it all."""
    if isinstance(value, int) and value in allowed:
        return int(value)
    raise ValueRangeError(f"{what} = {value!r} is not {describe(allowed)}")


def field_value(record: object, name: str, allowed: Allowed) -> int:
    """The checked int value of ``record.name``."""
    value = getattr(record, name)
    if isinstance(value, int) and value in allowed:
        return int(value)
    # Only now build the field's name: encoding checks every field of every frame.
    return check_value(f"{type(record).__name__}.{name}", value, allowed)


def field_stepped(record: object, name: str, allowed: range) -> int:
    """The checked value of ``record.name`` in wire units of ``allowed.step`` (2 ms, 10 A)."""
    return field_value(record, name, allowed) // allowed.step


def field_centi(record: object, name: str) -> int:
    """``record.name`` (V or A, 0..655.35) as the wire's u16 count of 0.01 units, rounded."""
    value = getattr(record, name)
    # The float comparison also turns away NaN; rounding to the 0.01 step is quantisation,
    # not clipping, since the range has been checked first.
    if isinstance(value, int | float) and 0 <= value <= 655.35:
        return round(value * 100)
    raise ValueRangeError(f"{type(record).__name__}.{name} = {value!r} is not in 0..655.35")


R = TypeVar("R")
Unpack: TypeAlias = Callable[[Buf], CkescMessage]
"""A type's decoder: the whole CAN data (its length already checked) to the record."""
Pack: TypeAlias = Callable[[Any], bytes]
"""A type's encoder: the record, checked, to the payload before the tail byte (the whole data
for the two types without a transfer ID)."""

# The table's rows say who sends a type and at which of the seed's priorities, in these words.
FROM_HOST, FROM_ESC = True, False
REQUEST, RESPONSE = True, False
HIGHEST, MEDIUM, LOW, LOWEST = PRIORITY_HIGHEST, PRIORITY_MEDIUM, PRIORITY_LOW, PRIORITY_LOWEST


@dataclass(frozen=True, slots=True)
class TypeCodec:
    """One row of the codec's table: a frame type and how its payload is laid out."""

    record: type[CkescMessage]
    name: str
    """For error messages: the record and its type ID, e.g. "Msg1 (20050)"."""
    type_id: int
    service: bool
    from_host: bool
    """Message frame: sent by the host (RawCommand, requests). Service frame: a request."""
    dlc: int
    """Data length, the tail byte included."""
    priority: int
    """The seed's priority for the type."""
    unpack: Unpack
    pack: Pack
    has_transfer_id: bool
    """False: no transfer ID in the tail byte, and ``pack`` returns the whole data."""


def message_type(
    record: type[CkescMessage],
    type_id: int,
    from_host: bool,
    dlc: int,
    priority: int,
    unpack: Unpack,
    pack: Pack,
    has_transfer_id: bool = True,
) -> TypeCodec:
    """The row of a message (broadcast) type; a type sent both ways has a row per direction."""
    name = f"{record.__name__} ({type_id})"
    return TypeCodec(
        record, name, type_id, False, from_host, dlc, priority, unpack, pack, has_transfer_id
    )


def service_type(
    record: type[CkescMessage],
    service_type: int,
    request: bool,
    dlc: int,
    priority: int,
    unpack: Unpack,
    pack: Pack,
) -> TypeCodec:
    """The row of a service type's request or response."""
    name = f"{record.__name__} ({service_type})"
    return TypeCodec(record, name, service_type, True, request, dlc, priority, unpack, pack, True)


def plain(record: Callable[..., R], fmt: str, **fields: Allowed) -> tuple[Callable[[Buf], R], Pack]:
    """Codec for a record of int fields in wire order; ``fields`` gives each one's range."""
    layout = struct.Struct(fmt)
    checks = tuple(fields.items())

    def unpack(data: Buf) -> R:
        return record(*layout.unpack_from(data))

    def pack(message: Any) -> bytes:
        return layout.pack(*[field_value(message, name, allowed) for name, allowed in checks])

    return unpack, pack
