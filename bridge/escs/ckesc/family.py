"""The CKESC family behind :class:`~bridge.escs.family.EscFamily`: what the rest of the bridge
asks of CKESC ESCs, answered from this folder (codec, driver, telemetry mapping, bus figures,
keys, GET_ESC_ID learning, simulator, set-up commands)."""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any, Final, cast

import can

from bridge.errors import ConfigError
from bridge.escs import ckesc, uavcan_v0
from bridge.escs.ckesc import bus, telemetry
from bridge.escs.ckesc.driver import CkescDriver
from bridge.escs.ckesc.keys import COMMAND_CHANNELS, CkescKeys
from bridge.escs.family import BusFigures, CommandSeen, EscFrame, EscTelemetry

if TYPE_CHECKING:
    import argparse

    from can.typechecking import CanFilter

    from bridge.config import BridgeConfig
    from bridge.sim.base import SimEsc
    from bridge.sim.motor import MotorParams

NAME: Final = "ckesc"


def keys_of(config: BridgeConfig) -> CkescKeys:
    """``config``'s CKESC keys."""
    return cast(CkescKeys, config.escs.keys(NAME))


class CkescFamily:
    """CKESC: UAVCAN v0 framing, the vendor's message and service types (docs/protocols.md §3)."""

    name = NAME
    title = "CKESC"
    node_ids = range(1, uavcan_v0.MAX_NODE_ID + 1)
    default_rate_hz = 400
    # CKESC ships at 500 kbit/s (docs/protocols.md §1.2).
    default_bitrate = 500_000
    learns_node_ids = True
    keys = CkescKeys

    # -- frames ------------------------------------------------------------------------------

    def owns(self, arbitration_id: int) -> bool:
        # Every CKESC message type (20000..20999) and service type (210..242) sets some of
        # bits 28..16; an FT ID never does.
        return arbitration_id >> 16 != 0

    def decode(self, msg: can.Message, esc_nodes: Collection[int] | None = None) -> EscFrame | None:
        return ckesc.decode(msg, esc_nodes)

    def node_of(self, msg: can.Message) -> int | None:
        if not msg.is_extended_id or msg.is_error_frame:
            return None
        return int(msg.arbitration_id & 0x7F) or None  # node 0 is the host

    def reader_filters(self, esc_ids: Collection[int], read_back_commands: bool) -> list[CanFilter]:
        return bus.reader_filters(esc_ids, read_back_commands)

    # -- telemetry ---------------------------------------------------------------------------

    def telemetry(self, frame: EscFrame) -> EscTelemetry | None:
        return telemetry.telemetry(cast(ckesc.CkescFrame, frame))

    def commands_seen(self, frame: EscFrame) -> Sequence[CommandSeen]:
        return telemetry.commands_seen(cast(ckesc.CkescFrame, frame))

    # -- output ------------------------------------------------------------------------------

    def driver(self, config: BridgeConfig) -> CkescDriver:
        keys = keys_of(config)
        return CkescDriver(keys.ckesc_command, keys.ckesc_channels)

    def bus_figures(self, config: BridgeConfig, rate_hz: float) -> BusFigures:
        keys = keys_of(config)
        return bus.bus_figures(
            len(config.escs.ids),
            keys.ckesc_channels,
            keys.ckesc_command,
            keys.ckesc_msg_hz,
            rate_hz,
        )

    def command_kind(self, config: BridgeConfig) -> str:
        return keys_of(config).ckesc_command

    def describe_command(self, config: BridgeConfig, fraction: float) -> str:
        full = 1000 if keys_of(config).ckesc_command == "10b" else 2000
        return f"CKESC throttle {int(fraction * full + 0.5)}/{full}"

    def describe_esc(self, config: BridgeConfig, index: int) -> str:
        channel = keys_of(config).ckesc_channels[index]
        return f"CKESC node {config.escs.ids[index]}, throttle channel {channel}"

    # -- configuration -----------------------------------------------------------------------

    def check_config(self, config: BridgeConfig) -> None:
        channels, ids = keys_of(config).ckesc_channels, config.escs.ids
        if channels and ids and len(channels) != len(ids):
            raise ConfigError(
                f"{config.source}: [escs] ckesc_channels has {len(channels)} entries but ids "
                f"has {len(ids)}; expected one channel per ESC"
            )

    def with_esc_count(self, config: BridgeConfig, n_outputs: int) -> CkescKeys:
        keys = keys_of(config)
        if keys.ckesc_channels and len(keys.ckesc_channels) != n_outputs:
            raise ConfigError(
                f"{config.source}: [escs] ckesc_channels has {len(keys.ckesc_channels)} entries "
                f"but mixer {config.mixer.name!r} has {n_outputs} outputs; expected one per output"
            )
        keys = replace(keys, ckesc_channels=keys.ckesc_channels or tuple(range(1, n_outputs + 1)))
        if config.output.protocol == NAME:
            most = COMMAND_CHANNELS[keys.ckesc_command]
            if max(keys.ckesc_channels) > most:
                raise ConfigError(
                    f"{config.source}: [escs] ckesc_command {keys.ckesc_command!r} carries "
                    f"channels 1..{most}, but the ESCs use channels {list(keys.ckesc_channels)}; "
                    'expected ckesc_command = "12b" (channels 1..20) or channels within 1..'
                    f"{most}"
                )
        return keys

    def channels(self, config: BridgeConfig) -> Sequence[int] | None:
        return keys_of(config).ckesc_channels

    def learn_node_ids(self, bus: can.BusABC, config: BridgeConfig) -> dict[int, int] | None:
        from bridge.escs.ckesc.setup import learn_node_ids

        return learn_node_ids(bus, keys_of(config).ckesc_channels)

    # -- simulation, demo, CLI ---------------------------------------------------------------

    def simulators(
        self,
        ids: Sequence[int],
        channels: Sequence[int] | None,
        motor_params: MotorParams | None,
    ) -> list[SimEsc]:
        from bridge.escs.ckesc.sim import SimCkesc
        from bridge.sim.motor import Motor

        n = len(ids)
        channels = list(range(1, n + 1)) if channels is None else list(channels)
        if len(channels) != n:
            raise ValueError(f"channels={channels!r}: {len(channels)} channels for {n} ESCs")
        return [
            SimCkesc(node_id, channel, motor=Motor(motor_params))
            for node_id, channel in zip(ids, channels, strict=True)
        ]

    def demo_settings(self, n_escs: int) -> dict[str, dict[str, Any]]:
        return {}

    def add_cli_commands(self, esc_commands: argparse._SubParsersAction[Any]) -> None:
        from bridge.escs.ckesc.cli import add_commands

        add_commands(esc_commands)
