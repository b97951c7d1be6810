"""ESC state from real decoded frames, and the CAN reader on a real python-can bus."""

from __future__ import annotations

import threading
import time

import can
import pytest

from bridge.can_in import CanReader
from bridge.errors import LinkError
from bridge.escs import ckesc, ft, registry
from bridge.escs.ckesc.setup import learn_node_ids
from bridge.escs.ckesc.telemetry import STATUS_FAILURES
from bridge.escs.family import (
    FAILURE_GENERIC,
    FAILURE_OVER_CURRENT,
    FAILURE_OVER_RPM,
    FAILURE_OVER_TEMPERATURE,
    FAILURE_OVER_VOLTAGE,
)
from bridge.telemetry.state import EscTable, TelemetryLimits

S = ckesc.Msg1Status
MS = 1_000_000
T0 = 10_000 * MS  # an arbitrary monotonic start


def ck(node: int, message: ckesc.CkescMessage, transfer_id: int = 0) -> can.Message:
    frame = ckesc.CkescFrame(ckesc.default_priority(message), node, None, transfer_id, message)
    return ckesc.encode(frame)


def host_ck(message: ckesc.CkescMessage) -> can.Message:
    return ck(ckesc.HOST_NODE_ID, message)


def ftm(esc_id: int, message: ft.FtMessage) -> can.Message:
    return ft.encode(ft.FtFrame(esc_id, message))


def feed(table: EscTable, msg: can.Message, now_ns: int) -> bool:
    """Through the family's codec and telemetry mapping into ``table``, as the reader does."""
    family = registry.family_of(msg.arbitration_id)
    assert family is not None
    frame = family.decode(msg)
    assert frame is not None
    telemetry = family.telemetry(frame)
    if telemetry is None:
        table.note_commands(family.commands_seen(frame))
        return False
    return table.ingest(telemetry, now_ns)


def test_ckesc_messages_fill_every_field() -> None:
    table = EscTable([11, 12, 13, 14])
    assert feed(table, ck(12, ckesc.Msg1(5230, 1500, S.RUNNING)), T0)
    assert feed(table, ck(12, ckesc.Msg2(24.51, 12.34, 61)), T0 + MS)
    assert feed(table, ck(12, ckesc.Msg3(62, 45, 70, 55)), T0 + 2 * MS)
    esc = table.snapshot(T0 + 3 * MS)[1]
    assert (esc.motor, esc.node_id, esc.online) == (2, 12, True)
    assert esc.rpm == 5230
    assert esc.throttle == pytest.approx(0.75)
    assert esc.voltage_v == pytest.approx(24.51)
    assert esc.current_a == pytest.approx(12.34)
    assert (esc.mos_temp_c, esc.capacitor_temp_c, esc.motor_temp_c, esc.mcu_temp_c) == (
        62,
        45,
        70,
        55,
    )
    assert esc.esc_temp_c == 62
    assert esc.status == int(S.RUNNING)
    assert esc.failure_flags == 0
    assert esc.frames == 3
    assert esc.age_ms == pytest.approx(1.0)
    others = [s for s in table.snapshot(T0) if s.motor != 2]
    assert all(s.frames == 0 and not s.online and s.rpm is None for s in others)


def test_ckesc_exp_messages() -> None:
    table = EscTable([1])
    feed(table, ck(1, ckesc.MsgExp1(4100, 47.9, 3.25)), T0)
    feed(table, ck(1, ckesc.MsgExp11(50, 40, 35, 60)), T0)
    feed(table, ck(1, ckesc.MsgExp8(17, 230, 228)), T0)
    feed(table, ck(1, ckesc.MsgExp9(3600, ckesc.SelfTestFault.NONE)), T0)
    feed(table, ck(1, ckesc.MsgExp10(95, 0)), T0)
    esc = table.snapshot(T0)[0]
    assert (esc.rpm, esc.current_a) == (4100, 3.25)
    assert esc.voltage_v == pytest.approx(47.9)
    assert (esc.mos_temp_c, esc.mcu_temp_c, esc.capacitor_temp_c, esc.motor_temp_c) == (
        50,
        40,
        35,
        60,
    )
    assert esc.counters == {
        "power_on_count": 17,
        "start_count": 230,
        "stop_count": 228,
        "total_run_time_s": 3600,
        "self_test_fault": 0,
        "run_time_s": 95,
        "fault_code_2": 0,
    }
    assert esc.failure_flags == 0
    feed(table, ck(1, ckesc.MsgExp9(3600, ckesc.SelfTestFault.PHASE_B_LOW)), T0)
    assert table.snapshot(T0)[0].failure_flags == FAILURE_GENERIC


