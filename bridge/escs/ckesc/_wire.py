"""CKESC wire constants, enumerations and range checks (docs/protocols.md §3.1, §3.2, §3.6);
the package docstring describes the protocol. The CAN ID, tail byte and transfer IDs are UAVCAN
v0's, in :mod:`bridge.escs.uavcan_v0`."""

from __future__ import annotations

import enum
from typing import Final, TypeAlias, TypeVar

from bridge.errors import (
    ValueRangeError,
)
from bridge.escs.uavcan_v0 import MAX_NODE_ID, MAX_TRANSFER_ID, PRIORITY_LOWEST

# --------------------------------------------------------------------------------------------
# Protocol constants (docs/protocols.md §1.2, §3.1, §3.2, §3.6)

HOST_NODE_ID: Final = 0
"""The bridge's own node ID; every CKESC request and throttle command comes from node 0."""
FACTORY_NODE_ID: Final = 0x7D
"""An ESC's node ID as shipped; an ESC at this ID sends no telemetry."""

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
# Range checks shared by the encoders


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
