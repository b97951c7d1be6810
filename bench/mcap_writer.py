"""The MCAP recording's cost per flight minute: CPU seconds and bytes, for a few flights' rates.

Run: ``python bench/mcap_writer.py [--runs 5] [--flight-s 10]``

Each run replays a made-up flight of ``--flight-s`` seconds, as fast as the machine goes, through
the code the bridge runs for it: the ESC state (``EscTable.ingest``, and ``take_commands`` for the
commands the loop says it sent, here as if every command changed), and with the MCAP on, what
the CAN reader adds for it (an ESC's snapshot after each telemetry frame), every ESC's last
command after each command, the MAVLink tap (the autopilot's SERVO_OUTPUT_RAW and HEARTBEAT, the
bridge's own HEARTBEAT, already packed), log lines, and
:class:`~bridge.telemetry.mcap_out.McapRecording` writing it all to a file until :meth:`close`
returns. The MCAP's cost is the process's CPU time (every thread: the writer's too) with it,
less the same replay without it, scaled to a minute of flight; the bytes are the file's. Medians
over ``--runs`` runs, and the 10th-90th percentile of the CPU.

The rows: ESCs x telemetry frames per second per ESC, commands at 400 Hz in frames of four ESCs,
the autopilot's outputs at 200 Hz. The demo's ESCs send about 50 (CKESC) and 200 (FT) telemetry
frames a second each. No ESC family is involved: the records are the neutral ones.

Replayed faster than real time, the writer takes bigger batches than the bridge's half-second
ones; its work per message is the same.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from _stats import percentile

from bridge.daemon.commands_sent import take_commands
from bridge.escs.family import CommandSeen, EscTelemetry
from bridge.mavlink import load_dialect
from bridge.mavlink.traffic import TrafficReader
from bridge.telemetry.mcap_channels import metadata
from bridge.telemetry.mcap_out import LogHandler, McapRecording
from bridge.telemetry.state import EscTable

COMMAND_RATE_HZ = 400
ESCS_PER_COMMAND_FRAME = 4
OUTPUT_RATE_HZ = 200
LOG_PERIOD_S = 5.0
T0_S = 1_790_000_000.0


@dataclass(frozen=True)
class Row:
    escs: int
    telemetry_hz: int
    """Telemetry frames per second per ESC."""

    @property
    def name(self) -> str:
        return f"{self.escs} ESCs x {self.telemetry_hz} frames/s"


ROWS = (Row(4, 50), Row(4, 200), Row(8, 200), Row(8, 600))

Event = tuple[float, int, Any]
_TELEMETRY, _COMMANDS, _MAVLINK, _LOG = range(4)


def flight(row: Row, flight_s: float) -> list[Event]:
    """The flight's events in time order: (wall time, kind, what)."""
    dialect: Any = load_dialect()
    autopilot = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
    bridge = dialect.MAVLink(None, srcSystem=1, srcComponent=191)
    events: list[Event] = []
    for motor in range(row.escs):
        for i in range(int(flight_s * row.telemetry_hz)):
            t = i / row.telemetry_hz + motor / (row.escs * row.telemetry_hz)
            rpm = int(6000 + 4000 * math.sin(t / 3 + motor))
            kind = i % 3  # rpm; volts, amps, temperature; rpm again
            telemetry = EscTelemetry(
                motor + 1,
                rpm=rpm,
                throttle=rpm / 12000,
                status=0,
                status_failures=0,
                uncommanded_failures=0,
            )
            if kind == 1:
                telemetry = EscTelemetry(
                    motor + 1,
                    voltage_v=round(24 - rpm / 5000, 2),
                    current_a=round(rpm / 800, 2),
                    mos_temp_c=40 + t // 10,
                )
            events.append((t, _TELEMETRY, telemetry))
    frames_per_tick = math.ceil(row.escs / ESCS_PER_COMMAND_FRAME)
    for i in range(int(flight_s * COMMAND_RATE_HZ)):
        t = i / COMMAND_RATE_HZ
        for f in range(frames_per_tick):
            first = f * ESCS_PER_COMMAND_FRAME
            last = min(row.escs, first + ESCS_PER_COMMAND_FRAME)
            value = float(int(1000 + 800 * math.sin(t)))
            seen = [CommandSeen(value, "throttle", node_id=n + 1) for n in range(first, last)]
            events.append((t + f * 1e-5, _COMMANDS, seen))
    for i in range(int(flight_s * OUTPUT_RATE_HZ)):
        t = i / OUTPUT_RATE_HZ
        raw = [int(1100 + 800 * abs(math.sin(t + k))) for k in range(8)]
        msg = autopilot.servo_output_raw_encode(int(t * 1e6), 0, *raw)
        events.append((t, _MAVLINK, bytes(msg.pack(autopilot))))
    for i in range(int(flight_s)):
        beat = autopilot.heartbeat_encode(2, 3, 0x80, 0, 4)
        events.append((i + 0.5, _MAVLINK, bytes(beat.pack(autopilot))))
        own = bridge.heartbeat_encode(18, 8, 0, 0, 4)
        events.append((i + 0.6, _MAVLINK, bytes(own.pack(bridge))))
    for i in range(int(flight_s / LOG_PERIOD_S)):
        events.append((i * LOG_PERIOD_S, _LOG, f"CAN send failures: {i} since the last report"))
    events.sort(key=lambda e: e[0])
    return [(T0_S + t, kind, what) for t, kind, what in events]


