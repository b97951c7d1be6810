"""CKESC message (broadcast) types: CANTest, MSGControl, GET_ESC_ID,
telemetry (MSG1..3, MSG_EXP1..12) and the throttle commands."""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence

from bridge.errors import (
    TailByteError,
    ValueRangeError,
)
from bridge.escs.ckesc._frame import (
    _ESC,
    _HIGHEST,
    _HOST,
    _LOWEST,
    _MEDIUM,
    _R,
    _message,
    _Pack,
    _plain,
)
from bridge.escs.ckesc._records import (
    CanTestReport,
    CanTestRequest,
    GetEscIdAnswer,
    GetEscIdRequest,
    Msg1,
    Msg2,
    Msg3,
    MsgControlAck,
    MsgControlRequest,
    MsgExp1,
    MsgExp2,
    MsgExp3,
    MsgExp4,
    MsgExp5,
    MsgExp6,
    MsgExp7,
    MsgExp8,
    MsgExp9,
    MsgExp10,
    MsgExp11,
    MsgExp12,
    RawCommand10b,
    RawCommand12b,
    RawCommand14b,
    _DebugData,
)
from bridge.escs.ckesc._wire import (
    _CAN_TEST_OPTIONS,
    _CHANNEL,
    _ESC_NODE,
    _GROUP,
    _HOST_CAN_TEST_OPTIONS,
    _HOST_MSG_CONTROL_COMMANDS,
    _MSG_CONTROL_COMMANDS,
    _NIBBLE,
    _SELF_TEST_FAULTS,
    _TEMP_RECORD_KIND_VALUES,
    _TEMP_RECORD_KINDS,
    _THROTTLE,
    _THROTTLE_10B,
    _U8,
    _U16,
    _U32,
    CHANNELS_PER_GROUP,
    THROTTLE_10B_MAX,
    THROTTLE_MAX,
    TYPE_CAN_TEST,
    TYPE_GET_ESC_ID,
    TYPE_MSG1,
    TYPE_MSG2,
    TYPE_MSG3,
    TYPE_MSG_CONTROL,
    TYPE_MSG_EXP1,
    TYPE_MSG_EXP2,
    TYPE_MSG_EXP3,
    TYPE_MSG_EXP4,
    TYPE_MSG_EXP5,
    TYPE_MSG_EXP6,
    TYPE_MSG_EXP7,
    TYPE_MSG_EXP8,
    TYPE_MSG_EXP9,
    TYPE_MSG_EXP10,
    TYPE_MSG_EXP11,
    TYPE_MSG_EXP12,
    TYPE_RAW_COMMAND_10B,
    TYPE_RAW_COMMAND_12B,
    TYPE_RAW_COMMAND_14B,
    Msg1Status,
    _Buf,
    _check,
    _describe,
    _field,
    _field_centi,
)

# ---- CANTest, MSGControl and GET_ESC_ID: the host's request from node 0, answers from ESCs

_S_OPTION_U32 = struct.Struct("<BI")


def _unpack_can_test_request(data: _Buf) -> CanTestRequest:
    option, count = _S_OPTION_U32.unpack_from(data)
    return CanTestRequest(_CAN_TEST_OPTIONS.get(option, option), count)


def _pack_can_test_request(message: CanTestRequest) -> bytes:
    option = _field(message, "option", _HOST_CAN_TEST_OPTIONS)
    return _S_OPTION_U32.pack(option, _field(message, "count", _U32))


def _unpack_can_test_report(data: _Buf) -> CanTestReport:
    option, count = _S_OPTION_U32.unpack_from(data)
    return CanTestReport(count, _CAN_TEST_OPTIONS.get(option, option))


def _pack_can_test_report(message: CanTestReport) -> bytes:
    return _S_OPTION_U32.pack(_field(message, "option", _U8), _field(message, "count", _U32))


def _unpack_msg_control_request(data: _Buf) -> MsgControlRequest:
    option, command = _S_OPTION_U32.unpack_from(data)
    return MsgControlRequest(_MSG_CONTROL_COMMANDS.get(command, command), option)


def _pack_msg_control_request(message: MsgControlRequest) -> bytes:
    command = _field(message, "command", _HOST_MSG_CONTROL_COMMANDS)
    return _S_OPTION_U32.pack(_field(message, "option", _U8), command)


