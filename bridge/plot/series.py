"""A CAN capture as per-ESC time series, for ``esc-bridge plot``.

The capture is decoded only through its family's :class:`~bridge.escs.family.EscFamily`
(``owns``, and its decoder's ``decode``, ``telemetry``, ``commands_seen``), so every family
plots alike. Per ESC:
the commands read back from the bus (one series per unit: a family may stop a motor with
another command than the one it runs it with), rpm (erpm / pole pairs for ESCs that report
erpm), supply and phase current, voltage, every temperature sensor it reports, and the runs of
its status failure flags (:attr:`~bridge.escs.family.EscTelemetry.status_failures`). Along the
way, when every ESC's last command became or stopped being a stop (for
:func:`bridge.plot.spans.stopped_while_armed`).

Which ESC a command is for: the family says a node ID, or a throttle channel; channel *n*
drives the *n*-th ESC in order (``ids``, else the IDs seen in ascending order), the bridge's
default ``[escs]`` channels, unless ``channels`` says otherwise.

Times are wall-clock seconds since the Unix epoch, as the capture stamps its frames. Pure: the
caller reads the capture (:func:`bridge.capture.read_capture`).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Final

import can

from bridge.capture import BadLine
from bridge.errors import ConfigError, FrameError
from bridge.escs import registry
from bridge.escs.family import (
    FAILURE_GENERIC,
    FAILURE_INCONSISTENT_CMD,
    FAILURE_MOTOR_STUCK,
    FAILURE_OVER_CURRENT,
    FAILURE_OVER_RPM,
    FAILURE_OVER_TEMPERATURE,
    FAILURE_OVER_VOLTAGE,
    CommandSeen,
    EscFamily,
    EscTelemetry,
)

DEFAULT_POLE_PAIRS: Final = 7
"""As ``[telemetry] pole_pairs``: rpm = erpm / pole pairs for ESCs that report erpm."""

FAILURE_NAMES: Final[Mapping[int, str]] = {
    FAILURE_OVER_CURRENT: "over current",
    FAILURE_OVER_VOLTAGE: "over voltage",
    FAILURE_OVER_TEMPERATURE: "over temperature",
    FAILURE_OVER_RPM: "over rpm",
    FAILURE_INCONSISTENT_CMD: "inconsistent command",
    FAILURE_MOTOR_STUCK: "motor stuck",
    FAILURE_GENERIC: "generic",
}
"""MAVLink ESC_FAILURE_FLAGS bits by name."""

STOP_UNITS: Final = frozenset({"brake_current_a", "brake_fraction"})
"""Command units (:attr:`~bridge.escs.family.CommandSeen.unit`) that stop a motor whatever
their value; any other command stops it at 0."""

TEMPERATURES: Final[Mapping[str, str]] = {
    "mos_temp_c": "MOSFET",
    "capacitor_temp_c": "capacitor",
    "motor_temp_c": "motor",
    "mcu_temp_c": "MCU",
}
"""The temperature fields of :class:`~bridge.escs.family.EscTelemetry`, by sensor name."""


def failure_names(flags: int) -> tuple[str, ...]:
    """The names of the ESC_FAILURE_FLAGS bits set in ``flags`` (unknown bits as ``bit N``)."""
    names = [name for bit, name in FAILURE_NAMES.items() if flags & bit]
    names += [f"bit {n}" for n in range(32) if flags & (1 << n) and (1 << n) not in FAILURE_NAMES]
    return tuple(names)


# -- records ------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Series:
    """One quantity over time: ``values[i]`` at ``t_s[i]`` (ascending)."""

    t_s: tuple[float, ...] = ()
    values: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if len(self.t_s) != len(self.values):
            raise ValueError(f"{len(self.t_s)} times but {len(self.values)} values")

    def __len__(self) -> int:
        return len(self.t_s)

    def shifted(self, by_s: float) -> Series:
        """The same values, their times ``by_s`` earlier."""
        return Series(tuple(t - by_s for t in self.t_s), self.values)

    def max_abs(self) -> float | None:
        return max((abs(v) for v in self.values), default=None)


@dataclass(frozen=True, slots=True)
class FailureRun:
    """An ESC reporting the same non-zero failure flags from ``start_s`` to ``end_s``."""

    start_s: float
    end_s: float
    flags: int

    @property
    def names(self) -> tuple[str, ...]:
        return failure_names(self.flags)


@dataclass(frozen=True)
class EscSeries:
    """Everything one ESC did in a recording. A quantity it never reported is an empty series;
    ``temps_c`` holds only the sensors it reported."""

    node_id: int | None
    """Its ID on the bus; None for a throttle channel commanded that no known ESC answers on."""
    motor: int | None = None
    """Its motor number, when the ESC list was given (``ids``)."""
    channel: int | None = None
    """Its throttle channel, for families that command by channel."""
    commands: Mapping[str, Series] = field(default_factory=dict)
    """The commands read back from the bus, by unit (throttle, current_a, brake_current_a, ...),
    the unit sent most often first."""
    rpm: Series = Series()
    current_a: Series = Series()
    """Supply (battery) current."""
    motor_current_a: Series = Series()
    """Phase current."""
    voltage_v: Series = Series()
    temps_c: Mapping[str, Series] = field(default_factory=dict)
    """By sensor name (:data:`TEMPERATURES`)."""
    failures: tuple[FailureRun, ...] = ()
    telemetry_frames: int = 0

    @property
    def title(self) -> str:
        """How the ESC is named on its pictures."""
        if self.node_id is None:
            return f"throttle channel {self.channel} (no ESC answered)"
        name = f"ESC {self.node_id}"
        if self.motor is not None:
            name = f"motor {self.motor}, {name}"
        return name if self.channel is None else f"{name}, channel {self.channel}"

    @property
    def slug(self) -> str:
        """A file-name part for its pictures."""
        return f"channel-{self.channel}" if self.node_id is None else f"esc-{self.node_id}"

    def shifted(self, by_s: float) -> EscSeries:
        return EscSeries(
            self.node_id,
            self.motor,
            self.channel,
            {unit: s.shifted(by_s) for unit, s in self.commands.items()},
            self.rpm.shifted(by_s),
            self.current_a.shifted(by_s),
            self.motor_current_a.shifted(by_s),
            self.voltage_v.shifted(by_s),
            {name: s.shifted(by_s) for name, s in self.temps_c.items()},
            tuple(FailureRun(r.start_s - by_s, r.end_s - by_s, r.flags) for r in self.failures),
            self.telemetry_frames,
        )


@dataclass(frozen=True)
class CanSummary:
    """How the capture went: what was read and what was not."""

    family: str
    """The family's title."""
    frames: int = 0
    telemetry_frames: int = 0
    command_frames: int = 0
    malformed: int = 0
    """Frames in the family's space that it could not decode."""
    other: int = 0
    """Frames of no interest to it (another protocol, service traffic)."""
    bad_lines: int = 0


