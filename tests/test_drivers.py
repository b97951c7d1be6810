"""Output drivers: fractions to frames, never out of range."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from bridge.config import build_config, with_esc_count
from bridge.escs import ckesc, ft
from bridge.escs.drivers import CkescDriver, FtDriver, make_driver

ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)


def _throttles(frames: list[ckesc.CkescFrame]) -> dict[int, int]:
    """Channel -> throttle from decoded 12b frames."""
    out = {}
    for frame in frames:
        message = frame.message
        assert isinstance(message, ckesc.RawCommand12b)
        for i, value in enumerate(message.throttles):
            out[4 * message.group - 3 + i] = value
    return out


def test_ckesc_12b_groups_and_scaling() -> None:
    driver = CkescDriver("12b", [1, 2, 3, 4, 5, 6, 7, 8])
    msgs = driver.tick_frames(0, [0.0, 0.25, 0.5, 1.0, 0.0005, 0.9995, 0.3, 0.7])
    frames = [ckesc.decode(m) for m in msgs]
    assert all(f is not None for f in frames)
    throttles = _throttles([f for f in frames if f is not None])
    assert throttles == {1: 0, 2: 500, 3: 1000, 4: 2000, 5: 1, 6: 1999, 7: 600, 8: 1400}
    # Each frame of the type takes the next transfer ID.
    assert [f.transfer_id for f in frames if f is not None] == [0, 1]
    assert [f.transfer_id for f in map(ckesc.decode, driver.safe_frames(1)) if f] == [2, 3]


def test_ckesc_channel_map_leaves_unused_channels_at_zero() -> None:
    driver = CkescDriver("12b", [3, 9])
    frames = [ckesc.decode(m) for m in driver.tick_frames(0, [1.0, 0.5])]
    throttles = _throttles([f for f in frames if f is not None])
    assert throttles[3] == 2000 and throttles[9] == 1000
    assert {k: v for k, v in throttles.items() if k not in (3, 9)} == dict.fromkeys(
        [1, 2, 4, 10, 11, 12], 0
    )


def test_ckesc_10b_and_14b() -> None:
    msg = CkescDriver("10b", [1, 2, 3, 4, 5, 6]).tick_frames(0, [0.1, 0.2, 0.3, 0.4, 0.5, 1.0])[0]
    frame = ckesc.decode(msg)
    assert frame is not None and isinstance(frame.message, ckesc.RawCommand10b)
    assert frame.message.throttles == (100, 200, 300, 400, 500, 1000)
    msg = CkescDriver("14b", [1, 2, 3, 4]).tick_frames(0, [0.5, 0.5, 0.5, 0.5])[0]
    assert msg.arbitration_id == 0x004E8400
    assert bytes(msg.data[:7]) == bytes.fromhex("e80fa03e80fa03")  # PROTOCOLS.md §1.5


@given(st.lists(ANY_FLOAT, min_size=8, max_size=8))
def test_ckesc_never_out_of_range(fractions: list[float]) -> None:
    for frame in map(ckesc.decode, CkescDriver("12b", range(1, 9)).tick_frames(0, fractions)):
        assert frame is not None and isinstance(frame.message, ckesc.RawCommand12b)
        assert all(0 <= t <= ckesc.THROTTLE_MAX for t in frame.message.throttles)


def _ft_driver(**escs: object) -> FtDriver:
    raw = {"output": {"protocol": "ft"}, "escs": {"ids": [5, 6, 7, 8], **escs}}
    driver = make_driver(with_esc_count(build_config(raw, "test"), 4))
    assert isinstance(driver, FtDriver)
    return driver


def test_ft_one_esc_per_tick_in_order() -> None:
    driver = _ft_driver(ft_max_current_a=30.0)
    assert driver.ticks_per_cycle == 4
    fractions = [0.1, 0.2, 0.5, 1.0]
    decoded = [ft.decode(driver.tick_frames(tick, fractions)[0]) for tick in range(8)]
    assert [f.esc_id for f in decoded if f] == [5, 6, 7, 8, 5, 6, 7, 8]
    currents = [
        f.message.current_a for f in decoded[:4] if f and isinstance(f.message, ft.SetCurrent)
    ]
    assert currents == [3.0, 6.0, 15.0, 30.0]


def test_ft_modes_and_safe_values() -> None:
    duty = ft.decode(_ft_driver(ft_mode="duty", ft_max_duty=0.9).tick_frames(0, [1.0] * 4)[0])
    assert duty is not None and duty.message == ft.SetDuty(duty=0.9, gear=ft.Gear.NONE, crc=True)
    erpm = ft.decode(
        _ft_driver(ft_mode="erpm", ft_max_erpm=40000, ft_crc=False, ft_gear="high").tick_frames(
            1, [0.0, 0.5, 0.0, 0.0]
        )[0]
    )
    assert erpm is not None and erpm.message == ft.SetErpm(erpm=20000, gear=ft.Gear.HIGH, crc=False)
    # Safe: 0 A whatever the mode, or brake current when configured.
    safe = ft.decode(_ft_driver(ft_mode="duty").safe_frames(2)[0])
    assert safe is not None and safe.esc_id == 7
    assert safe.message == ft.SetCurrent(current_a=0.0, gear=ft.Gear.NONE, crc=True)
    brake = ft.decode(_ft_driver(ft_brake_current_a=4.0).safe_frames(0)[0])
    assert brake is not None and brake.message == ft.SetCurrentBrake(current_a=4.0, crc=True)


@given(st.lists(ANY_FLOAT, min_size=4, max_size=4), st.integers(0, 3))
def test_ft_never_out_of_range(fractions: list[float], tick: int) -> None:
    frame = ft.decode(_ft_driver(ft_max_current_a=30.0).tick_frames(tick, fractions)[0])
    assert frame is not None and isinstance(frame.message, ft.SetCurrent)
    assert -30.0 <= frame.message.current_a <= 30.0
    assert math.isfinite(frame.message.current_a)
