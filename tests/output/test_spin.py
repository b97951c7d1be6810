"""`esc-bridge esc spin`: its plan and ramp, and the command through the console script against
simulated ESCs (bridge.sim) on a cross-process udp_multicast bus, watched by a python-can
observer."""

from __future__ import annotations

import itertools
import math
import re
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from conftest import ESC_BRIDGE, Observer, can_args, multicast_bus

from bridge.config import build_config
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.escs.vesc import codec as vesc_codec
from bridge.escs.vesc import records as vesc_records
from bridge.output.motor_test import SpinRequest
from bridge.output.spin import plan_spin
from bridge.sim.runner import Simulator, make_escs


def test_spin_requests_are_checked() -> None:
    for motor, throttle, seconds in ((0, 10, 2), (1, 101, 2), (1, math.nan, 2), (1, 10, 31)):
        with pytest.raises(ValueError, match="expected"):
            SpinRequest(motor, throttle, seconds)
    config = build_config({"mixer": {"name": "hex-x"}}, "test")
    plan = plan_spin(config, SpinRequest(6, 40, 1))
    assert (plan.index, plan.esc_id, plan.fraction, plan.ramp_s) == (5, 6, 0.4, 0.25)


# -- esc spin against simulated ESCs ----------------------------------------------------------


@pytest.fixture
def bus_args(can_port: int) -> list[str]:
    return can_args(can_port)


def simulator(can_port: int, protocol: str, ids: list[int]) -> Simulator:
    escs = make_escs(protocol, len(ids), ids)
    return Simulator(multicast_bus(can_port), escs, own_bus=True).start()


@pytest.fixture
def ckesc_sim(can_port: int) -> Iterator[Simulator]:
    sim = simulator(can_port, "ckesc", [1, 2, 3, 4])
    yield sim
    sim.close()


_STARTED: list[subprocess.Popen[str]] = []