# -- the capture ----------------------------------------------------------------------------------


def is_stop(seen: CommandSeen) -> bool:
    """Whether a command read back stops its motor (the bridge's safe value)."""
    return seen.unit in STOP_UNITS or seen.value == 0


def guess_family(
    messages: Iterable[can.Message | BadLine], esc_nodes: Collection[int] | None = None
) -> EscFamily | None:
    """The family that reads the most of ``messages`` as telemetry or commands (the first in the
    registry's order on a tie), or None if none reads any. ``esc_nodes``: our ESCs' IDs, if
    known (see :meth:`~bridge.escs.family.EscDecoder.decode`)."""
    families = registry.families()
    decoders = [family.decoder() for family in families]
    counts = [0] * len(families)
    for msg in messages:
        if isinstance(msg, BadLine):
            continue
        for i, family in enumerate(families):
            if not family.owns(msg.arbitration_id):
                continue
            decoder = decoders[i]
            try:
                frame = decoder.decode(msg, esc_nodes)
            except FrameError:
                continue
            if frame is not None and (
                decoder.telemetry(frame) is not None or decoder.commands_seen(frame)
            ):
                counts[i] += 1
    best = max(range(len(families)), key=lambda i: (counts[i], -i))
    return families[best] if counts[best] else None


class _Points:
    """A series being collected."""

    __slots__ = ("t_s", "values")

    def __init__(self) -> None:
        self.t_s: list[float] = []
        self.values: list[float] = []

    def add(self, t_s: float, value: float) -> None:
        self.t_s.append(t_s)
        self.values.append(value)

    def series(self) -> Series:
        return Series(tuple(self.t_s), tuple(self.values))


