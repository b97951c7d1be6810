"""Per-link MAVLink message sets through the whole daemon (its CLI), with real components.

The autopilot is pymavlink on loopback UDP announcing itself as ArduPilot, PX4 or another stack
in its HEARTBEAT; a ground station is a pymavlink ``udpin`` connection named in ``[mavlink]
outputs``; simulated CKESCs send real telemetry frames on the cross-process udp_multicast bus.
What arrives is decoded with the project's dialect and timed by the kernel's receive stamps.

Rates are one batch's messages counted over a window of :data:`WINDOW_S` seconds, and must be
within :data:`RATE_TOLERANCE` of the configured rate. The sender keeps an absolute schedule
(each message due on a grid of its period) and skips, rather than catches up, what fell due
while it did not run: ±20 % leaves room for the arrival jitter at the window's ends and for
stalls of a few periods. A longer stall the daemon reports itself (``rounds held up`` in its
exit summary: the main process did not run, on a 2-core machine busy with the rest of the suite
once for 1.28 s): the link's silences longer than :data:`SILENCE_S`, as many as it reported and
each cut to the longest hold it reported, are taken out of the window (:func:`measure`).
"""

from __future__ import annotations

import itertools
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from conftest import (
    ESC_BRIDGE,
    Autopilot,
    Daemon,
    Holds,
    MavlinkReceiver,
    free_port,
    holds_of,
    multicast_bus,
)
from pymavlink import mavutil

from bridge.escs.ckesc import codec, records
from bridge.mavlink import load_dialect
from bridge.mavlink.esc_messages import AUTOPILOT_SETS, OTHER_AUTOPILOT_SET, Family, bytes_per_s

dialect = load_dialect()
ARDUPILOT = dialect.MAV_AUTOPILOT_ARDUPILOTMEGA
PX4 = dialect.MAV_AUTOPILOT_PX4
GENERIC = dialect.MAV_AUTOPILOT_GENERIC
N_ESCS = 6  # a hex: two batches of four, the second half padded
WARMUP_S = 1.0
WINDOW_S = 6.0
SILENCE_S = 0.5  # a link this long without an ESC message may be a hold-up the daemon reported
RATE_TOLERANCE = 0.2
FAMILY_KINDS = {
    "esc_status": ("ESC_STATUS",),
    "esc_info": ("ESC_INFO",),
    "esc_telemetry": ("ESC_TELEMETRY_1_TO_4", "ESC_TELEMETRY_5_TO_8"),
}
ESC_KINDS = {kind for kinds in FAMILY_KINDS.values() for kind in kinds}


class Escs:
    """Simulated CKESCs 1..n: MSG1, MSG2 and MSG3 every 20 ms, every value non-zero."""

    def __init__(self, port: int, n: int) -> None:
        self.bus = multicast_bus(port)
        self.n = n
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="escs", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        tick = 0
        status = records.Msg1Status.RUNNING
        while not self._stop.is_set():
            for node in range(1, self.n + 1):
                for message in (
                    records.Msg1(1000 * node, 100 * node, status),
                    records.Msg2(20 + node / 100, float(node), 30 + node),
                    records.Msg3(30 + node, 20 + node, 40 + node, 25 + node),
                ):
                    frame = codec.CkescFrame(
                        codec.default_priority(message), node, None, tick % 32, message
                    )
                    self.bus.send(codec.encode(frame))
            tick += 1
            time.sleep(0.02)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.bus.shutdown()


class Gcs:
    """A ground station on an output: a pymavlink ``udpin`` connection and its receiver."""

    def __init__(self) -> None:
        self.port = free_port()
        self.url = f"udpout:127.0.0.1:{self.port}"  # as the bridge's config names it
        self.conn: Any = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{self.port}", source_system=255, source_component=190
        )
        self.rx = MavlinkReceiver(self.conn)

    def close(self) -> None:
        self.rx.close()
        self.conn.close()


@pytest.fixture
def escs(can_port: int) -> Iterator[Escs]:
    sim = Escs(can_port, N_ESCS)
    yield sim
    sim.close()


@pytest.fixture
def gcs() -> Iterator[Gcs]:
    station = Gcs()
    yield station
    station.close()


