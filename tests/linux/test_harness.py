"""The harness itself: a call runs where the kernel is, on a vcan of its own, and its failures
come back with the guest's log."""

from __future__ import annotations

import platform

import pytest

from linux import guest
from linux.kernel import GuestError, Kernel


def frames_through_vcan(count: int) -> dict[str, object]:
    channel = guest.vcan()
    dump = guest.Candump(channel)
    guest.wait_until(lambda: bool(guest.receivers(channel)), 10, "candump's socket")
    for i in range(count):
        guest.cansend(channel, f"1{i:02X}#{i:02X}")
    guest.wait_until(lambda: len(dump.frames()) == count, 10, f"{count} frames")
    return {
        "release": platform.release(),
        "channel": channel,
        "frames": [f for _, f in dump.frames()],
    }


def fails_with_a_log() -> None:
    guest.run(["ip", "link", "show", "no-such-interface"])


def test_a_call_sends_frames_through_a_vcan(linux: Kernel) -> None:
    result = linux.call(frames_through_vcan, count=3)
    assert result["frames"] == ["100#00", "101#01", "102#02"]
    if linux.mode == "uml":
        assert result["release"] == linux.release != platform.release()


def test_a_failing_call_says_what_it_ran(linux: Kernel) -> None:
    with pytest.raises(GuestError) as failure:
        linux.call(fails_with_a_log)
    assert "CalledProcessError" in str(failure.value)
    assert "ip link show no-such-interface" in str(failure.value)
