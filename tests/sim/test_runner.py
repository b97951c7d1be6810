"""The simulator runner (bridge/sim/runner.py) on a real python-can ``virtual`` bus, and
``esc-bridge sim`` as a process of its own on udp_multicast, commanded by the test."""

from __future__ import annotations

import itertools
import logging
import re
import signal
import statistics
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest
from conftest import ESC_BRIDGE, MULTICAST_GROUP, Daemon, free_port, multicast_bus

from bridge.cli import main
from bridge.errors import CrcError
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.ckesc.keys import CkescKeys
from bridge.escs.ckesc.sim import SimCkesc
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.escs.ft.sim import TELEMETRY_PERIOD_S, SimFt
from bridge.sim.base import SimEsc
from bridge.sim.motor import Battery
from bridge.sim.runner import FAULT_KINDS, ScheduledFault, Simulator, make_escs

_channels = itertools.count()


@pytest.fixture
def buses() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    """(simulator's bus, test's bus) on a virtual channel of this test's own."""
    channel = f"sim-test-{next(_channels)}"
    sim_bus = can.Bus(interface="virtual", channel=channel)
    test_bus = can.Bus(interface="virtual", channel=channel)
    yield sim_bus, test_bus
    test_bus.shutdown()
    sim_bus.shutdown()


def drive(
    bus: can.BusABC,
    seconds: float,
    commands: Callable[[], list[can.Message]],
    every_s: float = 0.02,
) -> list[tuple[float, can.Message]]:
    """Send ``commands()`` every ``every_s`` for ``seconds``; every frame received, timed."""
    received: list[tuple[float, can.Message]] = []
    start = time.monotonic()
    next_send = start
    while (now := time.monotonic()) < start + seconds:
        if now >= next_send:
            for command in commands():
                bus.send(command)
            next_send += every_s
        msg = bus.recv(max(0.0, min(next_send, start + seconds) - time.monotonic()))
        if msg is not None:
            received.append((time.monotonic() - start, msg))
    return received


def ft_telemetry(
    received: list[tuple[float, can.Message]], kind: type[ft_records.FtTelemetry]
) -> dict[int, list[tuple[float, ft_records.FtTelemetry]]]:
    """Decoded FT telemetry of one kind, per ESC ID."""
    out: dict[int, list[tuple[float, ft_records.FtTelemetry]]] = {}
    for t, msg in received:
        frame = ft_codec.decode(msg)
        if frame is not None and isinstance(frame.message, kind):
            out.setdefault(frame.esc_id, []).append((t, frame.message))
    return out


def is_telemetry(msg: can.Message) -> bool:
    """An FT telemetry frame (the test's multicast bus also hears its own commands)."""
    return msg.arbitration_id & 0xFF in set(ft_records.Telemetry)


def duty(esc_id: int, value: float) -> can.Message:
    return ft_codec.encode(ft_records.FtFrame(esc_id, ft_records.SetDuty(value)))


class TimedFt(SimFt):
    """A real FT sim that records the ESCs' clock at each telemetry set it sends."""

    def __init__(self, esc_id: int) -> None:
        super().__init__(esc_id)
        self.sets_s: list[float] = []

    def poll(self, now_s: float, supply_v: float) -> list[can.Message]:
        frames = super().poll(now_s, supply_v)
        if frames:
            self.sets_s.append(now_s)
        return frames


