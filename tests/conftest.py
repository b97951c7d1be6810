"""Shared pieces for tests that run real components: ports, buses, an autopilot, the daemon.

Every test picks its own ports (the OS hands out a free one), so tests never share a bus or a
MAVLink link and can run in any order. CAN between processes is python-can's udp_multicast
interface with hop_limit 0 (TTL 0): the frames never leave this machine.
"""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import multiprocessing
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import HealthCheck, settings

# The simulated autopilot speaks MAVLink 2, as current ArduPilot and PX4 do; pymavlink picks
# its wire version from this variable when it is first imported.
os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

from bridge.config import SECTIONS, EscsConfig
from bridge.escs import registry
from bridge.mavlink import load_dialect
from bridge.sim.autopilot import PHASES
from bridge.telemetry.state import EscTable

# Hypothesis fails an example that takes over 200 ms (its deadline) and a test whose examples are
# slow to generate (too_slow); on a loaded machine (the suite's own workers, CI on shared cores)
# any example can be, and no property test here is about time.
settings.register_profile("loaded", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("loaded")

ROOT = Path(__file__).resolve().parent.parent
STARTUP_TIMEOUT_S = 40.0
"""How long a daemon started through its CLI may take to send its first frames: two
interpreters' imports (the main process and the output loop's). About 1 s on a quiet machine;
17 s was seen with the other xdist worker flying the ArduCopter SITL (load 8). A wait for
readiness, not a claim about time: the tests that are about time measure from a ready daemon."""
MULTICAST_GROUP = "239.74.163.2"
ESC_BRIDGE = str(Path(sys.executable).parent / "esc-bridge")


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``--numprocesses=auto``: a worker more than the CPUs. Most of the suite waits rather
    than computes (flights in real time, a kernel in UML reading its files, daemons starting):
    a third worker on 2 CPUs took the suite from 10 min 53 s to 8 min 53 s, two runs back to
    back."""
    return (os.cpu_count() or 1) + 1


LONG_FILES = (
    "sitl/test_arducopter.py",
    "linux/test_socketcan.py",
    "test_safety_e2e.py",
    "plot/test_plot_cli.py",
    "linux/test_systemd.py",
    "sitl/test_px4.py",
    "sim/test_demo.py",
    "mavlink/test_link_sets.py",
    "telemetry/test_mcap_recording.py",
    "daemon/test_preflight.py",
)
"""The files that keep a worker longest (junit's times of a clean clone's run, summed per
file: 145 s down to 49 s), longest first."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The long files first: xdist hands each worker whole files in this order, and a long one
    handed out last would end the suite with the other workers idle."""

    tests = ROOT / "tests"

    def rank(item: pytest.Item) -> int:
        path = item.path.relative_to(tests).as_posix() if item.path.is_relative_to(tests) else ""
        return LONG_FILES.index(path) if path in LONG_FILES else len(LONG_FILES)

    items.sort(key=rank)  # stable: the rest in pytest's own order


def _own_ports() -> range:
    """This worker's block of the ports from 20000 (above the SITLs' fixed ports: ArduPilot's
    5760 + 10·N, PX4's 13030 to 19459) to the kernel's ephemeral range (32768 by default), which
    the kernel never hands to a socket bound to port 0: another worker's, an autopilot's, a
    daemon's. A port asked of the kernel and let go (port 0, then close) could go to another
    worker in between: in CI a daemon could not bind the port PX4 had just taken."""
    with open("/proc/sys/net/ipv4/ip_local_port_range") as ranges:
        ephemeral_low = int(ranges.read().split()[0])
    low = 20000
    assert ephemeral_low > low + 1000, f"the ephemeral ports start at {ephemeral_low}"
    index = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw"))
    size = (ephemeral_low - low) // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    return range(low + index * size, low + (index + 1) * size)


_OWN_PORTS = _own_ports()
_next_own_port = itertools.cycle(_OWN_PORTS)


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port of this worker's own (:func:`_own_ports`) that no socket of ``kind`` holds."""
    for _ in _OWN_PORTS:
        port = next(_next_own_port)
        with socket.socket(socket.AF_INET, kind) as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise AssertionError(f"every port of {_OWN_PORTS} is in use")


def can_args(can_port: int) -> list[str]:
    """The CLI flags of a udp_multicast bus of its own (hop limit 0: never off this machine)."""
    return [
        "--can-interface",
        "udp_multicast",
        "--can-channel",
        MULTICAST_GROUP,
        "--can-option",
        f"port={can_port}",
        "--can-option",
        "hop_limit=0",
    ]


def multicast_bus(port: int, fd: bool = True) -> can.BusABC:
    """A handle on the udp_multicast bus of ``port``; ``fd``: CAN FD (python-can's default)."""
    return can.Bus(
        interface="udp_multicast", channel=MULTICAST_GROUP, port=port, hop_limit=0, fd=fd
    )


def wall_minus_monotonic() -> float:
    """time.time() - time.monotonic(), read between two monotonic readings at most 50 µs apart
    (a few tries): a thread preempted between the two clocks' readings on a loaded machine
    would move the kernel's wall-clock stamps by the time it waited."""
    best = (float("inf"), 0.0)
    for _ in range(5):
        before = time.monotonic()
        wall = time.time()
        after = time.monotonic()
        best = min(best, (after - before, wall - (before + after) / 2))
        if best[0] < 50e-6:
            break
    return best[1]


class Observer:
    """Records every frame on a cross-process bus, in a thread, with the kernel's receive
    times (monotonic)."""

    def __init__(self, port: int) -> None:
        self.bus = multicast_bus(port)
        self.frames: list[tuple[float, can.Message]] = []
        self.garbage = 0  # datagrams that were not CAN frames
        self.senders: list[Daemon] = []
        """Daemons whose failing exit (a status over 0: a port taken, a refused configuration)
        ends a wait at once, naming it, rather than at its timeout."""
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="observer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(0.05)
            except can.CanOperationError:
                # A datagram that is not python-can's (another test's traffic to a port of
                # the same number): counted and dropped, the observer goes on.
                self.garbage += 1
                continue
            if msg is not None:
                # The kernel's receive time (udp_multicast reads SO_TIMESTAMPNS) on the
                # monotonic clock: when the bridge sent the frame, however late this thread
                # got to it on a loaded machine.
                now = time.monotonic()
                stamp = msg.timestamp - wall_minus_monotonic() if msg.timestamp else now
                with self._lock:
                    self.frames.append((min(stamp, now), msg))

    def since(self, t: float) -> list[can.Message]:
        with self._lock:
            return [m for ts, m in self.frames if ts >= t]

    def stamps(self, start: float, end: float) -> list[float]:
        """The receive times of the frames from ``start`` until ``end`` (monotonic)."""
        with self._lock:
            return [ts for ts, _ in self.frames if start <= ts < end]

    def wait_for(
        self, predicate: Callable[[can.Message], bool], timeout_s: float, after: float = 0.0
    ) -> tuple[float, can.Message]:
        """The first frame after ``after`` matching ``predicate``, waiting up to timeout_s."""
        deadline = time.monotonic() + timeout_s
        seen = 0
        while time.monotonic() < deadline:
            with self._lock:
                window = self.frames[seen:]
                seen = len(self.frames)
            for ts, msg in window:
                if ts >= after and predicate(msg):
                    return ts, msg
            for daemon in self.senders:
                status = daemon.proc.poll()
                if status is not None and status > 0:
                    daemon.stop()
                    raise AssertionError(
                        f"no matching frame: the daemon exited with status {status}:\n"
                        + "\n".join(daemon.output.splitlines()[-10:])
                    )
            time.sleep(0.005)
        raise AssertionError(f"no matching frame within {timeout_s} s")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.bus.shutdown()


class Autopilot:
    """A pymavlink sender playing the autopilot: HEARTBEAT and motor outputs, on loopback."""

    def __init__(
        self,
        port: int,
        system: int = 1,
        component: int = 1,
        stack: int = mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
    ) -> None:
        self.stack = stack  # its HEARTBEAT's autopilot field (MAV_AUTOPILOT)
        self.conn: Any = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=system, source_component=component
        )
        self.mav = self.conn.mav
        self.armed = False
        self.pwm: list[int] = [1000] * 8
        self.output_times: list[float] = []
        """When each SERVO_OUTPUT_RAW was sent (monotonic): on a loaded machine this thread may
        fall quiet for longer than a bridge's input timeout."""
        self._stop = threading.Event()
        self._streaming = threading.Event()
        self._thread: threading.Thread | None = None

    def heartbeat(self) -> None:
        base_mode = mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            base_mode |= mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        self.mav.heartbeat_send(
            mavutil.mavlink.MAV_TYPE_QUADROTOR,
            self.stack,
            base_mode,
            0,
            mavutil.mavlink.MAV_STATE_ACTIVE,
        )

    def servo_output_raw(self, pwm: list[int], time_us: int | None = None) -> None:
        """``time_us``: its time_usec (default: now, on the monotonic clock)."""
        values = (list(pwm) + [0] * 16)[:16]
        extensions = {f"servo{i}_raw": values[i - 1] for i in range(9, 17)}  # MAVLink 2 only
        now = time.monotonic()
        if time_us is None:
            time_us = int(now * 1e6)
        self.mav.servo_output_raw_send(time_us & 0xFFFFFFFF, 0, *values[:8], **extensions)
        self.output_times.append(now)

    def start_stream(self, rate_hz: float = 50.0) -> None:
        """Send HEARTBEAT at 10 Hz and SERVO_OUTPUT_RAW of ``self.pwm`` at ``rate_hz``."""
        self._streaming.set()

        def run() -> None:
            period = 1.0 / rate_hz
            tick = 0
            while not self._stop.is_set():
                if tick % max(1, round(rate_hz / 10)) == 0:
                    self.heartbeat()
                if self._streaming.is_set():
                    self.servo_output_raw(self.pwm)
                tick += 1
                time.sleep(period)

        self._thread = threading.Thread(target=run, name="autopilot", daemon=True)
        self._thread.start()

    def pause_outputs(self) -> None:
        self._streaming.clear()

    def resume_outputs(self) -> None:
        self._streaming.set()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
        self.conn.close()


