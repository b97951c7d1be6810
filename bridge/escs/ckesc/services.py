"""CKESC service types, configuration (210..222) and information (240..242): each request's and
response's payload layout and its row of the codec's table (:data:`SERVICE_TYPES`). Pure: no
I/O, clock or logging."""

from __future__ import annotations

import struct
from collections.abc import Callable

from bridge.errors import FrameError
from bridge.escs.ckesc import layout, records
from bridge.escs.ckesc.layout import (
    LOW,
    LOWEST,
    MEDIUM,
    REQUEST,
    RESPONSE,
    plain,
    service_type,
)

# ---- Configuration services 210..222. Most responses repeat the request's layout.

_SET_ID_FIELDS = {"node_id": layout.ESC_NODE, "throttle_channel": layout.CHANNEL}
_S_3U8 = struct.Struct("<BBB")
_S_SET_FREQ = struct.Struct("<BBBB")


def _set_led(
    record: Callable[[bool, records.LedColor, int], layout.R],
) -> tuple[Callable[[layout.Buf], layout.R], layout.Pack]:
    def unpack(data: layout.Buf) -> layout.R:
        save, color, blink = _S_3U8.unpack_from(data)
        return record(bool(save), records.LedColor(color), blink)

    def pack(message: records.SetLed) -> bytes:
        return _S_3U8.pack(
            layout.field_value(message, "save", layout.BOOL),
            layout.field_value(message, "color", layout.LED_RGB),
            layout.field_value(message, "blink_hz", layout.BLINK_HZ),
        )

    return unpack, pack


def _set_rotation(
    record: Callable[[records.Rotation | int], layout.R],
) -> tuple[Callable[[layout.Buf], layout.R], layout.Pack]:
    def unpack(data: layout.Buf) -> layout.R:
        return record(layout.ROTATIONS.get(data[0], data[0]))

    def pack(message: records.SetRotation) -> bytes:
        return bytes((layout.field_value(message, "rotation", layout.ROTATION_VALUES),))

    return unpack, pack


def _set_freq(
    record: Callable[[bool, int, int, int], layout.R], write_range: range
) -> tuple[Callable[[layout.Buf], layout.R], layout.Pack]:
    """``write_range``: the intervals a write may carry (a read's are ignored by the ESC)."""

    def unpack(data: layout.Buf) -> layout.R:
        write, msg1, msg2, msg3 = _S_SET_FREQ.unpack_from(data)
        return record(bool(write), 2 * msg1, 2 * msg2, 2 * msg3)

    def pack(message: records.SetFreq) -> bytes:
        write = layout.field_value(message, "write", layout.BOOL)
        allowed = write_range if write else layout.INTERVAL_MS
        return _S_SET_FREQ.pack(
            write,
            layout.field_stepped(message, "msg1_interval_ms", allowed),
            layout.field_stepped(message, "msg2_interval_ms", allowed),
            layout.field_stepped(message, "msg3_interval_ms", allowed),
        )

    return unpack, pack


def _throttle_select(
    record: Callable[[records.ThrottleSource | int], layout.R],
) -> tuple[Callable[[layout.Buf], layout.R], layout.Pack]:
    def unpack(data: layout.Buf) -> layout.R:
        return record(layout.THROTTLE_SOURCES.get(data[0], data[0]))

    def pack(message: records.ThrottleSelect) -> bytes:
        return bytes((layout.field_value(message, "source", layout.THROTTLE_SOURCE_VALUES),))

    return unpack, pack


def _unpack_self_test_request(data: layout.Buf) -> records.SelfTestRequest:
    return records.SelfTestRequest()


def _pack_self_test_request(message: records.SelfTestRequest) -> bytes:
    return b""


def _unpack_self_test_response(data: layout.Buf) -> records.SelfTestResponse:
    return records.SelfTestResponse(data[0] == 0)


def _pack_self_test_response(message: records.SelfTestResponse) -> bytes:
    return bytes((0 if layout.field_value(message, "passed", layout.BOOL) else 1,))


_S_EXPAND_SET = struct.Struct("<HB")


def _unpack_expand_set(data: layout.Buf) -> records.ExpandSetRequest:
    command, part = _S_EXPAND_SET.unpack_from(data)
    return records.ExpandSetRequest(layout.EXPAND_SET_COMMANDS.get(command, command), part)


def _pack_expand_set(message: records.ExpandSetRequest) -> bytes:
    command = layout.field_value(message, "command", layout.EXPAND_SET_VALUES)
    what = f"ExpandSetRequest.part (for {records.ExpandSetCommand(command).name})"
    return _S_EXPAND_SET.pack(
        command, layout.check_value(what, message.part, layout.EXPAND_SET_PARTS[command])
    )


