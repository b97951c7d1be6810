"""CKESC CAN codec: UAVCAN v0 framing carrying the vendor's own message and service types.

The reference is ``PROTOCOLS.md`` §1 (the project's reading of the vendor's "CKESC UAVCAN
Protocol 2.1"); section numbers "seed 4.4.x" below point into the vendor document. This module
is pure: it imports only the standard library and ``can`` (for :class:`can.Message`), and has
no I/O, clock or logging.

Wire format in one paragraph: 29-bit data frames only. A message (broadcast) frame's ID is
priority (5 bits) · type ID (16) · 0 · source node (7); a service frame's ID is priority ·
service type (8) · request flag · destination node (7) · 1 · source node. All multi-byte fields
are little-endian. Every frame but RawCommand_10b ends in a tail byte ``0xC0 | transfer_id``
(single-frame transfer); MSG_EXP12 uses its tail byte's transfer ID for a record kind.

Public API:

- ID helpers :func:`message_id`, :func:`service_id`, :func:`parse_id` (→ :class:`CanId`),
  :func:`tail_byte`, and :class:`TransferIds` (one 0..31 counter per type ID).
- One frozen record class per payload (:data:`CkescMessage` is their union), wrapped in a
  :class:`CkescFrame` envelope; :func:`decode` and :func:`encode` convert envelopes.
- Throttle hot path: :func:`encode_raw_12b`, :func:`encode_raw_14b`, :func:`encode_raw_10b`
  and :func:`raw_12b_groups`.

Decisions where the seed is silent or ambiguous (each also noted where it is coded):

- Three message types go both ways (CANTest, MSGControl, GET_ESC_ID). A frame from the host
  (source node 0) is the host's request; from any other node it is the ESC's answer. So
  :func:`encode` requires source 0 for those requests and a non-zero source for the answers.
- Maintenance Information (241) responses do not say which option they answer; the seed shows
  the option in byte 6 only for option 2. We read byte 6 as the option for all three and write
  it so (the only way a response can be decoded without remembering the request); a byte 6
  outside 0..2 raises :class:`~bridge.errors.FrameError`. Needs checking on hardware.
- Expand Set (222) has no response (the motor beeps), so a 222 response frame, like Get/Clear
  temperature record (223/224, payloads unspecified), raises ``UnknownTypeError``.
- Reserved bytes and nibbles are ignored on decode and sent as zero. Option bytes the seed fixes
  at 0 are still fields (default 0) so that a frame decodes and re-encodes unchanged.
- Report intervals are in milliseconds (the wire counts 2 ms units): writes accept 20..500 ms
  in steps of 2, reads and reports any byte (0..510 ms).
- ``MajorConfigResponse.led_blink_hz``: the seed calls bits 7..3 "LED blink state"; we take it
  to be the Set LED blink setting (0 off, 1/2/5 Hz) and keep whatever value arrives.
- ``EscInfoResponse.firmware_year`` is the byte as sent (the seed does not give its epoch).
- Values that arrive outside their documented range (a throttle of 3000, group 6) decode as
  sent: decoding reports what is on the bus; only :func:`encode` refuses such values.
- Node IDs for encoding are 0..0x7D (0x7E and 0x7F are reserved, seed 4.1.2), also for the
  Set ID destination, which the ESC ignores.
- ``esc_nodes`` (see :func:`decode`) filters services as well as messages: vendor service IDs
  200..255 are as shared as vendor message IDs. A service frame is ours if its host side is
  node 0 and its ESC side is in ``esc_nodes``; Set ID is exempt from the second test, since its
  destination is ignored and the answering ESC's ID is the one being set.
- Flag bytes become ``bool``: Set LED ``save`` and Set/Get Freq ``write`` are true for any
  non-zero byte, Self Test ``passed`` only for status 0 (the seed defines 0 pass, 1 fail).
- The throttle encoders take 1..n values and send the missing channels as 0 (stopped): the only
  value that is safe for an ESC that happens to follow one of them.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Callable, Container, Sequence
from dataclasses import dataclass
from typing import Any, Final, TypeAlias, TypeVar

import can

from bridge.errors import (
    DlcError,
    FrameError,
    NotExtendedIdError,
    TailByteError,
    UnknownTypeError,
    ValueRangeError,
)

# --------------------------------------------------------------------------------------------
# Protocol constants (PROTOCOLS.md §1.1, §1.3)

PRIORITY_HIGHEST: Final = 0
PRIORITY_HIGH: Final = 8
PRIORITY_MEDIUM: Final = 16
PRIORITY_LOW: Final = 24
PRIORITY_LOWEST: Final = 31

HOST_NODE_ID: Final = 0
"""The bridge's own node ID; every CKESC request and throttle command comes from node 0."""
FACTORY_NODE_ID: Final = 0x7D
"""An ESC's node ID as shipped; an ESC at this ID sends no telemetry."""
MAX_NODE_ID: Final = 0x7D
"""Highest usable node ID (0x7E and 0x7F are reserved)."""
MAX_TRANSFER_ID: Final = 31

MESSAGE_TYPE_RANGE: Final = range(20000, 21000)
"""UAVCAN v0's vendor message type IDs, which CKESC uses; other message types are not ours."""
SERVICE_TYPE_RANGE: Final = range(200, 256)
"""UAVCAN v0's vendor service type IDs, which CKESC uses; other service types are not ours."""

TYPE_CAN_TEST: Final = 20000
TYPE_MSG_CONTROL: Final = 20010
TYPE_GET_ESC_ID: Final = 20013
TYPE_MSG1: Final = 20050
TYPE_MSG2: Final = 20051
TYPE_MSG3: Final = 20052
TYPE_MSG_EXP1: Final = 20053
TYPE_MSG_EXP2: Final = 20054
TYPE_MSG_EXP3: Final = 20055
TYPE_MSG_EXP4: Final = 20056
TYPE_MSG_EXP5: Final = 20057
TYPE_MSG_EXP6: Final = 20058
TYPE_MSG_EXP7: Final = 20059
TYPE_MSG_EXP8: Final = 20060
TYPE_MSG_EXP9: Final = 20061
TYPE_MSG_EXP10: Final = 20062
TYPE_MSG_EXP11: Final = 20063
TYPE_MSG_EXP12: Final = 20064
TYPE_RAW_COMMAND_14B: Final = 20100
TYPE_RAW_COMMAND_12B: Final = 20101
TYPE_RAW_COMMAND_10B: Final = 20102

SERVICE_SET_ID: Final = 210
SERVICE_SET_BAUD: Final = 211
SERVICE_SET_LED: Final = 212
SERVICE_SET_ROTATION: Final = 213
SERVICE_SET_FREQ: Final = 214
SERVICE_THROTTLE_SELECT: Final = 215
SERVICE_SELF_TEST: Final = 216
SERVICE_EXPAND_SET: Final = 222
SERVICE_GET_TEMP_RECORD: Final = 223
"""Defined by the seed without a payload; decoding it raises ``UnknownTypeError``."""
SERVICE_CLEAR_TEMP_RECORD: Final = 224
"""Defined by the seed without a payload; decoding it raises ``UnknownTypeError``."""
SERVICE_ESC_INFO: Final = 240
SERVICE_MAINTENANCE: Final = 241
SERVICE_MAJOR_CONFIG: Final = 242

THROTTLE_MAX: Final = 2000
"""Full throttle for RawCommand_14b/12b (and MSG1's throttle report)."""
THROTTLE_10B_MAX: Final = 1000
"""Full throttle for RawCommand_10b; the ESC doubles the value."""
MAX_CHANNELS: Final = 20
"""Throttle channels an ESC can be assigned (Set ID), i.e. RawCommand_12b groups 1..5 of 4."""
CHANNELS_PER_GROUP: Final = 4
MAX_GROUP: Final = 5

BAUD_RATES_BPS: Final = (1_000_000, 500_000, 250_000, 200_000, 125_000, 100_000, 50_000)
"""Bit rate for each Set Baud code (the index); 1 (500 kbit/s) is the factory setting."""

