"""What a test's function uses on the kernel under test: its interfaces, processes and observers.

These run where the agent (:mod:`linux.agent`) runs: inside User-Mode Linux, or on a host that
makes its own vcan. A function the host's test asks for (``linux.call(function, ...)``) uses
them and returns plain data (numbers, strings, lists and dicts: JSON) for the host to assert on.

Everything a call starts is its own and ends with it: the processes (:func:`start`), the
interfaces (:func:`vcan`) and the scratch directory (:func:`scratch`); what the processes
printed and every command run goes into :data:`LOG`, which the host shows when its test fails.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import can
import conftest

MODE = os.environ.get("ESC_BRIDGE_KERNEL", "host")
"""``uml`` inside User-Mode Linux (the guest's own kernel: any interface name is free), else
``host`` (the host's kernel: interfaces get names of their own, and are removed after)."""

ESC_BRIDGE = str(Path(sys.executable).parent / "esc-bridge")
CANDUMP_BUFFER_BYTES = 8 << 20
CANDUMP_LINE = re.compile(r"\((?P<time>\d+\.\d+)\) (?P<channel>\S+) (?P<frame>\S+)")


class Log:
    """What happened during one call: commands, their outputs, what processes printed."""

    def __init__(self) -> None:
        self._parts: list[str] = []
        self._started = time.monotonic()

    def reset(self, title: str) -> None:
        self._parts = [f"== {title}"]
        self._started = time.monotonic()

    def add(self, text: str) -> None:
        self._parts.append(f"[{time.monotonic() - self._started:7.3f}] {text.rstrip()}")

    def text(self) -> str:
        return "\n".join(self._parts)


LOG = Log()


@dataclass
class _Call:
    processes: list[Process] = field(default_factory=list)
    interfaces: list[str] = field(default_factory=list)
    scratch: Path | None = None


_call = _Call()
_names = itertools.count()


def begin_call(title: str) -> None:
    global _call
    LOG.reset(title)
    _call = _Call()


def end_call() -> None:
    """Stop what the call left running (its output into the log), remove its interfaces and
    scratch directory."""
    for process in reversed(_call.processes):
        if process.running():
            LOG.add(f"{process.name}: still running at the end of the call; killed")
            process.stop(signal.SIGKILL)
    for process in _call.processes:
        LOG.add(f"--- {process.name} ({' '.join(process.argv)}), exit {process.returncode}:")
        LOG.add(process.output()[-20_000:])
    for name in _call.interfaces:
        subprocess.run(["ip", "link", "delete", name], capture_output=True, check=False)
    if _call.scratch is not None:
        shutil.rmtree(_call.scratch, ignore_errors=True)


def scratch() -> Path:
    """A directory of this call's, on the guest's own memory (never the host's files)."""
    if _call.scratch is None:
        base = "/run" if MODE == "uml" else None
        _call.scratch = Path(tempfile.mkdtemp(prefix="esc-bridge-call-", dir=base))
    return _call.scratch


def run(argv: Sequence[str], *, check: bool = True, timeout_s: float = 30.0) -> str:
    """Run a command to its end; its output (stdout and stderr), logged.

    Raises:
        subprocess.CalledProcessError: it failed (with ``check``).
    """
    done = subprocess.run(
        list(argv),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=timeout_s,
        check=False,
    )
    LOG.add(f"$ {' '.join(argv)} -> {done.returncode}\n{done.stdout}")
    if check and done.returncode != 0:
        raise subprocess.CalledProcessError(done.returncode, list(argv), done.stdout)
    return done.stdout


def vcan(*, up: bool = True) -> str:
    """A new vcan interface of this call's (``can0``, ``can1``, ... in the guest), removed at
    the end of the call."""
    number = next(_names)
    name = f"can{number}" if MODE == "uml" else f"ebt{os.getpid() % 100000}x{number}"
    run(["ip", "link", "add", "dev", name, "type", "vcan"])
    _call.interfaces.append(name)
    if up:
        run(["ip", "link", "set", name, "up"])
    return name


class Process:
    """A process of this call's; its output (stdout and stderr) goes to a file in scratch."""

    def __init__(self, argv: Sequence[str], name: str, env: dict[str, str] | None = None) -> None:
        self.argv = list(argv)
        self.name = name
        self._path = scratch() / f"{name}-{len(_call.processes)}.out"
        self._file: IO[bytes] = self._path.open("wb")
        self.proc = subprocess.Popen(
            self.argv,
            stdin=subprocess.DEVNULL,
            stdout=self._file,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
            start_new_session=True,  # a group of its own: a stop reaches its children too
        )
        _call.processes.append(self)
        LOG.add(f"started {name} (pid {self.proc.pid}): {' '.join(self.argv)}")

    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def returncode(self) -> int | None:
        return self.proc.returncode

    def running(self) -> bool:
        return self.proc.poll() is None

    def output(self) -> str:
        return self._path.read_text(errors="replace")

    def send(self, sig: int) -> None:
        """Signal the process itself (not its group)."""
        if self.running():
            self.proc.send_signal(sig)

    def wait(self, timeout_s: float) -> int:
        """Wait for the process to end by itself.

        Raises:
            AssertionError: it did not within ``timeout_s``.
        """
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{self.name} did not end within {timeout_s} s") from None

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 20.0) -> int:
        """Signal the process (a SIGKILL goes to its whole group) and wait for its exit."""
        if self.running():
            with contextlib.suppress(ProcessLookupError):
                if sig == signal.SIGKILL:
                    os.killpg(self.proc.pid, sig)
                else:
                    self.proc.send_signal(sig)
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            LOG.add(f"{self.name}: no exit {timeout_s} s after signal {sig}; killed")
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        self._file.close()
        return self.proc.returncode

    def wait_for_output(self, text: str, timeout_s: float) -> None:
        """Wait until the process has printed ``text``.

        Raises:
            AssertionError: not within ``timeout_s``, or the process ended first.
        """
        deadline = time.monotonic() + timeout_s
        while text not in self.output():
            if not self.running():
                raise AssertionError(f"{self.name} exited ({self.returncode}) before {text!r}")
            if time.monotonic() > deadline:
                raise AssertionError(f"{self.name} did not print {text!r} within {timeout_s} s")
            time.sleep(0.1)


def start(argv: Sequence[str], name: str, env: dict[str, str] | None = None) -> Process:
    return Process(argv, name, env)


def bridge(channel: str, mavlink_port: int, *extra: str) -> Process:
    """``esc-bridge run`` on SocketCAN ``channel``, its autopilot on loopback UDP."""
    return start(
        [
            ESC_BRIDGE,
            "run",
            "--can-interface",
            "socketcan",
            "--can-channel",
            channel,
            "--mavlink",
            f"udpin:127.0.0.1:{mavlink_port}",
            *extra,
        ],
        "bridge",
    )


def sim(channel: str, *extra: str) -> Process:
    """``esc-bridge sim``: simulated ESCs on SocketCAN ``channel``."""
    argv = [ESC_BRIDGE, "sim", "--can-interface", "socketcan", "--can-channel", channel, *extra]
    return start(argv, "sim")


def candump_message(line: str) -> tuple[float, can.Message]:
    """A ``candump -L`` line as (the kernel's receive time, the frame).

    Raises:
        ValueError: not a ``candump -L`` line.
    """
    match = CANDUMP_LINE.match(line)
    if match is None:
        raise ValueError(f"not a candump -L line: {line!r}")
    ident, _, data = match["frame"].partition("#")
    message = can.Message(
        arbitration_id=int(ident, 16), is_extended_id=len(ident) == 8, data=bytes.fromhex(data)
    )
    return float(match["time"]), message


class Candump:
    """``candump -L`` on an interface: every frame with the kernel's receive time, the
    observer that is not the bridge. Its socket has a large receive buffer (a guest on a loaded
    host holds candump off for a while; with the default buffer it lost frames under a flood),
    and it reports what it lost all the same (:meth:`drops`). Returns once its socket receives
    (an interpreter's start and candump's own take seconds in a guest on a loaded host)."""

    def __init__(self, channel: str, *options: str, timeout_s: float = 60.0) -> None:
        device = channel.split(",")[0]  # "can0,ID:MASK": candump's filters after the device
        before = len(receivers(device))
        argv = ["candump", "-L", "-d", "-r", str(CANDUMP_BUFFER_BYTES), *options, channel]
        self.process = start(argv, f"candump-{device}")
        wait_until(lambda: len(receivers(device)) > before, timeout_s, "candump's socket")

    def drops(self) -> int:
        """The frames candump's socket dropped so far (its receive buffer overflowed)."""
        totals = re.findall(r"total drops (\d+)", self.process.output())
        return int(totals[-1]) if totals else 0

    def lines(self) -> list[str]:
        """The ``candump -L`` lines so far (whole lines only)."""
        text = self.process.output()
        return [line for line in text.splitlines(keepends=True) if line.endswith("\n")]

    def frames(self) -> list[tuple[float, str]]:
        """(receive time, ``ID#DATA``) of each frame so far."""
        found = (CANDUMP_LINE.match(line) for line in self.lines())
        return [(float(m["time"]), m["frame"]) for m in found if m]

    def stop(self) -> list[str]:
        self.process.stop()
        return self.lines()


class Autopilot(conftest.Autopilot):
    """conftest's pymavlink autopilot (HEARTBEAT and SERVO_OUTPUT_RAW on loopback UDP), noting
    when it produced each output (:attr:`sent`) and when its send returned (:attr:`delivered`),
    on ``time.time()``, the clock candump's stamps are on: where the guest stood still, the
    input was stale by the bridge's rules too. Both, since a guest may stall between the two:
    the bridge dates an output by its time_usec (the stamp), and has it once it is sent."""

    def __init__(self, port: int, **kwargs: Any) -> None:
        super().__init__(port, **kwargs)
        self.sent: list[float] = []
        """When each output was stamped (read with its time_usec)."""
        self.delivered: list[float] = []
        """When each output's send returned: in the bridge's socket from then on."""

    def servo_output_raw(self, pwm: list[int], time_us: int | None = None) -> None:
        produced_s = time.time()
        if time_us is None:
            time_us = int(time.monotonic() * 1e6)
        super().servo_output_raw(pwm, time_us)
        self.sent.append(produced_s)
        self.delivered.append(time.time())


class MavlinkWatch:
    """What the bridge sends to a pymavlink connection (an autopilot's), decoded with the
    project's dialect when asked: a select on its socket, no thread polling the guest's CPU."""

    def __init__(self, conn: Any) -> None:
        from bridge.mavlink import load_dialect

        self._conn = conn
        self._parser = load_dialect().MAVLink(None)
        self._parser.robust_parsing = True

    def wait_for(self, kind: str, predicate: Callable[[Any], bool], timeout_s: float) -> Any:
        """The first ``kind`` message from now on that matches ``predicate``.

        Raises:
            AssertionError: none within ``timeout_s`` (naming the kinds that came).
        """
        deadline = time.monotonic() + timeout_s
        seen: set[str] = set()
        while (left := deadline - time.monotonic()) > 0:
            if not select.select([self._conn.port.fileno()], [], [], left)[0]:
                continue
            for msg in self._parser.parse_buffer(self._conn.recv()) or []:
                seen.add(msg.get_type())
                if msg.get_type() == kind and predicate(msg):
                    return msg
        raise AssertionError(f"no matching {kind} within {timeout_s} s; saw {sorted(seen)}")


def cansend(channel: str, frame: str) -> None:
    run(["cansend", channel, frame])


def cangen(channel: str, *options: str) -> Process:
    """``cangen`` on ``channel`` with its options (e.g. ``-g 0 -I 7FF``: as fast as it can)."""
    return start(["cangen", channel, *options], f"cangen-{channel}")


@contextlib.contextmanager
def netem_hold(channel: str, delay_ms: int) -> Iterator[None]:
    """Delay every frame ``channel`` sends by ``delay_ms`` (a netem qdisc; with vcan's echo,
    what every socket receives is delayed too) until the block ends."""
    run(["tc", "qdisc", "add", "dev", channel, "root", "netem", "delay", f"{delay_ms}ms"])
    try:
        yield
    finally:
        run(["tc", "qdisc", "del", "dev", channel, "root"], check=False)


RECEIVE_LISTS = (
    "rcvlist_all",
    "rcvlist_fil",
    "rcvlist_inv",
    "rcvlist_sff",
    "rcvlist_eff",
    "rcvlist_err",
)
"""The CAN core's receive lists (net/can/proc.c): catch-alls, filters, inverted filters, single
standard and extended IDs (where the kernel files an exact-ID filter), error frames."""


def receivers(device: str) -> list[dict[str, str | int]]:
    """Every receiver the CAN core holds for ``device``: its list (``fil``, ``all``, ...), the
    ``can_id`` and ``can_mask`` as the kernel keeps them, ``owner`` (the socket, as the kernel
    prints its address) and ``matches`` (the frames it passed)."""
    rows: list[dict[str, str | int]] = []
    for table in RECEIVE_LISTS:
        for line in Path("/proc/net/can", table).read_text().splitlines():
            # "   can0  9f4e5200  9fffff00  000000006a1a8d3c  0000000062aa4180      1234  raw"
            fields = line.split()
            if len(fields) == 7 and fields[0] == device:
                rows.append(
                    {
                        "list": table.removeprefix("rcvlist_"),
                        "can_id": int(fields[1], 16),
                        "can_mask": int(fields[2], 16),
                        "owner": fields[4],
                        "matches": int(fields[5]),
                        "ident": fields[6],
                    }
                )
    return rows


def systemctl_show(unit: str, *properties: str) -> dict[str, str]:
    """``systemctl show``'s values of ``properties`` for ``unit``."""
    out = run(["systemctl", "show", unit, *(f"--property={p}" for p in properties)])
    return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)


def children(pid: int) -> list[int]:
    """The child processes of ``pid`` (the bridge's output loop, of its main process)."""
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds (user + system) of each of a process's threads, by thread name (the sum
    where names repeat)."""
    ticks = os.sysconf("SC_CLK_TCK")
    found: dict[str, float] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            stat = (task / "stat").read_text()
            name = stat[stat.index("(") + 1 : stat.rindex(")")]
            fields = stat[stat.rindex(")") + 2 :].split()
            found[name] = found.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / ticks
    return found


def wait_until(predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Poll ``predicate`` until it holds.

    Raises:
        AssertionError: naming ``what``, after ``timeout_s``.
    """
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s} s")
        time.sleep(0.05)
