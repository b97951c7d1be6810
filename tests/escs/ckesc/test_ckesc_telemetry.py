"""CKESC frames as the ESC state sees them (bridge/escs/ckesc/telemetry.py): every telemetry
message into the neutral record, MSG1 status bits into failure flags; and the node IDs learnt
with GET_ESC_ID (bridge/escs/ckesc/setup.py) on a real python-can bus."""

from __future__ import annotations

import threading
import time

import can
import pytest
from conftest import feed

from bridge.errors import LinkError
from bridge.escs import registry
from bridge.escs.ckesc import codec, records
from bridge.escs.ckesc.keys import CkescKeys
from bridge.escs.ckesc.setup import learn_node_ids
from bridge.escs.ckesc.telemetry import NO_COMMAND, STATUS_FAILURES
from bridge.escs.family import (
    FAILURE_GENERIC,
    FAILURE_OVER_CURRENT,
    FAILURE_OVER_TEMPERATURE,
    FAILURE_OVER_VOLTAGE,
    EscSetup,
)
from bridge.telemetry.state import EscTable, TelemetryLimits

S = records.Msg1Status
MS = 1_000_000
T0 = 10_000 * MS  # an arbitrary monotonic start


def ck(node: int, message: records.CkescMessage, transfer_id: int = 0) -> can.Message:
    frame = codec.CkescFrame(codec.default_priority(message), node, None, transfer_id, message)
    return codec.encode(frame)


def test_ckesc_messages_fill_every_field() -> None:
    table = EscTable([11, 12, 13, 14])
    assert feed(table, ck(12, records.Msg1(5230, 1500, S.RUNNING)), T0)
    assert feed(table, ck(12, records.Msg2(24.51, 12.34, 61)), T0 + MS)
    assert feed(table, ck(12, records.Msg3(62, 45, 70, 55)), T0 + 2 * MS)
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
    feed(table, ck(1, records.MsgExp1(4100, 47.9, 3.25)), T0)
    feed(table, ck(1, records.MsgExp11(50, 40, 35, 60)), T0)
    feed(table, ck(1, records.MsgExp8(17, 230, 228)), T0)
    feed(table, ck(1, records.MsgExp9(3600, records.SelfTestFault.NONE)), T0)
    feed(table, ck(1, records.MsgExp10(95, 0)), T0)
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
    feed(table, ck(1, records.MsgExp9(3600, records.SelfTestFault.PHASE_B_LOW)), T0)
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
    feed(table, ck(3, records.Msg1(0, 0, status)), T0)
    assert table.snapshot(T0)[0].failure_flags == flags


def test_no_command_is_a_failure_only_to_a_commanding_owner() -> None:
    # Every idle CKESC raises its comms fault 200 ms after the last command: the bridge, which
    # sends commands, sees a failure; the monitor, listening, an idle ESC.
    idle = ck(3, records.Msg1(0, 0, S.COMMS_FAULT | S.UNDER_VOLTAGE))
    quiet = ck(3, records.Msg1(0, 0, S.COMMS_FAULT))
    for commanded, flags in ((True, FAILURE_GENERIC), (False, 0)):
        table = EscTable([3], commanded=commanded)
        feed(table, quiet, T0)
        assert table.snapshot(T0)[0].failure_flags == flags
    listening = EscTable([3], commanded=False)
    feed(listening, idle, T0)  # under-voltage is a failure to anyone
    assert listening.snapshot(T0)[0].failure_flags == FAILURE_GENERIC
    feed(listening, ck(3, records.Msg1(0, 0, S(0))), T0 + 1)
    assert listening.snapshot(T0 + 1)[0].failure_flags == 0


def test_every_mapped_status_bit_is_a_fault_bit() -> None:
    mapped = NO_COMMAND
    for bits, _ in STATUS_FAILURES:
        assert not bits & NO_COMMAND
        mapped |= bits
    informational = S.DIRECTION_CCW | S.THROTTLE_SOURCE_PWM | S.RUNNING
    assert mapped | informational == 0xFFFF
    assert mapped & informational == 0


def test_node_of_malformed_frames() -> None:
    decoder = registry.family("ckesc").decoder()
    assert decoder.node_of(can.Message(arbitration_id=0x1F4E5203, data=b"")) == 3
    assert decoder.node_of(can.Message(arbitration_id=0x1F4E5200, data=b"")) is None


def _virtual_pair(channel: str) -> tuple[can.BusABC, can.BusABC]:
    return (
        can.Bus(interface="virtual", channel=channel),
        can.Bus(interface="virtual", channel=channel),
    )


def _answering_escs(bus: can.BusABC, answers: list[tuple[int, int]], stop: threading.Event) -> None:
    """Plays CKESCs: each answers GET_ESC_ID with (node, channel) after node % 32 x 2 ms."""
    while not stop.is_set():
        msg = bus.recv(0.05)
        if msg is None:
            continue
        frame = codec.decode(msg)
        if frame is not None and isinstance(frame.message, records.GetEscIdRequest):
            for node, channel in sorted(answers, key=lambda a: a[0] % 32):
                time.sleep(0.002)
                bus.send(ck(node, records.GetEscIdAnswer(node, channel)))


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
        setup = EscSetup((11, 12, 13, 14), CkescKeys(), channels=(1, 2, 3, 4))
        assert learn_node_ids(host, setup) == {c - 1: n for c, n in expected.items()}
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
            learn_node_ids(host, EscSetup((1, 2), CkescKeys(), channels=(1, 2)))
    finally:
        stop.set()
        thread.join()
        host.shutdown()
        escs.shutdown()
