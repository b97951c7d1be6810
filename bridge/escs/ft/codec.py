"""FT encoding and decoding: records to frames and back (docs/protocols.md §4). Pure: no I/O,
clock or logging."""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from typing import Final, NamedTuple, TypeAlias

import can

from bridge._compat import assert_never
from bridge.errors import (
    CrcError,
    DlcError,
    FrameError,
    NotExtendedIdError,
    ValueRangeError,
)
from bridge.escs.ft.records import (
    COMMAND_RECORDS,
    CURRENT_SCALE,
    DUTY_MAX,
    DUTY_SCALE,
    ERPM_SCALE,
    ESC_ID_MAX,
    ESC_ID_MIN,
    FRACTION_MAX,
    FRACTION_SCALE,
    FT_ID_MAX,
    I16_MAX,
    I16_MIN,
    I24_MAX,
    I24_MIN,
    I32_MAX,
    I32_MIN,
    ID_CURRENT_DLCS,
    POSITION_MAX_DEG,
    POSITION_SCALE,
    RT_CURRENT_SCALE,
    RT_DUTY_SCALE,
    RT_TEMP_SCALE,
    RT_VOLTAGE_SCALE,
    TELEMETRY_DLC,
    Command,
    FtCommand,
    FtFrame,
    Gear,
    RealtimeData0,
    RealtimeData1,
    RealtimeData2,
    SetCurrent,
    SetCurrentBrake,
    SetCurrentBrakePercent,
    SetCurrentPercent,
    SetDuty,
    SetErpm,
    SetIdCurrent,
    SetPosition,
    Telemetry,
    can_id,
    crc16_modbus,
)

_I32 = struct.Struct(">i")
_I32_U8 = struct.Struct(">iB")
_I32_U8_U16 = struct.Struct(">iBH")
_I32_U16 = struct.Struct(">iH")
_U16 = struct.Struct(">H")
# An i24 is read as its signed top 16 bits and unsigned low 8 bits: (hi << 8) | lo then
# sign-extends bit 23 for free, and one unpack call reads the whole frame.
_I24X2_U16 = struct.Struct(">hBhBH")
_I16X3 = struct.Struct(">hhh")
_I16X3_U16 = struct.Struct(">hhhH")

_GEARS: Final = tuple(Gear)
_GEAR_VALUES: Final = frozenset(_GEARS)
_RECORD_COMMANDS: Final = {key: command for command, key in COMMAND_RECORDS.items()}

# ---------------------------------------------------------------------------------------------
# Encoding


class _Quantity(NamedTuple):
    """What a command's i32 carries: record field name, unit, scale and range."""

    name: str
    unit: str
    scale: int
    limit: float | None  # the unscaled value must lie in -limit..limit; None: i32 alone


_CURRENT: Final = _Quantity("current_a", " A", CURRENT_SCALE, None)
_DUTY: Final = _Quantity("duty", "", DUTY_SCALE, DUTY_MAX)
_FRACTION: Final = _Quantity("fraction", "", FRACTION_SCALE, FRACTION_MAX)
_ERPM: Final = _Quantity("erpm", " erpm", ERPM_SCALE, None)
_POSITION: Final = _Quantity("angle_deg", " deg", POSITION_SCALE, POSITION_MAX_DEG)

_QUANTITIES: Final[dict[int, _Quantity]] = {
    Command.SET_CURRENT_GEAR_CRC16: _CURRENT,
    Command.SET_CURRENT_BRAKE_CRC16: _CURRENT,
    Command.SET_DUTY_GEAR_CRC16: _DUTY,
    Command.SET_CURRENT_PERCENT_CRC16: _FRACTION,
    Command.SET_CURRENT_PERCENT_GEAR_CRC16: _FRACTION,
    Command.SET_CURRENT_BRAKE_PERCENT_CRC16: _FRACTION,
    Command.SET_ERPM_GEAR_CRC16: _ERPM,
    Command.SET_POSITION_GEAR_CRC16: _POSITION,
    Command.SET_ID_CURRENT_CRC16: _CURRENT,
    Command.SET_CURRENT_GEAR: _CURRENT,
    Command.SET_CURRENT_PERCENT_GEAR: _FRACTION,
    Command.SET_DUTY_GEAR: _DUTY,
    Command.SET_ERPM_GEAR: _ERPM,
    Command.SET_POSITION_GEAR: _POSITION,
    Command.SET_CURRENT_BRAKE: _CURRENT,
    Command.SET_CURRENT_BRAKE_PERCENT: _FRACTION,
}