def start(tmp_path: Path, start_daemon: Callable[..., Daemon], mavlink: str, *extra: str) -> Daemon:
    config = tmp_path / "bridge.toml"
    config.write_text(f"[mavlink]\nstream_rate_hz = 0\n{mavlink}", encoding="utf-8")
    return start_daemon("--mixer", "passthrough-6", "--config", str(config), *extra)


@dataclass(frozen=True)
class Rate:
    hz: float
    longest_gap_s: float  # between two messages in the window, or from its ends: what a stall took


@dataclass(frozen=True)
class Window:
    since: float
    until: float


def measure(rx: MavlinkReceiver, window: Window, holds: Holds) -> tuple[dict[str, Rate], float]:
    """Each ESC message kind's rate (batch 0 for ESC_STATUS/ESC_INFO) and the ESC messages'
    bytes per second, from what arrived in ``window``, counted over the window less the
    link's silences the daemon's ``holds`` account for: its ``count`` longest silences over
    :data:`SILENCE_S` (no ESC message of any kind), each cut to ``longest_s``."""
    since, until = window.since, window.until
    with rx._lock:
        got = [(t, m) for t, m in rx.messages if since <= t <= until]
    times: dict[str, list[float]] = {}
    arrivals = [since]
    size = 0
    for t, m in got:
        kind = m.get_type()
        if kind not in ESC_KINDS:
            continue
        size += len(m.get_msgbuf())
        arrivals.append(t)
        if getattr(m, "index", 0) == 0:
            times.setdefault(kind, []).append(t)
    silences = sorted(b - a for a, b in itertools.pairwise([*arrivals, until]) if b - a > SILENCE_S)
    held_s = sum(min(s, holds.longest_s) for s in silences[::-1][: holds.count])
    # Counted over the window, not from the first to the last arrival: at load 8 a late first
    # or last message moved that span enough to read 10 Hz as 12.
    span_s = until - since - held_s
    rates = {
        kind: Rate(
            len(ts) / span_s,
            max(b - a for a, b in itertools.pairwise([since, *ts, until])),
        )
        for kind, ts in times.items()
    }
    return rates, size / span_s


def esc_frames(rx: MavlinkReceiver) -> list[tuple[float, bytes]]:
    """Every ESC telemetry frame received, as on the wire, with its arrival time."""
    with rx._lock:
        return [(t, bytes(m.get_msgbuf())) for t, m in rx.messages if m.get_type() in ESC_KINDS]


def assert_rates(where: str, rates: dict[str, Rate], expected: dict[Family, float]) -> None:
    print(where, {kind: round(rate.hz, 2) for kind, rate in sorted(rates.items())})  # with -s
    for family, hz in expected.items():
        for kind in FAMILY_KINDS[family]:
            rate = rates.get(kind, Rate(0.0, WINDOW_S))
            if hz == 0:
                assert rate.hz == 0, f"{where}: {kind} at {rate.hz:.2f} Hz, expected none"
            else:
                assert abs(rate.hz - hz) <= RATE_TOLERANCE * hz, (
                    f"{where}: {kind} at {rate.hz:.2f} Hz, expected {hz:g} Hz ±20 % "
                    f"(longest gap {rate.longest_gap_s:.2f} s)"
                )


def wait_for_a_window(*receivers: MavlinkReceiver) -> Window:
    """Wait for telemetry to flow on every receiver, then for one window to pass."""
    for rx in receivers:
        rx.wait_for("HEARTBEAT", lambda m: m.get_srcComponent() == 191, timeout_s=15)
    time.sleep(WARMUP_S + 1.0)  # the autopilot's first HEARTBEAT has chosen its set by now
    return a_window()


def a_window() -> Window:
    since = time.monotonic()
    time.sleep(WINDOW_S)
    return Window(since, time.monotonic())


GCS_DEFAULT: dict[Family, float] = {"esc_status": 10.0, "esc_info": 1.0, "esc_telemetry": 10.0}


