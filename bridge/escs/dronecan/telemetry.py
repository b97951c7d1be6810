"""DroneCAN transfers as neutral telemetry (:class:`~bridge.escs.family.EscTelemetry`) and
the commands a command frame carries (:class:`~bridge.escs.family.CommandSeen`): the family's
side of the ESC state. An ESC is known by its ESC number, ``esc_index + 1`` (``[escs] ids``).

- esc.Status: rpm (signed), voltage, current, the ESC's temperature as its MOSFET temperature
  (kelvin to °C, as ArduPilot's ``handle_ESC_status``), power rating / 100 as its output (with
  the sign of the rpm), and ``error_count`` as a counter; NaN fields are left out.
- NodeStatus of a node whose Status named its index: health as the status word (0 OK,
  1 WARNING, 2 ERROR, 3 CRITICAL), ERROR and CRITICAL as a GENERIC failure; mode and uptime as
  counters. A NodeStatus of an unknown node is no telemetry.
- RawCommand: each slot's value, "raw_command" (-8192..8191), for the ESC number slot + 1.

:class:`DronecanDecoder` is the family's reader of one stream: its own transfer reassembler
(:class:`~bridge.escs.dronecan.codec.Decoder`), so each stream's partial transfers are its
own; a transfer decodes with its last frame, each frame before it to a ``TransferPart``.
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Final, cast

import can

from bridge.escs.dronecan.codec import Decoder, DronecanFrame, EscStatus, NodeStatus, RawCommand
from bridge.escs.dronecan.wire import HEALTH_ERROR, owns
from bridge.escs.family import (
    FAILURE_GENERIC,
    FAILURE_NONE,
    CommandSeen,
    EscFrame,
    EscTelemetry,
)

COMMAND_UNIT: Final = "raw_command"


def telemetry(frame: DronecanFrame) -> EscTelemetry | None:
    """An esc.Status or an ESC's NodeStatus as telemetry; None for anything else."""
    message = frame.message
    if isinstance(message, EscStatus):
        return EscTelemetry(
            message.esc_index + 1,
            rpm=message.rpm,
            voltage_v=message.voltage_v,
            current_a=message.current_a,
            throttle=(-1 if message.rpm < 0 else 1) * message.power_rating_pct / 100,
            mos_temp_c=message.temperature_c,
            counters={"error_count": message.error_count},
        )
    if isinstance(message, NodeStatus) and frame.esc_index is not None:
        return EscTelemetry(
            frame.esc_index + 1,
            status=message.health,
            status_failures=FAILURE_GENERIC if message.health >= HEALTH_ERROR else FAILURE_NONE,
            counters={"uptime_s": message.uptime_s, "mode": message.mode},
        )
    return None


def commands_seen(frame: DronecanFrame) -> list[CommandSeen]:
    """The value a RawCommand gives each slot (none for other transfers)."""
    if not isinstance(frame.message, RawCommand):
        return []
    return [
        CommandSeen(float(value), COMMAND_UNIT, node_id=slot + 1)
        for slot, value in enumerate(frame.message.commands)
    ]


class DronecanDecoder:
    """One stream's DroneCAN reader. ``esc_nodes`` are ESC numbers (esc_index + 1)."""

    def __init__(self) -> None:
        self._decoder = Decoder()
        self._nodes: Collection[int] | None = None
        self._indices: frozenset[int] = frozenset()

    def decode(self, msg: can.Message, esc_nodes: Collection[int] | None = None) -> EscFrame | None:
        indices = None
        if esc_nodes is not None:
            if esc_nodes is not self._nodes:  # the reader passes one set, frame after frame
                self._nodes, self._indices = esc_nodes, frozenset(n - 1 for n in esc_nodes)
            indices = self._indices
        return self._decoder.decode(msg, indices)

    def node_of(self, msg: can.Message) -> int | None:
        if not msg.is_extended_id or msg.is_error_frame or not owns(msg.arbitration_id):
            return None
        index = self._decoder.index_of_node(msg.arbitration_id & 0x7F)
        return None if index is None else index + 1

    def telemetry(self, frame: EscFrame) -> EscTelemetry | None:
        return telemetry(cast(DronecanFrame, frame))

    def commands_seen(self, frame: EscFrame) -> list[CommandSeen]:
        return commands_seen(cast(DronecanFrame, frame))
