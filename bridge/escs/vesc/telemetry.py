"""VESC frames as neutral telemetry (:class:`~bridge.escs.family.EscTelemetry`) and the commands a
command frame carries (:class:`~bridge.escs.family.CommandSeen`): the family's side of the ESC state
(docs/protocols.md §6.5). VESC reports no faults over CAN; the bridge's limits raise its
failure flags.

Input current and voltage are the battery side (``current_a``, ``voltage_v``); the motor
current is the phase current, negative while regenerating. Amp and watt hours and the
tachometer are counters. PONG and NOTIFY_BOOT are no telemetry: a VESC whose status frames are
off stays silent to the ESC state, and is reported as never heard.
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Final, cast

import can

from bridge.escs.family import CommandSeen, EscFrame, EscTelemetry
from bridge.escs.vesc.codec import decode
from bridge.escs.vesc.records import (
    VESC_ID_MAX,
    SetCurrent,
    SetCurrentBrake,
    SetCurrentRel,
    SetDuty,
    SetRpm,
    Status,
    Status2,
    Status3,
    Status4,
    Status5,
    Status6,
    VescFrame,
)

_MILLI: Final = 1000

# VESC command records -> (CommandSeen unit, the record's value field).
COMMAND_FIELDS: Final[dict[type, tuple[str, str]]] = {
    SetDuty: ("duty", "duty"),
    SetCurrent: ("current_a", "current_a"),
    SetCurrentBrake: ("brake_current_a", "current_a"),
    SetRpm: ("erpm", "erpm"),
    SetCurrentRel: ("current_fraction", "fraction"),
}


def telemetry(frame: VescFrame) -> EscTelemetry | None:
    """A status frame as telemetry; None for commands, PING, PONG and NOTIFY_BOOT."""
    message = frame.message
    node = frame.controller_id
    match message:
        case Status():
            return EscTelemetry(
                node,
                erpm=message.erpm,
                motor_current_a=message.motor_current_a,
                throttle=message.duty,
            )
        case Status4():
            return EscTelemetry(
                node,
                mos_temp_c=message.fet_temp_c,
                motor_temp_c=message.motor_temp_c,
                current_a=message.input_current_a,
            )
        case Status5():
            return EscTelemetry(
                node, voltage_v=message.input_voltage_v, counters={"tachometer": message.tachometer}
            )
        case Status2():
            return EscTelemetry(
                node,
                counters={
                    "used_mah": round(message.used_ah * _MILLI),
                    "charged_mah": round(message.charged_ah * _MILLI),
                },
            )
        case Status3():
            return EscTelemetry(
                node,
                counters={
                    "used_mwh": round(message.used_wh * _MILLI),
                    "charged_mwh": round(message.charged_wh * _MILLI),
                },
            )
        case Status6():
            return EscTelemetry(node)  # ADC and PPM inputs: nothing of the ESC's state
    return None


def commands_seen(frame: VescFrame) -> list[CommandSeen]:
    """The command a command frame carries to its VESC (none for other frames)."""
    unit_and_field = COMMAND_FIELDS.get(type(frame.message))
    if unit_and_field is None:
        return []
    unit, name = unit_and_field
    return [CommandSeen(float(getattr(frame.message, name)), unit, node_id=frame.controller_id)]


class VescDecoder:
    """The VESC reader of one stream: stateless (every VESC frame stands alone), so one serves
    any number of streams."""

    def decode(self, msg: can.Message, esc_nodes: Collection[int] | None = None) -> EscFrame | None:
        return decode(msg)

    def node_of(self, msg: can.Message) -> int | None:
        if not msg.is_extended_id or msg.is_error_frame or msg.arbitration_id > VESC_ID_MAX:
            return None
        return int(msg.arbitration_id & 0xFF)

    def telemetry(self, frame: EscFrame) -> EscTelemetry | None:
        return telemetry(cast(VescFrame, frame))

    def commands_seen(self, frame: EscFrame) -> list[CommandSeen]:
        return commands_seen(cast(VescFrame, frame))
