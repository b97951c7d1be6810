"""Lock-free hand-over between the bridge's two sides, across processes or threads.

The control loop (its own real-time process where the bus allows it) owns the autopilot link,
the mixer and the CAN transmit handle; the best-effort side (the main process: commands from
ground stations, telemetry, logging) must never make it wait, and it must never wait on them.
What little crosses between them goes through shared memory, one writer per block:

* :class:`MotorTestBlock`: a MAV_CMD_DO_MOTOR_TEST accepted by the main process, for the loop;
* :class:`InputSnapshot`: the input the loop acts on (its mix, when the autopilot produced it,
  the arming state), for the main process's health report and motor-test checks;
* :class:`SentCommands`: the commands the loop last sent, for the main process's reports;
* :class:`LoopStats`: the loop's counters, single 8-byte words.

A block is ``seq | body | CRC-32 of seq and body``. The writer packs all three; a reader copies
the whole block in one go and accepts the copy only if its CRC matches. A copy taken while a
write was in progress mixes old and new bytes and fails the check, whatever order the stores
reached memory in, so the hand-over needs no memory barrier and holds on the weak ordering of
ARM64 (the Raspberry Pi, the Jetson) as on x86: a reader never sees a new sequence number with
an old body. (A torn copy passes the check with probability 2^-32; a torn copy needs a reader
and the writer within the same microsecond, a few times a second at most.) A reader that
keeps colliding with writes keeps the last good copy it read: a collision never turns into
"no input" or "disarmed".

The memory is ``multiprocessing`` RawArrays from the spawn context: handed to the loop's
process when it starts (no named segment to leak), and working the same within one process.
"""

from __future__ import annotations

import math
import multiprocessing
import struct
import zlib
from dataclasses import dataclass
from typing import Any

from bridge.mixing.definition import INPUT_NAMES
from bridge.output.safety import LoopState
from bridge.output.transmit import TxState

INPUT_VECTOR_LEN = len(INPUT_NAMES)

__all__ = [
    "LATENESS_RING",
    "SENT_COMMANDS",
    "SENT_SAFE",
    "SENT_TEST",
    "STAT_FIELDS",
    "InputSnapshot",
    "LoopState",
    "LoopStats",
    "MotorTest",
    "MotorTestBlock",
    "Sent",
    "SentCommands",
    "SharedBlock",
    "Snapshot",
]

_READ_ATTEMPTS = 4  # copies tried per read before the last good one is returned
_SEQ = struct.Struct("<Q")
_CRC = struct.Struct("<I")


class SharedBlock:
    """One record of fixed layout (a :mod:`struct` format), one writer, any number of readers,
    in any processes; see the module docstring for why a CRC rather than a seqlock."""

    def __init__(self, body_format: str, ctx: Any = None) -> None:
        ctx = ctx or multiprocessing.get_context("spawn")
        self._format = body_format
        self._raw = ctx.RawArray("B", _SEQ.size + struct.calcsize("<" + body_format) + _CRC.size)
        self._attach()

    def _attach(self) -> None:
        self._record = struct.Struct("<Q" + self._format)
        self._crc_at = self._record.size
        self._buf = memoryview(self._raw).cast("B")
        self._seq_word = memoryview(self._raw).cast("B")[: _SEQ.size].cast("Q")
        self._seq = 0
        self._last: tuple[Any, ...] | None = None  # the reader's last good copy

    def __getstate__(self) -> dict[str, Any]:
        return {"format": self._format, "raw": self._raw}  # views are made again on arrival

    def __setstate__(self, state: dict[str, Any]) -> None:
        self._format, self._raw = state["format"], state["raw"]
        self._attach()

    def write(self, *body: Any) -> None:
        """Publish a new record (the writer's sequence number goes up by one).

        Raises:
            struct.error: ``body`` does not fit the format.
        """
        self._seq += 1
        buf = self._buf
        self._record.pack_into(buf, 0, self._seq, *body)
        _CRC.pack_into(buf, self._crc_at, zlib.crc32(buf[: self._crc_at]))

    def seq(self) -> int:
        """The sequence number in memory now (one 8-byte load, possibly of a write in
        progress): cheap, to skip a read when nothing changed. 0 before the first write."""
        return int(self._seq_word[0])

    def read(self) -> tuple[Any, ...] | None:
        """``(seq, *body)`` of the newest whole record; the last good one read if every copy
        collided with a write; None before the first write."""
        crc_at = self._crc_at
        for _ in range(_READ_ATTEMPTS):
            copy = bytes(self._buf)
            if zlib.crc32(copy[:crc_at]) == _CRC.unpack_from(copy, crc_at)[0]:
                record: tuple[Any, ...] = self._record.unpack_from(copy)
                self._last = record
                return record
        return self._last  # None before the first write: zeros do not pass the CRC


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


