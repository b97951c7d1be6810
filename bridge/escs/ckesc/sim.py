"""A simulated CKESC ESC (docs/protocols.md §3): a pure state machine with an explicit clock.

Longer than 600 lines on purpose: :class:`SimCkesc` is one state machine whose frame
handlers, services and report streams share its state (flash, clock, pending answers); cut
into pieces it would read worse. Its constants and helpers come first.

Frames in (:meth:`SimCkesc.handle`), time in (:meth:`SimCkesc.poll`), frames out; no bus, no
thread, no sleeping. Every frame goes through the production codec (:mod:`bridge.escs.ckesc.codec`),
so the simulator and the bridge read the wire alike.

What it does, in the spec's words where the spec has words:

- Follows its throttle channel in RawCommand_12b (its group), RawCommand_14b (channels 1..4)
  and RawCommand_10b (channels 1..6, value doubled) from the host (node 0):
  ``motor.set_duty(throttle / 2000)``, negated when the rotation is reversed (the motor turns
  the other way; MSG1 still reports a positive speed and sets DIRECTION_CCW).
- Sends MSG1, MSG2 and MSG3 at the Set Freq intervals (factory 20, 100, 500 ms), each type
  with its own transfer ID counter, or MSG_EXP1..11 instead after MSGControl "resume EXP";
  MSG_EXP12 (the four temperature records) once per read request.
- Answers every service request to its node with the matching response and the request's
  transfer ID; answers GET_ESC_ID and acknowledges MSGControl after (node_id % 32) x 2 ms.
- Raises COMMS_FAULT and stops the motor after 200 ms without a valid CAN throttle; the next
  valid command clears it.
- Set ID is accepted only in the first 120 s after power-up and only while no other ESC has
  been heard for 1 s; Set Baud only in the first 120 s, and it applies at the next power-up.
- CANTest: "enter" stops every other report and sends CANTest reports with a counter that
  rises by one per frame; "leave" restores the reports as they were.

Flash
-----
Settings live in a plain dict, "the flash" (:func:`default_flash` lists every key). Pass the
same dict to a new :class:`SimCkesc` to simulate a power cycle: what was saved survives and
``power_on_count`` goes up by one. Values already in the dict win over the constructor's
``node_id`` and ``throttle_channel``, exactly as a real ESC keeps the ID it was given.

==========================  ====================================================================
 key                         meaning (all ints unless said)
==========================  ====================================================================
 node_id, throttle_channel   Set ID (1..0x7D, 1..20)
 baud_code                   Set Baud / Expand Set BAUD (0..6); in effect from the next power-up
 led_color, led_blink_hz     Set LED with save=1, Expand Set LED (RGB bits 0..7; 0, 1, 2, 5 Hz)
 rotation                    0 normal, 1 reversed (Set Rotation, Expand Set DIRECTION)
 msg1/2/3_interval_ms        Set Freq (20..500 ms, even)
 throttle_source             0 CAN, 1 PWM+CAN (Throttle Select, Expand Set THROTTLE_INTERFACE)
 active_freewheeling, ...    the other Expand Set nibbles reported in MSG_EXP7
 power_on_count              +1 per SimCkesc built on this flash
 start_count, stop_count     motor starts (throttle 0 -> > 0) and normal stops (commanded 0)
 total_run_time_s            float, seconds powered over all power-ups
 temp_records                {"mcu"|"mos"|"capacitor"|"motor": [max °C, run count, run time s]}
==========================  ====================================================================

Decisions where the spec is silent
----------------------------------
- **Refusals.** A request the ESC refuses (out of range, outside the 120 s window, another ESC
  on the bus, motor not stopped, reports paused) is not applied and is answered with the
  values in effect, so the host sees what it got by comparing with what it asked. The one
  request that is not answered is Maintenance Information with an option other than 0..2
  (there is no response record for it); Expand Set is never answered (the motor beeps:
  :attr:`SimCkesc.beeps` counts accepted Expand Set commands).
- **Set ID** takes effect at once: the response already comes from the new node ID, and the
  ESC follows the new channel from the next command. Out-of-range values are refused.
  "Alone on the bus": no frame from a node other than 0 and its own in the last second
  (:data:`ALONE_WINDOW_S`). A request from a node other than 0 is ignored altogether.
- **Reports.** MSGControl "resume EXP" replaces MSG1..3 by MSG_EXP1..11 (the seed: MSG1..3
  "can be turned off and replaced by MSG_EXP data"); "resume MSG" switches back; "pause"
  stops both. MSG_EXP1 follows the MSG1 interval, MSG_EXP2..6 and 11 the MSG2 interval,
  MSG_EXP7..10 the MSG3 interval. Reports are on at power-up, except at the factory node ID
  0x7D, which never reports. MSGControl commands other than the three are not acknowledged.
  MSGControl state and CANTest mode are volatile (lost at power-off).
- Set LED and Set Rotation are refused while reports are paused; a rotation query (0xFF) is
  still answered. Set Rotation and Expand Set need the motor stopped (throttle 0 and the
  reported speed 0), Throttle Select needs throttle 0. An unknown Set LED blink rate is taken
  as 0 (steady), the colour's upper five bits are dropped; an Expand Set part outside the
  seed's table (or a "reserved" interface: PWM only, DShot, UAVCAN) is ignored without a beep;
  factory reset (SYSTEM 0x00, "not enabled" in the seed) likewise. SYSTEM 0x10/0x11 only
  toggle :attr:`SimCkesc.debug_mode`.
- **Temperature records**: Expand Set READ_TEMP_RECORD or a Get Temperature Record request
  (223, any payload) sends the four MSG_EXP12 records (MCU, MOS, capacitor, motor) at once,
  whatever the report mode; Clear Temperature Record (224) zeroes them. Neither is answered
  (the seed defines no payload). A record holds the highest temperature reported, the run
  (power-up) count and the seconds into that run when it was reached.
- **Run time and counts**: a "run" is a power-up: run time is the time since power-up,
  run count the power-on count.
- **Throttle source**: PWM+CAN prefers the PWM input (:attr:`SimCkesc.pwm_throttle`, 0..2000,
  None: no PWM signal) and falls back to CAN when there is no PWM signal (seed 4.2). MSG1's
  THROTTLE_SOURCE_PWM bit says which one is in use; the comms fault is raised only while CAN
  is. A CAN throttle outside 0..2000 (10b: 0..1000) or a malformed frame is not a valid
  command (ignored; the comms timer runs on).
- **Status bits**: UNDER_VOLTAGE below 3.0 V per cell, the cell count taken from the first
  supply voltage of at least 3 V (rounded up at 4.25 V per cell); OVER_VOLTAGE above 4.35 V
  per cell at the rated 14 cells; OVER_CURRENT above the rated 80 A; OVER_TEMPERATURE above
  110 °C at the MOSFETs; RUNNING while the reported speed is not 0; bits 7..0 from
  :attr:`SimCkesc.self_test_fault` (which does not stop the motor).
- Capacitor and MCU temperatures follow the MOSFETs: ambient + 0.6 x and ambient + 5 + 0.3 x
  the MOSFETs' rise. Vendor debug data (MSG_EXP2..6) is six zero bytes.
- Faults: ``over_temperature`` reports 150 °C at the MOSFETs, ``over_current`` 600 A, each
  with its status bit; ``corrupt`` clears the start-of-transfer bit in the tail byte of every
  frame the ESC sends on its own (MSG*, MSG_EXP*, CANTest reports; not answers and acks);
  ``silent`` sends nothing, answers included (commands and requests still act);
  ``stuck_motor`` sets ``motor.stuck``.
- Periodic frames keep their schedule (``due += interval``, so a late poll does not slow the
  rate), at most one frame of a type per poll: a stream a whole interval behind (a stall of
  the caller) skips ahead instead of bursting, and an interval shorter than the poll period
  is capped by it. CANTest reports go out every 2 ms (:data:`CAN_TEST_INTERVAL_S`). A changed
  interval or report mode restarts the affected streams at the next poll.
"""

