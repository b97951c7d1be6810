"""``esc-bridge monitor --web``: the monitor's vehicles served as a live web page.

One process, threads only. A publisher thread asks the source for its vehicles every
:data:`PUSH_PERIOD_S`, turns them into one JSON message (:mod:`.model`) and offers it to every
connected browser; each browser has a thread of its own (the standard library's
``ThreadingHTTPServer``) that writes its messages as Server-Sent Events. The hand-over is a
queue of :data:`CLIENT_QUEUE` messages per browser that drops its oldest when full, so a slow
browser misses snapshots (each one is whole, the next replaces it) and a stuck one is dropped
after :data:`WRITE_TIMEOUT_S`; neither ever waits the publisher, let alone the Zenoh side, which
only ever hands its samples to the source under the source's own short lock.

Read-only by construction: GET and HEAD of five paths, nothing that takes a parameter, and no
other method (the standard library answers 501). The page's script, style and markup are
package data beside this module (hand-written, under the project's licence); the
Content-Security-Policy header forbids the page anything from elsewhere.
"""

from __future__ import annotations

import json
import logging
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from socketserver import TCPServer
from types import TracebackType
from typing import Any, Final

from bridge._compat import Self
from bridge.errors import ConfigError, LinkError
from bridge.monitor.sources import Source
from bridge.monitor.web import model

log = logging.getLogger(__name__)

PUSH_PERIOD_S: Final = 0.1
"""A snapshot to every browser ten times a second (the issue asks for at least five)."""
CLIENT_QUEUE: Final = 4
"""Messages waiting per browser; when full, the oldest is dropped for the newest."""
WRITE_TIMEOUT_S: Final = 10.0
"""A browser that takes nothing for this long is disconnected (it reconnects by itself)."""
RETRY_MS: Final = 1000
"""How soon a browser reconnects after losing the stream (SSE ``retry:``)."""
DEFAULT_HOST: Final = "127.0.0.1"
"""Where the page is served unless a host is given: this machine only."""
LOOPBACK_HOSTS: Final = frozenset(("127.0.0.1", "::1", "localhost"))

# Path -> (package file, content type). The page and its two files, nothing else.
_FILES: Final = {
    "/": ("page.html", "text/html; charset=utf-8"),
    "/page.js": ("page.js", "text/javascript; charset=utf-8"),
    "/page.css": ("page.css", "text/css; charset=utf-8"),
}
_HEADERS: Final = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self'; "
        "img-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    ),
}


