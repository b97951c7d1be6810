"""One connection of the MAVLink link (:class:`bridge.mavlink.link.MavlinkLink`): the
autopilot's or an extra output's.

pymavlink opens the transport (:func:`open_pymavlink`), or the daemon's relay stands in for the
autopilot's. Writes happen under the connection's lock; an output's frames wait in a bounded
queue for the output's own writer thread (:meth:`Connection.run_writer`), so a congested or dead
output (a wedged UART, a stalled TCP client) delays nobody but itself. A TCP or serial
connection that drops is reopened with jittered, capped exponential backoff
(:meth:`Connection.reopen`). Parsing what is read is the link's.
"""

from __future__ import annotations

import logging
import random
import select
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Final

from bridge.errors import LinkError
from bridge.mavlink.endpoints import Endpoint
from bridge.mavlink.stats import Counters, OutputStats, log_sparsely

__all__ = ["POLL_S", "Connection", "open_pymavlink", "wait_readable"]

log = logging.getLogger(__name__)


def _import_mavutil() -> Any:
    """``pymavlink.mavutil``, loaded without numpy.

    mavutil loads its log-expression helpers, and they load numpy where it is installed (on most
    companion computers, for vision; here, for the plot extra) for quaternions the bridge never
    uses, and numpy is most of what loading mavutil costs, at every start of the bridge. They
    load it inside a ``try``, so numpy hidden while mavutil loads is numpy skipped. A process
    that has numpy already keeps it, and mavutil gets its quaternions.
    """
    if "numpy" in sys.modules:
        from pymavlink import mavutil
    else:
        sys.modules["numpy"] = None  # type: ignore[assignment]  # import numpy: ImportError
        try:
            from pymavlink import mavutil
        finally:
            if "numpy" in sys.modules and sys.modules["numpy"] is None:
                del sys.modules["numpy"]
    return mavutil


mavutil: Any = _import_mavutil()

POLL_S: Final = 0.1
"""Readers and writers wake at least this often to notice that the link is closing."""
_BACKOFF_FIRST_S: Final = 0.1  # a restarting TCP peer is often listening again within this
_BACKOFF_CAP_S: Final = 5.0
# A write that blocks holds the connection's lock and would stall its reader; a UART without
# flow control never blocks this long, so hitting it means the port is wedged.
_SERIAL_WRITE_TIMEOUT_S: Final = 0.1
# Frames waiting for an output's writer. At the bridge's own rates (a HEARTBEAT, ~30 telemetry
# messages a second) this is seconds of backlog: a full queue means the output is stuck, and
# the oldest frames, the least useful ones, are dropped first.
_OUTPUT_QUEUE_FRAMES: Final = 256
_SERIAL_WRITE_FAILED: Final = -1  # what pymavlink's serial write returns after an exception


def open_pymavlink(endpoint: Endpoint, source_system: int, source_component: int) -> Any:
    """Open ``endpoint`` with pymavlink's transport.

    Raises:
        LinkError: it cannot be opened (no such device, port in use, refused, no pyserial).
    """
    ids = {"source_system": source_system, "source_component": source_component}
    try:
        if endpoint.kind == "serial":
            conn = mavutil.mavserial(endpoint.address, baud=endpoint.baud, **ids)
            conn.port.write_timeout = _SERIAL_WRITE_TIMEOUT_S
            return conn
        if endpoint.kind == "tcp":
            # retries=0 is a single attempt: the backoff between attempts is ours.
            return mavutil.mavtcp(endpoint.address, retries=0, **ids)
        if endpoint.kind == "tcpin":
            return mavutil.mavtcpin(endpoint.address, **ids)
        return mavutil.mavudp(endpoint.address, input=endpoint.kind == "udpin", **ids)
    except ImportError as exc:
        raise LinkError(
            f"cannot open MAVLink {endpoint.url!r}: serial links need pyserial ({exc})"
        ) from exc
    except (OSError, ValueError) as exc:
        raise LinkError(f"cannot open MAVLink {endpoint.url!r}: {exc}") from exc


def wait_readable(fd: int, timeout_s: float) -> bool:
    """True when ``fd`` has data, an end of stream or an error to report (poll, not select:
    select fails for descriptors above 1023)."""
    poller = select.poll()
    poller.register(fd, select.POLLIN | select.POLLPRI)
    return bool(poller.poll(timeout_s * 1000))


