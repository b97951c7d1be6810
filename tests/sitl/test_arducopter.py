"""The bridge against a real ArduCopter SITL: two flights, two rigs each, many checks.

What runs (all on loopback, see conftest.py): ArduCopter SITL (quad, real time) with a ground
station on SERIAL0 and two bridges through their CLI on SERIAL1 and SERIAL2, each through a
recording tap and each on a CAN bus of its own with four simulated ESCs and an independent
observer. The four rigs fly in pairs (FLIGHTS), each pair in a flight of its own: a CKESC
bridge (RawCommand_12b, 400 Hz) with a VESC one (duty, 0.95 full scale, 200 Hz per ESC), then
an FT one (current mode, 20 A full scale, 100 Hz per ESC) with a DroneCAN one (RawCommand,
400 Hz). A rig is an ESC family's name (the registry's) and its expected command; the frames
are read through the family (``commands_seen``, ``telemetry``), so the checks are the same for
every rig. The module-scoped ``flights`` fixture flies each pair once, the first time a test
asks for one of its rigs (about 80 s: ArduCopter refuses to arm for ~40 s after a start), and
keeps the record; each test then asserts one property of it:

1. while the autopilot boots: ArduCopter's own motor test (B), during which the autopilot is
   killed (SIGKILL); a restart in the same directory and instance;
2. while the restarted one boots: HEARTBEAT and SERVO_OUTPUT_RAW rates asked on the ground
   station's link (what ArduCopter grants), and two more motor tests (A, then C);
3. arm, GUIDED, take off, hover; a 1 s SIGSTOP of the autopilot mid-hover, hover; LAND, which
   disarms.

``pytest tests/sitl`` (or ``-m sitl``) runs it; the numbers each test measured go to the file
``$ESC_BRIDGE_SITL_REPORT`` names (bench/sitl_table.py) and, without xdist (``-p no:xdist``), to
a "SITL measurements" section at the end of the run. ESC_BRIDGE_ARDUCOPTER names another
build (see conftest.py).

The scaling is the passthrough mixer's: PWM 1000..2000 µs to 0..1, then CKESC throttle
round(2000·x), FT current 20 A·x (the bridge's `[escs] ft_max_current_a` default), DroneCAN
RawCommand round(8191·x) and VESC duty 0.95·x (`[escs] vesc_max_duty`).
"""

from __future__ import annotations

import bisect
import contextlib
import itertools
import os
import re
import statistics
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from conftest import Observer, free_port

from bridge.errors import CodecError
from bridge.escs.family import EscDecoder, EscTelemetry

from .conftest import (
    ARDUPILOT_SERIAL_PORTS,
    ARDUPILOT_UDP_PORTS,
    ArduCopter,
    ArduCopterBuild,
    GroundStation,
    MavTap,
    Process,
    ServoOutput,
    TapRecord,
    armed,
    commands_by_motor,
    esc_period_s,
    frame_reader,
    from_autopilot,
    mavlink,
    measured,
    reserved_instance,
    start_bridge,
    start_sim,
    stream_answers,
    udp_drops,
    wait_until,
    wide_observer,
    write_bridge_config,
)

PERIOD_S = 1 / 400  # every bridge ticks at 400 Hz (CKESC, DroneCAN 400 Hz; FT 4 ESCs x 100 Hz)
INPUT_TIMEOUT_S = 0.100  # [output] input_timeout_ms default
STREAM_HZ = 200  # [mavlink] stream_rate_hz default
FT_FULL_SCALE_A = 20.0
DRONECAN_FULL_SCALE = 8191
VESC_FULL_SCALE_DUTY = 0.95
POLE_PAIRS = 7  # [telemetry] pole_pairs default: the bridge's rpm of a family reporting erpm
# The observer's and the tap's stamps, taken in two processes, may be this far apart (as in
# test_px4.py's lag rule): a frame stamped just before the tap's stamp of the output it carries.
CLOCK_SKEW_S = 0.001
# An armed HEARTBEAT the tap stamped may reach the bridge's loop this much later on a loaded
# machine (loopback delivered from ksoftirqd): one frame 3 ms after the tap's stamp still went
# out disarmed at load ~5. Frames that close to the arming are not judged.
ARMING_LATE_S = 0.010
# A frame is judged against the motor output only while that output is fresh: newer than half
# the input timeout at the tap. Older ones (the stall, the kill) are the failsafe tests' part.
FRESH_S = INPUT_TIMEOUT_S / 2
# After a silence of the outputs longer than the input timeout the bridge is safe, and it judges
# the first inputs after it old until their rhythm shows the autopilot's clock stood still
# (the SITL paused) rather than a backlog arriving (test_stall_recovers_after_sigcont: within
# 50 ms). Frames this soon after a silence are not judged against the newest output.
RESUME_S = 0.100
TEST_THROTTLE_PERCENT = 20.0
TELEMETRY_TIMEOUT_S = 0.5  # [telemetry] timeout_ms default: an ESC silent this long is offline
# The ground station gets the bridge's ESC_TELEMETRY some time after the bridge built it
# (ArduCopter forwards it at its own pace): a silence this much shorter than the timeout
# before the receipt may have reached the timeout when the bridge built the message.
TELEMETRY_SLACK_S = 0.1
# How long before the ground station got an ESC_TELEMETRY the bus may have carried its values:
# the bridge's 2 Hz, ArduCopter's forwarding, and this process's reader, which lagged over a
# second behind in the whole suite.
RELAY_LAG_S = 3.0
HEARTBEAT_HZ = 20  # [mavlink] autopilot_heartbeat_hz default; ArduCopter grants it
# A FT ESC's frame comes every 10 ms, the HEARTBEAT's forwarding and the tap on a loaded
# 2-core machine a few ms more.
MOTOR_TEST_SLACK_S = 0.025
TEST_PWM = 1200  # ArduCopter: percent of MOT_PWM_MIN..MAX (1000..2000)
# Hover after the stall before landing; ESC_BRIDGE_SITL_RECOVERY_S longer measures how long the
# bridge takes to trust the autopilot's inputs again.
RECOVERY_WAIT_S = float(os.environ.get("ESC_BRIDGE_SITL_RECOVERY_S", "3"))

pytestmark = pytest.mark.sitl


# --------------------------------------------------------------------------------------------
# The scaling, written out here rather than taken from the bridge


def ckesc_throttle(pwm: int) -> int:
    return 2 * (min(max(pwm, 1000), 2000) - 1000)


def ft_current(pwm: int) -> float:
    return (min(max(pwm, 1000), 2000) - 1000) / 1000 * FT_FULL_SCALE_A


def dronecan_command(pwm: int) -> float:
    return round((min(max(pwm, 1000), 2000) - 1000) / 1000 * DRONECAN_FULL_SCALE)


def vesc_duty(pwm: int) -> float:
    return (min(max(pwm, 1000), 2000) - 1000) / 1000 * VESC_FULL_SCALE_DUTY


@dataclass(frozen=True)
class RigSpec:
    """A rig: the ESC family (its registry name), what its commands should be for a PWM, and
    how far a command may be from that (the bridge's float arithmetic)."""

    family: str
    expected: Callable[[int], float]
    tolerance: float


RIGS = {
    spec.family: spec
    for spec in (
        RigSpec("ckesc", ckesc_throttle, 0.0),
        RigSpec("ft", ft_current, 1e-4),
        RigSpec("dronecan", dronecan_command, 1.0),
        RigSpec("vesc", vesc_duty, 1e-5),  # duty in steps of 1e-5
    )
}
RIG_NAMES = list(RIGS)
FLIGHTS = (("ckesc", "vesc"), ("ft", "dronecan"))
"""The rigs that fly together, each pair in a flight of its own. All four in one flight (a
bridge of two processes and a simulator each, beside the autopilot, the tap and this process's
observers) needed more than the 2 cores here: the simulators fell silent for up to a second and
the bridges rightly called their ESCs offline. The busiest bus (VESC: 1 000 status frames a
second) and the costliest to decode here (DroneCAN, through the ``dronecan`` package) fly
apart."""
# A flight's rigs, in order, on these links (ArduCopter's SERIAL1, SERIAL2), components 191, 192.
SERIALS = (1, 2)


