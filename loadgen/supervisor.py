"""The supervisor of one load (:mod:`loadgen.load`), run in the load's own process as
``python loadgen/supervisor.py SPEC_JSON``: it runs the generator the spec names (or
starts its children), says "ready" on stdout once the load is on, stops on a signal or when its
stdin closes (the caller stopped it, or died), kills and reaps its children, and prints its
report. The caller's side (specs, presets, starting and stopping) is :mod:`loadgen.load`.
"""

from __future__ import annotations

import ctypes
import json
import mmap
import os
import random
import resource
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any, Final, TypeAlias

from bridge.errors import BridgeError

MIB: Final = 1 << 20
DISK_BLOCK_MB: Final = 1
DISK_FILE_MB: Final = 4
DISK_KEEP_FILES: Final = 4
FLOOD_BURST_S: Final = 0.001
FLOOD_POOL: Final = 2048
"""Distinct junk frames, encoded once and sent round robin (fresh randomness per frame would
cost more CPU than the sending)."""
_PR_SET_PDEATHSIG: Final = 1


class _Stop:
    """Set by SIGTERM/SIGINT/SIGHUP or by EOF on stdin (the caller closed it, or died).

    The signal handler only sets a flag and writes to a pipe of its own, which :meth:`wait`
    selects on beside stdin: safe whatever the main thread was doing when the signal came.
    """

    def __init__(self) -> None:
        self._read_fd, self._write_fd = os.pipe()
        os.set_blocking(self._write_fd, False)
        self.is_set = False
        for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            signal.signal(signum, self._on_signal)

    def _on_signal(self, _signum: int, _frame: FrameType | None) -> None:
        self.is_set = True
        with suppress(OSError):
            os.write(self._write_fd, b"x")

    def wait(self, timeout_s: float) -> bool:
        """Sleep up to ``timeout_s`` unless told to stop; True once told."""
        if self.is_set:
            return True
        ready = select.select([0, self._read_fd], [], [], max(0.0, timeout_s))[0]
        if 0 in ready and not os.read(0, 4096):
            self.is_set = True  # EOF
        return self.is_set or self._read_fd in ready


_Emit: TypeAlias = Callable[[dict[str, Any]], None]


def _emit(message: dict[str, Any]) -> None:
    with suppress(OSError):  # a caller that died reads nothing; the load stops all the same
        sys.stdout.write(json.dumps(message) + "\n")
        sys.stdout.flush()


_libc: ctypes.CDLL | None = None


def _child_setup() -> Callable[[], None]:
    """A ``preexec_fn``: the child gets SIGKILL when the supervisor dies (the supervisor is
    single-threaded, so running Python between fork and exec is safe here)."""
    global _libc
    if _libc is None:
        _libc = ctypes.CDLL(None, use_errno=True)
    libc = _libc
    parent = os.getpid()

    def setup() -> None:
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        if os.getppid() != parent:  # the supervisor died before prctl took effect
            os._exit(1)

    return setup


def _start_child(args: Sequence[str], cwd: str | None = None) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        list(args),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        cwd=cwd,
        preexec_fn=_child_setup(),  # safe: the supervisor is single-threaded
    )


def _reap(children: Sequence[subprocess.Popen[bytes]]) -> None:
    for child in children:
        with suppress(ProcessLookupError):
            child.kill()
    for child in children:
        child.wait()


@dataclass
class _Outcome:
    """What a generator tells its supervisor's report."""

    asked_per_s: float | None = None
    done: float = 0.0  # in the unit of asked_per_s (MiB, frames)
    unit: str = ""
    details: dict[str, float] = field(default_factory=dict)


def _run_busy(params: Mapping[str, Any], stop: _Stop, ready: Callable[[], None]) -> _Outcome:
    spinner = [sys.executable, "-I", "-S", "-c", "while True: pass"]
    children = [_start_child(spinner) for _ in range(int(params["n"]))]
    try:
        ready()
        restarts = 0
        while not stop.wait(0.5):
            for i, child in enumerate(children):
                if child.poll() is not None:  # someone killed a spinner: the load stays n
                    children[i] = _start_child(spinner)
                    restarts += 1
        return _Outcome(details={"spinners": len(children), "restarts": restarts})
    finally:
        _reap(children)


