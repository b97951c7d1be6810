"""The slew limiter: how fast each output may rise and fall, applied by the output loop each
tick (it needs the time step, which the mixer does not have)."""

from __future__ import annotations

import math
from collections.abc import Sequence

from bridge.mixing.definition import MixerDefinition

__all__ = ["SlewLimiter"]


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
        self.limits = any(rate > 0.0 for rate in (*rise_per_s, *fall_per_s))
        """Some output has a rate: without one, :meth:`apply` returns its targets unchanged,
        and the loop need not call it."""

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
