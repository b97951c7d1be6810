"""The MCAP recording's channels: their topics, their JSON Schemas, and the message each record
makes. docs/telemetry.md lists them.

=========================  ========================  ==========================================
topic                      schema                    one message per
=========================  ========================  ==========================================
``/esc/<n>/telemetry``     ``esc_bridge.EscTelemetry``  telemetry frame of motor *n*'s ESC: its
                                                     state after it, as Zenoh's
                                                     ``esc/<n>/telemetry``
``/bridge/commands``       ``esc_bridge.CommandsSent``  commands the bridge sent: every ESC's
                                                     last command, in motor order
``/autopilot/outputs``     ``esc_bridge.MotorOutputs``  motor-output message from the autopilot
``/autopilot/heartbeat``   ``esc_bridge.AutopilotHeartbeat``  HEARTBEAT from the autopilot
``/bridge/state``          ``esc_bridge.BridgeState``   state the output loop entered
``/mavlink/statustext``    ``foxglove.Log``             STATUSTEXT (anyone's, the bridge's too)
``/bridge/log``            ``foxglove.Log``             log line of the bridge's main process
=========================  ========================  ==========================================

Every message is one JSON object (message encoding ``json``) and every schema a JSON Schema
(schema encoding ``jsonschema``), made from the record's own fields
(:mod:`bridge.telemetry.json_schema`), except ``foxglove.Log``, whose shape is Foxglove's, so that
its Log panel shows those topics.

Pure: no I/O, no clock.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

from bridge.mavlink.traffic import AutopilotHeartbeat, MotorOutputs, StatusText
from bridge.telemetry.json_schema import DIALECT, record_schema, to_json
from bridge.telemetry.payload import CommandOut, EscTelemetryPayload
from bridge.telemetry.state import EscSnapshot, LastCommand

MESSAGE_ENCODING: Final = "json"
SCHEMA_ENCODING: Final = "jsonschema"
METADATA_NAME: Final = "esc-bridge"
"""The MCAP metadata record that says what was recorded (:func:`metadata`)."""

COMMANDS_TOPIC: Final = "/bridge/commands"
OUTPUTS_TOPIC: Final = "/autopilot/outputs"
HEARTBEAT_TOPIC: Final = "/autopilot/heartbeat"
STATE_TOPIC: Final = "/bridge/state"
STATUSTEXT_TOPIC: Final = "/mavlink/statustext"
LOG_TOPIC: Final = "/bridge/log"
ESC_TOPIC_PREFIX: Final = "/esc/"
ESC_TOPIC_SUFFIX: Final = "/telemetry"

# foxglove.Log's levels.
LOG_UNKNOWN: Final = 0
LOG_DEBUG: Final = 1
LOG_INFO: Final = 2
LOG_WARNING: Final = 3
LOG_ERROR: Final = 4
LOG_FATAL: Final = 5


def esc_topic(motor: int) -> str:
    """The topic of motor ``motor``'s ESC telemetry (1-based, the mixer's output order)."""
    return f"{ESC_TOPIC_PREFIX}{motor}{ESC_TOPIC_SUFFIX}"


@dataclass(frozen=True, kw_only=True)
class CommandsSent:
    """The commands the bridge sent: every ESC's last command, in motor order (``commands[i]``
    is motor i + 1's), as Zenoh's ``actuators/output`` has them."""

    commands: tuple[CommandOut, ...]


@dataclass(frozen=True, kw_only=True)
class BridgeState:
    """A state the bridge's output loop entered, as it reports it by STATUSTEXT."""

    state: str
    """As ``bridge/health`` on Zenoh names it: no_input, disarmed, running, stale, ..."""
    failsafe: bool
    """True unless running or in a motor test."""
    severity: int
    """The STATUSTEXT's MAV_SEVERITY."""
    text: str


def _log_schema() -> dict[str, Any]:
    time = {
        "type": "object",
        "properties": {
            "sec": {"type": "integer", "minimum": 0},
            "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
        },
        "required": ["sec", "nsec"],
    }
    return {
        "$schema": DIALECT,
        "title": "foxglove.Log",
        "description": "A log message (Foxglove's Log).",
        "type": "object",
        "properties": {
            "timestamp": time,
            "level": {"type": "integer", "enum": list(range(LOG_UNKNOWN, LOG_FATAL + 1))},
            "message": {"type": "string"},
            "name": {"type": "string"},
            "file": {"type": "string"},
            "line": {"type": "integer", "minimum": 0},
        },
        "required": ["timestamp", "level", "message", "name", "file", "line"],
    }


SCHEMAS: Final[Mapping[str, dict[str, Any]]] = {
    "esc_bridge.EscTelemetry": record_schema(EscTelemetryPayload, "esc_bridge.EscTelemetry"),
    "esc_bridge.CommandsSent": record_schema(CommandsSent, "esc_bridge.CommandsSent"),
    "esc_bridge.MotorOutputs": record_schema(MotorOutputs, "esc_bridge.MotorOutputs"),
    "esc_bridge.AutopilotHeartbeat": record_schema(
        AutopilotHeartbeat, "esc_bridge.AutopilotHeartbeat"
    ),
    "esc_bridge.BridgeState": record_schema(BridgeState, "esc_bridge.BridgeState"),
    "foxglove.Log": _log_schema(),
}
"""Every schema by name."""

