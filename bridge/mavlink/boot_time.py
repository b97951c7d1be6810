"""The autopilot's boot clock, as read from its SYSTEM_TIME and TIMESYNC, for outgoing stamps.

Ground stations and mavros read ESC_STATUS/ESC_INFO ``time_usec`` as the autopilot's time since
boot (PX4 sends that; mavros adds its timesync offset to it, so a Unix-epoch stamp lands decades
in the future). The bridge is one more component of the vehicle, so it stamps its ESC reports
on the autopilot's boot clock once it knows it.

The autopilot tells its boot time in SYSTEM_TIME (``time_boot_ms``) and in the TIMESYNC
requests it sends (``tc1`` 0, ``ts1`` its boot time in ns). Seen on the bridge's link: PX4 1.16
SITL sends SYSTEM_TIME at 1 Hz and TIMESYNC at about 10 Hz unasked; ArduCopter SITL a TIMESYNC
every 10 s and SYSTEM_TIME only in a stream someone asked for. TIMESYNC answers (``tc1`` not 0)
carry another system's clock and are ignored.

Estimate. Each sample gives an offset, local receive time minus remote time: the true offset
plus that message's transport delay. The estimate is the least offset of the samples received
within :data:`WINDOW_NS` of the newest (the newest is always kept, however old), so a delayed
message does not move it and the crystals' drift is followed. A sample whose offset is more
than :data:`STEP_NS` above the estimate starts the window afresh from itself: the autopilot
restarted (its clock stepped back) or its clock stood still while it was stopped (a SITL under
SIGSTOP). A single late message does that too, and the next timely one undoes it. Unlike the
control loop's :class:`~bridge.mavlink.clock.AutopilotClock`, which must never take a late input
for a fresh one, a stamp may follow the autopilot at once.

Pure: the caller passes the receive and current times (``time.monotonic_ns()``).
"""

from __future__ import annotations

from collections import deque
from typing import Final

__all__ = ["STEP_NS", "WINDOW_NS", "AutopilotBootTime"]

WINDOW_NS: Final = 5_000_000_000
"""The estimate is the least offset of the samples this recent (local time)."""
STEP_NS: Final = 250_000_000
"""A sample's offset this far above the estimate restarts it: a reboot or a pause."""
_NS_PER_US: Final = 1000
_NS_PER_MS: Final = 1_000_000


class AutopilotBootTime:
    """The autopilot's time since boot at a local monotonic instant, once it has said it.

    Written by one thread (the link's reader), read by another (the telemetry sender): the
    estimate is one attribute, replaced whole."""

    def __init__(self) -> None:
        self._samples: deque[tuple[int, int]] = deque()  # (received_ns, offset_ns), oldest first
        self._offset_ns: int | None = None
        self.samples = 0
        """SYSTEM_TIME and TIMESYNC samples taken."""
        self.steps = 0
        """Times a sample restarted the estimate (reboots, pauses, late messages)."""

    def on_system_time(self, time_boot_ms: int, received_ns: int) -> None:
        """A SYSTEM_TIME from the autopilot, read at ``received_ns`` (local monotonic)."""
        if time_boot_ms > 0:
            self._sample(received_ns - time_boot_ms * _NS_PER_MS, received_ns)

    def on_timesync(self, tc1: int, ts1: int, received_ns: int) -> None:
        """A TIMESYNC from the autopilot: a request (``tc1`` 0) carries its boot time in ns."""
        if tc1 == 0 and ts1 > 0:
            self._sample(received_ns - ts1, received_ns)

    def _sample(self, offset_ns: int, received_ns: int) -> None:
        self.samples += 1
        samples = self._samples
        if self._offset_ns is not None and offset_ns > self._offset_ns + STEP_NS:
            samples.clear()
            self.steps += 1
        samples.append((received_ns, offset_ns))
        while len(samples) > 1 and received_ns - samples[0][0] > WINDOW_NS:
            samples.popleft()
        self._offset_ns = min(offset for _, offset in samples)

    def boot_usec(self, now_ns: int) -> int | None:
        """The autopilot's µs since boot at the local monotonic ``now_ns``; None before the
        autopilot said its time."""
        offset_ns = self._offset_ns
        if offset_ns is None:
            return None
        return max(0, (now_ns - offset_ns) // _NS_PER_US)
