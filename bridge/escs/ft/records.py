"""FT constants, the CRC-16, enumerations, records and CAN IDs (docs/protocols.md §4); the package
docstring describes the protocol. Pure: no I/O, clock or logging."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Final, TypeAlias

from bridge.errors import ValueRangeError

# ---------------------------------------------------------------------------------------------
# Protocol constants

ESC_ID_MIN: Final = 0
ESC_ID_MAX: Final = 255
FT_ID_MAX: Final = 0xFFFF
"""Largest FT arbitration ID: bits 28..16 are always zero."""

I32_MIN: Final = -(1 << 31)
I32_MAX: Final = (1 << 31) - 1
I24_MIN: Final = -(1 << 23)
I24_MAX: Final = (1 << 23) - 1
I16_MIN: Final = -(1 << 15)
I16_MAX: Final = (1 << 15) - 1

CURRENT_SCALE: Final = 100_000
"""Command currents (A), including brake and d-axis currents, are sent in units of 10 uA."""
DUTY_SCALE: Final = 1_000_000
FRACTION_SCALE: Final = 100_000
ERPM_SCALE: Final = 1
POSITION_SCALE: Final = 100_000
"""Angles in units of 1e-5 degree."""

RT_CURRENT_SCALE: Final = 1000
"""Telemetry currents in mA."""
RT_DUTY_SCALE: Final = 1000
RT_TEMP_SCALE: Final = 100
"""Telemetry temperatures in 0.01 degC."""
RT_VOLTAGE_SCALE: Final = 100
"""Telemetry battery voltage in 10 mV."""

DUTY_MAX: Final = 1.0
FRACTION_MAX: Final = 1.0
POSITION_MAX_DEG: Final = 180.0

TELEMETRY_DLC: Final = 8
ID_CURRENT_DLCS: Final = (6, 7)

CRC16_MODBUS_POLY_REFLECTED: Final = 0xA001
CRC16_MODBUS_INIT: Final = 0xFFFF


def _crc16_modbus_table() -> tuple[int, ...]:
    """Byte-wise lookup table for the reflected polynomial 0xA001."""
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ CRC16_MODBUS_POLY_REFLECTED if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE: Final = _crc16_modbus_table()


def crc16_modbus(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/MODBUS of ``data``: reflected poly 0xA001, init 0xFFFF, no final XOR.

    FT frames carry it high byte first. ``crc16_modbus(b"123456789") == 0x4B37``.
    """
    crc = CRC16_MODBUS_INIT
    table = _CRC_TABLE
    for byte in data:
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


# ---------------------------------------------------------------------------------------------
# Enumerations


class Command(IntEnum):
    """FT command IDs (the low byte of the CAN ID), bridge → ESC."""

    SET_CURRENT_GEAR_CRC16 = 0x00
    SET_CURRENT_BRAKE_CRC16 = 0x01
    SET_DUTY_GEAR_CRC16 = 0x02
    SET_CURRENT_PERCENT_CRC16 = 0x03
    SET_CURRENT_PERCENT_GEAR_CRC16 = 0x04
    SET_CURRENT_BRAKE_PERCENT_CRC16 = 0x05
    SET_ERPM_GEAR_CRC16 = 0x12
    SET_POSITION_GEAR_CRC16 = 0x13
    SET_ID_CURRENT_CRC16 = 0x14
    SET_CURRENT_GEAR = 0x15
    SET_CURRENT_PERCENT_GEAR = 0x16
    SET_DUTY_GEAR = 0x17
    SET_ERPM_GEAR = 0x18
    SET_POSITION_GEAR = 0x19
    # The seed's headings say 20H/21H; its enum says 26, 27 (docs/protocols.md §4.9).
    SET_CURRENT_BRAKE = 0x1A
    SET_CURRENT_BRAKE_PERCENT = 0x1B


class Telemetry(IntEnum):
    """FT real-time telemetry IDs, ESC → bridge."""

    REALTIME_DATA_0 = 0x0B
    REALTIME_DATA_1 = 0x0C
    REALTIME_DATA_2 = 0x0D


class Gear(IntEnum):
    """Speed gear byte of the gear-carrying commands; NONE disables gear speed limiting."""

    NONE = 0
    LOW = 1
    MIDDLE = 2
    HIGH = 3
    REVERSE = 4


# ---------------------------------------------------------------------------------------------
# Records. Plain data: values are checked once, when encoded (see encode_command), so that
# decoding stays cheap and a capture with odd values can still be represented.


@dataclass(frozen=True, slots=True)
class SetCurrent:
    """Motor current command (0x00 with CRC, 0x15 without).

    ``current_a``: motor current in A (negative reverses torque), resolution 1e-5 A.
    """

    current_a: float
    gear: Gear = Gear.NONE
    crc: bool = True


@dataclass(frozen=True, slots=True)
class SetCurrentBrake:
    """Brake current command (0x01 with CRC, 0x1A without); ``current_a`` in A, 1e-5 A."""

    current_a: float
    crc: bool = True


@dataclass(frozen=True, slots=True)
class SetDuty:
    """Duty-cycle command (0x02 with CRC, 0x17 without); ``duty`` in -1..1, 1e-6 steps."""

    duty: float
    gear: Gear = Gear.NONE
    crc: bool = True


@dataclass(frozen=True, slots=True)
class SetCurrentPercent:
    """Current as a fraction (-1..1, 1e-5 steps) of the ESC's configured motor current.

    ``gear=None`` is 0x03 (CRC only); with a gear it is 0x04 (CRC) or 0x16 (no CRC).
    """

    fraction: float
    gear: Gear | None = Gear.NONE
    crc: bool = True