def _paced(
    stop: _Stop, rate_per_s: float, unit_size: float, work: Callable[[], None], out: _Outcome
) -> None:
    """Call ``work`` (``unit_size`` of the rate's unit each time) at ``rate_per_s`` until told
    to stop; after falling more than a second behind it carries on from now, no burst.

    Each unit is done when the rate has earned it (the first one after ``unit_size / rate``),
    so the amount done at any time is the rate times the time, rounded down to a unit."""
    start = time.monotonic()
    done = 0.0
    while True:
        behind_s = time.monotonic() - (start + (done + unit_size) / rate_per_s)
        if behind_s > 1.0:
            start += behind_s
            out.details["fell_behind"] = out.details.get("fell_behind", 0) + 1
        elif behind_s < 0:
            if stop.wait(-behind_s):
                return
            continue
        if stop.is_set:
            return
        work()
        done += unit_size
        out.done = done


def _run_memory_churn(
    params: Mapping[str, Any], stop: _Stop, ready: Callable[[], None]
) -> _Outcome:
    size = int(params["chunk_mb"]) * MIB
    pattern = bytes([0x5A]) * size
    out = _Outcome(float(params["mb_per_s"]), unit="MiB/s")

    def churn() -> None:
        # A fresh private anonymous mapping every time: each page faults in and is zeroed by
        # the kernel, then written in full; unmapping gives it all back.
        buffer = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE)
        buffer.write(pattern)
        buffer.close()
        out.details["chunks"] = out.details.get("chunks", 0) + 1

    ready()
    _paced(stop, float(params["mb_per_s"]), size / MIB, churn, out)
    return out


def _run_disk_writer(params: Mapping[str, Any], stop: _Stop, ready: Callable[[], None]) -> _Outcome:
    directory = Path(params["dir"])
    block = os.urandom(DISK_BLOCK_MB * MIB)  # random: nothing for a filesystem to compress
    out = _Outcome(float(params["mb_per_s"]), unit="MiB/s", details={"files": 0})
    blocks_per_file = DISK_FILE_MB // DISK_BLOCK_MB
    files: list[Path] = []
    state = {"fd": -1, "blocks": 0}
    fsync_max_s = 0.0

    def write_block() -> None:
        nonlocal fsync_max_s
        if state["fd"] < 0:
            path = directory / f"load-{int(out.details['files']):06d}.bin"
            state["fd"] = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            state["blocks"] = 0
            files.append(path)
            out.details["files"] += 1
            while len(files) > DISK_KEEP_FILES:
                files.pop(0).unlink(missing_ok=True)
        os.write(state["fd"], block)
        started = time.monotonic()
        os.fsync(state["fd"])
        fsync_max_s = max(fsync_max_s, time.monotonic() - started)
        state["blocks"] += 1
        if state["blocks"] >= blocks_per_file:
            os.close(state["fd"])
            state["fd"] = -1

    try:
        ready()
        _paced(stop, float(params["mb_per_s"]), DISK_BLOCK_MB, write_block, out)
    finally:
        if state["fd"] >= 0:
            os.close(state["fd"])
        shutil.rmtree(directory, ignore_errors=True)
    out.details["fsync_max_s"] = fsync_max_s
    return out


