"""Lock-free hand-over between the input side and the output loop, across processes or threads.

The output loop may run in a process of its own (free of the main process's GIL), so the
mixer's newest command vector, the arming state and a motor test (MAV_CMD_DO_MOTOR_TEST) reach
it through shared memory rather than a queue: the loop must never wait on the input side, and
the input side must never wait on the loop. Each block has one writer and is guarded by a
sequence counter (a seqlock): the writer makes the counter odd, writes, and makes it even
again; a reader that sees an odd or changed counter reads again. Both sides only copy a few
dozen bytes, so a retry is rare and cheap, and neither side ever blocks.

The memory is a ``multiprocessing`` RawArray from the spawn context: it is handed to the loop's
process when it starts (no named segment to leak) and works the same within one process.
"""

from __future__ import annotations

import enum
import multiprocessing
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

# A read that keeps colliding with writes gives up and reports "nothing new" for this tick;
# the writer finishes within microseconds, so the next tick reads it.
_READ_ATTEMPTS = 4

# Block layout: seq u64, then the body. The body is written only while seq is odd, and seq is
# made even by a store of its own, so a reader that sees the same even seq before and after
# reading the body has read one whole write.
_SEQ = struct.Struct("<Q")
_BODY = struct.Struct("<qq")  # input time ns, valid (1) or not (0); the values follow
_ARMED_BODY = struct.Struct("<qq")  # armed time ns, armed
# A motor test: first output index, count (0 = none), fraction, start ns, on ns, step ns.
_TEST_BODY = struct.Struct("<qqdqqq")
_VALUES_AT = _SEQ.size + _BODY.size


class LoopState(enum.IntEnum):
    """What the output loop is sending and why (safe unless RUNNING)."""

    STARTING = 0  # the loop has not opened the bus yet
    NO_INPUT = 1  # no valid input since start
    DISARMED = 2
    STALE = 3  # the last valid input is older than the input timeout
    INVALID = 4  # the newest input had a NaN or infinite value, or the mixer failed
    RUNNING = 5  # the mixer's commands are sent
    STOPPING = 6  # shutdown: safe values for shutdown_flush_ms, then exit
    STOPPED = 7
    FAILED = 8  # the loop could not start (e.g. the bus did not open)
    MOTOR_TEST = 9  # disarmed, a motor test runs: one motor at its test throttle, others safe


@dataclass(frozen=True, slots=True)
class Commands:
    """The newest command vector as the loop read it."""

    seq: int  # grows with every write; equal seq means nothing new
    time_ns: int  # time.monotonic_ns() when the input arrived
    valid: bool  # False: the input or mixer failed; send safe values
    fractions: tuple[float, ...]  # one per mixer output, in the mixer's [min, max]


@dataclass(frozen=True, slots=True)
class MotorTest:
    """A motor test as the loop read it: outputs ``first .. first + count - 1`` one after
    another, each at ``fraction`` for ``on_ns``, a new one every ``step_ns`` from ``start_ns``
    (monotonic); safe values between them. ``count`` 0 means no test (stopped)."""

    seq: int
    first: int
    count: int
    fraction: float
    start_ns: int
    on_ns: int
    step_ns: int

    @property
    def until_ns(self) -> int:
        """When the last motor stops; 0 for no test."""
        if self.count <= 0:
            return 0
        return self.start_ns + (self.count - 1) * self.step_ns + self.on_ns

    def index_at(self, now_ns: int) -> int:
        """The output spinning at ``now_ns``, or -1 (before, between motors, after)."""
        elapsed = now_ns - self.start_ns
        if elapsed < 0 or self.count <= 0:
            return -1
        k, into = divmod(elapsed, self.step_ns)
        return self.first + k if k < self.count and into < self.on_ns else -1


