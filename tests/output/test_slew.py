"""bridge.output.slew: the slew limiter."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridge.mixing.loader import load_mixer
from bridge.output.slew import SlewLimiter

NAN = math.nan


def write(tmp_path: Path, text: str) -> str:
    path = tmp_path / "frame.toml"
    path.write_text(text, encoding="utf-8")
    return str(path)


# --------------------------------------------------------------------------------------------
# Slew limiting


def test_slew_up_and_down_over_time() -> None:
    limiter = SlewLimiter([2.0, 0.0], [4.0, 0.0])  # output 2 unlimited
    ramp = [limiter.apply([1.0, 1.0], 0.1) for _ in range(6)]
    assert [r[0] for r in ramp] == pytest.approx([0.2, 0.4, 0.6, 0.8, 1.0, 1.0])
    assert all(r[1] == 1.0 for r in ramp)
    fall = [limiter.apply([0.0, 0.0], 0.1) for _ in range(3)]
    assert [r[0] for r in fall] == pytest.approx([0.6, 0.2, 0.0])
    assert all(r[1] == 0.0 for r in fall)


def test_slew_negative_direction_uses_fall_rate() -> None:
    limiter = SlewLimiter([1.0], [0.5])
    assert limiter.apply([-1.0], 1.0) == [-0.5]
    assert limiter.apply([1.0], 1.0) == [0.5]


def test_slew_zero_dt_holds_and_reset_sets() -> None:
    limiter = SlewLimiter([1.0], [1.0])
    assert limiter.apply([1.0], 0.0) == [0.0]
    limiter.reset([0.7])
    assert limiter.values == (0.7,)
    assert limiter.apply([0.7], 0.01) == [0.7]


def test_slew_from_definition(tmp_path: Path) -> None:
    mixer_def = load_mixer(
        write(
            tmp_path,
            '[info]\ndescription = "s"\n[[outputs]]\nname = "m1"\nsource = "ch1"\n'
            "slew_up = 5.0\nslew_down = 10.0\n",
        )
    )
    limiter = SlewLimiter.for_definition(mixer_def)
    assert limiter.apply([1.0], 0.1) == pytest.approx([0.5])
    assert limiter.apply([0.0], 0.01) == pytest.approx([0.4])


def test_slew_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="rise rates"):
        SlewLimiter([1.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="finite and >= 0"):
        SlewLimiter([-1.0], [1.0])
    limiter = SlewLimiter([1.0], [1.0])
    with pytest.raises(ValueError, match="dt_s"):
        limiter.apply([0.5], -0.01)
    with pytest.raises(ValueError, match="dt_s"):
        limiter.apply([0.5], NAN)
    with pytest.raises(ValueError, match="targets must be finite"):
        limiter.apply([NAN], 0.01)
    with pytest.raises(ValueError, match="expected 1 values"):
        limiter.reset([0.0, 0.0])


@given(
    targets=st.lists(st.floats(min_value=-1.0, max_value=1.0), min_size=1, max_size=20),
    dt_s=st.floats(min_value=0.0, max_value=0.1),
)
def test_slew_never_exceeds_rates(targets: list[float], dt_s: float) -> None:
    limiter = SlewLimiter([3.0], [6.0])
    previous = 0.0
    for target in targets:
        (v,) = limiter.apply([target], dt_s)
        assert -6.0 * dt_s - 1e-12 <= v - previous <= 3.0 * dt_s + 1e-12
        previous = v
