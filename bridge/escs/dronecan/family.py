"""Standard DroneCAN (UAVCAN v0) ESCs behind :class:`~bridge.escs.family.EscFamily`: their ID
space, reader, filters, driver, bus figures and keys, answered from this folder. Its simulator
is :mod:`bridge.escs.dronecan.sim`; no set-up commands and no ID discovery.

An ESC is known by its ESC number (``[escs] ids``, default 1..N): its ``esc_index`` parameter
+ 1, the slot of RawCommand it follows, as ArduPilot numbers "ESC 1".. in ``CAN_D1_UC_ESC_BM``.

An esc.Status is three frames, so each stream of frames gets a reader of its own
(:class:`~bridge.escs.dronecan.telemetry.DronecanDecoder`). The ``dronecan`` package (behind the
codec) is imported only when a reader is first made: the output loop never imports it.
"""

from __future__ import annotations

from collections.abc import Collection
from typing import TYPE_CHECKING

from bridge.errors import ConfigError
from bridge.escs.dronecan import bus
from bridge.escs.dronecan.driver import DronecanDriver
from bridge.escs.dronecan.keys import DronecanKeys
from bridge.escs.dronecan.wire import MAX_COMMANDS, owns
from bridge.escs.family import BusFigures, EscSetup

if TYPE_CHECKING:
    from can.typechecking import CanFilter

    from bridge.escs.dronecan.telemetry import DronecanDecoder


class DronecanFamily:
    """DroneCAN: RawCommand out (priority 7, our own node), esc.Status and NodeStatus in."""

    name = "dronecan"
    title = "DroneCAN"
    node_ids = range(1, MAX_COMMANDS + 1)
    default_rate_hz = 400
    # DroneCAN's customary bit rate (ArduPilot's CAN_P1_BITRATE default, most ESCs' own).
    default_bitrate = 1_000_000
    keys = DronecanKeys

    def owns(self, arbitration_id: int) -> bool:
        return owns(arbitration_id)

    def decoder(self) -> DronecanDecoder:
        from bridge.escs.dronecan.telemetry import DronecanDecoder

        return DronecanDecoder()

    def reader_filters(self, esc_ids: Collection[int]) -> list[CanFilter]:
        return bus.reader_filters(esc_ids)

    def check(self, setup: EscSetup[DronecanKeys], rate_hz: int) -> EscSetup[DronecanKeys]:
        ids = setup.ids
        if any(number not in self.node_ids for number in ids):
            raise ConfigError(
                f"[escs] ids {list(ids)}: a DroneCAN RawCommand carries ESCs 1..{MAX_COMMANDS} "
                f"(esc_index 0..{MAX_COMMANDS - 1}); expected ESC numbers 1..{MAX_COMMANDS}"
            )
        stray = sorted(set(setup.keys.dronecan_reversible) - set(ids)) if ids else []
        if stray:
            raise ConfigError(
                f"[escs] dronecan_reversible names ESCs {stray} that are not in ids "
                f"{list(ids)}; expected ESC numbers from ids"
            )
        return setup

    def driver(self, setup: EscSetup[DronecanKeys]) -> DronecanDriver:
        keys = setup.keys
        reversible = set(keys.dronecan_reversible)
        return DronecanDriver(
            [number - 1 for number in setup.ids],
            keys.dronecan_node_id,
            [number in reversible for number in setup.ids],
        )

    def bus_figures(self, setup: EscSetup[DronecanKeys], rate_hz: float) -> BusFigures:
        ids = setup.ids
        return bus.bus_figures(max(ids), len(ids), setup.keys.dronecan_status_hz, rate_hz)
