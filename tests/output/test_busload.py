"""bridge.output.busload: the worst-case bus load of a configuration (docs/protocols.md §1.3),
and the refusal of one above the ceiling."""

from __future__ import annotations

import pytest

from bridge.config import build_config, with_esc_count
from bridge.daemon import preflight
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
    # docs/protocols.md §1.3: an 8-byte frame is at most 160 bits (160 µs at 1 Mbit/s).
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


def test_dronecan_bus_load_arithmetic() -> None:
    config = with_esc_count(
        build_config({"output": {"protocol": "dronecan"}, "mixer": {"name": "passthrough-8"}}, "v"),
        8,
    )
    assert config.bitrate == 1_000_000 and config.rate_hz == 400  # the family's defaults
    load = bus_load(config)
    # Eight values are 14 bytes, with the transfer CRC 16: frames of 8, 8 and 3 bytes per tick,
    # and our NodeStatus (8 bytes) once a second.
    assert load.command_frames_per_s == 400 * 3 + 1
    assert load.command_bits_per_s == 400 * (2 * 160 + frame_bits(3)) + 160
    # Each ESC: esc.Status (14 bytes: 8, 8, 3) at 50 Hz, NodeStatus once a second.
    assert load.telemetry_frames_per_s == 8 * (50 * 3 + 1)
    assert load.telemetry_bits_per_s == 8 * (50 * (2 * 160 + frame_bits(3)) + 160)
    # Four ESCs fit one frame; ESC numbers 5..8 alone still need slots 0..7.
    quad = with_esc_count(build_config({"output": {"protocol": "dronecan"}}, "v"), 4)
    assert bus_load(quad).command_frames_per_s == 401
    high = build_config({"output": {"protocol": "dronecan"}, "escs": {"ids": [5, 6, 7, 8]}}, "v")
    assert bus_load(with_esc_count(high, 4)).command_frames_per_s == 400 * 3 + 1


def test_vesc_bus_load_arithmetic_and_the_octo_that_needs_1_mbit() -> None:
    quad = with_esc_count(build_config({"output": {"protocol": "vesc"}}, "v"), 4)
    assert quad.bitrate == 500_000 and quad.rate_hz == 200  # the family's defaults
    load = bus_load(quad)
    # A 4-byte command per VESC per cycle; STATUS 1-5 (8 bytes) at 50 Hz from each.
    assert load.command_frames_per_s == 4 * 200
    assert load.command_bits_per_s == 4 * 200 * frame_bits(4) == 96_000
    assert load.telemetry_frames_per_s == 4 * 5 * 50
    assert load.telemetry_bits_per_s == 4 * 5 * 50 * 160 == 160_000
    raw = {"output": {"protocol": "vesc"}, "mixer": {"name": "passthrough-8"}}
    with pytest.raises(ConfigError, match=r"bus load 102\.4% of 500 kbit/s.*exceeds the ceiling"):
        preflight.plan(build_config(raw, "v.toml"))
    preflight.plan(build_config({**raw, "can": {"bitrate": 1_000_000}}, "v.toml"))
