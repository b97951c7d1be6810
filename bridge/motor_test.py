"""Motor tests: one motor spun on purpose, propellers off, everything else held safe.

Two ways in, one way out to the bus:

* ``esc-bridge esc spin`` (:func:`plan_spin`, then :func:`spin`): the bridge is not running;
  this process opens the bus itself, ramps one motor up to the asked throttle, holds it, ramps
  it down, and sends safe values to every ESC afterwards, whatever ends the spin (the time
  limit, Ctrl-C, SIGTERM, an exception).
* MAV_CMD_DO_MOTOR_TEST to the running daemon (:func:`decide`): the daemon checks the
  command against the vehicle (the mixer's motors, their input ranges, the time cap) and,
  while the autopilot is disarmed, hands a :class:`~bridge.mailbox.MotorTest` to the output
  loop, which sends it instead of the safe values until the time is up or the vehicle arms.

Both build each tick's frames with :func:`test_frames` through the project's drivers
(:func:`bridge.escs.drivers.make_driver`): the frames are exactly the daemon's, every value is
limited to the protocol's range by the driver, and every ESC but the one under test gets its
safe value (in the same frame, or on its own tick, as its family's driver addresses ESCs).

A throttle is a fraction of the ESC's full range as its family defines it (its
:meth:`~bridge.escs.family.EscFamily.describe_command` says what it is on the wire), never
above the mixer output's ``max``. Nothing here prints; the CLI does.
"""

from __future__ import annotations

import contextlib
import enum
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Final, Literal

import can

from bridge.can_io import check_interface, is_transient, open_bus
from bridge.config import BridgeConfig, with_esc_count
from bridge.errors import ConfigError, LinkError
from bridge.escs import registry
from bridge.escs.drivers import EscDriver, flush_safe_values, make_driver
from bridge.mixer import PWM_RANGE_US, MixerDefinition, load_mixer

__all__ = [
    "SPIN_RAMP_S",
    "SPIN_SECONDS",
    "Decision",
    "MotorTestCommand",
    "MotorTestLimits",
    "MotorTestPlan",
    "SpinPlan",
    "SpinProgress",
    "SpinRequest",
    "SpinResult",
    "TestOrder",
    "ThrottleType",
    "Verdict",
    "command_text",
    "decide",
    "limits_for",
    "plan_spin",
    "ramp_fraction",
    "spin",
    "test_frames",
]

SPIN_SECONDS: Final = (1.0, 30.0)
"""The shortest and longest ``esc spin`` (the hard time limit, ramps included), s."""
SPIN_RAMP_S: Final = 0.5
"""Ramp up at the start and down at the end of a spin, s (at most a quarter of the spin)."""
SPIN_PROGRESS_S: Final = 0.5
"""A spin reports its progress this often, and at each change of phase."""
SPIN_MIN_FLUSH_MS: Final = 50
"""Safe values are sent at least this long after a spin, even with shutdown_flush_ms 0."""
SEQUENCE_GAP: Final = 0.5
"""Between the motors of a DO_MOTOR_TEST sequence, every motor is held safe for this fraction
of the per-motor time (ArduCopter pauses the same way), so each motor is seen on its own."""


def test_frames(
    driver: EscDriver, tick: int, fractions: Sequence[float], index: int
) -> list[can.Message]:
    """One tick of a motor test: motor ``index`` (0-based) at ``fractions[index]``, every other
    ESC at its safe value; ``fractions`` holds 0 everywhere else.

    A driver that addresses every ESC on every tick (``ticks_per_cycle`` 1: one frame per group
    of channels) gets the whole vector, and a 0 there is exactly its safe value. A driver that
    addresses one ESC per tick (ESC ``tick % ticks_per_cycle``) sends the test command on the
    tested ESC's tick and the safe command on the others', since "0" in some of its modes
    (duty, erpm) need not be its safe value (0 A, or a brake current).

    Raises:
        whatever the driver raises for a vector of the wrong length (the daemon's loop sends
        safe values for that tick instead).
    """
    per_tick = driver.ticks_per_cycle
    if per_tick == 1 or tick % per_tick == index:
        return driver.tick_frames(tick, fractions)
    return driver.safe_frames(tick)


