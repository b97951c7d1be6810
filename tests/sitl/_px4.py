"""Harness for flying a real PX4 SITL (SIH quad, no Gazebo) through the bridge.

Two parts. The first section holds generic pieces any real-autopilot test needs (a logged
subprocess, the bridge and the simulated ESCs through their CLI, a UDP tap that records what
the autopilot sends the bridge, a pymavlink ground station); they are kept apart so that they
can move into ``tests/sitl/conftest.py`` beside the ArduCopter harness. The second section is
PX4's: finding and extracting the build, claiming an instance number whose ports are free,
starting, stalling, killing and restarting PX4, and adding onboard MAVLink links to it.
"""

from __future__ import annotations

import contextlib
import fcntl
import multiprocessing
import os
import signal
import socket
import subprocess
import tarfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

# conftest sets MAVLINK20 before pymavlink is first imported (MAVLink 2, as PX4 speaks).
from conftest import ESC_BRIDGE, MULTICAST_GROUP, ROOT
from pymavlink import mavutil

from bridge.mavlink import load_dialect

from . import _udp_tap

dialect: Any = load_dialect()

# =============================================================================================
# Generic helpers (candidates for tests/sitl/conftest.py, shared with the ArduCopter harness)
# =============================================================================================


def wait_until(
    condition: Callable[[], bool], timeout_s: float, what: str, poll_s: float = 0.02
) -> float:
    """Poll ``condition`` until it holds; its monotonic time. Fails naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return time.monotonic()
        time.sleep(poll_s)
    raise AssertionError(f"{what}: not within {timeout_s} s")


class LoggedProcess:
    """A subprocess in a process group of its own, its output in a file (never a pipe: a
    full pipe would block a daemon that logs more than a pipe holds in a long flight)."""

    def __init__(
        self, args: Sequence[str], log_path: Path, env: dict[str, str] | None = None
    ) -> None:
        self.args = list(args)
        self.log_path = log_path
        self._log: IO[bytes] = log_path.open("ab")
        self.proc = subprocess.Popen(
            self.args,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
            start_new_session=True,
        )

    @property
    def pid(self) -> int:
        return self.proc.pid

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 10.0) -> int:
        """Signal the whole group (a stopped process is continued first so it can act on
        it), then kill what is left after ``timeout_s``; the exit status."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGCONT)
                os.killpg(self.proc.pid, sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        # Children the leader left behind (the bridge's loop exits by itself; anything else
        # of the group must not outlive the test).
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self._log.close()
        return self.proc.returncode


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


def write_bridge_config(
    path: Path,
    *,
    source: str,
    autopilot_system_id: int,
    component_id: int,
    protocol: str = "ckesc",
    stream_rate_hz: float = 200.0,
    input_timeout_ms: int = 100,
) -> Path:
    """A bridge configuration for the keys the CLI has no flag for (the autopilot's system id,
    the bridge's component id); the rest comes as flags."""
    path.write_text(
        "[mavlink]\n"
        f'source = "{source}"\n'
        f"autopilot_system_id = {autopilot_system_id}\n"
        f"component_id = {component_id}\n"
        f"stream_rate_hz = {stream_rate_hz}\n"
        "[output]\n"
        f'protocol = "{protocol}"\n'
        f"input_timeout_ms = {input_timeout_ms}\n"
        "[mixer]\n"
        'name = "passthrough-4"\n'
        "[escs]\n"
        "ids = [1, 2, 3, 4]\n"
    )
    return path


def start_bridge(
    config: Path, mavlink_url: str, can_port: int, log_path: Path, *extra: str
) -> LoggedProcess:
    """``esc-bridge run`` through its CLI on the bus ``can_port``."""
    return LoggedProcess(
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


def start_sim_escs(can_port: int, log_path: Path, protocol: str = "ckesc") -> LoggedProcess:
    """``esc-bridge sim``: four simulated ESCs, IDs (and CKESC throttle channels) 1..4."""
    return LoggedProcess(
        [
            ESC_BRIDGE,
            "sim",
            "--protocol",
            protocol,
            "--escs",
            "4",
            *can_args(can_port),
            "--status-interval",
            "60",
        ],
        log_path,
    )


class UdpTap:
    """A UDP relay between an autopilot's link and the bridge, in a process of its own: it
    forwards every datagram both ways unchanged and records each one the autopilot sends,
    stamped with the monotonic clock just before it is forwarded. It is the test's own view
    of which motor output the bridge had at any moment (a relay on loopback adds tens of µs).
    """

    def __init__(self, listen_port: int, bridge_port: int, record: Path) -> None:
        self.listen_port = listen_port
        self.bridge_port = bridge_port
        self.record = record
        ctx = multiprocessing.get_context("spawn")
        self._stop = ctx.Event()
        ready = ctx.Event()
        # The relay's body lives in a module of the standard library only: a spawned child
        # imports it in milliseconds, where this module's imports (pymavlink, the dialect)
        # take seconds on a loaded machine, and PX4's first packets would find no one.
        self._process = ctx.Process(
            target=_udp_tap.run,
            args=(listen_port, bridge_port, str(record), self._stop, ready),
            name="udp-tap",
            daemon=True,
        )
        self._process.start()
        if not ready.wait(20):
            self.close()
            raise AssertionError(f"the UDP tap on port {listen_port} did not start in 20 s")
        self._parser: Any = dialect.MAVLink(None)
        self._parser.robust_parsing = True
        self._offset = 0
        self.messages: list[tuple[float, Any]] = []
        """(monotonic s, message) of everything read so far by :meth:`poll`."""

    def poll(self) -> list[tuple[float, Any]]:
        """Parse what was recorded since the last call; all messages so far."""
        data = b""  # the tap's process may not have created the file yet
        with contextlib.suppress(FileNotFoundError), self.record.open("rb") as f:
            f.seek(self._offset)
            data = f.read()
        at = 0
        while at + 12 <= len(data):
            stamp = int.from_bytes(data[at : at + 8], "little") / 1e9
            size = int.from_bytes(data[at + 8 : at + 12], "little")
            if at + 12 + size > len(data):
                break
            for msg in self._parser.parse_buffer(data[at + 12 : at + 12 + size]) or []:
                if msg.get_type() != "BAD_DATA":
                    self.messages.append((stamp, msg))
            at += 12 + size
        self._offset += at
        return self.messages

    def close(self) -> None:
        self._stop.set()
        self._process.join(3)
        if self._process.is_alive():
            self._process.kill()


class GroundStation:
    """A pymavlink ground station on an autopilot's GCS port: it speaks first (a HEARTBEAT a
    second), so the autopilot answers to its own port, and it keeps every message it gets,
    decoded with the project's dialect (ESC_INFO, ESC_STATUS), with its receive time."""

    def __init__(self, url: str, system: int = 255, component: int = 190) -> None:
        self.conn: Any = mavutil.mavlink_connection(
            url, source_system=system, source_component=component
        )
        self.mav: Any = dialect.MAVLink(self.conn, srcSystem=system, srcComponent=component)
        """The project dialect's encoder with this station's ids."""
        self._parser: Any = dialect.MAVLink(None)
        self._parser.robust_parsing = True
        self.messages: list[tuple[float, Any]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="gcs", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_beat = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_beat:
                with contextlib.suppress(OSError):
                    self.send(
                        self.mav.heartbeat_encode(
                            dialect.MAV_TYPE_GCS, dialect.MAV_AUTOPILOT_INVALID, 0, 0, 4
                        )
                    )
                next_beat = now + 1.0
            try:
                data = self.conn.recv()
            except OSError:
                time.sleep(0.01)
                continue
            if not data:
                time.sleep(0.002)
                continue
            stamp = time.monotonic()
            batch = [m for m in self._parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]
            with self._lock:
                self.messages.extend((stamp, m) for m in batch)

    def send(self, msg: Any) -> None:
        self.conn.write(msg.pack(self.mav))

    def received(
        self, kind: str, after: float = 0.0, sender: tuple[int, int] | None = None
    ) -> list[tuple[float, Any]]:
        with self._lock:
            return [
                (t, m)
                for t, m in self.messages
                if t >= after
                and m.get_type() == kind
                and (sender is None or (m.get_srcSystem(), m.get_srcComponent()) == sender)
            ]

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
        the last result."""
        deadline = time.monotonic() + timeout_s
        results: list[int] = []
        while time.monotonic() < deadline:
            sent = time.monotonic()
            p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
            self.send(self.mav.command_long_encode(*target, command, 0, *p))
            answer_by = min(deadline, sent + retry_s)
            while time.monotonic() < answer_by:
                for t, ack in self.received("COMMAND_ACK", after=sent):
                    if ack.command == command:
                        if ack.result == dialect.MAV_RESULT_ACCEPTED:
                            return t
                        results.append(int(ack.result))
                        break
                else:
                    time.sleep(0.02)
                    continue
                break
            time.sleep(max(0.0, answer_by - time.monotonic()))
        texts = [m.text for _, m in self.received("STATUSTEXT")][-5:]
        raise AssertionError(
            f"{what}: COMMAND_LONG {command} not accepted within {timeout_s} s "
            f"(results {results[-5:]}, last STATUSTEXTs {texts})"
        )

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.conn.close()


def udp_port_free(port: int) -> bool:
    """Nobody has ``port`` bound on this machine (any address: PX4 binds them all)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


# =============================================================================================
# PX4
# =============================================================================================

BUILD_ENV = "ESC_BRIDGE_PX4"
"""A PX4 SITL tarball (like the one below) or an extracted ``px4-sitl`` directory."""
DEFAULT_BUILD = ROOT.parent / "shared" / "sitl" / "px4" / "px4-sitl-v1.16.0-sih.tar.gz"
# PX4's posix start-up gives instance N these UDP ports (its etc/init.d-posix/px4-rc.mavlink):
# it binds the first of each pair and sends to the second. Above 9 its onboard links share
# remote ports, so only 0..9 can run side by side.
_PORT_BASES = ((14580, 14540), (18570, None), (14280, 14030), (13030, 13280), (19450, 19410))
MAX_INSTANCES = 10
PAYLOAD_PORT_BASE = 14280
PX4_READY = "Ready for takeoff"


def find_build() -> tuple[Path | None, str]:
    """The PX4 build to use (``$ESC_BRIDGE_PX4``, else the shared tarball), or None with why."""
    configured = os.environ.get(BUILD_ENV)
    path = Path(configured) if configured else DEFAULT_BUILD
    origin = f"${BUILD_ENV}={configured}" if configured else f"the default {DEFAULT_BUILD}"
    if path.is_file():
        return path, ""
    if (path / "bin" / "px4").is_file() and (path / "etc").is_dir():
        return path, ""
    if path.is_dir():
        return None, f"PX4 SITL build: {origin} is a directory without bin/px4 and etc/"
    return None, (
        f"PX4 SITL build not found: {origin} does not exist; set {BUILD_ENV} to a PX4 SITL "
        "tarball or an extracted px4-sitl directory (bin/px4 + etc/)"
    )


def extract_build(build: Path, into: Path) -> Path:
    """The ``px4-sitl`` root of ``build`` (a directory is used in place; a tarball is
    extracted into ``into``)."""
    if build.is_dir():
        return build
    with tarfile.open(build) as tar:
        # "data" refuses absolute paths and links out of the tree; px4's command links are
        # relative symlinks to bin/px4, which it keeps.
        tar.extractall(into, filter="data")
    for candidate in (into, *sorted(into.iterdir())):
        if (candidate / "bin" / "px4").is_file() and (candidate / "etc").is_dir():
            return candidate
    raise AssertionError(f"{build}: no bin/px4 and etc/ inside after extraction")


@dataclass(frozen=True)
class Px4Ports:
    onboard_local: int
    """PX4 sends its onboard link from here ..."""
    onboard_remote: int
    """... to 127.0.0.1 here (a companion listens)."""
    gcs_local: int
    """A ground station sends here; PX4 answers to the sender."""


class InstanceClaim:
    """A PX4 instance number held for this test only: a lock file any other test process on
    this machine also takes, a free PX4 server socket and every port of the instance free."""

    def __init__(self, first: int = 0) -> None:
        self.number = -1
        self._lock: IO[bytes] | None = None
        busy: list[str] = []
        for n in [*range(first, MAX_INSTANCES), *range(first)]:
            # Held open (and locked) for the instance's life, so not a with-block.
            lock = Path(f"/tmp/esc-bridge-px4-instance-{n}.lock").open("ab")  # noqa: SIM115
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                lock.close()
                busy.append(f"{n}: locked by another test")
                continue
            taken = [
                port
                for local, remote in _PORT_BASES
                for port in (local + n, *(() if remote is None else (remote + n,)))
                if not udp_port_free(port)
            ]
            if taken or self._server_running(n):
                lock.close()
                busy.append(f"{n}: ports {taken} in use" if taken else f"{n}: a PX4 runs")
                continue
            self.number, self._lock = n, lock
            return
        raise AssertionError(f"no free PX4 SITL instance: {'; '.join(busy)}")

    @staticmethod
    def _server_running(n: int) -> bool:
        """A PX4 daemon of instance ``n`` answers on its command socket."""
        path = f"/tmp/px4-sock-{n}"
        if not os.path.exists(path):
            return False
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            try:
                sock.connect(path)
            except OSError:
                return False
        return True

    @property
    def ports(self) -> Px4Ports:
        n = self.number
        return Px4Ports(14580 + n, 14540 + n, 18570 + n)

    def release(self) -> None:
        if self._lock is not None:
            self._lock.close()
            self._lock = None


class Px4:
    """One PX4 SITL instance (SIH quad), in a working directory of its own."""

    def __init__(self, root: Path, instance: int, workdir: Path) -> None:
        self.root = root
        self.instance = instance
        self.workdir = workdir
        self.system_id = instance + 1  # its start-up sets MAV_SYS_ID to the instance + 1
        self.process: LoggedProcess | None = None
        self.starts = 0
        self._links: list[tuple[int, int]] = []

    def start(self) -> None:
        """Start it (again, on the same working directory and parameters after a kill)."""
        assert self.process is None or not self.process.alive(), "PX4 already running"
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.starts += 1
        self.process = LoggedProcess(
            [
                str(self.root / "bin" / "px4"),
                "-d",
                "-i",
                str(self.instance),
                "-w",
                str(self.workdir),
                str(self.root / "etc"),
            ],
            self.workdir.parent / f"px4-{self.instance}-start{self.starts}.log",
            env={"PX4_SIM_MODEL": "sihsim_quadx", "PX4_SIMULATOR": "sihsim"},
        )

    def wait_ready(self, timeout_s: float = 30.0) -> float:
        """Until PX4 says it is ready for takeoff; the monotonic time it was seen."""
        process = self.process
        assert process is not None

        def ready() -> bool:
            if not process.alive():
                raise AssertionError(f"PX4 exited at start:\n{process.output()[-3000:]}")
            return PX4_READY in process.output()

        try:
            return wait_until(ready, timeout_s, "PX4 'Ready for takeoff'", poll_s=0.05)
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{process.output()[-3000:]}") from None

    def shell(self, *args: str, timeout_s: float = 10.0) -> None:
        """A PX4 shell command through its client (``px4-<module> --instance N ...``)."""
        tool = self.root / "bin" / f"px4-{args[0]}"
        subprocess.run(
            [str(tool), "--instance", str(self.instance), *args[1:]],
            check=True,
            timeout=timeout_s,
            capture_output=True,
        )

    def add_onboard_link(self, local_port: int, remote_port: int) -> None:
        """Another onboard MAVLink link (like its own: 4 MB/s, forwarding on) from
        ``local_port`` to 127.0.0.1:``remote_port``; added again after every restart."""
        self._links.append((local_port, remote_port))
        self._start_link(len(self._links) - 1)

    def _start_link(self, index: int) -> None:
        if index == 1:
            # PX4 runs at most six MAVLink instances and SITL starts five; a second link of
            # ours takes the slot of the camera's payload link (unused with SIH).
            self.shell("mavlink", "stop", "-u", str(PAYLOAD_PORT_BASE + self.instance))
        local_port, remote_port = self._links[index]
        self.shell(
            "mavlink",
            "start",
            "-u",
            str(local_port),
            "-o",
            str(remote_port),
            "-m",
            "onboard",
            "-r",
            "4000000",
            "-f",
        )

    def restore_links(self) -> None:
        for index in range(len(self._links)):
            self._start_link(index)

    def pause(self) -> None:
        assert self.process is not None
        os.kill(self.process.pid, signal.SIGSTOP)

    def resume(self) -> None:
        assert self.process is not None
        os.kill(self.process.pid, signal.SIGCONT)

    def kill(self) -> None:
        assert self.process is not None
        self.process.stop(signal.SIGKILL, timeout_s=5)

    def stop(self) -> None:
        if self.process is not None:
            self.process.stop(signal.SIGTERM, timeout_s=5)


@contextlib.contextmanager
def px4_instance(root: Path, workdir: Path) -> Iterator[tuple[Px4, InstanceClaim]]:
    """A claimed instance number and a PX4 on it (not started); stopped and released after."""
    claim = InstanceClaim()
    px4 = Px4(root, claim.number, workdir / f"px4-{claim.number}")
    try:
        yield px4, claim
    finally:
        px4.stop()
        claim.release()