# The wire limits and spec ranges the encoders check against (``range`` membership is O(1)).
_U8 = range(0x100)
_U16 = range(0x1_0000)
_U32 = range(0x1_0000_0000)
_NIBBLE = range(0x10)
_BOOL = range(2)
_PRIORITY = range(PRIORITY_LOWEST + 1)
_TYPE_ID = _U16
_SERVICE_TYPE = _U8
_NODE = range(MAX_NODE_ID + 1)
_ESC_NODE = range(1, MAX_NODE_ID + 1)
_TRANSFER_ID = range(MAX_TRANSFER_ID + 1)
_CHANNEL = range(1, MAX_CHANNELS + 1)
_GROUP = range(1, MAX_GROUP + 1)
_THROTTLE = range(THROTTLE_MAX + 1)
_THROTTLE_10B = range(THROTTLE_10B_MAX + 1)
_BAUD_CODE = range(len(BAUD_RATES_BPS))
_LED_RGB = range(8)
_BLINK_HZ = (0, 1, 2, 5)
_INTERVAL_MS = range(0, 2 * 0xFF + 1, 2)
_INTERVAL_WRITE_MS = range(20, 501, 2)
_MAX_CURRENT_A = range(0, 10 * 0xFF + 1, 10)

_Allowed: TypeAlias = range | tuple[int, ...]
_Buf: TypeAlias = bytes | bytearray

# --------------------------------------------------------------------------------------------
# Enumerations


class Msg1Status(enum.IntFlag):
    """MSG1 status word (seed 4.4.4). Bits 7..0 are the power-on self-test's findings."""

    DIRECTION_CCW = 1 << 15
    """Set: the motor turns counter-clockwise (reversed); clear: clockwise."""
    THROTTLE_SOURCE_PWM = 1 << 14
    """Set: the throttle comes from the PWM input; clear: from CAN."""
    COMMS_FAULT = 1 << 13
    """No valid CAN throttle for more than 200 ms; cleared by the next valid command."""
    UNDER_VOLTAGE = 1 << 12
    OVER_VOLTAGE = 1 << 11
    OVER_CURRENT = 1 << 10
    OVER_TEMPERATURE = 1 << 9
    RUNNING = 1 << 8
    SELF_TEST_COM_INPUT_LOW = 1 << 7
    SELF_TEST_PHASE_C_OUTPUT_LOW = 1 << 6
    SELF_TEST_PHASE_B_OUTPUT_LOW = 1 << 5
    SELF_TEST_PHASE_A_OUTPUT_LOW = 1 << 4
    SELF_TEST_COM_INPUT_HIGH = 1 << 3
    SELF_TEST_PHASE_C_OUTPUT_HIGH = 1 << 2
    SELF_TEST_PHASE_B_OUTPUT_HIGH = 1 << 1
    SELF_TEST_PHASE_A_OUTPUT_HIGH = 1 << 0
    SELF_TEST_ERRORS = 0xFF
    """Mask of the eight self-test bits."""


class SelfTestFault(enum.IntEnum):
    """Self-test fault code 1 (MSG_EXP9, Maintenance option 2; seed appendix). 0 is a pass."""

    NONE = 0x00
    COM_LOW = 0x01
    COM_HIGH = 0x02
    PHASE_A_HIGH = 0x11
    PHASE_B_HIGH = 0x12
    PHASE_C_HIGH = 0x13
    PHASE_A_LOW = 0x21
    PHASE_B_LOW = 0x22
    PHASE_C_LOW = 0x23


class CanTestOption(enum.IntEnum):
    """CANTest option byte (seed 4.4.1)."""

    REPORT = 0x00
    """An ESC's periodic report while in bus test mode."""
    ENTER = 0xAA
    LEAVE = 0x55


class MsgControlCommand(enum.IntEnum):
    """MSGControl command word (seed 4.4.2)."""

    ACK = 0x0000_0000
    """The ESCs' answer to any command."""
    PAUSE = 0x5555_5555
    """Stop all periodic reports."""
    RESUME_MSG = 0xAAAA_AAAA
    """Resume MSG1..MSG3."""
    RESUME_EXP = 0xEEEE_EEEE
    """Resume MSG_EXP1..MSG_EXP12."""


class TempRecordKind(enum.IntEnum):
    """Which maximum a MSG_EXP12 temperature record holds (its tail byte's transfer ID)."""

    MCU = 1
    MOS = 2
    CAPACITOR = 3
    MOTOR = 4


class LedColor(enum.IntFlag):
    """Set LED colour bits (seed 4.4.20); ``LedColor(0)`` is off. Other bits are kept as sent."""

    BLUE = 1 << 0
    GREEN = 1 << 1
    RED = 1 << 2


class Rotation(enum.IntEnum):
    """Set Rotation argument (seed 4.4.21)."""

    NORMAL = 0x00
    REVERSED = 0x01
    QUERY = 0xFF
    """Request only: ask for the current direction, which the response carries."""


class ThrottleSource(enum.IntEnum):
    """Where the ESC takes its throttle from (Throttle Select, seed 4.4.23)."""

    CAN = 0x00
    PWM_AND_CAN = 0x01


class ExpandSetCommand(enum.IntEnum):
    """Expand Set ``set_cmd`` (seed 4.4.25; the seed's five-digit 0xffffN means 0xFFFN)."""

    DIRECTION = 0xFFF0
    """Part 1 normal, 2 reversed."""
    LED = 0xFFF1
    """Part 0 off, 1 red, 2 green, 3 blue."""
    THROTTLE_INTERFACE = 0xFFF2
    """Part 1 PWM, 2 PWM+TCAN, 3 TCAN, 4 DShot, 5 PWM+UAVCAN, 6 UAVCAN (1, 4 reserved)."""
    ACTIVE_FREEWHEELING = 0xFFF4
    """Synchronous rectification: part 0 off, 1 on."""
    TIMING = 0xFFF5
    """Commutation advance, part 1..4 low to high (reserved)."""
    TIMING_2 = 0xFFF6
    """Second advance setting, part 1..4 (reserved)."""
    LOAD_TYPE = 0xFFF7
    """Part 1 light, 2 standard, 3 heavy, 4 very heavy (reserved)."""
    PROP_LOCK = 0xFFF8
    """Holding torque on a stopped propeller: part 0 off, 1 weak, 2 medium, 3 strong."""
    STARTUP_ACCELERATION = 0xFFF9
    """Part 0..15: higher starts faster."""
    SIGNAL_LOSS_RATE = 0xFFFA
    """Part 0..15: higher cuts the throttle faster when the signal is lost."""
    READ_TEMP_RECORD = 0xFFFB
    """Part 1: send the temperature records (as four MSG_EXP12 frames)."""
    BAUD = 0xFFFC
    """Part 0..6: a Set Baud code."""
    SYSTEM = 0xFFFE
    """Part 0x00 factory reset (not enabled in firmware), 0x10 leave / 0x11 enter test mode."""


# The parts each Expand Set command accepts (seed 4.4.25's table, reserved entries included).
_EXPAND_SET_PARTS: Final[dict[int, _Allowed]] = {
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
    ExpandSetCommand.BAUD: _BAUD_CODE,
    ExpandSetCommand.SYSTEM: (0x00, 0x10, 0x11),
}

_E = TypeVar("_E", bound=enum.IntEnum)


def _members(enum_type: type[_E]) -> dict[int, _E]:
    """Value → member, for decoding with ``.get(raw, raw)``: unknown values stay plain ints."""
    return {member.value: member for member in enum_type}


_SELF_TEST_FAULTS = _members(SelfTestFault)
_CAN_TEST_OPTIONS = _members(CanTestOption)
_MSG_CONTROL_COMMANDS = _members(MsgControlCommand)
_ROTATIONS = _members(Rotation)
_THROTTLE_SOURCES = _members(ThrottleSource)
_EXPAND_SET_COMMANDS = _members(ExpandSetCommand)
_TEMP_RECORD_KINDS = _members(TempRecordKind)

# The values the encoders accept for enumerated fields.
_HOST_CAN_TEST_OPTIONS = (CanTestOption.ENTER, CanTestOption.LEAVE)
_HOST_MSG_CONTROL_COMMANDS = (
    MsgControlCommand.PAUSE,
    MsgControlCommand.RESUME_MSG,
    MsgControlCommand.RESUME_EXP,
)
_ROTATION_VALUES = tuple(Rotation)
_THROTTLE_SOURCE_VALUES = tuple(ThrottleSource)
_EXPAND_SET_VALUES = tuple(ExpandSetCommand)
_TEMP_RECORD_KIND_VALUES = tuple(TempRecordKind)

