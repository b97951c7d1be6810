"""The hand encoders the output loop uses (bridge/escs/dronecan/wire.py) against ``dronecan``:
RawCommand of 1..20 values, frame for frame, and NodeStatus; the CAN ID, priority and node
ArduPilot uses; the transfer ID per transfer; refusals."""

from __future__ import annotations

from typing import Any

import dronecan
import pytest
from dronecan.transport import Transfer as DcTransfer
from hypothesis import given
from hypothesis import strategies as st

from bridge.errors import ValueRangeError
from bridge.escs.dronecan import wire

DC: Any = dronecan
COMMANDS = st.lists(st.integers(-8192, 8191), min_size=1, max_size=20)


def dronecan_frames(commands: list[int], node: int, transfer_id: int) -> list[tuple[int, bytes]]:
    transfer = DcTransfer(
        transfer_id=transfer_id,
        source_node_id=node,
        payload=DC.uavcan.equipment.esc.RawCommand(cmd=commands),
        transfer_priority=wire.PRIORITY_ESC_COMMAND,
    )
    return [(frame.message_id, bytes(frame.bytes)) for frame in transfer.to_frames()]


@given(COMMANDS, st.integers(1, 125), st.integers(0, 31))
def test_raw_command_is_dronecans(commands: list[int], node: int, transfer_id: int) -> None:
    encoder = wire.RawCommandEncoder(len(commands), node)
    encoder.transfer_id = transfer_id
    frames = encoder.frames(commands)
    assert all(frame.is_extended_id for frame in frames)
    assert [(f.arbitration_id, bytes(f.data)) for f in frames] == dronecan_frames(
        commands, node, transfer_id
    )
    assert (
        wire.pack_raw_command(commands)
        == b"".join(bytes(f.data[:-1]) for f in frames)[-wire.raw_command_bytes(len(commands)) :]
    )


def test_known_frames() -> None:
    """ArduPilot's defaults: node 10, priority 7; four values fit one frame, five need two."""
    encoder = wire.RawCommandEncoder(4, wire.DEFAULT_NODE_ID)
    (frame,) = encoder.frames([1000, 1000, 1000, 1000])
    assert frame.arbitration_id == 0x0704060A
    # The same bit order as CKESC's RawCommand_14b (docs/protocols.md §2.6, §3.3), tail 0xC0.
    assert bytes(frame.data) == bytes.fromhex("e80fa03e80fa03c0")
    five = wire.RawCommandEncoder(5, 10).frames([8191, 0, -1, -8192, 4096])
    assert [len(f.data) for f in five] == [8, 5]
    assert [f.data[-1] for f in five] == [0x80, 0x60]  # start, then end with the toggle set
    assert wire.raw_command_bytes(5) == 9 and wire.raw_command_bytes(20) == 35


def test_transfer_id_counts_per_transfer_and_wraps() -> None:
    encoder = wire.RawCommandEncoder(8, 10)
    tails = [[f.data[-1] & 0x1F for f in encoder.frames([0] * 8)] for _ in range(33)]
    assert [t[0] for t in tails] == [*range(32), 0]
    assert all(len(set(t)) == 1 and len(t) == 3 for t in tails)


def test_refusals() -> None:
    with pytest.raises(ValueRangeError):
        wire.RawCommandEncoder(0, 10)
    with pytest.raises(ValueRangeError):
        wire.RawCommandEncoder(21, 10)
    with pytest.raises(ValueRangeError):
        wire.RawCommandEncoder(4, 0)
    with pytest.raises(ValueRangeError):
        wire.RawCommandEncoder(4, 126)
    encoder = wire.RawCommandEncoder(2, 10)
    with pytest.raises(ValueRangeError):
        encoder.frames([0, 8192])
    with pytest.raises(ValueRangeError):
        encoder.frames([-8193, 0])
    with pytest.raises(ValueRangeError):
        encoder.frames([0])
    assert encoder.transfer_id == 0  # nothing sent, no transfer ID used
    with pytest.raises(ValueRangeError):
        wire.pack_node_status(1, health=4)
    with pytest.raises(ValueRangeError):
        wire.node_status_frame(0, 0, 1)


@given(
    st.integers(0, 0xFFFF_FFFF),
    st.integers(0, 3),
    st.integers(0, 7),
    st.integers(0, 7),
    st.integers(0, 0xFFFF),
    st.integers(0, 31),
)
def test_node_status_is_dronecans(
    uptime: int, health: int, mode: int, sub_mode: int, vendor: int, transfer_id: int
) -> None:
    message = DC.uavcan.protocol.NodeStatus(
        uptime_sec=uptime,
        health=health,
        mode=mode,
        sub_mode=sub_mode,
        vendor_specific_status_code=vendor,
    )
    (expected,) = DcTransfer(
        transfer_id=transfer_id, source_node_id=10, payload=message, transfer_priority=31
    ).to_frames()
    assert wire.pack_node_status(uptime, health, mode, sub_mode, vendor) == bytes(
        expected.bytes[:-1]
    )
    if sub_mode == 0 and vendor == 0:
        frame = wire.node_status_frame(10, transfer_id, uptime, health, mode)
        assert (frame.arbitration_id, bytes(frame.data)) == (
            expected.message_id,
            bytes(expected.bytes),
        )
