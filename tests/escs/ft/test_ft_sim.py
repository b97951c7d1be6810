"""The simulated FT ESC (bridge/escs/ft/sim.py), driven with real encoded commands and an
explicit clock: every command kind with and without CRC, bad frames, the 10 ms telemetry
cadence, the motor's lag, the 450 ms command timeout and each fault."""

from __future__ import annotations

import itertools
import math
from typing import TypeVar

import can
import pytest

from bridge.errors import CrcError
from bridge.escs.ft import codec, records
from bridge.escs.ft.sim import OVER_CURRENT_A, OVER_TEMPERATURE_C, SimFt
from bridge.sim.motor import Motor, MotorParams

ESC = 3
SUPPLY_V = 16.8
PARAMS = MotorParams()
FULL_RPM = PARAMS.kv_rpm_per_v * SUPPLY_V  # at SUPPLY_V, which is the nominal voltage
STEP_S = 0.001

T = TypeVar("T", records.RealtimeData0, records.RealtimeData1, records.RealtimeData2)


def command(record: records.FtCommand, esc_id: int = ESC) -> can.Message:
    return codec.encode(records.FtFrame(esc_id, record))


class Clock:
    """Drives one SimFt like the runner does: polls every millisecond, commands in between."""

    def __init__(self, esc: SimFt) -> None:
        self.esc = esc
        self.tick = 0
        self.sent: list[tuple[float, can.Message]] = []

    @property
    def now(self) -> float:
        return self.tick * STEP_S

    def send(self, msg: can.Message) -> None:
        assert self.esc.handle(msg, self.now) == []  # FT never answers a command

    def run(self, seconds: float, repeat: can.Message | None = None, every_s: float = 0.1) -> None:
        """Poll for ``seconds``; with ``repeat``, send it first and then every ``every_s``."""
        every = round(every_s / STEP_S)
        for i in range(round(seconds / STEP_S)):
            if repeat is not None and i % every == 0:
                self.send(repeat)
            for msg in self.esc.poll(self.now, SUPPLY_V):
                self.sent.append((self.now, msg))
            self.tick += 1

    def telemetry(self, kind: type[T]) -> list[T]:
        records: list[T] = []
        for _, msg in self.sent:
            frame = codec.decode(msg)
            assert frame is not None and frame.esc_id == ESC
            if isinstance(frame.message, kind):
                records.append(frame.message)
        return records

    def last(self, kind: type[T]) -> T:
        return self.telemetry(kind)[-1]


def rpm_for_current(current_a: float) -> float:
    """Steady speed for a motor current (the propeller load, bridge/sim/motor.py)."""
    fraction = min(abs(current_a) / PARAMS.full_current_a, 1.0)
    return math.copysign(FULL_RPM * fraction ** (1 / 3), current_a)


# One record per FT command ID (all 16), with the steady rpm it drives the motor to; None: the
# motor is held still (brake, position, d-axis current).
SPINNING: list[tuple[records.FtCommand, float | None]] = [
    (records.SetCurrent(10.0, records.Gear.NONE, crc=True), rpm_for_current(10.0)),
    (records.SetCurrent(-5.0, records.Gear.HIGH, crc=False), rpm_for_current(-5.0)),
    (records.SetDuty(0.5, records.Gear.NONE, crc=True), 0.5 * FULL_RPM),
    (records.SetDuty(-0.25, records.Gear.LOW, crc=False), -0.25 * FULL_RPM),
    (records.SetCurrentPercent(0.5, None, crc=True), rpm_for_current(10.0)),
    (records.SetCurrentPercent(0.25, records.Gear.MIDDLE, crc=True), rpm_for_current(5.0)),
    (records.SetCurrentPercent(-0.5, records.Gear.NONE, crc=False), rpm_for_current(-10.0)),
    (records.SetErpm(35_000, records.Gear.NONE, crc=True), 5000.0),
    (records.SetErpm(-14_000, records.Gear.REVERSE, crc=False), -2000.0),
    (records.SetCurrentBrake(5.0, crc=True), None),
    (records.SetCurrentBrake(5.0, crc=False), None),
    (records.SetCurrentBrakePercent(0.25, crc=True), None),
    (records.SetCurrentBrakePercent(0.25, crc=False), None),
    (records.SetPosition(45.6, records.Gear.NONE, crc=True), None),
    (records.SetPosition(-90.0, records.Gear.NONE, crc=False), None),
    (records.SetIdCurrent(2.0), None),
]


