"""Motor tests: DO_MOTOR_TEST decisions as a table, and the spin's ramp."""

from __future__ import annotations

import math

import pytest

from bridge.mavlink import load_dialect
from bridge.mixing.loader import load_mixer
from bridge.output.motor_test import (
    Decision,
    MotorTestCommand,
    MotorTestLimits,
    MotorTestPlan,
    TestOrder,
    ThrottleType,
    Verdict,
    decide,
    limits_for,
    ramp_fraction,
)

dialect = load_dialect()
QUAD = MotorTestLimits(((1000.0, 2000.0),) * 4, (1.0, 1.0, 0.8, 1.0), max_s=10.0)
PCT, PWM = ThrottleType.PERCENT, ThrottleType.PWM


# -- DO_MOTOR_TEST decisions (pure) -----------------------------------------------------------


def test_the_enums_carry_mavlinks_values() -> None:
    assert [int(t) for t in ThrottleType] == [
        dialect.MOTOR_TEST_THROTTLE_PERCENT,
        dialect.MOTOR_TEST_THROTTLE_PWM,
        dialect.MOTOR_TEST_THROTTLE_PILOT,
        dialect.MOTOR_TEST_COMPASS_CAL,
    ]
    for order in TestOrder:
        assert order == getattr(dialect, f"MOTOR_TEST_ORDER_{order.name}")
    for verdict in Verdict:
        assert hasattr(dialect, f"MAV_RESULT_{verdict.value}")


@pytest.mark.parametrize(
    ("command", "want"),
    [
        # one motor, percent and PWM; the mixer output's max caps the throttle (motor 3: 0.8)
        ((2, PCT, 30, 2), (Verdict.ACCEPTED, MotorTestPlan(1, 1, 0.3, 2.0, 0.0))),
        ((2, PWM, 1250, 2), (Verdict.ACCEPTED, MotorTestPlan(1, 1, 0.25, 2.0, 0.0))),
        ((3, PCT, 100, 2), (Verdict.ACCEPTED, MotorTestPlan(2, 1, 0.8, 2.0, 0.0))),
        ((4, PWM, 2000, 1.5), (Verdict.ACCEPTED, MotorTestPlan(3, 1, 1.0, 1.5, 0.0))),
        # the timeout is cut to the cap; a count runs motors in turn, half the time apart
        ((1, PCT, 10, 60), (Verdict.ACCEPTED, MotorTestPlan(0, 1, 0.1, 10.0, 0.0))),
        ((1, PCT, 10, 2, 4), (Verdict.ACCEPTED, MotorTestPlan(0, 4, 0.1, 2.0, 1.0))),
        ((2, PCT, 10, 2, 3, 2), (Verdict.ACCEPTED, MotorTestPlan(1, 3, 0.1, 2.0, 1.0))),
        ((4, PCT, 10, 2, 1, 1), (Verdict.ACCEPTED, MotorTestPlan(3, 1, 0.1, 2.0, 0.0))),
        # throttle 0 stops, whatever the timeout
        ((1, PCT, 0, 0), (Verdict.ACCEPTED, None)),
        ((2, PWM, 1000, 0), (Verdict.ACCEPTED, None)),
        # refused
        ((0, PCT, 10, 2), (Verdict.DENIED, None)),
        ((5, PCT, 10, 2), (Verdict.DENIED, None)),
        ((1.5, PCT, 10, 2), (Verdict.DENIED, None)),
        ((math.nan, PCT, 10, 2), (Verdict.DENIED, None)),
        ((1, PCT, 100.5, 2), (Verdict.DENIED, None)),
        ((1, PCT, -0.1, 2), (Verdict.DENIED, None)),
        ((1, PCT, math.inf, 2), (Verdict.DENIED, None)),
        ((1, PWM, 999, 2), (Verdict.DENIED, None)),
        ((1, PWM, 2001, 2), (Verdict.DENIED, None)),
        ((1, PCT, 10, 0), (Verdict.DENIED, None)),
        ((1, PCT, 10, -1), (Verdict.DENIED, None)),
        ((1, PCT, 10, math.inf), (Verdict.DENIED, None)),
        ((2, PCT, 10, 2, 4), (Verdict.DENIED, None)),  # motors 2..5
        ((1, PCT, 10, 2, -1), (Verdict.DENIED, None)),
        ((1, PCT, 10, 2, 2.5), (Verdict.DENIED, None)),
        ((1, PCT, 10, 2, 0, 3), (Verdict.DENIED, None)),
        ((1, ThrottleType.PILOT, 10, 2), (Verdict.UNSUPPORTED, None)),
        ((1, ThrottleType.COMPASS_CAL, 10, 2), (Verdict.UNSUPPORTED, None)),
        ((1, 4, 10, 2), (Verdict.DENIED, None)),
        ((1, 0.5, 10, 2), (Verdict.DENIED, None)),
    ],
)
def test_decide(command: tuple[float, ...], want: tuple[Verdict, MotorTestPlan | None]) -> None:
    decision = decide(MotorTestCommand(*command), QUAD)
    assert (decision.verdict, decision.plan) == want
    assert 0 < len(decision.text) <= 50  # one STATUSTEXT


def test_decide_texts() -> None:
    assert decide(MotorTestCommand(2, PCT, 30, 60), QUAD) == Decision(
        Verdict.ACCEPTED,
        "Motor test: motor 2 30% 10s (cut to 10 s)",
        MotorTestPlan(1, 1, 0.3, 10, 0),
    )
    assert decide(MotorTestCommand(1, PCT, 20, 2, 4), QUAD).text == (
        "Motor test: motors 1-4 20% 2s"
    )
    assert decide(MotorTestCommand(7, PCT, 20, 2), QUAD).text == "Motor test: motor 7 not 1..4"


def test_pwm_maps_through_the_mixers_input_range() -> None:
    hil = limits_for(load_mixer("passthrough-4").with_input_range(0, 1), None, 5.0)
    assert decide(MotorTestCommand(1, PWM, 0.5, 1), hil).plan == MotorTestPlan(0, 1, 0.5, 1, 0)
    assert decide(MotorTestCommand(1, PWM, 1500, 1), hil).verdict is Verdict.DENIED
    quad_x = limits_for(load_mixer("quad-x"), (1100.0, 1900.0), 5.0)  # rotors: the channel range
    assert decide(MotorTestCommand(2, PWM, 1500, 1), quad_x).plan == MotorTestPlan(1, 1, 0.5, 1, 0)


def test_ramp_up_hold_ramp_down() -> None:
    at = [ramp_fraction(t, 2.0, 0.5, 0.4) for t in (-0.1, 0.0, 0.25, 0.5, 1.0, 1.75, 1.99, 2.0)]
    assert at == pytest.approx([0.0, 0.0, 0.2, 0.4, 0.4, 0.2, 0.008, 0.0])
