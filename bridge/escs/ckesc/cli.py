"""``esc-bridge esc COMMAND``: set up CKESC ESCs from the command line (arguments and output);
``esc spin``, the motor test for every family, is in :mod:`bridge.cli.spin`.

One row of :data:`COMMANDS` per command: :func:`add_commands` adds its parser to the ``esc``
group that :mod:`bridge.cli.esc` creates; each parser has the bus flags the CLI hands over
(:class:`~bridge.escs.tools.BusFlags`), ``--node`` where the command takes one, its own
arguments, and a handler that runs :class:`~bridge.escs.ckesc.setup.CkescClient` (imported
lazily) and prints the result, as text or with ``--json`` as one JSON object. Like the rest of
:mod:`bridge.cli` this module prints.

Longer than 600 lines on purpose: fourteen commands, each a row of the table, a handler and the
names its arguments take; cut in two (as it once was), every command would be read in two
places.

Exit status: 0 done; 1 no answer, a refusal, a failed self-test, lost CANTest frames or a bus
error (one line on stderr); 2 bad arguments, including values outside the protocol's range,
which are refused before anything is sent (the message names the flag).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import enum
import json
import sys
import textwrap
from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING, Any, Final, TypeAlias, TypeVar

from bridge.bitrate import parse_bitrate
from bridge.errors import ConfigError, NoAnswerError, ValueRangeError, WrongNodeError
from bridge.escs.ckesc import records
from bridge.escs.ckesc.results import scan_warnings, value_name

if TYPE_CHECKING:
    from bridge.escs.ckesc.setup import CkescClient
    from bridge.escs.tools import BusFlags

    EscCommands: TypeAlias = argparse._SubParsersAction[argparse.ArgumentParser]
    """What ``add_subparsers`` returns: the ``esc`` group's commands."""

SUMMARY: Final = "CKESC scan, node ID and channel, LED, direction, rates, self tests"
"""What these commands do, for ``esc-bridge esc --help``."""

# Exit statuses, as every esc-bridge command's.
EXIT_OK: Final = 0
EXIT_FAILED: Final = 1  # no answer, a refusal, a failed check or a bus error
EXIT_INTERRUPTED: Final = 130  # Ctrl-C

_T = TypeVar("_T")


