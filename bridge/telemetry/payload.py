"""The Zenoh schema: one typed record per key the bridge publishes, encoded and decoded here only.

=========================  ==========================
key (under the prefix)     record
=========================  ==========================
``esc/<n>/telemetry``      :class:`EscTelemetryPayload`
``esc/<n>/info``           :class:`EscInfoPayload`
``esc/status``             :class:`EscStatusPayload`
``bridge/health``          :class:`HealthPayload`
``actuators/input``        :class:`ActuatorsInputPayload`
``actuators/output``       :class:`ActuatorsOutputPayload`
=========================  ==========================

A record's fields are the JSON object's names, in the order published (docs/telemetry.md);
nested records are nested objects, tuples are arrays. ``encode()`` gives the bytes published
(compact JSON, UTF-8; NaN and infinities refused); ``Record.decode(payload)`` gives the record
back or raises :class:`~bridge.errors.PayloadError` naming the key and the field. A reader on the
network counts such a payload and drops it. Names a reader does not know are ignored, so a newer
bridge can add some.

Pure: no I/O, no clock, no configuration. Who fills ``time_unix_ms`` is the publisher, when
it publishes (:mod:`bridge.telemetry.zenoh_out`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar

from bridge._compat import Self
from bridge.errors import PayloadError
from bridge.telemetry.json_schema import to_json
from bridge.telemetry.state import EscSnapshot

_OMIT_NONE = {"omit_none": True}
"""A field's metadata: left out of the object when None (and absent means None)."""


class Payload:
    """What every record of this module has: its key, :meth:`encode`, :meth:`decode`."""

    KEY: ClassVar[str]
    """The key this record is published on (``<n>``: a motor number), for error messages."""
    time_unix_ms: int | None
    """When it was published (wall clock, ms since 1970); None until the publisher stamps it."""

    def encode(self) -> bytes:
        """The JSON published for this record.

        Raises:
            ValueError: a number is NaN or infinite (JSON has neither).
        """
        return json.dumps(to_json(self), separators=(",", ":"), allow_nan=False).encode()

    @classmethod
    def decode(cls, payload: bytes) -> Self:
        """The record a payload of :attr:`KEY` carries.

        Raises:
            PayloadError: not JSON, or a field missing or of the wrong type (both named).
        """
        try:
            value = json.loads(payload)
        except (UnicodeDecodeError, ValueError) as exc:
            raise PayloadError(f"{cls.KEY}: not JSON ({exc})") from exc
        record: Self = _record(cls, value, cls.KEY, "")
        return record

    def stamped(self, time_unix_ms: int) -> Self:
        """This record with ``time_unix_ms`` set (every key's record has one)."""
        stamped: Self = dataclasses.replace(self, time_unix_ms=time_unix_ms)  # type: ignore[type-var]
        return stamped


@dataclass(frozen=True, kw_only=True)
class Temperatures:
    """``temperature_c`` of an ESC's telemetry, °C each; None: not reported."""

    mos: float | None
    capacitor: float | None
    motor: float | None
    mcu: float | None


@dataclass(frozen=True, kw_only=True)
class EscTelemetryPayload(Payload):
    """``esc/<n>/telemetry``, and each of ``esc/status``'s ``escs``: one ESC's fast data."""

    KEY: ClassVar[str] = "esc/<n>/telemetry"

    time_unix_ms: int | None = field(default=None, metadata=_OMIT_NONE)
    """None inside ``esc/status`` (which has its own)."""
    motor: int
    node_id: int
    online: bool
    age_ms: float | None
    rpm: int | None
    voltage_v: float | None
    current_a: float | None
    motor_current_a: float | None
    throttle: float | None
    temperature_c: Temperatures
    status: int | None
    failure_flags: int
    consumed_mah: float
    command: float | None
    command_unit: str

    @classmethod
    def of(cls, snap: EscSnapshot) -> EscTelemetryPayload:
        """The fast data of a snapshot (``age_ms`` to 0.1 ms, ``consumed_mah`` to 0.001)."""
        return cls(
            motor=snap.motor,
            node_id=snap.node_id,
            online=snap.online,
            age_ms=None if snap.age_ms is None else round(snap.age_ms, 1),
            rpm=snap.rpm,
            voltage_v=snap.voltage_v,
            current_a=snap.current_a,
            motor_current_a=snap.motor_current_a,
            throttle=snap.throttle,
            temperature_c=Temperatures(
                mos=snap.mos_temp_c,
                capacitor=snap.capacitor_temp_c,
                motor=snap.motor_temp_c,
                mcu=snap.mcu_temp_c,
            ),
            status=snap.status,
            failure_flags=snap.failure_flags,
            consumed_mah=round(snap.consumed_mah, 3),
            command=snap.command,
            command_unit=snap.command_unit,
        )