@dataclass(frozen=True)
class Command:
    """One command frame as the observer saw it: kernel receive time, motor index (0-based),
    value (CKESC throttle, FT amps, DroneCAN RawCommand value, VESC duty). A frame for four ESCs
    (CKESC 12b, DroneCAN) becomes four of these."""

    t: float
    motor: int
    value: float


@dataclass
class Rig:
    """One bridge and what sits on its bus; ``name`` is its ESC family's."""

    name: str
    link: int
    component: int
    can_port: int
    observer: Observer
    bridge: Process
    sim: Process
    expected: Callable[[int], float]
    tolerance: float
    esc_period_s: float
    """How often each ESC gets a command (the family's ticks per cycle at the bridge's rate)."""
    reader: EscDecoder
    """The rig's family, decoding this bus's frames (:func:`frame_reader`)."""
    commands: list[list[Command]] = field(default_factory=list)
    """Per command frame (CKESC, DroneCAN: all four motors; FT, VESC: one ESC), its commands."""
    telemetry: list[tuple[float, EscTelemetry]] = field(default_factory=list)
    """Every telemetry frame: its receive time and what it said, in the family's neutral terms."""
    malformed: list[str] = field(default_factory=list)
    """Frames that do not decode, and commands for motors past the quad's four."""
    decoded: int = 0
    """How many of the observer's frames :meth:`decode_new` has read."""
    decoded_until: float = 0.0
    """The stamp of the last of them: the bus is decoded up to then."""
    decode_s: float = 0.0
    """The time decoding took."""
    lock: threading.Lock = field(default_factory=threading.Lock)
    observer_drops: int = 0
    tap: TapRecord = field(default_factory=TapRecord)
    bridge_exit: int | None = None

    def decode_new(self) -> None:
        """Decode the frames the observer got since the last call, in the order it got them
        (not by their stamps: the kernel's, moved onto the monotonic clock, can put the frames
        of a multi-frame transfer a few µs out of order). Called from one thread only (the
        flight's :class:`Decoding`): a family's decoder keeps its state per thread."""
        with self.observer._lock:
            frames = self.observer.frames[self.decoded :]
        self.decoded += len(frames)
        began = time.perf_counter()
        commands: list[list[Command]] = []
        telemetry: list[tuple[float, EscTelemetry]] = []
        malformed: list[str] = []
        for t, msg in frames:
            # Let the observers' threads in: a thread that keeps the GIL holds each of them to
            # a frame per switch interval (5 ms), and a bus of 1 600 frames/s falls behind.
            time.sleep(0)
            try:
                frame = self.reader.decode(msg)
            except CodecError as exc:
                malformed.append(f"{msg}: {exc}")
                continue
            if frame is None:
                continue
            by_motor = commands_by_motor(self.reader, frame)
            if by_motor is None:
                reading = self.reader.telemetry(frame)
                if reading is not None:
                    telemetry.append((t, reading))
            elif max(by_motor) > 3:
                malformed.append(f"{msg}: commands for motors {sorted(by_motor)} on a quad")
            else:
                commands.append([Command(t, motor, value) for motor, value in by_motor.items()])
        with self.lock:
            self.commands.extend(commands)
            self.telemetry.extend(telemetry)
            self.malformed.extend(malformed)
            if frames:  # after the frames' commands are in: a reader may rely on both
                self.decoded_until = frames[-1][0]
        self.decode_s += time.perf_counter() - began

    def commands_since(self, t: float) -> list[list[Command]]:
        with self.lock:
            return [frame for frame in self.commands if frame[0].t >= t]

    def value_of(self, servo: ServoOutput, motor: int) -> float:
        return self.expected(servo.servos[motor])

    def newest_index(self, t: float) -> int:
        """Index of the newest motor output the tap forwarded at or before ``t`` (-1: none)."""
        return bisect.bisect_right(self._servo_times, t) - 1

    def prepare(self) -> None:
        """After the flight: the commands in time order, the tap's record indexed."""
        self.commands.sort(key=lambda frame: frame[0].t)
        self.telemetry.sort(key=lambda reading: reading[0])
        self._servo_times = [s.t for s in self.tap.servo]
        self._servo_sent = [s.t_sent for s in self.tap.servo]
        self._silence_ends = [
            b.t for a, b in itertools.pairwise(self.tap.servo) if b.t - a.t > INPUT_TIMEOUT_S
        ]

    def soon_after_silence(self, t: float) -> bool:
        """Whether a silence of the motor outputs longer than the input timeout ended within
        RESUME_S before ``t`` (as the tap saw them)."""
        i = bisect.bisect_right(self._silence_ends, t + CLOCK_SKEW_S) - 1
        return i >= 0 and t - self._silence_ends[i] < RESUME_S

    def allowed(self, t: float, motor: int) -> set[float]:
        """The values a command frame sent at ``t`` may carry: those of the newest motor output
        whose forwarding had begun by ``t``, of the one before it (one message of lag), and of
        any back to the newest the bridge had a whole output period before ``t`` (forwarded by
        t - PERIOD_S; one tick of lag). A fixed-rate sender carries the newest input it had
        taken when its tick fired; one that arrived since may not have been taken yet. The
        stamps themselves can be a few ms late on a loaded machine (the kernel may deliver
        loopback packets from ksoftirqd), hence the message of lag beside the tick."""
        # CLOCK_SKEW_S: the observer's stamp (the kernel's wall clock, moved onto the monotonic
        # one) and the tap's (monotonic) can disagree by that much.
        i = self.newest_index(t + CLOCK_SKEW_S)
        j = bisect.bisect_right(self._servo_sent, t - PERIOD_S) - 1
        j = max(min(j, i - 1), 0)
        servo = self.tap.servo
        return {self.value_of(servo[k], motor) for k in range(j, i + 1)} if i >= 0 else set()

    def allowed_between(self, start: float, end: float, motor: int) -> set[float]:
        """The values a frame decided at some moment from ``start`` to ``end`` may carry: what
        :meth:`allowed` gives at ``start``, and every output forwarded since, up to the newest
        at ``end``."""
        i = self.newest_index(end + CLOCK_SKEW_S)
        j = bisect.bisect_right(self._servo_sent, start - PERIOD_S) - 1
        j = max(min(j, self.newest_index(start + CLOCK_SKEW_S) - 1), 0)
        return {self.value_of(s, motor) for s in self.tap.servo[j : i + 1]}

    def left_late(self) -> int:
        """The ticks the bridge counted as left late (its exit summary): frames that left over
        a period after their decision, the loop held up after its last look at the clock."""
        found = re.search(r"(\d+) left late", self.bridge.log_path.read_text(errors="replace"))
        assert found, f"no exit summary in {self.bridge.log_path}:\n{self.bridge.tail(15)}"
        return int(found.group(1))

    def matches(self, value: float, allowed: set[float]) -> bool:
        return any(abs(value - a) <= self.tolerance for a in allowed)


class Decoding:
    """Decodes every rig's bus in a thread of its own while the flight goes on: DroneCAN's
    frames cost the ``dronecan`` package ~0.1-0.3 ms each, some 15 s of CPU for a flight, spent
    while the flight mostly waits (ArduCopter's arming) rather than after it."""

    def __init__(self, rigs: Sequence[Rig], poll_s: float = 0.2) -> None:
        self.rigs = list(rigs)
        self.poll_s = poll_s
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="decoding", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.wait(self.poll_s):
                for rig in self.rigs:
                    rig.decode_new()
            for rig in self.rigs:  # what came until finish()
                rig.decode_new()
        except Exception as exc:  # noqa: BLE001 - re-raised by finish()
            self.error = exc

    def finish(self) -> None:
        """Decode what the observers got so far, and stop."""
        self._stop.set()
        self._thread.join(120)
        assert not self._thread.is_alive(), "the decoding thread did not finish within 120 s"
        error, self.error = self.error, None  # raised once (the exit stack calls again)
        if error is not None:
            raise AssertionError(f"decoding failed: {error!r}") from error


