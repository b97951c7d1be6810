"""The ESC telemetry sender (rates, commands, outputs, recording), end to end on 127.0.0.1 (free
ports per test, no mocks).

Real CAN frames are built with the vendor encoders, decoded with ``bridge.escs.decode`` and
ingested into a real :class:`EscTable`; a real :class:`MavlinkLink` and
:class:`MavlinkTelemetry` send what the table holds to a ground station played by a UDP socket
that decodes with the project's dialect (the stock one lacks ESC_INFO and ESC_STATUS). The
expected wire values are worked out here from the frames' inputs, not from the table.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import telemetrypeer
from pymavlink import mavutil
from telemetrypeer import (
    DIALECT,
    OUR_ID,
    Gcs,
    MakeBridge,
    check_esc_info,
    check_esc_status,
    check_esc_telemetry,
    first_round,
    make_table,
    populate,
)

from bridge.config import MavlinkConfig
from bridge.mavlink.link import MavlinkLink
from bridge.mavlink.telemetry_out import MavlinkTelemetry

make_bridge = telemetrypeer.make_bridge


def rate_hz(gcs: Gcs, kind: str, start: float, end: float, index: int = 0) -> float:
    times = [t for t, m in gcs.of(kind) if start <= t < end and getattr(m, "index", 0) == index]
    return len(times) / (end - start)


def test_configured_rates_are_roughly_honoured(make_bridge: MakeBridge) -> None:
    table = make_table(8)
    populate(table, 8)
    bridge = make_bridge(table, esc_status_hz=25.0, esc_info_hz=4.0, esc_telemetry_hz=10.0)
    gcs = bridge.gcs
    gcs.wait_for("ESC_STATUS")
    start = time.monotonic()
    time.sleep(1.5)
    end = time.monotonic()

    assert 15 < rate_hz(gcs, "ESC_STATUS", start, end) < 35
    assert 15 < rate_hz(gcs, "ESC_STATUS", start, end, index=4) < 35
    assert 2 < rate_hz(gcs, "ESC_INFO", start, end) < 6
    assert 6 < rate_hz(gcs, "ESC_TELEMETRY_1_TO_4", start, end) < 14
    assert 6 < rate_hz(gcs, "ESC_TELEMETRY_5_TO_8", start, end) < 14
    assert bridge.telemetry.stats.errors == 0


def test_set_message_interval_changes_a_rate_and_is_acked(make_bridge: MakeBridge) -> None:
    table = make_table(4)
    populate(table, 4)
    bridge = make_bridge(table, esc_status_hz=5.0, esc_info_hz=0.0, esc_telemetry_hz=5.0)
    gcs = bridge.gcs
    gcs.wait_for("ESC_STATUS")

    since = gcs.command(DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL, 291, 25_000)  # 40 Hz
    ack = gcs.ack(DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL, since)
    assert ack.result == DIALECT.MAV_RESULT_ACCEPTED
    assert (ack.target_system, ack.target_component) == (255, 190)
    assert (ack.get_srcSystem(), ack.get_srcComponent()) == OUR_ID
    start = time.monotonic()
    time.sleep(1.0)
    end = time.monotonic()
    assert 25 < rate_hz(gcs, "ESC_STATUS", start, end) < 55
    assert 2 < rate_hz(gcs, "ESC_TELEMETRY_1_TO_4", start, end) < 8  # unchanged

    # Any ESC_TELEMETRY id sets the family; -1 turns it off; 0 restores the configured rate.
    since = gcs.command(DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL, 11031, -1)  # ..._5_TO_8
    assert gcs.ack(DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL, since).result == 0
    time.sleep(0.1)
    quiet_from = gcs.count()
    time.sleep(0.5)
    assert not gcs.of("ESC_TELEMETRY_1_TO_4", quiet_from)
    assert bridge.telemetry.rate_hz("esc_telemetry") == 0.0
    since = gcs.command(DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL, 11030, 0)
    assert gcs.ack(DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL, since).result == 0
    gcs.wait_for("ESC_TELEMETRY_1_TO_4", since=since)
    assert bridge.telemetry.rate_hz("esc_telemetry") == 5.0

    # Faster than 100 Hz, or a negative interval other than -1: refused, rate kept.
    for interval_us in (9_999, -2):
        since = gcs.command(DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL, 291, interval_us)
        ack = gcs.ack(DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL, since)
        assert ack.result == DIALECT.MAV_RESULT_DENIED
    assert bridge.telemetry.rate_hz("esc_status") == 40.0


def test_commands_about_other_messages_are_not_claimed(make_bridge: MakeBridge) -> None:
    table = make_table(4)
    populate(table, 4)
    bridge = make_bridge(table, esc_status_hz=5.0, esc_info_hz=0.0, esc_telemetry_hz=0.0)
    gcs = bridge.gcs
    gcs.wait_for("ESC_STATUS")
    set_interval = DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL
    gps = DIALECT.MAVLINK_MSG_ID_GLOBAL_POSITION_INT

    # Broadcast to every component: not ours, so no answer at all...
    start = gcs.command(set_interval, gps, 100_000, target=(1, 0))
    # ...addressed to the bridge itself: nobody claims it, so UNSUPPORTED.
    since = gcs.command(set_interval, gps, 100_000)
    ack = gcs.ack(set_interval, since)
    assert ack.result == DIALECT.MAV_RESULT_UNSUPPORTED
    # A broadcast about our own message is ours.
    since = gcs.command(set_interval, 291, 100_000, target=(0, 0))
    assert gcs.ack(set_interval, since).result == DIALECT.MAV_RESULT_ACCEPTED
    # To another component: not ours.
    gcs.command(set_interval, 291, 50_000, target=(1, 1))
    marker = gcs.command(DIALECT.MAV_CMD_GET_MESSAGE_INTERVAL, 291)
    reply = gcs.wait_for("MESSAGE_INTERVAL", since=marker)
    assert (reply.message_id, reply.interval_us) == (291, 100_000)
    gcs.ack(DIALECT.MAV_CMD_GET_MESSAGE_INTERVAL, marker)

    assert [m.result for _, m in gcs.of("COMMAND_ACK", start)] == [
        DIALECT.MAV_RESULT_UNSUPPORTED,
        DIALECT.MAV_RESULT_ACCEPTED,
        DIALECT.MAV_RESULT_ACCEPTED,
    ]
    assert bridge.telemetry.rate_hz("esc_status") == 10.0


def test_telemetry_shares_the_link_with_other_command_handlers(make_bridge: MakeBridge) -> None:
    table = make_table(4)
    populate(table, 4)
    bridge = make_bridge(table, esc_status_hz=0.0, esc_info_hz=0.0, esc_telemetry_hz=0.0)
    gcs = bridge.gcs
    set_interval, motor_test = DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL, DIALECT.MAV_CMD_DO_MOTOR_TEST

    def other(msg: Any) -> int | None:
        return int(DIALECT.MAV_RESULT_DENIED) if msg.command == motor_test else None

    bridge.link.add_command_handler(other)
    gcs.wait_for("HEARTBEAT")
    since = gcs.command(set_interval, 291, 100_000)
    assert gcs.ack(set_interval, since).result == DIALECT.MAV_RESULT_ACCEPTED
    since = gcs.command(motor_test, 1)
    assert gcs.ack(motor_test, since).result == DIALECT.MAV_RESULT_DENIED
    bridge.telemetry.close()  # takes its own handler away, and only that one
    since = gcs.command(set_interval, 291, 100_000)
    assert gcs.ack(set_interval, since).result == DIALECT.MAV_RESULT_UNSUPPORTED
    since = gcs.command(motor_test, 1)
    assert gcs.ack(motor_test, since).result == DIALECT.MAV_RESULT_DENIED


def test_request_message_sends_once_now(make_bridge: MakeBridge) -> None:
    table = make_table(6)
    expected = populate(table, 6)
    bridge = make_bridge(table, esc_status_hz=0.0, esc_info_hz=0.0, esc_telemetry_hz=0.0)
    gcs = bridge.gcs
    request = DIALECT.MAV_CMD_REQUEST_MESSAGE
    gcs.wait_for("HEARTBEAT")

    since = gcs.command(request, 290)
    assert gcs.ack(request, since).result == DIALECT.MAV_RESULT_ACCEPTED
    info = first_round(gcs, "ESC_INFO", 2, since)
    check_esc_info(info[4], expected, (0, 2**64 - 1))
    since = gcs.command(request, 11031)  # ESC_TELEMETRY_5_TO_8: that batch only
    assert gcs.ack(request, since).result == DIALECT.MAV_RESULT_ACCEPTED
    check_esc_telemetry(gcs.wait_for("ESC_TELEMETRY_5_TO_8", since=since), 1, expected)
    since = gcs.command(request, 11032)  # ESCs 9..12: there are none
    assert gcs.ack(request, since).result == DIALECT.MAV_RESULT_DENIED
    time.sleep(0.3)
    assert [m.index for _, m in gcs.of("ESC_INFO")] == [0, 4]  # once, not a stream
    assert len(gcs.of("ESC_TELEMETRY_5_TO_8")) == 1
    assert not gcs.of("ESC_TELEMETRY_1_TO_4")
    assert not gcs.of("ESC_TELEMETRY_9_TO_12")
    assert not gcs.of("ESC_STATUS")


def test_an_extra_output_gets_heartbeat_and_telemetry_and_may_command(
    make_bridge: MakeBridge,
) -> None:
    table = make_table(4)
    expected = populate(table, 4)
    gcs = Gcs()
    autopilot = Gcs(system=1, component=1)
    try:
        bridge = make_bridge(
            table,
            gcs=autopilot,
            outputs=(gcs.url,),
            heartbeat_hz=5.0,
            esc_status_hz=10.0,
            esc_info_hz=10.0,
            esc_telemetry_hz=10.0,
        )
        beat = gcs.wait_for("HEARTBEAT")
        assert (beat.get_srcSystem(), beat.get_srcComponent()) == OUR_ID
        check_esc_status(gcs.wait_for("ESC_STATUS"), expected, (0, 2**64 - 1))
        check_esc_info(gcs.wait_for("ESC_INFO"), expected, (0, 2**64 - 1))
        check_esc_telemetry(gcs.wait_for("ESC_TELEMETRY_1_TO_4"), 0, expected)
        autopilot.wait_for("ESC_STATUS")

        since = gcs.command(DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL, 290, -1)
        assert gcs.ack(DIALECT.MAV_CMD_SET_MESSAGE_INTERVAL, since).result == 0
        assert bridge.telemetry.rate_hz("esc_info", gcs.url) == 0.0  # on its own link only
        assert bridge.telemetry.rate_hz("esc_info") == 10.0
        time.sleep(0.2)
        assert not autopilot.of("COMMAND_ACK")  # answered on the output it came from only
        assert bridge.link.output_stats[0].messages == 1
        assert bridge.link.output_stats[0].sent > 0
    finally:
        gcs.close()


def test_tlog_holds_telemetry_readable_with_our_dialect(tmp_path: Path) -> None:
    table = make_table(4)
    expected = populate(table, 4)
    path = tmp_path / "flight.tlog"
    gcs = Gcs()
    mavlink = MavlinkConfig(
        url=gcs.url,
        stream_rate_hz=0.0,
        autopilot_messages={"esc_status": 10.0, "esc_info": 10.0, "esc_telemetry": 10.0},
    )
    try:
        with path.open("wb") as tlog:
            link = MavlinkLink(mavlink, tlog=tlog)
            with link, MavlinkTelemetry(mavlink, link, table) as telemetry:
                link.start()
                telemetry.start()
                gcs.wait_for("ESC_INFO")
                gcs.wait_for("ESC_STATUS")
    finally:
        gcs.close()

    recording: Any = mavutil.mavlink_connection(str(path))
    recording.mav = DIALECT.MAVLink(recording)  # the stock dialect sees UNKNOWN_290, _291
    recording.mav.robust_parsing = True
    seen: dict[str, Any] = {}
    while (msg := recording.recv_msg()) is not None:
        seen.setdefault(msg.get_type(), msg)
    recording.close()
    assert {"HEARTBEAT", "ESC_STATUS", "ESC_INFO", "ESC_TELEMETRY_1_TO_4"} <= set(seen)
    assert "BAD_DATA" not in seen
    check_esc_status(seen["ESC_STATUS"], expected, (0, 2**64 - 1))
    check_esc_info(seen["ESC_INFO"], expected, (0, 2**64 - 1))
    assert abs(seen["ESC_INFO"]._timestamp - time.time()) < 10


def test_stamps_on_the_autopilots_boot_clock_once_it_tells_it(make_bridge: MakeBridge) -> None:
    table = make_table(4)
    populate(table, 4)
    autopilot = Gcs(system=1, component=1)  # the obeyed autopilot, on the link's own URL
    encoder = DIALECT.MAVLink(None)
    boot_ms = 7_200_000  # two hours since the autopilot's boot
    try:
        make_bridge(table, gcs=autopilot, esc_status_hz=20.0, esc_info_hz=20.0)
        # Before the autopilot said its time: µs since the Unix epoch.
        assert abs(autopilot.wait_for("ESC_STATUS").time_usec / 1e6 - time.time()) < 10
        # Another component's SYSTEM_TIME (a ground station's, a camera's) is not its clock.
        autopilot.send(encoder.system_time_encode(0, 1000), source=(1, 100))
        time.sleep(0.1)
        since = autopilot.count()
        assert autopilot.wait_for("ESC_STATUS", since=since).time_usec > 10**15
        # Timed before the send: the bridge cannot read it earlier. (Timed after it, a test
        # thread preempted between the two once made the bridge's stamp look 3 ms ahead.)
        sent = time.monotonic()
        autopilot.send(encoder.system_time_encode(0, boot_ms))
        since = autopilot.count()
        info = autopilot.wait_for("ESC_INFO", lambda m: m.time_usec < 10**12, since)
        status = autopilot.wait_for("ESC_STATUS", lambda m: m.time_usec < 10**12, since)
        for msg in (info, status):
            elapsed_us = (time.monotonic() - sent) * 1e6
            assert boot_ms * 1000 <= msg.time_usec <= boot_ms * 1000 + elapsed_us + 1000
        # A TIMESYNC request carries the same clock in ns: a reboot (its clock back at 5 s) is
        # followed at once.
        autopilot.send(encoder.timesync_encode(0, 5_000_000_000))
        since = autopilot.count()
        rebooted = autopilot.wait_for("ESC_STATUS", lambda m: m.time_usec < 10**9, since)
        assert 5_000_000 <= rebooted.time_usec < 5_000_000 + 2_000_000
    finally:
        autopilot.close()
