"""``esc-bridge decode``: a CAN capture, one line per frame, then a summary."""

from __future__ import annotations

import argparse
import dataclasses
import enum
import json
import sys
from typing import Any, cast

from bridge.capture import BadLine, CaptureItem, CaptureSummary, DecodedFrame, decode_capture
from bridge.cli._common import EXIT_FAILED, EXIT_OK
from bridge.escs import registry


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    decode = commands.add_parser(
        "decode",
        help="decode a CAN capture (a candump .log, -L or as printed; .asc, .blf, .csv, .trc, "
        ".mf4, .db)",
        description="Decode a CAN capture into one line per frame, then a summary.",
    )
    decode.add_argument("file", help="the capture; its format is taken from the file suffix")
    decode.add_argument(
        "--protocol",
        choices=("auto", *registry.names()),
        default="auto",
        help="decode every frame as this protocol (default: by each frame's CAN ID space)",
    )
    decode.add_argument(
        "--nodes",
        type=_node_list,
        default=None,
        metavar="N,N,...",
        help="your ESCs' IDs on the bus (node or ESC IDs): where a family shares its ID space "
        "with other devices (UAVCAN v0 vendors' messages), a frame from another node is then "
        "reported as not understood",
    )
    decode.add_argument("--json", action="store_true", help="print JSON lines instead of text")
    decode.set_defaults(handler=_decode)


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
    decoded = 0
    for item in decode_capture(args.file, args.protocol, args.nodes):
        summary.add(item)
        decoded += isinstance(item, DecodedFrame)
        print(show(item))
    if args.json:
        print(json.dumps({"summary": summary.as_dict()}))
    else:
        print(_summary_text(summary))
    if decoded:
        return EXIT_OK
    protocol = "any ESC protocol" if args.protocol == "auto" else f"--protocol {args.protocol}"
    print(
        f"esc-bridge: error: nothing in {args.file} decoded as {protocol}: {summary.frames} "
        f"frames read, {summary.bad_lines} line{'' if summary.bad_lines == 1 else 's'} that "
        f"{'is' if summary.bad_lines == 1 else 'are'} no frame",
        file=sys.stderr,
    )
    return EXIT_FAILED


def _text_line(item: CaptureItem) -> str:
    if isinstance(item, BadLine):
        return f"line {item.line_no}: not a frame ({item.reason}): {item.text!r}"
    msg = item.msg
    head = f"{msg.timestamp:14.6f}  {msg.arbitration_id:08X}  {msg.data.hex(' '):<23}"
    if isinstance(item, DecodedFrame):
        fields = " ".join(f"{k}={_text_value(v)}" for k, v in _message_fields(item))
        return f"{head}  {item.protocol:<5} node {item.frame.node_id:<3} {item.type_name}  {fields}"
    if item.error is None:
        return f"{head}  not understood" + (f": {item.why}" if item.why else "")
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
            for f in dataclasses.fields(cast(Any, item.frame))  # every family's is a dataclass
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
        if item.why:
            record["detail"] = item.why
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
    # The one-bit members set in ``value``, in definition order: what iterating a flag value gives
    # on Python 3.11, spelled so that 3.10 (which cannot iterate one) gives it too. Masks such as
    # Msg1Status.SELF_TEST_ERRORS are not findings.
    bits = [m for m in type(value) if m.value and m.value & (m.value - 1) == 0 and m in value]
    names = [member.name or "" for member in bits]
    # Bits the protocol does not name are shown as a number rather than dropped.
    unnamed = value.value & ~sum(member.value for member in bits)
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
