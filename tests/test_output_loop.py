"""The control loop in a thread on python-can's virtual bus, fed by a real pymavlink autopilot on
loopback UDP; and its per-tick selector on its own: a fault in a tick means safe values."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import can
import pytest
from conftest import Autopilot, free_port

from bridge.autopilot_input import InputSetup
from bridge.config import build_config
from bridge.escs import ckesc
from bridge.escs.ckesc.driver import CkescDriver
from bridge.mailbox import InputSnapshot, LoopStats, MotorTestBlock
from bridge.mixer import SlewLimiter
from bridge.output_loop import CommandSelector, LoopSetup, OutputLoop
from bridge.preflight import plan
from bridge.relay import relay_pair
from bridge.safety import ControlInputs, LoopState, SafetyLimits

MS = 1_000_000


def _throttles(observer: can.BusABC, count: int) -> list[tuple[int, ...]]:
    seen: list[tuple[int, ...]] = []
    while len(seen) < count and (msg := observer.recv(1.0)) is not None:
        frame = ckesc.decode(msg)
        assert frame is not None and isinstance(frame.message, ckesc.RawCommand12b)
        seen.append(frame.message.throttles)
    return seen


@pytest.fixture
def loop_on_virtual_bus(
    request: pytest.FixtureRequest,
) -> Iterator[tuple[int, LoopStats]]:
    channel = f"loop-{request.node.name}"
    port = free_port()
    raw = {
        "mavlink": {"url": f"udpin:127.0.0.1:{port}"},
        "can": {"interface": "virtual", "channel": channel},
        "output": {"realtime_priority": 0, "loop": "thread"},
        "zenoh": {"enabled": False},
    }
    checked = plan(build_config(raw, "test"))
    stats = LoopStats()
    n = len(checked.mixer.outputs)
    loop_end, main_end = relay_pair()
    setup = LoopSetup(checked.config, InputSetup(checked.mixer, checked.valid_range, None))
    loop = OutputLoop(setup, MotorTestBlock(n), InputSnapshot(n), stats, loop_end)
    thread = threading.Thread(target=loop.run)
    thread.start()
    yield port, stats
    loop.request_stop()
    thread.join(5)
    main_end.close()
    assert not thread.is_alive()
    assert stats["state"] == LoopState.STOPPED


def test_the_loop_reads_the_autopilot_itself_and_sends_the_mix(
    loop_on_virtual_bus: tuple[int, LoopStats], request: pytest.FixtureRequest
) -> None:
    port, stats = loop_on_virtual_bus
    observer = can.Bus(interface="virtual", channel=f"loop-{request.node.name}")
    autopilot = Autopilot(port)
    try:
        assert set(_throttles(observer, 5)) == {(0, 0, 0, 0)}  # no input yet
        autopilot.pwm = [1250, 1500, 1750, 2000]
        autopilot.armed = True
        autopilot.start_stream(100)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and stats["state"] != LoopState.RUNNING:
            time.sleep(0.01)
        assert stats["state"] == LoopState.RUNNING
        while observer.recv(0) is not None:
            pass  # what was queued before
        assert set(_throttles(observer, 20)[-10:]) == {(500, 1000, 1500, 2000)}
        assert stats["input_outputs"] > 0 and stats["input_heartbeats"] > 0
        autopilot.pause_outputs()
        time.sleep(0.2)
        assert stats["state"] == LoopState.STALE
        while observer.recv(0) is not None:
            pass  # what was queued before
        assert set(_throttles(observer, 10)[-5:]) == {(0, 0, 0, 0)}
    finally:
        autopilot.close()
        observer.shutdown()


def test_a_fault_in_a_tick_sends_safe_values_and_the_next_tick_runs_again() -> None:
    # A stream at 200 Hz for long enough to arm on.
    inputs = ControlInputs(
        have_input=True, input_valid=True, armed=True, input_interval_ns=5 * MS, input_intervals=3
    )
    limits = SafetyLimits(True, 100 * MS, 3000 * MS)
    selector = CommandSelector(
        CkescDriver("12b", [1, 2, 3, 4]), SlewLimiter([0.0] * 4, [0.0] * 4), limits, inputs, 4
    )
    now = 10_000 * MS
    inputs.input_produced_ns = inputs.armed_heard_ns = now
    good = [0.5, 0.5, 0.5, 0.5]

    def throttles(fractions: list[float]) -> tuple[int, ...]:
        frames = selector.select(0, now, fractions, 0.0025)
        decoded = ckesc.decode(frames[0])
        assert decoded is not None and isinstance(decoded.message, ckesc.RawCommand12b)
        return decoded.message.throttles

    assert throttles(good) == (1000, 1000, 1000, 1000)
    # A vector the slew limiter cannot take (one output short): safe values, counted.
    assert throttles([0.5, 0.5, 0.5]) == (0, 0, 0, 0)
    assert selector.faults == 1 and selector.state == LoopState.RUNNING
    assert throttles(good) == (1000, 1000, 1000, 1000)
