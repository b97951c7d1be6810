"""What DroneCAN puts on the bus: the kernel filters for its telemetry, and its worst-case load
(docs/protocols.md §1.3's frame lengths; the transfers' frame counts, §2.5, from
:mod:`bridge.escs.uavcan_v0`)."""

from __future__ import annotations

from collections.abc import Collection
from typing import Final

from can.typechecking import CanFilter

from bridge.escs.dronecan.wire import (
    NODE_STATUS_BYTES,
    STATUS_BYTES,
    TYPE_ESC_STATUS,
    TYPE_NODE_STATUS,
    raw_command_bytes,
)
from bridge.escs.family import BusFigures, frame_bits
from bridge.escs.filters import check_ids
from bridge.escs.uavcan_v0 import frame_sizes

ESC_NUMBERS: Final = range(1, 21)
_TYPE_MASK: Final = 0xFFFF << 8 | 0x80  # the message type, and bit 7 clear: a message frame


def _type_filter(type_id: int) -> CanFilter:
    return {"can_id": type_id << 8, "can_mask": _TYPE_MASK, "extended": True}


def reader_filters(esc_ids: Collection[int]) -> list[CanFilter]:
    """python-can ``can_filters`` passing every node's esc.Status and NodeStatus. An ESC's
    index is in its Status's payload and its node ID is not known in advance, so the kernel
    cannot pick our ESCs out: the decoder does.

    Raises:
        ValueRangeError: an ESC number outside 1..20.
    """
    check_ids(esc_ids, ESC_NUMBERS, "DroneCAN ESC")
    return [_type_filter(type_id) for type_id in (TYPE_ESC_STATUS, TYPE_NODE_STATUS)]


def _bits(payload_bytes: int) -> int:
    return sum(frame_bits(size) for size in frame_sizes(payload_bytes))


def bus_figures(command_slots: int, n_escs: int, status_hz: float, rate_hz: float) -> BusFigures:
    """Worst-case traffic: a RawCommand of ``command_slots`` values per tick and our NodeStatus
    once a second; from each ESC its esc.Status at ``status_hz`` and NodeStatus once a second."""
    command_bytes = raw_command_bytes(command_slots)
    status_frames = len(frame_sizes(STATUS_BYTES))
    return BusFigures(
        command_frames_per_s=rate_hz * len(frame_sizes(command_bytes)) + 1,
        command_bits_per_s=rate_hz * _bits(command_bytes) + _bits(NODE_STATUS_BYTES),
        telemetry_frames_per_s=n_escs * (status_hz * status_frames + 1),
        telemetry_bits_per_s=n_escs * (status_hz * _bits(STATUS_BYTES) + _bits(NODE_STATUS_BYTES)),
    )
