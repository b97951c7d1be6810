"""The DroneCAN output driver (bridge/escs/dronecan/driver.py): scaling and limits (forward-only
and reversible), the slots up to the highest ESC index, safe frames, one transfer per tick with
its transfer ID, and our NodeStatus once a second on the driver's clock."""

from __future__ import annotations

import math
import subprocess
import sys

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridge.errors import ValueRangeError
from bridge.escs.dronecan import wire
from bridge.escs.dronecan.codec import Decoder, NodeStatus, RawCommand
from bridge.escs.dronecan.driver import DronecanDriver


class FakeClock:
    def __init__(self) -> None:
        self.ns = 5_000_000_000

    def __call__(self) -> int:
        return self.ns


def messages(frames: list[can.Message]) -> list[object]:
    decoder = Decoder()
    return [f.message for f in (decoder.decode(m) for m in frames) if f is not None]


def commands(frames: list[can.Message]) -> tuple[int, ...]:
    (command,) = [m for m in messages(frames) if isinstance(m, RawCommand)]
    return command.commands


def test_scaling_and_slots() -> None:
    driver = DronecanDriver([0, 1, 2, 3], node_status=False)
    frames = driver.tick_frames(0, [0.0, 0.5, 1.0, 0.25])
    assert len(frames) == 1 and frames[0].arbitration_id == 0x0704060A
    assert commands(frames) == (0, 4096, 8191, 2048)
    # ESCs at indices 4..7 (ArduPilot's ESC_OF habit is done by the ESCs' own indices here):
    # the transfer carries slots 0..7, the unused ones at 0, in three frames.
    driver = DronecanDriver([7, 4, 5, 6], node_id=42, node_status=False)
    frames = driver.tick_frames(0, [1.0, 0.5, 0.0, 0.25])
    assert len(frames) == 3 and all(f.arbitration_id & 0x7F == 42 for f in frames)
    assert commands(frames) == (0, 0, 0, 0, 4096, 0, 2048, 8191)
    assert driver.command_slots == 8 and driver.ticks_per_cycle == 1


def test_forward_only_and_reversible_limits() -> None:
    driver = DronecanDriver([0, 1, 2, 3], reversible=[False, False, True, True], node_status=False)
    frames = driver.tick_frames(0, [-0.5, 1.7, -0.5, -3.0])
    assert commands(frames) == (0, 8191, -4096, -8191)
    frames = driver.tick_frames(1, [math.nan, math.inf, math.nan, -math.inf])
    assert commands(frames) == (0, 8191, 0, -8191)


@given(
    st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=6, max_size=6),
    st.lists(st.booleans(), min_size=6, max_size=6),
)
def test_never_out_of_range(fractions: list[float], reversible: list[bool]) -> None:
    driver = DronecanDriver(range(6), reversible=reversible, node_status=False)
    values = commands(driver.tick_frames(0, fractions))
    for value, reverse in zip(values, reversible, strict=True):
        assert (-8191 if reverse else 0) <= value <= 8191


def test_safe_frames_are_zeros_and_every_tick_takes_the_next_transfer_id() -> None:
    driver = DronecanDriver(range(8), node_status=False)
    # Each tick's frames read before the next call, which may reuse them (as sending does).
    ticks = [
        (commands(frames), [f.data[-1] & 0x1F for f in frames])
        for frames in (
            driver.tick_frames(0, [0.5] * 8) if tick == 0 else driver.safe_frames(tick)
            for tick in range(3)
        )
    ]
    assert ticks[1][0] == (0,) * 8 == ticks[2][0]
    assert [ids for _, ids in ticks] == [[0] * 3, [1] * 3, [2] * 3]


