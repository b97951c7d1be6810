"""What VESC puts on the bus: the kernel filters for its status frames, and its worst-case load
(docs/protocols.md §6.2, §6.5, §6.8, §1.3)."""

from __future__ import annotations

from collections.abc import Collection
from typing import Final

from can.typechecking import CanFilter

from bridge.escs.family import BusFigures, frame_bits
from bridge.escs.filters import check_ids, fewest_blocks
from bridge.escs.vesc.records import COMMAND_DLC, STATUS_DLC, STATUS_PACKETS

STATUS_FRAMES: Final = 5
"""STATUS 1-5, what docs/escs.md asks to turn on; each at ``vesc_status_hz``."""
ESC_IDS: Final = range(0, 255)
"""A VESC's own ID: 255 addresses all of them."""

_FIELD_BITS = 8  # packet in bits 15..8, controller ID in bits 7..0
_ZERO_BITS = 0x1FFF_0000  # bits 28..16 are zero in every VESC ID


def reader_filters(esc_ids: Collection[int]) -> list[CanFilter]:
    """python-can ``can_filters`` that pass exactly the status frames of the VESCs ``esc_ids``.
    Nothing else: not the commands, PONG, NOTIFY_BOOT or VESC Tool's traffic.

    Each ID field (packet, controller ID) is split into the fewest aligned blocks that cover
    exactly its values, one filter per pair of blocks.

    Raises:
        ValueRangeError: a VESC ID outside 0..254.
    """
    ids = frozenset(esc_ids)
    check_ids(ids, ESC_IDS, "VESC")
    return [
        {
            "can_id": packet << 8 | controller_id,
            "can_mask": _ZERO_BITS | packet_mask << 8 | controller_mask,
            "extended": True,
        }
        for packet, packet_mask in fewest_blocks(STATUS_PACKETS, _FIELD_BITS)
        for controller_id, controller_mask in fewest_blocks(ids, _FIELD_BITS)
    ]


def bus_figures(n_escs: int, status_hz: float, rate_hz: float) -> BusFigures:
    """Worst-case traffic: a command per VESC per cycle, and five status frames per VESC."""
    frames = rate_hz * n_escs
    status_frames = n_escs * STATUS_FRAMES * status_hz
    return BusFigures(
        command_frames_per_s=frames,
        command_bits_per_s=frames * frame_bits(COMMAND_DLC),
        telemetry_frames_per_s=status_frames,
        telemetry_bits_per_s=status_frames * frame_bits(STATUS_DLC),
    )