@pytest.mark.parametrize(
    ("status", "flags"),
    [
        (S.OVER_CURRENT, FAILURE_OVER_CURRENT),
        (S.OVER_VOLTAGE, FAILURE_OVER_VOLTAGE),
        (S.OVER_TEMPERATURE, FAILURE_OVER_TEMPERATURE),
        (S.UNDER_VOLTAGE, FAILURE_GENERIC),
        (S.COMMS_FAULT, FAILURE_GENERIC),
        (S.SELF_TEST_PHASE_A_OUTPUT_HIGH, FAILURE_GENERIC),
        (S.SELF_TEST_COM_INPUT_LOW, FAILURE_GENERIC),
        (S.RUNNING | S.DIRECTION_CCW | S.THROTTLE_SOURCE_PWM, 0),
        (S.OVER_CURRENT | S.OVER_TEMPERATURE, FAILURE_OVER_CURRENT | FAILURE_OVER_TEMPERATURE),
    ],
)
def test_ckesc_status_bits_become_failure_flags(status: S, flags: int) -> None:
    table = EscTable([3], limits=TelemetryLimits(max_temp_c=None))
    feed(table, ck(3, ckesc.Msg1(0, 0, status)), T0)
    assert table.snapshot(T0)[0].failure_flags == flags


def test_every_mapped_status_bit_is_a_fault_bit() -> None:
    mapped = 0
    for bits, _ in STATUS_FAILURES:
        mapped |= bits
    informational = S.DIRECTION_CCW | S.THROTTLE_SOURCE_PWM | S.RUNNING
    assert mapped | informational == 0xFFFF
    assert mapped & informational == 0


def test_ft_frames_signed_rpm_by_pole_pairs() -> None:
    table = EscTable([1, 2], pole_pairs=[7, 14])
    feed(table, ftm(1, ft.RealtimeData1(erpm=-70_007, duty=-0.5)), T0)
    feed(table, ftm(2, ft.RealtimeData1(erpm=70_000, duty=0.25)), T0)
    feed(table, ftm(2, ft.RealtimeData0(motor_current_a=30.5, battery_current_a=-2.25)), T0)
    feed(table, ftm(2, ft.RealtimeData2(65.5, 80.25, 50.4)), T0)
    first, second = table.snapshot(T0)
    assert (first.rpm, first.throttle) == (-10_001, -0.5)  # toward zero: |reverse| = |forward|
    assert (second.rpm, second.throttle) == (5_000, 0.25)
    assert (second.motor_current_a, second.current_a) == (30.5, -2.25)
    assert (second.mos_temp_c, second.motor_temp_c, second.voltage_v) == (65.5, 80.25, 50.4)
    assert second.capacitor_temp_c is None and second.status is None
    assert second.failure_flags == 0


def test_online_only_within_the_timeout() -> None:
    table = EscTable([1], timeout_ms=200)
    assert not table.snapshot(T0)[0].online
    feed(table, ck(1, ckesc.Msg1(1, 1, S(0))), T0)
    assert table.snapshot(T0 + 200 * MS)[0].online
    stale = table.snapshot(T0 + 201 * MS)[0]
    assert not stale.online and stale.age_ms == pytest.approx(201)
    feed(table, ck(1, ckesc.Msg1(1, 1, S(0))), T0 + 300 * MS)
    assert table.snapshot(T0 + 300 * MS)[0].online


def test_consumed_charge_integrates_current() -> None:
    table = EscTable([5], timeout_ms=500)
    step_ns = 100 * MS
    for i in range(36_001):  # 10 A for an hour, one sample every 100 ms
        feed(table, ftm(5, ft.RealtimeData0(0.0, 10.0)), T0 + i * step_ns)
    assert table.snapshot(T0)[0].consumed_mah == pytest.approx(10_000, rel=1e-9)
    # A gap longer than the timeout (the ESC was silent) adds nothing.
    feed(table, ftm(5, ft.RealtimeData0(0.0, 10.0)), T0 + 36_000 * step_ns + 600 * MS)
    assert table.snapshot(T0)[0].consumed_mah == pytest.approx(10_000, rel=1e-9)


def test_limits_raise_flags_for_ft() -> None:
    limits = TelemetryLimits(max_temp_c=90.0, max_current_a=40.0, max_rpm=8000)
    table = EscTable([1], pole_pairs=1, limits=limits)
    feed(table, ftm(1, ft.RealtimeData2(90.0, 90.0, 25.0)), T0)
    feed(table, ftm(1, ft.RealtimeData0(0.0, -40.0)), T0)
    feed(table, ftm(1, ft.RealtimeData1(-8000, 0.1)), T0)
    assert table.snapshot(T0)[0].failure_flags == 0  # at the limits, not beyond
    feed(table, ftm(1, ft.RealtimeData2(25.0, 90.5, 25.0)), T0)
    assert table.snapshot(T0)[0].failure_flags == FAILURE_OVER_TEMPERATURE
    feed(table, ftm(1, ft.RealtimeData0(0.0, -40.01)), T0)
    feed(table, ftm(1, ft.RealtimeData1(-8001, 0.1)), T0)
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
    assert not feed(table, ck(9, ckesc.Msg1(100, 100, S(0))), T0)
    assert table.unknown_frames == 1
    assert not feed(table, ck(1, ckesc.GetEscIdAnswer(1, 1)), T0)
    assert all(s.frames == 0 for s in table.snapshot(T0))


