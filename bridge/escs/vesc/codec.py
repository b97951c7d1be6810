"""VESC encoding and decoding: records to frames and back (docs/protocols.md §6).

Pure: no I/O, clock or logging. Values are rounded to the nearest wire step (ties to even),
not truncated as the firmware's own casts do, and a value that does not fit its field is
refused, never wrapped or clipped (docs/protocols.md §6.3).
"""

from __future__ import annotations

import dataclasses
import math
import struct
from collections.abc import Callable
from typing import Final, NamedTuple, TypeAlias

import can

from bridge._compat import assert_never
from bridge.errors import DlcError, NotExtendedIdError, ValueRangeError
from bridge.escs.vesc.records import (
    ADC_SCALE,
    COMMAND_DLC,
    COMMAND_PACKETS,
    CONTROLLER_ID_MAX,
    CONTROLLER_ID_MIN,
    CURRENT_REL_MAX,
    CURRENT_REL_SCALE,
    CURRENT_SCALE,
    DUTY_MAX,
    DUTY_SCALE,
    ENERGY_SCALE,
    I16_MAX,
    I16_MIN,
    I32_MAX,
    I32_MIN,
    NOTIFY_BOOT_MAX_DLC,
    PID_POSITION_SCALE,
    PING_DLC,
    PONG_DLCS,
    RPM_SCALE,
    STATUS_CURRENT_SCALE,
    STATUS_DUTY_SCALE,
    TEMP_SCALE,
    VESC_ID_MAX,
    VOLTAGE_SCALE,
    HwType,
    NotifyBoot,
    Packet,
    Ping,
    Pong,
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
    VescCommand,
    VescFrame,
    VescStatus,
    can_id,
)

# Big-endian wire layouts: i32 ``i``, i16 ``h``, u8 ``B``.
_I32: Final = struct.Struct(">i")
_I32X2: Final = struct.Struct(">ii")
_I32_I16X2: Final = struct.Struct(">ihh")
_I16X4: Final = struct.Struct(">hhhh")
_U8X2: Final = struct.Struct(">BB")

# ---------------------------------------------------------------------------------------------
# Commands: the hot path


class _Quantity(NamedTuple):
    """What a command's i32 carries: record field name, unit, scale and range."""

    name: str
    unit: str
    scale: int
    limit: float | None  # the unscaled value must lie in -limit..limit; None: i32 alone


_QUANTITIES: Final[dict[int, _Quantity]] = {
    Packet.SET_DUTY: _Quantity("duty", "", DUTY_SCALE, DUTY_MAX),
    Packet.SET_CURRENT: _Quantity("current_a", " A", CURRENT_SCALE, None),
    Packet.SET_CURRENT_BRAKE: _Quantity("current_a", " A", CURRENT_SCALE, None),
    Packet.SET_RPM: _Quantity("erpm", " erpm", RPM_SCALE, None),
    Packet.SET_CURRENT_REL: _Quantity("fraction", "", CURRENT_REL_SCALE, CURRENT_REL_MAX),
}


def _layout(quantity: _Quantity) -> tuple[int, float, float]:
    """(scale, lowest, highest unscaled value let through) for encode_command. Without a
    limit the bounds sit one step beyond i32: they stop NaN and infinities before round()
    (which would raise on them), and the exact i32 check after rounding decides."""
    scale, limit = quantity.scale, quantity.limit
    if limit is not None:
        return scale, -limit, limit
    return scale, (I32_MIN - 1) / scale, (I32_MAX + 1) / scale


_LAYOUTS: Final = {packet: _layout(quantity) for packet, quantity in _QUANTITIES.items()}


def _name(packet: int) -> str:
    return f"{Packet(packet).name} ({packet})"


def _scaled_range(lowest: int, highest: int, scale: int, unit: str) -> str:
    """``lowest/scale..highest/scale`` printed exactly (every VESC scale is a power of ten or
    50)."""
    decimals = math.ceil(math.log10(scale)) if scale > 1 else 0
    return f"{lowest / scale:.{decimals}f}..{highest / scale:.{decimals}f}{unit}"


