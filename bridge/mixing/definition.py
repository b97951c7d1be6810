"""Mixers as data: the autopilot's actuator vector in, one command fraction per ESC output out.

A mixer definition is a TOML file (schema: ``mixers/README.md``). It describes outputs of two
kinds, numbered 1..n in this order:

* rotor outputs (``[[rotors]]``): one per rotor of a multirotor geometry (position, thrust axis,
  spin direction, thrust and moment coefficients). :func:`mix_matrix` turns the geometry into
  weights over the ``roll``, ``pitch``, ``yaw`` and ``thrust`` inputs at load time, and
  :class:`Mixer` desaturates them as PX4's airmode does: roll and pitch keep their authority
  before yaw, and yaw before thrust.
* direct outputs (``[[outputs]]``): a weighted sum of inputs plus an offset. Passthrough,
  hand-written multirotor tables and reversible-ESC mappings are all of this kind.

Every output is then shaped the same way: reversed (mirrored inside ``[min, max]``), clamped to
``[min, max]``, deadband (a command closer to 0 than ``deadband`` becomes exactly 0), and, when
armed, raised to at least ``idle``. :class:`SlewLimiter` limits how fast each output may rise or
fall; it is separate because it needs the time step.

A definition says where each rotor sits and what each output computes; which ESC drives
output i is configuration, not mixer.

Everything here is pure: definition files are read at load, nothing else touches I/O, a clock
or a logger.
"""

from __future__ import annotations

import dataclasses
import math
import re
import sys
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Literal

from bridge.errors import ConfigError

__all__ = [
    "AXIS_NAMES",
    "AXIS_VALID_RANGE",
    "CHANNEL_COUNT",
    "INPUT_NAMES",
    "INPUT_RANGE_LIMITS",
    "MAX_OUTPUTS",
    "PWM_RANGE_US",
    "Mixer",
    "MixerDefinition",
    "OutputSpec",
    "Rotor",
    "SlewLimiter",
    "bundled_mixer_names",
    "effectiveness_matrix",
    "load_mixer",
    "mix_matrix",
]

CHANNEL_COUNT = 32
"""Actuator channels ``ch1``..``ch32`` (MAVLink carries up to 32 servo/actuator outputs)."""

AXIS_NAMES: tuple[str, ...] = ("roll", "pitch", "yaw", "thrust")
"""Normalized torque and thrust inputs for geometry mixers, in the mix matrix's column order."""

INPUT_NAMES: tuple[str, ...] = tuple(f"ch{i}" for i in range(1, CHANNEL_COUNT + 1)) + AXIS_NAMES
"""Order of the flat input vector :meth:`Mixer.mix` takes; absent inputs are NaN."""

MAX_OUTPUTS = 32
PWM_RANGE_US = (1000.0, 2000.0)
"""Default channel input range: PWM pulse width in microseconds."""

AXIS_VALID_RANGE = (-1.5, 1.5)
"""Roll, pitch, yaw and thrust inputs outside this are garbage: the input is refused."""

INPUT_RANGE_LIMITS = (-1.0, 65535.0)
"""Bounds for a channel input range: MAVLink's normalized floats (-1..1) to uint16 PWM (µs)."""

# Range each axis input is clamped to before mixing.
_AXIS_RANGES: dict[str, tuple[float, float]] = {
    "roll": (-1.0, 1.0),
    "pitch": (-1.0, 1.0),
    "yaw": (-1.0, 1.0),
    "thrust": (0.0, 1.0),
}
_INPUT_INDEX = {name: i for i, name in enumerate(INPUT_NAMES)}
_ROLL, _PITCH, _YAW, _THRUST = (_INPUT_INDEX[name] for name in AXIS_NAMES)
_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*\Z")

# Below this a pivot of the 4x4 normal matrix (relative to its largest diagonal entry) or a mix
# weight counts as zero: the geometry then cannot produce that axis independently.
_SINGULAR_TOL = 1e-9
# Rounding slack, in thrust units, when desaturation checks that the rotors fit their bounds.
_FIT_TOL = 1e-9


def _finite(value: float, what: str) -> None:
    if not math.isfinite(value):
        raise ValueError(f"{what} must be finite, got {value!r}")


