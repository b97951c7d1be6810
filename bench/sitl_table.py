"""The bridge against the real autopilots: docs/simulation.md's table, from the SITL tests'
own flights.

Run: ``python bench/sitl_table.py [--flights 3] [--json FILE]``

(Not ``bench/sitl.py``: the benchmarks are top-level modules to mypy, and ``sitl`` is the test
package tests/sitl.)

Each flight is one run of ``pytest tests/sitl`` (both files in parallel, as in the suite): an
ArduCopter SITL flown through a CKESC, an FT and a DroneCAN bridge (source SERVO_OUTPUT_RAW),
and a PX4 SITL (SIH quad) flown through three bridges (ACTUATOR_OUTPUT_STATUS with CKESC and
FT, SERVO_OUTPUT_RAW with CKESC). The tests record what they measure in the file named by
``$ESC_BRIDGE_SITL_REPORT`` (tests/sitl/conftest.py ``measured``); this script reads it back and
prints one row per autopilot, source and ESC protocol, each number the median over the flights
(with the range when they differ). The checks themselves stay the tests': each flight's pytest
summary is printed too, so a number from a failing flight is seen as such.

Needs the builds the tests use (``$ESC_BRIDGE_ARDUCOPTER``, ``$ESC_BRIDGE_PX4`` or
``../shared/sitl``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
NUMBER = re.compile(r"-?\d+(?:\.\d+)?")


@dataclass(frozen=True)
class Row:
    autopilot: str
    source: str
    protocol: str
    key: str
    """The tests' name for this bridge: ArduCopter's rig (its ESC family, "ckesc"), PX4's side
    ("aos")."""


ROWS = (
    Row("ArduCopter", "servo_output_raw", "CKESC", "ckesc"),
    Row("ArduCopter", "servo_output_raw", "FT", "ft"),
    Row("ArduCopter", "servo_output_raw", "DroneCAN", "dronecan"),
    Row("PX4", "actuator_output_status", "CKESC", "aos"),
    Row("PX4", "servo_output_raw", "CKESC", "sor"),
    Row("PX4", "actuator_output_status", "FT", "ft"),
)


def fly(report: Path) -> tuple[int, str]:
    """One run of the SITL tests; (exit status, pytest's last line)."""
    env = {**os.environ, "ESC_BRIDGE_SITL_REPORT": str(report)}
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "tests/sitl", "-q", "-p", "no:cacheprovider"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    lines = [line for line in done.stdout.splitlines() if line.strip()]
    failed = [line for line in lines if line.startswith(("FAILED", "ERROR"))]
    return done.returncode, "\n    ".join([lines[-1] if lines else "(no output)", *failed])


def read_report(path: Path) -> dict[str, Any]:
    values: dict[str, Any] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            entry = json.loads(line)
            values[entry["name"]] = entry["value"]
    return values


def numbers(value: Any) -> list[float]:
    """The numbers in a measurement (the tests record some as text: "103 ms after ...")."""
    if isinstance(value, int | float):
        return [float(value)]
    return [float(n) for n in NUMBER.findall(str(value))]


def cell(flights: list[dict[str, Any]], name: str, pick: int = 0, unit: str = "") -> str:
    """Median (and range) over the flights of the ``pick``-th number in measurement ``name``;
    "never" when a flight recorded none (e.g. no recovery), "-" when none measured it."""
    values: list[float] = []
    never = 0
    for flight in flights:
        if name not in flight:
            continue
        found = numbers(flight[name])
        if len(found) > pick:
            values.append(found[pick])
        else:
            never += 1
    if not values:
        return "never" if never else "-"
    median = statistics.median(values)
    text = f"{median:.4g}{unit}"
    if max(values) != min(values):
        text += f" ({min(values):.4g}-{max(values):.4g})"
    if never:
        text += f", never in {never}"
    return text


def texts(flights: list[dict[str, Any]], name: str) -> str:
    """The distinct text values of ``name`` over the flights."""
    seen = [str(f[name]) for f in flights if name in f]
    return " | ".join(dict.fromkeys(seen)) or "-"


def senders(flights: list[dict[str, Any]], name: str) -> str:
    """The sysid/compid in "2.0 Hz in hover from 1/191, ..." over the flights."""
    found = [re.search(r"from (\d+/\d+)", str(f[name])) for f in flights if name in f]
    return " | ".join(dict.fromkeys(m[1] for m in found if m)) or "-"


def motor_test_delays(flights: list[dict[str, Any]], rig: str) -> str:
    """ArduCopter's motor tests: the first non-zero frame after the first test output, ms,
    over every test of every flight (B runs while ArduCopter boots)."""
    delays = [
        d for f in flights for d in numbers(f.get(f"{rig} motor test first non-zero frame", ""))[:3]
    ]
    if not delays:
        return "-"
    return f"motor test {statistics.median(delays):.0f} ms (max {max(delays):.0f})"


def columns(row: Row, flights: list[dict[str, Any]]) -> list[str]:
    k = row.key
    if row.autopilot == "ArduCopter":
        return [
            cell(flights, f"{k} SERVO_OUTPUT_RAW at the bridge (asked 200 Hz)", 0, " Hz"),
            "200 Hz: " + texts(flights, f"{k} SERVO_OUTPUT_RAW request answered"),
            # "99.7% of N frames equal the newest output exactly, 99.97% within one period":
            # the second share is the lag rule PX4's column uses.
            cell(flights, f"{k} tracking, takeoff and hover", 2, " %"),
            cell(flights, f"{k} zero frames in flight, takeoff and hover"),
            cell(flights, f"{k} failsafe after SIGSTOP", 0, " ms"),
            cell(flights, f"{k} recovery after SIGCONT", 0, " ms"),
            cell(flights, f"{k} reconnect after restart", 0, " s"),
            motor_test_delays(flights, k),
            "ESC_TELEMETRY_1_TO_4 "
            + cell(flights, f"{k} ESC_TELEMETRY_1_TO_4 at the ground station", 0, " Hz")
            + " from "
            + senders(flights, f"{k} ESC_TELEMETRY_1_TO_4 at the ground station"),
        ]
    p = f"PX4 {k}:"
    message = row.source.upper()
    return [
        cell(flights, f"{p} output rate at the bridge in flight, Hz", 0, " Hz"),
        "200 Hz: " + texts(flights, f"{p} {message} request answered"),
        cell(
            flights, f"{p} tracking frames equal to the newest output >= 1 period old, %", 0, " %"
        ),
        cell(flights, f"{p} all-zero frames while armed with fresh input"),
        cell(flights, f"{p} SIGSTOP: safe after the last output, ms", 0, " ms"),
        cell(flights, f"{p} SIGCONT: running again after PX4's first new output, ms", 0, " ms"),
        cell(flights, f"{p} restart: first output at the bridge after PX4's restart, s", 0, " s"),
        "arming " + cell(flights, f"{p} arming: outputs armed -> first non-zero command, ms"),
        "ESC_STATUS "
        + cell(flights, f"{p} ESC_STATUS at the GCS in flight, per s", 0, " Hz")
        + " + ESC_INFO "
        + cell(flights, f"{p} ESC_INFO at the GCS in flight, per s", 0, " Hz")
        + " from "
        + texts(flights, f"{p} ESC telemetry at the GCS from"),
    ]


HEADER = [
    "autopilot",
    "source",
    "ESC",
    "output rate at the bridge",
    "asked: answered",
    "tracking",
    "all-zero frames in flight",
    "failsafe after SIGSTOP",
    "running after SIGCONT",
    "reconnect after restart",
    "arming / motor-test delay (ms)",
    "ESC telemetry at the GCS",
]


def table(flights: list[dict[str, Any]]) -> str:
    lines = ["| " + " | ".join(HEADER) + " |", "|" + " --- |" * len(HEADER)]
    for row in ROWS:
        cells = [row.autopilot, row.source, row.protocol, *columns(row, flights)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--flights", type=int, default=1, help="runs of tests/sitl (default 1)")
    parser.add_argument("--json", type=Path, help="also write every flight's measurements here")
    args = parser.parse_args()
    flights: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in range(args.flights):
            report = Path(tmp) / f"flight-{n}.jsonl"
            started = time.monotonic()
            _status, summary = fly(report)
            print(f"flight {n + 1}/{args.flights}: {time.monotonic() - started:.0f} s, {summary}")
            flights.append(read_report(report))
    if args.json:
        args.json.write_text(json.dumps(flights, indent=1))
    print()
    print(f"Medians over {args.flights} flight(s) (range in brackets):")
    print(table(flights))


if __name__ == "__main__":
    main()
