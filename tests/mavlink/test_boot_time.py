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
    # A sample that took 30 ms longer on the way does not move the estimate.
    boot.on_system_time(61_000, 2_030 * MS)
    assert boot.boot_usec(2_000 * MS) == 61_000_000
    # One that was quicker does, at once.
    boot.on_system_time(62_000, 2_995 * MS)
    assert boot.boot_usec(3_000 * MS) == 62_005_000


def test_timesync_requests_carry_the_same_clock_in_ns() -> None:
    boot = AutopilotBootTime()
    boot.on_timesync(0, 90_000_000_000, 400 * MS)  # 90 s since boot
    assert boot.boot_usec(500 * MS) == 90_100_000
    assert boot.samples == 1


def test_drift_is_followed_over_the_window() -> None:
    boot = AutopilotBootTime()
    # The autopilot's crystal runs 1 % slow (an extreme one): one sample a second.
    for second in range(20):
        boot.on_system_time(10_000 + 990 * second, (100 + second * 1000) * MS)
    expected_us = (10_000 + 990 * 19) * 1000
    got = boot.boot_usec(19_100 * MS)
    assert got is not None and expected_us - 5_000 <= got <= expected_us + 50_000


def test_a_reboot_or_a_pause_is_followed_at_once_and_a_late_message_undone() -> None:
    boot = AutopilotBootTime()
    boot.on_system_time(3_600_000, 1_000 * MS)
    boot.on_system_time(2_000, 2_000 * MS)  # the clock stepped back: it restarted
    assert boot.boot_usec(2_000 * MS) == 2_000_000
    boot.on_system_time(3_000, 3_000 * MS)
    boot.on_system_time(4_000, 5_000 * MS)  # stood still for a second (SIGSTOP), goes on
    assert boot.boot_usec(5_000 * MS) == 4_000_000
    boot.on_system_time(5_000, 6_400 * MS)  # 400 ms late on the way: followed...
    boot.on_system_time(6_000, 7_000 * MS)  # ... and undone by the next timely one
    assert boot.boot_usec(7_000 * MS) == 6_000_000
    assert boot.steps == 3
