"""The PX4 harness for tests/sitl/test_px4.py: a real PX4 SITL (SIH quad, no Gazebo).

Finding and extracting the build (``$ESC_BRIDGE_PX4``), claiming an instance number whose ports
are free, starting, stalling, killing and restarting PX4, adding onboard MAVLink links to it,
and the UDP tap that records what PX4 sends a bridge.
The generic pieces (processes, the bridge and the simulated ESCs through their CLI, waits,
instance locks, the ground station) are the package's, in ``tests/sitl/conftest.py``.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import socket
import subprocess
import tarfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from conftest import ROOT

from . import _udp_tap
from .conftest import (
    Process,
    SitlAutopilot,
    claimed_instance,
    dialect,
    make_realtime,
    port_free,
    wait_until,
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
        # The wire to the autopilot, real-time as ArduCopter's tap is. At normal priority,
        # beside the whole suite, a tap can sit on PX4's outputs past input_timeout_ms and stamp
        # them fresh as it forwards them: the bridge's rightly safe frames then look like motor
        # stops (seen: all-zero frames on two sides in the same 50 ms, input "fresh").
        assert self._process.pid is not None
        make_realtime(self._process.pid)
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


def _instance_free(n: int) -> str | None:
    """Why PX4 instance ``n`` cannot run now (its ports taken, a PX4 of it running), or None."""
    taken = [
        port
        for local, remote in _PORT_BASES
        for port in (local + n, *(() if remote is None else (remote + n,)))
        if not port_free(port)
    ]
    if taken:
        return f"ports {taken} in use"
    # A PX4 daemon of instance n answers on its command socket.
    path = f"/tmp/px4-sock-{n}"
    if os.path.exists(path):
        with (
            socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock,
            contextlib.suppress(OSError),
        ):
            sock.connect(path)
            return "a PX4 runs"
    return None


def px4_ports(n: int) -> Px4Ports:
    return Px4Ports(14580 + n, 14540 + n, 18570 + n)


class Px4(SitlAutopilot):
    """One PX4 SITL instance (SIH quad), in a working directory of its own."""

    def __init__(self, root: Path, instance: int, workdir: Path) -> None:
        self.root = root
        self.instance = instance
        self.workdir = workdir
        self.system_id = instance + 1  # its start-up sets MAV_SYS_ID to the instance + 1
        self.ports = px4_ports(instance)
        self.process: Process | None = None
        self.starts = 0
        self._links: list[tuple[int, int]] = []

    def start(self) -> None:
        """Start it (again, on the same working directory and parameters after a kill)."""
        assert self.process is None or not self.process.alive(), "PX4 already running"
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.starts += 1
        self.process = Process(
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


@contextlib.contextmanager
def px4_instance(root: Path, workdir: Path) -> Iterator[Px4]:
    """A claimed instance number and a PX4 on it (not started); stopped and released after."""
    with claimed_instance("px4", range(MAX_INSTANCES), _instance_free) as n:
        px4 = Px4(root, n, workdir / f"px4-{n}")
        try:
            yield px4
        finally:
            px4.stop()
