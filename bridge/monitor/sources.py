"""Where the monitor's telemetry comes from: a bridge over Zenoh, or the CAN bus itself.

Both sources give the same thing, :meth:`vehicles`: the latest ESC telemetry records per vehicle
(:class:`~bridge.monitor.view.VehicleState`), taken whenever the screen is redrawn. Over Zenoh,
each payload is decoded by :mod:`bridge.telemetry.payload`; one that is not what its key
carries is counted and dropped. A bridge is known from its first ``esc/status`` or from its
liveliness token (``<prefix>/alive``), whichever comes first, and is never forgotten: when it
goes quiet or its token goes away it stays, stale. Neither source ever sends anything to the
ESCs: the CAN source opens the bus and only reads it.

Only :class:`ZenohSource` imports zenoh (through :mod:`bridge.telemetry.zenoh_out`), and only
when opened.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass, field, replace
from types import TracebackType
from typing import TYPE_CHECKING, Protocol

from bridge._compat import Self
from bridge.can_io import check_interface, open_bus
from bridge.config import BridgeConfig, ZenohConfig
from bridge.errors import ConfigError, LinkError, PayloadError
from bridge.escs import registry
from bridge.monitor.view import EscRow, VehicleState
from bridge.telemetry.for_config import esc_table
from bridge.telemetry.payload import (
    EscInfoPayload,
    EscStatusPayload,
    EscTelemetryPayload,
    HealthPayload,
)
from bridge.telemetry.reader import CanReader

if TYPE_CHECKING:
    import can
    import zenoh

log = logging.getLogger(__name__)

DEFAULT_PREFIX = "esc-bridge/*"
"""Every vehicle's bridge (a bridge publishes under esc-bridge/<vehicle> by default)."""
STALE_AFTER_S = 1.0
"""A vehicle with no ``esc/status`` for longer than this is shown as stale."""
STATUS_SUFFIX = "esc/status"
INFO_SUFFIX = "esc/*/info"
HEALTH_SUFFIX = "bridge/health"
ALIVE_SUFFIX = "alive"
_BRIDGE_PREFIX = "esc-bridge/"
# Endpoints a bridge listens on that a monitor on the same host reaches through loopback.
_WILDCARD_HOSTS = {"0.0.0.0": "127.0.0.1", "[::]": "[::1]"}


class Source(Protocol):
    """What the monitor reads: the latest telemetry per vehicle."""

    @property
    def where(self) -> str:
        """Where the data comes from, for "waiting for esc-bridge on ..."."""
        ...

    def vehicles(self) -> list[VehicleState]:
        """The latest state of every vehicle heard from so far (none: still waiting)."""
        ...

    def close(self) -> None: ...


def vehicle_name(key_prefix: str) -> str:
    """The vehicle's name as shown: its key prefix without the leading ``esc-bridge/``."""
    if key_prefix.startswith(_BRIDGE_PREFIX) and len(key_prefix) > len(_BRIDGE_PREFIX):
        return key_prefix[len(_BRIDGE_PREFIX) :]
    return key_prefix


def check_prefix(prefix: str) -> str | None:
    """What is wrong with a key prefix to subscribe under, or None. Zenoh key expressions are
    '/'-separated non-empty chunks without ``?#$``; ``*`` and ``**`` stand for chunks."""
    if not prefix or prefix.startswith("/") or prefix.endswith("/"):
        return "a key expression without leading or trailing '/', e.g. esc-bridge/drone1"
    for chunk in prefix.split("/"):
        if not chunk:
            return "no empty chunk ('//')"
        if any(c in chunk for c in "?#$ "):
            return "no '?', '#', '$' or spaces"
        if "*" in chunk and chunk not in ("*", "**"):
            return "'*' and '**' only as whole chunks (esc-bridge/*)"
    return None


def prefix_of(config: ZenohConfig) -> str:
    """The prefix to watch for a bridge configured with ``config``: its prefix or vehicle when
    the file names one, else every vehicle (the bridge's default vehicle is *its* host name,
    which the monitor cannot know)."""
    if config.prefix or config.vehicle:
        return config.key_prefix()
    return DEFAULT_PREFIX


def monitor_zenoh_config(bridge: ZenohConfig) -> ZenohConfig:
    """The monitor's session settings from a bridge's ``[zenoh]``: the same mode, routers and
    scouting, and a connection to each endpoint the bridge listens on (a wildcard address
    becomes loopback) instead of listening there too, which would collide with the bridge."""
    listened = tuple(_loopback(endpoint) for endpoint in bridge.listen)
    connect = bridge.connect + tuple(e for e in listened if e not in bridge.connect)
    mode = "peer" if bridge.mode == "router" else bridge.mode
    return replace(bridge, mode=mode, connect=connect, listen=())


