"""FT frames as neutral telemetry (:class:`~bridge.escs.family.EscTelemetry`) and commands read
back (:class:`~bridge.escs.family.CommandSeen`): the family's side of the ESC state. FT reports
no faults of its own; the bridge's limits raise its failure flags."""

from __future__ import annotations

from typing import Final

from bridge.escs import ft
from bridge.escs.family import CommandSeen, EscTelemetry

# FT command records -> (command_unit, the record's value field).
COMMAND_FIELDS: Final[dict[type, tuple[str, str]]] = {
    ft.SetCurrent: ("current_a", "current_a"),
    ft.SetCurrentBrake: ("brake_current_a", "current_a"),
    ft.SetDuty: ("duty", "duty"),
    ft.SetCurrentPercent: ("current_fraction", "fraction"),
    ft.SetCurrentBrakePercent: ("brake_fraction", "fraction"),
    ft.SetErpm: ("erpm", "erpm"),
    ft.SetPosition: ("position_deg", "angle_deg"),
    ft.SetIdCurrent: ("id_current_a", "current_a"),
}


def telemetry(frame: ft.FtFrame) -> EscTelemetry | None:
    """A real-time data frame as telemetry; None for commands."""
    message = frame.message
    if isinstance(message, ft.RealtimeData0):
        return EscTelemetry(
            frame.esc_id,
            motor_current_a=message.motor_current_a,
            current_a=message.battery_current_a,
        )
    if isinstance(message, ft.RealtimeData1):
        return EscTelemetry(frame.esc_id, erpm=message.erpm, throttle=message.duty)
    if isinstance(message, ft.RealtimeData2):
        return EscTelemetry(
            frame.esc_id,
            mos_temp_c=message.mosfet_temp_c,
            motor_temp_c=message.motor_temp_c,
            voltage_v=message.battery_voltage_v,
        )
    return None


def commands_seen(frame: ft.FtFrame) -> list[CommandSeen]:
    """The command a command frame carries to its ESC (none for other frames)."""
    unit_and_field = COMMAND_FIELDS.get(type(frame.message))
    if unit_and_field is None:
        return []
    unit, name = unit_and_field
    return [CommandSeen(float(getattr(frame.message, name)), unit, node_id=frame.esc_id)]
