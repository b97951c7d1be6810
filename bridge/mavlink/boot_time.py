"""The autopilot's boot clock, as read from its SYSTEM_TIME and TIMESYNC, for outgoing stamps.

Ground stations and mavros read ESC_STATUS/ESC_INFO ``time_usec`` as the autopilot's time since
boot (PX4 sends that; mavros adds its timesync offset to it, so a Unix-epoch stamp lands decades
in the future). The bridge is one more component of the vehicle, so it stamps its ESC reports
on the autopilot's boot clock once it knows it.

The autopilot tells its boot time in SYSTEM_TIME (``time_boot_ms``) and in the TIMESYNC
requests it sends (``tc1`` 0, ``ts1`` its boot time in ns). Seen on the bridge's link: PX4 1.16
SITL sends SYSTEM_TIME at 1 Hz and TIMESYNC at about 10 Hz unasked; ArduCopter SITL a TIMESYNC
every 10 s and SYSTEM_TIME only in a stream someone asked for. Each
sample goes through :class:`~bridge.mavlink.clock.AutopilotClock`, which keeps the offset of the
least transport delay and re-seeds after a reboot, so the estimate is the one the control loop
uses for motor outputs. TIMESYNC answers (``tc1`` not 0) carry another system's clock and are
ignored.

Pure: the caller passes the receive and current times (``time.monotonic_ns()``).
"""

from __future__ import annotations

from typing import Final

from bridge.mavlink.clock import AutopilotClock

__all__ = ["AutopilotBootTime"]

_NS_PER_US: Final = 1000
_US_PER_MS: Final = 1000


class AutopilotBootTime:
    """The autopilot's time since boot at a local monotonic instant, once it has said it."""

    def __init__(self) -> None:
        self._clock = AutopilotClock(time_bits=64)
        self.samples = 0
        """SYSTEM_TIME and TIMESYNC samples taken."""

    def on_system_time(self, time_boot_ms: int, received_ns: int) -> None:
        """A SYSTEM_TIME from the autopilot, read at ``received_ns`` (local monotonic)."""
        if time_boot_ms > 0:
            self._sample(time_boot_ms * _US_PER_MS, received_ns)

    def on_timesync(self, tc1: int, ts1: int, received_ns: int) -> None:
        """A TIMESYNC from the autopilot: a request (``tc1`` 0) carries its boot time in ns."""
        if tc1 == 0 and ts1 > 0:
            self._sample(ts1 // _NS_PER_US, received_ns)

    def _sample(self, remote_us: int, received_ns: int) -> None:
        self._clock.produced_ns(remote_us, received_ns)
        self.samples += 1

    def boot_usec(self, now_ns: int) -> int | None:
        """The autopilot's µs since boot at the local monotonic ``now_ns``; None while unknown
        (no sample yet, or its time runs at no clock's rate)."""
        offset_ns = self._clock.offset_ns
        if offset_ns is None or self._clock.not_a_clock:
            return None
        return max(0, (now_ns - offset_ns) // _NS_PER_US)