def _c_source(seed: int, functions: int) -> str:
    """A C file of ``functions`` functions whose loops and switches keep ``cc -O2`` busy
    (unrolling, vectorising, jump tables); different for every seed, so nothing is reused."""
    rng = random.Random(seed)
    parts = ["#include <stdint.h>\n"]
    for f in range(functions):
        parts.append(
            f"uint32_t f{seed}_{f}(uint32_t x, uint32_t y) {{\n"
            f"  uint32_t a = x ^ {rng.getrandbits(32)}u, b = y + {rng.getrandbits(16)}u;\n"
            "  for (int i = 0; i < (int)(y & 63); i++) {\n"
        )
        for _ in range(8):
            parts.append(
                f"    a = (a {rng.choice('+^*-')} (b >> {rng.randrange(1, 31)})) "
                f"{rng.choice('+^')} {rng.getrandbits(20)}u;\n"
                f"    b = b * {rng.getrandbits(8) | 1}u + (a << {rng.randrange(1, 7)});\n"
            )
        parts.append("    switch ((a + i) & 7) {\n")
        parts.extend(f"      case {c}: a += b * {rng.getrandbits(10)}u; break;\n" for c in range(8))
        parts.append("    }\n  }\n  return a ^ b;\n}\n")
    return "".join(parts)


def _run_compiler_build(
    params: Mapping[str, Any], stop: _Stop, ready: Callable[[], None]
) -> _Outcome:
    directory = Path(params["dir"])
    jobs = int(params["jobs"])
    sources = []
    for i in range(2 * jobs):
        source = directory / f"unit{i}.c"
        source.write_text(_c_source(i, int(params["functions"])))
        sources.append(source)
    out = _Outcome(details={"builds": 0, "failures": 0})
    running: list[subprocess.Popen[bytes]] = []
    turn = 0
    try:
        ready()
        while True:
            for child in [c for c in running if c.poll() is not None]:
                running.remove(child)
                key = "builds" if child.returncode == 0 else "failures"
                out.details[key] += 1
            if out.details["failures"] >= 3 and out.details["builds"] == 0:
                raise BridgeError(f"{params['cc']} failed on every one of 3 generated files")
            while len(running) < jobs:
                source = sources[turn % len(sources)]
                turn += 1
                args = [params["cc"], "-O2", "-c", source.name, "-o", f"{source.stem}.o"]
                running.append(_start_child(args, cwd=str(directory)))
            if stop.wait(0.02):
                return out
    finally:
        _reap(running)
        shutil.rmtree(directory, ignore_errors=True)


def _run_stall(params: Mapping[str, Any], stop: _Stop, ready: Callable[[], None]) -> _Outcome:
    pid = int(params["pid"])
    period_s, stopped_s = float(params["period_s"]), float(params["stopped_s"])
    os.kill(pid, 0)  # raises ProcessLookupError now, before "ready", if there is no such process
    out = _Outcome(details={"stalls": 0, "stopped_max_s": 0.0, "stopped_total_s": 0.0})
    ready()
    next_stop = time.monotonic()
    try:
        while not stop.wait(next_stop - time.monotonic()):
            os.kill(pid, signal.SIGSTOP)
            stopped_at = time.monotonic()
            try:
                stop.wait(stopped_s)
            finally:
                os.kill(pid, signal.SIGCONT)
            stopped = time.monotonic() - stopped_at
            out.details["stalls"] += 1
            out.details["stopped_total_s"] += stopped
            out.details["stopped_max_s"] = max(out.details["stopped_max_s"], stopped)
            next_stop = max(next_stop + period_s, time.monotonic())
    except ProcessLookupError:
        out.details["target_gone"] = 1
    finally:
        with suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)
    return out


def _junk_frames(count: int, extended_share: float, seed: int) -> list[Any]:
    """``count`` random ``can.Message`` frames that no ESC family takes for its own: standard
    IDs (which the decoders refuse as not 29-bit, with no ESC to blame) and extended IDs that
    no family's decoder claims or calls malformed (so no ESC gets a fault from them)."""
    import can

    from bridge.errors import CodecError
    from bridge.escs import registry

    rng = random.Random(seed)
    decoders = [family.decoder() for family in registry.families()]
    frames: list[Any] = []
    while len(frames) < count:
        extended = rng.random() < extended_share
        msg = can.Message(
            arbitration_id=rng.getrandbits(29 if extended else 11),
            is_extended_id=extended,
            data=rng.randbytes(rng.randrange(9)),
        )
        if extended:
            try:
                if any(decoder.decode(msg) is not None for decoder in decoders):
                    continue
            except CodecError:
                continue
        frames.append(msg)
    return frames


