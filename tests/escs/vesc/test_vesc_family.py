"""The VESC family behind EscFamily (bridge/escs/vesc/family.py, bus.py): its ID space, the
kernel filters (exactly the status frames of our VESCs, and with read-back their commands), the
bus-load figures and the check of the command rate against the VESCs' timeout."""

from __future__ import annotations

import dataclasses

import pytest

from bridge.errors import ConfigError, ValueRangeError
from bridge.escs.family import EscSetup, frame_bits
from bridge.escs.vesc.family import VescFamily
from bridge.escs.vesc.keys import VescKeys
from bridge.escs.vesc.records import STATUS_PACKETS

FAMILY = VescFamily()


def passed(filters: list[dict[str, object]]) -> set[int]:
    """Every ID of VESC's space, and a few just above it, that some filter passes (as the
    kernel matches them)."""
    return {
        arbitration_id
        for arbitration_id in [*range(0x10000), 0x10917, 0x1E917, 0x1FFF0917]
        if any(
            arbitration_id & int(f["can_mask"]) == int(f["can_id"]) & int(f["can_mask"])  # type: ignore[call-overload]
            for f in filters
        )
    }


def test_id_space() -> None:
    assert FAMILY.owns(0x117) and FAMILY.owns(0x0) and FAMILY.owns(0xFFFF)
    assert not FAMILY.owns(0x10000) and not FAMILY.owns(0x1F01550A)
    assert FAMILY.node_ids == range(0, 255)
    assert (FAMILY.name, FAMILY.title, FAMILY.default_bitrate) == ("vesc", "VESC", 500_000)


def test_filters_pass_exactly_our_status_frames() -> None:
    ids = [1, 2, 3, 4, 23]
    filters = FAMILY.reader_filters(ids)
    assert all(f["extended"] for f in filters)
    assert passed(filters) == {p << 8 | i for p in STATUS_PACKETS for i in ids}  # type: ignore[arg-type]


def test_filters_are_few() -> None:
    # STATUS 9, 14, 15, 16, 27, 58: {9}, {14, 15}, {16}, {27}, {58}; IDs 1..4: {1}, {2, 3}, {4}.
    assert len(FAMILY.reader_filters([1, 2, 3, 4])) == 15
    assert len(FAMILY.reader_filters(range(0, 8))) == 5


def test_filters_refuse_impossible_ids() -> None:
    with pytest.raises(ValueRangeError, match=r"VESC IDs \[255\]"):
        FAMILY.reader_filters([1, 255])


def test_bus_figures() -> None:
    figures = FAMILY.bus_figures(EscSetup((1, 2, 3, 4), VescKeys()), 200.0)
    assert frame_bits(4) == 120 and frame_bits(8) == 160
    assert figures.command_frames_per_s == 800
    assert figures.command_bits_per_s == 800 * 120
    assert figures.telemetry_frames_per_s == 4 * 5 * 50
    assert figures.telemetry_bits_per_s == 1000 * 160
    quiet = FAMILY.bus_figures(EscSetup((1,), VescKeys(vesc_status_hz=0.0)), 100.0)
    assert quiet.telemetry_frames_per_s == 0


def test_the_rate_must_refresh_each_vesc_four_times_within_its_timeout() -> None:
    setup = EscSetup((1, 2, 3, 4), VescKeys())
    assert FAMILY.check(setup, 4) is setup
    with pytest.raises(ConfigError, match=r"3 Hz refreshes each VESC every 333 ms.*at least 4 Hz"):
        FAMILY.check(setup, 3)
    fast = EscSetup((1,), dataclasses.replace(VescKeys(), vesc_timeout_ms=100))
    with pytest.raises(ConfigError, match=r"vesc_timeout_ms\), so expected at least 40 Hz"):
        FAMILY.check(fast, 39)
    assert FAMILY.check(fast, 40) is fast
