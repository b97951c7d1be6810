"""Non-blocking transports against real sockets on 127.0.0.1 and real ptys (one per test).

Every call into a transport under test goes through :class:`Watched`, which times it. A call
that took more than 5 ms fails the test if it slept in the kernel (a voluntary context switch:
it waited) or spent those 5 ms on the CPU (it spun, as pyserial's ``write`` with
``write_timeout=0`` does on a full buffer). One that took long only because the shared machine
preempted the thread did neither, and is tolerated.
"""

from __future__ import annotations

import contextlib
import errno
import gc
import itertools
import logging
import os
import resource
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import TypeVar

import pytest

from bridge.errors import LinkError
from bridge.mavlink.endpoints import parse_url
from bridge.mavlink.transport import open_transport
from bridge.mavlink.transport.base import PENDING_LIMIT_BYTES
from bridge.mavlink.transport.serial import SerialTransport
from bridge.mavlink.transport.tcp import TcpClientTransport, TcpServerTransport
from bridge.mavlink.transport.udp import UdpInTransport, UdpOutTransport

T = TypeVar("T")
BLOCKED_NS = 5_000_000
TIMEOUT_S = 5.0
LOGGER = "bridge.mavlink.transport"


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def voluntary_switches() -> int:
    """Times this thread went to sleep in the kernel (waited) so far."""
    return resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw


def measured(call: Callable[[], T]) -> tuple[T, int, bool]:
    """``call()``'s result, how long it took (ns), and whether it blocked: slept in the kernel
    or spun on the CPU, for more than 5 ms in all."""
    switches = voluntary_switches()
    cpu_start_ns = time.thread_time_ns()
    start_ns = time.perf_counter_ns()
    result = call()
    took_ns = time.perf_counter_ns() - start_ns
    spun = time.thread_time_ns() - cpu_start_ns > BLOCKED_NS
    slept = voluntary_switches() > switches
    return result, took_ns, took_ns > BLOCKED_NS and (slept or spun)


class Watched:
    """A transport opened and then called with every call timed; ``blocked`` lists the calls
    that blocked (see :func:`measured`).

    ``open_transport`` is timed too (``open_blocked``) but not held to the rule: it may wait by
    design (a name to resolve, a serial device's first open and its helper thread to start).
    """

    def __init__(
        self, url: str, wait_for_link: bool = True, pending_limit_bytes: int = PENDING_LIMIT_BYTES
    ) -> None:
        self.calls = 0
        self.longest_ns = 0
        self.blocked: list[str] = []
        endpoint = parse_url(url)
        self.transport, self.open_ns, self.open_blocked = measured(
            lambda: open_transport(endpoint, wait_for_link, pending_limit_bytes)
        )
        self.stats = self.transport.stats

    def _call(self, name: str, call: Callable[[], T]) -> T:
        result, took_ns, blocked = measured(call)
        self.calls += 1
        self.longest_ns = max(self.longest_ns, took_ns)
        if blocked:
            self.blocked.append(f"{name} blocked for {took_ns / 1e6:.1f} ms")
        return result

    def fileno(self) -> int | None:
        return self._call("fileno", self.transport.fileno)

    def service(self) -> None:
        now_ns = time.monotonic_ns()
        self._call("service", lambda: self.transport.service(now_ns))

    def recv(self) -> tuple[bytes, int] | None:
        return self._call("recv", self.transport.recv)

    def send(self, frame: bytes) -> bool:
        return self._call("send", lambda: self.transport.send(frame))

    def wants_write(self) -> bool:
        return self._call("wants_write", self.transport.wants_write)

    def close(self) -> None:
        self._call("close", self.transport.close)

    def assert_never_blocked(self) -> None:
        assert self.calls > 0
        assert not self.blocked, self.blocked


Open = Callable[..., Watched]


