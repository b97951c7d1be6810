"""Per-ESC telemetry state: decoded frames in, one consistent snapshot per motor out.

Pure bookkeeping, no I/O: the CAN reader feeds it telemetry in the neutral record of
:mod:`bridge.escs.family` (each ESC family maps its own frames into it), commands read back
and codec errors, with their receive times; the publishers (MAVLink, Zenoh, the monitor) take
:class:`EscSnapshot` copies (:mod:`bridge.telemetry.payload` makes the Zenoh JSON of them).
One lock guards it, held only for a few attribute updates, so neither side waits on the other.

ESCs are keyed by motor: motor *n* (1-based, the mixer's output order) is the ESC whose ID
on the bus is the *n*-th entry of ``[escs] ids``.

Failure flags follow MAVLink's ESC_FAILURE_FLAGS; where they come from is the ESC's status
word (as its family maps it, :attr:`~bridge.escs.family.EscTelemetry.status_failures`), its
fault counters, plus the configured limits of :class:`TelemetryLimits` (docs/telemetry.md,
"Failure flags").
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

from bridge.escs.family import (
    FAILURE_GENERIC,
    FAILURE_OVER_CURRENT,
    FAILURE_OVER_RPM,
    FAILURE_OVER_TEMPERATURE,
    CommandSeen,
    EscTelemetry,
)

_NS_PER_HOUR = 3_600_000_000_000
ERROR_BURST_WINDOW_NS = 1_000_000_000  # CRC/format errors are counted per second for the flag


@dataclass(frozen=True)
class TelemetryLimits:
    """Limits beyond which the bridge itself raises failure flags (whatever the ESC reports)."""

    max_temp_c: float | None = 100.0
    """Any reported temperature above this: OVER_TEMPERATURE."""
    max_current_a: float | None = None
    """|current| above this: OVER_CURRENT."""
    max_rpm: int | None = None
    """|rpm| above this: OVER_RPM."""
    error_burst: int = 5
    """This many CRC/format errors within a second: GENERIC, for that second."""


@dataclass(frozen=True, slots=True)
class EscSnapshot:
    """One ESC's state at one moment. ``None``: not (yet) reported by this ESC."""

    motor: int
    """1-based motor (mixer output) number."""
    node_id: int
    """The ESC's ID on the bus (its family's node or ESC ID)."""
    online: bool
    """A frame arrived within the telemetry timeout."""
    age_ms: float | None
    """Time since the last frame from this ESC; None if none ever came."""
    rpm: int | None
    """Mechanical rpm, negative when turning in reverse (erpm / pole pairs for ESCs that
    report erpm)."""
    voltage_v: float | None
    current_a: float | None
    """Supply (battery) current."""
    motor_current_a: float | None
    """Phase current, from ESCs that report it."""
    throttle: float | None
    """The ESC's reported output as a fraction (-1..1), as its family maps it."""
    mos_temp_c: float | None
    capacitor_temp_c: float | None
    motor_temp_c: float | None
    mcu_temp_c: float | None
    status: int | None
    """The ESC's status word as received (None from ESCs without one)."""
    failure_flags: int
    """MAVLink ESC_FAILURE_FLAGS."""
    frames: int
    """Telemetry frames received."""
    errors: int
    """CRC and format errors in frames from this ESC."""
    consumed_mah: float
    """Charge drawn since start, integrated from current_a."""
    counters: dict[str, int] = field(default_factory=dict)
    """Slow information the ESC reported (counts, run times, fault codes), named by its
    family."""
    command: float | None = None
    """The last command seen on the bus for this ESC (the bridge's own, read back)."""
    command_unit: str = ""
    """What ``command`` is, named by the ESC's family: throttle, current_a, current_fraction,
    duty, erpm, brake_current_a, brake_fraction, position_deg, id_current_a, ..."""

    @property
    def esc_temp_c(self) -> float | None:
        """The ESC's own temperature: its MOSFETs, else the hottest other sensor on the ESC."""
        if self.mos_temp_c is not None:
            return self.mos_temp_c
        known = [t for t in (self.capacitor_temp_c, self.mcu_temp_c) if t is not None]
        return max(known) if known else None


