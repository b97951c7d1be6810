"""One tick of the output loop, back to back: what the loop's own Python and its sends cost
when nothing else runs between ticks, against what a tick costs in the running bridge.

Run: ``python bench/tick.py [--runs 5] [--ticks 10000] [--protocols ckesc dronecan]``

An :class:`~bridge.output.output_loop.OutputLoop` for CKESC 12b x8 (two frames a tick), or
DroneCAN x8 (one RawCommand of three frames a tick), is opened in this process and ticked
``--ticks`` times in a row, on a ``virtual`` bus (the tick's Python alone: a send is an append
to a queue nobody reads) and on a ``udp_multicast`` bus of its own port (python-can's packing
and the ``sendto``), with the autopilot's input RUNNING (``require_armed`` off, five
SERVO_OUTPUT_RAW 10 ms apart read before the first tick; checked to be still RUNNING after the
last) and, separately, with no input (the safe values). Each tick is timed with this thread's
CPU clock (``time.thread_time_ns``). The table gives, per case, the median over the runs of
each run's p50 and p99 µs a tick.

``bench/cpu.py`` measures the running bridge: its loop process's CPU over its 400 ticks a
second (and the inputs between them) divided by the ticks is what a tick costs with a wait
between ticks; this is what it costs without one.
"""

from __future__ import annotations

import argparse
import itertools
import os
import socket
import statistics
import time
from typing import Any

from _common import GROUP, free_port
from _stats import percentile

CASES = ("virtual", "udp_multicast")
PROTOCOLS = {"ckesc": "CKESC 12b", "dronecan": "DroneCAN"}
ESC_IDS = list(range(1, 9))
STREAM_INPUTS = 5  # 10 ms apart, before the first tick


def measure(protocol: str, interface: str, running: bool, ticks: int) -> list[float]:
    """µs of CPU of each of ``ticks`` ticks in a row."""
    from pymavlink import mavutil

    from bridge.config import build_config
    from bridge.daemon.preflight import plan
    from bridge.mavlink.relay import relay_pair
    from bridge.output.autopilot_input import InputSetup
    from bridge.output.mailbox import InputSnapshot, LoopStats, MotorTestBlock, SentCommands
    from bridge.output.output_loop import LoopSetup, OutputLoop
    from bridge.output.safety import LoopState

    link_port = free_port()
    can: dict[str, Any] = {"interface": interface, "channel": "bench-tick"}
    if interface == "udp_multicast":
        can = {"interface": interface, "channel": GROUP}
        can["options"] = {"port": free_port(), "hop_limit": 0}
    raw = {
        "mavlink": {"url": f"udpin:127.0.0.1:{link_port}"},
        "can": can,
        "escs": {"ids": ESC_IDS},
        "mixer": {"name": "passthrough-8"},
        "output": {
            "protocol": protocol,
            "realtime_priority": 0,
            "loop": "thread",
            "require_armed": not running,
            "input_timeout_ms": 1000,  # the one input stays fresh through every tick of a run
        },
        "zenoh": {"enabled": False},
    }
    checked = plan(build_config(raw, "bench"))
    n = len(checked.mixer.outputs)
    loop_end, main_end = relay_pair()
    stats = LoopStats()
    loop = OutputLoop(
        LoopSetup(checked.config, InputSetup(checked.mixer, checked.valid_range, None)),
        MotorTestBlock(n),
        InputSnapshot(n),
        stats,
        loop_end,
        sent=SentCommands(n),
    )
    loop.open()
    autopilot: Any = mavutil.mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    spent: list[float] = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            for _ in range(STREAM_INPUTS if running else 0):
                # A stream, not one input: a stream too slow for the timeout never starts.
                sent_us = time.monotonic_ns() // 1000
                frame = autopilot.servo_output_raw_encode(sent_us & 0xFFFFFFFF, 0, *[1500] * 8)
                sock.sendto(bytes(frame.pack(autopilot)), ("127.0.0.1", link_port))
                time.sleep(0.01)
                loop.read(time.monotonic_ns())
            clock, cpu = time.monotonic_ns, time.thread_time_ns
            for _ in range(ticks):
                now = clock()
                started = cpu()
                loop.tick(now, now)
                spent.append((cpu() - started) / 1000)
            state = LoopState(stats["state"])
            if state != (LoopState.RUNNING if running else LoopState.NO_INPUT):
                raise SystemExit(
                    f"{protocol}, {interface}: the loop was {state.name} at the end of a run"
                )
        finally:
            loop.request_stop()
            loop.close()
            main_end.close()
    return spent


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--ticks", type=int, default=10000, help="ticks in a row per run")
    parser.add_argument("--protocols", nargs="+", choices=PROTOCOLS, default=["ckesc"])
    args = parser.parse_args()
    load = os.getloadavg()[0]
    rows: dict[tuple[str, str, bool], tuple[list[float], list[float]]] = {}
    for _ in range(args.runs):
        for protocol, interface in itertools.product(args.protocols, CASES):
            for running in (True, False):
                spent = measure(protocol, interface, running, args.ticks)
                p50s, p99s = rows.setdefault((protocol, interface, running), ([], []))
                p50s.append(percentile(spent, 0.5))
                p99s.append(percentile(spent, 0.99))
    print(
        f"output loop: CPU µs a tick, 8 ESCs, {args.ticks} ticks in a row; medians over "
        f"{args.runs} runs; load {load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end"
    )
    print(f"{'ESCs':<10}{'bus':<15}{'input':<18}{'p50 µs':>8}{'p99 µs':>8}")
    print("-" * 59)
    for (protocol, interface, running), (p50s, p99s) in rows.items():
        what = "running" if running else "none (safe)"
        print(
            f"{PROTOCOLS[protocol]:<10}{interface:<15}{what:<18}"
            f"{statistics.median(p50s):>8.1f}{statistics.median(p99s):>8.1f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
