"""``esc-bridge esc vesc-scan``: the VESCs on a bus, found by PING (docs/protocols.md §6.6), and
which of them send their status frames. The family's one set-up command: everything else about
a VESC is set in VESC Tool (docs/escs.md). Like the rest of the command line it prints.

Exit status: 0 every VESC answered and sends STATUS 1-5; 1 no answer, a bus error, or a
warning (a shared ID, status frames off); 2 bad arguments.
"""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING, Any, Final

from bridge.escs.tools import BusFlags
from bridge.escs.vesc.records import BROADCAST_ID, Packet

if TYPE_CHECKING:
    from bridge.escs.vesc.setup import FoundVesc

SUMMARY: Final = "VESC scan by PING"
"""What this command does, for ``esc-bridge esc --help``."""

# Exit statuses, as every esc-bridge command's.
_OK: Final = 0
_FAILED: Final = 1


def _controller_id(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        value = -1
    if not 0 <= value < BROADCAST_ID:
        raise argparse.ArgumentTypeError(f"expected a VESC ID 0..{BROADCAST_ID - 1}, got {text!r}")
    return value


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0 < value <= 60:
        raise argparse.ArgumentTypeError(f"expected seconds, above 0 and at most 60, got {text!r}")
    return value


def add_commands(esc_commands: argparse._SubParsersAction[Any], bus_flags: BusFlags) -> None:
    """Add ``vesc-scan`` to the ``esc`` group."""
    parser = esc_commands.add_parser(
        "vesc-scan",
        help="VESC: find the VESCs on the bus by PING, and which send their status frames",
        description="PING every VESC ID (0..254) in turn, list those that answered with their "
        "hardware type and the status frames each sent meanwhile, and warn about VESCs that "
        "share an ID or send no status frames (off from the factory: VESC Tool turns them "
        "on). Exit status 0 all well, 1 no answer, a bus error or a warning, 2 bad arguments.",
    )
    bus_flags.add(
        parser.add_argument_group("CAN bus (as for `esc-bridge run`)"),
        bitrate_help="CAN bit rate: 500000, 500k or 1M (VESC factory: 500k)",
    )
    parser.add_argument(
        "--host-id",
        type=_controller_id,
        default=None,
        metavar="ID",
        help="the ID the PINGs come from, where the answers go (default 254)",
    )
    parser.add_argument(
        "--listen",
        type=_seconds,
        default=None,
        metavar="S",
        help="how long to listen for answers and status frames after the last PING (default 0.5 s)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(handler=lambda args: _scan(args, bus_flags))


def _scan(args: argparse.Namespace, bus_flags: BusFlags) -> int:
    from bridge.escs.vesc.setup import DEFAULT_HOST_ID, DEFAULT_LISTEN_S, scan, scan_warnings

    with bus_flags.open(args) as bus:
        found = scan(
            bus,
            host_id=DEFAULT_HOST_ID if args.host_id is None else args.host_id,
            listen_s=DEFAULT_LISTEN_S if args.listen is None else args.listen,
        )
    warnings = scan_warnings(found)
    if args.json:
        print(json.dumps({"vescs": [_record(vesc) for vesc in found], "warnings": warnings}))
    else:
        print("  id  type        status frames")
        for vesc in found:
            print(f"{vesc.controller_id:>4}  {vesc.hw_name:<10}  {_status_text(vesc)}")
        print(f"{len(found)} VESC{'s' if len(found) != 1 else ''} answered.")
        for warning in warnings:
            print(f"warning: {warning}")
    return _FAILED if warnings else _OK


def _status_text(vesc: FoundVesc) -> str:
    if not vesc.status:
        return "none"
    return ", ".join(Packet(packet).name for packet in sorted(vesc.status))


def _record(vesc: FoundVesc) -> dict[str, Any]:
    return {
        "controller_id": vesc.controller_id,
        "hw_type": vesc.hw_name,
        "answers": vesc.answers,
        "status": [Packet(packet).name for packet in sorted(vesc.status)],
    }