@pytest.mark.parametrize(
    "stack", [ARDUPILOT, PX4, GENERIC], ids=["ardupilot", "px4", "other-stack"]
)
def test_the_default_sets_by_the_autopilots_heartbeat(
    stack: int,
    tmp_path: Path,
    mavlink_port: int,
    start_daemon: Callable[..., Daemon],
    escs: Escs,
    gcs: Gcs,
) -> None:
    autopilot = Autopilot(mavlink_port, stack=stack)
    pilot_rx = MavlinkReceiver(autopilot.conn)
    try:
        daemon = start(tmp_path, start_daemon, f'outputs = ["{gcs.url}"]\n')
        autopilot.start_stream(20)
        window = wait_for_a_window(pilot_rx, gcs.rx)
        # A family due on both links at once is one frame for both (the same sequence number,
        # the same ESC_INFO round): every one the autopilot got, the ground station got too
        # (the schedules share one grid, and the ground station's rates are multiples).
        sent_to_pilot = esc_frames(pilot_rx)
        sent_to_gcs = {frame for _, frame in esc_frames(gcs.rx)}
    finally:
        pilot_rx.close()
        autopilot.close()
    holds = holds_of(daemon)
    pilot_rates, pilot_bytes = measure(pilot_rx, window, holds)
    gcs_rates, _ = measure(gcs.rx, window, holds)
    # The set's first messages go out at once when the HEARTBEAT chooses it, off the grid.
    first = sent_to_pilot[0][0]
    later = [frame for t, frame in sent_to_pilot if t > first + 0.5]
    assert later
    # On a loaded machine (two busy processes beside the suite) a tick late for one link was
    # sent apart: 4 of the autopilot's frames were not the ground station's. Most are shared.
    apart = sum(frame not in sent_to_gcs for frame in later)
    assert apart <= len(later) // 4, f"{apart} of {len(later)} frames sent apart"
    expected = AUTOPILOT_SETS.get(stack, OTHER_AUTOPILOT_SET)
    assert_rates("autopilot link", pilot_rates, expected)
    assert_rates("ground station", gcs_rates, GCS_DEFAULT)
    # Every ESC online, every frame full but the padded batch's: the computed load is what
    # goes on the wire (HEARTBEAT and STATUSTEXT not counted).
    most = bytes_per_s(expected, N_ESCS)
    print(f"autopilot link: {pilot_bytes:.0f} B/s of ESC telemetry (at most {most:.0f})")
    assert 0.8 * most <= pilot_bytes <= 1.1 * most, (pilot_bytes, most)
    assert f"MAVLink ESC telemetry to the autopilot (MAV_AUTOPILOT {stack}):" in daemon.output


def test_nothing_to_the_autopilot_before_its_heartbeat(
    tmp_path: Path, mavlink_port: int, start_daemon: Callable[..., Daemon], gcs: Gcs
) -> None:
    autopilot = Autopilot(mavlink_port, stack=PX4)
    pilot_rx = MavlinkReceiver(autopilot.conn)
    try:
        start(tmp_path, start_daemon, f'outputs = ["{gcs.url}"]\n')
        # Motor outputs but no HEARTBEAT: the bridge answers to this link, knows no stack.
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and not pilot_rx.messages:
            autopilot.servo_output_raw([1000] * 6)
            time.sleep(0.05)
        gcs.rx.wait_for("ESC_INFO", lambda m: True, timeout_s=5)  # the output's flows
        since = time.monotonic()
        for _ in range(30):
            autopilot.servo_output_raw([1000] * 6)
            time.sleep(0.05)
        assert not [m for t, m in pilot_rx.messages if m.get_type() in ESC_KINDS]
        autopilot.start_stream(20)  # HEARTBEATs: PX4's set starts at once
        pilot_rx.wait_for("ESC_STATUS", lambda m: True, after=since, timeout_s=3)
        pilot_rx.wait_for("ESC_INFO", lambda m: True, after=since, timeout_s=3)
        assert not [m for t, m in pilot_rx.messages if m.get_type().startswith("ESC_TELEMETRY")]
    finally:
        pilot_rx.close()
        autopilot.close()


def set_interval(conn: Any, msg_id: int, interval_us: float) -> None:
    conn.mav.command_long_send(
        1, 191, dialect.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, interval_us, 0, 0, 0, 0, 0
    )


