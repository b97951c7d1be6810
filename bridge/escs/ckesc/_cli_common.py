"""The plumbing of the CKESC set-up commands (:mod:`bridge.escs.ckesc.cli`): the names the
commands take, the bus flags, the client on the bus the flags name, errors named by flag, and
the text and JSON forms of the answers. Prints only the interrupted notice."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import enum
import json
import sys
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any, Final, TypeVar

from bridge.bitrate import bitrate_text
from bridge.cli._common import (
    CAN_FLAGS,
    EXIT_INTERRUPTED,
    add_can_flags,
    flag_overrides,
    merged_config,
    positive_seconds,
)
from bridge.config import CanConfig
from bridge.errors import ConfigError, NoAnswerError, ValueRangeError, WrongNodeError
from bridge.escs.ckesc import (
    BAUD_RATES_BPS,
    ExpandSetCommand,
    LedColor,
    MsgControlCommand,
    Rotation,
    ThrottleSource,
)

if TYPE_CHECKING:
    from bridge.escs.ckesc.setup import CkescClient

_T = TypeVar("_T")


COLORS: Final[dict[str, LedColor]] = {
    "off": LedColor(0),
    "blue": LedColor.BLUE,
    "green": LedColor.GREEN,
    "cyan": LedColor.GREEN | LedColor.BLUE,
    "red": LedColor.RED,
    "magenta": LedColor.RED | LedColor.BLUE,
    "yellow": LedColor.RED | LedColor.GREEN,
    "white": LedColor.RED | LedColor.GREEN | LedColor.BLUE,
}
ROTATIONS: Final = {"normal": Rotation.NORMAL, "reversed": Rotation.REVERSED}
SOURCES: Final = {"can": ThrottleSource.CAN, "pwm-can": ThrottleSource.PWM_AND_CAN}
REPORT_COMMANDS: Final = {
    "pause": MsgControlCommand.PAUSE,
    "resume": MsgControlCommand.RESUME_MSG,
    "resume-exp": MsgControlCommand.RESUME_EXP,
}
EXPAND_COMMANDS: Final = {
    command.name.lower().replace("_", "-"): command for command in ExpandSetCommand
}
"""Expand Set commands by name: direction, led, throttle-interface, ..., system."""
EXPAND_PARTS: Final[dict[ExpandSetCommand, dict[str, int]]] = {
    ExpandSetCommand.DIRECTION: {"normal": 1, "reversed": 2},
    ExpandSetCommand.LED: {"off": 0, "red": 1, "green": 2, "blue": 3},
    ExpandSetCommand.THROTTLE_INTERFACE: {
        "pwm": 1,
        "pwm-tcan": 2,
        "tcan": 3,
        "dshot": 4,
        "pwm-uavcan": 5,
        "uavcan": 6,
    },
    ExpandSetCommand.ACTIVE_FREEWHEELING: {"off": 0, "on": 1},
    ExpandSetCommand.TIMING: {},
    ExpandSetCommand.TIMING_2: {},
    ExpandSetCommand.LOAD_TYPE: {"light": 1, "standard": 2, "heavy": 3, "very-heavy": 4},
    ExpandSetCommand.PROP_LOCK: {"off": 0, "weak": 1, "medium": 2, "strong": 3},
    ExpandSetCommand.STARTUP_ACCELERATION: {},
    ExpandSetCommand.SIGNAL_LOSS_RATE: {},
    ExpandSetCommand.READ_TEMP_RECORD: {"read": 1},
    ExpandSetCommand.BAUD: {
        f"{rate // 1_000_000}m" if rate % 1_000_000 == 0 else f"{rate // 1000}k": code
        for code, rate in enumerate(BAUD_RATES_BPS)
    },
    ExpandSetCommand.SYSTEM: {
        "factory-reset": 0x00,
        "leave-test-mode": 0x10,
        "enter-test-mode": 0x11,
    },
}
"""Names for each Expand Set command's parts (seed 4.4.25); a number is always accepted too."""
_EXPAND_NUMBERS: Final = {
    ExpandSetCommand.TIMING: "1..4",
    ExpandSetCommand.TIMING_2: "1..4",
    ExpandSetCommand.STARTUP_ACCELERATION: "0..15, higher starts faster",
    ExpandSetCommand.SIGNAL_LOSS_RATE: "0..15, higher cuts the throttle faster",
}

# The codec's and the client's field names in a ValueRangeError -> the flag that gave them.
_FIELD_FLAGS: Final = (
    ("SetIdRequest.node_id", "--node"),
    ("SetIdRequest.throttle_channel", "--channel"),
    ("node = ", "--node"),
    ("bitrate = ", "BITRATE"),
    ("SetLedRequest.color", "--color"),
    ("SetLedRequest.blink_hz", "--blink"),
    ("SetFreqRequest.msg1_interval_ms", "--msg1-hz"),
    ("SetFreqRequest.msg2_interval_ms", "--msg2-hz"),
    ("SetFreqRequest.msg3_interval_ms", "--msg3-hz"),
    ("ExpandSetRequest.part", "PART"),
    ("MaintenanceRequest.option", "--option"),
    ("duration = ", "--seconds"),
)


# --------------------------------------------------------------------------------------------
# Shared arguments and plumbing