@dataclass
class MotorTest:
    label: str
    motor: int  # param1 as sent; which output ArduCopter drives is read from the tap
    sent: float
    ack: int
    end: float = 0.0


@dataclass
class Flight:
    ap: ArduCopter
    gcs: GroundStation
    rigs: list[Rig]
    started: float
    events: dict[str, float] = field(default_factory=dict)
    motor_tests: list[MotorTest] = field(default_factory=list)
    heartbeat_rates: dict[int, tuple[int, float]] = field(default_factory=dict)
    servo_400: tuple[int, str, float] = (0, "", 0.0)
    arm_attempts: int = 0


# --------------------------------------------------------------------------------------------
# Flying it


def streaming(tap: MavTap, link: int, since: float, min_messages: int = 50) -> bool:
    rec = tap.records().get(link)
    return rec is not None and sum(1 for s in rec.servo if s.t >= since) >= min_messages


def heartbeat_granted(tap: MavTap, link: int, window_s: float = 0.5) -> bool:
    """Whether the autopilot's HEARTBEAT reaches ``link`` at about the HEARTBEAT_HZ its bridge
    asks for (four in five of them), over the newest ``window_s`` the tap logged."""
    rec = tap.records().get(link)
    if rec is None or not rec.heartbeats:
        return False
    newest = rec.heartbeats[-1][0]
    recent = sum(1 for t, _ in rec.heartbeats if t > newest - window_s)
    return recent >= 0.8 * HEARTBEAT_HZ * window_s


def first_spinning(rig: Rig, since: float) -> float | None:
    """When the first command frame with some motor non-zero since ``since`` was sent (as
    decoded so far)."""
    return next((f[0].t for f in rig.commands_since(since) if any(c.value > 0 for c in f)), None)


def wait_spinning(rig: Rig, since: float, within_s: float, what: str) -> None:
    """Assert that the rig's bridge sent a non-zero command within ``within_s`` of ``since``,
    by the frames' kernel stamps: on a loaded machine this process may read and decode the
    bus seconds behind it, so the answer waits until it has read past the deadline."""
    wait_until(
        lambda: first_spinning(rig, since) is not None or rig.decoded_until > since + within_s,
        within_s + 60,
        f"{what}: this process reading the bus up to {within_s} s after {since:.3f}",
    )
    first = first_spinning(rig, since)
    assert first is not None and first - since <= within_s, (
        f"{what}: no motor spinning within {within_s} s (first: "
        f"{'none' if first is None else f'{first - since:.3f} s'}; frames read up to "
        f"{rig.decoded_until - since:.3f} s)"
    )


def message_interval(gcs: GroundStation, msg_id: int, hz: float) -> tuple[int, float]:
    """Ask for ``msg_id`` at ``hz`` on the ground station's link: (ACK result, sent time)."""
    sent = gcs.send_command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
    return gcs.ack(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, sent, timeout_s=20), sent


def heartbeats_between_acks(gcs: GroundStation, after: float) -> int:
    """The autopilot's HEARTBEATs between the first two SET_MESSAGE_INTERVAL acknowledgements
    received after ``after``, in the order the link carried them: what the autopilot sent
    between acting on the two requests, however late this process read the link."""
    acks = 0
    beats = 0
    for _, m in gcs.received(after=after):
        if m.get_type() == "COMMAND_ACK" and m.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            acks += 1
            if acks == 2:
                return beats
        elif acks == 1 and m.get_type() == "HEARTBEAT" and from_autopilot(m):
            beats += 1
    raise AssertionError("two SET_MESSAGE_INTERVAL acknowledgements were not received")


def measure_heartbeat_rates(flight: Flight) -> None:
    """What ArduCopter makes of MAV_CMD_SET_MESSAGE_INTERVAL for HEARTBEAT (id 0)."""
    gcs = flight.gcs
    for hz in (10, 50, 400):
        # Counted between the request's acknowledgement and that of the same request again,
        # 1.2 s later, over the time between the two sends: this process's reader, which
        # lagged over a second behind in the whole suite, does not enter the count.
        result, sent = message_interval(gcs, 0, hz)
        time.sleep(1.2)
        _, again = message_interval(gcs, 0, hz)
        flight.heartbeat_rates[hz] = (result, heartbeats_between_acks(gcs, sent) / (again - sent))
    # The rate the motor-test measurement below uses on this link.
    message_interval(gcs, 0, 50)
    result, sent = message_interval(gcs, 36, 400)
    time.sleep(0.3)
    # ArduPilot splits a long STATUSTEXT into chunks sharing a non-zero id.
    chunks = [m for _, m in gcs.received("STATUSTEXT", sent) if m.id]
    texts = "".join(m.text for m in chunks if m.id == chunks[0].id) if chunks else ""
    message_interval(gcs, 36, STREAM_HZ)
    time.sleep(1.0)
    got = [m for _, m in gcs.received("SERVO_OUTPUT_RAW", time.monotonic() - 0.8)]
    flight.servo_400 = (result, texts, len(got) / 0.8)


def motor_test(flight: Flight, label: str, motor: int, seconds: float) -> MotorTest:
    """ArduCopter's own motor test, sent by the ground station to the autopilot."""
    sent = flight.gcs.send_command(
        mavlink.MAV_CMD_DO_MOTOR_TEST,
        motor,
        mavlink.MOTOR_TEST_THROTTLE_PERCENT,
        TEST_THROTTLE_PERCENT,
        seconds,
        0,
        mavlink.MOTOR_TEST_ORDER_BOARD,
    )
    result = flight.gcs.ack(mavlink.MAV_CMD_DO_MOTOR_TEST, sent)
    test = MotorTest(label, motor, sent, result)
    flight.motor_tests.append(test)
    return test


def wait_disarmed_at_gcs(flight: Flight, after: float, timeout_s: float, what: str) -> float:
    flight.gcs.wait_for(
        "HEARTBEAT",
        lambda m: from_autopilot(m) and not armed(m),
        timeout_s,
        after,
        first=True,
        what=what,
    )
    return time.monotonic()


def wait_motor_test_over(flight: Flight, test: MotorTest, what: str) -> float:
    """When ``test`` ended at the ground station: the first disarmed HEARTBEAT after the armed
    one it began with (ArduCopter reports armed during its own motor test), in the order they
    arrived. Not by receive time: a disarmed HEARTBEAT from before the test, read in one batch
    with the first armed one, has its stamp (most likely what ended test A 40 ms in, in one run
    of the suite, the next test sent while this one still ran; before that, at load 8, one
    stamped after ``test.sent`` did)."""

    def armed_states() -> list[bool]:
        beats = flight.gcs.received("HEARTBEAT", test.sent)
        return [armed(m) for _, m in beats if from_autopilot(m)]

    def over(states: list[bool]) -> bool:
        return True in states and False in states[states.index(True) :]

    # Generous: a wait for ArduCopter's report, read by this process's ground station thread,
    # which may lag seconds behind beside the decoding of two busy buses; no time is judged.
    wait_until(lambda: True in armed_states(), 20, f"{what}: armed")
    return wait_until(lambda: over(armed_states()), 20, f"{what}: disarmed after")


def arm_and_take_off(flight: Flight, altitude_m: float) -> None:
    gcs = flight.gcs
    deadline = flight.events["restart"] + 120 if "restart" in flight.events else 0
    deadline = max(deadline, time.monotonic() + 120)
    while True:  # pre-arm checks refuse until the EKF is happy (~40 s after start)
        sent = gcs.send_command(mavlink.MAV_CMD_DO_SET_MODE, 1, 4)  # custom mode 4: GUIDED
        gcs.ack(mavlink.MAV_CMD_DO_SET_MODE, sent)
        sent = gcs.send_command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        flight.arm_attempts += 1
        if gcs.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, sent) == mavlink.MAV_RESULT_ACCEPTED:
            break
        if time.monotonic() > deadline:
            texts = [m.text for _, m in gcs.received("STATUSTEXT", sent)]
            raise AssertionError(f"ArduCopter refused to arm for 120 s: {texts}")
        time.sleep(1.0)
    flight.events["armed"] = time.monotonic()
    sent = gcs.send_command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, altitude_m)
    result = gcs.ack(mavlink.MAV_CMD_NAV_TAKEOFF, sent)
    assert result == mavlink.MAV_RESULT_ACCEPTED, f"takeoff refused: {result}"
    gcs.wait_for(
        "GLOBAL_POSITION_INT",
        lambda m: m.relative_alt >= 900 * altitude_m,
        30,
        sent,
        first=True,
        what=f"altitude {0.9 * altitude_m} m after takeoff",
    )
    flight.events["hover"] = time.monotonic()


