"""Generic pieces for tests against real autopilot SITL builds.

The builds live in ``../shared/sitl`` beside the repository (see its README); a user points the
tests at a build of their own with an environment variable, and without a build the tests skip
and say why. Everything runs on loopback: the autopilot's MAVLink on TCP, CAN between processes
on python-can's udp_multicast interface with hop limit 0.

The pieces both test files use (test_arducopter.py, and test_px4.py with its PX4 harness in
_px4.py): a logged :class:`Process` in a session of its own, :func:`wait_until` with a
deadline, instance numbers held by lock files (:func:`claimed_instance`), the autopilot's
process signals (:class:`SitlAutopilot`), the bridge through its CLI (:func:`start_bridge`,
:func:`write_bridge_config`), the simulated ESCs (:func:`start_sim`), observers with a 4 MiB
receive buffer whose kernel drops are counted (:func:`wide_observer`, :func:`udp_drops`), the
frames read through their ESC family (:func:`frame_reader`, :func:`commands_by_motor`), one
:class:`GroundStation` (TCP for ArduPilot, UDP for PX4) and :func:`measured`. The taps differ
because the links do: ArduPilot's TCP tap (``mavtap.py``) and PX4's UDP relay
(``_px4.UdpTap``). Every process started here is stopped in a ``finally`` (the fixtures use
context managers), also when a test fails.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import random
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import pytest
from conftest import ESC_BRIDGE, ROOT, Observer, can_args, free_port

from bridge.config import build_config
from bridge.config_file import read_config_file
from bridge.escs import registry
from bridge.escs.family import EscDecoder, EscFrame
from bridge.mavlink import load_dialect

# The project's dialect (ArduPilot's messages plus ESC_INFO/ESC_STATUS), MAVLink 2: tests/conftest
# sets MAVLINK20 before pymavlink is first imported.
dialect: Any = load_dialect()
mavlink: Any = dialect

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
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # Linux's; Python names it from 3.12


# --------------------------------------------------------------------------------------------
# Measurements: the tests record numbers here and the session prints them at its end, for the
# table in docs/simulation.md (``pytest tests/sitl -s`` or the summary at the end of any run).

MEASUREMENTS: dict[str, Any] = {}
REPORT_ENV = "ESC_BRIDGE_SITL_REPORT"
"""A file to append every measurement to, one JSON object a line (bench/sitl_table.py reads it):
under pytest-xdist the measurements are made in the workers, whose values the controller's
summary never sees."""


def measured(name: str, value: Any) -> None:
    MEASUREMENTS[name] = value
    target = os.environ.get(REPORT_ENV)
    if target:
        with open(target, "a") as f:
            f.write(json.dumps({"name": name, "value": value}) + "\n")


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


@pytest.fixture(scope="module", autouse=True)
def one_sitl_module_at_a_time() -> Iterator[None]:
    """One SITL test module flies at a time on this machine, whichever xdist worker has it:
    ArduCopter's four rigs (a bridge and simulated ESCs per family) beside PX4's flight put the
    two cores at load 35 and failed both."""
    with (Path(tempfile.gettempdir()) / "esc-bridge-sitl.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


@pytest.fixture(scope="session")
def arducopter_build() -> ArduCopterBuild:
    found = find_arducopter()
    if isinstance(found, str):
        pytest.skip(found)
    return found


# --------------------------------------------------------------------------------------------
# Ports


def port_free(port: int, kind: int = socket.SOCK_DGRAM, host: str = "0.0.0.0") -> bool:
    """Nobody has ``port`` bound on this machine (any address: PX4 binds them all)."""
    with socket.socket(socket.AF_INET, kind) as sock:
        try:
            sock.bind((host, port))
        except OSError:
            return False
    return True


@contextlib.contextmanager
def claimed_instance(
    kind: str, candidates: Sequence[int], free: Callable[[int], str | None]
) -> Iterator[int]:
    """An autopilot instance number from ``candidates`` that ``free`` finds usable (it returns
    None, or why not), held against every other test process on this machine by a lock file
    (``esc-bridge-<kind>-instance-<n>.lock``) until the block ends. The lock matters because a
    free port is only claimed when the autopilot binds it, a second or so later."""
    lock_dir = Path(tempfile.gettempdir())
    busy: list[str] = []
    for n in candidates:
        handle: IO[bytes] = open(lock_dir / f"esc-bridge-{kind}-instance-{n}.lock", "ab")  # noqa: SIM115
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            busy.append(f"{n}: locked by another test")
            continue
        why = free(n)
        if why is not None:
            handle.close()
            busy.append(f"{n}: {why}")
            continue
        try:
            yield n
        finally:
            handle.close()
        return
    raise AssertionError(f"no free {kind} SITL instance: {'; '.join(busy[-10:])}")


@contextlib.contextmanager
def reserved_instance(
    tcp_ports: tuple[int, ...], udp_ports: tuple[int, ...] = (), step: int = 10
) -> Iterator[int]:
    """An ArduPilot instance number N (1..99, shuffled) whose ports (each base + step·N) are
    free now."""

    def free(n: int) -> str | None:
        taken = [p + step * n for p in tcp_ports if not port_free(p + step * n, socket.SOCK_STREAM)]
        taken += [p + step * n for p in udp_ports if not port_free(p + step * n)]
        return f"ports {taken} in use" if taken else None

    candidates = list(range(1, 100))
    random.shuffle(candidates)
    with claimed_instance("ardupilot", candidates, free) as n:
        yield n


def widen_receive_buffer(bus: Any, size: int = 64 << 20) -> None:
    """Let an observer's udp_multicast socket queue ``size`` bytes: a thread in a busy test
    process may not read for a while, and ~1 600 frames/s (an FT bus) would overflow the
    default buffer within a tenth of a second. With CAP_NET_ADMIN (root) past the system's
    ``net.core.rmem_max`` (4 MiB here, some 5 s of an FT bus: the whole suite beside two busy
    processes starved a PX4 flight's observer longer); otherwise up to it. (A duplicate of the
    descriptor shares the socket, so closing it leaves the bus's own open.)"""
    with socket.fromfd(bus.fileno(), socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, size)
        except PermissionError:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)


