"""A simulated autopilot for the demo: an ArduPilot-like multirotor flying a scripted flight.

:func:`outputs_at` is the whole flight as a pure function of time: the phase, the arming state
and one PWM value per motor. :class:`SimAutopilot` plays it over MAVLink 2 on UDP (system 1,
component 1, to a bridge's ``udpin`` link): HEARTBEAT at 5 Hz and on every arming change, with
the armed flag in ``base_mode`` while armed, and SERVO_OUTPUT_RAW at 50 Hz. Like ArduCopter it
answers MAV_CMD_SET_MESSAGE_INTERVAL for those two with a COMMAND_ACK: ACCEPTED and streamed at
the rate asked up to its loop rate (:data:`LOOP_HZ`), DENIED above it.

The flight (:data:`PHASES`, 30 s in all):

==========  =====  ==============================================================
phase       s      motors
==========  =====  ==============================================================
preflight   2      disarmed, 1000 µs
arm         2      armed, idle 1100 µs
spool-up    2      all motors up to 1450 µs
take-off    3      climb at 1720 µs, then ease back to hover
hover       3      1590 µs with small corrections
roll        3      hover ± 100 µs by the rotors' roll factors: right, then left
pitch       3      hover ± 100 µs by the pitch factors: nose down, then up
yaw         3      hover ± 80 µs by spin direction: nose right, then left
descend     3      down to 1520 µs
land        3      down to 1150 µs, touch down at idle
disarm      3      disarmed, 1000 µs
==========  =====  ==============================================================

Motor numbers, positions and spin directions are those of the bundled X mixers
(``mixers/quad-x.toml``, ``hex-x.toml`` and ``octo-x.toml``: ArduPilot's order), and the roll,
pitch and yaw factors come from the geometry code the bridge mixes with
(:func:`bridge.mixing.geometry.mix_matrix`).

Only the project's MAVLink dialect module is used (:func:`bridge.mavlink.load_dialect`, always
MAVLink 2), never ``mavutil``, so the wire version does not depend on ``MAVLINK20``.
"""

from __future__ import annotations

import functools
import logging
import math
import socket
import threading
import time
from collections.abc import Sequence
from types import TracebackType
from typing import Any, Final, Literal

from bridge._compat import Self
from bridge.mavlink import load_dialect
from bridge.mixing.geometry import mix_matrix
from bridge.mixing.loader import load_mixer

log = logging.getLogger(__name__)

Airframe = Literal["quad", "hex", "octo"]
AIRFRAMES: Final[tuple[Airframe, ...]] = ("quad", "hex", "octo")

PWM_STOP_US: Final = 1000
PWM_MAX_US: Final = 2000
PWM_IDLE_US: Final = 1100
"""Armed and spinning slowly (ArduPilot's MOT_SPIN_ARM)."""
PWM_HOVER_US: Final = 1590
PWM_CLIMB_US: Final = 1720
PWM_DESCEND_US: Final = 1520
PWM_TOUCHDOWN_US: Final = 1150
ROLL_PITCH_US: Final = 100.0
"""Largest roll or pitch difference from the collective, for the motor with the largest factor."""
YAW_US: Final = 80.0
WOBBLE_US: Final = 4.0
"""Small corrections an autopilot makes while hovering."""

PHASES: Final[tuple[tuple[str, float], ...]] = (
    ("preflight", 2.0),
    ("arm", 2.0),
    ("spool-up", 2.0),
    ("take-off", 3.0),
    ("hover", 3.0),
    ("roll", 3.0),
    ("pitch", 3.0),
    ("yaw", 3.0),
    ("descend", 3.0),
    ("land", 3.0),
    ("disarm", 3.0),
)
"""The flight: (phase name, duration in seconds), in order."""
FLIGHT_S: Final = sum(duration for _, duration in PHASES)
ARMED_PHASES: Final = frozenset(name for name, _ in PHASES[1:-1])
WAITING: Final = "waiting"
"""The phase before :meth:`SimAutopilot.fly`: disarmed, 1000 µs."""

SERVO_HZ: Final = 50.0
"""SERVO_OUTPUT_RAW until asked for another rate."""
HEARTBEAT_HZ: Final = 5.0
"""HEARTBEAT until asked for another rate."""
LOOP_HZ: Final = 400.0
"""The fastest rate it streams anything at (ArduCopter's main loop rate): faster is DENIED."""
CLOSE_BURST: Final = 5
"""Disarmed HEARTBEAT + stopped outputs sent by close(), one per output period."""