# --------------------------------------------------------------------------------------------
# Range checks shared by the ID helpers and the encoders


def _describe(allowed: _Allowed) -> str:
    """``allowed`` for an error message: "in 0..31", "in 20..500 in steps of 2", "one of 1, 2"."""
    if isinstance(allowed, tuple):
        return "one of " + ", ".join(
            str(value) if value < 0x100 else hex(value) for value in allowed
        )
    text = f"in {allowed.start}..{allowed.stop - 1}"
    return text if allowed.step == 1 else f"{text} in steps of {allowed.step}"


def _check(what: str, value: object, allowed: _Allowed) -> int:
    """``value`` as an int if it is one of ``allowed``; else ValueRangeError naming it all."""
    if isinstance(value, int) and value in allowed:
        return int(value)
    raise ValueRangeError(f"{what} = {value!r} is not {_describe(allowed)}")


def _field(record: object, name: str, allowed: _Allowed) -> int:
    """The checked int value of ``record.name``."""
    value = getattr(record, name)
    if isinstance(value, int) and value in allowed:
        return int(value)
    # Only now build the field's name: encoding checks every field of every frame.
    return _check(f"{type(record).__name__}.{name}", value, allowed)


def _field_stepped(record: object, name: str, allowed: range) -> int:
    """The checked value of ``record.name`` in wire units of ``allowed.step`` (2 ms, 10 A)."""
    return _field(record, name, allowed) // allowed.step


def _field_centi(record: object, name: str) -> int:
    """``record.name`` (V or A, 0..655.35) as the wire's u16 count of 0.01 units, rounded."""
    value = getattr(record, name)
    # The float comparison also turns away NaN; rounding to the 0.01 step is quantisation,
    # not clipping, since the range has been checked first.
    if isinstance(value, int | float) and 0 <= value <= 655.35:
        return round(value * 100)
    raise ValueRangeError(f"{type(record).__name__}.{name} = {value!r} is not in 0..655.35")


# --------------------------------------------------------------------------------------------
# CAN ID, tail byte, transfer IDs


@dataclass(frozen=True, slots=True)
class CanId:
    """The fields of a UAVCAN v0 CAN ID (PROTOCOLS.md §1.1).

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

    Message and service type IDs share the map: CKESC's (20000.. and ..255) never collide.
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
# Message (broadcast) records


@dataclass(frozen=True, slots=True)
class CanTestRequest:
    """CANTest (20000) from the host: enter or leave bus test mode (seed 4.4.1)."""

    option: CanTestOption | int
    """:attr:`CanTestOption.ENTER` or :attr:`CanTestOption.LEAVE`."""
    count: int = 0
    """Any u32; the ESC ignores it."""


@dataclass(frozen=True, slots=True)
class CanTestReport:
    """CANTest (20000) from an ESC in test mode: a counter that rises by one per frame."""

    count: int
    """u32, wraps."""
    option: CanTestOption | int = CanTestOption.REPORT


@dataclass(frozen=True, slots=True)
class MsgControlRequest:
    """MSGControl (20010) from the host to all ESCs: pause or resume periodic reports."""

    command: MsgControlCommand | int
    """PAUSE, RESUME_MSG or RESUME_EXP."""
    option: int = 0


@dataclass(frozen=True, slots=True)
class MsgControlAck:
    """MSGControl (20010) from an ESC: the acknowledgement (after 2 ms per node_id % 32)."""

    command: MsgControlCommand | int = MsgControlCommand.ACK
    option: int = 0


@dataclass(frozen=True, slots=True)
class GetEscIdRequest:
    """GET_ESC_ID (20013) from the host: every ESC answers with its node ID and channel."""

    option: int = 0


@dataclass(frozen=True, slots=True)
class GetEscIdAnswer:
    """GET_ESC_ID (20013) from an ESC (after 2 ms per node_id % 32)."""

    node_id: int
    """1..0x7D."""
    throttle_channel: int
    """The RawCommand channel the ESC follows, 1..20."""


@dataclass(frozen=True, slots=True)
class Msg1:
    """MSG1 (20050): speed, throttle and status; 50 Hz by default (seed 4.4.4)."""

    speed_rpm: int
    """Mechanical rpm, u16."""
    throttle: int
    """Throttle output, 0..2000."""
    status: Msg1Status


@dataclass(frozen=True, slots=True)
class Msg2:
    """MSG2 (20051): supply voltage, bus current and MOSFET temperature; 10 Hz by default."""

    voltage_v: float
    """Input voltage, 0..655.35 V in 0.01 V steps."""
    current_a: float
    """Bus current, 0..655.35 A in 0.01 A steps."""
    mos_temp_c: int
    """°C, u8."""


@dataclass(frozen=True, slots=True)
class Msg3:
    """MSG3 (20052): temperatures in °C (u8 each); 2 Hz by default."""

    mos_temp_c: int
    capacitor_temp_c: int
    motor_temp_c: int
    """Needs a motor temperature sensor."""
    mcu_temp_c: int


@dataclass(frozen=True, slots=True)
class MsgExp1:
    """MSG_EXP1 (20053): speed, voltage and current in one frame."""

    speed_rpm: int
    """Mechanical rpm, u16."""
    voltage_v: float
    """0..655.35 V in 0.01 V steps."""
    current_a: float
    """0..655.35 A in 0.01 A steps."""


@dataclass(frozen=True, slots=True)
class _DebugData:
    data: bytes
    """Six bytes of vendor debug data, kept raw."""


@dataclass(frozen=True, slots=True)
class MsgExp2(_DebugData):
    """MSG_EXP2 (20054): vendor debug data."""


@dataclass(frozen=True, slots=True)
class MsgExp3(_DebugData):
    """MSG_EXP3 (20055): vendor debug data."""


@dataclass(frozen=True, slots=True)
class MsgExp4(_DebugData):
    """MSG_EXP4 (20056): vendor debug data."""


@dataclass(frozen=True, slots=True)
class MsgExp5(_DebugData):
    """MSG_EXP5 (20057): vendor debug data."""


@dataclass(frozen=True, slots=True)
class MsgExp6(_DebugData):
    """MSG_EXP6 (20058): vendor debug data."""


@dataclass(frozen=True, slots=True)
class MsgExp7:
    """MSG_EXP7 (20059): the ESC's settings, one nibble (0..15) each (seed 4.4.9).

    The seed's "BIT4..4" means bits 7..4. Values follow Expand Set's parts (seed 4.4.25).
    """

    motor_direction: int
    """Set_0 bits 3..0: 1 normal, 2 reversed."""
    led: int
    """Set_0 bits 7..4: 0 off, 1 red, 2 green, 3 blue (not the Set LED RGB bits)."""
    throttle_interface: int
    """Set_1 bits 3..0: 2 PWM+CAN, 3 CAN."""
    active_freewheeling: int
    """Set_2 bits 3..0: 0 off, 1 on."""
    timing: int
    """Set_2 bits 7..4 (reserved: advance setting 1)."""
    timing_2: int
    """Set_3 bits 3..0 (reserved: advance setting 2)."""
    load_type: int
    """Set_3 bits 7..4 (reserved: load type)."""
    prop_lock: int
    """Set_4 bits 3..0: 0 off, 1 weak, 2 medium, 3 strong."""
    startup_acceleration: int
    """Set_4 bits 7..4: 1..15, higher starts faster."""
    signal_loss_rate: int
    """Set_5 bits 3..0: 1..15, higher cuts the throttle faster on signal loss."""


@dataclass(frozen=True, slots=True)
class MsgExp8:
    """MSG_EXP8 (20060): lifetime counters, u16 each."""

    power_on_count: int
    start_count: int
    stop_count: int
    """Normal stops."""


@dataclass(frozen=True, slots=True)
class MsgExp9:
    """MSG_EXP9 (20061): total run time and self-test fault code 1."""

    total_run_time_s: int
    """u32 seconds."""
    self_test_fault: SelfTestFault | int
    """u16; a code the seed does not list stays a plain int."""


@dataclass(frozen=True, slots=True)
class MsgExp10:
    """MSG_EXP10 (20062): this run's time and self-test fault code 2."""

    run_time_s: int
    """u32 seconds since power-up."""
    fault_code_2: int
    """u16; the seed defines no codes (0 is a pass)."""


