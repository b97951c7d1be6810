"""Motor tests: one motor spun on purpose, propellers off, everything else held safe.

Two ways in, one way out to the bus:

* ``esc-bridge esc spin`` (:mod:`bridge.output.spin`): the bridge is not running; that
  process opens the bus itself, ramps one motor up to the asked throttle, holds it, ramps
  it down, and sends safe values to every ESC afterwards, whatever ends the spin (the time
  limit, Ctrl-C, SIGTERM, an exception).
* MAV_CMD_DO_MOTOR_TEST to the running daemon (:func:`decide`): the daemon checks the
  command against the vehicle (the mixer's motors, their input ranges, the time cap) and,
  while the autopilot is disarmed, hands a :class:`~bridge.output.mailbox.MotorTest` to the output
  loop, which sends it instead of the safe values until the time is up or the vehicle arms.

Both build each tick's frames with :func:`test_frames` through the family's driver
(:meth:`~bridge.escs.family.EscFamily.driver`): the frames are exactly the daemon's, every value
is limited to the protocol's range by the driver, and every ESC but the one under test gets its
safe value (in the same frame, or on its own tick, as its family's driver addresses ESCs).

A throttle is a fraction of the ESC's full range as its family defines it (its
:meth:`~bridge.escs.family.EscDriver.describe_command` says what it is on the wire), never
above the mixer output's ``max``. Nothing here prints; the CLI does.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from bridge.mixing.definition import PWM_RANGE_US, MixerDefinition

if TYPE_CHECKING:
    import can

    from bridge.config import BridgeConfig
    from bridge.escs.family import EscDriver

__all__ = [
    "SPIN_RAMP_S",
    "SPIN_SECONDS",
    "Decision",
    "MotorTestCommand",
    "MotorTestLimits",
    "MotorTestPlan",
    "SpinRequest",
    "TestOrder",
    "ThrottleType",
    "Verdict",
    "command_text",
    "decide",
    "limits_for",
    "ramp_fraction",
    "test_frames",
]

SPIN_SECONDS: Final = (1.0, 30.0)
"""The shortest and longest ``esc spin`` (the hard time limit, ramps included), s."""
SPIN_RAMP_S: Final = 0.5
"""Ramp up at the start and down at the end of a spin, s (at most a quarter of the spin)."""
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
    return config.family.driver(config.esc_setup).describe_command(fraction)


# -- esc spin: the request and the ramp (the spin itself: bridge/output/spin.py) -------------


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


def ramp_fraction(elapsed_s: float, seconds: float, ramp_s: float, target: float) -> float:
    """The spin's throttle ``elapsed_s`` into it: up from 0 over ``ramp_s``, held at ``target``,
    down to 0 over the last ``ramp_s`` of ``seconds``; 0 outside the spin."""
    if not 0.0 <= elapsed_s < seconds:
        return 0.0
    if ramp_s <= 0.0:
        return target
    return target * min(1.0, elapsed_s / ramp_s, (seconds - elapsed_s) / ramp_s)


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
