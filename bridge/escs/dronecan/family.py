"""Standard DroneCAN (UAVCAN v0) ESCs behind :class:`~bridge.escs.family.EscFamily`: what the rest
of the bridge asks of them, answered from this folder (transfer layer, codec, driver, telemetry
mapping, bus figures, keys, simulator). No set-up commands and no ID discovery.

An ESC is known by its ESC number (``[escs] ids``, default 1..N): its ``esc_index`` parameter
+ 1, the slot of RawCommand it follows, as ArduPilot numbers "ESC 1".. in ``CAN_D1_UC_ESC_BM``.

Where the interface assumes one frame is one message, DroneCAN does not: an esc.Status is three
frames. :meth:`DronecanFamily.decode` keeps a :class:`~bridge.escs.dronecan.codec.Decoder` per
thread (each thread reads one stream of frames: the CAN reader, ``decode``, the monitor): a
transfer decodes with its last frame, each frame before it to a ``TransferPart``. The
``dronecan`` package (behind the codec) is imported only when a frame is first decoded: the
output loop never imports it.
"""

from __future__ import annotations

import threading
from collections.abc import Collection, Sequence
from typing import TYPE_CHECKING, Any, Final, cast

import can

from bridge.errors import ConfigError
from bridge.escs.dronecan import bus
from bridge.escs.dronecan.driver import DronecanDriver
from bridge.escs.dronecan.keys import DronecanKeys
from bridge.escs.dronecan.wire import COMMAND_MAX, MAX_COMMANDS, owns
from bridge.escs.family import BusFigures, CommandSeen, EscFrame, EscTelemetry

if TYPE_CHECKING:
    import argparse

    from can.typechecking import CanFilter

    from bridge.config import BridgeConfig
    from bridge.escs.dronecan.codec import Decoder, DronecanFrame
    from bridge.sim.base import SimEsc
    from bridge.sim.motor import MotorParams

NAME: Final = "dronecan"


def keys_of(config: BridgeConfig) -> DronecanKeys:
    """``config``'s DroneCAN keys."""
    return cast(DronecanKeys, config.escs.keys(NAME))


def _indices(config: BridgeConfig) -> list[int]:
    return [number - 1 for number in config.escs.ids]


class DronecanFamily:
    """DroneCAN: RawCommand out (priority 7, our own node), esc.Status and NodeStatus in."""

    name = NAME
    title = "DroneCAN"
    node_ids = range(1, MAX_COMMANDS + 1)
    default_rate_hz = 400
    # DroneCAN's customary bit rate (ArduPilot's CAN_P1_BITRATE default, most ESCs' own).
    default_bitrate = 1_000_000
    learns_node_ids = False
    keys = DronecanKeys

    def __init__(self) -> None:
        self._local = threading.local()

    def _decoder(self) -> Decoder:
        decoder: Decoder | None = getattr(self._local, "decoder", None)
        if decoder is None:
            from bridge.escs.dronecan.codec import Decoder

            decoder = self._local.decoder = Decoder()
        return decoder

    # -- frames ------------------------------------------------------------------------------

    def owns(self, arbitration_id: int) -> bool:
        return owns(arbitration_id)

    def decode(self, msg: can.Message, esc_nodes: Collection[int] | None = None) -> EscFrame | None:
        local = self._local
        if esc_nodes is None:
            indices = None
        elif getattr(local, "nodes", None) is esc_nodes:  # the reader's set, frame after frame
            indices = local.indices
        else:
            indices = frozenset(number - 1 for number in esc_nodes)
            local.nodes, local.indices = esc_nodes, indices
        return self._decoder().decode(msg, indices)

    def node_of(self, msg: can.Message) -> int | None:
        if not msg.is_extended_id or msg.is_error_frame or not self.owns(msg.arbitration_id):
            return None
        index = self._decoder().index_of_node(msg.arbitration_id & 0x7F)
        return None if index is None else index + 1

    def reader_filters(self, esc_ids: Collection[int], read_back_commands: bool) -> list[CanFilter]:
        return bus.reader_filters(esc_ids, read_back_commands)

    # -- telemetry ---------------------------------------------------------------------------

    def telemetry(self, frame: EscFrame) -> EscTelemetry | None:
        from bridge.escs.dronecan import telemetry

        return telemetry.telemetry(cast("DronecanFrame", frame))

    def commands_seen(self, frame: EscFrame) -> Sequence[CommandSeen]:
        from bridge.escs.dronecan import telemetry

        return telemetry.commands_seen(cast("DronecanFrame", frame))

    # -- output ------------------------------------------------------------------------------

    def driver(self, config: BridgeConfig) -> DronecanDriver:
        keys = keys_of(config)
        reversible = set(keys.dronecan_reversible)
        return DronecanDriver(
            _indices(config),
            keys.dronecan_node_id,
            [number in reversible for number in config.escs.ids],
        )

    def bus_figures(self, config: BridgeConfig, rate_hz: float) -> BusFigures:
        return bus.bus_figures(
            max(config.escs.ids), len(config.escs.ids), keys_of(config).dronecan_status_hz, rate_hz
        )

    def command_kind(self, config: BridgeConfig) -> str:
        return f"RawCommand x{max(config.escs.ids)}"

    def describe_command(self, config: BridgeConfig, fraction: float) -> str:
        return f"DroneCAN RawCommand {round(fraction * COMMAND_MAX)}"

    def describe_esc(self, config: BridgeConfig, index: int) -> str:
        number = config.escs.ids[index]
        return f"DroneCAN ESC {number} (esc_index {number - 1})"

    # -- configuration -----------------------------------------------------------------------

    def check_config(self, config: BridgeConfig) -> None:
        if config.output.protocol != NAME:
            return
        keys = keys_of(config)
        ids = config.escs.ids
        stray = sorted(set(keys.dronecan_reversible) - set(ids)) if ids else []
        if stray:
            raise ConfigError(
                f"{config.source}: [escs] dronecan_reversible names ESCs {stray} that are not in "
                f"ids {list(ids)}; expected ESC numbers from ids"
            )

    def with_esc_count(self, config: BridgeConfig, n_outputs: int) -> DronecanKeys:
        ids = config.escs.ids
        if config.output.protocol == NAME and any(number not in self.node_ids for number in ids):
            raise ConfigError(
                f"{config.source}: [escs] ids {list(ids)}: a DroneCAN RawCommand carries ESCs "
                f"1..{MAX_COMMANDS} (esc_index 0..{MAX_COMMANDS - 1}); expected ESC numbers "
                f"1..{MAX_COMMANDS}"
            )
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
        from bridge.escs.dronecan.sim import make_escs

        if channels is not None:
            raise ValueError("channels: DroneCAN ESCs follow their esc_index, not a channel")
        return list(make_escs([number - 1 for number in ids], motor_params=motor_params))

    def demo_settings(self, n_escs: int) -> dict[str, dict[str, Any]]:
        return {}

    def add_cli_commands(self, esc_commands: argparse._SubParsersAction[Any]) -> None:
        return None