def command_text(config: BridgeConfig, fraction: float) -> str:
    """What ``fraction`` of the full range means on the wire for ``config``'s ESCs."""
    return registry.family(config.output.protocol).describe_command(config, fraction)


# -- esc spin --------------------------------------------------------------------------------


@dataclass(frozen=True)
class SpinRequest:
    """What ``esc spin`` was asked: motor number (1-based), throttle in percent of the ESC's
    full range, and the hard time limit in seconds, ramps included.

    Raises:
        ValueError: a value out of range, NaN or infinite (the value is in the message).
    """

    motor: int
    throttle_pct: float
    seconds: float

    def __post_init__(self) -> None:
        if isinstance(self.motor, bool) or not isinstance(self.motor, int) or self.motor < 1:
            raise ValueError(f"motor={self.motor!r}: expected a motor number 1, 2, ...")
        if not 0.0 <= self.throttle_pct <= 100.0:
            raise ValueError(f"throttle_pct={self.throttle_pct!r}: expected 0..100")
        low, high = SPIN_SECONDS
        if not low <= self.seconds <= high:
            raise ValueError(f"seconds={self.seconds!r}: expected {low:g}..{high:g}")


@dataclass(frozen=True)
class SpinPlan:
    """A checked spin: nothing has been opened or sent yet."""

    config: BridgeConfig
    """With the ESC lists filled in."""
    mixer: MixerDefinition
    request: SpinRequest
    fraction: float
    """The held throttle, 0..1 of the full range (the request, capped at the output's max)."""
    ramp_s: float

    @property
    def index(self) -> int:
        """The motor's 0-based output index."""
        return self.request.motor - 1

    @property
    def esc_id(self) -> int:
        """The ID on the bus of the motor's ESC."""
        return self.config.escs.ids[self.index]

    @property
    def rate_hz(self) -> float:
        """Frames per second put on the bus: the daemon's command rate."""
        return float(self.config.rate_hz * make_driver(self.config).ticks_per_cycle)


def plan_spin(config: BridgeConfig, request: SpinRequest) -> SpinPlan:
    """Check ``request`` against ``config``: interface, mixer, ESC lists, bus load, motor number.

    Raises:
        ConfigError: the configuration is invalid, or the motor is not one of the mixer's.
    """
    # Imported here: busload imports the output loop, which imports this module.
    from bridge.busload import check_bus_load

    check_interface(config.can, config.source)
    mixer = load_mixer(config.mixer.name)
    n_motors = len(mixer.outputs)
    if request.motor > n_motors:
        raise ConfigError(
            f"--motor {request.motor}: mixer {mixer.name!r} has motors 1..{n_motors}; "
            "expected one of those"
        )
    config = with_esc_count(config, n_motors)
    check_bus_load(config)
    output = mixer.outputs[request.motor - 1]
    fraction = min(request.throttle_pct / 100.0, output.maximum)
    return SpinPlan(config, mixer, request, fraction, min(SPIN_RAMP_S, request.seconds / 4))


def ramp_fraction(elapsed_s: float, seconds: float, ramp_s: float, target: float) -> float:
    """The spin's throttle ``elapsed_s`` into it: up from 0 over ``ramp_s``, held at ``target``,
    down to 0 over the last ``ramp_s`` of ``seconds``; 0 outside the spin."""
    if not 0.0 <= elapsed_s < seconds:
        return 0.0
    if ramp_s <= 0.0:
        return target
    return target * min(1.0, elapsed_s / ramp_s, (seconds - elapsed_s) / ramp_s)


Phase = Literal["ramp up", "hold", "ramp down"]


@dataclass(frozen=True)
class SpinProgress:
    """Where a running spin is, for the caller's progress lines."""

    phase: Phase
    elapsed_s: float
    fraction: float
    """The throttle sent on this tick, 0..1 of the full range."""


@dataclass(frozen=True)
class SpinResult:
    """How a spin went. ``ended``: ``done`` (the time limit), ``interrupted`` (a signal or the
    stop event), ``bus error`` (the bus went away)."""

    ended: Literal["done", "interrupted", "bus error"]
    elapsed_s: float
    frames_sent: int
    """Frames sent while the motor was commanded (ramps and hold)."""
    safe_frames_sent: int
    """Safe-value frames sent afterwards."""
    send_errors: int
    peak_fraction: float


