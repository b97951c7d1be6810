"""CKESC payload records: one frozen dataclass per message and service type
(docs/protocols.md §3.2, §3.6)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeAlias

from bridge.escs.ckesc._wire import (
    CanTestOption,
    ExpandSetCommand,
    LedColor,
    Msg1Status,
    MsgControlCommand,
    Rotation,
    SelfTestFault,
    TempRecordKind,
    ThrottleSource,
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