def test_ft_escs_spin_up_after_a_duty_command(buses: tuple[can.BusABC, can.BusABC]) -> None:
    sim_bus, bus = buses
    escs = [TimedFt(1), TimedFt(2)]
    with Simulator(sim_bus, escs) as sim:
        received = drive(bus, 0.6, lambda: [duty(1, 0.3), duty(2, 0.6)])
    while (late := bus.recv(0)) is not None:  # sent before close, not yet read
        received.append((0.6, late))
    stats = sim.stats
    battery_v, battery_a = sim.battery.voltage_v, sim.battery.current_a
    data1 = ft_telemetry(received, ft_records.RealtimeData1)
    assert set(data1) == {1, 2}
    for esc_id, want in ((1, 0.3), (2, 0.6)):
        erpms = [m.erpm for _, m in data1[esc_id] if isinstance(m, ft_records.RealtimeData1)]
        sets_s = escs[esc_id - 1].sets_s
        assert len(erpms) == len(sets_s) <= 61  # every set sent received; 0.6 s at 100 Hz
        # 100 Hz on the ESC's own clock, each set at the first 1 ms poll it is due at: never
        # faster, and on time while its thread runs (one starved by a busy machine skips sets
        # rather than bursting them afterwards).
        intervals_s = [b - a for a, b in itertools.pairwise(sets_s)]
        assert len(intervals_s) <= (sets_s[-1] - sets_s[0]) / TELEMETRY_PERIOD_S + 1
        median_s = statistics.median(intervals_s)
        assert abs(median_s - TELEMETRY_PERIOD_S) < sim.poll_period_s
        assert erpms[0] < erpms[-1]
        full_erpm = 920 * battery_v * 7
        assert erpms[-1] == pytest.approx(want * full_erpm, rel=0.03)
    data2 = ft_telemetry(received, ft_records.RealtimeData2)[2][-1][1]
    assert isinstance(data2, ft_records.RealtimeData2)
    assert data2.battery_voltage_v == pytest.approx(battery_v, abs=0.05)
    # One battery feeds both: it carries their sum and sags under it.
    assert battery_a == pytest.approx(sum(e.motor.current_a for e in escs), rel=0.05)
    assert battery_a > 2.0
    assert battery_v < Battery().open_circuit_v - 0.02
    assert stats.frames_in >= 2 * 25
    assert stats.frames_out == sum(len(v) for v in data1.values()) * 3
    assert stats.send_failures == 0


def test_ft_telemetry_stops_when_commands_stop(buses: tuple[can.BusABC, can.BusABC]) -> None:
    sim_bus, bus = buses
    with Simulator(sim_bus, make_escs("ft", 1)):
        drive(bus, 0.1, lambda: [duty(1, 0.2)])
        quiet = drive(bus, 0.7, list)
    last = max(t for t, _ in quiet)
    assert last > 0.3  # it carries on for 450 ms after the last command (sent at ~0.08 s)...
    assert last < 0.55  # ... and then stops


class RecordingFt(SimFt):
    """A real FT sim that records the ESCs' clock at each of its polls, and the host's."""

    def __init__(self, esc_id: int) -> None:
        super().__init__(esc_id, idle_telemetry=True)
        self.polls: list[float] = []
        self.polls_host_s: list[float] = []

    def poll(self, now_s: float, supply_v: float) -> list[can.Message]:
        self.polls.append(now_s)
        self.polls_host_s.append(time.monotonic())
        return super().poll(now_s, supply_v)


def test_poll_schedule_is_steady_without_bursts(buses: tuple[can.BusABC, can.BusABC]) -> None:
    sim_bus, _ = buses
    esc = RecordingFt(1)
    sim = Simulator(sim_bus, [esc]).start()
    time.sleep(0.5)
    sim.close()
    stats = sim.stats
    # The slots of the 1 ms schedule up to the last poll (slot 0 at 0 s): counted there, not
    # when this thread reads the counters, which on a loaded machine may be long after.
    due = int(esc.polls[-1] / 0.001) + 1
    assert stats.polls == len(esc.polls)
    assert stats.polls <= due + 1  # never more polls than the schedule has slots
    assert abs(stats.polls + stats.late_polls - due) <= 1  # every slot polled or counted skipped
    assert stats.polls > 0.3 * due


