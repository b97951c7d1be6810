"""The datagram transports (udpin, udpout) against real sockets on 127.0.0.1.

Every call into a transport under test is timed (:class:`watched.Watched`): one that waited
or spun fails the test.
"""

from __future__ import annotations

import itertools
import socket
import time

import pytest
import watched
from conftest import free_port
from watched import TIMEOUT_S, Open, frame, receive_datagram

from bridge.mavlink.transport.udp import UdpInTransport, UdpOutTransport

opened = watched.opened


def test_udpin_and_udpout_carry_data_both_ways(opened: Open) -> None:
    address = f"127.0.0.1:{free_port()}"
    server = opened(f"udpin:{address}")
    client = opened(f"udpout:{address}")
    assert isinstance(server.transport, UdpInTransport)
    assert isinstance(client.transport, UdpOutTransport)
    assert server.stats.connected and client.stats.connected

    assert server.send(b"nobody yet") is False  # udpin knows no peer before a datagram
    assert server.stats.frames_dropped == 1
    assert client.send(b"\xfd" + bytes(range(40)))
    data, _ = receive_datagram(server)
    assert data == b"\xfd" + bytes(range(40))
    assert server.send(b"reply")
    assert receive_datagram(client)[0] == b"reply"

    assert (server.stats.reads, server.stats.bytes_in, server.stats.frames_sent) == (1, 41, 1)
    assert (client.stats.reads, client.stats.bytes_in, client.stats.bytes_out) == (1, 5, 41)


def test_udpin_replies_to_the_latest_sender(opened: Open) -> None:
    port = free_port()
    server = opened(f"udpin:127.0.0.1:{port}")
    first = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    second = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for sock in (first, second):
            sock.bind(("127.0.0.1", 0))
            sock.settimeout(TIMEOUT_S)
        first.sendto(b"one", ("127.0.0.1", port))
        assert receive_datagram(server)[0] == b"one"
        assert server.send(b"to first")
        assert first.recv(100) == b"to first"

        second.sendto(b"two", ("127.0.0.1", port))
        assert receive_datagram(server)[0] == b"two"
        assert server.send(b"to second")
        assert second.recv(100) == b"to second"
        first.settimeout(0.1)
        with pytest.raises(TimeoutError):
            first.recv(100)
    finally:
        first.close()
        second.close()


def test_udpin_names_each_sender_and_replies_where_its_reader_says(opened: Open) -> None:
    """Its reader (the loop's input side) learns who sent each datagram, and pins the replies
    to the autopilot once it knows it: a later datagram from anyone else no longer steals them."""
    port = free_port()
    server = opened(f"udpin:127.0.0.1:{port}")
    assert server.transport.datagrams and server.transport.sender is None
    assert server.transport.configured_peer is None
    autopilot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for sock in (autopilot, other):
            sock.bind(("127.0.0.1", 0))
            sock.settimeout(TIMEOUT_S)
        autopilot.sendto(b"one", ("127.0.0.1", port))
        receive_datagram(server)
        assert server.transport.sender == autopilot.getsockname()
        server.transport.reply_to(autopilot.getsockname())
        other.sendto(b"two", ("127.0.0.1", port))
        receive_datagram(server)
        assert server.transport.sender == other.getsockname()
        assert server.send(b"to the autopilot")
        assert autopilot.recv(100) == b"to the autopilot"

        server.transport.reply_to(None)  # following the latest sender again
        other.sendto(b"three", ("127.0.0.1", port))
        receive_datagram(server)
        assert server.send(b"to other")
        assert other.recv(100) == b"to other"
    finally:
        autopilot.close()
        other.close()


def test_udpout_names_its_configured_peer_and_streams_have_no_sender(opened: Open) -> None:
    port = free_port()
    client = opened(f"udpout:localhost:{port}")
    assert client.transport.datagrams
    assert client.transport.configured_peer == ("127.0.0.1", port)
    client.transport.reply_to(("127.0.0.1", 1))  # nothing to steer: it sends to its peer
    assert client.transport.configured_peer == ("127.0.0.1", port)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        stream = opened(f"tcp:127.0.0.1:{listener.getsockname()[1]}")
        assert not stream.transport.datagrams
        assert stream.transport.sender is None and stream.transport.configured_peer is None


def test_udp_stamps_are_kernel_arrival_times_on_the_monotonic_clock(opened: Open) -> None:
    port = free_port()
    server = opened(f"udpin:127.0.0.1:{port}")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        sent_ns: list[tuple[int, int]] = []
        for index in range(4):
            before_ns = time.monotonic_ns()
            sender.sendto(frame(index, 40), ("127.0.0.1", port))
            sent_ns.append((before_ns, time.monotonic_ns()))
            time.sleep(0.02)
        time.sleep(0.2)  # the datagrams wait in the socket: their stamps must not move
        read_before_ns = time.monotonic_ns()
        stamps = [receive_datagram(server)[1] for _ in range(4)]
        read_after_ns = time.monotonic_ns()

    # Read back to back, yet stamped when each arrived: 20+ ms apart, the last ~200 ms old.
    for (before_ns, after_ns), stamp_ns in zip(sent_ns, stamps, strict=True):
        assert before_ns - 1_000_000 <= stamp_ns <= after_ns + 1_000_000
        assert stamp_ns <= read_after_ns  # never later than the read
    gaps_ms = [(b - a) / 1e6 for a, b in itertools.pairwise(stamps)]
    assert all(gap >= 19 for gap in gaps_ms), gaps_ms
    assert read_before_ns - stamps[-1] >= 190_000_000
