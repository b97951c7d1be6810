"""bridge.output.busload: the worst-case bus load of a configuration (PROTOCOLS.md §3), and the
refusal of one above the ceiling."""

from __future__ import annotations

import pytest

from bridge import preflight
from bridge.config import build_config, with_esc_count
from bridge.errors import ConfigError
from bridge.escs.family import frame_bits
from bridge.output.busload import bus_load


def test_bus_load_above_ceiling_is_refused_with_numbers() -> None:
    raw = {
        "mixer": {"name": "passthrough-16"},
        "output": {"protocol": "ft", "rate_hz": 400},
        "can": {"bitrate": 250_000},
    }
    with pytest.raises(ConfigError, match=r"bus load \d+\.\d% of 250 kbit/s.*exceeds the ceiling"):
        preflight.plan(build_config(raw, "v.toml"))


def test_bus_load_arithmetic() -> None:
    # PROTOCOLS.md §3: an 8-byte frame is at most 160 bits (160 µs at 1 Mbit/s).
    assert frame_bits(8) == 160
    assert frame_bits(0) == 80
    config = with_esc_count(
        build_config({"output": {"rate_hz": 400}, "can": {"bitrate": 1_000_000}}, "v"), 4
    )
    load = bus_load(config)
    assert load.command_frames_per_s == 400  # one 12b group
    assert load.command_bits_per_s == 400 * 160
    # 4 ESCs x (MSG1 50 Hz x 7 bytes, MSG2 10 Hz x 6 bytes, MSG3 2 Hz x 8 bytes)
    assert load.telemetry_bits_per_s == 4 * (50 * frame_bits(7) + 10 * frame_bits(6) + 2 * 160)
