"""Shared by the ESC telemetry tests: end to end on 127.0.0.1 (free ports per test, no mocks).

Real CAN frames are built with the vendor encoders, decoded through their family
(``bridge.escs.registry``) and ingested into a real :class:`EscTable`; a real
:class:`MavlinkLink` and :class:`MavlinkTelemetry` send what the table holds to a ground station
played by a UDP socket that decodes with the project's dialect (the stock one lacks ESC_INFO and
ESC_STATUS). The expected wire values are worked out here from the frames' inputs, not from the
table.

The test modules take the fixture with ``make_bridge = telemetrypeer.make_bridge``.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import can
import pytest

from bridge.config import MavlinkConfig
from bridge.escs import registry
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.mavlink import load_dialect
from bridge.mavlink.link import MavlinkLink
from bridge.mavlink.telemetry_out import MavlinkTelemetry
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

    def send(self, msg: Any, source: tuple[int, int] | None = None) -> None:
        """Send ``msg`` to the bridge, from this station's IDs or from ``source``."""
        with self._cond:
            self._cond.wait_for(lambda: self._bridge is not None, TIMEOUT_S)
            assert self._bridge is not None, "the bridge never sent anything"
            address = self._bridge
        packer = self._packer
        if source is not None:
            packer = DIALECT.MAVLink(None, srcSystem=source[0], srcComponent=source[1])
        frame = msg.pack(packer)
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
    family = registry.families_of(msg.arbitration_id)[0]
    decoder = family.decoder()  # CKESC and FT: one frame is one message
    frame = decoder.decode(msg)
    assert frame is not None
    telemetry = decoder.telemetry(frame)
    assert telemetry is not None
    assert table.ingest(telemetry, now_ns)


def feed(table: EscTable, i: int, now_ns: int) -> Expected:
    """Feed ESC ``i`` (node/ESC ID ``i + 1``) the frames of its kind; what it should report."""
    node = i + 1
    kind = KINDS[i % len(KINDS)]

    def ck(message: Any, at_ns: int = now_ns) -> None:
        ingest(
            table,
            ckesc_codec.encode(ckesc_codec.CkescFrame(31, node, None, i % 32, message)),
            at_ns,
        )

    status = ckesc_records.Msg1Status
    if kind == "ckesc_full":
        # 36 A for the 100 ms up to the second sample: 36 A * 0.1 s = 1.0 mAh.
        ck(ckesc_records.Msg2(12.0 + 0.5 * i, 36.0, 40 + i), now_ns - 100 * MS)
        ck(ckesc_records.Msg1(1000 * (i + 1), 1000, status.RUNNING))
        ck(ckesc_records.Msg2(12.0 + 0.5 * i, 2.5 + i, 40 + i))
        return Expected(True, 1000 * (i + 1), 12.0 + 0.5 * i, 2.5 + i, 40 + i, 0, 0, 3, 1.0)
    if kind == "ckesc_fault":
        ck(ckesc_records.Msg1(500 + i, 1000, status.RUNNING | status.OVER_CURRENT))
        ck(ckesc_records.Msg2(11.1, 20.0, 120))  # above the 100 °C limit: OVER_TEMPERATURE
        table.count_error(node, now_ns)
        table.count_error(node, now_ns)
        return Expected(True, 500 + i, 11.1, 20.0, 120, 1 | 4, 2, 2, 0.0)
    if kind == "ckesc_rpm_only":
        ck(ckesc_records.Msg1(1500 + i, 0, status(0)))
        return Expected(True, 1500 + i, None, None, None, 0, 0, 1, 0.0)
    if kind == "ft_reverse":
        for message in (
            ft_records.RealtimeData0(3.5, 2.0 + i),
            ft_records.RealtimeData1(-700 * (i + 1), -0.25),  # reverse: -100 * (i + 1) rpm
            ft_records.RealtimeData2(30.4 + i, 60.0, 24.3),
        ):
            ingest(table, ft_codec.encode(ft_records.FtFrame(node, message)), now_ns)
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
            # sets are tested in test_link_sets.py).
            settings["autopilot_messages"] = MavlinkConfig(**settings).output_rates("")
        mavlink = MavlinkConfig(**settings)
        link = MavlinkLink(mavlink)
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
    # The whole vehicle's online bits in every batch, bit i = motor i (QGroundControl's reading).
    assert msg.info == sum(1 << i for i, esc in enumerate(expected[:8]) if esc.online)
    assert msg.counter == sum(esc.frames for esc in expected) % 65536  # packets received
    batch = [slot(expected, msg.index + j) for j in range(4)]
    for j, esc in enumerate(batch):
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