@dataclass(frozen=True)
class Rotor:
    """One rotor of a multirotor geometry, in the body frame FRD (x forward, y right, z down).

    ``direction`` is the spin as seen looking against the thrust (from above, for a rotor that
    lifts). The rotor pushes with ``ct * u`` along ``axis`` and twists the body with ``cm * u``
    about it, opposite to its spin, where u is the command fraction. Only ratios between rotors
    matter: :func:`mix_matrix` normalizes each axis.
    """

    name: str
    position_m: tuple[float, float, float]
    direction: Literal["CW", "CCW"]
    axis: tuple[float, float, float] = (0.0, 0.0, -1.0)
    """Direction of the thrust force; any length but zero (it is normalized)."""
    ct: float = 1.0
    """Thrust at full command, N (or any unit shared by all rotors); > 0."""
    cm: float = 0.05
    """Reaction moment at full command, N·m (same scale as ``ct`` times metres); >= 0."""

    def __post_init__(self) -> None:
        if self.direction not in ("CW", "CCW"):
            raise ValueError(f"direction must be 'CW' or 'CCW', got {self.direction!r}")
        for i, x in enumerate(self.position_m):
            _finite(x, f"position[{i}]")
        for i, x in enumerate(self.axis):
            _finite(x, f"axis[{i}]")
        if not any(self.axis):
            raise ValueError("axis must not be the zero vector")
        _finite(self.ct, "Ct")
        _finite(self.cm, "Cm")
        if self.ct <= 0.0:
            raise ValueError(f"Ct {self.ct:g} must be > 0")
        if self.cm < 0.0:
            raise ValueError(f"Cm {self.cm:g} must be >= 0 (the spin sign is in 'direction')")


@dataclass(frozen=True)
class OutputSpec:
    """What one output computes, and how it is shaped. All values are command fractions.

    ``weights`` pairs input names with weights; the output is ``offset + sum(w * x)``, where a
    channel ``x`` is its raw value mapped from ``input_range`` onto 0..1 and an axis ``x`` is
    used as is. Both are clamped to their range first (0..1; -1..1 for roll, pitch, yaw).
    For a rotor output (``rotor`` set) the weights are its row of the mix matrix and the mixer
    desaturates all rotor outputs together.
    """

    name: str
    weights: tuple[tuple[str, float], ...]
    offset: float = 0.0
    input_range: tuple[float, float] = PWM_RANGE_US
    """Raw channel values (µs for PWM, or normalized) that map to 0 and 1."""
    reversed: bool = False
    """Mirror the value inside ``[minimum, maximum]`` (v -> minimum + maximum - v)."""
    deadband: float = 0.0
    """Values with ``|v| < deadband`` after clamping become exactly 0 (stop); 0 <= deadband < 1."""
    minimum: float = 0.0
    maximum: float = 1.0
    idle: float = 0.0
    """Floor applied only while armed; minimum <= idle <= maximum (file default: ``min``)."""
    slew_up_per_s: float = 0.0
    """Largest rise per second, fraction/s; 0 = unlimited."""
    slew_down_per_s: float = 0.0
    """Largest fall per second, fraction/s; 0 = unlimited."""
    rotor: Rotor | None = None

    def __post_init__(self) -> None:
        if not self.weights:
            raise ValueError("source names no input")
        seen: set[str] = set()
        for input_name, weight in self.weights:
            if input_name not in _INPUT_INDEX:
                raise ValueError(
                    f"source: unknown input {input_name!r} "
                    f"(inputs are ch1..ch{CHANNEL_COUNT}, {', '.join(AXIS_NAMES)})"
                )
            if input_name in seen:
                raise ValueError(f"source: input {input_name!r} given twice")
            seen.add(input_name)
            _finite(weight, f"source weight of {input_name!r}")
        _finite(self.offset, "offset")
        if not -1.0 <= self.offset <= 1.0:
            raise ValueError(f"offset {self.offset:g} outside -1..1")
        lo, hi = self.input_range
        _finite(lo, "input_range[0]")
        _finite(hi, "input_range[1]")
        if not lo < hi:
            raise ValueError(f"input_range low {lo:g} must be < high {hi:g}")
        if lo < INPUT_RANGE_LIMITS[0] or hi > INPUT_RANGE_LIMITS[1]:
            raise ValueError(
                f"input_range [{lo:g}, {hi:g}] outside "
                f"{INPUT_RANGE_LIMITS[0]:g}..{INPUT_RANGE_LIMITS[1]:g}"
            )
        for what, x in (("min", self.minimum), ("max", self.maximum), ("idle", self.idle)):
            _finite(x, what)
            if not -1.0 <= x <= 1.0:
                raise ValueError(f"{what} {x:g} outside -1..1")
        if self.minimum > self.maximum:
            raise ValueError(f"min {self.minimum:g} > max {self.maximum:g}")
        # 0 is every ESC's stop command: the deadband and the daemon's failsafe both send it.
        if not self.minimum <= 0.0 < self.maximum:
            raise ValueError(
                f"[min {self.minimum:g}, max {self.maximum:g}] must contain 0 (stop) "
                "and have max > 0"
            )
        if not self.minimum <= self.idle <= self.maximum:
            raise ValueError(
                f"idle {self.idle:g} outside [min {self.minimum:g}, max {self.maximum:g}]"
            )
        _finite(self.deadband, "deadband")
        if not 0.0 <= self.deadband < 1.0:
            raise ValueError(f"deadband {self.deadband:g} outside 0 <= deadband < 1")
        for what, x in (("slew_up", self.slew_up_per_s), ("slew_down", self.slew_down_per_s)):
            _finite(x, what)
            if x < 0.0:
                raise ValueError(f"{what} {x:g} must be >= 0 (0 = unlimited)")
        if self.rotor is not None:
            self._check_rotor_output()

    def _check_rotor_output(self) -> None:
        # Desaturation assumes thrust grows with the command from a stopped rotor at 0.
        names = tuple(name for name, _ in self.weights)
        if names != AXIS_NAMES:
            raise ValueError(f"a rotor output's weights must be over {AXIS_NAMES}, got {names}")
        if self.weights[3][1] <= 0.0:
            raise ValueError(f"a rotor output needs a thrust weight > 0, got {self.weights[3][1]}")
        if self.minimum != 0.0 or self.reversed or self.deadband or self.offset:
            raise ValueError("a rotor output has min 0, no reversing, deadband or offset")

    @property
    def uses_channels(self) -> bool:
        """True when any input is an actuator channel (so ``input_range`` applies)."""
        return any(name not in _AXIS_RANGES for name, _ in self.weights)


