"""The ``esc-bridge`` command line. The only module that prints; the rest log or return values."""

from __future__ import annotations

import argparse
import dataclasses
import enum
import json
import logging
import sys
from collections.abc import Callable, Sequence
from typing import Any

from bridge import __version__
from bridge.capture import BadLine, CaptureItem, CaptureSummary, DecodedFrame, decode_capture
from bridge.config import BridgeConfig, build_config, merge, read_config_file
from bridge.errors import BridgeError, ConfigError

EXIT_OK = 0
EXIT_USAGE = 2  # what argparse uses for bad arguments; a bad config is the same kind of mistake


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        result: int = args.handler(args)
    except ConfigError as exc:
        print(f"esc-bridge: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BridgeError as exc:
        print(f"esc-bridge: error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # `esc-bridge decode big.log | head` is normal use
        sys.stderr.close()
        return EXIT_OK
    return result


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="esc-bridge",
        description="Bridge between MAVLink autopilots and CAN-bus ESCs (CKESC, Flipsky FT).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    decode = commands.add_parser(
        "decode",
        help="decode a CAN capture (candump -L .log, .asc, .blf, .csv, .trc, .mf4, .db)",
        description="Decode a CAN capture into one line per frame, then a summary.",
    )
    decode.add_argument("file", help="the capture; its format is taken from the file suffix")
    decode.add_argument(
        "--protocol",
        choices=("auto", "ckesc", "ft"),
        default="auto",
        help="decode every frame as this protocol (default: by each frame's CAN ID space)",
    )
    decode.add_argument(
        "--nodes",
        type=_node_list,
        default=None,
        metavar="N,N,...",
        help="CKESC node IDs of your ESCs: frames from other nodes that reuse CKESC type IDs "
        "(other vendors' DroneCAN messages) are then reported as not understood",
    )
    decode.add_argument("--json", action="store_true", help="print JSON lines instead of text")
    decode.set_defaults(handler=_decode)

    run = commands.add_parser(
        "run",
        help="run the bridge: MAVLink motor outputs to CAN ESC commands, safe by default",
        description="Run the bridge. Without --config, the defaults plus these flags make a "
        "working bridge (passthrough mixer, one ESC per output, IDs 1..N).",
    )
    run.add_argument("--config", metavar="FILE", help="TOML configuration (see config/README.md)")
    _add_run_overrides(run)
    run.add_argument(
        "--log-level",
        choices=("debug", "info", "warning", "error"),
        default="info",
        help="logging threshold (default info)",
    )
    run.add_argument(
        "--record",
        metavar="DIR",
        help="record every CAN frame sent and received (candump .log) and the MAVLink traffic "
        "(.tlog) into DIR",
    )
    run.add_argument(
        "--check",
        action="store_true",
        help="validate the configuration, print the plan and bus load, and exit",
    )
    run.set_defaults(handler=_run)
    _add_monitor(commands)
    _add_sim(commands)
    _add_demo(commands)
    _add_esc(commands)
    return parser


# --flag -> (section, key, type) for the settings people change most.
RUN_OVERRIDES: dict[str, tuple[str, str, Callable[[str], Any], str]] = {
    "--mavlink": ("mavlink", "url", str, "autopilot connection (pymavlink URL)"),
    "--source": ("mavlink", "source", str, "MAVLink message with the motor outputs"),
    "--can-interface": ("can", "interface", str, "python-can interface (default socketcan)"),
    "--can-channel": ("can", "channel", str, "python-can channel (default can0)"),
    "--bitrate": ("can", "bitrate", int, "CAN bit rate, bit/s"),
    "--protocol": ("output", "protocol", str, "ESC protocol: ckesc or ft"),
    "--rate": ("output", "rate_hz", int, "command rate per ESC, Hz"),
    "--latency": ("output", "latency", str, "fixed or immediate"),
    "--mixer": ("mixer", "name", str, "bundled mixer name or mixer .toml path"),
    "--vehicle": ("zenoh", "vehicle", str, "vehicle name in the Zenoh keys (default host name)"),
}


RUN_METAVARS = {
    "--mavlink": "URL",
    "--source": "MESSAGE",
    "--can-interface": "NAME",
    "--can-channel": "CHANNEL",
    "--bitrate": "BPS",
    "--protocol": "ckesc|ft",
    "--rate": "HZ",
    "--latency": "fixed|immediate",
    "--mixer": "NAME|FILE",
    "--vehicle": "NAME",
}


def _add_run_overrides(parser: argparse.ArgumentParser) -> None:
    for flag, (section, key, kind, text) in RUN_OVERRIDES.items():
        parser.add_argument(
            flag,
            type=kind,
            default=None,
            metavar=RUN_METAVARS.get(flag, "VALUE"),
            help=f"{text} ([{section}] {key})",
        )
    parser.add_argument(
        "--can-option",
        action="append",
        default=[],
        type=_can_option,
        metavar="KEY=VALUE",
        help="extra python-can interface argument, repeatable (e.g. port=43113)",
    )
    parser.add_argument(
        "--zenoh-connect",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh endpoint to connect to, repeatable (e.g. tcp/192.168.1.2:7447) "
        "([zenoh] connect)",
    )
    parser.add_argument(
        "--zenoh-listen",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh endpoint to listen on, repeatable (e.g. tcp/0.0.0.0:7447) ([zenoh] listen)",
    )
    parser.add_argument(
        "--no-zenoh-scouting",
        dest="zenoh_scouting",
        action="store_false",
        default=None,
        help="do not look for Zenoh peers by multicast ([zenoh] multicast_scouting = false)",
    )
    parser.add_argument(
        "--no-zenoh",
        dest="zenoh_enabled",
        action="store_false",
        default=None,
        help="do not publish over Zenoh ([zenoh] enabled = false)",
    )


def _can_option(text: str) -> tuple[str, Any]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"{text!r}: expected KEY=VALUE, e.g. port=43113")
    parsed: Any = value
    if value.lower() in ("true", "false"):
        parsed = value.lower() == "true"
    else:
        for kind in (int, float):
            try:
                parsed = kind(value)
                break
            except ValueError:
                continue
    return key, parsed


