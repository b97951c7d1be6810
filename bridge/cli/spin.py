"""``esc-bridge esc spin``: the motor test for every ESC family, propellers off."""

from __future__ import annotations

import argparse
import sys

from bridge.bitrate import bitrate_text
from bridge.cli._common import (
    CAN_FLAGS,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    add_can_flags,
    flag_overrides,
    merged_config,
)
from bridge.config import BridgeConfig
from bridge.escs import registry

# Flags of `esc spin` -> (section, key) of the configuration they override, as for `run`.
SPIN_FLAGS: dict[str, tuple[str, str]] = {
    **CAN_FLAGS,
    "--protocol": ("output", "protocol"),
    "--mixer": ("mixer", "name"),
}
PROPS_WARNING = (
    "refusing to spin without --props-removed: a motor spinning with its propeller on can "
    "cut fingers and throw the vehicle off the bench. Take every propeller off, then add "
    "--props-removed to say so"
)


def add_parser(esc_commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    spin = esc_commands.add_parser(
        "spin",
        help="spin one motor for a few seconds to check it, PROPELLERS OFF "
        f"({registry.titles('or')})",
        description="Spin one motor with its propeller removed, to check its direction, "
        "wiring and ESC: ramp up to --throttle over 0.5 s, hold, ramp down, stop at --seconds "
        "whatever happens, then send safe values to every ESC; the other motors get safe "
        "values throughout. The frames are the bridge's own (its drivers, rate and limits), "
        "so do not run this while `esc-bridge run` drives the same bus. Ctrl-C or SIGTERM "
        "stops the motor at once (safe values, then exit status 130).",
    )
    spin.add_argument(
        "--motor",
        type=_motor_number,
        required=True,
        metavar="N",
        help="the motor: 1..N in the mixer's output order (the N-th of [escs] ids)",
    )
    spin.add_argument(
        "--throttle",
        type=_percent,
        required=True,
        metavar="P",
        help="percent 0..100 of the ESC's full range: CKESC throttle 2000 (10b: 1000); FT "
        "ft_max_current_a, 100 %%, ft_max_duty or ft_max_erpm by ft_mode; never above the "
        "mixer output's max",
    )
    spin.add_argument(
        "--seconds",
        type=_spin_seconds,
        required=True,
        metavar="S",
        help="hard time limit, ramps included: 1..30",
    )
    spin.add_argument(
        "--props-removed",
        action="store_true",
        help="required: you confirm that every propeller is off",
    )
    spin.add_argument(
        "--config",
        metavar="FILE",
        help="a bridge configuration: its [can], [output] (protocol, rate, shutdown_flush_ms), "
        "[mixer] and [escs]",
    )
    bus = spin.add_argument_group("CAN bus and ESCs (as for `esc-bridge run`)")
    add_can_flags(bus)
    bus.add_argument(
        "--protocol", choices=registry.names(), help=f"ESC protocol (default {registry.DEFAULT})"
    )
    bus.add_argument(
        "--mixer", metavar="NAME|FILE", help="the mixer: its outputs are the motors (passthrough-4)"
    )
    spin.set_defaults(handler=_esc_spin, spin_parser=spin)


def _motor_number(text: str) -> int:
    try:
        motor = int(text)
    except ValueError:
        motor = 0
    if motor < 1:
        raise argparse.ArgumentTypeError(f"expected a motor number 1, 2, ..., got {text!r}")
    return motor


def _percent(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 <= value <= 100:
        raise argparse.ArgumentTypeError(f"expected a throttle in percent 0..100, got {text!r}")
    return value


def _spin_seconds(text: str) -> float:
    from bridge.output.motor_test import SPIN_SECONDS

    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    low, high = SPIN_SECONDS
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(f"expected {low:g}..{high:g} seconds, got {text!r}")
    return value


def spin_config(args: argparse.Namespace) -> BridgeConfig:
    """The configuration ``esc spin`` uses: defaults < --config file < flags.

    Raises:
        ConfigError: a flag or the file is invalid.
    """
    return merged_config(args, flag_overrides(args, SPIN_FLAGS), SPIN_FLAGS)[0]


def _esc_spin(args: argparse.Namespace) -> int:
    # python-can and the drivers only for `esc spin`
    from bridge.output import motor_test, spin

    if not args.props_removed:
        args.spin_parser.error(PROPS_WARNING)
    request = motor_test.SpinRequest(args.motor, args.throttle, args.seconds)
    plan = spin.plan_spin(spin_config(args), request)
    config = plan.config
    esc = config.family.driver(config.esc_setup).describe_esc(plan.index)
    print(
        f"spinning motor {request.motor} ({esc}) up to {100 * plan.fraction:g}% = "
        f"{motor_test.command_text(config, plan.fraction)} for {request.seconds:g} s on "
        f"{config.can.interface} {config.can.channel}, {plan.rate_hz:g} frames/s; "
        "Ctrl-C stops it",
        flush=True,
    )

    def show(progress: spin.SpinProgress) -> None:
        print(
            f"  {progress.elapsed_s:5.2f} s  {progress.phase:<9}  {100 * progress.fraction:5.1f}%",
            flush=True,
        )

    result = spin.spin(plan, progress=show)
    answered = result.telemetry_frames > 0
    ended = result.ended if answered or result.ended != "done" else "no answer"
    rpm = "" if result.rpm is None else f", last rpm {result.rpm}"
    print(
        f"motor {request.motor} stopped, safe values sent: {ended} after "
        f"{result.elapsed_s:.2f} s, {result.frames_sent} frames, then {result.safe_frames_sent} "
        f"safe; {result.send_errors} send errors; {result.telemetry_frames} telemetry frames "
        f"from its ESC{rpm}",
        flush=True,
    )
    if result.ended == "bus error":
        print("esc-bridge: error: the CAN bus failed during the spin", file=sys.stderr)
        return EXIT_FAILED
    if result.ended == "interrupted":
        return EXIT_INTERRUPTED
    if not answered:
        rate = config.bitrate
        print(
            f"esc-bridge: error: nothing answered: no telemetry from motor {request.motor}'s ESC "
            f"({esc}) on "
            f"{config.can.interface} {config.can.channel} at {rate} bit/s "
            f"({bitrate_text(rate)}) during the spin; is the ESC powered and wired, is its ID "
            "the one in [escs] ids, does it run at that bit rate and take CAN commands "
            "(docs/troubleshooting.md)?",
            file=sys.stderr,
        )
        return EXIT_FAILED
    return EXIT_OK
