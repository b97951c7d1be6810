"""``esc-bridge demo``: the simulated autopilot's flight profile, the bridge configuration the
demo writes, and the whole demo run headless through its console script."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import pytest
from conftest import phase_start
from pymavlink import mavutil

from bridge._compat import tomllib
from bridge.config import build_config
from bridge.daemon import preflight
from bridge.demo.system import (
    DemoOptions,
    DemoPorts,
    bridge_args,
    bridge_config,
    bridge_settings,
    toml_text,
)
from bridge.mavlink import load_dialect
from bridge.mixing.loader import load_mixer
from bridge.sim.autopilot import (
    AIRFRAMES,
    ARMED_PHASES,
    FLIGHT_S,
    LOOP_HZ,
    PHASES,
    PWM_HOVER_US,
    Airframe,
    SimAutopilot,
    motor_count,
    outputs_at,
)

ESC_BRIDGE = str(Path(sys.executable).parent / "esc-bridge")
STEP_S = 0.01
TIMES = [i * STEP_S for i in range(round(-1 / STEP_S), round((FLIGHT_S + 2) / STEP_S))]


def _peak(phase: str) -> float:
    """A quarter into the phase: where its first swing is largest."""
    duration = dict(PHASES)[phase]
    return phase_start(phase) + duration / 4


def _assert_sign(offset: float, wanted: float, what: str) -> None:
    """``offset`` (µs from hover) is clearly of the sign of ``wanted``, or ~0 when it is 0."""
    if abs(wanted) < 1e-6:
        assert abs(offset) <= 1, (what, offset)
    else:
        assert offset > 20 if wanted > 0 else offset < -20, (what, offset)


# -- the flight profile ---------------------------------------------------------------------


@pytest.mark.parametrize("airframe", AIRFRAMES)
def test_phases_come_in_order_and_arming_spans_arm_to_land(airframe: Airframe) -> None:
    seen: list[str] = []
    arm, disarm = phase_start("arm"), phase_start("disarm")
    for t in TIMES:
        phase, armed, pwm = outputs_at(t, airframe)
        if not seen or seen[-1] != phase:
            seen.append(phase)
        assert armed == (arm <= t < disarm), (t, phase)
        assert len(pwm) == motor_count(airframe)
        assert all(1000 <= v <= 2000 for v in pwm), (t, pwm)
        if armed:
            assert all(v >= 1100 for v in pwm), (t, pwm)  # armed motors keep spinning
        else:
            assert pwm == [1000] * len(pwm), (t, pwm)
    assert seen == [
        "preflight",
        "arm",
        "spool-up",
        "take-off",
        "hover",
        "roll",
        "pitch",
        "yaw",
        "descend",
        "land",
        "disarm",
    ]
    assert 25 <= FLIGHT_S <= 35


@pytest.mark.parametrize("airframe", AIRFRAMES)
def test_hover_holds_about_1590_us(airframe: Airframe) -> None:
    start = phase_start("hover")
    for t in (start + 0.1, start + 1.5, start + 2.9):
        phase, armed, pwm = outputs_at(t, airframe)
        assert (phase, armed) == ("hover", True)
        assert all(abs(v - PWM_HOVER_US) <= 10 for v in pwm), pwm
        assert sum(pwm) / len(pwm) == pytest.approx(PWM_HOVER_US, abs=3)


@pytest.mark.parametrize("airframe", AIRFRAMES)
def test_manoeuvres_are_differential_by_the_frames_geometry(airframe: Airframe) -> None:
    # Which motor is where, and its spin, from the bundled X mixers (ArduPilot's numbering).
    rotors = load_mixer(f"{airframe}-x").rotors
    assert len(rotors) == motor_count(airframe)

    def offsets(phase: str) -> list[float]:
        name, armed, pwm = outputs_at(_peak(phase), airframe)
        assert (name, armed) == (phase, True)
        assert sum(pwm) / len(pwm) == pytest.approx(PWM_HOVER_US, abs=2)  # collective kept
        return [v - PWM_HOVER_US for v in pwm]

    # Roll right first: the left motors (y < 0) speed up, the right ones slow down.
    for rotor, d in zip(rotors, offsets("roll"), strict=True):
        _assert_sign(d, -rotor.position_m[1], rotor.name)
    # Pitch nose down first: the rear motors (x < 0) speed up, the front ones slow down.
    for rotor, d in zip(rotors, offsets("pitch"), strict=True):
        _assert_sign(d, -rotor.position_m[0], rotor.name)
    # Yaw right first: the counter-clockwise motors speed up, the clockwise ones slow down.
    for rotor, d in zip(rotors, offsets("yaw"), strict=True):
        _assert_sign(d, 1 if rotor.direction == "CCW" else -1, rotor.name)
    # Then the other way.
    _, _, back = outputs_at(_peak("roll") + dict(PHASES)["roll"] / 2, airframe)
    _, _, there = outputs_at(_peak("roll"), airframe)
    assert [b - PWM_HOVER_US for b in back] == pytest.approx(
        [PWM_HOVER_US - v for v in there], abs=1
    )


def test_outputs_at_refuses_nonsense() -> None:
    with pytest.raises(ValueError, match="airframe"):
        outputs_at(1.0, "tricopter")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="finite"):
        outputs_at(float("nan"), "quad")


# -- the bridge's configuration ---------------------------------------------------------------


@pytest.mark.parametrize("protocol", ["ckesc", "ft", "dronecan", "vesc"])
@pytest.mark.parametrize("airframe", AIRFRAMES)
def test_the_bridge_configuration_is_valid_and_fits_the_bus(
    protocol: str, airframe: Airframe
) -> None:
    options = DemoOptions(protocol=protocol, airframe=airframe)
    ports = DemoPorts(14550, 43113, 7447)
    written = tomllib.loads(toml_text(bridge_settings(options, ports)))
    config = build_config(written, "demo.toml")
    assert config == build_config(bridge_settings(options, ports), "demo.toml")
    assert config.mavlink.url == "udpin:127.0.0.1:14550"
    assert config.can.options == {"port": 43113, "hop_limit": 0}
    assert config.zenoh.listen == ("tcp/127.0.0.1:7447",)
    assert (config.zenoh.vehicle, config.zenoh.multicast_scouting) == ("demo", False)
    planned = preflight.plan(bridge_config(options, ports))  # bus load, one ESC per output
    assert len(planned.mixer.outputs) == motor_count(airframe)


def test_the_bridge_records_the_flight_when_asked() -> None:
    assert bridge_args(Path("demo.toml")) == ["run", "--config", "demo.toml"]
    assert bridge_args(Path("demo.toml"), Path("flights")) == [
        "run",
        "--config",
        "demo.toml",
        "--record",
        "flights",
    ]
    # tests/plot/test_plot_cli.py records a whole demo flight this way and draws it.


# -- the demo, end to end ---------------------------------------------------------------------


def _processes_with(marker: str) -> list[int]:
    """PIDs of live processes whose environment carries ``marker``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            environ = (entry / "environ").read_bytes()
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if marker.encode() in environ and state != "Z":
            found.append(int(entry.name))
    return found