def _hot_layout(command: Command) -> tuple[int, float, float, bool, bool]:
    """(scale, lowest, highest unscaled value let through, gear?, crc?) for encode_command.

    For i32-only quantities the bounds sit one LSB beyond i32: they stop NaN and infinities
    before round() (which would raise on them), and the exact i32 check after rounding decides.
    """
    quantity = _QUANTITIES[command]
    _, has_crc, has_gear = COMMAND_RECORDS[command]
    scale = quantity.scale
    if quantity.limit is not None:
        return scale, -quantity.limit, quantity.limit, has_gear, has_crc
    return scale, (I32_MIN - 1) / scale, (I32_MAX + 1) / scale, has_gear, has_crc


_LAYOUTS: Final = {command: _hot_layout(command) for command in Command}


def _scaled_range(lowest: int, highest: int, scale: int, unit: str) -> str:
    """``lowest/scale..highest/scale`` printed exactly (every FT scale is a power of ten)."""
    decimals = len(str(scale)) - 1
    return f"{lowest / scale:.{decimals}f}..{highest / scale:.{decimals}f}{unit}"


def _value_error(command: int, value: float) -> ValueRangeError:
    """Build the error for a command value that failed encode_command's checks (cold path)."""
    quantity = _QUANTITIES[command]
    unit = quantity.unit
    what = f"{Command(command).name} (0x{command:02X}): {quantity.name}={value!r}{unit}"
    if quantity.limit is not None:
        allowed = f"{-quantity.limit:g}..{quantity.limit:g}{unit}"
        return ValueRangeError(f"{what} outside the allowed range {allowed}")
    allowed = _scaled_range(I32_MIN, I32_MAX, quantity.scale, unit)
    if not math.isfinite(value):
        return ValueRangeError(f"{what} is not finite; allowed range {allowed}")
    return ValueRangeError(
        f"{what} scales (x{quantity.scale}) to {round(value * quantity.scale)}, which does not fit "
        f"i32 ({I32_MIN}..{I32_MAX}); allowed range {allowed}"
    )


def encode_command(
    esc_id: int, command: Command, value: float, gear: Gear = Gear.NONE
) -> can.Message:
    """Encode one FT command; the hot path used by the CAN writer.

    ``value`` is in the command's natural unit: A for currents, -1..1 for duty and current
    fractions, erpm, or degrees (-180..180) for positions. It is rounded to the nearest wire
    LSB. ``gear`` must be ``Gear.NONE`` for commands without a gear byte.

    Raises:
        ValueRangeError: ``esc_id`` outside 0..255, ``command`` not a :class:`Command`, a value
            that is NaN, infinite, outside the command's range or beyond i32 once scaled, or a
            gear outside 0..4 or given to a command that has none. Never wrapped or clipped.
    """
    layout = _LAYOUTS.get(command)
    if layout is None:
        raise ValueRangeError(f"command={command!r} is not an FT command")
    scale, lowest, highest, has_gear, has_crc = layout
    if not ESC_ID_MIN <= esc_id <= ESC_ID_MAX:
        raise ValueRangeError(f"esc_id={esc_id!r} outside {ESC_ID_MIN}..{ESC_ID_MAX}")
    # A chained comparison is False for NaN, so NaN is refused here too.
    if not lowest <= value <= highest:
        raise _value_error(command, value)
    raw = round(value * scale)
    if not I32_MIN <= raw <= I32_MAX:
        raise _value_error(command, value)
    if has_gear:
        if gear not in _GEAR_VALUES:
            raise ValueRangeError(
                f"{Command(command).name} (0x{command:02X}): gear={gear!r} outside 0..4"
            )
        payload = _I32_U8.pack(raw, gear)
    else:
        if gear != Gear.NONE:
            raise ValueRangeError(
                f"{Command(command).name} (0x{command:02X}) has no gear byte; "
                f"gear={gear!r}, expected Gear.NONE"
            )
        payload = _I32.pack(raw)
    if has_crc:
        payload += _U16.pack(crc16_modbus(payload))
    return can.Message(arbitration_id=(esc_id << 8) | command, data=payload, is_extended_id=True)


def _to_int(name: str, value: float, scale: int, lowest: int, highest: int, kind: str) -> int:
    """Scale and round a telemetry value, refusing anything that does not fit ``kind``."""
    if math.isfinite(value):  # round() raises on NaN and infinities
        raw = round(value * scale)
        if lowest <= raw <= highest:
            return raw
    raise ValueRangeError(
        f"{name}={value!r} does not fit {kind} at scale x{scale}: allowed range "
        f"{_scaled_range(lowest, highest, scale, '')}"
    )


