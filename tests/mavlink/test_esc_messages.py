"""The ESC telemetry encoders and message sets, as pure functions: snapshots in, messages out.

Each message is packed with the project's dialect and decoded again, so what is checked is what
goes on the wire. The sender around them is tested end to end in test_telemetry_out.py.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import pytest

from bridge.config import MavlinkConfig
from bridge.mavlink import load_dialect
from bridge.mavlink.esc_messages import (
    AUTOPILOT_SETS,
    OTHER_AUTOPILOT_SET,
    bytes_per_s,
    describe_sets,
    esc_info_messages,
    esc_status_messages,
    esc_telemetry_messages,
    messages_per_round,
)
from bridge.telemetry.state import EscSnapshot

DIALECT = load_dialect()
INT16_MAX = 32_767


def snapshot(motor: int, **fields: Any) -> EscSnapshot:
    """An online ESC with every measurement known, then ``fields`` over it."""
    esc = EscSnapshot(
        motor=motor,
        node_id=motor,
        online=True,
        age_ms=1.0,
        rpm=1000 * motor,
        voltage_v=16.0,
        current_a=2.5,
        motor_current_a=None,
        throttle=0.5,
        mos_temp_c=40.0,
        capacitor_temp_c=None,
        motor_temp_c=None,
        mcu_temp_c=None,
        status=0,
        failure_flags=0,
        frames=10,
        errors=0,
        consumed_mah=12.0,
    )
    return replace(esc, **fields)


def on_wire(messages: list[Any]) -> list[Any]:
    """Each message packed as the link would, and parsed back."""
    mav = DIALECT.MAVLink(None, srcSystem=1, srcComponent=191)
    parsed = []
    for message in messages:
        (back,) = mav.parse_buffer(message.pack(mav)) or []
        parsed.append(back)
    return parsed


def test_esc_status_batches_four_and_reports_an_offline_esc_as_unknown() -> None:
    escs = [snapshot(1), snapshot(2, online=False), snapshot(3), snapshot(4), snapshot(5)]
    first, second = on_wire(esc_status_messages(DIALECT.MAVLink(None), escs, 123))
    assert (first.index, second.index) == (0, 4)
    assert first.time_usec == 123
    assert first.rpm == [1000, 0, 3000, 4000]
    assert first.voltage[1] == first.current[1] == 0.0
    assert second.rpm == [5000, 0, 0, 0]  # the last batch padded


def test_esc_status_clamps_and_turns_nan_and_infinity_into_unknown() -> None:
    escs = [
        snapshot(1, rpm=2**40, voltage_v=math.nan, current_a=1e39),
        snapshot(2, rpm=-(2**40), voltage_v=math.inf),
    ]
    (msg,) = on_wire(esc_status_messages(DIALECT.MAVLink(None), escs, 0))
    assert msg.rpm[:2] == [2**31 - 1, -(2**31)]
    assert msg.voltage[:2] == [0.0, 0.0]
    assert msg.current[0] == pytest.approx(3.4028234663852886e38)


def test_esc_info_counts_online_escs_and_keeps_int16_max_for_unknown() -> None:
    escs = [
        snapshot(1, mos_temp_c=1000.0, failure_flags=3, errors=7),
        snapshot(2, online=False),
        snapshot(3, mos_temp_c=None),
    ]
    (msg,) = on_wire(esc_info_messages(DIALECT.MAVLink(None), escs, 5, 65537))
    assert (msg.count, msg.counter, msg.info) == (3, 1, 0b101)
    assert msg.temperature == [INT16_MAX - 1, INT16_MAX, INT16_MAX, INT16_MAX]
    assert msg.failure_flags[:2] == [3, 0]
    assert msg.error_count[0] == 7


def test_esc_telemetry_covers_the_first_32_escs_only() -> None:
    escs = [snapshot(n) for n in range(1, 35)]
    messages = on_wire(esc_telemetry_messages(DIALECT.MAVLink(None), escs))
    assert [m.get_type() for m in messages][-1] == "ESC_TELEMETRY_29_TO_32"
    assert len(messages) == 8
    first = messages[0]
    assert first.temperature[0] == 40
    assert first.voltage[0] == 1600
    assert first.current[0] == 250
    assert first.totalcurrent[0] == 12
    assert first.rpm[0] == 1000
    assert first.count[0] == 10


def test_bytes_per_s_and_messages_per_round() -> None:
    assert messages_per_round("esc_telemetry", 40) == 8
    assert messages_per_round("esc_status", 5) == 2
    assert bytes_per_s(AUTOPILOT_SETS[3], 4) == pytest.approx(2.0 * (44 + 12))
    assert bytes_per_s(AUTOPILOT_SETS[3], 4, signed=True) == pytest.approx(2.0 * (44 + 12 + 13))
    assert bytes_per_s(AUTOPILOT_SETS[None], 8) == 0


def test_describe_sets_names_each_connection() -> None:
    config = MavlinkConfig(url="udpin:127.0.0.1:14550", outputs=("udpout:127.0.0.1:14551",))
    text = describe_sets(config, 4)
    assert text.startswith("MAVLink ESC telemetry for 4 ESCs: autopilot link by its HEARTBEAT")
    assert "udpout:127.0.0.1:14551 ESC_STATUS" in text
    assert OTHER_AUTOPILOT_SET["esc_telemetry"] > 0
