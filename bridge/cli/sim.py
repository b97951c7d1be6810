"""``esc-bridge sim``: simulated ESCs of any family, each with a motor, on a CAN bus."""

from __future__ import annotations

import argparse
import logging
import sys

from bridge.cli._common import (
    CAN_FLAGS,
    ESC_FLAGS,
    EXIT_OK,
    EXIT_USAGE,
    add_can_flags,
    esc_count,
    flag_overrides,
    id_list,
    merged_config,
    positive_seconds,
)
from bridge.config import BridgeConfig
from bridge.escs import registry

# Flags of `sim` -> (section, key) of the configuration they override.
SIM_FLAGS: dict[str, tuple[str, str]] = {
    **CAN_FLAGS,
    **ESC_FLAGS,
}


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    sim = commands.add_parser(
        "sim",
        help="simulate ESCs of any family (--protocol), each with a motor, on a CAN bus (tests "
        "and demos)",
        description="Put simulated ESCs on a CAN bus: they obey the bridge's commands and send "
        "telemetry as real ones do, from motors and a battery that respond believably. Runs "
        "until Ctrl-C, SIGTERM or --duration, logging a status line every few seconds.",
    )
    sim.add_argument(
        "--config",
        metavar="FILE",
        help="a bridge configuration: its [can], [output] protocol and [escs] ids and "
        "ckesc_channels (without ids: one ESC per output of its mixer)",
    )
    sim.add_argument(
        "--protocol", choices=registry.names(), help=f"ESC protocol (default {registry.DEFAULT})"
    )
    sim.add_argument(
        "--escs", type=esc_count, metavar="N", help="N ESCs, IDs 1..N unless --ids gives them"
    )
    sim.add_argument(
        "--ids",
        type=id_list,
        metavar="ID,ID,...",
        help="the ESCs' IDs on the bus (each family's node or ESC ID), motor 1 first; ESCs that "
        "follow a throttle channel get channels 1..N unless the file's [escs] says otherwise",
    )
    bus = sim.add_argument_group("CAN bus")
    add_can_flags(bus)
    sim.add_argument(
        "--duration",
        type=positive_seconds,
        default=None,
        metavar="S",
        help="stop after S seconds (default: until Ctrl-C or SIGTERM)",
    )
    sim.add_argument(
        "--fault",
        action="append",
        default=[],
        type=_fault_spec,
        metavar="MOTOR:KIND[@SECONDS]",
        help="inject a fault into motor MOTOR's ESC (1..N, the order of the IDs), from the "
        "start or SECONDS in; KIND is over_temperature, over_current, corrupt (bad CRC / tail "
        "byte on its telemetry), silent or stuck_motor; repeatable",
    )
    sim.add_argument(
        "--battery-cells",
        type=_cell_count,
        default=4,
        metavar="N",
        help="LiPo cells in series of the shared battery (default 4)",
    )
    sim.add_argument(
        "--status-interval",
        type=positive_seconds,
        default=5.0,
        metavar="S",
        help="log a status line (rpm of each ESC, battery) every S seconds (default 5)",
    )
    sim.add_argument(
        "--log-level",
        choices=("debug", "info", "warning", "error"),
        default="info",
        help="logging threshold (default info)",
    )
    sim.set_defaults(handler=_sim, sim_parser=sim)


def _fault_spec(text: str) -> tuple[int, str, float, str]:
    """``MOTOR:KIND[@SECONDS]`` -> (motor, kind, seconds, text)."""
    from bridge.sim.runner import FAULT_KINDS

    expected = f"MOTOR:KIND[@SECONDS] with KIND one of {', '.join(FAULT_KINDS)}"
    motor_text, sep, rest = text.partition(":")
    kind, at, seconds_text = rest.partition("@")
    try:
        motor = int(motor_text)
        seconds = float(seconds_text) if at else 0.0
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
    if not sep or motor < 1 or kind not in FAULT_KINDS:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    if not 0 <= seconds < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a time in seconds >= 0 after @, got {text!r}")
    return motor, kind, seconds, text


