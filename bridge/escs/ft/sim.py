"""A simulated Flipsky FT ESC (docs/protocols.md §4): a pure state machine with an explicit clock.

It obeys every FT command addressed to its ESC ID, with or without CRC, and sends the three
real-time telemetry frames every 10 ms while a command is in force. Frames go through the
production codec (:mod:`bridge.escs.ft.codec`), so the simulator and the bridge read the wire alike.

What each command does to the motor (:class:`~bridge.sim.motor.Motor`):

========================  ===============================================================
 command                   effect
========================  ===============================================================
 SetCurrent                ``motor.set_current(current_a)``
 SetCurrentPercent         ``motor.set_current(fraction x full_scale_current_a)``
 SetCurrentBrake           ``motor.brake()``
 SetCurrentBrakePercent    ``motor.brake()``
 SetDuty                   ``motor.set_duty(duty)``
 SetErpm                   ``motor.set_erpm(erpm)``
 SetPosition               accepted and held: the rotor is held still (``motor.brake()``)
 SetIdCurrent              accepted and held: a parking hold (``motor.brake()``)
========================  ===============================================================

Decisions where the spec is silent
----------------------------------
- A command is in force for 450 ms after it arrives (docs/protocols.md §4.4); at 450 ms it is
  dropped and the motor released (``motor.set_current(0)``: it coasts down with its lag).
- Telemetry is sent only while a command is in force: an ESC that was never commanded, or
  whose command timed out, is quiet until the next command, which restarts telemetry at
  once. The seed only says the frames are sent "every 10 ms"; this follows the project's
  reading that FT goes quiet after 450 ms without a command. ``idle_telemetry=True`` keeps
  the frames coming regardless.
- The gear byte is accepted and held (``gear``) but limits nothing.
- A command with a bad CRC is ignored and counted (``stats.crc_errors``); one with the wrong
  DLC or a gear byte above 4 likewise (``stats.bad_frames``). Neither refreshes the timeout.
- Reported motor current carries the sign of the rotation (positive when stopped); battery
  current is what the motor draws. Values are clamped to their wire fields, never refused.
- Faults: ``over_temperature`` reports a MOSFET at 300 degC, ``over_current`` motor and
  battery currents of 5000 A, ``corrupt`` flips the CRC of every telemetry frame,
  ``silent`` sends nothing (commands still act), ``stuck_motor`` blocks the rotor.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Final

import can

from bridge.errors import CrcError, FrameError, NotExtendedIdError
from bridge.escs.family import EscSetup
from bridge.escs.ft import codec, records
from bridge.escs.ft.keys import FtKeys
from bridge.sim.base import Faults, SimEsc
from bridge.sim.motor import Motor, MotorParams

__all__ = [
    "COMMAND_TIMEOUT_S",
    "DEMO_SETTINGS",
    "OVER_CURRENT_A",
    "OVER_TEMPERATURE_C",
    "TELEMETRY_PERIOD_S",
    "FtSimStats",
    "SimFt",
    "simulators",
]

log = logging.getLogger(__name__)

COMMAND_TIMEOUT_S: Final = 0.450
"""A command not repeated within this is dropped (docs/protocols.md §4.4)."""
TELEMETRY_PERIOD_S: Final = 0.010
"""Each of the three real-time frames is sent this often (docs/protocols.md §4.6)."""
OVER_TEMPERATURE_C: Final = 300.0
"""MOSFET temperature reported under the over_temperature fault (fits i16 x 100)."""
OVER_CURRENT_A: Final = 5000.0
"""Motor and battery current reported under the over_current fault (fits i24 x 1000)."""

DEMO_SETTINGS: Final[dict[str, dict[str, Any]]] = {
    # 100 commands per ESC per second, and a 1 Mbit/s bus so that eight ESCs' real-time
    # telemetry (3 frames x 100 Hz each) stays under the bus-load ceiling.
    "output": {"rate_hz": 100},
    "can": {"bitrate": 1_000_000},
    "escs": {"ft_mode": "current"},
}
"""What the demo sets for FT ESCs over its own settings."""

# Clock comparisons allow this much float error: poll times built by adding 1 ms steps do not
# land exactly on 10 ms or 450 ms.
_EPS_S: Final = 1e-9

# Wire field limits of the telemetry values (bridge/escs/ft/): i24 and i16 at their scales.
_I24_MAX: Final = (1 << 23) - 1
_CURRENT_MAX_A: Final = _I24_MAX / 1000
_DUTY_MAX: Final = _I24_MAX / 1000
_I16_MAX: Final = (1 << 15) - 1
_TEMP_MAX_C: Final = _I16_MAX / 100
_VOLTAGE_MAX_V: Final = _I16_MAX / 100


@dataclass
class FtSimStats:
    """Counters of one simulated FT ESC."""

    commands: int = 0
    """Commands obeyed."""
    crc_errors: int = 0
    """Commands addressed to this ESC ignored for a bad CRC."""
    bad_frames: int = 0
    """Commands addressed to this ESC ignored for a wrong DLC or gear byte."""
    timeouts: int = 0
    """Times a command was dropped after 450 ms without a new one."""
    telemetry_frames: int = 0
    """Telemetry frames returned by poll()."""


def _clamp(value: float, limit: float) -> float:
    if math.isnan(value):
        return 0.0
    return max(-limit, min(limit, value))


class SimFt:
    """One simulated FT ESC with ID ``esc_id`` (0..255) driving ``motor``.

    ``full_scale_current_a`` is the "configured motor current" a current-percent command is
    a fraction of (default: the motor's full current); ``full_scale_brake_current_a`` the
    brake current of the brake-percent command (default: the same).

    Raises:
        ValueError: ``esc_id`` outside 0..255 or a full-scale current that is not > 0.
    """

    def __init__(
        self,
        esc_id: int,
        *,
        motor: Motor | None = None,
        full_scale_current_a: float | None = None,
        full_scale_brake_current_a: float | None = None,
        idle_telemetry: bool = False,
    ) -> None:
        if not 0 <= esc_id <= 255:
            raise ValueError(f"esc_id={esc_id!r} outside 0..255")
        self.node_id = esc_id
        self.motor = motor or Motor()
        self.faults = Faults()
        if full_scale_current_a is None:
            full_scale_current_a = self.motor.params.full_current_a
        if full_scale_brake_current_a is None:
            full_scale_brake_current_a = full_scale_current_a
        self.full_scale_current_a = full_scale_current_a
        self.full_scale_brake_current_a = full_scale_brake_current_a
        for name in ("full_scale_current_a", "full_scale_brake_current_a"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"{name}={value!r}: expected a current > 0 A")
        self.idle_telemetry = idle_telemetry
        self.stats = FtSimStats()
        self.last_command: records.FtCommand | None = None
        """The last command obeyed (kept after it times out; see :attr:`commanded`)."""
        self.gear: records.Gear = records.Gear.NONE
        """Gear byte of the last geared command: held, limits nothing."""
        self.brake_current_a = 0.0
        """Brake current last commanded (A); the motor model brakes at any current."""
        self._last_command_s: float | None = None
        self._last_poll_s: float | None = None
        self._next_telemetry_s: float | None = None

    @property
    def esc_id(self) -> int:
        return self.node_id

    @property
    def commanded(self) -> bool:
        """True while a command is in force (less than 450 ms old)."""
        return self._last_command_s is not None

    # -- frames in --------------------------------------------------------------------------

    def handle(self, msg: can.Message, now_s: float) -> list[can.Message]:
        """Obey ``msg`` if it is an FT command to this ESC; FT never answers, so always []."""
        if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
            return []
        if (msg.arbitration_id >> 8) != self.node_id or msg.arbitration_id > 0xFFFF:
            return []
        try:
            frame = codec.decode(msg)
        except NotExtendedIdError:
            return []
        except CrcError:
            self.stats.crc_errors += 1
            return []
        except FrameError:
            self.stats.bad_frames += 1
            return []
        if frame is not None:
            self._obey(frame, now_s)
        return []

    def _expire(self, now_s: float) -> None:
        """Drop the command in force once it is 450 ms old: the motor is released."""
        last = self._last_command_s
        if last is not None and now_s - last >= COMMAND_TIMEOUT_S - _EPS_S:
            self._last_command_s = None
            self.stats.timeouts += 1
            self.motor.set_current(0.0)
            log.debug("FT ESC %d: no command for %.0f ms", self.node_id, COMMAND_TIMEOUT_S * 1e3)

    def _obey(self, frame: records.FtFrame, now_s: float) -> None:
        message = frame.message
        if not isinstance(
            message, records.RealtimeData0 | records.RealtimeData1 | records.RealtimeData2
        ):
            self._expire(now_s)  # a late command: the old one timed out before it came
        motor = self.motor
        match message:
            case records.SetCurrent(current_a=current, gear=gear):
                motor.set_current(current)
                self.gear = gear
            case records.SetCurrentPercent(fraction=fraction, gear=gear):
                motor.set_current(fraction * self.full_scale_current_a)
                self.gear = records.Gear.NONE if gear is None else gear
            case records.SetDuty(duty=duty, gear=gear):
                motor.set_duty(duty)
                self.gear = gear
            case records.SetErpm(erpm=erpm, gear=gear):
                motor.set_erpm(erpm)
                self.gear = gear
            case records.SetCurrentBrake(current_a=current):
                self.brake_current_a = abs(current)
                motor.brake()
            case records.SetCurrentBrakePercent(fraction=fraction):
                self.brake_current_a = abs(fraction) * self.full_scale_brake_current_a
                motor.brake()
            case records.SetPosition(gear=gear):
                motor.brake()
                self.gear = gear
            case records.SetIdCurrent():
                motor.brake()
            case _:  # telemetry of another ESC with our ID: not a command
                return
        self.last_command = message
        self.stats.commands += 1
        self._last_command_s = now_s

    # -- clock ------------------------------------------------------------------------------

    def poll(self, now_s: float, supply_v: float) -> list[can.Message]:
        """Advance the motor to ``now_s``, drop a command older than 450 ms, and return the
        telemetry frames due (three every 10 ms, at most one set per call: no bursts)."""
        motor = self.motor
        motor.stuck = self.faults.stuck_motor
        self._expire(now_s)
        dt = 0.0 if self._last_poll_s is None else max(0.0, now_s - self._last_poll_s)
        self._last_poll_s = now_s
        motor.step(dt, supply_v)

        if not (self.commanded or self.idle_telemetry):
            return []
        due = self._next_telemetry_s
        if due is None:
            due = self._next_telemetry_s = now_s
        if now_s + _EPS_S < due:
            return []
        # Next set one period on; after a stall, one period from now rather than a burst.
        due += TELEMETRY_PERIOD_S
        self._next_telemetry_s = due if due > now_s else now_s + TELEMETRY_PERIOD_S
        if self.faults.silent:
            return []
        frames = [
            codec.encode(records.FtFrame(self.node_id, record))
            for record in self._telemetry(supply_v)
        ]
        if self.faults.corrupt:
            for frame in frames:
                frame.data[-1] ^= 0xFF  # the CRC's low byte: never matches again
        self.stats.telemetry_frames += len(frames)
        return frames

    def _telemetry(
        self, supply_v: float
    ) -> tuple[records.RealtimeData0, records.RealtimeData1, records.RealtimeData2]:
        motor = self.motor
        motor_current = math.copysign(motor.motor_current_a, motor.rpm or 1.0)
        battery_current = motor.current_a
        if self.faults.over_current:
            motor_current = math.copysign(OVER_CURRENT_A, motor_current)
            battery_current = OVER_CURRENT_A
        mos_temp = OVER_TEMPERATURE_C if self.faults.over_temperature else motor.mos_temp_c
        erpm = _clamp(motor.rpm * motor.params.pole_pairs, _I24_MAX)
        return (
            records.RealtimeData0(
                _clamp(motor_current, _CURRENT_MAX_A), _clamp(battery_current, _CURRENT_MAX_A)
            ),
            records.RealtimeData1(round(erpm), _clamp(motor.duty, _DUTY_MAX)),
            records.RealtimeData2(
                _clamp(mos_temp, _TEMP_MAX_C),
                _clamp(motor.motor_temp_c, _TEMP_MAX_C),
                _clamp(supply_v, _VOLTAGE_MAX_V),
            ),
        )


def simulators(setup: EscSetup[FtKeys], motor_params: MotorParams | None) -> list[SimEsc]:
    """A simulated FT ESC for each of ``setup.ids``, each with a motor of its own."""
    return [SimFt(esc_id, motor=Motor(motor_params)) for esc_id in setup.ids]