class CommandMailbox:
    """The mixer's newest output; written by the input side, read by the output loop."""

    def __init__(self, n_outputs: int, ctx: Any = None) -> None:
        ctx = ctx or multiprocessing.get_context("spawn")
        self.n_outputs = n_outputs
        self._values = struct.Struct(f"<{n_outputs}d")
        self._raw = ctx.RawArray("B", _VALUES_AT + self._values.size)
        self._armed_raw = ctx.RawArray("B", _SEQ.size + _ARMED_BODY.size)
        self._test_raw = ctx.RawArray("B", _SEQ.size + _TEST_BODY.size)
        self._attach()

    def _attach(self) -> None:
        self._buf = memoryview(self._raw).cast("B")
        self._armed_buf = memoryview(self._armed_raw).cast("B")
        self._test_buf = memoryview(self._test_raw).cast("B")
        self._test_words = memoryview(self._test_raw).cast("B").cast("q")  # [0] is its seq
        self._seq = 0
        self._armed_seq = 0
        self._test_seq = 0

    def __getstate__(self) -> dict[str, Any]:
        # Only the shared arrays travel to the loop's process; views are made again there.
        return {
            "n": self.n_outputs,
            "raw": self._raw,
            "armed_raw": self._armed_raw,
            "test_raw": self._test_raw,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.n_outputs = state["n"]
        self._values = struct.Struct(f"<{self.n_outputs}d")
        self._raw = state["raw"]
        self._armed_raw = state["armed_raw"]
        self._test_raw = state["test_raw"]
        self._attach()

    # -- writer side (the input thread) --------------------------------------------------

    def write(self, fractions: Sequence[float] | None, time_ns: int) -> None:
        """Publish a new command vector; ``None`` marks the input as invalid (go safe)."""
        buf = self._buf
        self._seq += 1  # odd: a write is in progress
        _SEQ.pack_into(buf, 0, self._seq)
        _BODY.pack_into(buf, _SEQ.size, time_ns, fractions is not None)
        if fractions is not None:
            self._values.pack_into(buf, _VALUES_AT, *fractions)
        self._seq += 1
        _SEQ.pack_into(buf, 0, self._seq)

    def write_armed(self, armed: bool, time_ns: int) -> None:
        buf = self._armed_buf
        self._armed_seq += 1
        _SEQ.pack_into(buf, 0, self._armed_seq)
        _ARMED_BODY.pack_into(buf, _SEQ.size, time_ns, armed)
        self._armed_seq += 1
        _SEQ.pack_into(buf, 0, self._armed_seq)

    def write_motor_test(
        self, first: int, count: int, fraction: float, start_ns: int, on_ns: int, step_ns: int
    ) -> None:
        """Start a motor test (replacing any): see :class:`MotorTest`. One writer at a time:
        callers on several threads hold a lock of their own around this.

        Raises:
            ValueError: outputs outside the mailbox's, a fraction outside 0..1 (or NaN), or
                times that are not ``0 < on_ns <= step_ns``.
        """
        if not (first >= 0 and count >= 1 and first + count <= self.n_outputs):
            raise ValueError(
                f"first={first!r}, count={count!r}: expected outputs within 0..{self.n_outputs - 1}"
            )
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"fraction={fraction!r}: expected 0..1")
        if not 0 < on_ns <= step_ns:
            raise ValueError(f"on_ns={on_ns!r}, step_ns={step_ns!r}: expected 0 < on <= step")
        self._write_test(first, count, fraction, start_ns, on_ns, step_ns)

    def stop_motor_test(self) -> None:
        """End any motor test at once (the loop reads it on its next tick)."""
        self._write_test(0, 0, 0.0, 0, 1, 1)

    def _write_test(
        self, first: int, count: int, fraction: float, start_ns: int, on_ns: int, step_ns: int
    ) -> None:
        buf = self._test_buf
        self._test_seq += 1
        _SEQ.pack_into(buf, 0, self._test_seq)
        _TEST_BODY.pack_into(buf, _SEQ.size, first, count, fraction, start_ns, on_ns, step_ns)
        self._test_seq += 1
        _SEQ.pack_into(buf, 0, self._test_seq)

    # -- reader side (the output loop) ---------------------------------------------------

    def read(self) -> Commands | None:
        """The newest vector, or None before the first write (or after colliding writes)."""
        buf = self._buf
        for _ in range(_READ_ATTEMPTS):
            (seq,) = _SEQ.unpack_from(buf, 0)
            if seq == 0:
                return None
            if seq & 1:
                continue
            time_ns, valid = _BODY.unpack_from(buf, _SEQ.size)
            values = self._values.unpack_from(buf, _VALUES_AT) if valid else ()
            if _SEQ.unpack_from(buf, 0)[0] == seq:
                return Commands(seq, time_ns, bool(valid), values)
        return None

    def read_armed(self) -> bool:
        """The autopilot's arming state; False until it has been heard."""
        buf = self._armed_buf
        for _ in range(_READ_ATTEMPTS):
            (seq,) = _SEQ.unpack_from(buf, 0)
            if seq & 1:
                continue
            _, armed = _ARMED_BODY.unpack_from(buf, _SEQ.size)
            if _SEQ.unpack_from(buf, 0)[0] == seq:
                return bool(armed)
        return False

    def read_motor_test(self, last_seq: int) -> MotorTest | None:
        """The motor test written since ``last_seq`` (the ``seq`` of the last one read, 0 at
        first), or None when nothing new was written (or colliding writes kept it from being
        read; the next call reads it). The loop calls this every tick: when nothing changed it
        costs one 8-byte read."""
        seq: int = self._test_words[0]
        if seq == last_seq:
            return None
        buf = self._test_buf
        for _ in range(_READ_ATTEMPTS):
            if seq & 1 == 0:
                body = _TEST_BODY.unpack_from(buf, _SEQ.size)
                if _SEQ.unpack_from(buf, 0)[0] == seq:
                    return MotorTest(seq, *body)
            seq = self._test_words[0]
        return None


