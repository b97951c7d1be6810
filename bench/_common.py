"""What the benchmarks that run the bridge share: the bus they put it on, the sockets they watch
that bus with, /proc readings, and the bits of their reports.

The bridge runs through its CLI on a udp_multicast CAN bus of this machine (TTL/hop limit 0:
never leaves it) and MAVLink on loopback UDP; one copy of that command line, of the socket
options and of the /proc parsing keeps every bench measuring the same way.
"""

from __future__ import annotations

import os
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

# The load generators (loadgen/, beside bench/) are test and bench support, not installed: a
# bench script run as `python bench/NAME.py` finds them through this, its first import.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from loadgen.load import stat_fields

GROUP = "239.74.163.2"
ESC_BRIDGE = str(Path(sys.executable).parent / "esc-bridge")
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
# Not every Python names these Linux socket options; the numbers are Linux's.
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
OBSERVER_RCVBUF = 8 << 20
TIMESPEC = struct.Struct("@ll")
MAX_DATAGRAM = 4096


# -- the bridge -----------------------------------------------------------------------------


def bridge_command(mavlink_port: int, can_port: int, log_level: str) -> list[str]:
    """``esc-bridge run`` with MAVLink on loopback UDP port ``mavlink_port`` and the CAN bus on
    udp_multicast port ``can_port``; a bench appends its own flags (--config, ...)."""
    return [
        ESC_BRIDGE,
        "run",
        "--log-level",
        log_level,
        "--mavlink",
        f"udpin:127.0.0.1:{mavlink_port}",
        "--can-interface",
        "udp_multicast",
        "--can-channel",
        GROUP,
        "--can-option",
        f"port={can_port}",
        "--can-option",
        "hop_limit=0",
    ]


def log_tail(path: Path, text: str | None = None, lines: int = 15) -> str:
    """The last ``lines`` lines of a log: of ``text`` if given (already read), else of ``path``."""
    if text is None:
        text = path.read_text(errors="replace")
    return "\n".join(text.splitlines()[-lines:])


# -- sockets --------------------------------------------------------------------------------


def free_port() -> int:
    """A UDP port on loopback that nothing holds now (the kernel's pick)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def multicast_listener(port: int) -> socket.socket:
    """A socket on the bus, as python-can's udp_multicast opens it, with a large buffer."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, OBSERVER_RCVBUF)
    except PermissionError:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, OBSERVER_RCVBUF)
    sock.bind(("", port))
    request = socket.inet_aton(GROUP) + struct.pack("@I", socket.INADDR_ANY)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, request)
    return sock


def recv_stamped(sock: socket.socket) -> tuple[bytes, int, float]:
    """One datagram, its sender's port and its kernel receive time (wall clock, s)."""
    data, ancillary, _flags, sender = sock.recvmsg(MAX_DATAGRAM, socket.CMSG_SPACE(TIMESPEC.size))
    stamp = time.time()
    for level, kind, payload in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            seconds, nanoseconds = TIMESPEC.unpack(payload[: TIMESPEC.size])
            stamp = seconds + nanoseconds * 1e-9
    return data, int(sender[1]), stamp


# -- /proc ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class UdpSocket:
    """One line of /proc/net/udp."""

    inode: int
    rx_queue_bytes: int
    drops: int


def udp_sockets(port: int) -> dict[int, UdpSocket]:
    """Every IPv4 UDP socket bound to ``port``, by inode."""
    found = {}
    with suppress(OSError):
        for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
            fields = line.split()
            if int(fields[1].rsplit(":", 1)[1], 16) != port:
                continue
            inode = int(fields[9])
            found[inode] = UdpSocket(inode, int(fields[4].split(":")[1], 16), int(fields[12]))
    return found


def socket_inodes(pid: int) -> set[int]:
    """The inodes of the sockets process ``pid`` holds (none if it is gone)."""
    inodes = set()
    with suppress(OSError):
        for fd in os.listdir(f"/proc/{pid}/fd"):
            with suppress(OSError):
                target = os.readlink(f"/proc/{pid}/fd/{fd}")
                if target.startswith("socket:["):
                    inodes.add(int(target[8:-1]))
    return inodes


def process_sockets(pid: int, port: int) -> list[UdpSocket]:
    """The UDP sockets on ``port`` that process ``pid`` holds."""
    mine = socket_inodes(pid)
    return [s for inode, s in udp_sockets(port).items() if inode in mine]


def children(pid: int) -> list[int]:
    """The live processes whose parent is ``pid``."""
    kids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        fields = stat_fields(int(entry.name))
        if fields is not None and int(fields[1]) == pid:
            kids.append(int(entry.name))
    return kids


def cpu_seconds(pids: Sequence[int]) -> float:
    """User + system time of ``pids``, each as of now (a process gone counts 0)."""
    total = 0
    for pid in pids:
        if (fields := stat_fields(pid)) is not None:
            total += int(fields[11]) + int(fields[12])
    return total / CLOCK_TICKS


