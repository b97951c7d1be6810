"""ESC telemetry fan-out over Zenoh: the only module that imports zenoh.

Keys, all under :meth:`bridge.config.ZenohConfig.key_prefix` (default ``esc-bridge/<vehicle>``):

=========================  ===========================================  ==============
key                        payload (JSON, ``application/json``)         rate cap
=========================  ===========================================  ==============
``esc/<n>/telemetry``      :class:`~.payload.EscTelemetryPayload`       ``telemetry_hz``
``esc/<n>/info``           :class:`~.payload.EscInfoPayload`            ``info_hz``
``esc/status``             :class:`~.payload.EscStatusPayload`          ``status_hz``
``bridge/health``          ``TelemetrySources.health()``                ``health_hz``
``actuators/input``        ``TelemetrySources.actuators_input()``       ``actuators_hz``
``actuators/output``       ``TelemetrySources.actuators_output()``      ``actuators_hz``
=========================  ===========================================  ==============

Every payload is encoded by its record in :mod:`bridge.telemetry.payload`, and carries
``time_unix_ms`` (wall clock, when published) unless its source already put one in. A
source that returns ``None`` (nothing yet) is skipped. A sample is made, encoded and sent only
while a subscriber matches its key (Zenoh's matching status): nobody listening costs nothing. A
queryable on ``<prefix>/**`` answers with the current value of each matching key, made when
asked, and a liveliness token on ``<prefix>/alive`` exists while the bridge has a session.

Zenoh never holds up the bridge: :meth:`ZenohOut.start` returns at once, one daemon thread
opens the session (retrying with jittered, capped backoff when it cannot), declares the
publishers and publishes on a fixed schedule. Queries wait in a small ring channel for a second
thread of ours, which ends when the queryable is undeclared and which closing waits for. (With a
Python callback, zenoh would answer on a thread of its own making that nobody waits for; one
still inside zenoh's code as the interpreter exits makes glibc abort the process, "FATAL:
exception not rethrown", and systemd would see a crash on every such stop.) Publishers drop
under congestion rather than block; samples due while no session is open are counted as
dropped. :meth:`ZenohOut.close` returns within :data:`CLOSE_TIMEOUT_S` whatever the network
does.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import random
import re
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from types import TracebackType
from typing import Any

import zenoh

from bridge.config import ZenohConfig
from bridge.errors import ConfigError
from bridge.telemetry.payload import (
    ActuatorsInputPayload,
    ActuatorsOutputPayload,
    EscInfoPayload,
    EscStatusPayload,
    EscTelemetryPayload,
    HealthPayload,
    Payload,
)
from bridge.telemetry.state import EscSnapshot, EscTable

log = logging.getLogger(__name__)

BACKOFF_S = (0.5, 10.0)  # first and longest wait between attempts to open a session
BACKOFF_JITTER = 0.2  # each wait is scaled by a random factor in 1 ± this
WARN_INTERVAL_S = 60.0  # after the first warning, repeat a persisting problem at most this often
PEERS_POLL_S = 1.0  # how often the connected routers and peers are counted
CLOSE_TIMEOUT_S = 1.5  # close() waits this long for the thread to close the session
QUERY_QUEUE = 16  # queries waiting to be answered; beyond this the oldest is dropped
BROKEN_AFTER_ERRORS = 50  # consecutive failed puts after which the session is reopened
ENCODING = zenoh.Encoding.APPLICATION_JSON
PRIORITY = zenoh.Priority.DATA_LOW  # telemetry yields to anything else on the vehicle's network

# Zenoh locator protocols whose address is <host>:<port>, and those with another address form.
IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
OTHER_PROTOCOLS = ("unixsock-stream", "unixpipe", "serial", "vsock")
ENDPOINT_FORM = (
    "endpoints of the form <protocol>/<host>:<port> such as tcp/192.168.1.2:7447 or "
    "udp/[fe80::1]:7447 (protocol one of " + ", ".join(IP_PROTOCOLS) + "), or "
    "<protocol>/<address> for " + ", ".join(OTHER_PROTOCOLS)
)
_LABEL = r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOSTNAME = re.compile(rf"{_LABEL}(\.{_LABEL})*\.?")  # a DNS name


@dataclass
class TelemetrySources:
    """Where the published data comes from. The callables are cheap and thread-safe; each
    returns the latest record, or ``None`` when there is nothing yet."""

    escs: EscTable
    health: Callable[[], HealthPayload]
    actuators_input: Callable[[], ActuatorsInputPayload | None]
    actuators_output: Callable[[], ActuatorsOutputPayload | None]


@dataclass
class ZenohStats:
    """Counters since :meth:`ZenohOut.start`."""

    session_up: bool = False
    """A Zenoh session is open (it may still have no peer or router to talk to)."""
    published: int = 0
    """Samples handed to Zenoh."""
    dropped: int = 0
    """Samples that were due while no session was open (while an attempt to open one hangs,
    nothing is due: the thread waits in it)."""
    errors: int = 0
    """Failed puts and replies, records that cannot be JSON (NaN), sources that raised."""
    reconnects: int = 0
    """Times a router or peer was connected again after all were gone (the link dropped, or
    the session was lost and reopened)."""
    peers: int = 0
    """Routers and peers the session is connected to (checked every second)."""


def _endpoint_problem(endpoint: str, *, listen: bool) -> str | None:
    """Why ``endpoint`` is not a Zenoh endpoint we accept, or None if it is one."""
    locator = endpoint.split("#", 1)[0].split("?", 1)[0]
    protocol, slash, address = locator.partition("/")
    if not slash or not address:
        return "no <protocol>/<address>"
    if protocol in OTHER_PROTOCOLS:
        return None
    if protocol not in IP_PROTOCOLS:
        return f"unknown protocol {protocol!r}"
    host, colon, port = address.rpartition(":")
    if not colon or not port.isdigit() or not port.isascii():
        return "no :<port>"
    if not (0 if listen else 1) <= int(port) <= 65535:
        return f"port {port} out of range"
    if host.startswith("[") and host.endswith("]"):
        try:
            ipaddress.IPv6Address(host[1:-1].split("%", 1)[0])
        except ValueError:
            return f"bad IPv6 address {host}"
        return None
    if all(part.isdigit() for part in host.split(".")):
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            return f"bad IPv4 address {host!r}"
        return None
    if not _HOSTNAME.fullmatch(host):
        return f"bad host {host!r}"
    return None


def _check_endpoints(name: str, endpoints: Iterable[str], *, listen: bool) -> list[str]:
    result = []
    for endpoint in endpoints:
        problem = _endpoint_problem(endpoint, listen=listen)
        if problem is not None:
            raise ConfigError(
                f"[zenoh] {name}: expected {ENDPOINT_FORM}; got {endpoint!r} ({problem})"
            )
        result.append(endpoint)
    return result


def session_config(config: ZenohConfig) -> zenoh.Config:
    """The Zenoh session configuration for ``config``: mode, connect and listen endpoints,
    multicast scouting. Endpoints left empty keep Zenoh's defaults (a peer listens on a free
    TCP port of every interface, a client looks for a router by scouting).

    Raises:
        ConfigError: an endpoint is malformed, or Zenoh refuses a value; the message names the
            ``[zenoh]`` key and what is expected.
    """
    connect = _check_endpoints("connect", config.connect, listen=False)
    listen = _check_endpoints("listen", config.listen, listen=True)
    settings: list[tuple[str, str, Any]] = [("mode", "mode", config.mode)]
    if connect:
        settings.append(("connect", "connect/endpoints", connect))
    if listen:
        settings.append(("listen", "listen/endpoints", listen))
    settings.append(("multicast_scouting", "scouting/multicast/enabled", config.multicast_scouting))
    # Annotated: zenoh's stub types the constructor with typing.Self, which is Any as Python 3.10.
    zconfig: zenoh.Config = zenoh.Config()
    for name, path, value in settings:
        try:
            zconfig.insert_json5(path, json.dumps(value))
        except zenoh.ZError as exc:
            expected = ENDPOINT_FORM if name in ("connect", "listen") else "a value Zenoh accepts"
            raise ConfigError(
                f"[zenoh] {name}: expected {expected}; got {value!r} ({exc})"
            ) from exc
    return zconfig


class _Every:
    """A fixed-rate schedule that never catches up in a burst: at most ``hz`` per second."""

    def __init__(self, hz: float, now: float) -> None:
        self.period = 1.0 / hz
        self.next = now

    def due(self, now: float) -> bool:
        if now < self.next:
            return False
        self.next += self.period
        if self.next <= now:  # woke late (or a session opening held the thread): skip, no burst
            self.next = now + self.period
        return True


class _Sparse:
    """Lets a message through at most once per interval."""

    def __init__(self, interval_s: float = WARN_INTERVAL_S) -> None:
        self._interval = interval_s
        self._next = 0.0

    def ready(self) -> bool:
        now = time.monotonic()
        if now < self._next:
            return False
        self._next = now + self._interval
        return True


class _Live:
    """One open session and what was declared on it."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.publishers: dict[str, zenoh.Publisher] = {}
        self.queryable: zenoh.Queryable[zenoh.handlers.Handler[zenoh.Query]] | None = None
        self.answering: threading.Thread | None = None  # answers the queryable's queries
        self.token: zenoh.LivelinessToken | None = None
        self.failed_puts = 0  # consecutive


