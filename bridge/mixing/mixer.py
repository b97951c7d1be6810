"""The mixer at run time: the 36-entry input vector in, one command fraction per output out.

Built once from a :class:`~bridge.mixing.definition.MixerDefinition`; :meth:`Mixer.mix` runs on
every input in the control loop. Rotor outputs are desaturated together
(:class:`~bridge.mixing.desaturation.Desaturator`), direct outputs are weighted sums, and every
output is then shaped: reversed, clamped to ``[min, max]``, deadband, and raised to ``idle``
when armed. :class:`AxisChannels` feeds a geometry mixer's axes from channels. Pure: no I/O,
clock or logger.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence

from bridge.mixing.definition import (
    AXIS_NAMES,
    AXIS_RANGES,
    CHANNEL_COUNT,
    INPUT_INDEX,
    INPUT_NAMES,
    MixerDefinition,
)
from bridge.mixing.desaturation import Desaturator

__all__ = ["AxisChannels", "Mixer"]

_ROLL, _PITCH, _YAW, _THRUST = (INPUT_INDEX[name] for name in AXIS_NAMES)


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
                AXIS_RANGES[axis],
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
        self._rotors = Desaturator(rotor_outputs)

        # Direct outputs: (offset, ((index, raw_low, scale, clamp_lo, clamp_hi, weight), ...)).
        self._direct: list[tuple[float, tuple[tuple[int, float, float, float, float, float], ...]]]
        self._direct = []
        for o in outputs[self._n_rotors :]:
            terms = []
            for name, weight in o.weights:
                if name in AXIS_RANGES:
                    low, high = AXIS_RANGES[name]
                    terms.append((INPUT_INDEX[name], 0.0, 1.0, low, high, weight))
                else:
                    raw_lo, raw_hi = o.input_range
                    scale = 1.0 / (raw_hi - raw_lo)
                    terms.append((INPUT_INDEX[name], raw_lo, scale, 0.0, 1.0, weight))
            self._direct.append((o.offset, tuple(terms)))

        # Shaping per output: (reversed, min + max, min, max, deadband, idle).
        self._shape = [
            (o.reversed, o.minimum + o.maximum, o.minimum, o.maximum, o.deadband, o.idle)
            for o in outputs
        ]
        used = sorted({INPUT_INDEX[name] for o in outputs for name, _ in o.weights})
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
        out = (
            self._rotors.mix(inputs[_ROLL], inputs[_PITCH], inputs[_YAW], inputs[_THRUST], armed)
            if self._n_rotors
            else []
        )
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
