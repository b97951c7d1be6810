"""The warnings that name what is missing (bridge/daemon/absence.py): on a clock the test
moves, with the link's real counters and a real ESC state; then the daemon itself, started
through its CLI with nothing on either side."""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from datetime import datetime

from conftest import Daemon

from bridge.config import build_config
from bridge.daemon.absence import GRACE_S, REPEAT_S, AbsenceWatch, EscsHeard
from bridge.escs.family import EscTelemetry
from bridge.mavlink.stats import LinkStats
from bridge.telemetry.state import EscTable

S = 1_000_000_000
START = 1000 * S


class Watched:
    def __init__(self, raw: dict[str, dict[str, object]] | None = None) -> None:
        self.config = build_config(raw or {}, "test")
        self.reports: list[tuple[int, str]] = []
        self.watch = AbsenceWatch(
            self.config, START, lambda level, text: self.reports.append((level, text))
        )
        self.link = LinkStats()
        self.table = EscTable([1, 2, 3, 4], timeout_ms=500)
        self.frames = 0

    def at(self, seconds: float) -> list[tuple[int, str]]:
        now = START + round(seconds * S)
        before = len(self.reports)
        self.watch.check(
            now,
            self.link,
            lambda: EscsHeard(self.table.snapshot(now), self.frames, self.table.unknown_frames),
        )
        return self.reports[before:]

    def esc(self, node: int, seconds: float) -> None:
        self.table.ingest(EscTelemetry(node, rpm=0), START + round(seconds * S))


def test_nothing_is_said_before_the_grace_then_each_missing_piece_is_named() -> None:
    w = Watched({"mavlink": {"url": "serial:/dev/ttyAMA0:921600"}, "can": {"channel": "can7"}})
    assert w.at(GRACE_S - 0.1) == []
    first = w.at(GRACE_S)
    assert [level for level, _ in first] == [logging.WARNING, logging.WARNING]
    assert first[0][1].startswith(
        "no HEARTBEAT from the autopilot 1/1 on serial:/dev/ttyAMA0:921600 5 s after start; "
        "nothing arrived: is the flight controller's telemetry port wired to it"
    )
    assert first[1][1].startswith(
        "no telemetry from CKESC ESC IDs 1, 2, 3, 4 (motors 1, 2, 3, 4) of 4 on socketcan can7 "
        "at 500000 bit/s (500 kbit/s): no ESC telemetry on the bus at all (0 frames read): "
    )
    # Once, then again every REPEAT_S while it lasts.
    assert w.at(GRACE_S + 1) == [] and w.at(GRACE_S + REPEAT_S - 1) == []
    again = w.at(GRACE_S + REPEAT_S)
    assert [text.split(" on ")[0] for _, text in again] == [
        "no HEARTBEAT from the autopilot 1/1",
        "no telemetry from CKESC ESC IDs 1, 2, 3, 4 (motors 1, 2, 3, 4) of 4",
    ]
    assert "35 s after start" in again[0][1]


def test_the_pieces_that_turn_up_are_said_once_and_the_rest_named() -> None:
    w = Watched({"mavlink": {"url": "udpin:0.0.0.0:14550"}})
    w.at(GRACE_S)
    w.link.messages = 12  # a ground station's, say: no HEARTBEAT from 1/1
    w.esc(2, GRACE_S + 0.5)
    w.esc(4, GRACE_S + 0.5)
    w.frames = 40
    said = w.at(GRACE_S + 1)
    assert [text for _, text in said] == [
        "no telemetry from CKESC ESC IDs 1, 3 (motors 1, 3) of 4 on socketcan can0 at 500000 "
        "bit/s (500 kbit/s): 1, 3 never heard: is each such ESC powered and wired, its ID the "
        "one in [escs] ids, its reports on? (docs/troubleshooting.md)"
    ]
    w.link.last_heartbeat_ns = START + round((GRACE_S + 1.5) * S)
    for node in (1, 2, 3, 4):
        w.esc(node, GRACE_S + 1.8)
    assert w.at(GRACE_S + 2) == [
        (logging.INFO, "HEARTBEAT from the autopilot 1/1 on udpin:0.0.0.0:14550"),
        (logging.INFO, "ESC telemetry: all 4 ESCs online"),
    ]
    assert w.at(GRACE_S + 2.4) == []  # checked once a second
    # Lost again: the HEARTBEAT 3 s old, ESC 4 past its 500 ms timeout.
    for node in (1, 2, 3):
        w.esc(node, GRACE_S + 5.5)
    lost = [text for _, text in w.at(GRACE_S + 5.6)]
    assert lost[0].startswith(
        "no HEARTBEAT from the autopilot 1/1 on udpin:0.0.0.0:14550 for 4 s; 12 MAVLink "
        "messages arrived, none a HEARTBEAT from system 1/1: are [mavlink] autopilot_system_id"
    )
    assert lost[1].startswith(
        "no telemetry from CKESC ESC ID 4 (motor 4) of 4 on socketcan can0 at 500000 bit/s "
        "(500 kbit/s): heard before, silent now"
    )


def test_telemetry_from_other_ids_is_pointed_at() -> None:
    w = Watched({"output": {"protocol": "ft"}})
    w.table.ingest(EscTelemetry(9, rpm=0), START)
    said = w.at(GRACE_S)[1][1]
    assert said.startswith("no telemetry from FT ESC IDs 1, 2, 3, 4 (motors 1, 2, 3, 4) of 4")
    assert ": 1 telemetry frames came from IDs not in [escs] ids: are those the ESCs' IDs?" in said


# -- the daemon, nothing on either side --------------------------------------------------------

_STAMP = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) \w+ esc-bridge ")


def _logged_at(output: str, pattern: str) -> float:
    """When the first line matching ``pattern`` (a regular expression) was logged."""
    for line in output.splitlines():
        match = _STAMP.match(line)
        if match and re.search(pattern, line):
            return datetime.strptime(match[1], "%Y-%m-%d %H:%M:%S,%f").timestamp()
    raise AssertionError(f"{pattern!r} not in the log:\n{output}")


def test_the_daemon_names_what_is_missing(
    start_daemon: Callable[..., Daemon], mavlink_port: int
) -> None:
    daemon = start_daemon("--no-zenoh", "--bitrate", "1M")
    daemon.loop_pid()  # spawned
    # GRACE_S after the loop has started, checked once a second from the supervisor's 10 Hz
    # watch; at load 8 the loop's start and the supervisor may take seconds more: wait well past.
    time.sleep(GRACE_S + 8.0)
    assert daemon.stop() == 0, daemon.output
    started = _logged_at(daemon.output, "output loop runs ")
    url = re.escape(f"udpin:127.0.0.1:{mavlink_port}")
    heartbeat = _logged_at(
        daemon.output,
        f"WARNING esc-bridge no HEARTBEAT from the autopilot 1/1 on {url} \\d+ s after start; "
        "nothing arrived: is the autopilot \\(or SITL\\) sending to this address\\?",
    )
    silent = _logged_at(
        daemon.output,
        re.escape(
            "WARNING esc-bridge no telemetry from CKESC ESC IDs 1, 2, 3, 4 (motors 1, 2, 3, 4) "
            "of 4 on udp_multicast 239.74.163.2 at 1000000 bit/s (1 Mbit/s): "
        ),
    )
    for at in (heartbeat, silent):
        assert GRACE_S - 0.5 <= at - started <= GRACE_S + 5.0, daemon.output
    assert daemon.output.count("no HEARTBEAT from the autopilot") == 1
