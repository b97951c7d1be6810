"""Shared by the transport tests: real sockets on 127.0.0.1 and real ptys (one per test).

Every call into a transport under test goes through :class:`Watched`, which times it. A call
that took more than 20 ms fails the test if it slept in the kernel (a voluntary context switch:
it waited) or spent those 20 ms on the CPU (it spun, as pyserial's ``write`` with
``write_timeout=0`` does on a full buffer). One that took long only because the shared machine
preempted the thread did neither, and is tolerated. The waits this catches last as long as the
peer stalls (seconds here). Waiting for the GIL is also a voluntary switch, and a send was seen
"blocked" for 8 ms on a machine running four test sessions at once: hence 20 ms, not less.

The test modules take the fixtures with ``opened = watched.opened`` (an import would shadow
the argument).
"""

from __future__ import annotations

import contextlib
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

from bridge.mavlink.endpoints import parse_url
from bridge.mavlink.transport import open_transport
from bridge.mavlink.transport.base import PENDING_LIMIT_BYTES

T = TypeVar("T")


BLOCKED_NS = 20_000_000


TIMEOUT_S = 5.0


LOGGER = "bridge.mavlink.transport"


def voluntary_switches() -> int:
    """Times this thread went to sleep in the kernel (waited) so far."""
    return resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw


def measured(call: Callable[[], T]) -> tuple[T, int, bool]:
    """``call()``'s result, how long it took (ns), and whether it blocked: slept in the kernel
    or spun on the CPU, for more than 20 ms in all."""
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


def occupied_udp() -> tuple[socket.socket, str]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    return sock, f"udpin:127.0.0.1:{sock.getsockname()[1]}"


def occupied_tcp() -> tuple[socket.socket, str]:
    sock = socket.create_server(("127.0.0.1", 0))
    return sock, f"tcpin:127.0.0.1:{sock.getsockname()[1]}"
