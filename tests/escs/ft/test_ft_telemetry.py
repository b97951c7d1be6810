"""FT frames as the ESC state sees them (bridge/escs/ft/telemetry.py): erpm into signed rpm
by each motor's pole pairs."""

from __future__ import annotations

import can
from conftest import feed

from bridge.escs import registry
from bridge.escs.ft import codec, records
from bridge.telemetry.state import EscTable

MS = 1_000_000
T0 = 10_000 * MS  # an arbitrary monotonic start


def ftm(esc_id: int, message: records.FtMessage) -> can.Message:
    return codec.encode(records.FtFrame(esc_id, message))


def test_ft_frames_signed_rpm_by_pole_pairs() -> None:
    table = EscTable([1, 2], pole_pairs=[7, 14])
    feed(table, ftm(1, records.RealtimeData1(erpm=-70_007, duty=-0.5)), T0)
    feed(table, ftm(2, records.RealtimeData1(erpm=70_000, duty=0.25)), T0)
    feed(table, ftm(2, records.RealtimeData0(motor_current_a=30.5, battery_current_a=-2.25)), T0)
    feed(table, ftm(2, records.RealtimeData2(65.5, 80.25, 50.4)), T0)
    first, second = table.snapshot(T0)
    assert (first.rpm, first.throttle) == (-10_001, -0.5)  # toward zero: |reverse| = |forward|
    assert (second.rpm, second.throttle) == (5_000, 0.25)
    assert (second.motor_current_a, second.current_a) == (30.5, -2.25)
    assert (second.mos_temp_c, second.motor_temp_c, second.voltage_v) == (65.5, 80.25, 50.4)
    assert second.capacitor_temp_c is None and second.status is None
    assert second.failure_flags == 0


def test_node_of_malformed_frames() -> None:
    decoder = registry.family("ft").decoder()
    assert decoder.node_of(can.Message(arbitration_id=0x0000050C, data=b"\0" * 8)) == 5
    assert decoder.node_of(can.Message(arbitration_id=0x123, is_extended_id=False)) is None
