"""ESC state from real decoded frames, and the CAN reader on a real python-can bus."""

from __future__ import annotations

import time

import can
import pytest
from conftest import feed

from bridge.escs import registry
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.family import (
    FAILURE_GENERIC,
    FAILURE_OVER_CURRENT,
    FAILURE_OVER_RPM,
    FAILURE_OVER_TEMPERATURE,
)
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.telemetry.reader import CanReader
from bridge.telemetry.state import EscTable, TelemetryLimits

S = ckesc_records.Msg1Status
MS = 1_000_000
T0 = 10_000 * MS  # an arbitrary monotonic start


def ck(node: int, message: ckesc_records.CkescMessage, transfer_id: int = 0) -> can.Message:
    frame = ckesc_codec.CkescFrame(
        ckesc_codec.default_priority(message), node, None, transfer_id, message
    )
    return ckesc_codec.encode(frame)


def host_ck(message: ckesc_records.CkescMessage) -> can.Message:
    return ck(ckesc_records.HOST_NODE_ID, message)


def ftm(esc_id: int, message: ft_records.FtMessage) -> can.Message:
    return ft_codec.encode(ft_records.FtFrame(esc_id, message))


def test_online_only_within_the_timeout() -> None:
    table = EscTable([1], timeout_ms=200)
    assert not table.snapshot(T0)[0].online
    feed(table, ck(1, ckesc_records.Msg1(1, 1, S(0))), T0)
    assert table.snapshot(T0 + 200 * MS)[0].online
    stale = table.snapshot(T0 + 201 * MS)[0]
    assert not stale.online and stale.age_ms == pytest.approx(201)
    feed(table, ck(1, ckesc_records.Msg1(1, 1, S(0))), T0 + 300 * MS)
    assert table.snapshot(T0 + 300 * MS)[0].online


def test_consumed_charge_integrates_current() -> None:
    table = EscTable([5], timeout_ms=500)
    step_ns = 100 * MS
    for i in range(36_001):  # 10 A for an hour, one sample every 100 ms
        feed(table, ftm(5, ft_records.RealtimeData0(0.0, 10.0)), T0 + i * step_ns)
    assert table.snapshot(T0)[0].consumed_mah == pytest.approx(10_000, rel=1e-9)
    # A gap longer than the timeout (the ESC was silent) adds nothing.
    feed(table, ftm(5, ft_records.RealtimeData0(0.0, 10.0)), T0 + 36_000 * step_ns + 600 * MS)
    assert table.snapshot(T0)[0].consumed_mah == pytest.approx(10_000, rel=1e-9)


def test_limits_raise_flags_for_ft() -> None:
    limits = TelemetryLimits(max_temp_c=90.0, max_current_a=40.0, max_rpm=8000)
    table = EscTable([1], pole_pairs=1, limits=limits)
    feed(table, ftm(1, ft_records.RealtimeData2(90.0, 90.0, 25.0)), T0)
    feed(table, ftm(1, ft_records.RealtimeData0(0.0, -40.0)), T0)
    feed(table, ftm(1, ft_records.RealtimeData1(-8000, 0.1)), T0)
    assert table.snapshot(T0)[0].failure_flags == 0  # at the limits, not beyond
    feed(table, ftm(1, ft_records.RealtimeData2(25.0, 90.5, 25.0)), T0)
    assert table.snapshot(T0)[0].failure_flags == FAILURE_OVER_TEMPERATURE
    feed(table, ftm(1, ft_records.RealtimeData0(0.0, -40.01)), T0)
    feed(table, ftm(1, ft_records.RealtimeData1(-8001, 0.1)), T0)
    assert table.snapshot(T0)[0].failure_flags == (
        FAILURE_OVER_TEMPERATURE | FAILURE_OVER_CURRENT | FAILURE_OVER_RPM
    )


def test_a_burst_of_errors_raises_generic_for_a_second() -> None:
    table = EscTable([1, 2], limits=TelemetryLimits(error_burst=3))
    table.count_error(1, T0)
    table.count_error(1, T0 + 500 * MS)
    assert table.snapshot(T0 + 500 * MS)[0].failure_flags == 0
    table.count_error(1, T0 + 900 * MS)
    first, second = table.snapshot(T0 + 900 * MS)
    assert (first.failure_flags, first.errors) == (FAILURE_GENERIC, 3)
    assert (second.failure_flags, second.errors) == (0, 0)
    assert table.snapshot(T0 + 1_001 * MS)[0].failure_flags == 0  # the first left the window
    assert table.snapshot(T0 + 1_001 * MS)[0].errors == 3
    table.count_error(99, T0)
    table.count_error(None, T0)
    assert table.unattributed_errors == 2


def test_foreign_and_non_telemetry_frames_are_not_state() -> None:
    table = EscTable([1, 2])
    assert not feed(table, ck(9, ckesc_records.Msg1(100, 100, S(0))), T0)
    assert table.unknown_frames == 1
    assert not feed(table, ck(1, ckesc_records.GetEscIdAnswer(1, 1)), T0)
    assert all(s.frames == 0 for s in table.snapshot(T0))


