"""Tests for bridge.mixing: loading, geometry matrices, mixing, desaturation and slew limiting."""

from __future__ import annotations

import math
import timeit
from collections.abc import Sequence
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridge.errors import ConfigError
from bridge.mixing.definition import (
    AXIS_VALID_RANGE,
    INPUT_NAMES,
    Mixer,
    MixerDefinition,
    OutputSpec,
    Rotor,
    SlewLimiter,
    bundled_mixer_names,
    effectiveness_matrix,
    load_mixer,
    mix_matrix,
)

NAN = math.nan
GEOMETRY_MIXERS = ("quad-x", "hex-x", "octo-x", "coax-x8")
S3_2 = math.sqrt(3.0) / 2.0


def inputs(
    channels: Sequence[float] = (),
    roll: float = NAN,
    pitch: float = NAN,
    yaw: float = NAN,
    thrust: float = NAN,
) -> list[float]:
    """A 36-entry input vector: the given channels from ch1 on, NaN for the rest."""
    vector = [*channels, *[NAN] * (32 - len(channels)), roll, pitch, yaw, thrust]
    assert len(vector) == len(INPUT_NAMES)
    return vector


def axes(
    roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0, thrust: float = 0.5
) -> list[float]:
    return inputs(roll=roll, pitch=pitch, yaw=yaw, thrust=thrust)


def mix(mixer: Mixer, vector: Sequence[float], armed: bool = False) -> list[float]:
    result = mixer.mix(vector, armed)
    assert result is not None
    return result


def write(tmp_path: Path, text: str, name: str = "frame.toml") -> str:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return str(path)


def one_output(tmp_path: Path, keys: str) -> Mixer:
    """A mixer with a single direct output 'm1' whose keys are ``keys``."""
    text = f'[info]\ndescription = "test"\n\n[[outputs]]\nname = "m1"\n{keys}\n'
    return Mixer(load_mixer(write(tmp_path, text)))


# --------------------------------------------------------------------------------------------
# Bundled mixers


def test_bundled_names() -> None:
    assert bundled_mixer_names() == sorted(
        [
            "coax-x8",
            "hex-x",
            "octo-x",
            "passthrough-12",
            "passthrough-16",
            "passthrough-4",
            "passthrough-6",
            "passthrough-8",
            "quad-x",
        ]
    )


@pytest.mark.parametrize("name", bundled_mixer_names())
def test_every_bundled_mixer_loads_and_mixes(name: str) -> None:
    definition = load_mixer(name)
    assert definition.name == name  # the info key matches the file name
    assert definition.description
    mixer = Mixer(definition)
    vector = inputs([1500.0] * 32, roll=0.0, pitch=0.0, yaw=0.0, thrust=0.5)
    for armed in (False, True):
        out = mix(mixer, vector, armed)
        assert len(out) == mixer.n_outputs == len(definition.outputs)
        assert out == pytest.approx([0.5] * mixer.n_outputs)


@pytest.mark.parametrize("n", [4, 6, 8, 12, 16])
def test_passthrough_maps_channel_n_to_output_n(n: int) -> None:
    mixer = Mixer(load_mixer(f"passthrough-{n}"))
    assert mixer.n_outputs == n
    for k in range(n):
        for pwm_us, expected in ((1000.0, 0.0), (1500.0, 0.5), (2000.0, 1.0)):
            channels = [1250.0] * n
            channels[k] = pwm_us
            out = mix(mixer, inputs(channels))
            assert out[k] == pytest.approx(expected)
            assert all(v == pytest.approx(0.25) for i, v in enumerate(out) if i != k)


def test_passthrough_clamps_out_of_range_pulses() -> None:
    mixer = Mixer(load_mixer("passthrough-4"))
    assert mix(mixer, inputs([900.0, 2100.0, 0.0, 65535.0])) == [0.0, 1.0, 0.0, 1.0]


