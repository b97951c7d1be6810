"""The VESC family's ``[escs]`` keys (documented in config/README.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from bridge.config_checks import choice, float_range, int_range, key

VescMode = Literal["duty", "current_rel", "current", "rpm"]


@dataclass(frozen=True)
class VescKeys:
    vesc_mode: VescMode = key(
        "duty",
        choice("duty", "current_rel", "current", "rpm"),
        "VESC command: duty, current_rel (of the VESC's own limit), current (A) or rpm (erpm)",
    )
    vesc_max_duty: float = key(0.95, float_range(0.01, 1.0), "VESC duty at full throttle")
    vesc_max_current_a: float = key(20.0, float_range(0.1, 500), "VESC current at full throttle")
    vesc_max_erpm: int = key(50_000, int_range(100, 500_000), "VESC erpm at full throttle")
    vesc_brake_current_a: float = key(
        0.0, float_range(0, 500), "safe output: brake with this current (0: command 0 A)"
    )
    vesc_timeout_ms: int = key(
        1000, int_range(10, 60_000), "the VESCs' command timeout (VESC Tool: Timeout)"
    )
    vesc_status_hz: float = key(
        50.0,
        float_range(0, 1000),
        "status frames per VESC per second, each of STATUS 1-5 (VESC Tool: Can Status Rate 1)",
    )