@pytest.fixture
def opened() -> Iterator[Open]:
    """Open transports through :class:`Watched`; each is closed and checked at the end."""
    transports: list[Watched] = []

    def make(
        url: str, wait_for_link: bool = True, pending_limit_bytes: int = PENDING_LIMIT_BYTES
    ) -> Watched:
        watched = Watched(url, wait_for_link, pending_limit_bytes)
        transports.append(watched)
        return watched

    yield make
    for watched in transports:
        watched.close()
        watched.assert_never_blocked()


def pump(*transports: Watched, until: Callable[[], bool], what: str) -> None:
    """Service the transports (and read, so a lost stream is noticed) until ``until()``."""
    deadline = time.monotonic() + TIMEOUT_S
    while not until():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        for transport in transports:
            transport.service()
        time.sleep(0.002)


def receive(transport: Watched, size: int) -> tuple[bytes, list[int]]:
    """Read until ``size`` bytes arrived, servicing meanwhile; the bytes and each read's stamp."""
    data = b""
    stamps: list[int] = []
    deadline = time.monotonic() + TIMEOUT_S
    while len(data) < size:
        assert time.monotonic() < deadline, f"got {len(data)} of {size} bytes"
        transport.service()
        got = transport.recv()
        if got is None:
            time.sleep(0.001)
            continue
        data += got[0]
        stamps.append(got[1])
    return data, stamps


def receive_datagram(transport: Watched) -> tuple[bytes, int]:
    deadline = time.monotonic() + TIMEOUT_S
    while (got := transport.recv()) is None:
        assert time.monotonic() < deadline, "no datagram"
        time.sleep(0.001)
    return got


def read_fd(fd: int, size: int, serve: Watched | None = None) -> bytes:
    """Read ``size`` bytes from a plain descriptor (a socket, a pty controller), servicing
    ``serve`` meanwhile so that its pending bytes keep flowing."""
    data = b""
    deadline = time.monotonic() + TIMEOUT_S
    while len(data) < size:
        assert time.monotonic() < deadline, f"got {len(data)} of {size} bytes"
        if serve is not None:
            serve.service()
        ready, _, _ = select.select([fd], [], [], 0.005)
        if ready:
            chunk = os.read(fd, 65536)
            assert chunk, f"end of stream after {len(data)} of {size} bytes"
            data += chunk
    return data


