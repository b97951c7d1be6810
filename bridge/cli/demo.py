"""``esc-bridge demo``: the whole system on this machine, no hardware."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bridge.cli._common import positive_seconds
from bridge.escs import registry


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    demo = commands.add_parser(
        "demo",
        help="the whole system on this machine, no hardware: a simulated flight, live table",
        description="Run the bridge, simulated ESCs and a simulated autopilot flying a scripted "
        "flight (about 30 s: arm, take-off, hover, roll, pitch, yaw, land, disarm), all on "
        "loopback, and show every ESC's telemetry as the monitor does. No configuration "
        "needed. When stdout is not a terminal, a plain-text table is printed every second, "
        "then a summary.",
    )
    demo.add_argument(
        "--protocol",
        choices=registry.names(),
        default=registry.DEFAULT,
        help=f"ESC protocol (default {registry.DEFAULT})",
    )
    demo.add_argument(
        "--airframe",
        choices=("quad", "hex", "octo"),
        default="quad",
        help="X frame, ArduPilot motor order: 4, 6 or 8 ESCs (default quad)",
    )
    demo.add_argument(
        "--duration",
        type=positive_seconds,
        default=None,
        metavar="S",
        help="stop after S seconds, flying the flight again as needed (default: one flight)",
    )
    demo.add_argument(
        "--plain",
        action="store_true",
        help="print a plain-text table every second even when stdout is a terminal",
    )
    demo.add_argument(
        "--record",
        type=Path,
        default=None,
        metavar="DIR",
        help="the bridge records the flight into DIR as `esc-bridge run --record` does (a "
        "candump .log, a .tlog and an .mcap; `esc-bridge plot DIR` draws them)",
    )
    # Flies the same profile faster; for tests.
    demo.add_argument("--time-scale", type=positive_seconds, default=1.0, help=argparse.SUPPRESS)
    demo.set_defaults(handler=_demo)


def _demo(args: argparse.Namespace) -> int:
    # The simulated autopilot, rich and zenoh only for `demo`.
    from bridge.demo import system as demo

    options = demo.DemoOptions(
        protocol=args.protocol,
        airframe=args.airframe,
        duration_s=args.duration,
        plain=args.plain,
        time_scale=args.time_scale,
        record_dir=args.record,
    )
    return demo.run_demo(options, sys.stdout, sys.stderr)
