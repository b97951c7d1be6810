"""Load generators: a busy companion computer on demand, for the safety-under-load bench and tests.

On a vehicle esc-bridge shares its computer with vision, logging and mapping. These generators
make such load here, as real processes the kernel schedules like any other, so that
``bench/safety_load.py`` and the tests can show what the bridge does beside them.

Generators (each returns a :class:`Load`, started by ``with`` or by a :class:`LoadSet`):

- :func:`busy` ``(n, nice=0)``: ``n`` pure CPU spinners, a Python ``while True: pass`` each.
- :func:`memory_churn` ``(mb_per_s)``: maps, writes every byte of and unmaps 16 MiB private
  anonymous buffers at that rate (MiB/s): page faults, page zeroing, memory bandwidth.
- :func:`disk_writer` ``(mb_per_s)``: writes 1 MiB blocks of random bytes into 4 MiB files in a
  temporary directory at that rate, fsync after every block, keeping the newest four files; the
  directory is removed at the end.
- :func:`compiler_build` ``(jobs=2, nice=0)``: a real C build: generated C files, each about a
  second of ``cc -O2 -c`` here, compiled again and again, ``jobs`` compilers at a time.
- :func:`stall` ``(pid, period_s, stopped_s)``: SIGSTOP a process every ``period_s`` and SIGCONT
  it ``stopped_s`` later (what a process starved of the CPU looks like from outside). The target
  is always left running when the load stops.
- :func:`can_flood` ``(port, frames_per_s)``: junk frames on a udp_multicast CAN bus: random
  standard and extended IDs (none that an ESC family's decoder claims for itself), random lengths
  and data, sent in 1 ms bursts from a socket of their own (not the bus's port); the report
  says the rate it really reached.

Presets (:data:`PRESETS`, :func:`preset`), the loads the bench runs and the tests can use:

=====================  ============================================================
name                   loads
=====================  ============================================================
``idle``               none
``busy2``              ``busy(2)``: as many spinners as this machine has cores
``busy8``              ``busy(8)``
``busy+mem+disk``      ``busy(2)``, ``memory_churn(256)``, ``disk_writer(16)``
``busy+build``         ``busy(2)``, ``compiler_build(jobs=2)``
``busy+build-nice10``  ``busy(2, nice=10)``, ``compiler_build(jobs=2)`` at nice 0
``can-flood-60k``      ``can_flood(port, 60_000)`` on the bridge's own bus
=====================  ============================================================

How a load runs and stops
-------------------------
A started load is one supervisor process (``python loadgen/supervisor.py``, the module
:mod:`loadgen.supervisor`), in a session and process group of its own, at the
load's nice level and SCHED_OTHER whatever its caller runs at. It runs the generator itself or
starts its children (spinners, compilers). It says "ready" on its stdout once the load is on,
and its report when it ends.

Nothing outlives its load:

- stop (``with`` exit, also after an exception) closes the supervisor's stdin; the supervisor
  stops, kills and reaps its children, removes its files, resumes a stalled target and
  reports; then the caller kills whatever is left in the process group and waits until the
  group is empty;
- if the caller dies instead, the kernel closes that pipe and the supervisor does the same on
  its own: a watchdog on a pipe, which follows the caller's whole process, where
  PR_SET_PDEATHSIG would fire when the *thread* that started it ends;
- the supervisor's children get PR_SET_PDEATHSIG (SIGKILL): they die with it, even when it is
  killed with SIGKILL. Only a compiler's own children (cc1, as) can outlive a supervisor killed
  so, until their compile ends (about a second).

Everything here is measured against real time on a shared machine: a generator that falls
behind its rate does not burst to catch up, it reports the rate it reached.

This module is the caller's side, one job, a little over 600 lines: the loads' specs, the
presets, and the :class:`Load` handle (a third of the module: the start, stop and clean-up
protocol described above). What runs in the load's own process is
:mod:`loadgen.supervisor`.
"""

