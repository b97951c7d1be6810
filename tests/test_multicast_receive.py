"""The udp_multicast receive path that drops refused frames before unpacking them
(bridge/multicast_receive.py), on real udp_multicast buses of a port of each test's own: what
it returns is what python-can's own ``recv`` would, less the frames ``passes`` refuses."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Iterator

import can
import msgpack
import pytest
from can.interfaces.udp_multicast.utils import pack_message
from conftest import MULTICAST_GROUP, free_port, multicast_bus

from bridge.multicast_receive import MAX_DROPPED_PER_CALL, MulticastReceiver, receives_multicast

SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
WANTED = 0x10F1  # the one ID (extended) the receivers here take
REFUSED = 0x4E2  # an ID they do not


def wanted(can_id: int, extended: bool) -> bool:
    return (can_id, extended) == (WANTED, True)


class Link:
    """A receiving handle, a :class:`MulticastReceiver` on it, and a sender on the same bus:
    python-can's or, for hand-made datagrams, a plain UDP socket to the group."""

    def __init__(self, port: int, fd: bool = True) -> None:
        """``fd``: the receiving handle's CAN FD (python-can's default: on)."""
        self.port = port
        self.bus = multicast_bus(port, fd)
        self.receiver = MulticastReceiver(self.bus, wanted)
        self.sender = multicast_bus(port)
        self.raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.raw.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)

    def send_raw(self, datagram: bytes) -> None:
        self.raw.sendto(datagram, (MULTICAST_GROUP, self.port))

    def received(self) -> list[can.Message]:
        """Every frame the receiver returns until the queue is empty (a second at most)."""
        found: list[can.Message] = []
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            msg = self.receiver.recv(0.2)
            if msg is None:
                if found:
                    break
                continue
            found.append(msg)
        return found

    def close(self) -> None:
        self.receiver.close()
        self.raw.close()
        self.sender.shutdown()
        self.bus.shutdown()


@pytest.fixture
def link() -> Iterator[Link]:
    made = Link(free_port())
    yield made
    made.close()


def test_it_is_used_for_udp_multicast_handles_only(link: Link) -> None:
    virtual = can.Bus(interface="virtual", channel="multicast-receive")
    try:
        assert (receives_multicast(link.bus), receives_multicast(virtual)) == (True, False)
    finally:
        virtual.shutdown()


def test_it_returns_the_wanted_frames_whole_and_drops_the_others(link: Link) -> None:
    for i in range(20):
        link.sender.send(can.Message(arbitration_id=REFUSED, data=[i], is_extended_id=False))
        link.sender.send(can.Message(arbitration_id=WANTED, data=[i, 1, 2]))
    time.sleep(0.1)
    found = link.received()
    assert [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in found] == [
        (WANTED, True, bytes([i, 1, 2])) for i in range(20)
    ]
    assert link.receiver.dropped == 20
    # Stamped by the kernel on arrival (the sender's stamp, 0, is replaced).
    assert all(abs(m.timestamp - time.time()) < 5 for m in found), [m.timestamp for m in found]


def test_a_refused_frame_is_never_unpacked_a_wanted_one_is(link: Link) -> None:
    """A datagram whose head says a refused ID and whose rest is garbage is dropped without a
    word; with the wanted ID the same garbage is a read error, as python-can's would be."""

    def garbled(msg: can.Message) -> bytes:
        packed = pack_message(msg)
        head_end = packed.index(b"\xaeis_error_frame\xc2") + 16  # the ID and flags read
        return packed[:head_end] + b"\xc1\xc1\xc1"  # 0xc1: never used in msgpack

    link.send_raw(garbled(can.Message(arbitration_id=REFUSED, is_extended_id=False)))
    time.sleep(0.1)
    assert link.receiver.recv(0.2) is None
    assert link.receiver.dropped == 1
    link.send_raw(garbled(can.Message(arbitration_id=WANTED)))
    with pytest.raises(can.CanOperationError, match="could not unpack received message"):
        link.receiver.recv(1.0)


def test_a_datagram_laid_out_otherwise_is_judged_whole(link: Link) -> None:
    """Another sender's key order: unpacked, then judged on the message."""

    def packed(can_id: int, extended: bool) -> bytes:
        fields = {
            "arbitration_id": can_id,
            "data": b"\x07",
            "is_extended_id": extended,
            "timestamp": 1.5,
            "dlc": 1,
        }
        return bytes(msgpack.packb(fields, use_bin_type=True))

    link.send_raw(packed(REFUSED, False))
    link.send_raw(packed(WANTED, True))
    time.sleep(0.1)
    found = link.received()
    assert [(m.arbitration_id, bytes(m.data)) for m in found] == [(WANTED, b"\x07")]
    assert link.receiver.dropped == 1


def test_an_error_frame_always_passes(link: Link) -> None:
    link.sender.send(can.Message(arbitration_id=REFUSED, is_error_frame=True, is_extended_id=False))
    time.sleep(0.1)
    found = link.received()
    assert [(m.arbitration_id, m.is_error_frame) for m in found] == [(REFUSED, True)]


@pytest.mark.parametrize("fd", [True, False])
def test_a_can_fd_frame_is_dropped_on_a_classic_handle_only(fd: bool) -> None:
    link = Link(free_port(), fd=fd)
    try:
        link.sender.send(can.Message(arbitration_id=WANTED, is_fd=True, data=bytes(12)))
        link.sender.send(can.Message(arbitration_id=WANTED, data=b"\x01"))
        time.sleep(0.1)
        found = link.received()
        kept = [(True, bytes(12))] if fd else []
        assert [(m.is_fd, bytes(m.data)) for m in found] == [*kept, (False, b"\x01")]
        assert link.receiver.dropped == (0 if fd else 1)
    finally:
        link.close()


def test_refused_frames_end_the_wait_an_empty_queue_does_not(link: Link) -> None:
    """Once it has dropped frames an empty queue ends the call (the reader then lets frames
    gather); with nothing read it waits the whole timeout."""
    for _ in range(5):
        link.sender.send(can.Message(arbitration_id=REFUSED, is_extended_id=False))
    time.sleep(0.1)
    started = time.monotonic()
    assert link.receiver.recv(30.0) is None
    assert (link.receiver.dropped, time.monotonic() - started < 10) == (5, True)
    started = time.monotonic()
    assert link.receiver.recv(0.3) is None
    assert time.monotonic() - started >= 0.3


def test_a_flood_of_refused_frames_ends_a_call_before_the_queue_does(link: Link) -> None:
    """MAX_DROPPED_PER_CALL refused frames end a call (the reader then looks at its other
    duties), not drained; the next call drops the rest and finds the queue empty."""
    flood = MAX_DROPPED_PER_CALL + MAX_DROPPED_PER_CALL // 2
    with socket.socket(fileno=os.dup(link.bus.fileno())) as sock:
        try:  # room for the whole flood: past net.core.rmem_max, which only root may do
            sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 8 << 20)
        except PermissionError:
            pytest.skip("needs root (SO_RCVBUFFORCE) to queue the flood")
    datagram = pack_message(can.Message(arbitration_id=REFUSED, is_extended_id=False))
    for _ in range(flood):
        link.send_raw(datagram)
    time.sleep(0.2)
    assert link.receiver.recv(0) is None
    assert (link.receiver.dropped, link.receiver.drained) == (MAX_DROPPED_PER_CALL, False)
    assert link.receiver.recv(0) is None
    assert (link.receiver.dropped, link.receiver.drained) == (flood, True)
