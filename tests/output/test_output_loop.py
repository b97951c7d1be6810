"""The control loop on python-can's virtual bus, fed by a real pymavlink autopilot on loopback
UDP: its tick driven one at a time (what each safety case puts on the bus), the whole loop in a
thread, and its per-tick selector on its own (a fault in a tick means safe values)."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import can
import pytest
from can.interfaces.virtual import VirtualBus
from conftest import Autopilot, free_port

from bridge.config import build_config
from bridge.daemon.preflight import plan
from bridge.escs.ckesc import codec, records
from bridge.escs.ckesc.driver import CkescDriver
from bridge.mavlink.relay import relay_pair
from bridge.output.autopilot_input import InputSetup
from bridge.output.mailbox import (
    SENT_COMMANDS,
    SENT_SAFE,
    InputSnapshot,
    LoopStats,
    MotorTestBlock,
    SentCommands,
)
from bridge.output.output_loop import CommandSelector, LoopSetup, OutputLoop
from bridge.output.safety import ControlInputs, LoopState, SafetyLimits
from bridge.output.slew import SlewLimiter

MS = 1_000_000
PWM = [1250, 1500, 1750, 2000]
THROTTLES = (500, 1000, 1500, 2000)  # PWM through passthrough-4 to CKESC 12b
SAFE = (0, 0, 0, 0)
INPUT_TIMEOUT_MS = 400  # the default 100 ms, widened for a loaded test machine


FRAME_TIMEOUT_S = 5.0


def _throttles(observer: can.BusABC, count: int) -> list[tuple[int, ...]]:
    # The throttles of the next ``count`` frames. The loop is a thread of this test's process,
    # which beside the whole suite and a soak once went over a second without running it: the
    # values are the test, not the time they take.
    seen: list[tuple[int, ...]] = []
    while len(seen) < count and (msg := observer.recv(FRAME_TIMEOUT_S)) is not None:
        frame = codec.decode(msg)
        assert frame is not None and isinstance(frame.message, records.RawCommand12b)
        seen.append(frame.message.throttles)
    return seen


@pytest.fixture
def loop_on_virtual_bus(
    request: pytest.FixtureRequest,
) -> Iterator[tuple[int, LoopStats]]:
    """The loop running in a thread; ``request.param``: more of its ``[output]`` settings."""
    channel = f"loop-{request.node.name}"
    port = free_port()
    output = {"realtime_priority": 0, "loop": "thread", **getattr(request, "param", {})}
    raw = {
        "mavlink": {"url": f"udpin:127.0.0.1:{port}"},
        "can": {"interface": "virtual", "channel": channel},
        "output": output,
        "zenoh": {"enabled": False},
    }
    checked = plan(build_config(raw, "test"))
    stats = LoopStats()
    n = len(checked.mixer.outputs)
    loop_end, main_end = relay_pair()
    setup = LoopSetup(checked.config, InputSetup(checked.mixer, checked.valid_range, None))
    loop = OutputLoop(setup, MotorTestBlock(n), InputSnapshot(n), stats, loop_end)
    thread = threading.Thread(target=loop.run)
    thread.start()
    yield port, stats
    loop.request_stop()
    thread.join(5)
    main_end.close()
    assert not thread.is_alive()
    assert stats["state"] == LoopState.STOPPED


def test_the_loop_reads_the_autopilot_itself_and_sends_the_mix(
    loop_on_virtual_bus: tuple[int, LoopStats], request: pytest.FixtureRequest
) -> None:
    port, stats = loop_on_virtual_bus
    observer = can.Bus(interface="virtual", channel=f"loop-{request.node.name}")
    autopilot = Autopilot(port)
    try:
        assert set(_throttles(observer, 5)) == {(0, 0, 0, 0)}  # no input yet
        autopilot.pwm = [1250, 1500, 1750, 2000]
        autopilot.armed = True
        autopilot.start_stream(100)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and stats["state"] != LoopState.RUNNING:
            time.sleep(0.01)
        assert stats["state"] == LoopState.RUNNING
        while observer.recv(0) is not None:
            pass  # what was queued before
        assert set(_throttles(observer, 20)[-10:]) == {(500, 1000, 1500, 2000)}
        assert stats["input_outputs"] > 0 and stats["input_heartbeats"] > 0
        autopilot.pause_outputs()
        time.sleep(0.2)
        assert stats["state"] == LoopState.STALE
        while observer.recv(0) is not None:
            pass  # what was queued before
        assert set(_throttles(observer, 10)[-5:]) == {(0, 0, 0, 0)}
    finally:
        autopilot.close()
        observer.shutdown()


@pytest.mark.parametrize(
    "loop_on_virtual_bus", [{"rate_hz": 1, "input_timeout_ms": 1000}], indirect=True
)
def test_at_a_fixed_rate_an_input_is_taken_as_it_arrives_not_at_the_tick(
    loop_on_virtual_bus: tuple[int, LoopStats],
) -> None:
    """At 1 Hz, an input sent just after a tick is read and mixed within half a second, with
    no tick between: a tick only decides and sends, the same work every tick, so its frames
    leave at even intervals."""
    port, stats = loop_on_virtual_bus
    autopilot = Autopilot(port)
    try:
        ticks = stats["ticks"]
        deadline = time.monotonic() + 5
        while stats["ticks"] == ticks and time.monotonic() < deadline:
            time.sleep(0.001)
        ticks = stats["ticks"]  # one just happened: the next is a second away
        sent = time.monotonic()
        autopilot.servo_output_raw(PWM)
        while stats["input_outputs"] == 0 and time.monotonic() < sent + 5:
            time.sleep(0.001)
        took_s = time.monotonic() - sent
        assert stats["input_outputs"] == 1
        assert (stats["ticks"], took_s < 0.5) == (ticks, True), took_s
    finally:
        autopilot.close()


@pytest.mark.parametrize(
    "loop_on_virtual_bus", [{"rate_hz": 1, "input_timeout_ms": 1000}], indirect=True
)
def test_at_a_fixed_rate_an_inputs_frames_are_made_as_it_arrives(
    loop_on_virtual_bus: tuple[int, LoopStats], ckesc_12b_encodes: list[float]
) -> None:
    """At 1 Hz, running, a new input sent just after a tick has its frame encoded within half
    a second, with no tick between: the tick that sends it only stamps its transfer ID."""
    encoded = ckesc_12b_encodes
    port, stats = loop_on_virtual_bus
    autopilot = Autopilot(port)
    try:
        autopilot.pwm, autopilot.armed = PWM, True
        autopilot.start_stream(100)
        deadline = time.monotonic() + 10
        while stats["state"] != LoopState.RUNNING and time.monotonic() < deadline:
            time.sleep(0.01)
        assert LoopState(stats["state"]) == LoopState.RUNNING
        ticks = stats["ticks"]
        while stats["ticks"] == ticks and time.monotonic() < deadline:
            time.sleep(0.001)
        ticks, made = stats["ticks"], len(encoded)  # a tick just happened: the next is 1 s away
        changed = time.monotonic()
        autopilot.pwm = [1300, 1400, 1600, 1700]  # one group of four: one frame
        while len(encoded) == made and time.monotonic() < changed + 5:
            time.sleep(0.001)
        assert (len(encoded), stats["ticks"]) == (made + 1, ticks)
        assert encoded[-1] - changed < 0.5
    finally:
        autopilot.close()


# -- one tick at a time --------------------------------------------------------------------


@dataclass
class Rig:
    """An output loop opened on a virtual bus (not running: the test ticks it), its real
    mailbox blocks and relay, an autopilot on its link and an observer on its bus."""

    loop: OutputLoop
    stats: LoopStats
    motor_tests: MotorTestBlock
    main_end: socket.socket
    autopilot: Autopilot
    observer: can.BusABC
    sent: SentCommands
    now_ns: int = 0
    running: bool = True

    def tick(self, ahead_ms: float = 0.0) -> tuple[int, ...]:
        """Read what arrived, tick once (``ahead_ms`` after now), and return the throttles the
        tick put on the bus."""
        now = max(time.monotonic_ns() + round(ahead_ms * MS), self.now_ns + 1)
        self.now_ns = now
        self.loop.read(now)
        self.running = self.loop.tick(now, now)
        (throttles,) = _throttles(self.observer, 1)
        assert self.observer.recv(0) is None  # one frame a tick: four motors, one 12b group
        return throttles

    def state(self) -> LoopState:
        return LoopState(self.stats["state"])

    def outputs(self, pwm: list[int], count: int = 4, interval_s: float = 0.01) -> None:
        """``count`` SERVO_OUTPUT_RAW of ``pwm``, ``interval_s`` apart (by the autopilot's
        clock and on the wire)."""
        for i in range(count):
            if i:
                time.sleep(interval_s)
            self.autopilot.servo_output_raw(pwm)

    def heartbeat(self, armed: bool) -> None:
        self.autopilot.armed = armed
        self.autopilot.heartbeat()


@pytest.fixture
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    channel = f"tick-{request.node.name}"
    port = free_port()
    raw = {
        "mavlink": {"url": f"udpin:127.0.0.1:{port}"},
        "can": {"interface": "virtual", "channel": channel},
        "output": {"realtime_priority": 0, "loop": "thread", "input_timeout_ms": INPUT_TIMEOUT_MS},
        "zenoh": {"enabled": False},
    }
    checked = plan(build_config(raw, "test"))
    n = len(checked.mixer.outputs)
    stats, motor_tests = LoopStats(), MotorTestBlock(n)
    loop_end, main_end = relay_pair()
    setup = LoopSetup(checked.config, InputSetup(checked.mixer, checked.valid_range, None))
    sent = SentCommands(n)
    loop = OutputLoop(setup, motor_tests, InputSnapshot(n), stats, loop_end, sent=sent)
    observer = can.Bus(interface="virtual", channel=channel)
    loop.open()
    autopilot = Autopilot(port)
    try:
        yield Rig(loop, stats, motor_tests, main_end, autopilot, observer, sent)
    finally:
        autopilot.close()
        loop.close()
        observer.shutdown()
        main_end.close()
    assert stats["state"] == LoopState.STOPPED


def test_tick_no_input_then_disarmed_then_armed(rig: Rig) -> None:
    assert rig.tick() == SAFE
    assert rig.state() == LoopState.NO_INPUT
    rig.heartbeat(armed=False)
    rig.outputs(PWM)
    assert rig.tick() == SAFE
    assert rig.state() == LoopState.DISARMED
    rig.heartbeat(armed=True)
    rig.outputs(PWM)
    assert rig.tick() == THROTTLES
    assert rig.state() == LoopState.RUNNING
    rig.heartbeat(armed=False)  # the next tick after the HEARTBEAT
    assert rig.tick() == SAFE
    assert rig.state() == LoopState.DISARMED
    assert rig.stats["ticks"] == rig.stats["frames_sent"] == 4


def test_tick_shares_what_it_sent_when_that_changes(rig: Rig) -> None:
    """The main process learns the commands from the loop (no read-back off the bus): a new
    record when what goes out changes, none for a tick that repeats the last."""
    assert rig.tick() == SAFE
    record = rig.sent.read()
    assert record is not None and record.kind == SENT_SAFE
    assert rig.tick() == SAFE
    assert rig.sent.seq() == record.seq
    rig.heartbeat(armed=True)
    rig.outputs(PWM)
    assert rig.tick() == THROTTLES
    record = rig.sent.read()
    assert record is not None and record.kind == SENT_COMMANDS
    assert record.fractions == pytest.approx([t / 2000 for t in THROTTLES])
    assert rig.tick() == THROTTLES  # the same input
    assert rig.sent.seq() == record.seq
    rig.heartbeat(armed=False)
    assert rig.tick() == SAFE
    record = rig.sent.read()
    assert record is not None and record.kind == SENT_SAFE


def test_tick_stale_input_stops_the_motors_until_a_fresh_one(rig: Rig) -> None:
    rig.heartbeat(armed=True)
    rig.outputs(PWM)
    assert rig.tick() == THROTTLES
    time.sleep(INPUT_TIMEOUT_MS / 1000 + 0.05)  # produced longer ago than the timeout
    assert rig.tick() == SAFE
    assert rig.state() == LoopState.STALE
    rig.outputs(PWM, count=1)  # in flight: one fresh input runs again
    assert rig.tick() == THROTTLES
    assert rig.state() == LoopState.RUNNING


def test_tick_held_up_before_sending_decides_again(rig: Rig) -> None:
    """The loop stopped between taking the time and sending (SIGSTOP, swap, a higher-priority
    task): the frame carries what holds when it leaves, not what held when the time was
    taken (an input fresh then and stale now: the safe values, not the running commands)."""
    rig.heartbeat(armed=True)
    rig.outputs(PWM)
    assert rig.tick() == THROTTLES
    taken = time.monotonic_ns()
    rig.loop.read(taken)
    time.sleep(INPUT_TIMEOUT_MS / 1000 + 0.05)  # held up: the input went stale meanwhile
    rig.loop.tick(taken, taken)
    rig.now_ns = time.monotonic_ns()
    assert _throttles(rig.observer, 1) == [SAFE]
    assert rig.state() == LoopState.STALE
    assert rig.stats["redecided"] >= 1
    rig.outputs(PWM, count=1)  # in flight again
    assert rig.tick() == THROTTLES


def test_tick_held_up_before_sending_carries_the_input_that_arrived_meanwhile(rig: Rig) -> None:
    """Held up over a period between taking the time and sending while the autopilot went on
    (a virtual CPU the host took away for tens of ms, the autopilot on another): the frame
    carries the newest input, not the one read before the hold."""
    rig.heartbeat(armed=True)
    rig.outputs(PWM)
    assert rig.tick() == THROTTLES
    taken = time.monotonic_ns()
    rig.loop.read(taken)
    rig.outputs([1000, 1250, 1500, 1750], count=1)  # arrives while the loop is held up
    time.sleep(0.05)  # twenty periods at 400 Hz, well inside the input timeout
    # Counted from here: a loaded machine may hold up the tick before as well (seen in CI).
    before = rig.stats["redecided"]
    rig.loop.tick(taken, taken)
    assert _throttles(rig.observer, 1) == [(0, 500, 1000, 1500)]
    assert rig.state() == LoopState.RUNNING
    assert rig.stats["redecided"] - before == 1


def test_tick_held_up_while_its_frame_leaves_is_counted_as_left_late(rig: Rig) -> None:
    """Held up after the loop's last look at the clock, while its frame is on its way to the
    bus (here the observer's receive queue, which python-can's virtual bus takes to deliver a
    frame, locked by another thread for 50 ms): the frame leaves on the decision made, and the
    tick is counted as left late, for the exit summary to say."""
    rig.heartbeat(armed=True)
    rig.outputs(PWM)
    assert rig.tick() == THROTTLES
    before = rig.stats["left_late"]
    assert isinstance(rig.observer, VirtualBus)
    delivery = rig.observer.queue.mutex  # its receive queue's lock
    delivery.acquire()
    threading.Timer(0.05, delivery.release).start()
    assert rig.tick() == THROTTLES
    assert rig.stats["left_late"] - before == 1


def test_tick_a_slow_stream_never_starts_the_motors(rig: Rig) -> None:
    rig.heartbeat(armed=True)
    slow_s = INPUT_TIMEOUT_MS / 1000 * 0.6  # fewer than two inputs per timeout
    for _ in range(5):
        rig.outputs(PWM, count=1)
        assert rig.tick() == SAFE
        assert rig.state() == LoopState.SLOW_STREAM
        time.sleep(slow_s)
    rig.outputs(PWM, count=12)  # fast enough now (the mean over about the last 8)
    assert rig.tick() == THROTTLES
    assert rig.state() == LoopState.RUNNING


def test_tick_heartbeat_lost_stops_the_motors(rig: Rig) -> None:
    rig.heartbeat(armed=True)
    rig.outputs(PWM)
    assert rig.tick() == THROTTLES
    assert rig.tick(ahead_ms=3100) == SAFE  # arming_timeout_ms (3000) without a HEARTBEAT
    assert rig.state() == LoopState.HEARTBEAT_LOST


def test_tick_invalid_input_stops_the_motors(rig: Rig) -> None:
    rig.heartbeat(armed=True)
    rig.outputs(PWM)
    assert rig.tick() == THROTTLES
    rig.outputs([2500, 1500, 1750, 2000], count=1)  # ch1 above valid_range (800..2200 µs)
    assert rig.tick() == SAFE
    assert rig.state() == LoopState.INVALID
    assert rig.stats["input_invalid"] == 1
    rig.outputs(PWM, count=1)
    assert rig.tick() == THROTTLES


def test_tick_motor_test_spins_one_motor_while_disarmed_and_arming_ends_it(rig: Rig) -> None:
    rig.heartbeat(armed=False)
    assert rig.tick() == SAFE
    rig.motor_tests.write_motor_test(1, 1, 0.25, time.monotonic_ns(), 5000 * MS, 5000 * MS)
    assert rig.tick() == (0, 500, 0, 0)  # motor 2 at 25 % of throttle 2000, the others safe
    assert rig.state() == LoopState.MOTOR_TEST
    assert rig.stats["motor_test_motor"] == 2
    rig.heartbeat(armed=True)  # arming ends the test for good
    assert rig.tick() == SAFE
    assert rig.state() == LoopState.NO_INPUT
    assert rig.stats["motor_test_motor"] == 0
    rig.heartbeat(armed=False)
    assert rig.tick() == SAFE
    assert rig.state() == LoopState.NO_INPUT


def test_tick_stop_flushes_safe_values_then_ends(rig: Rig) -> None:
    rig.heartbeat(armed=True)
    rig.outputs(PWM)
    assert rig.tick() == THROTTLES
    rig.loop.request_stop()
    assert rig.tick() == SAFE
    assert (rig.state(), rig.running) == (LoopState.STOPPING, True)
    rig.outputs(PWM, count=1)  # inputs no longer count
    assert rig.tick(ahead_ms=100) == SAFE
    assert rig.running
    assert rig.tick(ahead_ms=250) == SAFE  # shutdown_flush_ms (200) after the stop: the last
    assert not rig.running


def test_tick_main_process_gone_flushes_safe_values_then_ends(rig: Rig) -> None:
    rig.heartbeat(armed=True)
    rig.outputs(PWM)
    assert rig.tick() == THROTTLES
    rig.main_end.close()  # its end of the relay: what a dead main process leaves
    assert rig.tick() == SAFE
    assert (rig.state(), rig.running) == (LoopState.STOPPING, True)
    assert rig.tick(ahead_ms=250) == SAFE
    assert not rig.running


# -- the selector alone ----------------------------------------------------------------------


def test_a_fault_in_a_tick_sends_safe_values_and_the_next_tick_runs_again() -> None:
    # A stream at 200 Hz for long enough to arm on.
    inputs = ControlInputs(
        have_input=True, input_valid=True, armed=True, input_interval_ns=5 * MS, input_intervals=3
    )
    limits = SafetyLimits(True, 100 * MS, 3000 * MS)
    selector = CommandSelector(
        CkescDriver("12b", [1, 2, 3, 4]), SlewLimiter([0.0] * 4, [0.0] * 4), limits, inputs, 4
    )
    now = 10_000 * MS
    inputs.input_produced_ns = inputs.armed_heard_ns = now
    good = [0.5, 0.5, 0.5, 0.5]

    def throttles(fractions: list[float]) -> tuple[int, ...]:
        frames = selector.select(0, now, fractions, 0.0025)
        decoded = codec.decode(frames[0])
        assert decoded is not None and isinstance(decoded.message, records.RawCommand12b)
        return decoded.message.throttles

    assert throttles(good) == (1000, 1000, 1000, 1000)
    # A vector the slew limiter cannot take (one output short): safe values, counted.
    assert throttles([0.5, 0.5, 0.5]) == (0, 0, 0, 0)
    assert selector.faults == 1 and selector.state == LoopState.RUNNING
    assert throttles(good) == (1000, 1000, 1000, 1000)


def _running_selector(slew_rates: list[float]) -> tuple[CommandSelector, int]:
    """A selector over CKESC x4, RUNNING after one tick at the time it returns."""
    inputs = ControlInputs(
        have_input=True, input_valid=True, armed=True, input_interval_ns=5 * MS, input_intervals=3
    )
    limits = SafetyLimits(True, 100 * MS, 3000 * MS)
    selector = CommandSelector(
        CkescDriver("12b", [1, 2, 3, 4]), SlewLimiter(slew_rates, slew_rates), limits, inputs, 4
    )
    now = 10_000 * MS
    inputs.input_produced_ns = inputs.armed_heard_ns = now
    selector.select(0, now, [0.0] * 4, 0.0025)
    assert selector.state == LoopState.RUNNING
    return selector, now


def test_the_selector_has_an_inputs_frames_made_ahead_only_when_a_tick_sends_them_as_they_are(
    ckesc_12b_encodes: list[float],
) -> None:
    """Running without slew rates, a new input's frames are made when it arrives; with slew
    rates (a tick sends other values) or in any other state, nothing is made ahead. A vector
    that cannot be encoded raises nothing there: the tick meets it with the safe values."""
    encoded = ckesc_12b_encodes
    selector, now = _running_selector([0.0] * 4)
    made = len(encoded)
    selector.prepare([0.5] * 4)
    assert len(encoded) == made + 1
    frames = selector.select(1, now, [0.5] * 4, 0.0025)
    assert len(encoded) == made + 1  # the tick only stamped it
    decoded = codec.decode(frames[0])
    assert decoded is not None and isinstance(decoded.message, records.RawCommand12b)
    assert decoded.message.throttles == (1000, 1000, 1000, 1000)
    selector.prepare(None)  # an invalid input: nothing to make
    selector.prepare([0.5] * 3)  # one output short: raises nothing here
    assert len(encoded) == made + 1
    assert throttles_of(selector.select(2, now, [0.5] * 3, 0.0025)) == SAFE
    assert selector.faults == 1

    slewing, now = _running_selector([1.0] * 4)
    made = len(encoded)
    slewing.prepare([0.5] * 4)
    assert len(encoded) == made
    slewing.state = LoopState.DISARMED
    selector.state = LoopState.DISARMED
    selector.prepare([0.75] * 4)
    assert len(encoded) == made


def throttles_of(frames: list[can.Message]) -> tuple[int, ...]:
    decoded = codec.decode(frames[0])
    assert decoded is not None and isinstance(decoded.message, records.RawCommand12b)
    return decoded.message.throttles
