"""Worst-case CAN bus load of a configuration (docs/protocols.md §1.3), checked before anything
is sent.

The load is the sum over every periodic frame, the bridge's commands and the ESCs' telemetry at
their configured rates, of bits x rate / bit rate; each ESC family counts its own frames
(:meth:`~bridge.escs.family.EscFamily.bus_figures`, with the worst-case frame length of
:func:`bridge.escs.family.frame_bits`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from bridge.config import BridgeConfig
from bridge.errors import ConfigError

IMMEDIATE_MAX_RATE_FACTOR = 2  # latency = "immediate" sends at most this many times the rate


@dataclass(frozen=True)
class BusLoad:
    """Bits per second by source, and the share of the bus they take."""

    bitrate: int
    command_bits_per_s: float
    telemetry_bits_per_s: float
    command_frames_per_s: float
    telemetry_frames_per_s: float

    @property
    def fraction(self) -> float:
        return (self.command_bits_per_s + self.telemetry_bits_per_s) / self.bitrate

    def describe(self) -> str:
        return (
            f"bus load {100 * self.fraction:.1f}% of {self.bitrate // 1000} kbit/s: commands "
            f"{self.command_frames_per_s:.0f} frames/s ({self.command_bits_per_s / 1000:.1f} "
            f"kbit/s), ESC telemetry {self.telemetry_frames_per_s:.0f} frames/s "
            f"({self.telemetry_bits_per_s / 1000:.1f} kbit/s)"
        )


def bus_load(config: BridgeConfig) -> BusLoad:
    """The worst-case load of ``config`` (its ESC lists already filled in): the figures of its
    ESC family's commands and telemetry."""
    # Immediate mode sends on fresh input too, at most IMMEDIATE_MAX_RATE_FACTOR x the rate.
    rate_hz = config.rate_hz * (
        IMMEDIATE_MAX_RATE_FACTOR if config.output.latency == "immediate" else 1
    )
    figures = config.family.bus_figures(config.esc_setup, rate_hz)
    return BusLoad(
        config.bitrate,
        figures.command_bits_per_s,
        figures.telemetry_bits_per_s,
        figures.command_frames_per_s,
        figures.telemetry_frames_per_s,
    )


def check_bus_load(config: BridgeConfig) -> BusLoad:
    """The load of ``config``, or ConfigError with the numbers when it exceeds the ceiling."""
    load = bus_load(config)
    ceiling = config.output.bus_load_ceiling
    if load.fraction > ceiling:
        room_bits = ceiling * load.bitrate - load.telemetry_bits_per_s
        most_hz = math.floor(config.rate_hz * room_bits / load.command_bits_per_s)
        raise ConfigError(
            f"{config.source}: {load.describe()} exceeds the ceiling of {100 * ceiling:.0f}% "
            f"([output] bus_load_ceiling); lower [output] rate_hz (at most {max(most_hz, 0)} Hz "
            "fits), the ESCs' telemetry rates, or raise [can] bitrate"
        )
    return load