def fly(flight: Flight, tap: MavTap) -> None:
    ap, gcs = flight.ap, flight.gcs
    # Both bridges ask for SERVO_OUTPUT_RAW themselves; wait until it flows to each.
    for rig in flight.rigs:
        wait_until(
            lambda rig=rig: streaming(tap, rig.link, flight.started),  # type: ignore[misc]
            40,
            f"SERVO_OUTPUT_RAW reaching the {rig.name} bridge",
        )
    flight.events["streaming"] = time.monotonic()
    # The bridges learn the arming from HEARTBEAT alone, and ask for it at HEARTBEAT_HZ only
    # after the outputs' rate (one request a second): the motor test is timed against that rate,
    # so it starts once each link has it. (In one run's two flights it was granted under a
    # second before the wait above ended; a motor test started before it would wait up to
    # ArduCopter's default HEARTBEAT period: the likely cause, not shown, of a 416 ms start in CI.)
    for rig in flight.rigs:
        wait_until(
            lambda rig=rig: heartbeat_granted(tap, rig.link),  # type: ignore[misc]
            20,
            f"HEARTBEAT at {HEARTBEAT_HZ} Hz reaching the {rig.name} bridge",
        )

    # 1. While the autopilot boots (disarmed, on the ground, the EKF not ready to arm yet):
    # ArduCopter's own motor test, cut short by killing the autopilot. It is asked for 30 s:
    # the kill must come while it runs, after this process saw each bridge spin the motor,
    # which on a loaded machine it may see seconds late (wait_spinning).
    test = motor_test(flight, "B", 2, 30.0)
    assert test.ack == mavlink.MAV_RESULT_ACCEPTED, f"motor test refused: {test.ack}"
    for rig in flight.rigs:
        wait_spinning(rig, test.sent, 3.0, f"the {rig.name} bridge in ArduCopter's motor test")
    time.sleep(0.5)
    flight.events["kill"] = time.monotonic()
    ap.kill()
    test.end = flight.events["kill"]
    time.sleep(0.5)

    # 2. The restart: the same working directory and instance, so the same ports. While it
    # boots (~40 s before it lets itself be armed): the rates ArduCopter grants, and two more
    # motor tests, the first with HEARTBEAT at 50 Hz on the ground station's link.
    flight.events["restart"] = time.monotonic()
    ap.start()
    gcs.connect(20)
    gcs.wait_for("HEARTBEAT", from_autopilot, 20, flight.events["restart"], what="HEARTBEAT")
    for rig in flight.rigs:
        wait_until(
            lambda rig=rig: streaming(tap, rig.link, flight.events["restart"], 20),  # type: ignore[misc]
            30,
            f"SERVO_OUTPUT_RAW reaching the {rig.name} bridge after the restart",
        )
    measure_heartbeat_rates(flight)
    test = motor_test(flight, "A", 3, 2.0)
    assert test.ack == mavlink.MAV_RESULT_ACCEPTED, f"motor test refused: {test.ack}"
    test.end = wait_motor_test_over(flight, test, "motor test A at the ground station")
    message_interval(gcs, 0, 1)  # back to ArduCopter's usual HEARTBEAT on this link too
    test = motor_test(flight, "C", 4, 2.0)
    assert test.ack == mavlink.MAV_RESULT_ACCEPTED, f"motor test refused: {test.ack}"
    test.end = wait_motor_test_over(flight, test, "motor test C at the ground station")
    message_interval(gcs, 33, 10)  # GLOBAL_POSITION_INT, for the altitude

    # 3. The flight, on the restarted autopilot, the stall in its hover.
    arm_and_take_off(flight, 3.0)
    time.sleep(2.0)
    flight.events["stall"] = time.monotonic()
    ap.pause()
    time.sleep(1.0)
    ap.resume()
    flight.events["resume"] = time.monotonic()
    time.sleep(RECOVERY_WAIT_S)
    sent = gcs.send_command(mavlink.MAV_CMD_DO_SET_MODE, 1, 9)  # LAND
    assert gcs.ack(mavlink.MAV_CMD_DO_SET_MODE, sent) == mavlink.MAV_RESULT_ACCEPTED
    flight.events["land"] = sent
    flight.events["disarmed"] = wait_disarmed_at_gcs(flight, sent, 40, "disarmed after LAND")


def fly_rigs(build: ArduCopterBuild, workdir: Path, names: Sequence[str]) -> Flight:
    """ArduCopter with the rigs ``names`` on its links, through the whole flight; its record,
    every process stopped."""
    with contextlib.ExitStack() as stack:
        instance = stack.enter_context(
            reserved_instance(ARDUPILOT_SERIAL_PORTS, ARDUPILOT_UDP_PORTS)
        )
        ap = ArduCopter(build, workdir, instance, {"SIM_ESC_TELEM": 0})
        stack.callback(ap.stop)
        tap = MavTap(workdir, [ap.port(n) for n in SERIALS[: len(names)]])
        stack.callback(tap.stop)
        rigs = []
        for link, name in enumerate(names):
            spec, component = RIGS[name], 191 + link
            can_port = free_port()
            observer = wide_observer(can_port)
            stack.callback(observer.close)
            sim = start_sim(can_port, workdir / f"sim-{name}.log", name)
            stack.callback(sim.stop)
            config = write_bridge_config(
                workdir / f"{name}.toml",
                component_id=component,
                protocol=name,
                stream_rate_hz=STREAM_HZ,
                input_timeout_ms=round(INPUT_TIMEOUT_S * 1000),
            )
            bridge = start_bridge(
                config,
                f"tcp:127.0.0.1:{tap.listen_ports[link]}",
                can_port,
                workdir / f"bridge-{name}.log",
                "--vehicle",
                name,
            )
            stack.callback(bridge.stop)
            rigs.append(
                Rig(
                    name,
                    link,
                    component,
                    can_port,
                    observer,
                    bridge,
                    sim,
                    spec.expected,
                    spec.tolerance,
                    esc_period_s(config),
                    frame_reader(name),
                )
            )
        decoding = Decoding(rigs)
        stack.callback(decoding.finish)
        ap.start()
        started = time.monotonic()
        gcs = GroundStation(f"tcp:127.0.0.1:{ap.port(0)}")
        stack.callback(gcs.close)
        result = Flight(ap, gcs, rigs, started)
        try:
            fly(result, tap)
        except Exception as exc:
            logs = "\n".join(
                f"--- {p.log_path.name} ---\n{p.tail(15)}"
                for p in [*(r.bridge for r in rigs), ap.process]
                if p is not None
            )
            raise AssertionError(f"the flight failed: {exc}\n{logs}") from exc
        finally:
            records = tap.records()
            for rig in rigs:
                rig.tap = records.get(rig.link, TapRecord())
                rig.bridge_exit = rig.bridge.stop()
                rig.observer_drops = udp_drops(rig.observer.bus)
            decoding.finish()
            for rig in rigs:
                rig.prepare()
        result.events["end"] = time.monotonic()
        measured(
            f"ArduCopter flight wall time ({flight_id(tuple(names))})",
            f"{result.events['end'] - started:.1f} s",
        )
        measured(
            f"ArduCopter SITL and its tap at SCHED_FIFO 5 ({flight_id(tuple(names))})",
            f"{ap.realtime}, {tap.realtime}",
        )
        for rig in rigs:
            measured(
                f"{rig.name} frames decoded by the test",
                f"{rig.decoded} in {rig.decode_s:.1f} s (its decoding thread, during the flight)",
            )
        measured(
            f"ArduCopter arming accepted ({flight_id(tuple(names))})",
            f"{result.events['armed'] - result.events['restart']:.1f} s after its (re)start, "
            f"attempt {result.arm_attempts}",
        )
    return result