# fmt: off
_CONFIGURATION_TYPES = (
    service_type(records.SetIdRequest, records.SERVICE_SET_ID, REQUEST, 3, MEDIUM,
        *plain(records.SetIdRequest, "<BB", **_SET_ID_FIELDS)),
    service_type(records.SetIdResponse, records.SERVICE_SET_ID, RESPONSE, 3, MEDIUM,
        *plain(records.SetIdResponse, "<BB", **_SET_ID_FIELDS)),
    service_type(records.SetBaudRequest, records.SERVICE_SET_BAUD, REQUEST, 2, MEDIUM,
        *plain(records.SetBaudRequest, "<B", baud_code=layout.BAUD_CODE)),
    service_type(records.SetBaudResponse, records.SERVICE_SET_BAUD, RESPONSE, 2, MEDIUM,
        *plain(records.SetBaudResponse, "<B", baud_code=layout.BAUD_CODE)),
    service_type(records.SetLedRequest, records.SERVICE_SET_LED, REQUEST, 4, LOW,
        *_set_led(records.SetLedRequest)),
    service_type(records.SetLedResponse, records.SERVICE_SET_LED, RESPONSE, 4, LOW,
        *_set_led(records.SetLedResponse)),
    service_type(records.SetRotationRequest, records.SERVICE_SET_ROTATION, REQUEST, 2, LOW,
        *_set_rotation(records.SetRotationRequest)),
    service_type(records.SetRotationResponse, records.SERVICE_SET_ROTATION, RESPONSE, 2, LOW,
        *_set_rotation(records.SetRotationResponse)),
    service_type(records.SetFreqRequest, records.SERVICE_SET_FREQ, REQUEST, 5, MEDIUM,
        *_set_freq(records.SetFreqRequest, layout.INTERVAL_WRITE_MS)),
    # A response reports whatever intervals the ESC has.
    service_type(records.SetFreqResponse, records.SERVICE_SET_FREQ, RESPONSE, 5, MEDIUM,
        *_set_freq(records.SetFreqResponse, layout.INTERVAL_MS)),
    service_type(records.ThrottleSelectRequest, records.SERVICE_THROTTLE_SELECT, REQUEST, 2, MEDIUM,
        *_throttle_select(records.ThrottleSelectRequest)),
    service_type(records.ThrottleSelectResponse, records.SERVICE_THROTTLE_SELECT, RESPONSE, 2,
        MEDIUM, *_throttle_select(records.ThrottleSelectResponse)),
    service_type(records.SelfTestRequest, records.SERVICE_SELF_TEST, REQUEST, 1, LOWEST,
        _unpack_self_test_request, _pack_self_test_request),
    service_type(records.SelfTestResponse, records.SERVICE_SELF_TEST, RESPONSE, 2, LOWEST,
        _unpack_self_test_response, _pack_self_test_response),
    service_type(records.ExpandSetRequest, records.SERVICE_EXPAND_SET, REQUEST, 4, MEDIUM,
        _unpack_expand_set, _pack_expand_set),
)
# fmt: on

# ---- Information services 240..242: a one-byte request, a seven-byte response

_S_ESC_INFO = struct.Struct("<7B")
_S_MAINTENANCE_0 = struct.Struct("<IBBB")
_S_MAINTENANCE_1 = struct.Struct("<IHB")
_S_MAINTENANCE_2 = struct.Struct("<HHHB")
_S_MAJOR_CONFIG = struct.Struct("<BBBBBxx")


def _unpack_esc_info(data: layout.Buf) -> records.EscInfoResponse:
    cells, current, hardware, protocol, year, month, day = _S_ESC_INFO.unpack_from(data)
    return records.EscInfoResponse(cells, 10 * current, hardware, protocol, year, month, day)


def _pack_esc_info(message: records.EscInfoResponse) -> bytes:
    return _S_ESC_INFO.pack(
        layout.field_value(message, "max_cells", layout.U8),
        layout.field_stepped(message, "max_current_a", layout.MAX_CURRENT_A),
        layout.field_value(message, "hardware_version", layout.U8),
        layout.field_value(message, "protocol_version", layout.U8),
        layout.field_value(message, "firmware_year", layout.U8),
        layout.field_value(message, "firmware_month", layout.U8),
        layout.field_value(message, "firmware_day", layout.U8),
    )


