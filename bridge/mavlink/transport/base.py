"""What every non-blocking transport to the autopilot is: :class:`AutopilotTransport` and its
counters, and the helpers the kinds share (see :mod:`bridge.mavlink.transport`)."""

from __future__ import annotations

import logging
import socket
from abc import ABC, abstractmethod
from dataclasses import dataclass
from types import TracebackType
from typing import ClassVar, Final, cast

from bridge.errors import LinkError
from bridge.mavlink.endpoints import Endpoint

__all__ = ["PENDING_LIMIT_BYTES", "AutopilotTransport", "TransportStats", "reason", "resolve"]

log = logging.getLogger(__name__)

PENDING_LIMIT_BYTES: Final = 4096
"""Default bound of a stream's pending buffer: about 15 full-size MAVLink 2 frames (280 bytes),
0.35 s of a 115200 bit/s UART. More would only queue stale frames behind a stalled peer."""


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


def reason(exc: BaseException) -> str:
    """A short human text for an OS error: its strerror when it has one."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


def resolve(endpoint: Endpoint, sock_type: int) -> tuple[str, int]:
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
            f"cannot open MAVLink {endpoint.url!r}: unknown host {host!r} ({reason(exc)}); "
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
    datagrams: ClassVar[bool] = False
    """Each :meth:`recv` returns one whole datagram (UDP), so a frame never spans two reads and
    a reader scans each on its own; False for a byte stream, whose reads cut frames anywhere."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.stats = TransportStats()
        self.sender: tuple[str, int] | None = None
        """Datagrams: the address the datagram :meth:`recv` returned last came from. None on a
        stream, and before the first datagram."""
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

    @property
    def configured_peer(self) -> tuple[str, int] | None:
        """``udpout``: the address it sends to, resolved; None for every other kind."""
        return None

    def reply_to(self, peer: tuple[str, int] | None) -> None:
        """``udpin``: send to ``peer`` from now on, whoever else sends to us; None: to the
        sender of the latest datagram again (the default). Nothing for every other kind."""
        return

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
