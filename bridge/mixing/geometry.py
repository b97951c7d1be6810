"""Multirotor geometry to mix weights: pure functions of the parsed rotors.

:func:`effectiveness_matrix` says what full command on each rotor produces (roll, pitch and yaw
torque, thrust); :func:`mix_matrix` is its pseudo-inverse, scaled so the inputs mean the same on
every airframe. The loader builds each rotor output's weights with it, and the simulated
autopilot (:mod:`bridge.sim.autopilot`) its roll, pitch and yaw factors.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from bridge.mixing.definition import Rotor

__all__ = ["effectiveness_matrix", "mix_matrix"]

# Below this a pivot of the 4x4 normal matrix (relative to its largest diagonal entry) or a mix
# weight counts as zero: the geometry then cannot produce that axis independently.
_SINGULAR_TOL = 1e-9


def effectiveness_matrix(rotors: Sequence[Rotor]) -> tuple[tuple[float, ...], ...]:
    """Return the 4 x n effectiveness matrix: what full command on rotor j produces.

    Rows: roll, pitch and yaw torque about body x, y, z (FRD; positive = right side down, nose
    up, nose right), in the units of ``cm`` and of ``ct`` times metres; then upward thrust
    (along body -z) in the units of ``ct``. Lateral force from tilted rotors is left out: no
    input commands it.
    """
    rows: list[list[float]] = [[], [], [], []]
    for r in rotors:
        norm = math.sqrt(sum(a * a for a in r.axis))
        ax, ay, az = (a / norm for a in r.axis)
        fx, fy, fz = r.ct * ax, r.ct * ay, r.ct * az
        px, py, pz = r.position_m
        # A rotor spinning CCW (seen against its thrust) has its angular momentum along +axis;
        # the body reacts with a moment along -axis, CW ones the opposite.
        spin = 1.0 if r.direction == "CCW" else -1.0
        rows[0].append(py * fz - pz * fy - spin * r.cm * ax)
        rows[1].append(pz * fx - px * fz - spin * r.cm * ay)
        rows[2].append(px * fy - py * fx - spin * r.cm * az)
        rows[3].append(-fz)
    return tuple(tuple(row) for row in rows)


def _invert(matrix: list[list[float]]) -> list[list[float]] | None:
    """Invert a small square matrix by Gauss-Jordan with partial pivoting; None if singular."""
    n = len(matrix)
    a = [row[:] + [1.0 if i == j else 0.0 for j in range(n)] for i, row in enumerate(matrix)]
    scale = max(abs(matrix[i][i]) for i in range(n)) or 1.0
    for col in range(n):
        pivot = max(range(col, n), key=lambda r: abs(a[r][col]))
        if abs(a[pivot][col]) < _SINGULAR_TOL * scale:
            return None
        a[col], a[pivot] = a[pivot], a[col]
        p = a[col][col]
        a[col] = [x / p for x in a[col]]
        for r in range(n):
            if r != col and a[r][col] != 0.0:
                f = a[r][col]
                a[r] = [x - f * y for x, y in zip(a[r], a[col], strict=True)]
    return [row[n:] for row in a]


def mix_matrix(rotors: Sequence[Rotor]) -> tuple[tuple[float, float, float, float], ...]:
    """Return the n x 4 mix matrix (rows: rotors; columns: roll, pitch, yaw, thrust).

    It is the pseudo-inverse of :func:`effectiveness_matrix`, with each column rescaled so the
    inputs mean the same on every airframe:

    * thrust: the largest entry is 1, so thrust 1 alone puts the most loaded rotor at full;
    * roll and pitch share one scale with their largest entry 0.5, so +-1 alone at half thrust
      takes the most affected rotor exactly to 0 or 1 on the weaker axis, and one unit of roll
      is the same torque as one unit of pitch;
    * yaw: the largest entry is 0.5, with the same meaning.

    Raises:
        ValueError: the rotors cannot produce roll, pitch, yaw and thrust independently, or a
            rotor would get no share of thrust.
    """
    if not rotors:
        raise ValueError("no rotors")
    b = effectiveness_matrix(rotors)
    for axis_name, row in zip(
        ("roll torque", "pitch torque", "yaw torque", "thrust"), b, strict=True
    ):
        if max(abs(x) for x in row) < _SINGULAR_TOL:
            raise ValueError(f"no rotor produces {axis_name}")
    normal = [[sum(x * y for x, y in zip(bi, bj, strict=True)) for bj in b] for bi in b]
    inverse = _invert(normal)
    if inverse is None:
        raise ValueError(
            "the rotors cannot produce roll, pitch, yaw and thrust independently "
            "(effectiveness matrix is rank-deficient)"
        )
    # pinv(B) = B^T (B B^T)^-1 for B with full row rank.
    columns = [
        [sum(b[k][j] * inverse[k][c] for k in range(4)) for j in range(len(rotors))]
        for c in range(4)
    ]
    for j, w in enumerate(columns[3]):
        if w < _SINGULAR_TOL:
            raise ValueError(
                f"rotor {j + 1} ({rotors[j].name!r}) gets no share of thrust (weight {w:.3g})"
            )
    rp_peak = max(abs(x) for x in columns[0] + columns[1])
    scales = (
        0.5 / rp_peak,
        0.5 / rp_peak,
        0.5 / max(abs(x) for x in columns[2]),
        1.0 / max(columns[3]),
    )
    return tuple(
        (
            columns[0][j] * scales[0],
            columns[1][j] * scales[1],
            columns[2][j] * scales[2],
            columns[3][j] * scales[3],
        )
        for j in range(len(rotors))
    )
