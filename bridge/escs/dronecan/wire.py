"""What the bridge sends to DroneCAN ESCs, encoded by hand: ``uavcan.equipment.esc.RawCommand``
and its own ``uavcan.protocol.NodeStatus``. Pure; the output loop's only DroneCAN import.

Why by hand: the ``dronecan`` package (the reference serializer, used for everything received in
:mod:`bridge.escs.dronecan.codec`) builds a RawCommand transfer for 8 ESCs (3 frames) in about
54 µs, the precomputed encoder below in about 9 µs, the ``can.Message`` objects included
(``python bench/codec.py``: 17.9 and 3.1 µs a frame, medians of 7 runs, on the development
machine's shared core). A Raspberry Pi core is several times slower than that one, so
``dronecan`` would spend a tenth or more of the 2.5 ms period at 400 Hz where the encoder spends
about one percent, and importing ``dronecan`` would cost the loop process 0.3 s of CPU and its
DSDL tables: the loop imports nothing it does not run. The tests check this encoder against
``dronecan`` frame for frame.

The DSDL serialization rule both encoders follow (UAVCAN v0): fields are written into one bit
stream, each byte filled from its top bit. A field of more than 8 bits is written as its
little-endian bytes, the last one holding only the remaining bits; a field of up to 8 bits is
written as its bits, top bit first. A RawCommand's ``cmd`` (int14[<=20]) is its last field, so
its length is not sent (tail array optimization): N commands are ceil(14 N / 8) bytes, one
frame up to 4 commands, a multi-frame transfer beyond (:mod:`bridge.escs.uavcan_v0`).

Constants follow ArduPilot's ``AP_DroneCAN`` where the standard leaves a choice: RawCommand at
priority 7 (``CANARD_TRANSFER_PRIORITY_HIGH - 1``, "one higher than high priority", above its
actuator commands), from node 10 (``CAN_D1_UC_NODE``'s default), command full scale 8191
(``scale_esc_output``: 0..8191 for a forward-only ESC, -8191..8191 for a reversible one),
NodeStatus at priority 31 (lowest) once a second, health OK, mode OPERATIONAL.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final

import can

from bridge.errors import ValueRangeError
from bridge.escs.uavcan_v0 import (
    PRIORITY_HIGH,
    PRIORITY_LOWEST,
    frames_data,
    message_id,
    signature_crc,
)

# Data type IDs and signatures (DSDL: uavcan/equipment/esc/1030.RawCommand.uavcan, ...).
TYPE_RAW_COMMAND: Final = 1030
TYPE_ESC_STATUS: Final = 1034
TYPE_NODE_STATUS: Final = 341
SIGNATURE_RAW_COMMAND: Final = 0x217F5C87D7EC951D
SIGNATURE_ESC_STATUS: Final = 0xA9AF28AEA2FBB254
SIGNATURE_NODE_STATUS: Final = 0x0F0868D0C1A7C6F1
CRC_START: Final[dict[int, int]] = {
    TYPE_RAW_COMMAND: signature_crc(SIGNATURE_RAW_COMMAND),
    TYPE_ESC_STATUS: signature_crc(SIGNATURE_ESC_STATUS),
    TYPE_NODE_STATUS: signature_crc(SIGNATURE_NODE_STATUS),
}
"""The transfer CRC's start per data type ID (its signature's CRC)."""

PRIORITY_ESC_COMMAND: Final = PRIORITY_HIGH - 1
"""ArduPilot's RawCommand priority: one above its actuator commands."""

DEFAULT_NODE_ID: Final = 10
"""The bridge's own node ID unless configured: ArduPilot's default (``CAN_D1_UC_NODE``)."""
NODE_IDS: Final = range(1, 126)
"""Node IDs the bridge can take: 1..125 (0 is anonymous; 126 and 127 are customarily left to
maintenance tools, and CKESC reserves them: :func:`~bridge.escs.uavcan_v0.message_id` refuses
them)."""
MAX_COMMANDS: Final = 20
"""RawCommand carries up to 20 commands (``int14[<=20] cmd``): ESC indices 0..19."""
COMMAND_MAX: Final = 8191
"""Full scale of a RawCommand value, forward (and, negated, reverse)."""
COMMAND_MIN: Final = -8192
STATUS_BYTES: Final = 14
"""An esc.Status payload: 110 bits (u32, three float16, int18, u7, u5), three frames."""
NODE_STATUS_BYTES: Final = 7
NODE_STATUS_PERIOD_NS: Final = 1_000_000_000
"""NodeStatus is sent once a second (the standard's MAX_BROADCASTING_PERIOD_MS is 1000)."""

HEALTH_OK: Final = 0
HEALTH_WARNING: Final = 1
HEALTH_ERROR: Final = 2
HEALTH_CRITICAL: Final = 3
MODE_OPERATIONAL: Final = 0
MODE_INITIALIZATION: Final = 1
MODE_MAINTENANCE: Final = 2
MODE_SOFTWARE_UPDATE: Final = 3
MODE_OFFLINE: Final = 7

_RAW_COMMAND_CRC: Final = CRC_START[TYPE_RAW_COMMAND]


def owns(arbitration_id: int) -> bool:
    """Whether a 29-bit ID is a message frame (bit 7 clear) of RawCommand, esc.Status or
    NodeStatus from a named node (not anonymous node 0)."""
    return (
        not arbitration_id & 0x80
        and arbitration_id & 0x7F != 0
        and (arbitration_id >> 8) & 0xFFFF in CRC_START
    )


