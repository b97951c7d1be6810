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
        "--check",
        action="store_true",
        help="validate the configuration, print the plan and bus load, and exit",
    )
    run.set_defaults(handler=_run)
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
    # The flags alone first, so that a bad flag is reported as the flag it is.
    try:
        build_config(overrides, "command line")
    except ConfigError as exc:
        text = str(exc)
        for flag, (section, key, _, _) in RUN_OVERRIDES.items():
            text = text.replace(f"[{section}] {key}:", f"{flag}:")
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
    return daemon.run(config)


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