def wide_observer(can_port: int) -> Observer:
    """An observer of the bus at ``can_port`` whose socket queues 64 MiB where allowed (see
    :func:`widen_receive_buffer`); ask :func:`udp_drops` afterwards whether it lost any."""
    observer = Observer(can_port)
    widen_receive_buffer(observer.bus)
    return observer


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
    """A subprocess in a session of its own, its output in a log file (never a pipe: a full
    pipe would block a daemon that logs more than a pipe holds in a long flight); always
    ended by :meth:`stop`."""

    def __init__(
        self,
        args: Sequence[str],
        log: Path,
        cwd: Path | None = None,
        env: dict[str, str] | None = None,
    ) -> None:
        self.args = list(args)
        self.log_path = log
        self._log: IO[bytes] = open(log, "ab")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            self.args,
            cwd=cwd,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
            start_new_session=True,
        )
        self.started = time.monotonic()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

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

    def output(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def tail(self, lines: int = 30) -> str:
        return "\n".join(self.output().splitlines()[-lines:])


def wait_until(
    condition: Callable[[], bool], timeout_s: float, what: str, poll_s: float = 0.02
) -> float:
    """Poll ``condition`` until it holds; its monotonic time. Fails naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while True:
        if condition():
            return time.monotonic()
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s} s")
        time.sleep(poll_s)


def make_realtime(pid: int) -> bool:
    """Run process ``pid`` at a low SCHED_FIFO priority where permitted (5: below the bridge's
    loop, 50); whether it was permitted.

    For the processes that play the hardware around the companion computer: the autopilot and
    the wire to it (the tap). SITL's clock (``time_usec``) is simulated time, which stands still
    while the process waits for a CPU, and a tap that waits delivers the outputs in bursts; a
    flight controller's hardware timer and a UART do neither. On a loaded test machine (2
    cores, the other xdist worker's tests beside) gaps of 100-300 ms were seen, each a stale
    input to the bridge, which then rightly went safe, and after the flight's 1 s stall the
    tap's bursts kept the bridge judging the inputs old for 1-12 s. Both sleep nearly all the
    time, so the priority costs the machine little (not so the ESC simulators: see
    :func:`start_sim`). Threads inherit the policy from the thread that creates them; any
    already there get it here too."""
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            os.sched_setscheduler(int(task.name), os.SCHED_FIFO, os.sched_param(5))
    except (PermissionError, OSError):
        return False
    return True


class SitlAutopilot:
    """What a test does to an autopilot's SITL process, whichever autopilot it is."""

    process: Process | None = None

    @property
    def pid(self) -> int:
        assert self.process is not None
        return self.process.pid

    def pause(self) -> None:
        """SIGSTOP: the autopilot falls silent, its simulated clock standing still."""
        assert self.process is not None
        os.kill(self.process.pid, signal.SIGSTOP)

    def resume(self) -> None:
        assert self.process is not None
        os.kill(self.process.pid, signal.SIGCONT)

    def kill(self) -> None:
        """SIGKILL: the links drop at once, as when the flight controller dies."""
        assert self.process is not None
        self.process.stop(signal.SIGKILL, timeout_s=5)

    def stop(self) -> None:
        if self.process is not None:
            self.process.stop(signal.SIGTERM, timeout_s=5)


class ArduCopter(SitlAutopilot):
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
        self.realtime = make_realtime(self.process.pid)


def write_bridge_config(
    path: Path,
    *,
    component_id: int,
    protocol: str,
    source: str | None = None,
    autopilot_system_id: int | None = None,
    stream_rate_hz: float = 200.0,
    input_timeout_ms: int = 100,
) -> Path:
    """A bridge configuration for the keys the CLI has no flag for (the autopilot's system id,
    the bridge's component id, the stream rate); the rest keeps the defaults."""
    mavlink_keys = [f"component_id = {component_id}", f"stream_rate_hz = {stream_rate_hz:g}"]
    if source is not None:
        mavlink_keys.append(f'source = "{source}"')
    if autopilot_system_id is not None:
        mavlink_keys.append(f"autopilot_system_id = {autopilot_system_id}")
    path.write_text(
        "[mavlink]\n"
        + "".join(f"{line}\n" for line in mavlink_keys)
        + f'[output]\nprotocol = "{protocol}"\ninput_timeout_ms = {input_timeout_ms}\n'
        + '[mixer]\nname = "passthrough-4"\n[escs]\nids = [1, 2, 3, 4]\n'
    )
    return path


def esc_period_s(config: Path) -> float:
    """How often a bridge run with ``config`` commands each ESC: its family's driver's ticks
    per cycle at its output rate (CKESC, DroneCAN: every tick; FT, VESC: one ESC a tick)."""
    built = build_config(read_config_file(config), str(config))
    return built.family.driver(built.esc_setup).ticks_per_cycle / built.rate_hz


def start_bridge(
    config: Path, mavlink_url: str, can_port: int, log_path: Path, *extra: str
) -> Process:
    """``esc-bridge run`` through its CLI on its own udp_multicast bus (port ``can_port``)."""
    return Process(
        [
            ESC_BRIDGE,
            "run",
            "--config",
            str(config),
            "--mavlink",
            mavlink_url,
            *can_args(can_port),
            # No Zenoh peer discovery: parallel test runs must never see each other.
            "--no-zenoh-scouting",
            *extra,
        ],
        log_path,
    )


def start_sim(can_port: int, log_path: Path, protocol: str, *extra: str) -> Process:
    """``esc-bridge sim``: four simulated ESCs, IDs (and CKESC throttle channels) 1..4, at nice
    -5 where permitted: ESCs whose telemetry does not pause for the other tests' load (a
    DroneCAN simulator fell silent for 794 ms at nice 0 beside the other xdist worker; at a
    real-time priority four of them starved the bridges)."""
    sim = Process(
        [ESC_BRIDGE, "sim", "--protocol", protocol, "--escs", "4", *can_args(can_port), *extra],
        log_path,
    )
    with contextlib.suppress(PermissionError, ProcessLookupError):
        os.setpriority(os.PRIO_PROCESS, sim.pid, -5)
    return sim


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
        self.realtime = make_realtime(self.process.pid)
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
    """A pymavlink ground station on an autopilot's GCS port, reading in a thread of its own:
    ``tcp:HOST:PORT`` (ArduPilot SITL's SERIAL ports; it connects, retrying until SITL
    listens) or ``udpout:HOST:PORT`` (PX4's GCS port; PX4 answers the sender). It sends a
    HEARTBEAT a second (PX4 talks only to a station that spoke first) and keeps every message
    it gets, decoded with the project's dialect (ESC_INFO, ESC_STATUS, ArduPilot's messages),
    with its monotonic receive time."""

    def __init__(
        self, url: str, system: int = 255, component: int = 190, connect_timeout_s: float = 20.0
    ) -> None:
        scheme, host, port = url.split(":")
        assert scheme in ("tcp", "udpout"), f"unsupported ground station link {url}"
        self.url = url
        self._address = (host, int(port))
        self.mav: Any = dialect.MAVLink(None, srcSystem=system, srcComponent=component)
        """The project dialect's encoder with this station's ids."""
        self._lock = threading.Lock()
        self.messages: list[tuple[float, Any]] = []
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.connect(connect_timeout_s)

    def connect(self, timeout_s: float) -> None:
        """Connect (again: a restarted SITL drops its TCP links)."""
        self.disconnect()
        if self.url.startswith("udpout:"):
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.connect(self._address)
        else:
            deadline = time.monotonic() + timeout_s
            while True:
                try:
                    sock = socket.create_connection(self._address, timeout=1.0)
                    break
                except OSError as exc:
                    if time.monotonic() > deadline:
                        raise AssertionError(
                            f"the autopilot's TCP port {self._address[1]} did not accept a "
                            f"connection within {timeout_s} s ({exc})"
                        ) from exc
                    time.sleep(0.1)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(0.1)
        self._sock = sock
        self._stop = threading.Event()
        parser: Any = dialect.MAVLink(None)
        parser.robust_parsing = True
        self._thread = threading.Thread(
            target=self._run, args=(sock, parser, self._stop), name="gcs", daemon=True
        )
        self._thread.start()

    def _run(self, sock: socket.socket, parser: Any, stop: threading.Event) -> None:
        next_beat = 0.0
        while not stop.is_set():
            now = time.monotonic()
            if now >= next_beat:
                beat = self.mav.heartbeat_encode(
                    dialect.MAV_TYPE_GCS, dialect.MAV_AUTOPILOT_INVALID, 0, 0, 4
                )
                with contextlib.suppress(OSError):
                    sock.send(beat.pack(self.mav))
                next_beat = now + 1.0
            try:
                data = sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                if self.url.startswith("udpout:"):  # nobody listening yet: ICMP refused
                    time.sleep(0.05)
                    continue
                return
            if not data:
                return
            stamp = time.monotonic()
            batch = [m for m in parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]
            with self._lock:
                self.messages.extend((stamp, m) for m in batch)

    def disconnect(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
        if self._sock is not None:
            self._sock.close()
        self._sock = None

    def close(self) -> None:
        self.disconnect()

    def send(self, msg: Any) -> None:
        assert self._sock is not None
        self._sock.send(msg.pack(self.mav))

    def send_command(self, command: int, *params: float, target: tuple[int, int] = (1, 1)) -> float:
        """Send COMMAND_LONG to ``target`` once; returns when it was sent."""
        values = [*params, *([0.0] * (7 - len(params)))]
        sent = time.monotonic()
        self.send(self.mav.command_long_encode(*target, command, 0, *values))
        return sent

    def ack(self, command: int, after: float, timeout_s: float = 5.0) -> int:
        """The result of the first COMMAND_ACK for ``command`` received after ``after``."""
        msg = self.wait_for(
            "COMMAND_ACK", lambda m: m.command == command, timeout_s, after, first=True
        )
        return int(msg.result)

    def command(
        self,
        target: tuple[int, int],
        command: int,
        params: Sequence[float],
        timeout_s: float,
        what: str,
        retry_s: float = 1.0,
    ) -> float:
        """Send COMMAND_LONG until it is ACCEPTED (refusals are retried: pre-arm checks pass
        a little after start-up); the monotonic time of the ACK. Fails naming ``what`` with
        the last results."""
        deadline = time.monotonic() + timeout_s
        results: list[int] = []
        while time.monotonic() < deadline:
            sent = self.send_command(command, *params, target=target)
            answer_by = min(deadline, sent + retry_s)
            while time.monotonic() < answer_by:
                acks = [
                    (t, m) for t, m in self.received("COMMAND_ACK", sent) if m.command == command
                ]
                if acks:
                    t, ack = acks[0]
                    if ack.result == dialect.MAV_RESULT_ACCEPTED:
                        return t
                    results.append(int(ack.result))
                    break
                time.sleep(0.02)
            time.sleep(max(0.0, answer_by - time.monotonic()))
        texts = [m.text for _, m in self.received("STATUSTEXT")][-5:]
        raise AssertionError(
            f"{what}: COMMAND_LONG {command} not accepted within {timeout_s} s "
            f"(results {results[-5:]}, last STATUSTEXTs {texts})"
        )

    def received(
        self, kind: str | None = None, after: float = 0.0, sender: tuple[int, int] | None = None
    ) -> list[tuple[float, Any]]:
        """(receive time, message) of ``kind`` (any: None) from ``after`` on, from ``sender``
        (system, component) or anyone."""
        with self._lock:
            return [
                (t, m)
                for t, m in self.messages
                if t >= after
                and (kind is None or m.get_type() == kind)
                and (sender is None or (m.get_srcSystem(), m.get_srcComponent()) == sender)
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
        """The last (``first``: the first) ``kind`` message after ``after`` that satisfies
        ``predicate``, waiting up to ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            found = [m for _, m in self.received(kind, after) if predicate(m)]
            if found:
                return found[0] if first else found[-1]
            if time.monotonic() > deadline:
                texts = [m.text for _, m in self.received("STATUSTEXT", after)][-8:]
                raise AssertionError(
                    f"no {what or kind} at the ground station within {timeout_s} s; "
                    f"the autopilot said: {texts}"
                )
            time.sleep(0.02)


def frame_reader(family: str) -> EscDecoder:
    """A decoder of the ESC family ``family`` (registry name) for one pass over one stream of
    frames: one of its own, since a family may keep state per stream (DroneCAN puts multi-frame
    transfers back together), and a pass that starts mid-record must not leave a half transfer
    to the next."""
    return registry.family(family).decoder()


def commands_by_motor(reader: EscDecoder, frame: EscFrame) -> dict[int, float] | None:
    """The motor commands a frame ``reader`` decoded carries, by motor (0-based), as the family
    reads them back (:meth:`EscDecoder.commands_seen`: CKESC throttles by channel, FT currents
    in A by ESC ID, DroneCAN RawCommand values by ESC number; the tests' bridges and ESCs
    number channels and IDs 1..4 for motors 1..4); None for any other frame."""
    commands = {}
    for seen in reader.commands_seen(frame):
        target = seen.node_id if seen.node_id is not None else seen.channel
        assert target is not None, f"a command for no ESC: {seen}"
        commands[target - 1] = seen.value
    return commands or None


def stream_answers(bridge_log: str, message: str) -> str:
    """What the autopilot answered the bridge's stream requests for ``message``, as the bridge
    logged each COMMAND_ACK ("ACCEPTED 200 Hz", "FAILED 20 Hz"), in order, repeats folded;
    "no answer logged" when there was none."""
    pattern = re.compile(
        rf"autopilot \d+/\d+:? (?:([A-Z_]+) )?{message} at ([\d.]+) Hz(?:: MAV_RESULT_([A-Z_]+))?"
    )
    answers: list[str] = []
    for match in pattern.finditer(bridge_log):
        answer = f"{match[1] or match[3]} {match[2]} Hz"
        if (match[1] or match[3]) and (not answers or answers[-1] != answer):
            answers.append(answer)
    return ", ".join(answers) or "no answer logged"


def armed(heartbeat: Any) -> bool:
    return bool(heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)


def from_autopilot(msg: Any) -> bool:
    return bool(msg.get_srcSystem() == 1 and msg.get_srcComponent() == 1)
