"""Mixer definitions: the inputs a mixer reads, and what each of its outputs computes.

A definition (schema: ``mixers/README.md``) describes outputs of two kinds, numbered 1..n in this
order:

* rotor outputs: one per rotor of a multirotor geometry (:class:`Rotor`: position, thrust axis,
  spin direction, thrust and moment coefficients), whose weights over the ``roll``, ``pitch``,
  ``yaw`` and ``thrust`` inputs come from the geometry (:mod:`bridge.mixing.geometry`) and which
  are desaturated together (:mod:`bridge.mixing.desaturation`);
* direct outputs: a weighted sum of inputs plus an offset. Passthrough, hand-written multirotor
  tables and reversible-ESC mappings are all of this kind.

Every output is then shaped the same way (:class:`bridge.mixing.mixer.Mixer`): reversed
(mirrored inside ``[min, max]``), clamped to ``[min, max]``, deadband (a command closer to 0 than
``deadband`` becomes exactly 0), and, when armed, raised to at least ``idle``. Its slew limits
are applied by the output loop (:class:`bridge.output.slew.SlewLimiter`), which has the time step.

A definition says where each rotor sits and what each output computes; which ESC drives
output i is configuration, not mixer. Pure: no I/O, clock or logger
(:mod:`bridge.mixing.loader` reads the files).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

from bridge.errors import ConfigError

__all__ = [
    "AXIS_NAMES",
    "AXIS_RANGES",
    "AXIS_VALID_RANGE",
    "CHANNEL_COUNT",
    "INPUT_INDEX",
    "INPUT_NAMES",
    "INPUT_RANGE_LIMITS",
    "MAX_OUTPUTS",
    "PWM_RANGE_US",
    "MixerDefinition",
    "OutputSpec",
    "Rotor",
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

AXIS_RANGES: dict[str, tuple[float, float]] = {
    "roll": (-1.0, 1.0),
    "pitch": (-1.0, 1.0),
    "yaw": (-1.0, 1.0),
    "thrust": (0.0, 1.0),
}
"""Range each axis input is clamped to before mixing."""
INPUT_INDEX = {name: i for i, name in enumerate(INPUT_NAMES)}
"""Position of each input name in :data:`INPUT_NAMES`."""


def _finite(value: float, what: str) -> None:
    if not math.isfinite(value):
        raise ValueError(f"{what} must be finite, got {value!r}")


@dataclass(frozen=True)
class Rotor:
    """One rotor of a multirotor geometry, in the body frame FRD (x forward, y right, z down).

    ``direction`` is the spin as seen looking against the thrust (from above, for a rotor that
    lifts). The rotor pushes with ``ct * u`` along ``axis`` and twists the body with ``cm * u``
    about it, opposite to its spin, where u is the command fraction. Only ratios between rotors
    matter: :func:`~bridge.mixing.geometry.mix_matrix` normalizes each axis.
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
            if input_name not in INPUT_INDEX:
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
        return any(name not in AXIS_RANGES for name, _ in self.weights)


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