@dataclass(frozen=True, kw_only=True)
class EscInfoPayload(Payload):
    """``esc/<n>/info``: one ESC's slow data."""

    KEY: ClassVar[str] = "esc/<n>/info"

    time_unix_ms: int | None = None
    motor: int
    node_id: int
    online: bool
    frames: int
    errors: int
    failure_flags: int
    counters: dict[str, int]

    @classmethod
    def of(cls, snap: EscSnapshot) -> EscInfoPayload:
        return cls(
            motor=snap.motor,
            node_id=snap.node_id,
            online=snap.online,
            frames=snap.frames,
            errors=snap.errors,
            failure_flags=snap.failure_flags,
            counters=dict(snap.counters),
        )


@dataclass(frozen=True, kw_only=True)
class EscStatusPayload(Payload):
    """``esc/status``: every ESC in one message, in motor order."""

    KEY: ClassVar[str] = "esc/status"

    time_unix_ms: int | None = None
    count: int
    online: int
    escs: tuple[EscTelemetryPayload, ...]

    @classmethod
    def of(cls, snapshots: typing.Sequence[EscSnapshot], time_unix_ms: int) -> EscStatusPayload:
        return cls(
            time_unix_ms=time_unix_ms,
            count=len(snapshots),
            online=sum(1 for snap in snapshots if snap.online),
            escs=tuple(EscTelemetryPayload.of(snap) for snap in snapshots),
        )


@dataclass(frozen=True, kw_only=True)
class MotorTestHealth:
    """``motor_test`` of the health: the running motor test."""

    motor: int | None
    """The motor spinning now; None between two motors of a sequence."""
    motors: tuple[int, ...]
    throttle: float
    remaining_s: float


@dataclass(frozen=True, kw_only=True)
class OutputHealth:
    """``output`` of the health: the control loop's sending."""

    rate_hz: float
    configured_rate_hz: int
    ticks: int
    frames_sent: int
    send_errors: int
    overruns: int
    tick_errors: int
    bus_reopens: int
    realtime: bool


@dataclass(frozen=True, kw_only=True)
class InputHealth:
    """``input`` of the health: the autopilot's motor outputs as the loop took them."""

    rate_hz: float
    outputs: int
    messages: int
    bad_data: int
    invalid: int
    mixer_errors: int
    age_ms: float
    out_of_order: int
    unsigned: int
    other_address: int


@dataclass(frozen=True, kw_only=True)
class LinkHealth:
    """``link`` of the health: the autopilot link as the loop, its owner, keeps it."""

    relay_dropped: int
    sent: int
    send_dropped: int
    reconnects: int


@dataclass(frozen=True, kw_only=True)
class CanRxHealth:
    """``can_rx`` of the health: the CAN reader's counters."""

    frames: int
    telemetry: int
    malformed: int
    read_errors: int
    kernel_drops: int | None
    unknown_esc_frames: int


@dataclass(frozen=True, kw_only=True)
class CanBusHealth:
    """``can_bus`` of the health: the bus as the loop's frames and the controller find it."""

    tx_state: str
    """How the loop's frames leave: ``moving``, ``stuck``, ``down``, ``gone``."""
    ticks_held: int
    """Ticks not sent: frames of an earlier tick were still in the kernel."""
    tx_probes: int
    stuck: int
    """Times the loop's frames stopped leaving for longer than the input timeout."""
    down: int
    gone: int
    controller_state: str
    """As the controller's error frames last said: ``error_active``, ``error_warning``,
    ``error_passive``, ``bus_off``."""
    error_frames: int
    error_warning: int
    error_passive: int
    bus_off: int
    restarts: int
    receive_overflows: int
    """Times the controller's own receive buffer overflowed."""
    reader_reopens: int


@dataclass(frozen=True, kw_only=True)
class ZenohHealth:
    """``zenoh`` of the health: the publisher's counters."""

    session_up: bool
    published: int
    dropped: int