@dataclass(frozen=True)
class MixerDefinition:
    """A validated mixer: rotor outputs first, then direct outputs.

    ``path`` is the file it came from (empty when built in code), for error messages.
    """

    name: str
    description: str
    outputs: tuple[OutputSpec, ...]
    path: str = ""

    def __post_init__(self) -> None:
        if not 1 <= len(self.outputs) <= MAX_OUTPUTS:
            raise ValueError(f"{len(self.outputs)} outputs; a mixer has 1..{MAX_OUTPUTS}")
        names = [o.name for o in self.outputs]
        for i, name in enumerate(names):
            if name in names[:i]:
                raise ValueError(
                    f"output {i + 1} ({name!r}): name already used by output "
                    f"{names.index(name) + 1}"
                )
        n_rotors = len(self.rotors)
        if any(o.rotor is None for o in self.outputs[:n_rotors]):
            raise ValueError("rotor outputs must come before direct outputs")

    @property
    def rotors(self) -> tuple[Rotor, ...]:
        """The geometry: the rotor of output 1, 2, ... (empty for a mixer without one)."""
        return tuple(o.rotor for o in self.outputs if o.rotor is not None)

    def with_input_range(self, low: float, high: float) -> MixerDefinition:
        """Return a copy whose channel inputs all use the raw range ``low..high``.

        The right range depends on the MAVLink source: µs for PWM (SERVO_OUTPUT_RAW), 0..1 or
        -1..1 for normalized ones (HIL_ACTUATOR_CONTROLS). Outputs that read no channel are
        returned unchanged.

        Raises:
            ConfigError: the range is not finite, empty or outside :data:`INPUT_RANGE_LIMITS`.
        """
        try:
            outputs = tuple(
                dataclasses.replace(o, input_range=(float(low), float(high)))
                if o.uses_channels
                else o
                for o in self.outputs
            )
        except ValueError as exc:
            raise ConfigError(f"{self.path or self.name}: input range override: {exc}") from exc
        return dataclasses.replace(self, outputs=outputs)


# --------------------------------------------------------------------------------------------
# Geometry -> matrices (pure functions of the parsed rotors)


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