def _demo(*args: str, marker: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [ESC_BRIDGE, "demo", "--plain", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "ESC_BRIDGE_DEMO_TEST": marker},
    )


def _summary(output: str, escs: int) -> dict[int, tuple[int, str]]:
    """motor -> (max rpm, online) from the summary table at the end of the output."""
    rows = re.findall(r"^\s*(\d+)\s+(\d+)\s+(\d+|-)\s+(\d+|-)\s+(yes|no)$", output, re.M)
    table = {int(m): (int(rpm) if rpm != "-" else -1, online) for m, _, rpm, _, online in rows}
    assert sorted(table) == list(range(1, escs + 1)), output[-2000:]
    return table


@pytest.mark.parametrize(
    ("protocol", "extra"),
    [
        ("ckesc", []),
        ("ft", ["--duration", "10"]),
        ("dronecan", ["--duration", "10"]),
        ("vesc", ["--duration", "10"]),
    ],
    ids=["ckesc-one-flight", "ft-duration", "dronecan-duration", "vesc-duration"],
)
def test_demo_runs_headless_and_cleans_up(protocol: str, extra: list[str]) -> None:
    marker = uuid.uuid4().hex
    start = time.monotonic()
    proc = _demo("--protocol", protocol, "--time-scale", "4", *extra, marker=marker)
    try:
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    elapsed = time.monotonic() - start
    assert proc.returncode == 0, out[-3000:] + err
    assert "bridge exit status 0, sim exit status 0" in out
    if extra:
        assert "duration reached" in out and elapsed < 30
    else:
        assert "flight complete" in out
    # Plain tables once a second, with the flight's phases in the header.
    headers = re.findall(rf"^esc-bridge demo: {protocol} quad \(4 ESCs\) \| phase (\S+)", out, re.M)
    order = ["waiting", *(name for name, _ in PHASES)]
    ranks = [order.index(phase) for phase in headers]
    if not extra:  # one flight: the phases in order (with --duration the flight repeats)
        assert ranks == sorted(ranks), headers
    assert len(headers) >= 5 and len(set(headers) & ARMED_PHASES) >= 3, headers
    assert re.search(r"^\|\s+4 \|\s+4 \| online ", out, re.M), out[-3000:]
    for motor, (max_rpm, online) in _summary(out, 4).items():
        assert max_rpm > 1000 and online == "yes", (motor, max_rpm, online)
    assert _processes_with(marker) == []  # bridge, its loop process and sim all gone


