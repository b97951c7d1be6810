"""Worst-case CAN bus load of a configuration (PROTOCOLS.md §3), checked before anything is sent.

A frame's worst-case length with n data bytes, bit stuffing and the 3-bit interframe space
included, is ``67 + 8n + floor((54 + 8n - 1) / 4)`` bits (Davis, Burns, Bril, Lukkien 2007).
The load is the sum over every periodic frame, the bridge's commands and the ESCs' telemetry at
their configured rates, of bits x rate / bit rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from bridge.config import BridgeConfig
from bridge.errors import ConfigError
from bridge.escs.drivers import ft_command_dlc

CKESC_THROTTLE_FRAME_BYTES = 8  # 12b, 14b (7 + tail) and 10b all fill the frame
CKESC_TELEMETRY_BYTES = (7, 6, 8)  # MSG1, MSG2, MSG3 with their tail bytes
FT_TELEMETRY_FRAMES = 3  # REALTIME_DATA_0, 1 and 2, 8 bytes each
FT_TELEMETRY_BYTES = 8
IMMEDIATE_MAX_RATE_FACTOR = 2  # latency = "immediate" sends at most this many times the rate


def frame_bits(data_bytes: int) -> int:
    """Worst-case bits on the wire for an extended data frame carrying ``data_bytes`` (0..8)."""
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"a classic CAN frame carries 0..8 data bytes, not {data_bytes}")
    return 67 + 8 * data_bytes + (54 + 8 * data_bytes - 1) // 4


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


def ckesc_groups(channels: tuple[int, ...], command: str) -> int:
    """Throttle frames per cycle: 12b needs one per group of four channels in use."""
    if command == "12b":
        return len({(channel - 1) // 4 for channel in channels})
    return 1


def bus_load(config: BridgeConfig) -> BusLoad:
    """The worst-case load of ``config`` (its ESC lists already filled in)."""
    escs = config.escs
    n = len(escs.ids)
    # Immediate mode sends on fresh input too, at most IMMEDIATE_MAX_RATE_FACTOR x the rate.
    rate_hz = config.rate_hz * (
        IMMEDIATE_MAX_RATE_FACTOR if config.output.latency == "immediate" else 1
    )
    if config.output.protocol == "ckesc":
        frames = rate_hz * ckesc_groups(escs.ckesc_channels, escs.ckesc_command)
        command_bits = frames * frame_bits(CKESC_THROTTLE_FRAME_BYTES)
        telemetry_frames = n * sum(escs.ckesc_msg_hz)
        telemetry_bits = n * sum(
            hz * frame_bits(size)
            for hz, size in zip(escs.ckesc_msg_hz, CKESC_TELEMETRY_BYTES, strict=True)
        )
    else:
        frames = rate_hz * n
        command_bits = frames * frame_bits(ft_command_dlc(escs.ft_crc))
        telemetry_frames = n * FT_TELEMETRY_FRAMES * escs.ft_telemetry_hz
        telemetry_bits = telemetry_frames * frame_bits(FT_TELEMETRY_BYTES)
    return BusLoad(config.bitrate, command_bits, telemetry_bits, frames, telemetry_frames)


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