@dataclass(frozen=True, slots=True)
class MsgExp11:
    """MSG_EXP11 (20063): temperatures in °C (u8 each); on the wire MOS, MCU, capacitor, motor."""

    mos_temp_c: int
    mcu_temp_c: int
    capacitor_temp_c: int
    motor_temp_c: int


@dataclass(frozen=True, slots=True)
class MsgExp12:
    """MSG_EXP12 (20064): one maximum-temperature record, sent once per read request.

    Its tail byte is ``0xC0 | kind``, so the frame has no transfer ID of its own.
    """

    kind: TempRecordKind
    max_temp_c: int
    """u8 °C."""
    run_count: int
    """u16: the run in which the maximum was reached."""
    run_time_s: int
    """u32 seconds into that run (the seed gives no unit; seconds as elsewhere)."""


@dataclass(frozen=True, slots=True)
class RawCommand14b:
    """RawCommand_14b (20100): channels 1..4, 0..2000 each, UAVCAN v0 bit order (§1.4)."""

    throttles: tuple[int, int, int, int]


@dataclass(frozen=True, slots=True)
class RawCommand12b:
    """RawCommand_12b (20101): channels 4 * group - 3 .. 4 * group, 0..2000 each."""

    group: int
    """1..5."""
    throttles: tuple[int, int, int, int]


@dataclass(frozen=True, slots=True)
class RawCommand10b:
    """RawCommand_10b (20102): channels 1..6, 0..1000 each (the ESC doubles them)."""

    throttles: tuple[int, int, int, int, int, int]


# --------------------------------------------------------------------------------------------
# Service records: requests come from the host, responses from the addressed ESC


@dataclass(frozen=True, slots=True)
class _SetId:
    node_id: int
    """1..0x7D."""
    throttle_channel: int
    """The RawCommand channel to follow, 1..20."""


@dataclass(frozen=True, slots=True)
class SetIdRequest(_SetId):
    """Set ID (210). The ESC ignores the destination: only one ESC may be on the bus, and only
    in its first 120 s after power-up. Saved to flash."""


@dataclass(frozen=True, slots=True)
class SetIdResponse(_SetId):
    """Set ID (210) response: the values set."""


@dataclass(frozen=True, slots=True)
class _SetBaud:
    baud_code: int
    """0..6, an index into :data:`BAUD_RATES_BPS`."""


@dataclass(frozen=True, slots=True)
class SetBaudRequest(_SetBaud):
    """Set Baud (211): first 120 s after power-up only; applies after a power cycle."""


@dataclass(frozen=True, slots=True)
class SetBaudResponse(_SetBaud):
    """Set Baud (211) response: the code set."""


@dataclass(frozen=True, slots=True)
class _SetLed:
    save: bool
    """Save to flash as the default (else lost at power-off)."""
    color: LedColor
    """0..7 on encode."""
    blink_hz: int
    """0 (steady), 1, 2 or 5 Hz."""


@dataclass(frozen=True, slots=True)
class SetLedRequest(_SetLed):
    """Set LED (212): only while reports are enabled (not paused by MSGControl)."""


@dataclass(frozen=True, slots=True)
class SetLedResponse(_SetLed):
    """Set LED (212) response: the values set."""


@dataclass(frozen=True, slots=True)
class _SetRotation:
    rotation: Rotation | int


@dataclass(frozen=True, slots=True)
class SetRotationRequest(_SetRotation):
    """Set Rotation (213): motor stopped, reports enabled; saved to flash."""


@dataclass(frozen=True, slots=True)
class SetRotationResponse(_SetRotation):
    """Set Rotation (213) response: the direction now set (also the answer to a query)."""


@dataclass(frozen=True, slots=True)
class _SetFreq:
    write: bool
    """True: set the intervals; False: read them (the ESC ignores the values sent)."""
    msg1_interval_ms: int
    msg2_interval_ms: int
    msg3_interval_ms: int


@dataclass(frozen=True, slots=True)
class SetFreqRequest(_SetFreq):
    """Set/Get Freq (214): MSG1..3 report intervals, 20..500 ms in 2 ms steps for a write.

    Factory values are 20, 100 and 500 ms; the ESC ignores a write outside the range.
    """


@dataclass(frozen=True, slots=True)
class SetFreqResponse(_SetFreq):
    """Set/Get Freq (214) response: the intervals now in use."""


@dataclass(frozen=True, slots=True)
class _ThrottleSelect:
    source: ThrottleSource | int


@dataclass(frozen=True, slots=True)
class ThrottleSelectRequest(_ThrottleSelect):
    """Throttle Select (215): at zero throttle only; saved to flash."""


@dataclass(frozen=True, slots=True)
class ThrottleSelectResponse(_ThrottleSelect):
    """Throttle Select (215) response: the source now set."""


@dataclass(frozen=True, slots=True)
class SelfTestRequest:
    """Self Test (216): ask for the power-on self-test result (empty payload)."""


@dataclass(frozen=True, slots=True)
class SelfTestResponse:
    """Self Test (216) response."""

    passed: bool
    """Status byte 0 (pass); any other value is a failure (the seed defines 1)."""


@dataclass(frozen=True, slots=True)
class ExpandSetRequest:
    """Expand Set (222): one setting per command, motor stopped; no response, the motor beeps."""

    command: ExpandSetCommand | int
    part: int
    """The argument; the allowed values depend on the command (seed 4.4.25)."""


@dataclass(frozen=True, slots=True)
class EscInfoRequest:
    """ESC Information (240) request."""

    option: int = 0


@dataclass(frozen=True, slots=True)
class EscInfoResponse:
    """ESC Information (240) response: hardware limits and firmware identity (u8 each)."""

    max_cells: int
    """Highest supported battery voltage, in Li-ion cells (S)."""
    max_current_a: int
    """Current rating, 0..2550 A in 10 A steps."""
    hardware_version: int
    protocol_version: int
    firmware_year: int
    """The byte as sent; the seed does not say from which year it counts."""
    firmware_month: int
    firmware_day: int


@dataclass(frozen=True, slots=True)
class MaintenanceRequest:
    """Maintenance Information (241): option 0, 1 or 2 selects the response record."""

    option: int


@dataclass(frozen=True, slots=True)
class Maintenance0Response:
    """Maintenance Information (241) response to option 0: lifetime run time and maxima."""

    total_run_time_s: int
    """u32 seconds."""
    max_mos_temp_c: int
    max_capacitor_temp_c: int


@dataclass(frozen=True, slots=True)
class Maintenance1Response:
    """Maintenance Information (241) response to option 1: this run."""

    run_time_s: int
    """u32 seconds since power-up."""
    run_count: int
    """u16."""


@dataclass(frozen=True, slots=True)
class Maintenance2Response:
    """Maintenance Information (241) response to option 2: counters and self-test result."""

    power_on_count: int
    stop_count: int
    self_test_fault: SelfTestFault | int
    """u16 fault code 1; a code the seed does not list stays a plain int."""


@dataclass(frozen=True, slots=True)
class MajorConfigRequest:
    """Get Major Configuration (242) request; the seed says the option names the ESC type."""

    option: int = 0


@dataclass(frozen=True, slots=True)
class MajorConfigResponse:
    """Get Major Configuration (242) response: the main settings in one frame (seed 4.4.28)."""

    direction_reversed: bool
    throttle_source: ThrottleSource
    throttle_channel: int
    """6 bits: 0..63 on the wire, 1..20 in practice."""
    led_blink_hz: int
    """5 bits; presumably the Set LED blink setting (0 steady, 1, 2 or 5 Hz)."""
    led_color: LedColor
    """3 bits."""
    msg1_interval_ms: int
    msg2_interval_ms: int
    msg3_interval_ms: int