def _command_error(packet: int, value: float) -> ValueRangeError:
    """The error for a command value that failed encode_command's checks (cold path)."""
    name, unit, scale, limit = _QUANTITIES[packet]
    what = f"VESC {_name(packet)}: {name}={value!r}{unit}"
    if limit is not None:
        return ValueRangeError(f"{what} outside the allowed range {-limit:g}..{limit:g}{unit}")
    allowed = _scaled_range(I32_MIN, I32_MAX, scale, unit)
    if not math.isfinite(value):
        return ValueRangeError(f"{what} is not finite; allowed range {allowed}")
    return ValueRangeError(
        f"{what} scales (x{scale}) to {round(value * scale)}, which does not fit i32 "
        f"({I32_MIN}..{I32_MAX}); allowed range {allowed}"
    )


def encode_command(controller_id: int, packet: Packet, value: float) -> can.Message:
    """One VESC motor command, the output loop's hot path.

    ``value`` is in the packet's unit: duty and current fraction -1..1, currents in A, speed
    in electrical rpm; it is rounded to the nearest wire step. ``controller_id`` 255 addresses
    every VESC.

    Raises:
        ValueRangeError: ``controller_id`` outside 0..255, ``packet`` not a motor command, or a
            value that is NaN, infinite, outside the packet's range or beyond i32 once scaled.
    """
    layout = _LAYOUTS.get(packet)
    if layout is None:
        raise ValueRangeError(f"packet={packet!r} is not a VESC motor command")
    scale, lowest, highest = layout
    if not CONTROLLER_ID_MIN <= controller_id <= CONTROLLER_ID_MAX:
        raise ValueRangeError(
            f"controller_id={controller_id!r} outside {CONTROLLER_ID_MIN}..{CONTROLLER_ID_MAX}"
        )
    # A chained comparison is False for NaN, so NaN is refused here too.
    if not lowest <= value <= highest:
        raise _command_error(packet, value)
    raw = round(value * scale)
    if not I32_MIN <= raw <= I32_MAX:
        raise _command_error(packet, value)
    return can.Message(
        arbitration_id=packet << 8 | controller_id, data=_I32.pack(raw), is_extended_id=True
    )


# ---------------------------------------------------------------------------------------------
# Everything else (the simulator's status frames, PING and PONG)


class _StatusLayout(NamedTuple):
    """A status frame: its record, its wire fields (i32 ``i``, i16 ``h``, big-endian) and the
    scale of each record field, in order. Wire fields past the record's are reserved: sent as
    0, ignored when read."""

    record: type[VescStatus]
    wire: struct.Struct
    scales: tuple[int, ...]


_STATUS_LAYOUTS: Final[dict[Packet, _StatusLayout]] = {
    Packet.STATUS: _StatusLayout(Status, _I32_I16X2, (1, STATUS_CURRENT_SCALE, STATUS_DUTY_SCALE)),
    Packet.STATUS_2: _StatusLayout(Status2, _I32X2, (ENERGY_SCALE, ENERGY_SCALE)),
    Packet.STATUS_3: _StatusLayout(Status3, _I32X2, (ENERGY_SCALE, ENERGY_SCALE)),
    Packet.STATUS_4: _StatusLayout(
        Status4, _I16X4, (TEMP_SCALE, TEMP_SCALE, STATUS_CURRENT_SCALE, PID_POSITION_SCALE)
    ),
    Packet.STATUS_5: _StatusLayout(Status5, _I32_I16X2, (1, VOLTAGE_SCALE)),
    Packet.STATUS_6: _StatusLayout(Status6, _I16X4, (ADC_SCALE,) * 4),
}
_STATUS_PACKETS: Final = {layout.record: packet for packet, layout in _STATUS_LAYOUTS.items()}
_BOUNDS: Final = {"i": (I32_MIN, I32_MAX, "i32"), "h": (I16_MIN, I16_MAX, "i16")}


def _to_int(name: str, value: float, scale: int, kind: str) -> int:
    """Scale and round a value, refusing anything that does not fit ``kind`` (``i`` or ``h``)."""
    lowest, highest, kind_name = _BOUNDS[kind]
    if math.isfinite(value):  # round() raises on NaN and infinities
        raw = round(value * scale)
        if lowest <= raw <= highest:
            return raw
    raise ValueRangeError(
        f"VESC {name}={value!r} does not fit {kind_name} at scale x{scale}: allowed range "
        f"{_scaled_range(lowest, highest, scale, '')}"
    )


