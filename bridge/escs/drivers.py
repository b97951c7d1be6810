"""What the families' drivers (:class:`~bridge.escs.family.EscDriver`) share: limiting a
fraction to what a command may carry, and sending safe values at the ends of things.

A driver is the one place where a fraction becomes a protocol value, so it is also where every
value is limited to what the protocol allows: whatever the stages before it did, no frame ever
carries an out-of-range command.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import can

from bridge.escs.family import EscDriver


def unit_fraction(fraction: float) -> float:
    """Limit to 0..1 for a unidirectional command; NaN (never expected here) becomes 0."""
    return fraction if 0.0 <= fraction <= 1.0 else (1.0 if fraction > 1.0 else 0.0)


def signed_fraction(fraction: float) -> float:
    """Limit to -1..1; NaN (never expected here) becomes 0."""
    if -1.0 <= fraction <= 1.0:
        return fraction
    return 1.0 if fraction > 1.0 else -1.0 if fraction < -1.0 else 0.0


def flush_safe_values(
    send: Callable[[list[can.Message]], object],
    driver: EscDriver,
    period_ns: int,
    duration_ms: float,
    first_tick: int = 0,
) -> int:
    """Send the safe values every ``period_ns`` for ``duration_ms`` (at least one whole cycle,
    so every ESC of a family that addresses one per tick gets one) through ``send``, on absolute
    deadlines; returns the next tick. For the ends of things: the end of a spin, the survivor of
    a dead control loop."""
    ticks = max(driver.ticks_per_cycle, math.ceil(duration_ms * 1e6 / period_ns))
    tick = first_tick
    next_ns = time.monotonic_ns()
    for _ in range(ticks):
        send(driver.safe_frames(tick))
        tick += 1
        next_ns += period_ns
        delay_ns = next_ns - time.monotonic_ns()
        if delay_ns > 0:
            time.sleep(delay_ns / 1e9)
    return tick