class StallingFt(RecordingFt):
    """A real FT sim whose 50th poll takes 50 ms (a stalled machine)."""

    def poll(self, now_s: float, supply_v: float) -> list[can.Message]:
        frames = super().poll(now_s, supply_v)
        if len(self.polls) == 50:
            time.sleep(0.05)
        return frames


def test_after_a_stall_polls_resume_without_a_burst(buses: tuple[can.BusABC, can.BusABC]) -> None:
    sim_bus, _ = buses
    esc = StallingFt(1)
    before_start_s = time.monotonic()
    with Simulator(sim_bus, [esc]) as sim:
        after_start_s = time.monotonic()
        time.sleep(0.3)
    polls = esc.polls
    # The ESCs' clock starts at 0 (their power-up) when the simulator starts, however late its
    # thread first runs: each poll's clock is the host's time since then, read a moment before
    # the poll (by at least the least of those moments, as the thread can be preempted there).
    zeros_s = [host_s - clock_s for clock_s, host_s in zip(polls, esc.polls_host_s, strict=True)]
    assert before_start_s <= min(zeros_s) <= after_start_s + 0.001
    after = polls[50]
    assert after - polls[49] >= 0.05  # the stall, covered by one longer step
    assert len([t for t in polls if after < t <= after + 0.02]) <= 21  # not ~70 at once
    assert sim.stats.late_polls >= 40


def test_a_scheduled_fault_switches_on_at_its_time(buses: tuple[can.BusABC, can.BusABC]) -> None:
    sim_bus, bus = buses
    faults = [ScheduledFault(2, "silent", at_s=0.3), ScheduledFault(1, "corrupt", at_s=0.0)]
    with Simulator(sim_bus, make_escs("ft", 2), faults=faults) as sim:
        received = drive(bus, 0.6, lambda: [duty(1, 0.2), duty(2, 0.2)])
        assert sim.escs[1].faults.silent
        assert "2:silent" in sim.status_line()
    from_2 = [t for t, m in received if m.arbitration_id >> 8 == 2]
    assert from_2 and max(from_2) < 0.45
    from_1 = [m for _, m in received if m.arbitration_id >> 8 == 1]
    assert len(from_1) > 100
    for msg in from_1:
        with pytest.raises(CrcError):
            ft_codec.decode(msg)


def test_set_fault_acts_at_once(buses: tuple[can.BusABC, can.BusABC]) -> None:
    sim_bus, bus = buses
    with Simulator(sim_bus, make_escs("ft", 1)) as sim:
        drive(bus, 0.2, lambda: [duty(1, 0.5)])
        sim.set_fault(1, "stuck_motor")
        received = drive(bus, 0.2, lambda: [duty(1, 0.5)])
    last = ft_telemetry(received, ft_records.RealtimeData1)[1][-1][1]
    assert isinstance(last, ft_records.RealtimeData1) and last.erpm == 0


def test_send_failures_are_counted_not_fatal(buses: tuple[can.BusABC, can.BusABC]) -> None:
    sim_bus, _ = buses
    sim = Simulator(sim_bus, [SimFt(1, idle_telemetry=True)]).start()
    time.sleep(0.05)
    sim_bus.shutdown()  # the bus goes away under the simulator: sends and receives fail
    time.sleep(0.1)
    assert sim.running
    stats = sim.stats
    sim.close()
    assert stats.send_failures >= 15
    assert stats.recv_failures > 0
    assert sim.error is None
    assert not sim.running


def test_ckesc_escs_follow_their_throttle_channels(buses: tuple[can.BusABC, can.BusABC]) -> None:
    sim_bus, bus = buses
    escs = make_escs("ckesc", 2, [5, 6], keys=CkescKeys(ckesc_channels=(2, 1)))
    tids = itertools.count()
    with Simulator(sim_bus, escs):
        received = drive(
            bus, 0.6, lambda: [ckesc_codec.encode_raw_12b(1, [400, 1200], next(tids) % 32)], 0.01
        )
    speeds: dict[int, list[int]] = {}
    for _, msg in received:
        frame = ckesc_codec.decode(msg)
        if frame is not None and isinstance(frame.message, ckesc_records.Msg1):
            speeds.setdefault(frame.source_node, []).append(frame.message.speed_rpm)
    assert set(speeds) == {5, 6}
    for node, throttle in ((5, 1200), (6, 400)):  # node 5 is on channel 2, node 6 on 1
        assert speeds[node][0] < speeds[node][-1]
        assert speeds[node][-1] == pytest.approx(throttle / 2000 * 920 * 16.8, rel=0.05)