def test_own_commands_are_read_back_per_motor() -> None:
    table = EscTable([21, 22, 23, 24, 25, 26], channels=[5, 6, 7, 8, 1, 2])
    feed(table, ckesc.encode_raw_10b([10, 20, 0, 0, 0, 0]), T0)
    feed(table, host_ck(ckesc.RawCommand12b(2, (100, 200, 300, 400))), T0)
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
    feed(ft_table, ftm(4, ft.SetDuty(0.5, ft.Gear.NONE)), T0)
    feed(ft_table, ftm(3, ft.SetCurrentBrake(2.5)), T0)
    assert [(s.command, s.command_unit) for s in ft_table.snapshot(T0)] == [
        (2.5, "brake_current_a"),
        (0.5, "duty"),
    ]
    assert all(s.frames == 0 for s in ft_table.snapshot(T0))


def test_remap_keeps_state_per_motor() -> None:
    table = EscTable([1, 2])
    feed(table, ck(1, ckesc.Msg1(111, 0, S(0))), T0)
    table.remap([7, 8])
    feed(table, ck(8, ckesc.Msg1(222, 0, S(0))), T0)
    assert not feed(table, ck(1, ckesc.Msg1(333, 0, S(0))), T0)
    assert [(s.node_id, s.rpm) for s in table.snapshot(T0)] == [(7, 111), (8, 222)]
    assert table.node_set == {7, 8}
    with pytest.raises(ValueError, match="distinct"):
        table.remap([3, 3])


def test_pole_pairs_must_match_the_motors() -> None:
    with pytest.raises(ValueError, match="pole_pairs"):
        EscTable([1, 2], pole_pairs=[7])
    with pytest.raises(ValueError, match="pole_pairs"):
        EscTable([1], pole_pairs=0)


def test_node_of_malformed_frames() -> None:
    ft_family, ckesc_family = registry.family("ft"), registry.family("ckesc")
    assert ft_family.node_of(can.Message(arbitration_id=0x0000050C, data=b"\0" * 8)) == 5
    assert ckesc_family.node_of(can.Message(arbitration_id=0x1F4E5203, data=b"")) == 3
    assert ft_family.node_of(can.Message(arbitration_id=0x123, is_extended_id=False)) is None
    assert ckesc_family.node_of(can.Message(arbitration_id=0x1F4E5200, data=b"")) is None


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
        good = ftm(2, ft.RealtimeData1(erpm=7000, duty=0.3))
        bad = ftm(2, ft.RealtimeData2(50.0, 50.0, 25.0))
        bad.data[7] ^= 0xFF  # the CRC's low byte
        esc_bus.send(good)
        esc_bus.send(bad)
        esc_bus.send(ftm(1, ft.SetCurrent(3.0)))  # a command: read back, not telemetry
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


def _answering_escs(bus: can.BusABC, answers: list[tuple[int, int]], stop: threading.Event) -> None:
    """Plays CKESCs: each answers GET_ESC_ID with (node, channel) after node % 32 x 2 ms."""
    while not stop.is_set():
        msg = bus.recv(0.05)
        if msg is None:
            continue
        frame = ckesc.decode(msg)
        if frame is not None and isinstance(frame.message, ckesc.GetEscIdRequest):
            for node, channel in sorted(answers, key=lambda a: a[0] % 32):
                time.sleep(0.002)
                bus.send(ck(node, ckesc.GetEscIdAnswer(node, channel)))


@pytest.mark.parametrize(
    ("answers", "expected"),
    [
        ([(40, 1), (33, 2), (7, 3), (9, 4), (50, 9)], {1: 40, 2: 33, 3: 7, 4: 9}),
        ([(40, 1), (7, 3)], {1: 40, 3: 7}),
        ([], {}),
    ],
)
def test_learning_ckesc_ids_by_channel(
    answers: list[tuple[int, int]], expected: dict[int, int]
) -> None:
    host, escs = _virtual_pair(f"test_learn_{len(answers)}")
    stop = threading.Event()
    thread = threading.Thread(target=_answering_escs, args=(escs, answers, stop), daemon=True)
    thread.start()
    try:
        # {motor index: node}: channel c is motor c - 1's here.
        assert learn_node_ids(host, [1, 2, 3, 4]) == {c - 1: n for c, n in expected.items()}
    finally:
        stop.set()
        thread.join()
        host.shutdown()
        escs.shutdown()


def test_two_escs_on_one_channel_are_refused() -> None:
    host, escs = _virtual_pair("test_learn_clash")
    stop = threading.Event()
    thread = threading.Thread(
        target=_answering_escs, args=(escs, [(3, 2), (4, 2)], stop), daemon=True
    )
    thread.start()
    try:
        with pytest.raises(LinkError, match="nodes 3 and 4 both follow throttle channel 2"):
            learn_node_ids(host, [1, 2])
    finally:
        stop.set()
        thread.join()
        host.shutdown()
        escs.shutdown()


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
