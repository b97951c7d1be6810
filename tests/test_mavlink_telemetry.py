"""ESC telemetry over MAVLink, end to end on 127.0.0.1 (free ports per test, no mocks).

Real CAN frames are built with the vendor encoders, decoded with ``bridge.escs.decode`` and
ingested into a real :class:`EscTable`; a real :class:`MavlinkLink` and
:class:`MavlinkTelemetry` send what the table holds to a ground station played by a UDP socket
that decodes with the project's dialect (the stock one lacks ESC_INFO and ESC_STATUS). The
expected wire values are worked out here from the frames' inputs, not from the table.
"""

from __future__ import annotations

import math
import select
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from pymavlink import mavutil

from bridge.config import MavlinkConfig
from bridge.escs import ckesc, ft, registry
from bridge.mavlink import load_dialect
from bridge.mavlink_in import MavlinkLink
from bridge.mavlink_out import MavlinkTelemetry
from bridge.telemetry.state import EscTable

DIALECT = load_dialect()
INT16_MAX = 32767
OUR_ID = (1, 191)  # the vehicle's system ID, the bridge's component ID
TIMEOUT_S = 3.0
POLE_PAIRS = 7
MS = 1_000_000  # ns


class Gcs:
    """A ground station on a loopback UDP port: records what arrives, in a thread."""

    def __init__(self, system: int = 255, component: int = 190) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port: int = self.sock.getsockname()[1]
        self.url = f"udpout:127.0.0.1:{self.port}"  # where the bridge sends to
        self._parser: Any = DIALECT.MAVLink(None)
        self._parser.robust_parsing = True
        self._packer: Any = DIALECT.MAVLink(None, srcSystem=system, srcComponent=component)
        self._bridge: tuple[str, int] | None = None
        self._got: list[tuple[float, Any]] = []
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="gcs", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.sock], [], [], 0.05)
            if not ready:
                continue
            data, address = self.sock.recvfrom(65536)
            now = time.monotonic()
            msgs = [m for m in self._parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]
            with self._cond:
                self._bridge = address
                self._got.extend((now, m) for m in msgs)
                self._cond.notify_all()

    def count(self) -> int:
        with self._cond:
            return len(self._got)

    def of(self, kind: str, since: int = 0) -> list[tuple[float, Any]]:
        """Every ``kind`` received, from the ``since``-th message received on."""
        with self._cond:
            return [(t, m) for t, m in self._got[since:] if m.get_type() == kind]

    def wait_for(
        self,
        kind: str,
        predicate: Callable[[Any], bool] = lambda _: True,
        since: int = 0,
        timeout_s: float = TIMEOUT_S,
    ) -> Any:
        def found() -> Any:
            return next((m for _, m in self.of(kind, since) if predicate(m)), None)

        with self._cond:
            self._cond.wait_for(lambda: found() is not None, timeout_s)
        msg = found()
        assert msg is not None, f"no matching {kind} within {timeout_s} s"
        return msg

    def send(self, msg: Any) -> None:
        with self._cond:
            self._cond.wait_for(lambda: self._bridge is not None, TIMEOUT_S)
            assert self._bridge is not None, "the bridge never sent anything"
            address = self._bridge
        frame = msg.pack(self._packer)
        self._packer.seq = (self._packer.seq + 1) % 256
        self.sock.sendto(frame, address)

    def command(
        self, command: int, param1: float = 0, param2: float = 0, target: tuple[int, int] = OUR_ID
    ) -> int:
        """Send a COMMAND_LONG; returns the message count before it (for ``since``)."""
        since = self.count()
        self.send(
            self._packer.command_long_encode(*target, command, 0, param1, param2, 0, 0, 0, 0, 0)
        )
        return since

    def ack(self, command: int, since: int) -> Any:
        return self.wait_for("COMMAND_ACK", lambda m: m.command == command, since)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()