def test_make_escs_defaults_and_checks() -> None:
    fts = make_escs("ft", 3)
    assert [type(e) for e in fts] == [SimFt] * 3
    assert [e.node_id for e in fts] == [1, 2, 3]
    assert len({id(e.motor) for e in fts}) == 3  # a motor each
    cks: list[SimEsc] = make_escs("ckesc", 3)
    assert all(isinstance(e, SimCkesc) for e in cks)
    assert [(e.node_id, e.throttle_channel) for e in cks if isinstance(e, SimCkesc)] == [
        (1, 1),
        (2, 2),
        (3, 3),
    ]
    assert [e.node_id for e in make_escs("ft", 2, [0, 200])] == [0, 200]
    vescs = make_escs("vesc", 2, [0, 254])
    assert [(type(e).__name__, e.node_id) for e in vescs] == [("SimVesc", 0), ("SimVesc", 254)]
    bad: list[tuple[Callable[[], object], str]] = [
        (lambda: make_escs("ft", 0), "at least one"),
        (lambda: make_escs("ft", 2, [1]), "1 IDs for 2"),
        (lambda: make_escs("ft", 2, [4, 4]), "distinct"),
        (lambda: make_escs("ft", 1, [256]), "0..255"),
        (lambda: make_escs("ckesc", 1, [126]), "1..125"),
        (lambda: make_escs("vesc", 1, [255]), "0..254"),  # 255 addresses every VESC
        (lambda: make_escs("ckesc", 2, keys=CkescKeys(ckesc_channels=(1,))), "1 channels for 2"),
        (lambda: make_escs("dshot", 1), "'ckesc' or 'ft'"),
    ]
    for call, match in bad:
        with pytest.raises(ValueError, match=match):
            call()


def test_simulator_checks(buses: tuple[can.BusABC, can.BusABC]) -> None:
    sim_bus, _ = buses
    with pytest.raises(ValueError, match="no ESCs"):
        Simulator(sim_bus, [])
    with pytest.raises(ValueError, match="not distinct"):
        Simulator(sim_bus, [SimFt(1), SimFt(1)])
    with pytest.raises(ValueError, match="no ESC with node ID 9"):
        Simulator(sim_bus, [SimFt(1)], faults=[ScheduledFault(9, "silent")])
    with pytest.raises(ValueError, match="kind="):
        ScheduledFault(1, "melted")  # type: ignore[arg-type]
    sim = Simulator(sim_bus, [SimFt(1)])
    with pytest.raises(KeyError):
        sim.set_fault(2, "silent")
    sim.close()
    with pytest.raises(RuntimeError, match="already started or closed"):
        sim.start()


# -- esc-bridge sim --------------------------------------------------------------------------


def sim_args(port: int, *extra: str) -> list[str]:
    return [
        "sim",
        "--can-interface",
        "udp_multicast",
        "--can-channel",
        MULTICAST_GROUP,
        "--can-option",
        f"port={port}",
        "--can-option",
        "hop_limit=0",
        *extra,
    ]


