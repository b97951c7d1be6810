"""bridge.mavlink.boot_time: the autopilot's boot clock from its SYSTEM_TIME and TIMESYNC, pure
(times passed in, ns on our monotonic clock)."""

from __future__ import annotations

from bridge.mavlink.boot_time import AutopilotBootTime

MS = 1_000_000  # ns


def test_unknown_until_the_autopilot_says_its_time() -> None:
    boot = AutopilotBootTime()
    assert boot.boot_usec(5 * MS) is None
    boot.on_system_time(0, 5 * MS)  # 0: not filled in
    boot.on_timesync(123, 456, 5 * MS)  # an answer to someone's request: another clock
    assert boot.boot_usec(5 * MS) is None
    assert boot.samples == 0


def test_system_time_maps_the_boot_clock_onto_ours() -> None:
    boot = AutopilotBootTime()
    boot.on_system_time(60_000, 1_000 * MS)  # a minute after its boot, at our 1 s
    assert boot.boot_usec(1_000 * MS) == 60_000_000
    assert boot.boot_usec(1_250 * MS) == 60_250_000
    # A later sample that took 30 ms longer on the way moves the estimate by at most 2 % of
    # the second between them (the clock's allowed drift), not by its delay.
    boot.on_system_time(61_000, 2_030 * MS)
    later = boot.boot_usec(2_000 * MS)
    assert later is not None and 61_000_000 - 20_000 <= later <= 61_000_000


def test_timesync_requests_carry_the_same_clock_in_ns() -> None:
    boot = AutopilotBootTime()
    boot.on_timesync(0, 90_000_000_000, 400 * MS)  # 90 s since boot
    assert boot.boot_usec(500 * MS) == 90_100_000
    assert boot.samples == 1


def test_a_reboot_is_followed_at_once() -> None:
    boot = AutopilotBootTime()
    boot.on_system_time(3_600_000, 1_000 * MS)
    boot.on_system_time(2_000, 9_000 * MS)  # the clock stepped back: it restarted
    assert boot.boot_usec(9_000 * MS) == 2_000_000
