"""The simulated VESC (bridge/escs/vesc/sim.py), driven with real encoded frames and an explicit
clock: each command, broadcast, PING, the status frames (off by default, then at their rate),
NOTIFY_BOOT, the 1 s command timeout, regeneration's sign and each fault."""

from __future__ import annotations

import itertools
import math
from typing import TypeVar

import can
import pytest

from bridge.errors import DlcError
from bridge.escs.vesc.codec import decode, encode
from bridge.escs.vesc.records import (
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
    VescCommand,
    VescFrame,
)
from bridge.escs.vesc.sim import OVER_CURRENT_A, OVER_TEMPERATURE_C, STATUS_1_TO_5, SimVesc
from bridge.sim.motor import Motor, MotorParams

VESC = 23
SUPPLY_V = 16.8
PARAMS = MotorParams()
FULL_RPM = PARAMS.kv_rpm_per_v * SUPPLY_V  # at SUPPLY_V, which is the nominal voltage
STEP_S = 0.001

T = TypeVar("T")


def command(record: VescCommand, controller_id: int = VESC) -> can.Message:
    return encode(VescFrame(controller_id, record))


class Clock:
    """Drives one SimVesc as the runner does: polls every millisecond, frames in between."""

    def __init__(self, esc: SimVesc) -> None:
        self.esc = esc
        self.tick = 0
        self.sent: list[tuple[float, can.Message]] = []

    @property
    def now(self) -> float:
        return self.tick * STEP_S

    def send(self, msg: can.Message) -> list[can.Message]:
        return self.esc.handle(msg, self.now)

    def run(self, seconds: float, repeat: can.Message | None = None, every_s: float = 0.1) -> None:
        """Poll for ``seconds``; with ``repeat``, send it first and then every ``every_s``."""
        every = round(every_s / STEP_S)
        for i in range(round(seconds / STEP_S)):
            if repeat is not None and i % every == 0:
                assert self.send(repeat) == []
            for msg in self.esc.poll(self.now, SUPPLY_V):
                self.sent.append((self.now, msg))
            self.tick += 1

    def records(self, kind: type[T]) -> list[T]:
        found: list[T] = []
        for _, msg in self.sent:
            frame = decode(msg)
            assert frame is not None and frame.controller_id == VESC
            if isinstance(frame.message, kind):
                found.append(frame.message)
        return found

    def times(self, packet: Packet) -> list[float]:
        return [t for t, msg in self.sent if msg.arbitration_id >> 8 == packet]


def vesc(**options: object) -> SimVesc:
    return SimVesc(VESC, motor=Motor(PARAMS), **options)  # type: ignore[arg-type]


def test_status_frames_are_off_by_default_and_boot_is_announced_once() -> None:
    clock = Clock(vesc())
    clock.run(1.0, repeat=command(SetDuty(0.5)), every_s=0.05)
    assert [msg.arbitration_id for _, msg in clock.sent] == [Packet.NOTIFY_BOOT << 8 | VESC]
    assert clock.records(NotifyBoot) == [NotifyBoot("sim")]
    assert clock.esc.motor.rpm > 0.4 * FULL_RPM  # the command acted all the same


def test_enabled_status_frames_come_at_their_rate_whether_commanded_or_not() -> None:
    clock = Clock(vesc(status=STATUS_1_TO_5, status_hz=50.0))
    clock.run(1.0)
    for packet in STATUS_1_TO_5:
        times = clock.times(packet)
        assert len(times) == 50, packet
        gaps = {round(b - a, 6) for a, b in itertools.pairwise(times)}
        assert gaps == {0.02}, packet
    assert clock.times(Packet.STATUS_6) == []
    # All of a period's frames together, in the firmware's order.
    first = [msg.arbitration_id >> 8 for t, msg in clock.sent if t == 0.0]
    assert first == [57, 9, 14, 15, 16, 27]


def test_status_rate_is_configurable_and_status_6_can_be_asked_for() -> None:
    clock = Clock(vesc(status=frozenset({Packet.STATUS_6}), status_hz=10.0))
    clock.run(1.0)
    assert len(clock.times(Packet.STATUS_6)) == 10
    assert clock.times(Packet.STATUS) == []


