"""DroneCAN records (bridge/escs/dronecan/codec.py): round trips through ``dronecan``'s
serializer for every field's range, NaN fields, the decoder's reassembly across interleaved
ESCs, NodeStatus mapped to the ESC index its node reported, and what is not ours."""

from __future__ import annotations

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridge.errors import CrcError, DlcError, FrameError, ValueRangeError
from bridge.escs.dronecan import codec, wire
from bridge.escs.dronecan.codec import Decoder, EscStatus, NodeStatus, RawCommand, TransferPart
from bridge.escs.uavcan_v0 import frames_data

# Values a float16 holds exactly, and NaN (not measured).
HALF = st.one_of(
    st.none(), st.integers(-2048, 2048).map(float), st.sampled_from([0.5, 16.25, 300.5, 65504.0])
)


def decode_all(decoder: Decoder, frames: list[can.Message]) -> list[codec.DronecanFrame]:
    """The whole transfers ``frames`` carry (every other frame decodes to a part of one)."""
    decoded = [decoder.decode(m) for m in frames]
    assert all(f is not None for f in decoded)
    return [f for f in decoded if f is not None and not isinstance(f.message, TransferPart)]


@given(
    st.integers(0, 31),
    st.integers(0, 0xFFFF_FFFF),
    HALF,
    HALF,
    HALF,
    st.integers(-(1 << 17), (1 << 17) - 1),
    st.integers(0, 127),
    st.integers(1, 125),
    st.integers(0, 31),
)
def test_esc_status_round_trip(
    index: int,
    errors: int,
    voltage: float | None,
    current: float | None,
    temperature: float | None,
    rpm: int,
    power: int,
    node: int,
    transfer_id: int,
) -> None:
    status = EscStatus(index, errors, voltage, current, temperature, rpm, power)
    frames = codec.encode(status, node, transfer_id)
    assert len(frames) == 3  # 14 bytes: a multi-frame transfer
    (frame,) = decode_all(Decoder(), frames)
    assert frame.message == status
    assert (frame.source_node, frame.node_id, frame.esc_index) == (node, node, index)
    assert (frame.transfer_id, frame.priority, frame.frames) == (transfer_id, 16, 3)
    fresh = Decoder()
    parts = [fresh.decode(m) for m in frames[:2]]
    assert [p.message if p else None for p in parts] == [
        TransferPart("EscStatus", 1),
        TransferPart("EscStatus", 2),
    ]
    assert all(p is not None and p.transfer_id == transfer_id for p in parts)


@given(st.lists(st.integers(-8192, 8191), min_size=1, max_size=20), st.integers(0, 31))
def test_raw_command_from_the_hand_encoder_decodes(commands: list[int], transfer_id: int) -> None:
    encoder = wire.RawCommandEncoder(len(commands), 10)
    encoder.transfer_id = transfer_id
    (frame,) = decode_all(Decoder(), encoder.frames(commands))
    assert frame.message == RawCommand(tuple(commands))
    assert (frame.priority, frame.source_node, frame.esc_index) == (7, 10, None)
    # And dronecan's encoder (the codec's) gives the very frames the hand encoder gave.
    by_dronecan = codec.encode(RawCommand(tuple(commands)), 10, transfer_id)
    encoder.transfer_id = transfer_id
    assert [(m.arbitration_id, bytes(m.data)) for m in by_dronecan] == [
        (m.arbitration_id, bytes(m.data)) for m in encoder.frames(commands)
    ]


def test_node_status_maps_to_the_index_its_node_reported() -> None:
    decoder = Decoder()
    node_status = codec.encode(NodeStatus(42, 2, 0), 25, 0)
    (before,) = decode_all(decoder, node_status)
    assert before.esc_index is None and before.message == NodeStatus(42, 2, 0)
    decode_all(decoder, codec.encode(EscStatus(3, 0, 16.0, 1.0, 300.0, 100, 10), 25, 0))
    (after,) = decode_all(decoder, codec.encode(NodeStatus(43, 0, 0), 25, 1))
    assert after.esc_index == 3 and decoder.index_of_node(25) == 3
    # Filtered by our ESC indices: another index's Status and its node's NodeStatus are not ours.
    assert decoder.decode(node_status[0], esc_indices={0, 1}) is None
    assert decoder.decode(node_status[0], esc_indices={3}) is not None
    other = codec.encode(EscStatus(7, 0, 16.0, 1.0, 300.0, 100, 10), 26, 0)
    first = decoder.decode(other[0], esc_indices={3})  # a part: its node's index is not known
    assert first is not None and isinstance(first.message, TransferPart)
    second, last = (decoder.decode(msg, esc_indices={3}) for msg in other[1:])
    assert second is not None and isinstance(second.message, TransferPart) and last is None
    assert decoder.index_of_node(26) == 7
    assert decoder.decode(other[0], esc_indices={3}) is None  # now it is


