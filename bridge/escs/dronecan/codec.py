"""DroneCAN frames on the bus as records: ``uavcan.equipment.esc.RawCommand`` (a command, ours
or another node's), ``uavcan.equipment.esc.Status`` (an ESC's telemetry) and
``uavcan.protocol.NodeStatus`` (any node's health, mode and uptime).

Payloads are (de)serialized by the ``dronecan`` package, the DSDL reference implementation for
Python; this module adds the transfer layer (:mod:`bridge.escs.uavcan_v0`) and the
records. What the output loop sends is encoded by hand in :mod:`bridge.escs.dronecan.wire`
(why is said there), and the tests check the two against each other.

:class:`Decoder` is the one stateful part: a Status is 14 bytes, a multi-frame transfer of three
frames, and a RawCommand for more than four ESCs is one too, so frames are put back together per
sender (each frame before a transfer's last decodes to a :class:`TransferPart`, so every frame
of ours is accounted for); and a NodeStatus names only its sender's node ID, which the decoder
maps to an ESC index once that node's Status has said which index it is. One decoder per
stream of frames (a reader thread, a capture file). No I/O, clock or logging.

Decisions where the standard leaves a choice:

- An ESC is known by its ``esc_index`` (the RawCommand slot it follows, 0..19), as ArduPilot
  knows it: a Status says it; node IDs are often allocated at run time.
- A float16 field that is NaN (the ESC does not measure it) decodes as ``None``.
- Service frames, anonymous frames and other message types are not ours (``None``); a frame of
  one of our three types that breaks the transfer rules raises a :class:`~bridge.errors.
  FrameError` (its transfer is lost), and a complete payload of the wrong length a
  :class:`~bridge.errors.DlcError`.
"""

from __future__ import annotations

import math
from collections.abc import Container
from dataclasses import dataclass
from typing import Any, Final, TypeAlias

import can
import dronecan
from dronecan.transport import Frame as _DcFrame
from dronecan.transport import Transfer as _DcTransfer
from dronecan.transport import bits_from_bytes

from bridge.errors import DlcError, ValueRangeError
from bridge.escs.dronecan.wire import (
    COMMAND_MAX,
    COMMAND_MIN,
    CRC_START,
    MAX_COMMANDS,
    NODE_STATUS_BYTES,
    PRIORITY_ESC_COMMAND,
    STATUS_BYTES,
    TYPE_ESC_STATUS,
    TYPE_NODE_STATUS,
    TYPE_RAW_COMMAND,
    owns,
    raw_command_bytes,
)
from bridge.escs.uavcan_v0 import (
    PRIORITY_LOWEST,
    PRIORITY_MEDIUM,
    Reassembler,
    Transfer,
    TransferIds,
    message_id,
    parse_id,
)

__all__ = [
    "KELVIN_OFFSET",
    "Decoder",
    "DronecanFrame",
    "DronecanMessage",
    "EscStatus",
    "NodeStatus",
    "RawCommand",
    "Sender",
    "TransferPart",
    "default_priority",
    "encode",
    "owns",
]

KELVIN_OFFSET: Final = 273.15

_DC: Any = dronecan
_DC_RAW_COMMAND: Any = _DC.uavcan.equipment.esc.RawCommand
_DC_ESC_STATUS: Any = _DC.uavcan.equipment.esc.Status
_DC_NODE_STATUS: Any = _DC.uavcan.protocol.NodeStatus


@dataclass(frozen=True, slots=True)
class RawCommand:
    """``uavcan.equipment.esc.RawCommand``: one value per ESC index, -8192..8191 (8191 full
    forward; negative is reverse for a reversible ESC, stop for the others)."""

    commands: tuple[int, ...]

    def __post_init__(self) -> None:
        if not 1 <= len(self.commands) <= MAX_COMMANDS:
            raise ValueRangeError(f"commands = {self.commands!r}: 1..{MAX_COMMANDS} values")
        if not all(COMMAND_MIN <= value <= COMMAND_MAX for value in self.commands):
            raise ValueRangeError(f"commands = {self.commands!r}: each -8192..8191")


@dataclass(frozen=True, slots=True)
class EscStatus:
    """``uavcan.equipment.esc.Status``: one ESC's telemetry. ``None``: the ESC sent NaN."""

    esc_index: int
    """The RawCommand slot this ESC follows (0..31 on the wire; 0..19 usable)."""
    error_count: int
    """Errors the ESC counted since it started (its own notion of an error)."""
    voltage_v: float | None
    current_a: float | None
    temperature_k: float | None
    rpm: int
    """Signed: negative in reverse."""
    power_rating_pct: int
    """The ESC's output as a percentage of its rating (0..127 on the wire)."""

    @property
    def temperature_c(self) -> float | None:
        return None if self.temperature_k is None else self.temperature_k - KELVIN_OFFSET