def motor_count(airframe: Airframe) -> int:
    """How many motors the airframe has.

    Raises:
        ValueError: an unknown airframe.
    """
    return len(factors(airframe))


@functools.cache
def factors(airframe: Airframe) -> tuple[tuple[float, float, float], ...]:
    """(roll, pitch, yaw) factor of each motor, each axis scaled to a largest magnitude of 1.

    The columns of the bundled ``<airframe>-x`` mixer's mix matrix: positive roll is right side
    down (the left motors speed up), positive pitch nose up (the front motors), positive yaw
    nose right (the counter-clockwise motors, whose drag turns the frame clockwise).

    Raises:
        ValueError: an unknown airframe.
    """
    if airframe not in AIRFRAMES:
        raise ValueError(f"unknown airframe {airframe!r}; expected one of {', '.join(AIRFRAMES)}")
    matrix = mix_matrix(load_mixer(f"{airframe}-x").rotors)
    scales = [max(abs(row[axis]) for row in matrix) for axis in range(3)]
    return tuple(
        (
            _tidy(roll / scales[0]),
            _tidy(pitch / scales[1]),
            _tidy(yaw / scales[2]),
        )
        for roll, pitch, yaw, _ in matrix
    )


def outputs_at(t_s: float, airframe: Airframe) -> tuple[str, bool, list[int]]:
    """The flight at ``t_s`` seconds after its start: (phase, armed, PWM µs per motor).

    Before 0 it is ``preflight``; from :data:`FLIGHT_S` on, ``disarm`` (stopped). Every value
    is within 1000..2000 µs, and within 1100..2000 µs while armed.

    Raises:
        ValueError: an unknown airframe, or a time that is not a finite number.
    """
    if not math.isfinite(t_s):
        raise ValueError(f"time must be finite, got {t_s!r}")
    motors = factors(airframe)
    phase, u = _phase_at(t_s)
    armed = phase in ARMED_PHASES
    if not armed:
        return phase, False, [PWM_STOP_US] * len(motors)
    collective = _collective(phase, u)
    roll = pitch = yaw = 0.0
    wave = math.sin(2 * math.pi * u)
    if phase == "roll":
        roll = ROLL_PITCH_US * wave
    elif phase == "pitch":
        pitch = -ROLL_PITCH_US * wave  # nose down first: fly forward, then brake
    elif phase == "yaw":
        yaw = YAW_US * wave
    pwm = []
    for i, (k_roll, k_pitch, k_yaw) in enumerate(motors):
        value = collective + roll * k_roll + pitch * k_pitch + yaw * k_yaw
        if phase in ("hover", "descend"):
            value += WOBBLE_US * math.sin(2 * math.pi * (1.3 * t_s + i / len(motors)))
        pwm.append(round(min(PWM_MAX_US, max(PWM_IDLE_US, value))))
    return phase, True, pwm


def _tidy(x: float) -> float:
    return 0.0 if abs(x) < 1e-9 else round(x, 9)


def _phase_at(t_s: float) -> tuple[str, float]:
    """The phase at ``t_s`` and how far into it, 0..1."""
    if t_s < 0:
        return PHASES[0][0], 0.0
    start = 0.0
    for name, duration in PHASES:
        if t_s < start + duration:
            return name, (t_s - start) / duration
        start += duration
    return PHASES[-1][0], 1.0


def _ease(a: float, b: float, u: float) -> float:
    """From ``a`` to ``b`` as ``u`` goes 0..1, smoothly (no jump in slope at either end)."""
    u = min(1.0, max(0.0, u))
    return a + (b - a) * u * u * (3 - 2 * u)


def _collective(phase: str, u: float) -> float:
    if phase == "arm":
        return PWM_IDLE_US
    if phase == "spool-up":
        return _ease(PWM_IDLE_US, 1450, u)
    if phase == "take-off":
        if u < 0.4:
            return _ease(1450, PWM_CLIMB_US, u / 0.4)
        return _ease(PWM_CLIMB_US, PWM_HOVER_US, (u - 0.4) / 0.6)
    if phase == "descend":
        return _ease(PWM_HOVER_US, PWM_DESCEND_US, u / 0.3)
    if phase == "land":
        if u < 0.6:
            return _ease(PWM_DESCEND_US, PWM_TOUCHDOWN_US, u / 0.6)
        return _ease(PWM_TOUCHDOWN_US, PWM_IDLE_US, (u - 0.6) / 0.2)
    return PWM_HOVER_US  # hover, roll, pitch, yaw