def test_out_of_range_channel_counts_as_its_end_in_a_sum(tmp_path: Path) -> None:
    # Clamped per input, so a glitching channel cannot push its partner's share around.
    mixer = one_output(tmp_path, "source = { ch1 = 0.5, ch2 = 0.5 }")
    assert mix(mixer, inputs([2500.0, 1000.0])) == pytest.approx([0.5])
    assert mix(mixer, inputs([500.0, 2000.0])) == pytest.approx([0.5])


def test_passthrough_ignores_channels_it_does_not_use() -> None:
    mixer = Mixer(load_mixer("passthrough-4"))
    vector = inputs([1500.0] * 4)  # ch5..ch32 and the axes are NaN
    assert mix(mixer, vector) == [0.5] * 4


def test_input_range_override_for_normalized_sources() -> None:
    unit = load_mixer("passthrough-4").with_input_range(0.0, 1.0)
    assert mix(Mixer(unit), inputs([0.0, 0.25, 1.0, 0.5])) == [0.0, 0.25, 1.0, 0.5]
    signed = load_mixer("passthrough-4", input_range=(-1.0, 1.0))
    assert mix(Mixer(signed), inputs([-1.0, 0.0, 1.0, 0.5])) == [0.0, 0.5, 1.0, 0.75]


def test_input_range_override_leaves_axis_only_outputs_alone() -> None:
    definition = load_mixer("quad-x")
    assert definition.with_input_range(0.0, 1.0) == definition


def test_input_range_override_is_validated() -> None:
    with pytest.raises(ConfigError, match=r"passthrough-4\.toml: input range override: .*< high"):
        load_mixer("passthrough-4").with_input_range(2000.0, 1000.0)


def test_unknown_bundled_name() -> None:
    with pytest.raises(ConfigError, match="unknown mixer 'quad-y'; bundled: coax-x8"):
        load_mixer("quad-y")


def test_missing_file(tmp_path: Path) -> None:
    missing = tmp_path / "absent.toml"
    with pytest.raises(ConfigError, match=r"absent\.toml: cannot read mixer"):
        load_mixer(str(missing))


def test_rotor_positions_are_kept_with_their_outputs() -> None:
    definition = load_mixer("quad-x")
    assert [o.name for o in definition.outputs] == [
        "front_right",
        "rear_left",
        "front_left",
        "rear_right",
    ]
    assert [r.direction for r in definition.rotors] == ["CCW", "CCW", "CW", "CW"]
    x, y, _ = definition.rotors[0].position_m
    assert x > 0.0 and y > 0.0  # motor 1 front right, in metres FRD


# --------------------------------------------------------------------------------------------
# Geometry matrices, against hand-worked values


def quad_x_rotors(arm_m: float = 1.0) -> list[Rotor]:
    """PX4/ArduPilot quad X: 1 front right CCW, 2 rear left CCW, 3 front left CW, 4 rear right CW.

    Arms of ``arm_m`` metres.
    """
    c = arm_m / math.sqrt(2.0)
    return [
        Rotor("front_right", (c, c, 0.0), "CCW"),
        Rotor("rear_left", (-c, -c, 0.0), "CCW"),
        Rotor("front_left", (c, -c, 0.0), "CW"),
        Rotor("rear_right", (-c, c, 0.0), "CW"),
    ]


def hex_x_rotors() -> list[Rotor]:
    """PX4/ArduPilot hexa X with unit arms.

    1 right CW, 2 left CCW, 3 front left CW, 4 rear right CCW, 5 front right CCW, 6 rear left CW.
    """
    return [
        Rotor("right", (0.0, 1.0, 0.0), "CW"),
        Rotor("left", (0.0, -1.0, 0.0), "CCW"),
        Rotor("front_left", (S3_2, -0.5, 0.0), "CW"),
        Rotor("rear_right", (-S3_2, 0.5, 0.0), "CCW"),
        Rotor("front_right", (S3_2, 0.5, 0.0), "CCW"),
        Rotor("rear_left", (-S3_2, -0.5, 0.0), "CW"),
    ]