def test_the_table_covers_every_command() -> None:
    ids = {command(record).arbitration_id & 0xFF for record, _ in SPINNING}
    assert ids == set(records.COMMAND_RECORDS)


@pytest.mark.parametrize(("record", "rpm"), SPINNING, ids=lambda v: repr(v)[:40])
def test_every_command_drives_the_motor(record: records.FtCommand, rpm: float | None) -> None:
    esc = SimFt(ESC)
    clock = Clock(esc)
    clock.run(0.6, command(records.SetDuty(0.3)))  # spinning first, so a brake or hold shows
    assert esc.motor.rpm == pytest.approx(0.3 * FULL_RPM, rel=1e-3)
    clock.run(1.0, command(record))
    assert esc.last_command == record
    assert esc.stats.commands == 6 + 10
    if rpm is None:
        assert abs(esc.motor.rpm) < 1.0
    else:
        assert esc.motor.rpm == pytest.approx(rpm, rel=1e-3)
    assert esc.commanded  # repeated within 450 ms: still in force, telemetry still flowing
    assert clock.sent[-1][0] > clock.now - 0.011


def test_brake_commands_record_the_brake_current() -> None:
    esc = SimFt(ESC, full_scale_brake_current_a=40.0)
    esc.handle(command(records.SetCurrentBrake(-7.5, crc=False)), 0.0)
    assert esc.brake_current_a == 7.5
    esc.handle(command(records.SetCurrentBrakePercent(0.25)), 0.01)
    assert esc.brake_current_a == 10.0


def test_current_percent_is_of_the_configured_full_scale() -> None:
    esc = SimFt(ESC, full_scale_current_a=10.0)
    clock = Clock(esc)
    clock.run(1.0, command(records.SetCurrentPercent(0.5, None)))
    assert esc.motor.rpm == pytest.approx(rpm_for_current(5.0), rel=1e-3)


def test_gear_is_held() -> None:
    esc = SimFt(ESC)
    esc.handle(command(records.SetDuty(0.1, records.Gear.MIDDLE, crc=False)), 0.0)
    assert esc.gear == records.Gear.MIDDLE


def bad_crc(msg: can.Message) -> can.Message:
    data = bytearray(msg.data)
    data[-1] ^= 0x01
    return can.Message(arbitration_id=msg.arbitration_id, data=data, is_extended_id=True)


def test_a_command_with_a_bad_crc_is_ignored_and_counted() -> None:
    esc = SimFt(ESC)
    clock = Clock(esc)
    clock.run(0.5, command(records.SetDuty(0.2)))
    clock.run(0.3, bad_crc(command(records.SetDuty(0.9))))
    assert esc.stats.crc_errors == 3
    assert esc.stats.commands == 5
    assert esc.last_command == records.SetDuty(0.2)
    assert esc.motor.rpm == pytest.approx(0.2 * FULL_RPM, rel=1e-3)
    # Bad frames do not refresh the timeout either: the last good command was at 0.4 s.
    assert esc.commanded
    clock.run(0.1, bad_crc(command(records.SetDuty(0.9))))
    assert not esc.commanded
    assert esc.stats.timeouts == 1


def test_a_malformed_command_is_ignored_and_counted() -> None:
    esc = SimFt(ESC)
    good = command(records.SetCurrent(10.0, crc=False))
    short = can.Message(arbitration_id=good.arbitration_id, data=good.data[:4], is_extended_id=True)
    bad_gear = can.Message(
        arbitration_id=good.arbitration_id, data=good.data[:4] + b"\x07", is_extended_id=True
    )
    for msg in (short, bad_gear):
        assert esc.handle(msg, 0.0) == []
    assert esc.stats.bad_frames == 2
    assert esc.stats.commands == 0
    assert esc.poll(0.0, SUPPLY_V) == []


def test_frames_for_other_escs_and_protocols_are_ignored() -> None:
    esc = SimFt(ESC)
    others = [
        command(records.SetDuty(0.5), esc_id=ESC + 1),
        bad_crc(command(records.SetDuty(0.5), esc_id=ESC + 1)),
        can.Message(arbitration_id=(ESC << 8) | 0x02, data=b"\x00" * 7, is_extended_id=False),
        can.Message(arbitration_id=0x1000000 | (ESC << 8) | 0x02, data=b"\x00" * 7),
        can.Message(arbitration_id=(ESC << 8) | 0x7F, data=b"\x00" * 4),  # no such command
        codec.encode(
            records.FtFrame(ESC, records.RealtimeData1(1000, 0.1))
        ),  # telemetry, not a command
    ]
    for msg in others:
        assert esc.handle(msg, 0.0) == []
    assert esc.stats.commands == esc.stats.crc_errors == esc.stats.bad_frames == 0
    assert esc.poll(0.0, SUPPLY_V) == []


