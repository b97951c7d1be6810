"""The CKESC reader (:class:`CkescDecoder`): frames to records, and records to neutral telemetry
(:class:`~bridge.escs.family.EscTelemetry`) and the commands a command frame carries
(:class:`~bridge.escs.family.CommandSeen`), the family's side of the ESC state.

Failure flags follow MAVLink's ESC_FAILURE_FLAGS; a MSG1 status word maps through
:data:`STATUS_FAILURES` (docs/telemetry.md). MSG_EXP9's self-test fault and MSG_EXP10's
fault code are counters whose non-zero value is a fault (``fault_counters``).
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Final, cast

import can

from bridge.escs.ckesc import codec, records
from bridge.escs.family import (
    FAILURE_GENERIC,
    FAILURE_NONE,
    FAILURE_OVER_CURRENT,
    FAILURE_OVER_TEMPERATURE,
    FAILURE_OVER_VOLTAGE,
    CommandSeen,
    EscFrame,
    EscTelemetry,
)

_S = records.Msg1Status
# CKESC MSG1 status bits -> ESC_FAILURE_FLAGS. MAVLink has no under-voltage, comms or self-test
# bit: those are GENERIC (the ESC's raw status word is published beside the flags).
# Plain ints: a Flag enum's ``&`` costs a microsecond per bit, on every MSG1 (50 Hz per ESC).
STATUS_FAILURES: Final[tuple[tuple[int, int], ...]] = (
    (int(_S.OVER_CURRENT), FAILURE_OVER_CURRENT),
    (int(_S.OVER_VOLTAGE), FAILURE_OVER_VOLTAGE),
    (int(_S.OVER_TEMPERATURE), FAILURE_OVER_TEMPERATURE),
    (int(_S.UNDER_VOLTAGE), FAILURE_GENERIC),
    (int(_S.SELF_TEST_ERRORS), FAILURE_GENERIC),
)
NO_COMMAND: Final = int(_S.COMMS_FAULT)
"""MSG1's comms fault, no valid CAN throttle for 200 ms: GENERIC as the record's
``uncommanded_failures`` (every idle ESC raises it when nothing commands it)."""
_SELF_TEST_FAULT: Final = frozenset({"self_test_fault"})
_FAULT_CODE_2: Final = frozenset({"fault_code_2"})

_TELEMETRY: Final = (
    records.Msg1,
    records.Msg2,
    records.Msg3,
    records.MsgExp1,
    records.MsgExp2,
    records.MsgExp3,
    records.MsgExp4,
    records.MsgExp5,
    records.MsgExp6,
    records.MsgExp7,
    records.MsgExp8,
    records.MsgExp9,
    records.MsgExp10,
    records.MsgExp11,
    records.MsgExp12,
)


def status_failures(status: int) -> int:
    """ESC_FAILURE_FLAGS for a CKESC MSG1 status word."""
    flags = 0
    for bits, failure in STATUS_FAILURES:
        if status & bits:
            flags |= failure
    return flags


def telemetry(frame: codec.CkescFrame) -> EscTelemetry | None:
    """A CKESC frame as telemetry; None for commands, service traffic and answers.

    MSG_EXP2..6 (vendor debug), 7 (settings) and 12 (temperature records) map to a record with
    nothing but the node: they keep the ESC online, their contents are not state.
    """
    message = frame.message
    if not isinstance(message, _TELEMETRY):
        return None
    node = frame.node_id
    if isinstance(message, records.Msg1):
        status = int(message.status)
        return EscTelemetry(
            node,
            rpm=message.speed_rpm,
            throttle=message.throttle / records.THROTTLE_MAX,
            status=status,
            status_failures=status_failures(status),
            uncommanded_failures=FAILURE_GENERIC if status & NO_COMMAND else FAILURE_NONE,
        )
    if isinstance(message, records.Msg2):
        return EscTelemetry(
            node,
            voltage_v=message.voltage_v,
            current_a=message.current_a,
            mos_temp_c=message.mos_temp_c,
        )
    if isinstance(message, records.Msg3 | records.MsgExp11):
        return EscTelemetry(
            node,
            mos_temp_c=message.mos_temp_c,
            capacitor_temp_c=message.capacitor_temp_c,
            motor_temp_c=message.motor_temp_c,
            mcu_temp_c=message.mcu_temp_c,
        )
    if isinstance(message, records.MsgExp1):
        return EscTelemetry(
            node,
            rpm=message.speed_rpm,
            voltage_v=message.voltage_v,
            current_a=message.current_a,
        )
    if isinstance(message, records.MsgExp8):
        return EscTelemetry(
            node,
            counters={
                "power_on_count": message.power_on_count,
                "start_count": message.start_count,
                "stop_count": message.stop_count,
            },
        )
    if isinstance(message, records.MsgExp9):
        return EscTelemetry(
            node,
            counters={
                "total_run_time_s": message.total_run_time_s,
                "self_test_fault": int(message.self_test_fault),
            },
            fault_counters=_SELF_TEST_FAULT,
        )
    if isinstance(message, records.MsgExp10):
        return EscTelemetry(
            node,
            counters={"run_time_s": message.run_time_s, "fault_code_2": message.fault_code_2},
            fault_counters=_FAULT_CODE_2,
        )
    return EscTelemetry(node)


def commands_seen(frame: codec.CkescFrame) -> list[CommandSeen]:
    """The throttles of a RawCommand frame, by channel (none for other frames)."""
    message = frame.message
    if isinstance(message, records.RawCommand12b):
        first, scale = 4 * message.group - 3, 1
    elif isinstance(message, records.RawCommand14b):
        first, scale = 1, 1
    elif isinstance(message, records.RawCommand10b):
        first, scale = 1, 2  # RawCommand_10b carries 0..1000, which the ESC doubles
    else:
        return []
    return [
        CommandSeen(float(throttle * scale), "throttle", channel=first + offset)
        for offset, throttle in enumerate(message.throttles)
    ]


class CkescDecoder:
    """CKESC frames through :mod:`~bridge.escs.ckesc.codec`: one frame is one message, so one
    decoder serves every stream."""

    def decode(self, msg: can.Message, esc_nodes: Collection[int] | None = None) -> EscFrame | None:
        return codec.decode(msg, esc_nodes)

    def node_of(self, msg: can.Message) -> int | None:
        if not msg.is_extended_id or msg.is_error_frame:
            return None
        return int(msg.arbitration_id & 0x7F) or None  # node 0 is the host

    def telemetry(self, frame: EscFrame) -> EscTelemetry | None:
        return telemetry(cast(codec.CkescFrame, frame))

    def commands_seen(self, frame: EscFrame) -> list[CommandSeen]:
        return commands_seen(cast(codec.CkescFrame, frame))