SIOCGSTAMPNS = 0x8907  # Linux: the kernel's receive time of a socket's last datagram


def kernel_receive_time(sock: socket.socket) -> float | None:
    """When the kernel received ``sock``'s last datagram, on the monotonic clock (None if it
    cannot say)."""
    try:
        stamp = fcntl.ioctl(sock, SIOCGSTAMPNS, bytes(16))
    except OSError:
        return None
    seconds, nanoseconds = struct.unpack("qq", stamp)
    return float(seconds + nanoseconds * 1e-9 - wall_minus_monotonic())


class MavlinkReceiver:
    """Decodes, with the project's dialect, what the daemon sends back to a pymavlink link, each
    message stamped with the kernel's receive time (monotonic) when the link is a UDP socket:
    a rate counted over a window then holds however late this thread got to a datagram on a
    loaded machine."""

    def __init__(self, conn: Any) -> None:
        self._conn = conn
        sock = getattr(conn, "port", None)  # pymavlink's UDP connections keep their socket there
        self._socket = sock if isinstance(sock, socket.socket) else None
        if self._socket is not None:
            kernel_receive_time(self._socket)  # the first ask turns the kernel's stamps on
        self._parser = load_dialect().MAVLink(None)
        self._parser.robust_parsing = True
        self.messages: list[tuple[float, Any]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="receiver", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._conn.recv()
            except OSError:
                return
            if not data:
                time.sleep(0.002)
                continue
            now = time.monotonic()
            if self._socket is not None:
                now = min(kernel_receive_time(self._socket) or now, now)
            for msg in self._parser.parse_buffer(data) or []:
                with self._lock:
                    self.messages.append((now, msg))

    def wait_for(
        self,
        kind: str,
        predicate: Callable[[Any], bool],
        timeout_s: float = 5.0,
        after: float = 0,
        first: bool = False,
    ) -> Any:
        """The newest (or with ``first``, the earliest) ``kind`` message received after
        ``after`` that matches ``predicate``, waiting up to ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                found = [
                    m
                    for t, m in self.messages
                    if t >= after and m.get_type() == kind and predicate(m)
                ]
            if found:
                return found[0] if first else found[-1]
            time.sleep(0.02)
        with self._lock:
            seen = sorted({m.get_type() for _, m in self.messages})
        raise AssertionError(f"no matching {kind} within {timeout_s} s; saw {seen}")

    def close(self) -> None:
        """Stop reading (the connection stays open: whoever opened it closes it)."""
        self._stop.set()
        self._thread.join(1.0)


class Daemon:
    """``esc-bridge run`` as a subprocess, stopped with SIGTERM at the end of the test."""

    def __init__(self, args: list[str]) -> None:
        self.args = [ESC_BRIDGE, *args]
        self.proc = subprocess.Popen(
            self.args,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
            # A process group of its own: a test can signal the whole bridge (as a closing
            # terminal does) without signalling pytest.
            start_new_session=True,
        )
        self.output = ""

    def children(self) -> list[int]:
        """The daemon's child processes (the output loop's, in process mode)."""
        try:
            text = Path(f"/proc/{self.proc.pid}/task/{self.proc.pid}/children").read_text()
        except OSError:
            return []
        return [int(pid) for pid in text.split()]

    def loop_pid(self, timeout_s: float = 15.0) -> int:
        """The output loop's process (the one spawned child that runs the bridge)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for pid in self.children():
                try:
                    cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
                except OSError:
                    continue
                if b"spawn_main" in cmdline:
                    return pid
            time.sleep(0.05)
        raise AssertionError("no output loop process found")

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            out, _ = self.proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        self.output += out or ""
        return self.proc.returncode


