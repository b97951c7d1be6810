"""The simulated CKESC ESC, driven through real frames: requests built with the production
encoder, answers and telemetry read back with the production decoder.

Time is simulated in whole milliseconds (``Bench``): poll() is called every 1 ms, as a runner
polling at 1 kHz would, so rates and timeouts are checked to the millisecond.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections import Counter
from typing import Any, TypeVar

import can
import pytest

from bridge.errors import TailByteError
from bridge.escs import uavcan_v0
from bridge.escs.ckesc import codec, records
from bridge.escs.ckesc.sim import ESC_INFO, ReportMode, SimCkesc, default_flash

R = TypeVar("R")
FULL_V = 16.8  # a full 4S pack
S = records.Msg1Status
MEDIUM, LOW, LOWEST = uavcan_v0.PRIORITY_MEDIUM, uavcan_v0.PRIORITY_LOW, uavcan_v0.PRIORITY_LOWEST


class Bench:
    """A host (node 0) and a clock in whole milliseconds around one simulated ESC."""

    def __init__(self, sim: SimCkesc, ms: int = 0, supply_v: float = FULL_V) -> None:
        self.sim = sim
        self.ms = ms
        self.supply_v = supply_v
        self.tid = 0
        self.throttle_tid = 0

    @property
    def now(self) -> float:
        return self.ms / 1000

    def next_tid(self) -> int:
        self.tid = (self.tid + 1) % 32
        return self.tid

    def send(self, msg: can.Message) -> list[can.Message]:
        """Hand ``msg`` to the ESC now; what it answers at once."""
        return self.sim.handle(msg, self.now)

    def request(
        self, record: records.CkescMessage, node: int | None = None
    ) -> list[codec.CkescFrame]:
        """A service request to ``node`` (default: the ESC's), its decoded answers."""
        frame = codec.CkescFrame(
            priority=codec.default_priority(record),
            source_node=0,
            destination_node=self.sim.node_id if node is None else node,
            transfer_id=self.next_tid(),
            message=record,
        )
        return decode_all(self.send(codec.encode(frame)))

    def broadcast(self, record: records.CkescMessage) -> list[can.Message]:
        frame = codec.CkescFrame(codec.default_priority(record), 0, None, self.next_tid(), record)
        return self.send(codec.encode(frame))

    def throttle(self, value: int) -> None:
        """RawCommand_12b with ``value`` on the ESC's channel, 0 on the others of its group."""
        channel = self.sim.throttle_channel
        group = (channel - 1) // 4 + 1
        values = [0, 0, 0, 0]
        values[(channel - 1) % 4] = value
        self.throttle_tid = (self.throttle_tid + 1) % 32
        assert self.send(codec.encode_raw_12b(group, values, self.throttle_tid)) == []

    def run(
        self, ms: int, *, throttle: int | None = None, every_ms: int = 10
    ) -> list[tuple[int, can.Message]]:
        """Poll every 1 ms for ``ms`` ms (this ms included, the last excluded), sending
        ``throttle`` every ``every_ms``; every frame out with the ms it came at."""
        out: list[tuple[int, can.Message]] = []
        for _ in range(ms):
            if throttle is not None and self.ms % every_ms == 0:
                self.throttle(throttle)
            out += [(self.ms, msg) for msg in self.sim.poll(self.now, self.supply_v)]
            self.ms += 1
        return out


def decode_all(msgs: list[can.Message]) -> list[codec.CkescFrame]:
    frames = [codec.decode(msg) for msg in msgs]
    assert all(frame is not None for frame in frames)
    return [frame for frame in frames if frame is not None]


def of_kind(out: list[tuple[int, can.Message]], kind: type[R]) -> list[R]:
    """The decoded ``kind`` records among ``out``, in order."""
    return [f.message for f in decode_all([m for _, m in out]) if isinstance(f.message, kind)]


def type_counts(out: list[tuple[int, can.Message]]) -> Counter[int]:
    return Counter(uavcan_v0.parse_id(msg.arbitration_id).type_id for _, msg in out)


def response(record: records.CkescMessage, node: int, tid: int) -> codec.CkescFrame:
    """The frame the ESC at ``node`` should answer with."""
    return codec.CkescFrame(codec.default_priority(record), node, 0, tid, record)


def service_raw(service: int, node: int, data: bytes, priority: int = MEDIUM) -> can.Message:
    """A request frame built by hand (for values the encoder rightly refuses)."""
    can_id = uavcan_v0.service_id(priority, service, True, node, 0)
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=True)


def stop_motor(bench: Bench) -> None:
    """Throttle 0 until the reported speed is 0 (Set Rotation and Expand Set need it)."""
    bench.run(2000, throttle=0)
    assert bench.sim.motor.rpm == pytest.approx(0, abs=0.5)


# --------------------------------------------------------------------------------------------
# Telemetry


def test_default_rates_transfer_ids_and_ids() -> None:
    bench = Bench(SimCkesc(3, 1))
    out = bench.run(1000, throttle=0)
    assert type_counts(out) == {records.TYPE_MSG1: 50, records.TYPE_MSG2: 10, records.TYPE_MSG3: 2}
    frames = decode_all([m for _, m in out])
    for record_type in (records.Msg1, records.Msg2, records.Msg3):
        mine = [f for f in frames if isinstance(f.message, record_type)]
        assert [f.transfer_id for f in mine] == [i % 32 for i in range(len(mine))]
        assert {(f.priority, f.source_node, f.destination_node) for f in mine} == {
            (LOWEST, 3, None)
        }
    msg1_ms = [
        ms for ms, m in out if uavcan_v0.parse_id(m.arbitration_id).type_id == records.TYPE_MSG1
    ]
    assert msg1_ms == list(range(0, 1000, 20))