# --------------------------------------------------------------------------------------------
# Runtime


def _fit_scale(
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


class AxisChannels:
    """Fills the roll/pitch/yaw/thrust inputs from configured channels, for geometry mixers
    driven by channels (e.g. a companion controller's outputs) rather than by
    ACTUATOR_CONTROL_TARGET. A channel's input range maps onto the axis's range: the low end to
    -1 (thrust 0), the high end to +1; values outside it are limited, NaN stays NaN."""

    def __init__(self, channels: Mapping[str, int], input_range: tuple[float, float]) -> None:
        low, high = input_range
        self._map = [
            (
                CHANNEL_COUNT + AXIS_NAMES.index(axis),
                channel - 1,
                low,
                high - low,
                _AXIS_RANGES[axis],
            )
            for axis, channel in channels.items()
        ]

    def fill(self, inputs: list[float]) -> None:
        """Write the axis inputs of ``inputs`` (a full input vector) from its channels."""
        for slot, channel, low, span, (axis_low, axis_high) in self._map:
            fraction = (inputs[channel] - low) / span
            value = axis_low + fraction * (axis_high - axis_low)
            inputs[slot] = min(max(value, axis_low), axis_high) if value == value else value


class Mixer:
    """Maps the 36-entry input vector (order :data:`INPUT_NAMES`) to one fraction per output.

    Everything that does not depend on the inputs is precomputed here, so :meth:`mix` is a few
    flat loops (it runs at 400..1000 Hz).
    """

    def __init__(
        self,
        definition: MixerDefinition,
        valid_range: tuple[float, float] | None = None,
        axis_valid_range: tuple[float, float] | None = None,
    ) -> None:
        """``valid_range`` and ``axis_valid_range``: channel and axis inputs outside them make
        :meth:`mix` refuse the input (None: any finite value is taken, and clamped). The bridge
        passes its configured range and :data:`AXIS_VALID_RANGE`."""
        self.definition = definition
        outputs = definition.outputs
        rotor_outputs = [o for o in outputs if o.rotor is not None]
        self._n_rotors = len(rotor_outputs)
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

        # Direct outputs: (offset, ((index, raw_low, scale, clamp_lo, clamp_hi, weight), ...)).
        self._direct: list[tuple[float, tuple[tuple[int, float, float, float, float, float], ...]]]
        self._direct = []
        for o in outputs[self._n_rotors :]:
            terms = []
            for name, weight in o.weights:
                if name in _AXIS_RANGES:
                    low, high = _AXIS_RANGES[name]
                    terms.append((_INPUT_INDEX[name], 0.0, 1.0, low, high, weight))
                else:
                    raw_lo, raw_hi = o.input_range
                    scale = 1.0 / (raw_hi - raw_lo)
                    terms.append((_INPUT_INDEX[name], raw_lo, scale, 0.0, 1.0, weight))
            self._direct.append((o.offset, tuple(terms)))

        # Shaping per output: (reversed, min + max, min, max, deadband, idle).
        self._shape = [
            (o.reversed, o.minimum + o.maximum, o.minimum, o.maximum, o.deadband, o.idle)
            for o in outputs
        ]
        used = sorted({_INPUT_INDEX[name] for o in outputs for name, _ in o.weights})
        finite = (-sys.float_info.max, sys.float_info.max)
        channels, axes = valid_range or finite, axis_valid_range or finite
        # (index, lowest, highest) of every input some output uses; NaN fails both compares.
        self._valid = tuple((i, *(channels if i < CHANNEL_COUNT else axes)) for i in used)

    @property
    def n_outputs(self) -> int:
        """Number of outputs :meth:`mix` returns."""
        return len(self._shape)

    def mix(self, inputs: Sequence[float], armed: bool) -> list[float] | None:
        """Return one command fraction per output, each within its ``[min, max]``.

        ``inputs`` holds 36 raw values in :data:`INPUT_NAMES` order (µs or normalized for
        channels, as the definition's ``input_range`` says; normalized for the axes); values
        out of range are clamped to it. Armed, every output is at least its ``idle``; disarmed,
        the result is still computed (the daemon sends stop instead).

        Returns None when an input that some output uses is NaN, infinite or outside the valid
        range (the ``valid_range`` given, :data:`AXIS_VALID_RANGE` for axes): the caller must
        fail safe rather than guess. An autopilot's PWM 65535 or 3000, or a float of 1e38, is
        garbage, not full throttle.

        Raises:
            ValueError: ``inputs`` does not have 36 entries.
        """
        if len(inputs) != len(INPUT_NAMES):
            raise ValueError(f"expected {len(INPUT_NAMES)} inputs, got {len(inputs)}")
        for i, lowest, highest in self._valid:
            if not lowest <= inputs[i] <= highest:
                return None
        out = self._mix_rotors(inputs, armed) if self._n_rotors else []
        for offset, terms in self._direct:
            v = offset
            for index, raw_lo, scale, clamp_lo, clamp_hi, weight in terms:
                x = (inputs[index] - raw_lo) * scale
                v += weight * (clamp_lo if x < clamp_lo else clamp_hi if x > clamp_hi else x)
            out.append(v)
        for k, (rev, mirror, lo, hi, deadband, idle) in enumerate(self._shape):
            v = out[k]
            if rev:
                v = mirror - v
            v = lo if v < lo else hi if v > hi else v
            if -deadband < v < deadband:
                v = 0.0
            if armed and v < idle:
                v = idle
            out[k] = v
        return out

    def _mix_rotors(self, inputs: Sequence[float], armed: bool) -> list[float]:
        """Desaturate the rotor outputs: roll/pitch first, then yaw, then thrust.

        1. Scale roll and pitch together (keeping the torque direction) by the largest factor
           that still fits some thrust level; thrust may move up or down for it (airmode).
        2. Add as much of the yaw command as still fits some thrust level.
        3. Take the commanded thrust if it fits, else the nearest level that does.
        """
        roll = inputs[_ROLL]
        roll = -1.0 if roll < -1.0 else 1.0 if roll > 1.0 else roll
        pitch = inputs[_PITCH]
        pitch = -1.0 if pitch < -1.0 else 1.0 if pitch > 1.0 else pitch
        yaw = inputs[_YAW]
        yaw = -1.0 if yaw < -1.0 else 1.0 if yaw > 1.0 else yaw
        thrust = inputs[_THRUST]
        thrust = 0.0 if thrust < 0.0 else 1.0 if thrust > 1.0 else thrust
        # Armed, the floor is idle: fitting the torques above it keeps them instead of letting
        # the idle clamp eat the low side.
        lo = self._lo_armed if armed else self._lo_disarmed
        hi = self._hi

        att = [ar * roll + ap * pitch for ar, ap in self._rp_w]
        g, _, _ = _fit_scale(lo, hi, att)
        if g < 1.0:
            att = [g * a for a in att]
        yw = [ay * yaw for ay in self._yaw_w]
        k, tau_lo, tau_hi = _fit_scale(
            [x - a for x, a in zip(lo, att, strict=True)],
            [x - a for x, a in zip(hi, att, strict=True)],
            yw,
        )
        # When no thrust fits at all (see _fit_scale), tau_hi wins; the per-output clamp
        # afterwards keeps the contract.
        tau = tau_lo if thrust < tau_lo else thrust
        if tau > tau_hi:
            tau = tau_hi
        return [t * (tau + a + k * y) for t, a, y in zip(self._thrust_w, att, yw, strict=True)]


class SlewLimiter:
    """Limits how fast each output may rise and fall, in fraction per second.

    The state starts at 0 (stop) for every output; :meth:`reset` sets it, e.g. on arming.
    A rate of 0 means unlimited.
    """

    def __init__(self, rise_per_s: Sequence[float], fall_per_s: Sequence[float]) -> None:
        """Raises ValueError on unequal lengths or a negative or non-finite rate."""
        if len(rise_per_s) != len(fall_per_s):
            raise ValueError(f"{len(rise_per_s)} rise rates but {len(fall_per_s)} fall rates")
        for rate in (*rise_per_s, *fall_per_s):
            if not (math.isfinite(rate) and rate >= 0.0):
                raise ValueError(f"slew rate {rate!r} must be finite and >= 0")
        self._rates = list(zip(rise_per_s, fall_per_s, strict=True))
        self._values = [0.0] * len(self._rates)

    @classmethod
    def for_definition(cls, definition: MixerDefinition) -> SlewLimiter:
        """Build a limiter from the definition's ``slew_up`` and ``slew_down`` fields."""
        return cls(
            [o.slew_up_per_s for o in definition.outputs],
            [o.slew_down_per_s for o in definition.outputs],
        )

    @property
    def values(self) -> tuple[float, ...]:
        """The last output values (what the next :meth:`apply` moves from)."""
        return tuple(self._values)

    def reset(self, values: Sequence[float]) -> None:
        """Set the state to ``values`` without limiting.

        Raises:
            ValueError: wrong length or a non-finite value.
        """
        self._check(values, "values")
        self._values = list(values)

    def apply(self, targets: Sequence[float], dt_s: float) -> list[float]:
        """Move each output toward its target by at most rate * ``dt_s`` and return them.

        Raises:
            ValueError: wrong length, a non-finite target, or ``dt_s`` negative or not finite.
        """
        self._check(targets, "targets")
        if not (math.isfinite(dt_s) and dt_s >= 0.0):
            raise ValueError(f"dt_s {dt_s!r} must be finite and >= 0")
        out = []
        for target, prev, (up, down) in zip(targets, self._values, self._rates, strict=True):
            if up and target > prev + up * dt_s:
                v = prev + up * dt_s
            elif down and target < prev - down * dt_s:
                v = prev - down * dt_s
            else:
                v = target
            out.append(v)
        self._values = out
        return list(out)

    def _check(self, values: Sequence[float], what: str) -> None:
        if len(values) != len(self._rates):
            raise ValueError(f"expected {len(self._rates)} {what}, got {len(values)}")
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"{what} must be finite, got {list(values)}")