def frame(index: int, size: int = 100) -> bytes:
    """A frame whose every 4 bytes name it, so a frame cut or interleaved is seen."""
    return struct.pack(">I", index) * (size // 4)


# -- UDP --------------------------------------------------------------------------------------


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


# -- TCP --------------------------------------------------------------------------------------


def test_tcp_and_tcpin_carry_data_both_ways(opened: Open) -> None:
    address = f"127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    server = opened(f"tcpin:{address}")
    client = opened(f"tcp:{address}")
    assert isinstance(server.transport, TcpServerTransport)
    assert isinstance(client.transport, TcpClientTransport)
    assert server.fileno() is None  # listening, no client yet
    pump(
        server,
        client,
        until=lambda: server.stats.connected and client.stats.connected,
        what="a connection",
    )
    assert client.fileno() is not None and server.fileno() is not None

    assert client.send(frame(1)) and client.send(frame(2))
    assert receive(server, 200)[0] == frame(1) + frame(2)
    assert server.send(frame(3))
    assert receive(client, 100)[0] == frame(3)
    assert client.stats.reconnects == server.stats.reconnects == 0
    assert client.stats.bytes_out == server.stats.bytes_in == 200


def test_tcp_server_down_at_start_is_connected_to_by_itself_without_blocking(
    opened: Open, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    port = free_port(socket.SOCK_STREAM)
    client = opened(f"tcp:127.0.0.1:{port}")  # nothing listens: no error, retried
    assert not client.open_blocked, f"open_transport took {client.open_ns / 1e6:.1f} ms"
    assert not client.stats.connected and client.fileno() is None
    assert client.send(frame(0)) is False

    deadline = time.monotonic() + 0.6
    while time.monotonic() < deadline:
        client.service()
        assert client.recv() is None
        time.sleep(0.002)
    attempts = client.stats.attempts
    # Backoff: 0.1 s doubling, jittered down to half: a few attempts, not one per service().
    assert 3 <= attempts <= 8, attempts
    assert client.stats.last_error == os.strerror(errno.ECONNREFUSED)
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "retrying in the background" in warnings[0].getMessage()

    with socket.create_server(("127.0.0.1", port)) as listener:
        listener.settimeout(TIMEOUT_S)
        pump(client, until=lambda: client.stats.connected, what="the connect")
        peer, _ = listener.accept()
        with peer:
            assert client.send(frame(7))
            assert read_fd(peer.fileno(), 100) == frame(7)
            peer.sendall(frame(8))
            assert receive(client, 100)[0] == frame(8)
    assert client.stats.reconnects == 0  # the first connection, however late, is no reconnect
    assert sum(r.levelno >= logging.WARNING for r in caplog.records) == 1
    assert any(r.getMessage().endswith(" connected") for r in caplog.records)
    client.assert_never_blocked()


def test_tcp_reconnects_when_the_server_restarts(opened: Open) -> None:
    port = free_port(socket.SOCK_STREAM)
    listener = socket.create_server(("127.0.0.1", port))
    client = opened(f"tcp:127.0.0.1:{port}")
    pump(client, until=lambda: client.stats.connected, what="the connect")
    peer, _ = listener.accept()
    peer.sendall(b"before")
    assert receive(client, 6)[0] == b"before"

    peer.close()
    listener.close()
    pump(client, until=lambda: client.recv() is None and not client.stats.connected, what="loss")
    assert client.fileno() is None
    assert client.stats.last_error == "closed by the other end"

    with socket.create_server(("127.0.0.1", port)) as listener:
        pump(client, until=lambda: client.stats.connected, what="the reconnect")
        peer, _ = listener.accept()
        with peer:
            assert client.send(b"after")
            assert read_fd(peer.fileno(), 5) == b"after"
            peer.sendall(b"again")
            assert receive(client, 5)[0] == b"again"
    assert client.stats.reconnects == 1


def test_tcp_connect_nobody_answers_is_given_up_without_blocking(
    opened: Open,
) -> None:
    # A listener whose one-slot accept queue is full drops further SYNs: a connect to it hangs.
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(0)
        filler = socket.create_connection(listener.getsockname())
        time.sleep(0.05)
        client = opened(f"tcp:127.0.0.1:{listener.getsockname()[1]}")
        pump(client, until=lambda: client.stats.last_error.startswith("no answer"), what="give up")
        assert not client.stats.connected and client.fileno() is None

        accepted, _ = listener.accept()  # room in the queue: the next attempt gets through
        pump(client, until=lambda: client.stats.connected, what="the connect")
        assert client.stats.attempts >= 2
        filler.close()
        accepted.close()


def test_tcpin_new_client_replaces_the_old(opened: Open) -> None:
    port = free_port(socket.SOCK_STREAM)
    server = opened(f"tcpin:127.0.0.1:{port}")
    first = socket.create_connection(("127.0.0.1", port))
    second: socket.socket | None = None
    try:
        pump(server, until=lambda: server.stats.connected, what="the first client")
        first.sendall(b"first")
        assert receive(server, 5)[0] == b"first"

        second = socket.create_connection(("127.0.0.1", port))
        pump(server, until=lambda: server.stats.reconnects == 1, what="the second client")
        first.settimeout(TIMEOUT_S)
        assert first.recv(100) == b""  # the old client was closed
        assert server.send(b"to second")
        assert read_fd(second.fileno(), 9) == b"to second"
        second.sendall(b"second")
        assert receive(server, 6)[0] == b"second"

        second.close()
        second = None
        pump(
            server, until=lambda: server.recv() is None and not server.stats.connected, what="loss"
        )
        assert server.fileno() is None and server.send(b"nobody") is False
        with socket.create_connection(("127.0.0.1", port)) as third:
            pump(server, until=lambda: server.stats.connected, what="the third client")
            assert server.send(b"to third")
            assert read_fd(third.fileno(), 8) == b"to third"
        assert server.stats.reconnects == 2
        assert server.stats.attempts == 3
    finally:
        first.close()
        if second is not None:
            second.close()


# -- serial -----------------------------------------------------------------------------------


class Pty:
    """A pseudo-terminal playing the autopilot's UART; ``link`` is a stable path to its device,
    like /dev/serial/by-id/..., re-pointed by :meth:`replace`."""

    def __init__(self, directory: Path) -> None:
        self.link = directory / "ttyAUTOPILOT"
        self.controller = -1
        self.replace()

    def replace(self) -> None:
        """Close the current pty (the device goes away) and make a new one at ``link``."""
        self.close()
        self.controller, device = os.openpty()
        path = os.ttyname(device)
        os.close(device)  # the device stays while the controller is open
        staging = self.link.with_suffix(".new")
        staging.symlink_to(path)
        os.replace(staging, self.link)

    def close(self) -> None:
        if self.controller >= 0:
            os.close(self.controller)
            self.controller = -1


@pytest.fixture
def pty(tmp_path: Path) -> Iterator[Pty]:
    made = Pty(tmp_path)
    yield made
    made.close()


def test_serial_carries_every_byte_value_raw_both_ways(opened: Open, pty: Pty) -> None:
    serial = opened(f"serial:{pty.link}:921600")
    assert isinstance(serial.transport, SerialTransport)
    assert serial.stats.connected and serial.fileno() is not None
    # Raw 8N1, no flow control: CR, LF, ^C, ^S/^Q (XOFF/XON), ^D, 0x7f, 0xff pass unchanged.
    everything = bytes(range(256)) * 2
    os.write(pty.controller, everything)
    data, stamps = receive(serial, len(everything))
    assert data == everything
    assert all(stamp <= time.monotonic_ns() for stamp in stamps)
    assert serial.send(everything)
    assert read_fd(pty.controller, len(everything), serve=serial) == everything


def test_serial_device_that_goes_away_is_reopened(
    opened: Open, pty: Pty, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    serial = opened(f"serial:{pty.link}:115200")
    os.write(pty.controller, b"before")
    assert receive(serial, 6)[0] == b"before"

    pty.close()  # the USB adapter is pulled
    pump(serial, until=lambda: serial.recv() is None and not serial.stats.connected, what="loss")
    assert serial.fileno() is None and serial.send(b"lost") is False
    deadline = time.monotonic() + 0.4
    while time.monotonic() < deadline:  # retrying meanwhile, quietly
        serial.service()
        time.sleep(0.002)
    assert serial.stats.attempts >= 3
    assert not serial.stats.connected

    pty.replace()  # plugged in again, under a new /dev/pts name behind the same link
    pump(serial, until=lambda: serial.stats.connected, what="the reopen")
    os.write(pty.controller, b"after")
    assert receive(serial, 5)[0] == b"after"
    assert serial.send(b"again")
    assert read_fd(pty.controller, 5, serve=serial) == b"again"
    assert serial.stats.reconnects == 1
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 2, warnings  # lost; then "not available" once, however many tries
    assert "lost (Input/output error)" in warnings[0]  # EIO: the device is gone
    assert "No such file or directory" in warnings[1]


def test_serial_device_absent_at_start_is_waited_for(opened: Open, tmp_path: Path) -> None:
    link = tmp_path / "ttyAUTOPILOT"
    with pytest.raises(LinkError, match=f"'serial:{link}'.*No such file"):
        open_transport(parse_url(f"serial:{link}"), wait_for_link=False)

    serial = opened(f"serial:{link}")
    assert not serial.stats.connected and serial.fileno() is None
    pump(serial, until=lambda: serial.stats.attempts >= 2, what="a retry")
    made = Pty(tmp_path)
    try:
        pump(serial, until=lambda: serial.stats.connected, what="the device")
        os.write(made.controller, b"hello")
        assert receive(serial, 5)[0] == b"hello"
        assert serial.stats.reconnects == 0
    finally:
        serial.close()
        made.close()


# -- a peer that stops reading ----------------------------------------------------------------


def stalled_peer(kind: str, opened: Open, tmp_path: Path, stack: ExitStack) -> tuple[Watched, int]:
    """A stream transport whose peer (returned as a descriptor) reads nothing yet."""
    limit = 1000
    if kind == "serial":
        pty = Pty(tmp_path)
        stack.callback(pty.close)
        return opened(f"serial:{pty.link}", pending_limit_bytes=limit), pty.controller
    listener = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_STREAM))
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # the accepted peer's too
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    link = opened(f"tcp:127.0.0.1:{listener.getsockname()[1]}", pending_limit_bytes=limit)
    pump(link, until=lambda: link.stats.connected, what="the connect")
    peer = stack.enter_context(listener.accept()[0])
    return link, peer.fileno()


@pytest.mark.parametrize("kind", ["tcp", "serial"])
def test_a_stalled_peer_never_blocks_send_and_frames_stay_whole(
    opened: Open, tmp_path: Path, kind: str
) -> None:
    with ExitStack() as stack:
        link, peer_fd = stalled_peer(kind, opened, tmp_path, stack)
        stack.callback(link.close)  # before the pty goes
        accepted: list[bytes] = []
        refused = 0
        sizes = (100, 37, 280, 9)  # odd sizes, so frames straddle the kernel's free space
        for index in range(200_000):
            candidate = frame(index, sizes[index % len(sizes)])
            if link.send(candidate):
                accepted.append(candidate)
                continue
            refused += 1
            assert link.wants_write()  # refused because bytes are pending
            if refused == 50:
                break
        assert refused == 50, "the peer never stalled"
        assert link.stats.frames_dropped == refused
        assert link.stats.frames_sent == len(accepted)

        expected = b"".join(accepted)
        received = read_fd(peer_fd, len(expected), serve=link)
        # Every accepted frame whole and in order, nothing between them.
        assert received == expected
        pump(link, until=lambda: not link.wants_write(), what="the pending bytes")
        assert link.stats.bytes_out == len(expected)


def test_pending_bytes_of_a_lost_stream_are_counted_as_dropped(opened: Open, pty: Pty) -> None:
    serial = opened(f"serial:{pty.link}", pending_limit_bytes=PENDING_LIMIT_BYTES)
    sent = 0
    while serial.send(frame(sent)):
        sent += 1
    assert serial.wants_write()
    pending_frames = serial.stats.frames_sent
    pty.close()
    pump(serial, until=lambda: serial.recv() is None and not serial.stats.connected, what="loss")
    assert not serial.wants_write()
    dropped = serial.stats.frames_dropped - 1  # the refused one that ended the loop
    assert 1 <= dropped <= pending_frames


# -- lifecycle and errors -----------------------------------------------------------------------


def open_descriptors() -> set[tuple[str, str]]:
    """This process's descriptors with what each refers to (``socket:[inode]``, a pty path)."""
    found = set()
    for name in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):  # the listing's own descriptor is gone by now
            found.add((name, os.readlink(f"/proc/self/fd/{name}")))
    return found