def test_three_frames_every_10_ms_over_a_simulated_second() -> None:
    esc = SimFt(ESC)
    clock = Clock(esc)
    clock.run(1.0, command(records.SetDuty(0.4)))
    assert len(clock.sent) == 300
    times = sorted({t for t, _ in clock.sent})
    assert len(times) == 100
    assert all(b - a == pytest.approx(0.010) for a, b in itertools.pairwise(times))
    for t in times:
        ids = [m.arbitration_id for ts, m in clock.sent if ts == t]
        assert ids == [(ESC << 8) | kind for kind in records.Telemetry]
    assert all(m.dlc == 8 and m.is_extended_id for _, m in clock.sent)
    assert esc.stats.telemetry_frames == 300


def test_no_burst_after_a_stall() -> None:
    esc = SimFt(ESC)
    esc.handle(command(records.SetDuty(0.4)), 0.0)
    assert len(esc.poll(0.0, SUPPLY_V)) == 3
    esc.handle(command(records.SetDuty(0.4)), 0.1)
    assert len(esc.poll(0.1, SUPPLY_V)) == 3  # 100 ms late: one set, not ten
    assert esc.poll(0.105, SUPPLY_V) == []
    assert len(esc.poll(0.110, SUPPLY_V)) == 3


def test_telemetry_reports_the_motor() -> None:
    esc = SimFt(ESC)
    clock = Clock(esc)
    clock.run(1.0, command(records.SetDuty(-0.5)))
    motor = esc.motor
    data0 = clock.last(records.RealtimeData0)
    data1 = clock.last(records.RealtimeData1)
    data2 = clock.last(records.RealtimeData2)
    assert data1.erpm == pytest.approx(-0.5 * FULL_RPM * PARAMS.pole_pairs, rel=1e-3)
    assert data1.erpm == round(motor.rpm * PARAMS.pole_pairs)
    assert data1.duty == pytest.approx(-0.5, abs=0.001)
    assert data0.motor_current_a == pytest.approx(-motor.motor_current_a, abs=0.001)
    assert data0.motor_current_a < -1.0  # signed by the direction of rotation
    assert data0.battery_current_a == pytest.approx(motor.current_a, abs=0.001)
    assert data0.battery_current_a > PARAMS.idle_current_a
    assert data2.battery_voltage_v == pytest.approx(SUPPLY_V)
    assert data2.mosfet_temp_c == pytest.approx(motor.mos_temp_c, abs=0.01)
    assert data2.motor_temp_c == pytest.approx(motor.motor_temp_c, abs=0.01)
    assert data2.mosfet_temp_c > PARAMS.ambient_c  # it heats while it works


def test_rpm_follows_the_command_with_the_motors_lag() -> None:
    esc = SimFt(ESC, motor=Motor(MotorParams(time_constant_s=0.1)))
    clock = Clock(esc)
    clock.run(0.1, command(records.SetDuty(0.6)))
    target = 0.6 * FULL_RPM
    assert esc.motor.rpm == pytest.approx(target * (1 - math.exp(-1)), rel=0.02)
    clock.run(0.9, command(records.SetDuty(0.6)))
    erpms = [r.erpm for r in clock.telemetry(records.RealtimeData1)]
    assert erpms == sorted(erpms)
    assert erpms[0] < 0.1 * target * PARAMS.pole_pairs
    assert erpms[-1] == pytest.approx(target * PARAMS.pole_pairs, rel=1e-3)