def raw_command_bytes(commands: int) -> int:
    """Payload bytes of a RawCommand with ``commands`` values: ceil(14 N / 8)."""
    return (14 * commands + 7) // 8


def pack_raw_command(commands: Sequence[int]) -> bytes:
    """The payload of a RawCommand carrying ``commands`` (each -8192..8191; unchecked here).

    Each int14 goes in as its low 8 bits, then its high 6 bits (two's complement)."""
    bits = 0
    for command in commands:
        value = command & 0x3FFF
        bits = bits << 14 | (value & 0xFF) << 6 | value >> 8
    size = (14 * len(commands) + 7) // 8
    return (bits << (8 * size - 14 * len(commands))).to_bytes(size, "big")


class RawCommandEncoder:
    """RawCommand transfers of a fixed length from one node, the transfer ID counting 0..31
    per transfer: everything but the values is worked out once, and the frames of the same
    values are made once (a transfer that repeats them only writes its transfer ID into their
    tail bytes).

    Raises:
        ValueRangeError: ``channels`` outside 1..20, ``source_node`` outside 1..125 or a
            priority outside 0..31.
    """

    __slots__ = ("_arbitration_id", "_channels", "_commands", "_frames", "transfer_id")

    def __init__(
        self, channels: int, source_node: int, priority: int = PRIORITY_ESC_COMMAND
    ) -> None:
        if not 1 <= channels <= MAX_COMMANDS:
            raise ValueRangeError(f"a RawCommand carries 1..{MAX_COMMANDS} values, not {channels}")
        if source_node not in NODE_IDS:
            raise ValueRangeError(f"source_node = {source_node!r} is not in 1..125")
        self._arbitration_id = message_id(priority, TYPE_RAW_COMMAND, source_node)
        self._channels = channels
        self._commands: Sequence[int] = ()  # whose frames self._frames are
        self._frames: list[can.Message] = []
        self.transfer_id = 0
        """The next transfer's ID."""

    @property
    def arbitration_id(self) -> int:
        return self._arbitration_id

    def prepare(self, commands: Sequence[int]) -> list[can.Message]:
        """The frames of a transfer carrying ``commands`` (one per channel), their transfer ID
        not written yet: made when the values change, kept while they do not.

        Raises:
            ValueRangeError: the wrong number of values, or one outside -8192..8191 (nothing
                is kept).
        """
        if commands != self._commands:
            self._commands = ()  # until every frame is made: a raise leaves none kept
            if len(commands) != self._channels:
                raise ValueRangeError(f"expected {self._channels} commands, got {len(commands)}")
            if commands and not (min(commands) >= COMMAND_MIN and max(commands) <= COMMAND_MAX):
                raise ValueRangeError(
                    f"RawCommand values {list(commands)} are not all in -8192..8191"
                )
            payload = pack_raw_command(commands)
            arbitration_id = self._arbitration_id
            self._frames = [
                can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=True)
                for data in frames_data(payload, 0, _RAW_COMMAND_CRC)
            ]
            self._commands = list(commands)
        return self._frames

    def frames(self, commands: Sequence[int]) -> list[can.Message]:
        """The frames of the next transfer carrying ``commands`` (one per channel). They are
        the encoder's until its next call, which may reuse them: send them before then.

        Raises:
            ValueRangeError: the wrong number of values, or one outside -8192..8191 (nothing
                is sent and the transfer ID is not used).
        """
        frames = self.prepare(commands)
        transfer_id = self.transfer_id
        self.transfer_id = (transfer_id + 1) & 0x1F
        for frame in frames:
            data = frame.data
            data[-1] = data[-1] & 0xE0 | transfer_id  # its start, end and toggle bits kept
        return frames


def pack_node_status(
    uptime_s: int,
    health: int = HEALTH_OK,
    mode: int = MODE_OPERATIONAL,
    sub_mode: int = 0,
    vendor_status: int = 0,
) -> bytes:
    """The 7-byte payload of a NodeStatus: uptime u32, health u2, mode u3, sub-mode u3, vendor
    status u16. The uptime wraps at 2^32 s.

    Raises:
        ValueRangeError: a field that does not fit.
    """
    if not (0 <= health <= 3 and 0 <= mode <= 7 and 0 <= sub_mode <= 7):
        raise ValueRangeError(f"NodeStatus health/mode/sub_mode {health}/{mode}/{sub_mode}")
    if not 0 <= vendor_status <= 0xFFFF or uptime_s < 0:
        raise ValueRangeError(f"NodeStatus uptime {uptime_s} s, vendor status {vendor_status}")
    return (
        (uptime_s & 0xFFFF_FFFF).to_bytes(4, "little")
        + bytes((health << 6 | mode << 3 | sub_mode,))
        + vendor_status.to_bytes(2, "little")
    )


def node_status_frame(
    source_node: int,
    transfer_id: int,
    uptime_s: int,
    health: int = HEALTH_OK,
    mode: int = MODE_OPERATIONAL,
) -> can.Message:
    """Our NodeStatus as one frame (its 7 bytes and the tail byte).

    Raises:
        ValueRangeError: a node ID outside 1..125, a transfer ID outside 0..31 or a field that
            does not fit.
    """
    if source_node not in NODE_IDS:
        raise ValueRangeError(f"source_node = {source_node!r} is not in 1..125")
    (data,) = frames_data(
        pack_node_status(uptime_s, health, mode), transfer_id, CRC_START[TYPE_NODE_STATUS]
    )
    return can.Message(
        arbitration_id=message_id(PRIORITY_LOWEST, TYPE_NODE_STATUS, source_node),
        data=data,
        is_extended_id=True,
    )
