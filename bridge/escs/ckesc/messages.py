"""CKESC message (broadcast) types, CANTest, MSGControl, GET_ESC_ID, telemetry (MSG1..3,
MSG_EXP1..12) and the throttle commands: each type's payload layout and its row of the codec's
table (:data:`MESSAGE_TYPES`), and the throttle bit packing the hot-path encoders share. Pure:
no I/O, clock or logging."""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence

from bridge.errors import TailByteError, ValueRangeError
from bridge.escs.ckesc import layout, records
from bridge.escs.ckesc.layout import (
    FROM_ESC,
    FROM_HOST,
    HIGHEST,
    LOWEST,
    MEDIUM,
    message_type,
    plain,
)

# ---- CANTest, MSGControl and GET_ESC_ID: the host's request from node 0, answers from ESCs

_S_OPTION_U32 = struct.Struct("<BI")


def _unpack_can_test_request(data: layout.Buf) -> records.CanTestRequest:
    option, count = _S_OPTION_U32.unpack_from(data)
    return records.CanTestRequest(layout.CAN_TEST_OPTIONS.get(option, option), count)


def _pack_can_test_request(message: records.CanTestRequest) -> bytes:
    option = layout.field_value(message, "option", layout.HOST_CAN_TEST_OPTIONS)
    return _S_OPTION_U32.pack(option, layout.field_value(message, "count", layout.U32))


def _unpack_can_test_report(data: layout.Buf) -> records.CanTestReport:
    option, count = _S_OPTION_U32.unpack_from(data)
    return records.CanTestReport(count, layout.CAN_TEST_OPTIONS.get(option, option))


def _pack_can_test_report(message: records.CanTestReport) -> bytes:
    return _S_OPTION_U32.pack(
        layout.field_value(message, "option", layout.U8),
        layout.field_value(message, "count", layout.U32),
    )


def _unpack_msg_control_request(data: layout.Buf) -> records.MsgControlRequest:
    option, command = _S_OPTION_U32.unpack_from(data)
    return records.MsgControlRequest(layout.MSG_CONTROL_COMMANDS.get(command, command), option)


def _pack_msg_control_request(message: records.MsgControlRequest) -> bytes:
    command = layout.field_value(message, "command", layout.HOST_MSG_CONTROL_COMMANDS)
    return _S_OPTION_U32.pack(layout.field_value(message, "option", layout.U8), command)


def _unpack_msg_control_ack(data: layout.Buf) -> records.MsgControlAck:
    option, command = _S_OPTION_U32.unpack_from(data)
    return records.MsgControlAck(layout.MSG_CONTROL_COMMANDS.get(command, command), option)


def _pack_msg_control_ack(message: records.MsgControlAck) -> bytes:
    return _S_OPTION_U32.pack(
        layout.field_value(message, "option", layout.U8),
        layout.field_value(message, "command", layout.U32),
    )


# fmt: off
_CONTROL_TYPES = (
    message_type(records.CanTestRequest, records.TYPE_CAN_TEST, FROM_HOST, 6, LOWEST,
        _unpack_can_test_request, _pack_can_test_request),
    message_type(records.CanTestReport, records.TYPE_CAN_TEST, FROM_ESC, 6, LOWEST,
        _unpack_can_test_report, _pack_can_test_report),
    message_type(records.MsgControlRequest, records.TYPE_MSG_CONTROL, FROM_HOST, 6, MEDIUM,
        _unpack_msg_control_request, _pack_msg_control_request),
    message_type(records.MsgControlAck, records.TYPE_MSG_CONTROL, FROM_ESC, 6, MEDIUM,
        _unpack_msg_control_ack, _pack_msg_control_ack),
    message_type(records.GetEscIdRequest, records.TYPE_GET_ESC_ID, FROM_HOST, 2, MEDIUM,
        *plain(records.GetEscIdRequest, "<B", option=layout.U8)),
    message_type(records.GetEscIdAnswer, records.TYPE_GET_ESC_ID, FROM_ESC, 3, MEDIUM,
        *plain(records.GetEscIdAnswer, "<BB",
               node_id=layout.ESC_NODE, throttle_channel=layout.CHANNEL)),
)
# fmt: on

# ---- Telemetry: MSG1..3, MSG_EXP1..12

_S_MSG1 = struct.Struct("<HHH")
_S_MSG2 = struct.Struct("<HHB")


def _unpack_msg1(data: layout.Buf) -> records.Msg1:
    speed, throttle, status = _S_MSG1.unpack_from(data)
    return records.Msg1(speed, throttle, records.Msg1Status(status))