from __future__ import annotations

import copy
import enum
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

import can

from bridge.errors import FrameError
from bridge.escs import uavcan_v0
from bridge.escs.ckesc import codec, records
from bridge.escs.ckesc.keys import CkescKeys
from bridge.escs.family import EscSetup
from bridge.sim.base import Faults, SimEsc
from bridge.sim.motor import Motor, MotorParams

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
ESC_INFO: Final = records.EscInfoResponse(
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
    records.TempRecordKind.MCU: "mcu",
    records.TempRecordKind.MOS: "mos",
    records.TempRecordKind.CAPACITOR: "capacitor",
    records.TempRecordKind.MOTOR: "motor",
}

# Self-test fault code 1 -> MSG1 status bit.
_SELF_TEST_BITS: Final = {
    records.SelfTestFault.COM_LOW: records.Msg1Status.SELF_TEST_COM_INPUT_LOW,
    records.SelfTestFault.COM_HIGH: records.Msg1Status.SELF_TEST_COM_INPUT_HIGH,
    records.SelfTestFault.PHASE_A_HIGH: records.Msg1Status.SELF_TEST_PHASE_A_OUTPUT_HIGH,
    records.SelfTestFault.PHASE_B_HIGH: records.Msg1Status.SELF_TEST_PHASE_B_OUTPUT_HIGH,
    records.SelfTestFault.PHASE_C_HIGH: records.Msg1Status.SELF_TEST_PHASE_C_OUTPUT_HIGH,
    records.SelfTestFault.PHASE_A_LOW: records.Msg1Status.SELF_TEST_PHASE_A_OUTPUT_LOW,
    records.SelfTestFault.PHASE_B_LOW: records.Msg1Status.SELF_TEST_PHASE_B_OUTPUT_LOW,
    records.SelfTestFault.PHASE_C_LOW: records.Msg1Status.SELF_TEST_PHASE_C_OUTPUT_LOW,
}

