"""CKESC's vocabulary: the protocol's constants, enumerations and one frozen record per message
and service type (docs/protocols.md §3.1, §3.2, §3.6); the package docstring describes the
protocol. Pure data: no I/O, clock or logging.

Longer than 600 lines on purpose: it is the protocol's table of types, one record per row of
§3.2 and §3.6 with the constants and enumerations its fields take; split, the table would only
be harder to read whole.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Final, TypeAlias, TypeVar, cast

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


# --------------------------------------------------------------------------------------------
# Records. One type per frame type; where several types carry the same fields (a service whose
# response repeats its request, the debug frames, the one-byte option requests), one dataclass
# of the fields and a type of it for each (:func:`_types`): the codec tells them apart by type.

_Fields = TypeVar("_Fields")


def _types(fields: type[_Fields], *names: str) -> tuple[type[_Fields], ...]:
    """A type of ``fields`` named each of ``names``: the same data, never equal to each other."""

    def named(name: str) -> type[_Fields]:
        namespace = {"__slots__": (), "__module__": fields.__module__}
        return cast("type[_Fields]", type(name, (fields,), namespace))

    return tuple(named(name) for name in names)


@dataclass(frozen=True, slots=True)
class OptionRequest:
    """A request of one option byte (0 unless the seed says otherwise): GET_ESC_ID (20013) from
    the host, which every ESC answers with its node ID and channel; ESC Information (240); Get
    Major Configuration (242), whose option the seed says names the ESC type."""

    option: int = 0


GetEscIdRequest, EscInfoRequest, MajorConfigRequest = _types(
    OptionRequest, "GetEscIdRequest", "EscInfoRequest", "MajorConfigRequest"
)


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
class DebugData:
    """MSG_EXP2..6 (20054..20058): vendor debug data, a type of it for each."""

    data: bytes
    """Six bytes of vendor debug data, kept raw."""


MsgExp2, MsgExp3, MsgExp4, MsgExp5, MsgExp6 = _types(
    DebugData, "MsgExp2", "MsgExp3", "MsgExp4", "MsgExp5", "MsgExp6"
)


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
    """RawCommand_14b (20100): channels 1..4, 0..2000 each, UAVCAN v0 bit order
    (docs/protocols.md §3.3)."""

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
class SetId:
    """Set ID (210). The ESC ignores the destination: only one ESC may be on the bus, and only
    in its first 120 s after power-up. Saved to flash; the response holds the values set."""

    node_id: int
    """1..0x7D."""
    throttle_channel: int
    """The RawCommand channel to follow, 1..20."""


SetIdRequest, SetIdResponse = _types(SetId, "SetIdRequest", "SetIdResponse")


@dataclass(frozen=True, slots=True)
class SetBaud:
    """Set Baud (211): first 120 s after power-up only; applies after a power cycle. The
    response holds the code set."""

    baud_code: int
    """0..6, an index into :data:`BAUD_RATES_BPS`."""


SetBaudRequest, SetBaudResponse = _types(SetBaud, "SetBaudRequest", "SetBaudResponse")


@dataclass(frozen=True, slots=True)
class SetLed:
    """Set LED (212): only while reports are enabled (not paused by MSGControl); the response
    holds the values set."""

    save: bool
    """Save to flash as the default (else lost at power-off)."""
    color: LedColor
    """0..7 on encode."""
    blink_hz: int
    """0 (steady), 1, 2 or 5 Hz."""


SetLedRequest, SetLedResponse = _types(SetLed, "SetLedRequest", "SetLedResponse")


@dataclass(frozen=True, slots=True)
class SetRotation:
    """Set Rotation (213): motor stopped, reports enabled; saved to flash. The response holds
    the direction now set (also the answer to a query)."""

    rotation: Rotation | int


SetRotationRequest, SetRotationResponse = _types(
    SetRotation, "SetRotationRequest", "SetRotationResponse"
)


@dataclass(frozen=True, slots=True)
class SetFreq:
    """Set/Get Freq (214): MSG1..3 report intervals, 20..500 ms in 2 ms steps for a write.

    Factory values are 20, 100 and 500 ms; the ESC ignores a write outside the range. The
    response holds the intervals now in use.
    """

    write: bool
    """True: set the intervals; False: read them (the ESC ignores the values sent)."""
    msg1_interval_ms: int
    msg2_interval_ms: int
    msg3_interval_ms: int


SetFreqRequest, SetFreqResponse = _types(SetFreq, "SetFreqRequest", "SetFreqResponse")


@dataclass(frozen=True, slots=True)
class ThrottleSelect:
    """Throttle Select (215): at zero throttle only; saved to flash. The response holds the
    source now set."""

    source: ThrottleSource | int


ThrottleSelectRequest, ThrottleSelectResponse = _types(
    ThrottleSelect, "ThrottleSelectRequest", "ThrottleSelectResponse"
)


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
    | OptionRequest
    | GetEscIdAnswer
    | Msg1
    | Msg2
    | Msg3
    | MsgExp1
    | DebugData
    | MsgExp7
    | MsgExp8
    | MsgExp9
    | MsgExp10
    | MsgExp11
    | MsgExp12
    | RawCommand14b
    | RawCommand12b
    | RawCommand10b
    | SetId
    | SetBaud
    | SetLed
    | SetRotation
    | SetFreq
    | ThrottleSelect
    | SelfTestRequest
    | SelfTestResponse
    | ExpandSetRequest
    | EscInfoResponse
    | MaintenanceRequest
    | Maintenance0Response
    | Maintenance1Response
    | Maintenance2Response
    | MajorConfigResponse
)
"""Every CKESC payload record."""