class Flights:
    """The module's flights (:data:`FLIGHTS`), each flown the first time a test asks for it and
    kept, or its failure kept: a flight is flown once."""

    def __init__(self, build: ArduCopterBuild, tmp_path_factory: pytest.TempPathFactory) -> None:
        self._build = build
        self._tmp = tmp_path_factory
        self._flown: dict[tuple[str, ...], Flight | str] = {}

    def of(self, rig_name: str) -> Flight:
        """The flight that ``rig_name`` flew in."""
        return self.group(next(g for g in FLIGHTS if rig_name in g))

    def group(self, names: tuple[str, ...]) -> Flight:
        if names not in self._flown:
            workdir = self._tmp.mktemp("arducopter-" + "-".join(names))
            try:
                self._flown[names] = fly_rigs(self._build, workdir, names)
            except Exception as exc:  # noqa: BLE001 - kept, and raised for every test
                self._flown[names] = f"{exc}"
        flown = self._flown[names]
        if isinstance(flown, str):
            raise AssertionError(f"the flight of {'+'.join(names)} failed: {flown}")
        return flown


@pytest.fixture(scope="module")
def flights(arducopter_build: ArduCopterBuild, tmp_path_factory: pytest.TempPathFactory) -> Flights:
    return Flights(arducopter_build, tmp_path_factory)


def flight_id(names: tuple[str, ...]) -> str:
    return "+".join(names)


# --------------------------------------------------------------------------------------------
# Reading the record


def ms(seconds: float) -> str:
    return f"{seconds * 1000:.0f} ms"