def test_a_killed_demo_takes_its_children_with_it() -> None:
    """SIGKILL leaves the demo no time to stop its children: the kernel sends each SIGTERM
    (the bridge sends safe values and exits), none is left running alone."""
    marker = uuid.uuid4().hex
    proc = _demo(marker=marker)
    try:
        assert proc.stdout is not None
        for line in proc.stdout:  # the bridge is up (its signal handlers too) and reporting
            if "| online " in line:
                break
        assert len(_processes_with(marker)) >= 4  # the demo, bridge, its loop process, sim
        proc.kill()
        proc.communicate(timeout=10)
    finally:
        proc.kill()
    deadline = time.monotonic() + 20
    while (left := _processes_with(marker)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert left == []


def test_demo_reports_a_child_that_dies_and_stops_the_rest() -> None:
    marker = uuid.uuid4().hex
    proc = _demo(marker=marker)
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        sim_pid = int(re.findall(r"sim pid (\d+)", first)[0])
        for line in proc.stdout:  # the bridge is up (its signal handlers too) and reporting
            if "| online " in line:
                break
        os.kill(sim_pid, signal.SIGKILL)
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 1, out + err
    assert "the sim (esc-bridge sim) exited early with status -9" in err, err
    assert "failed after" in out and "bridge exit status 0" in out, out[-1000:]
    assert _processes_with(marker) == []


# -- the simulated autopilot on the wire -----------------------------------------------------


def test_the_sim_autopilot_answers_stream_requests_as_arducopter_does() -> None:
    """ACCEPTED and streamed at the rate asked up to its loop rate; DENIED above it."""
    dialect: Any = load_dialect()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    bridge = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{port}", source_system=1, source_component=191, dialect="ardupilotmega"
    )
    codec: Any = dialect.MAVLink(bridge, srcSystem=1, srcComponent=191)
    codec.robust_parsing = True

    def receive(seconds: float) -> list[tuple[float, Any]]:
        got: list[tuple[float, Any]] = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            bridge.select(0.01)
            if data := bridge.recv(4096):
                got += [(time.monotonic(), m) for m in codec.parse_buffer(data) or []]
        return got

    def ask(msg_id: int, rate_hz: float) -> int:
        codec.send(
            codec.command_long_encode(
                1, 1, dialect.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, 1e6 / rate_hz, 0, 0, 0, 0, 0
            )
        )
        acks = [m for _, m in receive(0.5) if m.get_type() == "COMMAND_ACK"]
        assert len(acks) == 1 and acks[0].target_component == 191, acks
        return int(acks[0].result)

    def rate(kind: str) -> float:
        times = [t for t, m in receive(1.0) if m.get_type() == kind]
        return (len(times) - 1) / (times[-1] - times[0])

    with SimAutopilot(port) as pilot:
        receive(0.3)  # its first datagram tells the udpin side where it is
        assert rate("SERVO_OUTPUT_RAW") == pytest.approx(50, rel=0.2)
        assert ask(dialect.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, LOOP_HZ * 2) == (
            dialect.MAV_RESULT_DENIED
        )
        assert ask(dialect.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, 200) == dialect.MAV_RESULT_ACCEPTED
        assert ask(dialect.MAVLINK_MSG_ID_HEARTBEAT, 20) == dialect.MAV_RESULT_ACCEPTED
        assert ask(dialect.MAVLINK_MSG_ID_ESC_INFO, 1) == dialect.MAV_RESULT_UNSUPPORTED
        assert (pilot.servo_hz, pilot.heartbeat_hz) == (200, 20)
        assert rate("SERVO_OUTPUT_RAW") > 150  # a busy machine may hold a send off
        assert rate("HEARTBEAT") == pytest.approx(20, rel=0.25)
    bridge.close()
