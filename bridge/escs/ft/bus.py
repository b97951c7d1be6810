"""What FT puts on the bus: the kernel filters for its telemetry, and its worst-case load
(docs/protocols.md §4.2, §4.6, §1.3)."""

from __future__ import annotations

from collections.abc import Collection
from typing import Final

from can.typechecking import CanFilter

from bridge.escs.family import BusFigures, frame_bits
from bridge.escs.filters import check_ids, fewest_blocks
from bridge.escs.ft import records
from bridge.escs.ft.driver import ft_command_dlc

TELEMETRY_COMMANDS: Final = frozenset(records.Telemetry)
TELEMETRY_FRAMES: Final = 3  # REALTIME_DATA_0, 1 and 2, 8 bytes each
TELEMETRY_BYTES: Final = 8

_FIELD_BITS = 8  # ESC ID in bits 15..8, command in bits 7..0
_ZERO_BITS = 0x1FFF_0000  # bits 28..16 are zero in every FT ID


def reader_filters(esc_ids: Collection[int]) -> list[CanFilter]:
    """python-can ``can_filters`` that pass exactly the real-time data frames of the ESCs
    ``esc_ids``. Nothing else.

    Each ID field (command, ESC ID) is split into the fewest aligned blocks that cover exactly
    its values, one filter per pair of blocks: a quad with ESC IDs 1..4 needs 6.

    Raises:
        ValueRangeError: an ESC ID outside 0..255.
    """
    ids = frozenset(esc_ids)
    check_ids(ids, range(records.ESC_ID_MIN, records.ESC_ID_MAX + 1), "FT ESC")
    return [
        {
            "can_id": esc_id << 8 | command,
            "can_mask": _ZERO_BITS | esc_mask << 8 | command_mask,
            "extended": True,
        }
        for esc_id, esc_mask in fewest_blocks(ids, _FIELD_BITS)
        for command, command_mask in fewest_blocks(TELEMETRY_COMMANDS, _FIELD_BITS)
    ]


def bus_figures(n_escs: int, crc: bool, telemetry_hz: float, rate_hz: float) -> BusFigures:
    """Worst-case traffic: a command per ESC per tick, and three real-time frames per ESC."""
    frames = rate_hz * n_escs
    telemetry_frames = n_escs * TELEMETRY_FRAMES * telemetry_hz
    return BusFigures(
        command_frames_per_s=frames,
        command_bits_per_s=frames * frame_bits(ft_command_dlc(crc)),
        telemetry_frames_per_s=telemetry_frames,
        telemetry_bits_per_s=telemetry_frames * frame_bits(TELEMETRY_BYTES),
    )
