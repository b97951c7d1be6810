"""Replay of real autopilot output streams (../shared/data/tlogs) through the daemon.

The log's own MAVLink frames are sent, byte for byte (MAVLink 1 for the ArduPlane log), with its
HEARTBEATs, so arming comes from the log too. Outputs are re-sent every 20 ms until the bridge's
frame shows them (the logs stream at 4 Hz, slower than the bridge's input timeout).
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from conftest import SHARED_DATA, Daemon, Observer
from pymavlink import mavutil
from test_daemon_e2e import ARM_TIMEOUT_S, ckesc_throttles, pwm_to_throttle

TLOGS = SHARED_DATA / "tlogs"
SAMPLES = 40  # outputs checked per log, spread over the whole log
RESEND_S = 0.02

LIFT_MIXER = """
[info]
description = "QuadPlane lift motors: channels 5-8 to outputs 1-4"

[output_default]
input_range = [1000.0, 2000.0]
min = 0.0
max = 1.0
""" + "".join(f'\n[[outputs]]\nname = "lift{i}"\nsource = "ch{i + 4}"\n' for i in range(1, 5))


@dataclass
class Step:
    heartbeat: bytes  # the autopilot's latest HEARTBEAT before this output
    armed: bool
    output: bytes  # the SERVO_OUTPUT_RAW frame as logged
    pwm: tuple[int, ...]  # servo1..servo8


def read_steps(path: Path) -> list[Step]:
    log = mavutil.mavlink_connection(str(path))
    steps: list[Step] = []
    heartbeat: tuple[bytes, bool] | None = None
    while (msg := log.recv_match(type=["HEARTBEAT", "SERVO_OUTPUT_RAW"])) is not None:
        if (msg.get_srcSystem(), msg.get_srcComponent()) != (1, 1):
            continue
        if msg.get_type() == "HEARTBEAT":
            armed = bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            heartbeat = (bytes(msg.get_msgbuf()), armed)
        elif heartbeat is not None and msg.port == 0:
            pwm = tuple(getattr(msg, f"servo{i}_raw") for i in range(1, 9))
            steps.append(Step(heartbeat[0], heartbeat[1], bytes(msg.get_msgbuf()), pwm))
    stride = max(1, len(steps) // SAMPLES)
    return steps[::stride][:SAMPLES]


@pytest.mark.parametrize(
    ("log_name", "channels", "mixer"),
    [
        ("handgesture_sitl_copter45_mav.tlog", slice(0, 4), None),
        ("uavlogviewer_quadplane_sitl_vtol.tlog", slice(4, 8), LIFT_MIXER),
    ],
    ids=["arducopter-4.5", "arduplane-3.10-quadplane"],
)
def test_replay_tlog(
    start_daemon: Callable[..., Daemon],
    observer: Observer,
    mavlink_port: int,
    tmp_path: Path,
    log_name: str,
    channels: slice,
    mixer: str | None,
) -> None:
    path = TLOGS / log_name
    if not path.is_file():
        pytest.skip(f"{path} is absent: the shared data sets are not beside this checkout")
    steps = read_steps(path)
    assert len(steps) == SAMPLES
    args = []
    if mixer is not None:
        mixer_file = tmp_path / "lift.toml"
        mixer_file.write_text(mixer)
        args = ["--mixer", str(mixer_file)]
    start_daemon(*args)
    checked = armed_steps = 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        target = ("127.0.0.1", mavlink_port)
        first = True
        for step in steps:
            want = (
                tuple(pwm_to_throttle(p) for p in step.pwm[channels])
                if step.armed
                else (0, 0, 0, 0)
            )
            deadline = time.monotonic() + (ARM_TIMEOUT_S if first else 3.0)
            first = False
            matched = False
            while not matched and time.monotonic() < deadline:
                sock.sendto(step.heartbeat, target)
                sock.sendto(step.output, target)
                sent = time.monotonic()
                time.sleep(RESEND_S)
                matched = any(ckesc_throttles(m) == want for m in observer.since(sent))
            assert matched, f"log output {step.pwm} (armed {step.armed}) never sent as {want}"
            checked += 1
            armed_steps += step.armed
    assert checked == SAMPLES
    assert armed_steps >= SAMPLES // 2  # the logs are mostly armed: the values were exercised
