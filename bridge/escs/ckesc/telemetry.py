"""CKESC frames as neutral telemetry (:class:`~bridge.escs.family.EscTelemetry`) and commands
read back (:class:`~bridge.escs.family.CommandSeen`): the family's side of the ESC state.

Failure flags follow MAVLink's ESC_FAILURE_FLAGS; a MSG1 status word maps through
:data:`STATUS_FAILURES` (docs/telemetry.md). MSG_EXP9's self-test fault and MSG_EXP10's
fault code are counters whose non-zero value is a fault (``fault_counters``).
"""

from __future__ import annotations

from typing import Final

from bridge.escs import ckesc
from bridge.escs.family import (
    FAILURE_GENERIC,
    FAILURE_NONE,
    FAILURE_OVER_CURRENT,
    FAILURE_OVER_TEMPERATURE,
    FAILURE_OVER_VOLTAGE,
    CommandSeen,
    EscTelemetry,
)

_S = ckesc.Msg1Status
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
    ckesc.Msg1,
    ckesc.Msg2,
    ckesc.Msg3,
    ckesc.MsgExp1,
    ckesc.MsgExp2,
    ckesc.MsgExp3,
    ckesc.MsgExp4,
    ckesc.MsgExp5,
    ckesc.MsgExp6,
    ckesc.MsgExp7,
    ckesc.MsgExp8,
    ckesc.MsgExp9,
    ckesc.MsgExp10,
    ckesc.MsgExp11,
    ckesc.MsgExp12,
)


def status_failures(status: int) -> int:
    """ESC_FAILURE_FLAGS for a CKESC MSG1 status word."""
    flags = 0
    for bits, failure in STATUS_FAILURES:
        if status & bits:
            flags |= failure
    return flags


def telemetry(frame: ckesc.CkescFrame) -> EscTelemetry | None:
    """A CKESC frame as telemetry; None for commands, service traffic and answers.

    MSG_EXP2..6 (vendor debug), 7 (settings) and 12 (temperature records) map to a record with
    nothing but the node: they keep the ESC online, their contents are not state.
    """
    message = frame.message
    if not isinstance(message, _TELEMETRY):
        return None
    node = frame.node_id
    if isinstance(message, ckesc.Msg1):
        status = int(message.status)
        return EscTelemetry(
            node,
            rpm=message.speed_rpm,
            throttle=message.throttle / ckesc.THROTTLE_MAX,
            status=status,
            status_failures=status_failures(status),
            uncommanded_failures=FAILURE_GENERIC if status & NO_COMMAND else FAILURE_NONE,
        )
    if isinstance(message, ckesc.Msg2):
        return EscTelemetry(
            node,
            voltage_v=message.voltage_v,
            current_a=message.current_a,
            mos_temp_c=message.mos_temp_c,
        )
    if isinstance(message, ckesc.Msg3 | ckesc.MsgExp11):
        return EscTelemetry(
            node,
            mos_temp_c=message.mos_temp_c,
            capacitor_temp_c=message.capacitor_temp_c,
            motor_temp_c=message.motor_temp_c,
            mcu_temp_c=message.mcu_temp_c,
        )
    if isinstance(message, ckesc.MsgExp1):
        return EscTelemetry(
            node,
            rpm=message.speed_rpm,
            voltage_v=message.voltage_v,
            current_a=message.current_a,
        )
    if isinstance(message, ckesc.MsgExp8):
        return EscTelemetry(
            node,
            counters={
                "power_on_count": message.power_on_count,
                "start_count": message.start_count,
                "stop_count": message.stop_count,
            },
        )
    if isinstance(message, ckesc.MsgExp9):
        return EscTelemetry(
            node,
            counters={
                "total_run_time_s": message.total_run_time_s,
                "self_test_fault": int(message.self_test_fault),
            },
            fault_counters=_SELF_TEST_FAULT,
        )
    if isinstance(message, ckesc.MsgExp10):
        return EscTelemetry(
            node,
            counters={"run_time_s": message.run_time_s, "fault_code_2": message.fault_code_2},
            fault_counters=_FAULT_CODE_2,
        )
    return EscTelemetry(node)


def commands_seen(frame: ckesc.CkescFrame) -> list[CommandSeen]:
    """The throttles of a RawCommand frame, by channel (none for other frames)."""
    message = frame.message
    if isinstance(message, ckesc.RawCommand12b):
        first, scale = 4 * message.group - 3, 1
    elif isinstance(message, ckesc.RawCommand14b):
        first, scale = 1, 1
    elif isinstance(message, ckesc.RawCommand10b):
        first, scale = 1, 2  # RawCommand_10b carries 0..1000, which the ESC doubles
    else:
        return []
    return [
        CommandSeen(float(throttle * scale), "throttle", channel=first + offset)
        for offset, throttle in enumerate(message.throttles)
    ]
