"""The FT driver: one ESC per tick, fractions to commands, never out of range."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from bridge.config import build_config, with_esc_count
from bridge.escs.ft import codec, records
from bridge.escs.ft.driver import FtDriver

ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)


def _ft_driver(**escs: object) -> FtDriver:
    raw = {"output": {"protocol": "ft"}, "escs": {"ids": [5, 6, 7, 8], **escs}}
    config = with_esc_count(build_config(raw, "test"), 4)
    driver = config.family.driver(config.esc_setup)
    assert isinstance(driver, FtDriver)
    return driver


def test_ft_one_esc_per_tick_in_order() -> None:
    driver = _ft_driver(ft_max_current_a=30.0)
    assert driver.ticks_per_cycle == 4
    fractions = [0.1, 0.2, 0.5, 1.0]
    decoded = [codec.decode(driver.tick_frames(tick, fractions)[0]) for tick in range(8)]
    assert [f.esc_id for f in decoded if f] == [5, 6, 7, 8, 5, 6, 7, 8]
    currents = [
        f.message.current_a for f in decoded[:4] if f and isinstance(f.message, records.SetCurrent)
    ]
    assert currents == [3.0, 6.0, 15.0, 30.0]


def test_ft_modes_and_safe_values() -> None:
    duty = codec.decode(_ft_driver(ft_mode="duty", ft_max_duty=0.9).tick_frames(0, [1.0] * 4)[0])
    assert duty is not None and duty.message == records.SetDuty(
        duty=0.9, gear=records.Gear.NONE, crc=True
    )
    erpm = codec.decode(
        _ft_driver(ft_mode="erpm", ft_max_erpm=40000, ft_crc=False, ft_gear="high").tick_frames(
            1, [0.0, 0.5, 0.0, 0.0]
        )[0]
    )
    assert erpm is not None and erpm.message == records.SetErpm(
        erpm=20000, gear=records.Gear.HIGH, crc=False
    )
    # Safe: 0 A whatever the mode, or brake current when configured.
    safe = codec.decode(_ft_driver(ft_mode="duty").safe_frames(2)[0])
    assert safe is not None and safe.esc_id == 7
    assert safe.message == records.SetCurrent(current_a=0.0, gear=records.Gear.NONE, crc=True)
    brake = codec.decode(_ft_driver(ft_brake_current_a=4.0).safe_frames(0)[0])
    assert brake is not None and brake.message == records.SetCurrentBrake(current_a=4.0, crc=True)


@given(st.lists(ANY_FLOAT, min_size=4, max_size=4), st.integers(0, 3))
def test_ft_never_out_of_range(fractions: list[float], tick: int) -> None:
    frame = codec.decode(_ft_driver(ft_max_current_a=30.0).tick_frames(tick, fractions)[0])
    assert frame is not None and isinstance(frame.message, records.SetCurrent)
    assert -30.0 <= frame.message.current_a <= 30.0
    assert math.isfinite(frame.message.current_a)