def _pack_msg1(message: records.Msg1) -> bytes:
    return _S_MSG1.pack(
        layout.field_value(message, "speed_rpm", layout.U16),
        layout.field_value(message, "throttle", layout.THROTTLE),
        layout.field_value(message, "status", layout.U16),
    )


def _unpack_msg2(data: layout.Buf) -> records.Msg2:
    voltage, current, mos_temp = _S_MSG2.unpack_from(data)
    return records.Msg2(voltage / 100, current / 100, mos_temp)


def _pack_msg2(message: records.Msg2) -> bytes:
    return _S_MSG2.pack(
        layout.field_centi(message, "voltage_v"),
        layout.field_centi(message, "current_a"),
        layout.field_value(message, "mos_temp_c", layout.U8),
    )


def _unpack_exp1(data: layout.Buf) -> records.MsgExp1:
    speed, voltage, current = _S_MSG1.unpack_from(data)
    return records.MsgExp1(speed, voltage / 100, current / 100)


def _pack_exp1(message: records.MsgExp1) -> bytes:
    return _S_MSG1.pack(
        layout.field_value(message, "speed_rpm", layout.U16),
        layout.field_centi(message, "voltage_v"),
        layout.field_centi(message, "current_a"),
    )


def _debug_data(
    record: Callable[[bytes], layout.R],
) -> tuple[Callable[[layout.Buf], layout.R], layout.Pack]:
    def unpack(data: layout.Buf) -> layout.R:
        return record(bytes(data[:6]))

    def pack(message: records.DebugData) -> bytes:
        if isinstance(message.data, bytes) and len(message.data) == 6:
            return message.data
        raise ValueRangeError(
            f"{type(message).__name__}.data = {message.data!r} is not 6 bytes of debug data"
        )

    return unpack, pack


# MSG_EXP7's nibbles in wire order: Set_0 low, Set_0 high, Set_1 low, ... (None: reserved).
_EXP7_NIBBLES = (
    "motor_direction",
    "led",
    "throttle_interface",
    None,
    "active_freewheeling",
    "timing",
    "timing_2",
    "load_type",
    "prop_lock",
    "startup_acceleration",
    "signal_loss_rate",
    None,
)


def _unpack_exp7(data: layout.Buf) -> records.MsgExp7:
    s0, s1, s2, s3, s4, s5 = data[:6]
    return records.MsgExp7(
        s0 & 0xF,
        s0 >> 4,
        s1 & 0xF,
        s2 & 0xF,
        s2 >> 4,
        s3 & 0xF,
        s3 >> 4,
        s4 & 0xF,
        s4 >> 4,
        s5 & 0xF,
    )


def _pack_exp7(message: records.MsgExp7) -> bytes:
    nibbles = [
        0 if name is None else layout.field_value(message, name, layout.NIBBLE)
        for name in _EXP7_NIBBLES
    ]
    return bytes(low | high << 4 for low, high in zip(nibbles[::2], nibbles[1::2], strict=True))


_S_EXP9 = struct.Struct("<IH")


def _unpack_exp9(data: layout.Buf) -> records.MsgExp9:
    run_time, fault = _S_EXP9.unpack_from(data)
    return records.MsgExp9(run_time, layout.SELF_TEST_FAULTS.get(fault, fault))


def _pack_exp9(message: records.MsgExp9) -> bytes:
    return _S_EXP9.pack(
        layout.field_value(message, "total_run_time_s", layout.U32),
        layout.field_value(message, "self_test_fault", layout.U16),
    )


_S_EXP12 = struct.Struct("<BHIB")


def _unpack_exp12(data: layout.Buf) -> records.MsgExp12:
    max_temp, run_count, run_time, tail = _S_EXP12.unpack_from(data)
    kind = layout.TEMP_RECORD_KINDS.get(tail ^ 0xC0)
    if kind is None:
        raise TailByteError(
            f"MsgExp12 ({records.TYPE_MSG_EXP12}): tail byte 0x{tail:02X} names no temperature"
            " record"
            " (expected 0xC1 MCU, 0xC2 MOS, 0xC3 capacitor or 0xC4 motor)"
        )
    return records.MsgExp12(kind, max_temp, run_count, run_time)


def _pack_exp12(message: records.MsgExp12) -> bytes:
    return _S_EXP12.pack(
        layout.field_value(message, "max_temp_c", layout.U8),
        layout.field_value(message, "run_count", layout.U16),
        layout.field_value(message, "run_time_s", layout.U32),
        0xC0 | layout.field_value(message, "kind", layout.TEMP_RECORD_KIND_VALUES),
    )