# Expand Set: the parts the ESC acts on (seed 4.4.25), and the flash key each nibble lives in.
_EXPAND_PARTS: Final[dict[int, range | tuple[int, ...]]] = {
    records.ExpandSetCommand.DIRECTION: (1, 2),
    records.ExpandSetCommand.LED: range(4),
    records.ExpandSetCommand.THROTTLE_INTERFACE: (2, 3),
    records.ExpandSetCommand.ACTIVE_FREEWHEELING: range(2),
    records.ExpandSetCommand.TIMING: range(1, 5),
    records.ExpandSetCommand.TIMING_2: range(1, 5),
    records.ExpandSetCommand.LOAD_TYPE: range(1, 5),
    records.ExpandSetCommand.PROP_LOCK: range(4),
    records.ExpandSetCommand.STARTUP_ACCELERATION: range(16),
    records.ExpandSetCommand.SIGNAL_LOSS_RATE: range(16),
    records.ExpandSetCommand.READ_TEMP_RECORD: (1,),
    records.ExpandSetCommand.BAUD: range(len(records.BAUD_RATES_BPS)),
    records.ExpandSetCommand.SYSTEM: (0x10, 0x11),
}
_EXPAND_NIBBLES: Final = {
    records.ExpandSetCommand.ACTIVE_FREEWHEELING: "active_freewheeling",
    records.ExpandSetCommand.TIMING: "timing",
    records.ExpandSetCommand.TIMING_2: "timing_2",
    records.ExpandSetCommand.LOAD_TYPE: "load_type",
    records.ExpandSetCommand.PROP_LOCK: "prop_lock",
    records.ExpandSetCommand.STARTUP_ACCELERATION: "startup_acceleration",
    records.ExpandSetCommand.SIGNAL_LOSS_RATE: "signal_loss_rate",
}
# Expand Set LED part (and MSG_EXP7's LED nibble) <-> Set LED colour bits.
_EXPAND_LED_COLORS: Final = (
    records.LedColor(0),
    records.LedColor.RED,
    records.LedColor.GREEN,
    records.LedColor.BLUE,
)

_MSG_STREAMS: Final = (
    (records.TYPE_MSG1, "msg1_interval_ms"),
    (records.TYPE_MSG2, "msg2_interval_ms"),
    (records.TYPE_MSG3, "msg3_interval_ms"),
)
_EXP_STREAMS: Final = (
    (records.TYPE_MSG_EXP1, "msg1_interval_ms"),
    (records.TYPE_MSG_EXP2, "msg2_interval_ms"),
    (records.TYPE_MSG_EXP3, "msg2_interval_ms"),
    (records.TYPE_MSG_EXP4, "msg2_interval_ms"),
    (records.TYPE_MSG_EXP5, "msg2_interval_ms"),
    (records.TYPE_MSG_EXP6, "msg2_interval_ms"),
    (records.TYPE_MSG_EXP11, "msg2_interval_ms"),
    (records.TYPE_MSG_EXP7, "msg3_interval_ms"),
    (records.TYPE_MSG_EXP8, "msg3_interval_ms"),
    (records.TYPE_MSG_EXP9, "msg3_interval_ms"),
    (records.TYPE_MSG_EXP10, "msg3_interval_ms"),
)
_DEBUG_RECORDS: Final[dict[int, Callable[[bytes], records.CkescMessage]]] = {
    records.TYPE_MSG_EXP2: records.MsgExp2,
    records.TYPE_MSG_EXP3: records.MsgExp3,
    records.TYPE_MSG_EXP4: records.MsgExp4,
    records.TYPE_MSG_EXP5: records.MsgExp5,
    records.TYPE_MSG_EXP6: records.MsgExp6,
}


class ReportMode(enum.Enum):
    """Which periodic reports the ESC sends (MSGControl)."""

    MSG = "msg"
    """MSG1..MSG3 (power-up)."""
    EXP = "exp"
    """MSG_EXP1..MSG_EXP11 instead."""
    PAUSED = "paused"


