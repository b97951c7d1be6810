"""bridge.mixing.desaturation through the mixer: airmode priorities (roll and pitch, then
yaw, then thrust), against a brute-force reference."""

from __future__ import annotations

import math
from collections.abc import Sequence

import pytest
from _mixing import GEOMETRY_MIXERS, NAN, S3_2, axes, mix
from hypothesis import given
from hypothesis import strategies as st

from bridge.mixing.definition import MixerDefinition
from bridge.mixing.geometry import effectiveness_matrix
from bridge.mixing.loader import load_mixer
from bridge.mixing.mixer import Mixer

# --------------------------------------------------------------------------------------------
# Geometry mixing and desaturation


def test_quad_x_pure_roll_raises_left_lowers_right() -> None:
    mixer = Mixer(load_mixer("quad-x"))
    fr, rl, fl, rr = mix(mixer, axes(roll=0.2))
    assert (rl, fl) == pytest.approx((0.6, 0.6))  # left side up by 0.5 * 0.2
    assert (fr, rr) == pytest.approx((0.4, 0.4))


def test_quad_x_pure_pitch_raises_front() -> None:
    fr, rl, fl, rr = mix(Mixer(load_mixer("quad-x")), axes(pitch=0.2))
    assert (fr, fl, rl, rr) == pytest.approx((0.6, 0.6, 0.4, 0.4))


def test_quad_x_pure_yaw_by_spin_direction() -> None:
    # Nose right needs a clockwise reaction on the body: speed up the CCW rotors (1, 2).
    fr, rl, fl, rr = mix(Mixer(load_mixer("quad-x")), axes(yaw=0.2))
    assert (fr, rl) == pytest.approx((0.6, 0.6))
    assert (fl, rr) == pytest.approx((0.4, 0.4))


def test_hex_x_pure_axes() -> None:
    mixer = Mixer(load_mixer("hex-x"))
    # Outputs: right, left, front_left, rear_right, front_right, rear_left.
    assert mix(mixer, axes(roll=0.2)) == pytest.approx([0.4, 0.6, 0.55, 0.45, 0.45, 0.55], abs=1e-6)
    d = 0.2 * S3_2 / 2.0
    assert mix(mixer, axes(pitch=0.2)) == pytest.approx(
        [0.5, 0.5, 0.5 + d, 0.5 - d, 0.5 + d, 0.5 - d], abs=1e-6
    )
    assert mix(mixer, axes(yaw=0.2)) == pytest.approx([0.4, 0.6, 0.4, 0.6, 0.6, 0.4], abs=1e-6)


def test_thrust_alone_is_uniform() -> None:
    for name in GEOMETRY_MIXERS:
        mixer = Mixer(load_mixer(name))
        assert mix(mixer, axes(thrust=0.3)) == pytest.approx([0.3] * mixer.n_outputs, abs=1e-6)


def test_large_roll_with_high_thrust_keeps_roll_and_sacrifices_thrust() -> None:
    fr, rl, fl, rr = mix(Mixer(load_mixer("quad-x")), axes(roll=0.5, thrust=0.9))
    # Unsaturated this would be 0.9 -/+ 0.25, beyond full. The 0.5 left-right difference stays.
    assert (rl - fr, fl - rr) == pytest.approx((0.5, 0.5))
    assert max(fr, rl, fl, rr) == pytest.approx(1.0)
    assert (fr + rl + fl + rr) / 4 == pytest.approx(0.75)  # thrust gave way


def test_yaw_is_sacrificed_before_roll() -> None:
    # Full roll uses the whole range at half thrust: nothing is left for yaw.
    fr, rl, fl, rr = mix(Mixer(load_mixer("quad-x")), axes(roll=1.0, yaw=1.0))
    assert (fr, rl, fl, rr) == pytest.approx((0.0, 1.0, 1.0, 0.0))


def test_yaw_is_kept_before_thrust() -> None:
    fr, rl, fl, rr = mix(Mixer(load_mixer("quad-x")), axes(yaw=0.5, thrust=1.0))
    assert (fr, rl, fl, rr) == pytest.approx((1.0, 1.0, 0.5, 0.5))


def test_partial_yaw_when_roll_leaves_some_room() -> None:
    # roll 0.6 spans 0.6 of the range; yaw 1.0 would need another 1.0: only 0.4 is left.
    fr, rl, fl, rr = mix(Mixer(load_mixer("quad-x")), axes(roll=0.6, yaw=1.0))
    # Roll difference kept on both pairs (within a pair both rotors spin the same way, so yaw
    # moves them together).
    assert rl - fr == pytest.approx(0.6)
    assert fl - rr == pytest.approx(0.6)
    yaw_achieved = ((fr + rl) - (fl + rr)) / 2
    assert yaw_achieved == pytest.approx(0.4)
    assert min(fr, rl, fl, rr) == pytest.approx(0.0)
    assert max(fr, rl, fl, rr) == pytest.approx(1.0)


