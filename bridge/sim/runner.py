"""Puts simulated ESCs on a python-can bus: one named thread receives every frame, feeds it
to each ESC, polls them every millisecond and sends what they return.

The ESCs (:class:`~bridge.sim.base.SimEsc`) are pure state machines; this module owns the bus,
the monotonic clock and the battery they share. :func:`make_escs` builds a bus's worth of
simulated ESCs of one family (each family's own simulator) with the project's default IDs.

Decisions where the spec is silent
----------------------------------
- The ESCs' clock is the monotonic clock counted from :meth:`Simulator.start`, so every ESC
  powers up at 0 s (the start of any power-up window, the first comms timeout).
- Polls follow a steady 1 ms schedule on that clock. After a stall (a slow machine,
  a paused process) the simulator polls once, covering the whole gap, and carries on one
  period from then: the motors integrate the real elapsed time and no burst of polls (or of
  telemetry) follows. Skipped periods are counted (``late_polls``).
- Sends never block (``timeout=0``). A send that fails (transmit queue full, bus down) is
  counted and the frame dropped; the first failure is logged as a warning, later ones at
  debug level, as a real ESC would simply miss a slot.
- The battery is stepped after every poll with the sum of the motors' supply currents; each
  ESC sees the voltage at the start of the poll.
- A fault scheduled at ``at_s`` is switched on at the first poll at least ``at_s`` seconds
  after :meth:`Simulator.start`; it stays on.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any, Final, Literal, TypeAlias, get_args

import can

from bridge.escs import registry
from bridge.escs.family import EscSetup
from bridge.sim.base import SimEsc
from bridge.sim.motor import Battery, MotorParams

__all__ = [
    "FAULT_KINDS",
    "POLL_PERIOD_S",
    "FaultKind",
    "ScheduledFault",
    "SimBus",
    "SimStats",
    "Simulator",
    "make_escs",
]

log = logging.getLogger(__name__)

Simulators: TypeAlias = Callable[[EscSetup[Any], MotorParams | None], list[SimEsc]]
"""A family's ``sim.simulators`` (see :mod:`bridge.escs.family`)."""

POLL_PERIOD_S: Final = 0.001
"""How often every ESC is polled (motor step, timeouts, telemetry due)."""
RECV_TIMEOUT_S: Final = 0.001
"""Longest single wait for a frame, so a close() is noticed promptly."""
DRAIN_MAX_FRAMES: Final = 256
"""Queued frames taken before a poll: a stall of 100 ms at 400 Hz queues ~40 per ESC group."""

FaultKind: TypeAlias = Literal[
    "over_temperature", "over_current", "corrupt", "silent", "stuck_motor"
]
FAULT_KINDS: Final[tuple[str, ...]] = get_args(FaultKind)
"""The fault names, the fields of :class:`~bridge.sim.base.Faults`."""


@dataclass(frozen=True)
class ScheduledFault:
    """Switch fault ``kind`` on for the ESC with ``node_id``, ``at_s`` seconds after start.

    Raises:
        ValueError: an unknown kind or a negative time.
    """

    node_id: int
    kind: FaultKind
    at_s: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"kind={self.kind!r}: expected one of {', '.join(FAULT_KINDS)}")
        if not self.at_s >= 0:
            raise ValueError(f"at_s={self.at_s!r}: expected a time >= 0 s")


@dataclass
class SimStats:
    """Counters of one simulator since start (:attr:`Simulator.stats` hands out copies)."""

    frames_in: int = 0
    frames_out: int = 0
    send_failures: int = 0
    recv_failures: int = 0
    polls: int = 0
    late_polls: int = 0
    """Poll periods skipped after a stall (covered by the next poll's longer step)."""


