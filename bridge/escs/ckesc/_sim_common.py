"""The simulated CKESC's constants, its flash defaults, statistics and the frame helpers it
uses (:mod:`bridge.escs.ckesc.sim`)."""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

import can

from bridge.escs import ckesc
from bridge.escs.ckesc import (
    CkescMessage,
    EscInfoRequest,
    EscInfoResponse,
    ExpandSetCommand,
    LedColor,
    MaintenanceRequest,
    MajorConfigRequest,
    Msg1Status,
    MsgControlCommand,
    MsgExp2,
    MsgExp3,
    MsgExp4,
    MsgExp5,
    MsgExp6,
    SelfTestFault,
    SelfTestRequest,
    SetBaudRequest,
    SetFreqRequest,
    SetIdRequest,
    SetLedRequest,
    SetRotationRequest,
    TempRecordKind,
    ThrottleSelectRequest,
    ThrottleSource,
)

COMMS_TIMEOUT_S: Final = 0.200
"""No valid CAN throttle for this long: COMMS_FAULT, motor stopped (seed 4.4.4)."""
SET_ID_WINDOW_S: Final = 120.0
"""Set ID and Set Baud are accepted only this long after power-up (seed 4.3.2)."""
ALONE_WINDOW_S: Final = 1.0
"""Set ID is refused if another ESC was heard within this."""
ANSWER_DELAY_STEP_S: Final = 0.002
"""GET_ESC_ID answers and MSGControl acks wait (node_id % 32) times this (seed 4.4.2, 4.4.3)."""
MAX_STEP_S: Final = 0.050
"""The longest motor physics step one poll takes (a longer gap is not simulated)."""
CAN_TEST_INTERVAL_S: Final = 0.002
"""CANTest report interval in bus test mode (the seed says "continuously")."""
UNDER_VOLTAGE_PER_CELL_V: Final = 3.0
OVER_VOLTAGE_PER_CELL_V: Final = 4.35
CELL_DETECT_V: Final = 4.25
"""Cells = supply at first power / this, rounded up (a full LiPo cell is 4.2 V)."""
OVER_TEMPERATURE_C: Final = 110.0
"""MOSFET temperature above which OVER_TEMPERATURE is set."""
FAULT_MOS_TEMP_C: Final = 150
"""MOSFET temperature reported under the over_temperature fault."""
FAULT_CURRENT_A: Final = 600.0
"""Bus current reported under the over_current fault (fits the u16 x 0.01 A field)."""
ESC_INFO: Final = EscInfoResponse(
    max_cells=14,
    max_current_a=80,
    hardware_version=1,
    protocol_version=21,
    firmware_year=24,
    firmware_month=10,
    firmware_day=11,
)
"""What the simulated ESC says of itself (ESC Information, 240): a 14S 80 A ESC, protocol 2.1."""

# Float tolerance for clock comparisons: poll times built from 1 ms steps do not land exactly
# on 20 ms or 200 ms.
_EPS_S: Final = 1e-6
_U8_MAX: Final = 0xFF
_CENTI_MAX: Final = 655.35
_RECORD_KINDS: Final = {
    TempRecordKind.MCU: "mcu",
    TempRecordKind.MOS: "mos",
    TempRecordKind.CAPACITOR: "capacitor",
    TempRecordKind.MOTOR: "motor",
}

# Self-test fault code 1 -> MSG1 status bit.
_SELF_TEST_BITS: Final = {
    SelfTestFault.COM_LOW: Msg1Status.SELF_TEST_COM_INPUT_LOW,
    SelfTestFault.COM_HIGH: Msg1Status.SELF_TEST_COM_INPUT_HIGH,
    SelfTestFault.PHASE_A_HIGH: Msg1Status.SELF_TEST_PHASE_A_OUTPUT_HIGH,
    SelfTestFault.PHASE_B_HIGH: Msg1Status.SELF_TEST_PHASE_B_OUTPUT_HIGH,
    SelfTestFault.PHASE_C_HIGH: Msg1Status.SELF_TEST_PHASE_C_OUTPUT_HIGH,
    SelfTestFault.PHASE_A_LOW: Msg1Status.SELF_TEST_PHASE_A_OUTPUT_LOW,
    SelfTestFault.PHASE_B_LOW: Msg1Status.SELF_TEST_PHASE_B_OUTPUT_LOW,
    SelfTestFault.PHASE_C_LOW: Msg1Status.SELF_TEST_PHASE_C_OUTPUT_LOW,
}

# Expand Set: the parts the ESC acts on (seed 4.4.25), and the flash key each nibble lives in.
_EXPAND_PARTS: Final[dict[int, range | tuple[int, ...]]] = {
    ExpandSetCommand.DIRECTION: (1, 2),
    ExpandSetCommand.LED: range(4),
    ExpandSetCommand.THROTTLE_INTERFACE: (2, 3),
    ExpandSetCommand.ACTIVE_FREEWHEELING: range(2),
    ExpandSetCommand.TIMING: range(1, 5),
    ExpandSetCommand.TIMING_2: range(1, 5),
    ExpandSetCommand.LOAD_TYPE: range(1, 5),
    ExpandSetCommand.PROP_LOCK: range(4),
    ExpandSetCommand.STARTUP_ACCELERATION: range(16),
    ExpandSetCommand.SIGNAL_LOSS_RATE: range(16),
    ExpandSetCommand.READ_TEMP_RECORD: (1,),
    ExpandSetCommand.BAUD: range(len(ckesc.BAUD_RATES_BPS)),
    ExpandSetCommand.SYSTEM: (0x10, 0x11),
}
_EXPAND_NIBBLES: Final = {
    ExpandSetCommand.ACTIVE_FREEWHEELING: "active_freewheeling",
    ExpandSetCommand.TIMING: "timing",
    ExpandSetCommand.TIMING_2: "timing_2",
    ExpandSetCommand.LOAD_TYPE: "load_type",
    ExpandSetCommand.PROP_LOCK: "prop_lock",
    ExpandSetCommand.STARTUP_ACCELERATION: "startup_acceleration",
    ExpandSetCommand.SIGNAL_LOSS_RATE: "signal_loss_rate",
}
# Expand Set LED part (and MSG_EXP7's LED nibble) <-> Set LED colour bits.
_EXPAND_LED_COLORS: Final = (LedColor(0), LedColor.RED, LedColor.GREEN, LedColor.BLUE)

