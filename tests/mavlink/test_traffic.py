"""What a recording keeps of the MAVLink traffic (bridge/mavlink/traffic.py): frames packed by
pymavlink as the link packs them, read back into records; the autopilot's stamps on the wall
clock."""

from __future__ import annotations

from typing import Any

import pytest

from bridge.mavlink import load_dialect
from bridge.mavlink.traffic import (
    MAX_STAMP_AGE_US,
    AutopilotHeartbeat,
    MotorOutputs,
    StatusText,
    TrafficReader,
    autopilot_stamp_unix_ns,
)

AUTOPILOT = (1, 1)
BRIDGE = (1, 191)


def codec(system: int, component: int) -> Any:
    dialect: Any = load_dialect()
    return dialect.MAVLink(None, srcSystem=system, srcComponent=component)


def packed(mav: Any, msg: Any) -> bytes:
    return bytes(msg.pack(mav))


def reader(source: str = "servo_output_raw") -> TrafficReader:
    return TrafficReader(load_dialect(), source, AUTOPILOT, BRIDGE)


def test_the_autopilots_outputs_and_heartbeats_and_everyones_statustext() -> None:
    autopilot, bridge, other = codec(*AUTOPILOT), codec(*BRIDGE), codec(1, 2)
    traffic = reader()
    servo = autopilot.servo_output_raw_encode(123_456, 0, 1100, 1200, 0, 1400, 0, 0, 0, 0)
    assert traffic.read(packed(autopilot, servo)) == MotorOutputs(
        "SERVO_OUTPUT_RAW",
        {"ch1": 1100.0, "ch2": 1200.0, "ch4": 1400.0},  # 0: no output on that channel
        123_456,
        32,
        None,
    )
    beat = autopilot.heartbeat_encode(2, 3, 0x80 | 0x01, 4, 4)
    assert traffic.read(packed(autopilot, beat)) == AutopilotHeartbeat(3, 2, 0x81, 4, 4, True)
    text = bridge.statustext_encode(2, b"ESC out: FAILSAFE input stale, motors stopped")
    assert traffic.read(packed(bridge, text)) == StatusText(
        2, "ESC out: FAILSAFE input stale, motors stopped", *BRIDGE
    )
    # Outputs and HEARTBEATs count from the obeyed autopilot only; a STATUSTEXT from anyone.
    assert traffic.read(packed(other, servo)) is None
    assert traffic.read(packed(other, beat)) is None
    assert traffic.read(packed(other, other.statustext_encode(6, b"hi"))) == StatusText(
        6, "hi", 1, 2
    )
    # Everything else is skipped undecoded; a frame that does not read back is counted.
    assert traffic.read(packed(autopilot, autopilot.system_time_encode(1, 2))) is None
    broken = bytearray(packed(bridge, text))
    broken[-1] ^= 0xFF  # its CRC
    assert traffic.read(bytes(broken)) is None
    assert traffic.bad_frames == 1
    assert traffic.read(b"") is None


def test_other_sources_read_as_the_loop_reads_them() -> None:
    autopilot = codec(*AUTOPILOT)
    traffic = reader("hil_actuator_controls")
    controls = [0.5, -0.25] + [0.0] * 14
    msg = autopilot.hil_actuator_controls_encode(99, controls, 0x80, 0)
    got = traffic.read(packed(autopilot, msg))
    assert isinstance(got, MotorOutputs)
    assert (got.source, got.time_usec, got.time_bits, got.armed) == (
        "HIL_ACTUATOR_CONTROLS",
        99,
        64,
        True,
    )
    assert got.channels["ch1"] == 0.5 and got.channels["ch2"] == -0.25


@pytest.mark.parametrize(
    ("time_usec", "bits", "boot_now", "expected_age_us"),
    [
        (9_000_000, 64, 10_000_000, 1_000_000),
        (10_000_000, 64, 10_000_000, 0),
        (10_200_000, 64, 10_000_000, -200_000),  # a little ahead: the clock estimate's error
        # A 32-bit stamp that wrapped: the nearest instant with those low bits.
        ((2**32 + 5_000_000 - 3_000) % 2**32, 32, 2**32 + 5_000_000, 3_000),
        (2**32 - 1_000, 32, 2**32 + 1_000, 2_000),
        (1, 64, 1 + MAX_STAMP_AGE_US, MAX_STAMP_AGE_US),
    ],
)
def test_an_autopilot_stamp_on_the_wall_clock(
    time_usec: int, bits: int, boot_now: int, expected_age_us: int
) -> None:
    unix_now_ns = 1_790_000_000_000_000_000
    got = autopilot_stamp_unix_ns(time_usec, bits, boot_now, unix_now_ns)
    assert got == unix_now_ns - expected_age_us * 1000


@pytest.mark.parametrize(
    ("time_usec", "bits", "boot_now"),
    [
        (1, 64, 2 + MAX_STAMP_AGE_US),  # from before a reboot, or another clock
        (5_000_000, 64, 1_000_000),  # far ahead
        (1_790_000_000_000_000, 64, 10_000_000),  # a Unix-epoch stamp: not the boot clock
    ],
)
def test_a_stamp_on_another_clock_is_not_put_on_the_wall(
    time_usec: int, bits: int, boot_now: int
) -> None:
    assert autopilot_stamp_unix_ns(time_usec, bits, boot_now, 10**18) is None