class Simulator:
    """Runs ``escs`` on ``bus`` in a thread named ``name``; share ``battery`` among them.

    ``faults`` are switched on at their times; :meth:`set_fault` does it at once. With
    ``own_bus`` the bus is shut down by :meth:`close`.

    Raises:
        ValueError: no ESCs, two with one node ID, a fault for an unknown node ID, or a poll
            period that is not > 0.
    """

    def __init__(
        self,
        bus: can.BusABC,
        escs: Sequence[SimEsc],
        *,
        battery: Battery | None = None,
        faults: Iterable[ScheduledFault] = (),
        poll_period_s: float = POLL_PERIOD_S,
        own_bus: bool = False,
        name: str = "esc-sim",
    ) -> None:
        self._thread: threading.Thread | None = None
        self._closed = True  # until fully built: a half-built simulator has nothing to close
        if not escs:
            raise ValueError("no ESCs to simulate")
        by_id = {esc.node_id: esc for esc in escs}
        if len(by_id) != len(escs):
            raise ValueError(f"node IDs {[e.node_id for e in escs]} are not distinct")
        pending = sorted(faults, key=lambda fault: fault.at_s)
        for fault in pending:
            if fault.node_id not in by_id:
                raise ValueError(f"{fault}: no ESC with node ID {fault.node_id}")
        if not poll_period_s > 0:
            raise ValueError(f"poll_period_s={poll_period_s!r}: expected > 0")
        self.bus = bus
        self.escs: tuple[SimEsc, ...] = tuple(escs)
        self.battery = battery or Battery()
        self.poll_period_s = poll_period_s
        self.name = name
        self.error: BaseException | None = None
        """What stopped the thread, if anything did other than close()."""
        self._by_id = by_id
        self._pending = pending
        self._own_bus = own_bus
        self._stats = SimStats()
        self._stop = threading.Event()
        self._started_s: float | None = None
        self._closed = False

    # -- lifecycle --------------------------------------------------------------------------

    def start(self) -> Simulator:
        """Start the thread; returns self.

        Raises:
            RuntimeError: already started or closed.
        """
        if self._closed or self._thread is not None:
            raise RuntimeError(f"simulator {self.name!r} already started or closed")
        self._started_s = time.monotonic()
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()
        return self

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the thread (and shut the bus down if it is ours). A second call does nothing."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("simulator thread %r did not stop within %.1f s", self.name, timeout_s)
        if self._own_bus:
            self.bus.shutdown()

    def __enter__(self) -> Simulator:
        if self._thread is None:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def stats(self) -> SimStats:
        """A snapshot of the counters."""
        return replace(self._stats)

    @property
    def elapsed_s(self) -> float:
        """Seconds since start (0 before)."""
        return 0.0 if self._started_s is None else time.monotonic() - self._started_s

    def set_fault(self, node_id: int, kind: FaultKind, on: bool = True) -> None:
        """Switch a fault of the ESC with ``node_id`` on or off now.

        Raises:
            KeyError: no ESC has ``node_id``.
            ValueError: an unknown fault kind.
        """
        if kind not in FAULT_KINDS:
            raise ValueError(f"kind={kind!r}: expected one of {', '.join(FAULT_KINDS)}")
        setattr(self._by_id[node_id].faults, kind, on)

    def status_line(self) -> str:
        """One line: elapsed time, rpm of each ESC (by node ID), battery, frame counts."""
        stats = self._stats
        rpm = " ".join(f"{esc.node_id}:{esc.motor.rpm:.0f}" for esc in self.escs)
        faults = [
            f"{esc.node_id}:{kind}"
            for esc in self.escs
            for kind in FAULT_KINDS
            if getattr(esc.faults, kind)
        ]
        line = (
            f"t={self.elapsed_s:.1f}s rpm {rpm} | battery {self.battery.voltage_v:.2f} V "
            f"{self.battery.current_a:.1f} A | frames in {stats.frames_in} out {stats.frames_out}"
        )
        if stats.send_failures:
            line += f" send failures {stats.send_failures}"
        if faults:
            line += " | faults " + " ".join(faults)
        return line

    # -- the thread -------------------------------------------------------------------------

    def _clock(self) -> float:
        """The ESCs' clock: monotonic seconds since start (0 is their power-up)."""
        assert self._started_s is not None
        return time.monotonic() - self._started_s

    def _run(self) -> None:
        try:
            self._loop()
        except Exception as exc:  # a bug in an ESC model: stop and say so, never hang
            self.error = exc
            log.exception("simulator %r stopped", self.name)

    def _loop(self) -> None:
        clock = self._clock
        period = self.poll_period_s
        next_poll = 0.0
        last_poll: float | None = None
        stop = self._stop
        while not stop.is_set():
            now = clock()
            if now >= next_poll:
                # Frames that queued while this process was not scheduled reached a real ESC on
                # time: take them before judging the ESC's command timeout, or a starved
                # simulator raises COMMS_FAULT for commands the bridge did send. Bounded, so a
                # flooded bus still gets its telemetry polled.
                for _ in range(DRAIN_MAX_FRAMES):
                    if not self._receive(0.0):
                        break
                now = clock()
                self._poll(now, last_poll)
                last_poll = now
                next_poll += period
                if next_poll <= now:  # behind by a period or more: skip, do not burst
                    skipped = int((now - next_poll) / period) + 1
                    self._stats.late_polls += skipped
                    next_poll += skipped * period
                continue
            self._receive(min(next_poll - now, RECV_TIMEOUT_S))

    def _receive(self, timeout_s: float) -> bool:
        """Take one frame, waiting up to ``timeout_s``; whether one came."""
        try:
            msg = self.bus.recv(timeout_s)
        except (can.CanError, OSError) as exc:
            self._stats.recv_failures += 1
            log.debug("simulator %r: receive failed: %s", self.name, exc)
            self._stop.wait(timeout_s)
            return False
        if msg is None:
            return False
        self._stats.frames_in += 1
        now = self._clock()
        for esc in self.escs:
            replies = esc.handle(msg, now)
            if replies:
                self._emit(esc, replies, now)
        return True

    def _poll(self, now: float, last_poll: float | None) -> None:
        while self._pending and now >= self._pending[0].at_s:
            fault = self._pending.pop(0)
            setattr(self._by_id[fault.node_id].faults, fault.kind, True)
            log.info("fault %s switched on for ESC %d", fault.kind, fault.node_id)
        supply_v = self.battery.voltage_v
        for esc in self.escs:
            frames = esc.poll(now, supply_v)
            if frames:
                self._emit(esc, frames, now)
        dt = 0.0 if last_poll is None else now - last_poll
        self.battery.step(dt, sum(esc.motor.current_a for esc in self.escs))
        self._stats.polls += 1

    def _emit(self, sender: SimEsc, frames: list[can.Message], now: float) -> None:
        """Send ``sender``'s frames, and let the other ESCs of this runner hear them as they
        would on a real bus (the bus handle never returns our own frames): an ESC may refuse
        set-up while it hears another ESC. ESCs never answer each other, so their replies to
        these are sent but not passed round again."""
        self._send(frames)
        for frame in frames:
            for other in self.escs:
                if other is not sender:
                    replies = other.handle(frame, now)
                    if replies:
                        self._send(replies)

    def _send(self, frames: list[can.Message]) -> None:
        stats = self._stats
        for frame in frames:
            try:
                self.bus.send(frame, timeout=0.0)
                stats.frames_out += 1
            except (can.CanError, OSError) as exc:
                level = logging.DEBUG if stats.send_failures else logging.WARNING
                stats.send_failures += 1
                log.log(level, "simulator %r: send failed (frame dropped): %s", self.name, exc)


