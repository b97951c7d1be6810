"""The FT command driver: one command per ESC per cycle, one ESC per tick.

FT needs a frame per ESC, and the output loop spreads them evenly across the cycle, one ESC
per tick, so the bus never sees a burst of N frames followed by silence. Every value is
limited to the configured full scale here, whatever the stages before did.
"""

from __future__ import annotations

from collections.abc import Sequence

import can

from bridge.escs.drivers import signed_fraction
from bridge.escs.ft import codec, records
from bridge.escs.ft.keys import FtKeys

# The FT command the daemon sends for each throttle mode, with and without CRC.
FT_MODE_COMMANDS: dict[tuple[str, bool], records.Command] = {
    ("current", True): records.Command.SET_CURRENT_GEAR_CRC16,
    ("current", False): records.Command.SET_CURRENT_GEAR,
    ("current_percent", True): records.Command.SET_CURRENT_PERCENT_GEAR_CRC16,
    ("current_percent", False): records.Command.SET_CURRENT_PERCENT_GEAR,
    ("duty", True): records.Command.SET_DUTY_GEAR_CRC16,
    ("duty", False): records.Command.SET_DUTY_GEAR,
    ("erpm", True): records.Command.SET_ERPM_GEAR_CRC16,
    ("erpm", False): records.Command.SET_ERPM_GEAR,
}
FT_BRAKE_COMMANDS = {
    True: records.Command.SET_CURRENT_BRAKE_CRC16,
    False: records.Command.SET_CURRENT_BRAKE,
}
FT_GEARS = {
    "none": records.Gear.NONE,
    "low": records.Gear.LOW,
    "middle": records.Gear.MIDDLE,
    "high": records.Gear.HIGH,
    "reverse": records.Gear.REVERSE,
}


def ft_command_dlc(crc: bool) -> int:
    """Data bytes of every throttle command above: i32 value and gear, plus the CRC-16."""
    return 5 + (2 if crc else 0)


class FtDriver:
    """One FT command per ESC per cycle, one ESC per tick, in the configured mode."""

    def __init__(self, ids: Sequence[int], keys: FtKeys) -> None:
        self._ids = tuple(ids)
        self.ticks_per_cycle = len(ids)
        self._command = FT_MODE_COMMANDS[(keys.ft_mode, keys.ft_crc)]
        self._gear = FT_GEARS[keys.ft_gear]
        self._erpm = keys.ft_mode == "erpm"
        self._full_scale = {
            "current": keys.ft_max_current_a,
            "current_percent": 1.0,
            "duty": keys.ft_max_duty,
            "erpm": float(keys.ft_max_erpm),
        }[keys.ft_mode]
        self._brake_a = keys.ft_brake_current_a
        self._brake_command = FT_BRAKE_COMMANDS[keys.ft_crc]
        self._stop_command = FT_MODE_COMMANDS[("current", keys.ft_crc)]
        self.kind = keys.ft_mode
        self._keys = keys

    def tick_frames(self, tick: int, fractions: Sequence[float]) -> list[can.Message]:
        index = tick % self.ticks_per_cycle
        value = signed_fraction(fractions[index]) * self._full_scale
        if self._erpm:
            value = round(value)
        return [codec.encode_command(self._ids[index], self._command, value, self._gear)]

    def safe_frames(self, tick: int) -> list[can.Message]:
        esc_id = self._ids[tick % self.ticks_per_cycle]
        if self._brake_a > 0:
            return [codec.encode_command(esc_id, self._brake_command, self._brake_a)]
        # Zero current releases the motor whatever the throttle mode: it coasts to a stop.
        return [codec.encode_command(esc_id, self._stop_command, 0.0, records.Gear.NONE)]

    def prepare(self, fractions: Sequence[float]) -> None:
        # Each tick's one frame is for the next ESC in turn, with the newest input: nothing
        # to make ahead that the tick would not make again.
        pass

    def describe_command(self, fraction: float) -> str:
        keys = self._keys
        if keys.ft_mode == "current":
            return f"FT current {fraction * keys.ft_max_current_a:.2f} A"
        if keys.ft_mode == "current_percent":
            return f"FT current {100 * fraction:.1f} %"
        if keys.ft_mode == "duty":
            return f"FT duty {fraction * keys.ft_max_duty:.3f}"
        return f"FT {round(fraction * keys.ft_max_erpm)} erpm"

    def describe_esc(self, index: int) -> str:
        return f"FT ESC {self._ids[index]}, {self.kind} mode"