def test_quad_x_effectiveness() -> None:
    # Thrust f = (0, 0, -1) per rotor. Roll = p_y f_z - p_z f_y = -p_y: a rotor on the right
    # rolls the body left. Pitch = p_z f_x - p_x f_z = p_x: a front rotor pitches nose up.
    # Yaw: the reaction moment of a CCW rotor points down (+z), nose right: +Cm.
    c = 1.0 / math.sqrt(2.0)
    roll, pitch, yaw, thrust = effectiveness_matrix(quad_x_rotors())
    assert roll == pytest.approx([-c, c, c, -c])
    assert pitch == pytest.approx([c, -c, c, -c])
    assert yaw == pytest.approx([0.05, 0.05, -0.05, -0.05])
    assert thrust == pytest.approx([1.0, 1.0, 1.0, 1.0])


def test_quad_x_mix_matrix() -> None:
    # The rows above are orthogonal, so each pseudo-inverse column is row / |row|^2, e.g.
    # roll (-1, 1, 1, -1) / (4c); rescaled to largest entry 0.5 (torques) and 1 (thrust).
    expected = [
        (-0.5, 0.5, 0.5, 1.0),
        (0.5, -0.5, 0.5, 1.0),
        (0.5, 0.5, -0.5, 1.0),
        (-0.5, -0.5, -0.5, 1.0),
    ]
    for arm_m in (1.0, 0.25):  # the scale of the frame does not matter
        for row, want in zip(mix_matrix(quad_x_rotors(arm_m)), expected, strict=True):
            assert row == pytest.approx(want)


def test_hex_x_mix_matrix() -> None:
    # Roll row -p_y = (-1, 1, 1/2, -1/2, -1/2, 1/2), |.|^2 = 3; pitch row p_x =
    # (0, 0, s, -s, s, -s) with s = sqrt(3)/2, |.|^2 = 3; all rows orthogonal. Roll and pitch
    # share the scale that brings the larger entry (roll, 1/3) to 0.5: pitch peaks at s/2.
    q = S3_2 / 2.0
    expected = [
        (-0.5, 0.0, -0.5, 1.0),
        (0.5, 0.0, 0.5, 1.0),
        (0.25, q, -0.5, 1.0),
        (-0.25, -q, 0.5, 1.0),
        (-0.25, q, 0.5, 1.0),
        (0.25, -q, -0.5, 1.0),
    ]
    for row, want in zip(mix_matrix(hex_x_rotors()), expected, strict=True):
        assert row == pytest.approx(want)


def test_bundled_geometries_match_hand_worked_matrices() -> None:
    for name, rotors in (("quad-x", quad_x_rotors()), ("hex-x", hex_x_rotors())):
        bundled = [tuple(w for _, w in o.weights) for o in load_mixer(name).outputs]
        for got, want in zip(bundled, mix_matrix(rotors), strict=True):
            assert got == pytest.approx(want, abs=1e-5)


def test_axis_length_and_coefficient_scale_do_not_matter() -> None:
    base = mix_matrix(quad_x_rotors())
    scaled = [
        Rotor(r.name, r.position_m, r.direction, axis=(0.0, 0.0, -3.0), ct=7.0, cm=0.35)
        for r in quad_x_rotors()
    ]
    for got, want in zip(mix_matrix(scaled), base, strict=True):
        assert got == pytest.approx(want)


def test_uneven_rotor_gets_a_larger_thrust_share() -> None:
    # A weaker rear-left rotor (half Ct) must be commanded more for the same thrust; the
    # strongest-loaded rotor sets the thrust scale, so it reaches 1 at thrust 1.
    rotors = quad_x_rotors()
    rotors[1] = Rotor("rear_left", rotors[1].position_m, "CCW", ct=0.5)
    thrust_column = [row[3] for row in mix_matrix(rotors)]
    assert max(thrust_column) == pytest.approx(1.0)
    assert thrust_column.index(1.0) == 1


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


