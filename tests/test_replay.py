"""Replay of recorded autopilot output streams through the daemon.

The log's own MAVLink frames are sent, byte for byte (MAVLink 1 for the ArduPlane log), with its
HEARTBEATs, so arming comes from the log too. Outputs are re-sent every 20 ms until the bridge's
frame shows them (the logs stream at 4 Hz, slower than the bridge's input timeout).

The logs (``tests/data/README.md`` says where each comes from):

- ArduCopter 4.5 SITL, MAVLink 2, a quad on channels 1-4: an excerpt of a real log (MIT),
  vendored in ``tests/data/tlogs``.
- ArduPlane QuadPlane, MAVLink 1, lift motors on channels 5-8 behind four active surface
  channels: a stand-in written at test time by :func:`write_quadplane_standin`. The real
  ArduPlane 3.10 log it models is GPL-3.0, which this MIT project does not take in. Where the
  workspace has it beside the checkout (``../shared/data/tlogs``), it is replayed as one more
  case (not skipped elsewhere), and :func:`test_log_holds_what_the_replay_exercises` checks
  the stand-in and that original for the same properties.
"""

from __future__ import annotations

import itertools
import math
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from conftest import ROOT, STARTUP_TIMEOUT_S, Daemon, Observer
from pymavlink import mavutil
from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from test_daemon_e2e import ckesc_throttles, pwm_to_throttle

DATA_TLOGS = ROOT / "tests" / "data" / "tlogs"
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


# The workspace's copy of the GPL-3.0 log the stand-in models, if it sits beside the checkout.
QUADPLANE_ORIGINAL = (
    ROOT.parent / "shared" / "data" / "tlogs" / "uavlogviewer_quadplane_sitl_vtol.tlog"
)


@dataclass(frozen=True)
class Log:
    name: str
    path: Path | None  # None: the QuadPlane stand-in, written at test time
    lift: slice  # the SERVO_OUTPUT_RAW channels (0-based) that drive the four motors
    mixer: str | None  # None: the default quad mixer, channels 1-4
    wire: int  # the MAVLink version of the autopilot's frames
    bursty: bool  # written in bursts: the log's stamps do not say when a frame was sent


LOGS = [
    Log(
        "arducopter-4.5",
        DATA_TLOGS / "handgesture_sitl_copter45_excerpt.tlog",
        slice(0, 4),
        None,
        wire=2,
        bursty=False,
    ),
    Log("arduplane-quadplane-standin", None, slice(4, 8), LIFT_MIXER, wire=1, bursty=True),
]
if QUADPLANE_ORIGINAL.is_file():
    LOGS.append(
        Log("arduplane-3.10-quadplane", QUADPLANE_ORIGINAL, slice(4, 8), LIFT_MIXER, 1, True)
    )
with_each_log = pytest.mark.parametrize("log", LOGS, ids=lambda log: str(log.name))


# -- the QuadPlane stand-in ------------------------------------------------------------------

STANDIN_MS = 200_000  # the flight's length
STANDIN_DISARM_MS = 170_000
STANDIN_OUTPUT_MS = 250  # SERVO_OUTPUT_RAW at 4 Hz, HEARTBEAT at 1 Hz
STANDIN_BURST_MS = 1_200  # the ground station wrote what it had received this often
STANDIN_BOOT_US = 45_000_000  # the autopilot's uptime when the log starts
STANDIN_START_US = 1_700_000_000_000_000  # the log's first wall-clock stamp


def quadplane_lift(t: float, motor: int) -> int:
    """A lift motor's PWM ``t`` s into the flight: from idle up to the climb's 1949 µs at 10 s,
    a hover at about 1550 µs that corrects attitude (each motor a quarter turn out of phase),
    the descent from 140 s, idle from 165 s, disarmed at 170 s."""
    if t < 5:
        pwm = 1000 + 550 * t / 5
    elif t < 15:
        pwm = 1550 + 399 * math.sin(math.pi * (t - 5) / 10)
    elif t < 140:
        pwm = 1550 + 120 * math.sin(2 * math.pi * t / 9 + motor * math.pi / 2)
    elif t < 165:
        pwm = 1550 - 250 * (t - 140) / 25
    else:
        pwm = 1000
    return round(min(max(pwm, 1000), 1949))


def quadplane_surfaces(t: float) -> list[int]:
    """Channels 1-4 ``t`` s into the flight: aileron, elevator, the forward motor (running from
    60 to 120 s only) and rudder, moving all the time."""
    forward = 1000 + 800 * math.sin(math.pi * (t - 60) / 60) if 60 <= t < 120 else 1000
    return [
        round(1500 + 300 * math.sin(t / 7)),
        round(1500 + 250 * math.sin(t / 11 + 1)),
        round(forward),
        round(1500 + 200 * math.sin(t / 13 + 2)),
    ]