@dataclass(frozen=True, slots=True)
class LastCommand:
    """One ESC's last command, as the ESC state took it (:meth:`EscTable.note_commands`)."""

    motor: int
    node_id: int
    value: float | None
    """None: no command seen yet."""
    unit: str


class _Esc:
    """The mutable state of one ESC; only :class:`EscTable` touches it, under its lock."""

    __slots__ = (
        "capacitor_temp_c",
        "command",
        "command_unit",
        "consumed_mah",
        "counters",
        "current_a",
        "current_ns",
        "error_times",
        "errors",
        "fault_counters",
        "frames",
        "last_ns",
        "mcu_temp_c",
        "mos_temp_c",
        "motor",
        "motor_current_a",
        "motor_temp_c",
        "node_id",
        "pole_pairs",
        "reported_faults",
        "rpm",
        "status",
        "status_failures",
        "throttle",
        "uncommanded_failures",
        "voltage_v",
    )

    def __init__(self, motor: int, node_id: int, pole_pairs: int) -> None:
        self.motor = motor
        self.node_id = node_id
        self.pole_pairs = pole_pairs
        self.last_ns: int | None = None
        self.rpm: int | None = None
        self.voltage_v: float | None = None
        self.current_a: float | None = None
        self.current_ns: int | None = None
        self.motor_current_a: float | None = None
        self.throttle: float | None = None
        self.mos_temp_c: float | None = None
        self.capacitor_temp_c: float | None = None
        self.motor_temp_c: float | None = None
        self.mcu_temp_c: float | None = None
        self.status: int | None = None
        self.status_failures = 0  # what the status word raises, as the family maps it
        self.uncommanded_failures = 0  # ... only because no command reaches the ESC
        self.reported_faults = 0  # GENERIC from the family's fault counters
        self.frames = 0
        self.errors = 0
        self.error_times: deque[int] = deque()
        self.consumed_mah = 0.0
        self.counters: dict[str, int] = {}
        self.fault_counters: frozenset[str] = frozenset()  # counters that are fault codes
        self.command: float | None = None
        self.command_unit = ""

    def set_current(self, current_a: float, now_ns: int, max_gap_ns: int) -> None:
        # Integrate with the previous sample's current over the gap; a gap longer than the
        # timeout (the ESC was silent) adds nothing rather than a guess.
        if self.current_a is not None and self.current_ns is not None:
            gap_ns = now_ns - self.current_ns
            if 0 < gap_ns <= max_gap_ns:
                self.consumed_mah += self.current_a * 1000.0 * gap_ns / _NS_PER_HOUR
        self.current_a = current_a
        self.current_ns = now_ns