CkescMessage: TypeAlias = (
    CanTestRequest
    | CanTestReport
    | MsgControlRequest
    | MsgControlAck
    | GetEscIdRequest
    | GetEscIdAnswer
    | Msg1
    | Msg2
    | Msg3
    | MsgExp1
    | MsgExp2
    | MsgExp3
    | MsgExp4
    | MsgExp5
    | MsgExp6
    | MsgExp7
    | MsgExp8
    | MsgExp9
    | MsgExp10
    | MsgExp11
    | MsgExp12
    | RawCommand14b
    | RawCommand12b
    | RawCommand10b
    | SetIdRequest
    | SetIdResponse
    | SetBaudRequest
    | SetBaudResponse
    | SetLedRequest
    | SetLedResponse
    | SetRotationRequest
    | SetRotationResponse
    | SetFreqRequest
    | SetFreqResponse
    | ThrottleSelectRequest
    | ThrottleSelectResponse
    | SelfTestRequest
    | SelfTestResponse
    | ExpandSetRequest
    | EscInfoRequest
    | EscInfoResponse
    | MaintenanceRequest
    | Maintenance0Response
    | Maintenance1Response
    | Maintenance2Response
    | MajorConfigRequest
    | MajorConfigResponse
)
"""Every CKESC payload record."""


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
    message: CkescMessage

    @property
    def node_id(self) -> int:
        """The ESC this frame is from or to: a request's destination, else the source."""
        if self.destination_node is not None and _CODECS_BY_RECORD[type(self.message)].from_host:
            return self.destination_node
        return self.source_node


# --------------------------------------------------------------------------------------------
# The frame type table (PROTOCOLS.md §1.3) and each type's payload layout, type by type.
# An ``unpack`` takes the whole CAN data (its length already checked) and returns the record;
# a ``pack`` checks the record and returns the payload before the tail byte (the whole data for
# the two types without a transfer ID). The registration rows are left unformatted so that each
# reads as a table row: record, type ID, sender, DLC (tail byte included), priority, codec.

_R = TypeVar("_R")
_Unpack: TypeAlias = Callable[[_Buf], CkescMessage]
_Pack: TypeAlias = Callable[[Any], bytes]


@dataclass(frozen=True, slots=True)
class _Codec:
    name: str
    """For error messages: the record and its type ID, e.g. "Msg1 (20050)"."""
    type_id: int
    service: bool
    from_host: bool
    """Message frame: sent by the host (RawCommand, requests). Service frame: a request."""
    dlc: int
    priority: int
    """The seed's priority for the type."""
    unpack: _Unpack
    pack: _Pack
    has_transfer_id: bool
    """False: no transfer ID in the tail byte, and ``pack`` returns the whole data."""


_CODECS_BY_RECORD: Final[dict[type, _Codec]] = {}
# Keyed by plain ints so that a look-up allocates nothing. Messages: ``type_id << 1 | (source
# != host)``; a type sent one way only answers both keys, a type sent both ways has a record
# per direction. Services: ``service_type << 1 | is_request``.
_MESSAGE_CODECS: Final[dict[int, _Codec]] = {}
_SERVICE_CODECS: Final[dict[int, _Codec]] = {}

_HOST, _ESC = True, False
_REQUEST, _RESPONSE = True, False
_HIGHEST, _MEDIUM, _LOW, _LOWEST = PRIORITY_HIGHEST, PRIORITY_MEDIUM, PRIORITY_LOW, PRIORITY_LOWEST


def _message(
    record: type[CkescMessage],
    type_id: int,
    from_host: bool,
    dlc: int,
    priority: int,
    unpack: _Unpack,
    pack: _Pack,
    has_transfer_id: bool = True,
) -> None:
    name = f"{record.__name__} ({type_id})"
    codec = _Codec(name, type_id, False, from_host, dlc, priority, unpack, pack, has_transfer_id)
    _CODECS_BY_RECORD[record] = codec
    _MESSAGE_CODECS[type_id << 1 | (not from_host)] = codec
    _MESSAGE_CODECS.setdefault(type_id << 1 | from_host, codec)


def _service(
    record: type[CkescMessage],
    service_type: int,
    request: bool,
    dlc: int,
    priority: int,
    unpack: _Unpack,
    pack: _Pack,
) -> None:
    name = f"{record.__name__} ({service_type})"
    codec = _Codec(name, service_type, True, request, dlc, priority, unpack, pack, True)
    _CODECS_BY_RECORD[record] = codec
    _SERVICE_CODECS.setdefault(service_type << 1 | request, codec)


def _plain(
    record: Callable[..., _R], fmt: str, **fields: _Allowed
) -> tuple[Callable[[_Buf], _R], _Pack]:
    """Codec for a record of int fields in wire order; ``fields`` gives each one's range."""
    layout = struct.Struct(fmt)
    checks = tuple(fields.items())

    def unpack(data: _Buf) -> _R:
        return record(*layout.unpack_from(data))

    def pack(message: Any) -> bytes:
        return layout.pack(*[_field(message, name, allowed) for name, allowed in checks])

    return unpack, pack


# ---- CANTest, MSGControl and GET_ESC_ID: the host's request from node 0, answers from ESCs

_S_OPTION_U32 = struct.Struct("<BI")


def _unpack_can_test_request(data: _Buf) -> CanTestRequest:
    option, count = _S_OPTION_U32.unpack_from(data)
    return CanTestRequest(_CAN_TEST_OPTIONS.get(option, option), count)


def _pack_can_test_request(message: CanTestRequest) -> bytes:
    option = _field(message, "option", _HOST_CAN_TEST_OPTIONS)
    return _S_OPTION_U32.pack(option, _field(message, "count", _U32))


def _unpack_can_test_report(data: _Buf) -> CanTestReport:
    option, count = _S_OPTION_U32.unpack_from(data)
    return CanTestReport(count, _CAN_TEST_OPTIONS.get(option, option))


def _pack_can_test_report(message: CanTestReport) -> bytes:
    return _S_OPTION_U32.pack(_field(message, "option", _U8), _field(message, "count", _U32))


def _unpack_msg_control_request(data: _Buf) -> MsgControlRequest:
    option, command = _S_OPTION_U32.unpack_from(data)
    return MsgControlRequest(_MSG_CONTROL_COMMANDS.get(command, command), option)


def _pack_msg_control_request(message: MsgControlRequest) -> bytes:
    command = _field(message, "command", _HOST_MSG_CONTROL_COMMANDS)
    return _S_OPTION_U32.pack(_field(message, "option", _U8), command)


def _unpack_msg_control_ack(data: _Buf) -> MsgControlAck:
    option, command = _S_OPTION_U32.unpack_from(data)
    return MsgControlAck(_MSG_CONTROL_COMMANDS.get(command, command), option)


def _pack_msg_control_ack(message: MsgControlAck) -> bytes:
    return _S_OPTION_U32.pack(_field(message, "option", _U8), _field(message, "command", _U32))


# fmt: off
_message(CanTestRequest, TYPE_CAN_TEST, _HOST, 6, _LOWEST,
         _unpack_can_test_request, _pack_can_test_request)
_message(CanTestReport, TYPE_CAN_TEST, _ESC, 6, _LOWEST,
         _unpack_can_test_report, _pack_can_test_report)
_message(MsgControlRequest, TYPE_MSG_CONTROL, _HOST, 6, _MEDIUM,
         _unpack_msg_control_request, _pack_msg_control_request)
_message(MsgControlAck, TYPE_MSG_CONTROL, _ESC, 6, _MEDIUM,
         _unpack_msg_control_ack, _pack_msg_control_ack)
_message(GetEscIdRequest, TYPE_GET_ESC_ID, _HOST, 2, _MEDIUM,
         *_plain(GetEscIdRequest, "<B", option=_U8))
_message(GetEscIdAnswer, TYPE_GET_ESC_ID, _ESC, 3, _MEDIUM,
         *_plain(GetEscIdAnswer, "<BB", node_id=_ESC_NODE, throttle_channel=_CHANNEL))
# fmt: on

# ---- Telemetry: MSG1..3, MSG_EXP1..12

_S_MSG1 = struct.Struct("<HHH")
_S_MSG2 = struct.Struct("<HHB")


def _unpack_msg1(data: _Buf) -> Msg1:
    speed, throttle, status = _S_MSG1.unpack_from(data)
    return Msg1(speed, throttle, Msg1Status(status))