@dataclass(frozen=True, slots=True)
class NodeStatus:
    """``uavcan.protocol.NodeStatus``: health 0 OK, 1 WARNING, 2 ERROR, 3 CRITICAL; mode 0
    OPERATIONAL, 1 INITIALIZATION, 2 MAINTENANCE, 3 SOFTWARE_UPDATE, 7 OFFLINE."""

    uptime_s: int
    health: int
    mode: int
    sub_mode: int = 0
    vendor_status: int = 0


@dataclass(frozen=True, slots=True)
class TransferPart:
    """A frame of a multi-frame transfer still in progress (the transfer itself is reported
    with its last frame): every frame of ours decodes to something, so a capture's lines and
    counts show each of them."""

    message_type: str
    """The record the transfer will be: ``RawCommand``, ``EscStatus`` or ``NodeStatus``."""
    frame: int
    """This frame's place in the transfer, from 1."""


DronecanMessage: TypeAlias = RawCommand | EscStatus | NodeStatus | TransferPart


@dataclass(frozen=True, slots=True)
class DronecanFrame:
    """One decoded transfer (a multi-frame one is reported with its last frame)."""

    priority: int
    source_node: int
    transfer_id: int
    message: DronecanMessage
    esc_index: int | None = None
    """The ESC it is from: a Status's own index, or for a NodeStatus the index its node last
    reported (None until then, and for commands)."""
    frames: int = 1
    """How many frames carried it (for a part: how many so far)."""

    @property
    def node_id(self) -> int:
        """The sending node's ID."""
        return self.source_node


_TYPES: Final[dict[type[Any], int]] = {
    RawCommand: TYPE_RAW_COMMAND,
    EscStatus: TYPE_ESC_STATUS,
    NodeStatus: TYPE_NODE_STATUS,
}
_NAMES: Final[dict[int, str]] = {type_id: record.__name__ for record, type_id in _TYPES.items()}


def default_priority(message: RawCommand | EscStatus | NodeStatus) -> int:
    """The priority a message is sent at: commands as ArduPilot sends them, ESC status at
    MEDIUM, NodeStatus at LOWEST."""
    if isinstance(message, RawCommand):
        return PRIORITY_ESC_COMMAND
    return PRIORITY_MEDIUM if isinstance(message, EscStatus) else PRIORITY_LOWEST


def _type_of(arbitration_id: int) -> int:
    return (arbitration_id >> 8) & 0xFFFF


def _float(value: float) -> float | None:
    return None if math.isnan(value) else float(value)


def _unpack(dc_type: Any, payload: bytes) -> Any:
    """Deserialize with ``dronecan``'s own unpacker (what its ``Transfer.from_frames`` calls
    once the frames are checked), tail array optimization on as on classic CAN."""
    message = dc_type()
    message._unpack(bits_from_bytes(payload), True)
    return message


def _deserialize(type_id: int, transfer: Transfer) -> DronecanMessage:
    payload = transfer.payload
    size = len(payload)
    if type_id == TYPE_ESC_STATUS:
        if size != STATUS_BYTES:
            raise DlcError(f"DroneCAN esc.Status of {size} bytes, expected {STATUS_BYTES}")
        status = _unpack(_DC_ESC_STATUS, payload)
        return EscStatus(
            int(status.esc_index),
            int(status.error_count),
            _float(status.voltage),
            _float(status.current),
            _float(status.temperature),
            int(status.rpm),
            int(status.power_rating_pct),
        )
    if type_id == TYPE_NODE_STATUS:
        if size != NODE_STATUS_BYTES:
            raise DlcError(f"DroneCAN NodeStatus of {size} bytes, expected {NODE_STATUS_BYTES}")
        node = _unpack(_DC_NODE_STATUS, payload)
        return NodeStatus(
            int(node.uptime_sec),
            int(node.health),
            int(node.mode),
            int(node.sub_mode),
            int(node.vendor_specific_status_code),
        )
    count = size * 8 // 14
    if not 1 <= count <= MAX_COMMANDS or raw_command_bytes(count) != size:
        raise DlcError(f"DroneCAN RawCommand of {size} bytes is no whole number of int14 values")
    return RawCommand(tuple(int(value) for value in _unpack(_DC_RAW_COMMAND, payload).cmd))