class EscTable:
    """The state of every configured ESC, fed by the CAN reader, read by the publishers."""

    def __init__(
        self,
        node_ids: Sequence[int],
        *,
        pole_pairs: Sequence[int] | int = 7,
        channels: Sequence[int] | None = None,
        timeout_ms: int = 500,
        limits: TelemetryLimits | None = None,
        commanded: bool = True,
    ) -> None:
        """``node_ids[i]`` is the ESC ID of motor i + 1; ``pole_pairs`` is one value for every
        motor or one per motor (used to turn erpm into rpm); ``channels[i]`` is the throttle
        channel of motor i + 1 (default i + 1), to read back commands sent by channel.
        ``commanded``: the owner sends the ESCs commands (the bridge), so an ESC's "no command
        received" report is a failure; False for a listener (the monitor on the bus), to which
        it is an idle ESC's state.

        Raises:
            ValueError: ``pole_pairs`` has the wrong length or a value below 1.
        """
        pairs = [pole_pairs] * len(node_ids) if isinstance(pole_pairs, int) else list(pole_pairs)
        if len(pairs) != len(node_ids) or any(p < 1 for p in pairs):
            raise ValueError(
                f"pole_pairs: expected one value >= 1 per ESC ({len(node_ids)}), got {pole_pairs}"
            )
        self._lock = threading.Lock()
        self._timeout_ns = timeout_ms * 1_000_000
        self._limits = limits or TelemetryLimits()
        self._commanded = commanded
        self._escs = [_Esc(i + 1, node, pairs[i]) for i, node in enumerate(node_ids)]
        self._by_node = {esc.node_id: esc for esc in self._escs}
        channels = channels or range(1, len(node_ids) + 1)
        self._by_channel = {c: esc for c, esc in zip(channels, self._escs, strict=True)}
        self.node_set = frozenset(self._by_node)
        """Our ESCs' IDs (for decoders that refuse foreign nodes)."""
        self.unknown_frames = 0
        """Telemetry from an ID that is not one of ours."""
        self.unattributed_errors = 0
        """Malformed frames whose ID names none of our ESCs."""

    @property
    def node_ids(self) -> tuple[int, ...]:
        return tuple(esc.node_id for esc in self._escs)

    def __len__(self) -> int:
        return len(self._escs)

    def remap(self, node_ids: Sequence[int]) -> None:
        """Assign node IDs to motors anew (learnt from the ESCs); state is kept per motor.

        Raises:
            ValueError: not one distinct ID per motor.
        """
        if len(node_ids) != len(self._escs) or len(set(node_ids)) != len(node_ids):
            raise ValueError(f"expected {len(self._escs)} distinct node IDs, got {node_ids}")
        with self._lock:
            for esc, node in zip(self._escs, node_ids, strict=True):
                esc.node_id = node
            self._by_node = {esc.node_id: esc for esc in self._escs}
            self.node_set = frozenset(self._by_node)

    def ingest(self, telemetry: EscTelemetry, now_ns: int) -> bool:
        """Take one frame's telemetry received at ``now_ns`` (monotonic). False if it is not
        from one of our ESCs."""
        with self._lock:
            esc = self._by_node.get(telemetry.node_id)
            if esc is None:
                self.unknown_frames += 1
                return False
            self._apply(esc, telemetry, now_ns)
            esc.frames += 1
            esc.last_ns = now_ns
        return True

    def note_commands(self, commands: Sequence[CommandSeen]) -> bool:
        """Take the commands read back from one frame (the ESC's last command). False if none
        was for one of our ESCs."""
        if not commands:
            return False
        taken = False
        with self._lock:
            for seen in commands:
                if seen.channel is not None:
                    esc = self._by_channel.get(seen.channel)
                else:
                    esc = self._by_node.get(seen.node_id) if seen.node_id is not None else None
                if esc is not None:
                    esc.command, esc.command_unit = seen.value, seen.unit
                    taken = True
        return taken

    def last_commands(self) -> tuple[LastCommand, ...]:
        """Every ESC's last command, in motor order."""
        with self._lock:
            return tuple(
                LastCommand(esc.motor, esc.node_id, esc.command, esc.command_unit)
                for esc in self._escs
            )

    def count_error(self, node_id: int | None, now_ns: int) -> None:
        """Count a malformed frame (bad CRC, DLC, tail byte) from ``node_id`` (None: unknown)."""
        with self._lock:
            esc = self._by_node.get(node_id) if node_id is not None else None
            if esc is None:
                self.unattributed_errors += 1
                return
            esc.errors += 1
            esc.error_times.append(now_ns)
            cutoff = now_ns - ERROR_BURST_WINDOW_NS
            while esc.error_times and esc.error_times[0] < cutoff:
                esc.error_times.popleft()

    def snapshot(self, now_ns: int) -> tuple[EscSnapshot, ...]:
        """Every ESC's state as of ``now_ns``, in motor order."""
        with self._lock:
            return tuple(self._snapshot(esc, now_ns) for esc in self._escs)

    def snapshot_of(self, node_id: int, now_ns: int) -> EscSnapshot | None:
        """The state of the ESC at ``node_id`` as of ``now_ns``; None if it is not one of ours."""
        with self._lock:
            esc = self._by_node.get(node_id)
            return None if esc is None else self._snapshot(esc, now_ns)

    # -- under the lock ---------------------------------------------------------------------

    def _apply(self, esc: _Esc, t: EscTelemetry, now_ns: int) -> None:
        if t.rpm is not None:
            esc.rpm = t.rpm
        elif t.erpm is not None:
            # int(x / p) truncates toward zero, so reverse rpm stays as large as forward rpm.
            esc.rpm = int(t.erpm / esc.pole_pairs)
        if t.voltage_v is not None:
            esc.voltage_v = t.voltage_v
        if t.current_a is not None:
            esc.set_current(t.current_a, now_ns, self._timeout_ns)
        if t.motor_current_a is not None:
            esc.motor_current_a = t.motor_current_a
        if t.throttle is not None:
            esc.throttle = t.throttle
        if t.mos_temp_c is not None:
            esc.mos_temp_c = t.mos_temp_c
        if t.capacitor_temp_c is not None:
            esc.capacitor_temp_c = t.capacitor_temp_c
        if t.motor_temp_c is not None:
            esc.motor_temp_c = t.motor_temp_c
        if t.mcu_temp_c is not None:
            esc.mcu_temp_c = t.mcu_temp_c
        if t.status is not None:
            esc.status = t.status
            esc.status_failures = t.status_failures or 0
            esc.uncommanded_failures = t.uncommanded_failures or 0
        if t.counters:
            esc.counters.update(t.counters)
            esc.fault_counters |= t.fault_counters
        counters = esc.counters
        if any(counters.get(name) for name in esc.fault_counters):
            esc.reported_faults = FAILURE_GENERIC
        else:
            esc.reported_faults = 0

    def _failure_flags(self, esc: _Esc, now_ns: int) -> int:
        limits = self._limits
        flags = esc.reported_faults | esc.status_failures
        if self._commanded:
            flags |= esc.uncommanded_failures
        if limits.max_temp_c is not None:
            temps = (esc.mos_temp_c, esc.capacitor_temp_c, esc.motor_temp_c, esc.mcu_temp_c)
            if any(t is not None and t > limits.max_temp_c for t in temps):
                flags |= FAILURE_OVER_TEMPERATURE
        if (
            limits.max_current_a is not None
            and esc.current_a is not None
            and abs(esc.current_a) > limits.max_current_a
        ):
            flags |= FAILURE_OVER_CURRENT
        if limits.max_rpm is not None and esc.rpm is not None and abs(esc.rpm) > limits.max_rpm:
            flags |= FAILURE_OVER_RPM
        cutoff = now_ns - ERROR_BURST_WINDOW_NS
        if sum(1 for t in esc.error_times if t >= cutoff) >= limits.error_burst:
            flags |= FAILURE_GENERIC
        return flags

    def _snapshot(self, esc: _Esc, now_ns: int) -> EscSnapshot:
        age_ns = None if esc.last_ns is None else now_ns - esc.last_ns
        return EscSnapshot(
            motor=esc.motor,
            node_id=esc.node_id,
            online=age_ns is not None and age_ns <= self._timeout_ns,
            age_ms=None if age_ns is None else age_ns / 1e6,
            rpm=esc.rpm,
            voltage_v=esc.voltage_v,
            current_a=esc.current_a,
            motor_current_a=esc.motor_current_a,
            throttle=esc.throttle,
            mos_temp_c=esc.mos_temp_c,
            capacitor_temp_c=esc.capacitor_temp_c,
            motor_temp_c=esc.motor_temp_c,
            mcu_temp_c=esc.mcu_temp_c,
            status=esc.status,
            failure_flags=self._failure_flags(esc, now_ns),
            frames=esc.frames,
            errors=esc.errors,
            consumed_mah=esc.consumed_mah,
            counters=dict(esc.counters),
            command=esc.command,
            command_unit=esc.command_unit,
        )
