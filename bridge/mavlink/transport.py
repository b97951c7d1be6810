"""Non-blocking byte transports to the autopilot, for a real-time loop that owns its MAVLink link.

The real-time control loop is one thread that polls the autopilot's link itself, decodes the
motor outputs, mixes and sends CAN frames at a fixed rate. It must never block: not on a read,
a write, a TCP connect, a serial port that vanished, or a reconnect. pymavlink's transports
(which :mod:`bridge.mavlink.link` uses from its own threads) block in several of those places, so
this module opens the same five kinds of connection with plain non-blocking file descriptors and
leaves framing to the caller: bytes in, bytes out, nothing about MAVLink.

One :class:`AutopilotTransport` per link, made by :func:`open_transport`, used by one thread::

    transport = open_transport(parse_url("tcp:127.0.0.1:5760"))
    while running:
        now_ns = time.monotonic_ns()
        transport.service(now_ns)            # connect, accept, reopen, flush: never waits
        fd = transport.fileno()              # None while not connected
        # poll fd for POLLIN (and POLLOUT while transport.wants_write()), up to the next tick;
        # on any event (POLLIN, POLLHUP, POLLERR) call recv(), which notices a lost link.
        # Ask for fileno() again every tick: a reconnect brings a new descriptor, which may
        # even reuse the old number.
        while (got := transport.recv()) is not None:
            data, received_ns = got
        transport.send(frame)                # False: dropped, never blocked
    transport.close()

Kinds (the URL forms of :data:`~bridge.mavlink.endpoints.ACCEPTED_URL_FORMS`, parsed by
:func:`~bridge.mavlink.endpoints.parse_url`):

* ``udpin:HOST:PORT`` binds there and replies to whoever sent the latest datagram, as
  pymavlink does; until a datagram arrives there is nobody to send to.
* ``udpout:HOST:PORT`` sends there and receives the replies on the same socket.
* ``tcp:HOST:PORT`` connects there, without blocking: the connect is started, and completed
  (or given up after 2 s without an answer) by :meth:`~AutopilotTransport.service`.
* ``tcpin:HOST:PORT`` listens there and serves one client at a time: a new client replaces the
  old one (an autopilot that restarted reconnects before its old connection times out).
* ``serial:DEVICE[:BAUD]`` opens a terminal device raw, 8N1, no flow control; a helper thread
  does the reopening, since a USB adapter's driver sleeps in open() (:class:`SerialTransport`).

Clocks: every input is stamped with ``time.monotonic_ns()``. A UDP datagram carries the kernel's
receive time (``SO_TIMESTAMPNS``), so its stamp says when it arrived even when the loop reads it
a tick later; the kernel stamps with the wall clock, converted here to the monotonic clock at
read time. A stream read is stamped with the read time: a byte stream has no arrival times.

Link trouble never raises once open: a TCP or serial stream that ends or fails is closed and
reopened with jittered, capped exponential backoff (0.1 s, doubling, 5 s cap, as
:mod:`bridge.mavlink.link`), and counted in :class:`TransportStats`. Each change of state (lost,
connected, a different reason for failing) is logged once through this module's logger; the
retries themselves are not. The logging happens on the calling thread, so the real-time
process should give its loggers a handler that never blocks (``logging.handlers.QueueHandler``
with a ``QueueListener``), not one that writes to a pipe or journald from the loop.
:func:`open_transport` raises :class:`~bridge.errors.LinkError` only for what is wrong at start
and will not get better (see its docstring).

Sends never block either. A stream that cannot take a whole frame now keeps the rest in a
bounded pending buffer, written out by later :meth:`~AutopilotTransport.send` and
:meth:`~AutopilotTransport.service` calls ahead of any later frame, so the peer never sees half
a frame followed by another frame; once the buffer is full, new frames are dropped whole.

Linux only (``SO_TIMESTAMPNS``, ``termios``), IPv4 only like pymavlink (the URL forms have no
room for an IPv6 literal). Not thread-safe: one thread owns a transport.
"""

from __future__ import annotations

import array
import contextlib
import errno
import fcntl
import logging
import os
import queue
import random
import select
import socket
import struct
import termios
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass
from types import TracebackType
from typing import Final, cast

from bridge.errors import LinkError
from bridge.mavlink.endpoints import Endpoint

__all__ = [
    "PENDING_LIMIT_BYTES",
    "AutopilotTransport",
    "SerialTransport",
    "TcpClientTransport",
    "TcpServerTransport",
    "TransportStats",
    "UdpInTransport",
    "UdpOutTransport",
    "open_transport",
]

