"""The safety decision: what the output loop may send on this tick, and why.

Pure: the loop passes in what it knows (the newest mixed input and when the autopilot produced
it, the autopilot's arming state and when it was heard, a motor test, a stop request) and the
time; :func:`decide` answers with a :class:`LoopState`. Everything but ``RUNNING`` and
``MOTOR_TEST`` means the safe values; ``MOTOR_TEST`` means one motor at its test throttle and
every other one safe. A hypothesis state machine (``tests/output/test_safety_model.py``) drives this
function and the real loop through random event sequences against a model of these rules.

The rules, first match wins:

1. stopping (a signal, the supervisor, the supervisor's death): ``STOPPING``;
2. a motor test whose time is not up, while the autopilot is known to be disarmed (its
   HEARTBEAT fresh): ``MOTOR_TEST``. Arming, or losing the autopilot's HEARTBEAT, ends the test
   for good (the caller clears it: :attr:`ControlInputs.motor_test_until_ns` = 0);
3. no usable input since start: ``NO_INPUT``;
4. arming required and the autopilot disarmed: ``DISARMED``; arming required and its
   HEARTBEAT older than the arming timeout: ``HEARTBEAT_LOST`` (ArduPilot and PX4 send one a
   second on every link, so three missing ones mean the autopilot or the link is gone);
   the motors stopped (the previous tick was none of ``RUNNING``, ``STALE``, ``INVALID``) and
   the inputs arriving less often than twice per input timeout (their mean interval, see
   :meth:`ControlInputs.note_input`): ``SLOW_STREAM``. A stream that slow would flap between
   running and stale, so it never starts the motors; one that slows in flight is left to the
   staleness rule, which stops them only for as long as an input is missing;
5. the newest input produced longer ago than the input timeout: ``STALE``. Produced, not
   received: an input that sat in a buffer (a stalled process, a full socket) past the timeout
   never moves a motor;
6. the newest input invalid (absent, NaN or out-of-range channel, a mixer fault): ``INVALID``;
7. otherwise ``RUNNING``: the newest input's commands are sent.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


class LoopState(enum.IntEnum):
    """What the output loop is sending and why (safe unless RUNNING or MOTOR_TEST)."""

    STARTING = 0  # the loop has not opened the bus yet
    NO_INPUT = 1  # no input since start
    DISARMED = 2
    STALE = 3  # the newest input was produced longer ago than the input timeout
    INVALID = 4  # the newest input had an absent, NaN or out-of-range channel, or mixing failed
    RUNNING = 5  # the mixer's commands are sent
    STOPPING = 6  # shutdown: safe values for shutdown_flush_ms, then exit
    STOPPED = 7
    FAILED = 8  # the loop could not start (e.g. the bus did not open)
    MOTOR_TEST = 9  # disarmed, a motor test runs: one motor at its test throttle, others safe
    HEARTBEAT_LOST = 10  # the autopilot's arming state is older than the arming timeout
    SLOW_STREAM = 11  # the inputs arrive too seldom for the input timeout to start the motors


SENDING_COMMANDS = frozenset({LoopState.RUNNING, LoopState.MOTOR_TEST})
"""The states in which something other than the safe values goes out."""

ENGAGED = frozenset({LoopState.RUNNING, LoopState.STALE, LoopState.INVALID})
"""The states of a vehicle in flight: RUNNING, or stopped only until the next good input."""

INTERVAL_WEIGHT = 8
"""The input interval estimate moves 1/8 of the way to each new interval (about the last 8)."""
MIN_INTERVALS = 3
"""Intervals seen before the estimate counts: until then the stream is unknown, so slow."""


@dataclass(frozen=True, slots=True)
class SafetyLimits:
    """The configuration's safety settings, in the loop's units."""

    require_armed: bool
    input_timeout_ns: int
    arming_timeout_ns: int


@dataclass(slots=True)
class ControlInputs:
    """What the loop knows, updated in place as input arrives (nothing allocated per tick)."""

    stopping: bool = False
    have_input: bool = False
    """An input from the autopilot arrived since start (valid or not)."""
    input_valid: bool = False
    input_produced_ns: int = 0
    """When the autopilot produced the newest input, on the local monotonic clock."""
    armed: bool = False
    armed_heard_ns: int = 0
    """When the autopilot's arming state was last heard (monotonic); 0 = never."""
    motor_test_until_ns: int = 0
    """When the running motor test ends (monotonic); 0 = none."""
    input_interval_ns: int = 0
    """The mean interval between the autopilot's inputs (by when it produced them), over
    about the last :data:`INTERVAL_WEIGHT`; meaningful after :data:`MIN_INTERVALS`."""
    input_intervals: int = 0
    """Intervals behind :attr:`input_interval_ns` (capped at :data:`MIN_INTERVALS`)."""

    def note_input(self, produced_ns: int, valid: bool) -> None:
        """A new input, produced at ``produced_ns`` (never before the newest so far)."""
        if self.have_input:
            interval = produced_ns - self.input_produced_ns
            if self.input_intervals == 0:
                self.input_interval_ns = interval
            else:
                self.input_interval_ns += (interval - self.input_interval_ns) // INTERVAL_WEIGHT
            self.input_intervals = min(self.input_intervals + 1, MIN_INTERVALS)
        self.have_input = True
        self.input_valid = valid
        self.input_produced_ns = produced_ns

    def stream_too_slow(self, input_timeout_ns: int) -> bool:
        """Fewer than two inputs per ``input_timeout_ns``, or too few seen to tell."""
        return self.input_intervals < MIN_INTERVALS or 2 * self.input_interval_ns > input_timeout_ns


def arming_fresh(inputs: ControlInputs, now_ns: int, limits: SafetyLimits) -> bool:
    """The autopilot's arming state was heard within the arming timeout."""
    heard = inputs.armed_heard_ns
    return heard != 0 and now_ns - heard <= limits.arming_timeout_ns


def decide(
    inputs: ControlInputs, now_ns: int, limits: SafetyLimits, previous: LoopState
) -> LoopState:
    """The state for this tick, after ``previous`` (see the module docstring for the rules)."""
    if inputs.stopping:
        return LoopState.STOPPING
    fresh = arming_fresh(inputs, now_ns, limits)
    if now_ns < inputs.motor_test_until_ns and fresh and not inputs.armed:
        return LoopState.MOTOR_TEST
    if not inputs.have_input:
        return LoopState.NO_INPUT
    if limits.require_armed:
        if not fresh:
            return LoopState.HEARTBEAT_LOST if inputs.armed_heard_ns else LoopState.DISARMED
        if not inputs.armed:
            return LoopState.DISARMED
    if previous not in ENGAGED and inputs.stream_too_slow(limits.input_timeout_ns):
        return LoopState.SLOW_STREAM
    if now_ns - inputs.input_produced_ns > limits.input_timeout_ns:
        return LoopState.STALE
    if not inputs.input_valid:
        return LoopState.INVALID
    return LoopState.RUNNING


def motor_test_ended(inputs: ControlInputs, now_ns: int, limits: SafetyLimits) -> bool:
    """A running motor test must end for good: the autopilot armed, or its arming state went
    stale (it may have armed unheard). A test that merely ran out of time ends by itself."""
    if not inputs.motor_test_until_ns or now_ns >= inputs.motor_test_until_ns:
        return False
    return inputs.armed or not arming_fresh(inputs, now_ns, limits)