def test_cli_sim_answers_every_esc_and_a_silent_one_stays_silent() -> None:
    port = free_port()
    bus = multicast_bus(port)
    flags = ["--protocol", "ft", "--ids", "4,5,6", "--fault", "1:silent"]
    proc = Daemon(sim_args(port, *flags, "--status-interval", "0.1"))
    try:
        seen: set[int] = set()
        deadline = time.monotonic() + 10.0
        while seen != {5, 6} and time.monotonic() < deadline:
            received = drive(bus, 0.2, lambda: [duty(i, 0.4) for i in (4, 5, 6)])
            seen |= {m.arbitration_id >> 8 for _, m in received if is_telemetry(m)}
            assert 4 not in seen  # motor 1 is ESC 4: silent
        assert seen == {5, 6}
        received = drive(bus, 0.5, lambda: [duty(i, 0.4) for i in (4, 5, 6)])
        data1 = ft_telemetry(received, ft_records.RealtimeData1)
        assert set(data1) == {5, 6}
        for esc_id in (5, 6):
            last = data1[esc_id][-1][1]
            assert isinstance(last, ft_records.RealtimeData1) and last.erpm > 10_000
    finally:
        code = proc.stop(signal.SIGTERM)
        bus.shutdown()
    assert code == 0, proc.output
    assert "3 ft ESCs (IDs 4,5,6)" in proc.output
    line = r"INFO esc-bridge sim t=[\d.]+s rpm 4:\d+ 5:\d+ 6:(\d+) \| battery "
    status = re.findall(line, proc.output)
    assert len(status) >= 3, proc.output  # every 0.1 s
    assert int(status[-1]) > 1000, proc.output
    assert "| faults 4:silent" in proc.output
    assert "Traceback" not in proc.output


