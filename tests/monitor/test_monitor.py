"""`esc-bridge monitor` through the real console script: from the CAN bus (udp_multicast) while
this test plays the ESCs, and from Zenoh while this test plays the bridge. Piped stdout makes
the monitor print a plain-text table every second and a final one, which these tests read."""

from __future__ import annotations

import json
import math
import os
import re
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import pytest
import zenoh
from conftest import ESC_BRIDGE, MULTICAST_GROUP, can_args, free_port, multicast_bus

from bridge.cli import main
from bridge.config import ZenohConfig
from bridge.errors import PayloadError
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.dronecan import codec as dronecan_codec
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.escs.vesc import codec as vesc_codec
from bridge.escs.vesc import records as vesc_records
from bridge.monitor import (
    VehicleState,
    failure_names,
    monitor_zenoh_config,
    plain_text,
    prefix_of,
)
from bridge.monitor.view import EscRow
from bridge.telemetry.payload import EscInfoPayload, EscStatusPayload, EscTelemetryPayload

Row = dict[str, str]


# -- reading the monitor's plain-text tables -------------------------------------------------


def tables(output: str) -> list[tuple[str, list[Row]]]:
    """Every table printed: (title line, rows as {header: cell})."""
    found = []
    for block in output.split("\n\n"):
        lines = [line for line in block.strip("\n").splitlines() if line]
        grid = [line for line in lines if line.startswith("|") and not line.startswith("|-")]
        if not grid:
            continue
        header = [cell.strip() for cell in grid[0].strip("|").split("|")]
        rows = [
            dict(zip(header, (cell.strip() for cell in line.strip("|").split("|")), strict=True))
            for line in grid[1:]
        ]
        found.append((lines[0], rows))
    return found


def by_motor(rows: list[Row], vehicle: str | None = None) -> dict[int, Row]:
    return {
        int(row["motor"]): row
        for row in rows
        if vehicle is None or row["vehicle"].split(" ")[0] == vehicle
    }