def _cell_count(text: str) -> int:
    try:
        cells = int(text)
    except ValueError:
        cells = 0
    if not 1 <= cells <= 14:
        raise argparse.ArgumentTypeError(f"expected a number of cells 1..14, got {text!r}")
    return cells


def sim_config(args: argparse.Namespace) -> BridgeConfig:
    """The configuration ``sim`` runs: defaults < --config file < flags, with the ESC list
    filled in (from --escs/--ids, the file's [escs] ids, or 1..N for the file's mixer).

    Raises:
        ConfigError: a flag or the file is invalid.
        SystemExit: no ESC list, or --escs and --ids disagree.
    """
    from bridge.config import with_esc_count, with_mixer_esc_count

    parser: argparse.ArgumentParser = args.sim_parser
    if args.escs is not None and args.ids is not None and len(args.ids) != args.escs:
        parser.error(f"--ids: {len(args.ids)} IDs, but --escs {args.escs}; expected one per ESC")
    if args.config is None and args.escs is None and args.ids is None:
        parser.error("the ESCs are needed: --escs N or --ids ID,ID,... (or --config)")
    config, _ = merged_config(args, flag_overrides(args, SIM_FLAGS), SIM_FLAGS)
    if config.escs.ids:
        return with_esc_count(config, len(config.escs.ids))
    return with_mixer_esc_count(config)


def _sim(args: argparse.Namespace) -> int:
    import signal
    import time

    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s esc-bridge sim %(message)s"
    )
    from bridge.can_io import open_bus  # python-can and the models only for `sim`
    from bridge.errors import LinkError
    from bridge.sim.motor import Battery
    from bridge.sim.runner import ScheduledFault, Simulator, make_escs

    config = sim_config(args)
    protocol, ids = config.output.protocol, list(config.escs.ids)
    faults = []
    for motor, kind, seconds, text in args.fault:
        if motor > len(ids):
            args.sim_parser.error(
                f"--fault {text}: motor {motor}, but there are {len(ids)} ESCs "
                f"(motors 1..{len(ids)})"
            )
        faults.append(ScheduledFault(ids[motor - 1], kind, seconds))
    escs = make_escs(protocol, len(ids), ids, keys=config.esc_setup.keys)
    try:
        bus = open_bus(config.can, config.bitrate)
    except LinkError as exc:
        print(f"esc-bridge: {exc}", file=sys.stderr)
        return EXIT_USAGE
    log = logging.getLogger("bridge.sim")
    # SIGTERM and Ctrl-C are a flag the loop below reads: a KeyboardInterrupt raised inside a
    # lock of the simulator's leaves it held (the sim once ignored Ctrl-C for 10 s at load 8),
    # and Event.set() from a handler can deadlock on the Event's own lock.
    stopped: list[int] = []
    previous = {
        sig: signal.signal(sig, lambda signum, _frame: stopped.append(signum))
        for sig in (signal.SIGTERM, signal.SIGINT)
    }
    sim = Simulator(
        bus, escs, battery=Battery(cells=args.battery_cells), faults=faults, own_bus=True
    )
    try:
        sim.start()
        log.info(
            "%d %s ESCs (IDs %s) on %s %s",
            len(ids),
            protocol,
            ",".join(map(str, ids)),
            config.can.interface,
            config.can.channel,
        )
        start = time.monotonic()
        end = None if args.duration is None else start + args.duration
        next_status = start + args.status_interval
        while not stopped and sim.running:
            now = time.monotonic()
            if end is not None and now >= end:
                break
            if now >= next_status:
                log.info("%s", sim.status_line())
                next_status = max(next_status + args.status_interval, now)
            time.sleep(max(0.0, min(0.1, next_status - now, (end or next_status) - now)))
    finally:
        sim.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    log.info("stopped: %s", sim.status_line())
    if sim.error is not None:
        print(f"esc-bridge: error: simulator stopped: {sim.error}", file=sys.stderr)
        return 1
    return EXIT_OK
