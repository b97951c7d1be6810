"""The UAVCAN v0 framing (bridge/escs/uavcan_v0.py) against the ``dronecan`` package's own: the
CAN ID helpers, tail byte and transfer IDs; the CRC, the signature's CRC start, the split into
frames, and the reassembly state machine's round trips and refusals."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import dronecan
import pytest
from dronecan.dsdl.common import crc16_from_bytes
from dronecan.transport import Transfer as DcTransfer
from hypothesis import given
from hypothesis import strategies as st

from bridge.errors import CrcError, DlcError, TailByteError, ValueRangeError
from bridge.escs.dronecan.wire import CRC_START, SIGNATURE_RAW_COMMAND, TYPE_RAW_COMMAND
from bridge.escs.uavcan_v0 import (
    CanId,
    Reassembler,
    TransferIds,
    crc16,
    frame_sizes,
    frames_data,
    message_id,
    parse_id,
    service_id,
    tail_byte,
)

DC: Any = dronecan
RAW_ID = 0x0704060A  # RawCommand, priority 7, node 10
STATUS_ID = 0x10040A14  # esc.Status, priority 16, node 20


def _type_of(arbitration_id: int) -> int:
    return (arbitration_id >> 8) & 0xFFFF


def _reassembler() -> Reassembler:
    return Reassembler(CRC_START, _type_of)


@given(st.binary(max_size=64), st.integers(0, 0xFFFF))
def test_crc16_is_dronecans(data: bytes, start: int) -> None:
    assert crc16(data, start) == crc16_from_bytes(data, initial=start)


def test_crc_starts_are_the_signatures_crc() -> None:
    for dc_type in (
        DC.uavcan.equipment.esc.RawCommand,
        DC.uavcan.equipment.esc.Status,
        DC.uavcan.protocol.NodeStatus,
    ):
        dtype = DC.get_dronecan_data_type(dc_type())
        assert CRC_START[dtype.default_dtid] == dtype.base_crc
    assert DC.get_dronecan_data_type(
        DC.uavcan.equipment.esc.RawCommand()
    ).get_data_type_signature() == (SIGNATURE_RAW_COMMAND)


@given(st.binary(min_size=1, max_size=40), st.integers(0, 31))
def test_frames_are_dronecans(payload: bytes, transfer_id: int) -> None:
    """Any payload split as ``dronecan`` splits a RawCommand transfer of those bytes."""
    transfer = DcTransfer(transfer_id=transfer_id, source_node_id=10, transfer_priority=7)
    transfer.payload = payload
    transfer.data_type_id = TYPE_RAW_COMMAND
    transfer.data_type_crc = CRC_START[TYPE_RAW_COMMAND]
    expected = [bytes(frame.bytes) for frame in transfer.to_frames()]
    assert frames_data(payload, transfer_id, CRC_START[TYPE_RAW_COMMAND]) == expected
    assert frame_sizes(len(payload)) == [len(data) for data in expected]


@given(st.binary(max_size=60), st.integers(0, 31))
def test_reassembly_round_trip(payload: bytes, transfer_id: int) -> None:
    reassembler = _reassembler()
    frames = frames_data(payload, transfer_id, CRC_START[TYPE_RAW_COMMAND])
    results = [reassembler.feed(RAW_ID, data) for data in frames]
    assert results[:-1] == [None] * (len(frames) - 1)
    last = results[-1]
    assert last is not None
    assert (last.payload, last.transfer_id, last.frames) == (payload, transfer_id, len(frames))
    assert (reassembler.transfers, reassembler.errors) == (1, 0)


def test_interleaved_senders_and_priorities_keep_their_own_sessions() -> None:
    reassembler = _reassembler()
    a = frames_data(bytes(range(20)), 3, CRC_START[TYPE_RAW_COMMAND])
    b = frames_data(bytes(range(100, 120)), 9, CRC_START[TYPE_RAW_COMMAND])
    other_node = RAW_ID + 1
    out = []
    for frame_a, frame_b in zip(a, b, strict=True):
        out.append(reassembler.feed(RAW_ID, frame_a))
        out.append(reassembler.feed(other_node, frame_b))
    done = [t for t in out if t is not None]
    assert [t.payload for t in done] == [bytes(range(20)), bytes(range(100, 120))]
    # The same session at another priority continues the transfer (the session ignores it).
    frames = frames_data(bytes(10), 1, CRC_START[TYPE_RAW_COMMAND])
    assert reassembler.feed(RAW_ID, frames[0]) is None
    assert reassembler.feed(RAW_ID & ~(0x1F << 24), frames[1]) is not None


def test_a_new_start_abandons_the_transfer_in_progress() -> None:
    reassembler = _reassembler()
    first = frames_data(bytes(20), 1, CRC_START[TYPE_RAW_COMMAND])
    second = frames_data(bytes(range(20)), 2, CRC_START[TYPE_RAW_COMMAND])
    assert reassembler.feed(RAW_ID, first[0]) is None
    results = [reassembler.feed(RAW_ID, data) for data in second]
    assert results[-1] is not None and results[-1].payload == bytes(range(20))
    with pytest.raises(TailByteError):  # the rest of the first: no transfer in progress
        reassembler.feed(RAW_ID, first[1])


def test_broken_sequences_are_refused_and_counted() -> None:
    crc_start = CRC_START[TYPE_RAW_COMMAND]
    frames = frames_data(bytes(range(30)), 4, crc_start)
    assert len(frames) == 5
    reassembler = _reassembler()
    with pytest.raises(TailByteError, match="no transfer in progress"):
        reassembler.feed(RAW_ID, frames[1])
    reassembler.feed(RAW_ID, frames[0])
    with pytest.raises(TailByteError, match="toggle"):
        reassembler.feed(RAW_ID, frames[2])  # frame 1 lost: the toggle does not match
    reassembler.feed(RAW_ID, frames[0])
    wrong_id = bytearray(frames[1])
    wrong_id[-1] ^= 0x01
    with pytest.raises(TailByteError, match="transfer ID 4"):
        reassembler.feed(RAW_ID, wrong_id)
    toggled_start = bytearray(frames[0])
    toggled_start[-1] |= 0x20
    with pytest.raises(TailByteError, match="toggle bit set"):
        reassembler.feed(RAW_ID, toggled_start)
    with pytest.raises(DlcError):
        reassembler.feed(RAW_ID, b"")
    with pytest.raises(DlcError):
        reassembler.feed(RAW_ID, frames[0][:4] + frames[0][-1:])  # a short first frame
    reassembler.feed(RAW_ID, frames[0])
    with pytest.raises(DlcError):
        reassembler.feed(RAW_ID, frames[1][:3] + frames[1][-1:])  # a short middle frame
    bad_crc = [bytearray(f) for f in frames]
    bad_crc[0][0] ^= 0xFF
    with pytest.raises(CrcError):
        for data in bad_crc:
            reassembler.feed(RAW_ID, data)
    # Another type's signature: a RawCommand transfer does not pass for an esc.Status.
    with pytest.raises(CrcError):
        for frame in frames:
            reassembler.feed(STATUS_ID, frame)
    assert reassembler.errors == 8 and reassembler.transfers == 0
    for frame in frames:  # and it still works
        result = reassembler.feed(RAW_ID, frame)
    assert result is not None and reassembler.transfers == 1


def test_reset_forgets_transfers_in_progress() -> None:
    reassembler = _reassembler()
    frames = frames_data(bytes(20), 0, CRC_START[TYPE_RAW_COMMAND])
    reassembler.feed(RAW_ID, frames[0])
    reassembler.reset()
    with pytest.raises(TailByteError):
        reassembler.feed(RAW_ID, frames[1])


def test_transfer_id_range() -> None:
    with pytest.raises(ValueRangeError):
        frames_data(b"\x00", 32, 0xFFFF)


# --------------------------------------------------------------------------------------------
# CAN ID, tail byte, transfer IDs


@given(st.integers(0, 31), st.integers(0, 0xFFFF), st.integers(0, 0x7D))
def test_parse_message_id(priority: int, type_id: int, source: int) -> None:
    assert parse_id(message_id(priority, type_id, source)) == CanId(
        priority, False, type_id, source, None, None
    )


@pytest.mark.parametrize(
    ("call", "pattern"),
    [
        (lambda: message_id(32, 20050, 1), r"priority = 32 is not in 0\.\.31"),
        (lambda: message_id(-1, 20050, 1), r"priority = -1 is not in 0\.\.31"),
        (lambda: message_id(0, 0x10000, 1), r"type_id = 65536 is not in 0\.\.65535"),
        (lambda: message_id(0, 20050, 0x7E), r"source_node = 126 is not in 0\.\.125"),
        (lambda: service_id(0, 256, True, 1, 0), r"service_type = 256 is not in 0\.\.255"),
        (lambda: service_id(0, 212, True, 0x7F, 0), r"destination_node = 127 is not in 0\.\.125"),
        (lambda: service_id(0, 212, True, 1, 0x7E), r"source_node = 126 is not in 0\.\.125"),
        (lambda: parse_id(1 << 29), r"arbitration_id = 536870912 is not in 0\.\.536870911"),
        (lambda: tail_byte(32), r"transfer_id = 32 is not in 0\.\.31"),
        (lambda: tail_byte(-1), r"transfer_id = -1 is not in 0\.\.31"),
    ],
)
def test_id_helper_ranges(call: Callable[[], object], pattern: str) -> None:
    with pytest.raises(ValueRangeError, match=pattern):
        call()


def test_tail_byte() -> None:
    assert [tail_byte(tid) for tid in (0, 1, 31)] == [0xC0, 0xC1, 0xDF]


def test_transfer_ids_count_per_type_and_wrap() -> None:
    ids = TransferIds()
    assert [ids.next(20101) for _ in range(33)] == [*range(32), 0]
    assert ids.next(20100) == 0  # another type has its own counter
    assert ids.next(212) == 0
    assert ids.next(20101) == 1
    assert TransferIds().next(20101) == 0  # and another sender too


@given(
    st.integers(0, 31), st.integers(1, 0x7D), st.lists(st.integers(0, 2000), min_size=4, max_size=4)
)
def test_message_id_layout_matches_dronecan(
    priority: int, source: int, throttles: list[int]
) -> None:
    command = DC.uavcan.equipment.esc.RawCommand(cmd=throttles)
    transfer = DcTransfer(source_node_id=source, payload=command, transfer_priority=priority)
    assert transfer.data_type_id == 1030
    (frame,) = transfer.to_frames()
    assert frame.message_id == message_id(priority, 1030, source)
    assert parse_id(frame.message_id) == CanId(priority, False, 1030, source, None, None)


@given(st.integers(0, 31), st.integers(0, 0xFFFF), st.integers(1, 0x7D))
def test_message_id_matches_dronecan_for_any_type(priority: int, type_id: int, source: int) -> None:
    transfer = DcTransfer(source_node_id=source, transfer_priority=priority)
    transfer.data_type_id = type_id
    assert transfer.message_id == message_id(priority, type_id, source)


@given(
    st.integers(0, 31),
    st.integers(0, 0xFF),
    st.booleans(),
    st.integers(1, 0x7D),
    st.integers(0, 0x7D),
)
def test_service_id_matches_dronecan(
    priority: int, service_type: int, request: bool, destination: int, source: int
) -> None:
    transfer = DcTransfer(
        source_node_id=source,
        dest_node_id=destination,
        transfer_priority=priority,
        service_not_message=True,
        request_not_response=request,
    )
    transfer.data_type_id = service_type
    can_id = service_id(priority, service_type, request, destination, source)
    assert transfer.message_id == can_id
    parsed = DcTransfer()
    parsed.message_id = can_id
    assert parse_id(can_id) == CanId(
        parsed.transfer_priority,
        True,
        parsed.data_type_id,
        parsed.source_node_id,
        parsed.dest_node_id,
        parsed.request_not_response,
    )