from __future__ import annotations

import json
import logging
import math
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Final, Literal, TypeAlias

from bridge.errors import BridgeError, ConfigError

__all__ = [
    "DEFAULT_GROUP",
    "KINDS",
    "PRESETS",
    "Kind",
    "Load",
    "LoadReport",
    "LoadSet",
    "LoadSpec",
    "busy",
    "can_flood",
    "compiler_build",
    "disk_writer",
    "group_pids",
    "memory_churn",
    "preset",
    "stall",
    "stat_fields",
]

log = logging.getLogger(__name__)

Kind: TypeAlias = Literal[
    "busy", "memory_churn", "disk_writer", "compiler_build", "stall", "can_flood"
]
KINDS: Final[tuple[Kind, ...]] = (
    "busy",
    "memory_churn",
    "disk_writer",
    "compiler_build",
    "stall",
    "can_flood",
)

DEFAULT_GROUP: Final = "239.74.163.2"
"""The udp_multicast group the tests, the benches and the demo put their buses on."""

MEMORY_CHUNK_MB: Final = 16
"""MiB mapped, written and unmapped at a time: above glibc's largest mmap threshold (32 MiB is
its ceiling for malloc, irrelevant here since the buffers are mmap'd directly), small enough to
pace 16..1000 MiB/s in steps of a few tens of ms."""
BUILD_FUNCTIONS: Final = 70
"""Generated functions per C file: about one second of ``cc -O2`` on the 2-core test machine."""

START_TIMEOUT_S: Final = 30.0
"""How long a supervisor may take to say it is ready (Python start-up on a loaded machine)."""
STOP_TIMEOUT_S: Final = 5.0
"""How long a supervisor may take to stop and report before its group is killed."""
GROUP_GONE_TIMEOUT_S: Final = 2.0

_NICE = range(-20, 20)
_CLOCK_TICKS: Final = os.sysconf("SC_CLK_TCK")
_SUPERVISOR: Final = str(Path(__file__).with_name("supervisor.py"))
"""Run by its path: this package is not installed (the bench and the tests find it beside them)."""


# -- what a load is -----------------------------------------------------------------------------


@dataclass(frozen=True)
class LoadSpec:
    """One load generator: its kind, parameters (JSON values), name and nice level."""

    kind: Kind
    name: str
    nice: int = 0
    params: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ConfigError(f"load kind {self.kind!r} is unknown; expected one of {KINDS}")
        if self.nice not in _NICE:
            raise ConfigError(f"load {self.name!r}: nice={self.nice!r}, expected -20..19")


@dataclass(frozen=True)
class LoadReport:
    """What a load did, from its supervisor's report at the end.

    ``asked_per_s``/``achieved_per_s`` are in ``unit`` (MiB/s, frames/s) for the paced
    generators and ``None`` for the others; ``details`` holds the generator's own counters
    (``builds``, ``files``, ``stalls``, ``stopped_max_s``, ``skipped`` ...); ``error`` is why a
    generator ended early, if it did.
    """

    name: str
    kind: Kind
    nice: int
    active_s: float
    cpu_s: float
    """User + system time of the supervisor and every child it reaped."""
    asked_per_s: float | None = None
    achieved_per_s: float | None = None
    unit: str = ""
    details: Mapping[str, float] = field(default_factory=dict)
    error: str | None = None


def _check_positive(name: str, what: str, value: float) -> None:
    if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name}: {what}={value!r}, expected a number > 0")


def busy(n: int, nice: int = 0) -> Load:
    """``n`` CPU spinners (one process each) at ``nice``.

    Raises:
        ConfigError: ``n`` outside 1..256 or nice outside -20..19.
    """
    if not (isinstance(n, int) and 1 <= n <= 256):
        raise ConfigError(f"busy: n={n!r}, expected 1..256 spinners")
    name = f"busy{n}" + (f"@nice{nice}" if nice else "")
    return Load(LoadSpec("busy", name, nice, {"n": n}))