def spin(
    plan: SpinPlan,
    *,
    stop: threading.Event | None = None,
    progress: Callable[[SpinProgress], None] | None = None,
    handle_signals: bool = True,
) -> SpinResult:
    """Spin ``plan``'s motor, then send safe values to every ESC, whatever happens.

    Frames go out at the daemon's rate on absolute deadlines of the monotonic clock. The spin
    ends at ``plan.request.seconds`` after the first frame (the hard limit), or at once when
    ``stop`` is set. With ``handle_signals`` (and on the main thread) SIGINT and SIGTERM set
    ``stop`` for the duration, so Ctrl-C ends the spin without interrupting the safe values.
    Afterwards safe values go to every ESC for ``shutdown_flush_ms`` (at least
    :data:`SPIN_MIN_FLUSH_MS` and one whole cycle, so every ESC gets one), also when an
    exception (from ``progress``, say) ends the spin; the exception then propagates.

    Raises:
        LinkError: the bus could not be opened (nothing was sent).
        ConfigError: the interface is not one python-can has.
    """
    stop = stop or threading.Event()
    config = plan.config
    driver = make_driver(config)
    period_ns = round(1e9 / (config.rate_hz * driver.ticks_per_cycle))
    bus = open_bus(config.can, config.bitrate)
    sender = _Sender(bus)
    fractions = [0.0] * len(config.escs.ids)
    index, target, ramp_s = plan.index, plan.fraction, plan.ramp_s
    seconds = plan.request.seconds
    ended: Literal["done", "interrupted", "bus error"] = "interrupted"
    peak = 0.0
    tick = 0
    start_ns = time.monotonic_ns()
    elapsed_s = 0.0
    try:
        with _signals_set(stop, handle_signals):
            end_ns = start_ns + round(seconds * 1e9)
            next_ns = start_ns
            next_report_s = 0.0
            last_phase: Phase | None = None
            while True:
                now = time.monotonic_ns()
                elapsed_s = (now - start_ns) / 1e9
                if now >= end_ns:
                    ended = "done"
                    break
                if stop.is_set():
                    break
                fraction = ramp_fraction(elapsed_s, seconds, ramp_s, target)
                fractions[index] = fraction
                peak = max(peak, fraction)
                if not sender.send(test_frames(driver, tick, fractions, index)):
                    ended = "bus error"
                    break
                tick += 1
                phase: Phase = (
                    "ramp up"
                    if elapsed_s < ramp_s
                    else "ramp down"
                    if elapsed_s >= seconds - ramp_s
                    else "hold"
                )
                if progress is not None and (phase != last_phase or elapsed_s >= next_report_s):
                    progress(SpinProgress(phase, elapsed_s, fraction))
                    next_report_s = elapsed_s + SPIN_PROGRESS_S
                    last_phase = phase
                next_ns += period_ns
                if now - next_ns >= period_ns:  # woke a period late or more: skip, no burst
                    next_ns += (now - next_ns) // period_ns * period_ns
                # Never sleep past the limit: the last tick may be shorter than a period.
                delay_ns = min(next_ns, end_ns) - time.monotonic_ns()
                if delay_ns > 0:
                    stop.wait(delay_ns / 1e9)
    finally:
        frames_sent = sender.sent
        sender.sent = 0
        try:
            with _signals_set(stop, handle_signals):
                if sender.gone:  # one more try on a fresh handle: the safe values matter most
                    bus.shutdown()
                    with contextlib.suppress(LinkError):
                        bus = sender.reopen(open_bus(config.can, config.bitrate))
                flush_ms = max(config.output.shutdown_flush_ms, SPIN_MIN_FLUSH_MS)
                flush_safe_values(sender.send, driver, period_ns, flush_ms, tick)
        finally:
            bus.shutdown()
    return SpinResult(ended, elapsed_s, frames_sent, sender.sent, sender.errors, peak)


