"""A simulated VESC (docs/protocols.md §6): a pure state machine with an explicit clock.

It behaves as the firmware's ``comm_can.c`` and ``timeout.c`` do (vedderb/bldc 7.01), through
the production codec (:mod:`bridge.escs.vesc.codec`), so the simulator and the bridge read the
wire alike:

========================  ===============================================================
 frame in                  effect
========================  ===============================================================
 SetDuty                   ``motor.set_duty(duty)``
 SetCurrent                ``motor.set_current(current_a)``
 SetCurrentRel             ``motor.set_current(fraction x motor_current_max_a)``
 SetCurrentBrake           ``motor.brake()``
 SetRpm                    ``motor.set_erpm(erpm)``
 Ping                      a Pong to the sender: the ID the PING was addressed to, type VESC
========================  ===============================================================

- Commands and PINGs to the VESC's own ID or to 255 (all) are obeyed, as the firmware does. A
  PING to 255 is answered with 255 as the ID, as the firmware does: only a PING to one ID
  tells who is there.
- A command is in force for ``timeout_s`` (1 s, the firmware's default). After it the motor
  is released (``motor.set_current(0)``: it coasts down with its lag) or, with a
  ``timeout_brake_current_a`` above 0, braked. A VESC that was never commanded is released.
- Status frames are **off by default**, as a VESC fresh from the factory: ``status`` names the
  ones to send (VESC Tool's "Can Messages Rate 1") and ``status_hz`` how often (its "Can
  Status Rate 1", 50 Hz by default). They are sent whether or not a command is in force, all
  of them together each period, at most one set per poll (no bursts after a stall).
- NOTIFY_BOOT is sent at the first poll (the power-up), with the hardware name ``hw_name``.
- Motor current (STATUS) is positive while the motor drives it, in either direction, and
  negative while a brake holds back a turning rotor (regenerating), as the firmware reports
  it; the input current (STATUS_4) likewise. Amp and watt hours (STATUS_2, 3) and the
  tachometer (STATUS_5: six steps per electrical turn) count from the power-up. Values are
  clamped to their wire fields, never refused.
- Faults: ``over_temperature`` reports a MOSFET at 300 degC, ``over_current`` motor and input
  currents of 3000 A, ``corrupt`` cuts the last byte off every status frame (VESC frames have
  no CRC: a short frame is what a receiver can catch), ``silent`` sends nothing (commands still
  act), ``stuck_motor`` blocks the rotor.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Final

import can

from bridge.errors import FrameError
from bridge.escs.family import EscSetup
from bridge.escs.vesc.codec import decode, encode
from bridge.escs.vesc.keys import VescKeys
from bridge.escs.vesc.records import (
    BROADCAST_ID,
    CONTROLLER_ID_MAX,
    ENERGY_SCALE,
    I16_MAX,
    I32_MAX,
    STATUS_CURRENT_SCALE,
    STATUS_DUTY_SCALE,
    TEMP_SCALE,
    VOLTAGE_SCALE,
    HwType,
    NotifyBoot,
    Packet,
    Ping,
    Pong,
    SetCurrent,
    SetCurrentBrake,
    SetCurrentRel,
    SetDuty,
    SetRpm,
    Status,
    Status2,
    Status3,
    Status4,
    Status5,
    Status6,
    VescCommand,
    VescFrame,
    VescStatus,
)
from bridge.sim.base import Faults, SimEsc
from bridge.sim.motor import Motor, MotorParams

__all__ = [
    "DEFAULT_STATUS_HZ",
    "DEFAULT_TIMEOUT_S",
    "DEMO_SETTINGS",
    "OVER_CURRENT_A",
    "OVER_TEMPERATURE_C",
    "STATUS_1_TO_5",
    "SimVesc",
    "VescSimStats",
    "simulators",
]

log = logging.getLogger(__name__)

DEFAULT_TIMEOUT_S: Final = 1.0
"""The firmware's default command timeout (``APPCONF_TIMEOUT_MSEC``, docs/protocols.md §6.4)."""
DEFAULT_STATUS_HZ: Final = 50.0
"""The firmware's default "Can Status Rate 1" (``APPCONF_CAN_STATUS_RATE_1``)."""
STATUS_1_TO_5: Final = frozenset(
    (Packet.STATUS, Packet.STATUS_2, Packet.STATUS_3, Packet.STATUS_4, Packet.STATUS_5)
)
"""What docs/escs.md asks a user to turn on in VESC Tool."""
OVER_TEMPERATURE_C: Final = 300.0
"""MOSFET temperature reported under the over_temperature fault."""
OVER_CURRENT_A: Final = 3000.0
"""Motor and input current reported under the over_current fault (fits i16 x 10)."""
HW_NAME: Final = "sim"

