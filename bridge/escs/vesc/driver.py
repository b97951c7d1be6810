"""The VESC command driver: one command per VESC per cycle, one VESC per tick
(docs/protocols.md §6.4).

VESC addresses one controller per frame, so the output loop spreads the frames evenly across
the cycle, one VESC per tick: the bus never sees a burst of N frames followed by silence. Every
value is limited to the configured full scale here, whatever the stages before did.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final

import can

from bridge.escs.drivers import signed_fraction
from bridge.escs.vesc.codec import encode_command
from bridge.escs.vesc.keys import VescKeys
from bridge.escs.vesc.records import Packet

MODE_PACKETS: Final[dict[str, Packet]] = {
    "duty": Packet.SET_DUTY,
    "current_rel": Packet.SET_CURRENT_REL,
    "current": Packet.SET_CURRENT,
    "rpm": Packet.SET_RPM,
}
"""The packet the bridge sends for each ``vesc_mode``."""


def full_scale(keys: VescKeys) -> float:
    """The value of a full-throttle command in ``keys.vesc_mode``'s unit."""
    return {
        "duty": keys.vesc_max_duty,
        "current_rel": 1.0,
        "current": keys.vesc_max_current_a,
        "rpm": float(keys.vesc_max_erpm),
    }[keys.vesc_mode]


class VescDriver:
    """One VESC command per VESC per cycle, one VESC per tick, in the configured mode."""

    def __init__(self, ids: Sequence[int], keys: VescKeys) -> None:
        self._ids = tuple(ids)
        self.ticks_per_cycle = len(ids)
        self.kind = keys.vesc_mode
        self._mode = keys.vesc_mode
        self._packet = MODE_PACKETS[keys.vesc_mode]
        self._rpm = keys.vesc_mode == "rpm"
        self._full_scale = full_scale(keys)
        self._brake_a = keys.vesc_brake_current_a

    def tick_frames(self, tick: int, fractions: Sequence[float]) -> list[can.Message]:
        index = tick % self.ticks_per_cycle
        value = signed_fraction(fractions[index]) * self._full_scale
        if self._rpm:
            value = round(value)
        return [encode_command(self._ids[index], self._packet, value)]

    def safe_frames(self, tick: int) -> list[can.Message]:
        controller_id = self._ids[tick % self.ticks_per_cycle]
        if self._brake_a > 0:
            return [encode_command(controller_id, Packet.SET_CURRENT_BRAKE, self._brake_a)]
        # Zero current releases the motor whatever the mode: it coasts to a stop. (Duty 0 would
        # brake it hard, and rpm 0 hold it.)
        return [encode_command(controller_id, Packet.SET_CURRENT, 0.0)]

    def prepare(self, fractions: Sequence[float]) -> None:
        # Each tick's one frame is for the next controller in turn, with the newest input:
        # nothing to make ahead that the tick would not make again.
        pass

    def describe_command(self, fraction: float) -> str:
        value = fraction * self._full_scale
        if self._mode == "current":
            return f"VESC current {value:.2f} A"
        if self._mode == "current_rel":
            return f"VESC current {100 * value:.1f} % of its limit"
        if self._mode == "duty":
            return f"VESC duty {value:.3f}"
        return f"VESC {round(value)} erpm"

    def describe_esc(self, index: int) -> str:
        return f"VESC {self._ids[index]}, {self._mode} mode"