def wait_for_helpers_to_stop() -> None:
    """A serial transport's helper thread closes its device and ends soon after close()."""
    deadline = time.monotonic() + TIMEOUT_S
    while any(t.name.startswith("serial-helper") for t in threading.enumerate()):
        assert time.monotonic() < deadline, "a serial helper thread is still running"
        time.sleep(0.005)


@pytest.mark.parametrize("kind", ["udpin", "udpout", "tcp", "tcpin", "serial"])
def test_close_is_idempotent_and_leaves_nothing_open(
    tmp_path: Path, kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    with ExitStack() as stack:
        if kind == "serial":
            pty = Pty(tmp_path)
            stack.callback(pty.close)
            url = f"serial:{pty.link}"
        elif kind == "tcp":  # a server to connect to, so that there is a socket to close
            listener = stack.enter_context(socket.create_server(("127.0.0.1", 0)))
            url = f"tcp:127.0.0.1:{listener.getsockname()[1]}"
        else:
            sock_type = socket.SOCK_STREAM if kind == "tcpin" else socket.SOCK_DGRAM
            url = f"{kind}:127.0.0.1:{free_port(sock_type)}"
        gc.collect()  # nothing forgotten by earlier tests closes in the middle
        before = open_descriptors()
        with open_transport(parse_url(url)) as transport:
            ours = open_descriptors() - before
            assert ours
            transport.close()
            transport.close()
            assert transport.fileno() is None and transport.recv() is None
            assert transport.send(b"x") is False and not transport.wants_write()
            transport.service(time.monotonic_ns())  # nothing reopens after close
            assert transport.fileno() is None and not transport.stats.connected
        wait_for_helpers_to_stop()
        assert not ours & open_descriptors()
    closed = [r for r in caplog.records if r.getMessage() == f"MAVLink {url} closed"]
    assert len(closed) == 1


@pytest.mark.parametrize("kind", ["udpin", "serial"])
def test_a_forgotten_transport_warns_when_collected(
    pty: Pty, kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    # The serial helper thread holds no reference to its transport: it is collected too.
    url = f"serial:{pty.link}" if kind == "serial" else f"udpin:127.0.0.1:{free_port()}"
    transport = open_transport(parse_url(url))
    del transport
    assert f"MAVLink {url} was not closed; closing it now" in caplog.text
    wait_for_helpers_to_stop()


def occupied_udp() -> tuple[socket.socket, str]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    return sock, f"udpin:127.0.0.1:{sock.getsockname()[1]}"


def occupied_tcp() -> tuple[socket.socket, str]:
    sock = socket.create_server(("127.0.0.1", 0))
    return sock, f"tcpin:127.0.0.1:{sock.getsockname()[1]}"


@pytest.mark.parametrize(
    ("url", "reason"),
    [
        ("udpin:192.0.2.1:14550", "Cannot assign requested address"),  # TEST-NET: not ours
        ("tcpin:192.0.2.1:5760", "Cannot assign requested address"),
        ("udpout:no-such-host.invalid:14550", "unknown host 'no-such-host.invalid'"),
        ("tcp:no-such-host.invalid:5760", "unknown host 'no-such-host.invalid'"),
        ("serial:/dev/null", "Inappropriate ioctl"),  # not a terminal
    ],
)
def test_what_will_not_get_better_is_a_link_error_naming_the_url(url: str, reason: str) -> None:
    with pytest.raises(LinkError) as raised:
        open_transport(parse_url(url))
    assert f"cannot open MAVLink {url!r}" in str(raised.value)
    assert reason in str(raised.value)


@pytest.mark.parametrize("occupy", [occupied_udp, occupied_tcp])
def test_an_address_in_use_is_a_link_error(occupy: Callable[[], tuple[socket.socket, str]]) -> None:
    sock, url = occupy()
    with sock, pytest.raises(LinkError, match=f"'{url}': Address already in use"):
        open_transport(parse_url(url))


def test_a_non_standard_baud_rate_is_a_link_error(pty: Pty) -> None:
    url = f"serial:{pty.link}:123456"
    with pytest.raises(LinkError, match=f"'{url}': 123456 bit/s is not a standard rate"):
        open_transport(parse_url(url))


def test_without_waiting_an_absent_tcp_server_is_a_link_error() -> None:
    url = f"tcp:127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    with pytest.raises(LinkError, match=f"cannot open MAVLink '{url}': Connection refused"):
        open_transport(parse_url(url), wait_for_link=False)
    with (
        socket.create_server(("127.0.0.1", int(url.rsplit(":", 1)[1]))),
        open_transport(parse_url(url), wait_for_link=False) as transport,
    ):
        assert transport.stats.connected and transport.fileno() is not None
