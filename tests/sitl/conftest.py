"""Generic pieces for tests against real autopilot SITL builds.

The builds live in ``../shared/sitl`` beside the repository (see its README); a user points the
tests at a build of their own with an environment variable, and without a build the tests skip
and say why. Everything runs on loopback: the autopilot's MAVLink on TCP, CAN between processes
on python-can's udp_multicast interface with hop limit 0.

The pieces: the autopilot in a working directory of its own with an instance number whose
ports are free (``-I N``), the bridge through its CLI (``esc-bridge run``), the simulated ESCs
(``esc-bridge sim``), a recording tap on the bridge's autopilot link (``mavtap.py``, a process
of its own), and a ground station on another autopilot port. Every process started here is
stopped in a ``finally`` (the fixtures use context managers), also when a test fails.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import pytest
from conftest import ESC_BRIDGE, MULTICAST_GROUP, ROOT, free_port

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil

mavlink: Any = mavutil.mavlink

ARDUCOPTER_ENV = "ESC_BRIDGE_ARDUCOPTER"
"""Path of an ``arducopter`` SITL binary (``./waf copter`` for board ``sitl``)."""
ARDUCOPTER_DEFAULTS_ENV = "ESC_BRIDGE_ARDUCOPTER_DEFAULTS"
"""Its defaults file; else ``copter.parm`` beside the binary."""
DEFAULT_ARDUCOPTER = ROOT.parent / "shared" / "sitl" / "ardupilot" / "arducopter"
MAVTAP = Path(__file__).resolve().parent / "mavtap.py"

# ArduPilot SITL's TCP ports for instance 0 (SERIAL0, SERIAL1, SERIAL2); ``-I N`` adds 10·N.
ARDUPILOT_SERIAL_PORTS = (5760, 5762, 5763)
# The sim's own UDP port (RC input) at instance 0, also shifted by 10·N.
ARDUPILOT_UDP_PORTS = (5501,)


# --------------------------------------------------------------------------------------------
# Measurements: the tests record numbers here and the session prints them at its end, for the
# README's table (``pytest tests/sitl -s`` or the summary at the end of any run).

MEASUREMENTS: dict[str, str] = {}


def measured(name: str, value: str) -> None:
    MEASUREMENTS[name] = value


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "sitl: runs a real autopilot SITL build (tests/sitl; skips without one)"
    )


def pytest_terminal_summary(terminalreporter: Any) -> None:
    if not MEASUREMENTS:
        return
    terminalreporter.section("SITL measurements")
    width = max(len(name) for name in MEASUREMENTS)
    for name, value in MEASUREMENTS.items():
        terminalreporter.write_line(f"{name:<{width}}  {value}")


# --------------------------------------------------------------------------------------------
# Finding the builds


@dataclass(frozen=True)
class ArduCopterBuild:
    binary: Path
    defaults: Path


def find_arducopter() -> ArduCopterBuild | str:
    """The ArduCopter SITL build to use, or why there is none (a skip reason)."""
    given = os.environ.get(ARDUCOPTER_ENV)
    binary = Path(given) if given else DEFAULT_ARDUCOPTER
    if not binary.is_file() or not os.access(binary, os.X_OK):
        where = f"{ARDUCOPTER_ENV}={given}" if given else f"default {binary}"
        return (
            f"no ArduCopter SITL binary ({where} is not an executable file); build one "
            f"(./waf configure --board sitl && ./waf copter) and set {ARDUCOPTER_ENV} to "
            "build/sitl/bin/arducopter"
        )
    given_defaults = os.environ.get(ARDUCOPTER_DEFAULTS_ENV)
    defaults = Path(given_defaults) if given_defaults else binary.parent / "copter.parm"
    if not defaults.is_file():
        return (
            f"no ArduCopter defaults file at {defaults}: put copter.parm "
            f"(Tools/autotest/default_params/copter.parm) beside the binary or set "
            f"{ARDUCOPTER_DEFAULTS_ENV}"
        )
    return ArduCopterBuild(binary.resolve(), defaults.resolve())


@pytest.fixture(scope="session")
def arducopter_build() -> ArduCopterBuild:
    found = find_arducopter()
    if isinstance(found, str):
        pytest.skip(found)
    return found


# --------------------------------------------------------------------------------------------
# Ports


def _port_free(port: int, kind: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


@contextlib.contextmanager
def reserved_instance(
    tcp_ports: tuple[int, ...], udp_ports: tuple[int, ...] = (), step: int = 10
) -> Iterator[int]:
    """An instance number N (1..99) whose ports (each base + step·N) are free now, held
    against other test processes by a lock file until the block ends. The lock matters because
    a free port is only claimed when the autopilot binds it, a second or so later."""
    lock_dir = Path(tempfile.gettempdir())
    candidates = list(range(1, 100))
    random.shuffle(candidates)
    for n in candidates:
        handle: IO[bytes] = open(lock_dir / f"esc-bridge-sitl-instance-{n}.lock", "wb")  # noqa: SIM115
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        free = all(_port_free(p + step * n, socket.SOCK_STREAM) for p in tcp_ports) and all(
            _port_free(p + step * n, socket.SOCK_DGRAM) for p in udp_ports
        )
        if not free:
            handle.close()
            continue
        try:
            yield n
        finally:
            handle.close()
        return
    raise AssertionError("no SITL instance number 1..99 with free ports")


def widen_receive_buffer(bus: Any, size: int = 4 << 20) -> None:
    """Let an observer's udp_multicast socket queue ``size`` bytes: a thread in a busy test
    process may not read for a while, and ~1 600 frames/s (an FT bus) would overflow the
    default buffer within a tenth of a second. (A duplicate of the descriptor shares the
    socket, so closing it leaves the bus's own open.)"""
    with socket.fromfd(bus.fileno(), socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)


def udp_drops(bus: Any) -> int:
    """Datagrams the kernel dropped for this bus's socket (a full receive buffer): an
    observer that lost frames cannot vouch for what was on the bus."""
    inode = os.fstat(bus.fileno()).st_ino
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        with contextlib.suppress(OSError), open(table) as f:
            for line in f.readlines()[1:]:
                fields = line.split()
                if int(fields[9]) == inode:
                    return int(fields[-1])
    raise AssertionError(f"socket inode {inode} not in /proc/net/udp")


# --------------------------------------------------------------------------------------------
# Processes


class Process:
    """A subprocess in a session of its own, its output in a log file; always ended."""

    def __init__(self, args: list[str], log: Path, cwd: Path | None = None) -> None:
        self.args = args
        self.log_path = log
        self._log = open(log, "ab")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            args,
            cwd=cwd,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
            start_new_session=True,
        )
        self.started = time.monotonic()

    def send_signal(self, sig: int) -> None:
        if self.proc.poll() is None:
            os.kill(self.proc.pid, sig)

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 10.0) -> int:
        """End it: ``sig``, then after ``timeout_s`` SIGKILL to its whole session (signalled
        while its leader is not yet reaped, so the group id cannot belong to anyone else)."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, signal.SIGCONT)  # a stopped process cannot exit
            self.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        self._log.close()
        return self.proc.returncode

    def tail(self, lines: int = 30) -> str:
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])


class ArduCopter:
    """An ArduCopter SITL quad at real time (speedup 1) in ``workdir``, instance ``instance``.

    Its defaults file is the build's ``copter.parm`` plus ``params`` (written to the working
    directory). SITL starts its loop only when something connects to SERIAL0, so connect the
    ground station there first."""

    def __init__(
        self,
        build: ArduCopterBuild,
        workdir: Path,
        instance: int,
        params: dict[str, float] | None = None,
    ) -> None:
        self.build = build
        self.workdir = workdir
        self.instance = instance
        workdir.mkdir(parents=True, exist_ok=True)
        self.defaults = workdir / "defaults.parm"
        extra = "".join(f"{name} {value:g}\n" for name, value in (params or {}).items())
        self.defaults.write_text(
            build.defaults.read_text()
            + "\n# esc-bridge tests: ESC data comes from the bridge\n"
            + extra
        )
        self.process: Process | None = None
        self.starts = 0
        self.realtime = False

    def port(self, serial: int) -> int:
        return ARDUPILOT_SERIAL_PORTS[serial] + 10 * self.instance

    def start(self) -> None:
        self.starts += 1
        self.process = Process(
            [
                str(self.build.binary),
                "--model",
                "quad",
                "--speedup",
                "1",
                "--defaults",
                str(self.defaults),
                f"-I{self.instance}",
            ],
            self.workdir / f"arducopter-{self.starts}.log",
            cwd=self.workdir,
        )
        self.realtime = self.make_realtime()

    def make_realtime(self) -> bool:
        """Run SITL at a low SCHED_FIFO priority where permitted (below the bridge's loop, 50).

        Why: SITL's clock (``time_usec``) is simulated time, which falls behind when the
        process waits for a CPU. A flight controller's clock is a hardware timer that never
        does, and on a loaded test machine (2 cores, other tests beside) a lag of a few hundred
        ms was seen; the bridge then rightly takes the inputs for old ones. SITL sleeps ~96 %
        of the time, so the priority costs the machine nothing. Threads inherit the policy
        from the thread that creates them; any already there get it here too. Returns whether
        it was permitted."""
        assert self.process is not None
        try:
            for task in Path(f"/proc/{self.process.proc.pid}/task").iterdir():
                os.sched_setscheduler(int(task.name), os.SCHED_FIFO, os.sched_param(5))
        except (PermissionError, OSError):
            return False
        return True

    @property
    def pid(self) -> int:
        assert self.process is not None
        return self.process.proc.pid

    def kill(self) -> None:
        """SIGKILL: the links drop at once, as when the flight controller dies."""
        assert self.process is not None
        self.process.stop(signal.SIGKILL, timeout_s=5)

    def stop(self) -> None:
        if self.process is not None:
            self.process.stop(signal.SIGTERM, timeout_s=5)


def start_bridge(
    workdir: Path,
    name: str,
    protocol: str,
    mavlink_port: int,
    can_port: int,
    config: str,
) -> Process:
    """``esc-bridge run`` on its own udp_multicast bus (port ``can_port``) with the autopilot
    link ``tcp:127.0.0.1:<mavlink_port>``; ``config`` is extra TOML (e.g. its component id)."""
    path = workdir / f"{name}.toml"
    path.write_text(config)
    return Process(
        [
            ESC_BRIDGE,
            "run",
            "--config",
            str(path),
            "--mavlink",
            f"tcp:127.0.0.1:{mavlink_port}",
            "--protocol",
            protocol,
            "--can-interface",
            "udp_multicast",
            "--can-channel",
            MULTICAST_GROUP,
            "--can-option",
            f"port={can_port}",
            "--can-option",
            "hop_limit=0",
            "--vehicle",
            name,
            # No Zenoh peer discovery: parallel test runs must never see each other.
            "--no-zenoh-scouting",
        ],
        workdir / f"bridge-{name}.log",
    )


def start_sim(workdir: Path, name: str, protocol: str, can_port: int, escs: int = 4) -> Process:
    """``esc-bridge sim``: ``escs`` simulated ESCs (IDs 1..N) on the bus at ``can_port``."""
    return Process(
        [
            ESC_BRIDGE,
            "sim",
            "--protocol",
            protocol,
            "--escs",
            str(escs),
            "--can-interface",
            "udp_multicast",
            "--can-channel",
            MULTICAST_GROUP,
            "--can-option",
            f"port={can_port}",
            "--can-option",
            "hop_limit=0",
        ],
        workdir / f"sim-{name}.log",
    )


# --------------------------------------------------------------------------------------------
# The tap on the bridges' links


@dataclass(frozen=True)
class ServoOutput:
    """A SERVO_OUTPUT_RAW the tap forwarded to the bridge: not before ``t``, and done by
    ``t_sent`` (monotonic)."""

    t: float
    t_sent: float
    time_usec: int
    servos: tuple[int, ...]


@dataclass
class TapRecord:
    servo: list[ServoOutput] = field(default_factory=list)
    heartbeats: list[tuple[float, bool]] = field(default_factory=list)
    events: list[tuple[float, str]] = field(default_factory=list)


class MavTap:
    """``mavtap.py`` in a process of its own: one listening port per upstream port."""

    def __init__(self, workdir: Path, upstream_ports: list[int]) -> None:
        self.listen_ports = [free_port(socket.SOCK_STREAM) for _ in upstream_ports]
        self.log_path = workdir / "mavtap.log"
        args = [
            str(p) for pair in zip(self.listen_ports, upstream_ports, strict=True) for p in pair
        ]
        self.process = Process(
            [sys.executable, str(MAVTAP), str(self.log_path), *args], workdir / "mavtap.out"
        )
        deadline = time.monotonic() + 20
        while not (self.log_path.exists() and "listening" in self.log_path.read_text()):
            assert self.process.proc.poll() is None, f"mavtap died:\n{self.process.tail()}"
            assert time.monotonic() < deadline, "mavtap did not start listening within 20 s"
            time.sleep(0.05)

    def records(self) -> dict[int, TapRecord]:
        """Everything the tap logged so far, per link."""
        out: dict[int, TapRecord] = {}
        # The last piece may be a line the tap is still writing: only whole lines count.
        for line in self.log_path.read_text().split("\n")[:-1]:
            parts = line.split()
            if len(parts) < 4:
                continue
            kind, link, t = parts[0], int(parts[1]), float(parts[2])
            rec = out.setdefault(link, TapRecord())
            if kind == "S" and len(parts) == 13:
                servos = tuple(int(p) for p in parts[5:])
                rec.servo.append(ServoOutput(t, float(parts[3]), int(parts[4]), servos))
            elif kind == "H":
                rec.heartbeats.append((t, parts[3] == "1"))
            elif kind == "E":
                rec.events.append((t, parts[3]))
        return out

    def stop(self) -> None:
        self.process.stop()


# --------------------------------------------------------------------------------------------
# The ground station


class GroundStation:
    """A pymavlink ground station (system 255) on one of the autopilot's TCP ports, reading in
    a thread of its own. Every message is kept with its monotonic receive time."""

    def __init__(self, port: int, connect_timeout_s: float = 20.0) -> None:
        self.port = port
        self._mav: Any = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self._lock = threading.Lock()
        self.messages: list[tuple[float, Any]] = []
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.connect(connect_timeout_s)

    def connect(self, timeout_s: float) -> None:
        """Connect (again): SITL listens on SERIAL0 from its first moments."""
        self.disconnect()
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                sock = socket.create_connection(("127.0.0.1", self.port), timeout=1.0)
                break
            except OSError as exc:
                if time.monotonic() > deadline:
                    raise AssertionError(
                        f"the autopilot's TCP port {self.port} did not accept a connection "
                        f"within {timeout_s} s ({exc})"
                    ) from exc
                time.sleep(0.1)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(0.1)
        self._sock = sock
        self._stop = threading.Event()
        parser: Any = mavlink.MAVLink(None)
        parser.robust_parsing = True
        self._thread = threading.Thread(
            target=self._run, args=(sock, parser, self._stop), name="gcs", daemon=True
        )
        self._thread.start()

    def _run(self, sock: socket.socket, parser: Any, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                data = sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            now = time.monotonic()
            msgs = parser.parse_buffer(data) or []
            with self._lock:
                self.messages.extend((now, m) for m in msgs)

    def disconnect(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
        if self._sock is not None:
            self._sock.close()
        self._sock = None

    def send(self, msg: Any) -> None:
        assert self._sock is not None
        self._sock.sendall(msg.pack(self._mav))

    def command(self, command: int, *params: float, component: int = 1) -> float:
        """Send COMMAND_LONG to the autopilot; returns when it was sent."""
        values = [*params, *([0.0] * (7 - len(params)))]
        sent = time.monotonic()
        self.send(self._mav.command_long_encode(1, component, command, 0, *values))
        return sent

    def ack(self, command: int, after: float, timeout_s: float = 5.0) -> int:
        """The result of the first COMMAND_ACK for ``command`` received after ``after``."""
        msg = self.wait_for(
            "COMMAND_ACK", lambda m: m.command == command, timeout_s, after, first=True
        )
        return int(msg.result)

    def since(self, after: float, kind: str | None = None) -> list[tuple[float, Any]]:
        with self._lock:
            return [
                (t, m)
                for t, m in self.messages
                if t >= after and (kind is None or m.get_type() == kind)
            ]

    def wait_for(
        self,
        kind: str,
        predicate: Callable[[Any], bool],
        timeout_s: float,
        after: float = 0.0,
        first: bool = False,
        what: str = "",
    ) -> Any:
        deadline = time.monotonic() + timeout_s
        while True:
            found = [m for _, m in self.since(after, kind) if predicate(m)]
            if found:
                return found[0] if first else found[-1]
            if time.monotonic() > deadline:
                texts = [m.text for _, m in self.since(after, "STATUSTEXT")][-8:]
                raise AssertionError(
                    f"no {what or kind} at the ground station within {timeout_s} s; "
                    f"the autopilot said: {texts}"
                )
            time.sleep(0.02)

    def close(self) -> None:
        self.disconnect()


def armed(heartbeat: Any) -> bool:
    return bool(heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)


def from_autopilot(msg: Any) -> bool:
    return bool(msg.get_srcSystem() == 1 and msg.get_srcComponent() == 1)