COLORS: Final[dict[str, records.LedColor]] = {
    "off": records.LedColor(0),
    "blue": records.LedColor.BLUE,
    "green": records.LedColor.GREEN,
    "cyan": records.LedColor.GREEN | records.LedColor.BLUE,
    "red": records.LedColor.RED,
    "magenta": records.LedColor.RED | records.LedColor.BLUE,
    "yellow": records.LedColor.RED | records.LedColor.GREEN,
    "white": records.LedColor.RED | records.LedColor.GREEN | records.LedColor.BLUE,
}
ROTATIONS: Final = {"normal": records.Rotation.NORMAL, "reversed": records.Rotation.REVERSED}
SOURCES: Final = {"can": records.ThrottleSource.CAN, "pwm-can": records.ThrottleSource.PWM_AND_CAN}
REPORT_COMMANDS: Final = {
    "pause": records.MsgControlCommand.PAUSE,
    "resume": records.MsgControlCommand.RESUME_MSG,
    "resume-exp": records.MsgControlCommand.RESUME_EXP,
}
EXPAND_COMMANDS: Final = {
    command.name.lower().replace("_", "-"): command for command in records.ExpandSetCommand
}
"""Expand Set commands by name: direction, led, throttle-interface, ..., system."""
EXPAND_PARTS: Final[dict[records.ExpandSetCommand, dict[str, int]]] = {
    records.ExpandSetCommand.DIRECTION: {"normal": 1, "reversed": 2},
    records.ExpandSetCommand.LED: {"off": 0, "red": 1, "green": 2, "blue": 3},
    records.ExpandSetCommand.THROTTLE_INTERFACE: {
        "pwm": 1,
        "pwm-tcan": 2,
        "tcan": 3,
        "dshot": 4,
        "pwm-uavcan": 5,
        "uavcan": 6,
    },
    records.ExpandSetCommand.ACTIVE_FREEWHEELING: {"off": 0, "on": 1},
    records.ExpandSetCommand.TIMING: {},
    records.ExpandSetCommand.TIMING_2: {},
    records.ExpandSetCommand.LOAD_TYPE: {"light": 1, "standard": 2, "heavy": 3, "very-heavy": 4},
    records.ExpandSetCommand.PROP_LOCK: {"off": 0, "weak": 1, "medium": 2, "strong": 3},
    records.ExpandSetCommand.STARTUP_ACCELERATION: {},
    records.ExpandSetCommand.SIGNAL_LOSS_RATE: {},
    records.ExpandSetCommand.READ_TEMP_RECORD: {"read": 1},
    records.ExpandSetCommand.BAUD: {
        f"{rate // 1_000_000}m" if rate % 1_000_000 == 0 else f"{rate // 1000}k": code
        for code, rate in enumerate(records.BAUD_RATES_BPS)
    },
    records.ExpandSetCommand.SYSTEM: {
        "factory-reset": 0x00,
        "leave-test-mode": 0x10,
        "enter-test-mode": 0x11,
    },
}
"""Names for each Expand Set command's parts (seed 4.4.25); a number is always accepted too."""
_EXPAND_NUMBERS: Final = {
    records.ExpandSetCommand.TIMING: "1..4",
    records.ExpandSetCommand.TIMING_2: "1..4",
    records.ExpandSetCommand.STARTUP_ACCELERATION: "0..15, higher starts faster",
    records.ExpandSetCommand.SIGNAL_LOSS_RATE: "0..15, higher cuts the throttle faster",
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


def add_bus_arguments(
    parser: argparse.ArgumentParser, bus_flags: BusFlags, *, json_output: bool = True
) -> None:
    """The bus flags (as ``run``'s), ``--timeout`` and ``--json``."""
    bus = parser.add_argument_group("CAN bus (as for `esc-bridge run`)")
    bus_flags.add(bus, bitrate_help="CAN bit rate: 500000, 500k or 1M (CKESC factory: 500k)")
    parser.add_argument(
        "--timeout",
        type=_positive_seconds,
        default=0.5,
        metavar="S",
        help="how long to wait for each answer (default 0.5 s)",
    )
    if json_output:
        parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(bus_flags=bus_flags)


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


def _positive(what: str) -> Callable[[str], float]:
    """An argument type: a finite number > 0, else an error naming ``what`` was expected."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not 0 < value < float("inf"):
            raise argparse.ArgumentTypeError(f"expected {what} > 0, got {text!r}")
        return value

    return parse


_hertz = _positive("a rate in Hz")
_positive_seconds = _positive("a number of seconds")


def _bitrate(text: str) -> int:
    """A bit rate as ``500000``, ``500k`` or ``1M``."""
    try:
        return parse_bitrate(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def interval_ms(hz: float) -> int:
    """A report rate as the nearest interval the ESC can take (2 ms units)."""
    return 2 * round(500 / hz)


@contextlib.contextmanager
def open_client(args: argparse.Namespace) -> Iterator[CkescClient]:
    """A client on the bus the flags name; the bus is shut down on exit.

    A ValueRangeError inside becomes a ConfigError naming the flag (exit status 2).

    Raises:
        ConfigError: bad flags, a bad file, or a value outside the protocol's range.
        LinkError: the bus cannot be opened.
    """
    from bridge.escs.ckesc.setup import CkescClient

    bus = args.bus_flags.open(args)
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
        where = f"; the bus: {args.bus_flags.describe(args)}"
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


# --------------------------------------------------------------------------------------------
# scan


_SCAN_HEADER: Final = (
    "node  channel  direction  throttle  LED            MSG1/2/3 ms    cells  current  "
    "hw  protocol  firmware"
)


def _scan(args: argparse.Namespace) -> int:
    escs = _run(args, lambda client: client.scan())
    warnings = scan_warnings(escs)
    incomplete = [esc for esc in escs if esc.problem is not None]
    if args.json:
        _print_json({"escs": escs, "warnings": warnings})
    elif escs:
        print(_SCAN_HEADER)
        for esc in escs:
            print(_scan_row(esc))
        print(f"{len(escs)} ESC{'s' if len(escs) != 1 else ''} answered.")
        for problem in dict.fromkeys(f"node {esc.node_id}: {esc.problem}" for esc in incomplete):
            print(problem)
        for warning in warnings:
            print(f"warning: {warning}")
    if not escs:
        print(
            "esc-bridge: error: no ESC answered GET_ESC_ID on "
            f"{args.bus_flags.describe(args)}: is the ESC powered and wired (CAN H/L, 120 ohm "
            "at both ends), and does it run at that bit rate (500 kbit/s from the factory; "
            "--bitrate or [can] bitrate for another)?",
            file=sys.stderr,
        )
        return EXIT_FAILED
    return EXIT_FAILED if incomplete else EXIT_OK


def _scan_row(esc: Any) -> str:
    head = f"{esc.node_id:>4}  {esc.throttle_channel:>7}  "
    config, info = esc.config, esc.info
    if config is None:
        middle = f"{'-':<9}  {'-':<8}  {'-':<13}  {'-':<13}"
    else:
        blink = "steady" if config.led_blink_hz == 0 else f"{config.led_blink_hz} Hz"
        led = f"{text_value(config.led_color)} {blink}"
        intervals = f"{config.msg1_interval_ms}/{config.msg2_interval_ms}/{config.msg3_interval_ms}"
        direction = "reversed" if config.direction_reversed else "normal"
        source = (
            "PWM+CAN" if config.throttle_source == records.ThrottleSource.PWM_AND_CAN else "CAN"
        )
        middle = f"{direction:<9}  {source:<8}  {led:<13}  {intervals:<13}"
    if info is None:
        tail = f"{'-':<5}  {'-':<7}  {'-':<2}  {'-':<8}  -"
    else:
        firmware = f"{info.firmware_year:02d}-{info.firmware_month:02d}-{info.firmware_day:02d}"
        tail = (
            f"{str(info.max_cells) + 'S':<5}  {str(info.max_current_a) + ' A':<7}  "
            f"{info.hardware_version:<2}  {info.protocol_version:<8}  {firmware}"
        )
    return f"{head}{middle}  {tail}"


# --------------------------------------------------------------------------------------------
# set-id, baud


def _set_id(args: argparse.Namespace) -> int:
    # No scan hint on a missing answer: the error explains the power-up window instead.
    result = _run(args, lambda client: client.set_id(args.node, args.channel), scan_hint=False)
    if args.json:
        _print_json(result)
    else:
        print(
            f"node {result.old_node_id} (channel {result.old_throttle_channel}) is now node "
            f"{result.node_id}, channel {result.throttle_channel} (saved in the ESC's flash)"
        )
    return EXIT_OK


def _baud(args: argparse.Namespace) -> int:
    bitrate = _run(args, lambda client: client.set_baud(args.node, args.new_bitrate))
    if args.json:
        _print_json({"node_id": args.node, "bitrate": bitrate})
    else:
        print(
            f"node {args.node}: CAN bit rate {bitrate} bit/s from its next power-up "
            f"(run the bus at {bitrate} bit/s then)"
        )
    return EXIT_OK


# --------------------------------------------------------------------------------------------
# led, rotation, report-rate, throttle-source


def _led(args: argparse.Namespace) -> int:
    color = COLORS[args.color]
    response = _run(
        args, lambda client: client.set_led(args.node, color, args.blink, save=args.save)
    )
    if args.json:
        _print_json({"node_id": args.node, **jsonable(response)})
    else:
        blink = "steady" if response.blink_hz == 0 else f"blinking {response.blink_hz} Hz"
        kept = "saved" if response.save else "until power-off"
        print(f"node {args.node}: LED {text_value(response.color)}, {blink} ({kept})")
    return EXIT_OK


def _rotation(args: argparse.Namespace) -> int:
    asked = None if args.direction is None else ROTATIONS[args.direction]
    rotation = _run(args, lambda client: client.rotation(args.node, asked))
    if args.json:
        _print_json({"node_id": args.node, "rotation": jsonable(rotation)})
    else:
        verb = "is" if asked is None else "set to"
        print(f"node {args.node}: rotation {verb} {text_value(rotation)}")
    return EXIT_OK


def _report_rate(args: argparse.Namespace) -> int:
    rates = (args.msg1_hz, args.msg2_hz, args.msg3_hz)
    m1, m2, m3 = (None if hz is None else interval_ms(hz) for hz in rates)
    response = _run(args, lambda client: client.report_intervals(args.node, m1, m2, m3))
    intervals = (response.msg1_interval_ms, response.msg2_interval_ms, response.msg3_interval_ms)
    if args.json:
        _print_json({"node_id": args.node, **jsonable(response)})
    else:
        verb = "set to" if response.write else "now"
        parts = [
            f"MSG{n} every {ms} ms ({1000 / ms:.3g} Hz)" if ms else f"MSG{n} off"
            for n, ms in enumerate(intervals, start=1)
        ]
        print(f"node {args.node}: reports {verb}: " + ", ".join(parts))
    return EXIT_OK


def _throttle_source(args: argparse.Namespace) -> int:
    asked = None if args.source is None else SOURCES[args.source]
    source = _run(args, lambda client: client.throttle_source(args.node, asked))
    name = text_value(source)
    if args.json:
        _print_json({"node_id": args.node, "throttle_source": name})
    else:
        verb = "is" if asked is None else "set to"
        print(f"node {args.node}: throttle source {verb} {name}")
    return EXIT_OK


# --------------------------------------------------------------------------------------------
# self-test, expand


def _self_test(args: argparse.Namespace) -> int:
    result = _run(args, lambda client: client.self_test(args.node))
    if args.json:
        _print_json(result)
    elif result.passed:
        print(f"node {args.node}: self-test passed")
    else:
        fault = "" if result.fault is None else f" (fault {_fault_text(result.fault)})"
        print(f"node {args.node}: self-test FAILED{fault}")
    return EXIT_OK if result.passed else EXIT_FAILED


def _fault_text(fault: Any) -> str:
    name = text_value(fault) if isinstance(fault, enum.Enum) else "unknown"
    return f"0x{int(fault):02X} {name}"


def expand_part(command: records.ExpandSetCommand, text: str | None) -> int:
    """PART as a number: a name of :data:`EXPAND_PARTS`, or a number (its range is the codec's).

    Raises:
        ConfigError: no PART where one is needed, or neither a name nor a number.
    """
    names = EXPAND_PARTS[command]
    flag = f"PART of expand {command.name.lower().replace('_', '-')}"
    if text is None:
        if len(names) == 1:
            return next(iter(names.values()))
        raise ConfigError(f"{flag} is needed: {_expand_choices(command)}")
    if text.lower() in names:
        return names[text.lower()]
    try:
        return int(text, 0)
    except ValueError:
        raise ConfigError(f"{flag}: {text!r} is not {_expand_choices(command)}") from None


def _expand_choices(command: records.ExpandSetCommand) -> str:
    names = EXPAND_PARTS[command]
    if names:
        return "one of " + ", ".join(names) + " (or their numbers)"
    return "a number " + _EXPAND_NUMBERS[command]


def _expand(args: argparse.Namespace) -> int:
    command = EXPAND_COMMANDS[args.name]
    part = expand_part(command, args.part)
    result = _run(args, lambda client: client.expand(args.node, command, part))
    if args.json:
        _print_json(result)
        return EXIT_OK
    names = {number: name for name, number in EXPAND_PARTS[command].items()}
    what = f"{args.name} {part}" + (f" ({names[part]})" if part in names else "")
    if command == records.ExpandSetCommand.READ_TEMP_RECORD:
        print(f"node {args.node}: temperature records (the highest temperature of each sensor)")
        print("  sensor     max °C  run  at s")
        for record in result.temp_records:
            kind = text_value(record.kind)
            print(
                f"  {kind:<9}  {record.max_temp_c:>6}  {record.run_count:>3}  "
                f"{record.run_time_s:>4}"
            )
    elif result.confirmed:
        print(f"node {args.node}: expand {what} sent; the major configuration shows it")
    else:
        print(
            f"node {args.node}: expand {what} sent (no answer is defined: the motor beeps "
            "when the ESC takes it)"
        )
    return EXIT_OK


# --------------------------------------------------------------------------------------------
# info, maintenance, config


def _info(args: argparse.Namespace) -> int:
    return _print_record(args, "ESC information", _run(args, lambda c: c.info(args.node)))


def _print_record(args: argparse.Namespace, title: str, record: Any) -> int:
    """One answer record of ``args.node``: as JSON, or titled lines of fields."""
    if args.json:
        _print_json({"node_id": args.node, **jsonable(record)})
    else:
        print(f"node {args.node}: {title}")
        print("\n".join(record_lines(record)))
    return EXIT_OK


def _maintenance(args: argparse.Namespace) -> int:
    options = (0, 1, 2) if args.option is None else (args.option,)
    answers = _run(args, lambda client: [client.maintenance(args.node, o) for o in options])
    if args.json:
        by_option = {str(o): jsonable(r) for o, r in zip(options, answers, strict=True)}
        _print_json({"node_id": args.node, "options": by_option})
    else:
        for option, record in zip(options, answers, strict=True):
            print(f"node {args.node}: maintenance information, option {option}")
            print("\n".join(record_lines(record)))
    return EXIT_OK


def _config(args: argparse.Namespace) -> int:
    config = _run(args, lambda client: client.major_config(args.node))
    return _print_record(args, "major configuration", config)


# --------------------------------------------------------------------------------------------
# reports, can-test: broadcasts


def _reports(args: argparse.Namespace) -> int:
    command = REPORT_COMMANDS[args.action]
    result = _run(args, lambda client: client.reports(command, args.node))
    if args.json:
        _print_json({"action": args.action, "acked_by": list(result.acked_by)})
    else:
        nodes = ", ".join(map(str, result.acked_by))
        print(f"reports {args.action}: acknowledged by node(s) {nodes}")
    return EXIT_OK


def _can_test(args: argparse.Namespace) -> int:
    results = _run(args, lambda client: client.can_test(args.seconds, args.node))
    lost = sum(result.lost for result in results)
    if args.json:
        rows = [{**jsonable(r), "expected": r.expected, "lost": r.lost} for r in results]
        _print_json({"seconds": args.seconds, "escs": rows, "lost": lost})
    else:
        print("node  received  counter span  lost  rate")
        for r in results:
            print(
                f"{r.node_id:>4}  {r.received:>8}  {r.expected:>12}  {r.lost:>4}  "
                f"{r.received / r.duration_s:.0f}/s"
            )
    if lost:
        print(
            f"esc-bridge: error: {lost} CANTest frame{'s' * (lost > 1)} lost: check the wiring, "
            "the 120 ohm terminations and the bus load",
            file=sys.stderr,
        )
        return EXIT_FAILED
    return EXIT_OK


# --------------------------------------------------------------------------------------------
# The commands, as data: one row each, added to the ``esc`` group by :func:`add_commands`.

_Argument: TypeAlias = tuple[tuple[str, ...], dict[str, Any]]


def _arg(*names: str, **options: Any) -> _Argument:
    """One ``parser.add_argument(*names, **options)``, kept for later."""
    return names, options


@dataclasses.dataclass(frozen=True)
class _Command:
    """One ``esc-bridge esc`` set-up command: its parser and its handler."""

    name: str
    help: str
    description: str
    handler: Callable[[argparse.Namespace], int]
    node: str | None = ""
    """``--node``'s help ("": the usual one); None: no --node."""
    node_required: bool = True
    arguments: tuple[_Argument, ...] = ()
    """Its own arguments, after the bus flags and --node."""
    parser_options: Mapping[str, Any] = dataclasses.field(default_factory=dict)


def _expand_epilog() -> str:
    lines = ["commands and their PARTs (a name or a number):"]
    for name, command in EXPAND_COMMANDS.items():
        parts = EXPAND_PARTS[command]
        listed = ", ".join(f"{part} ({number})" for part, number in parts.items())
        lines.append(f"  {name:<21} {listed or _EXPAND_NUMBERS.get(command, '')}")
    return "\n".join(lines)


_REPORTED: Final = ((1, "speed, throttle, status"), (2, "volts, amps"), (3, "temperatures"))

COMMANDS: Final[tuple[_Command, ...]] = (
    _Command(
        "scan",
        "list every CKESC on the bus: node ID, channel, information, configuration",
        "Ask every ESC for its node ID and throttle channel (GET_ESC_ID), wait out the answer "
        "window (node_id % 32 x 2 ms, up to 64 ms, plus --timeout), then ask each for its ESC "
        "information (240) and major configuration (242).",
        _scan,
        node=None,
    ),
    _Command(
        "set-id",
        "give the only ESC on the bus a node ID and throttle channel (saved in flash)",
        "Give the ESC a node ID and a throttle channel. Set ID reaches every ESC on the bus, so "
        "nothing is sent unless exactly one ESC answers a scan; and an ESC takes it only within "
        "120 s of its power-up. Connect one ESC at a time.",
        _set_id,
        node="the node ID to give the ESC, 1..125",
        arguments=(
            _arg(
                "--channel",
                type=_integer,
                required=True,
                metavar="C",
                help="the throttle channel it is to follow, 1..20 (RawCommand channel, motor "
                "order)",
            ),
        ),
    ),
    _Command(
        "baud",
        "set an ESC's CAN bit rate (from its next power-up)",
        "Set the ESC's CAN bit rate. The ESC takes it only within 120 s of its power-up and "
        "uses it from the next power-up: the bus (and --bitrate of every esc-bridge command) "
        "must then run at the new rate.",
        _baud,
        arguments=(
            _arg(
                "new_bitrate",  # not "bitrate": that is the bus's own (--bitrate)
                type=_bitrate,
                metavar="BITRATE",
                help="1M, 500k, 250k, 200k, 125k, 100k or 50k (or in bit/s)",
            ),
        ),
    ),
    _Command(
        "led",
        "set an ESC's LED colour and blinking",
        "Set the ESC's LED. The ESC takes it only while its reports are on.",
        _led,
        arguments=(
            _arg("--color", choices=tuple(COLORS), required=True, help="the colour"),
            _arg(
                "--blink",
                type=_integer,
                default=0,
                metavar="HZ",
                help="0 (steady, the default), 1, 2 or 5 Hz",
            ),
            _arg(
                "--save",
                action="store_true",
                help="keep it after power-off (default: until then)",
            ),
        ),
    ),
    _Command(
        "rotation",
        "set or show an ESC's motor direction",
        "Set the motor direction (saved in flash; the motor must be stopped and the reports "
        "on), or without a value show it.",
        _rotation,
        arguments=(
            _arg(
                "direction", nargs="?", choices=tuple(ROTATIONS), help="omit to show the direction"
            ),
        ),
    ),
    _Command(
        "report-rate",
        "show or set how often an ESC sends MSG1, MSG2 and MSG3",
        "Without rates, show the report intervals; with some, set them (2..50 Hz, taken as the "
        "nearest interval in 2 ms steps; the others are kept). Factory: MSG1 50 Hz, MSG2 10 "
        "Hz, MSG3 2 Hz.",
        _report_rate,
        arguments=tuple(
            _arg(f"--msg{n}-hz", type=_hertz, metavar="HZ", help=f"MSG{n} ({what}) rate, 2..50 Hz")
            for n, what in _REPORTED
        ),
    ),
    _Command(
        "throttle-source",
        "set or show where an ESC takes its throttle from (CAN, or PWM+CAN)",
        "Set the throttle source (saved in flash; at zero throttle only), or without a value "
        "show it. PWM+CAN prefers the PWM input while it has a signal.",
        _throttle_source,
        arguments=(
            _arg("source", nargs="?", choices=tuple(SOURCES), help="omit to show the source"),
        ),
    ),
    _Command(
        "self-test",
        "an ESC's power-on self-test result (exit status 1 if it failed)",
        "Ask for the power-on self-test result; for a failure, the fault code too (Maintenance "
        "Information option 2).",
        _self_test,
    ),
    _Command(
        "expand",
        "send one Expand Set command by name (direction, led, prop-lock, ...)",
        textwrap.fill(
            "Send one Expand Set command. It has no answer (the motor beeps): the ESC is asked "
            "for its information first, and afterwards what the major configuration shows "
            "(direction, LED, CAN or PWM+CAN) is checked. read-temp-record prints the four "
            "temperature records. The motor must be stopped.",
            width=78,
        ),
        _expand,
        arguments=(
            _arg("name", choices=tuple(EXPAND_COMMANDS), metavar="NAME", help="see below"),
            _arg("part", nargs="?", metavar="PART", help="see below"),
        ),
        parser_options={
            "epilog": _expand_epilog(),
            "formatter_class": argparse.RawDescriptionHelpFormatter,
        },
    ),
    _Command(
        "info",
        "an ESC's information: cells, current rating, versions, firmware date",
        "Ask for the ESC's information (ESC Information, 240).",
        _info,
    ),
    _Command(
        "maintenance",
        "an ESC's maintenance information: run times, maxima, counters, fault code",
        "Ask for Maintenance Information: option 0 (total run time, highest MOS and capacitor "
        "temperatures), 1 (this run's time, run count), 2 (power-on and stop counts, self-test "
        "fault code); all three by default.",
        _maintenance,
        arguments=(
            _arg("--option", type=int, choices=(0, 1, 2), help="one option (default: all three)"),
        ),
    ),
    _Command(
        "config",
        "an ESC's major configuration: direction, throttle source and channel, LED, rates",
        "Ask for the ESC's major configuration (Get Major Configuration, 242).",
        _config,
    ),
    _Command(
        "reports",
        "pause or resume the telemetry of every ESC (MSGControl)",
        "Pause every ESC's periodic reports, resume MSG1..3, or resume MSG_EXP1..11 instead "
        "(resume-exp). A broadcast: every ESC on the bus acts on it and acknowledges within 64 "
        "ms; --node names one whose acknowledgement is required.",
        _reports,
        node="require this ESC's acknowledgement",
        node_required=False,
        arguments=(_arg("action", choices=tuple(REPORT_COMMANDS), help="what to do"),),
    ),
    _Command(
        "can-test",
        "bus test: count each ESC's CANTest frames against its counter (lost frames)",
        "Put every ESC in CANTest mode (a broadcast), count the reports each sends (every 2 ms) "
        "against their counter for --seconds, report the lost frames, and end the mode (also "
        "on Ctrl-C). Exit status 1 if a frame was lost.",
        _can_test,
        node="only this ESC (default: every ESC that reports)",
        node_required=False,
        arguments=(
            _arg(
                "--seconds",
                type=_positive_seconds,
                default=2.0,
                metavar="S",
                help="test for S seconds (default 2)",
            ),
        ),
    ),
)


def add_commands(esc_commands: EscCommands, bus_flags: BusFlags) -> None:
    """Add every command of :data:`COMMANDS` to the ``esc`` group: the bus flags
    (``bus_flags``, see :func:`add_bus_arguments`), ``--node``, its own arguments, its
    handler."""
    for command in COMMANDS:
        parser = esc_commands.add_parser(
            command.name,
            help=command.help,
            description=command.description,
            **command.parser_options,
        )
        add_bus_arguments(parser, bus_flags)
        if command.node is not None:
            _node_argument(parser, required=command.node_required, text=command.node)
        for names, options in command.arguments:
            parser.add_argument(*names, **options)
        parser.set_defaults(handler=command.handler)
        if command.node is None:
            parser.set_defaults(node=None)
