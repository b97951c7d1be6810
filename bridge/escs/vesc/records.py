"""VESC constants, packet IDs, records and CAN IDs (docs/protocols.md §6), read from the VESC
firmware's own sources (vedderb/bldc, firmware 7.01: ``comm/comm_can.c``, ``datatypes.h``).

Records are plain frozen data, checked once when encoded (:mod:`bridge.escs.vesc.codec`), so
decoding stays cheap and a capture with odd values can still be shown.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Final, TypeAlias

from bridge.errors import ValueRangeError

# ---------------------------------------------------------------------------------------------
# Protocol constants

CONTROLLER_ID_MIN: Final = 0
CONTROLLER_ID_MAX: Final = 255
BROADCAST_ID: Final = 255
"""Every VESC obeys a command to this ID as its own (docs/protocols.md §6.2)."""
VESC_ID_MAX: Final = 0xFFFF
"""Largest VESC arbitration ID: ``packet << 8 | controller_id``, bits 28..16 always zero."""

I32_MIN: Final = -(1 << 31)
I32_MAX: Final = (1 << 31) - 1
I16_MIN: Final = -(1 << 15)
I16_MAX: Final = (1 << 15) - 1

DUTY_SCALE: Final = 100_000
CURRENT_SCALE: Final = 1000
"""Command currents (motor and brake) in mA."""
CURRENT_REL_SCALE: Final = 100_000
RPM_SCALE: Final = 1
DUTY_MAX: Final = 1.0
CURRENT_REL_MAX: Final = 1.0

STATUS_CURRENT_SCALE: Final = 10
"""STATUS motor current and STATUS_4 input current in 0.1 A."""
STATUS_DUTY_SCALE: Final = 1000
ENERGY_SCALE: Final = 10_000
"""STATUS_2 amp hours and STATUS_3 watt hours in units of 1e-4."""
TEMP_SCALE: Final = 10
"""STATUS_4 temperatures in 0.1 degC."""
PID_POSITION_SCALE: Final = 50
"""STATUS_4 PID position in 1/50 degree."""
VOLTAGE_SCALE: Final = 10
"""STATUS_5 input voltage in 0.1 V."""
ADC_SCALE: Final = 1000
"""STATUS_6 ADC volts and PPM input in units of 1e-3."""

COMMAND_DLC: Final = 4
STATUS_DLC: Final = 8
PING_DLC: Final = 1
PONG_DLCS: Final = (1, 2)
"""A PONG carries the answering VESC's ID and its hardware type; firmware reads one without the
type as a VESC."""
NOTIFY_BOOT_MAX_DLC: Final = 8

# ---------------------------------------------------------------------------------------------
# Enumerations


class Packet(IntEnum):
    """The VESC packets the bridge knows (``CAN_PACKET_ID`` in the firmware's ``datatypes.h``;
    bits 15..8 of the CAN ID). The firmware has more; a frame of another packet is not decoded."""

    SET_DUTY = 0
    SET_CURRENT = 1
    SET_CURRENT_BRAKE = 2
    SET_RPM = 3
    STATUS = 9
    SET_CURRENT_REL = 10
    STATUS_2 = 14
    STATUS_3 = 15
    STATUS_4 = 16
    PING = 17
    PONG = 18
    STATUS_5 = 27
    NOTIFY_BOOT = 57
    STATUS_6 = 58


COMMANDS: Final = frozenset(
    (
        Packet.SET_DUTY,
        Packet.SET_CURRENT,
        Packet.SET_CURRENT_BRAKE,
        Packet.SET_RPM,
        Packet.SET_CURRENT_REL,
    )
)
"""The motor commands: four data bytes each, addressed to a VESC (or 255, all)."""
STATUS_PACKETS: Final = frozenset(
    (
        Packet.STATUS,
        Packet.STATUS_2,
        Packet.STATUS_3,
        Packet.STATUS_4,
        Packet.STATUS_5,
        Packet.STATUS_6,
    )
)
"""The status frames: eight data bytes each, sent by a VESC under its own ID."""


class HwType(IntEnum):
    """The hardware type a PONG carries (``HW_TYPE`` in ``datatypes.h``)."""

    VESC = 0
    VESC_BMS = 1
    CUSTOM_MODULE = 2


# ---------------------------------------------------------------------------------------------
# Records


@dataclass(frozen=True, slots=True)
class SetDuty:
    """SET_DUTY (0): duty cycle, -1..1, in steps of 1e-5."""

    duty: float


@dataclass(frozen=True, slots=True)
class SetCurrent:
    """SET_CURRENT (1): motor current in A (negative reverses the torque), steps of 1 mA.
    Only the four-byte form (docs/protocols.md §6.3)."""

    current_a: float


@dataclass(frozen=True, slots=True)
class SetCurrentBrake:
    """SET_CURRENT_BRAKE (2): brake current in A, steps of 1 mA."""

    current_a: float


@dataclass(frozen=True, slots=True)
class SetRpm:
    """SET_RPM (3): speed in electrical rpm (mechanical rpm x pole pairs)."""

    erpm: int


@dataclass(frozen=True, slots=True)
class SetCurrentRel:
    """SET_CURRENT_REL (10): current as a fraction (-1..1, steps of 1e-5) of the VESC's own
    motor current limit: its maximum, or its minimum's size for a current against the
    rotation."""

    fraction: float


@dataclass(frozen=True, slots=True)
class Ping:
    """PING (17) to the frame's controller ID: answer with a PONG to ``sender_id``."""

    sender_id: int