def run_config(args: argparse.Namespace) -> BridgeConfig:
    """The configuration for ``run``: defaults < --config file < command-line flags.

    Raises:
        ConfigError: a flag or the file is invalid.
    """
    overrides: dict[str, dict[str, Any]] = {}
    for flag, (section, key, _, _) in RUN_OVERRIDES.items():
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        if value is not None:
            overrides.setdefault(section, {})[key] = value
    if args.can_option:
        overrides.setdefault("can", {})["options"] = dict(args.can_option)
    zenoh_flags = {
        "connect": args.zenoh_connect,
        "listen": args.zenoh_listen,
        "multicast_scouting": args.zenoh_scouting,
        "enabled": args.zenoh_enabled,
    }
    for key, value in zenoh_flags.items():
        if value is not None:
            overrides.setdefault("zenoh", {})[key] = value
    # The flags alone first, so that a bad flag is reported as the flag it is.
    try:
        build_config(overrides, "command line")
    except ConfigError as exc:
        text = str(exc)
        for flag, (section, key, _, _) in RUN_OVERRIDES.items():
            text = text.replace(f"[{section}] {key}:", f"{flag}:")
        for key, flag in (("connect", "--zenoh-connect"), ("listen", "--zenoh-listen")):
            text = text.replace(f"[zenoh] {key}:", f"{flag}:")
        raise ConfigError(text.replace("[can] options:", "--can-option:")) from None
    if args.config is None:
        return build_config(overrides, "command line")
    raw = read_config_file(args.config)
    if "options" in overrides.get("can", {}):
        file_options = raw.get("can", {}).get("options", {})
        if isinstance(file_options, dict):
            overrides["can"]["options"] = file_options | overrides["can"]["options"]
    return build_config(merge(raw, overrides), args.config)


def _run(args: argparse.Namespace) -> int:
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s esc-bridge %(message)s"
    )
    # pymavlink logs every new stream and replayed timestamp at INFO; the link counts those.
    logging.getLogger("pymavlink").setLevel(logging.WARNING)
    from bridge import daemon  # pymavlink and the loop are only loaded for `run`

    config = run_config(args)
    if args.check:
        checked = daemon.plan(config)
        print(f"{config.source}: OK")
        print(f"  mixer {checked.mixer.name}: {len(checked.mixer.outputs)} outputs")
        print(f"  {checked.load_text}")
        return EXIT_OK
    return daemon.run(config, record_dir=args.record)


def _node_list(text: str) -> frozenset[int]:
    try:
        nodes = frozenset(int(part, 0) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a comma-separated list of node IDs (e.g. 1,2,3,4)"
        ) from None
    if not all(1 <= node <= 0x7D for node in nodes):
        raise argparse.ArgumentTypeError(f"node IDs must be 1..125, got {text!r}")
    return nodes