_REPORT_MODES: Final[dict[int, ReportMode]] = {
    records.MsgControlCommand.PAUSE: ReportMode.PAUSED,
    records.MsgControlCommand.RESUME_MSG: ReportMode.MSG,
    records.MsgControlCommand.RESUME_EXP: ReportMode.EXP,
}
_SERVICE_REQUESTS: Final = (
    records.SetIdRequest,
    records.SetBaudRequest,
    records.SetLedRequest,
    records.SetRotationRequest,
    records.SetFreqRequest,
    records.ThrottleSelectRequest,
    records.SelfTestRequest,
    records.EscInfoRequest,
    records.MaintenanceRequest,
    records.MajorConfigRequest,
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
    node_id: int = records.FACTORY_NODE_ID, throttle_channel: int = 1
) -> dict[str, Any]:
    """A factory-fresh flash (see the module docstring for the keys), with this ID and channel."""
    return {
        "node_id": node_id,
        "throttle_channel": throttle_channel,
        "baud_code": 1,
        "led_color": int(records.LedColor.GREEN),
        "led_blink_hz": 0,
        "rotation": 0,
        "msg1_interval_ms": 20,
        "msg2_interval_ms": 100,
        "msg3_interval_ms": 500,
        "throttle_source": int(records.ThrottleSource.CAN),
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


__all__ = [
    "ALONE_WINDOW_S",
    "ANSWER_DELAY_STEP_S",
    "CAN_TEST_INTERVAL_S",
    "COMMS_TIMEOUT_S",
    "ESC_INFO",
    "FAULT_CURRENT_A",
    "FAULT_MOS_TEMP_C",
    "MAX_STEP_S",
    "OVER_TEMPERATURE_C",
    "SET_ID_WINDOW_S",
    "UNDER_VOLTAGE_PER_CELL_V",
    "ReportMode",
    "SimCkesc",
    "SimCkescStats",
    "default_flash",
    "simulators",
]


class SimCkesc:
    """One simulated CKESC ESC driving ``motor``.

    ``node_id`` and ``throttle_channel`` are the factory settings written to a fresh
    ``flash`` (a dict; see the module docstring); a flash that already holds them wins.
    ``power_on_s`` is the power-up time on the caller's clock (Set ID's 120 s window, run time,
    the first comms timeout count from it).

    Raises:
        ValueError: ``node_id`` outside 1..0x7D or ``throttle_channel`` outside 1..20.
    """

    def __init__(
        self,
        node_id: int,
        throttle_channel: int,
        *,
        motor: Motor | None = None,
        flash: dict[str, Any] | None = None,
        power_on_s: float = 0.0,
    ) -> None:
        if not 1 <= node_id <= uavcan_v0.MAX_NODE_ID:
            raise ValueError(f"node_id={node_id!r} outside 1..{uavcan_v0.MAX_NODE_ID}")
        if not 1 <= throttle_channel <= records.MAX_CHANNELS:
            raise ValueError(
                f"throttle_channel={throttle_channel!r} outside 1..{records.MAX_CHANNELS}"
            )
        self.flash: dict[str, Any] = flash if flash is not None else {}
        """The settings "in flash": the caller's dict, updated in place as settings are saved."""
        for key, value in default_flash(node_id, throttle_channel).items():
            self.flash.setdefault(key, value)
        self.flash["power_on_count"] = int(self.flash["power_on_count"]) + 1
        self.node_id: int = int(self.flash["node_id"])
        self.throttle_channel: int = int(self.flash["throttle_channel"])
        self.motor = motor or Motor()
        self.faults = Faults()
        self.stats = SimCkescStats()
        self.power_on_s = power_on_s
        self.baud_code: int = int(self.flash["baud_code"])
        """The bit rate in use (Set Baud codes 0..6): the flash's at power-up."""
        self.led_color = records.LedColor(int(self.flash["led_color"]) & 0x07)
        """The LED colour shown now (a Set LED without save changes only this)."""
        self.led_blink_hz: int = int(self.flash["led_blink_hz"])
        self.pwm_throttle: int | None = None
        """The PWM input, 0..2000, or None for no PWM signal (used only in PWM+CAN mode)."""
        self.self_test_fault: records.SelfTestFault | int = records.SelfTestFault.NONE
        """Power-on self-test fault code 1 (0: passed); set it to simulate a failed test."""
        self.fault_code_2 = 0
        """Self-test fault code 2 (undefined by the seed)."""
        self.debug_mode = False
        """Expand Set SYSTEM 0x11 / 0x10 (the vendor's debug test mode); changes nothing."""
        self.beeps = 0
        """Expand Set commands accepted (the motor beeps for each)."""
        self.report_mode = ReportMode.MSG
        self.can_test_mode = False
        self.can_test_count = 0
        """The CANTest counter: the next report's count (u32, wraps)."""
        self._tids = uavcan_v0.TransferIds()
        self._due: dict[int, float] = {}
        self._pending: list[tuple[float, can.Message]] = []
        self._others: dict[int, float] = {}
        self._can_throttle = 0
        self._applied = 0
        self._using_pwm = False
        self._comms_fault = False
        self._last_command_s = power_on_s
        self._last_poll_s: float | None = None
        self._supply_v = 0.0
        self._cells: int | None = None
        self._total_run_base_s = float(self.flash["total_run_time_s"])

    # -- read-only state ----------------------------------------------------------------------

    @property
    def applied_throttle(self) -> int:
        """The throttle the ESC applies now, 0..2000 (MSG1's throttle)."""
        return self._applied

    @property
    def comms_fault(self) -> bool:
        return self._comms_fault

    @property
    def reversed(self) -> bool:
        return int(self.flash["rotation"]) == 1

    @property
    def throttle_source(self) -> records.ThrottleSource:
        return records.ThrottleSource(int(self.flash["throttle_source"]))

    @property
    def intervals_ms(self) -> tuple[int, int, int]:
        """MSG1, MSG2, MSG3 report intervals."""
        f = self.flash
        return int(f["msg1_interval_ms"]), int(f["msg2_interval_ms"]), int(f["msg3_interval_ms"])

    @property
    def cells(self) -> int | None:
        """Battery cells, taken from the first supply voltage of at least 3 V."""
        return self._cells

    @property
    def run_time_s(self) -> int:
        """Whole seconds since power-up (at the last poll)."""
        return int(self._run_time_s())

    @property
    def status(self) -> records.Msg1Status:
        """MSG1's status word as of the last poll."""
        return self._status()

    def to_flash(self) -> dict[str, Any]:
        """A deep copy of the flash (for saving; the live dict is :attr:`flash`)."""
        return copy.deepcopy(self.flash)

    # -- frames in ------------------------------------------------------------------------------

    def handle(self, msg: can.Message, now_s: float) -> list[can.Message]:
        """Act on one frame from the bus at ``now_s``; the answers due at once: service
        responses, MSG_EXP12 records, and GET_ESC_ID answers / MSGControl acks of a node whose
        delay (node_id % 32 x 2 ms) is 0. Delayed answers come from :meth:`poll`."""
        if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
            return []
        can_id: int = msg.arbitration_id
        source = can_id & 0x7F
        if source != records.HOST_NODE_ID:
            if source != self.node_id:
                self._others[source] = now_s
            return []
        out: list[can.Message] = []
        if can_id & 0x80 and can_id & 0x8000 and (can_id >> 16 & 0xFF) in (223, 224):
            if (can_id >> 8 & 0x7F) == self.node_id:
                self.stats.requests += 1
                out = self._temp_record_request(can_id >> 16 & 0xFF)
        else:
            try:
                frame = codec.decode(msg)
            except FrameError:
                self.stats.bad_frames += 1
                return []
            if frame is not None:
                out = self._dispatch(frame, now_s)
        return [] if self.faults.silent else out

    def _dispatch(self, frame: codec.CkescFrame, now_s: float) -> list[can.Message]:
        message = frame.message
        if isinstance(
            message, records.RawCommand12b | records.RawCommand14b | records.RawCommand10b
        ):
            self._throttle_command(message, now_s)
            return []
        if isinstance(message, records.MsgControlRequest):
            return self._msg_control(message, now_s)
        if isinstance(message, records.GetEscIdRequest):
            return self._answer_later(
                records.GetEscIdAnswer(self.node_id, self.throttle_channel), now_s
            )
        if isinstance(message, records.CanTestRequest):
            self._can_test(message)
            return []
        if not isinstance(message, (*_SERVICE_REQUESTS, records.ExpandSetRequest)):
            return []  # an ESC's record sent from node 0: nothing to act on
        if frame.destination_node != self.node_id and not isinstance(message, records.SetIdRequest):
            return []
        self.stats.requests += 1
        if isinstance(message, records.ExpandSetRequest):
            return self._expand_set(message)
        answer = self._serve(message, now_s)
        if answer is None or frame.transfer_id is None:
            return []
        return [
            codec.encode(
                codec.CkescFrame(
                    priority=codec.default_priority(answer),
                    source_node=self.node_id,
                    destination_node=records.HOST_NODE_ID,
                    transfer_id=frame.transfer_id,
                    message=answer,
                )
            )
        ]

    # -- throttle -------------------------------------------------------------------------------

    def _throttle_command(
        self,
        message: records.RawCommand12b | records.RawCommand14b | records.RawCommand10b,
        now_s: float,
    ) -> None:
        channel = self.throttle_channel
        if isinstance(message, records.RawCommand12b):
            if not 1 <= message.group <= records.MAX_GROUP:
                self.stats.bad_frames += 1
                return
            first = records.CHANNELS_PER_GROUP * (message.group - 1) + 1
            values: tuple[int, ...] = message.throttles
            limit, scale = records.THROTTLE_MAX, 1
        elif isinstance(message, records.RawCommand14b):
            first, values, limit, scale = 1, message.throttles, records.THROTTLE_MAX, 1
        else:
            first, values, limit, scale = 1, message.throttles, records.THROTTLE_10B_MAX, 2
        index = channel - first
        if not 0 <= index < len(values):
            return  # not our channel
        value = values[index]
        if not 0 <= value <= limit:
            self.stats.bad_frames += 1
            return
        self.stats.commands += 1
        self._last_command_s = now_s
        self._comms_fault = False
        self._can_throttle = value * scale
        self._apply()

    def _apply(self, normal: bool = True) -> None:
        """Work out the throttle in use and command the motor; ``normal``: a stop now is a
        normal (commanded) stop."""
        pwm = self._pwm_input()
        self._using_pwm = pwm is not None
        if pwm is not None:
            applied = max(0, min(records.THROTTLE_MAX, pwm))
        else:
            applied = 0 if self._comms_fault else self._can_throttle
        if applied and not self._applied:
            self.flash["start_count"] = int(self.flash["start_count"]) + 1
        elif self._applied and not applied and normal:
            self.flash["stop_count"] = int(self.flash["stop_count"]) + 1
        self._applied = applied
        duty = applied / records.THROTTLE_MAX
        self.motor.set_duty(-duty if self.reversed else duty)

    def _pwm_input(self) -> int | None:
        """The PWM throttle if it is the one in use (PWM+CAN mode with a PWM signal)."""
        if self.throttle_source == records.ThrottleSource.PWM_AND_CAN:
            return self.pwm_throttle
        return None

    def _stopped(self) -> bool:
        return self._applied == 0 and self._speed_rpm() == 0

    # -- reports control, GET_ESC_ID, CANTest -------------------------------------------------

    def _answer_later(self, answer: records.CkescMessage, now_s: float) -> list[can.Message]:
        """Queue ``answer`` for (node_id % 32) x 2 ms from now; [the frame] if that is now."""
        frame = codec.encode(
            codec.CkescFrame(
                priority=codec.default_priority(answer),
                source_node=self.node_id,
                destination_node=None,
                transfer_id=self._tids.next(codec.type_id_of(answer)),
                message=answer,
            )
        )
        delay = (self.node_id % 32) * ANSWER_DELAY_STEP_S
        if delay == 0:
            return [frame]
        self._pending.append((now_s + delay, frame))
        return []

    def _take_pending(self, now_s: float) -> list[can.Message]:
        due = [frame for when, frame in self._pending if when <= now_s + _EPS_S]
        if due:
            self._pending = [(w, f) for w, f in self._pending if w > now_s + _EPS_S]
        return due

    def _msg_control(self, message: records.MsgControlRequest, now_s: float) -> list[can.Message]:
        mode = _REPORT_MODES.get(message.command)
        if mode is None:
            return []
        if mode != self.report_mode:
            self.report_mode = mode
            self._due.clear()
        return self._answer_later(records.MsgControlAck(), now_s)

    def _can_test(self, message: records.CanTestRequest) -> None:
        if message.option == records.CanTestOption.ENTER and not self.can_test_mode:
            self.can_test_mode = True
            self._due.clear()
        elif message.option == records.CanTestOption.LEAVE and self.can_test_mode:
            self.can_test_mode = False
            self._due.clear()

    # -- services -------------------------------------------------------------------------------

    def _refuse(self) -> None:
        self.stats.refused += 1

    def _serve(self, message: records.CkescMessage, now_s: float) -> records.CkescMessage | None:
        """The response to a request to this node (applying it if allowed), None: no answer."""
        f = self.flash
        reports_on = self.report_mode != ReportMode.PAUSED
        if isinstance(message, records.SetIdRequest):
            if (
                1 <= message.node_id <= uavcan_v0.MAX_NODE_ID
                and 1 <= message.throttle_channel <= records.MAX_CHANNELS
                and self._in_window(now_s)
                and self._alone(now_s)
            ):
                self.node_id = f["node_id"] = message.node_id
                self.throttle_channel = f["throttle_channel"] = message.throttle_channel
            else:
                self._refuse()
            return records.SetIdResponse(self.node_id, self.throttle_channel)
        if isinstance(message, records.SetBaudRequest):
            if message.baud_code in range(len(records.BAUD_RATES_BPS)) and self._in_window(now_s):
                f["baud_code"] = message.baud_code
            else:
                self._refuse()
            return records.SetBaudResponse(int(f["baud_code"]))
        if isinstance(message, records.SetLedRequest):
            if reports_on:
                self.led_color = records.LedColor(int(message.color) & 0x07)
                blink = message.blink_hz
                self.led_blink_hz = blink if blink in (0, 1, 2, 5) else 0
                if message.save:
                    f["led_color"], f["led_blink_hz"] = int(self.led_color), self.led_blink_hz
            else:
                self._refuse()
            return records.SetLedResponse(message.save, self.led_color, self.led_blink_hz)
        if isinstance(message, records.SetRotationRequest):
            if message.rotation in (records.Rotation.NORMAL, records.Rotation.REVERSED):
                if reports_on and self._stopped():
                    f["rotation"] = int(message.rotation)
                    self._apply()
                else:
                    self._refuse()
            elif message.rotation != records.Rotation.QUERY:
                self._refuse()
            return records.SetRotationResponse(
                records.Rotation.REVERSED if self.reversed else records.Rotation.NORMAL
            )
        if isinstance(message, records.SetFreqRequest):
            wanted = (message.msg1_interval_ms, message.msg2_interval_ms, message.msg3_interval_ms)
            if message.write:
                if all(20 <= ms <= 500 and ms % 2 == 0 for ms in wanted):
                    f["msg1_interval_ms"], f["msg2_interval_ms"], f["msg3_interval_ms"] = wanted
                    self._due.clear()
                else:
                    self._refuse()
            return records.SetFreqResponse(message.write, *self.intervals_ms)
        if isinstance(message, records.ThrottleSelectRequest):
            known = message.source in (
                records.ThrottleSource.CAN,
                records.ThrottleSource.PWM_AND_CAN,
            )
            if known and self._applied == 0:
                f["throttle_source"] = int(message.source)
                self._apply()
            else:
                self._refuse()
            return records.ThrottleSelectResponse(self.throttle_source)
        if isinstance(message, records.SelfTestRequest):
            return records.SelfTestResponse(
                passed=self.self_test_fault == records.SelfTestFault.NONE
            )
        if isinstance(message, records.EscInfoRequest):
            return ESC_INFO
        if isinstance(message, records.MaintenanceRequest):
            return self._maintenance(message.option)
        if isinstance(message, records.MajorConfigRequest):
            m1, m2, m3 = self.intervals_ms
            return records.MajorConfigResponse(
                direction_reversed=self.reversed,
                throttle_source=self.throttle_source,
                throttle_channel=self.throttle_channel,
                led_blink_hz=self.led_blink_hz,
                led_color=self.led_color,
                msg1_interval_ms=m1,
                msg2_interval_ms=m2,
                msg3_interval_ms=m3,
            )
        return None  # a response or a host-only record: not a request to serve

    def _maintenance(self, option: int) -> records.CkescMessage | None:
        f = self.flash
        if option == 0:
            temp_records = f["temp_records"]
            return records.Maintenance0Response(
                total_run_time_s=self._total_run_time_s(),
                max_mos_temp_c=int(temp_records["mos"][0]),
                max_capacitor_temp_c=int(temp_records["capacitor"][0]),
            )
        if option == 1:
            return records.Maintenance1Response(self.run_time_s, self._run_count())
        if option == 2:
            return records.Maintenance2Response(
                power_on_count=int(f["power_on_count"]) & 0xFFFF,
                stop_count=int(f["stop_count"]) & 0xFFFF,
                self_test_fault=self.self_test_fault,
            )
        self._refuse()
        return None

    def _in_window(self, now_s: float) -> bool:
        return now_s - self.power_on_s <= SET_ID_WINDOW_S

    def _alone(self, now_s: float) -> bool:
        return all(
            now_s - seen > ALONE_WINDOW_S
            for node, seen in self._others.items()
            if node != self.node_id
        )

    def _expand_set(self, message: records.ExpandSetRequest) -> list[can.Message]:
        command, part = int(message.command), message.part
        allowed = _EXPAND_PARTS.get(command)
        if allowed is None or part not in allowed or not self._stopped():
            self._refuse()
            return []
        self.beeps += 1
        f = self.flash
        if command == records.ExpandSetCommand.DIRECTION:
            f["rotation"] = part - 1
            self._apply()
        elif command == records.ExpandSetCommand.LED:
            self.led_color = _EXPAND_LED_COLORS[part]
            f["led_color"] = int(self.led_color)
        elif command == records.ExpandSetCommand.THROTTLE_INTERFACE:
            f["throttle_source"] = int(
                records.ThrottleSource.PWM_AND_CAN if part == 2 else records.ThrottleSource.CAN
            )
            self._apply()
        elif command == records.ExpandSetCommand.READ_TEMP_RECORD:
            return self._temp_records()
        elif command == records.ExpandSetCommand.BAUD:
            f["baud_code"] = part
        elif command == records.ExpandSetCommand.SYSTEM:
            self.debug_mode = part == 0x11
        else:
            f[_EXPAND_NIBBLES[records.ExpandSetCommand(command)]] = part
        return []

    def _temp_record_request(self, service_type: int) -> list[can.Message]:
        if service_type == records.SERVICE_GET_TEMP_RECORD:
            return self._temp_records()
        self.flash["temp_records"] = {name: [0, 0, 0] for name in _RECORD_KINDS.values()}
        return []

    def _temp_records(self) -> list[can.Message]:
        out = []
        for kind, name in _RECORD_KINDS.items():
            max_temp, run_count, run_time = self.flash["temp_records"][name]
            record = records.MsgExp12(kind, int(max_temp), int(run_count) & 0xFFFF, int(run_time))
            out.append(self._broadcast(record, None))
        return out

    # -- time -----------------------------------------------------------------------------------

    def poll(self, now_s: float, supply_v: float) -> list[can.Message]:
        """Advance the motor to ``now_s`` at ``supply_v``, apply the comms timeout; the answers
        and telemetry due by now."""
        dt = (
            0.0
            if self._last_poll_s is None
            else min(max(now_s - self._last_poll_s, 0.0), MAX_STEP_S)
        )
        self._last_poll_s = now_s
        self._supply_v = supply_v
        if self._cells is None and supply_v >= UNDER_VOLTAGE_PER_CELL_V:
            self._cells = math.ceil(supply_v / CELL_DETECT_V)
        self.motor.stuck = self.faults.stuck_motor
        self.motor.step(dt, supply_v)
        self._expire(now_s)
        self._apply(normal=not self._comms_fault)
        self.flash["total_run_time_s"] = self._total_run_base_s + self._run_time_s()
        temps = self._temperatures()
        self._record(records.TempRecordKind.MOS, temps[0])
        self._record(records.TempRecordKind.CAPACITOR, temps[1])
        self._record(records.TempRecordKind.MOTOR, temps[2])
        self._record(records.TempRecordKind.MCU, temps[3])
        out = self._take_pending(now_s) + self._reports(now_s)
        return [] if self.faults.silent else out

    def _expire(self, now_s: float) -> None:
        if self._pwm_input() is not None or self._comms_fault:
            return
        if now_s - self._last_command_s >= COMMS_TIMEOUT_S - _EPS_S:
            self._comms_fault = True
            self._can_throttle = 0
            self.stats.comms_faults += 1

    def _run_time_s(self) -> float:
        if self._last_poll_s is None:
            return 0.0
        return max(0.0, self._last_poll_s - self.power_on_s)

    def _total_run_time_s(self) -> int:
        return int(float(self.flash["total_run_time_s"]))

    def _run_count(self) -> int:
        return int(self.flash["power_on_count"]) & 0xFFFF

    def _record(self, kind: records.TempRecordKind, temp_c: int) -> None:
        record = self.flash["temp_records"][_RECORD_KINDS[kind]]
        if temp_c > record[0]:
            record[:] = [temp_c, self._run_count(), self.run_time_s]

    def _reports(self, now_s: float) -> list[can.Message]:
        if self.can_test_mode:
            return self._stream(records.TYPE_CAN_TEST, CAN_TEST_INTERVAL_S, now_s)
        if self.node_id == records.FACTORY_NODE_ID or self.report_mode == ReportMode.PAUSED:
            return []
        streams = _MSG_STREAMS if self.report_mode == ReportMode.MSG else _EXP_STREAMS
        out: list[can.Message] = []
        for type_id, key in streams:
            out += self._stream(type_id, int(self.flash[key]) / 1000, now_s)
        return out

    def _stream(self, type_id: int, interval_s: float, now_s: float) -> list[can.Message]:
        due = self._due.get(type_id, now_s)
        if due > now_s + _EPS_S:
            return []
        due += interval_s
        if due <= now_s + _EPS_S:
            due = now_s + interval_s  # a whole interval behind: skip ahead, do not burst
        self._due[type_id] = due
        return [self._report(type_id)]

    def _report(self, type_id: int) -> can.Message:
        if type_id == records.TYPE_CAN_TEST:
            count, self.can_test_count = self.can_test_count, (self.can_test_count + 1) & 0xFFFFFFFF
            record: records.CkescMessage = records.CanTestReport(count)
        else:
            record = self._telemetry(type_id)
        return self._broadcast(record, self._tids.next(type_id))

    def _broadcast(self, record: records.CkescMessage, transfer_id: int | None) -> can.Message:
        """An unsolicited frame (report), corrupted under the ``corrupt`` fault."""
        msg = codec.encode(
            codec.CkescFrame(
                priority=codec.default_priority(record),
                source_node=self.node_id,
                destination_node=None,
                transfer_id=transfer_id,
                message=record,
            )
        )
        return _corrupt(msg) if self.faults.corrupt else msg

    # -- telemetry values -------------------------------------------------------------------

    def _status(self) -> records.Msg1Status:
        status = records.Msg1Status(0)
        if self.reversed:
            status |= records.Msg1Status.DIRECTION_CCW
        if self._using_pwm:
            status |= records.Msg1Status.THROTTLE_SOURCE_PWM
        if self._comms_fault:
            status |= records.Msg1Status.COMMS_FAULT
        cells = self._cells or 1
        if self._supply_v < UNDER_VOLTAGE_PER_CELL_V * cells:
            status |= records.Msg1Status.UNDER_VOLTAGE
        if self._supply_v > OVER_VOLTAGE_PER_CELL_V * ESC_INFO.max_cells:
            status |= records.Msg1Status.OVER_VOLTAGE
        if self.faults.over_current or self.motor.current_a > ESC_INFO.max_current_a:
            status |= records.Msg1Status.OVER_CURRENT
        if self.faults.over_temperature or self.motor.mos_temp_c > OVER_TEMPERATURE_C:
            status |= records.Msg1Status.OVER_TEMPERATURE
        if self._speed_rpm():
            status |= records.Msg1Status.RUNNING
        if self.self_test_fault in _SELF_TEST_BITS:
            status |= _SELF_TEST_BITS[records.SelfTestFault(self.self_test_fault)]
        return status

    def _speed_rpm(self) -> int:
        return min(0xFFFF, round(abs(self.motor.rpm)))

    def _current_a(self) -> float:
        return FAULT_CURRENT_A if self.faults.over_current else _clamp_centi(self.motor.current_a)

    def _temperatures(self) -> tuple[int, int, int, int]:
        """Reported MOS, capacitor, motor and MCU temperatures (°C, u8)."""
        ambient = self.motor.params.ambient_c
        mos = self.motor.mos_temp_c
        rise = mos - ambient
        reported_mos = FAULT_MOS_TEMP_C if self.faults.over_temperature else _clamp_u8(mos)
        return (
            reported_mos,
            _clamp_u8(ambient + 0.6 * rise),
            _clamp_u8(self.motor.motor_temp_c),
            _clamp_u8(ambient + 5.0 + 0.3 * rise),
        )

    def _telemetry(self, type_id: int) -> records.CkescMessage:
        f = self.flash
        mos, capacitor, motor, mcu = self._temperatures()
        voltage = _clamp_centi(self._supply_v)
        if type_id == records.TYPE_MSG1:
            return records.Msg1(self._speed_rpm(), self._applied, self._status())
        if type_id == records.TYPE_MSG2:
            return records.Msg2(voltage, self._current_a(), mos)
        if type_id == records.TYPE_MSG3:
            return records.Msg3(mos, capacitor, motor, mcu)
        if type_id == records.TYPE_MSG_EXP1:
            return records.MsgExp1(self._speed_rpm(), voltage, self._current_a())
        if type_id in _DEBUG_RECORDS:
            return _DEBUG_RECORDS[type_id](bytes(6))
        if type_id == records.TYPE_MSG_EXP7:
            return records.MsgExp7(
                motor_direction=2 if self.reversed else 1,
                led=_led_nibble(self.led_color),
                throttle_interface=2
                if self.throttle_source == records.ThrottleSource.PWM_AND_CAN
                else 3,
                active_freewheeling=int(f["active_freewheeling"]),
                timing=int(f["timing"]),
                timing_2=int(f["timing_2"]),
                load_type=int(f["load_type"]),
                prop_lock=int(f["prop_lock"]),
                startup_acceleration=int(f["startup_acceleration"]),
                signal_loss_rate=int(f["signal_loss_rate"]),
            )
        if type_id == records.TYPE_MSG_EXP8:
            return records.MsgExp8(
                int(f["power_on_count"]) & 0xFFFF,
                int(f["start_count"]) & 0xFFFF,
                int(f["stop_count"]) & 0xFFFF,
            )
        if type_id == records.TYPE_MSG_EXP9:
            return records.MsgExp9(self._total_run_time_s(), self.self_test_fault)
        if type_id == records.TYPE_MSG_EXP10:
            return records.MsgExp10(self.run_time_s, self.fault_code_2)
        if type_id == records.TYPE_MSG_EXP11:
            return records.MsgExp11(mos, mcu, capacitor, motor)
        raise AssertionError(f"no telemetry record for type {type_id}")


def _led_nibble(color: records.LedColor) -> int:
    """MSG_EXP7's LED nibble (0 off, 1 red, 2 green, 3 blue): the first of red, green, blue lit."""
    for nibble, single in enumerate(_EXPAND_LED_COLORS[1:], start=1):
        if color & single:
            return nibble
    return 0


def simulators(setup: EscSetup[CkescKeys], motor_params: MotorParams | None) -> list[SimEsc]:
    """A simulated CKESC for each of ``setup.ids``, following the throttle channels of
    ``setup.channels`` (else ``[escs] ckesc_channels``, else 1..N), each with a motor of its own.

    Raises:
        ValueError: not one channel per ESC.
    """
    n = len(setup.ids)
    channels = list(setup.channels or setup.keys.ckesc_channels or range(1, n + 1))
    if len(channels) != n:
        raise ValueError(f"channels={channels!r}: {len(channels)} channels for {n} ESCs")
    return [
        SimCkesc(node_id, channel, motor=Motor(motor_params))
        for node_id, channel in zip(setup.ids, channels, strict=True)
    ]