def _pack_msg1(message: Msg1) -> bytes:
    return _S_MSG1.pack(
        _field(message, "speed_rpm", _U16),
        _field(message, "throttle", _THROTTLE),
        _field(message, "status", _U16),
    )


def _unpack_msg2(data: _Buf) -> Msg2:
    voltage, current, mos_temp = _S_MSG2.unpack_from(data)
    return Msg2(voltage / 100, current / 100, mos_temp)


def _pack_msg2(message: Msg2) -> bytes:
    return _S_MSG2.pack(
        _field_centi(message, "voltage_v"),
        _field_centi(message, "current_a"),
        _field(message, "mos_temp_c", _U8),
    )


def _unpack_exp1(data: _Buf) -> MsgExp1:
    speed, voltage, current = _S_MSG1.unpack_from(data)
    return MsgExp1(speed, voltage / 100, current / 100)


def _pack_exp1(message: MsgExp1) -> bytes:
    return _S_MSG1.pack(
        _field(message, "speed_rpm", _U16),
        _field_centi(message, "voltage_v"),
        _field_centi(message, "current_a"),
    )


def _debug_data(record: Callable[[bytes], _R]) -> tuple[Callable[[_Buf], _R], _Pack]:
    def unpack(data: _Buf) -> _R:
        return record(bytes(data[:6]))

    def pack(message: _DebugData) -> bytes:
        if isinstance(message.data, bytes) and len(message.data) == 6:
            return message.data
        raise ValueRangeError(
            f"{type(message).__name__}.data = {message.data!r} is not 6 bytes of debug data"
        )

    return unpack, pack


# MSG_EXP7's nibbles in wire order: Set_0 low, Set_0 high, Set_1 low, ... (None: reserved).
_EXP7_NIBBLES = (
    "motor_direction",
    "led",
    "throttle_interface",
    None,
    "active_freewheeling",
    "timing",
    "timing_2",
    "load_type",
    "prop_lock",
    "startup_acceleration",
    "signal_loss_rate",
    None,
)


def _unpack_exp7(data: _Buf) -> MsgExp7:
    s0, s1, s2, s3, s4, s5 = data[:6]
    return MsgExp7(
        s0 & 0xF,
        s0 >> 4,
        s1 & 0xF,
        s2 & 0xF,
        s2 >> 4,
        s3 & 0xF,
        s3 >> 4,
        s4 & 0xF,
        s4 >> 4,
        s5 & 0xF,
    )


def _pack_exp7(message: MsgExp7) -> bytes:
    nibbles = [0 if name is None else _field(message, name, _NIBBLE) for name in _EXP7_NIBBLES]
    return bytes(low | high << 4 for low, high in zip(nibbles[::2], nibbles[1::2], strict=True))


_S_EXP9 = struct.Struct("<IH")


def _unpack_exp9(data: _Buf) -> MsgExp9:
    run_time, fault = _S_EXP9.unpack_from(data)
    return MsgExp9(run_time, _SELF_TEST_FAULTS.get(fault, fault))


def _pack_exp9(message: MsgExp9) -> bytes:
    return _S_EXP9.pack(
        _field(message, "total_run_time_s", _U32), _field(message, "self_test_fault", _U16)
    )


_S_EXP12 = struct.Struct("<BHIB")


def _unpack_exp12(data: _Buf) -> MsgExp12:
    max_temp, run_count, run_time, tail = _S_EXP12.unpack_from(data)
    kind = _TEMP_RECORD_KINDS.get(tail ^ 0xC0)
    if kind is None:
        raise TailByteError(
            f"MsgExp12 ({TYPE_MSG_EXP12}): tail byte 0x{tail:02X} names no temperature record"
            " (expected 0xC1 MCU, 0xC2 MOS, 0xC3 capacitor or 0xC4 motor)"
        )
    return MsgExp12(kind, max_temp, run_count, run_time)


def _pack_exp12(message: MsgExp12) -> bytes:
    return _S_EXP12.pack(
        _field(message, "max_temp_c", _U8),
        _field(message, "run_count", _U16),
        _field(message, "run_time_s", _U32),
        0xC0 | _field(message, "kind", _TEMP_RECORD_KIND_VALUES),
    )


# fmt: off
_message(Msg1, TYPE_MSG1, _ESC, 7, _LOWEST, _unpack_msg1, _pack_msg1)
_message(Msg2, TYPE_MSG2, _ESC, 6, _LOWEST, _unpack_msg2, _pack_msg2)
_message(Msg3, TYPE_MSG3, _ESC, 8, _LOWEST,
         *_plain(Msg3, "<BBBBxxx",
                 mos_temp_c=_U8, capacitor_temp_c=_U8, motor_temp_c=_U8, mcu_temp_c=_U8))
_message(MsgExp1, TYPE_MSG_EXP1, _ESC, 7, _LOWEST, _unpack_exp1, _pack_exp1)
_message(MsgExp2, TYPE_MSG_EXP2, _ESC, 7, _LOWEST, *_debug_data(MsgExp2))
_message(MsgExp3, TYPE_MSG_EXP3, _ESC, 7, _LOWEST, *_debug_data(MsgExp3))
_message(MsgExp4, TYPE_MSG_EXP4, _ESC, 7, _LOWEST, *_debug_data(MsgExp4))
_message(MsgExp5, TYPE_MSG_EXP5, _ESC, 7, _LOWEST, *_debug_data(MsgExp5))
_message(MsgExp6, TYPE_MSG_EXP6, _ESC, 7, _LOWEST, *_debug_data(MsgExp6))
_message(MsgExp7, TYPE_MSG_EXP7, _ESC, 7, _LOWEST, _unpack_exp7, _pack_exp7)
_message(MsgExp8, TYPE_MSG_EXP8, _ESC, 7, _LOWEST,
         *_plain(MsgExp8, "<HHH", power_on_count=_U16, start_count=_U16, stop_count=_U16))
_message(MsgExp9, TYPE_MSG_EXP9, _ESC, 7, _LOWEST, _unpack_exp9, _pack_exp9)
_message(MsgExp10, TYPE_MSG_EXP10, _ESC, 7, _LOWEST,
         *_plain(MsgExp10, "<IH", run_time_s=_U32, fault_code_2=_U16))
_message(MsgExp11, TYPE_MSG_EXP11, _ESC, 7, _LOWEST,
         *_plain(MsgExp11, "<BBBBxx",
                 mos_temp_c=_U8, mcu_temp_c=_U8, capacitor_temp_c=_U8, motor_temp_c=_U8))
_message(MsgExp12, TYPE_MSG_EXP12, _ESC, 8, _LOWEST,
         _unpack_exp12, _pack_exp12, has_transfer_id=False)
# fmt: on

# ---- Throttle commands (§1.4). The ``_bits_*`` helpers are shared with the hot-path encoders
# at the end of the module; each takes 1..n throttles and sends the missing channels as 0.


def _count_error(command: str, throttles: Sequence[int], most: int) -> ValueRangeError:
    return ValueRangeError(f"{command} takes 1..{most} throttles, got {len(throttles)}")


def _throttle_error(command: str, throttles: Sequence[int], allowed: range) -> ValueRangeError:
    """The error for the first throttle outside ``allowed`` (the caller has seen one)."""
    index, throttle = next(
        (index, throttle)
        for index, throttle in enumerate(throttles)
        if not (isinstance(throttle, int) and throttle in allowed)
    )
    return ValueRangeError(
        f"{command} throttles[{index}] = {throttle!r} is not {_describe(allowed)}"
    )


def _bits_14b(throttles: Sequence[int]) -> int:
    """Channels 1..4 as the 56-bit UAVCAN v0 stream, its first bit the integer's top bit.

    Each channel is an int14 written as its low 8 bits, then its high 6 bits, MSB first.
    """
    if not 1 <= len(throttles) <= CHANNELS_PER_GROUP:
        raise _count_error("RawCommand14b", throttles, CHANNELS_PER_GROUP)
    bits = 0
    for throttle in throttles:
        if not 0 <= throttle <= THROTTLE_MAX:
            raise _throttle_error("RawCommand14b", throttles, _THROTTLE)
        bits = bits << 14 | (throttle & 0xFF) << 6 | throttle >> 8
    return bits << 14 * (CHANNELS_PER_GROUP - len(throttles))