@dataclass(frozen=True)
class Holds:
    """What a daemon's exit summary says of its ESC telemetry sender's hold-ups."""

    count: int
    longest_s: float


def holds_of(daemon: Daemon) -> Holds:
    """The hold-ups ``daemon`` reported (stopping it first: the exit summary says them)."""
    assert daemon.stop() == 0, daemon.output
    found = re.search(r"(\d+) rounds held up \(the longest (\d+\.\d+) s late\)", daemon.output)
    assert found, f"no ESC telemetry summary in the daemon's output:\n{daemon.output}"
    return Holds(int(found.group(1)), float(found.group(2)))


@pytest.fixture
def ckesc_12b_encodes(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """The monotonic time of every CKESC RawCommand_12b frame encoded from now on (the real
    encoder still makes each one)."""
    from bridge.escs.ckesc import codec

    encoded: list[float] = []
    encode = codec.encode_raw_12b

    def counted(group: int, throttles: list[int], transfer_id: int) -> can.Message:
        encoded.append(time.monotonic())
        return encode(group, throttles, transfer_id)

    monkeypatch.setattr(codec, "encode_raw_12b", counted)
    return encoded


@pytest.fixture
def can_port() -> int:
    return free_port()


@pytest.fixture
def daemons() -> list[Daemon]:
    """The daemons :func:`start_daemon` started in this test (the :func:`observer` watches
    them)."""
    return []


@pytest.fixture
def observer(can_port: int, daemons: list[Daemon]) -> Iterator[Observer]:
    obs = Observer(can_port)
    obs.senders = daemons
    yield obs
    obs.close()


@pytest.fixture
def mavlink_port() -> int:
    return free_port()


@pytest.fixture
def autopilot(mavlink_port: int) -> Iterator[Autopilot]:
    pilot = Autopilot(mavlink_port)
    yield pilot
    pilot.close()


@pytest.fixture
def start_daemon(
    can_port: int, mavlink_port: int, daemons: list[Daemon]
) -> Iterator[Callable[..., Daemon]]:
    """Start the daemon on this test's bus and link; extra CLI args may follow."""
    started = daemons

    def start(*extra: str) -> Daemon:
        daemon = Daemon(
            [
                "run",
                "--mavlink",
                f"udpin:127.0.0.1:{mavlink_port}",
                *can_args(can_port),
                # No Zenoh peer discovery: parallel test runs must never see each other.
                "--no-zenoh-scouting",
                *extra,
            ]
        )
        started.append(daemon)
        return daemon

    yield start
    for daemon in started:
        daemon.stop()
        print(f"--- {' '.join(daemon.args[1:])}\n{daemon.output}")  # shown when a test fails


def _stream_outputs(port: int, pwm: list[int], priority: int, control: Any, stop: Any) -> None:
    """The body of :class:`RealtimeAutopilot`'s process."""
    with contextlib.suppress(PermissionError, OSError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    conn: Any = mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{port}", source_system=1, source_component=1
    )
    mav = conn.mav
    asked = (list(pwm) + [0] * 16)[:16]
    values: list[int] = []
    extensions: dict[str, int] = {}
    shift_us = -1  # the first pass makes the values
    next_ns = time.monotonic_ns()
    next_beat_ns = next_ns
    largest_gap_ns = last_ns = 0
    while not stop.is_set():
        now = time.monotonic_ns()
        if control[1] and now >= next_beat_ns:  # heartbeats on
            base_mode = mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            if control[0]:
                base_mode |= mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            mav.heartbeat_send(
                mavutil.mavlink.MAV_TYPE_QUADROTOR,
                mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                base_mode,
                0,
                mavutil.mavlink.MAV_STATE_ACTIVE,
            )
            next_beat_ns = now + 1_000_000_000
        if control[6] != shift_us:  # the outputs moved by the test
            shift_us = control[6]
            values = [v + shift_us if v else 0 for v in asked]
            extensions = {f"servo{i}_raw": values[i - 1] for i in range(9, 17)}
        if control[2]:  # outputs on
            mav.servo_output_raw_send((now // 1000) & 0xFFFFFFFF, 0, *values[:8], **extensions)
            if last_ns:
                largest_gap_ns = max(largest_gap_ns, now - last_ns)
            last_ns = now
            control[5] += 1
        control[3] = largest_gap_ns // 1000
        next_ns += control[4]  # the period, which the test may change
        delay = next_ns - time.monotonic_ns()
        if delay > 0:
            time.sleep(delay / 1e9)
    conn.close()


class RealtimeAutopilot:
    """An autopilot in a process of its own at SCHED_FIFO (where permitted), as a flight
    controller is: SERVO_OUTPUT_RAW at ``rate_hz`` on absolute deadlines and a HEARTBEAT a
    second, armed. Its sends keep their rhythm on a loaded machine, so a safe frame from the
    bridge while it streams is the bridge's fault."""

    def __init__(self, port: int, pwm: list[int], rate_hz: float = 200.0) -> None:
        """Returns once the first outputs are sent: a spawned interpreter took seconds to get
        there beside the whole suite, and a test timing the stream must not time its start."""
        ctx = multiprocessing.get_context("spawn")
        # armed, heartbeats on, outputs on, the largest gap between two sends (µs), period (ns),
        # outputs sent, µs added to every output
        self._control = ctx.RawArray("q", [1, 1, 1, 0, round(1e9 / rate_hz), 0, 0])
        self._stop = ctx.Event()
        self._process = ctx.Process(
            target=_stream_outputs,
            args=(port, pwm, 60, self._control, self._stop),
            name="rt-autopilot",
            daemon=True,
        )
        self._process.start()
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not self.outputs_sent:
            if not self._process.is_alive() or time.monotonic() > deadline:
                self.close()
                raise AssertionError("the real-time autopilot sent nothing")
            time.sleep(0.01)

    @property
    def outputs_sent(self) -> int:
        return int(self._control[5])

    @property
    def largest_gap_ms(self) -> float:
        return float(self._control[3]) / 1000

    def heartbeats(self, on: bool) -> None:
        self._control[1] = int(on)

    def outputs(self, on: bool) -> None:
        self._control[2] = int(on)

    def rate(self, rate_hz: float) -> None:
        """Send the outputs at ``rate_hz`` from the next one on."""
        self._control[4] = round(1e9 / rate_hz)

    def shift(self, us: int) -> None:
        """From the next send on, every output (but those at 0) ``us`` above the one asked at
        the start."""
        self._control[6] = us

    def close(self) -> None:
        self._stop.set()
        self._process.join(5)
        if self._process.is_alive():
            self._process.kill()


def documented_keys() -> list[tuple[str, str, Any, str]]:
    """(section, key, default, doc) for every configuration key, every family's ``[escs]`` keys
    included, as docs and their tests list them."""
    rows = []
    for name, cls in SECTIONS.items():
        keys = [f for f in fields(cls) if f.name != "families"]
        if cls is EscsConfig:
            keys += [f for family in registry.families() for f in fields(family.keys)]
        rows += [(name, f.name, f.default, f.metadata["doc"]) for f in keys]
    return rows


def phase_start(name: str) -> float:
    """When the demo flight's phase called ``name`` begins, in seconds from its start."""
    names = [phase for phase, _ in PHASES]
    return sum(duration for _, duration in PHASES[: names.index(name)])


def feed(table: EscTable, msg: can.Message, now_ns: int) -> bool:
    """One frame of a one-frame family (CKESC, FT) through its decoder into ``table``:
    telemetry ingested as the CAN reader does (True if from one of its ESCs), commands noted as
    the loop's commands are (:mod:`bridge.daemon.commands_sent`)."""
    family = registry.families_of(msg.arbitration_id)[0]
    decoder = family.decoder()  # one frame is one message for the families fed here
    frame = decoder.decode(msg)
    assert frame is not None
    telemetry = decoder.telemetry(frame)
    if telemetry is None:
        table.note_commands(decoder.commands_seen(frame))
        return False
    return table.ingest(telemetry, now_ns)
