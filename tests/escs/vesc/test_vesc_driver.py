"""The VESC driver (bridge/escs/vesc/driver.py): one VESC per tick, fractions to commands in each
mode, the safe output, never out of range."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridge.escs.family import EscSetup
from bridge.escs.vesc.codec import decode
from bridge.escs.vesc.driver import VescDriver
from bridge.escs.vesc.family import VescFamily
from bridge.escs.vesc.keys import VescKeys
from bridge.escs.vesc.records import (
    SetCurrent,
    SetCurrentBrake,
    SetCurrentRel,
    SetDuty,
    SetRpm,
    VescMessage,
)

IDS = (23, 24, 25, 26)
ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)


def driver(**keys: Any) -> VescDriver:
    return VescFamily().driver(EscSetup(IDS, dataclasses.replace(VescKeys(), **keys)))


def sent(frames: list[can.Message]) -> tuple[int, VescMessage]:
    (msg,) = frames
    frame = decode(msg)
    assert frame is not None
    return frame.controller_id, frame.message


def test_one_vesc_per_tick_in_order() -> None:
    vesc = driver()
    assert vesc.ticks_per_cycle == 4
    fractions = [0.1, 0.2, 0.5, 1.0]
    decoded = [sent(vesc.tick_frames(tick, fractions)) for tick in range(8)]
    assert [controller for controller, _ in decoded] == [*IDS, *IDS]
    assert [message for _, message in decoded[:4]] == [
        SetDuty(0.095),
        SetDuty(0.19),
        SetDuty(0.475),
        SetDuty(0.95),
    ]


@pytest.mark.parametrize(
    ("keys", "fraction", "expected", "described"),
    [
        ({}, 0.5, SetDuty(0.475), "VESC duty 0.475"),
        ({"vesc_max_duty": 0.8}, -1.0, SetDuty(-0.8), "VESC duty -0.800"),
        ({"vesc_mode": "current_rel"}, 0.25, SetCurrentRel(0.25), "VESC current 25.0 % of its"),
        (
            {"vesc_mode": "current", "vesc_max_current_a": 40.0},
            0.5,
            SetCurrent(20.0),
            "VESC current 20.00 A",
        ),
        ({"vesc_mode": "rpm", "vesc_max_erpm": 30001}, 0.5, SetRpm(15000), "VESC 15000 erpm"),
    ],
)
def test_modes(
    keys: dict[str, object], fraction: float, expected: VescMessage, described: str
) -> None:
    vesc = driver(**keys)
    assert sent(vesc.tick_frames(1, [0.0, fraction, 0.0, 0.0])) == (24, expected)
    assert vesc.kind == keys.get("vesc_mode", "duty")
    assert vesc.describe_command(fraction).startswith(described)
    assert vesc.describe_esc(1) == f"VESC 24, {vesc.kind} mode"


@pytest.mark.parametrize("mode", ["duty", "current_rel", "current", "rpm"])
def test_safe_output_releases_the_motor_in_every_mode(mode: str) -> None:
    assert sent(driver(vesc_mode=mode).safe_frames(2)) == (25, SetCurrent(0.0))


def test_safe_output_brakes_with_a_brake_current() -> None:
    assert sent(driver(vesc_brake_current_a=4.0).safe_frames(5)) == (24, SetCurrentBrake(4.0))


@given(
    st.lists(ANY_FLOAT, min_size=4, max_size=4),
    st.integers(0, 3),
    st.sampled_from(["duty", "current_rel", "current", "rpm"]),
)
def test_never_out_of_range(fractions: list[float], tick: int, mode: str) -> None:
    vesc = driver(vesc_mode=mode, vesc_max_duty=0.9, vesc_max_current_a=30.0, vesc_max_erpm=40000)
    _, message = sent(vesc.tick_frames(tick, fractions))
    value = float(dataclasses.astuple(message)[0])
    limit = {"duty": 0.9, "current_rel": 1.0, "current": 30.0, "rpm": 40000.0}[mode]
    assert math.isfinite(value) and -limit <= value <= limit
