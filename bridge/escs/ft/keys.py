"""The FT family's ``[escs]`` keys (documented in config/README.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from bridge.config_checks import boolean, choice, float_range, int_range, key

FtMode = Literal["current", "current_percent", "duty", "erpm"]
FtGear = Literal["none", "low", "middle", "high", "reverse"]


@dataclass(frozen=True)
class FtKeys:
    ft_mode: FtMode = key(
        "current",
        choice("current", "current_percent", "duty", "erpm"),
        "FT command: current (A), current_percent, duty or erpm",
    )
    ft_crc: bool = key(True, boolean, "use the FT commands with CRC-16")
    ft_gear: FtGear = key(
        "none", choice("none", "low", "middle", "high", "reverse"), "FT speed gear"
    )
    ft_max_current_a: float = key(20.0, float_range(0.1, 500), "FT current at full throttle")
    ft_max_duty: float = key(0.95, float_range(0.01, 1.0), "FT duty at full throttle")
    ft_max_erpm: int = key(50_000, int_range(100, 500_000), "FT erpm at full throttle")
    ft_brake_current_a: float = key(
        0.0, float_range(0, 500), "safe output: brake with this current (0: command 0 A)"
    )
    ft_telemetry_hz: float = key(
        100.0, float_range(0, 1000), "FT real-time frames per ESC per second (each of 3 kinds)"
    )