def pct(values: Sequence[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def armed_at(rig: Rig, t: float) -> bool:
    """The arming state of the newest HEARTBEAT the tap forwarded before ``t``."""
    beats = rig.tap.heartbeats
    i = bisect.bisect_right([b[0] for b in beats], t) - 1
    return i >= 0 and beats[i][1]


def armed_throughout(rig: Rig, start: float, end: float) -> bool:
    """Whether the autopilot was armed at ``start`` and the tap forwarded no disarmed HEARTBEAT
    up to ``end``."""
    beats = rig.tap.heartbeats
    i = bisect.bisect_right([b[0] for b in beats], start) - 1
    if i < 0 or not beats[i][1]:
        return False
    return all(armed for t, armed in beats[i + 1 :] if t <= end)


def judged(rig: Rig, start: float, end: float) -> list[list[Command]]:
    """The frames sent in [start, end] that must carry the newest motor output: the autopilot
    armed throughout the time the frame may answer to (from a whole output period and
    ARMING_LATE_S before it, to CLOCK_SKEW_S after it: the bridge obeys the HEARTBEAT, not the
    outputs, and obeys a disarm at once; at the end of a motor test the bridge sent a zero 4 ms
    after ArduCopter's last 1200 µs output, the disarm between them) and the newest motor
    output fresh (forwarded within FRESH_S) and not just after a silence (RESUME_S)."""
    out = []
    for frame in rig.commands:
        t = frame[0].t
        if not start <= t <= end:
            continue
        if not armed_throughout(rig, t - PERIOD_S - ARMING_LATE_S, t + CLOCK_SKEW_S):
            continue
        i = rig.newest_index(t)
        if i >= 0 and t - rig.tap.servo[i].t <= FRESH_S and not rig.soon_after_silence(t):
            out.append(frame)
    return out


def clock_lags(rig: Rig, start: float, end: float) -> list[str]:
    """Where the autopilot's clock fell behind ours by more than 30 ms (a SITL process that
    waited for a CPU, or was stopped): the least offset between the tap's stamp and the
    message's ``time_usec`` per half second, compared with the half second before. The bridge
    then rightly judges the inputs that much older, which explains zero frames with input
    that looks fresh at the tap."""
    least: dict[int, float] = {}
    for s in rig.tap.servo:
        if start <= s.t <= end:
            k = int((s.t - start) * 2)
            least[k] = min(least.get(k, float("inf")), s.t - s.time_usec / 1e6)
    keys = sorted(least)
    return [
        f"{(least[b] - least[a]) * 1000:.0f} ms at t={b / 2:.1f} s of the phase"
        for a, b in itertools.pairwise(keys)
        if least[b] - least[a] > 0.03
    ]


def phases(flight: Flight) -> dict[str, tuple[float, float]]:
    e = flight.events
    tests = {t.label: t for t in flight.motor_tests}
    return {
        "motor test A": (tests["A"].sent, tests["A"].end),
        "takeoff and hover": (e["armed"], e["stall"]),
        # From 0.1 s after SIGCONT: the bridge judges the first inputs after the pause old
        # until their rhythm confirms it (test_stall_recovers_after_sigcont: within 50 ms).
        # To 0.2 s before the ground station saw the landing's disarm: the bridge may act on
        # that HEARTBEAT within one output period of the tap's stamp, which the armed_at rule
        # would count as armed (the HEARTBEAT tests judge the disarm).
        "hover after the stall, land": (e["resume"] + RESUME_S, e["disarmed"] - 0.2),
        "motor test B (killed)": (tests["B"].sent, e["kill"]),
        "motor test C": (tests["C"].sent, tests["C"].end),
    }


PHASES = [
    "motor test A",
    "takeoff and hover",
    "hover after the stall, land",
    "motor test B (killed)",
    "motor test C",
]


def phase_params() -> list[Any]:
    params = []
    for rig in RIG_NAMES:
        for phase in PHASES:
            params.append(pytest.param(rig, phase, id=f"{rig}-{phase}"))
    return params


def rig_of(flight: Flight, name: str) -> Rig:
    return next(r for r in flight.rigs if r.name == name)


def first_test_input(rig: Rig, test: MotorTest) -> tuple[ServoOutput, int]:
    """The first motor output of ``test`` that moved a motor, and which (0-based)."""
    for servo in rig.tap.servo:
        if servo.t >= test.sent and any(v != 1000 for v in servo.servos[:4]):
            moved = [i for i, v in enumerate(servo.servos[:4]) if v != 1000]
            assert len(moved) == 1, f"motor test {test.label} moved outputs {moved}: {servo}"
            return servo, moved[0]
    raise AssertionError(f"motor test {test.label}: no output moved on the {rig.name} link")


# --------------------------------------------------------------------------------------------
# The checks


def lag_of(rig: Rig, command: Command) -> str:
    """Which output a command off the newest carries, and the gap before its frame: a gap says
    the bridge's loop was held up between reading and sending, none that it read late."""
    newest = rig.newest_index(command.t)
    carried = next(
        (
            k
            for k in range(newest, max(newest - 100, -1), -1)
            if rig.matches(command.value, {rig.value_of(rig.tap.servo[k], command.motor)})
        ),
        None,
    )
    sent = [f[0].t for f in rig.commands]
    k = bisect.bisect_left(sent, command.t)
    gap = f"the frame before {ms(command.t - sent[k - 1])} before" if k else "the first frame"
    if carried is None:
        return f"none of the last 100 outputs carries it; {gap}"
    return (
        f"it is the output {newest - carried} before the newest, forwarded "
        f"{ms(command.t - rig.tap.servo[carried].t)} before; {gap}"
    )


@pytest.mark.parametrize(("rig_name", "phase"), phase_params())
def test_every_frame_carries_the_newest_motor_output(
    flights: Flights, rig_name: str, phase: str
) -> None:
    """Every command frame sent while armed with fresh input equals the passthrough scaling of
    the newest SERVO_OUTPUT_RAW, with the lag fixed-rate sending implies: the frame at t
    carries the newest output the tap had begun to forward by t, the one before it, or one
    forwarded within the output period before t (Rig.allowed).

    But a frame that left late: a loop held up after its last look at the clock (its virtual
    CPU taken by the host, at SCHED_FIFO) sends, when it runs again, what it decided before.
    No process can prevent that, and the bridge counts each such tick (``left late`` in its
    exit summary). So a frame off the newest passes only if it came over a tick after the frame
    before it (the ticks between were missed), it carries what the bridge had at some moment
    since that frame (Rig.allowed_between), and the bridge counted at least as many ticks left
    late in the flight as the phase has such frames."""
    flight = flights.of(rig_name)
    rig = rig_of(flight, rig_name)
    start, end = phases(flight)[phase]
    frames = judged(rig, start, end)
    sent = [f[0].t for f in rig.commands]
    after_silence = sum(
        1 for f in rig.commands if start <= f[0].t <= end and rig.soon_after_silence(f[0].t)
    )
    assert len(frames) >= 100, (
        f"{phase}: only {len(frames)} {rig_name} frames sent armed with fresh input "
        f"(of {sum(1 for f in rig.commands if start <= f[0].t <= end)} in the phase)"
    )
    wrong = []
    late = []  # frames off the newest that left late
    exact = 0
    for frame in frames:
        t = frame[0].t
        newest = rig.tap.servo[rig.newest_index(t)]
        if all(c.value == rig.value_of(newest, c.motor) for c in frame):
            exact += 1
        off = [c for c in frame if not rig.matches(c.value, rig.allowed(t, c.motor))]
        k = bisect.bisect_left(sent, t)
        before = sent[k - 1] if k else None
        if (
            off
            and before is not None
            and t - before > PERIOD_S + CLOCK_SKEW_S
            and all(rig.matches(c.value, rig.allowed_between(before, t, c.motor)) for c in off)
        ):
            late.append(t)
            continue
        for c in off:
            wrong.append(
                f"t={t - flight.started:.3f} s motor {c.motor + 1}: {c.value:g}, allowed "
                f"{sorted(rig.allowed(t, c.motor))}; newest output {newest.servos[:4]} "
                f"forwarded {ms(t - newest.t)} before; {lag_of(rig, c)}"
            )
    measured(
        f"{rig_name} tracking, {phase}",
        f"{exact / len(frames):.1%} of {len(frames)} frames equal the newest output exactly, "
        f"{1 - len(wrong) / len(frames) / len(frames[0]):.2%} within one period; "
        f"{after_silence} frames within {RESUME_S * 1000:.0f} ms after a silence of the "
        f"outputs not judged; {len(late)} left late",
    )
    counted = rig.left_late()
    assert len(late) <= counted, (
        f"{len(late)} frames off the newest output after a gap, at t = "
        f"{[round(t - flight.started, 3) for t in late[:10]]} s, but the bridge counted "
        f"{counted} ticks left late"
    )
    assert not wrong, (
        f"{len(wrong)} commands off the newest output:\n"
        + "\n".join(wrong[:10])
        + f"\nthe autopilot's clock fell behind: {clock_lags(rig, start, end)}"
    )


@pytest.mark.parametrize(
    ("rig_name", "phase"),
    [
        pytest.param(r, p, id=f"{r}-{p}")
        for r in RIG_NAMES
        for p in ("takeoff and hover", "hover after the stall, land")
    ],
)
def test_no_zero_frames_in_flight(flights: Flights, rig_name: str, phase: str) -> None:
    """No all-zero (safe) frame while armed with fresh input, unless every output it may carry
    (Rig.allowed: the newest, or one of lag) scales to zero there."""
    flight = flights.of(rig_name)
    rig = rig_of(flight, rig_name)
    start, end = phases(flight)[phase]
    frames = judged(rig, start, end)
    blips = [
        f[0].t - flight.started
        for f in frames
        if all(c.value == 0 for c in f)
        and not all(rig.matches(0, rig.allowed(f[0].t, c.motor)) for c in f)
    ]
    measured(f"{rig_name} zero frames in flight, {phase}", f"{len(blips)} of {len(frames)}")
    assert len(frames) >= 100, f"only {len(frames)} frames judged"
    assert not blips, (
        f"{len(blips)} all-zero frames in flight, at t = {blips[:10]} s; the autopilot's clock "
        f"fell behind: {clock_lags(rig, start, end)}"
    )


def gap_after(rig: Rig, t: float) -> tuple[ServoOutput, ServoOutput]:
    """The last motor output before, and the first after, the first silence of over 0.5 s
    that ends after ``t`` (a stall, a kill): found in the record rather than taken from when
    the signal was sent, since bytes written just before it still arrive after it."""
    servo = rig.tap.servo
    for a, b in itertools.pairwise(servo[max(rig.newest_index(t), 0) :]):
        if b.t - a.t > 0.5:
            return a, b
    raise AssertionError(f"no gap in the {rig.name} link's motor outputs after t={t}")


def safe_deadline_check(rig: Rig, until: float, what: str) -> tuple[float, float]:
    """From the last motor output forwarded before the gap that ends at ``until`` (the
    autopilot stopped or died; bytes it wrote just before still arrive after the signal, so
    the gap is where the outputs stop, not when the signal was sent), every ESC gets a safe
    (zero) command within input_timeout + 2 output periods, and nothing but safe commands
    follow until ``until``. Returns (last input, first safe frame)."""
    last = rig.tap.servo[rig.newest_index(until - 1e-6)]
    deadline = last.t + INPUT_TIMEOUT_S + 2 * rig.esc_period_s
    after = [c for f in rig.commands for c in f if last.t < c.t <= until]
    zero_by = {
        m: min((c.t for c in after if c.motor == m and c.value == 0), default=None)
        for m in range(4)
    }
    late = {m + 1: t for m, t in zero_by.items() if t is None or t > deadline}
    assert not late, (
        f"{what}: ESC(s) {sorted(late)} got no safe command within "
        f"{ms(deadline - last.t)} of the last input (first at "
        f"{[None if t is None else ms(t - last.t) for t in late.values()]})"
    )
    nonzero = [c for c in after if c.t > deadline and c.value != 0]
    assert not nonzero, (
        f"{what}: {len(nonzero)} non-zero commands after the failsafe deadline, the first "
        f"{ms(nonzero[0].t - last.t)} after the last input: {nonzero[:3]}"
    )
    first_safe = min(t for t in zero_by.values() if t is not None)
    return last.t, first_safe


@pytest.mark.parametrize("rig_name", RIG_NAMES)
def test_stall_goes_safe_in_time(flights: Flights, rig_name: str) -> None:
    """SIGSTOP of the autopilot for 1 s mid-hover: safe within input_timeout + 2 periods."""
    flight = flights.of(rig_name)
    rig = rig_of(flight, rig_name)
    e = flight.events
    _, first_after = gap_after(rig, e["stall"] - 0.1)
    last, first_safe = safe_deadline_check(rig, first_after.t, "stall")
    assert armed_at(rig, last), "the stall was not in flight"
    measured(f"{rig_name} failsafe after SIGSTOP", f"{ms(first_safe - last)} after the last input")


@pytest.mark.parametrize("rig_name", RIG_NAMES)
def test_stall_recovers_after_sigcont(flights: Flights, rig_name: str) -> None:
    """After SIGCONT the bridge tracks the motor outputs again within a few output periods."""
    flight = flights.of(rig_name)
    rig = rig_of(flight, rig_name)
    e = flight.events
    _, resumed = gap_after(rig, e["stall"] - 0.1)
    running = [f[0].t for f in rig.commands if f[0].t > resumed.t and any(c.value > 0 for c in f)]
    recovery = running[0] - resumed.t if running else None
    measured(
        f"{rig_name} recovery after SIGCONT",
        f"{ms(recovery)} after the first input" if recovery is not None else "never (in flight)",
    )
    assert recovery is not None and recovery <= 0.05, (
        f"no non-zero frame within 50 ms of the first input after SIGCONT "
        f"(first: {None if recovery is None else ms(recovery)}); bridge log:\n"
        + "\n".join(rig.bridge.tail(8).splitlines())
    )


@pytest.mark.parametrize("rig_name", RIG_NAMES)
def test_kill_and_restart(flights: Flights, rig_name: str) -> None:
    """The autopilot killed mid motor test: safe values in time, kept up (the loop goes on
    sending), then the bridge reconnects to the restarted autopilot and gets its outputs."""
    flight = flights.of(rig_name)
    rig = rig_of(flight, rig_name)
    e = flight.events
    last, first_safe = safe_deadline_check(rig, e["restart"], "kill")
    assert armed_at(rig, last), "the kill was not while the outputs were armed"
    outage = [f for f in rig.commands if e["kill"] + 0.2 <= f[0].t <= e["restart"]]
    expected = (e["restart"] - e["kill"] - 0.2) / PERIOD_S
    assert len(outage) >= 0.5 * expected, (
        f"the bridge sent {len(outage)} frames while the autopilot was dead (~{expected:.0f} "
        "expected): it must keep the ESCs fed with safe values"
    )
    inputs = [s for s in rig.tap.servo if s.t > e["restart"]]
    assert inputs, "no SERVO_OUTPUT_RAW reached the bridge after the restart"
    reconnect = inputs[0].t - e["restart"]
    measured(f"{rig_name} failsafe after kill", f"{ms(first_safe - last)} after the last input")
    measured(
        f"{rig_name} reconnect after restart",
        f"{reconnect:.2f} s from the autopilot's start to the first motor output at the bridge",
    )
    assert reconnect < 15, f"the bridge got outputs only {reconnect:.1f} s after the restart"


def motor_tests_of(flight: Flight) -> list[MotorTest]:
    """The motor tests in the order they ran (B, killed, first)."""
    return list(flight.motor_tests)


@pytest.mark.parametrize("rig_name", RIG_NAMES)
def test_ardupilot_motor_test_spins_the_right_motor(flights: Flights, rig_name: str) -> None:
    """ArduCopter's own DO_MOTOR_TEST: the ESC on the output ArduCopter drives spins at the
    test's value, and no other ESC gets anything but zero."""
    flight = flights.of(rig_name)
    rig = rig_of(flight, rig_name)
    for test in motor_tests_of(flight):
        first, motor = first_test_input(rig, test)
        assert first.servos[motor] == TEST_PWM
        frames = [c for f in rig.commands for c in f if first.t <= c.t <= test.end]
        others = [c for c in frames if c.motor != motor and c.value != 0]
        assert not others, f"motor test {test.label}: other motors commanded: {others[:3]}"
        spun = [c for c in frames if c.motor == motor and c.value != 0]
        assert spun, f"motor test {test.label}: motor {motor + 1} never commanded"
        assert all(rig.matches(c.value, {rig.expected(TEST_PWM)}) for c in spun), spun[:3]
        measured(
            f"ArduCopter motor test {test.label}: param1 {test.motor} drives", f"servo{motor + 1}"
        )


@pytest.mark.parametrize("rig_name", RIG_NAMES)
def test_ardupilot_motor_test_within_a_heartbeat_period(flights: Flights, rig_name: str) -> None:
    """The motor spins within one HEARTBEAT period (at the 20 Hz the bridge asks for and
    ArduCopter grants) of the test's first output reaching the bridge, plus a tick and the
    machine's slack. Not from the first frame: the bridge learns ArduCopter's arming from its
    HEARTBEAT only (SERVO_OUTPUT_RAW carries none), so up to one period of the test's outputs
    go out as zeros (measured 0-53 ms; on the first frame in some tests, not in others)."""
    flight = flights.of(rig_name)
    rig = rig_of(flight, rig_name)
    delays = []
    for test in motor_tests_of(flight):
        first, motor = first_test_input(rig, test)
        mine = [c for f in rig.commands for c in f if c.motor == motor and c.t > first.t]
        spinning = [c for c in mine if c.value != 0]
        delays.append(spinning[0].t - first.t if spinning else float("inf"))
    measured(
        f"{rig_name} motor test first non-zero frame",
        ", ".join(f"{t.label} {ms(d)}" for t, d in zip(motor_tests_of(flight), delays, strict=True))
        + " after the first test output",
    )
    bound = 1 / HEARTBEAT_HZ + MOTOR_TEST_SLACK_S
    assert max(delays) <= bound, f"motor test delays {[ms(d) for d in delays]} (bound {ms(bound)})"


def longest_gap(times: Iterable[float], start: float, end: float) -> float:
    """The longest time between two of ``times`` (or ``start``/``end``) within [start, end]."""
    within = [start, *(t for t in times if start <= t <= end), end]
    return max(b - a for a, b in itertools.pairwise(within))


def forwarding_context(
    flight: Flight, received: list[tuple[float, Any]], start: float, end: float
) -> str:
    """Whether the ground station heard ArduCopter itself and the other bridges between
    ``start`` and ``end``: a silence of everything points at the station or ArduCopter's
    forwarding, a silence of one bridge at that bridge."""
    own = [t for t, _ in flight.gcs.received(after=start, sender=(1, 1)) if t <= end]
    silence = longest_gap(own, start, end)
    counts = {
        rig.name: sum(
            1 for t, m in received if m.get_srcComponent() == rig.component and start <= t <= end
        )
        for rig in flight.rigs
    }
    return (
        f"ArduCopter's own messages there: {len(own)}, the longest silence {silence:.2f} s; "
        f"ESC_TELEMETRY_1_TO_4 of each bridge there: {counts}"
    )


@pytest.mark.parametrize("names", FLIGHTS, ids=flight_id)
def test_esc_telemetry_reaches_the_ground_station(flights: Flights, names: tuple[str, ...]) -> None:
    """ESC_TELEMETRY_1_TO_4 from each bridge (components 191, 192), forwarded by ArduCopter
    to the ground station, carries the simulated ESCs' rpm and volts as they were on the bus
    (read as the family's neutral telemetry; erpm over the pole pairs); ArduCopter sends none
    of its own (SIM_ESC_TELEM 0)."""
    flight = flights.group(names)
    start, end = flight.events["hover"], flight.events["stall"]
    received = flight.gcs.received("ESC_TELEMETRY_1_TO_4", flight.started)
    own = [m for _, m in received if m.get_srcComponent() == 1]
    assert not own, f"ArduCopter sent ESC telemetry of its own: {own[:2]}"
    for rig in flight.rigs:
        offline: list[str] = []
        bus: dict[int, list[tuple[float, int, int]]] = {m: [] for m in range(4)}
        rpm_now: dict[int, int] = {}
        volts_now: dict[int, int] = {}
        for t, telemetry in rig.telemetry:
            m = telemetry.node_id - 1
            rpm = telemetry.rpm
            if rpm is None and telemetry.erpm is not None:
                rpm = int(telemetry.erpm / POLE_PAIRS)
            if rpm is None and telemetry.voltage_v is None:
                continue
            if rpm is not None:
                rpm_now[m] = abs(rpm)
            if telemetry.voltage_v is not None:
                volts_now[m] = round(telemetry.voltage_v * 100)
            if m in rpm_now and m in volts_now:
                bus[m].append((t, rpm_now[m], volts_now[m]))
        mine = [
            (t, m)
            for t, m in received
            if m.get_srcComponent() == rig.component and start <= t <= end
        ]
        sysid = mine[0][1].get_srcSystem() if mine else None
        # The bridge sends ArduPilot's link ESC_TELEMETRY_1_TO_4 at 2 Hz (its per-link set,
        # kept small for a telemetry radio), counted from the arming to the stall (takeoff
        # and hover, ~10 s: the hover alone is too short to tell a rate); a boundary may cut
        # one, ArduCopter's forwarding on a loaded machine drop another. The span ends with
        # the last message the station read from ArduCopter itself before the stall: what
        # ArduCopter forwarded after it was still on its way. (In CI the station once heard
        # none of this bridge's messages in the 1.48 s before the stall, and nothing at all
        # from ArduCopter for 1.19 s of the span: this process not running, most likely.)
        armed = flight.events["armed"]
        heard = max(t for t, _ in flight.gcs.received(after=armed, sender=(1, 1)) if t <= end)
        rate_span = [
            t for t, m in received if m.get_srcComponent() == rig.component and armed <= t <= heard
        ]
        hz = len(rate_span) / (heard - armed)
        gaps = [
            f"{b - a:.2f} s from {a - armed:.2f} s"
            for a, b in itertools.pairwise([armed, *rate_span, heard])
            if b - a > 0.75
        ]
        assert abs(len(rate_span) - 2 * (heard - armed)) <= 2.5, (
            f"{len(rate_span)} ESC_TELEMETRY_1_TO_4 from the {rig.name} bridge (component "
            f"{rig.component}) reached the ground station in {heard - armed:.1f} s of takeoff "
            f"and hover ({hz:.1f} Hz; 2 Hz expected); gaps over 0.75 s after arming: {gaps}; "
            + forwarding_context(flight, received, armed, heard)
        )
        assert len(mine) >= 2, f"{len(mine)} ESC_TELEMETRY_1_TO_4 from {rig.name} in hover"
        for t, msg in mine:
            for m in range(4):
                # The bus in the RELAY_LAG_S before the ground station got it (and a little
                # after: the stamps of two processes on a loaded machine can be a few ms apart).
                seen = [(r, v) for ts, r, v in bus[m] if t - RELAY_LAG_S <= ts <= t + 0.05]
                rpms, volts = {r for r, _ in seen}, {v for _, v in seen}
                silence = longest_gap((ts for ts, _, _ in bus[m]), t - RELAY_LAG_S, t)
                if silence > TELEMETRY_TIMEOUT_S - TELEMETRY_SLACK_S and msg.rpm[m] == 0:
                    # The ESC fell silent on the bus for longer than the bridge's timeout, so
                    # the bridge may rightly have called it offline: values unknown (0).
                    offline.append(f"ESC {m + 1} {t - start:.3f} s in ({ms(silence)} silent)")
                    continue
                assert msg.rpm[m] > 1000, (
                    f"{rig.name} ESC {m + 1}: {msg.rpm[m]} rpm in hover, {t - start:.3f} s "
                    f"after it began; the bus carried {sorted(rpms)[:8]} in the {RELAY_LAG_S:g} s "
                    f"before, its longest silence there {ms(silence)}"
                )
                assert any(abs(msg.rpm[m] - r) <= 1 for r in rpms), (
                    f"{rig.name} ESC {m + 1}: the ground station got {msg.rpm[m]} rpm; the bus "
                    f"carried {sorted(rpms, key=lambda r: abs(r - msg.rpm[m]))[:5]} (nearest) "
                    f"in the {RELAY_LAG_S:g} s before"
                )
                assert any(abs(msg.voltage[m] - v) <= 1 for v in volts), (
                    f"{rig.name} ESC {m + 1}: the ground station got {msg.voltage[m]} cV; the "
                    f"bus carried {sorted(volts)} in the {RELAY_LAG_S:g} s before"
                )
        measured(
            f"{rig.name} ESC_TELEMETRY_1_TO_4 at the ground station",
            f"{hz:.1f} Hz in hover from {sysid}/{rig.component}, values as on the bus; "
            f"offline after a silence on the bus: {', '.join(offline) or 'none'}",
        )
        # Rare, or the simulators cannot stand for ESCs: at most one reading in ten.
        assert len(offline) <= 0.1 * 4 * len(mine), f"{rig.name}: offline too often: {offline}"


@pytest.mark.parametrize("names", FLIGHTS, ids=flight_id)
def test_servo_output_rate(flights: Flights, names: tuple[str, ...]) -> None:
    """SERVO_OUTPUT_RAW reaches each bridge at the 200 Hz it asks for; 400 Hz is denied."""
    flight = flights.group(names)
    e = flight.events
    for rig in flight.rigs:
        times = [s.t for s in rig.tap.servo if e["armed"] <= s.t <= e["stall"]]
        rate = (len(times) - 1) / (times[-1] - times[0])
        gaps = [b - a for a, b in itertools.pairwise(times)]
        measured(
            f"{rig.name} SERVO_OUTPUT_RAW at the bridge (asked {STREAM_HZ} Hz)",
            f"{rate:.1f} Hz; gap p50 {ms(statistics.median(gaps))}, p99 {ms(pct(gaps, 0.99))},"
            f" max {ms(max(gaps))}",
        )
        answers = stream_answers(rig.bridge.output(), "SERVO_OUTPUT_RAW")
        measured(f"{rig.name} SERVO_OUTPUT_RAW request answered", answers)
        assert 0.9 * STREAM_HZ <= rate <= 1.1 * STREAM_HZ, f"{rig.name}: {rate:.1f} Hz"
        assert f"ACCEPTED {STREAM_HZ} Hz" in answers, f"{rig.name}: ArduCopter answered {answers}"
    result, texts, rate = flight.servo_400
    measured(
        "SERVO_OUTPUT_RAW at 400 Hz (ground station link)",
        f"ACK {result} ({texts.strip()}); the 200 Hz asked before stays: {rate:.0f} Hz",
    )
    assert result == mavlink.MAV_RESULT_DENIED


@pytest.mark.parametrize("names", FLIGHTS, ids=flight_id)
def test_heartbeat_interval(flights: Flights, names: tuple[str, ...]) -> None:
    """What a higher-rate HEARTBEAT request can rely on: ArduCopter honours
    MAV_CMD_SET_MESSAGE_INTERVAL for HEARTBEAT (id 0) up to its loop rate, per link."""
    flight = flights.group(names)
    rates = flight.heartbeat_rates
    measured(
        "HEARTBEAT interval (ground station link)",
        ", ".join(f"{hz} Hz asked: ACK {r}, {got:.0f}/s" for hz, (r, got) in rates.items()),
    )
    # At least 0.6 of the asked rate: a SITL process waiting for a CPU at load ~8 delivered 38
    # of 50 a second (its default is 1).
    for hz in (10, 50):
        result, got = rates[hz]
        assert result == mavlink.MAV_RESULT_ACCEPTED and 0.6 * hz <= got <= 1.2 * hz, rates
    assert rates[400][0] == mavlink.MAV_RESULT_DENIED, rates
    # Motor test A ran with HEARTBEAT at 50 Hz and SERVO_OUTPUT_RAW at 200 Hz on this link:
    # how long after the test's first output the armed HEARTBEAT came, by the autopilot's own
    # clock (the SERVO_OUTPUT_RAW just before that HEARTBEAT in the stream), so that this
    # process's receive jitter does not count.
    test = next(t for t in flight.motor_tests if t.label == "A")
    first_out: int | None = None
    newest_out = 0
    for _, m in flight.gcs.received(after=test.sent):
        if m.get_type() == "SERVO_OUTPUT_RAW":
            newest_out = m.time_usec
            moved = any(getattr(m, f"servo{i}_raw") != 1000 for i in range(1, 5))
            if first_out is None and moved:
                first_out = m.time_usec
        elif m.get_type() == "HEARTBEAT" and from_autopilot(m) and armed(m):
            break
    # None: the armed HEARTBEAT came before the test's first output.
    delay_s = 0.0 if first_out is None else (newest_out - first_out) / 1e6
    measured(
        "motor test A, armed HEARTBEAT at 50 Hz",
        "before the first test output"
        if first_out is None
        else f"within {ms(delay_s + 0.005)} of the first test output (autopilot clock)",
    )
    assert delay_s <= 0.025, f"armed HEARTBEAT {ms(delay_s)} after the test began"


@pytest.mark.parametrize("rig_name", RIG_NAMES)
def test_bus_clean_and_bridge_stopped_cleanly(flights: Flights, rig_name: str) -> None:
    """Every frame on the bus decodes (the bridge's commands and the ESCs' telemetry), the
    observer lost none of them, and the bridge, stopped with SIGTERM after the flight, exits
    0."""
    flight = flights.of(rig_name)
    rig = rig_of(flight, rig_name)
    assert rig.observer_drops == 0, f"the observer's socket dropped {rig.observer_drops} frames"
    assert not rig.malformed, f"{len(rig.malformed)} malformed frames: {rig.malformed[:5]}"
    assert rig.bridge_exit == 0, f"exit status {rig.bridge_exit}:\n{rig.bridge.tail(15)}"