def test_own_commands_are_read_back_per_motor() -> None:
    table = EscTable([21, 22, 23, 24, 25, 26], channels=[5, 6, 7, 8, 1, 2])
    feed(table, ckesc_codec.encode_raw_10b([10, 20, 0, 0, 0, 0]), T0)
    feed(table, host_ck(ckesc_records.RawCommand12b(2, (100, 200, 300, 400))), T0)
    commands = [(s.command, s.command_unit) for s in table.snapshot(T0)]
    assert commands == [
        (100.0, "throttle"),
        (200.0, "throttle"),
        (300.0, "throttle"),
        (400.0, "throttle"),
        (20.0, "throttle"),  # 10b carries half: the ESC doubles it
        (40.0, "throttle"),
    ]
    ft_table = EscTable([3, 4])
    feed(ft_table, ftm(4, ft_records.SetDuty(0.5, ft_records.Gear.NONE)), T0)
    feed(ft_table, ftm(3, ft_records.SetCurrentBrake(2.5)), T0)
    assert [(s.command, s.command_unit) for s in ft_table.snapshot(T0)] == [
        (2.5, "brake_current_a"),
        (0.5, "duty"),
    ]
    assert all(s.frames == 0 for s in ft_table.snapshot(T0))


def test_remap_keeps_state_per_motor() -> None:
    table = EscTable([1, 2])
    feed(table, ck(1, ckesc_records.Msg1(111, 0, S(0))), T0)
    table.remap([7, 8])
    feed(table, ck(8, ckesc_records.Msg1(222, 0, S(0))), T0)
    assert not feed(table, ck(1, ckesc_records.Msg1(333, 0, S(0))), T0)
    assert [(s.node_id, s.rpm) for s in table.snapshot(T0)] == [(7, 111), (8, 222)]
    assert table.node_set == {7, 8}
    with pytest.raises(ValueError, match="distinct"):
        table.remap([3, 3])


def test_pole_pairs_must_match_the_motors() -> None:
    with pytest.raises(ValueError, match="pole_pairs"):
        EscTable([1, 2], pole_pairs=[7])
    with pytest.raises(ValueError, match="pole_pairs"):
        EscTable([1], pole_pairs=0)


def _virtual_pair(channel: str) -> tuple[can.BusABC, can.BusABC]:
    return (
        can.Bus(interface="virtual", channel=channel),
        can.Bus(interface="virtual", channel=channel),
    )


def _wait(predicate: object, timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():  # type: ignore[operator]
            return
        time.sleep(0.01)
    raise AssertionError("condition not met in time")


def test_reader_on_a_real_bus_counts_bad_frames_against_their_esc() -> None:
    reader_bus, esc_bus = _virtual_pair("test_reader_counts")
    recorded: list[can.Message] = []
    table = EscTable([1, 2])
    reader = CanReader(reader_bus, table, registry.family("ft"), recorder=recorded.append)
    reader.start()
    try:
        good = ftm(2, ft_records.RealtimeData1(erpm=7000, duty=0.3))
        bad = ftm(2, ft_records.RealtimeData2(50.0, 50.0, 25.0))
        bad.data[7] ^= 0xFF  # the CRC's low byte
        esc_bus.send(good)
        esc_bus.send(bad)
        esc_bus.send(ftm(1, ft_records.SetCurrent(3.0)))  # a command: read back, not telemetry
        esc_bus.send(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"x"))
        _wait(lambda: reader.stats.frames == 4)
    finally:
        reader.close()
        reader_bus.shutdown()
        esc_bus.shutdown()
    first, second = table.snapshot(time.monotonic_ns())
    assert (second.rpm, second.errors, second.frames) == (1000, 1, 1)
    assert (first.command, first.command_unit, first.errors) == (3.0, "current_a", 0)
    assert (reader.stats.telemetry, reader.stats.malformed) == (1, 2)
    assert table.unattributed_errors == 1  # the 11-bit frame names no ESC
    assert [m.arbitration_id for m in recorded] == [0x20C, 0x20D, 0x100, 0x7FF]


def test_the_reader_socket_buffer_can_be_enlarged() -> None:
    from pathlib import Path

    from conftest import free_port, multicast_bus

    from bridge.can_io import enlarge_receive_buffer

    rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
    bus = multicast_bus(free_port())
    virtual = can.Bus(interface="virtual", channel="test_rcvbuf")
    try:
        wanted = 4 * 1024 * 1024
        # Linux doubles the asked size for its bookkeeping, after capping it at rmem_max.
        assert enlarge_receive_buffer(bus, wanted) == 2 * min(wanted, rmem_max)
        assert enlarge_receive_buffer(virtual, wanted) is None  # no socket to size
    finally:
        bus.shutdown()
        virtual.shutdown()