log = logging.getLogger(__name__)

PENDING_LIMIT_BYTES: Final = 4096
"""Default bound of a stream's pending buffer: about 15 full-size MAVLink 2 frames (280 bytes),
0.35 s of a 115200 bit/s UART. More would only queue stale frames behind a stalled peer."""

_READ_SIZE: Final = 4096  # bytes per stream read
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
_BACKOFF_FIRST_S: Final = 0.1  # a restarting TCP peer is often listening again within this
_BACKOFF_CAP_S: Final = 5.0
# A SYN that gets no answer is retried by the kernel at 1 s, 3 s, 7 s...; a peer on the LAN or
# a radio link answers well within 2 s, so waiting longer only delays the next fresh attempt.
_CONNECT_TIMEOUT_NS: Final = 2_000_000_000
_NS_PER_S: Final = 1_000_000_000
# Opening a serial device that fails with one of these may work later: the USB adapter is not
# enumerated yet (ENOENT, ENODEV, ENXIO), is going away (EIO), udev has not set its group yet
# (EACCES, EPERM), or another program still holds it (EBUSY). Anything else (ENOTTY: not a
# terminal) is a configuration mistake.
_SERIAL_TRANSIENT: Final = frozenset(
    {
        errno.ENOENT,
        errno.ENODEV,
        errno.ENXIO,
        errno.EIO,
        errno.EACCES,
        errno.EPERM,
        errno.EBUSY,
        errno.EAGAIN,
    }
)


@dataclass
class TransportStats:
    """Counters of one transport, updated in place by the thread that owns it."""

    bytes_in: int = 0
    bytes_out: int = 0
    """Bytes the kernel took (a stream's pending bytes count once written)."""
    reads: int = 0
    """Datagrams (UDP) or reads (streams) that returned data."""
    frames_sent: int = 0
    """Frames :meth:`AutopilotTransport.send` accepted: written whole, or partly pending."""
    frames_dropped: int = 0
    """Frames :meth:`AutopilotTransport.send` refused (not connected, no UDP peer yet, pending
    buffer full, write failed), plus accepted frames still pending when their stream was lost
    or replaced."""
    attempts: int = 0
    """Tries to open, connect or reopen a stream, successful or not (tcpin: clients accepted)."""
    reconnects: int = 0
    """Connections made after the first: a stream that came back after it was lost, a tcpin
    client that followed or replaced an earlier one."""
    connected: bool = False
    """Input can arrive now: UDP once open; a stream while its connection is up."""
    last_error: str = ""
    """The latest trouble (a failed attempt, a lost stream, a failed send); "" = none yet."""


