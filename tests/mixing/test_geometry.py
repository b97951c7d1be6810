"""bridge.mixing.geometry: effectiveness and mix matrices against hand-worked quad-X and hex-X
results."""

from __future__ import annotations

import math

import pytest

from bridge.mixing.definition import Rotor
from bridge.mixing.geometry import effectiveness_matrix, mix_matrix
from bridge.mixing.loader import load_mixer

S3_2 = math.sqrt(3.0) / 2.0

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
