"""The control loop's input side, per UDP datagram: what reading, scanning, judging and mixing
one datagram costs in :meth:`AutopilotInput.on_readable`, in-process on loopback UDP.

Run: ``python bench/input_side.py [--rounds 5] [--runs 3] [--datagrams 4000] [--bridge-source DIR]``

Workloads, each one frame per datagram as ArduPilot and pymavlink send them:

- ``autopilot``: SERVO_OUTPUT_RAW from the autopilot's own address, a HEARTBEAT every tenth
  (the link's usual traffic: decoded, dated and mixed);
- ``ground station``: HEARTBEATs of system 255 from another address (relayed, not acted on);
- ``impostor``: HEARTBEATs claiming to be the autopilot from another address.

Each run sends a workload's datagrams in chunks of 100 and takes the CPU time of this thread
spent in ``on_readable`` only (``time.thread_time_ns``: time the thread sat preempted on a busy
machine is not counted); the table gives the median µs per datagram over runs with the 10th
and 90th percentile.
Each checkout runs in child processes that take turns; ``--bridge-source DIR`` adds another
checkout's ``bridge`` package (e.g. ``git archive COMMIT bridge | tar -x -C DIR``) to compare.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from _stats import percentile

CHUNK = 100
HOST = "127.0.0.1"
WORKLOADS = ("autopilot", "ground station", "impostor")


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((HOST, 0))
        port: int = sock.getsockname()[1]
        return port


def measure(runs: int, datagrams: int) -> dict[str, list[float]]:
    """µs per datagram of each run, by workload (imports ``bridge`` from wherever it is found)."""
    from bridge.config import build_config
    from bridge.daemon.preflight import plan
    from bridge.mavlink import load_dialect
    from bridge.mavlink.relay import LoopEnd, relay_pair
    from bridge.output.autopilot_input import AutopilotInput, InputSetup
    from bridge.output.mailbox import InputSnapshot, LoopStats
    from bridge.output.safety import ControlInputs

    dialect: Any = load_dialect()
    port = _free_port()
    raw = {
        "mavlink": {"url": f"udpin:{HOST}:{port}"},
        "can": {"interface": "virtual", "channel": "bench"},
        "zenoh": {"enabled": False},
    }
    checked = plan(build_config(raw, "bench"))
    loop_end, main_end = relay_pair()
    main_end.setblocking(False)
    side = AutopilotInput(
        checked.config,
        InputSetup(checked.mixer, checked.valid_range, None),
        ControlInputs(),
        LoopStats(),
        InputSnapshot(len(checked.mixer.outputs)),
        LoopEnd(loop_end),
    )
    side.open()
    autopilot_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    autopilot: Any = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
    station: Any = dialect.MAVLink(None, srcSystem=255, srcComponent=190)

    def beat(mav: Any) -> bytes:
        return bytes(mav.heartbeat_encode(2, 3, 1, 0, 4).pack(mav))

    def chunk(workload: str, start_us: int) -> tuple[socket.socket, list[bytes]]:
        if workload == "ground station":
            return other_sock, [beat(station) for _ in range(CHUNK)]
        if workload == "impostor":
            return other_sock, [beat(autopilot) for _ in range(CHUNK)]
        return autopilot_sock, [
            beat(autopilot)
            if i % 10 == 0
            else bytes(
                autopilot.servo_output_raw_encode(
                    (start_us + i * 2500) & 0xFFFFFFFF, 0, *[1500] * 8
                ).pack(autopilot)
            )
            for i in range(CHUNK)
        ]

    def drain() -> None:
        try:
            while main_end.recv(1 << 17):
                pass
        except BlockingIOError:
            return

    results: dict[str, list[float]] = {w: [] for w in WORKLOADS}
    try:
        autopilot_sock.sendto(beat(autopilot), (HOST, port))  # the autopilot's address first
        time.sleep(0.01)
        side.on_readable(time.monotonic_ns())
        for _ in range(runs):
            for workload in WORKLOADS:
                spent_ns = read = 0
                for _ in range(max(1, datagrams // CHUNK)):
                    sock, data = chunk(workload, time.monotonic_ns() // 1000)
                    for datagram in data:
                        sock.sendto(datagram, (HOST, port))
                    time.sleep(0.001)  # loopback delivers at once; this is only a margin
                    started = time.thread_time_ns()
                    side.on_readable(time.monotonic_ns())
                    spent_ns += time.thread_time_ns() - started
                    read += len(data)
                    drain()
                results[workload].append(spent_ns / read / 1000)
    finally:
        side.close()
        autopilot_sock.close()
        other_sock.close()
        main_end.close()
    return results


def _child(source: Path | None, runs: int, datagrams: int) -> tuple[str, dict[str, list[float]]]:
    """Which bridge a child process imported, and its µs per datagram by workload."""
    env = dict(os.environ)
    if source is not None:
        env["PYTHONPATH"] = str(source)
    command = [sys.executable, __file__, "--child", "--runs", str(runs)]
    out = subprocess.run(
        [*command, "--datagrams", str(datagrams)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.splitlines()
    rows = [line.split("\t") for line in out]
    return rows[0][1], {row[0]: [float(v) for v in row[1:]] for row in rows[1:]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5, help="child processes per checkout")
    parser.add_argument("--runs", type=int, default=3, help="runs per child process")
    parser.add_argument("--datagrams", type=int, default=4000, help="per workload and run")
    parser.add_argument("--bridge-source", type=Path, metavar="DIR")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        import bridge

        print("bridge", bridge.__file__, sep="\t")
        for workload, values in measure(args.runs, args.datagrams).items():
            print(workload, *values, sep="\t")
        return 0
    sources: list[tuple[str, Path | None]] = [("this checkout", None)]
    if args.bridge_source:
        sources.append((str(args.bridge_source), args.bridge_source.resolve()))
    load = os.getloadavg()[0]
    # The checkouts take turns, so a change in the machine's load falls on both alike.
    results: list[dict[str, list[float]]] = [{w: [] for w in WORKLOADS} for _ in sources]
    imported = [""] * len(sources)
    for _ in range(args.rounds):
        for index, (_, source) in enumerate(sources):
            imported[index], taken = _child(source, args.runs, args.datagrams)
            for workload in WORKLOADS:
                results[index][workload] += taken[workload]
    print(
        f"input side: CPU µs per datagram, median [p10, p90] over {args.rounds * args.runs} runs "
        f"of {args.datagrams} datagrams; load {load:.1f} at the start, "
        f"{os.getloadavg()[0]:.1f} at the end"
    )
    for (label, _), path in zip(sources, imported, strict=True):
        print(f"  {label}: bridge from {Path(path).parent}")
    header = f"{'workload':<16}" + "".join(f"{label:>28}" for label, _ in sources)
    print(header)
    print("-" * len(header))
    for workload in WORKLOADS:
        cells = [
            f"{statistics.median(column[workload]):.2f} "
            f"[{percentile(column[workload], 0.1):.2f}, {percentile(column[workload], 0.9):.2f}]"
            for column in results
        ]
        print(f"{workload:<16}" + "".join(f"{cell:>28}" for cell in cells))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
