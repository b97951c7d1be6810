"""``esc-bridge run``: the bridge itself, its flags and its configuration."""

from __future__ import annotations

import argparse
import logging
import re
from collections.abc import Callable
from typing import Any

from bridge.cli._common import (
    EXIT_OK,
    add_can_option,
    bitrate_arg,
    flag_overrides,
    merged_config,
)
from bridge.config import SECTIONS, BridgeConfig
from bridge.errors import ConfigError, LinkError
from bridge.escs import registry


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
        help="record every CAN frame sent and received (candump .log), the MAVLink traffic "
        "(.tlog) and the flight as JSON channels for Foxglove and PlotJuggler (.mcap) into DIR",
    )
    run.add_argument(
        "--check",
        action="store_true",
        help="validate the configuration (and --record's directory) as run does before it "
        "sends anything, print the plan, bus load and each check, and exit",
    )
    run.set_defaults(handler=_run)


# --flag -> (section, key, type) for the settings people change most.
RUN_OVERRIDES: dict[str, tuple[str, str, Callable[[str], Any], str]] = {
    "--mavlink": ("mavlink", "url", str, "autopilot connection (pymavlink URL)"),
    "--source": ("mavlink", "source", str, "MAVLink message with the motor outputs"),
    "--can-interface": ("can", "interface", str, "python-can interface (default socketcan)"),
    "--can-channel": ("can", "channel", str, "python-can channel (default can0)"),
    "--bitrate": ("can", "bitrate", bitrate_arg, "CAN bit rate: 500000, 500k or 1M"),
    "--protocol": ("output", "protocol", str, "ESC protocol: " + " or ".join(registry.names())),
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
    "--protocol": "|".join(registry.names()),
    "--rate": "HZ",
    "--latency": "fixed|immediate",
    "--mixer": "NAME|FILE",
    "--vehicle": "NAME",
}


# The flags that set a config key without a RUN_OVERRIDES entry: args attribute -> (section, key).
OTHER_FLAGS: dict[str, tuple[str, str, str]] = {
    "--can-option": ("can_option", "can", "options"),
    "--zenoh-connect": ("zenoh_connect", "zenoh", "connect"),
    "--zenoh-listen": ("zenoh_listen", "zenoh", "listen"),
    "--no-zenoh-scouting": ("zenoh_scouting", "zenoh", "multicast_scouting"),
    "--no-zenoh": ("zenoh_enabled", "zenoh", "enabled"),
}
# A key as messages name it, e.g. "[mavlink] url".
_KEY_NAME = re.compile(r"\[(?:" + "|".join(SECTIONS) + r")\] \w+")


def _add_run_overrides(parser: argparse.ArgumentParser) -> None:
    for flag, (section, key, kind, text) in RUN_OVERRIDES.items():
        parser.add_argument(
            flag,
            type=kind,
            default=None,
            metavar=RUN_METAVARS.get(flag, "VALUE"),
            help=f"{text} ([{section}] {key})",
        )
    add_can_option(parser)
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


def run_config(args: argparse.Namespace) -> BridgeConfig:
    """The configuration for ``run``: defaults < --config file < command-line flags.

    Raises:
        ConfigError: a flag or the file is invalid.
    """
    flags = {flag: (section, key) for flag, (section, key, _, _) in RUN_OVERRIDES.items()}
    overrides = flag_overrides(args, flags)
    zenoh_flags = {
        "connect": args.zenoh_connect,
        "listen": args.zenoh_listen,
        "multicast_scouting": args.zenoh_scouting,
        "enabled": args.zenoh_enabled,
    }
    for key, value in zenoh_flags.items():
        if value is not None:
            overrides.setdefault("zenoh", {})[key] = value
    flags |= {"--zenoh-connect": ("zenoh", "connect"), "--zenoh-listen": ("zenoh", "listen")}
    return merged_config(args, overrides, flags)[0]


def given_flags(args: argparse.Namespace) -> dict[str, tuple[str, str]]:
    """The config-setting flags given on the command line: flag -> (section, key)."""
    given = {
        flag: (section, key)
        for flag, (section, key, _, _) in RUN_OVERRIDES.items()
        if getattr(args, flag.lstrip("-").replace("-", "_")) not in (None, [])
    }
    for flag, (name, section, key) in OTHER_FLAGS.items():
        if getattr(args, name) not in (None, []):
            given[flag] = (section, key)
    return given


def name_given_flags(exc: ConfigError, args: argparse.Namespace, source: str) -> ConfigError:
    """``exc`` with each ``[section] key`` that a flag set written as that flag.

    A flag wins over the file, so a key it set is the flag's value. When the message then names
    no other key, the flags alone are to blame and it says "command line" instead of the file.
    """
    text = str(exc)
    named = 0
    for flag, (section, key) in given_flags(args).items():
        text, count = re.subn(rf"\[{section}\] {key}\b", flag, text)
        named += count
    if named and not _KEY_NAME.search(text) and text.startswith(f"{source}: "):
        text = "command line: " + text.removeprefix(f"{source}: ")
    return ConfigError(text)


def _run(args: argparse.Namespace) -> int:
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s esc-bridge %(message)s"
    )
    # pymavlink logs every new stream and replayed timestamp at INFO; the link counts those.
    logging.getLogger("pymavlink").setLevel(logging.WARNING)
    # pymavlink and the loop are only loaded for `run`.
    from bridge.daemon import preflight, supervisor

    config = run_config(args)
    # The same checks with and without --check: whatever run refuses, --check finds first.
    try:
        checked = preflight.plan(config, record_dir=args.record)
    except ConfigError as exc:
        raise name_given_flags(exc, args, config.source) from None
    if args.check:
        print(f"{config.source}: OK")
        print(f"  mixer {checked.mixer.name}: {len(checked.mixer.outputs)} outputs")
        print(f"  {checked.load_text}")
        for line in checked.passed:
            print(f"  {line}")
    # --check refuses what run refuses, in the same words and with the same exit status.
    if checked.interface_refusal is not None:
        raise LinkError(f"cannot start: {checked.interface_refusal}")
    if args.check:
        return EXIT_OK
    return supervisor.run(checked, record_dir=args.record, stop_signals=args.stop)