class ZenohOut:
    """Publishes ESC telemetry, bridge health and actuator vectors over Zenoh.

    Use as a context manager, or call :meth:`start` and :meth:`close`.
    """

    def __init__(self, config: ZenohConfig, sources: TelemetrySources) -> None:
        """Check the configuration; nothing is opened until :meth:`start`.

        Raises:
            ConfigError: a malformed endpoint (see :func:`session_config`).
        """
        session_config(config)  # refuse a bad configuration before the bridge sends anything
        self._config = config
        self._sources = sources
        self.prefix = config.key_prefix()
        motors = range(1, len(sources.escs) + 1)
        self._telemetry_keys = [self._key(f"esc/{n}/telemetry") for n in motors]
        self._info_keys = [self._key(f"esc/{n}/info") for n in motors]
        self._status_key = self._key("esc/status")
        self._health_key = self._key("bridge/health")
        self._input_key = self._key("actuators/input")
        self._output_key = self._key("actuators/output")
        self.keys: tuple[str, ...] = (
            *self._telemetry_keys,
            *self._info_keys,
            self._status_key,
            self._health_key,
            self._input_key,
            self._output_key,
        )
        """Every key this publishes on."""
        self.alive_key = self._key("alive")
        self._stats = ZenohStats()
        self._stats_lock = threading.Lock()
        # The ESC keys' motor index (0-based) and record, by key.
        self._esc_records: dict[str, tuple[int, Callable[[EscSnapshot], Payload]]] = {
            **{key: (i, EscTelemetryPayload.of) for i, key in enumerate(self._telemetry_keys)},
            **{key: (i, EscInfoPayload.of) for i, key in enumerate(self._info_keys)},
        }
        self._sourced: dict[str, Callable[[], Payload | None]] = {
            self._health_key: sources.health,
            self._input_key: sources.actuators_input,
            self._output_key: sources.actuators_output,
        }
        self._live: _Live | None = None  # touched by the thread only
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        self._error_log = _Sparse()
        # The thread's own state.
        self._next_open = 0.0  # monotonic time of the next attempt to open a session
        self._next_poll = 0.0  # ... of the next look at how many peers the session has
        self._backoff = BACKOFF_S[0]
        self._failures = 0  # attempts to open a session since the last that succeeded
        self._open_log = _Sparse()
        self._had_peers = False  # a router or peer was connected at some time
        self._lost_peers = False  # ... and then none (or the session was lost)

    def _key(self, suffix: str) -> str:
        return f"{self.prefix}/{suffix}"

    @property
    def stats(self) -> ZenohStats:
        """A copy of the counters."""
        with self._stats_lock:
            return replace(self._stats)

    def _count(self, **increments: int) -> None:
        with self._stats_lock:
            for name, n in increments.items():
                setattr(self._stats, name, getattr(self._stats, name) + n)

    def start(self) -> None:
        """Start the background thread and return at once; a no-op when ``enabled`` is false
        or when already started.

        Raises:
            RuntimeError: after :meth:`close`.
        """
        if self._closed:
            raise RuntimeError("ZenohOut is closed")
        if self._thread is not None:
            return
        if not self._config.enabled:
            log.info("Zenoh disabled ([zenoh] enabled = false)")
            return
        self._thread = threading.Thread(target=self._run, name="zenoh-out", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Undeclare the liveliness token and close the session; returns within
        :data:`CLOSE_TIMEOUT_S` even if Zenoh hangs (the daemon thread then finishes alone).
        A second call does nothing."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        thread = self._thread
        if thread is None:
            return
        thread.join(CLOSE_TIMEOUT_S)
        if thread.is_alive():
            log.warning(
                "Zenoh did not close within %.1f s (an open or close still waits on the "
                "network); leaving it to its daemon thread",
                CLOSE_TIMEOUT_S,
            )

    def __enter__(self) -> ZenohOut:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- the thread ------------------------------------------------------------------------

    def _run(self) -> None:
        config = self._config
        now = time.monotonic()
        telemetry = _Every(config.telemetry_hz, now)
        status = _Every(config.status_hz, now)
        info = _Every(config.info_hz, now)
        health = _Every(config.health_hz, now)
        actuators = _Every(config.actuators_hz, now)
        schedules = (telemetry, status, info, health, actuators)
        self._next_open = now
        self._next_poll = now
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if self._live is not None and self._is_broken(self._live):
                    log.warning("Zenoh session lost; reopening it")
                    self._teardown()
                    self._next_open = now
                if self._live is None and now >= self._next_open:
                    self._try_open()
                    if self._stop.is_set():
                        break
                now = time.monotonic()
                if self._live is not None and now >= self._next_poll:
                    self._poll_peers(self._live)
                    self._next_poll = now + PEERS_POLL_S
                try:
                    self._publish_due(now, telemetry, status, info, health, actuators)
                except Exception:  # a fault here must not end publishing
                    self._count(errors=1)
                    if self._error_log.ready():
                        log.exception("Zenoh: publishing failed")
                wake = min(s.next for s in schedules)
                wake = min(wake, self._next_open if self._live is None else self._next_poll)
                self._stop.wait(max(0.0, wake - time.monotonic()))
        finally:
            self._teardown()

    def _try_open(self) -> None:
        try:
            self._open()
        except Exception as exc:  # noqa: BLE001 - whatever Zenoh raises, run without it
            self._failures += 1
            wait = self._backoff * random.uniform(1 - BACKOFF_JITTER, 1 + BACKOFF_JITTER)
            self._backoff = min(self._backoff * 2, BACKOFF_S[1])
            self._next_open = time.monotonic() + wait
            if self._failures == 1:
                self._open_log.ready()
                log.warning(
                    "Zenoh: cannot open a session (%s); the bridge runs without Zenoh and "
                    "keeps trying in the background",
                    exc,
                )
            elif self._open_log.ready():
                log.warning("Zenoh: still no session after %d attempts (%s)", self._failures, exc)
            else:
                log.debug("Zenoh: open attempt %d failed: %s", self._failures, exc)
            return
        log.info(
            "Zenoh session open (%s mode), publishing under %s%s",
            self._config.mode,
            self.prefix,
            f" after {self._failures + 1} attempts" if self._failures else "",
        )
        self._failures = 0
        self._backoff = BACKOFF_S[0]
        self._next_poll = time.monotonic()

    def _poll_peers(self, live: _Live) -> None:
        info = live.session.info
        peers = len(info.routers_zid()) + len(info.peers_zid())
        with self._stats_lock:
            self._stats.peers = peers
        if peers:
            if self._lost_peers:
                self._count(reconnects=1)
                log.info("Zenoh: connected again (%d routers and peers)", peers)
            self._had_peers, self._lost_peers = True, False
        elif self._had_peers and not self._lost_peers:
            self._lost_peers = True
            log.info("Zenoh: no router or peer connected any more")

    def _open(self) -> None:
        session = zenoh.open(session_config(self._config))
        live = _Live(session)
        try:
            for key in self.keys:
                live.publishers[key] = session.declare_publisher(
                    key,
                    encoding=ENCODING,
                    congestion_control=zenoh.CongestionControl.DROP,
                    priority=PRIORITY,
                    express=False,
                )
            # A ring channel never holds up zenoh's own threads when answering falls behind.
            live.queryable = session.declare_queryable(
                self._key("**"), zenoh.handlers.RingChannel(QUERY_QUEUE), complete=True
            )
            live.token = session.liveliness().declare_token(self.alive_key)
        except BaseException:
            session.close()  # type: ignore[no-untyped-call]
            raise
        live.answering = threading.Thread(
            target=self._answer_queries, args=(live.queryable,), name="zenoh-queries", daemon=True
        )
        live.answering.start()
        self._live = live
        with self._stats_lock:
            self._stats.session_up = True

    def _is_broken(self, live: _Live) -> bool:
        return live.failed_puts >= BROKEN_AFTER_ERRORS or live.session.is_closed()

    def _teardown(self) -> None:
        live, self._live = self._live, None
        with self._stats_lock:
            self._stats.session_up = False
            self._stats.peers = 0
        if live is None:
            return
        self._lost_peers = self._lost_peers or self._had_peers
        for name, entity in (("liveliness token", live.token), ("queryable", live.queryable)):
            if entity is None:
                continue
            try:
                entity.undeclare()  # type: ignore[no-untyped-call]
            except zenoh.ZError as exc:
                log.debug("Zenoh: undeclaring the %s failed: %s", name, exc)
        if live.answering is not None:
            live.answering.join(CLOSE_TIMEOUT_S)  # it ends once the queryable is undeclared
            if live.answering.is_alive():
                log.warning("Zenoh: the thread answering queries did not end")
        try:
            live.session.close()  # type: ignore[no-untyped-call]
        except zenoh.ZError as exc:
            log.debug("Zenoh: closing the session failed: %s", exc)

    def _publish_due(
        self,
        now: float,
        telemetry: _Every,
        status: _Every,
        info: _Every,
        health: _Every,
        actuators: _Every,
    ) -> None:
        due: list[str] = []
        if telemetry.due(now):
            due += self._telemetry_keys
        if info.due(now):
            due += self._info_keys
        if status.due(now):
            due.append(self._status_key)
        if health.due(now):
            due.append(self._health_key)
        if actuators.due(now):
            due += (self._input_key, self._output_key)
        live = self._live
        if live is None:
            self._count(dropped=len(due))
            return
        # Making and encoding a record is most of the cost of a sample, and nobody may be
        # listening (a vehicle whose fleet is not watched): only what a subscriber matches is
        # made, encoded and sent.
        wanted = [key for key in due if _has_subscribers(live.publishers[key])]
        for key, record in self._records(wanted):
            self._publish(live, key, record)

    def _records(self, keys: Sequence[str]) -> list[tuple[str, Payload]]:
        """The current record of each of ``keys``, stamped now; a source with nothing yet (or
        failing) gives none. The ESCs' state is read once for all."""
        snapshots: Sequence[EscSnapshot] = ()
        if any(key in self._esc_records or key == self._status_key for key in keys):
            snapshots = self._sources.escs.snapshot(time.monotonic_ns())
        now_ms = _now_ms()
        records: list[tuple[str, Payload]] = []
        for key in keys:
            record: Payload | None
            esc = self._esc_records.get(key)
            if esc is not None:
                record = esc[1](snapshots[esc[0]])
            elif key == self._status_key:
                record = EscStatusPayload.of(snapshots, now_ms)
            else:
                record = self._call(self._sourced[key])
            if record is not None:
                records.append(
                    (key, record if record.time_unix_ms is not None else record.stamped(now_ms))
                )
        return records

    def _call(self, source: Callable[[], Payload | None]) -> Payload | None:
        try:
            return source()
        except Exception:  # a faulty source must not stop the others
            self._count(errors=1)
            if self._error_log.ready():
                log.exception("Zenoh: telemetry source %r failed", source)
            return None

    def _publish(self, live: _Live, key: str, record: Payload) -> None:
        payload = self._encode(key, record)
        if payload is None:
            return
        try:
            live.publishers[key].put(payload)
        except zenoh.ZError as exc:
            live.failed_puts += 1
            self._count(errors=1)
            if self._error_log.ready():
                log.warning("Zenoh: publishing %s failed: %s", key, exc)
            return
        live.failed_puts = 0
        self._count(published=1)

    def _encode(self, key: str, value: Payload) -> bytes | None:
        """``value``'s JSON, or None (counted, logged now and then) when it has none (NaN)."""
        try:
            return value.encode()
        except (TypeError, ValueError) as exc:
            self._count(errors=1)
            if self._error_log.ready():
                log.error("Zenoh: %s is not JSON (%s): %r", key, exc, value)
            return None

    def _answer_queries(
        self, queryable: zenoh.Queryable[zenoh.handlers.Handler[zenoh.Query]]
    ) -> None:
        """The body of the thread answering queries: until the queryable is undeclared."""
        for query in queryable:
            try:
                self._answer(query)
            except Exception:  # a fault here must not end answering
                self._count(errors=1)
                if self._error_log.ready():
                    log.exception("Zenoh: answering a query failed")

    def _answer(self, query: zenoh.Query) -> None:
        # The records are made from the sources (cheap, thread-safe), never waiting on the
        # publishing thread.
        with query:
            selector = query.key_expr
            asked = [key for key in self.keys if selector.intersects(key)]
            for key, record in self._records(asked):
                try:
                    payload = self._encode(key, record)
                    if payload is not None:
                        query.reply(key, payload, encoding=ENCODING)
                except zenoh.ZError as exc:
                    self._count(errors=1)
                    if self._error_log.ready():
                        log.warning("Zenoh: replying to %s failed: %s", selector, exc)


def _has_subscribers(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches ``publisher``'s key. (zenoh's stub types
    ``matching_status`` as a bool; it is a ``MatchingStatus``, whose ``matching`` says.)"""
    status: Any = publisher.matching_status
    return bool(status.matching)


def _now_ms() -> int:
    return time.time_ns() // 1_000_000