def _decode(args: argparse.Namespace) -> int:
    summary = CaptureSummary()
    show = _json_line if args.json else _text_line
    for item in decode_capture(args.file, args.protocol, args.nodes):
        summary.add(item)
        print(show(item))
    if args.json:
        print(json.dumps({"summary": summary.as_dict()}))
    else:
        print(_summary_text(summary))
    return EXIT_OK


def _text_line(item: CaptureItem) -> str:
    if isinstance(item, BadLine):
        return f"line {item.line_no}: not a frame ({item.reason}): {item.text!r}"
    msg = item.msg
    head = f"{msg.timestamp:14.6f}  {msg.arbitration_id:08X}  {msg.data.hex(' '):<23}"
    if isinstance(item, DecodedFrame):
        fields = " ".join(f"{k}={_text_value(v)}" for k, v in _message_fields(item))
        return f"{head}  {item.protocol:<5} node {item.frame.node_id:<3} {item.type_name}  {fields}"
    if item.error is None:
        return f"{head}  not understood"
    return f"{head}  {item.protocol:<5} {type(item.error).__name__}: {item.error}"


def _json_line(item: CaptureItem) -> str:
    if isinstance(item, BadLine):
        record: dict[str, Any] = {
            "line": item.line_no,
            "error": "BadLine",
            "detail": item.reason,
            "text": item.text,
        }
        return json.dumps(record)
    msg = item.msg
    record = {
        "t": msg.timestamp,
        "can_id": f"0x{msg.arbitration_id:08X}",
        "data": msg.data.hex(),
        "protocol": item.protocol,
    }
    if isinstance(item, DecodedFrame):
        envelope = {
            f.name: _json_value(getattr(item.frame, f.name))
            for f in dataclasses.fields(item.frame)
            if f.name != "message"
        }
        record |= {
            "node": item.frame.node_id,
            "type": item.type_name,
            **envelope,
            "fields": {k: _json_value(v) for k, v in _message_fields(item)},
        }
    elif item.error is None:
        record["error"] = "NotOurs"
    else:
        record |= {"error": type(item.error).__name__, "detail": str(item.error)}
    return json.dumps(record)


def _message_fields(item: DecodedFrame) -> list[tuple[str, Any]]:
    message = item.frame.message
    return [(f.name, getattr(message, f.name)) for f in dataclasses.fields(message)]


def _text_value(value: Any) -> str:
    if isinstance(value, enum.Flag):
        return "|".join(_flag_names(value)) or "0"
    if isinstance(value, enum.Enum):
        return str(value.name)
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, bytes | bytearray):
        return value.hex(" ") if value else "-"
    if isinstance(value, tuple):
        return ",".join(_text_value(v) for v in value)
    return str(value)


def _json_value(value: Any) -> Any:
    if isinstance(value, enum.Flag):
        return _flag_names(value)
    if isinstance(value, enum.Enum):
        return value.name
    if isinstance(value, bytes | bytearray):
        return value.hex()
    if isinstance(value, tuple):
        return [_json_value(v) for v in value]
    return value


def _flag_names(value: enum.Flag) -> list[str]:
    names = [member.name or "" for member in value]
    # Bits the protocol does not name are shown as a number rather than dropped.
    unnamed = int(value) & ~sum(int(member) for member in value)  # type: ignore[call-overload]
    return [*names, hex(unnamed)] if unnamed else names


def _summary_text(summary: CaptureSummary) -> str:
    lines = [f"-- {summary.frames} frames"]
    lines += [f"   {count:8d}  {name}" for name, count in sorted(summary.by_type.items())]
    lines.append(f"   {summary.not_ours:8d}  not understood (another protocol)")
    for name, count in sorted(summary.errors.items()):
        lines.append(f"   {count:8d}  {name}")
    crc = summary.errors.get("CrcError", 0)
    lines.append(f"-- CRC errors: {crc}; malformed lines skipped: {summary.bad_lines}")
    return "\n".join(lines)


# -- monitor ---------------------------------------------------------------------------------

