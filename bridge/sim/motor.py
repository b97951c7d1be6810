"""A brushless motor with a propeller, and the battery that feeds them: just enough physics
for simulated ESCs to report believable telemetry.

- Speed follows its target with a first-order lag (``time_constant_s``). The target comes from
  the command: a duty (fraction of the supply voltage, rpm = duty x Kv x volts), a current
  (the speed at which the propeller's load draws that current), or a speed (erpm).
- A propeller's torque grows with rpm², its power with rpm³, so the supply current is
  ``idle + full x (rpm / full rpm)³`` and the phase current grows with rpm².
- The MOSFETs and the winding heat with I²R toward ``ambient + rise``, with their own lags.
- The battery sags with the total current through its internal resistance, and its open-circuit
  voltage falls as charge is drawn.

Pure arithmetic, no clock: :meth:`Motor.step` and :meth:`Battery.step` take the time step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class MotorParams:
    kv_rpm_per_v: float = 920.0
    pole_pairs: int = 7
    time_constant_s: float = 0.08
    """Speed response to a step in command (motor + propeller inertia)."""
    full_current_a: float = 20.0
    """Supply current at full speed (duty 1 at the nominal voltage)."""
    nominal_voltage_v: float = 16.8
    idle_current_a: float = 0.3
    """Current with the motor stopped or barely turning (ESC electronics, magnetising)."""
    phase_resistance_ohm: float = 0.06
    mos_resistance_ohm: float = 0.01
    mos_heat_c_per_w: float = 4.0
    """Steady-state MOSFET temperature rise per watt dissipated."""
    motor_heat_c_per_w: float = 1.5
    mos_time_constant_s: float = 8.0
    motor_time_constant_s: float = 40.0
    ambient_c: float = 25.0

    @property
    def full_rpm(self) -> float:
        return self.kv_rpm_per_v * self.nominal_voltage_v


class Motor:
    """One motor and propeller. Command it, then :meth:`step` it."""

    def __init__(self, params: MotorParams | None = None) -> None:
        self.params = params or MotorParams()
        self.rpm = 0.0
        """Mechanical rpm, negative in reverse."""
        self.current_a = self.params.idle_current_a
        """Supply (battery) current."""
        self.motor_current_a = 0.0
        """Phase current."""
        self.mos_temp_c = self.params.ambient_c
        self.motor_temp_c = self.params.ambient_c
        self.stuck = False
        """Fault: the rotor is blocked; commanded current flows, the speed stays 0."""
        self.duty = 0.0
        """The duty the ESC applies now (-1..1), for families that report it."""
        self._target_rpm = 0.0
        self._mode = "duty"
        self._setpoint = 0.0

    # -- commands (what an ESC does with a throttle, current or speed) ---------------------

    def set_duty(self, duty: float) -> None:
        """Fraction of the supply voltage, -1..1 (a throttle fraction maps here)."""
        self._mode, self._setpoint = "duty", max(-1.0, min(1.0, duty))

    def set_current(self, current_a: float) -> None:
        """Motor current: the speed at which the propeller's load draws it (negative: reverse)."""
        self._mode, self._setpoint = "current", current_a

    def set_erpm(self, erpm: float) -> None:
        self._mode, self._setpoint = "erpm", erpm

    def brake(self) -> None:
        """Stop actively (brake current): speed goes to 0 with the same lag."""
        self._mode, self._setpoint = "duty", 0.0

    # -- physics ----------------------------------------------------------------------------

    def step(self, dt_s: float, supply_v: float) -> None:
        p = self.params
        full_rpm = p.kv_rpm_per_v * max(supply_v, 0.0)
        if self._mode == "duty":
            target = self._setpoint * full_rpm
        elif self._mode == "current":
            fraction = min(abs(self._setpoint) / p.full_current_a, 1.0)
            target = math.copysign(full_rpm * fraction ** (1 / 3), self._setpoint)
        else:
            target = max(-full_rpm, min(full_rpm, self._setpoint / p.pole_pairs))
        if self.stuck:
            target = 0.0
        self._target_rpm = target
        alpha = 1.0 - math.exp(-dt_s / p.time_constant_s) if dt_s > 0 else 0.0
        self.rpm += (target - self.rpm) * alpha
        if self.stuck:
            self.rpm = 0.0
        load = abs(self.rpm) / p.full_rpm
        if self.stuck:
            # A blocked rotor has no back-EMF: it draws what the command pushes, up to the
            # ESC's full current, and turns it all into heat.
            if self._mode == "current":
                stall = min(abs(self._setpoint), p.full_current_a)
            else:
                stall = min(abs(self._setpoint), 1.0) * p.full_current_a
            self.current_a = p.idle_current_a + stall
            self.motor_current_a = stall
        else:
            self.current_a = p.idle_current_a + p.full_current_a * load**3
            self.motor_current_a = p.full_current_a * 1.4 * load**2
        self.duty = self.rpm / full_rpm if full_rpm > 0 else 0.0
        self._heat(dt_s)

    def _heat(self, dt_s: float) -> None:
        p = self.params
        phase_sq = self.motor_current_a**2
        mos_target = p.ambient_c + p.mos_heat_c_per_w * phase_sq * p.mos_resistance_ohm
        motor_target = p.ambient_c + p.motor_heat_c_per_w * phase_sq * p.phase_resistance_ohm
        self.mos_temp_c += (mos_target - self.mos_temp_c) * (
            1.0 - math.exp(-dt_s / p.mos_time_constant_s)
        )
        self.motor_temp_c += (motor_target - self.motor_temp_c) * (
            1.0 - math.exp(-dt_s / p.motor_time_constant_s)
        )

    @property
    def erpm(self) -> float:
        return self.rpm * self.params.pole_pairs


@dataclass
class Battery:
    """A LiPo pack: open-circuit voltage by charge left, sag by internal resistance."""

    cells: int = 4
    capacity_mah: float = 5000.0
    internal_resistance_ohm: float = 0.02
    drawn_mah: float = 0.0
    current_a: float = 0.0

    @property
    def open_circuit_v(self) -> float:
        left = max(0.0, 1.0 - self.drawn_mah / self.capacity_mah)
        return self.cells * (3.5 + 0.7 * left)  # 4.2 V per cell full, 3.5 V empty

    @property
    def voltage_v(self) -> float:
        return max(0.0, self.open_circuit_v - self.internal_resistance_ohm * self.current_a)

    def step(self, dt_s: float, total_current_a: float) -> None:
        self.current_a = total_current_a
        self.drawn_mah += total_current_a * dt_s / 3.6
