"""The FT reader (:class:`FtDecoder`): frames to records, and records to neutral telemetry
(:class:`~bridge.escs.family.EscTelemetry`) and the commands a command frame carries
(:class:`~bridge.escs.family.CommandSeen`), the family's side of the ESC state. FT reports no
faults of its own; the bridge's limits raise its failure flags."""

from __future__ import annotations

from collections.abc import Collection
from typing import Final, cast

import can

from bridge.escs.family import CommandSeen, EscFrame, EscTelemetry
from bridge.escs.ft import codec, records

# FT command records -> (command_unit, the record's value field).
COMMAND_FIELDS: Final[dict[type, tuple[str, str]]] = {
    records.SetCurrent: ("current_a", "current_a"),
    records.SetCurrentBrake: ("brake_current_a", "current_a"),
    records.SetDuty: ("duty", "duty"),
    records.SetCurrentPercent: ("current_fraction", "fraction"),
    records.SetCurrentBrakePercent: ("brake_fraction", "fraction"),
    records.SetErpm: ("erpm", "erpm"),
    records.SetPosition: ("position_deg", "angle_deg"),
    records.SetIdCurrent: ("id_current_a", "current_a"),
}


def telemetry(frame: records.FtFrame) -> EscTelemetry | None:
    """A real-time data frame as telemetry; None for commands."""
    message = frame.message
    if isinstance(message, records.RealtimeData0):
        return EscTelemetry(
            frame.esc_id,
            motor_current_a=message.motor_current_a,
            current_a=message.battery_current_a,
        )
    if isinstance(message, records.RealtimeData1):
        return EscTelemetry(frame.esc_id, erpm=message.erpm, throttle=message.duty)
    if isinstance(message, records.RealtimeData2):
        return EscTelemetry(
            frame.esc_id,
            mos_temp_c=message.mosfet_temp_c,
            motor_temp_c=message.motor_temp_c,
            voltage_v=message.battery_voltage_v,
        )
    return None


def commands_seen(frame: records.FtFrame) -> list[CommandSeen]:
    """The command a command frame carries to its ESC (none for other frames)."""
    unit_and_field = COMMAND_FIELDS.get(type(frame.message))
    if unit_and_field is None:
        return []
    unit, name = unit_and_field
    return [CommandSeen(float(getattr(frame.message, name)), unit, node_id=frame.esc_id)]


class FtDecoder:
    """FT frames through :mod:`~bridge.escs.ft.codec`: one frame is one message, so one decoder
    serves every stream."""

    def decode(self, msg: can.Message, esc_nodes: Collection[int] | None = None) -> EscFrame | None:
        return codec.decode(msg)

    def node_of(self, msg: can.Message) -> int | None:
        if not msg.is_extended_id or msg.is_error_frame or msg.arbitration_id >> 16 != 0:
            return None
        return records.parse_id(msg.arbitration_id)[0]

    def telemetry(self, frame: EscFrame) -> EscTelemetry | None:
        return telemetry(cast(records.FtFrame, frame))

    def commands_seen(self, frame: EscFrame) -> list[CommandSeen]:
        return commands_seen(cast(records.FtFrame, frame))