def _byte(name: str, value: int) -> int:
    if not 0 <= value <= 0xFF:
        raise ValueRangeError(f"VESC {name}={value!r} outside 0..255")
    return value


def _status_payload(status: VescStatus) -> tuple[Packet, bytes]:
    packet = _STATUS_PACKETS[type(status)]
    record, wire, scales = _STATUS_LAYOUTS[packet]
    kinds = wire.format.lstrip(">")
    raw = [
        _to_int(field.name, getattr(status, field.name), scale, kind)
        for field, scale, kind in zip(dataclasses.fields(record), scales, kinds, strict=False)
    ]
    return packet, wire.pack(*raw, *[0] * (len(kinds) - len(raw)))


def _payload(message: Ping | Pong | NotifyBoot) -> tuple[Packet, bytes]:
    match message:
        case Ping():
            return Packet.PING, bytes((_byte("sender_id", message.sender_id),))
        case Pong():
            return Packet.PONG, _U8X2.pack(
                _byte("controller_id", message.controller_id), _byte("hw_type", message.hw_type)
            )
        case NotifyBoot():
            name = message.hw_name
            if not name.isascii() or len(name) > NOTIFY_BOOT_MAX_DLC:
                raise ValueRangeError(
                    f"VESC NOTIFY_BOOT hw_name={name!r}: expected at most "
                    f"{NOTIFY_BOOT_MAX_DLC} ASCII characters"
                )
            return Packet.NOTIFY_BOOT, name.encode("ascii")
        case _:
            assert_never(message)


def encode(frame: VescFrame) -> can.Message:
    """Encode any VESC record as an extended-ID :class:`can.Message`. Commands go through
    :func:`encode_command`; other values only have to fit their field.

    Raises:
        ValueRangeError: as :func:`encode_command`; a controller ID outside 0..255, a value
            beyond its field (i32, i16 or a byte) once scaled, NaN or infinite; a hardware name
            of more than 8 characters or not ASCII.
    """
    message = frame.message
    match message:
        case SetDuty(duty=value) | SetCurrentRel(fraction=value):
            pass
        case SetCurrent(current_a=value) | SetCurrentBrake(current_a=value):
            pass
        case SetRpm(erpm=value):
            pass
        case Status() | Status2() | Status3() | Status4() | Status5() | Status6():
            return _message(frame.controller_id, *_status_payload(message))
        case Ping() | Pong() | NotifyBoot():
            return _message(frame.controller_id, *_payload(message))
        case _:
            assert_never(message)
    return encode_command(frame.controller_id, COMMAND_PACKETS[type(message)], value)


def _message(controller_id: int, packet: Packet, data: bytes) -> can.Message:
    return can.Message(arbitration_id=can_id(controller_id, packet), data=data, is_extended_id=True)


# ---------------------------------------------------------------------------------------------
# Decoding

_Decoder: TypeAlias = Callable[[int, bytearray], VescFrame]


def _dlc_error(packet: int, controller_id: int, data: bytearray, expected: object) -> DlcError:
    return DlcError(
        f"VESC {_name(packet)}, controller {controller_id}: {len(data)} data bytes, expected "
        f"{expected}"
    )


def _command_decoder(packet: Packet, make: Callable[[int], VescCommand]) -> _Decoder:
    # SET_CURRENT and SET_CURRENT_REL have a 6-byte form with an off-delay: firmware 5.x reads
    # SET_CURRENT's as current then delay, 6.x and later as delay then current, so a 6-byte
    # frame cannot be read without knowing the receiver (docs/protocols.md §6.3).
    expected: object = COMMAND_DLC
    if packet in (Packet.SET_CURRENT, Packet.SET_CURRENT_REL):
        expected = (
            f"{COMMAND_DLC} (the 6-byte form with an off-delay, which firmware versions read "
            "differently, is neither sent nor read by the bridge)"
        )

    def decode_command(controller_id: int, data: bytearray) -> VescFrame:
        if len(data) != COMMAND_DLC:
            raise _dlc_error(packet, controller_id, data, expected)
        return VescFrame(controller_id, make(_I32.unpack(data)[0]))

    return decode_command


