"""The safety path against a model: random sequences of events, and never an unsafe frame.

The system under test is the loop's own per-tick code (:class:`CommandSelector`: the safety
decision, motor tests, the slew limiter, the fault handling) driving a real CKESC driver; its
frames are decoded back to throttles. The model is written from the rules in docs/running.md,
"Safe values", apart from the code: what each motor may receive at each moment. A frame is unsafe
when a motor gets a throttle the model does not allow: anything but 0 in a safe state, anything
but the newest valid input's command while running, anything but the test throttle on the
motor under test (and 0 on the others) during a motor test.

Events: an input (valid, out of range, or one the mixer cannot take: a fault), produced some
time before it arrives (late delivery, a stalled process); a stream of inputs at some interval
(fast enough to start the motors or not); the autopilot's HEARTBEAT armed or
disarmed; silence (time passing: staleness, HEARTBEAT loss); a motor test or its stop; a stop
signal or the main process's death (the loop flushes); ticks. Two drivers: hypothesis's state
machine (shrinks a failure to its shortest sequence) and a seeded random walk that runs many
more sequences cheaply (``ESC_BRIDGE_MODEL_SEQUENCES``, default 10 000; docs/development.md's
claim of 10^5 is measured with that variable set).
"""

from __future__ import annotations

import os
import random
from dataclasses import dataclass, field

from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from bridge.escs.ckesc import codec, records
from bridge.escs.ckesc.driver import CkescDriver
from bridge.output.mailbox import MotorTest
from bridge.output.output_loop import CommandSelector
from bridge.output.safety import ControlInputs, SafetyLimits
from bridge.output.slew import SlewLimiter

N = 4
MS = 1_000_000
INPUT_TIMEOUT_NS = 100 * MS
ARMING_TIMEOUT_NS = 3000 * MS
FULL = records.THROTTLE_MAX


@dataclass
class Model:
    """What the rules allow, kept apart from the code under test."""

    now_ns: int = 10_000 * MS
    stopping: bool = False
    armed: bool = False
    heard_ns: int | None = None
    produced_ns: int | None = None
    command: list[float] | None = None  # the newest input's fractions; None: invalid
    test: MotorTest | None = None
    test_cancelled: bool = False
    # The stream's mean interval, as docs/running.md defines it: each new interval moves
    # it 1/8 of the way; it counts after 3 intervals.
    intervals: int = 0
    interval_ns: int = 0
    engaged: bool = False  # in flight: running, or stopped only by a stale or invalid input
    seq: int = 0
    log: list[str] = field(default_factory=list)

    def heartbeat_fresh(self) -> bool:
        return self.heard_ns is not None and self.now_ns - self.heard_ns <= ARMING_TIMEOUT_NS

    def note_input(self, produced_ns: int) -> None:
        if self.produced_ns is not None:
            interval = produced_ns - self.produced_ns
            if self.intervals == 0:
                self.interval_ns = interval
            else:
                self.interval_ns += (interval - self.interval_ns) // 8
            self.intervals += 1
        self.produced_ns = produced_ns

    def allowed(self) -> list[int]:
        """The throttle each motor must get now."""
        safe = [0] * N
        engaged, self.engaged = self.engaged, False
        if self.stopping:
            return safe
        test = self.test
        if test is not None and test.count and not self.test_cancelled:
            if self.now_ns >= test.until_ns:
                pass
            elif self.armed or not self.heartbeat_fresh():
                self.test_cancelled = True  # arming or silence ends a test for good
            else:
                spinning = test.index_at(self.now_ns)
                if spinning >= 0:
                    safe[spinning] = int(test.fraction * FULL + 0.5)
                return safe
        if self.produced_ns is None or not self.heartbeat_fresh() or not self.armed:
            return safe
        slow = self.intervals < 3 or 2 * self.interval_ns > INPUT_TIMEOUT_NS
        if slow and not engaged:
            return safe  # a stream too slow never starts the motors
        self.engaged = True
        if self.now_ns - self.produced_ns > INPUT_TIMEOUT_NS or self.command is None:
            return safe
        return [int(fraction * FULL + 0.5) for fraction in self.command]


