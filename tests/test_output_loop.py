"""The output loop in a thread on python-can's virtual bus: a fault in a tick means safe values."""

from __future__ import annotations

import threading
import time

import can

from bridge.config import build_config, with_esc_count
from bridge.escs import ckesc
from bridge.mailbox import CommandMailbox, LoopState, LoopStats
from bridge.mixer import load_mixer
from bridge.output_loop import LoopSetup, OutputLoop


def test_a_fault_in_a_tick_sends_safe_values_and_the_loop_lives_on() -> None:
    raw = {
        "can": {"interface": "virtual", "channel": "tick-fault"},
        "output": {"realtime_priority": 0},
    }
    config = with_esc_count(build_config(raw, "test"), 4)
    # A mailbox one output short of the mixer: every RUNNING tick's slew step raises.
    mailbox, stats = CommandMailbox(3), LoopStats()
    loop = OutputLoop(LoopSetup(config, load_mixer("passthrough-4")), mailbox, stats, None)
    observer = can.Bus(interface="virtual", channel="tick-fault")
    thread = threading.Thread(target=loop.run)
    thread.start()
    try:
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and stats["tick_errors"] < 20:
            mailbox.write_armed(True, time.monotonic_ns())
            mailbox.write([0.5, 0.5, 0.5], time.monotonic_ns())
            time.sleep(0.01)
        assert stats["tick_errors"] >= 20
        assert stats["state"] == LoopState.RUNNING
        seen: list[tuple[int, ...]] = []
        while (msg := observer.recv(0.05)) is not None and len(seen) < 50:
            frame = ckesc.decode(msg)
            assert frame is not None and isinstance(frame.message, ckesc.RawCommand12b)
            seen.append(frame.message.throttles)
        assert len(seen) >= 20
        assert set(seen) == {(0, 0, 0, 0)}
    finally:
        loop.request_stop()
        thread.join(5)
        observer.shutdown()
    assert not thread.is_alive()
    assert stats["state"] == LoopState.STOPPED