def _status_decoder(packet: Packet, layout: _StatusLayout) -> _Decoder:
    record, wire, scales = layout
    size = wire.size

    def decode_status(controller_id: int, data: bytearray) -> VescFrame:
        if len(data) != size:
            raise _dlc_error(packet, controller_id, data, size)
        raw = wire.unpack(data)
        # zip() stops at the record's last field: the reserved ones are dropped.
        values = [r if scale == 1 else r / scale for r, scale in zip(raw, scales, strict=False)]
        return VescFrame(controller_id, record(*values))

    return decode_status


def _decode_ping(controller_id: int, data: bytearray) -> VescFrame:
    if len(data) != PING_DLC:
        raise _dlc_error(Packet.PING, controller_id, data, PING_DLC)
    return VescFrame(controller_id, Ping(data[0]))


def _decode_pong(controller_id: int, data: bytearray) -> VescFrame:
    if len(data) not in PONG_DLCS:
        raise _dlc_error(Packet.PONG, controller_id, data, "1 or 2")
    # Without the type byte the firmware takes the answer to be a VESC's.
    hw_type = data[1] if len(data) == 2 else HwType.VESC
    return VescFrame(controller_id, Pong(data[0], hw_type))


def _decode_notify_boot(controller_id: int, data: bytearray) -> VescFrame:
    return VescFrame(controller_id, NotifyBoot(bytes(data).decode("ascii", "replace")))


# Wire integer -> record: division by the integer scale (not multiplication by its reciprocal)
# gives the float nearest the exact quotient, so values exact at the scale survive a round trip.
_DECODERS: Final[dict[int, _Decoder]] = {
    Packet.SET_DUTY: _command_decoder(Packet.SET_DUTY, lambda raw: SetDuty(raw / DUTY_SCALE)),
    Packet.SET_CURRENT: _command_decoder(
        Packet.SET_CURRENT, lambda raw: SetCurrent(raw / CURRENT_SCALE)
    ),
    Packet.SET_CURRENT_BRAKE: _command_decoder(
        Packet.SET_CURRENT_BRAKE, lambda raw: SetCurrentBrake(raw / CURRENT_SCALE)
    ),
    Packet.SET_RPM: _command_decoder(Packet.SET_RPM, SetRpm),
    Packet.SET_CURRENT_REL: _command_decoder(
        Packet.SET_CURRENT_REL, lambda raw: SetCurrentRel(raw / CURRENT_REL_SCALE)
    ),
    **{packet: _status_decoder(packet, layout) for packet, layout in _STATUS_LAYOUTS.items()},
    Packet.PING: _decode_ping,
    Packet.PONG: _decode_pong,
    Packet.NOTIFY_BOOT: _decode_notify_boot,
}


def _not_extended(msg: can.Message) -> NotExtendedIdError:
    if msg.is_error_frame:
        came = "an error frame"
    elif msg.is_remote_frame:
        came = f"a remote (RTR) frame, ID 0x{msg.arbitration_id:X}"
    else:
        came = f"an 11-bit ID 0x{msg.arbitration_id:03X}"
    return NotExtendedIdError(f"VESC uses 29-bit data frames only; got {came}")


def decode(msg: can.Message) -> VescFrame | None:
    """Decode a VESC frame; ``None`` if it is not one the bridge knows: an ID with any of bits
    28..16 set, or a packet :class:`~bridge.escs.vesc.records.Packet` does not name.

    Raises:
        NotExtendedIdError: an error frame, a remote frame or an 11-bit ID.
        DlcError: a data length other than the packet's (commands 4, status frames 8, PING 1,
            PONG 1 or 2, NOTIFY_BOOT at most 8).
    """
    if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
        raise _not_extended(msg)
    arbitration_id: int = msg.arbitration_id
    if arbitration_id > VESC_ID_MAX:
        return None
    decoder = _DECODERS.get(arbitration_id >> 8)
    if decoder is None:
        return None
    return decoder(arbitration_id & 0xFF, msg.data)
