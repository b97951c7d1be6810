"""VESC frames as the ESC state sees them (bridge/escs/vesc/telemetry.py): erpm into rpm by pole
pairs, input current and volts to the battery side, temperatures, counters; commands read back;
PONG and NOTIFY_BOOT are no telemetry."""

from __future__ import annotations

import can

from bridge.escs.family import CommandSeen, EscTelemetry
from bridge.escs.vesc.codec import encode
from bridge.escs.vesc.family import VescFamily
from bridge.escs.vesc.records import (
    HwType,
    NotifyBoot,
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
    VescFrame,
    VescMessage,
)
from bridge.telemetry.state import EscTable

MS = 1_000_000
T0 = 10_000 * MS  # an arbitrary monotonic start
DECODER = VescFamily().decoder()


def frame_of(controller_id: int, message: VescMessage) -> can.Message:
    return encode(VescFrame(controller_id, message))


def feed(table: EscTable, msg: can.Message, now_ns: int) -> bool:
    """Through VESC's decoder into ``table``, as the CAN reader does (conftest.feed takes the
    first family whose ID space holds a frame: FT's, for a VESC ID)."""
    frame = DECODER.decode(msg)
    assert frame is not None
    telemetry = DECODER.telemetry(frame)
    if telemetry is None:
        table.note_commands(DECODER.commands_seen(frame))
        return False
    return table.ingest(telemetry, now_ns)


def test_status_frames_into_the_esc_state() -> None:
    table = EscTable([23, 24], pole_pairs=[7, 14])
    feed(table, frame_of(23, Status(-70_007, 12.5, -0.5)), T0)
    feed(table, frame_of(24, Status(70_000, -3.2, 0.25)), T0)  # regenerating
    feed(table, frame_of(24, Status4(65.5, 80.2, -2.5, 0.0)), T0)
    feed(table, frame_of(24, Status5(123_456, 50.4)), T0)
    feed(table, frame_of(24, Status2(1.2346, 0.0101)), T0)
    feed(table, frame_of(24, Status3(45.6789, 0.5)), T0)
    first, second = table.snapshot(T0)
    assert (first.rpm, first.motor_current_a, first.throttle) == (-10_001, 12.5, -0.5)
    assert first.current_a is None and first.voltage_v is None  # STATUS is the motor side only
    assert (second.rpm, second.motor_current_a, second.throttle) == (5_000, -3.2, 0.25)
    assert (second.current_a, second.voltage_v) == (-2.5, 50.4)
    assert (second.mos_temp_c, second.motor_temp_c) == (65.5, 80.2)
    assert second.capacitor_temp_c is None and second.mcu_temp_c is None
    assert second.counters == {
        "tachometer": 123_456,
        "used_mah": 1235,
        "charged_mah": 10,
        "used_mwh": 45679,
        "charged_mwh": 500,
    }
    assert second.failure_flags == 0


def test_the_mapping_per_frame() -> None:
    assert DECODER.telemetry(VescFrame(5, Status6(1.0, 2.0, 3.0, 0.5))) == EscTelemetry(5)
    silent: list[VescMessage] = [Pong(5, HwType.VESC), Ping(254), NotifyBoot("60"), SetDuty(0.5)]
    for message in silent:
        assert DECODER.telemetry(VescFrame(5, message)) is None


def test_commands_a_command_frame_carries() -> None:
    expected: dict[VescMessage, CommandSeen] = {
        SetDuty(0.5): CommandSeen(0.5, "duty", node_id=7),
        SetCurrent(-2.5): CommandSeen(-2.5, "current_a", node_id=7),
        SetCurrentBrake(4.0): CommandSeen(4.0, "brake_current_a", node_id=7),
        SetRpm(1200): CommandSeen(1200.0, "erpm", node_id=7),
        SetCurrentRel(0.25): CommandSeen(0.25, "current_fraction", node_id=7),
    }
    for record, seen in expected.items():
        assert DECODER.commands_seen(VescFrame(7, record)) == [seen]
    assert DECODER.commands_seen(VescFrame(7, Status(0, 0.0, 0.0))) == []


def test_node_of_malformed_frames() -> None:
    short = can.Message(arbitration_id=0x917, data=b"\0" * 7, is_extended_id=True)
    assert DECODER.node_of(short) == 23
    assert DECODER.node_of(can.Message(arbitration_id=0x117, is_extended_id=False)) is None
    assert DECODER.node_of(can.Message(arbitration_id=0x10917, is_extended_id=True)) is None


def test_the_decoder_is_stateless_and_shared() -> None:
    assert VescFamily().decoder() is VescFamily().decoder()
