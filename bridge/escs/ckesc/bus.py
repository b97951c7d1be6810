"""What CKESC puts on the bus: the kernel filters for its telemetry, and its worst-case load
(docs/protocols.md §2.1, §3.2, §1.3)."""

from __future__ import annotations

from collections.abc import Collection
from typing import Final

from can.typechecking import CanFilter

from bridge.escs import uavcan_v0
from bridge.escs.ckesc import records
from bridge.escs.family import BusFigures, frame_bits
from bridge.escs.filters import check_ids, fewest_blocks

TELEMETRY_TYPES: Final = frozenset(range(records.TYPE_MSG1, records.TYPE_MSG_EXP12 + 1))
"""MSG1..MSG_EXP12 (20050..20064): what :class:`~bridge.telemetry.state.EscTable` takes from an
ESC. CANTest reports, MSGControl acks, GET_ESC_ID answers and service responses are not."""

THROTTLE_FRAME_BYTES: Final = 8  # 12b, 14b (7 + tail) and 10b all fill the frame
TELEMETRY_BYTES: Final = (7, 6, 8)  # MSG1, MSG2, MSG3 with their tail bytes

_TYPE_BITS = 16  # bits 23..8 of a message frame's ID
_NODE_BITS = 7  # bits 6..0
_SERVICE_FLAG = 0x80  # bit 7: 0 for a message (broadcast) frame


def reader_filters(esc_ids: Collection[int]) -> list[CanFilter]:
    """python-can ``can_filters`` that pass exactly the telemetry frames (MSG1..MSG_EXP12) of
    the nodes ``esc_ids``. Nothing else: no 11-bit frame, no other node's frames, no commands,
    no service traffic.

    Each ID field (message type, source node) is split into the fewest aligned blocks that
    cover exactly its values, one filter per pair of blocks: a quad with node IDs 1..4 needs
    12. The priority bits (28..24) match anything, as the decoder ignores them. Remote (RTR)
    frames with a matching ID also pass; the decoder refuses them and counts them malformed.

    Raises:
        ValueRangeError: a node ID outside 1..125 (0 is the host).
    """
    ids = frozenset(esc_ids)
    check_ids(ids, range(1, uavcan_v0.MAX_NODE_ID + 1), "CKESC node")
    return [
        {
            "can_id": type_id << 8 | node,
            "can_mask": type_mask << 8 | _SERVICE_FLAG | node_mask,
            "extended": True,
        }
        for node, node_mask in fewest_blocks(ids, _NODE_BITS)
        for type_id, type_mask in fewest_blocks(TELEMETRY_TYPES, _TYPE_BITS)
    ]


def groups(channels: Collection[int], command: str) -> int:
    """Throttle frames per cycle: 12b needs one per group of four channels in use."""
    if command == "12b":
        return len({(channel - 1) // 4 for channel in channels})
    return 1


def bus_figures(
    n_escs: int,
    channels: Collection[int],
    command: str,
    msg_hz: tuple[float, float, float],
    rate_hz: float,
) -> BusFigures:
    """Worst-case traffic: the throttle frames at ``rate_hz`` and MSG1..3 of every ESC."""
    frames = rate_hz * groups(channels, command)
    return BusFigures(
        command_frames_per_s=frames,
        command_bits_per_s=frames * frame_bits(THROTTLE_FRAME_BYTES),
        telemetry_frames_per_s=n_escs * sum(msg_hz),
        telemetry_bits_per_s=n_escs
        * sum(hz * frame_bits(size) for hz, size in zip(msg_hz, TELEMETRY_BYTES, strict=True)),
    )