class MotorTestBlock:
    """MAV_CMD_DO_MOTOR_TEST from the main process to the loop. One writer at a time: callers
    on several threads hold a lock of their own around the writes."""

    # first output index, count (0 = none), fraction, start ns, on ns, step ns
    _BODY = "qqdqqq"

    def __init__(self, n_outputs: int, ctx: Any = None) -> None:
        self.n_outputs = n_outputs
        self._block = SharedBlock(self._BODY, ctx)

    def write_motor_test(
        self, first: int, count: int, fraction: float, start_ns: int, on_ns: int, step_ns: int
    ) -> None:
        """Start a motor test (replacing any): see :class:`MotorTest`.

        Raises:
            ValueError: outputs outside the block's, a fraction outside 0..1 (or NaN), or
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
        self._block.write(first, count, fraction, start_ns, on_ns, step_ns)

    def stop_motor_test(self) -> None:
        """End any motor test at once (the loop reads it on its next tick)."""
        self._block.write(0, 0, 0.0, 0, 1, 1)

    def read_motor_test(self, last_seq: int) -> MotorTest | None:
        """The motor test written since ``last_seq`` (the ``seq`` of the last one read, 0 at
        first), or None when nothing new was written (or a write is in progress: the next call
        reads it). The loop calls this every tick: when nothing changed it costs one 8-byte
        load."""
        if self._block.seq() == last_seq:
            return None
        record = self._block.read()
        if record is None or record[0] == last_seq:
            return None
        return MotorTest(*record)


@dataclass(frozen=True, slots=True)
class Snapshot:
    """The input the loop acts on, as the main process read it."""

    seq: int
    produced_ns: int
    """When the autopilot produced the newest input (local monotonic ns); 0 = none yet."""
    valid: bool
    armed: bool
    armed_heard_ns: int
    """When the arming state was last heard (monotonic ns); 0 = never."""
    fractions: tuple[float, ...]
    """The mix of the newest input (empty when invalid)."""
    inputs: tuple[float, ...]
    """The newest input vector as decoded (``bridge.mixing.definition.INPUT_NAMES`` order,
    NaN = absent); empty before the first."""


class InputSnapshot:
    """The loop's newest input and arming state, for the main process (best-effort reading)."""

    def __init__(self, n_outputs: int, n_inputs: int = INPUT_VECTOR_LEN, ctx: Any = None) -> None:
        self.n_outputs = n_outputs
        self._n_inputs = n_inputs
        self._block = SharedBlock(f"qqqq{n_outputs}d{n_inputs}d", ctx)
        self._no_fractions = (math.nan,) * n_outputs
        self._no_inputs = (math.nan,) * n_inputs

    def write(
        self,
        produced_ns: int,
        fractions: list[float] | None,
        armed: bool,
        armed_heard_ns: int,
        inputs: list[float] | None,
    ) -> None:
        """From the loop, on each input and each HEARTBEAT."""
        self._block.write(
            produced_ns,
            fractions is not None,
            armed,
            armed_heard_ns,
            *(self._no_fractions if fractions is None else fractions),
            *(self._no_inputs if inputs is None else inputs),
        )

    def read(self) -> Snapshot | None:
        """The newest snapshot; None before the loop wrote one."""
        record = self._block.read()
        if record is None:
            return None
        seq, produced_ns, valid, armed, heard_ns, *values = record
        fractions, inputs = values[: self.n_outputs], values[self.n_outputs :]
        return Snapshot(
            seq,
            produced_ns,
            bool(valid),
            bool(armed),
            heard_ns,
            tuple(fractions) if valid else (),
            tuple(inputs) if produced_ns else (),
        )


SENT_COMMANDS, SENT_SAFE, SENT_TEST = 1, 2, 3
"""What a tick's frames carry: the commands of some fractions; the safe values; a motor test
(one motor at its test fraction, the others at their safe values)."""


@dataclass(frozen=True, slots=True)
class Sent:
    """The commands the loop last put on the bus, as the main process read them."""

    seq: int
    kind: int
    """:data:`SENT_COMMANDS`, :data:`SENT_SAFE` or :data:`SENT_TEST`."""
    test_index: int
    """The motor a motor test spins, 0-based (with :data:`SENT_TEST`)."""
    fractions: tuple[float, ...]
    """The fractions the commands carry (with :data:`SENT_COMMANDS` and :data:`SENT_TEST`)."""


