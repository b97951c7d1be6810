"""DroneCAN's kernel filters and bus-load figures (bridge/escs/dronecan/bus.py): a filtered
python-can handle receives every node's esc.Status and NodeStatus (and, reading commands back,
RawCommand) and nothing else; the figures count each frame of a transfer."""

from __future__ import annotations

import itertools

import can
import pytest

from bridge.can_io import open_bus
from bridge.config import CanConfig
from bridge.errors import ValueRangeError
from bridge.escs.dronecan import bus, wire
from bridge.escs.family import frame_bits
from bridge.escs.uavcan_v0 import message_id, service_id

_channels = itertools.count()


def test_a_filtered_handle_receives_our_types_from_any_node() -> None:
    telemetry = [
        message_id(priority, type_id, node)
        for type_id in (wire.TYPE_ESC_STATUS, wire.TYPE_NODE_STATUS)
        for priority, node in ((16, 20), (31, 21), (0, 125))
    ]
    commands = [message_id(7, wire.TYPE_RAW_COMMAND, 10), message_id(0, wire.TYPE_RAW_COMMAND, 3)]
    others = [
        message_id(16, wire.TYPE_RAW_COMMAND + 1, 20),  # esc.RPMCommand
        message_id(31, 20050, 3),  # a CKESC MSG1
        service_id(16, 1, True, 20, 10),  # GetNodeInfo, a service
        wire.TYPE_ESC_STATUS << 8 | 0x80 | 20,  # the status type's bits with the service bit set
    ]
    config = CanConfig(interface="virtual", channel=f"dronecan-filters-{next(_channels)}")
    filters = bus.reader_filters([1, 2, 3, 4])
    receiver = open_bus(config, 1_000_000, receive="telemetry", filters=filters)
    sender = open_bus(config, 1_000_000)
    try:
        for can_id in telemetry + commands + others:
            sender.send(can.Message(arbitration_id=can_id, data=bytes(8)))
        sender.send(can.Message(arbitration_id=0x155, data=bytes(8), is_extended_id=False))
        got = []
        while (msg := receiver.recv(0.05)) is not None:
            got.append(msg.arbitration_id)
        assert got == telemetry
    finally:
        receiver.shutdown()
        sender.shutdown()


def test_esc_numbers_outside_1_to_20_are_refused() -> None:
    with pytest.raises(ValueRangeError, match=r"DroneCAN ESC IDs \[0, 21\] are not in 1\.\.20"):
        bus.reader_filters([0, 1, 21])


def test_figures_count_every_frame_of_a_transfer() -> None:
    one = bus.bus_figures(4, 4, 50.0, 400.0)  # four values: one 8-byte frame a tick
    assert one.command_frames_per_s == 401
    assert one.command_bits_per_s == 400 * 160 + 160
    assert one.telemetry_frames_per_s == 4 * (50 * 3 + 1)
    assert one.telemetry_bits_per_s == 4 * (50 * (2 * 160 + frame_bits(3)) + 160)
    # Twenty values: 35 bytes and the CRC, 37 in six frames (five of 8 bytes, one of 3).
    twenty = bus.bus_figures(20, 20, 0.0, 100.0)
    assert twenty.command_frames_per_s == 100 * 6 + 1
    assert twenty.command_bits_per_s == 100 * (5 * 160 + frame_bits(3)) + 160
    assert twenty.telemetry_frames_per_s == 20
