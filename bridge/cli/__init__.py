"""The ``esc-bridge`` command line: the top parser and the exit statuses of errors.

One module per subcommand adds its parser and handler (``add_parser(commands)``); what several
share is in :mod:`bridge.cli._common`. This package is the only one that prints; the rest of
the bridge logs or returns values. The subcommands load their heavy parts (pymavlink, zenoh,
rich, the simulator, the ESC client) only when they run.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from bridge import __version__
from bridge.cli._common import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE
from bridge.errors import BridgeError, ConfigError
from bridge.escs import registry
from bridge.stopping import StopSignals

__all__ = ["EXIT_FAILED", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_USAGE", "build_parser", "main"]


def main(argv: Sequence[str] | None = None) -> int:
    # Before anything else (the subcommands' imports take a few hundred ms): a SIGTERM or
    # SIGHUP in that time must end `run` in its safe flush, not kill it on the spot.
    stop = StopSignals.install()
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "run":
        args.stop = stop
    else:
        stop.release()
    try:
        result: int = args.handler(args)
    except ConfigError as exc:
        print(f"esc-bridge: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BridgeError as exc:
        print(f"esc-bridge: error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except BrokenPipeError:  # `esc-bridge decode big.log | head` is normal use
        sys.stderr.close()
        return EXIT_OK
    return result


def build_parser() -> argparse.ArgumentParser:
    """The ``esc-bridge`` parser with every subcommand; each sets ``handler`` to its function."""
    parser = argparse.ArgumentParser(
        prog="esc-bridge",
        description=f"Bridge between MAVLink autopilots and CAN-bus ESCs ({registry.titles()}).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    from bridge.cli import decode, demo, esc, monitor, plot, run, sim  # after main's first line

    decode.add_parser(commands)
    run.add_parser(commands)
    monitor.add_parser(commands)
    sim.add_parser(commands)
    demo.add_parser(commands)
    esc.add_parser(commands)
    plot.add_parser(commands)
    from bridge.cli import dialect

    dialect.add_parser(commands)
    return parser
