"""The datagram transports: ``udpin`` and ``udpout``, stamped with the kernel's receive time
(see :mod:`bridge.mavlink.transport`)."""

from __future__ import annotations

import logging
import socket
import struct
import time
from typing import Final

from bridge.errors import LinkError
from bridge.mavlink.endpoints import Endpoint
from bridge.mavlink.transport.base import AutopilotTransport, reason, resolve

__all__ = ["UdpInTransport", "UdpOutTransport"]

log = logging.getLogger(__name__)

# A datagram is read whole whatever its size: a router may pack several frames into one.
_DATAGRAM_MAX: Final = 65_535
# Python does not export SO_TIMESTAMPNS; 35 is SO_TIMESTAMPNS_OLD in Linux's generic socket
# ABI (x86, ARM, AArch64, RISC-V). Its control message has the same number (SCM_TIMESTAMPNS).
_SO_TIMESTAMPNS: Final = int(getattr(socket, "SO_TIMESTAMPNS", 35))
# The control message holds a struct timespec: two longs, 16 bytes on 64-bit, 8 on 32-bit.
_TIMESPEC_64: Final = struct.Struct("@qq")
_TIMESPEC_32: Final = struct.Struct("@ii")
_ANCILLARY_BYTES: Final = socket.CMSG_SPACE(_TIMESPEC_64.size)
_OFFSET_SPREAD_NS: Final = 20_000  # reading three clocks takes < 1 µs unless preempted
_OFFSET_TRIES: Final = 3
_SENDERS_LOGGED: Final = 16  # udpin logs the first senders it replies to, then stays quiet
_NS_PER_S: Final = 1_000_000_000


def _wall_minus_monotonic_ns() -> int:
    """How far the wall clock is ahead of the monotonic clock now.

    The wall clock is read between two monotonic readings and compared with their midpoint; a
    pair that lies far apart (the thread was preempted in between) is read again, so the
    offset is good to a few microseconds even on a loaded machine.
    """
    for _ in range(_OFFSET_TRIES):
        before_ns = time.monotonic_ns()
        wall_ns = time.time_ns()
        after_ns = time.monotonic_ns()
        if after_ns - before_ns <= _OFFSET_SPREAD_NS:
            break
    return wall_ns - (before_ns + after_ns) // 2


class _DatagramTransport(AutopilotTransport):
    """UDP: one socket, open from start to close, one datagram per read, kernel timestamps."""

    datagrams = True

    def __init__(self, endpoint: Endpoint, bind: tuple[str, int] | None) -> None:
        super().__init__(endpoint)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.setblocking(False)
            self._sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            if bind is not None:
                # No SO_REUSEADDR: a second bridge on the same port must fail here rather than
                # share (and steal) the autopilot's datagrams.
                self._sock.bind(bind)
        except OSError as exc:
            self._sock.close()
            raise LinkError(f"cannot open MAVLink {endpoint.url!r}: {reason(exc)}") from exc
        self._fd = self._sock.fileno()
        self._peer: tuple[str, int] | None = None
        # Every datagram read after the socket was last found empty arrived after that moment:
        # the lower bound of a stamp that a wall-clock step (NTP, GPS time at boot) could skew.
        self._empty_at_ns = time.monotonic_ns()
        self._closed = False
        self.stats.connected = True

    def fileno(self) -> int | None:
        return None if self._closed else self._fd

    def service(self, now_ns: int) -> None:
        pass  # nothing to connect, and a datagram is sent whole or not at all

    def recv(self) -> tuple[bytes, int] | None:
        if self._closed:
            return None
        try:
            data, ancillary, _flags, sender = self._sock.recvmsg(_DATAGRAM_MAX, _ANCILLARY_BYTES)
        except BlockingIOError:
            self._empty_at_ns = time.monotonic_ns()
            return None
        except OSError as exc:  # an ICMP error queued on the socket; the next read goes on
            self._note_trouble(reason(exc), "MAVLink %s: read failed: %s", self.endpoint.url, exc)
            return None
        received_ns = now_ns = time.monotonic_ns()
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
                layout = _TIMESPEC_64 if len(payload) >= _TIMESPEC_64.size else _TIMESPEC_32
                seconds, nanoseconds = layout.unpack_from(payload)
                wall_ns = seconds * _NS_PER_S + nanoseconds
                stamp_ns = wall_ns - _wall_minus_monotonic_ns()
                received_ns = min(max(stamp_ns, self._empty_at_ns), now_ns)
        self.sender = sender
        self._on_datagram(sender)
        self.stats.reads += 1
        self.stats.bytes_in += len(data)
        return data, received_ns

    def _on_datagram(self, sender: tuple[str, int]) -> None:
        """Called for each datagram read, with its sender's address."""

    def send(self, frame: bytes) -> bool:
        peer = self._peer
        if self._closed or peer is None:
            self.stats.frames_dropped += 1
            return False
        try:
            sent = self._sock.sendto(frame, peer)
        except OSError as exc:  # EAGAIN (send buffer full), ENETUNREACH (interface down), ...
            self.stats.frames_dropped += 1
            self._note_trouble(
                reason(exc), "MAVLink %s: send to %s:%d failed: %s", self.endpoint.url, *peer, exc
            )
            return False
        if self._logged_error:
            log.info("MAVLink %s: sending again", self.endpoint.url)
            self._logged_error = ""
        self.stats.frames_sent += 1
        self.stats.bytes_out += sent
        return True

    def _close_all(self) -> None:
        self._sock.close()


class UdpInTransport(_DatagramTransport):
    """``udpin``: bound to HOST:PORT; replies go to the sender of the latest datagram, or to the
    peer given to :meth:`reply_to` (the autopilot's address, once its reader knows it)."""

    def __init__(self, endpoint: Endpoint) -> None:
        """Raises:
        LinkError: the address cannot be bound (in use, not local) or the host is unknown.
        """
        super().__init__(endpoint, bind=resolve(endpoint, socket.SOCK_DGRAM))
        self._senders_logged: set[tuple[str, int]] = set()
        self._pinned = False
        log.info("MAVLink %s listening", endpoint.url)

    def reply_to(self, peer: tuple[str, int] | None) -> None:
        self._pinned = peer is not None
        if peer is not None and peer != self._peer:
            self._peer = peer
            log.info("MAVLink %s: replying to %s:%d", self.endpoint.url, *peer)

    def _on_datagram(self, sender: tuple[str, int]) -> None:
        if sender == self._peer or self._pinned:
            return
        self._peer = sender
        # Two senders taking turns would otherwise log every datagram.
        if sender not in self._senders_logged and len(self._senders_logged) < _SENDERS_LOGGED:
            self._senders_logged.add(sender)
            log.info("MAVLink %s: replying to %s:%d", self.endpoint.url, *sender)


class UdpOutTransport(_DatagramTransport):
    """``udpout``: sends to HOST:PORT and reads the replies on the same socket."""

    def __init__(self, endpoint: Endpoint) -> None:
        """Raises:
        LinkError: the host is unknown.
        """
        peer = resolve(endpoint, socket.SOCK_DGRAM)
        super().__init__(endpoint, bind=None)  # bound to a free port by the first send
        self._peer = peer
        log.info("MAVLink %s sending to %s:%d", endpoint.url, *peer)

    @property
    def configured_peer(self) -> tuple[str, int] | None:
        return self._peer