@pytest.mark.parametrize(
    ("record", "expected_rpm"),
    [
        (SetDuty(0.5), 0.5 * FULL_RPM),
        (SetDuty(-0.5), -0.5 * FULL_RPM),
        (SetCurrent(PARAMS.full_current_a), FULL_RPM),
        (SetCurrentRel(1.0), FULL_RPM),
        (SetCurrentRel(-1.0), -FULL_RPM),
        (SetRpm(7000), 1000.0),
        (SetCurrentBrake(5.0), 0.0),
    ],
)
def test_commands_drive_the_motor(record: VescCommand, expected_rpm: float) -> None:
    clock = Clock(vesc(status=frozenset({Packet.STATUS})))
    clock.run(1.5, repeat=command(record))
    assert clock.esc.last_command == record
    assert math.isclose(clock.esc.motor.rpm, expected_rpm, rel_tol=0.02, abs_tol=1.0)
    erpm = clock.records(Status)[-1].erpm
    assert math.isclose(erpm, expected_rpm * PARAMS.pole_pairs, rel_tol=0.02, abs_tol=10)


def test_current_rel_is_a_fraction_of_its_own_limit() -> None:
    clock = Clock(vesc(motor_current_max_a=PARAMS.full_current_a / 8))
    clock.run(1.5, repeat=command(SetCurrentRel(1.0)))
    # A quarter of full speed: the propeller draws current with the cube of speed.
    assert math.isclose(clock.esc.motor.rpm, FULL_RPM / 2, rel_tol=0.02)


def test_broadcast_commands_are_obeyed_and_others_ignored() -> None:
    clock = Clock(vesc())
    clock.run(1.0, repeat=command(SetDuty(0.3), controller_id=255))
    assert clock.esc.stats.commands == 10
    clock.run(0.1, repeat=command(SetDuty(0.9), controller_id=VESC + 1))
    assert clock.esc.stats.commands == 10 and clock.esc.last_command == SetDuty(0.3)


def test_a_malformed_command_is_counted_and_ignored() -> None:
    clock = Clock(vesc())
    bad = can.Message(arbitration_id=0x100 | VESC, data=b"\0\0\1\0\0\0", is_extended_id=True)
    with pytest.raises(DlcError):
        decode(bad)
    assert clock.send(bad) == []
    assert clock.esc.stats.bad_frames == 1 and clock.esc.stats.commands == 0


def test_ping_gets_a_pong_to_the_sender() -> None:
    esc = vesc()
    (pong,) = esc.handle(encode(VescFrame(VESC, Ping(254))), 0.0)
    assert (pong.arbitration_id, bytes(pong.data)) == (0x12FE, bytes([VESC, 0]))
    assert decode(pong) == VescFrame(254, Pong(VESC, HwType.VESC))
    # To all: the firmware answers with the ID the PING was sent to.
    (pong,) = esc.handle(encode(VescFrame(255, Ping(3))), 0.0)
    assert decode(pong) == VescFrame(3, Pong(255, HwType.VESC))
    assert esc.handle(encode(VescFrame(VESC + 1, Ping(3))), 0.0) == []
    assert esc.stats.pings == 2


def test_the_command_timeout_releases_the_motor_after_one_second() -> None:
    clock = Clock(vesc())
    clock.send(command(SetDuty(0.5)))
    clock.run(0.999)
    assert clock.esc.commanded and clock.esc.stats.timeouts == 0
    clock.run(0.002)
    assert not clock.esc.commanded and clock.esc.stats.timeouts == 1
    spinning = clock.esc.motor.rpm
    clock.run(1.0)
    assert clock.esc.motor.rpm < 0.01 * spinning  # coasted down, released
    assert not clock.esc.braking


def test_the_timeout_brakes_with_a_timeout_brake_current() -> None:
    clock = Clock(vesc(timeout_s=0.2, timeout_brake_current_a=3.0))
    clock.run(0.5, repeat=command(SetDuty(0.5)), every_s=0.1)
    clock.run(0.25)
    assert clock.esc.braking and clock.esc.stats.timeouts == 1


def test_regenerating_motor_and_input_current_are_negative() -> None:
    clock = Clock(vesc(status=STATUS_1_TO_5))
    clock.run(1.0, repeat=command(SetDuty(0.8)))
    driving = clock.records(Status)[-1]
    assert driving.motor_current_a > 1.0 and driving.duty > 0.7
    assert clock.records(Status4)[-1].input_current_a > 1.0
    clock.run(0.05, repeat=command(SetCurrentBrake(10.0)))
    assert clock.records(Status)[-1].motor_current_a < -1.0
    assert clock.records(Status4)[-1].input_current_a < 0
    assert clock.records(Status2)[-1].charged_ah > 0
    assert clock.records(Status3)[-1].charged_wh > 0