class _UdpOut:
    """The file pymavlink's encoder writes to: each message is one datagram to ``address``."""

    def __init__(self, sock: socket.socket, address: tuple[str, int]) -> None:
        self._sock = sock
        self._address = address
        self.send_errors = 0

    def write(self, data: bytes) -> None:
        try:
            self._sock.sendto(data, self._address)
        except OSError:  # nobody listening yet (ICMP port unreachable), a full buffer
            self.send_errors += 1


class SimAutopilot:
    """Plays :func:`outputs_at` over MAVLink 2 on UDP, in a thread of its own.

    After :meth:`start` it sends disarmed HEARTBEATs and stopped outputs (phase ``waiting``)
    until :meth:`fly` starts the flight clock. ``time_scale`` > 1 flies the same profile faster.
    With ``loop`` the flight repeats; without it, it stays in ``disarm`` once over
    (:attr:`finished`). :meth:`close` disarms, sends a last few stopped outputs, and stops.
    """

    def __init__(
        self,
        port: int,
        airframe: Airframe = "quad",
        *,
        host: str = "127.0.0.1",
        time_scale: float = 1.0,
        loop: bool = False,
        system: int = 1,
        component: int = 1,
    ) -> None:
        """Nothing is opened or sent until :meth:`start`.

        Raises:
            ValueError: an unknown airframe, or ``time_scale`` not > 0.
        """
        if not time_scale > 0 or not math.isfinite(time_scale):
            raise ValueError(f"time_scale must be a finite number > 0, got {time_scale!r}")
        self.airframe: Airframe = airframe
        self.motors = motor_count(airframe)
        self.address = (host, port)
        self.time_scale = time_scale
        self.loop = loop
        self.system = system
        self.component = component
        self.phase = WAITING
        """The current phase's name (:data:`PHASES`, or ``waiting`` before :meth:`fly`)."""
        self.armed = False
        self.pwm: tuple[int, ...] = (PWM_STOP_US,) * self.motors
        """The last outputs sent."""
        self.sent = 0
        """SERVO_OUTPUT_RAW messages sent."""
        self._lock = threading.Lock()
        self._flight_start: float | None = None
        self._disarmed = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self._out: _UdpOut | None = None
        self._mav: Any = None
        self._dialect: Any = None
        self._parser: Any = None
        self.servo_hz = SERVO_HZ
        """The SERVO_OUTPUT_RAW rate now (the bridge may ask for another)."""
        self.heartbeat_hz = HEARTBEAT_HZ
        """The HEARTBEAT rate now."""

    @property
    def flight_time_s(self) -> float:
        """Profile seconds since :meth:`fly` (scaled by ``time_scale``); 0 before."""
        with self._lock:
            start = self._flight_start
        if start is None:
            return 0.0
        return (time.monotonic() - start) * self.time_scale

    @property
    def finished(self) -> bool:
        """The flight is over (never, when looping)."""
        return not self.loop and self.flight_time_s >= FLIGHT_S

    @property
    def send_errors(self) -> int:
        return 0 if self._out is None else self._out.send_errors

    def start(self) -> None:
        """Open the socket and start sending (disarmed until :meth:`fly`).

        Raises:
            OSError: the socket cannot be opened.
            bridge.mavlink.DialectError: the MAVLink dialect cannot be loaded.
        """
        if self._thread is not None:
            return
        self._dialect = load_dialect()
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.address[0], 0))
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self._sock = sock
        self._out = _UdpOut(sock, self.address)
        self._mav = self._dialect.MAVLink(
            self._out, srcSystem=self.system, srcComponent=self.component
        )
        self._parser = self._dialect.MAVLink(None)
        self._parser.robust_parsing = True
        self._thread = threading.Thread(target=self._run, name="sim-autopilot", daemon=True)
        self._thread.start()

    def fly(self) -> None:
        """Start the flight clock: the flight begins with ``preflight``."""
        with self._lock:
            if self._flight_start is None:
                self._flight_start = time.monotonic()

    def disarm(self) -> None:
        """Stop the motors and disarm now, whatever the phase; it stays so until closed."""
        with self._lock:
            self._disarmed = True

    def close(self) -> None:
        """Disarm, send a last few stopped outputs, stop the thread and close the socket.
        A second call does nothing."""
        self.disarm()
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join(2.0)
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_thread", None) is not None:
            log.warning("SimAutopilot to %s:%d was not closed", *self.address)

    # -- the sender thread --------------------------------------------------------------------

    def _now(self) -> tuple[str, bool, list[int]]:
        with self._lock:
            start, disarmed = self._flight_start, self._disarmed
        if disarmed:
            return PHASES[-1][0], False, [PWM_STOP_US] * self.motors
        if start is None:
            return WAITING, False, [PWM_STOP_US] * self.motors
        t = (time.monotonic() - start) * self.time_scale
        if self.loop:
            t %= FLIGHT_S
        return outputs_at(t, self.airframe)

    def _run(self) -> None:
        servo_due = beat_due = time.monotonic()
        was_armed: bool | None = None
        while not self._stop.is_set():
            now = time.monotonic()
            phase, armed, pwm = self._now()
            if now >= beat_due or armed != was_armed:
                self._heartbeat(armed)
                beat_due = max(beat_due + 1.0 / self.heartbeat_hz, now)
            if now >= servo_due:
                self._servo_output_raw(pwm)
                self.phase, self.armed, self.pwm = phase, armed, tuple(pwm)
                # No burst after a stall: a late send starts the rhythm again.
                servo_due = max(servo_due + 1.0 / self.servo_hz, now)
            was_armed = armed
            self._drain()
            self._stop.wait(max(0.0, min(servo_due, beat_due) - time.monotonic()))
        stopped = [PWM_STOP_US] * self.motors
        self.phase, self.armed, self.pwm = PHASES[-1][0], False, tuple(stopped)
        for _ in range(CLOSE_BURST):
            self._heartbeat(False)
            self._servo_output_raw(stopped)
            time.sleep(1.0 / SERVO_HZ)

    def _heartbeat(self, armed: bool) -> None:
        d = self._dialect
        mav_type = {
            "quad": d.MAV_TYPE_QUADROTOR,
            "hex": d.MAV_TYPE_HEXAROTOR,
            "octo": d.MAV_TYPE_OCTOROTOR,
        }[self.airframe]
        base_mode = d.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | d.MAV_MODE_FLAG_STABILIZE_ENABLED
        if armed:
            base_mode |= d.MAV_MODE_FLAG_SAFETY_ARMED
        status = d.MAV_STATE_ACTIVE if armed else d.MAV_STATE_STANDBY
        self._mav.heartbeat_send(mav_type, d.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode, 0, status)

    def _servo_output_raw(self, pwm: Sequence[int]) -> None:
        values = (list(pwm) + [0] * 16)[:16]
        time_usec = int(time.monotonic() * 1e6) & 0xFFFFFFFF
        self._mav.servo_output_raw_send(time_usec, 0, *values)
        self.sent += 1

    def _drain(self) -> None:
        """Read what the bridge sends back: answer its stream requests, drop the rest (its
        HEARTBEAT, ESC telemetry)."""
        sock = self._sock
        if sock is None:
            return
        for _ in range(64):
            try:
                data = sock.recv(4096)
            except OSError:  # nothing more (BlockingIOError), or an ICMP error
                return
            for msg in self._parser.parse_buffer(data) or []:
                if msg.get_type() == "COMMAND_LONG":
                    self._on_command(msg)

    def _on_command(self, msg: Any) -> None:
        d = self._dialect
        if (msg.target_system, msg.target_component) not in (
            (self.system, self.component),
            (self.system, 0),
            (0, 0),
        ) or msg.command != d.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        message_id, interval_us = int(msg.param1), msg.param2
        result = d.MAV_RESULT_UNSUPPORTED
        if message_id in (d.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, d.MAVLINK_MSG_ID_HEARTBEAT):
            rate_hz = 1e6 / interval_us if interval_us > 0 else 0.0
            result = d.MAV_RESULT_DENIED
            if 0 < rate_hz <= LOOP_HZ:
                result = d.MAV_RESULT_ACCEPTED
                if message_id == d.MAVLINK_MSG_ID_HEARTBEAT:
                    self.heartbeat_hz = rate_hz
                else:
                    self.servo_hz = rate_hz
        self._mav.command_ack_send(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )
