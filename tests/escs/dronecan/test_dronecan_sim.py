"""Simulated DroneCAN ESCs (bridge/escs/dronecan/sim.py): driven with explicit clocks by the
bridge's own driver (read back with ``dronecan``), then on a real python-can ``virtual`` bus
under the simulator runner: slots, reverse, the 500 ms command timeout, Status and NodeStatus
cadence and contents, and each fault."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator

import can
import pytest

from bridge.errors import FrameError
from bridge.escs.dronecan import wire
from bridge.escs.dronecan.codec import (
    KELVIN_OFFSET,
    Decoder,
    DronecanFrame,
    EscStatus,
    NodeStatus,
    TransferPart,
)
from bridge.escs.dronecan.driver import DronecanDriver
from bridge.escs.dronecan.sim import (
    OVER_CURRENT_A,
    OVER_TEMPERATURE_C,
    SimDronecanEsc,
    make_escs,
)
from bridge.sim.motor import MotorParams
from bridge.sim.runner import Simulator

SUPPLY_V = 16.8
FULL_RPM = MotorParams().kv_rpm_per_v * SUPPLY_V
_channels = itertools.count()


def run(
    escs: list[SimDronecanEsc],
    driver: DronecanDriver | None,
    fractions: list[float],
    seconds: float,
    start_s: float = 0.0,
) -> list[tuple[float, can.Message]]:
    """Poll every ms and send the driver's frames every 2.5 ms (400 Hz) for ``seconds``; the
    frames the ESCs sent, timed."""
    out: list[tuple[float, can.Message]] = []
    for step in range(round(seconds * 1000)):
        now = start_s + step / 1000
        if driver is not None and step % 5 in (0, 2):  # 2.5 ms on average
            for msg in driver.tick_frames(step, fractions):
                for esc in escs:
                    esc.handle(msg, now)
        for esc in escs:
            out += [(now, m) for m in esc.poll(now, SUPPLY_V)]
    return out


def decoded(sent: list[tuple[float, can.Message]]) -> list[tuple[float, DronecanFrame]]:
    decoder = Decoder()
    frames = ((t, decoder.decode(m)) for t, m in sent)
    return [(t, f) for t, f in frames if f is not None and not isinstance(f.message, TransferPart)]


def test_escs_follow_their_slots_and_report() -> None:
    escs = make_escs([0, 1, 2, 3])
    driver = DronecanDriver([0, 1, 2, 3], node_status=False)
    sent = run(escs, driver, [0.2, 0.4, 0.6, 0.0], 1.0)
    assert [esc.command for esc in escs] == [1638, 3276, 4915, 0]
    # The runner knows each by its ESC number (index + 1), the bus by its node ID (20 + index).
    assert [(esc.node_id, esc.can_node_id) for esc in escs] == [(1, 20), (2, 21), (3, 22), (4, 23)]
    for esc, fraction in zip(escs, [0.2, 0.4, 0.6, 0.0], strict=True):
        assert esc.motor.rpm == pytest.approx(fraction * FULL_RPM, rel=0.01, abs=1)
        assert esc.stats.commands == 400 and esc.stats.bad_frames == 0
    statuses = [(t, f) for t, f in decoded(sent) if isinstance(f.message, EscStatus)]
    by_index = {i: [f for _, f in statuses if f.esc_index == i] for i in range(4)}
    assert all(len(frames) == 20 for frames in by_index.values())  # every 50 ms for 1 s
    last = by_index[2][-1]
    assert last.source_node == 22 and last.priority == 16
    status = last.message
    assert isinstance(status, EscStatus)
    assert status.rpm == pytest.approx(0.6 * FULL_RPM, rel=0.02)
    assert status.voltage_v == pytest.approx(SUPPLY_V, abs=0.02)
    assert status.power_rating_pct == 60 and status.error_count == 0
    assert status.temperature_c == pytest.approx(escs[2].motor.mos_temp_c, abs=0.5)
    node_statuses = [f for _, f in decoded(sent) if isinstance(f.message, NodeStatus)]
    assert len(node_statuses) == 4 and {f.esc_index for f in node_statuses} == {0, 1, 2, 3}
    assert all(f.message == NodeStatus(0, wire.HEALTH_OK, 0) for f in node_statuses)


def test_reverse_short_commands_and_timeout() -> None:
    forward, reverse, far = (
        SimDronecanEsc(0),
        SimDronecanEsc(1, reversible=True),
        SimDronecanEsc(5, can_node_id=99),
    )
    driver = DronecanDriver([0, 1], reversible=[True, True], node_status=False)
    run([forward, reverse, far], driver, [-0.5, -0.5], 0.6)
    assert forward.command == -4096 and forward.motor.rpm == pytest.approx(0.0, abs=1)
    assert reverse.motor.rpm == pytest.approx(-0.5 * FULL_RPM, rel=0.02)
    assert far.command is None and far.stats.commands == 0  # its slot is beyond the command
    assert reverse.commanded
    run([forward, reverse, far], None, [], 0.7, start_s=0.6)  # silence: released at +500 ms
    assert not reverse.commanded and reverse.stats.timeouts == 1
    assert abs(reverse.motor.rpm) < 0.1 * FULL_RPM


def test_faults() -> None:
    esc = SimDronecanEsc(0)
    esc.faults.over_temperature = True
    esc.faults.over_current = True
    (status, node) = [f.message for _, f in decoded(run([esc], None, [], 0.01))]
    assert isinstance(status, EscStatus) and isinstance(node, NodeStatus)
    assert status.temperature_k == pytest.approx(OVER_TEMPERATURE_C + KELVIN_OFFSET, abs=0.5)
    assert status.current_a == OVER_CURRENT_A and node.health == wire.HEALTH_ERROR
    esc = SimDronecanEsc(0)
    esc.faults.corrupt = True
    decoder = Decoder()
    errors = 0
    for _, msg in run([esc], None, [], 0.01):
        try:
            frame = decoder.decode(msg)
            assert frame is not None and isinstance(frame.message, TransferPart)
        except FrameError:
            errors += 1
    assert errors == 2  # the Status's CRC, the NodeStatus's tail byte
    esc = SimDronecanEsc(0)
    esc.faults.silent = True
    driver = DronecanDriver([0], node_status=False)
    assert run([esc], driver, [0.5], 0.3) == [] and esc.motor.rpm > 0.3 * FULL_RPM
    esc = SimDronecanEsc(0)
    esc.faults.stuck_motor = True
    run([esc], driver, [0.5], 0.3)
    assert esc.motor.rpm == 0.0 and esc.motor.current_a > 5.0


def test_broken_commands_count_as_errors() -> None:
    esc = SimDronecanEsc(0)
    frames = DronecanDriver(range(6), node_status=False).tick_frames(0, [0.5] * 6)
    esc.handle(frames[1], 0.0)  # a middle frame with no start
    (_, status), _ = decoded(run([esc], None, [], 0.001))
    assert isinstance(status.message, EscStatus) and status.message.error_count == 1


def test_refusals() -> None:
    with pytest.raises(ValueError):
        SimDronecanEsc(20)
    with pytest.raises(ValueError):
        SimDronecanEsc(0, can_node_id=126)
    with pytest.raises(ValueError):
        make_escs([0, 0])
    with pytest.raises(ValueError):
        make_escs([0, 1], reversible=[True])


@pytest.fixture
def buses() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    """(simulator's bus, test's bus) on a virtual channel of this test's own."""
    channel = f"dronecan-sim-{next(_channels)}"
    sim_bus = can.Bus(interface="virtual", channel=channel)
    test_bus = can.Bus(interface="virtual", channel=channel)
    yield sim_bus, test_bus
    test_bus.shutdown()
    sim_bus.shutdown()


def test_on_a_virtual_bus(buses: tuple[can.BusABC, can.BusABC]) -> None:
    """Eight ESCs (multi-frame RawCommand) under the runner, commanded at 400 Hz."""
    sim_bus, test_bus = buses
    escs = make_escs(range(8))
    driver = DronecanDriver(range(8), node_id=10)
    fractions = [0.1 * (i + 1) for i in range(8)]
    decoder = Decoder()
    frames: list[DronecanFrame] = []
    with Simulator(sim_bus, escs):
        start = time.monotonic()
        next_tick = start
        tick = 0
        while (now := time.monotonic()) < start + 1.0:
            if now >= next_tick:
                for msg in driver.tick_frames(tick, fractions):
                    test_bus.send(msg)
                tick += 1
                next_tick += 0.0025
            received = test_bus.recv(max(0.0, next_tick - time.monotonic()))
            if received is not None and (frame := decoder.decode(received)) is not None:
                frames.append(frame)
    assert decoder.errors == 0
    statuses = {f.message.esc_index: f.message for f in frames if isinstance(f.message, EscStatus)}
    assert sorted(statuses) == list(range(8))
    for index, status in statuses.items():
        assert status.rpm > 0.5 * fractions[index] * FULL_RPM
    assert all(esc.stats.commands > 100 and esc.stats.bad_frames == 0 for esc in escs)
    assert {f.esc_index for f in frames if isinstance(f.message, NodeStatus)} == set(range(8))
