"""What every simulated ESC offers the runner that puts it on a bus.

A simulated ESC is a state machine with an explicit clock: frames in, frames out, no I/O, so
each behaviour is tested by feeding it frames and times. The runner (bridge/sim/runner.py)
owns the bus, the clock and the shared battery.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import can

from bridge.sim.motor import Motor


@dataclass
class Faults:
    """Faults injected into one simulated ESC; set or cleared at any time."""

    over_temperature: bool = False
    """Report a MOSFET temperature far above any limit (and any status bit of its family)."""
    over_current: bool = False
    """Report a current far above full scale (and any status bit of its family)."""
    corrupt: bool = False
    """Corrupt every telemetry frame it sends (a bad CRC or tail byte, as its family can)."""
    silent: bool = False
    """Send nothing at all (a dead ESC or a broken wire); commands still reach the motor."""
    stuck_motor: bool = False
    """The rotor is blocked (Motor.stuck)."""


class SimEsc(Protocol):
    """One simulated ESC."""

    node_id: int
    """The ESC's ID on the bus."""
    motor: Motor
    faults: Faults

    def handle(self, msg: can.Message, now_s: float) -> list[can.Message]:
        """Take one frame from the bus at ``now_s`` (monotonic seconds); the frames to send in
        answer (service responses, acks), possibly none."""
        ...

    def poll(self, now_s: float, supply_v: float) -> list[can.Message]:
        """Advance the motor to ``now_s`` at ``supply_v`` and apply the command timeouts; the
        telemetry frames due by now."""
        ...
