"""Desaturation of a geometry mixer's rotor outputs, as PX4's airmode does it.

Roll and pitch keep their authority before yaw, and yaw before thrust: when the commanded
torques do not fit between the rotors' floor and ceiling at the commanded thrust, thrust moves
(up or down) to make room, then yaw gives way, then roll and pitch are scaled down together.
"""

from __future__ import annotations

from collections.abc import Sequence

from bridge.mixing.definition import OutputSpec

__all__ = ["Desaturator"]

# Rounding slack, in thrust units, when desaturation checks that the rotors fit their bounds.
_FIT_TOL = 1e-9


def fit_scale(
    free_lo: list[float], free_hi: list[float], d: list[float]
) -> tuple[float, float, float]:
    """Largest s in [0, 1] for which one common thrust tau fits every rotor, and tau's range.

    In thrust units (each rotor's values divided by its thrust weight) rotor i needs
    ``free_lo[i] <= tau + s*d[i] <= free_hi[i]``, so tau must lie in
    ``[max_i(free_lo[i] - s*d[i]), min_i(free_hi[i] - s*d[i])]``. The width of that range is
    a concave, piecewise-linear function of s. Newton steps from s = 1 on such a function
    never overshoot its root and hit it exactly once on its last linear piece, so a few O(n)
    passes do what a search over all rotor pairs would. Returns ``(s, tau_low, tau_high)``;
    if even s = 0 does not fit (uneven thrust weights with a high idle), s is 0 and
    ``tau_low > tau_high``.
    """
    s = 1.0
    steps_left = 2 * len(d) + 2  # the width has at most 2n linear pieces
    while True:
        lows = [lo - s * x for lo, x in zip(free_lo, d, strict=True)]
        highs = [hi - s * x for hi, x in zip(free_hi, d, strict=True)]
        tau_lo = max(lows)
        tau_hi = min(highs)
        gap = tau_hi - tau_lo
        steps_left -= 1
        if gap >= -_FIT_TOL or s == 0.0 or steps_left == 0:
            return s, tau_lo, tau_hi
        # Slope of the width here: the binding low rotor's d minus the binding high rotor's d.
        slope = d[lows.index(tau_lo)] - d[highs.index(tau_hi)]
        s = s - gap / slope if slope < 0.0 else 0.0
        if s < 0.0:
            s = 0.0


class Desaturator:
    """The rotor outputs of a geometry mixer, mixed and desaturated together.

    Everything that does not depend on the inputs is precomputed, so :meth:`mix` is a few flat
    loops (it runs at 400..1000 Hz).
    """

    def __init__(self, rotor_outputs: Sequence[OutputSpec]) -> None:
        """``rotor_outputs``: the definition's rotor outputs (weights over roll, pitch, yaw,
        thrust; see :class:`~bridge.mixing.definition.OutputSpec`)."""
        # Rotor weights divided by the rotor's thrust weight, so that desaturation can shift one
        # common thrust: output = t * (tau + ar*roll + ap*pitch + ay*yaw).
        self._thrust_w = [o.weights[3][1] for o in rotor_outputs]
        self._rp_w = [
            (o.weights[0][1] / t, o.weights[1][1] / t)
            for o, t in zip(rotor_outputs, self._thrust_w, strict=True)
        ]
        self._yaw_w = [
            o.weights[2][1] / t for o, t in zip(rotor_outputs, self._thrust_w, strict=True)
        ]
        self._hi = [o.maximum / t for o, t in zip(rotor_outputs, self._thrust_w, strict=True)]
        self._lo_disarmed = [
            o.minimum / t for o, t in zip(rotor_outputs, self._thrust_w, strict=True)
        ]
        self._lo_armed = [o.idle / t for o, t in zip(rotor_outputs, self._thrust_w, strict=True)]

    def mix(self, roll: float, pitch: float, yaw: float, thrust: float, armed: bool) -> list[float]:
        """One command per rotor: roll/pitch first, then yaw, then thrust.

        The inputs are clamped to their ranges (-1..1; thrust 0..1) first; NaN is the caller's
        to refuse.

        1. Scale roll and pitch together (keeping the torque direction) by the largest factor
           that still fits some thrust level; thrust may move up or down for it (airmode).
        2. Add as much of the yaw command as still fits some thrust level.
        3. Take the commanded thrust if it fits, else the nearest level that does.
        """
        roll = -1.0 if roll < -1.0 else 1.0 if roll > 1.0 else roll
        pitch = -1.0 if pitch < -1.0 else 1.0 if pitch > 1.0 else pitch
        yaw = -1.0 if yaw < -1.0 else 1.0 if yaw > 1.0 else yaw
        thrust = 0.0 if thrust < 0.0 else 1.0 if thrust > 1.0 else thrust
        # Armed, the floor is idle: fitting the torques above it keeps them instead of letting
        # the idle clamp eat the low side.
        lo = self._lo_armed if armed else self._lo_disarmed
        hi = self._hi

        att = [ar * roll + ap * pitch for ar, ap in self._rp_w]
        g, _, _ = fit_scale(lo, hi, att)
        if g < 1.0:
            att = [g * a for a in att]
        yw = [ay * yaw for ay in self._yaw_w]
        k, tau_lo, tau_hi = fit_scale(
            [x - a for x, a in zip(lo, att, strict=True)],
            [x - a for x, a in zip(hi, att, strict=True)],
            yw,
        )
        # When no thrust fits at all (see fit_scale), tau_hi wins; the per-output clamp
        # afterwards keeps the contract.
        tau = tau_lo if thrust < tau_lo else thrust
        if tau > tau_hi:
            tau = tau_hi
        return [t * (tau + a + k * y) for t, a, y in zip(self._thrust_w, att, yw, strict=True)]