def _i24_bytes(name: str, value: float, scale: int) -> bytes:
    raw = _to_int(name, value, scale, I24_MIN, I24_MAX, "i24")
    return (raw & 0xFFFFFF).to_bytes(3, "big")


def _i16(name: str, value: float, scale: int) -> int:
    return _to_int(name, value, scale, I16_MIN, I16_MAX, "i16")


def _telemetry_message(esc_id: int, telemetry: Telemetry, payload: bytes) -> can.Message:
    return can.Message(
        arbitration_id=can_id(esc_id, telemetry),
        data=payload + _U16.pack(crc16_modbus(payload)),
        is_extended_id=True,
    )


def encode(frame: FtFrame) -> can.Message:
    """Encode a command or telemetry record as an extended-ID :class:`can.Message`.

    Commands go through :func:`encode_command`. Telemetry values only have to fit their i24
    or i16 field (this exists for the ESC simulator).

    Raises:
        ValueRangeError: as :func:`encode_command`; a telemetry value beyond i24/i16, NaN or
            infinite; or ``SetCurrentPercent(gear=None, crc=False)``, which has no FT command.
    """
    esc_id = frame.esc_id
    message = frame.message
    value: float
    gear: Gear | None = None  # None: the record has no gear or (0x03) chose none
    crc = True
    match message:
        case SetCurrent(current_a=value, gear=gear, crc=crc):
            pass
        case SetCurrentBrake(current_a=value, crc=crc):
            pass
        case SetDuty(duty=value, gear=gear, crc=crc):
            pass
        case SetCurrentPercent(fraction=value, gear=gear, crc=crc):
            pass
        case SetCurrentBrakePercent(fraction=value, crc=crc):
            pass
        case SetErpm(erpm=value, gear=gear, crc=crc):
            pass
        case SetPosition(angle_deg=value, gear=gear, crc=crc):
            pass
        case SetIdCurrent(current_a=value):
            pass
        case RealtimeData0():
            return _telemetry_message(
                esc_id,
                Telemetry.REALTIME_DATA_0,
                _i24_bytes("motor_current_a", message.motor_current_a, RT_CURRENT_SCALE)
                + _i24_bytes("battery_current_a", message.battery_current_a, RT_CURRENT_SCALE),
            )
        case RealtimeData1():
            return _telemetry_message(
                esc_id,
                Telemetry.REALTIME_DATA_1,
                _i24_bytes("erpm", message.erpm, ERPM_SCALE)
                + _i24_bytes("duty", message.duty, RT_DUTY_SCALE),
            )
        case RealtimeData2():
            return _telemetry_message(
                esc_id,
                Telemetry.REALTIME_DATA_2,
                _I16X3.pack(
                    _i16("mosfet_temp_c", message.mosfet_temp_c, RT_TEMP_SCALE),
                    _i16("motor_temp_c", message.motor_temp_c, RT_TEMP_SCALE),
                    _i16("battery_voltage_v", message.battery_voltage_v, RT_VOLTAGE_SCALE),
                ),
            )
        case _:
            assert_never(message)
    command = _RECORD_COMMANDS.get((type(message), bool(crc), gear is not None))
    if command is None:
        raise ValueRangeError(
            f"{message!r} has no FT command: without a gear only the CRC form (0x03) exists; "
            "use crc=True or a gear (Gear.NONE for no gear limiting)"
        )
    return encode_command(esc_id, command, value, Gear.NONE if gear is None else gear)


# ---------------------------------------------------------------------------------------------
# Decoding

_Decoder: TypeAlias = Callable[[int, bytearray], FtFrame]


def _name(command: int) -> str:
    kind = Command if command in COMMAND_RECORDS else Telemetry
    return f"{kind(command).name} (0x{command:02X})"


def _dlc_error(command: int, esc_id: int, data: bytearray, expected: object) -> DlcError:
    return DlcError(
        f"FT {_name(command)}, ESC {esc_id}: {len(data)} data bytes, expected {expected}"
    )


def _crc_error(
    command: int, esc_id: int, data: bytearray, received: int, computed: int
) -> CrcError:
    return CrcError(
        f"FT {_name(command)}, ESC {esc_id}: CRC 0x{received:04X} in frame, expected "
        f"0x{computed:04X} over {bytes(data[:-2]).hex(' ')}"
    )


def _gear(command: int, esc_id: int, byte: int) -> Gear:
    if byte >= len(_GEARS):
        raise FrameError(f"FT {_name(command)}, ESC {esc_id}: gear byte {byte}, expected 0..4")
    return _GEARS[byte]


