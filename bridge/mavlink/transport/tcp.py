"""The TCP transports: ``tcp`` (a client that connects without blocking) and ``tcpin`` (a
server of one client at a time); see :mod:`bridge.mavlink.transport`."""

from __future__ import annotations

import errno
import logging
import os
import select
import socket
import time
from typing import Final

from bridge.errors import LinkError
from bridge.mavlink.endpoints import Endpoint
from bridge.mavlink.transport.base import PENDING_LIMIT_BYTES, reason, resolve
from bridge.mavlink.transport.stream import READ_SIZE, ReopeningStream, StreamTransport

__all__ = ["TcpClientTransport", "TcpServerTransport"]

log = logging.getLogger(__name__)


# A SYN that gets no answer is retried by the kernel at 1 s, 3 s, 7 s...; a peer on the LAN or
# a radio link answers well within 2 s, so waiting longer only delays the next fresh attempt.
_CONNECT_TIMEOUT_NS: Final = 2_000_000_000
_NS_PER_S: Final = 1_000_000_000


class _SocketStream(StreamTransport):
    """What both TCP sides share: the stream is the socket ``_sock`` (the client's connected or
    connecting socket; the server's accepted one), read, written and closed the same way."""

    def __init__(self, endpoint: Endpoint, pending_limit_bytes: int) -> None:
        super().__init__(endpoint, pending_limit_bytes)
        self._sock: socket.socket | None = None

    def _read_some(self) -> bytes:
        assert self._sock is not None
        return self._sock.recv(READ_SIZE)

    def _write_some(self, data: bytes | bytearray) -> int:
        assert self._sock is not None
        # MSG_NOSIGNAL: a peer that closed gives EPIPE here, never a SIGPIPE.
        return self._sock.send(data, socket.MSG_NOSIGNAL)

    def _close_stream(self) -> None:
        if self._sock is not None:
            self._sock.close()
        self._sock = None
        self._fd = None


class TcpClientTransport(_SocketStream, ReopeningStream):
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
        self._address = resolve(endpoint, socket.SOCK_STREAM)
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
            raise LinkError(f"cannot open MAVLink {endpoint.url!r}: {reason(exc)}") from exc
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
            self._abandon_connect(reason(exc))
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
        address = resolve(endpoint, socket.SOCK_STREAM)
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
            raise LinkError(f"cannot open MAVLink {endpoint.url!r}: {reason(exc)}") from exc
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
                    reason(exc), "MAVLink %s: accept failed: %s", self.endpoint.url, exc
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