def ack_of(rx: MavlinkReceiver, since: float) -> int:
    ack = rx.wait_for(
        "COMMAND_ACK",
        lambda m: m.command == dialect.MAV_CMD_SET_MESSAGE_INTERVAL,
        after=since,
    )
    return int(ack.result)


def test_configured_sets_and_rates_set_per_link(
    tmp_path: Path,
    autopilot: Autopilot,
    start_daemon: Callable[..., Daemon],
    escs: Escs,
    gcs: Gcs,
) -> None:
    other = Gcs()  # a second output with the esc_*_hz rates
    pilot_rx = MavlinkReceiver(autopilot.conn)
    try:
        daemon = start(
            tmp_path,
            start_daemon,
            f'outputs = ["{gcs.url}", "{other.url}"]\n'
            "autopilot_messages = { esc_telemetry = 20, esc_info = 4 }\n"
            f'output_messages = {{ "{gcs.url}" = {{ esc_status = 5 }} }}\n'
            "esc_status_hz = 3\nesc_info_hz = 2\nesc_telemetry_hz = 0\n",
        )
        autopilot.start_stream(20)  # ArduPilot's HEARTBEAT: the configured set wins
        configured = wait_for_a_window(pilot_rx, gcs.rx, other.rx)

        # SET_MESSAGE_INTERVAL acts on the link it came in on: ESC_INFO at 10 Hz from the
        # ground station, ESC_STATUS at 10 Hz from the autopilot's link (a ground station
        # behind the autopilot), ESC_TELEMETRY off on the autopilot's link.
        since = time.monotonic()
        set_interval(gcs.conn, dialect.MAVLINK_MSG_ID_ESC_INFO, 100_000)
        set_interval(autopilot.conn, dialect.MAVLINK_MSG_ID_ESC_STATUS, 100_000)
        set_interval(autopilot.conn, dialect.MAVLINK_MSG_ID_ESC_TELEMETRY_1_TO_4, -1)
        assert ack_of(gcs.rx, since) == dialect.MAV_RESULT_ACCEPTED
        assert ack_of(pilot_rx, since) == dialect.MAV_RESULT_ACCEPTED
        time.sleep(WARMUP_S)
        asked = a_window()
        holds = holds_of(daemon)
        rates = [
            {rx: measure(rx, window, holds)[0] for rx in (pilot_rx, gcs.rx, other.rx)}
            for window in (configured, asked)
        ]
    finally:
        pilot_rx.close()
        other.close()
    pilot, station, second = rates[0][pilot_rx], rates[0][gcs.rx], rates[0][other.rx]
    assert_rates("autopilot", pilot, {"esc_status": 0, "esc_info": 4, "esc_telemetry": 20})
    assert_rates("gcs", station, {"esc_status": 5, "esc_info": 0, "esc_telemetry": 0})
    assert_rates("other", second, {"esc_status": 3, "esc_info": 2, "esc_telemetry": 0})
    pilot, station, second = rates[1][pilot_rx], rates[1][gcs.rx], rates[1][other.rx]
    assert_rates("autopilot", pilot, {"esc_status": 10, "esc_info": 4, "esc_telemetry": 0})
    assert_rates("gcs", station, {"esc_status": 5, "esc_info": 10, "esc_telemetry": 0})
    assert_rates("other", second, {"esc_status": 3, "esc_info": 2, "esc_telemetry": 0})