def test_node_status_once_a_second_on_the_clock() -> None:
    clock = FakeClock()
    driver = DronecanDriver([0, 1], node_id=11, clock=clock)
    sent: list[tuple[int, NodeStatus]] = []
    for tick in range(2000):  # 400 Hz for 5 s, with a 3 s stall in the middle
        clock.ns += 3_000_000_000 if tick == 1000 else 0
        frames = driver.tick_frames(tick, [0.1, 0.2]) if tick % 2 else driver.safe_frames(tick)
        for message in messages(frames):
            if isinstance(message, NodeStatus):
                sent.append((tick, message))
        clock.ns += 2_500_000
    ticks = [tick for tick, _ in sent]
    # First at the first tick, then every 400 ticks; after the stall at once, then a second on.
    assert ticks == [0, 400, 800, 1000, 1400, 1800]
    assert [status.uptime_s for _, status in sent] == [0, 1, 2, 5, 6, 7]
    assert all(s.health == wire.HEALTH_OK and s.mode == wire.MODE_OPERATIONAL for _, s in sent)
    frames = driver.safe_frames(2000)
    clock.ns += 10**9
    (status_frame,) = [f for f in driver.safe_frames(2001) if f.arbitration_id >> 8 & 0xFFFF == 341]
    assert status_frame.arbitration_id == 0x1F01550B  # priority 31, NodeStatus, node 11
    assert status_frame.data[-1] & 0x1F == 6  # its own transfer IDs


def test_refusals() -> None:
    with pytest.raises(ValueRangeError):
        DronecanDriver([])
    with pytest.raises(ValueRangeError):
        DronecanDriver([0, 20])
    with pytest.raises(ValueRangeError):
        DronecanDriver([1, 1])
    with pytest.raises(ValueRangeError):
        DronecanDriver([0, 1], reversible=[True])
    with pytest.raises(ValueRangeError):
        DronecanDriver([0], node_id=0)
    with pytest.raises(ValueError):
        DronecanDriver([0, 1], node_status=False).tick_frames(0, [0.5])


def test_the_output_loop_never_imports_dronecan() -> None:
    """The loop's process builds its driver from the config without the ``dronecan`` package
    (its import costs 0.3 s of CPU and its DSDL tables); only decoding imports it."""
    code = (
        "import sys\n"
        "import bridge.output.output_loop\n"
        "from bridge.config import build_config, with_esc_count\n"
        "config = with_esc_count(build_config({'output': {'protocol': 'dronecan'}}, 'x'), 8)\n"
        "config.family.driver(config.esc_setup).tick_frames(0, [0.5] * 8)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'dronecan'))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert result.stdout.strip() == "[]"


def test_an_inputs_frames_are_made_once_and_each_tick_writes_its_transfer_id() -> None:
    """``prepare`` makes the RawCommand's frames (three for eight ESCs); each tick that sends
    them reuses them and writes only its transfer ID: a decoder (the transfer CRC, the toggle
    bits) reads every tick's transfer whole, with its values and the next transfer ID."""
    fractions = [0.0, 0.125, 0.25, 0.5, 0.75, 0.875, 1.0, 0.3]
    driver = DronecanDriver(range(8), node_status=False)
    driver.prepare(fractions)
    made: list[can.Message] | None = None
    decoder = Decoder()
    for tick in range(3):
        frames = driver.tick_frames(tick, list(fractions))  # an equal list, not the same one
        if made is None:
            made = list(frames)
        assert len(frames) == 3 and all(a is b for a, b in zip(frames, made, strict=True))
        decoded = [d for d in (decoder.decode(m) for m in frames) if d is not None]
        whole = [(d.transfer_id, d.frames, d.message) for d in decoded]
        values = tuple(round(f * wire.COMMAND_MAX) for f in fractions)
        assert whole[-1] == (tick, 3, RawCommand(values))


def test_a_prepare_that_fails_leaves_no_frames_behind() -> None:
    """A vector of the wrong length raises, and the frames made before it are dropped: the
    tick makes its own again."""
    driver = DronecanDriver(range(4), node_status=False)
    driver.prepare([0.5] * 4)
    with pytest.raises(ValueError):
        driver.prepare([0.25] * 3)
    assert commands(driver.tick_frames(0, [1.0] * 4)) == (wire.COMMAND_MAX,) * 4