# fmt: off
_TELEMETRY_TYPES = (
    message_type(records.Msg1, records.TYPE_MSG1, FROM_ESC, 7, LOWEST, _unpack_msg1, _pack_msg1),
    message_type(records.Msg2, records.TYPE_MSG2, FROM_ESC, 6, LOWEST, _unpack_msg2, _pack_msg2),
    message_type(records.Msg3, records.TYPE_MSG3, FROM_ESC, 8, LOWEST,
        *plain(records.Msg3, "<BBBBxxx",
               mos_temp_c=layout.U8, capacitor_temp_c=layout.U8, motor_temp_c=layout.U8,
               mcu_temp_c=layout.U8)),
    message_type(records.MsgExp1, records.TYPE_MSG_EXP1, FROM_ESC, 7, LOWEST,
        _unpack_exp1, _pack_exp1),
    message_type(records.MsgExp2, records.TYPE_MSG_EXP2, FROM_ESC, 7, LOWEST,
        *_debug_data(records.MsgExp2)),
    message_type(records.MsgExp3, records.TYPE_MSG_EXP3, FROM_ESC, 7, LOWEST,
        *_debug_data(records.MsgExp3)),
    message_type(records.MsgExp4, records.TYPE_MSG_EXP4, FROM_ESC, 7, LOWEST,
        *_debug_data(records.MsgExp4)),
    message_type(records.MsgExp5, records.TYPE_MSG_EXP5, FROM_ESC, 7, LOWEST,
        *_debug_data(records.MsgExp5)),
    message_type(records.MsgExp6, records.TYPE_MSG_EXP6, FROM_ESC, 7, LOWEST,
        *_debug_data(records.MsgExp6)),
    message_type(records.MsgExp7, records.TYPE_MSG_EXP7, FROM_ESC, 7, LOWEST,
        _unpack_exp7, _pack_exp7),
    message_type(records.MsgExp8, records.TYPE_MSG_EXP8, FROM_ESC, 7, LOWEST,
        *plain(records.MsgExp8, "<HHH",
               power_on_count=layout.U16, start_count=layout.U16, stop_count=layout.U16)),
    message_type(records.MsgExp9, records.TYPE_MSG_EXP9, FROM_ESC, 7, LOWEST,
        _unpack_exp9, _pack_exp9),
    message_type(records.MsgExp10, records.TYPE_MSG_EXP10, FROM_ESC, 7, LOWEST,
        *plain(records.MsgExp10, "<IH", run_time_s=layout.U32, fault_code_2=layout.U16)),
    message_type(records.MsgExp11, records.TYPE_MSG_EXP11, FROM_ESC, 7, LOWEST,
        *plain(records.MsgExp11, "<BBBBxx",
               mos_temp_c=layout.U8, mcu_temp_c=layout.U8, capacitor_temp_c=layout.U8,
               motor_temp_c=layout.U8)),
    message_type(records.MsgExp12, records.TYPE_MSG_EXP12, FROM_ESC, 8, LOWEST,
        _unpack_exp12, _pack_exp12, has_transfer_id=False),
)
# fmt: on

# ---- Throttle commands (docs/protocols.md §3.3). The ``bits_*`` helpers are shared with the
# hot-path encoders of :mod:`~bridge.escs.ckesc.codec`; each takes 1..n throttles and sends the
# missing channels as 0.


def _count_error(command: str, throttles: Sequence[int], most: int) -> ValueRangeError:
    return ValueRangeError(f"{command} takes 1..{most} throttles, got {len(throttles)}")


def _throttle_error(command: str, throttles: Sequence[int], allowed: range) -> ValueRangeError:
    """The error for the first throttle outside ``allowed`` (the caller has seen one)."""
    index, throttle = next(
        (index, throttle)
        for index, throttle in enumerate(throttles)
        if not (isinstance(throttle, int) and throttle in allowed)
    )
    return ValueRangeError(
        f"{command} throttles[{index}] = {throttle!r} is not {layout.describe(allowed)}"
    )


def bits_14b(throttles: Sequence[int]) -> int:
    """Channels 1..4 as the 56-bit UAVCAN v0 stream, its first bit the integer's top bit.

    Each channel is an int14 written as its low 8 bits, then its high 6 bits, MSB first.
    """
    if not 1 <= len(throttles) <= records.CHANNELS_PER_GROUP:
        raise _count_error("RawCommand14b", throttles, records.CHANNELS_PER_GROUP)
    bits = 0
    for throttle in throttles:
        if not 0 <= throttle <= records.THROTTLE_MAX:
            raise _throttle_error("RawCommand14b", throttles, layout.THROTTLE)
        bits = bits << 14 | (throttle & 0xFF) << 6 | throttle >> 8
    return bits << 14 * (records.CHANNELS_PER_GROUP - len(throttles))


