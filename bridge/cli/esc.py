"""``esc-bridge esc``: the group of ESC commands, each ESC family's set-up ones (its
``add_cli_commands``; each handler loads the family's client itself) and ``spin``
(:mod:`bridge.cli.spin`)."""

from __future__ import annotations

import argparse

from bridge.cli import spin
from bridge.escs import registry


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
    for family in registry.families():
        family.add_cli_commands(esc_commands)  # its set-up commands, if it has any
    spin.add_parser(esc_commands)  # every family: its own bus flags, as for `run`
