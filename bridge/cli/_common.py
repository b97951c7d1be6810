"""What several subcommands share: exit statuses, argument types and the CAN bus flags."""

from __future__ import annotations

import argparse
from typing import Any, Final

from bridge.errors import ConfigError

EXIT_OK: Final = 0
EXIT_FAILED: Final = 1  # no answer, a refusal, a failed check or a bus error
EXIT_USAGE: Final = 2  # what argparse uses for bad arguments; a bad config is the same mistake
EXIT_INTERRUPTED: Final = 130  # Ctrl-C or SIGTERM ended the command (a spin: after safe values)


def add_can_flags(
    group: argparse._ArgumentGroup, *, bitrate_help: str = "CAN bit rate, bit/s"
) -> None:
    """``--can-interface``, ``--can-channel``, ``--can-option`` and ``--bitrate``, as for
    ``run`` (each default None or [], so that a file's [can] section is kept)."""
    group.add_argument("--can-interface", metavar="NAME", help="python-can interface (socketcan)")
    group.add_argument("--can-channel", metavar="CHANNEL", help="python-can channel (can0)")
    group.add_argument(
        "--can-option",
        action="append",
        default=[],
        type=can_option,
        metavar="KEY=VALUE",
        help="extra python-can interface argument, repeatable (e.g. port=43113)",
    )
    group.add_argument("--bitrate", type=int, metavar="BPS", help=bitrate_help)


def can_option(text: str) -> tuple[str, Any]:
    """``KEY=VALUE`` -> (key, value), the value as a bool, int or float when it reads as one."""
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


def positive_seconds(text: str) -> float:
    """A finite number of seconds > 0."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a number of seconds > 0, got {text!r}")
    return value


def esc_count(text: str) -> int:
    """A number of ESCs, 1..125."""
    try:
        count = int(text)
    except ValueError:
        count = 0
    if not 1 <= count <= 125:
        raise argparse.ArgumentTypeError(f"expected a number of ESCs 1..125, got {text!r}")
    return count


def int_list(text: str, what: str, example: str) -> list[int]:
    """``1,2,3`` -> [1, 2, 3]; the error names ``what`` and gives ``example``."""
    try:
        return [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a comma-separated list of {what} (e.g. {example}), got {text!r}"
        ) from None


def id_list(text: str) -> list[int]:
    """The ESCs' IDs, motor 1 first."""
    return int_list(text, "ESC IDs", "1,2,3,4")


def with_flag_names(exc: ConfigError, flags: dict[str, tuple[str, str]]) -> ConfigError:
    """``exc`` with each ``[section] key:`` of ``flags`` written as the flag that set it."""
    text = str(exc)
    for flag, (section, key) in flags.items():
        text = text.replace(f"[{section}] {key}:", f"{flag}:")
    return ConfigError(text.replace("[can] options:", "--can-option:"))