def bits_12b(throttles: Sequence[int]) -> int:
    """Up to four channels, 12 bits each, the first in the lowest bits."""
    if not 1 <= len(throttles) <= records.CHANNELS_PER_GROUP:
        raise _count_error("RawCommand12b", throttles, records.CHANNELS_PER_GROUP)
    bits = 0
    shift = 0
    for throttle in throttles:
        if not 0 <= throttle <= records.THROTTLE_MAX:
            raise _throttle_error("RawCommand12b", throttles, layout.THROTTLE)
        bits |= throttle << shift
        shift += 12
    return bits


def bits_10b(throttles: Sequence[int]) -> int:
    """Up to six channels, 10 bits each, the first in the lowest bits."""
    if not 1 <= len(throttles) <= 6:
        raise _count_error("RawCommand10b", throttles, 6)
    bits = 0
    shift = 0
    for throttle in throttles:
        if not 0 <= throttle <= records.THROTTLE_10B_MAX:
            raise _throttle_error("RawCommand10b", throttles, layout.THROTTLE_10B)
        bits |= throttle << shift
        shift += 10
    return bits


def _record_throttles(
    message: records.RawCommand14b | records.RawCommand12b | records.RawCommand10b,
    count: int,
    allowed: range,
) -> tuple[int, ...]:
    """A record's throttles, checked: exactly ``count``, as the record stands for every channel."""
    throttles = message.throttles
    what = f"{type(message).__name__}.throttles"
    if not (isinstance(throttles, tuple) and len(throttles) == count):
        raise ValueRangeError(f"{what} = {throttles!r} is not a tuple of {count} throttles")
    for index, throttle in enumerate(throttles):
        layout.check_value(f"{what}[{index}]", throttle, allowed)
    return throttles


def _unpack_raw_14b(data: layout.Buf) -> records.RawCommand14b:
    bits = int.from_bytes(data, "big") >> 8  # drop the tail byte
    # Each 14-bit chunk holds a channel's low 8 bits above its high 6 bits.
    c1, c2, c3, c4 = (bits >> shift & 0x3FFF for shift in (42, 28, 14, 0))
    return records.RawCommand14b(
        (
            c1 >> 6 | (c1 & 0x3F) << 8,
            c2 >> 6 | (c2 & 0x3F) << 8,
            c3 >> 6 | (c3 & 0x3F) << 8,
            c4 >> 6 | (c4 & 0x3F) << 8,
        )
    )


def _pack_raw_14b(message: records.RawCommand14b) -> bytes:
    return bits_14b(_record_throttles(message, 4, layout.THROTTLE)).to_bytes(7, "big")


def _unpack_raw_12b(data: layout.Buf) -> records.RawCommand12b:
    bits = int.from_bytes(data, "little")
    return records.RawCommand12b(
        bits >> 48 & 0xFF,
        (bits & 0xFFF, bits >> 12 & 0xFFF, bits >> 24 & 0xFFF, bits >> 36 & 0xFFF),
    )


def _pack_raw_12b(message: records.RawCommand12b) -> bytes:
    bits = (
        bits_12b(_record_throttles(message, 4, layout.THROTTLE))
        | layout.field_value(message, "group", layout.GROUP) << 48
    )
    return bits.to_bytes(7, "little")


def _unpack_raw_10b(data: layout.Buf) -> records.RawCommand10b:
    # The top four bits of byte 7 are unused.
    bits = int.from_bytes(data, "little")
    return records.RawCommand10b(
        (
            bits & 0x3FF,
            bits >> 10 & 0x3FF,
            bits >> 20 & 0x3FF,
            bits >> 30 & 0x3FF,
            bits >> 40 & 0x3FF,
            bits >> 50 & 0x3FF,
        )
    )


def _pack_raw_10b(message: records.RawCommand10b) -> bytes:
    return bits_10b(_record_throttles(message, 6, layout.THROTTLE_10B)).to_bytes(8, "little")


# fmt: off
_THROTTLE_TYPES = (
    message_type(records.RawCommand14b, records.TYPE_RAW_COMMAND_14B, FROM_HOST, 8, HIGHEST,
        _unpack_raw_14b, _pack_raw_14b),
    message_type(records.RawCommand12b, records.TYPE_RAW_COMMAND_12B, FROM_HOST, 8, HIGHEST,
        _unpack_raw_12b, _pack_raw_12b),
    message_type(records.RawCommand10b, records.TYPE_RAW_COMMAND_10B, FROM_HOST, 8, HIGHEST,
        _unpack_raw_10b, _pack_raw_10b, has_transfer_id=False),
)
# fmt: on

MESSAGE_TYPES = (*_CONTROL_TYPES, *_TELEMETRY_TYPES, *_THROTTLE_TYPES)
"""Every message (broadcast) type's row, in the order the codec looks them up."""