STAT_FIELDS = (
    "state",  # LoopState
    "ticks",
    "frames_sent",
    "send_errors",
    "bus_reopens",
    "overruns",  # ticks skipped because the loop woke more than a period late
    "immediate_sends",  # ticks sent at once for a fresh input (latency = "immediate")
    "tick_errors",  # ticks whose commands could not be encoded: safe values were sent instead
    "realtime",  # 1 when the loop runs with SCHED_FIFO priority
    "stop_requested",  # written by the supervisor: the one field the loop only reads
    "lateness_count",  # entries written to the lateness ring
    "motor_test_motor",  # the motor a motor test spins now, 1-based; 0 = none
)
LATENESS_RING = 1 << 16  # wake-up lateness samples kept, µs; enough for 160 s at 400 Hz


class LoopStats:
    """Counters the output loop publishes; plain int64 slots, each with a single writer.

    Aligned 8-byte stores are not torn on the platforms we run on, so single counters need
    no seqlock; the supervisor only samples them for logs, health and benchmarks.
    """

    def __init__(self, ctx: Any = None) -> None:
        ctx = ctx or multiprocessing.get_context("spawn")
        self._counters = ctx.RawArray("q", len(STAT_FIELDS))
        self._lateness = ctx.RawArray("i", LATENESS_RING)
        self._index = {name: i for i, name in enumerate(STAT_FIELDS)}

    def __getitem__(self, name: str) -> int:
        return int(self._counters[self._index[name]])

    def __setitem__(self, name: str, value: int) -> None:
        self._counters[self._index[name]] = value

    def slot(self, name: str) -> int:
        """The index of a counter, for the loop's hot path (no dict lookup per tick)."""
        return self._index[name]

    @property
    def counters(self) -> Any:
        return self._counters

    @property
    def lateness_ring(self) -> Any:
        return self._lateness

    def lateness_us(self) -> list[int]:
        """The wake-up lateness samples recorded so far (up to the ring's size), µs."""
        count = self["lateness_count"]
        n = min(count, LATENESS_RING)
        if count <= LATENESS_RING:
            return list(self._lateness[:n])
        start = count % LATENESS_RING
        return list(self._lateness[start:]) + list(self._lateness[:start])