def add_bus_arguments(parser: argparse.ArgumentParser, *, json_output: bool = True) -> None:
    """The bus flags (as ``run``'s), ``--timeout`` and ``--json``."""
    bus = parser.add_argument_group("CAN bus (as for `esc-bridge run`)")
    bus.add_argument("--config", metavar="FILE", help="a bridge configuration: its [can] section")
    add_can_flags(bus, bitrate_help="CAN bit rate: 500000, 500k or 1M (CKESC factory: 500k)")
    parser.add_argument(
        "--timeout",
        type=positive_seconds,
        default=0.5,
        metavar="S",
        help="how long to wait for each answer (default 0.5 s)",
    )
    if json_output:
        parser.add_argument("--json", action="store_true", help="print one JSON object")


def _node_argument(
    parser: argparse.ArgumentParser, *, required: bool = True, text: str = ""
) -> None:
    parser.add_argument(
        "--node",
        type=_integer,
        required=required,
        metavar="N",
        help=text or "the ESC's node ID, 1..125 (`esc scan` lists them; factory ID 125)",
    )


def _integer(text: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None


def _hertz(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a rate in Hz > 0, got {text!r}")
    return value


def interval_ms(hz: float) -> int:
    """A report rate as the nearest interval the ESC can take (2 ms units)."""
    return 2 * round(500 / hz)


def bus_config(args: argparse.Namespace) -> tuple[CanConfig, int]:
    """The [can] configuration and bit rate: defaults < --config file < flags.

    Raises:
        ConfigError: a flag or the file is invalid, or the file is for FT ESCs.
    """
    config, _ = merged_config(args, flag_overrides(args, CAN_FLAGS), CAN_FLAGS)
    if args.config is not None and config.output.protocol != "ckesc":
        raise ConfigError(
            f"{args.config}: [output] protocol is {config.output.protocol!r}; "
            "`esc-bridge esc` sets up CKESC ESCs only"
        )
    return config.can, config.bitrate


def bus_text(args: argparse.Namespace) -> str:
    """The bus the flags name, for messages: ``socketcan can7 at 500000 bit/s (500 kbit/s)``.

    Raises:
        ConfigError: a flag or the file is invalid.
    """
    can_config, bitrate = bus_config(args)
    return (
        f"{can_config.interface} {can_config.channel} at {bitrate} bit/s ({bitrate_text(bitrate)})"
    )


@contextlib.contextmanager
def open_client(args: argparse.Namespace) -> Iterator[CkescClient]:
    """A client on the bus the flags name; the bus is shut down on exit.

    A ValueRangeError inside becomes a ConfigError naming the flag (exit status 2).

    Raises:
        ConfigError: bad flags, a bad file, or a value outside the protocol's range.
        LinkError: the bus cannot be opened.
    """
    from bridge.can_io import open_bus
    from bridge.escs.ckesc.setup import CkescClient

    can_config, bitrate = bus_config(args)
    bus = open_bus(can_config, bitrate)
    try:
        yield CkescClient(bus, timeout_s=args.timeout)
    except ValueRangeError as exc:
        raise ConfigError(_flag_error(exc)) from None
    finally:
        bus.shutdown()


def _flag_error(exc: ValueRangeError) -> str:
    text = str(exc)
    for field, flag in _FIELD_FLAGS:
        if field in text:
            if flag.startswith("--msg"):
                text += f" ({flag} takes 2..50 Hz)"
            return f"{flag}: {text}; nothing was sent"
    return f"{text}; nothing was sent"


def _run(
    args: argparse.Namespace, action: Callable[[CkescClient], _T], *, scan_hint: bool = True
) -> _T:
    """``action`` with a client. A node that does not answer gets a hint to scan; Ctrl-C is
    a quiet exit with status 130 (the client has ended what it started)."""
    try:
        with open_client(args) as client:
            return action(client)
    except NoAnswerError as exc:
        where = f"; the bus: {bus_text(args)}"
        if not scan_hint or isinstance(exc, WrongNodeError) or args.node is None:
            raise type(exc)(f"{exc}{where}") from None
        raise type(exc)(f"{exc}{where} (`esc-bridge esc scan` lists the ESCs on the bus)") from None
    except KeyboardInterrupt:
        print("esc-bridge: interrupted", file=sys.stderr)
        raise SystemExit(EXIT_INTERRUPTED) from None


def _print_json(value: Any) -> None:
    print(json.dumps(jsonable(value)))


def jsonable(value: Any) -> Any:
    """A result for JSON: records as objects, enums and LED colours by their CLI names."""
    from bridge.escs.ckesc.setup import value_name

    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Enum):
        return value_name(value)
    if isinstance(value, tuple | list):
        return [jsonable(item) for item in value]
    if isinstance(value, dict):
        return {str(key): jsonable(item) for key, item in value.items()}
    return value


# A field name's unit suffix -> the unit printed after the value.
_UNITS: Final = (("_ms", " ms"), ("_c", " °C"), ("_hz", " Hz"), ("_a", " A"), ("_s", " s"))


def text_value(value: Any) -> str:
    """A field's value for the text output ("reversed", "pwm-can", "cyan", "yes", "14")."""
    from bridge.escs.ckesc.setup import value_name

    return value_name(value)


def record_lines(record: Any, indent: str = "  ") -> list[str]:
    """One ``label  value unit`` line per field of a response record."""
    lines = []
    for f in dataclasses.fields(record):
        label, unit = f.name, ""
        for suffix, text in _UNITS:
            if label.endswith(suffix):
                label, unit = label.removesuffix(suffix), text
                break
        label = label.replace("_", " ")
        lines.append(f"{indent}{label:<24} {text_value(getattr(record, f.name))}{unit}")
    return lines