@dataclass(frozen=True, slots=True)
class SetCurrentBrakePercent:
    """Brake current as a fraction (-1..1, 1e-5 steps) of the configured brake current.

    0x05 with CRC, 0x1B without.
    """

    fraction: float
    crc: bool = True


@dataclass(frozen=True, slots=True)
class SetErpm:
    """Speed command (0x12 with CRC, 0x18 without); ``erpm`` = mechanical rpm x pole pairs."""

    erpm: int
    gear: Gear = Gear.NONE
    crc: bool = True


@dataclass(frozen=True, slots=True)
class SetPosition:
    """Position command (0x13 with CRC, 0x19 without); ``angle_deg`` in -180..180, 1e-5 deg."""

    angle_deg: float
    gear: Gear = Gear.NONE
    crc: bool = True


@dataclass(frozen=True, slots=True)
class SetIdCurrent:
    """d-axis current injection (0x14, always CRC): a parking hold that heats the motor.

    ``current_a`` in A, resolution 1e-5 A.
    """

    current_a: float


@dataclass(frozen=True, slots=True)
class RealtimeData0:
    """Telemetry 0x0B: motor and battery current in A, resolution 1 mA."""

    motor_current_a: float
    battery_current_a: float


@dataclass(frozen=True, slots=True)
class RealtimeData1:
    """Telemetry 0x0C: electrical rpm and duty cycle (-1..1 nominal, resolution 0.001)."""

    erpm: int
    duty: float


@dataclass(frozen=True, slots=True)
class RealtimeData2:
    """Telemetry 0x0D: MOSFET and motor temperature in degC, battery voltage in V (0.01 steps)."""

    mosfet_temp_c: float
    motor_temp_c: float
    battery_voltage_v: float


FtCommand: TypeAlias = (
    SetCurrent
    | SetCurrentBrake
    | SetDuty
    | SetCurrentPercent
    | SetCurrentBrakePercent
    | SetErpm
    | SetPosition
    | SetIdCurrent
)
FtTelemetry: TypeAlias = RealtimeData0 | RealtimeData1 | RealtimeData2
FtMessage: TypeAlias = FtCommand | FtTelemetry


@dataclass(frozen=True, slots=True)
class FtFrame:
    """One FT frame: the ESC it is addressed to (command) or sent by (telemetry), and content.

    ``esc_id`` is 0..255; it is checked when encoded.
    """

    esc_id: int
    message: FtMessage

    @property
    def node_id(self) -> int:
        """The ESC ID, under the name the CKESC codec uses."""
        return self.esc_id


COMMAND_RECORDS: Final[dict[Command, tuple[type[FtCommand], bool, bool]]] = {
    Command.SET_CURRENT_GEAR_CRC16: (SetCurrent, True, True),
    Command.SET_CURRENT_BRAKE_CRC16: (SetCurrentBrake, True, False),
    Command.SET_DUTY_GEAR_CRC16: (SetDuty, True, True),
    Command.SET_CURRENT_PERCENT_CRC16: (SetCurrentPercent, True, False),
    Command.SET_CURRENT_PERCENT_GEAR_CRC16: (SetCurrentPercent, True, True),
    Command.SET_CURRENT_BRAKE_PERCENT_CRC16: (SetCurrentBrakePercent, True, False),
    Command.SET_ERPM_GEAR_CRC16: (SetErpm, True, True),
    Command.SET_POSITION_GEAR_CRC16: (SetPosition, True, True),
    Command.SET_ID_CURRENT_CRC16: (SetIdCurrent, True, False),
    Command.SET_CURRENT_GEAR: (SetCurrent, False, True),
    Command.SET_CURRENT_PERCENT_GEAR: (SetCurrentPercent, False, True),
    Command.SET_DUTY_GEAR: (SetDuty, False, True),
    Command.SET_ERPM_GEAR: (SetErpm, False, True),
    Command.SET_POSITION_GEAR: (SetPosition, False, True),
    Command.SET_CURRENT_BRAKE: (SetCurrentBrake, False, False),
    Command.SET_CURRENT_BRAKE_PERCENT: (SetCurrentBrakePercent, False, False),
}
"""Command ID → (record class, crc, gear present); one-to-one, the module docstring's table."""

# ---------------------------------------------------------------------------------------------
# CAN ID


def can_id(esc_id: int, command: int) -> int:
    """The 29-bit arbitration ID ``(esc_id << 8) | command``.

    Raises:
        ValueRangeError: ``esc_id`` or ``command`` outside 0..255.
    """
    if not ESC_ID_MIN <= esc_id <= ESC_ID_MAX:
        raise ValueRangeError(f"esc_id={esc_id!r} outside {ESC_ID_MIN}..{ESC_ID_MAX}")
    if not 0 <= command <= 0xFF:
        raise ValueRangeError(f"command={command!r} outside 0x00..0xFF")
    return (esc_id << 8) | command


def parse_id(arbitration_id: int) -> tuple[int, int]:
    """Split an FT arbitration ID into ``(esc_id, command byte)``.

    The command byte is returned as an int: it need not name a known command.

    Raises:
        ValueRangeError: the ID has bits above 15 set (or is negative), so it is not FT's.
    """
    if not 0 <= arbitration_id <= FT_ID_MAX:
        raise ValueRangeError(
            f"arbitration_id=0x{arbitration_id:X} outside FT's ID range 0x0000..0x{FT_ID_MAX:04X}"
        )
    return arbitration_id >> 8, arbitration_id & 0xFF
