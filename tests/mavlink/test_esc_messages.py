"""The ESC telemetry encoders and message sets: first as pure functions (snapshots in, messages
out, packed with the project's dialect and parsed back), then every field of every batch end to
end, from real CAN frames through a real :class:`EscTable`, link and sender to a ground station
on 127.0.0.1 (the helpers in telemetrypeer.py). The sender's own behaviour (rates, commands,
outputs) is tested in test_telemetry_out.py.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import math
import time
from dataclasses import replace
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import telemetrypeer
from pymavlink.generator import mavgen
from telemetrypeer import (
    DIALECT,
    INT16_MAX,
    OUR_ID,
    TIMEOUT_S,
    MakeBridge,
    check_esc_info,
    check_esc_status,
    check_esc_telemetry,
    feed,
    first_round,
    ingest,
    make_table,
    populate,
    telemetry_round,
)

from bridge.config import MavlinkConfig
from bridge.escs.ckesc import codec, records
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

make_bridge = telemetrypeer.make_bridge


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
    (msg,) = on_wire(esc_info_messages(DIALECT.MAVLink(None), escs, 5))
    assert (msg.count, msg.counter, msg.info) == (3, 30, 0b101)
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


def test_index_stops_at_60_and_info_is_the_vehicles_in_every_batch() -> None:
    escs = [snapshot(n, online=n % 3 != 0) for n in range(1, 71)]
    status = on_wire(esc_status_messages(DIALECT.MAVLink(None), escs, 0))
    info = on_wire(esc_info_messages(DIALECT.MAVLink(None), escs, 0))
    assert [m.index for m in status] == [m.index for m in info] == list(range(0, 61, 4))
    assert {m.count for m in info} == {64}
    # Motors 1..8 (bits 0..7), every third offline: the same byte in every batch.
    assert {m.info for m in info} == {0b1101_1011}


# -- as the ground stations read them, decoded with upstream's definitions -----------------------

UPSTREAM_COMMON = Path(__file__).resolve().parents[1] / "data" / "mavlink" / "common.xml"


@pytest.fixture(scope="module")
def upstream_common(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    """A dialect generated from upstream's common.xml: ESC_INFO/ESC_STATUS as QGroundControl,
    PX4 and mavros compile them."""
    output = tmp_path_factory.mktemp("upstream") / "upstream_common.py"
    opts = mavgen.Opts(str(output), wire_protocol="2.0", language="Python3")
    with contextlib.redirect_stdout(io.StringIO()):
        assert mavgen.mavgen(opts, [str(UPSTREAM_COMMON)])
    spec = importlib.util.spec_from_file_location("upstream_common_for_tests", output)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def decoded_by(dialect: ModuleType, messages: list[Any]) -> list[Any]:
    """Each message packed by the bridge (1/191) and parsed by a receiver built on ``dialect``."""
    packer = DIALECT.MAVLink(None, srcSystem=1, srcComponent=191)
    receiver = dialect.MAVLink(None)
    parsed = []
    for message in messages:
        (back,) = receiver.parse_buffer(message.pack(packer)) or []
        parsed.append(back)
    return parsed


@pytest.mark.parametrize("n", [4, 6, 8])
def test_qgroundcontrol_esc_page_and_mavros_read_every_motor(
    upstream_common: ModuleType, n: int
) -> None:
    # The second motor fell silent; the rest report.
    escs = [snapshot(m, online=m != 2, frames=100 * m) for m in range(1, n + 1)]
    boot_usec = 12_345_678_901  # the autopilot's clock: 3.4 h since its boot
    info = decoded_by(upstream_common, esc_info_messages(DIALECT.MAVLink(None), escs, boot_usec))
    status = decoded_by(
        upstream_common, esc_status_messages(DIALECT.MAVLink(None), escs, boot_usec)
    )
    assert {m.get_type() for m in info} == {"ESC_INFO"}
    assert {m.get_type() for m in status} == {"ESC_STATUS"}

    # QGroundControl's ESC page: one entry per ESC up to ESC_INFO ``count``, its online state
    # bit i of the ``info`` byte (index 0's batch; every batch carries the same), its values
    # from slot i % 4 of the batch whose ``index`` is the multiple of four below i.
    by_index = {m.index: m for m in info}
    status_by_index = {m.index: m for m in status}
    vehicle_info = by_index[0].info
    assert all(m.info == vehicle_info and m.count == n for m in info)
    for motor, esc in enumerate(escs):
        online = bool(vehicle_info >> motor & 1)
        assert online == esc.online, f"motor {motor + 1} of {n} shows {online}"
        batch, slot_no = by_index[motor - motor % 4], motor % 4
        values = status_by_index[motor - motor % 4]
        assert values.rpm[slot_no] == (esc.rpm if esc.online else 0)
        assert batch.temperature[slot_no] == (4000 if esc.online else INT16_MAX)
    # mavros: ``time_usec`` is the autopilot's boot time (it adds its timesync offset to it),
    # ``counter`` the telemetry packets received, ``index`` within the definition's 0..60.
    assert {m.time_usec for m in info + status} == {boot_usec}
    assert {m.counter for m in info} == {sum(100 * m for m in range(1, n + 1))}
    assert all(0 <= m.index <= 60 and m.index % 4 == 0 for m in info + status)


# -- every field, end to end ---------------------------------------------------------------------


@pytest.mark.parametrize("n", [4, 6, 8, 20])  # 6: the last batch is padded
def test_every_field_of_every_batch(make_bridge: MakeBridge, n: int) -> None:
    table = make_table(n)
    expected = populate(table, n)
    before_us = time.time_ns() // 1000
    bridge = make_bridge(table, esc_status_hz=20.0, esc_info_hz=20.0, esc_telemetry_hz=20.0)
    batches = math.ceil(n / 4)

    status = first_round(bridge.gcs, "ESC_STATUS", batches)
    info = first_round(bridge.gcs, "ESC_INFO", batches)
    telemetry = telemetry_round(bridge.gcs, min(batches, 8))
    after_us = time.time_ns() // 1000

    assert any(e.rpm is not None and e.rpm < 0 for e in expected)  # an FT ESC in reverse
    for msg in status.values():
        check_esc_status(msg, expected, (before_us, after_us))
    for msg in info.values():
        check_esc_info(msg, expected, (before_us, after_us))
        assert (msg.get_srcSystem(), msg.get_srcComponent()) == OUR_ID
    for batch, msg in telemetry.items():
        check_esc_telemetry(msg, batch, expected)
    # The counter counts telemetry frames received: no new frame, no change between rounds.
    bridge.gcs.wait_for("ESC_INFO", since=bridge.gcs.count())
    assert {m.counter for _, m in bridge.gcs.of("ESC_INFO")} == {sum(e.frames for e in expected)}


def test_esc_telemetry_stops_at_32_escs(make_bridge: MakeBridge) -> None:
    table = make_table(37)
    expected = populate(table, 37)
    bridge = make_bridge(table, esc_status_hz=20.0, esc_info_hz=0.0, esc_telemetry_hz=20.0)

    telemetry = telemetry_round(bridge.gcs, 8)
    status = first_round(bridge.gcs, "ESC_STATUS", 10)  # 37 ESCs: batches 0..36

    check_esc_telemetry(telemetry[7], 7, expected)
    check_esc_status(status[36], expected, (0, 2**64 - 1))
    assert not bridge.gcs.of("ESC_INFO")  # 0 Hz is off


def test_esc_goes_offline_after_the_timeout_and_comes_back(make_bridge: MakeBridge) -> None:
    table = make_table(2, timeout_ms=150)
    now = time.monotonic_ns()
    first = feed(table, 0, now)  # ckesc_full
    feed(table, 1, now)
    bridge = make_bridge(table, esc_status_hz=40.0, esc_info_hz=40.0, esc_telemetry_hz=40.0)
    gcs = bridge.gcs

    def info_bits(since: int) -> Any:
        return gcs.wait_for("ESC_INFO", lambda m: True, since)

    assert info_bits(0).info == 0b11
    # Keep ESC 2 talking while ESC 1 falls silent.
    deadline = time.monotonic() + TIMEOUT_S
    while (msg := gcs.of("ESC_INFO")[-1][1]).info != 0b10:
        assert time.monotonic() < deadline, "ESC 1 never went offline"
        ingest(
            table,
            codec.encode(
                codec.CkescFrame(31, 2, None, 0, records.Msg1(7, 0, records.Msg1Status(0)))
            ),
            now,
        )
        now = time.monotonic_ns()
        time.sleep(0.02)
    assert msg.temperature[0] == INT16_MAX  # offline: unknown, not its last value
    assert msg.error_count[0] == 0
    since = gcs.count()
    ingest(
        table,
        codec.encode(codec.CkescFrame(31, 2, None, 0, records.Msg1(7, 0, records.Msg1Status(0)))),
        now,
    )
    offline_status = gcs.wait_for("ESC_STATUS", since=since)
    assert offline_status.rpm[0] == 0
    assert offline_status.voltage[0] == 0.0
    assert offline_status.current[0] == 0.0
    assert offline_status.rpm[1] == 7
    offline_telemetry = gcs.wait_for("ESC_TELEMETRY_1_TO_4", since=since)
    assert offline_telemetry.rpm[0] == 0
    assert offline_telemetry.temperature[0] == 0
    assert offline_telemetry.voltage[0] == 0
    assert offline_telemetry.count[0] == first.frames  # counters are kept
    assert offline_telemetry.totalcurrent[0] == 1

    # ESC 1 speaks again: online, with its values.
    now = time.monotonic_ns()
    ingest(
        table,
        codec.encode(
            codec.CkescFrame(31, 1, None, 1, records.Msg1(4321, 0, records.Msg1Status(0)))
        ),
        now,
    )
    ingest(
        table,
        codec.encode(codec.CkescFrame(31, 2, None, 1, records.Msg1(7, 0, records.Msg1Status(0)))),
        now,
    )
    since = gcs.count()
    back = gcs.wait_for("ESC_INFO", lambda m: m.info == 0b11, since)
    assert back.temperature[0] == 4000  # 40 °C from its earlier MSG2
    status = gcs.wait_for("ESC_STATUS", lambda m: m.rpm[0] == 4321, since)
    assert status.voltage[0] == pytest.approx(12.0)
