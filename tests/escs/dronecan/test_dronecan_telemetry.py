"""DroneCAN transfers as neutral telemetry and commands read back
(bridge/escs/dronecan/telemetry.py): each field of esc.Status, NaN fields left out, NodeStatus
health as a failure once its node's index is known, RawCommand slots as ESC numbers."""

from __future__ import annotations

import pytest

from bridge.escs.dronecan.codec import (
    DronecanFrame,
    DronecanMessage,
    EscStatus,
    NodeStatus,
    RawCommand,
    TransferPart,
)
from bridge.escs.dronecan.telemetry import commands_seen, telemetry
from bridge.escs.family import FAILURE_GENERIC, CommandSeen


def frame(message: DronecanMessage, esc_index: int | None = None) -> DronecanFrame:
    return DronecanFrame(16, 25, 0, message, esc_index)


def test_esc_status() -> None:
    status = EscStatus(2, 7, 16.4, 12.5, 273.15 + 45.5, -5000, 37)
    got = telemetry(frame(status, 2))
    assert got is not None
    assert got.node_id == 3  # ESC number: index + 1
    assert (got.rpm, got.voltage_v, got.current_a) == (-5000, 16.4, 12.5)
    assert got.mos_temp_c == pytest.approx(45.5)
    assert got.throttle == pytest.approx(-0.37)  # the power rating, with the rpm's sign
    assert got.counters == {"error_count": 7}
    assert got.erpm is None and got.status is None
    missing = telemetry(frame(EscStatus(0, 0, None, None, None, 10, 0), 0))
    assert missing is not None
    assert (missing.voltage_v, missing.current_a, missing.mos_temp_c) == (None, None, None)


def test_node_status() -> None:
    assert telemetry(frame(NodeStatus(5, 0, 0))) is None  # its node's index is not known yet
    ok = telemetry(frame(NodeStatus(5, 1, 0), 0))
    assert ok is not None and (ok.node_id, ok.status, ok.status_failures) == (1, 1, 0)
    assert ok.counters == {"uptime_s": 5, "mode": 0}
    for health in (2, 3):
        bad = telemetry(frame(NodeStatus(6, health, 0), 4))
        assert bad is not None and bad.status_failures == FAILURE_GENERIC and bad.node_id == 5


def test_commands_and_parts() -> None:
    assert commands_seen(frame(RawCommand((0, 8191, -100)))) == [
        CommandSeen(0.0, "raw_command", node_id=1),
        CommandSeen(8191.0, "raw_command", node_id=2),
        CommandSeen(-100.0, "raw_command", node_id=3),
    ]
    assert telemetry(frame(RawCommand((1,)))) is None
    part = frame(TransferPart("EscStatus", 1))
    assert telemetry(part) is None and commands_seen(part) == []
    assert commands_seen(frame(NodeStatus(1, 0, 0), 0)) == []