def _run_can_flood(params: Mapping[str, Any], stop: _Stop, ready: Callable[[], None]) -> _Outcome:
    from can.interfaces.udp_multicast.utils import pack_message

    frames = _junk_frames(FLOOD_POOL, float(params["extended_share"]), int(params["seed"]))
    packets = [pack_message(msg) for msg in frames]
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    # TTL 0: the frames never leave this machine (as python-can's hop_limit=0).
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("@I", 0))
    sock.connect((str(params["group"]), int(params["port"])))
    fps = float(params["frames_per_s"])
    out = _Outcome(fps, unit="frames/s", details={"skipped": 0, "send_errors": 0})
    max_burst = 2 * max(1, round(fps * FLOOD_BURST_S))
    send = sock.send
    try:
        ready()
        start = next_burst = time.monotonic()
        sent = skipped = errors = 0
        cursor = 0
        n_packets = len(packets)
        while not stop.is_set:
            due = int((time.monotonic() - start) * fps) - (sent + skipped + errors)
            if due > max_burst:  # fell behind: a real bus would not have carried the backlog
                skipped += due - max_burst
                due = max_burst
            for _ in range(due):
                try:
                    send(packets[cursor])
                except OSError:  # ENOBUFS and friends: a frame lost, as on a real bus
                    errors += 1
                else:
                    sent += 1
                cursor = (cursor + 1) % n_packets
            out.done = sent
            next_burst += FLOOD_BURST_S
            delay = next_burst - time.monotonic()
            if delay < -FLOOD_BURST_S:
                next_burst = time.monotonic()  # woke late: no run of back-to-back bursts
            if stop.wait(delay):
                break
        out.details.update(skipped=skipped, send_errors=errors, sent=sent)
    finally:
        sock.close()
    return out


_GENERATORS: Final[
    dict[str, Callable[[Mapping[str, Any], _Stop, Callable[[], None]], _Outcome]]
] = {
    "busy": _run_busy,
    "memory_churn": _run_memory_churn,
    "disk_writer": _run_disk_writer,
    "compiler_build": _run_compiler_build,
    "stall": _run_stall,
    "can_flood": _run_can_flood,
}


def _supervise(spec_json: str) -> int:
    """The supervisor's main: run one generator until told to stop, then report on stdout."""
    spec = json.loads(spec_json)
    # Loads are ordinary processes, whatever priority the caller runs at.
    with suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    if spec["nice"]:
        os.setpriority(os.PRIO_PROCESS, 0, int(spec["nice"]))
    stop = _Stop()
    started = time.monotonic()
    outcome: _Outcome | None = None
    error: str | None = None
    was_ready = False

    def ready() -> None:
        nonlocal was_ready, started
        was_ready = True
        started = time.monotonic()
        _emit({"event": "ready", "pid": os.getpid()})

    try:
        outcome = _GENERATORS[spec["kind"]](spec["params"], stop, ready)
    except Exception as exc:  # noqa: BLE001 - reported to the caller, who raises or logs it
        error = f"{type(exc).__name__}: {exc}"
    active_s = time.monotonic() - started
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime
    if not was_ready:
        _emit({"event": "error", "error": error or "the generator ended before starting"})
        return 1
    report: dict[str, Any] = {"event": "report", "active_s": active_s, "cpu_s": cpu_s}
    if outcome is not None:
        report["details"] = outcome.details
        report["unit"] = outcome.unit
        if outcome.asked_per_s is not None:
            report["asked_per_s"] = outcome.asked_per_s
            report["achieved_per_s"] = outcome.done / active_s if active_s > 0 else 0.0
    if error is not None:
        report["error"] = error
    _emit(report)
    return 0


if __name__ == "__main__":
    raise SystemExit(_supervise(sys.argv[1]))