# --------------------------------------------------------------------------------------------
# Output shaping on direct outputs


def test_reversed_unidirectional(tmp_path: Path) -> None:
    mixer = one_output(tmp_path, 'source = "ch1"\nreversed = true')
    assert mix(mixer, inputs([1200.0])) == pytest.approx([0.8])
    assert mix(mixer, inputs([2000.0])) == pytest.approx([0.0])


def test_reversible_esc_from_centred_pwm(tmp_path: Path) -> None:
    mixer = one_output(tmp_path, "source = { ch1 = 2.0 }\noffset = -1.0\nmin = -1.0")
    for pwm_us, expected in ((1000.0, -1.0), (1250.0, -0.5), (1500.0, 0.0), (2000.0, 1.0)):
        assert mix(mixer, inputs([pwm_us]), armed=True) == pytest.approx([expected])


def test_reversed_bidirectional_mirrors_about_zero(tmp_path: Path) -> None:
    keys = "source = { ch1 = 2.0 }\noffset = -1.0\nmin = -1.0\nreversed = true"
    mixer = one_output(tmp_path, keys)
    assert mix(mixer, inputs([1750.0])) == pytest.approx([-0.5])
    assert mix(mixer, inputs([1000.0])) == pytest.approx([1.0])


def test_deadband_around_stop(tmp_path: Path) -> None:
    keys = "source = { ch1 = 2.0 }\noffset = -1.0\nmin = -1.0\ndeadband = 0.1"
    mixer = one_output(tmp_path, keys)
    assert mix(mixer, inputs([1520.0])) == [0.0]
    assert mix(mixer, inputs([1480.0])) == [0.0]
    assert mix(mixer, inputs([1600.0])) == pytest.approx([0.2])  # not rescaled
    assert mix(mixer, inputs([1400.0])) == pytest.approx([-0.2])


def test_idle_only_when_armed(tmp_path: Path) -> None:
    mixer = one_output(tmp_path, 'source = "ch1"\nidle = 0.1\ndeadband = 0.05')
    assert mix(mixer, inputs([1000.0]), armed=True) == pytest.approx([0.1])
    assert mix(mixer, inputs([1000.0]), armed=False) == [0.0]
    assert mix(mixer, inputs([1030.0]), armed=True) == pytest.approx([0.1])  # deadband, then idle
    assert mix(mixer, inputs([1500.0]), armed=True) == pytest.approx([0.5])


def test_min_max_clamps(tmp_path: Path) -> None:
    keys = "source = { ch1 = 2.0 }\noffset = -1.0\nmin = -0.5\nmax = 0.8"
    mixer = one_output(tmp_path, keys)
    assert mix(mixer, inputs([2000.0])) == pytest.approx([0.8])
    assert mix(mixer, inputs([1000.0])) == pytest.approx([-0.5])
    assert mix(mixer, inputs([1600.0])) == pytest.approx([0.2])


def test_weighted_sum_with_axes_and_channels(tmp_path: Path) -> None:
    # A coaxial pair by hand: upper = thrust + yaw/2, lower = thrust - yaw/2 from a channel.
    text = """
[info]
description = "coax pair"

[output_default]
input_range = [0.0, 1.0]

[[outputs]]
name = "upper"
source = { thrust = 1.0, yaw = 0.5 }

[[outputs]]
name = "lower"
source = { ch5 = 1.0, yaw = -0.5 }
"""
    mixer = Mixer(load_mixer(write(tmp_path, text)))
    vector = inputs([0.0] * 4 + [0.6], yaw=0.4, thrust=0.6)
    assert mix(mixer, vector) == pytest.approx([0.8, 0.4])
    vector[4] = NAN  # lower's channel missing
    assert mixer.mix(vector, True) is None