def write_quadplane_standin(path: Path) -> None:
    """A 200 s tlog with the shape of an ArduPlane QuadPlane SITL flight as a ground station logs
    it: MAVLink 1 throughout, the autopilot's HEARTBEAT (armed until 170 s) and a ground
    station's, SERVO_OUTPUT_RAW with the surfaces on channels 1-4 and the lift motors on 5-8.
    The records are stamped in bursts, as they were written, so only the messages' own
    ``time_usec`` say when they were sent."""
    autopilot = mavlink1.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = mavlink1.MAVLink(None, srcSystem=255, srcComponent=190)
    records: list[bytes] = []
    burst = in_burst = 0
    for ms in range(0, STANDIN_MS, STANDIN_OUTPUT_MS):
        t = ms / 1000
        armed = ms < STANDIN_DISARM_MS
        messages: list[tuple[Any, Any]] = []
        if ms % 1000 == 0:
            base_mode = mavlink1.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            if armed:
                base_mode |= mavlink1.MAV_MODE_FLAG_SAFETY_ARMED
            mode = mavlink1.PLANE_MODE_QLOITER if t < 140 else mavlink1.PLANE_MODE_QLAND
            state = mavlink1.MAV_STATE_ACTIVE if armed else mavlink1.MAV_STATE_STANDBY
            messages.append(
                (
                    autopilot,
                    autopilot.heartbeat_encode(
                        mavlink1.MAV_TYPE_FIXED_WING,
                        mavlink1.MAV_AUTOPILOT_ARDUPILOTMEGA,
                        base_mode,
                        mode,
                        state,
                    ),
                )
            )
        if ms % 1000 == 500:
            messages.append(
                (
                    gcs,
                    gcs.heartbeat_encode(
                        mavlink1.MAV_TYPE_GCS,
                        mavlink1.MAV_AUTOPILOT_INVALID,
                        0,
                        0,
                        mavlink1.MAV_STATE_ACTIVE,
                    ),
                )
            )
        lift = [quadplane_lift(t, motor) if armed else 1000 for motor in range(4)]
        pwm = quadplane_surfaces(t) + lift
        time_usec = STANDIN_BOOT_US + ms * 1000
        messages.append((autopilot, autopilot.servo_output_raw_encode(time_usec, 0, *pwm)))
        if ms // STANDIN_BURST_MS != burst:
            burst, in_burst = ms // STANDIN_BURST_MS, 0
        for sender, message in messages:
            # Written when the burst ends, 0.2 ms apart.
            stamp_us = STANDIN_START_US + (burst + 1) * STANDIN_BURST_MS * 1000 + 200 * in_burst
            records.append(struct.pack(">Q", stamp_us) + bytes(message.pack(sender)))
            sender.seq = (sender.seq + 1) % 256
            in_burst += 1
    path.write_bytes(b"".join(records))


@pytest.fixture(scope="module")
def standin(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("tlogs") / "quadplane_standin.tlog"
    write_quadplane_standin(path)
    return path


# -- reading a log ---------------------------------------------------------------------------


@dataclass
class Step:
    heartbeat: bytes  # the autopilot's latest HEARTBEAT before this output
    armed: bool
    output: bytes  # the SERVO_OUTPUT_RAW frame as logged
    pwm: tuple[int, ...]  # servo1..servo8
    stamp_s: float  # the log's stamp
    time_usec: int  # the message's own


def read_steps(path: Path) -> list[Step]:
    """Every SERVO_OUTPUT_RAW of the autopilot (1/1) after its first HEARTBEAT, in log order."""
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
            output = bytes(msg.get_msgbuf())
            steps.append(Step(*heartbeat, output, pwm, msg._timestamp, msg.time_usec))
    return steps


def spread(steps: list[Step]) -> list[Step]:
    """SAMPLES steps spread over the whole log."""
    stride = max(1, len(steps) // SAMPLES)
    return steps[::stride][:SAMPLES]


def log_file(log: Log, standin: Path) -> Path:
    return standin if log.path is None else log.path


# -- the tests -------------------------------------------------------------------------------


@with_each_log
def test_log_holds_what_the_replay_exercises(log: Log, standin: Path) -> None:
    """What the replay relies on in each log. The stand-in is held to the same properties as
    the original it models, which is checked too where it is present."""
    steps = read_steps(log_file(log, standin))
    magic = {1: mavlink1.PROTOCOL_MARKER_V1, 2: mavutil.mavlink.PROTOCOL_MARKER_V2}[log.wire]
    assert {s.output[0] for s in steps} == {s.heartbeat[0] for s in steps} == {magic}
    # The lift motors' channels span idle to well above hover while armed.
    armed = [s for s in steps if s.armed]
    for channel in range(8)[log.lift]:
        values = [s.pwm[channel] for s in armed]
        assert (min(values), max(values) >= 1600) == (1000, True), f"channel {channel + 1}"
    # Reading the wrong four channels would send other throttles at most of the samples.
    told_apart = [
        s
        for s in spread(steps)
        if s.armed
        and [pwm_to_throttle(p) for p in s.pwm[:4]] != [pwm_to_throttle(p) for p in s.pwm[4:]]
    ]
    assert len(told_apart) >= SAMPLES // 2
    # Bursts: outputs logged within 10 ms of each other although sent 200 ms or more apart.
    pairs = list(itertools.pairwise(steps))
    bunched = [
        (a, b)
        for a, b in pairs
        if b.stamp_s - a.stamp_s < 0.01 and b.time_usec - a.time_usec >= 200_000
    ]
    assert (len(bunched) >= len(pairs) // 4) == log.bursty


@with_each_log
def test_replay_tlog(
    start_daemon: Callable[..., Daemon],
    observer: Observer,
    mavlink_port: int,
    tmp_path: Path,
    standin: Path,
    log: Log,
) -> None:
    steps = spread(read_steps(log_file(log, standin)))
    assert len(steps) == SAMPLES
    args = []
    if log.mixer is not None:
        mixer_file = tmp_path / "lift.toml"
        mixer_file.write_text(log.mixer)
        args = ["--mixer", str(mixer_file)]
    start_daemon(*args)
    checked = armed_steps = 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        target = ("127.0.0.1", mavlink_port)
        first = True
        for step in steps:
            want = (
                tuple(pwm_to_throttle(p) for p in step.pwm[log.lift])
                if step.armed
                else (0, 0, 0, 0)
            )
            deadline = time.monotonic() + (STARTUP_TIMEOUT_S if first else 3.0)
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