def memory_churn(mb_per_s: float, nice: int = 0, chunk_mb: int = MEMORY_CHUNK_MB) -> Load:
    """Map, write and unmap ``chunk_mb`` MiB buffers, ``mb_per_s`` MiB per second in all.

    Raises:
        ConfigError: a rate or chunk that is not > 0, or nice outside -20..19.
    """
    _check_positive("memory_churn", "mb_per_s", mb_per_s)
    _check_positive("memory_churn", "chunk_mb", chunk_mb)
    params = {"mb_per_s": float(mb_per_s), "chunk_mb": int(chunk_mb)}
    return Load(LoadSpec("memory_churn", f"memory {mb_per_s:g} MiB/s", nice, params))


def disk_writer(mb_per_s: float, nice: int = 0, directory: str | Path | None = None) -> Load:
    """Write and fsync ``mb_per_s`` MiB per second into files in a new temporary directory
    (under ``directory``, default the system's), removed when the load stops.

    Raises:
        ConfigError: a rate that is not > 0, or nice outside -20..19.
    """
    _check_positive("disk_writer", "mb_per_s", mb_per_s)
    params = {"mb_per_s": float(mb_per_s), "under": None if directory is None else str(directory)}
    return Load(LoadSpec("disk_writer", f"disk {mb_per_s:g} MiB/s", nice, params))


def compiler_build(jobs: int = 2, nice: int = 0, functions: int = BUILD_FUNCTIONS) -> Load:
    """Compile generated C files with ``cc -O2`` (``$CC`` if set), ``jobs`` at a time, over and
    over; ``functions`` per file sets how long each compile takes.

    Raises:
        ConfigError: jobs outside 1..64, functions outside 1..10000, or nice outside -20..19.
    """
    if not (isinstance(jobs, int) and 1 <= jobs <= 64):
        raise ConfigError(f"compiler_build: jobs={jobs!r}, expected 1..64")
    if not (isinstance(functions, int) and 1 <= functions <= 10_000):
        raise ConfigError(f"compiler_build: functions={functions!r}, expected 1..10000")
    name = f"build -j{jobs}" + (f"@nice{nice}" if nice else "")
    return Load(LoadSpec("compiler_build", name, nice, {"jobs": jobs, "functions": functions}))


def stall(pid: int, period_s: float, stopped_s: float) -> Load:
    """Stop process ``pid`` (SIGSTOP) every ``period_s`` for ``stopped_s`` (then SIGCONT).

    Raises:
        ConfigError: a period or stop time that is not > 0, or ``stopped_s >= period_s``.
    """
    _check_positive("stall", "period_s", period_s)
    _check_positive("stall", "stopped_s", stopped_s)
    if stopped_s >= period_s:
        raise ConfigError(
            f"stall: stopped_s={stopped_s!r} must be shorter than period_s={period_s!r}, "
            "or the process never runs"
        )
    params = {"pid": int(pid), "period_s": float(period_s), "stopped_s": float(stopped_s)}
    return Load(LoadSpec("stall", f"stall pid {pid} {stopped_s:g}/{period_s:g} s", 0, params))


def can_flood(
    port: int,
    frames_per_s: float,
    group: str = DEFAULT_GROUP,
    extended_share: float = 0.5,
    seed: int = 1,
    nice: int = 0,
) -> Load:
    """Junk CAN frames on the udp_multicast bus ``group``:``port``, ``frames_per_s`` in all, a
    share ``extended_share`` of them with 29-bit IDs.

    Raises:
        ConfigError: a port outside 1..65535, a rate that is not > 0, a share outside 0..1, or
            nice outside -20..19.
    """
    if not (isinstance(port, int) and 1 <= port <= 65535):
        raise ConfigError(f"can_flood: port={port!r}, expected 1..65535")
    _check_positive("can_flood", "frames_per_s", frames_per_s)
    if not 0.0 <= extended_share <= 1.0:
        raise ConfigError(f"can_flood: extended_share={extended_share!r}, expected 0..1")
    params = {
        "port": port,
        "group": group,
        "frames_per_s": float(frames_per_s),
        "extended_share": float(extended_share),
        "seed": int(seed),
    }
    return Load(LoadSpec("can_flood", f"CAN flood {frames_per_s:g}/s", nice, params))


