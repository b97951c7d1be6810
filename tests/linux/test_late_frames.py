"""No command reaches an ESC late: through a hold of the bus, the bridge's live throttle reaches
the ESCs at most one tick late, also beside two busy processes and a flood of other frames
(the measurement is tests/linux/late_frames.py's, the figures bench/late_frames.py's)."""

from __future__ import annotations

import pytest

from linux import late_frames
from linux.kernel import Kernel

HOLD_MS = 1000


@pytest.mark.parametrize("loaded", [False, True], ids=["idle", "busy-and-flooded"])
def test_a_held_bus_delivers_one_tick_late_at_most(linux: Kernel, loaded: bool) -> None:
    # 100 Hz: the loop runs at real-time priority in the guest's one CPU. One command frame a
    # tick (CKESC x4: one RawCommand_12b).
    found = linux.call(
        late_frames.hold_through_a_disarm, timeout_s=600, hold_ms=HOLD_MS, rate_hz=100,
        loaded=loaded,
    )  # fmt: skip
    # The tick written as the hold began, delivered when it ended, after the disarm; nothing
    # was written behind it. The landed code delivered every frame of the hold's first half
    # after the disarm, the last one a whole hold after it. How long after the disarm the held
    # tick comes is not asserted from below: tc takes seconds to start and end the hold in a
    # loaded host's guest (351 ms after a disarm nominally 500 ms before the hold's end). Where
    # tc's end of the hold comes late, each tick written after an echo is held a whole hold
    # again, each spell stuck reported as such (5 in a run at load 17), each tick after the
    # disarm safe. Not asserted to be 1 or more: where tc returned late, the disarm came after
    # the hold's end (0 in a run of bench/late_frames.py at load 10, and in one here).
    assert found["live_after"] <= 2, found
    assert found["latest_ms"] < HOLD_MS * 0.8, found
    assert found["stuck_reports"] >= 1, found