TOPIC_SCHEMAS: Final[Mapping[str, str]] = {
    COMMANDS_TOPIC: "esc_bridge.CommandsSent",
    OUTPUTS_TOPIC: "esc_bridge.MotorOutputs",
    HEARTBEAT_TOPIC: "esc_bridge.AutopilotHeartbeat",
    STATE_TOPIC: "esc_bridge.BridgeState",
    STATUSTEXT_TOPIC: "foxglove.Log",
    LOG_TOPIC: "foxglove.Log",
}
"""The schema of each fixed topic (an ESC's is :func:`schema_of`'s)."""


def schema_of(topic: str) -> str:
    """The name of ``topic``'s schema.

    Raises:
        KeyError: no channel has that topic.
    """
    if topic.startswith(ESC_TOPIC_PREFIX) and topic.endswith(ESC_TOPIC_SUFFIX):
        return "esc_bridge.EscTelemetry"
    return TOPIC_SCHEMAS[topic]


# -- messages ---------------------------------------------------------------------------------


def esc_message(snap: EscSnapshot) -> tuple[str, object]:
    """An ESC's state as its topic's message: ``EscTelemetryPayload.of(snap)``'s JSON, built
    directly (the writer makes thousands a second; tests check that the two agree)."""
    age_ms = snap.age_ms
    return esc_topic(snap.motor), {
        "motor": snap.motor,
        "node_id": snap.node_id,
        "online": snap.online,
        "age_ms": None if age_ms is None else round(age_ms, 1),
        "rpm": snap.rpm,
        "voltage_v": snap.voltage_v,
        "current_a": snap.current_a,
        "motor_current_a": snap.motor_current_a,
        "throttle": snap.throttle,
        "temperature_c": {
            "mos": snap.mos_temp_c,
            "capacitor": snap.capacitor_temp_c,
            "motor": snap.motor_temp_c,
            "mcu": snap.mcu_temp_c,
        },
        "status": snap.status,
        "failure_flags": snap.failure_flags,
        "consumed_mah": round(snap.consumed_mah, 3),
        "command": snap.command,
        "command_unit": snap.command_unit,
    }


def commands_message(commands: Sequence[LastCommand]) -> tuple[str, object]:
    """Every ESC's last command as ``/bridge/commands``' message (:class:`CommandsSent`'s JSON,
    built directly)."""
    return COMMANDS_TOPIC, {
        "commands": [
            {"motor": c.motor, "node_id": c.node_id, "value": c.value, "unit": c.unit}
            for c in commands
        ]
    }


def traffic_message(
    record: MotorOutputs | AutopilotHeartbeat | StatusText, time_ns: int
) -> tuple[str, object]:
    """A record of the MAVLink traffic as its topic's message (``time_ns``: a STATUSTEXT's)."""
    if isinstance(record, MotorOutputs):
        return OUTPUTS_TOPIC, {
            "source": record.source,
            "channels": record.channels,
            "time_usec": record.time_usec,
            "time_bits": record.time_bits,
            "armed": record.armed,
        }
    if isinstance(record, AutopilotHeartbeat):
        return HEARTBEAT_TOPIC, to_json(record)
    return STATUSTEXT_TOPIC, log_message(
        time_ns,
        severity_level(record.severity),
        record.text,
        f"{record.system}/{record.component}",
    )


def state_message(state: BridgeState) -> tuple[str, object]:
    return STATE_TOPIC, to_json(state)


def log_message(
    time_ns: int, level: int, text: str, name: str, file: str = "", line: int = 0
) -> dict[str, object]:
    """A ``foxglove.Log`` message."""
    sec, nsec = divmod(time_ns, 1_000_000_000)
    return {
        "timestamp": {"sec": sec, "nsec": nsec},
        "level": level,
        "message": text,
        "name": name,
        "file": file,
        "line": line,
    }


def severity_level(severity: int) -> int:
    """A STATUSTEXT's MAV_SEVERITY (0 emergency .. 7 debug) as a ``foxglove.Log`` level."""
    if severity <= 2:  # emergency, alert, critical: the bridge's failsafes are critical
        return LOG_FATAL
    return {3: LOG_ERROR, 4: LOG_WARNING, 5: LOG_INFO, 6: LOG_INFO, 7: LOG_DEBUG}.get(
        severity, LOG_UNKNOWN
    )


def python_level(levelno: int) -> int:
    """A Python logging level as a ``foxglove.Log`` level."""
    if levelno >= logging.CRITICAL:
        return LOG_FATAL
    if levelno >= logging.ERROR:
        return LOG_ERROR
    if levelno >= logging.WARNING:
        return LOG_WARNING
    if levelno >= logging.INFO:
        return LOG_INFO
    return LOG_DEBUG if levelno > logging.NOTSET else LOG_UNKNOWN


# -- what was recorded ------------------------------------------------------------------------


def metadata(protocol: str, esc_ids: Sequence[int], **more: str) -> dict[str, str]:
    """The ``esc-bridge`` metadata record: the ESC family's name (``[output] protocol``), the
    ESCs' IDs in motor order, and ``more`` (all strings, as MCAP metadata is)."""
    return {"protocol": protocol, "esc_ids": ",".join(map(str, esc_ids)), **more}


def esc_ids_of(meta: Mapping[str, str]) -> tuple[int, ...] | None:
    """The ESC IDs of an ``esc-bridge`` metadata record; None when it has none (or garbage)."""
    try:
        return tuple(int(i) for i in meta.get("esc_ids", "").split(",") if i) or None
    except ValueError:
        return None