@dataclass(frozen=True, slots=True)
class Pong:
    """PONG (18), sent to the pinging node's ID: the answering VESC's ID and hardware type
    (:class:`HwType`; kept as a number, which a newer firmware may extend)."""

    controller_id: int
    hw_type: int


@dataclass(frozen=True, slots=True)
class NotifyBoot:
    """NOTIFY_BOOT (57), sent once by a VESC that has just started: its hardware name
    (ASCII, at most 8 characters)."""

    hw_name: str


@dataclass(frozen=True, slots=True)
class Status:
    """STATUS (9): electrical rpm, motor current in A (0.1 A steps; negative while
    regenerating) and duty cycle (steps of 0.001)."""

    erpm: int
    motor_current_a: float
    duty: float


@dataclass(frozen=True, slots=True)
class Status2:
    """STATUS_2 (14): charge drawn from and given back to the battery since start, Ah (1e-4)."""

    used_ah: float
    charged_ah: float


@dataclass(frozen=True, slots=True)
class Status3:
    """STATUS_3 (15): energy drawn from and given back to the battery since start, Wh (1e-4)."""

    used_wh: float
    charged_wh: float


@dataclass(frozen=True, slots=True)
class Status4:
    """STATUS_4 (16): MOSFET and motor temperature in degC (0.1 degC steps), input (battery)
    current in A (0.1 A steps) and the position controller's angle in degrees (1/50 steps)."""

    fet_temp_c: float
    motor_temp_c: float
    input_current_a: float
    pid_position_deg: float


@dataclass(frozen=True, slots=True)
class Status5:
    """STATUS_5 (27): the tachometer (electrical steps counted since start; six per electrical
    turn) and the input voltage in V (0.1 V steps). Its last two bytes are reserved: sent as 0,
    ignored when read."""

    tachometer: int
    input_voltage_v: float


@dataclass(frozen=True, slots=True)
class Status6:
    """STATUS_6 (58): the three ADC inputs in V and the PPM input (-1..1), steps of 0.001."""

    adc1_v: float
    adc2_v: float
    adc3_v: float
    ppm: float


VescCommand: TypeAlias = SetDuty | SetCurrent | SetCurrentBrake | SetRpm | SetCurrentRel
VescStatus: TypeAlias = Status | Status2 | Status3 | Status4 | Status5 | Status6
VescMessage: TypeAlias = VescCommand | VescStatus | Ping | Pong | NotifyBoot


@dataclass(frozen=True, slots=True)
class VescFrame:
    """One VESC frame: ``controller_id`` is the CAN ID's low byte, which is the VESC addressed
    (commands, PING; 255 all), the node answered (PONG), or the VESC sending (status frames,
    NOTIFY_BOOT). Checked when encoded."""

    controller_id: int
    message: VescMessage

    @property
    def node_id(self) -> int:
        """The controller ID, under the name every family's frame has."""
        return self.controller_id


COMMAND_PACKETS: Final[dict[type[VescCommand], Packet]] = {
    SetDuty: Packet.SET_DUTY,
    SetCurrent: Packet.SET_CURRENT,
    SetCurrentBrake: Packet.SET_CURRENT_BRAKE,
    SetRpm: Packet.SET_RPM,
    SetCurrentRel: Packet.SET_CURRENT_REL,
}
"""Command record -> its packet, one-to-one."""

# ---------------------------------------------------------------------------------------------
# CAN ID


def can_id(controller_id: int, packet: int) -> int:
    """The 29-bit arbitration ID ``packet << 8 | controller_id``.

    Raises:
        ValueRangeError: ``controller_id`` or ``packet`` outside 0..255.
    """
    if not CONTROLLER_ID_MIN <= controller_id <= CONTROLLER_ID_MAX:
        raise ValueRangeError(
            f"controller_id={controller_id!r} outside {CONTROLLER_ID_MIN}..{CONTROLLER_ID_MAX}"
        )
    if not 0 <= packet <= 0xFF:
        raise ValueRangeError(f"packet={packet!r} outside 0..255")
    return packet << 8 | controller_id


def parse_id(arbitration_id: int) -> tuple[int, int]:
    """Split a VESC arbitration ID into ``(packet, controller_id)``; the packet need not be one
    :class:`Packet` names.

    Raises:
        ValueRangeError: the ID has bits above 15 set (or is negative): not VESC's.
    """
    if not 0 <= arbitration_id <= VESC_ID_MAX:
        raise ValueRangeError(
            f"arbitration_id=0x{arbitration_id:X} outside VESC's ID range "
            f"0x0000..0x{VESC_ID_MAX:04X}"
        )
    return arbitration_id >> 8, arbitration_id & 0xFF
