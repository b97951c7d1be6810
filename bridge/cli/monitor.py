"""``esc-bridge monitor``: the live ESC table, from bridges over Zenoh or from the CAN bus, in
the terminal or (``--web``) as a web page."""

from __future__ import annotations

import argparse
import dataclasses
import signal
import sys
from collections.abc import Callable, Sequence
from typing import Any

from bridge.cli._common import (
    CAN_FLAGS,
    ESC_FLAGS,
    EXIT_OK,
    EXIT_USAGE,
    add_can_flags,
    esc_count,
    flag_overrides,
    id_list,
    int_list,
    merged_config,
    positive_seconds,
    with_flag_names,
)
from bridge.config import BridgeConfig, build_config
from bridge.errors import ConfigError
from bridge.escs import registry

# Flags of the CAN source -> (section, key) of the configuration they override.
MONITOR_CAN_FLAGS: dict[str, tuple[str, str]] = {
    **CAN_FLAGS,
    **ESC_FLAGS,
    "--pole-pairs": ("telemetry", "pole_pairs"),
    "--telemetry-timeout-ms": ("telemetry", "timeout_ms"),
}
MONITOR_ZENOH_FLAGS = ("--prefix", "--connect", "--listen", "--mode", "--no-multicast-scouting")
# Flags that say how to reach the bridges: without them (and without --config), the monitor
# also connects to what runs on this machine unseen by scouting (bridge.monitor.local).
CONNECTION_FLAGS = ("--connect", "--listen", "--mode", "--no-multicast-scouting")


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    monitor = commands.add_parser(
        "monitor",
        help="live table of every ESC, from a bridge over Zenoh or straight from the CAN bus",
        description="Show every ESC's telemetry, refreshed 10 times a second. By default it "
        "comes from the bridges on the network (Zenoh, key <prefix>/esc/status); with CAN "
        "flags (or --source can) it is read from the bus itself, which is never written to. "
        "When stdout is not a terminal, a plain-text table is printed every second instead. "
        "With --web the same is served as a live web page instead, for any number of browsers.",
    )
    monitor.add_argument(
        "--config",
        metavar="FILE",
        help="a bridge configuration: its [zenoh] section (connecting to the endpoints the "
        "bridge listens on), or with --source can its [can], [output] protocol, [escs] and "
        "[telemetry] sections",
    )
    monitor.add_argument(
        "--source",
        choices=("zenoh", "can"),
        default=None,
        help="where the telemetry comes from (default: can when a CAN flag is given, else zenoh)",
    )
    monitor.add_argument(
        "--duration",
        type=positive_seconds,
        default=None,
        metavar="S",
        help="stop after S seconds (default: until Ctrl-C)",
    )
    shown = monitor.add_mutually_exclusive_group()
    shown.add_argument(
        "--plain",
        action="store_true",
        help="print a plain-text table every second even when stdout is a terminal",
    )
    shown.add_argument(
        "--web",
        type=_web_address,
        default=None,
        metavar="[HOST:]PORT",
        help="serve a live, read-only web page of every vehicle on PORT instead of the table, "
        "on 127.0.0.1 (this machine only) unless HOST is given (0.0.0.0 or [::]: every "
        "network this machine is on)",
    )
    zenoh = monitor.add_argument_group("Zenoh source")
    zenoh.add_argument(
        "--prefix",
        type=_key_prefix,
        default=None,
        metavar="KEYEXPR",
        help="key prefix of the bridges to watch (default esc-bridge/*: every vehicle)",
    )
    zenoh.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="connect to this Zenoh endpoint, e.g. tcp/192.168.1.2:7447 (repeatable)",
    )
    zenoh.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="listen on this Zenoh endpoint, e.g. tcp/0.0.0.0:7448 (repeatable)",
    )
    zenoh.add_argument(
        "--mode", choices=("peer", "client"), default=None, help="Zenoh session mode (default peer)"
    )
    zenoh.add_argument(
        "--no-multicast-scouting",
        action="store_true",
        help="do not look for bridges by multicast; use --connect",
    )
    bus = monitor.add_argument_group("CAN source (read only)")
    add_can_flags(bus)
    bus.add_argument(
        "--protocol", choices=registry.names(), help=f"ESC protocol (default {registry.DEFAULT})"
    )
    escs = bus.add_mutually_exclusive_group()
    escs.add_argument(
        "--escs", type=esc_count, metavar="N", help="N ESCs with IDs 1..N, motor 1 first"
    )
    escs.add_argument(
        "--ids",
        type=id_list,
        metavar="ID,ID,...",
        help="the ESCs' IDs on the bus (each family's node or ESC ID), motor 1 first",
    )
    bus.add_argument(
        "--pole-pairs",
        type=_pole_pairs,
        metavar="P[,P,...]",
        help="motor pole pairs, one or one per motor (ESCs that report erpm: rpm = erpm / P; "
        "default 7)",
    )
    bus.add_argument(
        "--telemetry-timeout-ms",
        type=int,
        metavar="MS",
        help="an ESC is offline when no frame came for this long (default 500)",
    )
    monitor.set_defaults(handler=_monitor, monitor_parser=monitor)