def test_450_ms_without_a_command_stops_telemetry_and_motor() -> None:
    esc = SimFt(ESC)
    clock = Clock(esc)
    clock.run(0.2, command(records.SetDuty(0.5)), every_s=0.1)  # commands at 0.0 and 0.1 s
    clock.run(0.341)  # the last command came at 0.1 s; now 0.541 s
    sets = sorted({t for t, _ in clock.sent})
    assert sets[-1] == pytest.approx(0.54)  # 440 ms after the last command: still sending
    assert esc.commanded
    spinning = esc.motor.rpm
    assert spinning > 0.9 * 0.5 * FULL_RPM
    clock.run(0.5)
    assert sorted({t for t, _ in clock.sent})[-1] == pytest.approx(0.54)  # none at 0.55 on
    assert not esc.commanded
    assert esc.stats.timeouts == 1
    assert esc.motor.rpm < 0.01 * spinning  # released at 0.55 s: coasted down since
    # The next command brings it back, telemetry at once.
    resume_at = clock.now
    clock.run(0.3, command(records.SetDuty(0.5)))
    assert min(t for t, _ in clock.sent if t >= resume_at) == pytest.approx(resume_at)
    assert esc.motor.rpm > 0.9 * spinning


def test_a_late_command_first_times_out_the_old_one() -> None:
    esc = SimFt(ESC)
    esc.handle(command(records.SetDuty(0.5)), 0.0)
    assert len(esc.poll(0.0, SUPPLY_V)) == 3
    esc.handle(command(records.SetDuty(0.2)), 1.0)  # no poll in between
    assert esc.stats.timeouts == 1
    assert esc.commanded
    assert len(esc.poll(1.0, SUPPLY_V)) == 3


def test_a_never_commanded_esc_is_quiet_unless_idle_telemetry() -> None:
    quiet = Clock(SimFt(ESC))
    quiet.run(1.0)
    assert quiet.sent == []
    chatty = Clock(SimFt(ESC, idle_telemetry=True))
    chatty.run(1.0)
    assert len(chatty.sent) == 300
    data1 = chatty.last(records.RealtimeData1)
    assert data1.erpm == 0


def test_fault_over_temperature() -> None:
    esc = SimFt(ESC)
    esc.faults.over_temperature = True
    clock = Clock(esc)
    clock.run(0.1, command(records.SetDuty(0.2)))
    data2 = clock.last(records.RealtimeData2)
    assert data2.mosfet_temp_c == OVER_TEMPERATURE_C
    assert data2.motor_temp_c < 30.0


def test_fault_over_current() -> None:
    esc = SimFt(ESC)
    esc.faults.over_current = True
    clock = Clock(esc)
    clock.run(0.1, command(records.SetDuty(0.2)))
    data0 = clock.last(records.RealtimeData0)
    assert data0.motor_current_a == OVER_CURRENT_A
    assert data0.battery_current_a == OVER_CURRENT_A


def test_fault_corrupt_breaks_every_telemetry_crc() -> None:
    esc = SimFt(ESC)
    esc.faults.corrupt = True
    clock = Clock(esc)
    clock.run(0.2, command(records.SetDuty(0.2)))
    assert len(clock.sent) == 60  # still on time, just unreadable
    for _, msg in clock.sent:
        with pytest.raises(CrcError):
            codec.decode(msg)
    esc.faults.corrupt = False
    clock.sent.clear()
    clock.run(0.1, command(records.SetDuty(0.2)))
    assert all(codec.decode(msg) is not None for _, msg in clock.sent)


def test_fault_silent_sends_nothing_but_obeys() -> None:
    esc = SimFt(ESC)
    esc.faults.silent = True
    clock = Clock(esc)
    clock.run(1.0, command(records.SetDuty(0.5)))
    assert clock.sent == []
    assert esc.motor.rpm == pytest.approx(0.5 * FULL_RPM, rel=1e-3)
    esc.faults.silent = False
    clock.run(0.05, command(records.SetDuty(0.5)))
    assert len(clock.sent) == 15


def test_fault_stuck_motor() -> None:
    esc = SimFt(ESC)
    esc.faults.stuck_motor = True
    clock = Clock(esc)
    clock.run(0.5, command(records.SetDuty(0.5)))
    data0, data1 = clock.last(records.RealtimeData0), clock.last(records.RealtimeData1)
    assert data1.erpm == 0
    assert data0.motor_current_a == pytest.approx(0.5 * PARAMS.full_current_a, abs=0.001)
    esc.faults.stuck_motor = False
    clock.run(1.0, command(records.SetDuty(0.5)))
    assert esc.motor.rpm == pytest.approx(0.5 * FULL_RPM, rel=1e-3)


def test_bad_construction() -> None:
    with pytest.raises(ValueError, match="esc_id=256"):
        SimFt(256)
    with pytest.raises(ValueError, match="full_scale_current_a=-1"):
        SimFt(1, full_scale_current_a=-1.0)
