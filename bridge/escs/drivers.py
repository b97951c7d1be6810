"""Output drivers: the mixer's command fractions to the frames of one output tick.

A driver is the one place where a fraction becomes a protocol value, so it is also where every
value is limited to what the protocol allows: whatever the stages before it did, no frame ever
carries an out-of-range command.

The output loop ticks ``ticks_per_cycle`` times per cycle. CKESC sends all throttle groups in
one tick (one frame per group of four channels; the ESCs read them as one command). FT needs a
frame per ESC, and the loop spreads them evenly across the cycle, one ESC per tick, so the bus
never sees a burst of N frames followed by silence.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Protocol

import can

from bridge.config import BridgeConfig, EscsConfig
from bridge.escs import ckesc, ft


class EscDriver(Protocol):
    """Turns one tick's command fractions into CAN frames."""

    ticks_per_cycle: int

    def tick_frames(self, tick: int, fractions: Sequence[float]) -> list[can.Message]:
        """Frames for ``tick`` commanding ``fractions`` (one per mixer output, -1..1)."""

    def safe_frames(self, tick: int) -> list[can.Message]:
        """Frames for ``tick`` commanding the safe output (motors stopped)."""


def _unit_fraction(fraction: float) -> float:
    """Limit to 0..1 for a unidirectional command; NaN (never expected here) becomes 0."""
    return fraction if 0.0 <= fraction <= 1.0 else (1.0 if fraction > 1.0 else 0.0)


def _signed_fraction(fraction: float) -> float:
    """Limit to -1..1; NaN (never expected here) becomes 0."""
    if -1.0 <= fraction <= 1.0:
        return fraction
    return 1.0 if fraction > 1.0 else -1.0 if fraction < -1.0 else 0.0


class CkescDriver:
    """RawCommand_12b (one frame per group of four channels), 14b or 10b throttle frames."""

    ticks_per_cycle = 1

    def __init__(self, command: str, channels: Sequence[int]) -> None:
        self._command = command
        self._channel_index = [channel - 1 for channel in channels]
        self._full_scale = ckesc.THROTTLE_10B_MAX if command == "10b" else ckesc.THROTTLE_MAX
        self._throttles = [0] * ckesc.MAX_CHANNELS
        self._groups = sorted({index // 4 + 1 for index in self._channel_index})
        self._transfer_ids = ckesc.TransferIds()
        self._zeros = [0.0] * len(self._channel_index)

    def tick_frames(self, tick: int, fractions: Sequence[float]) -> list[can.Message]:
        throttles = self._throttles
        full_scale = self._full_scale
        for index, fraction in zip(self._channel_index, fractions, strict=True):
            throttles[index] = int(_unit_fraction(fraction) * full_scale + 0.5)
        if self._command == "12b":
            next_id = self._transfer_ids.next
            return [
                ckesc.encode_raw_12b(
                    group, throttles[4 * group - 4 : 4 * group], next_id(ckesc.TYPE_RAW_COMMAND_12B)
                )
                for group in self._groups
            ]
        if self._command == "14b":
            tid = self._transfer_ids.next(ckesc.TYPE_RAW_COMMAND_14B)
            return [ckesc.encode_raw_14b(throttles[:4], tid)]
        return [ckesc.encode_raw_10b(throttles[:6])]

    def safe_frames(self, tick: int) -> list[can.Message]:
        return self.tick_frames(tick, self._zeros)


# The FT command the daemon sends for each throttle mode, with and without CRC.
FT_MODE_COMMANDS: dict[tuple[str, bool], ft.Command] = {
    ("current", True): ft.Command.SET_CURRENT_GEAR_CRC16,
    ("current", False): ft.Command.SET_CURRENT_GEAR,
    ("current_percent", True): ft.Command.SET_CURRENT_PERCENT_GEAR_CRC16,
    ("current_percent", False): ft.Command.SET_CURRENT_PERCENT_GEAR,
    ("duty", True): ft.Command.SET_DUTY_GEAR_CRC16,
    ("duty", False): ft.Command.SET_DUTY_GEAR,
    ("erpm", True): ft.Command.SET_ERPM_GEAR_CRC16,
    ("erpm", False): ft.Command.SET_ERPM_GEAR,
}
FT_BRAKE_COMMANDS = {True: ft.Command.SET_CURRENT_BRAKE_CRC16, False: ft.Command.SET_CURRENT_BRAKE}
FT_GEARS = {
    "none": ft.Gear.NONE,
    "low": ft.Gear.LOW,
    "middle": ft.Gear.MIDDLE,
    "high": ft.Gear.HIGH,
    "reverse": ft.Gear.REVERSE,
}


def ft_command_dlc(crc: bool) -> int:
    """Data bytes of every throttle command above: i32 value and gear, plus the CRC-16."""
    return 5 + (2 if crc else 0)


class FtDriver:
    """One FT command per ESC per cycle, one ESC per tick, in the configured mode."""

    def __init__(self, escs: EscsConfig) -> None:
        self._ids = escs.ids
        self.ticks_per_cycle = len(escs.ids)
        self._command = FT_MODE_COMMANDS[(escs.ft_mode, escs.ft_crc)]
        self._gear = FT_GEARS[escs.ft_gear]
        self._erpm = escs.ft_mode == "erpm"
        self._full_scale = {
            "current": escs.ft_max_current_a,
            "current_percent": 1.0,
            "duty": escs.ft_max_duty,
            "erpm": float(escs.ft_max_erpm),
        }[escs.ft_mode]
        self._brake_a = escs.ft_brake_current_a
        self._brake_command = FT_BRAKE_COMMANDS[escs.ft_crc]
        self._stop_command = FT_MODE_COMMANDS[("current", escs.ft_crc)]

    def tick_frames(self, tick: int, fractions: Sequence[float]) -> list[can.Message]:
        index = tick % self.ticks_per_cycle
        value = _signed_fraction(fractions[index]) * self._full_scale
        if self._erpm:
            value = round(value)
        return [ft.encode_command(self._ids[index], self._command, value, self._gear)]

    def safe_frames(self, tick: int) -> list[can.Message]:
        esc_id = self._ids[tick % self.ticks_per_cycle]
        if self._brake_a > 0:
            return [ft.encode_command(esc_id, self._brake_command, self._brake_a)]
        # Zero current releases the motor whatever the throttle mode: it coasts to a stop.
        return [ft.encode_command(esc_id, self._stop_command, 0.0, ft.Gear.NONE)]


def make_driver(config: BridgeConfig) -> EscDriver:
    """The driver for ``config`` (its ESC lists already filled in)."""
    escs = config.escs
    if config.output.protocol == "ckesc":
        return CkescDriver(escs.ckesc_command, escs.ckesc_channels)
    return FtDriver(escs)


def flush_safe_values(
    send: Callable[[list[can.Message]], object],
    driver: EscDriver,
    period_ns: int,
    duration_ms: float,
    first_tick: int = 0,
) -> int:
    """Send the safe values every ``period_ns`` for ``duration_ms`` (at least one whole cycle,
    so every FT ESC gets one) through ``send``, on absolute deadlines; returns the next tick.
    For the ends of things: the end of a spin, the survivor of a dead control loop."""
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