def test_a_poll_gap_skips_ahead_instead_of_bursting() -> None:
    bench = Bench(SimCkesc(3, 1))
    bench.run(1)
    bench.ms = 1000  # a 1 s stall of the caller
    out = bench.run(100)
    msg1_ms = [
        ms for ms, m in out if uavcan_v0.parse_id(m.arbitration_id).type_id == records.TYPE_MSG1
    ]
    assert msg1_ms == [1000, 1020, 1040, 1060, 1080]


def test_telemetry_follows_the_12b_throttle_of_its_channel() -> None:
    sim = SimCkesc(4, 6)  # channel 6: group 2, second slot
    bench = Bench(sim)
    out = bench.run(601, throttle=1500)  # the last poll (600 ms) sends MSG1
    msg1 = of_kind(out, records.Msg1)[-1]
    assert msg1 == records.Msg1(round(abs(sim.motor.rpm)), 1500, S.RUNNING)
    assert sim.motor.rpm == pytest.approx(1500 / 2000 * 920 * FULL_V, rel=0.01)
    msg2 = of_kind(out, records.Msg2)[-1]
    assert msg2.voltage_v == FULL_V
    assert msg2.current_a == pytest.approx(sim.motor.current_a, abs=0.01)
    assert msg2.current_a > 5
    assert msg2.mos_temp_c == round(sim.motor.mos_temp_c)
    msg3 = of_kind(out, records.Msg3)[-1]
    assert msg3.motor_temp_c == round(sim.motor.motor_temp_c)
    assert msg3.mos_temp_c >= 25 and msg3.capacitor_temp_c >= 25 and msg3.mcu_temp_c >= 30
    # A frame for group 1 (channels 1..4) carries nothing for channel 6: comms time out.
    for ms in range(0, 300, 10):
        bench.send(codec.encode_raw_12b(1, [2000, 2000, 2000, 2000], ms // 10 % 32))
        bench.run(10)
    assert sim.applied_throttle == 0 and sim.comms_fault


@pytest.mark.parametrize(
    ("channel", "frame", "expected"),
    [
        (3, codec.encode_raw_14b([0, 0, 1200, 0], 0), 1200),
        (4, codec.encode_raw_14b([0, 0, 1200, 2000], 0), 2000),
        (3, codec.encode_raw_10b([0, 0, 600, 0, 0, 0]), 1200),
        (6, codec.encode_raw_10b([1, 1, 1, 1, 1, 1000]), 2000),
        (5, codec.encode_raw_12b(2, [1999, 1], 0), 1999),
        (5, codec.encode_raw_14b([1000, 1000, 1000, 1000], 0), None),  # 14b: channels 1..4
        (7, codec.encode_raw_10b([1000] * 6), None),  # 10b: channels 1..6
    ],
)
def test_throttle_formats(channel: int, frame: can.Message, expected: int | None) -> None:
    sim = SimCkesc(2, channel)
    bench = Bench(sim)
    bench.run(5)
    assert bench.send(frame) == []
    out = bench.run(30)
    if expected is None:
        assert sim.stats.commands == 0
        assert of_kind(out, records.Msg1)[-1].throttle == 0
    else:
        assert sim.stats.commands == 1
        assert of_kind(out, records.Msg1)[-1].throttle == expected
        assert sim.motor.rpm > 0


def test_invalid_throttles_are_not_commands() -> None:
    sim = SimCkesc(2, 1)
    bench = Bench(sim)
    bench.throttle(800)
    # 12b with 2500 on channel 1 (the encoder refuses it: build it by hand), 10b with 1001,
    # a 12b frame from node 5, one with a bad tail byte and one for group 7.
    bad_12b = (2500 | 1 << 48 | 0xC1 << 56).to_bytes(8, "little")
    bad_10b = (1001).to_bytes(8, "little")
    good = codec.encode_raw_12b(1, [2000], 2)
    frames = [
        can.Message(arbitration_id=good.arbitration_id, data=bad_12b, is_extended_id=True),
        can.Message(
            arbitration_id=codec.encode_raw_10b([0]).arbitration_id,
            data=bad_10b,
            is_extended_id=True,
        ),
        codec.encode_raw_12b(1, [2000], 3, source_node=5),
        can.Message(
            arbitration_id=good.arbitration_id, data=good.data[:7] + b"\x02", is_extended_id=True
        ),
        can.Message(
            arbitration_id=good.arbitration_id,
            data=(2000 | 7 << 48 | 0xC4 << 56).to_bytes(8, "little"),
            is_extended_id=True,
        ),
    ]
    for _ in range(25):
        for msg in frames:
            bench.send(msg)
        bench.run(10)
    assert sim.stats.commands == 1
    assert sim.stats.bad_frames == 25 * 4  # all but the frame from node 5
    assert sim.comms_fault and sim.applied_throttle == 0


def test_reversed_rotation_reports_positive_speed_and_the_direction_bit() -> None:
    sim = SimCkesc(8, 1)
    bench = Bench(sim)
    assert bench.request(records.SetRotationRequest(records.Rotation.REVERSED)) == [
        response(records.SetRotationResponse(records.Rotation.REVERSED), 8, bench.tid)
    ]
    out = bench.run(501, throttle=1000)  # the last poll (500 ms) sends MSG1
    assert sim.motor.rpm < -5000
    assert of_kind(out, records.Msg1)[-1] == records.Msg1(
        round(-sim.motor.rpm), 1000, S.RUNNING | S.DIRECTION_CCW
    )


def test_comms_fault_after_200_ms_cleared_by_the_next_command() -> None:
    sim = SimCkesc(3, 1)
    bench = Bench(sim)
    bench.run(1000, throttle=1000)  # the last command at 990 ms
    bench.run(180)  # polls 1000 .. 1179
    out = bench.run(1)  # 1180 ms: 190 ms after the command
    assert not sim.comms_fault and sim.applied_throttle == 1000
    assert of_kind(out, records.Msg1) == [records.Msg1(round(sim.motor.rpm), 1000, S.RUNNING)]
    bench.run(9)  # 1181 .. 1189
    assert not sim.comms_fault
    bench.run(1)  # 1190 ms: 200 ms
    assert sim.comms_fault and sim.applied_throttle == 0
    assert sim.stats.comms_faults == 1
    out = bench.run(30)
    msg1 = of_kind(out, records.Msg1)[0]
    assert msg1.throttle == 0 and msg1.status & S.COMMS_FAULT
    bench.throttle(700)
    assert not sim.comms_fault and sim.applied_throttle == 700
    out = bench.run(20)
    assert of_kind(out, records.Msg1)[0] == records.Msg1(round(sim.motor.rpm), 700, S.RUNNING)


def test_comms_fault_from_power_up_without_commands() -> None:
    sim = SimCkesc(3, 1, power_on_s=5.0)
    bench = Bench(sim, ms=5000)
    bench.run(200)  # 5.000 .. 5.199
    assert not sim.comms_fault
    out = bench.run(1)
    assert sim.comms_fault
    assert of_kind(out, records.Msg1)[0].status == S.COMMS_FAULT


def test_pwm_and_can_prefers_pwm_and_falls_back_to_can() -> None:
    sim = SimCkesc(3, 1)
    bench = Bench(sim)
    bench.throttle(500)
    # Throttle Select only at zero throttle: refused, answered with the source in use.
    assert bench.request(records.ThrottleSelectRequest(records.ThrottleSource.PWM_AND_CAN)) == [
        response(records.ThrottleSelectResponse(records.ThrottleSource.CAN), 3, bench.tid)
    ]
    assert sim.stats.refused == 1
    bench.throttle(0)
    assert bench.request(records.ThrottleSelectRequest(records.ThrottleSource.PWM_AND_CAN)) == [
        response(records.ThrottleSelectResponse(records.ThrottleSource.PWM_AND_CAN), 3, bench.tid)
    ]
    assert sim.flash["throttle_source"] == records.ThrottleSource.PWM_AND_CAN
    # An unknown source (0x02, built by hand) is refused.
    raw = service_raw(records.SERVICE_THROTTLE_SELECT, 3, bytes((2, 0xC7)))
    assert decode_all(bench.send(raw)) == [
        response(records.ThrottleSelectResponse(records.ThrottleSource.PWM_AND_CAN), 3, 7)
    ]
    assert sim.stats.refused == 2
    sim.pwm_throttle = 300  # a PWM signal: CAN throttle ignored
    out = bench.run(241, throttle=1500, every_ms=100)  # the last poll (240 ms) sends MSG1
    assert of_kind(out, records.Msg1)[-1] == records.Msg1(
        round(sim.motor.rpm), 300, S.RUNNING | S.THROTTLE_SOURCE_PWM
    )
    out = bench.run(300)  # no CAN at all: no comms fault while PWM drives
    assert of_kind(out, records.Msg1)[-1].status == S.RUNNING | S.THROTTLE_SOURCE_PWM
    sim.pwm_throttle = None  # PWM lost: CAN takes over
    out = bench.run(100, throttle=1500)
    assert of_kind(out, records.Msg1)[-1].throttle == 1500
    assert not of_kind(out, records.Msg1)[-1].status & S.THROTTLE_SOURCE_PWM


def test_status_voltage_and_model_limits() -> None:
    sim = SimCkesc(3, 1)
    bench = Bench(sim)
    out = bench.run(20, throttle=0)
    assert sim.cells == 4
    assert of_kind(out, records.Msg1)[0].status == 0
    bench.supply_v = 11.9  # below 3.0 V per cell
    assert of_kind(bench.run(20, throttle=0), records.Msg1)[0].status == S.UNDER_VOLTAGE
    bench.supply_v = 12.1
    assert of_kind(bench.run(20, throttle=0), records.Msg1)[0].status == 0
    bench.supply_v = 61.0  # above 4.35 V at the rated 14 cells
    assert of_kind(bench.run(20, throttle=0), records.Msg1)[0].status == S.OVER_VOLTAGE
    bench.supply_v = FULL_V
    sim.motor.mos_temp_c = 115.0  # the model, not a fault
    assert of_kind(bench.run(20, throttle=0), records.Msg1)[0].status == S.OVER_TEMPERATURE
    sim.motor.mos_temp_c = 100.0
    assert of_kind(bench.run(20, throttle=0), records.Msg1)[0].status == 0


def test_self_test_result() -> None:
    sim = SimCkesc(3, 1)
    bench = Bench(sim)
    assert bench.request(records.SelfTestRequest()) == [
        response(records.SelfTestResponse(True), 3, bench.tid)
    ]
    sim.self_test_fault = records.SelfTestFault.PHASE_B_LOW
    assert bench.request(records.SelfTestRequest()) == [
        response(records.SelfTestResponse(False), 3, bench.tid)
    ]
    out = bench.run(20, throttle=0)
    assert of_kind(out, records.Msg1)[0].status == S.SELF_TEST_PHASE_B_OUTPUT_LOW
    maintenance = bench.request(records.MaintenanceRequest(2))[0].message
    assert maintenance == records.Maintenance2Response(1, 0, records.SelfTestFault.PHASE_B_LOW)
    sim.self_test_fault = records.SelfTestFault.COM_HIGH
    assert of_kind(bench.run(20, throttle=0), records.Msg1)[0].status == S.SELF_TEST_COM_INPUT_HIGH


# --------------------------------------------------------------------------------------------
# Reports control, GET_ESC_ID, CANTest


def test_get_esc_id_answer_waits_node_id_mod_32_times_2_ms() -> None:
    sim = SimCkesc(39, 11)  # 39 % 32 = 7: 14 ms
    bench = Bench(sim, ms=3000)
    bench.run(7)
    assert bench.broadcast(records.GetEscIdRequest()) == []  # at 3007 ms
    out = bench.run(100)
    timed = [
        (ms, frame)
        for (ms, _), frame in zip(out, decode_all([m for _, m in out]), strict=True)
        if isinstance(frame.message, records.GetEscIdAnswer)
    ]
    assert timed == [(3021, codec.CkescFrame(MEDIUM, 39, None, 0, records.GetEscIdAnswer(39, 11)))]
    # Node 64 (64 % 32 = 0) answers at once, from handle(); its transfer ID counts per type.
    sim = SimCkesc(64, 2)
    bench = Bench(sim)
    for tid in range(2):
        answers = decode_all(bench.broadcast(records.GetEscIdRequest()))
        assert answers == [codec.CkescFrame(MEDIUM, 64, None, tid, records.GetEscIdAnswer(64, 2))]


def test_msg_control_pause_resume_exp_and_msg() -> None:
    sim = SimCkesc(5, 1)  # ack after 10 ms
    bench = Bench(sim)
    bench.run(100, throttle=800)
    assert bench.broadcast(records.MsgControlRequest(records.MsgControlCommand.PAUSE)) == []
    out = bench.run(1000, throttle=800)
    assert decode_all([m for _, m in out]) == [
        codec.CkescFrame(
            MEDIUM, 5, None, 0, records.MsgControlAck(records.MsgControlCommand.ACK, 0)
        )
    ]
    assert out[0][0] == 110  # sent at 100 ms, node 5: 10 ms later
    assert sim.report_mode == ReportMode.PAUSED
    assert sim.applied_throttle == 800  # paused reports, not paused control
    # While paused, Set LED and Set Rotation are refused (answered with what is in effect).
    assert bench.request(records.SetLedRequest(False, records.LedColor.RED, 1)) == [
        response(records.SetLedResponse(False, records.LedColor.GREEN, 0), 5, bench.tid)
    ]
    assert bench.request(records.SetRotationRequest(records.Rotation.QUERY)) == [
        response(records.SetRotationResponse(records.Rotation.NORMAL), 5, bench.tid)
    ]

    bench.broadcast(records.MsgControlRequest(records.MsgControlCommand.RESUME_EXP))
    out = bench.run(1000, throttle=800)
    counts = type_counts(out)
    assert counts[records.TYPE_MSG_CONTROL] == 1
    assert counts[records.TYPE_MSG_EXP1] == 50
    for type_id in (
        *range(records.TYPE_MSG_EXP2, records.TYPE_MSG_EXP6 + 1),
        records.TYPE_MSG_EXP11,
    ):
        assert counts[type_id] == 10, type_id
    for type_id in range(records.TYPE_MSG_EXP7, records.TYPE_MSG_EXP10 + 1):
        assert counts[type_id] == 2, type_id
    assert counts[records.TYPE_MSG1] == counts[records.TYPE_MSG2] == counts[records.TYPE_MSG3] == 0
    assert counts[records.TYPE_MSG_EXP12] == 0
    assert of_kind(out, records.MsgExp1)[-1] == records.MsgExp1(
        round(sim.motor.rpm), FULL_V, round(sim.motor.current_a, 2)
    )
    assert of_kind(out, records.MsgExp2)[-1] == records.MsgExp2(bytes(6))
    assert of_kind(out, records.MsgExp7)[-1] == records.MsgExp7(1, 2, 3, 1, 2, 2, 2, 0, 8, 8)
    assert of_kind(out, records.MsgExp8)[-1] == records.MsgExp8(1, 1, 0)
    assert of_kind(out, records.MsgExp9)[-1] == records.MsgExp9(1, records.SelfTestFault.NONE)
    assert of_kind(out, records.MsgExp10)[-1] == records.MsgExp10(1, 0)
    exp11 = of_kind(out, records.MsgExp11)[-1]
    assert exp11.mos_temp_c == round(sim.motor.mos_temp_c)
    assert exp11.motor_temp_c == round(sim.motor.motor_temp_c)

    bench.broadcast(records.MsgControlRequest(records.MsgControlCommand.RESUME_MSG))
    out = bench.run(1000, throttle=800)
    counts = type_counts(out)
    assert (counts[records.TYPE_MSG1], counts[records.TYPE_MSG2], counts[records.TYPE_MSG3]) == (
        50,
        10,
        2,
    )
    assert counts[records.TYPE_MSG_EXP1] == 0
    msg3 = of_kind(out, records.Msg3)[-1]
    assert (msg3.mos_temp_c, msg3.mcu_temp_c, msg3.capacitor_temp_c, msg3.motor_temp_c) == (
        exp11.mos_temp_c,
        exp11.mcu_temp_c,
        exp11.capacitor_temp_c,
        exp11.motor_temp_c,
    )


def test_set_rotation_refused_while_reports_are_paused() -> None:
    sim = SimCkesc(7, 1)
    bench = Bench(sim)
    bench.broadcast(records.MsgControlRequest(records.MsgControlCommand.PAUSE))
    assert bench.request(records.SetRotationRequest(records.Rotation.REVERSED)) == [
        response(records.SetRotationResponse(records.Rotation.NORMAL), 7, bench.tid)
    ]
    bench.broadcast(records.MsgControlRequest(records.MsgControlCommand.RESUME_MSG))
    assert bench.request(records.SetRotationRequest(records.Rotation.REVERSED)) == [
        response(records.SetRotationResponse(records.Rotation.REVERSED), 7, bench.tid)
    ]
    assert sim.stats.refused == 1


def test_can_test_mode_counts_and_restores_reports() -> None:
    sim = SimCkesc(6, 1)
    bench = Bench(sim)
    bench.run(100, throttle=0)
    bench.broadcast(records.CanTestRequest(records.CanTestOption.ENTER))
    out = bench.run(1000, throttle=0)
    assert set(type_counts(out)) == {records.TYPE_CAN_TEST}
    reports = decode_all([m for _, m in out])
    assert [f.message for f in reports] == [records.CanTestReport(i) for i in range(500)]
    assert [f.transfer_id for f in reports] == [i % 32 for i in range(500)]
    assert {(f.priority, f.source_node) for f in reports} == {(LOWEST, 6)}
    bench.broadcast(records.CanTestRequest(records.CanTestOption.LEAVE))
    counts = type_counts(bench.run(1000, throttle=0))
    assert counts == {records.TYPE_MSG1: 50, records.TYPE_MSG2: 10, records.TYPE_MSG3: 2}
    bench.broadcast(records.CanTestRequest(records.CanTestOption.ENTER))
    assert of_kind(bench.run(4), records.CanTestReport) == [
        records.CanTestReport(500),
        records.CanTestReport(501),
    ]


# --------------------------------------------------------------------------------------------
# Services


def test_set_freq_changes_the_rates_and_refuses_bad_writes() -> None:
    flash: dict[str, Any] = {}
    sim = SimCkesc(3, 1, flash=flash)
    bench = Bench(sim)
    assert bench.request(records.SetFreqRequest(False, 0, 0, 0)) == [
        response(records.SetFreqResponse(False, 20, 100, 500), 3, bench.tid)
    ]
    assert bench.request(records.SetFreqRequest(True, 40, 200, 250)) == [
        response(records.SetFreqResponse(True, 40, 200, 250), 3, bench.tid)
    ]
    counts = type_counts(bench.run(1000, throttle=0))
    assert counts == {records.TYPE_MSG1: 25, records.TYPE_MSG2: 5, records.TYPE_MSG3: 4}
    # MSG1 at 18 ms (byte 9) is out of range: the whole write is ignored.
    bad = service_raw(records.SERVICE_SET_FREQ, 3, bytes((1, 9, 100, 100, 0xC5)))
    assert decode_all(bench.send(bad)) == [
        response(records.SetFreqResponse(True, 40, 200, 250), 3, 5)
    ]
    assert sim.stats.refused == 1
    # Saved to flash: a power cycle keeps the intervals.
    bench = Bench(SimCkesc(3, 1, flash=flash))
    counts = type_counts(bench.run(1000, throttle=0))
    assert counts == {records.TYPE_MSG1: 25, records.TYPE_MSG2: 5, records.TYPE_MSG3: 4}


def test_set_id_alone_within_120_s_survives_a_power_cycle() -> None:
    flash: dict[str, Any] = {}
    sim = SimCkesc(records.FACTORY_NODE_ID, 1, flash=flash, power_on_s=100.0)
    bench = Bench(sim, ms=100_000)
    assert bench.run(1000, throttle=0) == []  # node 0x7D sends no telemetry
    bench.ms = 100_000 + 119_900
    # The destination is ignored (42 here): the answer comes from the new node ID.
    assert bench.request(records.SetIdRequest(9, 3), node=42) == [
        response(records.SetIdResponse(9, 3), 9, bench.tid)
    ]
    assert (sim.node_id, sim.throttle_channel) == (9, 3)
    assert (flash["node_id"], flash["throttle_channel"]) == (9, 3)
    out = bench.run(100, throttle=900)
    assert {uavcan_v0.parse_id(m.arbitration_id).source_node for _, m in out} == {9}
    assert of_kind(out, records.Msg1)[-1].throttle == 900  # follows channel 3

    # Power cycle: the same flash, whatever the constructor says.
    sim = SimCkesc(records.FACTORY_NODE_ID, 1, flash=flash, power_on_s=500.0)
    bench = Bench(sim, ms=500_000)
    assert (sim.node_id, sim.throttle_channel) == (9, 3)
    assert bench.request(records.MaintenanceRequest(2)) == [
        response(records.Maintenance2Response(2, 0, records.SelfTestFault.NONE), 9, bench.tid)
    ]
    bench.broadcast(records.GetEscIdRequest())
    assert of_kind(bench.run(19), records.GetEscIdAnswer) == [records.GetEscIdAnswer(9, 3)]


def test_set_id_refused_after_120_s() -> None:
    flash = default_flash(5, 1)
    sim = SimCkesc(5, 1, flash=flash, power_on_s=10.0)
    bench = Bench(sim, ms=10_000 + 120_001)
    assert bench.request(records.SetIdRequest(9, 3), node=0) == [
        response(records.SetIdResponse(5, 1), 5, bench.tid)
    ]
    assert (sim.node_id, sim.throttle_channel, flash["node_id"]) == (5, 1, 5)
    assert sim.stats.refused == 1


def test_set_id_refused_while_another_esc_is_on_the_bus() -> None:
    sim = SimCkesc(5, 1)
    bench = Bench(sim, ms=5000)
    other = codec.encode(codec.CkescFrame(LOWEST, 6, None, 0, records.Msg1(0, 0, S(0))))
    assert bench.send(other) == []
    bench.ms = 5900
    assert bench.request(records.SetIdRequest(9, 3)) == [
        response(records.SetIdResponse(5, 1), 5, bench.tid)
    ]
    assert sim.node_id == 5
    bench.ms = 6001  # 1.001 s later: alone again
    assert bench.request(records.SetIdRequest(9, 3)) == [
        response(records.SetIdResponse(9, 3), 9, bench.tid)
    ]
    # Out-of-range values (built by hand: the encoder refuses them) are refused too.
    for data in (bytes((0x7E, 1, 0xC0)), bytes((0, 1, 0xC0)), bytes((9, 21, 0xC0))):
        answer = decode_all(bench.send(service_raw(records.SERVICE_SET_ID, 9, data)))
        assert answer == [response(records.SetIdResponse(9, 3), 9, 0)]
    assert sim.stats.refused == 4


def test_set_baud_within_120_s_applies_after_a_power_cycle() -> None:
    flash: dict[str, Any] = {}
    sim = SimCkesc(5, 1, flash=flash)
    bench = Bench(sim, ms=60_000)
    assert bench.request(records.SetBaudRequest(0)) == [
        response(records.SetBaudResponse(0), 5, bench.tid)
    ]
    assert sim.baud_code == 1 and flash["baud_code"] == 0
    bad = service_raw(records.SERVICE_SET_BAUD, 5, bytes((7, 0xC3)))
    assert decode_all(bench.send(bad)) == [response(records.SetBaudResponse(0), 5, 3)]
    bench.ms = 121_000
    assert bench.request(records.SetBaudRequest(4)) == [
        response(records.SetBaudResponse(0), 5, bench.tid)
    ]
    assert sim.stats.refused == 2
    assert SimCkesc(5, 1, flash=flash).baud_code == 0


def test_set_led_volatile_or_saved() -> None:
    flash: dict[str, Any] = {}
    sim = SimCkesc(5, 1, flash=flash)
    bench = Bench(sim)
    assert bench.request(
        records.SetLedRequest(False, records.LedColor.RED | records.LedColor.BLUE, 2)
    ) == [
        response(
            records.SetLedResponse(False, records.LedColor.RED | records.LedColor.BLUE, 2),
            5,
            bench.tid,
        )
    ]
    config = bench.request(records.MajorConfigRequest())[0].message
    assert isinstance(config, records.MajorConfigResponse)
    assert (config.led_color, config.led_blink_hz) == (
        records.LedColor.RED | records.LedColor.BLUE,
        2,
    )
    assert SimCkesc(5, 1, flash=flash).led_color == records.LedColor.GREEN  # not saved
    # An unknown blink rate is taken as steady; the colour's upper bits are dropped.
    raw = service_raw(records.SERVICE_SET_LED, 5, bytes((1, 0xFC, 3, 0xC9)), LOW)
    assert decode_all(bench.send(raw)) == [
        response(records.SetLedResponse(True, records.LedColor.RED, 0), 5, 9)
    ]
    assert SimCkesc(5, 1, flash=flash).led_color == records.LedColor.RED
    assert bench.request(records.SetLedRequest(False, records.LedColor(0), 0)) == [
        response(records.SetLedResponse(False, records.LedColor(0), 0), 5, bench.tid)
    ]


def test_set_rotation_query_and_motor_running_refusal() -> None:
    flash: dict[str, Any] = {}
    sim = SimCkesc(5, 1, flash=flash)
    bench = Bench(sim)
    bench.run(300, throttle=600)
    assert bench.request(records.SetRotationRequest(records.Rotation.REVERSED)) == [
        response(records.SetRotationResponse(records.Rotation.NORMAL), 5, bench.tid)
    ]
    assert sim.stats.refused == 1
    bench.run(200, throttle=0)  # throttle 0 but still turning
    assert bench.request(records.SetRotationRequest(records.Rotation.REVERSED))[0].message == (
        records.SetRotationResponse(records.Rotation.NORMAL)
    )
    stop_motor(bench)
    assert bench.request(records.SetRotationRequest(records.Rotation.REVERSED))[0].message == (
        records.SetRotationResponse(records.Rotation.REVERSED)
    )
    assert bench.request(records.SetRotationRequest(records.Rotation.QUERY)) == [
        response(records.SetRotationResponse(records.Rotation.REVERSED), 5, bench.tid)
    ]
    raw = service_raw(records.SERVICE_SET_ROTATION, 5, bytes((2, 0xC4)), LOW)
    assert decode_all(bench.send(raw)) == [
        response(records.SetRotationResponse(records.Rotation.REVERSED), 5, 4)
    ]
    assert sim.stats.refused == 3
    assert SimCkesc(5, 1, flash=flash).reversed


def test_information_services() -> None:
    sim = SimCkesc(5, 7)
    bench = Bench(sim, ms=0)
    bench.run(3500, throttle=2000)  # polls 0 .. 3499 ms
    assert bench.request(records.EscInfoRequest()) == [response(ESC_INFO, 5, bench.tid)]
    mos_max = sim.flash["temp_records"]["mos"][0]
    cap_max = sim.flash["temp_records"]["capacitor"][0]
    assert mos_max > 25 and cap_max > 25
    assert bench.request(records.MaintenanceRequest(0)) == [
        response(records.Maintenance0Response(3, mos_max, cap_max), 5, bench.tid)
    ]
    assert bench.request(records.MaintenanceRequest(1)) == [
        response(records.Maintenance1Response(3, 1), 5, bench.tid)
    ]
    assert bench.request(records.MaintenanceRequest(2)) == [
        response(records.Maintenance2Response(1, 0, records.SelfTestFault.NONE), 5, bench.tid)
    ]
    raw = service_raw(records.SERVICE_MAINTENANCE, 5, bytes((3, 0xC0)))
    assert bench.send(raw) == []  # option 3: no response record exists
    assert bench.request(records.MajorConfigRequest()) == [
        response(
            records.MajorConfigResponse(
                False, records.ThrottleSource.CAN, 7, 0, records.LedColor.GREEN, 20, 100, 500
            ),
            5,
            bench.tid,
        )
    ]
    # Power cycle: run time starts again, the total goes on, maxima and counts are kept.
    sim = SimCkesc(5, 7, flash=sim.flash, power_on_s=10.0)
    bench = Bench(sim, ms=10_000)
    bench.run(2001)  # 2.000 s powered; 3.499 s before
    assert bench.request(records.MaintenanceRequest(0)) == [
        response(records.Maintenance0Response(5, mos_max, cap_max), 5, bench.tid)
    ]
    assert bench.request(records.MaintenanceRequest(1)) == [
        response(records.Maintenance1Response(2, 2), 5, bench.tid)
    ]
    assert bench.request(records.MaintenanceRequest(2)) == [
        response(
            records.Maintenance2Response(2, 0, records.SelfTestFault.NONE), 5, bench.tid
        )  # comms stop
    ]


def test_requests_for_other_nodes_or_from_other_nodes_are_ignored() -> None:
    sim = SimCkesc(5, 1)
    bench = Bench(sim)
    assert bench.request(records.EscInfoRequest(), node=6) == []
    from_esc = codec.encode(codec.CkescFrame(MEDIUM, 6, 5, 0, records.EscInfoRequest()))
    assert bench.send(from_esc) == []
    assert sim.stats.requests == 0


def test_expand_set() -> None:
    sim = SimCkesc(5, 1)
    bench = Bench(sim)
    bench.run(100, throttle=500)
    assert bench.request(records.ExpandSetRequest(records.ExpandSetCommand.PROP_LOCK, 3)) == []
    assert sim.beeps == 0 and sim.flash["prop_lock"] == 0  # motor running
    stop_motor(bench)
    for command, part in [
        (records.ExpandSetCommand.DIRECTION, 2),
        (records.ExpandSetCommand.LED, 3),
        (records.ExpandSetCommand.THROTTLE_INTERFACE, 2),
        (records.ExpandSetCommand.PROP_LOCK, 3),
        (records.ExpandSetCommand.STARTUP_ACCELERATION, 15),
        (records.ExpandSetCommand.SIGNAL_LOSS_RATE, 4),
        (records.ExpandSetCommand.ACTIVE_FREEWHEELING, 0),
        (records.ExpandSetCommand.BAUD, 2),
        (records.ExpandSetCommand.SYSTEM, 0x11),
    ]:
        assert bench.request(records.ExpandSetRequest(command, part)) == [], command
    assert sim.beeps == 9
    assert sim.debug_mode and sim.flash["baud_code"] == 2 and sim.baud_code == 1
    assert (
        bench.request(records.ExpandSetRequest(records.ExpandSetCommand.THROTTLE_INTERFACE, 5))
        == []
    )
    assert bench.request(records.ExpandSetRequest(records.ExpandSetCommand.SYSTEM, 0)) == []
    assert sim.beeps == 9  # UAVCAN interface and factory reset are not supported
    bench.broadcast(records.MsgControlRequest(records.MsgControlCommand.RESUME_EXP))
    out = bench.run(20, throttle=0)
    assert of_kind(out, records.MsgExp7) == [records.MsgExp7(2, 3, 2, 0, 2, 2, 2, 3, 15, 4)]
    config = bench.request(records.MajorConfigRequest())[0].message
    assert config == records.MajorConfigResponse(
        True, records.ThrottleSource.PWM_AND_CAN, 1, 0, records.LedColor.BLUE, 20, 100, 500
    )


def test_temperature_records_once_per_request() -> None:
    sim = SimCkesc(5, 1)
    bench = Bench(sim)
    sim.faults.over_temperature = True
    bench.run(1000)
    sim.faults.over_temperature = False
    stop_motor(bench)
    answers = bench.request(records.ExpandSetRequest(records.ExpandSetCommand.READ_TEMP_RECORD, 1))
    assert [f.message for f in answers] == [
        records.MsgExp12(records.TempRecordKind.MCU, records_of(sim, "mcu")[0], 1, 0),
        records.MsgExp12(records.TempRecordKind.MOS, 150, 1, 0),
        records.MsgExp12(records.TempRecordKind.CAPACITOR, records_of(sim, "capacitor")[0], 1, 0),
        records.MsgExp12(records.TempRecordKind.MOTOR, records_of(sim, "motor")[0], 1, 0),
    ]
    assert {(f.priority, f.source_node, f.transfer_id) for f in answers} == {(LOWEST, 5, None)}
    assert type_counts(bench.run(1000, throttle=0))[records.TYPE_MSG_EXP12] == 0
    # Get (223) and Clear (224) Temperature Record, payload unspecified: one byte + tail here.
    get = service_raw(records.SERVICE_GET_TEMP_RECORD, 5, bytes((0, 0xC0)))
    assert len(decode_all(bench.send(get))) == 4
    assert bench.send(service_raw(records.SERVICE_GET_TEMP_RECORD, 6, bytes((0, 0xC0)))) == []
    clear = service_raw(records.SERVICE_CLEAR_TEMP_RECORD, 5, bytes((0, 0xC0)))
    assert bench.send(clear) == []
    after = [f.message for f in decode_all(bench.send(get))]
    assert [r.max_temp_c for r in after if isinstance(r, records.MsgExp12)] == [0, 0, 0, 0]


def records_of(sim: SimCkesc, name: str) -> list[int]:
    record: list[int] = sim.flash["temp_records"][name]
    return record


def test_start_and_stop_counts() -> None:
    flash: dict[str, Any] = {}
    sim = SimCkesc(5, 1, flash=flash)
    bench = Bench(sim)
    bench.run(100, throttle=1000)
    bench.run(100, throttle=0)  # a normal stop
    bench.run(100, throttle=1000)
    bench.run(300)  # comms fault: not a normal stop
    assert (flash["start_count"], flash["stop_count"]) == (2, 1)
    bench.broadcast(records.MsgControlRequest(records.MsgControlCommand.RESUME_EXP))
    assert of_kind(bench.run(20), records.MsgExp8) == [records.MsgExp8(1, 2, 1)]


# --------------------------------------------------------------------------------------------
# Faults


def test_fault_over_temperature_and_over_current() -> None:
    sim = SimCkesc(3, 1)
    bench = Bench(sim)
    bench.run(200, throttle=1000)
    sim.faults.over_temperature = True
    out = bench.run(500, throttle=1000)
    assert of_kind(out, records.Msg1)[-1].status == S.RUNNING | S.OVER_TEMPERATURE
    assert of_kind(out, records.Msg2)[-1].mos_temp_c == 150
    assert of_kind(out, records.Msg3)[-1].mos_temp_c == 150
    sim.faults.over_temperature = False
    sim.faults.over_current = True
    out = bench.run(100, throttle=1000)
    assert of_kind(out, records.Msg1)[-1].status == S.RUNNING | S.OVER_CURRENT
    assert of_kind(out, records.Msg2)[-1].current_a == 600.0
    sim.faults.over_current = False
    out = bench.run(100, throttle=1000)
    assert of_kind(out, records.Msg1)[-1].status == S.RUNNING
    assert of_kind(out, records.Msg2)[-1].current_a < 80


def test_fault_corrupt_spoils_every_report_not_the_answers() -> None:
    sim = SimCkesc(3, 1)
    bench = Bench(sim)
    sim.faults.corrupt = True
    out = bench.run(1000, throttle=0)
    assert len(out) == 62
    for _, msg in out:
        with pytest.raises(TailByteError):
            codec.decode(msg)
    assert bench.request(records.EscInfoRequest()) == [response(ESC_INFO, 3, bench.tid)]
    sim.faults.corrupt = False
    assert len(decode_all([m for _, m in bench.run(100, throttle=0)])) > 0


def test_fault_silent_sends_nothing_but_obeys() -> None:
    sim = SimCkesc(32, 1)  # answers GET_ESC_ID at once when not silent
    bench = Bench(sim)
    sim.faults.silent = True
    assert bench.run(1000, throttle=1200) == []
    assert bench.request(records.SetFreqRequest(True, 40, 200, 500)) == []
    assert bench.broadcast(records.GetEscIdRequest()) == []
    assert sim.intervals_ms == (40, 200, 500)  # applied all the same
    assert sim.applied_throttle == 1200 and sim.motor.rpm > 9000
    sim.faults.silent = False
    assert type_counts(bench.run(1000, throttle=1200))[records.TYPE_MSG1] == 25


def test_fault_stuck_motor() -> None:
    sim = SimCkesc(3, 1)
    bench = Bench(sim)
    sim.faults.stuck_motor = True
    out = bench.run(300, throttle=1000)
    assert sim.motor.stuck
    assert of_kind(out, records.Msg1)[-1] == records.Msg1(0, 1000, S(0))
    assert of_kind(out, records.Msg2)[-1].current_a > 10
    sim.faults.stuck_motor = False
    bench.run(300, throttle=1000)
    assert not sim.motor.stuck and sim.motor.rpm > 5000


def test_constructor_checks() -> None:
    with pytest.raises(ValueError, match="node_id=126"):
        SimCkesc(126, 1)
    with pytest.raises(ValueError, match="throttle_channel=21"):
        SimCkesc(5, 21)
    sim = SimCkesc(5, 2)
    assert sim.to_flash() == {**default_flash(5, 2), "power_on_count": 1}
    assert sim.to_flash() is not sim.flash


# --------------------------------------------------------------------------------------------
# On a real python-can bus


def test_on_a_virtual_bus() -> None:
    channel = f"ckesc-sim-{uuid.uuid4()}"
    host = can.Bus(interface="virtual", channel=channel)
    esc_bus = can.Bus(interface="virtual", channel=channel)
    sim = SimCkesc(3, 2, power_on_s=time.monotonic())  # answers after 6 ms
    stop = threading.Event()

    def esc_loop() -> None:
        while not stop.is_set():
            msg = esc_bus.recv(0.001)
            out = [] if msg is None else sim.handle(msg, time.monotonic())
            for frame in out + sim.poll(time.monotonic(), FULL_V):
                esc_bus.send(frame)

    thread = threading.Thread(target=esc_loop, name="sim-ckesc", daemon=True)
    thread.start()
    try:
        sent = time.monotonic()
        host.send(codec.encode(codec.CkescFrame(MEDIUM, 0, None, 0, records.GetEscIdRequest())))
        received: list[can.Message] = []
        deadline = sent + 0.6
        tid = 0
        while time.monotonic() < deadline:
            host.send(codec.encode_raw_12b(1, [0, 1000], tid))
            tid = (tid + 1) % 32
            msg = host.recv(0.005)
            while msg is not None:
                received.append(msg)
                msg = host.recv(0)
    finally:
        stop.set()
        thread.join(1.0)
        host.shutdown()
        esc_bus.shutdown()
    assert all(m.is_extended_id and not m.is_remote_frame for m in received)
    frames = decode_all(received)  # every frame valid
    answers = [f for f in frames if isinstance(f.message, records.GetEscIdAnswer)]
    assert answers == [codec.CkescFrame(MEDIUM, 3, None, 0, records.GetEscIdAnswer(3, 2))]
    msg1 = [f for f in frames if isinstance(f.message, records.Msg1)]
    assert len(msg1) >= 15
    assert [f.transfer_id for f in msg1] == [i % 32 for i in range(len(msg1))]
    last = msg1[-1].message
    assert isinstance(last, records.Msg1)
    assert last == records.Msg1(last.speed_rpm, 1000, S.RUNNING)
    assert last.speed_rpm > 3000
