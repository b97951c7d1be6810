"""CKESC service types: configuration (210..222) and information (240..242)."""

from __future__ import annotations

import struct
from collections.abc import Callable

from bridge.errors import (
    FrameError,
)
from bridge.escs.ckesc._frame import (
    _LOW,
    _LOWEST,
    _MEDIUM,
    _R,
    _REQUEST,
    _RESPONSE,
    _Pack,
    _plain,
    _service,
)
from bridge.escs.ckesc._records import (
    EscInfoRequest,
    EscInfoResponse,
    ExpandSetRequest,
    Maintenance0Response,
    Maintenance1Response,
    Maintenance2Response,
    MaintenanceRequest,
    MajorConfigRequest,
    MajorConfigResponse,
    SelfTestRequest,
    SelfTestResponse,
    SetBaudRequest,
    SetBaudResponse,
    SetFreqRequest,
    SetFreqResponse,
    SetIdRequest,
    SetIdResponse,
    SetLedRequest,
    SetLedResponse,
    SetRotationRequest,
    SetRotationResponse,
    ThrottleSelectRequest,
    ThrottleSelectResponse,
    _SetFreq,
    _SetLed,
    _SetRotation,
    _ThrottleSelect,
)
from bridge.escs.ckesc._wire import (
    _BAUD_CODE,
    _BLINK_HZ,
    _BOOL,
    _CHANNEL,
    _ESC_NODE,
    _EXPAND_SET_COMMANDS,
    _EXPAND_SET_PARTS,
    _EXPAND_SET_VALUES,
    _INTERVAL_MS,
    _INTERVAL_WRITE_MS,
    _LED_RGB,
    _MAX_CURRENT_A,
    _ROTATION_VALUES,
    _ROTATIONS,
    _SELF_TEST_FAULTS,
    _THROTTLE_SOURCE_VALUES,
    _THROTTLE_SOURCES,
    _U8,
    _U16,
    _U32,
    SERVICE_ESC_INFO,
    SERVICE_EXPAND_SET,
    SERVICE_MAINTENANCE,
    SERVICE_MAJOR_CONFIG,
    SERVICE_SELF_TEST,
    SERVICE_SET_BAUD,
    SERVICE_SET_FREQ,
    SERVICE_SET_ID,
    SERVICE_SET_LED,
    SERVICE_SET_ROTATION,
    SERVICE_THROTTLE_SELECT,
    ExpandSetCommand,
    LedColor,
    Rotation,
    ThrottleSource,
    _Buf,
    _check,
    _field,
    _field_stepped,
)

# ---- Configuration services 210..222. Most responses repeat the request's layout.

_SET_ID_FIELDS = {"node_id": _ESC_NODE, "throttle_channel": _CHANNEL}
_S_3U8 = struct.Struct("<BBB")
_S_SET_FREQ = struct.Struct("<BBBB")


def _set_led(record: Callable[[bool, LedColor, int], _R]) -> tuple[Callable[[_Buf], _R], _Pack]:
    def unpack(data: _Buf) -> _R:
        save, color, blink = _S_3U8.unpack_from(data)
        return record(bool(save), LedColor(color), blink)

    def pack(message: _SetLed) -> bytes:
        return _S_3U8.pack(
            _field(message, "save", _BOOL),
            _field(message, "color", _LED_RGB),
            _field(message, "blink_hz", _BLINK_HZ),
        )

    return unpack, pack


def _set_rotation(record: Callable[[Rotation | int], _R]) -> tuple[Callable[[_Buf], _R], _Pack]:
    def unpack(data: _Buf) -> _R:
        return record(_ROTATIONS.get(data[0], data[0]))

    def pack(message: _SetRotation) -> bytes:
        return bytes((_field(message, "rotation", _ROTATION_VALUES),))

    return unpack, pack


def _set_freq(
    record: Callable[[bool, int, int, int], _R], write_range: range
) -> tuple[Callable[[_Buf], _R], _Pack]:
    """``write_range``: the intervals a write may carry (a read's are ignored by the ESC)."""

    def unpack(data: _Buf) -> _R:
        write, msg1, msg2, msg3 = _S_SET_FREQ.unpack_from(data)
        return record(bool(write), 2 * msg1, 2 * msg2, 2 * msg3)

    def pack(message: _SetFreq) -> bytes:
        write = _field(message, "write", _BOOL)
        allowed = write_range if write else _INTERVAL_MS
        return _S_SET_FREQ.pack(
            write,
            _field_stepped(message, "msg1_interval_ms", allowed),
            _field_stepped(message, "msg2_interval_ms", allowed),
            _field_stepped(message, "msg3_interval_ms", allowed),
        )

    return unpack, pack