class Harness:
    """The code under test and the model, fed the same events."""

    def __init__(self) -> None:
        self.model = Model()
        self.inputs = ControlInputs()
        limits = SafetyLimits(True, INPUT_TIMEOUT_NS, ARMING_TIMEOUT_NS)
        slew = SlewLimiter([0.0] * N, [0.0] * N)  # unlimited: the model expects the command
        self.selector = CommandSelector(
            CkescDriver("12b", range(1, N + 1)), slew, limits, self.inputs, N
        )
        self.fractions: list[float] | None = None
        self.tick = 0

    def input(self, fractions: list[float] | None, late_ms: int, fault: bool = False) -> None:
        model = self.model
        produced = model.now_ns - late_ms * MS
        if self.inputs.have_input and produced < self.inputs.input_produced_ns:
            return  # the loop ignores an input overtaken by a newer one; so does the model
        model.log.append(f"input {fractions} late {late_ms} ms fault={fault}")
        # A fault: a vector the slew limiter cannot take (the loop's tick fault).
        self.fractions = [0.5] * (N - 1) if fault else fractions
        self.inputs.note_input(produced, fractions is not None)
        model.note_input(produced)
        model.command = None if fault or fractions is None else fractions

    def stream(self, fractions: list[float], count: int, interval_ms: float) -> None:
        """``count`` inputs ``interval_ms`` apart, a tick after each."""
        for _ in range(count):
            self.input(fractions, 0)
            self.check_tick()
            self.advance(interval_ms)

    def heartbeat(self, armed: bool) -> None:
        self.model.log.append(f"heartbeat armed={armed}")
        self.inputs.armed = armed
        self.inputs.armed_heard_ns = self.model.now_ns
        self.model.armed = armed
        self.model.heard_ns = self.model.now_ns

    def motor_test(self, first: int, count: int, fraction: float, on_ms: int) -> None:
        model = self.model
        model.seq += 1
        test = MotorTest(
            model.seq, first, count, fraction, model.now_ns, on_ms * MS, on_ms * MS * 2
        )
        model.log.append(f"motor test {test}")
        self.selector.start_motor_test(test)
        model.test = test
        model.test_cancelled = False

    def stop(self) -> None:
        self.model.log.append("stop signal or main process death")
        self.inputs.stopping = True
        self.model.stopping = True

    def advance(self, ms: float) -> None:
        self.model.now_ns += int(ms * MS)

    def check_tick(self) -> None:
        model = self.model
        frames = self.selector.select(self.tick, model.now_ns, self.fractions, 0.0025)
        self.tick += 1
        throttles: list[int] = []
        for frame in frames:
            decoded = codec.decode(frame)
            assert decoded is not None and isinstance(decoded.message, records.RawCommand12b)
            throttles.extend(decoded.message.throttles)
        expected = model.allowed()
        assert throttles[:N] == expected, (
            f"unsafe frame: sent {throttles[:N]}, allowed {expected} in state "
            f"{self.selector.state.name}\n" + "\n".join(model.log[-20:])
        )


FRACTIONS = st.lists(st.floats(0.0, 1.0), min_size=N, max_size=N)


class SafetyMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.h = Harness()

    @rule(fractions=FRACTIONS, late_ms=st.sampled_from([0, 5, 50, 99, 101, 500, 3000]))
    def input(self, fractions: list[float], late_ms: int) -> None:
        self.h.input(fractions, late_ms)

    @rule(
        fractions=FRACTIONS,
        count=st.integers(1, 12),
        interval_ms=st.sampled_from([2.5, 5, 20, 49, 51, 60, 99]),
    )
    def stream(self, fractions: list[float], count: int, interval_ms: float) -> None:
        self.h.stream(fractions, count, interval_ms)

    @rule(late_ms=st.sampled_from([0, 20]))
    def invalid_input(self, late_ms: int) -> None:
        self.h.input(None, late_ms)

    @rule()
    def faulty_input(self) -> None:
        self.h.input([0.5] * N, 0, fault=True)

    @rule(armed=st.booleans())
    def heartbeat(self, armed: bool) -> None:
        self.h.heartbeat(armed)

    @rule(ms=st.sampled_from([1, 2.5, 10, 60, 99, 101, 150, 1000, 2999, 3001, 5000]))
    def silence(self, ms: float) -> None:
        self.h.advance(ms)

    @rule(
        first=st.integers(0, N - 1),
        count=st.integers(0, N),
        fraction=st.floats(0.0, 1.0),
        on_ms=st.sampled_from([5, 50, 500]),
    )
    def motor_test(self, first: int, count: int, fraction: float, on_ms: int) -> None:
        self.h.motor_test(first, min(count, N - first), fraction, on_ms)

    @rule()
    def stop(self) -> None:
        self.h.stop()

    @rule()
    def tick(self) -> None:
        self.h.check_tick()

    @invariant()
    def every_moment_is_safe(self) -> None:
        self.h.check_tick()


SafetyMachine.TestCase.settings = settings(
    max_examples=int(os.environ.get("ESC_BRIDGE_MODEL_EXAMPLES", "300")),
    stateful_step_count=40,
    deadline=None,
)
test_safety_state_machine = SafetyMachine.TestCase


def test_random_walks_never_send_an_unsafe_frame() -> None:
    """Many more sequences than hypothesis affords, each a seeded random walk."""
    sequences = int(os.environ.get("ESC_BRIDGE_MODEL_SEQUENCES", "10000"))
    rng = random.Random(20261124)
    for _ in range(sequences):
        h = Harness()
        for _ in range(rng.randint(5, 40)):
            event = rng.random()
            if event < 0.12:
                h.stream(
                    [rng.random() for _ in range(N)],
                    rng.randint(1, 12),
                    rng.choice((2.5, 5, 20, 49, 51, 60, 99)),
                )
            elif event < 0.30:
                h.input(
                    [rng.choice((0.0, 0.3, 1.0, rng.random())) for _ in range(N)],
                    rng.choice((0, 3, 50, 101, 2700)),
                )
            elif event < 0.35:
                h.input(None, 0)
            elif event < 0.38:
                h.input([0.4] * N, 0, fault=True)
            elif event < 0.55:
                h.heartbeat(rng.random() < 0.7)
            elif event < 0.80:
                h.advance(rng.choice((2.5, 10, 99, 101, 400, 2999, 3001)))
            elif event < 0.88:
                first = rng.randrange(N)
                h.motor_test(
                    first, rng.randint(0, N - first), rng.random(), rng.choice((5, 50, 500))
                )
            elif event < 0.90:
                h.stop()
            h.check_tick()
