"""The Flipsky FT family behind :class:`~bridge.escs.family.EscFamily`: what the rest of the
bridge asks of FT ESCs, answered from this folder (codec, driver, telemetry mapping, bus
figures, keys, simulator). FT has no set-up commands and no ID discovery."""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from typing import TYPE_CHECKING, Any, Final, cast

import can

from bridge.errors import ConfigError
from bridge.escs import ft
from bridge.escs.family import BusFigures, CommandSeen, EscFrame, EscTelemetry
from bridge.escs.ft import bus, telemetry
from bridge.escs.ft.driver import FtDriver
from bridge.escs.ft.keys import FtKeys

if TYPE_CHECKING:
    import argparse

    from can.typechecking import CanFilter

    from bridge.config import BridgeConfig
    from bridge.sim.base import SimEsc
    from bridge.sim.motor import MotorParams

NAME: Final = "ft"
COMMAND_TIMEOUT_MS: Final = 450
"""The ESC drops a command not repeated within this (docs/protocols.md §4.4)."""
MIN_REFRESHES_PER_TIMEOUT: Final = 4
"""A command must reach each ESC at least this many times within its timeout, so that a few
lost frames or a stalled cycle never let the ESC time out mid-flight."""


def keys_of(config: BridgeConfig) -> FtKeys:
    """``config``'s FT keys."""
    return cast(FtKeys, config.escs.keys(NAME))


class FtFamily:
    """Flipsky FT: ``id = esc_id << 8 | command``, 16 commands, three telemetry frames."""

    name = NAME
    title = "FT"
    node_ids = range(ft.ESC_ID_MIN, ft.ESC_ID_MAX + 1)
    default_rate_hz = 100
    # FT has no factory rate; VESC firmware uses 500k.
    default_bitrate = 500_000
    learns_node_ids = False
    keys = FtKeys

    # -- frames ------------------------------------------------------------------------------

    def owns(self, arbitration_id: int) -> bool:
        return arbitration_id >> 16 == 0  # bits 28..16 are clear in every FT ID

    def decode(self, msg: can.Message, esc_nodes: Collection[int] | None = None) -> EscFrame | None:
        return ft.decode(msg)

    def node_of(self, msg: can.Message) -> int | None:
        if not msg.is_extended_id or msg.is_error_frame or msg.arbitration_id >> 16 != 0:
            return None
        return ft.parse_id(msg.arbitration_id)[0]

    def reader_filters(self, esc_ids: Collection[int], read_back_commands: bool) -> list[CanFilter]:
        return bus.reader_filters(esc_ids, read_back_commands)

    # -- telemetry ---------------------------------------------------------------------------

    def telemetry(self, frame: EscFrame) -> EscTelemetry | None:
        return telemetry.telemetry(cast(ft.FtFrame, frame))

    def commands_seen(self, frame: EscFrame) -> Sequence[CommandSeen]:
        return telemetry.commands_seen(cast(ft.FtFrame, frame))

    # -- output ------------------------------------------------------------------------------

    def driver(self, config: BridgeConfig) -> FtDriver:
        return FtDriver(config.escs.ids, keys_of(config))

    def bus_figures(self, config: BridgeConfig, rate_hz: float) -> BusFigures:
        keys = keys_of(config)
        return bus.bus_figures(len(config.escs.ids), keys.ft_crc, keys.ft_telemetry_hz, rate_hz)

    def command_kind(self, config: BridgeConfig) -> str:
        return keys_of(config).ft_mode

    def describe_command(self, config: BridgeConfig, fraction: float) -> str:
        keys = keys_of(config)
        if keys.ft_mode == "current":
            return f"FT current {fraction * keys.ft_max_current_a:.2f} A"
        if keys.ft_mode == "current_percent":
            return f"FT current {100 * fraction:.1f} %"
        if keys.ft_mode == "duty":
            return f"FT duty {fraction * keys.ft_max_duty:.3f}"
        return f"FT {round(fraction * keys.ft_max_erpm)} erpm"

    def describe_esc(self, config: BridgeConfig, index: int) -> str:
        return f"FT ESC {config.escs.ids[index]}, {keys_of(config).ft_mode} mode"

    # -- configuration -----------------------------------------------------------------------

    def check_config(self, config: BridgeConfig) -> None:
        if config.output.protocol != NAME:
            return
        period_ms = 1000 / config.rate_hz
        if period_ms * MIN_REFRESHES_PER_TIMEOUT > COMMAND_TIMEOUT_MS:
            slowest = math.ceil(1000 * MIN_REFRESHES_PER_TIMEOUT / COMMAND_TIMEOUT_MS)
            raise ConfigError(
                f"{config.source}: [output] rate_hz: {config.rate_hz} Hz refreshes each FT ESC "
                f"every {period_ms:.0f} ms; the ESC drops a command after {COMMAND_TIMEOUT_MS} "
                f"ms, so expected at least {slowest} Hz ({MIN_REFRESHES_PER_TIMEOUT} refreshes "
                "within the timeout)"
            )

    def with_esc_count(self, config: BridgeConfig, n_outputs: int) -> FtKeys:
        return keys_of(config)

    def channels(self, config: BridgeConfig) -> Sequence[int] | None:
        return None

    def learn_node_ids(self, bus: can.BusABC, config: BridgeConfig) -> dict[int, int] | None:
        return None

    # -- simulation, demo, CLI ---------------------------------------------------------------

    def simulators(
        self,
        ids: Sequence[int],
        channels: Sequence[int] | None,
        motor_params: MotorParams | None,
    ) -> list[SimEsc]:
        from bridge.escs.ft.sim import SimFt
        from bridge.sim.motor import Motor

        if channels is not None:
            raise ValueError("channels: FT ESCs have no throttle channel")
        return [SimFt(esc_id, motor=Motor(motor_params)) for esc_id in ids]

    def demo_settings(self, n_escs: int) -> dict[str, dict[str, Any]]:
        # 100 commands per ESC per second, and a 1 Mbit/s bus so that eight ESCs' real-time
        # telemetry (3 frames x 100 Hz each) stays under the bus-load ceiling.
        return {
            "output": {"rate_hz": 100},
            "can": {"bitrate": 1_000_000},
            "escs": {"ft_mode": "current"},
        }

    def add_cli_commands(self, esc_commands: argparse._SubParsersAction[Any]) -> None:
        return None