class Connection:
    """One transport the link reads and writes: the autopilot's, or an extra output."""

    def __init__(self, endpoint: Endpoint, counters: Counters, is_autopilot: bool) -> None:
        self.endpoint = endpoint
        self.counters = counters
        self.is_autopilot = is_autopilot
        self.lock = threading.Lock()
        """Guards ``conn``: its reads, writes, closing and replacement."""
        self.conn: Any = None
        self.parser: Any = None
        """Owned by the reader thread; used under the link's codec lock (shared signing)."""
        # Outputs only: frames for the writer thread; oldest dropped first when full.
        self._queue: deque[bytes] = deque()
        self._queued = threading.Condition()

    @property
    def url(self) -> str:
        return self.endpoint.url

    def write(self, frame: bytes) -> None:
        """Write one frame now; called with :attr:`lock` held."""
        counters = self.counters
        if self.conn is None:
            counters.send_failures += 1
            return
        try:
            written = self.conn.write(frame)
        # pymavlink's transports swallow most socket errors; whatever still escapes is the
        # connection's trouble, never the sender's.
        except Exception:  # noqa: BLE001
            counters.send_failures += 1
            log_sparsely(
                log,
                logging.WARNING,
                counters.send_failures,
                "MAVLink %s: write failed",
                self.url,
                exc_info=True,
            )
            return
        if written == _SERIAL_WRITE_FAILED:
            counters.send_failures += 1
            log_sparsely(
                log, logging.WARNING, counters.send_failures, "MAVLink %s: write failed", self.url
            )
        elif isinstance(counters, OutputStats):
            counters.sent += 1

    def enqueue(self, frame: bytes) -> None:
        """Queue ``frame`` for an output's writer, dropping the oldest when the queue is full."""
        counters = self.counters
        with self._queued:
            if len(self._queue) >= _OUTPUT_QUEUE_FRAMES:
                self._queue.popleft()
                counters.send_failures += 1
                log_sparsely(
                    log,
                    logging.WARNING,
                    counters.send_failures,
                    "MAVLink output %s is not keeping up; dropped its oldest frame",
                    self.url,
                )
            self._queue.append(frame)
            self._queued.notify()

    def run_writer(self, stop: threading.Event) -> None:
        """An output's writer thread: drains its queue, so its troubles stay its own."""
        while True:
            with self._queued:
                while not self._queue and not stop.is_set():
                    self._queued.wait(POLL_S)
                if stop.is_set():
                    return
                frames = list(self._queue)
                self._queue.clear()
            with self.lock:
                for frame in frames:
                    self.write(frame)

    def wake_writer(self) -> None:
        """Wake the writer thread at once (to notice that the link is closing)."""
        with self._queued:
            self._queued.notify_all()

    def drop(self) -> None:
        """Close the live transport, if any. Called with :attr:`lock` held."""
        if self.conn is not None:
            self.conn.close()
        self.conn = None

    def reopen(
        self,
        reason: str,
        stop: threading.Event,
        open_conn: Callable[[], Any],
        install: Callable[[Connection, Any], bool],
    ) -> None:
        """Close the dropped transport and open it again (``open_conn``, which raises
        LinkError), backing off, until it opens and ``install`` takes it, or ``stop`` is set."""
        endpoint = self.endpoint
        with self.lock:
            self.drop()
        log.warning("MAVLink %s lost (%s); reconnecting", endpoint.url, reason)
        lost_at = time.monotonic()
        delay = _BACKOFF_FIRST_S
        attempts = 0
        # Jitter keeps several bridges that lost the same router from retrying in lockstep.
        while not stop.wait(delay * random.uniform(0.5, 1.0)):
            attempts += 1
            try:
                conn = open_conn()
            except LinkError as exc:
                log.debug("reconnect attempt %d failed: %s", attempts, exc)
                delay = min(delay * 2, _BACKOFF_CAP_S)
                continue
            if not install(self, conn):
                return
            self.counters.reconnects += 1
            log.info(
                "MAVLink %s reconnected after %.1f s, at attempt %d (%d reconnects in all)",
                endpoint.url,
                time.monotonic() - lost_at,
                attempts,
                self.counters.reconnects,
            )
            return