def _throttle_select(
    record: Callable[[ThrottleSource | int], _R],
) -> tuple[Callable[[_Buf], _R], _Pack]:
    def unpack(data: _Buf) -> _R:
        return record(_THROTTLE_SOURCES.get(data[0], data[0]))

    def pack(message: _ThrottleSelect) -> bytes:
        return bytes((_field(message, "source", _THROTTLE_SOURCE_VALUES),))

    return unpack, pack


def _unpack_self_test_request(data: _Buf) -> SelfTestRequest:
    return SelfTestRequest()


def _pack_self_test_request(message: SelfTestRequest) -> bytes:
    return b""


def _unpack_self_test_response(data: _Buf) -> SelfTestResponse:
    return SelfTestResponse(data[0] == 0)


def _pack_self_test_response(message: SelfTestResponse) -> bytes:
    return bytes((0 if _field(message, "passed", _BOOL) else 1,))


_S_EXPAND_SET = struct.Struct("<HB")


def _unpack_expand_set(data: _Buf) -> ExpandSetRequest:
    command, part = _S_EXPAND_SET.unpack_from(data)
    return ExpandSetRequest(_EXPAND_SET_COMMANDS.get(command, command), part)


def _pack_expand_set(message: ExpandSetRequest) -> bytes:
    command = _field(message, "command", _EXPAND_SET_VALUES)
    what = f"ExpandSetRequest.part (for {ExpandSetCommand(command).name})"
    return _S_EXPAND_SET.pack(command, _check(what, message.part, _EXPAND_SET_PARTS[command]))


# fmt: off
_service(SetIdRequest, SERVICE_SET_ID, _REQUEST, 3, _MEDIUM,
         *_plain(SetIdRequest, "<BB", **_SET_ID_FIELDS))
_service(SetIdResponse, SERVICE_SET_ID, _RESPONSE, 3, _MEDIUM,
         *_plain(SetIdResponse, "<BB", **_SET_ID_FIELDS))
_service(SetBaudRequest, SERVICE_SET_BAUD, _REQUEST, 2, _MEDIUM,
         *_plain(SetBaudRequest, "<B", baud_code=_BAUD_CODE))
_service(SetBaudResponse, SERVICE_SET_BAUD, _RESPONSE, 2, _MEDIUM,
         *_plain(SetBaudResponse, "<B", baud_code=_BAUD_CODE))
_service(SetLedRequest, SERVICE_SET_LED, _REQUEST, 4, _LOW, *_set_led(SetLedRequest))
_service(SetLedResponse, SERVICE_SET_LED, _RESPONSE, 4, _LOW, *_set_led(SetLedResponse))
_service(SetRotationRequest, SERVICE_SET_ROTATION, _REQUEST, 2, _LOW,
         *_set_rotation(SetRotationRequest))
_service(SetRotationResponse, SERVICE_SET_ROTATION, _RESPONSE, 2, _LOW,
         *_set_rotation(SetRotationResponse))
_service(SetFreqRequest, SERVICE_SET_FREQ, _REQUEST, 5, _MEDIUM,
         *_set_freq(SetFreqRequest, _INTERVAL_WRITE_MS))
# A response reports whatever intervals the ESC has.
_service(SetFreqResponse, SERVICE_SET_FREQ, _RESPONSE, 5, _MEDIUM,
         *_set_freq(SetFreqResponse, _INTERVAL_MS))
_service(ThrottleSelectRequest, SERVICE_THROTTLE_SELECT, _REQUEST, 2, _MEDIUM,
         *_throttle_select(ThrottleSelectRequest))
_service(ThrottleSelectResponse, SERVICE_THROTTLE_SELECT, _RESPONSE, 2, _MEDIUM,
         *_throttle_select(ThrottleSelectResponse))
_service(SelfTestRequest, SERVICE_SELF_TEST, _REQUEST, 1, _LOWEST,
         _unpack_self_test_request, _pack_self_test_request)
_service(SelfTestResponse, SERVICE_SELF_TEST, _RESPONSE, 2, _LOWEST,
         _unpack_self_test_response, _pack_self_test_response)
_service(ExpandSetRequest, SERVICE_EXPAND_SET, _REQUEST, 4, _MEDIUM,
         _unpack_expand_set, _pack_expand_set)
# fmt: on

# ---- Information services 240..242: a one-byte request, a seven-byte response

_S_ESC_INFO = struct.Struct("<7B")
_S_MAINTENANCE_0 = struct.Struct("<IBBB")
_S_MAINTENANCE_1 = struct.Struct("<IHB")
_S_MAINTENANCE_2 = struct.Struct("<HHHB")
_S_MAJOR_CONFIG = struct.Struct("<BBBBBxx")


def _unpack_esc_info(data: _Buf) -> EscInfoResponse:
    cells, current, hardware, protocol, year, month, day = _S_ESC_INFO.unpack_from(data)
    return EscInfoResponse(cells, 10 * current, hardware, protocol, year, month, day)