# Flags of the CAN source -> (section, key) of the configuration they override.
MONITOR_CAN_FLAGS: dict[str, tuple[str, str]] = {
    "--can-interface": ("can", "interface"),
    "--can-channel": ("can", "channel"),
    "--bitrate": ("can", "bitrate"),
    "--protocol": ("output", "protocol"),
    "--ids": ("escs", "ids"),
    "--pole-pairs": ("telemetry", "pole_pairs"),
    "--telemetry-timeout-ms": ("telemetry", "timeout_ms"),
}
MONITOR_ZENOH_FLAGS = ("--prefix", "--connect", "--listen", "--mode", "--no-multicast-scouting")


def _add_monitor(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    monitor = commands.add_parser(
        "monitor",
        help="live table of every ESC, from a bridge over Zenoh or straight from the CAN bus",
        description="Show every ESC's telemetry, refreshed 10 times a second. By default it "
        "comes from the bridges on the network (Zenoh, key <prefix>/esc/status); with CAN "
        "flags (or --source can) it is read from the bus itself, which is never written to. "
        "When stdout is not a terminal, a plain-text table is printed every second instead.",
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
        type=_seconds,
        default=None,
        metavar="S",
        help="stop after S seconds (default: until Ctrl-C)",
    )
    monitor.add_argument(
        "--plain",
        action="store_true",
        help="print a plain-text table every second even when stdout is a terminal",
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
    bus.add_argument("--can-interface", metavar="NAME", help="python-can interface (socketcan)")
    bus.add_argument("--can-channel", metavar="CHANNEL", help="python-can channel (can0)")
    bus.add_argument(
        "--can-option",
        action="append",
        default=[],
        type=_can_option,
        metavar="KEY=VALUE",
        help="extra python-can interface argument, repeatable (e.g. port=43113)",
    )
    bus.add_argument("--bitrate", type=int, metavar="BPS", help="CAN bit rate, bit/s")
    bus.add_argument("--protocol", choices=("ckesc", "ft"), help="ESC protocol (default ckesc)")
    escs = bus.add_mutually_exclusive_group()
    escs.add_argument(
        "--escs", type=_esc_count, metavar="N", help="N ESCs with IDs 1..N, motor 1 first"
    )
    escs.add_argument(
        "--ids",
        type=_id_list,
        metavar="ID,ID,...",
        help="the ESCs' CKESC node IDs / FT ESC IDs, motor 1 first",
    )
    bus.add_argument(
        "--pole-pairs",
        type=_pole_pairs,
        metavar="P[,P,...]",
        help="motor pole pairs, one or one per motor (FT: rpm = erpm / P; default 7)",
    )
    bus.add_argument(
        "--telemetry-timeout-ms",
        type=int,
        metavar="MS",
        help="an ESC is offline when no frame came for this long (default 500)",
    )
    monitor.set_defaults(handler=_monitor, monitor_parser=monitor)


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a number of seconds > 0, got {text!r}")
    return value


def _key_prefix(text: str) -> str:
    from bridge.monitor.sources import check_prefix

    problem = check_prefix(text)
    if problem is not None:
        raise argparse.ArgumentTypeError(f"expected {problem}, got {text!r}")
    return text


def _esc_count(text: str) -> int:
    try:
        count = int(text)
    except ValueError:
        count = 0
    if not 1 <= count <= 125:
        raise argparse.ArgumentTypeError(f"expected a number of ESCs 1..125, got {text!r}")
    return count


def _int_list(text: str, what: str, example: str) -> list[int]:
    try:
        return [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a comma-separated list of {what} (e.g. {example}), got {text!r}"
        ) from None


def _id_list(text: str) -> list[int]:
    return _int_list(text, "ESC IDs", "1,2,3,4")


def _pole_pairs(text: str) -> int | list[int]:
    pairs = _int_list(text, "pole pair counts", "7 or 7,7,14,14")
    return pairs[0] if len(pairs) == 1 else pairs


def _given(args: argparse.Namespace, flags: Sequence[str]) -> list[str]:
    """The ones of ``flags`` on the command line (unset: None, an empty list or False)."""
    given = []
    for flag in flags:
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        if value is not None and value is not False and value != []:
            given.append(flag)
    return given


def _with_flag_names(exc: ConfigError, flags: dict[str, tuple[str, str]]) -> ConfigError:
    text = str(exc)
    for flag, (section, key) in flags.items():
        text = text.replace(f"[{section}] {key}:", f"{flag}:")
    return ConfigError(text.replace("[can] options:", "--can-option:"))


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
    from bridge.config import with_esc_count

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

    overrides: dict[str, dict[str, Any]] = {}
    flags = dict(MONITOR_CAN_FLAGS)
    for flag, (section, key) in MONITOR_CAN_FLAGS.items():
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        if value is not None:
            overrides.setdefault(section, {})[key] = value
    if args.escs is not None:
        overrides.setdefault("escs", {})["ids"] = list(range(1, args.escs + 1))
    if args.can_option:
        overrides.setdefault("can", {})["options"] = dict(args.can_option)
    zenoh = {"mode": args.mode, "connect": args.connect, "listen": args.listen}
    if args.no_multicast_scouting:
        zenoh["multicast_scouting"] = False
    zenoh = {key: value for key, value in zenoh.items() if value not in (None, [])}
    if zenoh:
        overrides["zenoh"] = zenoh
        flags |= {f"--{key}": ("zenoh", key) for key in ("mode", "connect", "listen")}
    try:
        config = build_config(overrides, "command line")  # the flags alone name themselves
    except ConfigError as exc:
        raise _with_flag_names(exc, flags) from None
    prefix = args.prefix or monitor.DEFAULT_PREFIX
    if args.config is not None:
        raw = read_config_file(args.config)
        if "options" in overrides.get("can", {}):
            file_options = raw.get("can", {}).get("options", {})
            if isinstance(file_options, dict):
                overrides["can"]["options"] = file_options | overrides["can"]["options"]
        config = build_config(merge(raw, overrides), args.config)
        from_file = build_config(raw, args.config).zenoh
        zconfig = monitor.monitor_zenoh_config(from_file)
        zconfig = dataclasses.replace(zconfig, **{k: getattr(config.zenoh, k) for k in zenoh})
        config = dataclasses.replace(config, zenoh=zconfig)
        prefix = args.prefix or monitor.prefix_of(from_file)
    if source == "can" and not config.escs.ids:
        from bridge.mixer import load_mixer

        config = with_esc_count(config, len(load_mixer(config.mixer.name).outputs))
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
            try:
                source = monitor.ZenohSource.open(config.zenoh, prefix)
            except ConfigError as exc:
                flags = {f"--{key}": ("zenoh", key) for key in ("connect", "listen")}
                raise exc if args.config else _with_flag_names(exc, flags) from None
    except LinkError as exc:
        # Nothing to show without a source: the same exit status as a bad argument.
        print(f"esc-bridge: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return EXIT_OK
    try:
        if args.plain or not sys.stdout.isatty():
            _monitor_plain(lambda: _monitor_text(source), args.duration)
        else:
            _monitor_live(source, args.duration)
    finally:
        source.close()
    return EXIT_OK


def _monitor_text(source: Any) -> str:
    from bridge import monitor

    vehicles = source.vehicles()
    return monitor.plain_text(vehicles) if vehicles else monitor.waiting_text(source.where)


def _monitor_plain(text: Callable[[], str], duration: float | None) -> None:
    from bridge import monitor

    try:
        for _ in monitor.schedule(monitor.PLAIN_PERIOD_S, duration):
            print(text(), end="\n\n", flush=True)
    except KeyboardInterrupt:
        print(text(), flush=True)  # Ctrl-C: the final table, as at the end of --duration


def _monitor_live(source: Any, duration: float | None) -> None:
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
        try:
            for _ in monitor.schedule(monitor.LIVE_PERIOD_S, duration):
                live.update(view(), refresh=True)
        except KeyboardInterrupt:
            live.update(view(), refresh=True)


# -- sim -------------------------------------------------------------------------------------

# Flags of `sim` -> (section, key) of the configuration they override.
SIM_FLAGS: dict[str, tuple[str, str]] = {
    "--can-interface": ("can", "interface"),
    "--can-channel": ("can", "channel"),
    "--bitrate": ("can", "bitrate"),
    "--protocol": ("output", "protocol"),
    "--ids": ("escs", "ids"),
}


def _add_sim(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    sim = commands.add_parser(
        "sim",
        help="simulate CKESC or FT ESCs, each with a motor, on a CAN bus (tests and demos)",
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
    sim.add_argument("--protocol", choices=("ckesc", "ft"), help="ESC protocol (default ckesc)")
    sim.add_argument(
        "--escs", type=_esc_count, metavar="N", help="N ESCs, IDs 1..N unless --ids gives them"
    )
    sim.add_argument(
        "--ids",
        type=_id_list,
        metavar="ID,ID,...",
        help="the ESCs' CKESC node IDs / FT ESC IDs, motor 1 first (CKESC throttle channels "
        "are 1..N, or the file's [escs] ckesc_channels)",
    )
    bus = sim.add_argument_group("CAN bus")
    bus.add_argument("--can-interface", metavar="NAME", help="python-can interface (socketcan)")
    bus.add_argument("--can-channel", metavar="CHANNEL", help="python-can channel (can0)")
    bus.add_argument(
        "--can-option",
        action="append",
        default=[],
        type=_can_option,
        metavar="KEY=VALUE",
        help="extra python-can interface argument, repeatable (e.g. port=43113)",
    )
    bus.add_argument("--bitrate", type=int, metavar="BPS", help="CAN bit rate, bit/s")
    sim.add_argument(
        "--duration",
        type=_seconds,
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
        type=_seconds,
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
    from bridge.config import with_esc_count

    parser: argparse.ArgumentParser = args.sim_parser
    if args.escs is not None and args.ids is not None and len(args.ids) != args.escs:
        parser.error(f"--ids: {len(args.ids)} IDs, but --escs {args.escs}; expected one per ESC")
    if args.config is None and args.escs is None and args.ids is None:
        parser.error("the ESCs are needed: --escs N or --ids ID,ID,... (or --config)")
    overrides: dict[str, dict[str, Any]] = {}
    for flag, (section, key) in SIM_FLAGS.items():
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        if value is not None:
            overrides.setdefault(section, {})[key] = value
    if args.escs is not None and args.ids is None:
        overrides.setdefault("escs", {})["ids"] = list(range(1, args.escs + 1))
    if args.can_option:
        overrides.setdefault("can", {})["options"] = dict(args.can_option)
    try:
        config = build_config(overrides, "command line")  # the flags alone name themselves
    except ConfigError as exc:
        raise _with_flag_names(exc, SIM_FLAGS) from None
    if args.config is not None:
        raw = read_config_file(args.config)
        if "options" in overrides.get("can", {}):
            file_options = raw.get("can", {}).get("options", {})
            if isinstance(file_options, dict):
                overrides["can"]["options"] = file_options | overrides["can"]["options"]
        config = build_config(merge(raw, overrides), args.config)
    count = len(config.escs.ids)
    if not count:
        from bridge.mixer import load_mixer

        count = len(load_mixer(config.mixer.name).outputs)
    return with_esc_count(config, count)


def _sim(args: argparse.Namespace) -> int:
    import signal
    import threading
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
    channels = list(config.escs.ckesc_channels) if protocol == "ckesc" else None
    escs = make_escs(protocol, len(ids), ids, channels=channels)
    try:
        bus = open_bus(config.can, config.bitrate)
    except LinkError as exc:
        print(f"esc-bridge: {exc}", file=sys.stderr)
        return EXIT_USAGE
    log = logging.getLogger("bridge.sim")
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
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
        while not stop.is_set() and sim.running:
            now = time.monotonic()
            if end is not None and now >= end:
                break
            if now >= next_status:
                log.info("%s", sim.status_line())
                next_status = max(next_status + args.status_interval, now)
            stop.wait(min(0.1, next_status - now, (end or next_status) - now))
    except KeyboardInterrupt:
        pass
    finally:
        sim.close()
        signal.signal(signal.SIGTERM, previous)
    log.info("stopped: %s", sim.status_line())
    if sim.error is not None:
        print(f"esc-bridge: error: simulator stopped: {sim.error}", file=sys.stderr)
        return 1
    return EXIT_OK


# -- demo ------------------------------------------------------------------------------------


def _add_demo(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
        "--protocol", choices=("ckesc", "ft"), default="ckesc", help="ESC protocol (default ckesc)"
    )
    demo.add_argument(
        "--airframe",
        choices=("quad", "hex", "octo"),
        default="quad",
        help="X frame, ArduPilot motor order: 4, 6 or 8 ESCs (default quad)",
    )
    demo.add_argument(
        "--duration",
        type=_seconds,
        default=None,
        metavar="S",
        help="stop after S seconds, flying the flight again as needed (default: one flight)",
    )
    demo.add_argument(
        "--plain",
        action="store_true",
        help="print a plain-text table every second even when stdout is a terminal",
    )
    # Flies the same profile faster; for tests.
    demo.add_argument("--time-scale", type=_seconds, default=1.0, help=argparse.SUPPRESS)
    demo.set_defaults(handler=_demo)


def _demo(args: argparse.Namespace) -> int:
    from bridge import demo  # the simulated autopilot, rich and zenoh only for `demo`

    options = demo.DemoOptions(
        protocol=args.protocol,
        airframe=args.airframe,
        duration_s=args.duration,
        plain=args.plain,
        time_scale=args.time_scale,
    )
    return demo.run_demo(options, sys.stdout, sys.stderr)


# -- esc -------------------------------------------------------------------------------------


def _add_esc(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from bridge import esc_cli  # the commands' parsers; each handler loads the client itself

    esc = commands.add_parser(
        "esc",
        help="set up and test ESCs: CKESC scan, node ID and channel, LED, direction, rates, "
        "self tests; a motor test (spin) for CKESC and FT",
        description="Talk to ESCs over any python-can bus. The CKESC set-up commands wait for "
        "the ESC's answer (--timeout) and check it; `spin` runs one motor (CKESC or FT). Exit "
        "status 0 done, 1 no answer, refused or bus error, 2 bad arguments (out-of-range "
        "values are refused before anything is sent).",
    )
    esc_commands = esc.add_subparsers(dest="esc_command", required=True, metavar="ESC_COMMAND")
    esc_cli.add_esc_scan(esc_commands)
    esc_cli.add_esc_set_id(esc_commands)
    esc_cli.add_esc_baud(esc_commands)
    esc_cli.add_esc_led(esc_commands)
    esc_cli.add_esc_rotation(esc_commands)
    esc_cli.add_esc_report_rate(esc_commands)
    esc_cli.add_esc_throttle_source(esc_commands)
    esc_cli.add_esc_self_test(esc_commands)
    esc_cli.add_esc_expand(esc_commands)
    esc_cli.add_esc_info(esc_commands)
    esc_cli.add_esc_maintenance(esc_commands)
    esc_cli.add_esc_config(esc_commands)
    esc_cli.add_esc_reports(esc_commands)
    esc_cli.add_esc_can_test(esc_commands)
    _add_esc_spin(esc_commands)  # CKESC and FT: its own bus flags, as for `run`


# -- esc spin --------------------------------------------------------------------------------

# Flags of `esc spin` -> (section, key) of the configuration they override, as for `run`.
SPIN_FLAGS: dict[str, tuple[str, str]] = {
    "--can-interface": ("can", "interface"),
    "--can-channel": ("can", "channel"),
    "--bitrate": ("can", "bitrate"),
    "--protocol": ("output", "protocol"),
    "--mixer": ("mixer", "name"),
}
EXIT_INTERRUPTED = 130  # Ctrl-C or SIGTERM ended a spin (after its safe values)
PROPS_WARNING = (
    "refusing to spin without --props-removed: a motor spinning with its propeller on can "
    "cut fingers and throw the vehicle off the bench. Take every propeller off, then add "
    "--props-removed to say so"
)


def _add_esc_spin(esc_commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    spin = esc_commands.add_parser(
        "spin",
        help="spin one motor for a few seconds to check it, PROPELLERS OFF (CKESC or FT)",
        description="Spin one motor with its propeller removed, to check its direction, "
        "wiring and ESC: ramp up to --throttle over 0.5 s, hold, ramp down, stop at --seconds "
        "whatever happens, then send safe values to every ESC; the other motors get safe "
        "values throughout. The frames are the bridge's own (its drivers, rate and limits), "
        "so do not run this while `esc-bridge run` drives the same bus. Ctrl-C or SIGTERM "
        "stops the motor at once (safe values, then exit status 130).",
    )
    spin.add_argument(
        "--motor",
        type=_motor_number,
        required=True,
        metavar="N",
        help="the motor: 1..N in the mixer's output order (the N-th of [escs] ids)",
    )
    spin.add_argument(
        "--throttle",
        type=_percent,
        required=True,
        metavar="P",
        help="percent 0..100 of the ESC's full range: CKESC throttle 2000 (10b: 1000); FT "
        "ft_max_current_a, 100 %%, ft_max_duty or ft_max_erpm by ft_mode; never above the "
        "mixer output's max",
    )
    spin.add_argument(
        "--seconds",
        type=_spin_seconds,
        required=True,
        metavar="S",
        help="hard time limit, ramps included: 1..30",
    )
    spin.add_argument(
        "--props-removed",
        action="store_true",
        help="required: you confirm that every propeller is off",
    )
    spin.add_argument(
        "--config",
        metavar="FILE",
        help="a bridge configuration: its [can], [output] (protocol, rate, shutdown_flush_ms), "
        "[mixer] and [escs]",
    )
    bus = spin.add_argument_group("CAN bus and ESCs (as for `esc-bridge run`)")
    bus.add_argument("--can-interface", metavar="NAME", help="python-can interface (socketcan)")
    bus.add_argument("--can-channel", metavar="CHANNEL", help="python-can channel (can0)")
    bus.add_argument(
        "--can-option",
        action="append",
        default=[],
        type=_can_option,
        metavar="KEY=VALUE",
        help="extra python-can interface argument, repeatable (e.g. port=43113)",
    )
    bus.add_argument("--bitrate", type=int, metavar="BPS", help="CAN bit rate, bit/s")
    bus.add_argument("--protocol", choices=("ckesc", "ft"), help="ESC protocol (default ckesc)")
    bus.add_argument(
        "--mixer", metavar="NAME|FILE", help="the mixer: its outputs are the motors (passthrough-4)"
    )
    spin.set_defaults(handler=_esc_spin, spin_parser=spin)


def _motor_number(text: str) -> int:
    try:
        motor = int(text)
    except ValueError:
        motor = 0
    if motor < 1:
        raise argparse.ArgumentTypeError(f"expected a motor number 1, 2, ..., got {text!r}")
    return motor


def _percent(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 <= value <= 100:
        raise argparse.ArgumentTypeError(f"expected a throttle in percent 0..100, got {text!r}")
    return value


def _spin_seconds(text: str) -> float:
    from bridge.motor_test import SPIN_SECONDS

    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    low, high = SPIN_SECONDS
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(f"expected {low:g}..{high:g} seconds, got {text!r}")
    return value


def spin_config(args: argparse.Namespace) -> BridgeConfig:
    """The configuration ``esc spin`` uses: defaults < --config file < flags.

    Raises:
        ConfigError: a flag or the file is invalid.
    """
    overrides: dict[str, dict[str, Any]] = {}
    for flag, (section, key) in SPIN_FLAGS.items():
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        if value is not None:
            overrides.setdefault(section, {})[key] = value
    if args.can_option:
        overrides.setdefault("can", {})["options"] = dict(args.can_option)
    try:
        config = build_config(overrides, "command line")  # the flags alone name themselves
    except ConfigError as exc:
        raise _with_flag_names(exc, SPIN_FLAGS) from None
    if args.config is None:
        return config
    raw = read_config_file(args.config)
    if "options" in overrides.get("can", {}):
        file_options = raw.get("can", {}).get("options", {})
        if isinstance(file_options, dict):
            overrides["can"]["options"] = file_options | overrides["can"]["options"]
    return build_config(merge(raw, overrides), args.config)


def _esc_spin(args: argparse.Namespace) -> int:
    from bridge import motor_test  # python-can and the drivers only for `esc spin`

    if not args.props_removed:
        args.spin_parser.error(PROPS_WARNING)
    request = motor_test.SpinRequest(args.motor, args.throttle, args.seconds)
    plan = motor_test.plan_spin(spin_config(args), request)
    config = plan.config
    if config.output.protocol == "ckesc":
        channel = config.escs.ckesc_channels[plan.index]
        esc = f"CKESC node {plan.esc_id}, throttle channel {channel}"
    else:
        esc = f"FT ESC {plan.esc_id}, {config.escs.ft_mode} mode"
    print(
        f"spinning motor {request.motor} ({esc}) up to {100 * plan.fraction:g}% = "
        f"{motor_test.command_text(config, plan.fraction)} for {request.seconds:g} s on "
        f"{config.can.interface} {config.can.channel}, {plan.rate_hz:g} frames/s; "
        "Ctrl-C stops it",
        flush=True,
    )

    def show(progress: motor_test.SpinProgress) -> None:
        print(
            f"  {progress.elapsed_s:5.2f} s  {progress.phase:<9}  {100 * progress.fraction:5.1f}%",
            flush=True,
        )

    result = motor_test.spin(plan, progress=show)
    print(
        f"motor {request.motor} stopped, safe values sent: {result.ended} after "
        f"{result.elapsed_s:.2f} s, {result.frames_sent} frames, then {result.safe_frames_sent} "
        f"safe; {result.send_errors} send errors",
        flush=True,
    )
    if result.ended == "bus error":
        print("esc-bridge: error: the CAN bus failed during the spin", file=sys.stderr)
        return 1
    return EXIT_INTERRUPTED if result.ended == "interrupted" else EXIT_OK