def _loopback(endpoint: str) -> str:
    for wildcard, loopback in _WILDCARD_HOSTS.items():
        proto, sep, rest = endpoint.partition("/")
        if sep and rest.startswith(wildcard + ":"):
            return f"{proto}/{loopback}{rest[len(wildcard) :]}"
    return endpoint


@dataclass
class _Vehicle:
    escs: tuple[EscTelemetryPayload, ...] = ()
    received: float | None = None  # monotonic time of the last esc/status
    info: dict[int, EscInfoPayload] = field(default_factory=dict)
    health: HealthPayload | None = None
    alive: bool | None = None  # its liveliness token: there, gone, never seen
    gone_at: float = 0.0  # monotonic time its token last went away

    def row(self, esc: EscTelemetryPayload) -> EscRow:
        info = self.info.get(esc.motor)
        return EscRow(esc) if info is None else EscRow(esc, info.frames, info.errors)


class ZenohSource:
    """Subscribes to ``<prefix>/esc/status`` (and ``esc/*/info`` for frame and error counts,
    ``bridge/health`` for the bridge's state, the ``alive`` liveliness tokens for bridges
    coming and going) with a Zenoh session of its own; :meth:`vehicles` gives the latest per
    vehicle."""

    def __init__(self, prefix: str, stale_after_s: float = STALE_AFTER_S) -> None:
        """Not yet subscribed: :meth:`open` builds and starts one."""
        self.prefix = prefix
        self._stale_after_s = stale_after_s
        self._lock = threading.Lock()
        self._vehicles: dict[str, _Vehicle] = {}
        self._session: zenoh.Session | None = None
        self.bad_messages = 0
        """Samples on our keys that were not the JSON expected."""

    @property
    def where(self) -> str:
        return self.prefix

    @classmethod
    def open(cls, config: ZenohConfig, prefix: str = DEFAULT_PREFIX) -> ZenohSource:
        """Open a session with ``config``'s mode, endpoints and scouting and subscribe.

        Raises:
            ConfigError: the prefix is not a key expression, or an endpoint is malformed.
            LinkError: Zenoh cannot open the session (an endpoint cannot be listened on, ...).
        """
        problem = check_prefix(prefix)
        if problem is not None:
            raise ConfigError(f"prefix {prefix!r}: expected {problem}")
        import zenoh  # only the Zenoh source needs it

        from bridge.telemetry.zenoh_out import session_config

        source = cls(prefix)
        settings = session_config(config)
        try:
            session = zenoh.open(settings)
        except zenoh.ZError as exc:
            raise LinkError(f"cannot open a Zenoh session: {_without_sources(exc)}") from exc
        source._session = session
        try:
            session.declare_subscriber(f"{prefix}/{STATUS_SUFFIX}", source._on_status)
            session.declare_subscriber(f"{prefix}/{INFO_SUFFIX}", source._on_info)
            session.declare_subscriber(f"{prefix}/{HEALTH_SUFFIX}", source._on_health)
            # history: the tokens already there when the monitor starts come at once.
            session.liveliness().declare_subscriber(
                f"{prefix}/{ALIVE_SUFFIX}", source._on_alive, history=True
            )
        except zenoh.ZError as exc:
            source.close()
            raise ConfigError(f"prefix {prefix!r}: Zenoh refuses it: {exc}") from exc
        return source

    def vehicles(self, now: float | None = None) -> list[VehicleState]:
        now = time.monotonic() if now is None else now
        with self._lock:
            states: list[VehicleState] = []
            for name, vehicle in sorted(self._vehicles.items()):
                if vehicle.received is None and vehicle.alive is None:  # esc/<n>/info only
                    continue
                age = None if vehicle.received is None else now - vehicle.received
                # Gone: its token went away and no esc/status came since (data that still
                # flows outweighs a token lost on the way).
                gone = vehicle.alive is False and (
                    vehicle.received is None or vehicle.received <= vehicle.gone_at
                )
                stale = gone or (age is not None and age > self._stale_after_s)
                # A stale vehicle's records keep ageing: each is as old as when it was
                # published plus the time since (a fresh one's is at most a period behind).
                escs = tuple(
                    vehicle.row(_aged(esc, age) if stale and age is not None else esc)
                    for esc in vehicle.escs
                )
                states.append(
                    VehicleState(
                        vehicle_name(name),
                        escs,
                        stale,
                        age,
                        health=vehicle.health,
                        alive=vehicle.alive,
                    )
                )
            bad = self.bad_messages
        if bad and states:
            states[-1] = replace(states[-1], note=f"{bad} malformed messages ignored")
        return states

    def close(self) -> None:
        """Undeclare everything and close the session; a second call does nothing."""
        session, self._session = self._session, None
        if session is not None:
            session.close()  # type: ignore[no-untyped-call]

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- Zenoh's threads ----------------------------------------------------------------------

    def _on_status(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            status = EscStatusPayload.decode(sample.payload.to_bytes())
        except PayloadError as exc:
            self._count_bad(exc)
            return
        now = time.monotonic()
        with self._lock:
            vehicle = self._vehicles.setdefault(_key_prefix(key, STATUS_SUFFIX), _Vehicle())
            vehicle.escs = status.escs
            vehicle.received = now

    def _on_info(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            info = EscInfoPayload.decode(sample.payload.to_bytes())
        except PayloadError as exc:
            self._count_bad(exc)
            return
        with self._lock:
            vehicle = self._vehicles.setdefault(key.rsplit("/esc/", 1)[0], _Vehicle())
            vehicle.info[info.motor] = info

    def _on_health(self, sample: zenoh.Sample) -> None:
        try:
            health = HealthPayload.decode(sample.payload.to_bytes())
        except PayloadError as exc:
            self._count_bad(exc)
            return
        with self._lock:
            vehicle = self._vehicles.setdefault(
                _key_prefix(str(sample.key_expr), HEALTH_SUFFIX), _Vehicle()
            )
            vehicle.health = health

    def _on_alive(self, sample: zenoh.Sample) -> None:
        import zenoh

        alive = sample.kind == zenoh.SampleKind.PUT  # DELETE: the token went away
        now = time.monotonic()
        with self._lock:
            vehicle = self._vehicles.setdefault(
                _key_prefix(str(sample.key_expr), ALIVE_SUFFIX), _Vehicle()
            )
            vehicle.alive = alive
            if not alive:
                vehicle.gone_at = now

    def _count_bad(self, exc: PayloadError) -> None:
        with self._lock:
            self.bad_messages += 1
        log.debug("dropped a payload: %s", exc)


def _aged(esc: EscTelemetryPayload, seconds: float) -> EscTelemetryPayload:
    if esc.age_ms is None:
        return esc
    return replace(esc, age_ms=esc.age_ms + seconds * 1000.0)


def _without_sources(exc: Exception) -> str:
    # Zenoh's errors name the Rust source file of each cause; the user needs only the causes.
    return re.sub(r" at \S+\.rs:\d+\.?", "", str(exc)).strip()


def _key_prefix(key: str, suffix: str) -> str:
    return key[: -len(suffix) - 1] if key.endswith("/" + suffix) else key


class CanSource:
    """Reads the CAN bus directly (never sends) into an :class:`EscTable` through a
    :class:`CanReader`; :meth:`vehicles` gives one vehicle, named after the bus."""

    def __init__(self, config: BridgeConfig, bus: can.BusABC) -> None:
        """Use :meth:`open`, which opens the bus and starts reading."""
        # The monitor only listens: an ESC that reports "no command" is idle, not failing.
        self.table = esc_table(config, commanded=False)
        self._bus: can.BusABC | None = bus
        self.reader = CanReader(bus, self.table, registry.family(config.output.protocol))
        self._name = f"{config.can.interface}:{config.can.channel}"

    @property
    def where(self) -> str:
        return self._name

    @classmethod
    def open(cls, config: BridgeConfig) -> CanSource:
        """Open ``config.can`` and start reading; ``config.escs.ids`` names the ESCs, motor 1
        first (it must not be empty).

        Raises:
            ConfigError: the interface is unknown, or the ESC lists do not fit together.
            LinkError: the bus cannot be opened.
        """
        if not config.escs.ids:
            raise ConfigError(f"{config.source}: no ESCs to show; expected [escs] ids")
        check_interface(config.can, config.source)
        bus = open_bus(config.can, config.bitrate)
        try:
            source = cls(config, bus)
        except ValueError as exc:
            bus.shutdown()
            raise ConfigError(f"{config.source}: {exc}") from exc
        source.reader.start()
        return source

    def vehicles(self) -> list[VehicleState]:
        stats = self.reader.stats
        escs = tuple(
            EscRow(EscTelemetryPayload.of(snap), snap.frames, snap.errors)
            for snap in self.table.snapshot(time.monotonic_ns())
        )
        note = f"{stats.frames} frames read, {stats.malformed} malformed"
        if stats.read_errors:
            note += f", {stats.read_errors} read errors"
        return [VehicleState(self._name, escs, note=note)]

    def close(self) -> None:
        """Stop reading and shut the bus down; a second call does nothing."""
        bus, self._bus = self._bus, None
        if bus is not None:
            self.reader.close()
            bus.shutdown()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