def _unpack_maintenance(
    data: layout.Buf,
) -> records.Maintenance0Response | records.Maintenance1Response | records.Maintenance2Response:
    # Byte 6 is taken to echo the request's option (see the module docstring).
    option = data[6]
    if option == 0:
        total, mos, capacitor, _ = _S_MAINTENANCE_0.unpack_from(data)
        return records.Maintenance0Response(total, mos, capacitor)
    if option == 1:
        run_time, runs, _ = _S_MAINTENANCE_1.unpack_from(data)
        return records.Maintenance1Response(run_time, runs)
    if option == 2:
        power_ons, stops, fault, _ = _S_MAINTENANCE_2.unpack_from(data)
        return records.Maintenance2Response(
            power_ons, stops, layout.SELF_TEST_FAULTS.get(fault, fault)
        )
    raise FrameError(
        f"Maintenance Information ({records.SERVICE_MAINTENANCE}) response: option (byte 6) ="
        f" {option}, expected 0, 1 or 2"
    )


def _pack_maintenance_0(message: records.Maintenance0Response) -> bytes:
    return _S_MAINTENANCE_0.pack(
        layout.field_value(message, "total_run_time_s", layout.U32),
        layout.field_value(message, "max_mos_temp_c", layout.U8),
        layout.field_value(message, "max_capacitor_temp_c", layout.U8),
        0,
    )


def _pack_maintenance_1(message: records.Maintenance1Response) -> bytes:
    return _S_MAINTENANCE_1.pack(
        layout.field_value(message, "run_time_s", layout.U32),
        layout.field_value(message, "run_count", layout.U16),
        1,
    )


def _pack_maintenance_2(message: records.Maintenance2Response) -> bytes:
    return _S_MAINTENANCE_2.pack(
        layout.field_value(message, "power_on_count", layout.U16),
        layout.field_value(message, "stop_count", layout.U16),
        layout.field_value(message, "self_test_fault", layout.U16),
        2,
    )


def _unpack_major_config(data: layout.Buf) -> records.MajorConfigResponse:
    throttle, led, msg1, msg2, msg3 = _S_MAJOR_CONFIG.unpack_from(data)
    return records.MajorConfigResponse(
        bool(throttle & 0x80),
        records.ThrottleSource(throttle >> 6 & 1),
        throttle & 0x3F,
        led >> 3,
        records.LedColor(led & 0x07),
        2 * msg1,
        2 * msg2,
        2 * msg3,
    )


def _pack_major_config(message: records.MajorConfigResponse) -> bytes:
    return _S_MAJOR_CONFIG.pack(
        layout.field_value(message, "direction_reversed", layout.BOOL) << 7
        | layout.field_value(message, "throttle_source", layout.THROTTLE_SOURCE_VALUES) << 6
        | layout.field_value(message, "throttle_channel", range(0x40)),
        layout.field_value(message, "led_blink_hz", range(0x20)) << 3
        | layout.field_value(message, "led_color", layout.LED_RGB),
        layout.field_stepped(message, "msg1_interval_ms", layout.INTERVAL_MS),
        layout.field_stepped(message, "msg2_interval_ms", layout.INTERVAL_MS),
        layout.field_stepped(message, "msg3_interval_ms", layout.INTERVAL_MS),
    )


# fmt: off
_INFORMATION_TYPES = (
    service_type(records.EscInfoRequest, records.SERVICE_ESC_INFO, REQUEST, 2, MEDIUM,
        *plain(records.EscInfoRequest, "<B", option=layout.U8)),
    service_type(records.EscInfoResponse, records.SERVICE_ESC_INFO, RESPONSE, 8, MEDIUM,
        _unpack_esc_info, _pack_esc_info),
    service_type(records.MaintenanceRequest, records.SERVICE_MAINTENANCE, REQUEST, 2, MEDIUM,
        *plain(records.MaintenanceRequest, "<B", option=range(3))),
    # The three responses share one decoder, which tells them apart by byte 6.
    service_type(records.Maintenance0Response, records.SERVICE_MAINTENANCE, RESPONSE, 8, MEDIUM,
        _unpack_maintenance, _pack_maintenance_0),
    service_type(records.Maintenance1Response, records.SERVICE_MAINTENANCE, RESPONSE, 8, MEDIUM,
        _unpack_maintenance, _pack_maintenance_1),
    service_type(records.Maintenance2Response, records.SERVICE_MAINTENANCE, RESPONSE, 8, MEDIUM,
        _unpack_maintenance, _pack_maintenance_2),
    service_type(records.MajorConfigRequest, records.SERVICE_MAJOR_CONFIG, REQUEST, 2, MEDIUM,
        *plain(records.MajorConfigRequest, "<B", option=layout.U8)),
    service_type(records.MajorConfigResponse, records.SERVICE_MAJOR_CONFIG, RESPONSE, 8, MEDIUM,
        _unpack_major_config, _pack_major_config),
)
# fmt: on

SERVICE_TYPES = (*_CONFIGURATION_TYPES, *_INFORMATION_TYPES)
"""Every service type's rows, in the order the codec looks them up."""