# Clock comparisons allow this much float error: poll times built by adding 1 ms steps do not
# land exactly on 20 ms or 1 s.
_EPS_S: Final = 1e-9
_I16_CURRENT_A: Final = I16_MAX / STATUS_CURRENT_SCALE
_TACHO_STEPS_PER_ETURN: Final = 6

# The order the firmware sends an enabled set in (send_can_status() in comm_can.c).
_STATUS_ORDER: Final = (
    Packet.STATUS,
    Packet.STATUS_2,
    Packet.STATUS_3,
    Packet.STATUS_4,
    Packet.STATUS_5,
    Packet.STATUS_6,
)


@dataclass
class VescSimStats:
    """Counters of one simulated VESC."""

    commands: int = 0
    """Commands obeyed."""
    bad_frames: int = 0
    """Frames addressed to this VESC ignored for a wrong DLC."""
    pings: int = 0
    """PINGs answered."""
    timeouts: int = 0
    """Times the command timeout released the motor."""
    status_frames: int = 0
    """Status frames returned by poll()."""


def _clamp(value: float, limit: float) -> float:
    if math.isnan(value):
        return 0.0
    return max(-limit, min(limit, value))


class SimVesc:
    """One simulated VESC with controller ID ``controller_id`` (0..254) driving ``motor``.

    ``motor_current_max_a`` is the motor current limit a SET_CURRENT_REL is a fraction of
    (default: the motor's full current).

    Raises:
        ValueError: a controller ID outside 0..254, a rate or timeout that is not > 0, a
            negative brake current, a limit that is not > 0, or a status packet that is none.
    """

    def __init__(
        self,
        controller_id: int,
        *,
        motor: Motor | None = None,
        status: frozenset[Packet] = frozenset(),
        status_hz: float = DEFAULT_STATUS_HZ,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        timeout_brake_current_a: float = 0.0,
        motor_current_max_a: float | None = None,
        hw_name: str = HW_NAME,
    ) -> None:
        if not 0 <= controller_id < BROADCAST_ID:
            raise ValueError(f"controller_id={controller_id!r} outside 0..{BROADCAST_ID - 1}")
        if not status <= frozenset(_STATUS_ORDER):
            raise ValueError(f"status={sorted(status)!r}: expected status packets only")
        self.node_id = controller_id
        self.motor = motor or Motor()
        self.faults = Faults()
        if motor_current_max_a is None:
            motor_current_max_a = self.motor.params.full_current_a
        for name, value in (
            ("status_hz", status_hz),
            ("timeout_s", timeout_s),
            ("motor_current_max_a", motor_current_max_a),
        ):
            if not value > 0:
                raise ValueError(f"{name}={value!r}: expected > 0")
        if not timeout_brake_current_a >= 0:
            raise ValueError(f"timeout_brake_current_a={timeout_brake_current_a!r}: expected >= 0")
        self.status = status
        self.status_hz = status_hz
        self.timeout_s = timeout_s
        self.timeout_brake_current_a = timeout_brake_current_a
        self.motor_current_max_a = motor_current_max_a
        self.hw_name = hw_name
        self.stats = VescSimStats()
        self.last_command: VescCommand | None = None
        """The last command obeyed (kept after it times out; see :attr:`commanded`)."""
        self.braking = False
        """A brake holds the rotor (SET_CURRENT_BRAKE, or the timeout's brake current)."""
        self.used_ah = 0.0
        self.charged_ah = 0.0
        self.used_wh = 0.0
        self.charged_wh = 0.0
        self.tachometer = 0.0
        self._last_command_s: float | None = None
        self._last_poll_s: float | None = None
        self._next_status_s: float | None = None

    @property
    def commanded(self) -> bool:
        """True while a command is in force (younger than the timeout)."""
        return self._last_command_s is not None

    # -- frames in --------------------------------------------------------------------------

    def handle(self, msg: can.Message, now_s: float) -> list[can.Message]:
        """Obey ``msg`` if it is a command or PING to this VESC (or to all); the PONG a PING
        gets."""
        if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
            return []
        arbitration_id = msg.arbitration_id
        if arbitration_id > 0xFFFF or (arbitration_id & 0xFF) not in (self.node_id, BROADCAST_ID):
            return []
        try:
            frame = decode(msg)
        except FrameError:
            self.stats.bad_frames += 1
            return []
        if frame is None:
            return []
        message = frame.message
        if isinstance(message, Ping):
            if self.faults.silent or message.sender_id > CONTROLLER_ID_MAX:
                return []
            self.stats.pings += 1
            pong = Pong(frame.controller_id, HwType.VESC)
            return [encode(VescFrame(message.sender_id, pong))]
        if isinstance(message, SetDuty | SetCurrent | SetCurrentRel | SetCurrentBrake | SetRpm):
            self._obey(message, now_s)
        return []

    def _obey(self, message: VescCommand, now_s: float) -> None:
        motor = self.motor
        self.braking = False
        match message:
            case SetDuty(duty=duty):
                motor.set_duty(duty)
            case SetCurrent(current_a=current):
                motor.set_current(current)
            case SetCurrentRel(fraction=fraction):
                motor.set_current(fraction * self.motor_current_max_a)
            case SetCurrentBrake():
                self.braking = True
                motor.brake()
            case SetRpm(erpm=erpm):
                motor.set_erpm(erpm)
        self.last_command = message
        self.stats.commands += 1
        self._last_command_s = now_s

    def _expire(self, now_s: float) -> None:
        """Release (or brake) the motor once the command in force is older than the timeout."""
        last = self._last_command_s
        if last is not None and now_s - last > self.timeout_s - _EPS_S:
            self._last_command_s = None
            self.stats.timeouts += 1
            log.debug("VESC %d: no command for %.0f ms", self.node_id, self.timeout_s * 1e3)
            if self.timeout_brake_current_a > 0:
                self.braking = True
                self.motor.brake()
            else:
                self.braking = False
                self.motor.set_current(0.0)

    # -- clock ------------------------------------------------------------------------------

    def poll(self, now_s: float, supply_v: float) -> list[can.Message]:
        """Advance the motor to ``now_s``, apply the timeout, and return what is due: the
        NOTIFY_BOOT at the first poll, the enabled status frames once a period."""
        motor = self.motor
        motor.stuck = self.faults.stuck_motor
        self._expire(now_s)
        first = self._last_poll_s is None
        dt = 0.0 if self._last_poll_s is None else max(0.0, now_s - self._last_poll_s)
        self._last_poll_s = now_s
        motor.step(dt, supply_v)
        charge_ah = self._input_current_a() * dt / 3600
        if charge_ah >= 0:
            self.used_ah += charge_ah
            self.used_wh += charge_ah * supply_v
        else:
            self.charged_ah -= charge_ah
            self.charged_wh -= charge_ah * supply_v
        self.tachometer += motor.erpm / 60 * _TACHO_STEPS_PER_ETURN * dt

        frames: list[can.Message] = []
        if first and not self.faults.silent:
            frames.append(encode(VescFrame(self.node_id, NotifyBoot(self.hw_name))))
        if not self.status:
            return frames
        due = self._next_status_s
        if due is None:
            due = self._next_status_s = now_s
        if now_s + _EPS_S < due:
            return frames
        # Next set one period on; after a stall, one period from now rather than a burst.
        period = 1.0 / self.status_hz
        due += period
        self._next_status_s = due if due > now_s else now_s + period
        if self.faults.silent:
            return frames
        status = [encode(VescFrame(self.node_id, record)) for record in self._status(supply_v)]
        if self.faults.corrupt:
            for msg in status:
                msg.data = msg.data[:-1]
                msg.dlc = len(msg.data)
        self.stats.status_frames += len(status)
        return frames + status

    def _input_current_a(self) -> float:
        """Battery current: what the motor model draws, its load part negative while a brake
        turns the rotor's energy back."""
        motor = self.motor
        if not self.braking:
            return motor.current_a
        idle = motor.params.idle_current_a
        return idle - (motor.current_a - idle)

    def _status(self, supply_v: float) -> list[VescStatus]:
        motor = self.motor
        sign = -1.0 if self.braking else 1.0
        motor_current = sign * abs(motor.motor_current_a)
        input_current = self._input_current_a()
        if self.faults.over_current:
            motor_current = input_current = OVER_CURRENT_A
        fet_temp = OVER_TEMPERATURE_C if self.faults.over_temperature else motor.mos_temp_c
        energy_max = I32_MAX / ENERGY_SCALE
        records: dict[Packet, VescStatus] = {
            Packet.STATUS: Status(
                round(_clamp(motor.erpm, I32_MAX)),
                _clamp(motor_current, _I16_CURRENT_A),
                _clamp(motor.duty, I16_MAX / STATUS_DUTY_SCALE),
            ),
            Packet.STATUS_2: Status2(
                _clamp(self.used_ah, energy_max), _clamp(self.charged_ah, energy_max)
            ),
            Packet.STATUS_3: Status3(
                _clamp(self.used_wh, energy_max), _clamp(self.charged_wh, energy_max)
            ),
            Packet.STATUS_4: Status4(
                _clamp(fet_temp, I16_MAX / TEMP_SCALE),
                _clamp(motor.motor_temp_c, I16_MAX / TEMP_SCALE),
                _clamp(input_current, _I16_CURRENT_A),
                0.0,  # no position control
            ),
            Packet.STATUS_5: Status5(
                round(_clamp(self.tachometer, I32_MAX)),
                _clamp(supply_v, I16_MAX / VOLTAGE_SCALE),
            ),
            Packet.STATUS_6: Status6(0.0, 0.0, 0.0, 0.0),
        }
        return [records[packet] for packet in _STATUS_ORDER if packet in self.status]


DEMO_SETTINGS: Final[dict[str, dict[str, Any]]] = {"can": {"bitrate": 1_000_000}}
"""The demo's octocopter at 200 Hz with STATUS 1-5 at 50 Hz needs about 510 kbit/s: a 1 Mbit/s
bus keeps it under the bus-load ceiling."""


def simulators(setup: EscSetup[VescKeys], motor_params: MotorParams | None) -> list[SimEsc]:
    """Simulated VESCs with ``setup``'s IDs, set up as docs/escs.md says: STATUS 1-5 at
    ``vesc_status_hz`` (none at 0, as from the factory) and the ``vesc_timeout_ms`` timeout."""
    keys = setup.keys
    status = STATUS_1_TO_5 if keys.vesc_status_hz > 0 else frozenset()
    return [
        SimVesc(
            controller_id,
            motor=Motor(motor_params),
            status=status,
            status_hz=keys.vesc_status_hz or DEFAULT_STATUS_HZ,
            timeout_s=keys.vesc_timeout_ms / 1000,
        )
        for controller_id in setup.ids
    ]