def test_defaults_apply_and_entries_override(tmp_path: Path) -> None:
    text = """
[info]
description = "defaults"

[output_default]
max = 0.5
slew_up = 2.0

[[outputs]]
name = "a"
source = "ch1"

[[outputs]]
name = "b"
source = "ch2"
max = 0.9
"""
    definition = load_mixer(write(tmp_path, text))
    a, b = definition.outputs
    assert (a.maximum, a.slew_up_per_s, a.idle, a.input_range) == (0.5, 2.0, 0.0, (1000.0, 2000.0))
    assert (b.maximum, b.slew_up_per_s) == (0.9, 2.0)
    assert definition.name == "frame"  # no info key: the file name


@pytest.mark.parametrize("bad", [NAN, math.inf, -math.inf])
def test_direct_nan_or_inf_gives_none(bad: float) -> None:
    mixer = Mixer(load_mixer("passthrough-8"))
    vector = inputs([1500.0] * 8)
    vector[7] = bad
    assert mixer.mix(vector, True) is None
    assert mixer.mix(vector, False) is None


finite = st.floats(allow_nan=False, allow_infinity=False)


@given(channels=st.lists(finite, min_size=4, max_size=4), armed=st.booleans())
def test_outputs_within_range_for_any_finite_inputs(channels: list[float], armed: bool) -> None:
    outputs = (
        OutputSpec("fwd", (("ch1", 1.0),), idle=0.1, maximum=0.9),
        OutputSpec(
            "rev",
            (("ch2", 2.0), ("ch3", -0.7)),
            offset=-1.0,
            minimum=-0.8,
            idle=-0.8,
            reversed=True,
        ),
        OutputSpec("mixed", (("ch4", 3.0), ("roll", 1.0)), offset=-1.0, minimum=-1.0, deadband=0.3),
    )
    definition = MixerDefinition("prop", "property", outputs)
    out = mix(Mixer(definition), inputs(channels, roll=channels[0]), armed)
    for spec, v in zip(outputs, out, strict=True):
        assert spec.minimum <= v <= spec.maximum
        if armed:
            assert v >= spec.idle


@given(
    name=st.sampled_from(GEOMETRY_MIXERS),
    values=st.lists(finite, min_size=4, max_size=4),
    armed=st.booleans(),
)
def test_geometry_outputs_within_range_for_any_finite_inputs(
    name: str, values: list[float], armed: bool
) -> None:
    definition = load_mixer(name)
    out = mix(
        Mixer(definition),
        inputs(roll=values[0], pitch=values[1], yaw=values[2], thrust=values[3]),
        armed,
    )
    for spec, v in zip(definition.outputs, out, strict=True):
        assert (spec.idle if armed else spec.minimum) <= v <= spec.maximum


@pytest.mark.parametrize(
    ("pwm", "valid"),
    [
        (799.9, False),
        (800.0, True),
        (1500.0, True),
        (2200.0, True),
        (2200.1, False),
        (3000.0, False),
        (65535.0, False),
        (math.inf, False),
        (NAN, False),
    ],
)
def test_a_channel_outside_the_valid_range_refuses_the_input(pwm: float, valid: bool) -> None:
    mixer = Mixer(load_mixer("passthrough-4"), (800.0, 2200.0))
    result = mixer.mix(inputs([1500.0, pwm, 1500.0, 1500.0]), armed=True)
    if valid:
        assert result is not None and result[1] == min(max((pwm - 1000) / 1000, 0.0), 1.0)
    else:
        assert result is None  # never clamped into full throttle


@pytest.mark.parametrize("value", [1.6, -1.6, 1e38, -math.inf])
def test_an_axis_outside_its_valid_range_refuses_the_input(value: float) -> None:
    mixer = Mixer(load_mixer("quad-x"), None, AXIS_VALID_RANGE)
    assert mixer.mix(inputs(roll=value, pitch=0.0, yaw=0.0, thrust=0.5), armed=True) is None
    assert mixer.mix(inputs(roll=1.5, pitch=0.0, yaw=0.0, thrust=0.5), armed=True) is not None