def _geared_decoder(command: Command, make: Callable[[int, Gear], FtCommand]) -> _Decoder:
    """Decoder for a command carrying an i32 and a gear byte, with or without CRC."""
    if COMMAND_RECORDS[command][1]:

        def decode_crc(esc_id: int, data: bytearray) -> FtFrame:
            if len(data) != _I32_U8_U16.size:
                raise _dlc_error(command, esc_id, data, _I32_U8_U16.size)
            raw, gear, crc = _I32_U8_U16.unpack(data)
            computed = crc16_modbus(data[:-2])
            if computed != crc:
                raise _crc_error(command, esc_id, data, crc, computed)
            return FtFrame(esc_id, make(raw, _gear(command, esc_id, gear)))

        return decode_crc

    def decode_plain(esc_id: int, data: bytearray) -> FtFrame:
        if len(data) != _I32_U8.size:
            raise _dlc_error(command, esc_id, data, _I32_U8.size)
        raw, gear = _I32_U8.unpack(data)
        return FtFrame(esc_id, make(raw, _gear(command, esc_id, gear)))

    return decode_plain


def _plain_decoder(command: Command, make: Callable[[int], FtCommand]) -> _Decoder:
    """Decoder for a command carrying an i32 only, with or without CRC.

    0x14 also accepts the DLC-7 form of the seed's C example: the CRC still covers every
    byte but the last two, and the extra byte is ignored.
    """
    if COMMAND_RECORDS[command][1]:
        sizes = ID_CURRENT_DLCS if command == Command.SET_ID_CURRENT_CRC16 else (_I32_U16.size,)
        expected = " or ".join(map(str, sizes))

        def decode_crc(esc_id: int, data: bytearray) -> FtFrame:
            if len(data) not in sizes:
                raise _dlc_error(command, esc_id, data, expected)
            raw = _I32.unpack_from(data)[0]
            (crc,) = _U16.unpack_from(data, len(data) - 2)
            computed = crc16_modbus(data[:-2])
            if computed != crc:
                raise _crc_error(command, esc_id, data, crc, computed)
            return FtFrame(esc_id, make(raw))

        return decode_crc

    def decode_plain(esc_id: int, data: bytearray) -> FtFrame:
        if len(data) != _I32.size:
            raise _dlc_error(command, esc_id, data, _I32.size)
        return FtFrame(esc_id, make(_I32.unpack(data)[0]))

    return decode_plain


def _decode_realtime_0(esc_id: int, data: bytearray) -> FtFrame:
    if len(data) != TELEMETRY_DLC:
        raise _dlc_error(Telemetry.REALTIME_DATA_0, esc_id, data, TELEMETRY_DLC)
    motor_hi, motor_lo, battery_hi, battery_lo, crc = _I24X2_U16.unpack(data)
    computed = crc16_modbus(data[:6])
    if computed != crc:
        raise _crc_error(Telemetry.REALTIME_DATA_0, esc_id, data, crc, computed)
    return FtFrame(
        esc_id,
        RealtimeData0(
            ((motor_hi << 8) | motor_lo) / RT_CURRENT_SCALE,
            ((battery_hi << 8) | battery_lo) / RT_CURRENT_SCALE,
        ),
    )


def _decode_realtime_1(esc_id: int, data: bytearray) -> FtFrame:
    if len(data) != TELEMETRY_DLC:
        raise _dlc_error(Telemetry.REALTIME_DATA_1, esc_id, data, TELEMETRY_DLC)
    erpm_hi, erpm_lo, duty_hi, duty_lo, crc = _I24X2_U16.unpack(data)
    computed = crc16_modbus(data[:6])
    if computed != crc:
        raise _crc_error(Telemetry.REALTIME_DATA_1, esc_id, data, crc, computed)
    return FtFrame(
        esc_id,
        RealtimeData1((erpm_hi << 8) | erpm_lo, ((duty_hi << 8) | duty_lo) / RT_DUTY_SCALE),
    )


def _decode_realtime_2(esc_id: int, data: bytearray) -> FtFrame:
    if len(data) != TELEMETRY_DLC:
        raise _dlc_error(Telemetry.REALTIME_DATA_2, esc_id, data, TELEMETRY_DLC)
    mosfet, motor, voltage, crc = _I16X3_U16.unpack(data)
    computed = crc16_modbus(data[:6])
    if computed != crc:
        raise _crc_error(Telemetry.REALTIME_DATA_2, esc_id, data, crc, computed)
    return FtFrame(
        esc_id,
        RealtimeData2(mosfet / RT_TEMP_SCALE, motor / RT_TEMP_SCALE, voltage / RT_VOLTAGE_SCALE),
    )