def _unpack_msg_control_ack(data: _Buf) -> MsgControlAck:
    option, command = _S_OPTION_U32.unpack_from(data)
    return MsgControlAck(_MSG_CONTROL_COMMANDS.get(command, command), option)


def _pack_msg_control_ack(message: MsgControlAck) -> bytes:
    return _S_OPTION_U32.pack(_field(message, "option", _U8), _field(message, "command", _U32))


# fmt: off
_message(CanTestRequest, TYPE_CAN_TEST, _HOST, 6, _LOWEST,
         _unpack_can_test_request, _pack_can_test_request)
_message(CanTestReport, TYPE_CAN_TEST, _ESC, 6, _LOWEST,
         _unpack_can_test_report, _pack_can_test_report)
_message(MsgControlRequest, TYPE_MSG_CONTROL, _HOST, 6, _MEDIUM,
         _unpack_msg_control_request, _pack_msg_control_request)
_message(MsgControlAck, TYPE_MSG_CONTROL, _ESC, 6, _MEDIUM,
         _unpack_msg_control_ack, _pack_msg_control_ack)
_message(GetEscIdRequest, TYPE_GET_ESC_ID, _HOST, 2, _MEDIUM,
         *_plain(GetEscIdRequest, "<B", option=_U8))
_message(GetEscIdAnswer, TYPE_GET_ESC_ID, _ESC, 3, _MEDIUM,
         *_plain(GetEscIdAnswer, "<BB", node_id=_ESC_NODE, throttle_channel=_CHANNEL))
# fmt: on

# ---- Telemetry: MSG1..3, MSG_EXP1..12

_S_MSG1 = struct.Struct("<HHH")
_S_MSG2 = struct.Struct("<HHB")


def _unpack_msg1(data: _Buf) -> Msg1:
    speed, throttle, status = _S_MSG1.unpack_from(data)
    return Msg1(speed, throttle, Msg1Status(status))


def _pack_msg1(message: Msg1) -> bytes:
    return _S_MSG1.pack(
        _field(message, "speed_rpm", _U16),
        _field(message, "throttle", _THROTTLE),
        _field(message, "status", _U16),
    )


def _unpack_msg2(data: _Buf) -> Msg2:
    voltage, current, mos_temp = _S_MSG2.unpack_from(data)
    return Msg2(voltage / 100, current / 100, mos_temp)


def _pack_msg2(message: Msg2) -> bytes:
    return _S_MSG2.pack(
        _field_centi(message, "voltage_v"),
        _field_centi(message, "current_a"),
        _field(message, "mos_temp_c", _U8),
    )


def _unpack_exp1(data: _Buf) -> MsgExp1:
    speed, voltage, current = _S_MSG1.unpack_from(data)
    return MsgExp1(speed, voltage / 100, current / 100)


def _pack_exp1(message: MsgExp1) -> bytes:
    return _S_MSG1.pack(
        _field(message, "speed_rpm", _U16),
        _field_centi(message, "voltage_v"),
        _field_centi(message, "current_a"),
    )


def _debug_data(record: Callable[[bytes], _R]) -> tuple[Callable[[_Buf], _R], _Pack]:
    def unpack(data: _Buf) -> _R:
        return record(bytes(data[:6]))

    def pack(message: _DebugData) -> bytes:
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