def test_without_valid_ranges_only_non_finite_inputs_are_refused() -> None:
    mixer = Mixer(load_mixer("passthrough-4"))
    assert mix(mixer, inputs([1e300, 1500.0, 1500.0, 1500.0]))[0] == 1.0  # clamped
    assert mixer.mix(inputs([math.inf, 1500.0, 1500.0, 1500.0]), False) is None


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


# --------------------------------------------------------------------------------------------
# Invalid definitions: each refused with the file and the entry named

PASSTHROUGH_HEAD = '[info]\ndescription = "bad"\n\n'
OUT1 = '[[outputs]]\nname = "m1"\nsource = "ch1"\n\n[[outputs]]\nname = "m2"\nsource = "ch2"\n\n'
QUAD_HEAD = '[info]\ndescription = "bad"\n[rotor_default]\ndirection = "CW"\n'


def rotors_text(*entries: str) -> str:
    return QUAD_HEAD + "".join(f"\n[[rotors]]\n{e}\n" for e in entries)


GOOD_QUAD = (
    'name = "a"\nposition = [1.0, 1.0, 0.0]\ndirection = "CCW"',
    'name = "b"\nposition = [-1.0, -1.0, 0.0]\ndirection = "CCW"',
    'name = "c"\nposition = [1.0, -1.0, 0.0]',
    'name = "d"\nposition = [-1.0, 1.0, 0.0]',
)