# --------------------------------------------------------------------------------------------
# Loading


def bundled_mixer_names() -> list[str]:
    """Names of the mixers shipped in ``bridge.mixers`` (file names without ``.toml``), sorted."""
    return sorted(
        entry.name.removesuffix(".toml")
        for entry in resources.files("bridge.mixers").iterdir()
        if entry.name.endswith(".toml")
    )


def load_mixer(
    name_or_path: str, *, input_range: tuple[float, float] | None = None
) -> MixerDefinition:
    """Load a bundled mixer by name (``"quad-x"``) or a definition file by path.

    A string ending in ``.toml`` or containing a path separator is a path. ``input_range``
    overrides every channel input range (see :meth:`MixerDefinition.with_input_range`).

    Raises:
        ConfigError: unknown name, unreadable file, invalid TOML, or an invalid definition;
            the message names the file and the entry.
    """
    if name_or_path.endswith(".toml") or "/" in name_or_path or "\\" in name_or_path:
        path = Path(name_or_path)
        source = str(path)
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise ConfigError(f"{source}: cannot read mixer: {exc.strerror or exc}") from exc
        stem = path.stem
    else:
        names = bundled_mixer_names()
        if name_or_path not in names:
            raise ConfigError(
                f"unknown mixer {name_or_path!r}; bundled: {', '.join(names)} (or give a path)"
            )
        resource = resources.files("bridge.mixers").joinpath(f"{name_or_path}.toml")
        source = str(resource)
        data = resource.read_bytes()
        stem = name_or_path
    try:
        text = data.decode("utf-8")
        document = tomllib.loads(text)
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{source}: not UTF-8 text: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: invalid TOML: {exc}{_quote_line(text, str(exc))}") from exc
    definition = _parse_definition(document, source, stem)
    if input_range is not None:
        definition = definition.with_input_range(*input_range)
    return definition