# Wire integer → record, per command: the inverse of encode()'s scaling. Division by the
# integer scale (not multiplication by its reciprocal) gives the float nearest to the exact
# quotient, so values exactly representable at the scale survive a round trip unchanged.
_GEARED_MAKERS: Final[dict[Command, Callable[[int, Gear], FtCommand]]] = {
    Command.SET_CURRENT_GEAR_CRC16: lambda raw, gear: SetCurrent(raw / CURRENT_SCALE, gear, True),
    Command.SET_CURRENT_GEAR: lambda raw, gear: SetCurrent(raw / CURRENT_SCALE, gear, False),
    Command.SET_DUTY_GEAR_CRC16: lambda raw, gear: SetDuty(raw / DUTY_SCALE, gear, True),
    Command.SET_DUTY_GEAR: lambda raw, gear: SetDuty(raw / DUTY_SCALE, gear, False),
    Command.SET_CURRENT_PERCENT_GEAR_CRC16: lambda raw, gear: SetCurrentPercent(
        raw / FRACTION_SCALE, gear, True
    ),
    Command.SET_CURRENT_PERCENT_GEAR: lambda raw, gear: SetCurrentPercent(
        raw / FRACTION_SCALE, gear, False
    ),
    Command.SET_ERPM_GEAR_CRC16: lambda raw, gear: SetErpm(raw, gear, True),
    Command.SET_ERPM_GEAR: lambda raw, gear: SetErpm(raw, gear, False),
    Command.SET_POSITION_GEAR_CRC16: lambda raw, gear: SetPosition(
        raw / POSITION_SCALE, gear, True
    ),
    Command.SET_POSITION_GEAR: lambda raw, gear: SetPosition(raw / POSITION_SCALE, gear, False),
}
_PLAIN_MAKERS: Final[dict[Command, Callable[[int], FtCommand]]] = {
    Command.SET_CURRENT_BRAKE_CRC16: lambda raw: SetCurrentBrake(raw / CURRENT_SCALE, True),
    Command.SET_CURRENT_BRAKE: lambda raw: SetCurrentBrake(raw / CURRENT_SCALE, False),
    Command.SET_CURRENT_PERCENT_CRC16: lambda raw: SetCurrentPercent(
        raw / FRACTION_SCALE, None, True
    ),
    Command.SET_CURRENT_BRAKE_PERCENT_CRC16: lambda raw: SetCurrentBrakePercent(
        raw / FRACTION_SCALE, True
    ),
    Command.SET_CURRENT_BRAKE_PERCENT: lambda raw: SetCurrentBrakePercent(
        raw / FRACTION_SCALE, False
    ),
    Command.SET_ID_CURRENT_CRC16: lambda raw: SetIdCurrent(raw / CURRENT_SCALE),
}

_DECODERS: Final[dict[int, _Decoder]] = {
    Telemetry.REALTIME_DATA_0: _decode_realtime_0,
    Telemetry.REALTIME_DATA_1: _decode_realtime_1,
    Telemetry.REALTIME_DATA_2: _decode_realtime_2,
    **{command: _geared_decoder(command, make) for command, make in _GEARED_MAKERS.items()},
    **{command: _plain_decoder(command, make) for command, make in _PLAIN_MAKERS.items()},
}


def _not_extended(msg: can.Message) -> NotExtendedIdError:
    if msg.is_error_frame:
        came = "an error frame"
    elif msg.is_remote_frame:
        came = f"a remote (RTR) frame, ID 0x{msg.arbitration_id:X}"
    else:
        came = f"an 11-bit ID 0x{msg.arbitration_id:03X}"
    return NotExtendedIdError(f"FT uses 29-bit data frames only; got {came}")


def decode(msg: can.Message) -> FtFrame | None:
    """Decode an FT command or telemetry frame; ``None`` if the frame is not FT's.

    Not FT's: an ID with any of bits 28..16 set, or a command byte that names no FT command
    or telemetry frame.

    Raises:
        NotExtendedIdError: an error frame, a remote frame or an 11-bit ID.
        DlcError: a data length other than the command's (0x14: 6 or 7; telemetry: 8).
        CrcError: the CRC does not match the bytes before it.
        FrameError: a gear byte above 4.
    """
    if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
        raise _not_extended(msg)
    arbitration_id: int = msg.arbitration_id
    if arbitration_id > FT_ID_MAX:
        return None
    decoder = _DECODERS.get(arbitration_id & 0xFF)
    if decoder is None:
        return None
    return decoder(arbitration_id >> 8, msg.data)