INVALID = {
    "unknown input": (
        PASSTHROUGH_HEAD + OUT1 + '[[outputs]]\nname = "m3"\nsource = "ch33"\n',
        "output 3 ('m3'): source: unknown input 'ch33'",
    ),
    "unknown input in weights": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = { rol = 1.0 }\n',
        "output 1 ('m1'): source: unknown input 'rol'",
    ),
    "weights as an array": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = [1.0, 0.5]\n',
        "output 1 ('m1'): source must be an input name",
    ),
    "weight not a number": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = { ch1 = "1" }\n',
        "output 1 ('m1'): source weight of 'ch1' must be a number",
    ),
    "empty weights": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = {}\n',
        "output 1 ('m1'): source names no input",
    ),
    "min above max": (
        PASSTHROUGH_HEAD
        + OUT1
        + '[[outputs]]\nname = "m3"\nsource = "ch3"\nmin = 0.8\nmax = 0.2\n',
        "output 3 ('m3'): min 0.8 > max 0.2",
    ),
    "max beyond 1": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nmax = 1.5\n',
        "output 1 ('m1'): max 1.5 outside -1..1",
    ),
    "range without stop": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nmin = 0.1\n',
        "output 1 ('m1'): [min 0.1, max 1] must contain 0",
    ),
    "idle outside range": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nidle = -0.1\n',
        "output 1 ('m1'): idle -0.1 outside [min 0, max 1]",
    ),
    "input range reversed": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\ninput_range = [2000, 1000]\n',
        "output 1 ('m1'): input_range low 2000 must be < high 1000",
    ),
    "input range beyond limits": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\ninput_range = [0, 70000]\n',
        "output 1 ('m1'): input_range [0, 70000] outside -1..65535",
    ),
    "input range shape": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\ninput_range = [1000]\n',
        "output 1 ('m1'): input_range must be an array of 2 numbers",
    ),
    "deadband too large": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\ndeadband = 1.0\n',
        "output 1 ('m1'): deadband 1 outside 0 <= deadband < 1",
    ),
    "negative slew": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nslew_down = -1\n',
        "output 1 ('m1'): slew_down -1 must be >= 0",
    ),
    "offset too large": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\noffset = 2.0\n',
        "output 1 ('m1'): offset 2 outside -1..1",
    ),
    "bool for a number": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nmax = true\n',
        "output 1 ('m1'): max must be a number, got True",
    ),
    "string for a bool": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = "ch1"\nreversed = "yes"\n',
        "output 1 ('m1'): reversed must be true or false",
    ),
    "unknown output key": (
        PASSTHROUGH_HEAD + OUT1 + '[[outputs]]\nname = "m3"\nsource = "ch3"\nrevresed = true\n',
        "output 3 ('m3'): unknown key 'revresed' in an output",
    ),
    "unknown default key": (
        PASSTHROUGH_HEAD + "[output_default]\nidel = 0.1\n\n" + OUT1,
        "output_default: unknown key 'idel'",
    ),
    "unknown top-level key": (
        PASSTHROUGH_HEAD + OUT1 + "[mixer]\nx = 1\n",
        "top level: unknown key 'mixer'",
    ),
    "duplicate key": (
        PASSTHROUGH_HEAD + OUT1 + '[[outputs]]\nname = "m3"\nsource = "ch3"\nsource = "ch4"\n',
        "invalid TOML: Cannot overwrite a value (at line 15, column 15): 'source = \"ch4\"'",
    ),
    "duplicate weight": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\nsource = { ch1 = 1.0, ch1 = 0.5 }\n',
        "invalid TOML: Duplicate inline table key 'ch1'",
    ),
    "duplicate output name": (
        PASSTHROUGH_HEAD + OUT1 + '[[outputs]]\nname = "m1"\nsource = "ch3"\n',
        "output 3 ('m1'): name already used by output 1",
    ),
    "missing name": (
        PASSTHROUGH_HEAD + OUT1 + '[[outputs]]\nsource = "ch3"\n',
        "output 3: missing key 'name'",
    ),
    "missing source": (
        PASSTHROUGH_HEAD + '[[outputs]]\nname = "m1"\n',
        "output 1 ('m1'): missing key 'source'",
    ),
    "outputs not an array": (
        "outputs = 3\n" + PASSTHROUGH_HEAD,
        "outputs: outputs must be an array of tables",
    ),
    "too many outputs": (
        PASSTHROUGH_HEAD
        + "".join(f'[[outputs]]\nname = "m{i}"\nsource = "ch1"\n' for i in range(1, 34)),
        "33 outputs; a mixer has 1..32",
    ),
    "no outputs": (PASSTHROUGH_HEAD, "defines no outputs"),
    "missing description": ('[info]\nkey = "x"\n' + OUT1, "info: description must be"),
    "missing info": (OUT1, "info: [info] must be a table"),
    "bad key": ('[info]\nkey = "my frame"\ndescription = "d"\n' + OUT1, "info: key 'my frame'"),
    "syntax error": (PASSTHROUGH_HEAD + "[[outputs]\n", "invalid TOML"),
    "rotor direction": (
        rotors_text(*GOOD_QUAD[:3], 'name = "d"\nposition = [-1.0, 1.0, 0.0]\ndirection = "cw"'),
        "rotor 4 ('d'): direction must be 'CW' or 'CCW', got 'cw'",
    ),
    "rotor position shape": (
        rotors_text(*GOOD_QUAD[:3], 'name = "d"\nposition = [-1.0, 1.0]'),
        "rotor 4 ('d'): position must be an array of 3 numbers",
    ),
    "rotor missing position": (
        rotors_text(*GOOD_QUAD[:3], 'name = "d"'),
        "rotor 4 ('d'): missing key 'position'",
    ),
    "rotor missing direction": (
        '[info]\ndescription = "bad"\n[[rotors]]\nname = "a"\nposition = [1.0, 1.0, 0.0]\n',
        "rotor 1 ('a'): missing key 'direction'",
    ),
    "rotor zero axis": (
        rotors_text(*GOOD_QUAD[:3], GOOD_QUAD[3] + "\naxis = [0.0, 0.0, 0.0]"),
        "rotor 4 ('d'): axis must not be the zero vector",
    ),
    "rotor ct": (
        rotors_text(GOOD_QUAD[0] + "\nCt = 0.0", *GOOD_QUAD[1:]),
        "rotor 1 ('a'): Ct 0 must be > 0",
    ),
    "rotor negative cm": (
        rotors_text(GOOD_QUAD[0] + "\nCm = -0.05", *GOOD_QUAD[1:]),
        "rotor 1 ('a'): Cm -0.05 must be >= 0",
    ),
    "rotor reversed": (
        rotors_text(GOOD_QUAD[0] + "\nreversed = true", *GOOD_QUAD[1:]),
        "rotor 1 ('a'): unknown key 'reversed' in a rotor",
    ),
    "rotor idle above max": (
        rotors_text(*GOOD_QUAD[:2], GOOD_QUAD[2] + "\nidle = 0.5\nmax = 0.3", GOOD_QUAD[3]),
        "rotor 3 ('c'): idle 0.5 outside [min 0, max 0.3]",
    ),
    "rotor default unknown key": (
        rotors_text(*GOOD_QUAD).replace(
            "[rotor_default]\n", "[rotor_default]\nposition = [0, 0, 0]\n"
        ),
        "rotor_default: unknown key 'position'",
    ),
    "geometry cannot yaw": (
        rotors_text(*(r.replace('direction = "CCW"', 'direction = "CW"') for r in GOOD_QUAD)),
        "rotors: the rotors cannot produce roll, pitch, yaw and thrust independently",
    ),
    "geometry cannot roll": (
        rotors_text(
            'name = "a"\nposition = [1.0, 0.0, 0.0]\ndirection = "CCW"',
            'name = "b"\nposition = [-1.0, 0.0, 0.0]',
        ),
        "rotors: no rotor produces roll torque",
    ),
    "rotor and output share a name": (
        rotors_text(*GOOD_QUAD) + '\n[[outputs]]\nname = "a"\nsource = "ch5"\n',
        "output 5 ('a'): name already used by output 1",
    ),
}