class _Sender:
    """Sends without blocking and counts; False once the bus is gone (not a passing error)."""

    def __init__(self, bus: can.BusABC) -> None:
        self._bus = bus
        self.sent = 0
        self.errors = 0
        self.gone = False

    def reopen(self, bus: can.BusABC) -> can.BusABC:
        """Send on ``bus`` from now on (the old handle is the caller's to shut down)."""
        self._bus = bus
        self.gone = False
        return bus

    def send(self, frames: list[can.Message]) -> bool:
        if self.gone:
            return False
        for frame in frames:
            try:
                self._bus.send(frame, timeout=0)
            except (can.CanError, OSError) as exc:
                self.errors += 1
                self.gone = not is_transient(exc)
                return not self.gone
            self.sent += 1
        return True


@contextlib.contextmanager
def _signals_set(stop: threading.Event, enabled: bool) -> Iterator[None]:
    """While inside: SIGINT and SIGTERM set ``stop`` instead of raising or ending the process
    (main thread only; elsewhere signals are not ours to take)."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {
        sig: signal.signal(sig, lambda _signum, _frame: stop.set())
        for sig in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


# -- MAV_CMD_DO_MOTOR_TEST --------------------------------------------------------------------


class ThrottleType(enum.IntEnum):
    """MAVLink MOTOR_TEST_THROTTLE_TYPE (param2 of MAV_CMD_DO_MOTOR_TEST)."""

    PERCENT = 0  # 0..100 % of the ESC's full range
    PWM = 1  # µs, mapped through the mixer's input range for that motor
    PILOT = 2  # the pilot's throttle stick: the bridge has none
    COMPASS_CAL = 3  # per-motor compass calibration: the autopilot's business


class TestOrder(enum.IntEnum):
    """MAVLink MOTOR_TEST_ORDER (param6). All three mean the bridge's motor numbers (the
    mixer's output order): the bridge knows no other numbering."""

    __test__ = False  # not a pytest test class, whatever its name

    DEFAULT = 0
    SEQUENCE = 1
    BOARD = 2


class Verdict(enum.Enum):
    """The MAV_RESULT a command gets, by name (the daemon maps it to the dialect's value)."""

    ACCEPTED = "ACCEPTED"
    TEMPORARILY_REJECTED = "TEMPORARILY_REJECTED"
    DENIED = "DENIED"
    UNSUPPORTED = "UNSUPPORTED"


@dataclass(frozen=True)
class MotorTestCommand:
    """MAV_CMD_DO_MOTOR_TEST's parameters as received (COMMAND_LONG floats)."""

    motor: float  # param1: motor instance, 1-based
    throttle_type: float  # param2: MOTOR_TEST_THROTTLE_TYPE
    throttle: float  # param3: in the unit of throttle_type
    timeout_s: float  # param4: per motor
    count: float = 0.0  # param5: motors to test one after another; 0 means 1
    order: float = 0.0  # param6: MOTOR_TEST_ORDER


@dataclass(frozen=True)
class MotorTestLimits:
    """What a command is checked against: the vehicle's motors and the time cap."""

    pwm_ranges: tuple[tuple[float, float], ...]
    """Per motor: the input range (µs) that maps to 0..1 of the ESC's range."""
    max_fractions: tuple[float, ...]
    """Per motor: the mixer output's ``max``, the highest throttle a test may send."""
    max_s: float
    """The longest test per motor; longer timeouts are cut to it."""

    @property
    def n_motors(self) -> int:
        return len(self.pwm_ranges)


def limits_for(
    mixer: MixerDefinition, input_range: tuple[float, float] | None, max_s: float
) -> MotorTestLimits:
    """The limits of ``mixer``: a channel output maps PWM through its own input range, a rotor
    output (a geometry mixer) through the channel range (``input_range`` or PWM 1000..2000)."""
    channel_range = input_range or PWM_RANGE_US
    return MotorTestLimits(
        tuple(o.input_range if o.uses_channels else channel_range for o in mixer.outputs),
        tuple(o.maximum for o in mixer.outputs),
        max_s,
    )


@dataclass(frozen=True)
class MotorTestPlan:
    """An accepted test: motors ``first .. first + count - 1`` (0-based) one after another,
    each at ``fraction`` for ``on_s``, safe for ``gap_s`` between two of them."""

    first: int
    count: int
    fraction: float
    on_s: float
    gap_s: float

    @property
    def total_s(self) -> float:
        return self.count * self.on_s + (self.count - 1) * self.gap_s