def _quote_line(text: str, message: str) -> str:
    """Quote the line a TOML error points at, or return "" when the message names none.

    tomllib reports a duplicate key by line number only; the line's text names the entry.
    """
    match = re.search(r"at line (\d+)", message)
    lines = text.splitlines()
    if match is None or not 1 <= int(match.group(1)) <= len(lines):
        return ""
    return f": {lines[int(match.group(1)) - 1].strip()!r}"


# Keys each entry accepts; a default table accepts the same minus the entry's identity keys.
_OUTPUT_SHAPE_KEYS = frozenset({"idle", "max", "slew_up", "slew_down"})
_OUTPUT_KEYS = _OUTPUT_SHAPE_KEYS | {
    "name",
    "source",
    "offset",
    "input_range",
    "reversed",
    "deadband",
    "min",
}
_OUTPUT_DEFAULT_KEYS = _OUTPUT_KEYS - {"name", "source"}
_ROTOR_KEYS = _OUTPUT_SHAPE_KEYS | {"name", "position", "axis", "direction", "Ct", "Cm"}
_ROTOR_DEFAULT_KEYS = _ROTOR_KEYS - {"name", "position"}
_TOP_KEYS = frozenset({"info", "output_default", "outputs", "rotor_default", "rotors"})
_INFO_KEYS = frozenset({"key", "description"})