def test_cli_sim_stops_after_its_duration() -> None:
    result = subprocess.run(
        [ESC_BRIDGE, *sim_args(free_port(), "--escs", "2", "--duration", "0.3")],
        capture_output=True,
        text=True,
        timeout=20,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert "2 ckesc ESCs (IDs 1,2)" in result.stderr


def test_cli_sim_ctrl_c_is_a_clean_exit() -> None:
    port = free_port()
    bus = multicast_bus(port)
    proc = Daemon(sim_args(port, "--escs", "1"))
    try:
        deadline = time.monotonic() + 10.0
        heard = None
        while heard is None and time.monotonic() < deadline:
            heard = bus.recv(0.1)  # a CKESC reports from power-up, commanded or not
        assert heard is not None and ckesc_codec.decode(heard) is not None
    finally:
        code = proc.stop(signal.SIGINT)
        bus.shutdown()
    assert code == 0, proc.output
    assert "stopped: t=" in proc.output


def test_cli_sim_bad_fault_is_a_usage_error() -> None:
    result = subprocess.run(
        [ESC_BRIDGE, *sim_args(free_port(), "--escs", "2", "--fault", "2:melted@1")],
        capture_output=True,
        text=True,
        timeout=20,
        check=False,
    )
    assert result.returncode == 2
    assert "argument --fault: expected MOTOR:KIND[@SECONDS]" in result.stderr
    assert "'2:melted@1'" in result.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--escs", "2", "--fault", "3:silent"], "--fault 3:silent: motor 3, but there are 2 ESCs"),
        (["--escs", "2", "--fault", "1"], "expected MOTOR:KIND[@SECONDS]"),
        (["--escs", "2", "--fault", "1:silent@soon"], "expected MOTOR:KIND[@SECONDS]"),
        (["--escs", "2", "--fault", "1:silent@-1"], "a time in seconds >= 0"),
        (["--escs", "0"], "argument --escs: expected a number of ESCs 1..125, got '0'"),
        (["--ids", "1,x"], "argument --ids: expected a comma-separated list of ESC IDs"),
        (["--ids", "1,1"], "--ids: expected a list of distinct integers 1..125"),
        (["--ids", "1,2", "--escs", "3"], "--ids: 2 IDs, but --escs 3"),
        (["--protocol", "kdecan", "--escs", "1"], "argument --protocol: invalid choice: 'kdecan'"),
        (["--escs", "1", "--bitrate", "3"], "--bitrate: expected a bit rate such as 500000, 500k"),
        (["--escs", "1", "--battery-cells", "15"], "expected a number of cells 1..14"),
        (["--escs", "1", "--duration", "0"], "expected a number of seconds > 0"),
        (["--escs", "1", "--can-option", "port"], "expected KEY=VALUE"),
        ([], "the ESCs are needed: --escs N or --ids"),
    ],
)
def test_cli_sim_bad_arguments(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    try:
        code = main(["sim", "--can-interface", "virtual", "--duration", "0.01", *args])
    except SystemExit as exc:
        code = int(exc.code or 0)
    assert code == 2
    assert message in capsys.readouterr().err


def test_cli_sim_bus_that_cannot_be_opened(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--can-interface", "socketcan", "--can-channel", "nocan9", "--bitrate", "250k"]
    code = main(["sim", "--escs", "1", *args])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("esc-bridge: cannot open CAN bus socketcan:nocan9")
    # What is missing, named by the channel given (this machine has no such interface).
    assert "(SocketCAN interface nocan9 does not exist; expected a CAN interface: " in err
    assert err.count("\n") == 1


def test_cli_sim_reads_a_config_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    config = tmp_path / "bridge.toml"
    config.write_text(
        '[can]\ninterface = "virtual"\nchannel = "sim-config"\n'
        '[output]\nprotocol = "ckesc"\n'
        "[escs]\nids = [7, 8]\nckesc_channels = [3, 4]\n"
    )
    caplog.set_level(logging.INFO, logger="bridge.sim")
    assert main(["sim", "--config", str(config), "--duration", "0.1"]) == 0
    assert "2 ckesc ESCs (IDs 7,8) on virtual sim-config" in caplog.text
    assert main(["sim", "--config", str(config), "--protocol", "ft", "--duration", "0.1"]) == 0
    assert "2 ft ESCs (IDs 7,8)" in caplog.text
    with pytest.raises(SystemExit) as exited:
        main(["sim", "--config", str(config), "--fault", "3:silent"])
    assert exited.value.code == 2
    assert "motor 3, but there are 2 ESCs" in capsys.readouterr().err


def test_fault_kinds_are_the_faults_fields() -> None:
    from dataclasses import fields

    from bridge.sim.base import Faults

    assert tuple(f.name for f in fields(Faults)) == FAULT_KINDS


@pytest.mark.parametrize(("n_escs", "accepted"), [(1, True), (2, False)])
def test_set_id_only_when_alone_on_the_runners_bus(
    buses: tuple[can.BusABC, can.BusABC], n_escs: int, accepted: bool
) -> None:
    """ESCs of one runner hear each other, as on a real bus: Set ID is refused with two."""
    sim_bus, test_bus = buses
    with Simulator(sim_bus, make_escs("ckesc", n_escs)) as sim:
        time.sleep(0.3)  # long enough for each ESC to have heard the other's telemetry
        request = ckesc_records.SetIdRequest(node_id=9, throttle_channel=7)
        test_bus.send(
            ckesc_codec.encode(
                ckesc_codec.CkescFrame(ckesc_codec.default_priority(request), 0, 1, 0, request)
            )
        )
        deadline = time.monotonic() + 2.0
        responses: list[ckesc_records.SetId] = []
        while time.monotonic() < deadline and not responses:
            msg = test_bus.recv(0.1)
            frame = ckesc_codec.decode(msg) if msg is not None else None
            if frame is not None and isinstance(frame.message, ckesc_records.SetIdResponse):
                responses.append(frame.message)
        escs = list(sim.escs)
    assert responses, "no Set ID response"
    answer = responses[0]
    if accepted:
        assert (answer.node_id, answer.throttle_channel) == (9, 7)
        assert escs[0].node_id == 9
    else:
        assert (answer.node_id, answer.throttle_channel) == (1, 1)  # the values in effect
        assert [esc.node_id for esc in escs] == [1, 2]