def _key_prefix(text: str) -> str:
    from bridge.monitor.sources import check_prefix

    problem = check_prefix(text)
    if problem is not None:
        raise argparse.ArgumentTypeError(f"expected {problem}, got {text!r}")
    return text


def _web_address(text: str) -> tuple[str, int]:
    from bridge.monitor.web import parse_address

    try:
        return parse_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _pole_pairs(text: str) -> int | list[int]:
    pairs = int_list(text, "pole pair counts", "7 or 7,7,14,14")
    return pairs[0] if len(pairs) == 1 else pairs


def _given(args: argparse.Namespace, flags: Sequence[str]) -> list[str]:
    """The ones of ``flags`` on the command line (unset: None, an empty list or False)."""
    given = []
    for flag in flags:
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        if value is not None and value is not False and value != []:
            given.append(flag)
    return given


def monitor_config(args: argparse.Namespace) -> tuple[str, BridgeConfig, str]:
    """What ``monitor`` reads: the source ("zenoh" or "can"), its configuration (defaults <
    --config file < flags) and the Zenoh key prefix to watch.

    For the CAN source the ESC list is filled in: from --escs/--ids, the file's [escs] ids, or
    IDs 1..N for the file's mixer. For the Zenoh source a file's [zenoh] is turned into the
    monitor's side of it (see :func:`bridge.monitor.monitor_zenoh_config`) before the flags.

    Raises:
        ConfigError: a flag or the file is invalid.
        SystemExit: flags of both sources are mixed, or the CAN source has no ESC list.
    """
    from bridge import monitor
    from bridge.config import with_mixer_esc_count

    parser: argparse.ArgumentParser = args.monitor_parser
    can_flags = _given(args, [*MONITOR_CAN_FLAGS, "--escs", "--can-option"])
    zenoh_flags = _given(args, MONITOR_ZENOH_FLAGS)
    source = args.source or ("can" if can_flags else "zenoh")
    if source == "can" and zenoh_flags:
        why = "--source can" if args.source else f"{can_flags[0]} chooses the CAN bus"
        parser.error(f"{zenoh_flags[0]}: a Zenoh option, but {why}")
    if source == "zenoh" and can_flags:
        parser.error(f"{can_flags[0]}: a CAN option, but --source zenoh reads bridges over Zenoh")
    if source == "can" and args.config is None and args.escs is None and args.ids is None:
        parser.error("the CAN source needs the ESCs: --escs N or --ids ID,ID,... (or --config)")

    overrides = flag_overrides(args, MONITOR_CAN_FLAGS)
    flags = dict(MONITOR_CAN_FLAGS)
    zenoh = {"mode": args.mode, "connect": args.connect, "listen": args.listen}
    if args.no_multicast_scouting:
        zenoh["multicast_scouting"] = False
    zenoh = {key: value for key, value in zenoh.items() if value not in (None, [])}
    if zenoh:
        overrides["zenoh"] = zenoh
        flags |= {f"--{key}": ("zenoh", key) for key in ("mode", "connect", "listen")}
    config, raw = merged_config(args, overrides, flags)
    prefix = args.prefix or monitor.DEFAULT_PREFIX
    if raw is not None:
        from_file = build_config(raw, args.config).zenoh
        zconfig = monitor.monitor_zenoh_config(from_file)
        zconfig = dataclasses.replace(zconfig, **{k: getattr(config.zenoh, k) for k in zenoh})
        config = dataclasses.replace(config, zenoh=zconfig)
        prefix = args.prefix or monitor.prefix_of(from_file)
    if source == "can" and not config.escs.ids:
        config = with_mixer_esc_count(config)
    pairs, ids = config.telemetry.pole_pairs, config.escs.ids
    if source == "can" and isinstance(pairs, tuple) and len(pairs) != len(ids):
        where = "--pole-pairs" if args.pole_pairs else f"{config.source}: [telemetry] pole_pairs"
        raise ConfigError(
            f"{where}: {len(pairs)} values for {len(ids)} ESCs; expected one number, or one per ESC"
        )
    return source, config, prefix