def test_roll_and_pitch_beyond_range_scale_down_together() -> None:
    # roll = pitch = 1 would need front-left 2.0 above rear-right: scaled by 1/2, same direction.
    fr, rl, fl, rr = mix(Mixer(load_mixer("quad-x")), axes(roll=1.0, pitch=1.0))
    assert (fl, rr) == pytest.approx((1.0, 0.0))
    assert fr == pytest.approx(rl)


def test_airmode_keeps_torque_at_zero_thrust_above_idle() -> None:
    mixer = Mixer(load_mixer("quad-x"))  # idle 0.05
    fr, rl, fl, rr = mix(mixer, axes(roll=0.2, thrust=0.0), armed=True)
    assert (fr, rr) == pytest.approx((0.05, 0.05))
    assert (rl, fl) == pytest.approx((0.25, 0.25))
    assert mix(mixer, axes(thrust=0.0), armed=True) == pytest.approx([0.05] * 4)
    assert mix(mixer, axes(thrust=0.0), armed=False) == pytest.approx([0.0] * 4)


def test_geometry_nan_or_inf_gives_none() -> None:
    mixer = Mixer(load_mixer("quad-x"))
    for bad in (NAN, math.inf, -math.inf):
        for k in range(4):
            vector = axes()
            vector[32 + k] = bad
            assert mixer.mix(vector, True) is None


def test_wrong_input_length() -> None:
    with pytest.raises(ValueError, match="expected 36 inputs, got 4"):
        Mixer(load_mixer("passthrough-4")).mix([1500.0] * 4, False)


def largest_fitting_scale(
    lo: Sequence[float], hi: Sequence[float], t: Sequence[float], d: Sequence[float]
) -> float:
    """Reference for desaturation, by brute force over rotor pairs.

    The largest s in [0, 1] such that one thrust tau gives lo[i] <= t[i]*tau + s*d[i] <= hi[i].
    """
    best = 1.0
    for lo_i, t_i, d_i in zip(lo, t, d, strict=True):
        for hi_j, t_j, d_j in zip(hi, t, d, strict=True):
            # Need (lo_i - s d_i)/t_i <= (hi_j - s d_j)/t_j.
            slope = d_j / t_j - d_i / t_i
            if slope > 0.0:
                best = min(best, (hi_j / t_j - lo_i / t_i) / slope)
    return max(best, 0.0)


def achieved(definition: MixerDefinition, out: Sequence[float]) -> list[float]:
    """Roll, pitch, yaw, thrust (input units) that the rotor commands ``out`` produce."""
    b = effectiveness_matrix(definition.rotors)
    m = [tuple(w for _, w in o.weights) for o in definition.outputs]
    return [
        sum(bc * u for bc, u in zip(b[c], out, strict=True))
        / sum(bc * row[c] for bc, row in zip(b[c], m, strict=True))
        for c in range(4)
    ]


axis_value = st.floats(min_value=-1.0, max_value=1.0)


@given(
    name=st.sampled_from(GEOMETRY_MIXERS),
    roll=axis_value,
    pitch=axis_value,
    yaw=axis_value,
    thrust=st.floats(min_value=0.0, max_value=1.0),
    armed=st.booleans(),
)
def test_desaturation_priorities_property(
    name: str, roll: float, pitch: float, yaw: float, thrust: float, armed: bool
) -> None:
    definition = load_mixer(name)
    out = mix(Mixer(definition), axes(roll, pitch, yaw, thrust), armed)
    lo = [o.idle if armed else o.minimum for o in definition.outputs]
    hi = [o.maximum for o in definition.outputs]
    assert all(lo_i - 1e-9 <= v <= hi_i + 1e-9 for lo_i, v, hi_i in zip(lo, out, hi, strict=True))

    got_roll, got_pitch, got_yaw, got_thrust = achieved(definition, out)
    rows = [tuple(w for _, w in o.weights) for o in definition.outputs]
    t = [row[3] for row in rows]
    # Roll and pitch: the largest fitting fraction of the command, in the commanded direction.
    g = largest_fitting_scale(lo, hi, t, [row[0] * roll + row[1] * pitch for row in rows])
    assert got_roll == pytest.approx(g * roll, abs=1e-6)
    assert got_pitch == pytest.approx(g * pitch, abs=1e-6)
    # Yaw: the largest fraction that fits on top of that.
    free_lo = [x - g * (row[0] * roll + row[1] * pitch) for x, row in zip(lo, rows, strict=True)]
    free_hi = [x - g * (row[0] * roll + row[1] * pitch) for x, row in zip(hi, rows, strict=True)]
    k = largest_fitting_scale(free_lo, free_hi, t, [row[2] * yaw for row in rows])
    assert got_yaw == pytest.approx(k * yaw, abs=1e-6)
    # Thrust: exactly as commanded whenever torques took nothing from it.
    if g == 1.0 and k == 1.0:
        unsaturated = [
            ti * thrust + row[0] * roll + row[1] * pitch + row[2] * yaw
            for ti, row in zip(t, rows, strict=True)
        ]
        if all(a <= v <= b for a, v, b in zip(lo, unsaturated, hi, strict=True)):
            assert got_thrust == pytest.approx(thrust, abs=1e-6)
