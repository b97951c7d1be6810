"""Waits between attempts to reopen something that is gone (a CAN interface unplugged): short at
first, so that a quick return is caught quickly, doubling while attempts keep failing, capped,
and jittered so that several handles do not retry in lock-step. Pure: the caller draws the
random number and keeps the time."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["Backoff"]


@dataclass
class Backoff:
    """The wait before each next attempt: ``first_s``, doubling up to ``longest_s``, each scaled
    by a factor in ``1 - jitter .. 1 + jitter``."""

    first_s: float
    longest_s: float
    jitter: float = 0.5
    _next_s: float = field(init=False)

    def __post_init__(self) -> None:
        if not 0 < self.first_s <= self.longest_s or not 0 <= self.jitter < 1:
            raise ValueError(
                f"Backoff({self.first_s!r}, {self.longest_s!r}, jitter={self.jitter!r}): expected "
                "0 < first_s <= longest_s and 0 <= jitter < 1"
            )
        self._next_s = self.first_s

    @property
    def grown(self) -> bool:
        """An attempt failed since the last :meth:`reset`: the next wait is longer than the
        first."""
        return self._next_s != self.first_s

    def wait_s(self, random01: float) -> float:
        """The wait before the next attempt (after a failed one), ``random01`` a number drawn in
        0..1 for the jitter; the wait after it doubles."""
        wait = self._next_s * (1 - self.jitter + 2 * self.jitter * random01)
        self._next_s = min(2 * self._next_s, self.longest_s)
        return wait

    def reset(self) -> None:
        """It works again: the next wait is the first."""
        self._next_s = self.first_s