_MSG_STREAMS: Final = (
    (ckesc.TYPE_MSG1, "msg1_interval_ms"),
    (ckesc.TYPE_MSG2, "msg2_interval_ms"),
    (ckesc.TYPE_MSG3, "msg3_interval_ms"),
)
_EXP_STREAMS: Final = (
    (ckesc.TYPE_MSG_EXP1, "msg1_interval_ms"),
    (ckesc.TYPE_MSG_EXP2, "msg2_interval_ms"),
    (ckesc.TYPE_MSG_EXP3, "msg2_interval_ms"),
    (ckesc.TYPE_MSG_EXP4, "msg2_interval_ms"),
    (ckesc.TYPE_MSG_EXP5, "msg2_interval_ms"),
    (ckesc.TYPE_MSG_EXP6, "msg2_interval_ms"),
    (ckesc.TYPE_MSG_EXP11, "msg2_interval_ms"),
    (ckesc.TYPE_MSG_EXP7, "msg3_interval_ms"),
    (ckesc.TYPE_MSG_EXP8, "msg3_interval_ms"),
    (ckesc.TYPE_MSG_EXP9, "msg3_interval_ms"),
    (ckesc.TYPE_MSG_EXP10, "msg3_interval_ms"),
)
_DEBUG_RECORDS: Final[dict[int, Callable[[bytes], CkescMessage]]] = {
    ckesc.TYPE_MSG_EXP2: MsgExp2,
    ckesc.TYPE_MSG_EXP3: MsgExp3,
    ckesc.TYPE_MSG_EXP4: MsgExp4,
    ckesc.TYPE_MSG_EXP5: MsgExp5,
    ckesc.TYPE_MSG_EXP6: MsgExp6,
}


class ReportMode(enum.Enum):
    """Which periodic reports the ESC sends (MSGControl)."""

    MSG = "msg"
    """MSG1..MSG3 (power-up)."""
    EXP = "exp"
    """MSG_EXP1..MSG_EXP11 instead."""
    PAUSED = "paused"


_REPORT_MODES: Final[dict[int, ReportMode]] = {
    MsgControlCommand.PAUSE: ReportMode.PAUSED,
    MsgControlCommand.RESUME_MSG: ReportMode.MSG,
    MsgControlCommand.RESUME_EXP: ReportMode.EXP,
}
_SERVICE_REQUESTS: Final = (
    SetIdRequest,
    SetBaudRequest,
    SetLedRequest,
    SetRotationRequest,
    SetFreqRequest,
    ThrottleSelectRequest,
    SelfTestRequest,
    EscInfoRequest,
    MaintenanceRequest,
    MajorConfigRequest,
)


@dataclass
class SimCkescStats:
    """Counters of one simulated CKESC ESC."""

    commands: int = 0
    """Valid throttle commands for this ESC's channel."""
    bad_frames: int = 0
    """Frames from the host that claim to be CKESC's but are malformed, RawCommand_12b frames
    for a group outside 1..5, and out-of-range throttles on this ESC's channel."""
    requests: int = 0
    """Service requests to this ESC (answered or not)."""
    refused: int = 0
    """Requests refused (not applied), Expand Set included."""
    comms_faults: int = 0
    """Times the 200 ms comms timeout struck."""


def default_flash(
    node_id: int = ckesc.FACTORY_NODE_ID, throttle_channel: int = 1
) -> dict[str, Any]:
    """A factory-fresh flash (see the module docstring for the keys), with this ID and channel."""
    return {
        "node_id": node_id,
        "throttle_channel": throttle_channel,
        "baud_code": 1,
        "led_color": int(LedColor.GREEN),
        "led_blink_hz": 0,
        "rotation": 0,
        "msg1_interval_ms": 20,
        "msg2_interval_ms": 100,
        "msg3_interval_ms": 500,
        "throttle_source": int(ThrottleSource.CAN),
        "active_freewheeling": 1,
        "timing": 2,
        "timing_2": 2,
        "load_type": 2,
        "prop_lock": 0,
        "startup_acceleration": 8,
        "signal_loss_rate": 8,
        "power_on_count": 0,
        "start_count": 0,
        "stop_count": 0,
        "total_run_time_s": 0.0,
        "temp_records": {name: [0, 0, 0] for name in _RECORD_KINDS.values()},
    }


def _clamp_u8(value: float) -> int:
    return max(0, min(_U8_MAX, round(value)))


def _clamp_centi(value: float) -> float:
    return max(0.0, min(_CENTI_MAX, value)) if not math.isnan(value) else 0.0


def _corrupt(msg: can.Message) -> can.Message:
    """The frame with its tail byte's start-of-transfer bit cleared (not a CKESC transfer)."""
    data = bytearray(msg.data)
    data[-1] ^= 0x80
    return can.Message(arbitration_id=msg.arbitration_id, data=data, is_extended_id=True)