def _unpack_exp7(data: _Buf) -> MsgExp7:
    s0, s1, s2, s3, s4, s5 = data[:6]
    return MsgExp7(
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


def _pack_exp7(message: MsgExp7) -> bytes:
    nibbles = [0 if name is None else _field(message, name, _NIBBLE) for name in _EXP7_NIBBLES]
    return bytes(low | high << 4 for low, high in zip(nibbles[::2], nibbles[1::2], strict=True))


_S_EXP9 = struct.Struct("<IH")


def _unpack_exp9(data: _Buf) -> MsgExp9:
    run_time, fault = _S_EXP9.unpack_from(data)
    return MsgExp9(run_time, _SELF_TEST_FAULTS.get(fault, fault))


def _pack_exp9(message: MsgExp9) -> bytes:
    return _S_EXP9.pack(
        _field(message, "total_run_time_s", _U32), _field(message, "self_test_fault", _U16)
    )


_S_EXP12 = struct.Struct("<BHIB")


def _unpack_exp12(data: _Buf) -> MsgExp12:
    max_temp, run_count, run_time, tail = _S_EXP12.unpack_from(data)
    kind = _TEMP_RECORD_KINDS.get(tail ^ 0xC0)
    if kind is None:
        raise TailByteError(
            f"MsgExp12 ({TYPE_MSG_EXP12}): tail byte 0x{tail:02X} names no temperature record"
            " (expected 0xC1 MCU, 0xC2 MOS, 0xC3 capacitor or 0xC4 motor)"
        )
    return MsgExp12(kind, max_temp, run_count, run_time)


def _pack_exp12(message: MsgExp12) -> bytes:
    return _S_EXP12.pack(
        _field(message, "max_temp_c", _U8),
        _field(message, "run_count", _U16),
        _field(message, "run_time_s", _U32),
        0xC0 | _field(message, "kind", _TEMP_RECORD_KIND_VALUES),
    )


# fmt: off
_message(Msg1, TYPE_MSG1, _ESC, 7, _LOWEST, _unpack_msg1, _pack_msg1)
_message(Msg2, TYPE_MSG2, _ESC, 6, _LOWEST, _unpack_msg2, _pack_msg2)
_message(Msg3, TYPE_MSG3, _ESC, 8, _LOWEST,
         *_plain(Msg3, "<BBBBxxx",
                 mos_temp_c=_U8, capacitor_temp_c=_U8, motor_temp_c=_U8, mcu_temp_c=_U8))
_message(MsgExp1, TYPE_MSG_EXP1, _ESC, 7, _LOWEST, _unpack_exp1, _pack_exp1)
_message(MsgExp2, TYPE_MSG_EXP2, _ESC, 7, _LOWEST, *_debug_data(MsgExp2))
_message(MsgExp3, TYPE_MSG_EXP3, _ESC, 7, _LOWEST, *_debug_data(MsgExp3))
_message(MsgExp4, TYPE_MSG_EXP4, _ESC, 7, _LOWEST, *_debug_data(MsgExp4))
_message(MsgExp5, TYPE_MSG_EXP5, _ESC, 7, _LOWEST, *_debug_data(MsgExp5))
_message(MsgExp6, TYPE_MSG_EXP6, _ESC, 7, _LOWEST, *_debug_data(MsgExp6))
_message(MsgExp7, TYPE_MSG_EXP7, _ESC, 7, _LOWEST, _unpack_exp7, _pack_exp7)
_message(MsgExp8, TYPE_MSG_EXP8, _ESC, 7, _LOWEST,
         *_plain(MsgExp8, "<HHH", power_on_count=_U16, start_count=_U16, stop_count=_U16))
_message(MsgExp9, TYPE_MSG_EXP9, _ESC, 7, _LOWEST, _unpack_exp9, _pack_exp9)
_message(MsgExp10, TYPE_MSG_EXP10, _ESC, 7, _LOWEST,
         *_plain(MsgExp10, "<IH", run_time_s=_U32, fault_code_2=_U16))
_message(MsgExp11, TYPE_MSG_EXP11, _ESC, 7, _LOWEST,
         *_plain(MsgExp11, "<BBBBxx",
                 mos_temp_c=_U8, mcu_temp_c=_U8, capacitor_temp_c=_U8, motor_temp_c=_U8))
_message(MsgExp12, TYPE_MSG_EXP12, _ESC, 8, _LOWEST,
         _unpack_exp12, _pack_exp12, has_transfer_id=False)
# fmt: on

# ---- Throttle commands (docs/protocols.md §3.3). The ``_bits_*`` helpers are shared with the
# hot-path encoders at the end of the module; each takes 1..n throttles and sends the missing
# channels as 0.


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
        f"{command} throttles[{index}] = {throttle!r} is not {_describe(allowed)}"
    )


def _bits_14b(throttles: Sequence[int]) -> int:
    """Channels 1..4 as the 56-bit UAVCAN v0 stream, its first bit the integer's top bit.

    Each channel is an int14 written as its low 8 bits, then its high 6 bits, MSB first.
    """
    if not 1 <= len(throttles) <= CHANNELS_PER_GROUP:
        raise _count_error("RawCommand14b", throttles, CHANNELS_PER_GROUP)
    bits = 0
    for throttle in throttles:
        if not 0 <= throttle <= THROTTLE_MAX:
            raise _throttle_error("RawCommand14b", throttles, _THROTTLE)
        bits = bits << 14 | (throttle & 0xFF) << 6 | throttle >> 8
    return bits << 14 * (CHANNELS_PER_GROUP - len(throttles))