# -- presets ------------------------------------------------------------------------------------

PRESETS: Final[Mapping[str, str]] = {
    "idle": "no load",
    "busy2": "2 CPU spinners",
    "busy8": "8 CPU spinners",
    "busy+mem+disk": "2 CPU spinners, memory churn 256 MiB/s, disk writer 16 MiB/s (fsync)",
    "busy+build": "2 CPU spinners, a 2-job C build",
    "busy+build-nice10": "2 CPU spinners at nice 10, a 2-job C build at nice 0",
    "can-flood-60k": "60000 junk CAN frames/s on the bridge's own bus",
}
"""Preset name -> what it runs (see the module docstring)."""


def preset(name: str, can_port: int | None = None, group: str = DEFAULT_GROUP) -> LoadSet:
    """The :class:`LoadSet` (not started) of preset ``name``; ``can_port``/``group`` name the
    bus of the presets that flood it.

    Raises:
        ConfigError: an unknown name, or a flood preset without ``can_port``.
    """
    loads: list[Load]
    if name == "idle":
        loads = []
    elif name == "busy2":
        loads = [busy(2)]
    elif name == "busy8":
        loads = [busy(8)]
    elif name == "busy+mem+disk":
        loads = [busy(2), memory_churn(256), disk_writer(16)]
    elif name == "busy+build":
        loads = [busy(2), compiler_build(jobs=2)]
    elif name == "busy+build-nice10":
        loads = [busy(2, nice=10), compiler_build(jobs=2)]
    elif name == "can-flood-60k":
        if can_port is None:
            raise ConfigError(f"load preset {name!r} floods a bus: give its can_port")
        loads = [can_flood(can_port, 60_000, group)]
    else:
        raise ConfigError(f"load preset {name!r} is unknown; expected one of {', '.join(PRESETS)}")
    return LoadSet(loads, name)


# -- processes ----------------------------------------------------------------------------------


def stat_fields(pid: int) -> list[str] | None:
    """/proc/<pid>/stat after the command name (field 3, the state, first), or None if gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def group_pids(pgid: int) -> list[int]:
    """The live (not zombie) processes in process group ``pgid``."""
    found = []
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            fields = stat_fields(int(entry.name))
            if fields is not None and int(fields[2]) == pgid and fields[0] != "Z":
                found.append(int(entry.name))
    return found


def _cpu_seconds(pids: Sequence[int]) -> float:
    """User + system time of ``pids`` and of the children each has reaped."""
    total = 0
    for pid in pids:
        fields = stat_fields(pid)
        if fields is not None:
            total += sum(int(x) for x in fields[11:15])  # utime stime cutime cstime
    return total / _CLOCK_TICKS


def _package_root() -> str:
    """The directory holding the ``bridge`` package, for the supervisor's import path."""
    return str(Path(__file__).resolve().parent.parent.parent)