def _pack_esc_info(message: EscInfoResponse) -> bytes:
    return _S_ESC_INFO.pack(
        _field(message, "max_cells", _U8),
        _field_stepped(message, "max_current_a", _MAX_CURRENT_A),
        _field(message, "hardware_version", _U8),
        _field(message, "protocol_version", _U8),
        _field(message, "firmware_year", _U8),
        _field(message, "firmware_month", _U8),
        _field(message, "firmware_day", _U8),
    )


def _unpack_maintenance(
    data: _Buf,
) -> Maintenance0Response | Maintenance1Response | Maintenance2Response:
    # Byte 6 is taken to echo the request's option (see the module docstring).
    option = data[6]
    if option == 0:
        total, mos, capacitor, _ = _S_MAINTENANCE_0.unpack_from(data)
        return Maintenance0Response(total, mos, capacitor)
    if option == 1:
        run_time, runs, _ = _S_MAINTENANCE_1.unpack_from(data)
        return Maintenance1Response(run_time, runs)
    if option == 2:
        power_ons, stops, fault, _ = _S_MAINTENANCE_2.unpack_from(data)
        return Maintenance2Response(power_ons, stops, _SELF_TEST_FAULTS.get(fault, fault))
    raise FrameError(
        f"Maintenance Information ({SERVICE_MAINTENANCE}) response: option (byte 6) = {option},"
        " expected 0, 1 or 2"
    )


def _pack_maintenance_0(message: Maintenance0Response) -> bytes:
    return _S_MAINTENANCE_0.pack(
        _field(message, "total_run_time_s", _U32),
        _field(message, "max_mos_temp_c", _U8),
        _field(message, "max_capacitor_temp_c", _U8),
        0,
    )


def _pack_maintenance_1(message: Maintenance1Response) -> bytes:
    return _S_MAINTENANCE_1.pack(
        _field(message, "run_time_s", _U32), _field(message, "run_count", _U16), 1
    )


def _pack_maintenance_2(message: Maintenance2Response) -> bytes:
    return _S_MAINTENANCE_2.pack(
        _field(message, "power_on_count", _U16),
        _field(message, "stop_count", _U16),
        _field(message, "self_test_fault", _U16),
        2,
    )


def _unpack_major_config(data: _Buf) -> MajorConfigResponse:
    throttle, led, msg1, msg2, msg3 = _S_MAJOR_CONFIG.unpack_from(data)
    return MajorConfigResponse(
        bool(throttle & 0x80),
        ThrottleSource(throttle >> 6 & 1),
        throttle & 0x3F,
        led >> 3,
        LedColor(led & 0x07),
        2 * msg1,
        2 * msg2,
        2 * msg3,
    )


def _pack_major_config(message: MajorConfigResponse) -> bytes:
    return _S_MAJOR_CONFIG.pack(
        _field(message, "direction_reversed", _BOOL) << 7
        | _field(message, "throttle_source", _THROTTLE_SOURCE_VALUES) << 6
        | _field(message, "throttle_channel", range(0x40)),
        _field(message, "led_blink_hz", range(0x20)) << 3 | _field(message, "led_color", _LED_RGB),
        _field_stepped(message, "msg1_interval_ms", _INTERVAL_MS),
        _field_stepped(message, "msg2_interval_ms", _INTERVAL_MS),
        _field_stepped(message, "msg3_interval_ms", _INTERVAL_MS),
    )


# fmt: off
_service(EscInfoRequest, SERVICE_ESC_INFO, _REQUEST, 2, _MEDIUM,
         *_plain(EscInfoRequest, "<B", option=_U8))
_service(EscInfoResponse, SERVICE_ESC_INFO, _RESPONSE, 8, _MEDIUM, _unpack_esc_info, _pack_esc_info)
_service(MaintenanceRequest, SERVICE_MAINTENANCE, _REQUEST, 2, _MEDIUM,
         *_plain(MaintenanceRequest, "<B", option=range(3)))
# The three responses share one decoder, which tells them apart by byte 6.
_service(Maintenance0Response, SERVICE_MAINTENANCE, _RESPONSE, 8, _MEDIUM,
         _unpack_maintenance, _pack_maintenance_0)
_service(Maintenance1Response, SERVICE_MAINTENANCE, _RESPONSE, 8, _MEDIUM,
         _unpack_maintenance, _pack_maintenance_1)
_service(Maintenance2Response, SERVICE_MAINTENANCE, _RESPONSE, 8, _MEDIUM,
         _unpack_maintenance, _pack_maintenance_2)
_service(MajorConfigRequest, SERVICE_MAJOR_CONFIG, _REQUEST, 2, _MEDIUM,
         *_plain(MajorConfigRequest, "<B", option=_U8))
_service(MajorConfigResponse, SERVICE_MAJOR_CONFIG, _RESPONSE, 8, _MEDIUM,
         _unpack_major_config, _pack_major_config)
# fmt: on