def replay(events: list[Event], escs: int, path: Path | None) -> tuple[float, int]:
    """CPU seconds (the whole process) to replay ``events``, with an MCAP at ``path`` or none;
    and the file's size."""
    table = EscTable(list(range(1, escs + 1)))
    recording = None
    logger = logging.getLogger("bench.mcap")
    logger.propagate = False
    logger.handlers.clear()
    if path is not None:
        traffic = TrafficReader(load_dialect(), "servo_output_raw", (1, 1), (1, 191))
        recording = McapRecording(path.open("wb"), traffic, metadata("bench", range(1, escs + 1)))
        logger.addHandler(LogHandler(recording))
    ingest, snapshot_of = table.ingest, table.snapshot_of
    start = time.process_time()
    for t, kind, what in events:
        now_ns = int(t * 1e9)
        if kind == _TELEMETRY:
            if ingest(what, now_ns) and recording is not None:
                snap = snapshot_of(what.node_id, now_ns)
                if snap is not None:
                    recording.esc(snap, t)
        elif kind == _COMMANDS:
            take_commands(table, what, t, recording)
        elif recording is not None:
            if kind == _MAVLINK:
                recording.mavlink(int(t * 1e6), what)
            else:
                logger.warning("%s", what)
    if recording is not None:
        recording.close()
    cpu_s = time.process_time() - start
    return cpu_s, path.stat().st_size if path is not None else 0


def measure(row: Row, runs: int, flight_s: float) -> dict[str, float]:
    events = flight(row, flight_s)
    per_minute = 60.0 / flight_s
    cpu: list[float] = []
    sizes: list[float] = []
    messages = sum(1 for e in events if e[1] != _MAVLINK) + sum(
        1 for e in events if e[1] == _MAVLINK
    )
    with tempfile.TemporaryDirectory() as tmp:
        for run in range(runs):
            base_s, _ = replay(events, row.escs, None)
            with_s, size = replay(events, row.escs, Path(tmp) / f"run-{run}.mcap")
            cpu.append((with_s - base_s) * per_minute)
            sizes.append(size * per_minute)
    return {
        "items_per_min": messages * per_minute,
        "cpu_s": statistics.median(cpu),
        "cpu_p10": percentile(cpu, 0.1),
        "cpu_p90": percentile(cpu, 0.9),
        "mb": statistics.median(sizes) / 1e6,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=5, help="runs per row (default 5)")
    parser.add_argument(
        "--flight-s", type=float, default=10.0, help="seconds of flight per run (default 10)"
    )
    args = parser.parse_args(argv)
    load = os.getloadavg()[0]
    print(
        f"MCAP recording, cost per flight minute: median of {args.runs} runs of "
        f"{args.flight_s:g} s each; load average {load:.1f} at the start"
    )
    print()
    header = (
        "| flight | items per minute | CPU s per flight minute (p10-p90) | % of a core "
        "| MB per minute |"
    )
    print(header)
    print("| --- | --- | --- | --- | --- |")
    report: Callable[[Row, dict[str, float]], str] = lambda row, m: (  # noqa: E731
        f"| {row.name} | {m['items_per_min']:,.0f} | {m['cpu_s']:.2f} "
        f"({m['cpu_p10']:.2f}-{m['cpu_p90']:.2f}) | {m['cpu_s'] / 60 * 100:.1f} % "
        f"| {m['mb']:.2f} |"
    )
    for row in ROWS:
        print(report(row, measure(row, args.runs, args.flight_s)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
