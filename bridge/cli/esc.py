"""``esc-bridge esc``: the group of ESC commands, the CKESC set-up ones
(:mod:`bridge.escs.ckesc.cli`; each handler loads the client itself) and ``spin``
(:mod:`bridge.cli.spin`)."""

from __future__ import annotations

import argparse

from bridge.cli import spin
from bridge.escs.ckesc import cli as esc_setup


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
    esc_setup.add_esc_scan(esc_commands)
    esc_setup.add_esc_set_id(esc_commands)
    esc_setup.add_esc_baud(esc_commands)
    esc_setup.add_esc_led(esc_commands)
    esc_setup.add_esc_rotation(esc_commands)
    esc_setup.add_esc_report_rate(esc_commands)
    esc_setup.add_esc_throttle_source(esc_commands)
    esc_setup.add_esc_self_test(esc_commands)
    esc_setup.add_esc_expand(esc_commands)
    esc_setup.add_esc_info(esc_commands)
    esc_setup.add_esc_maintenance(esc_commands)
    esc_setup.add_esc_config(esc_commands)
    esc_setup.add_esc_reports(esc_commands)
    esc_setup.add_esc_can_test(esc_commands)
    spin.add_parser(esc_commands)  # CKESC and FT: its own bus flags, as for `run`