class _Esc:
    """One ESC's telemetry being collected."""

    def __init__(self, pole_pairs: int) -> None:
        self.pole_pairs = pole_pairs
        self.points: dict[str, _Points] = {}
        self.failures: list[FailureRun] = []
        self.flags = 0
        self.flags_since = 0.0
        self.frames = 0
        self.last_s = 0.0

    def add(self, t_s: float, telemetry: EscTelemetry) -> None:
        self.frames += 1
        self.last_s = t_s
        rpm = telemetry.rpm
        if rpm is None and telemetry.erpm is not None:
            rpm = round(telemetry.erpm / self.pole_pairs)
        values = {
            "rpm": rpm,
            "voltage_v": telemetry.voltage_v,
            "current_a": telemetry.current_a,
            "motor_current_a": telemetry.motor_current_a,
            **{name: getattr(telemetry, name) for name in TEMPERATURES},
        }
        for name, value in values.items():
            if value is not None and math.isfinite(value):
                self.points.setdefault(name, _Points()).add(t_s, float(value))
        # A recording is of the bridge, which commands the ESCs: "no command" is a failure.
        flags = telemetry.status_failures
        if flags is not None:
            flags |= telemetry.uncommanded_failures or 0
        if flags is not None and flags != self.flags:
            self._end_run(t_s)
            self.flags, self.flags_since = flags, t_s

    def _end_run(self, t_s: float) -> None:
        if self.flags:
            self.failures.append(FailureRun(self.flags_since, t_s, self.flags))

    def finish(self) -> tuple[FailureRun, ...]:
        self._end_run(self.last_s)
        self.flags = 0
        return tuple(self.failures)


@dataclass
class CaptureSeries:
    """What :func:`capture_series` collected, before ESCs are matched to channels."""

    telemetry: dict[int, EscSeries]
    """By node ID, without commands."""
    by_node: dict[int, dict[str, Series]]
    """Commands addressed to a node, by unit."""
    by_channel: dict[int, dict[str, Series]]
    """Commands addressed to a throttle channel, by unit."""
    all_stopped: list[tuple[float, bool]]
    """(time, every commanded ESC's last command stops it) at each change."""
    summary: CanSummary
    first_s: float | None
    last_s: float | None


def capture_series(
    messages: Iterable[can.Message | BadLine],
    family: EscFamily,
    pole_pairs: Mapping[int, int] | int = DEFAULT_POLE_PAIRS,
    esc_nodes: Collection[int] | None = None,
) -> CaptureSeries:
    """Collect a capture's telemetry and commands through ``family``. ``pole_pairs``: one for
    every ESC, or by node ID (nodes not in it: :data:`DEFAULT_POLE_PAIRS`). ``esc_nodes``: our
    ESCs' IDs, if known (see :meth:`~bridge.escs.family.EscDecoder.decode`)."""
    decoder = family.decoder()
    escs: dict[int, _Esc] = {}
    commands: dict[tuple[str, int], dict[str, _Points]] = {}
    stopped: dict[tuple[str, int], bool] = {}
    all_stopped: list[tuple[float, bool]] = []
    counts = {"frames": 0, "telemetry": 0, "commands": 0, "malformed": 0, "other": 0, "bad": 0}
    first_s = last_s = None
    for msg in messages:
        if isinstance(msg, BadLine):
            counts["bad"] += 1
            continue
        counts["frames"] += 1
        t_s = msg.timestamp
        first_s = t_s if first_s is None else first_s
        last_s = t_s
        try:
            frame = decoder.decode(msg, esc_nodes) if family.owns(msg.arbitration_id) else None
        except FrameError:
            counts["malformed"] += 1
            continue
        if frame is None:
            counts["other"] += 1
            continue
        telemetry = decoder.telemetry(frame)
        if telemetry is not None:
            counts["telemetry"] += 1
            esc = escs.get(telemetry.node_id)
            if esc is None:
                pairs = (
                    pole_pairs
                    if isinstance(pole_pairs, int)
                    else pole_pairs.get(telemetry.node_id, DEFAULT_POLE_PAIRS)
                )
                esc = escs[telemetry.node_id] = _Esc(pairs)
            esc.add(t_s, telemetry)
            continue
        seen = decoder.commands_seen(frame)
        if not seen:
            counts["other"] += 1
            continue
        counts["commands"] += 1
        for command in seen:
            if command.channel is not None:
                key = ("channel", command.channel)
            elif command.node_id is not None:
                key = ("node", command.node_id)
            else:
                continue
            commands.setdefault(key, {}).setdefault(command.unit, _Points()).add(t_s, command.value)
            stopped[key] = is_stop(command)
        now_all = all(stopped.values())
        if not all_stopped or all_stopped[-1][1] != now_all:
            all_stopped.append((t_s, now_all))

    def by_kind(kind: str) -> dict[int, dict[str, Series]]:
        return {
            number: {
                unit: points.series()
                for unit, points in sorted(units.items(), key=lambda u: -len(u[1].t_s))
            }
            for (k, number), units in commands.items()
            if k == kind
        }

    telemetry_series = {}
    for node, esc in escs.items():
        points = esc.points
        empty = _Points()
        telemetry_series[node] = EscSeries(
            node,
            rpm=points.get("rpm", empty).series(),
            current_a=points.get("current_a", empty).series(),
            motor_current_a=points.get("motor_current_a", empty).series(),
            voltage_v=points.get("voltage_v", empty).series(),
            temps_c={
                sensor: points[name].series()
                for name, sensor in TEMPERATURES.items()
                if name in points
            },
            failures=esc.finish(),
            telemetry_frames=esc.frames,
        )
    summary = CanSummary(
        family.title,
        counts["frames"],
        counts["telemetry"],
        counts["commands"],
        counts["malformed"],
        counts["other"],
        counts["bad"],
    )
    return CaptureSeries(
        telemetry_series,
        by_kind("node"),
        by_kind("channel"),
        all_stopped,
        summary,
        first_s,
        last_s,
    )