@dataclass(frozen=True)
class Decision:
    """A command's answer, the STATUSTEXT that explains it, and what to do: ``plan`` is the test
    to run, or None with ACCEPTED for "stop any test" (throttle 0)."""

    verdict: Verdict
    text: str
    plan: MotorTestPlan | None = None


def _whole(value: float) -> int | None:
    """``value`` as an int when it is a whole number (a MAVLink float carrying an integer)."""
    if not math.isfinite(value) or value != int(value):
        return None
    return int(value)


def decide(command: MotorTestCommand, limits: MotorTestLimits) -> Decision:
    """Check a DO_MOTOR_TEST against the motors; the vehicle's state is the caller's to check
    (an accepted plan is only run while the autopilot is disarmed).

    - param2 PILOT and COMPASS_CAL: UNSUPPORTED (the bridge has no pilot stick and no compass);
      another type: DENIED.
    - throttle 0 (percent 0, or PWM at the bottom of the range): ACCEPTED, stops any test.
    - a motor that is not 1..N, a count that runs past motor N, a throttle outside 0..100 % or
      outside the PWM range, a timeout that is not > 0, an unknown order: DENIED.
    - a timeout above ``limits.max_s`` is cut to it (ACCEPTED, and the text says so).
    """
    n = limits.n_motors
    throttle_type = _whole(command.throttle_type)
    if throttle_type in (ThrottleType.PILOT, ThrottleType.COMPASS_CAL):
        name = ThrottleType(throttle_type).name
        return Decision(Verdict.UNSUPPORTED, f"Motor test: throttle type {name} unsupported")
    if throttle_type not in (ThrottleType.PERCENT, ThrottleType.PWM):
        return Decision(Verdict.DENIED, f"Motor test: throttle type {command.throttle_type:g}?")
    motor = _whole(command.motor)
    if motor is None or not 1 <= motor <= n:
        return Decision(Verdict.DENIED, f"Motor test: motor {command.motor:g} not 1..{n}")
    count = _whole(command.count)
    if count is None or count < 0 or motor + max(count, 1) - 1 > n:
        return Decision(
            Verdict.DENIED, f"Motor test: {command.count:g} motors from {motor} past {n}"
        )
    count = max(count, 1)
    if _whole(command.order) not in tuple(TestOrder):
        return Decision(Verdict.DENIED, f"Motor test: test order {command.order:g}?")
    value = command.throttle
    if throttle_type == ThrottleType.PERCENT:
        if not 0.0 <= value <= 100.0:
            return Decision(Verdict.DENIED, f"Motor test: throttle {value:g}% not 0..100")
        fractions = [value / 100.0] * count
    else:
        lows_highs = limits.pwm_ranges[motor - 1 : motor - 1 + count]
        if not all(min(lo, hi) <= value <= max(lo, hi) for lo, hi in lows_highs):
            lo, hi = lows_highs[0]
            return Decision(Verdict.DENIED, f"Motor test: PWM {value:g} not {lo:g}..{hi:g}")
        fractions = [(value - lo) / (hi - lo) for lo, hi in lows_highs]
    caps = limits.max_fractions[motor - 1 : motor - 1 + count]
    fraction = min(min(f, cap) for f, cap in zip(fractions, caps, strict=True))
    if fraction <= 0.0:
        return Decision(Verdict.ACCEPTED, "Motor test: stopped, motors safe")
    timeout = command.timeout_s
    if not (math.isfinite(timeout) and timeout > 0):
        return Decision(Verdict.DENIED, f"Motor test: timeout {timeout:g} s not > 0")
    on_s = min(timeout, limits.max_s)
    plan = MotorTestPlan(motor - 1, count, fraction, on_s, on_s * SEQUENCE_GAP if count > 1 else 0)
    which = f"motor {motor}" if count == 1 else f"motors {motor}-{motor + count - 1}"
    capped = f" (cut to {limits.max_s:g} s)" if timeout > limits.max_s else ""
    text = f"Motor test: {which} {100 * fraction:.0f}% {on_s:g}s{capped}"
    return Decision(Verdict.ACCEPTED, text, plan)