def _table(value: object, what: str) -> dict[str, object]:
    if not isinstance(value, dict):
        raise ValueError(f"{what} must be a table, got {value!r}")
    return value


def _array_of_tables(value: object, what: str) -> list[object]:
    if not isinstance(value, list):
        raise ValueError(f"{what} must be an array of tables ([[{what}]]), got {value!r}")
    return value


def _check_keys(table: Mapping[str, object], allowed: frozenset[str], what: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ValueError(
            f"unknown key{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))} "
            f"in {what} (allowed: {', '.join(sorted(allowed))})"
        )


def _number(value: object, what: str) -> float:
    # bool is an int subclass in Python; a TOML 'true' where a number belongs is a mistake.
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{what} must be a number, got {value!r}")
    return float(value)


def _string(value: object, what: str) -> str:
    if not isinstance(value, str) or not value:
        raise ValueError(f"{what} must be a non-empty string, got {value!r}")
    return value


def _boolean(value: object, what: str) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"{what} must be true or false, got {value!r}")
    return value


def _vector(value: object, length: int, what: str) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != length:
        raise ValueError(f"{what} must be an array of {length} numbers, got {value!r}")
    return tuple(_number(x, f"{what}[{i}]") for i, x in enumerate(value))


def _weights(value: object) -> tuple[tuple[str, float], ...]:
    if isinstance(value, str):
        return ((value, 1.0),)
    if isinstance(value, dict):
        return tuple((name, _number(w, f"source weight of {name!r}")) for name, w in value.items())
    raise ValueError(
        'source must be an input name ("ch3") or a table of weights '
        f"({{ roll = -0.5, thrust = 1.0 }}), got {value!r}"
    )


def _shape_fields(entry: Mapping[str, object]) -> tuple[float, float, float]:
    """``max``, ``slew_up``, ``slew_down`` with defaults (rotors and outputs share these)."""
    return (
        _number(entry.get("max", 1.0), "max"),
        _number(entry.get("slew_up", 0.0), "slew_up"),
        _number(entry.get("slew_down", 0.0), "slew_down"),
    )


def _parse_output(entry: Mapping[str, object]) -> OutputSpec:
    if "source" not in entry:
        raise ValueError("missing key 'source'")
    minimum = _number(entry.get("min", 0.0), "min")
    low, high = _vector(entry.get("input_range", list(PWM_RANGE_US)), 2, "input_range")
    maximum, slew_up, slew_down = _shape_fields(entry)
    return OutputSpec(
        name=_string(entry["name"], "name"),
        weights=_weights(entry["source"]),
        offset=_number(entry.get("offset", 0.0), "offset"),
        input_range=(low, high),
        reversed=_boolean(entry.get("reversed", False), "reversed"),
        deadband=_number(entry.get("deadband", 0.0), "deadband"),
        minimum=minimum,
        # No floor unless asked for: a reversible output must be free to go below 0.
        idle=_number(entry.get("idle", minimum), "idle"),
        maximum=maximum,
        slew_up_per_s=slew_up,
        slew_down_per_s=slew_down,
    )


def _parse_rotor(entry: Mapping[str, object]) -> Rotor:
    if "direction" not in entry:
        raise ValueError("missing key 'direction' ('CW' or 'CCW', in the rotor or rotor_default)")
    direction = entry["direction"]
    if direction not in ("CW", "CCW"):
        raise ValueError(f"direction must be 'CW' or 'CCW', got {direction!r}")
    px, py, pz = _vector(entry["position"], 3, "position")
    ax, ay, az = _vector(entry.get("axis", [0.0, 0.0, -1.0]), 3, "axis")
    return Rotor(
        name=_string(entry["name"], "name"),
        position_m=(px, py, pz),
        direction="CW" if direction == "CW" else "CCW",
        axis=(ax, ay, az),
        ct=_number(entry.get("Ct", 1.0), "Ct"),
        cm=_number(entry.get("Cm", 0.05), "Cm"),
    )