def _bits_12b(throttles: Sequence[int]) -> int:
    """Up to four channels, 12 bits each, the first in the lowest bits."""
    if not 1 <= len(throttles) <= CHANNELS_PER_GROUP:
        raise _count_error("RawCommand12b", throttles, CHANNELS_PER_GROUP)
    bits = 0
    shift = 0
    for throttle in throttles:
        if not 0 <= throttle <= THROTTLE_MAX:
            raise _throttle_error("RawCommand12b", throttles, _THROTTLE)
        bits |= throttle << shift
        shift += 12
    return bits


def _bits_10b(throttles: Sequence[int]) -> int:
    """Up to six channels, 10 bits each, the first in the lowest bits."""
    if not 1 <= len(throttles) <= 6:
        raise _count_error("RawCommand10b", throttles, 6)
    bits = 0
    shift = 0
    for throttle in throttles:
        if not 0 <= throttle <= THROTTLE_10B_MAX:
            raise _throttle_error("RawCommand10b", throttles, _THROTTLE_10B)
        bits |= throttle << shift
        shift += 10
    return bits


def _record_throttles(
    message: RawCommand14b | RawCommand12b | RawCommand10b, count: int, allowed: range
) -> tuple[int, ...]:
    """A record's throttles, checked: exactly ``count``, as the record stands for every channel."""
    throttles = message.throttles
    what = f"{type(message).__name__}.throttles"
    if not (isinstance(throttles, tuple) and len(throttles) == count):
        raise ValueRangeError(f"{what} = {throttles!r} is not a tuple of {count} throttles")
    for index, throttle in enumerate(throttles):
        _check(f"{what}[{index}]", throttle, allowed)
    return throttles


def _unpack_raw_14b(data: _Buf) -> RawCommand14b:
    bits = int.from_bytes(data, "big") >> 8  # drop the tail byte
    # Each 14-bit chunk holds a channel's low 8 bits above its high 6 bits.
    c1, c2, c3, c4 = (bits >> shift & 0x3FFF for shift in (42, 28, 14, 0))
    return RawCommand14b(
        (
            c1 >> 6 | (c1 & 0x3F) << 8,
            c2 >> 6 | (c2 & 0x3F) << 8,
            c3 >> 6 | (c3 & 0x3F) << 8,
            c4 >> 6 | (c4 & 0x3F) << 8,
        )
    )


def _pack_raw_14b(message: RawCommand14b) -> bytes:
    return _bits_14b(_record_throttles(message, 4, _THROTTLE)).to_bytes(7, "big")


def _unpack_raw_12b(data: _Buf) -> RawCommand12b:
    bits = int.from_bytes(data, "little")
    return RawCommand12b(
        bits >> 48 & 0xFF,
        (bits & 0xFFF, bits >> 12 & 0xFFF, bits >> 24 & 0xFFF, bits >> 36 & 0xFFF),
    )


def _pack_raw_12b(message: RawCommand12b) -> bytes:
    bits = (
        _bits_12b(_record_throttles(message, 4, _THROTTLE)) | _field(message, "group", _GROUP) << 48
    )
    return bits.to_bytes(7, "little")


def _unpack_raw_10b(data: _Buf) -> RawCommand10b:
    # The top four bits of byte 7 are unused.
    bits = int.from_bytes(data, "little")
    return RawCommand10b(
        (
            bits & 0x3FF,
            bits >> 10 & 0x3FF,
            bits >> 20 & 0x3FF,
            bits >> 30 & 0x3FF,
            bits >> 40 & 0x3FF,
            bits >> 50 & 0x3FF,
        )
    )


def _pack_raw_10b(message: RawCommand10b) -> bytes:
    return _bits_10b(_record_throttles(message, 6, _THROTTLE_10B)).to_bytes(8, "little")


# fmt: off
_message(RawCommand14b, TYPE_RAW_COMMAND_14B, _HOST, 8, _HIGHEST, _unpack_raw_14b, _pack_raw_14b)
_message(RawCommand12b, TYPE_RAW_COMMAND_12B, _HOST, 8, _HIGHEST, _unpack_raw_12b, _pack_raw_12b)
_message(RawCommand10b, TYPE_RAW_COMMAND_10B, _HOST, 8, _HIGHEST,
         _unpack_raw_10b, _pack_raw_10b, has_transfer_id=False)
# fmt: on