class NullSink:
    def on_actuators(self, values: list[float], time_ns: int) -> None:
        pass

    def on_armed(self, armed: bool, time_ns: int) -> None:
        pass


# -- the ESCs: real frames in, expectations worked out by hand ---------------------------------

KINDS = ("ckesc_full", "ckesc_fault", "ckesc_rpm_only", "ft_reverse", "silent")


@dataclass(frozen=True)
class Expected:
    """What ESC ``i`` reported (None: never), before any encoding."""

    online: bool
    rpm: int | None
    voltage_v: float | None
    current_a: float | None
    temp_c: float | None
    failure_flags: int
    errors: int
    frames: int
    consumed_mah: float


def ingest(table: EscTable, msg: can.Message, now_ns: int) -> None:
    family = registry.family_of(msg.arbitration_id)
    assert family is not None
    frame = family.decode(msg)
    assert frame is not None
    telemetry = family.telemetry(frame)
    assert telemetry is not None
    assert table.ingest(telemetry, now_ns)


def feed(table: EscTable, i: int, now_ns: int) -> Expected:
    """Feed ESC ``i`` (node/ESC ID ``i + 1``) the frames of its kind; what it should report."""
    node = i + 1
    kind = KINDS[i % len(KINDS)]

    def ck(message: Any, at_ns: int = now_ns) -> None:
        ingest(table, ckesc.encode(ckesc.CkescFrame(31, node, None, i % 32, message)), at_ns)

    status = ckesc.Msg1Status
    if kind == "ckesc_full":
        # 36 A for the 100 ms up to the second sample: 36 A * 0.1 s = 1.0 mAh.
        ck(ckesc.Msg2(12.0 + 0.5 * i, 36.0, 40 + i), now_ns - 100 * MS)
        ck(ckesc.Msg1(1000 * (i + 1), 1000, status.RUNNING))
        ck(ckesc.Msg2(12.0 + 0.5 * i, 2.5 + i, 40 + i))
        return Expected(True, 1000 * (i + 1), 12.0 + 0.5 * i, 2.5 + i, 40 + i, 0, 0, 3, 1.0)
    if kind == "ckesc_fault":
        ck(ckesc.Msg1(500 + i, 1000, status.RUNNING | status.OVER_CURRENT))
        ck(ckesc.Msg2(11.1, 20.0, 120))  # above the 100 °C limit: OVER_TEMPERATURE
        table.count_error(node, now_ns)
        table.count_error(node, now_ns)
        return Expected(True, 500 + i, 11.1, 20.0, 120, 1 | 4, 2, 2, 0.0)
    if kind == "ckesc_rpm_only":
        ck(ckesc.Msg1(1500 + i, 0, status(0)))
        return Expected(True, 1500 + i, None, None, None, 0, 0, 1, 0.0)
    if kind == "ft_reverse":
        for message in (
            ft.RealtimeData0(3.5, 2.0 + i),
            ft.RealtimeData1(-700 * (i + 1), -0.25),  # reverse: -100 * (i + 1) rpm
            ft.RealtimeData2(30.4 + i, 60.0, 24.3),
        ):
            ingest(table, ft.encode(ft.FtFrame(node, message)), now_ns)
        return Expected(True, -100 * (i + 1), 24.3, 2.0 + i, 30.4 + i, 0, 0, 3, 0.0)
    return Expected(False, None, None, None, None, 0, 0, 0, 0.0)


def make_table(n: int, timeout_ms: int = 10_000) -> EscTable:
    return EscTable(list(range(1, n + 1)), pole_pairs=POLE_PAIRS, timeout_ms=timeout_ms)


def populate(table: EscTable, n: int) -> list[Expected]:
    now = time.monotonic_ns()
    return [feed(table, i, now) for i in range(n)]


def slot(expected: list[Expected], index: int) -> Expected | None:
    """ESC ``index``'s expectation, None for a padded slot; offline ESCs' measurements unknown."""
    if index >= len(expected):
        return None
    esc = expected[index]
    if esc.online:
        return esc
    return Expected(False, None, None, None, None, esc.failure_flags, esc.errors, esc.frames, 0.0)