def test_status_values_follow_the_motor_and_supply() -> None:
    clock = Clock(vesc(status=STATUS_1_TO_5))
    clock.run(2.0, repeat=command(SetDuty(0.5)))
    assert clock.records(Status5)[-1].input_voltage_v == SUPPLY_V
    status2 = clock.records(Status2)[-1]
    assert 0 < status2.used_ah < PARAMS.full_current_a * 2 / 3600
    temps = clock.records(Status4)[-1]
    assert temps.fet_temp_c >= PARAMS.ambient_c and temps.motor_temp_c >= PARAMS.ambient_c
    # Six steps per electrical turn, counted from the power-up.
    turns = clock.esc.tachometer / 6 / PARAMS.pole_pairs
    assert clock.records(Status5)[-1].tachometer > 0 and 0.5 * FULL_RPM / 60 < turns < FULL_RPM / 30


@pytest.mark.parametrize("fault", ["over_temperature", "over_current", "corrupt", "silent"])
def test_faults(fault: str) -> None:
    clock = Clock(vesc(status=STATUS_1_TO_5))
    setattr(clock.esc.faults, fault, True)
    clock.run(0.1, repeat=command(SetDuty(0.5)))
    if fault == "silent":
        assert clock.sent == []
        assert clock.send(encode(VescFrame(VESC, Ping(254)))) == []
        assert clock.esc.motor.rpm > 0  # commands still act
        return
    if fault == "corrupt":
        status = [msg for _, msg in clock.sent if msg.arbitration_id >> 8 != Packet.NOTIFY_BOOT]
        assert status and all(msg.dlc == 7 for msg in status)
        with pytest.raises(DlcError):
            decode(status[0])
        return
    if fault == "over_temperature":
        assert clock.records(Status4)[-1].fet_temp_c == OVER_TEMPERATURE_C
    else:
        assert clock.records(Status)[-1].motor_current_a == OVER_CURRENT_A
        assert clock.records(Status4)[-1].input_current_a == OVER_CURRENT_A


def test_stuck_motor() -> None:
    clock = Clock(vesc())
    clock.esc.faults.stuck_motor = True
    clock.run(0.5, repeat=command(SetDuty(0.5)))
    assert clock.esc.motor.rpm == 0.0


def test_no_burst_after_a_stall() -> None:
    esc = vesc(status=frozenset({Packet.STATUS}))
    assert len(esc.poll(0.0, SUPPLY_V)) == 2  # boot and the first STATUS
    assert len(esc.poll(0.5, SUPPLY_V)) == 1  # 24 periods missed: one frame, not 25
    assert esc.poll(0.51, SUPPLY_V) == []
    assert len(esc.poll(0.52, SUPPLY_V)) == 1


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"controller_id": 255}, "outside 0..254"),
        ({"status_hz": 0.0}, "status_hz"),
        ({"timeout_s": -1.0}, "timeout_s"),
        ({"timeout_brake_current_a": -1.0}, "timeout_brake_current_a"),
        ({"motor_current_max_a": 0.0}, "motor_current_max_a"),
        ({"status": frozenset({Packet.SET_DUTY})}, "status packets only"),
    ],
)
def test_bad_settings_are_refused(options: dict[str, object], match: str) -> None:
    controller_id = options.pop("controller_id", VESC)
    with pytest.raises(ValueError, match=match):
        SimVesc(controller_id, **options)  # type: ignore[arg-type]


def test_simulators_are_set_up_as_the_configuration_says() -> None:
    from bridge.escs.family import EscSetup
    from bridge.escs.vesc.keys import VescKeys
    from bridge.escs.vesc.sim import simulators

    built = simulators(EscSetup((1, 7), VescKeys(vesc_status_hz=25.0, vesc_timeout_ms=300)), PARAMS)
    escs = [esc for esc in built if isinstance(esc, SimVesc)]
    assert len(escs) == len(built)
    assert [esc.node_id for esc in escs] == [1, 7]
    assert all(esc.status == STATUS_1_TO_5 and esc.status_hz == 25.0 for esc in escs)
    assert all(esc.timeout_s == 0.3 and esc.motor.params == PARAMS for esc in escs)
    assert escs[0].motor is not escs[1].motor
    # vesc_status_hz 0: VESCs as from the factory, no status frames.
    (quiet,) = simulators(EscSetup((3,), VescKeys(vesc_status_hz=0.0)), None)
    assert isinstance(quiet, SimVesc) and quiet.status == frozenset()