@dataclass(frozen=True, kw_only=True)
class HealthPayload(Payload):
    """``bridge/health``: the bridge's state and counters."""

    KEY: ClassVar[str] = "bridge/health"

    time_unix_ms: int | None = None
    state: str
    failsafe: bool
    armed: bool
    motor_test: MotorTestHealth | None
    output: OutputHealth
    input: InputHealth
    link: LinkHealth
    escs_online: int
    can_rx: CanRxHealth
    can_bus: CanBusHealth | None = field(default=None, metadata=_OMIT_NONE)
    """None (left out) from a bridge older than the record."""
    zenoh: ZenohHealth | None = field(default=None, metadata=_OMIT_NONE)
    """None (left out) when Zenoh is off."""


@dataclass(frozen=True, kw_only=True)
class ActuatorsInputPayload(Payload):
    """``actuators/input``: the autopilot's newest outputs (the present channels) and their mix."""

    KEY: ClassVar[str] = "actuators/input"

    time_unix_ms: int | None = None
    source: str
    armed: bool
    age_ms: float
    channels: dict[str, float]
    mixed: tuple[float, ...] | None


@dataclass(frozen=True, kw_only=True)
class CommandOut:
    """One ESC's entry in ``actuators/output``: its last command on the bus, read back."""

    motor: int
    node_id: int
    value: float | None
    unit: str


@dataclass(frozen=True, kw_only=True)
class ActuatorsOutputPayload(Payload):
    """``actuators/output``: the output loop's state and the last command of each ESC."""

    KEY: ClassVar[str] = "actuators/output"

    time_unix_ms: int | None = None
    state: str
    commands: tuple[CommandOut, ...]


RECORDS: tuple[type[Payload], ...] = (
    EscTelemetryPayload,
    EscInfoPayload,
    EscStatusPayload,
    HealthPayload,
    ActuatorsInputPayload,
    ActuatorsOutputPayload,
)
"""Every key's record."""


# -- encoding and decoding, driven by the fields' types ---------------------------------------


_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    hints = _HINTS.get(cls)
    if hints is None:
        hints = _HINTS[cls] = typing.get_type_hints(cls)
    return hints


def _record(cls: type[Any], value: object, key: str, path: str) -> Any:
    if not isinstance(value, dict):
        where = f"field {path}" if path else "payload"
        raise PayloadError(f"{key}: {where}: expected an object, got {_show(value)}")
    hints = _hints(cls)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        where = f"{path}.{f.name}" if path else f.name
        if f.name not in value:
            if f.default is dataclasses.MISSING:
                raise PayloadError(f"{key}: field {where} missing")
            continue
        kwargs[f.name] = _value(hints[f.name], value[f.name], key, where)
    return cls(**kwargs)


def _value(kind: Any, value: object, key: str, where: str) -> Any:
    origin = typing.get_origin(kind)
    if origin is types.UnionType or origin is typing.Union:
        options = [a for a in typing.get_args(kind) if a is not type(None)]
        if value is None:
            return None
        (kind,) = options  # every optional field here is "one type or None"
        origin = typing.get_origin(kind)
    if isinstance(kind, type) and dataclasses.is_dataclass(kind):
        return _record(kind, value, key, where)
    if origin is tuple:
        if not isinstance(value, list):
            raise _wrong(key, where, "an array", value)
        item = typing.get_args(kind)[0]
        return tuple(_value(item, v, key, f"{where}[{i}]") for i, v in enumerate(value))
    if origin is dict:
        if not isinstance(value, dict):
            raise _wrong(key, where, "an object", value)
        item = typing.get_args(kind)[1]
        return {name: _value(item, v, key, f"{where}.{name}") for name, v in value.items()}
    if kind is bool:
        if not isinstance(value, bool):
            raise _wrong(key, where, "true or false", value)
    elif kind is int:
        if not isinstance(value, int) or isinstance(value, bool):
            raise _wrong(key, where, "an integer", value)
    elif kind is float:
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise _wrong(key, where, "a number", value)
        if not math.isfinite(value):
            raise _wrong(key, where, "a finite number", value)
    elif kind is str:
        if not isinstance(value, str):
            raise _wrong(key, where, "a string", value)
    else:  # pragma: no cover - a field type this module does not decode
        raise TypeError(f"{key}: field {where}: no decoder for {kind!r}")
    return value


def _wrong(key: str, where: str, expected: str, value: object) -> PayloadError:
    return PayloadError(f"{key}: field {where}: expected {expected}, got {_show(value)}")


def _show(value: object) -> str:
    text = json.dumps(value) if not isinstance(value, float) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."