# -- fixtures ------------------------------------------------------------------------------------


@dataclass
class Bridge:
    gcs: Gcs
    link: MavlinkLink
    telemetry: MavlinkTelemetry
    table: EscTable


MakeBridge = Callable[..., Bridge]


@pytest.fixture
def make_bridge() -> Iterator[MakeBridge]:
    """A GCS, and a link to it with telemetry from ``table``; everything closed at the end."""
    closers: list[Callable[[], None]] = []

    def make(table: EscTable, gcs: Gcs | None = None, **config: Any) -> Bridge:
        if gcs is None:
            gcs = Gcs()
            closers.append(gcs.close)
        settings: dict[str, Any] = {"url": gcs.url, "stream_rate_hz": 0.0} | config
        if "autopilot_messages" not in settings:
            # The GCS plays the autopilot's link here: give it the output rates (the per-link
            # sets are tested in test_mavlink_link_sets.py).
            settings["autopilot_messages"] = MavlinkConfig(**settings).output_rates("")
        mavlink = MavlinkConfig(**settings)
        link = MavlinkLink(mavlink, NullSink())
        closers.append(link.close)
        telemetry = MavlinkTelemetry(mavlink, link, table)
        closers.append(telemetry.close)
        link.start()
        telemetry.start()
        return Bridge(gcs, link, telemetry, table)

    yield make
    for close in reversed(closers):
        close()


def first_round(gcs: Gcs, kind: str, batches: int, since: int = 0) -> dict[int, Any]:
    """The first message of ``kind`` for each of ``batches`` batch indices (0, 4, 8, ...)."""
    wanted = {4 * b for b in range(batches)}
    deadline = time.monotonic() + TIMEOUT_S
    while True:
        got: dict[int, Any] = {}
        for _, msg in gcs.of(kind, since):
            got.setdefault(msg.index, msg)
        if set(got) >= wanted:
            assert set(got) == wanted, f"unexpected {kind} batches {sorted(got)}"
            return got
        assert time.monotonic() < deadline, f"{kind}: only batches {sorted(got)} arrived"
        time.sleep(0.01)


def telemetry_round(gcs: Gcs, batches: int, since: int = 0) -> dict[int, Any]:
    """One ESC_TELEMETRY_x_TO_y per batch (up to 8), keyed by batch number."""
    names = [f"ESC_TELEMETRY_{4 * b + 1}_TO_{4 * b + 4}" for b in range(8)]
    deadline = time.monotonic() + TIMEOUT_S
    while True:
        got = {b: gcs.of(name, since) for b, name in enumerate(names)}
        if all(got[b] for b in range(batches)):
            assert not any(got[b] for b in range(batches, 8)), "a batch beyond the ESCs was sent"
            return {b: got[b][0][1] for b in range(batches)}
        assert time.monotonic() < deadline, "ESC_TELEMETRY batches missing"
        time.sleep(0.01)


# -- every field ---------------------------------------------------------------------------------


def check_esc_status(msg: Any, expected: list[Expected], t_us: tuple[int, int]) -> None:
    assert (msg.get_srcSystem(), msg.get_srcComponent()) == OUR_ID
    assert t_us[0] <= msg.time_usec <= t_us[1]
    for j in range(4):
        esc = slot(expected, msg.index + j)
        rpm = esc.rpm if esc and esc.rpm is not None else 0
        voltage = esc.voltage_v if esc and esc.voltage_v is not None else 0.0
        current = esc.current_a if esc and esc.current_a is not None else 0.0
        assert msg.rpm[j] == rpm, (msg.index + j, msg.rpm)
        assert msg.voltage[j] == pytest.approx(voltage, rel=1e-6), (msg.index + j, msg.voltage)
        assert msg.current[j] == pytest.approx(current, rel=1e-6), (msg.index + j, msg.current)