def _reason(exc: BaseException) -> str:
    """A short human text for an OS error: its strerror when it has one."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


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


def _resolve(endpoint: Endpoint, sock_type: int) -> tuple[str, int]:
    """``HOST:PORT`` as an IPv4 socket address, resolved once: a DNS lookup can block for
    seconds, so the loop never does one.

    Raises:
        LinkError: the host is unknown (naming the URL).
    """
    host, port = endpoint.address.rsplit(":", 1)
    # An ASCII name goes in as bytes: a str would go through the idna codec, whose first use
    # imports it from disk, a wait even for "127.0.0.1".
    name: str | bytes = host.encode("ascii") if host.isascii() else host
    try:
        infos = socket.getaddrinfo(name, int(port), socket.AF_INET, sock_type)
    except OSError as exc:
        raise LinkError(
            f"cannot open MAVLink {endpoint.url!r}: unknown host {host!r} ({_reason(exc)}); "
            "expected an IPv4 address or a name that resolves to one"
        ) from exc
    address = cast(tuple[str, int], infos[0][4])
    return address[0], address[1]


class AutopilotTransport(ABC):
    """One non-blocking link to the autopilot; see the module docstring for the loop around it.

    A context manager; :meth:`close` tolerates a second call, and a transport garbage-collected
    without it logs a warning.
    """

    endpoint: Endpoint
    stats: TransportStats

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.stats = TransportStats()
        # True until a subclass has opened what it needs: a half-built transport has nothing
        # to close and must not warn when collected.
        self._closed = True
        self._logged_error = ""  # the failure last logged: a retry failing alike logs nothing

    @abstractmethod
    def fileno(self) -> int | None:
        """The descriptor to poll for input now; None while not connected (a stream that is
        down, a TCP connect in progress, a tcpin listener without a client, closed)."""

    @abstractmethod
    def service(self, now_ns: int) -> None:
        """Progress a connect, accept or reopen whose time has come, and write out pending
        bytes; ``now_ns`` is ``time.monotonic_ns()``. Never blocks; cheap when there is
        nothing to do. Call it every tick, connected or not."""

    @abstractmethod
    def recv(self) -> tuple[bytes, int] | None:
        """One read: the bytes and when they arrived (``time.monotonic_ns()``), or None when
        nothing is ready (or the read found the stream lost, which schedules a reconnect).

        UDP: one whole datagram, stamped with the kernel's receive time, never later than
        now. Streams: up to 4096 bytes, stamped with the read time. Never blocks or raises.
        """

    @abstractmethod
    def send(self, frame: bytes) -> bool:
        """Write one frame without blocking; False when it was dropped (counted in
        ``stats.frames_dropped``). Never raises for link trouble."""

    def wants_write(self) -> bool:
        """Bytes are pending: poll :meth:`fileno` for POLLOUT too and call :meth:`service`
        when it is writable."""
        return False

    def close(self) -> None:
        """Close every descriptor; pending bytes are dropped. A second call does nothing."""
        if self._closed:
            return
        self._closed = True
        self._close_all()
        self.stats.connected = False
        log.info("MAVLink %s closed", self.endpoint.url)

    @abstractmethod
    def _close_all(self) -> None:
        """Close what the subclass holds (called once, by :meth:`close`)."""

    def __enter__(self) -> AutopilotTransport:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __del__(self) -> None:
        if not getattr(self, "_closed", True):
            log.warning("MAVLink %s was not closed; closing it now", self.endpoint.url)
            self.close()

    def _note_trouble(self, reason: str, text: str, *args: object) -> None:
        """Record ``reason`` and log ``text`` at WARNING, unless the last logged trouble had
        the same reason: a link that keeps failing the same way logs once."""
        self.stats.last_error = reason
        if reason != self._logged_error:
            self._logged_error = reason
            log.warning(text, *args)


# -- datagrams --------------------------------------------------------------------------------


class _DatagramTransport(AutopilotTransport):
    """UDP: one socket, open from start to close, one datagram per read, kernel timestamps."""

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
            raise LinkError(f"cannot open MAVLink {endpoint.url!r}: {_reason(exc)}") from exc
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
            self._note_trouble(_reason(exc), "MAVLink %s: read failed: %s", self.endpoint.url, exc)
            return None
        received_ns = now_ns = time.monotonic_ns()
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
                layout = _TIMESPEC_64 if len(payload) >= _TIMESPEC_64.size else _TIMESPEC_32
                seconds, nanoseconds = layout.unpack_from(payload)
                wall_ns = seconds * _NS_PER_S + nanoseconds
                stamp_ns = wall_ns - _wall_minus_monotonic_ns()
                received_ns = min(max(stamp_ns, self._empty_at_ns), now_ns)
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
                _reason(exc), "MAVLink %s: send to %s:%d failed: %s", self.endpoint.url, *peer, exc
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
    """``udpin``: bound to HOST:PORT; replies go to the sender of the latest datagram."""

    def __init__(self, endpoint: Endpoint) -> None:
        """Raises:
        LinkError: the address cannot be bound (in use, not local) or the host is unknown.
        """
        super().__init__(endpoint, bind=_resolve(endpoint, socket.SOCK_DGRAM))
        self._senders_logged: set[tuple[str, int]] = set()
        log.info("MAVLink %s listening", endpoint.url)

    def _on_datagram(self, sender: tuple[str, int]) -> None:
        if sender == self._peer:
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
        peer = _resolve(endpoint, socket.SOCK_DGRAM)
        super().__init__(endpoint, bind=None)  # bound to a free port by the first send
        self._peer = peer
        log.info("MAVLink %s sending to %s:%d", endpoint.url, *peer)


# -- streams ----------------------------------------------------------------------------------


class _StreamTransport(AutopilotTransport):
    """What TCP (either side) and serial share: reads of up to 4096 bytes, a bounded pending
    buffer for writes, and loss handling."""

    def __init__(self, endpoint: Endpoint, pending_limit_bytes: int) -> None:
        super().__init__(endpoint)
        if pending_limit_bytes <= 0:
            raise ValueError(f"pending_limit_bytes {pending_limit_bytes} is not positive")
        self._pending_limit = pending_limit_bytes
        self._pending = bytearray()
        # The sizes of the frames (the first: of its unsent rest) in _pending, oldest first, so
        # a lost stream counts the frames it took with it.
        self._pending_frames: deque[int] = deque()
        self._fd: int | None = None
        self._ever_connected = False
        self._down_since_ns = time.monotonic_ns()

    # What a subclass provides: the raw operations on its connected descriptor, which raise
    # OSError (BlockingIOError: not now).

    @abstractmethod
    def _read_some(self) -> bytes | None:
        """Up to 4096 bytes; b"" at the end of the stream; None (or BlockingIOError) when
        there is nothing to read now."""

    @abstractmethod
    def _write_some(self, data: bytes | bytearray) -> int: ...

    @abstractmethod
    def _close_stream(self) -> None:
        """Close the connected descriptor (only)."""

    @abstractmethod
    def _on_lost(self, reason: str) -> None:
        """Log the loss and arrange the way back (a reopen after backoff, a new client)."""

    def fileno(self) -> int | None:
        return self._fd

    def wants_write(self) -> bool:
        return bool(self._pending)

    def recv(self) -> tuple[bytes, int] | None:
        if self._fd is None:
            return None
        try:
            data = self._read_some()
        except BlockingIOError:
            return None
        except OSError as exc:  # ECONNRESET, ETIMEDOUT; EIO from a serial port that went away
            self._lose(_reason(exc))
            return None
        if data is None:
            return None
        now_ns = time.monotonic_ns()
        if not data:  # readable yet empty: the end of the stream (a hang-up on a tty)
            self._lose("closed by the other end")
            return None
        self.stats.reads += 1
        self.stats.bytes_in += len(data)
        return data, now_ns

    def send(self, frame: bytes) -> bool:
        if self._fd is None or len(frame) > self._pending_limit:
            self.stats.frames_dropped += 1
            return False
        if self._pending:
            self._flush()
            if self._fd is None:  # the flush found the stream lost
                self.stats.frames_dropped += 1
                return False
        if self._pending:  # still behind: the frame waits its turn, or does not fit
            if len(self._pending) + len(frame) > self._pending_limit:
                self.stats.frames_dropped += 1
                return False
            self._pending += frame
            self._pending_frames.append(len(frame))
            self.stats.frames_sent += 1
            return True
        try:
            written = self._write_some(frame)
        except BlockingIOError:
            written = 0
        except OSError as exc:  # EPIPE, ECONNRESET; EIO from a serial port that went away
            self.stats.frames_dropped += 1
            self._lose(_reason(exc))
            return False
        self.stats.bytes_out += written
        self.stats.frames_sent += 1
        if written < len(frame):
            self._pending += frame[written:]
            self._pending_frames.append(len(frame) - written)
        return True

    def _flush(self) -> None:
        """Write what the kernel takes of the pending bytes now."""
        try:
            written = self._write_some(self._pending)
        except BlockingIOError:
            return
        except OSError as exc:
            self._lose(_reason(exc))
            return
        self.stats.bytes_out += written
        del self._pending[:written]
        frames = self._pending_frames
        while frames and written >= frames[0]:
            written -= frames.popleft()
        if frames:
            frames[0] -= written

    def _drop_pending(self) -> None:
        self.stats.frames_dropped += len(self._pending_frames)
        self._pending.clear()
        self._pending_frames.clear()

    def _lose(self, reason: str) -> None:
        """The stream ended or failed: close it, drop what was pending, find a way back."""
        self._close_stream()
        self._drop_pending()
        self.stats.connected = False
        self.stats.last_error = reason
        self._logged_error = ""  # the first failure to come back is news again
        self._down_since_ns = time.monotonic_ns()
        self._on_lost(reason)

    def _connected(self, fd: int, detail: str) -> None:
        """A stream is up on ``fd`` (``detail`` says how, for the log): count it, say so once."""
        if self._ever_connected:
            self.stats.reconnects += 1
            down_s = 0.0 if self.stats.connected else time.monotonic_ns() - self._down_since_ns
            log.info(
                "MAVLink %s %s (reconnect %d, after %.1f s without a connection)",
                self.endpoint.url,
                detail,
                self.stats.reconnects,
                down_s / _NS_PER_S,
            )
        else:
            log.info("MAVLink %s %s", self.endpoint.url, detail)
        self._fd = fd
        self.stats.connected = True
        self._logged_error = ""
        self._ever_connected = True

    def _close_all(self) -> None:
        if self._fd is not None:
            self._close_stream()
        self._drop_pending()


class _ReopeningStream(_StreamTransport):
    """A stream this side opens (TCP client, serial): reopened after a loss, with jittered,
    capped exponential backoff, by :meth:`service`."""

    def __init__(self, endpoint: Endpoint, pending_limit_bytes: int) -> None:
        super().__init__(endpoint, pending_limit_bytes)
        self._retry_at_ns = 0
        self._backoff_s = _BACKOFF_FIRST_S

    def _schedule_retry(self) -> None:
        # Jitter keeps several bridges that lost the same router from retrying in lockstep.
        delay_s = self._backoff_s * random.uniform(0.5, 1.0)
        self._retry_at_ns = time.monotonic_ns() + round(delay_s * _NS_PER_S)
        self._backoff_s = min(self._backoff_s * 2, _BACKOFF_CAP_S)

    def _attempt_failed(self, reason: str) -> None:
        self._note_trouble(
            reason,
            "MAVLink %s not available (%s); retrying in the background",
            self.endpoint.url,
            reason,
        )
        self._schedule_retry()

    def _on_lost(self, reason: str) -> None:
        log.warning("MAVLink %s lost (%s); reconnecting", self.endpoint.url, reason)
        self._logged_error = reason  # a first retry failing the same way is no news
        self._backoff_s = _BACKOFF_FIRST_S
        self._schedule_retry()

    def _connected(self, fd: int, detail: str) -> None:
        super()._connected(fd, detail)
        self._backoff_s = _BACKOFF_FIRST_S


class _SocketStream(_StreamTransport):
    """What both TCP sides share: the stream is the socket ``_sock`` (the client's connected or
    connecting socket; the server's accepted one), read, written and closed the same way."""

    def __init__(self, endpoint: Endpoint, pending_limit_bytes: int) -> None:
        super().__init__(endpoint, pending_limit_bytes)
        self._sock: socket.socket | None = None

    def _read_some(self) -> bytes:
        assert self._sock is not None
        return self._sock.recv(_READ_SIZE)

    def _write_some(self, data: bytes | bytearray) -> int:
        assert self._sock is not None
        # MSG_NOSIGNAL: a peer that closed gives EPIPE here, never a SIGPIPE.
        return self._sock.send(data, socket.MSG_NOSIGNAL)

    def _close_stream(self) -> None:
        if self._sock is not None:
            self._sock.close()
        self._sock = None
        self._fd = None


class TcpClientTransport(_SocketStream, _ReopeningStream):
    """``tcp``: connects to HOST:PORT without blocking, and again whenever the stream is lost."""

    def __init__(
        self,
        endpoint: Endpoint,
        wait_for_link: bool = True,
        pending_limit_bytes: int = PENDING_LIMIT_BYTES,
    ) -> None:
        """Start connecting; with ``wait_for_link`` False, wait (up to 2 s) until connected.

        Raises:
            LinkError: the host is unknown; without ``wait_for_link``, the server cannot be
                reached now.
        """
        super().__init__(endpoint, pending_limit_bytes)
        self._address = _resolve(endpoint, socket.SOCK_STREAM)
        self._connect_deadline_ns = 0
        self._connecting = select.poll()  # the socket being connected, for POLLOUT
        if wait_for_link:
            self._closed = False
            self._start_connect(time.monotonic_ns())
            return
        # The old daemon's start: connected now, or an error now.
        self.stats.attempts += 1
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.settimeout(_CONNECT_TIMEOUT_NS / _NS_PER_S)
            sock.connect(self._address)
            if sock.getsockname() == sock.getpeername():
                raise ConnectionRefusedError(errno.ECONNREFUSED, "connected to itself")
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError as exc:
            sock.close()
            raise LinkError(f"cannot open MAVLink {endpoint.url!r}: {_reason(exc)}") from exc
        self._sock = sock
        self._closed = False
        self._connected(sock.fileno(), "connected")

    def service(self, now_ns: int) -> None:
        if self._fd is not None:
            if self._pending:
                self._flush()
        elif self._sock is not None:
            self._progress_connect(now_ns)
        elif now_ns >= self._retry_at_ns and not self._closed:
            self._start_connect(now_ns)

    def _start_connect(self, now_ns: int) -> None:
        self.stats.attempts += 1
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setblocking(False)
        code = sock.connect_ex(self._address)
        if code not in (0, errno.EINPROGRESS):
            sock.close()
            self._attempt_failed(os.strerror(code))
            return
        self._sock = sock
        self._connect_deadline_ns = now_ns + _CONNECT_TIMEOUT_NS
        self._connecting.register(sock, select.POLLOUT)
        self._progress_connect(now_ns)

    def _progress_connect(self, now_ns: int) -> None:
        """Finish the connect in progress if it has completed, or give it up past its time."""
        sock = self._sock
        assert sock is not None
        if not self._connecting.poll(0):
            if now_ns >= self._connect_deadline_ns:
                self._abandon_connect(f"no answer within {_CONNECT_TIMEOUT_NS / _NS_PER_S:.0f} s")
            return
        code = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if code != 0:
            self._abandon_connect(os.strerror(code))
            return
        try:
            local, peer = sock.getsockname(), sock.getpeername()
        except OSError as exc:  # reset between the connect and here
            self._abandon_connect(_reason(exc))
            return
        if local == peer:
            # Retrying a local port nobody listens on can, once in ~30000 tries, pick that
            # very port as the source and connect to itself (TCP simultaneous open).
            self._abandon_connect("connected to itself: nothing listens there")
            return
        self._connecting.unregister(sock)
        # MAVLink frames are written whole and should leave at once, not wait for an ACK.
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._connected(sock.fileno(), "reconnected" if self._ever_connected else "connected")

    def _abandon_connect(self, reason: str) -> None:
        sock = self._sock
        assert sock is not None
        self._connecting.unregister(sock)
        sock.close()
        self._sock = None
        self._attempt_failed(reason)

    def _close_all(self) -> None:
        if self._sock is not None and self._fd is None:  # a connect in progress
            self._connecting.unregister(self._sock)
        self._close_stream()
        self._drop_pending()


class TcpServerTransport(_SocketStream):
    """``tcpin``: listens on HOST:PORT and serves one client at a time; a new client replaces
    the current one (whose pending bytes are dropped)."""

    def __init__(self, endpoint: Endpoint, pending_limit_bytes: int = PENDING_LIMIT_BYTES) -> None:
        """Raises:
        LinkError: the address cannot be bound (in use, not local) or the host is unknown.
        """
        super().__init__(endpoint, pending_limit_bytes)
        address = _resolve(endpoint, socket.SOCK_STREAM)
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            # A restarted bridge must rebind while its old connections sit in TIME_WAIT; a
            # port another program listens on still fails with EADDRINUSE.
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind(address)
            self._listener.listen(1)
            self._listener.setblocking(False)
        except OSError as exc:
            self._listener.close()
            raise LinkError(f"cannot open MAVLink {endpoint.url!r}: {_reason(exc)}") from exc
        self._client_name = ""  # of the client on _sock
        self._incoming = select.poll()
        self._incoming.register(self._listener, select.POLLIN)
        self._closed = False
        log.info("MAVLink %s listening", endpoint.url)

    def service(self, now_ns: int) -> None:
        if self._pending:
            self._flush()
        if self._closed or not self._incoming.poll(0):
            return
        while True:  # take every queued client; the last one stays
            try:
                client, (host, port) = self._listener.accept()
            except BlockingIOError:
                return
            except OSError as exc:  # ECONNABORTED (gone before accepted), EMFILE, ...
                self._note_trouble(
                    _reason(exc), "MAVLink %s: accept failed: %s", self.endpoint.url, exc
                )
                return
            client.setblocking(False)  # an accepted socket does not inherit it on Linux
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.stats.attempts += 1
            name = f"{host}:{port}"
            if self._sock is not None:
                log.info(
                    "MAVLink %s: client %s replaces %s", self.endpoint.url, name, self._client_name
                )
                self._close_stream()
                self._drop_pending()
            self._sock, self._client_name = client, name
            self._connected(client.fileno(), f"client {name} connected")

    def _on_lost(self, reason: str) -> None:
        log.warning(
            "MAVLink %s: client %s lost (%s); waiting for another",
            self.endpoint.url,
            self._client_name,
            reason,
        )

    def _close_all(self) -> None:
        super()._close_all()
        self._listener.close()


def _open_tty(path: str, speed: int) -> int:
    """Open a terminal device raw, 8N1, no flow control, non-blocking; raises OSError."""
    # O_NONBLOCK also keeps open() from waiting for a modem's carrier; O_NOCTTY keeps the
    # device from becoming our controlling terminal.
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        iflag, oflag, cflag, lflag, _, _, cc = termios.tcgetattr(fd)
        iflag &= ~(
            termios.IGNBRK
            | termios.BRKINT
            | termios.PARMRK
            | termios.ISTRIP
            | termios.INLCR
            | termios.IGNCR
            | termios.ICRNL
            | termios.IXON
            | termios.IXOFF
            | termios.IXANY
            | termios.INPCK
        )
        oflag &= ~termios.OPOST
        lflag &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
        cflag &= ~(termios.CSIZE | termios.PARENB | termios.CSTOPB | termios.CRTSCTS)
        cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL  # CLOCAL: ignore modem lines
        cc[termios.VMIN] = 0
        cc[termios.VTIME] = 0
        termios.tcsetattr(fd, termios.TCSANOW, [iflag, oflag, cflag, lflag, speed, speed, cc])
        # Bytes that waited in the driver before we opened would be stamped as just read.
        termios.tcflush(fd, termios.TCIOFLUSH)
    except termios.error as exc:
        os.close(fd)
        code, text = exc.args
        raise OSError(code, text) from exc
    except BaseException:
        os.close(fd)
        raise
    return fd


def _close_tty(fd: int) -> None:
    """Close a terminal device without waiting for its unsent output to drain (which close()
    would do, for up to the port's closing_wait, 30 s by default)."""
    with contextlib.suppress(termios.error):
        termios.tcflush(fd, termios.TCOFLUSH)
    with contextlib.suppress(OSError):
        os.close(fd)


_OPEN_REQUEST: Final = -1
"""Asks a serial helper to open its device; a descriptor (>= 0) asks it to close that one;
None asks it to stop."""


def _serve_serial(
    path: str,
    speed: int,
    requests: queue.SimpleQueue[int | None],
    results: queue.SimpleQueue[int | OSError],
) -> None:
    """A serial transport's helper thread: opens and closes the device, which a USB adapter's
    driver may sleep in for milliseconds (cdc-acm and ftdi_sio send USB control transfers
    from open() and tcsetattr() and wait for them), so the real-time thread never does.
    Holds no reference to the transport, so a forgotten transport is still collected."""
    while True:
        request = requests.get()
        if request is None:
            # Stopped: a device opened for a transport that has closed meanwhile is closed.
            while not results.empty():
                opened = results.get()
                if isinstance(opened, int):
                    _close_tty(opened)
            return
        if request >= 0:
            _close_tty(request)
            continue
        try:
            results.put(_open_tty(path, speed))
        except OSError as exc:
            results.put(exc)


class SerialTransport(_ReopeningStream):
    """``serial``: a terminal device opened raw, 8N1, no flow control, non-blocking; reopened
    (by path, so a ``/dev/serial/by-id`` link finds a re-enumerated adapter) when it goes away.

    Opened with ``os.open`` and ``termios`` rather than pyserial: pyserial's ``write`` with
    ``write_timeout=0`` retries EAGAIN in a loop, busy-waiting as long as the port's buffer
    stays full, and its ``read`` calls ``select()`` (which fails for descriptors above 1023)
    before every read. Here a read or write is one system call. The price: only the rates
    ``termios`` names (50..4000000 bit/s, every rate an autopilot uses).

    Opening (after the first time, at construction) and closing run in a helper thread, one
    per transport and idle otherwise, since a USB adapter's driver sleeps in both;
    :meth:`service` hands it the work and picks up the result. Reads ask first how many bytes
    wait (see :meth:`_read_some`). The caller's own ``poll()`` on a tty with nothing in it may
    wait for the kernel's flip-buffer worker in the same way (``n_tty_poll``), which a poll
    with a timeout up to the next tick absorbs.
    """

    def __init__(
        self,
        endpoint: Endpoint,
        wait_for_link: bool = True,
        pending_limit_bytes: int = PENDING_LIMIT_BYTES,
    ) -> None:
        """Open the device now if it is there; with ``wait_for_link``, a device that is
        absent (or not yet accessible) is opened later by :meth:`service`.

        Raises:
            LinkError: the baud rate is not a standard one, the path is no terminal, or (without
                ``wait_for_link``) the device cannot be opened now.
        """
        super().__init__(endpoint, pending_limit_bytes)
        speed = getattr(termios, f"B{endpoint.baud}", None)
        if not isinstance(speed, int):
            raise LinkError(
                f"cannot open MAVLink {endpoint.url!r}: {endpoint.baud} bit/s is not a standard "
                "rate; expected one of 57600, 115200, 230400, 460800, 921600, 1500000, ..."
            )
        self._waiting = array.array("i", [0])  # TIOCINQ's answer, written in place
        self.stats.attempts += 1
        try:
            fd: int | None = _open_tty(endpoint.address, speed)
        except OSError as exc:
            if not wait_for_link or exc.errno not in _SERIAL_TRANSIENT:
                raise LinkError(f"cannot open MAVLink {endpoint.url!r}: {_reason(exc)}") from exc
            fd, failure = None, _reason(exc)
        self._requests: queue.SimpleQueue[int | None] = queue.SimpleQueue()
        self._results: queue.SimpleQueue[int | OSError] = queue.SimpleQueue()
        self._opening = False  # an open request is with the helper
        threading.Thread(
            target=_serve_serial,
            args=(endpoint.address, speed, self._requests, self._results),
            name=f"serial-helper {endpoint.address}",
            daemon=True,  # a driver stuck in open() must not keep the process alive
        ).start()
        self._closed = False
        if fd is None:
            self._attempt_failed(failure)
        else:
            self._connected(fd, f"open at {endpoint.baud} bit/s")

    def service(self, now_ns: int) -> None:
        if self._fd is not None:
            if self._pending:
                self._flush()
            return
        if self._closed:
            return
        if self._opening:
            if self._results.empty():
                return  # the helper is still at it
            self._opening = False
            result = self._results.get()
            if isinstance(result, OSError):
                self._attempt_failed(_reason(result))
            else:
                self._connected(result, f"open at {self.endpoint.baud} bit/s")
        elif now_ns >= self._retry_at_ns:
            self.stats.attempts += 1
            self._opening = True
            self._requests.put(_OPEN_REQUEST)

    def _read_some(self) -> bytes | None:
        assert self._fd is not None
        # A tty read that finds the line discipline empty first waits for the kernel's
        # flip-buffer worker to finish (n_tty_read calls tty_buffer_flush_work), which on a
        # busy machine can take milliseconds to be scheduled. Asking how many bytes wait
        # (TIOCINQ) does not wait for it, and costs less than an empty read. A device that
        # went away answers EIO here.
        fcntl.ioctl(self._fd, termios.TIOCINQ, self._waiting, True)
        if self._waiting[0] == 0:
            return None
        return os.read(self._fd, _READ_SIZE)

    def _write_some(self, data: bytes | bytearray) -> int:
        assert self._fd is not None
        return os.write(self._fd, data)

    def _close_stream(self) -> None:
        if self._fd is not None:
            self._requests.put(self._fd)  # the helper closes it: close() may wait in the driver
        self._fd = None

    def _close_all(self) -> None:
        super()._close_all()
        self._requests.put(None)


def open_transport(
    endpoint: Endpoint,
    wait_for_link: bool = True,
    pending_limit_bytes: int = PENDING_LIMIT_BYTES,
) -> AutopilotTransport:
    """Open the transport for ``endpoint`` (from :func:`~bridge.mavlink.endpoints.parse_url`).
    Call it before the loop starts: it is the one call that may wait, to resolve a host name
    (once; the loop never does), to open a serial device the first time and start its helper
    thread, and, without ``wait_for_link``, for a TCP connect. No method of the transport waits
    after it.

    ``wait_for_link`` True (the default, for the real-time loop): a TCP server that is not up
    yet, or a serial device that does not exist yet (a USB adapter not enumerated at boot, a
    device node udev has not opened to us yet), is no error: the transport starts
    disconnected and :meth:`~AutopilotTransport.service` keeps retrying with backoff, logging
    once that it waits. False: the old daemon's behaviour, which refuses to start without its
    autopilot: such a link raises LinkError here (a TCP connect is waited for, up to 2 s). UDP
    and tcpin need no peer to open and behave the same either way.

    ``pending_limit_bytes``: the bound of a stream's pending buffer (see
    :data:`PENDING_LIMIT_BYTES`); frames larger than it are always dropped.

    Raises:
        LinkError: naming the URL, for what is wrong at start and will not get better: an
            address that cannot be bound (in use, not local), an unknown host, a serial path
            that is no terminal or a non-standard baud rate; and, with ``wait_for_link``
            False, a TCP server or serial device that cannot be reached now.
        ValueError: ``pending_limit_bytes`` is not positive.
    """
    if endpoint.kind == "udpin":
        return UdpInTransport(endpoint)
    if endpoint.kind == "udpout":
        return UdpOutTransport(endpoint)
    if endpoint.kind == "tcp":
        return TcpClientTransport(endpoint, wait_for_link, pending_limit_bytes)
    if endpoint.kind == "tcpin":
        return TcpServerTransport(endpoint, pending_limit_bytes)
    return SerialTransport(endpoint, wait_for_link, pending_limit_bytes)