def parse_address(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` (an IPv6 host in brackets: ``[::]:8080``) -> (host, port); the host
    defaults to :data:`DEFAULT_HOST`, port 0 picks a free one.

    Raises:
        ValueError: not of that form, naming what is expected.
    """
    expected = f"[HOST:]PORT such as 8080, 0.0.0.0:8080 or [::1]:8080, got {text!r}"
    host, colon, port_text = text.rpartition(":")
    if not colon:
        host = DEFAULT_HOST
    elif host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host or "[" in host or "]" in host:
        raise ValueError(f"expected {expected} (an IPv6 address goes in brackets)")
    if not host or not port_text.isascii() or not port_text.isdigit():
        raise ValueError(f"expected {expected}")
    port = int(port_text)
    if port > 65535:
        raise ValueError(f"expected a port 0..65535 in {expected}")
    return host, port


def is_loopback(host: str) -> bool:
    """Only this machine can reach a page served on ``host``."""
    return host in LOOPBACK_HOSTS or host.startswith("127.")


@dataclass
class WebStats:
    """Counters since :meth:`WebMonitor.start`."""

    pushes: int = 0
    """Snapshots made (each offered to every browser connected then)."""
    browsers: int = 0
    """Browsers connected now."""
    connections: int = 0
    """Event streams opened so far."""
    dropped: int = 0
    """Snapshots a slow browser never got (the newer ones replaced them)."""
    disconnected: int = 0
    """Browsers that went away or were dropped for taking nothing for WRITE_TIMEOUT_S."""


class _Client:
    """One browser's queue: the publisher offers, the browser's thread takes."""

    def __init__(self) -> None:
        self._messages: deque[bytes] = deque(maxlen=CLIENT_QUEUE)
        self._ready = threading.Condition()
        self.dropped = 0

    def offer(self, message: bytes) -> None:
        """Queue ``message`` without ever waiting; a full queue loses its oldest."""
        with self._ready:
            if len(self._messages) == self._messages.maxlen:
                self.dropped += 1
            self._messages.append(message)
            self._ready.notify()

    def take(self, timeout_s: float) -> list[bytes]:
        """Every queued message, waiting up to ``timeout_s`` for one."""
        with self._ready:
            if not self._messages:
                self._ready.wait(timeout_s)
            messages = list(self._messages)
            self._messages.clear()
            return messages


class WebMonitor:
    """Serves the page for ``source`` on ``host``:``port``; start with :meth:`start` or as a
    context manager. The source stays the caller's to close."""

    def __init__(
        self,
        source: Source,
        host: str = DEFAULT_HOST,
        port: int = 0,
        period_s: float = PUSH_PERIOD_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.source = source
        self.host = host
        self.port = port
        self.period_s = period_s
        self._clock = clock
        self._started_at = clock()
        self._model = model.PageModel(source.where)
        self._lock = threading.Lock()  # the clients, the model, the latest message, stats
        self._clients: set[_Client] = set()
        self._latest: bytes | None = None
        self._stats = WebStats()
        self._stop = threading.Event()
        self._server: ThreadingHTTPServer | None = None
        self._threads: list[threading.Thread] = []

    @property
    def url(self) -> str:
        """The page's address as bound (the real port when 0 was asked for)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    @property
    def stats(self) -> WebStats:
        with self._lock:
            dropped = self._stats.dropped + sum(c.dropped for c in self._clients)
            return WebStats(
                self._stats.pushes,
                len(self._clients),
                self._stats.connections,
                dropped,
                self._stats.disconnected,
            )

    def start(self) -> None:
        """Bind, then serve and push from threads of their own; returns at once.

        Raises:
            ConfigError: the host is not an address or name of this machine.
            LinkError: the address cannot be bound (the port is taken, ...).
        """
        try:
            infos = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_STREAM)
        except socket.gaierror as exc:
            raise ConfigError(f"--web {self.host}: not a host name or address ({exc})") from exc
        family, _, _, _, address = infos[0]
        try:
            server = _Server((str(address[0]), int(address[1])), family, self)
        except OSError as exc:
            where = f"{self.host}:{self.port}"
            raise LinkError(f"--web {where}: cannot serve there ({exc.strerror})") from exc
        self._server = server
        self.port = server.server_address[1]
        self._threads = [
            threading.Thread(target=server.serve_forever, args=(0.2,), name="web-serve"),
            threading.Thread(target=self._publish, name="web-publish"),
        ]
        for thread in self._threads:
            thread.daemon = True
            thread.start()

    def close(self) -> None:
        """Stop pushing and serving, end every stream; a second call does nothing."""
        if self._stop.is_set():
            return
        self._stop.set()
        server = self._server
        if server is not None:
            server.shutdown()
            server.server_close()
        for thread in self._threads:
            thread.join(2.0)

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- the publisher thread ---------------------------------------------------------------

    def _publish(self) -> None:
        due = self._clock()
        while not self._stop.is_set():
            try:
                self.push()
            except Exception:  # a fault in one snapshot must not end the page
                log.exception("web monitor: a snapshot failed")
            due = max(due + self.period_s, self._clock())
            self._stop.wait(max(0.0, due - self._clock()))

    def push(self) -> None:
        """One snapshot of the source, to every browser (the publisher thread's step)."""
        vehicles = self.source.vehicles()
        t_s = self._clock() - self._started_at
        with self._lock:
            message = _event("snapshot", self._model.snapshot(vehicles, t_s))
            self._latest = message
            self._stats.pushes += 1
            clients = list(self._clients)
        for client in clients:
            client.offer(message)

    # -- the browsers' threads --------------------------------------------------------------

    def _connect(self) -> tuple[_Client, bytes]:
        client = _Client()
        with self._lock:
            history = self._model.hello(self.period_s)
            latest = self._latest
            self._clients.add(client)
            self._stats.connections += 1
        first = f"retry: {RETRY_MS}\n\n".encode() + _event("hello", history)
        return client, first + (latest or b"")

    def _disconnect(self, client: _Client) -> None:
        with self._lock:
            self._clients.discard(client)
            self._stats.dropped += client.dropped
            self._stats.disconnected += 1

    def stream(self, write: Callable[[bytes], None]) -> None:
        """Write the event stream to one browser until it goes away or the monitor stops."""
        client, first = self._connect()
        try:
            write(first)
            while not self._stop.is_set():
                messages = client.take(0.5)
                if messages:
                    write(b"".join(messages))
        except OSError as exc:  # closed, reset, or WRITE_TIMEOUT_S without taking anything
            log.debug("web monitor: a browser went away (%s)", exc)
        finally:
            self._disconnect(client)

    def state_json(self) -> bytes:
        """The latest snapshot as a JSON document (``/state.json``)."""
        with self._lock:
            latest = self._latest
        if latest is None:
            return json.dumps({"source": self.source.where, "t": 0.0, "vehicles": []}).encode()
        # An event is "event: snapshot\ndata: <json>\n\n".
        return latest.split(b"\ndata: ", 1)[1].rstrip(b"\n")


def _event(name: str, data: Any) -> bytes:
    # Compact JSON has no newline, so one data: line carries it.
    text = json.dumps(data, separators=(",", ":"), allow_nan=False)
    return f"event: {name}\ndata: {text}\n\n".encode()


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, address: tuple[str, int], family: int, monitor: WebMonitor) -> None:
        self.address_family = family
        self.monitor = monitor
        # Read once: a missing file fails at start, not in front of a browser.
        package = resources.files("bridge.monitor.web")
        self.files = {
            path: (package.joinpath(name).read_bytes(), content_type)
            for path, (name, content_type) in _FILES.items()
        }
        super().__init__(address, _Handler)

    def server_bind(self) -> None:
        # HTTPServer's would look this machine's name up (socket.getfqdn), which waits on DNS
        # where none answers; the page never needs it.
        TCPServer.server_bind(self)
        self.server_name, self.server_port = str(self.server_address[0]), self.server_address[1]


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0]
        if path == "/events":
            self._events()
        elif path == "/state.json":
            self._send(self.server.monitor.state_json(), "application/json")
        elif path in self.server.files:
            self._send(*self.server.files[path])
        else:
            self._send(b"not found\n", "text/plain; charset=utf-8", HTTPStatus.NOT_FOUND)

    def do_HEAD(self) -> None:
        path = self.path.split("?", 1)[0]
        known = path in _FILES or path in ("/events", "/state.json")
        self.send_response(HTTPStatus.OK if known else HTTPStatus.NOT_FOUND)
        self.send_header("Content-Length", "0")
        self.end_headers()

    def _send(self, body: bytes, content_type: str, status: HTTPStatus = HTTPStatus.OK) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        for name, value in _HEADERS.items():
            self.send_header(name, value)
        self.end_headers()
        self.wfile.write(body)

    def _events(self) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        for name, value in _HEADERS.items():
            self.send_header(name, value)
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        self.connection.settimeout(WRITE_TIMEOUT_S)

        def write(data: bytes) -> None:
            self.wfile.write(data)
            self.wfile.flush()

        self.server.monitor.stream(write)

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("web monitor: %s %s", self.address_string(), format % args)
