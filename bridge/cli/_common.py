"""What several subcommands share: exit statuses, argument types, the CAN bus flags and the one
configuration merge (defaults < ``--config`` file < command-line flags)."""

from __future__ import annotations

import argparse
from collections.abc import Mapping
from typing import Any, Final

from bridge.bitrate import parse_bitrate
from bridge.config import BridgeConfig, build_config
from bridge.config_file import merge, read_config_file
from bridge.errors import ConfigError

EXIT_OK: Final = 0
EXIT_FAILED: Final = 1  # no answer, a refusal, a failed check or a bus error
EXIT_USAGE: Final = 2  # what argparse uses for bad arguments; a bad config is the same mistake
EXIT_INTERRUPTED: Final = 130  # Ctrl-C or SIGTERM ended the command (a spin: after safe values)

# The flags of :func:`add_can_flags` -> (section, key) of the configuration they override.
CAN_FLAGS: Final[dict[str, tuple[str, str]]] = {
    "--can-interface": ("can", "interface"),
    "--can-channel": ("can", "channel"),
    "--bitrate": ("can", "bitrate"),
}
# The ESC flags of the commands that read ESCs themselves (sim, monitor): the family and the IDs.
# Their --escs N (no key of its own) sets IDs 1..N when --ids is not given.
ESC_FLAGS: Final[dict[str, tuple[str, str]]] = {
    "--protocol": ("output", "protocol"),
    "--ids": ("escs", "ids"),
}


def add_can_flags(
    group: argparse._ArgumentGroup,
    *,
    bitrate_help: str = "CAN bit rate: 500000, 500k or 1M (default: the ESCs' factory rate)",
) -> None:
    """``--can-interface``, ``--can-channel``, ``--can-option`` and ``--bitrate``, as for
    ``run`` (each default None or [], so that a file's [can] section is kept)."""
    group.add_argument("--can-interface", metavar="NAME", help="python-can interface (socketcan)")
    group.add_argument("--can-channel", metavar="CHANNEL", help="python-can channel (can0)")
    add_can_option(group)
    group.add_argument("--bitrate", type=bitrate_arg, metavar="BPS", help=bitrate_help)


def bitrate_arg(text: str) -> int:
    """A bit rate as ``500000``, ``500k`` or ``1M``."""
    try:
        return parse_bitrate(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_can_option(group: argparse._ActionsContainer) -> None:
    """``--can-option KEY=VALUE``, repeatable (default [], so that a file's options are kept)."""
    group.add_argument(
        "--can-option",
        action="append",
        default=[],
        type=can_option,
        metavar="KEY=VALUE",
        help="extra python-can interface argument, repeatable (e.g. port=43113)",
    )


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


def with_flag_names(exc: ConfigError, flags: Mapping[str, tuple[str, str]]) -> ConfigError:
    """``exc`` with each ``[section] key:`` of ``flags`` written as the flag that set it."""
    text = str(exc)
    for flag, (section, key) in flags.items():
        text = text.replace(f"[{section}] {key}:", f"{flag}:")
    return ConfigError(text.replace("[can] options:", "--can-option:"))


def flag_overrides(
    args: argparse.Namespace, flags: Mapping[str, tuple[str, str]]
) -> dict[str, dict[str, Any]]:
    """The configuration keys the given flags set: ``flags`` maps each flag to its (section,
    key), its value read from the ``args`` attribute of the flag's name (None when not given);
    then ``--can-option``'s, as [can] options, and ``--escs N``'s, as [escs] ids 1..N."""
    overrides: dict[str, dict[str, Any]] = {}
    for flag, (section, key) in flags.items():
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        if value is not None:
            overrides.setdefault(section, {})[key] = value
    escs = getattr(args, "escs", None)
    if escs is not None and "ids" not in overrides.get("escs", {}):
        overrides.setdefault("escs", {})["ids"] = list(range(1, escs + 1))
    if args.can_option:
        overrides.setdefault("can", {})["options"] = dict(args.can_option)
    return overrides


def merged_config(
    args: argparse.Namespace,
    overrides: Mapping[str, Mapping[str, Any]],
    flag_names: Mapping[str, tuple[str, str]],
) -> tuple[BridgeConfig, dict[str, Any] | None]:
    """The configuration a subcommand runs with: defaults < ``args.config`` (the ``--config``
    file, if given) < ``overrides`` (the flags' keys), and the file's raw tables (None without
    one). ``--can-option``'s options are added to the file's, not put in their place.

    The flags are validated alone first, so that a bad one is reported as the flag it is
    (``flag_names``: flag -> the (section, key) it sets).

    Raises:
        ConfigError: a flag or the file is invalid.
    """
    try:
        config = build_config(overrides, "command line")
    except ConfigError as exc:
        raise with_flag_names(exc, flag_names) from None
    if args.config is None:
        return config, None
    raw = read_config_file(args.config)
    flag_options = overrides.get("can", {}).get("options")
    if flag_options is not None:
        file_can = raw.get("can")
        file_options = file_can.get("options", {}) if isinstance(file_can, dict) else None
        if isinstance(file_options, dict):
            can = {**overrides["can"], "options": file_options | flag_options}
            overrides = {**overrides, "can": can}
    return build_config(merge(raw, overrides), args.config), raw