def _bits_12b(throttles: Sequence[int]) -> int:
    """Up to four channels, 12 bits each, the first in the lowest bits."""
    if not 1 <= len(throttles) <= CHANNELS_PER_GROUP:
        raise _count_error("RawCommand12b", throttles, CHANNELS_PER_GROUP)
    bits = 0
    shift = 0
    for throttle in throttles:
        if not 0 <= throttle <= THROTTLE_MAX:
            raise _throttle_error("RawCommand12b", throttles, _THROTTLE)
        bits |= throttle << shift
        shift += 12
    return bits


def _bits_10b(throttles: Sequence[int]) -> int:
    """Up to six channels, 10 bits each, the first in the lowest bits."""
    if not 1 <= len(throttles) <= 6:
        raise _count_error("RawCommand10b", throttles, 6)
    bits = 0
    shift = 0
    for throttle in throttles:
        if not 0 <= throttle <= THROTTLE_10B_MAX:
            raise _throttle_error("RawCommand10b", throttles, _THROTTLE_10B)
        bits |= throttle << shift
        shift += 10
    return bits


def _record_throttles(
    message: RawCommand14b | RawCommand12b | RawCommand10b, count: int, allowed: range
) -> tuple[int, ...]:
    """A record's throttles, checked: exactly ``count``, as the record stands for every channel."""
    throttles = message.throttles
    what = f"{type(message).__name__}.throttles"
    if not (isinstance(throttles, tuple) and len(throttles) == count):
        raise ValueRangeError(f"{what} = {throttles!r} is not a tuple of {count} throttles")
    for index, throttle in enumerate(throttles):
        _check(f"{what}[{index}]", throttle, allowed)
    return throttles


def _unpack_raw_14b(data: _Buf) -> RawCommand14b:
    bits = int.from_bytes(data, "big") >> 8  # drop the tail byte
    # Each 14-bit chunk holds a channel's low 8 bits above its high 6 bits.
    c1, c2, c3, c4 = (bits >> shift & 0x3FFF for shift in (42, 28, 14, 0))
    return RawCommand14b(
        (
            c1 >> 6 | (c1 & 0x3F) << 8,
            c2 >> 6 | (c2 & 0x3F) << 8,
            c3 >> 6 | (c3 & 0x3F) << 8,
            c4 >> 6 | (c4 & 0x3F) << 8,
        )
    )


def _pack_raw_14b(message: RawCommand14b) -> bytes:
    return _bits_14b(_record_throttles(message, 4, _THROTTLE)).to_bytes(7, "big")


def _unpack_raw_12b(data: _Buf) -> RawCommand12b:
    bits = int.from_bytes(data, "little")
    return RawCommand12b(
        bits >> 48 & 0xFF,
        (bits & 0xFFF, bits >> 12 & 0xFFF, bits >> 24 & 0xFFF, bits >> 36 & 0xFFF),
    )


def _pack_raw_12b(message: RawCommand12b) -> bytes:
    bits = (
        _bits_12b(_record_throttles(message, 4, _THROTTLE)) | _field(message, "group", _GROUP) << 48
    )
    return bits.to_bytes(7, "little")


def _unpack_raw_10b(data: _Buf) -> RawCommand10b:
    # The top four bits of byte 7 are unused.
    bits = int.from_bytes(data, "little")
    return RawCommand10b(
        (
            bits & 0x3FF,
            bits >> 10 & 0x3FF,
            bits >> 20 & 0x3FF,
            bits >> 30 & 0x3FF,
            bits >> 40 & 0x3FF,
            bits >> 50 & 0x3FF,
        )
    )


def _pack_raw_10b(message: RawCommand10b) -> bytes:
    return _bits_10b(_record_throttles(message, 6, _THROTTLE_10B)).to_bytes(8, "little")


# fmt: off
_message(RawCommand14b, TYPE_RAW_COMMAND_14B, _HOST, 8, _HIGHEST, _unpack_raw_14b, _pack_raw_14b)
_message(RawCommand12b, TYPE_RAW_COMMAND_12B, _HOST, 8, _HIGHEST, _unpack_raw_12b, _pack_raw_12b)
_message(RawCommand10b, TYPE_RAW_COMMAND_10B, _HOST, 8, _HIGHEST,
         _unpack_raw_10b, _pack_raw_10b, has_transfer_id=False)
# fmt: on

# ---- Configuration services 210..222. Most responses repeat the request's layout.

_SET_ID_FIELDS = {"node_id": _ESC_NODE, "throttle_channel": _CHANNEL}
_S_3U8 = struct.Struct("<BBB")
_S_SET_FREQ = struct.Struct("<BBBB")


def _set_led(record: Callable[[bool, LedColor, int], _R]) -> tuple[Callable[[_Buf], _R], _Pack]:
    def unpack(data: _Buf) -> _R:
        save, color, blink = _S_3U8.unpack_from(data)
        return record(bool(save), LedColor(color), blink)

    def pack(message: _SetLed) -> bytes:
        return _S_3U8.pack(
            _field(message, "save", _BOOL),
            _field(message, "color", _LED_RGB),
            _field(message, "blink_hz", _BLINK_HZ),
        )

    return unpack, pack


def _set_rotation(record: Callable[[Rotation | int], _R]) -> tuple[Callable[[_Buf], _R], _Pack]:
    def unpack(data: _Buf) -> _R:
        return record(_ROTATIONS.get(data[0], data[0]))

    def pack(message: _SetRotation) -> bytes:
        return bytes((_field(message, "rotation", _ROTATION_VALUES),))

    return unpack, pack


def _set_freq(
    record: Callable[[bool, int, int, int], _R], write_range: range
) -> tuple[Callable[[_Buf], _R], _Pack]:
    """``write_range``: the intervals a write may carry (a read's are ignored by the ESC)."""

    def unpack(data: _Buf) -> _R:
        write, msg1, msg2, msg3 = _S_SET_FREQ.unpack_from(data)
        return record(bool(write), 2 * msg1, 2 * msg2, 2 * msg3)

    def pack(message: _SetFreq) -> bytes:
        write = _field(message, "write", _BOOL)
        allowed = write_range if write else _INTERVAL_MS
        return _S_SET_FREQ.pack(
            write,
            _field_stepped(message, "msg1_interval_ms", allowed),
            _field_stepped(message, "msg2_interval_ms", allowed),
            _field_stepped(message, "msg3_interval_ms", allowed),
        )

    return unpack, pack


def _throttle_select(
    record: Callable[[ThrottleSource | int], _R],
) -> tuple[Callable[[_Buf], _R], _Pack]:
    def unpack(data: _Buf) -> _R:
        return record(_THROTTLE_SOURCES.get(data[0], data[0]))

    def pack(message: _ThrottleSelect) -> bytes:
        return bytes((_field(message, "source", _THROTTLE_SOURCE_VALUES),))

    return unpack, pack


def _unpack_self_test_request(data: _Buf) -> SelfTestRequest:
    return SelfTestRequest()


def _pack_self_test_request(message: SelfTestRequest) -> bytes:
    return b""


def _unpack_self_test_response(data: _Buf) -> SelfTestResponse:
    return SelfTestResponse(data[0] == 0)


def _pack_self_test_response(message: SelfTestResponse) -> bytes:
    return bytes((0 if _field(message, "passed", _BOOL) else 1,))


_S_EXPAND_SET = struct.Struct("<HB")


def _unpack_expand_set(data: _Buf) -> ExpandSetRequest:
    command, part = _S_EXPAND_SET.unpack_from(data)
    return ExpandSetRequest(_EXPAND_SET_COMMANDS.get(command, command), part)


def _pack_expand_set(message: ExpandSetRequest) -> bytes:
    command = _field(message, "command", _EXPAND_SET_VALUES)
    what = f"ExpandSetRequest.part (for {ExpandSetCommand(command).name})"
    return _S_EXPAND_SET.pack(command, _check(what, message.part, _EXPAND_SET_PARTS[command]))


# fmt: off
_service(SetIdRequest, SERVICE_SET_ID, _REQUEST, 3, _MEDIUM,
         *_plain(SetIdRequest, "<BB", **_SET_ID_FIELDS))