@pytest.mark.parametrize("case", sorted(INVALID))
def test_invalid_definition_is_refused_with_file_and_entry(tmp_path: Path, case: str) -> None:
    text, expected = INVALID[case]
    path = write(tmp_path, text, name="broken.toml")
    with pytest.raises(ConfigError) as caught:
        load_mixer(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: "), message
    assert expected in message, message


def test_invalid_utf8_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "latin1.toml"
    path.write_bytes(b'[info]\ndescription = "caf\xe9"\n')
    with pytest.raises(ConfigError, match=r"latin1\.toml: not UTF-8"):
        load_mixer(str(path))


def test_valid_mixed_file_numbers_rotors_first(tmp_path: Path) -> None:
    text = rotors_text(*GOOD_QUAD) + '\n[[outputs]]\nname = "gimbal"\nsource = "ch5"\n'
    definition = load_mixer(write(tmp_path, text))
    assert [o.name for o in definition.outputs] == ["a", "b", "c", "d", "gimbal"]
    out = mix(Mixer(definition), inputs([1000.0] * 4 + [1750.0], 0.0, 0.0, 0.0, 0.5))
    assert out == pytest.approx([0.5, 0.5, 0.5, 0.5, 0.75])


# --------------------------------------------------------------------------------------------
# Speed (the real bound is asserted loosely; the measured figure is printed with -s)


@pytest.mark.parametrize("name", ["passthrough-8", "octo-x"])
def test_mix_is_fast(name: str) -> None:
    mixer = Mixer(load_mixer(name))
    vector = inputs([1500.0] * 8, roll=1.0, pitch=0.7, yaw=1.0, thrust=0.9)
    runs = 2000
    per_call_s = min(timeit.repeat(lambda: mixer.mix(vector, True), number=runs, repeat=3)) / runs
    print(f"{name}: mix() {per_call_s * 1e6:.1f} us")
    # 20 us is the target on the companion computer; leave room for slow CI machines.
    assert per_call_s < 200e-6