SimBus = Simulator
"""Another name for :class:`Simulator`."""


def make_escs(
    protocol: str,
    n: int,
    ids: Sequence[int] | None = None,
    *,
    keys: Any = None,
    motor_params: MotorParams | None = None,
) -> list[SimEsc]:
    """``n`` simulated ESCs of the family ``protocol``, each with a motor of its own, from the
    family's simulator (its tool module ``sim.py``).

    ``ids``: the ESCs' IDs on the bus (default 1..n). ``keys``: the family's ``[escs]`` keys
    the simulated ESCs follow (such as throttle channels; default: the family's defaults).

    Raises:
        ValueError: an unknown protocol, ``n`` < 1, lists whose length is not ``n``, or IDs that
            are not distinct or out of the family's range.
    """
    if protocol not in registry.names():
        raise ValueError(
            f"protocol={protocol!r}: expected " + " or ".join(repr(n) for n in registry.names())
        )
    if n < 1:
        raise ValueError(f"n={n!r}: expected at least one ESC")
    ids = list(range(1, n + 1)) if ids is None else list(ids)
    if len(ids) != n:
        raise ValueError(f"ids={ids!r}: {len(ids)} IDs for {n} ESCs")
    if len(set(ids)) != n:
        raise ValueError(f"ids={ids!r}: expected distinct IDs")
    family = registry.family(protocol)
    allowed = family.node_ids
    if not all(i in allowed for i in ids):
        raise ValueError(f"ids={ids!r}: {protocol} IDs must be {allowed.start}..{allowed.stop - 1}")
    tool = registry.tool(protocol, "sim")
    if tool is None:
        raise ValueError(f"protocol={protocol!r}: the family has no simulator")
    simulators: Simulators = tool.simulators
    return simulators(EscSetup(tuple(ids), family.keys() if keys is None else keys), motor_params)