def context_switches(pids: Sequence[int]) -> int:
    """Context switches of every thread of ``pids`` so far, voluntary (a wait: each a wake-up
    later) and not (preempted); a process or thread gone counts 0."""
    total = 0
    for pid in pids:
        with suppress(OSError):
            for tid in os.listdir(f"/proc/{pid}/task"):
                with suppress(OSError):
                    status = Path(f"/proc/{pid}/task/{tid}/status").read_text()
                    for line in status.splitlines():
                        # voluntary_ctxt_switches: and nonvoluntary_ctxt_switches:
                        if line.startswith(("voluntary_ctxt", "nonvoluntary_ctxt")):
                            total += int(line.split()[1])
    return total


def machine_busy_seconds() -> float:
    """CPU time all CPUs spent on anything but idle and I/O wait since boot."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return (sum(fields[:8]) - fields[3] - fields[4]) / CLOCK_TICKS


def set_fifo(priority: int) -> str | None:
    """SCHED_FIFO at ``priority`` for this process; None if done, else why not."""
    if priority <= 0:
        return "not asked for (priority 0)"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        return f"not permitted ({exc})"
    return None


def process_tree(pid: int) -> list[int]:
    """``pid`` and every live process under it (the daemon, its output loop, its helpers)."""
    parents: dict[int, list[int]] = {}
    for entry in os.scandir("/proc"):
        if entry.name.isdigit() and (fields := stat_fields(int(entry.name))) is not None:
            parents.setdefault(int(fields[1]), []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        current = todo.pop()
        found.append(current)
        todo.extend(parents.get(current, []))
    return found


def holds_bus(pid: int, port: int) -> bool:
    """Whether ``pid`` or a process under it holds a UDP socket bound to ``port``."""
    inodes = {inode for member in process_tree(pid) for inode in socket_inodes(member)}
    return not inodes.isdisjoint(udp_sockets(port))


def wait_for(
    done: Any, timeout_s: float, what: str, daemon: subprocess.Popen[bytes], log_path: Path
) -> None:
    """Wait until ``done()``, or raise if the daemon exits or ``timeout_s`` passes first."""
    deadline = time.monotonic() + timeout_s
    while not done():
        if daemon.poll() is not None:
            raise RuntimeError(
                f"the bridge exited (code {daemon.returncode}) {what}:\n{log_tail(log_path)}"
            )
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out {what}:\n{log_tail(log_path)}")
        time.sleep(0.02)


def sleep_watching(seconds: float, daemon: subprocess.Popen[bytes], log_path: Path) -> None:
    end = time.monotonic() + seconds
    wait_for(lambda: time.monotonic() >= end, seconds + 5.0, "during the run", daemon, log_path)


# -- processes and reports ------------------------------------------------------------------


def ignore_sigint() -> None:
    """Workers leave Ctrl-C to the parent, which stops them."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def raise_interrupt(_signum: int, _frame: FrameType | None) -> None:
    """A SIGTERM handler: stop as Ctrl-C does, so the bench stops what it started."""
    raise KeyboardInterrupt


class Processes:
    """Everything a run started (see :func:`processes`), stopped by :meth:`stop_all`: workers
    are asked to stop, the bridge gets SIGTERM and ``daemon_timeout_s`` to exit, then whatever
    is still there is killed."""

    def __init__(self, daemon_timeout_s: float) -> None:
        self.daemon: subprocess.Popen[bytes] | None = None
        self._daemon_timeout_s = daemon_timeout_s
        self._workers: list[tuple[Any, Any]] = []  # (process, its stop event or None)

    def add_worker(self, process: Any, stop: Any = None) -> None:
        """Stop ``process`` (a multiprocessing one) by setting ``stop``, its stop event, so
        that it still reports; without one, by SIGTERM. Killed if not gone 5 s later."""
        self._workers.append((process, stop))

    def stop_all(self) -> None:
        for process, stop in self._workers:
            if stop is not None:
                stop.set()
            elif process.is_alive():
                process.terminate()
        if self.daemon is not None and self.daemon.poll() is None:
            self.daemon.send_signal(signal.SIGTERM)
            try:
                self.daemon.wait(self._daemon_timeout_s)
            except subprocess.TimeoutExpired:
                self.daemon.kill()  # its loop process follows: it watches its parent
                self.daemon.wait()
        for process, _stop in self._workers:
            process.join(5)
            if process.is_alive():
                process.kill()
                process.join()


@contextmanager
def processes(daemon_timeout_s: float) -> Iterator[Processes]:
    """The :class:`Processes` of one run, all stopped when the ``with`` block ends, however."""
    procs = Processes(daemon_timeout_s)
    try:
        yield procs
    finally:
        procs.stop_all()


def num(value: float | int | None, spec: str, width: int) -> str:
    """A table cell: ``value`` formatted by ``spec`` in ``width`` columns, '-' for None or NaN."""
    if value is None or value != value:  # None or NaN
        return f"{'-':>{width}}"
    return f"{value:>{width}{spec}}"
