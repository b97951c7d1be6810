"""The motor and battery models: lag, load, heat and sag, by the numbers."""

from __future__ import annotations

import math

import pytest

from bridge.sim.motor import Battery, Motor, MotorParams

PARAMS = MotorParams()
V = PARAMS.nominal_voltage_v


def run(motor: Motor, seconds: float, dt_s: float = 0.001, volts: float = V) -> None:
    for _ in range(round(seconds / dt_s)):
        motor.step(dt_s, volts)


def test_speed_follows_a_duty_step_with_the_time_constant() -> None:
    motor = Motor()
    motor.set_duty(0.5)
    run(motor, PARAMS.time_constant_s)
    target = 0.5 * PARAMS.full_rpm
    assert motor.rpm == pytest.approx(target * (1 - math.exp(-1)), rel=0.01)
    run(motor, 10 * PARAMS.time_constant_s)
    assert motor.rpm == pytest.approx(target, rel=1e-3)
    assert motor.duty == pytest.approx(0.5, rel=1e-3)
    assert motor.erpm == pytest.approx(motor.rpm * PARAMS.pole_pairs)


def test_reverse_duty_turns_backwards() -> None:
    motor = Motor()
    motor.set_duty(-0.25)
    run(motor, 1.0)
    assert motor.rpm == pytest.approx(-0.25 * PARAMS.full_rpm, rel=1e-3)


def test_current_grows_with_the_cube_of_speed() -> None:
    motor = Motor()
    motor.set_duty(1.0)
    run(motor, 1.0)
    full = motor.current_a
    assert full == pytest.approx(PARAMS.idle_current_a + PARAMS.full_current_a, rel=1e-3)
    motor.set_duty(0.5)
    run(motor, 1.0)
    half = motor.current_a
    assert half == pytest.approx(PARAMS.idle_current_a + PARAMS.full_current_a / 8, rel=1e-3)


def test_a_current_command_settles_where_the_load_draws_it() -> None:
    motor = Motor()
    motor.set_current(PARAMS.full_current_a / 8)
    run(motor, 1.0)
    assert motor.rpm == pytest.approx(0.5 * PARAMS.full_rpm, rel=1e-3)
    motor.set_erpm(-7000)
    run(motor, 1.0)
    assert motor.rpm == pytest.approx(-7000 / PARAMS.pole_pairs, rel=1e-3)


def test_a_stuck_rotor_stays_still_draws_current_and_heats() -> None:
    motor = Motor()
    motor.stuck = True
    motor.set_duty(0.5)
    run(motor, 5.0, dt_s=0.01)
    assert motor.rpm == 0.0
    assert motor.current_a == pytest.approx(PARAMS.idle_current_a + 0.5 * PARAMS.full_current_a)
    assert motor.mos_temp_c > PARAMS.ambient_c + 1.0


def test_temperatures_rise_toward_their_steady_state() -> None:
    motor = Motor()
    motor.set_duty(1.0)
    run(motor, 300.0, dt_s=0.01)
    phase = motor.motor_current_a
    mos_rise = PARAMS.mos_heat_c_per_w * phase**2 * PARAMS.mos_resistance_ohm
    assert motor.mos_temp_c == pytest.approx(PARAMS.ambient_c + mos_rise, rel=1e-3)
    assert motor.motor_temp_c > PARAMS.ambient_c


def test_battery_sags_with_current_and_charge_drawn() -> None:
    battery = Battery(cells=4, capacity_mah=1000, internal_resistance_ohm=0.05)
    assert battery.voltage_v == pytest.approx(16.8)
    battery.step(1.0, 20.0)
    assert battery.voltage_v == pytest.approx(battery.open_circuit_v - 1.0)
    battery.step(3600 / 20 - 1.0, 20.0)  # the rest of 1000 mAh at 20 A
    assert battery.drawn_mah == pytest.approx(1000)
    assert battery.open_circuit_v == pytest.approx(4 * 3.5)