def check_esc_info(msg: Any, expected: list[Expected], t_us: tuple[int, int]) -> None:
    assert t_us[0] <= msg.time_usec <= t_us[1]
    assert msg.count == len(expected)
    assert msg.connection_type == DIALECT.ESC_CONNECTION_TYPE_CAN == 4
    online = [slot(expected, msg.index + j) for j in range(4)]
    assert msg.info == sum(1 << j for j, esc in enumerate(online) if esc and esc.online)
    for j, esc in enumerate(online):
        assert msg.failure_flags[j] == (esc.failure_flags if esc else 0), msg.index + j
        assert msg.error_count[j] == (esc.errors if esc else 0), msg.index + j
        temperature = INT16_MAX if esc is None or esc.temp_c is None else round(esc.temp_c * 100)
        assert msg.temperature[j] == temperature, (msg.index + j, msg.temperature)


def check_esc_telemetry(msg: Any, batch: int, expected: list[Expected]) -> None:
    assert msg.get_type() == f"ESC_TELEMETRY_{4 * batch + 1}_TO_{4 * batch + 4}"
    for j in range(4):
        esc = slot(expected, 4 * batch + j)
        whole = expected[4 * batch + j] if esc else None  # counters survive going offline

        def cents(value: float | None) -> int:
            return 0 if value is None else round(value * 100)

        assert msg.temperature[j] == (0 if not esc or esc.temp_c is None else round(esc.temp_c))
        assert msg.voltage[j] == cents(esc.voltage_v if esc else None), (batch, j, msg.voltage)
        assert msg.current[j] == cents(esc.current_a if esc else None), (batch, j, msg.current)
        assert msg.totalcurrent[j] == (round(whole.consumed_mah) if whole else 0)
        assert msg.rpm[j] == (abs(esc.rpm) if esc and esc.rpm is not None else 0)
        assert msg.count[j] == (whole.frames if whole else 0)


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
    # The counter counts ESC_INFO rounds: every batch of a round carries the same, +1 per round.
    assert {m.counter for m in info.values()} == {1}
    bridge.gcs.wait_for("ESC_INFO", lambda m: m.index == 0 and m.counter == 3)
    rounds = [m.counter for _, m in bridge.gcs.of("ESC_INFO") if m.index == 0][:3]
    assert rounds == [1, 2, 3]


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
            ckesc.encode(ckesc.CkescFrame(31, 2, None, 0, ckesc.Msg1(7, 0, ckesc.Msg1Status(0)))),
            now,
        )
        now = time.monotonic_ns()
        time.sleep(0.02)
    assert msg.temperature[0] == INT16_MAX  # offline: unknown, not its last value
    assert msg.error_count[0] == 0
    since = gcs.count()
    ingest(
        table,
        ckesc.encode(ckesc.CkescFrame(31, 2, None, 0, ckesc.Msg1(7, 0, ckesc.Msg1Status(0)))),
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
        ckesc.encode(ckesc.CkescFrame(31, 1, None, 1, ckesc.Msg1(4321, 0, ckesc.Msg1Status(0)))),
        now,
    )
    ingest(
        table,
        ckesc.encode(ckesc.CkescFrame(31, 2, None, 1, ckesc.Msg1(7, 0, ckesc.Msg1Status(0)))),
        now,
    )
    since = gcs.count()
    back = gcs.wait_for("ESC_INFO", lambda m: m.info == 0b11, since)
    assert back.temperature[0] == 4000  # 40 °C from its earlier MSG2
    status = gcs.wait_for("ESC_STATUS", lambda m: m.rpm[0] == 4321, since)
    assert status.voltage[0] == pytest.approx(12.0)


# -- rates and commands --------------------------------------------------------------------------


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


# -- outputs and recording -----------------------------------------------------------------------


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
            link = MavlinkLink(mavlink, NullSink(), tlog=tlog)
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