def monitor(*args: str, timeout_s: float = 20.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [ESC_BRIDGE, "monitor", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )


# -- playing the ESCs ------------------------------------------------------------------------

# CKESC node -> (rpm, throttle 0..2000, status, volts, amps, MOS, capacitor, motor, MCU °C)
CKESC_ESCS = {
    # ESC 1 reports "no command" (its comms fault), as every CKESC does with no bridge running.
    1: (1100, 500, ckesc_records.Msg1Status.COMMS_FAULT, 24.25, 2.5, 41, 31, 51, 46),
    2: (
        1200,
        1000,
        ckesc_records.Msg1Status.RUNNING | ckesc_records.Msg1Status.OVER_TEMPERATURE,
        24.5,
        5.0,
        42,
        32,
        52,
        47,
    ),
    3: (1300, 1500, ckesc_records.Msg1Status.UNDER_VOLTAGE, 24.75, 7.5, 43, 33, 53, 48),
}
# FT ESC ID -> (erpm, duty, battery A, motor A, MOSFET °C, motor °C, volts)
FT_ESCS = {
    1: (7000, 0.1, 1.5, 11.0, 36.0, 61.0, 48.1),
    2: (14000, 0.2, 3.0, 12.0, 37.0, 62.0, 48.2),
    3: (-21000, -0.3, 4.5, 13.0, 38.0, 120.0, 48.3),
}
# DroneCAN ESC number -> (rpm, power %, volts, amps, temperature °C, NodeStatus health); the
# ESC number is esc_index + 1, its node ID 40 + the number.
DRONECAN_ESCS = {
    1: (1500, 20, 24.25, 2.5, 35.0, 0),
    2: (-2500, 40, 24.5, 5.0, 110.0, 0),
    3: (3500, 60, 24.75, 7.5, 37.0, 3),
}
_dronecan_senders = {number: dronecan_codec.Sender(40 + number) for number in DRONECAN_ESCS}
# VESC ID -> (erpm, motor A, duty, MOSFET °C, motor °C, input A, volts); VESC 3 regenerates.
VESC_ESCS = {
    1: (7000, 11.0, 0.1, 36.0, 61.0, 1.5, 48.1),
    2: (14000, 12.0, 0.2, 37.0, 62.0, 3.0, 48.2),
    3: (21000, -13.0, 0.3, 38.0, 120.0, -4.5, 48.3),
}


def ckesc_frames(transfer_id: int) -> list[can.Message]:
    frames = []
    for node, (rpm, thr, status, volts, amps, mos, cap, motor, mcu) in CKESC_ESCS.items():
        for message in (
            ckesc_records.Msg1(rpm, thr, status),
            ckesc_records.Msg2(volts, amps, mos),
            ckesc_records.Msg3(mos, cap, motor, mcu),
        ):
            priority = ckesc_codec.default_priority(message)
            frame = ckesc_codec.CkescFrame(priority, node, None, transfer_id, message)
            frames.append(ckesc_codec.encode(frame))
    return frames


def ft_frames(transfer_id: int) -> list[can.Message]:
    frames = []
    for esc_id, (erpm, duty, battery_a, motor_a, mos, motor, volts) in FT_ESCS.items():
        for message in (
            ft_records.RealtimeData0(motor_a, battery_a),
            ft_records.RealtimeData1(erpm, duty),
            ft_records.RealtimeData2(mos, motor, volts),
        ):
            frames.append(ft_codec.encode(ft_records.FtFrame(esc_id, message)))
    return frames


def dronecan_frames(transfer_id: int) -> list[can.Message]:
    frames = []
    for number, (rpm, power, volts, amps, temp_c, health) in DRONECAN_ESCS.items():
        sender = _dronecan_senders[number]
        status = dronecan_codec.EscStatus(
            number - 1, 0, volts, amps, temp_c + dronecan_codec.KELVIN_OFFSET, rpm, power
        )
        frames += sender.frames(status)
        if transfer_id % 10 == 0:
            frames += sender.frames(dronecan_codec.NodeStatus(transfer_id, health, 0))
    return frames


def vesc_frames(transfer_id: int) -> list[can.Message]:
    frames = []
    for controller_id, (erpm, motor_a, duty, mos, motor, input_a, volts) in VESC_ESCS.items():
        for message in (
            vesc_records.Status(erpm, motor_a, duty),
            vesc_records.Status4(mos, motor, input_a, 0.0),
            vesc_records.Status5(transfer_id, volts),
        ):
            frames.append(vesc_codec.encode(vesc_records.VescFrame(controller_id, message)))
    return frames


class EscPlayer:
    """Sends telemetry on a udp_multicast bus every 20 ms, in a thread, until closed."""

    def __init__(self, port: int, frames: Callable[[int], list[can.Message]]) -> None:
        self._bus = multicast_bus(port)
        self._frames = frames
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="esc-player", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        transfer_id = 0
        while not self._stop.wait(0.02):
            for msg in self._frames(transfer_id):
                self._bus.send(msg)
            transfer_id = (transfer_id + 1) % 32

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._bus.shutdown()


@pytest.fixture
def can_port() -> int:
    return free_port()


@pytest.fixture
def player(can_port: int, request: pytest.FixtureRequest) -> Iterator[EscPlayer]:
    frames = {
        "ckesc": ckesc_frames,
        "ft": ft_frames,
        "dronecan": dronecan_frames,
        "vesc": vesc_frames,
    }[request.param]
    esc_player = EscPlayer(can_port, frames)
    yield esc_player
    esc_player.close()


# -- from the CAN bus ------------------------------------------------------------------------


@pytest.mark.parametrize("player", ["ckesc"], indirect=True)
def test_ckesc_from_the_bus(can_port: int, player: EscPlayer) -> None:
    result = monitor(*can_args(can_port), "--protocol", "ckesc", "--escs", "4", "--duration", "1.5")
    assert result.returncode == 0, result.stderr
    title, rows = tables(result.stdout)[-1]
    assert title == f"udp_multicast:{MULTICAST_GROUP}: 3/4 ESCs online"
    motors = by_motor(rows)
    for node, (rpm, thr, _, volts, amps, mos, cap, motor, mcu) in CKESC_ESCS.items():
        row = motors[node]
        assert row["node"] == str(node)
        assert row["state"] == "online"
        assert row["rpm"] == str(rpm)
        assert row["V"] == f"{volts:.2f}"
        assert row["A"] == f"{amps:.2f}"
        assert (row["MOS°C"], row["cap°C"], row["motor°C"], row["MCU°C"]) == tuple(
            str(t) for t in (mos, cap, motor, mcu)
        )
        assert row["thr%"] == str(thr // 20)
        assert int(row["frames"]) > 10 and row["errors"] == "0"
    assert motors[1]["flags"] == ""  # listening, "no command" is an idle ESC, not a failure
    assert motors[2]["flags"] == "overtemp"
    assert motors[3]["flags"] == "generic"  # under-voltage has no MAVLink bit of its own
    silent = motors[4]
    assert (silent["state"], silent["rpm"], silent["V"], silent["age"]) == (
        "offline",
        "-",
        "-",
        "-",
    )
    assert result.stdout.endswith("\n")
    assert "frames read, 0 malformed" in result.stdout


@pytest.mark.parametrize("player", ["ft"], indirect=True)
def test_ft_from_the_bus(can_port: int, player: EscPlayer) -> None:
    result = monitor(
        *can_args(can_port),
        "--protocol",
        "ft",
        "--ids",
        "1,2,3,4",
        "--pole-pairs",
        "14",
        "--bitrate",
        "500000",
        "--duration",
        "1.5",
    )
    assert result.returncode == 0, result.stderr
    _, rows = tables(result.stdout)[-1]
    motors = by_motor(rows)
    for esc_id, (erpm, duty, battery_a, _, mos, motor, volts) in FT_ESCS.items():
        row = motors[esc_id]
        assert row["state"] == "online"
        assert row["rpm"] == str(int(erpm / 14))
        assert row["V"] == f"{volts:.2f}"
        assert row["A"] == f"{battery_a:.2f}"
        assert (row["MOS°C"], row["motor°C"]) == (f"{mos:.0f}", f"{motor:.0f}")
        assert (row["cap°C"], row["MCU°C"]) == ("-", "-")  # FT reports neither
        assert row["thr%"] == f"{duty * 100:.0f}"
    assert motors[3]["rpm"] == "-1500"
    assert motors[3]["flags"] == "overtemp"  # 120 °C motor: above [telemetry] max_temp_c
    assert motors[4]["state"] == "offline"


@pytest.mark.parametrize("player", ["dronecan"], indirect=True)
def test_dronecan_from_the_bus(can_port: int, player: EscPlayer) -> None:
    result = monitor(
        *can_args(can_port), "--protocol", "dronecan", "--escs", "4", "--duration", "1.5"
    )
    assert result.returncode == 0, result.stderr
    title, rows = tables(result.stdout)[-1]
    assert title == f"udp_multicast:{MULTICAST_GROUP}: 3/4 ESCs online"
    motors = by_motor(rows)
    for number, (rpm, power, volts, amps, temp_c, _) in DRONECAN_ESCS.items():
        row = motors[number]
        assert (row["node"], row["state"], row["rpm"]) == (str(number), "online", str(rpm))
        assert row["V"] == f"{volts:.2f}" and row["A"] == f"{amps:.2f}"
        assert row["MOS°C"] == f"{temp_c:.0f}"
        assert (row["cap°C"], row["motor°C"], row["MCU°C"]) == ("-", "-", "-")
        assert row["thr%"] == str(power if rpm > 0 else -power)
        assert int(row["frames"]) > 10 and row["errors"] == "0"
    assert motors[1]["flags"] == ""
    assert motors[2]["flags"] == "overtemp"  # above [telemetry] max_temp_c
    assert motors[3]["flags"] == "generic"  # its NodeStatus says CRITICAL
    assert motors[4]["state"] == "offline"
    assert "frames read, 0 malformed" in result.stdout


@pytest.mark.parametrize("player", ["vesc"], indirect=True)
def test_vesc_from_the_bus(can_port: int, player: EscPlayer) -> None:
    result = monitor(*can_args(can_port), "--protocol", "vesc", "--escs", "4", "--duration", "1.5")
    assert result.returncode == 0, result.stderr
    title, rows = tables(result.stdout)[-1]
    assert title == f"udp_multicast:{MULTICAST_GROUP}: 3/4 ESCs online"
    motors = by_motor(rows)
    for controller_id, (erpm, _, duty, mos, motor, input_a, volts) in VESC_ESCS.items():
        row = motors[controller_id]
        assert (row["node"], row["state"]) == (str(controller_id), "online")
        assert row["rpm"] == str(int(erpm / 7))  # [telemetry] pole_pairs 7 unless set
        assert row["V"] == f"{volts:.2f}"
        assert row["A"] == f"{input_a:.2f}"  # the battery side: STATUS_4's input current
        assert (row["MOS°C"], row["motor°C"]) == (f"{mos:.0f}", f"{motor:.0f}")
        assert (row["cap°C"], row["MCU°C"]) == ("-", "-")  # VESC reports neither
        assert row["thr%"] == f"{duty * 100:.0f}"
        assert int(row["frames"]) > 10 and row["errors"] == "0"
    assert motors[3]["A"] == "-4.50"  # regenerating into the battery
    assert motors[3]["flags"] == "overtemp"  # 120 °C motor: above [telemetry] max_temp_c
    assert motors[1]["flags"] == motors[2]["flags"] == ""
    assert motors[4]["state"] == "offline"
    assert "frames read, 0 malformed" in result.stdout


@pytest.mark.parametrize("player", ["ft"], indirect=True)
def test_bus_settings_from_a_config_file(can_port: int, player: EscPlayer, tmp_path: Path) -> None:
    config = tmp_path / "bridge.toml"
    config.write_text(
        f"""
[can]
interface = "udp_multicast"
channel = "{MULTICAST_GROUP}"
options = {{ port = {can_port}, hop_limit = 0 }}

[output]
protocol = "ft"

[escs]
ids = [3, 9]

[telemetry]
pole_pairs = [14, 7]
"""
    )
    result = monitor("--config", str(config), "--source", "can", "--duration", "1.2")
    assert result.returncode == 0, result.stderr
    motors = by_motor(tables(result.stdout)[-1][1])
    assert motors[1]["node"] == "3" and motors[1]["rpm"] == str(int(-21000 / 14))
    assert motors[2]["node"] == "9" and motors[2]["state"] == "offline"


def test_ctrl_c_ends_cleanly_with_a_final_table(can_port: int) -> None:
    proc = start_monitor(*can_args(can_port), "--escs", "2")
    lines = Lines(proc)
    try:
        lines.wait_for("udp_multicast:", 15)  # the first table: the monitor is running
        deadline = time.monotonic() + 5
        while not tables(lines.text()) and time.monotonic() < deadline:
            time.sleep(0.02)  # the whole first table, not just its title, before Ctrl-C
        proc.send_signal(signal.SIGINT)
    finally:
        err = finish(proc)
    assert "Traceback" not in err
    printed = tables(lines.text())
    assert len(printed) >= 2  # the first table, and the final one after Ctrl-C
    assert by_motor(printed[-1][1])[2]["state"] == "offline"


# -- from Zenoh ------------------------------------------------------------------------------


def esc_dict(motor: int, **values: Any) -> dict[str, Any]:
    """A telemetry object as the bridge publishes it (docs/telemetry.md: Zenoh out), written out."""
    esc: dict[str, Any] = {
        "motor": motor,
        "node_id": motor,
        "online": True,
        "age_ms": 4.2,
        "rpm": None,
        "voltage_v": None,
        "current_a": None,
        "motor_current_a": None,
        "throttle": None,
        "temperature_c": {"mos": None, "capacitor": None, "motor": None, "mcu": None},
        "status": None,
        "failure_flags": 0,
        "consumed_mah": 0.0,
        "command": None,
        "command_unit": "",
    }
    esc.update(values)
    return esc


def status(escs: list[dict[str, Any]]) -> bytes:
    return json.dumps(
        {
            "time_unix_ms": time.time_ns() // 1_000_000,
            "count": len(escs),
            "online": sum(1 for e in escs if e["online"]),
            "escs": escs,
        }
    ).encode()


def bridge_session(port: int) -> zenoh.Session:
    """A Zenoh session playing the bridge: listens on loopback only, no multicast scouting."""
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


class Lines:
    """Collects a subprocess's stdout lines in a thread; :meth:`wait_for` one of them."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        self._stdout = proc.stdout
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._run, name="stdout", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        for line in self._stdout:
            self.lines.append(line)

    def wait_for(self, text: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if any(text in line for line in list(self.lines)):
                return
            time.sleep(0.02)
        raise AssertionError(f"no {text!r} within {timeout_s} s: {''.join(self.lines)!r}")

    def text(self) -> str:
        self._thread.join(10)
        return "".join(self.lines)


def start_monitor(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [ESC_BRIDGE, "monitor", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def finish(proc: subprocess.Popen[str], timeout_s: float = 15.0) -> str:
    try:
        proc.wait(timeout_s)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.stderr is not None
    err = proc.stderr.read()
    assert proc.returncode == 0, err
    return err


def test_zenoh_vehicles_values_and_staleness() -> None:
    port = free_port(socket.SOCK_STREAM)
    test_escs = [
        esc_dict(
            1,
            rpm=4321,
            voltage_v=25.2,
            current_a=12.34,
            throttle=0.42,
            consumed_mah=321.4,
            temperature_c={"mos": 55.0, "capacitor": 44.0, "motor": 66.0, "mcu": 33.0},
            failure_flags=1 | 4,
        ),
        esc_dict(2, online=False, age_ms=2500.0),
    ]
    other_escs = [esc_dict(1, rpm=999, voltage_v=12.0)]
    with bridge_session(port) as session:
        proc = start_monitor(
            "--connect", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting", "--duration", "5"
        )
        lines = Lines(proc)
        try:
            lines.wait_for("waiting for esc-bridge on esc-bridge/*", 15)
            session.put("esc-bridge/testvehicle/esc/status", b"not json")
            info = {
                "motor": 1,
                "node_id": 1,
                "online": True,
                "frames": 1234,
                "errors": 5,
                "failure_flags": 0,
                "counters": {},
            }
            start = time.monotonic()
            while proc.poll() is None:
                session.put(
                    "esc-bridge/testvehicle/esc/status",
                    status(test_escs),
                    encoding=zenoh.Encoding.APPLICATION_JSON,
                )
                session.put("esc-bridge/testvehicle/esc/1/info", json.dumps(info))
                if time.monotonic() - start < 2.0:  # then the other vehicle goes quiet
                    session.put("esc-bridge/othervehicle/esc/status", status(other_escs))
                time.sleep(0.1)
        finally:
            finish(proc)
    output = lines.text()
    assert output.startswith("waiting for esc-bridge on esc-bridge/*\n")
    printed = tables(output)
    fresh = [title for title, _ in printed if "2 vehicles" in title and "stale" not in title]
    assert fresh, output
    title, rows = printed[-1]
    assert title.startswith("2 vehicles: othervehicle 1/1 ESCs online, testvehicle 1/2")
    assert title.endswith("; 1 stale")
    other = by_motor(rows, "othervehicle")[1]
    assert (other["vehicle"], other["state"], other["rpm"]) == (
        "othervehicle (stale)",
        "stale",
        "999",
    )
    # Its row keeps ageing while nothing arrives: published 4.2 ms old, then stale for seconds.
    stale_ages = [
        by_motor(rows, "othervehicle")[1]["age"] for title, rows in printed if "1 stale" in title
    ]
    assert all(age.endswith(" s") for age in stale_ages), stale_ages
    seconds = [float(age[:-2]) for age in stale_ages]
    assert seconds[0] >= 1.0 and seconds[-1] > seconds[0], seconds
    motors = by_motor(rows, "testvehicle")
    row = motors[1]
    assert (row["vehicle"], row["state"], row["rpm"]) == ("testvehicle", "online", "4321")
    assert (row["V"], row["A"], row["mAh"], row["thr%"]) == ("25.20", "12.34", "321", "42")
    assert (row["MOS°C"], row["cap°C"], row["motor°C"], row["MCU°C"]) == ("55", "44", "66", "33")
    assert row["flags"] == "overcurrent overtemp"
    assert (row["frames"], row["errors"], row["age"]) == ("1234", "5", "4 ms")
    assert (motors[2]["state"], motors[2]["age"], motors[2]["frames"]) == ("offline", "2.5 s", "-")
    assert "1 malformed messages ignored" in output


def test_zenoh_settings_from_a_bridge_config(tmp_path: Path) -> None:
    # The bridge listens on all interfaces; the monitor, given the same file, connects to it
    # over loopback and watches only the vehicle the file names.
    port = free_port(socket.SOCK_STREAM)
    config = tmp_path / "bridge.toml"
    config.write_text(
        f"""
[zenoh]
listen = ["tcp/0.0.0.0:{port}"]
multicast_scouting = false
vehicle = "cfgvehicle"
"""
    )
    with bridge_session(port) as session:
        proc = start_monitor("--config", str(config), "--duration", "2.5")
        lines = Lines(proc)
        try:
            lines.wait_for("waiting for esc-bridge on esc-bridge/cfgvehicle", 15)
            while proc.poll() is None:
                session.put("esc-bridge/cfgvehicle/esc/status", status([esc_dict(1, rpm=777)]))
                session.put("esc-bridge/elsewhere/esc/status", status([esc_dict(1, rpm=1)]))
                time.sleep(0.1)
        finally:
            finish(proc)
    title, rows = tables(lines.text())[-1]
    assert title == "cfgvehicle: 1/1 ESCs online"
    assert [row["rpm"] for row in rows] == ["777"]


# -- bad arguments ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--escs", "4", "--ids", "1,2"], "argument --ids: not allowed with argument --escs"),
        (["--escs", "0"], "--escs: expected a number of ESCs 1..125, got '0'"),
        (["--ids", "1,x"], "--ids: expected a comma-separated list of ESC IDs"),
        (["--ids", "1,1"], "--ids: expected a list of distinct integers 1..125"),
        (["--duration", "-1"], "--duration: expected a number of seconds > 0"),
        (["--protocol", "xyz"], "--protocol: invalid choice: 'xyz'"),
        (["--can-interface", "udp_multicast"], "the CAN source needs the ESCs: --escs N or --ids"),
        (["--connect", "tcp/127.0.0.1:1", "--escs", "2"], "--connect: a Zenoh option, but --escs"),
        (["--source", "zenoh", "--ids", "1"], "--ids: a CAN option, but --source zenoh"),
        (
            ["--bitrate", "123", "--escs", "1"],
            "--bitrate: expected a bit rate such as 500000, 500k",
        ),
        (["--pole-pairs", "7,7", "--escs", "4"], "--pole-pairs: 2 values for 4 ESCs"),
        (["--telemetry-timeout-ms", "5", "--escs", "1"], "--telemetry-timeout-ms: expected an"),
        (["--can-interface", "nosuch", "--escs", "1"], "interface 'nosuch' is not available"),
        (["--can-option", "port", "--escs", "1"], "--can-option: 'port': expected KEY=VALUE"),
        (["--prefix", "esc-bridge/"], "--prefix: expected a key expression without leading"),
        (["--connect", "nonsense"], "--connect: expected endpoints of the form"),
        (["--config", "/nonexistent/bridge.toml"], "/nonexistent/bridge.toml: no such config"),
    ],
)
def test_bad_arguments_are_named(
    args: list[str], expected: str, capsys: pytest.CaptureFixture[str]
) -> None:
    try:
        code = main(["monitor", *args])
    except SystemExit as exc:  # argparse's own errors
        code = int(exc.code or 0)
    assert code == 2
    err = capsys.readouterr().err
    assert expected in err
    assert "Traceback" not in err


def test_a_bus_that_cannot_be_opened_is_one_line_and_exit_2() -> None:
    # No such netdev (and, on machines without SocketCAN, no CAN address family at all).
    result = monitor("--can-interface", "socketcan", "--can-channel", "nosuchcan9", "--escs", "1")
    assert result.returncode == 2
    assert result.stderr.startswith("esc-bridge: cannot open CAN bus socketcan:nosuchcan9: ")
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert result.stdout == ""


# -- the table's cells -----------------------------------------------------------------------


def test_failure_flags_are_named() -> None:
    assert failure_names(0) == ""
    assert failure_names(1 | 2 | 4 | 8 | 16 | 32 | 64) == (
        "overcurrent overvolt overtemp overrpm badcmd stuck generic"
    )
    assert failure_names(64 | 0x300) == "generic 0x300"  # bits MAVLink does not name: as hex
    assert failure_names(None) == "-"


def test_values_not_reported_show_as_missing() -> None:
    esc = EscTelemetryPayload.decode(json.dumps(esc_dict(3, online=False, age_ms=None)).encode())
    nan = replace(esc, voltage_v=math.nan, throttle=math.inf)  # never on the wire, still "-"
    text = plain_text([VehicleState("v", (EscRow(esc), EscRow(nan)))])
    for row in tables(text)[0][1]:
        assert row.pop("motor") == row.pop("node") == "3"
        assert (row.pop("state"), row.pop("flags"), row.pop("mAh")) == ("offline", "", "0")
        assert set(row.values()) == {"-"}


def test_a_bridge_config_becomes_the_monitors_side_of_it() -> None:
    bridge = ZenohConfig(
        mode="router",
        connect=("tcp/10.0.0.1:7447",),
        listen=("tcp/0.0.0.0:7447", "udp/[::]:7448", "tcp/192.168.1.5:7449"),
        multicast_scouting=False,
    )
    mine = monitor_zenoh_config(bridge)
    assert mine.connect == (
        "tcp/10.0.0.1:7447",
        "tcp/127.0.0.1:7447",
        "udp/[::1]:7448",
        "tcp/192.168.1.5:7449",
    )
    assert (mine.listen, mine.mode, mine.multicast_scouting) == ((), "peer", False)
    assert prefix_of(bridge) == "esc-bridge/*"  # the bridge's default vehicle is its host name
    assert prefix_of(replace(bridge, vehicle="drone1")) == "esc-bridge/drone1"
    assert prefix_of(replace(bridge, prefix="fleet/a")) == "fleet/a"


def test_payloads_that_are_not_ours_are_refused_naming_key_and_field() -> None:
    for payload, why in (
        (b"not json", "esc/status: not JSON"),
        (b"\xff\xfe", "esc/status: not JSON"),
        (b"[1, 2]", "esc/status: payload: expected an object, got [1, 2]"),
        (b'{"count": 1, "online": 1, "escs": [1]}', "esc/status: field escs[0]: expected an obj"),
        (b'{"count": 1, "online": 1, "escs": [{"motor": 1}]}', "field escs[0].node_id missing"),
    ):
        with pytest.raises(PayloadError, match=re.escape(why)):
            EscStatusPayload.decode(payload)
    with pytest.raises(PayloadError, match=re.escape("esc/<n>/info: field motor: expected an i")):
        EscInfoPayload.decode(b'{"motor": [1], "frames": 3}')
    info = b'{"motor": 2, "node_id": 5, "online": true, "frames": 3, "errors": 0, '
    info += b'"failure_flags": 0, "counters": {}, "added_later": 1}'  # unknown names: ignored
    assert EscInfoPayload.decode(info).frames == 3