def _entry_label(kind: str, number: int, entry: Mapping[str, object]) -> str:
    name = entry.get("name")
    return f"{kind} {number} ({name!r})" if isinstance(name, str) else f"{kind} {number}"


def _parse_definition(document: Mapping[str, object], source: str, stem: str) -> MixerDefinition:
    """Validate a parsed TOML document into a MixerDefinition; ConfigError names file and entry."""

    def fail(where: str, exc: Exception) -> ConfigError:
        return ConfigError(f"{source}: {where}: {exc}")

    try:
        _check_keys(document, _TOP_KEYS, "the top level")
    except ValueError as exc:
        raise fail("top level", exc) from exc
    try:
        info = _table(document.get("info"), "[info]")
        _check_keys(info, _INFO_KEYS, "[info]")
        description = _string(info.get("description"), "description")
        name = _string(info.get("key", stem), "key")
        if not _NAME_RE.match(name):
            raise ValueError(f"key {name!r}: use letters, digits, '.', '_', '-'")
    except ValueError as exc:
        raise fail("info", exc) from exc

    defaults: dict[str, dict[str, object]] = {}
    lists: dict[str, list[object]] = {}
    for table_key, list_key, allowed in (
        ("output_default", "outputs", _OUTPUT_DEFAULT_KEYS),
        ("rotor_default", "rotors", _ROTOR_DEFAULT_KEYS),
    ):
        try:
            defaults[list_key] = _table(document.get(table_key, {}), f"[{table_key}]")
            _check_keys(defaults[list_key], allowed, f"[{table_key}]")
        except ValueError as exc:
            raise fail(table_key, exc) from exc
        try:
            lists[list_key] = _array_of_tables(document.get(list_key, []), list_key)
        except ValueError as exc:
            raise fail(list_key, exc) from exc

    rotors: list[Rotor] = []
    # Per rotor: idle, max, slew_up, slew_down.
    rotor_fields: list[tuple[float, float, float, float]] = []
    for i, raw in enumerate(lists["rotors"], start=1):
        label = f"rotor {i}"
        try:
            entry = _table(raw, label)
            label = _entry_label("rotor", i, entry)
            _check_keys(entry, _ROTOR_KEYS, "a rotor (reversed, deadband and min are fixed)")
            for required in ("name", "position"):
                if required not in entry:
                    raise ValueError(f"missing key {required!r}")
            merged = {**defaults["rotors"], **entry}
            rotors.append(_parse_rotor(merged))
            rotor_fields.append((_number(merged.get("idle", 0.0), "idle"), *_shape_fields(merged)))
        except ValueError as exc:
            raise fail(label, exc) from exc

    outputs: list[OutputSpec] = []
    if rotors:
        try:
            matrix = mix_matrix(rotors)
        except ValueError as exc:
            raise fail("rotors", exc) from exc
        rows = zip(rotors, matrix, rotor_fields, strict=True)
        for i, (rotor, row, (idle, maximum, slew_up, slew_down)) in enumerate(rows, start=1):
            try:
                outputs.append(
                    OutputSpec(
                        name=rotor.name,
                        weights=tuple(zip(AXIS_NAMES, row, strict=True)),
                        idle=idle,
                        maximum=maximum,
                        slew_up_per_s=slew_up,
                        slew_down_per_s=slew_down,
                        rotor=rotor,
                    )
                )
            except ValueError as exc:
                raise fail(f"rotor {i} ({rotor.name!r})", exc) from exc

    for j, raw in enumerate(lists["outputs"], start=1):
        number = len(rotors) + j
        label = f"output {number}"
        try:
            entry = _table(raw, label)
            label = _entry_label("output", number, entry)
            _check_keys(entry, _OUTPUT_KEYS, "an output")
            if "name" not in entry:
                raise ValueError("missing key 'name'")
            outputs.append(_parse_output({**defaults["outputs"], **entry}))
        except ValueError as exc:
            raise fail(label, exc) from exc

    if not outputs:
        raise ConfigError(f"{source}: defines no outputs (add [[rotors]] or [[outputs]])")
    try:
        return MixerDefinition(
            name=name, description=description, outputs=tuple(outputs), path=source
        )
    except ValueError as exc:
        raise ConfigError(f"{source}: {exc}") from exc