def _monitor(args: argparse.Namespace) -> int:
    from bridge import monitor  # rich, and zenoh for that source, only for `monitor`
    from bridge.errors import LinkError

    try:
        source_name, config, prefix = monitor_config(args)
        source: monitor.Source
        if source_name == "can":
            source = monitor.CanSource.open(config)
        else:
            config = _with_local_bridges(args, config)
            try:
                source = monitor.ZenohSource.open(config.zenoh, prefix)
            except ConfigError as exc:
                flags = {f"--{key}": ("zenoh", key) for key in ("connect", "listen")}
                raise exc if args.config else with_flag_names(exc, flags) from None
    except LinkError as exc:
        # Nothing to show without a source: the same exit status as a bad argument.
        print(f"esc-bridge: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return EXIT_OK
    # Ctrl-C from here on is a flag the refresh loop reads, never a KeyboardInterrupt: one
    # raised inside the table's lock leaves it held, and the final table then waits for ever
    # (a monitor that ignored Ctrl-C for 15 s at load 8).
    pressed: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, _frame: pressed.append(signum))
    try:
        if args.web is not None:
            return _monitor_web(source, args.web, args.duration, lambda: bool(pressed))
        if args.plain or not sys.stdout.isatty():
            _monitor_plain(lambda: _monitor_text(source), args.duration, lambda: bool(pressed))
        else:
            _monitor_live(source, args.duration, lambda: bool(pressed))
    finally:
        signal.signal(signal.SIGINT, previous)
        source.close()
    return EXIT_OK


def _with_local_bridges(args: argparse.Namespace, config: BridgeConfig) -> BridgeConfig:
    """``config`` also connecting to the demos running on this machine, when nothing says how
    to reach the bridges (a demo's bridge cannot be scouted for)."""
    from bridge.monitor.local import announced

    if args.config is not None or _given(args, CONNECTION_FLAGS):
        return config
    local = [e for e in announced() if e not in config.zenoh.connect]
    if not local:
        return config
    print(
        f"esc-bridge monitor: also connecting to {', '.join(local)} (esc-bridge demo on this "
        "machine)",
        file=sys.stderr,
    )
    zenoh = dataclasses.replace(config.zenoh, connect=config.zenoh.connect + tuple(local))
    return dataclasses.replace(config, zenoh=zenoh)


def _monitor_web(
    source: Any, address: tuple[str, int], duration: float | None, stopped: Callable[[], bool]
) -> int:
    from bridge import monitor
    from bridge.errors import LinkError
    from bridge.monitor.web import WebMonitor, is_loopback

    host, port = address
    web = WebMonitor(source, host, port)
    try:
        web.start()
    except LinkError as exc:
        print(f"esc-bridge: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        print(f"esc-bridge monitor: {source.where} on {web.url} (read-only; Ctrl-C stops)")
        if not is_loopback(host):
            print(
                f"esc-bridge monitor: served on {host}: anyone who can reach this machine's "
                f"port {web.port} can watch every vehicle's telemetry (there is no password); "
                "nothing on the page can control a vehicle",
                file=sys.stderr,
            )
        sys.stdout.flush()
        for _ in monitor.schedule(monitor.PLAIN_PERIOD_S, duration, stopped):
            pass
    finally:
        web.close()
    return EXIT_OK


def _monitor_text(source: Any) -> str:
    from bridge import monitor

    vehicles = source.vehicles()
    return monitor.plain_text(vehicles) if vehicles else monitor.waiting_text(source.where)


def _monitor_plain(
    text: Callable[[], str], duration: float | None, stopped: Callable[[], bool]
) -> None:
    from bridge import monitor

    # The last one (after --duration or Ctrl-C) is the final table.
    for _ in monitor.schedule(monitor.PLAIN_PERIOD_S, duration, stopped):
        print(text(), end="\n\n", flush=True)


def _monitor_live(source: Any, duration: float | None, stopped: Callable[[], bool]) -> None:
    from rich.console import Console, RenderableType
    from rich.live import Live
    from rich.text import Text

    from bridge import monitor

    def view() -> RenderableType:
        vehicles = source.vehicles()
        if not vehicles:
            return Text(monitor.waiting_text(source.where))
        return monitor.render_table(vehicles)

    with Live(view(), console=Console(), auto_refresh=False) as live:
        for _ in monitor.schedule(monitor.LIVE_PERIOD_S, duration, stopped):
            live.update(view(), refresh=True)