class SentCommands:
    """The commands the loop last sent, for the main process (the ESC state's ``command``, the
    ``actuators/output`` key): the loop knows what it sent, so nothing reads it back off the
    bus. Written when the commands change (per input at most, without slew rates)."""

    def __init__(self, n_outputs: int, ctx: Any = None) -> None:
        self.n_outputs = n_outputs
        self._block = SharedBlock(f"qq{n_outputs}d", ctx)

    def write(self, kind: int, test_index: int, fractions: list[float]) -> None:
        """From the loop, when what it sends changes."""
        self._block.write(kind, test_index, *fractions)

    def seq(self) -> int:
        """The sequence number in memory now: cheap, to skip a read when nothing changed."""
        return self._block.seq()

    def read(self) -> Sent | None:
        """The newest record; None before the loop wrote one."""
        record = self._block.read()
        if record is None:
            return None
        seq, kind, test_index, *fractions = record
        return Sent(seq, kind, test_index, tuple(fractions))


STAT_FIELDS = (
    "state",  # LoopState
    "ticks",
    "frames_sent",
    "send_errors",
    "bus_reopens",
    "overruns",  # ticks skipped because the loop woke more than a period late
    "immediate_sends",  # ticks sent at once for a fresh input (latency = "immediate")
    "tick_errors",  # ticks whose commands could not be encoded: safe values were sent instead
    "redecided",  # ticks decided again: the loop was held up over a period before sending
    "left_late",  # ticks whose frames left over a period after their decision (held up sending)
    "realtime",  # 1 when the loop runs with SCHED_FIFO priority
    "stop_requested",  # written by the supervisor: the one field the loop only reads
    "lateness_count",  # entries written to the lateness ring
    "motor_test_motor",  # the motor a motor test spins now, 1-based; 0 = none
    "input_frames",  # MAVLink frames the loop found on the autopilot link
    "input_outputs",  # motor-output messages from the autopilot it acted on
    "input_heartbeats",  # HEARTBEATs (arming state) from the autopilot
    "input_foreign",  # motor outputs or HEARTBEATs from any other system or component
    "input_other_address",  # UDP: frames claiming the autopilot's IDs from another address
    "input_other_address_from",  # where the latest of those came from (address_code); 0: none
    "input_bad_crc",  # frames of known messages with a bad CRC
    "input_junk_bytes",  # bytes skipped while looking for a frame
    "input_unsigned",  # with a signing key: control messages refused (unsigned, bad, replayed)
    "input_out_of_order",  # inputs older than the newest one acted on, ignored
    "input_invalid",  # inputs with an absent, non-finite or out-of-range channel
    "mixer_errors",  # inputs whose mixing raised: safe values
    "relay_dropped",  # chunks the main process was too slow to take (best-effort only)
    "link_sent",  # frames from the main process written to the autopilot link
    "link_dropped",  # frames for the autopilot link dropped (link down or full)
    "link_reconnects",
    "link_autopilot_address",  # UDP: the autopilot's address (address_code); 0: not known yet
    "link_autopilot_moves",  # UDP: times another address took a silent autopilot's place
    "input_age_us",  # age of the newest input when it was acted on (produced -> acted), µs
    # How many times the loop entered each state, in LoopState's order: the supervisor reports
    # every state entered since it last looked, even one left again before it looked.
    *(f"entered_{state.name.lower()}" for state in LoopState),
    "tx_state",  # TxState: how the loop's frames are leaving (bridge.output.transmit)
    "ticks_held",  # ticks not sent: frames of an earlier tick were still in the kernel
    "tx_probes",  # ticks sent after the frames in flight were taken for lost (no echo)
    # How many times the transmit side entered each TxState, as for the loop's states.
    *(f"entered_tx_{state.name.lower()}" for state in TxState),
)
LATENESS_RING = 1 << 16  # wake-up lateness samples kept, µs; enough for 160 s at 400 Hz


class LoopStats:
    """Counters the control loop publishes; plain int64 slots, each with a single writer.

    Aligned 8-byte stores are single-copy atomic on x86-64 and ARM64, so single counters need
    no checksum; the supervisor only samples them for logs, health and benchmarks.
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

    def state_entries(self) -> list[int]:
        """How many times the loop entered each state, indexed by :class:`LoopState`."""
        first = self._index["entered_starting"]
        return list(self._counters[first : first + len(LoopState)])

    def tx_state_entries(self) -> list[int]:
        """How many times the transmit side entered each state, indexed by :class:`TxState`."""
        first = self._index["entered_tx_moving"]
        return list(self._counters[first : first + len(TxState)])

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