class Load:
    """One load generator: a description until :meth:`start`, then a supervisor process
    group until :meth:`stop`. A context manager; stop tolerates a second call."""

    def __init__(self, spec: LoadSpec) -> None:
        self.spec = spec
        self.report: LoadReport | None = None
        """The supervisor's report, once stopped."""
        self.workdir: Path | None = None
        """The load's temporary directory (disk writer, compiler build) while it runs."""
        self._proc: subprocess.Popen[bytes] | None = None
        self._stderr: IO[bytes] | None = None
        self._buffer = b""

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def nice(self) -> int:
        return self.spec.nice

    @property
    def pgid(self) -> int | None:
        """The supervisor's pid, which is its process group's ID; None before start."""
        return None if self._proc is None else self._proc.pid

    @property
    def running(self) -> bool:
        return self._proc is not None and self.report is None

    def pids(self) -> list[int]:
        """The live processes of this load (supervisor and children)."""
        return [] if self._proc is None else group_pids(self._proc.pid)

    def cpu_seconds(self) -> float:
        """CPU time the load has used so far (live processes and the children they reaped)."""
        return _cpu_seconds(self.pids())

    def start(self, timeout_s: float = START_TIMEOUT_S) -> Load:
        """Start the supervisor and wait until it says the load is on.

        Raises:
            BridgeError: already started, no C compiler for a build, or the supervisor failed
                or did not say it was ready within ``timeout_s`` (its message is included).
        """
        if self._proc is not None:
            raise BridgeError(f"load {self.name!r} was already started")
        params = dict(self.spec.params)
        if self.spec.kind == "compiler_build":
            compiler = os.environ.get("CC", "cc")
            path = shutil.which(compiler)
            if path is None:
                raise BridgeError(
                    f"load {self.name!r} needs a C compiler: {compiler!r} is not on PATH "
                    "(install gcc or clang, or set CC)"
                )
            params["cc"] = path
        if self.spec.kind in ("disk_writer", "compiler_build"):
            self.workdir = Path(
                tempfile.mkdtemp(prefix="esc-bridge-load-", dir=params.pop("under", None))
            )
            params["dir"] = str(self.workdir)
        spec = {"kind": self.spec.kind, "name": self.name, "nice": self.nice, "params": params}
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [_package_root(), env.get("PYTHONPATH")]))
        # Kept open for the load's life (its stderr goes there), closed by stop().
        self._stderr = tempfile.TemporaryFile()  # noqa: SIM115
        self._proc = subprocess.Popen(
            [sys.executable, _SUPERVISOR, json.dumps(spec)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            env=env,
            start_new_session=True,  # a process group of its own, killed as one
        )
        line = self._read_line(time.monotonic() + timeout_s)
        message: dict[str, Any] = {}
        with suppress(ValueError):
            message = json.loads(line or b"{}")
        if message.get("event") != "ready":
            if line is None:
                why = f"did not say it was ready within {timeout_s:g} s"
            else:
                why = f"failed: {message.get('error') or line.decode(errors='replace')}"
            self._kill_group()
            self._cleanup_files()
            errors = self._stderr_tail()
            if self._stderr is not None:
                self._stderr.close()
            self.report = LoadReport(self.name, self.spec.kind, self.nice, 0.0, 0.0, error=why)
            raise BridgeError(
                f"load {self.name!r}: the supervisor {why}"
                + (f"; its stderr:\n{errors}" if errors else "")
            )
        log.debug("load %s started: pgid %d", self.name, self._proc.pid)
        return self

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> LoadReport:
        """Stop the load and everything it started; its report.

        Never raises for a load that misbehaves: a supervisor that does not report within
        ``timeout_s`` is killed with its group and the report says so (``error``).
        """
        if self.report is not None:
            return self.report
        proc = self._proc
        if proc is None:
            self.report = LoadReport(self.name, self.spec.kind, self.nice, 0.0, 0.0)
            return self.report
        cpu_before_kill = self.cpu_seconds()
        if proc.stdin is not None:
            with suppress(OSError):
                proc.stdin.close()  # EOF: the supervisor's signal to stop
        message: dict[str, Any] | None = None
        deadline = time.monotonic() + timeout_s
        while (line := self._read_line(deadline)) is not None:
            with suppress(ValueError):
                decoded = json.loads(line)
                if decoded.get("event") == "report":
                    message = decoded
        self._kill_group()
        if self.spec.kind == "stall":
            with suppress(ProcessLookupError, PermissionError):
                os.kill(int(self.spec.params["pid"]), signal.SIGCONT)  # never leave it stopped
        self._cleanup_files()
        if message is None:
            self.report = LoadReport(
                self.name,
                self.spec.kind,
                self.nice,
                0.0,
                cpu_before_kill,
                error=f"no report within {timeout_s:g} s; killed\n{self._stderr_tail()}".strip(),
            )
        else:
            self.report = LoadReport(
                self.name,
                self.spec.kind,
                self.nice,
                float(message["active_s"]),
                float(message["cpu_s"]),
                message.get("asked_per_s"),
                message.get("achieved_per_s"),
                str(message.get("unit", "")),
                {str(k): float(v) for k, v in message.get("details", {}).items()},
                message.get("error"),
            )
        if self._stderr is not None:
            self._stderr.close()
        if self.report.error:
            log.warning("load %s: %s", self.name, self.report.error)
        return self.report

    def _read_line(self, deadline: float) -> bytes | None:
        """The supervisor's next stdout line, or None at EOF or at ``deadline``."""
        assert self._proc is not None and self._proc.stdout is not None
        fd = self._proc.stdout.fileno()
        while b"\n" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                return None
            chunk = os.read(fd, 65536)
            if not chunk:
                return None
            self._buffer += chunk
        line, self._buffer = self._buffer.split(b"\n", 1)
        return line

    def _kill_group(self) -> None:
        """SIGKILL the whole process group, reap the supervisor, wait until the group is empty."""
        proc = self._proc
        assert proc is not None
        with suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()
        # Children the supervisor left are now orphans that init reaps; wait for them to go.
        deadline = time.monotonic() + GROUP_GONE_TIMEOUT_S
        while (left := group_pids(proc.pid)) and time.monotonic() < deadline:
            with suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)
            time.sleep(0.01)
        if left:
            log.warning("load %s: processes %s still alive after SIGKILL", self.name, left)

    def _cleanup_files(self) -> None:
        if self.workdir is not None:
            shutil.rmtree(self.workdir, ignore_errors=True)

    def _stderr_tail(self, lines: int = 10) -> str:
        if self._stderr is None or self._stderr.closed:
            return ""
        self._stderr.seek(0)
        text = self._stderr.read().decode(errors="replace")
        return "\n".join(text.strip().splitlines()[-lines:])

    def __enter__(self) -> Load:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()

    def __del__(self) -> None:
        proc = getattr(self, "_proc", None)
        if proc is not None and getattr(self, "report", None) is None:
            log.warning("load %s was never stopped; killing its processes", self.spec.name)
            with suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)

    def __repr__(self) -> str:
        state = "running" if self.running else "stopped" if self.report else "not started"
        return f"<Load {self.name!r} {self.spec.kind} nice {self.nice} {state}>"


class LoadSet:
    """Several loads started together and stopped together (in reverse order), a context
    manager; if one fails to start, those already started are stopped before the error."""

    def __init__(self, loads: Sequence[Load] = (), name: str = "") -> None:
        self.loads = tuple(loads)
        self.name = name or "+".join(load.name for load in self.loads) or "idle"

    def start(self) -> LoadSet:
        """Start every load.

        Raises:
            BridgeError: as :meth:`Load.start`.
        """
        started: list[Load] = []
        try:
            for load in self.loads:
                started.append(load.start())
        except BaseException:
            for load in reversed(started):
                load.stop()
            raise
        return self

    def stop(self) -> tuple[LoadReport, ...]:
        """Stop every load; their reports, in the order the loads were given."""
        for load in reversed(self.loads):
            load.stop()
        return tuple(load.stop() for load in self.loads)  # the second stop returns the report

    def pids(self) -> list[int]:
        return [pid for load in self.loads for pid in load.pids()]

    def cpu_seconds(self) -> float:
        return sum(load.cpu_seconds() for load in self.loads)

    def __iter__(self) -> Iterator[Load]:
        return iter(self.loads)

    def __len__(self) -> int:
        return len(self.loads)

    def __enter__(self) -> LoadSet:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()