_service(SetIdResponse, SERVICE_SET_ID, _RESPONSE, 3, _MEDIUM,
         *_plain(SetIdResponse, "<BB", **_SET_ID_FIELDS))
_service(SetBaudRequest, SERVICE_SET_BAUD, _REQUEST, 2, _MEDIUM,
         *_plain(SetBaudRequest, "<B", baud_code=_BAUD_CODE))
_service(SetBaudResponse, SERVICE_SET_BAUD, _RESPONSE, 2, _MEDIUM,
         *_plain(SetBaudResponse, "<B", baud_code=_BAUD_CODE))
_service(SetLedRequest, SERVICE_SET_LED, _REQUEST, 4, _LOW, *_set_led(SetLedRequest))
_service(SetLedResponse, SERVICE_SET_LED, _RESPONSE, 4, _LOW, *_set_led(SetLedResponse))
_service(SetRotationRequest, SERVICE_SET_ROTATION, _REQUEST, 2, _LOW,
         *_set_rotation(SetRotationRequest))
_service(SetRotationResponse, SERVICE_SET_ROTATION, _RESPONSE, 2, _LOW,
         *_set_rotation(SetRotationResponse))
_service(SetFreqRequest, SERVICE_SET_FREQ, _REQUEST, 5, _MEDIUM,
         *_set_freq(SetFreqRequest, _INTERVAL_WRITE_MS))
# A response reports whatever intervals the ESC has.
_service(SetFreqResponse, SERVICE_SET_FREQ, _RESPONSE, 5, _MEDIUM,
         *_set_freq(SetFreqResponse, _INTERVAL_MS))
_service(ThrottleSelectRequest, SERVICE_THROTTLE_SELECT, _REQUEST, 2, _MEDIUM,
         *_throttle_select(ThrottleSelectRequest))
_service(ThrottleSelectResponse, SERVICE_THROTTLE_SELECT, _RESPONSE, 2, _MEDIUM,
         *_throttle_select(ThrottleSelectResponse))
_service(SelfTestRequest, SERVICE_SELF_TEST, _REQUEST, 1, _LOWEST,
         _unpack_self_test_request, _pack_self_test_request)
_service(SelfTestResponse, SERVICE_SELF_TEST, _RESPONSE, 2, _LOWEST,
         _unpack_self_test_response, _pack_self_test_response)
_service(ExpandSetRequest, SERVICE_EXPAND_SET, _REQUEST, 4, _MEDIUM,
         _unpack_expand_set, _pack_expand_set)
# fmt: on

# ---- Information services 240..242: a one-byte request, a seven-byte response

_S_ESC_INFO = struct.Struct("<7B")
_S_MAINTENANCE_0 = struct.Struct("<IBBB")
_S_MAINTENANCE_1 = struct.Struct("<IHB")
_S_MAINTENANCE_2 = struct.Struct("<HHHB")
_S_MAJOR_CONFIG = struct.Struct("<BBBBBxx")


def _unpack_esc_info(data: _Buf) -> EscInfoResponse:
    cells, current, hardware, protocol, year, month, day = _S_ESC_INFO.unpack_from(data)
    return EscInfoResponse(cells, 10 * current, hardware, protocol, year, month, day)


def _pack_esc_info(message: EscInfoResponse) -> bytes:
    return _S_ESC_INFO.pack(
        _field(message, "max_cells", _U8),
        _field_stepped(message, "max_current_a", _MAX_CURRENT_A),
        _field(message, "hardware_version", _U8),
        _field(message, "protocol_version", _U8),
        _field(message, "firmware_year", _U8),
        _field(message, "firmware_month", _U8),
        _field(message, "firmware_day", _U8),
    )


def _unpack_maintenance(
    data: _Buf,
) -> Maintenance0Response | Maintenance1Response | Maintenance2Response:
    # Byte 6 is taken to echo the request's option (see the module docstring).
    option = data[6]
    if option == 0:
        total, mos, capacitor, _ = _S_MAINTENANCE_0.unpack_from(data)
        return Maintenance0Response(total, mos, capacitor)
    if option == 1:
        run_time, runs, _ = _S_MAINTENANCE_1.unpack_from(data)
        return Maintenance1Response(run_time, runs)
    if option == 2:
        power_ons, stops, fault, _ = _S_MAINTENANCE_2.unpack_from(data)
        return Maintenance2Response(power_ons, stops, _SELF_TEST_FAULTS.get(fault, fault))
    raise FrameError(
        f"Maintenance Information ({SERVICE_MAINTENANCE}) response: option (byte 6) = {option},"
        " expected 0, 1 or 2"
    )


def _pack_maintenance_0(message: Maintenance0Response) -> bytes:
    return _S_MAINTENANCE_0.pack(
        _field(message, "total_run_time_s", _U32),
        _field(message, "max_mos_temp_c", _U8),
        _field(message, "max_capacitor_temp_c", _U8),
        0,
    )


def _pack_maintenance_1(message: Maintenance1Response) -> bytes:
    return _S_MAINTENANCE_1.pack(
        _field(message, "run_time_s", _U32), _field(message, "run_count", _U16), 1
    )


def _pack_maintenance_2(message: Maintenance2Response) -> bytes:
    return _S_MAINTENANCE_2.pack(
        _field(message, "power_on_count", _U16),
        _field(message, "stop_count", _U16),
        _field(message, "self_test_fault", _U16),
        2,
    )


def _unpack_major_config(data: _Buf) -> MajorConfigResponse:
    throttle, led, msg1, msg2, msg3 = _S_MAJOR_CONFIG.unpack_from(data)
    return MajorConfigResponse(
        bool(throttle & 0x80),
        ThrottleSource(throttle >> 6 & 1),
        throttle & 0x3F,
        led >> 3,
        LedColor(led & 0x07),
        2 * msg1,
        2 * msg2,
        2 * msg3,
    )


def _pack_major_config(message: MajorConfigResponse) -> bytes:
    return _S_MAJOR_CONFIG.pack(
        _field(message, "direction_reversed", _BOOL) << 7
        | _field(message, "throttle_source", _THROTTLE_SOURCE_VALUES) << 6
        | _field(message, "throttle_channel", range(0x40)),
        _field(message, "led_blink_hz", range(0x20)) << 3 | _field(message, "led_color", _LED_RGB),
        _field_stepped(message, "msg1_interval_ms", _INTERVAL_MS),
        _field_stepped(message, "msg2_interval_ms", _INTERVAL_MS),
        _field_stepped(message, "msg3_interval_ms", _INTERVAL_MS),
    )


# fmt: off
_service(EscInfoRequest, SERVICE_ESC_INFO, _REQUEST, 2, _MEDIUM,
         *_plain(EscInfoRequest, "<B", option=_U8))
_service(EscInfoResponse, SERVICE_ESC_INFO, _RESPONSE, 8, _MEDIUM, _unpack_esc_info, _pack_esc_info)
_service(MaintenanceRequest, SERVICE_MAINTENANCE, _REQUEST, 2, _MEDIUM,
         *_plain(MaintenanceRequest, "<B", option=range(3)))
# The three responses share one decoder, which tells them apart by byte 6.
_service(Maintenance0Response, SERVICE_MAINTENANCE, _RESPONSE, 8, _MEDIUM,
         _unpack_maintenance, _pack_maintenance_0)
_service(Maintenance1Response, SERVICE_MAINTENANCE, _RESPONSE, 8, _MEDIUM,
         _unpack_maintenance, _pack_maintenance_1)
_service(Maintenance2Response, SERVICE_MAINTENANCE, _RESPONSE, 8, _MEDIUM,
         _unpack_maintenance, _pack_maintenance_2)
_service(MajorConfigRequest, SERVICE_MAJOR_CONFIG, _REQUEST, 2, _MEDIUM,
         *_plain(MajorConfigRequest, "<B", option=_U8))
_service(MajorConfigResponse, SERVICE_MAJOR_CONFIG, _RESPONSE, 8, _MEDIUM,
         _unpack_major_config, _pack_major_config)
# fmt: on


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
    """The priority the seed gives the record's frame type (PROTOCOLS.md §1.3).

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