def match_escs(
    captured: CaptureSeries,
    ids: Sequence[int] | None = None,
    channels: Sequence[int] | None = None,
) -> tuple[EscSeries, ...]:
    """The ESCs with their commands: ``ids`` in motor order (motor 1 first), else every node
    that sent telemetry or was commanded, in ascending order; ``channels[i]`` is the throttle
    channel of the i-th of them (default i + 1). A channel commanded to something other than
    a stop that no ESC answers on is kept as an ESC of its own (``node_id`` None).

    Raises:
        ConfigError: ``channels`` has not one entry per ESC.
    """
    nodes = list(ids) if ids is not None else sorted(captured.telemetry.keys() | captured.by_node)
    if channels is not None and len(channels) != len(nodes):
        raise ConfigError(
            f"channels {list(channels)}: {len(channels)} for {len(nodes)} ESCs {nodes}; "
            "expected one per ESC"
        )
    channel_of = dict(zip(nodes, channels or range(1, len(nodes) + 1), strict=True))
    uses_channels = bool(captured.by_channel)
    escs: list[EscSeries] = []
    for i, node in enumerate(nodes):
        base = captured.telemetry.get(node, EscSeries(node))
        channel = channel_of[node] if uses_channels else None
        command = captured.by_channel.get(channel, {}) if channel is not None else {}
        escs.append(
            EscSeries(
                node,
                i + 1 if ids is not None else None,
                channel,
                command or captured.by_node.get(node, {}),
                base.rpm,
                base.current_a,
                base.motor_current_a,
                base.voltage_v,
                base.temps_c,
                base.failures,
                base.telemetry_frames,
            )
        )
    used = set(channel_of.values())
    for channel, units in sorted(captured.by_channel.items()):
        if channel in used:
            continue
        moving = any(
            v != 0 and unit not in STOP_UNITS for unit, s in units.items() for v in s.values
        )
        if moving:
            escs.append(EscSeries(None, channel=channel, commands=units))
    return tuple(escs)


def thin(series: Series, max_points: int) -> Series:
    """At most about ``max_points`` points that draw like all of them: for each of
    ``max_points / 2`` equal runs of points, its lowest and highest in time order."""
    n = len(series)
    if n <= max_points or max_points < 2:
        return series
    buckets = max_points // 2
    t_out: list[float] = []
    v_out: list[float] = []
    for b in range(buckets):
        lo, hi = b * n // buckets, (b + 1) * n // buckets
        if lo >= hi:
            continue
        chunk = series.values[lo:hi]
        i_min = lo + chunk.index(min(chunk))
        i_max = lo + chunk.index(max(chunk))
        for i in sorted({i_min, i_max}):
            t_out.append(series.t_s[i])
            v_out.append(series.values[i])
    return Series(tuple(t_out), tuple(v_out))
