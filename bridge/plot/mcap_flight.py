"""A recording's ``.mcap`` as the plot's series and events, for a recording whose candump log and
tlog are not at hand.

The MCAP's channels (:mod:`bridge.telemetry.mcap_channels`) give what the capture and the tlog
give: each ESC's telemetry (its state after each frame: the values it last reported), every
ESC's last command after each command, the autopilot's HEARTBEATs and every STATUSTEXT. The
result is the same :class:`~bridge.plot.series.CaptureSeries` and
:class:`~bridge.plot.recording.TlogEvents` that :func:`bridge.plot.flight.flight` puts together.
Times are the messages' log times. Two things differ from the capture: an ESC's failure flags
are the bridge's (its configured limits included), and a STATUSTEXT's severity comes back from
its ``foxglove.Log`` level (notice reads as info; emergency and alert as critical).

The reader is linear and stops quietly at a file cut short (a bridge that died): what came
before is drawn.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any, BinaryIO, Final

from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader

from bridge.errors import ConfigError
from bridge.escs import registry
from bridge.escs.family import CommandSeen
from bridge.plot.recording import Heartbeat, StatusText, TlogEvents
from bridge.plot.series import (
    TEMPERATURES,
    CanSummary,
    CaptureSeries,
    EscSeries,
    FailureRun,
    Series,
    is_stop,
)
from bridge.telemetry import mcap_channels as channels

_LEVEL_SEVERITY: Final = {
    channels.LOG_FATAL: 2,
    channels.LOG_ERROR: 3,
    channels.LOG_WARNING: 4,
    channels.LOG_INFO: 6,
    channels.LOG_DEBUG: 7,
}
"""A ``foxglove.Log`` level back to a MAV_SEVERITY (the highest it stands for)."""
_TEMPERATURE_FIELDS: Final = {
    "mos": "mos_temp_c",
    "capacitor": "capacitor_temp_c",
    "motor": "motor_temp_c",
    "mcu": "mcu_temp_c",
}


class _Points:
    __slots__ = ("t_s", "values")

    def __init__(self) -> None:
        self.t_s: list[float] = []
        self.values: list[float] = []

    def add(self, t_s: float, value: object) -> None:
        if isinstance(value, int | float) and not isinstance(value, bool):
            self.t_s.append(t_s)
            self.values.append(float(value))

    def series(self) -> Series:
        return Series(tuple(self.t_s), tuple(self.values))


class _Esc:
    def __init__(self) -> None:
        self.node_id: int | None = None
        self.points: dict[str, _Points] = {}
        self.failures: list[FailureRun] = []
        self.flags = 0
        self.flags_since = 0.0
        self.frames = 0
        self.last_s = 0.0

    def add(self, t_s: float, message: Mapping[str, Any]) -> None:
        self.frames += 1
        self.last_s = t_s
        self.node_id = message.get("node_id", self.node_id)
        for name in ("rpm", "voltage_v", "current_a", "motor_current_a"):
            self.points.setdefault(name, _Points()).add(t_s, message.get(name))
        for sensor, value in (message.get("temperature_c") or {}).items():
            field = _TEMPERATURE_FIELDS.get(sensor)
            if field is not None:
                self.points.setdefault(field, _Points()).add(t_s, value)
        flags = message.get("failure_flags", 0)
        if flags != self.flags:
            if self.flags:
                self.failures.append(FailureRun(self.flags_since, t_s, self.flags))
            self.flags, self.flags_since = flags, t_s

    def series(self) -> EscSeries:
        if self.flags:
            self.failures.append(FailureRun(self.flags_since, self.last_s, self.flags))
        empty = _Points()
        points = self.points
        return EscSeries(
            self.node_id,
            rpm=points.get("rpm", empty).series(),
            current_a=points.get("current_a", empty).series(),
            motor_current_a=points.get("motor_current_a", empty).series(),
            voltage_v=points.get("voltage_v", empty).series(),
            temps_c={
                sensor: points[name].series()
                for name, sensor in TEMPERATURES.items()
                if name in points and len(points[name].t_s)
            },
            failures=tuple(self.failures),
            telemetry_frames=self.frames,
        )


def _read(file: BinaryIO) -> tuple[list[tuple[str, int, Any]], dict[str, str]]:
    """(topic, log time ns, decoded JSON) of every message, in file order, and the
    ``esc-bridge`` metadata; to a cut-short end."""
    topics: dict[int, str] = {}
    found: list[tuple[str, int, Any]] = []
    meta: dict[str, str] = {}
    try:
        for record in StreamReader(file).records:
            if isinstance(record, Message):
                try:
                    found.append(
                        (topics[record.channel_id], record.log_time, json.loads(record.data))
                    )
                except (KeyError, ValueError):
                    continue  # no channel, or not JSON: not ours
            elif isinstance(record, Channel):
                topics[record.id] = record.topic
            elif isinstance(record, Metadata) and record.name == channels.METADATA_NAME:
                meta = dict(record.metadata)
    except (McapError, struct.error, EOFError):
        pass  # cut short: what came before stands
    return found, meta


def read_mcap(path: Path) -> tuple[CaptureSeries, TlogEvents, tuple[int, ...] | None]:
    """The series and events of the ``.mcap`` at ``path``, and the ESC IDs in motor order it
    names (None if it names none).

    Raises:
        ConfigError: the file cannot be read, or holds no message of ours.
    """
    try:
        with path.open("rb") as file:
            found, meta = _read(file)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read it: {exc.strerror or exc}") from exc
    escs: dict[str, _Esc] = {}
    commands: dict[int, dict[str, _Points]] = {}
    all_stopped: list[tuple[float, bool]] = []
    heartbeats: list[Heartbeat] = []
    texts: list[StatusText] = []
    command_messages = 0
    first_s = last_s = None
    for topic, time_ns, message in sorted(found, key=lambda m: m[1]):
        t_s = time_ns / 1e9
        if topic.startswith(channels.ESC_TOPIC_PREFIX) and topic.endswith(
            channels.ESC_TOPIC_SUFFIX
        ):
            escs.setdefault(topic, _Esc()).add(t_s, message)
        elif topic == channels.COMMANDS_TOPIC:
            command_messages += 1
            stops = []
            for command in message.get("commands", ()):
                value, unit, node = (
                    command.get("value"),
                    command.get("unit", ""),
                    command.get("node_id"),
                )
                if value is None or node is None:
                    continue
                commands.setdefault(node, {}).setdefault(unit, _Points()).add(t_s, value)
                stops.append(is_stop(CommandSeen(value, unit, node_id=node)))
            if stops and (not all_stopped or all_stopped[-1][1] != all(stops)):
                all_stopped.append((t_s, all(stops)))
        elif topic == channels.HEARTBEAT_TOPIC:
            heartbeats.append(Heartbeat(t_s, bool(message.get("armed"))))
        elif topic == channels.STATUSTEXT_TOPIC:
            system, _, component = str(message.get("name", "")).partition("/")
            texts.append(
                StatusText(
                    t_s,
                    _LEVEL_SEVERITY.get(message.get("level"), 6),
                    str(message.get("message", "")),
                    int(system) if system.isdigit() else 0,
                    int(component) if component.isdigit() else 0,
                )
            )
        else:
            continue
        if topic != channels.STATUSTEXT_TOPIC and topic != channels.HEARTBEAT_TOPIC:
            first_s = t_s if first_s is None else first_s
            last_s = t_s
    if not escs and not command_messages and not heartbeats:
        raise ConfigError(
            f"{path}: no ESC telemetry, command or HEARTBEAT in it; expected an MCAP written by "
            "esc-bridge run --record"
        )
    telemetry = {}
    for esc in escs.values():
        series = esc.series()
        if series.node_id is not None:
            telemetry[series.node_id] = series
    protocol = meta.get("protocol", "")
    title = registry.family(protocol).title if protocol in registry.names() else protocol or "?"
    frames = sum(e.frames for e in escs.values())
    times = [time_ns / 1e9 for _, time_ns, _ in found]  # every message: logs, outputs too
    captured = CaptureSeries(
        telemetry,
        {
            node: {
                unit: points.series()
                for unit, points in sorted(units.items(), key=lambda u: -len(u[1].t_s))
            }
            for node, units in commands.items()
        },
        {},
        all_stopped,
        CanSummary(title, frames + command_messages, frames, command_messages),
        first_s,
        last_s,
    )
    events = TlogEvents(
        tuple(heartbeats),
        tuple(texts),
        min(times, default=None),
        max(times, default=None),
        len(heartbeats) + len(texts),
    )
    return captured, events, channels.esc_ids_of(meta)