def spin(*args: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [ESC_BRIDGE, "esc", "spin", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    _STARTED.append(proc)
    return proc


@pytest.fixture(autouse=True)
def _no_spin_left_running() -> Iterator[None]:
    """A spin a failed test left running (one that hung past its wait) is killed with it."""
    yield
    while _STARTED:
        proc = _STARTED.pop()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def throttles(msg: can.Message) -> tuple[int, ...] | None:
    frame = ckesc_codec.decode(msg)
    if frame is None or not isinstance(frame.message, ckesc_records.RawCommand12b):
        return None
    return frame.message.throttles


def test_ckesc_spin_ramps_holds_stops_in_time_and_ends_safe(
    observer: Observer, ckesc_sim: Simulator, bus_args: list[str]
) -> None:
    proc = spin(
        "--motor", "2", "--throttle", "30", "--seconds", "1.5", "--props-removed", *bus_args
    )
    observer.wait_for(lambda m: throttles(m) == (0, 600, 0, 0), 10.0)
    time.sleep(0.3)  # holding: only motor 2 turns
    rpm = [esc.motor.rpm for esc in ckesc_sim.escs]
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "motor 2 stopped, safe values sent: done" in out
    # Its ESC answered: MSG1 at 50 Hz for about 1.7 s, the last after the spin's ramp down.
    heard = re.search(r"; (\d+) telemetry frames from its ESC, last rpm (\d+)\n", out)
    assert heard is not None, out
    assert int(heard[1]) >= 20
    time.sleep(0.2)
    assert rpm[1] > 1000 and rpm[0] == rpm[2] == rpm[3] == 0

    sent = [(m.timestamp, t) for _, m in observer.frames if (t := throttles(m)) is not None]
    assert {(t[0], t[2], t[3]) for _, t in sent} == {(0, 0, 0)}  # the others: safe throughout
    motor2 = [t[1] for _, t in sent]
    peak = motor2.index(600)
    last = max(i for i, v in enumerate(motor2) if v)
    assert motor2[0] < 20  # starts from stopped...
    assert motor2[:peak] == sorted(motor2[:peak]) and peak >= 100  # ...up over 0.5 s at 400 Hz
    hold = [i for i, v in enumerate(motor2) if v == 600]
    assert len(hold) >= 0.4 * 400  # held for the middle of the spin
    assert motor2[hold[-1] : last + 1] == sorted(motor2[hold[-1] : last + 1], reverse=True)
    assert sent[last][0] - sent[0][0] <= 1.5 + 0.02  # the hard time limit
    safe = motor2[last + 1 :]
    assert safe == [0] * len(safe) and 60 <= len(safe) <= 100  # 200 ms of safe values


def test_ft_spin_commands_one_esc_in_its_mode_and_brakes_the_others(
    observer: Observer, can_port: int, bus_args: list[str], tmp_path: Path
) -> None:
    config = tmp_path / "ft.toml"
    config.write_text(
        '[output]\nprotocol = "ft"\n[escs]\nids = [21, 22, 23, 24]\nft_mode = "current"\n'
        "ft_max_current_a = 10.0\nft_brake_current_a = 2.0\n"
    )
    sim = simulator(can_port, "ft", [21, 22, 23, 24])
    try:
        proc = spin(
            "--config", str(config), "--motor", "3", "--throttle", "40", "--seconds", "1.2",
            "--props-removed", *bus_args,
        )  # fmt: skip
        observer.wait_for(lambda m: ft_current(m) == (23, 4.0), 10.0)
        time.sleep(0.2)  # holding: only motor 3 turns
        rpm = [esc.motor.rpm for esc in sim.escs]
        out, err = proc.communicate(timeout=10)
    finally:
        sim.close()
    assert proc.returncode == 0, err
    assert "(FT ESC 23, current mode)" in out and "FT current 4.00 A" in out
    assert rpm[2] > 1000 and rpm[0] == rpm[1] == rpm[3] == 0
    time.sleep(0.2)
    telemetry = (
        ft_records.RealtimeData0,
        ft_records.RealtimeData1,
        ft_records.RealtimeData2,
    )  # from the simulator
    commands = [
        (f.esc_id, f.message)
        for _, m in observer.frames
        if (f := ft_codec.decode(m)) is not None and not isinstance(f.message, telemetry)
    ]
    spun = [
        m.current_a for esc, m in commands if esc == 23 and isinstance(m, ft_records.SetCurrent)
    ]
    assert max(spun) == pytest.approx(4.0) and spun[0] < 0.5 and spun[-1] < 0.5  # the ramps
    others = {(esc, type(m), getattr(m, "current_a", None)) for esc, m in commands if esc != 23}
    assert others == {(esc, ft_records.SetCurrentBrake, 2.0) for esc in (21, 22, 24)}
    last = max(i for i, (esc, m) in enumerate(commands) if isinstance(m, ft_records.SetCurrent))
    flush = commands[last + 1 :]  # the safe values: the brake, for every ESC
    assert {(esc, type(m)) for esc, m in flush} == {
        (e, ft_records.SetCurrentBrake) for e in (21, 22, 23, 24)
    }
    assert 60 <= len(flush) <= 100  # 200 ms at 4 x 100 frames/s


def test_vesc_spin_commands_one_vesc_in_duty_and_releases_the_others(
    observer: Observer, can_port: int, bus_args: list[str], tmp_path: Path
) -> None:
    config = tmp_path / "vesc.toml"
    config.write_text('[output]\nprotocol = "vesc"\n[escs]\nids = [21, 22, 23, 24]\n')
    sim = simulator(can_port, "vesc", [21, 22, 23, 24])
    try:
        proc = spin(
            "--config", str(config), "--motor", "2", "--throttle", "30", "--seconds", "1.2",
            "--props-removed", *bus_args,
        )  # fmt: skip
        observer.wait_for(lambda m: vesc_command(m) == (22, vesc_records.SetDuty(0.285)), 10.0)
        time.sleep(0.2)  # holding: only motor 2 turns
        rpm = [esc.motor.rpm for esc in sim.escs]
        out, err = proc.communicate(timeout=10)
    finally:
        sim.close()
    assert proc.returncode == 0, err
    assert "(VESC 22, duty mode)" in out and "VESC duty 0.285" in out
    assert rpm[1] > 1000 and rpm[0] == rpm[2] == rpm[3] == 0
    time.sleep(0.2)
    commands = [c for _, m in observer.frames if (c := vesc_command(m)) is not None]
    spun = [m.duty for esc, m in commands if isinstance(m, vesc_records.SetDuty)]
    assert {esc for esc, m in commands if isinstance(m, vesc_records.SetDuty)} == {22}
    assert max(spun) == pytest.approx(0.285) and spun[0] < 0.05 and spun[-1] < 0.05  # ramps
    released = vesc_records.SetCurrent(0.0)  # the safe value: the motor released
    assert {(esc, m) for esc, m in commands if esc != 22} == {(e, released) for e in (21, 23, 24)}
    last = max(i for i, (_, m) in enumerate(commands) if isinstance(m, vesc_records.SetDuty))
    flush = commands[last + 1 :]
    assert set(flush) == {(e, released) for e in (21, 22, 23, 24)}
    assert 120 <= len(flush) <= 200  # 200 ms at 4 x 200 frames/s


def vesc_command(msg: can.Message) -> tuple[int, vesc_records.VescMessage] | None:
    frame = vesc_codec.decode(msg)
    if frame is None or not isinstance(
        frame.message, vesc_records.SetDuty | vesc_records.SetCurrent
    ):
        return None
    return frame.controller_id, frame.message


def test_ft_spin_with_no_ft_esc_says_nothing_answered(
    observer: Observer, ckesc_sim: Simulator, bus_args: list[str]
) -> None:
    # CKESCs on the bus, commands sent as FT: the frames go out, no FT ESC answers.
    proc = spin(
        "--protocol", "ft", "--motor", "1", "--throttle", "10", "--seconds", "1",
        "--props-removed", "--bitrate", "1M", *bus_args,
    )  # fmt: skip
    out, err = proc.communicate(timeout=15)
    assert proc.returncode == 1, out + err
    assert "motor 1 stopped, safe values sent: no answer after " in out
    assert "; 0 telemetry frames from its ESC\n" in out and "done" not in out
    assert err == (
        "esc-bridge: error: nothing answered: no telemetry from motor 1's ESC (FT ESC 1, current "
        "mode) on "
        "udp_multicast 239.74.163.2 at 1000000 bit/s (1 Mbit/s) during the spin; is the ESC "
        "powered and wired, is its ID the one in [escs] ids, does it run at that bit rate and "
        "take CAN commands (docs/troubleshooting.md)?\n"
    )
    sent = [c for _, m in observer.frames if (c := ft_current(m)) is not None]
    assert max(current for _, current in sent) > 0  # the FT commands did go out


def ft_current(msg: can.Message) -> tuple[int, float] | None:
    frame = ft_codec.decode(msg)
    if frame is None or not isinstance(frame.message, ft_records.SetCurrent):
        return None
    return frame.esc_id, frame.message.current_a


def test_sigint_mid_spin_sends_safe_values_then_exits(
    observer: Observer, ckesc_sim: Simulator, bus_args: list[str]
) -> None:
    proc = spin("--motor", "4", "--throttle", "20", "--seconds", "10", "--props-removed", *bus_args)
    observer.wait_for(lambda m: throttles(m) == (0, 0, 0, 400), 10.0)
    assert ckesc_sim.escs[3].motor.rpm > 0
    proc.send_signal(signal.SIGINT)
    signalled = time.monotonic()
    out, err = proc.communicate(timeout=5)
    assert proc.returncode == 130, err
    # The safe values go out at once (below); the exit follows the flush, and on a loaded
    # machine (load 11 seen) the interpreter's teardown takes its time.
    assert time.monotonic() - signalled < 3.0
    assert "motor 4 stopped, safe values sent: interrupted" in out
    time.sleep(0.2)
    first_safe, _ = observer.wait_for(lambda m: throttles(m) == (0, 0, 0, 0), 1.0, signalled)
    assert first_safe - signalled < 0.1
    after = [t for m in observer.since(first_safe) if (t := throttles(m)) is not None]
    assert set(after) == {(0, 0, 0, 0)} and len(after) >= 60


def test_a_storm_of_signals_mid_spin_still_ends_in_safe_values(
    observer: Observer, ckesc_sim: Simulator, bus_args: list[str], tmp_path: Path
) -> None:
    """SIGINT and SIGTERM as fast as this process sends them for 0.3 s (repeated Ctrl-C): the
    spin ends once, safe values follow, exit status 130. A handler that set the Event the spin
    waits on could wait for good for the Event's lock, held by the main thread it interrupted.
    The flush lasts 1 s, so the storm is over before the spin gives the signals their default
    action back."""
    config = tmp_path / "spin.toml"
    config.write_text("[output]\nshutdown_flush_ms = 1000\n", encoding="utf-8")
    proc = spin(
        "--motor", "4", "--throttle", "20", "--seconds", "10", "--props-removed",
        "--config", str(config), *bus_args,
    )  # fmt: skip
    observer.wait_for(lambda m: throttles(m) == (0, 0, 0, 400), 10.0)
    signalled = time.monotonic()
    signals = itertools.cycle([signal.SIGINT, signal.SIGTERM])
    while time.monotonic() - signalled < 0.3:
        proc.send_signal(next(signals))
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 130, err
    assert "motor 4 stopped, safe values sent: interrupted" in out
    time.sleep(0.2)
    first_safe, _ = observer.wait_for(lambda m: throttles(m) == (0, 0, 0, 0), 1.0, signalled)
    after = [t for m in observer.since(first_safe) if (t := throttles(m)) is not None]
    assert set(after) == {(0, 0, 0, 0)}


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--motor", "1", "--throttle", "10", "--seconds", "2"], "without --props-removed"),
        (["--motor", "1", "--throttle", "150", "--seconds", "2", "--props-removed"], "--throttle"),
        (["--motor", "1", "--throttle", "-1", "--seconds", "2", "--props-removed"], "--throttle"),
        (["--motor", "1", "--throttle", "nan", "--seconds", "2", "--props-removed"], "--throttle"),
        (["--motor", "0", "--throttle", "10", "--seconds", "2", "--props-removed"], "--motor"),
        (["--motor", "5", "--throttle", "10", "--seconds", "2", "--props-removed"], "--motor 5"),
        (["--motor", "1", "--throttle", "10", "--seconds", "31", "--props-removed"], "--seconds"),
        (["--motor", "1", "--throttle", "10", "--seconds", "0.5", "--props-removed"], "--seconds"),
    ],
    ids=["no-props-removed", "throttle-150", "throttle-neg", "throttle-nan", "motor-0",
         "motor-5", "seconds-31", "seconds-0.5"],
)  # fmt: skip
def test_refused_before_anything_is_sent(
    observer: Observer, bus_args: list[str], args: list[str], message: str
) -> None:
    proc = spin(*args, *bus_args)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == 2
    assert message in err and "Traceback" not in err
    time.sleep(0.2)
    assert observer.frames == []
