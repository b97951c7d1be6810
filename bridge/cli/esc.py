"""``esc-bridge esc``: the group of ESC commands, each ESC family's set-up ones (its tool module
``cli.py``, given the bus flags below; each handler loads the family's client itself) and
``spin`` (:mod:`bridge.cli.spin`)."""

from __future__ import annotations

import argparse

import can

from bridge.bitrate import bitrate_text
from bridge.cli import spin
from bridge.cli._common import CAN_FLAGS, add_can_flags, flag_overrides, merged_config
from bridge.config import BridgeConfig
from bridge.errors import ConfigError
from bridge.escs import registry


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    # Each family's set-up commands, if it has any (its tool module cli.py).
    tools = {name: registry.tool(name, "cli") for name in registry.names()}
    setups = "; ".join(tool.SUMMARY for tool in tools.values() if tool is not None)
    esc = commands.add_parser(
        "esc",
        help=f"set up and test ESCs: {setups}; a motor test (spin) for {registry.titles()}",
        description="Talk to ESCs over any python-can bus. The set-up commands wait for the "
        "ESC's answer (--timeout) and check it; `spin` runs one motor "
        f"({registry.titles('or')}). Exit status 0 done, 1 no answer, refused or bus error, 2 "
        "bad arguments (out-of-range values are refused before anything is sent).",
    )
    esc_commands = esc.add_subparsers(dest="esc_command", required=True, metavar="ESC_COMMAND")
    for name, tool in tools.items():
        if tool is not None:
            tool.add_commands(esc_commands, FamilyBusFlags(name))
    spin.add_parser(esc_commands)  # every family: its own bus flags, as for `run`


class FamilyBusFlags:
    """The bus flags of one family's set-up commands (:class:`bridge.escs.tools.BusFlags`):
    ``--config`` and the CAN flags, merged as every command merges them."""

    def __init__(self, family: str) -> None:
        self._family = family

    def add(self, group: argparse._ArgumentGroup, *, bitrate_help: str) -> None:
        group.add_argument(
            "--config", metavar="FILE", help="a bridge configuration: its [can] section"
        )
        add_can_flags(group, bitrate_help=bitrate_help)

    def _config(self, args: argparse.Namespace) -> BridgeConfig:
        config, _ = merged_config(args, flag_overrides(args, CAN_FLAGS), CAN_FLAGS)
        if args.config is not None and config.output.protocol != self._family:
            title = registry.family(self._family).title
            raise ConfigError(
                f"{args.config}: [output] protocol is {config.output.protocol!r}; "
                f"`esc-bridge esc` sets up {title} ESCs only"
            )
        return config

    def open(self, args: argparse.Namespace) -> can.BusABC:
        from bridge.can_io import open_bus

        config = self._config(args)
        return open_bus(config.can, config.bitrate)

    def describe(self, args: argparse.Namespace) -> str:
        config = self._config(args)
        can_config, bitrate = config.can, config.bitrate
        where = f"{can_config.interface} {can_config.channel}"
        return f"{where} at {bitrate} bit/s ({bitrate_text(bitrate)})"