def test_interleaved_status_transfers_of_several_escs() -> None:
    decoder = Decoder()
    per_esc = [
        codec.encode(EscStatus(i, i, 16.0, float(i), 300.0, 1000 * i, i), 20 + i, i)
        for i in range(4)
    ]
    order = [per_esc[i][k] for k in range(3) for i in range(4)]
    frames = decode_all(decoder, order)
    assert [f.esc_index for f in frames] == [0, 1, 2, 3]
    assert decoder.transfers == 4 and decoder.errors == 0


def test_not_ours() -> None:
    decoder = Decoder()
    (status,) = codec.encode(NodeStatus(1, 0, 0), 25, 0)
    status_data = bytes(status.data)
    assert (
        decoder.decode(can.Message(arbitration_id=0x155, data=status_data, is_extended_id=False))
        is None
    )
    service = 0x1E01_9A19  # a service frame (bit 7) from node 25
    assert decoder.decode(can.Message(arbitration_id=service, data=status_data)) is None
    anonymous = status.arbitration_id & ~0x7F
    assert decoder.decode(can.Message(arbitration_id=anonymous, data=status_data)) is None
    other_type = wire.TYPE_RAW_COMMAND + 1  # esc.RPMCommand
    msg = can.Message(arbitration_id=0x07000000 | other_type << 8 | 10, data=status_data)
    assert decoder.decode(msg) is None
    ckesc_msg1 = can.Message(arbitration_id=0x1F4E5203, data=bytes.fromhex("e02edc050001c7"))
    assert decoder.decode(ckesc_msg1) is None
    assert codec.owns(status.arbitration_id) and not codec.owns(0x1F4E5203)


def test_malformed_transfers() -> None:
    decoder = Decoder()
    node_id = wire.TYPE_NODE_STATUS << 8 | 0x1F000019
    short = frames_data(bytes(5), 0, wire.CRC_START[wire.TYPE_NODE_STATUS])
    with pytest.raises(DlcError, match="NodeStatus of 5 bytes"):
        decoder.decode(can.Message(arbitration_id=node_id, data=short[0]))
    status_id = wire.TYPE_ESC_STATUS << 8 | 0x10000019
    for data in frames_data(bytes(13), 0, wire.CRC_START[wire.TYPE_ESC_STATUS])[:-1]:
        decoder.decode(can.Message(arbitration_id=status_id, data=data))
    with pytest.raises(DlcError, match=r"esc\.Status of 13 bytes"):
        last = frames_data(bytes(13), 0, wire.CRC_START[wire.TYPE_ESC_STATUS])[-1]
        decoder.decode(can.Message(arbitration_id=status_id, data=last))
    raw_id = wire.TYPE_RAW_COMMAND << 8 | 0x0700000A
    with pytest.raises(DlcError, match="RawCommand of 5 bytes"):
        decoder.decode(can.Message(arbitration_id=raw_id, data=bytes(5) + b"\xc0"))
    frames = codec.encode(EscStatus(1, 0, 1.0, 1.0, 1.0, 1, 1), 20, 0)
    frames[1].data[0] ^= 1
    with pytest.raises(CrcError):
        decode_all(decoder, frames)
    assert issubclass(CrcError, FrameError)


def test_encode_refusals_and_saturation() -> None:
    with pytest.raises(ValueRangeError):
        codec.encode(NodeStatus(1, 0, 0), 0, 0)
    with pytest.raises(ValueRangeError):
        codec.encode(NodeStatus(1, 0, 0), 10, 32)
    with pytest.raises(ValueRangeError):
        RawCommand(())
    with pytest.raises(ValueRangeError):
        RawCommand((8192,))
    (frame,) = decode_all(Decoder(), codec.encode(EscStatus(0, 0, 1e6, None, 1.0, 0, 0), 20, 0))
    assert isinstance(frame.message, EscStatus)
    assert frame.message.voltage_v == 65504.0 and frame.message.current_a is None
    assert frame.message.temperature_c == pytest.approx(1.0 - 273.15)


def test_sender_counts_transfer_ids_per_type() -> None:
    sender = codec.Sender(30)
    ids = [sender.frames(NodeStatus(i, 0, 0))[0].data[-1] & 0x1F for i in range(3)]
    status_ids = [sender.frames(EscStatus(0, 0, 1.0, 1.0, 1.0, 0, 0))[0].data[-1] & 0x1F]
    assert ids == [0, 1, 2] and status_ids == [0]