class Decoder:
    """Frames in, :class:`DronecanFrame` out (see the module docstring); one per frame stream.

    ``transfers``/``errors``: transfers decoded and lost.
    """

    __slots__ = ("_index_of_node", "_reassembler")

    def __init__(self) -> None:
        self._reassembler = Reassembler(CRC_START, _type_of)
        self._index_of_node: dict[int, int] = {}

    @property
    def transfers(self) -> int:
        return self._reassembler.transfers

    @property
    def errors(self) -> int:
        return self._reassembler.errors

    def index_of_node(self, node_id: int) -> int | None:
        """The ESC index the node last reported in a Status, if any."""
        return self._index_of_node.get(node_id)

    def decode(
        self, msg: can.Message, esc_indices: Container[int] | None = None
    ) -> DronecanFrame | None:
        """Take one frame; the transfer it completes, decoded, a :class:`TransferPart` for a
        frame of a transfer still in progress, or ``None`` (not ours). With ``esc_indices``, a
        Status of another ESC index (its parts too, once its node is known) and the NodeStatus
        of its node are not ours either.

        Raises:
            bridge.errors.FrameError: the frame breaks its transfer (tail byte, CRC), or a
                complete payload has the wrong length.
        """
        arbitration_id = msg.arbitration_id
        if not msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return None
        if not owns(arbitration_id):
            return None
        transfer = self._reassembler.feed(arbitration_id, msg.data)
        can_id = parse_id(arbitration_id)
        if transfer is None:
            index = self._index_of_node.get(can_id.source_node)
            if esc_indices is not None and index is not None and index not in esc_indices:
                return None
            part = self._reassembler.frames_so_far(arbitration_id)
            return DronecanFrame(
                can_id.priority,
                can_id.source_node,
                msg.data[-1] & 0x1F,
                TransferPart(_NAMES[can_id.type_id], part),
                None,
                part,
            )
        message = _deserialize(can_id.type_id, transfer)
        esc_index: int | None = None
        if isinstance(message, EscStatus):
            esc_index = message.esc_index
            self._index_of_node[can_id.source_node] = esc_index
        elif isinstance(message, NodeStatus):
            esc_index = self._index_of_node.get(can_id.source_node)
        if (
            esc_indices is not None
            and isinstance(message, EscStatus | NodeStatus)
            and (esc_index is None or esc_index not in esc_indices)
        ):
            return None
        return DronecanFrame(
            can_id.priority,
            can_id.source_node,
            transfer.transfer_id,
            message,
            esc_index,
            transfer.frames,
        )

    def reset(self) -> None:
        """Forget transfers in progress (not the node to index map)."""
        self._reassembler.reset()


def _dc_message(message: RawCommand | EscStatus | NodeStatus) -> Any:
    if isinstance(message, RawCommand):
        return _DC_RAW_COMMAND(cmd=list(message.commands))
    if isinstance(message, EscStatus):
        nan = math.nan
        return _DC_ESC_STATUS(
            error_count=message.error_count,
            voltage=nan if message.voltage_v is None else message.voltage_v,
            current=nan if message.current_a is None else message.current_a,
            temperature=nan if message.temperature_k is None else message.temperature_k,
            rpm=message.rpm,
            power_rating_pct=message.power_rating_pct,
            esc_index=message.esc_index,
        )
    return _DC_NODE_STATUS(
        uptime_sec=message.uptime_s,
        health=message.health,
        mode=message.mode,
        sub_mode=message.sub_mode,
        vendor_specific_status_code=message.vendor_status,
    )


def encode(
    message: RawCommand | EscStatus | NodeStatus,
    source_node: int,
    transfer_id: int,
    priority: int | None = None,
) -> list[can.Message]:
    """The frames of one transfer of ``message``, serialized by ``dronecan`` (for the
    simulator and tools: the output loop uses :mod:`bridge.escs.dronecan.wire`). Values beyond
    a field saturate, as ``dronecan`` does (a float16 at ±65504).

    Raises:
        ValueRangeError: a node ID outside 1..125, a transfer ID outside 0..31 or a priority
            outside 0..31.
    """
    if not 0 <= transfer_id <= 31:
        raise ValueRangeError(f"transfer_id = {transfer_id!r} is not in 0..31")
    if priority is None:
        priority = default_priority(message)
    arbitration_id = message_id(priority, _TYPES[type(message)], source_node)
    if source_node == 0:
        raise ValueRangeError("source_node = 0 is anonymous: DroneCAN ESCs ignore it")
    transfer = _DcTransfer(
        transfer_id=transfer_id,
        source_node_id=source_node,
        payload=_dc_message(message),
        transfer_priority=priority,
    )
    frames: list[_DcFrame] = transfer.to_frames()
    return [
        can.Message(arbitration_id=arbitration_id, data=bytes(frame.bytes), is_extended_id=True)
        for frame in frames
    ]


class Sender:
    """Transfer IDs for a node sending several types: :meth:`frames` encodes the next one."""

    __slots__ = ("_ids", "source_node")

    def __init__(self, source_node: int) -> None:
        self.source_node = source_node
        self._ids = TransferIds()

    def frames(self, message: RawCommand | EscStatus | NodeStatus) -> list[can.Message]:
        """The frames of ``message``'s next transfer from this node.

        Raises:
            ValueRangeError: as :func:`encode`.
        """
        transfer_id = self._ids.next(_TYPES[type(message)])
        return encode(message, self.source_node, transfer_id)