BAD_CONFIGS = [
    (
        "autopilot_messages = { esc_telemetry = 200 }",
        "[mavlink] autopilot_messages: expected a table of esc_status, esc_info, esc_telemetry "
        "= rate in Hz 0..100 (0 = off); esc_telemetry = 200 is no rate 0..100, got "
        "{'esc_telemetry': 200}",
    ),
    (
        "autopilot_messages = { esc_stat = 2 }",
        "[mavlink] autopilot_messages: expected a table of esc_status, esc_info, esc_telemetry "
        "= rate in Hz 0..100 (0 = off); 'esc_stat' is no message family, got {'esc_stat': 2}",
    ),
    (
        'autopilot_messages = "ardupilot"',
        "[mavlink] autopilot_messages: expected a table of esc_status, esc_info, esc_telemetry "
        "= rate in Hz 0..100 (0 = off), got 'ardupilot'",
    ),
    (
        'outputs = ["udpout:127.0.0.1:14551"]\n'
        'output_messages = { "udpout:127.0.0.1:14551" = { esc_info = -1 } }',
        '[mavlink] output_messages: expected a table of "output URL" = { esc_status = Hz, '
        "esc_info = Hz, esc_telemetry = Hz }; for 'udpout:127.0.0.1:14551': a table of "
        "esc_status, esc_info, esc_telemetry = rate in Hz 0..100 (0 = off); esc_info = -1 is "
        "no rate 0..100, got {'udpout:127.0.0.1:14551': {'esc_info': -1}}",
    ),
    (
        'outputs = ["udpout:127.0.0.1:14551"]\n'
        'output_messages = { "udpout:127.0.0.1:14552" = { esc_info = 1 } }',
        "[mavlink] output_messages: 'udpout:127.0.0.1:14552' is not one of [mavlink] outputs "
        "('udpout:127.0.0.1:14551'); expected an output URL written exactly as in outputs",
    ),
]


@pytest.mark.parametrize("check", [True, False], ids=["check", "run"])
@pytest.mark.parametrize("mavlink, message", BAD_CONFIGS)
def test_a_wrong_set_is_refused_naming_the_key(
    tmp_path: Path, mavlink: str, message: str, check: bool
) -> None:
    config = tmp_path / "bridge.toml"
    config.write_text(f"[mavlink]\n{mavlink}\n", encoding="utf-8")
    result = subprocess.run(
        [ESC_BRIDGE, "run", "--config", str(config), *(["--check"] if check else [])],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 2, result
    assert result.stderr == f"esc-bridge: {config}: {message}\n"
    assert result.stdout == ""


def test_check_shows_each_links_set_and_load(tmp_path: Path) -> None:
    config = tmp_path / "bridge.toml"
    config.write_text(
        '[mixer]\nname = "passthrough-8"\n[can]\ninterface = "virtual"\n'
        '[mavlink]\noutputs = ["udpout:127.0.0.1:14551"]\n',
        encoding="utf-8",
    )
    result = subprocess.run(
        [ESC_BRIDGE, "run", "--config", str(config), "--check"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 0, result
    assert (
        "  MAVLink ESC telemetry for 8 ESCs: autopilot link by its HEARTBEAT: ArduPilot "
        "ESC_TELEMETRY 2 Hz (224 B/s); PX4 ESC_STATUS 2 Hz, ESC_INFO 1 Hz (392 B/s); other "
        "ESC_STATUS 2 Hz, ESC_INFO 1 Hz, ESC_TELEMETRY 2 Hz (616 B/s); udpout:127.0.0.1:14551 "
        "ESC_STATUS 10 Hz, ESC_INFO 1 Hz, ESC_TELEMETRY 10 Hz (2616 B/s)\n"
    ) in result.stdout


def test_the_payload_sizes_are_the_dialects() -> None:
    mav = dialect.MAVLink(None, srcSystem=1, srcComponent=191)
    ones = [1, 1, 1, 1]
    full: dict[Family, Any] = {
        "esc_status": mav.esc_status_encode(1, 1, ones, [1.0] * 4, [1.0] * 4),
        "esc_info": mav.esc_info_encode(1, 1, 1, 1, 1, 1, ones, ones, ones),
        "esc_telemetry": mav.esc_telemetry_1_to_4_encode(ones, ones, ones, ones, ones, ones),
    }
    for family, msg in full.items():
        frame = msg.pack(mav)
        assert len(frame) == bytes_per_s({family: 1.0}, 4), family  # one full frame a second


def test_the_worst_case_loads_a_57600_baud_radio_little() -> None:
    radio = 5760  # bytes/s: 57600 baud, 10 bits a byte
    for n in (4, 6, 8):
        for chosen in (*AUTOPILOT_SETS.values(), OTHER_AUTOPILOT_SET):
            assert bytes_per_s(chosen, n) <= 0.11 * radio, (n, chosen)
