"""Safety under load: does the bridge send safe (all-zero) commands while the autopilot is fine?

Run: ``python bench/safety_load.py [--seconds 60] [--loads idle busy2 ...] [--protocol ckesc ft]
[--repeat 1] [--json FILE]``

For each load preset of ``bridge/sim/load.py`` (all of them unless ``--loads`` names some) and
each protocol, the bridge runs through its CLI only (``esc-bridge run``: the passthrough-4
mixer, a udp_multicast CAN bus on a port of its own, MAVLink on loopback UDP; CKESC
RawCommand_12b at 400 Hz, or FT current mode at 100 Hz per ESC), so the same bench measures
today's code and any later one. Beside it:

- an autopilot process, SCHED_FIFO when permitted (``--pilot-priority``): SERVO_OUTPUT_RAW at
  200 Hz with PWM 1500 on motors 1..4, HEARTBEAT armed at 1 Hz; it notes when it sent each;
- an observer process, SCHED_FIFO when permitted (``--observer-priority``; below the bridge's
  output loop, above every ordinary process) with an 8 MiB receive buffer, which times every
  command frame by the kernel (SO_TIMESTAMPNS: on loopback, the send time to within µs);
- the load, started once the bridge sends frames and given ``--settle`` seconds before the
  autopilot starts. Under a CAN flood the observer's socket drops the junk in the kernel (a
  socket filter on the sender's port) so that it does not compete with the bridge for CPU.

The measured window opens at the first non-zero command (armed, input flowing: from then on a
safe frame is a fault) and lasts ``--seconds``. In it:

- frames: command frames (CKESC: group-1 RawCommand_12b, the quad's one group; FT: the command
  frames of all four ESCs);
- zero: all-zero command frames (CKESC: all four throttles 0; FT: per-ESC frames at 0 A or
  braking); spells: runs of them; longest: the longest time from a zero frame to the next
  non-zero one, ms (how long the motors were told to stop);
- lost: frames the observer missed: its socket's kernel drop count; under a flood (whose
  filtered junk that count includes) the gaps in the CKESC transfer IDs instead, a lower
  bound; unknown for FT under a flood;
- pilot gap: the autopilot's longest time between two SERVO_OUTPUT_RAW sends, ms (5 ms is
  on time): proof that the autopilot itself was fine;
- period error: |interval between consecutive frames of one stream - its period|, µs, p50 and
  p99 (CKESC group 1 every 2.5 ms; each FT ESC every 10 ms);
- CPU, % of one core: the bridge (user + system time of the daemon and every process under it,
  as ``bench/loop.py`` counts it), the load's processes, and the whole machine's busy time.

One row per load and protocol; with ``--repeat N`` the counts are the median over the N runs
with their range, the percentiles pool every run's intervals. ``--json FILE`` writes every run.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import itertools
import json
import multiprocessing
import os
import select
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from contextlib import suppress
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from _common import (
    GROUP,
    MAX_DATAGRAM,
    bridge_command,
    cpu_seconds,
    free_port,
    holds_bus,
    ignore_sigint,
    log_tail,
    machine_busy_seconds,
    multicast_listener,
    num,
    process_tree,
    processes,
    raise_interrupt,
    recv_stamped,
    set_fifo,
    sleep_watching,
    udp_sockets,
    wait_for,
)
from _stats import percentile
from can.interfaces.udp_multicast.utils import unpack_message

from bridge.errors import BridgeError, CodecError
from bridge.escs import ckesc, ft, uavcan_v0
from bridge.mavlink import load_dialect
from bridge.sim.load import PRESETS, LoadReport, preset

OUTPUT_RATE_HZ = {"ckesc": 400, "ft": 100}  # per stream: CKESC group 1, each FT ESC
MOTORS = 4
PILOT_HZ = 200
HEARTBEAT_EVERY = PILOT_HZ  # 1 Hz
PWM_US = 1500
SO_ATTACH_FILTER = getattr(socket, "SO_ATTACH_FILTER", 26)
START_TIMEOUT_S = 30.0


# -- sockets, scheduling, /proc -------------------------------------------------------------


def _only_from_port(sock: socket.socket, port: int) -> ctypes.Array[ctypes.c_char]:
    """Attach a classic BPF filter: keep datagrams whose UDP source port is ``port`` (the
    bridge's bus socket is bound to the bus port; a flood sends from another). The filter
    runs with the UDP header at offset 0. Returns the program's buffer (keep it alive until
    attached; the kernel copies it)."""
    program = [
        (0x28, 0, 0, 0),  # ldh [0]: the source port
        (0x15, 0, 1, port),  # jeq #port, keep, drop
        (0x06, 0, 0, 0xFFFF),  # ret: keep (up to 64 KiB)
        (0x06, 0, 0, 0),  # ret: drop
    ]
    code = ctypes.create_string_buffer(b"".join(struct.pack("HBBI", *i) for i in program))
    sock.setsockopt(
        socket.SOL_SOCKET, SO_ATTACH_FILTER, struct.pack("HL", len(program), ctypes.addressof(code))
    )
    return code


def _socket_drops(sock: socket.socket) -> int | None:
    """The kernel's drop count of ``sock`` (from /proc/net/udp), None if not found."""
    found = udp_sockets(sock.getsockname()[1]).get(os.fstat(sock.fileno()).st_ino)
    return None if found is None else found.drops


# -- the observer process -------------------------------------------------------------------


@dataclass(frozen=True)
class Command:
    """One command frame the bridge sent, as the observer saw it."""

    stamp: float  # kernel time, wall clock, s
    stream: int  # CKESC throttle group; FT ESC ID
    transfer_id: int  # CKESC transfer ID; -1 for FT
    zero: bool  # every motor of the frame told to stop


def _ft_zero(message: object) -> bool:
    if isinstance(message, ft.SetCurrentBrake | ft.SetCurrentBrakePercent):
        return True
    for name in ("current_a", "duty", "fraction", "erpm"):
        if hasattr(message, name):
            return bool(getattr(message, name) == 0)
    return False


def _command(protocol: str, data: bytes, stamp: float) -> Command | None:
    """The command in one datagram of the bus, or None for anything else."""
    try:
        msg = unpack_message(data)
        if protocol == "ckesc":
            frame = ckesc.decode(msg)
            if frame is None or not isinstance(frame.message, ckesc.RawCommand12b):
                return None
            throttles = frame.message.throttles
            tid = -1 if frame.transfer_id is None else frame.transfer_id
            return Command(stamp, frame.message.group, tid, not any(throttles))
        ft_frame = ft.decode(msg)
    except (CodecError, ValueError, TypeError):
        return None
    if ft_frame is None or isinstance(ft_frame.message, ft.FtTelemetry):
        return None
    return Command(stamp, ft_frame.esc_id, -1, _ft_zero(ft_frame.message))


@dataclass
class ObserverReport:
    fifo_problem: str | None
    filtered: bool
    commands: list[Command]
    drops: int | None  # the kernel's count for the observer's socket over the run


def observer_worker(
    can_port: int,
    protocol: str,
    priority: int,
    filtered: bool,
    stop: Any,
    ready: Any,
    seen: Any,
    first_nonzero: Any,
    out: Any,
) -> None:
    """Record every command frame the bridge sends, kernel-timed, until ``stop`` is set.

    ``seen`` counts them live; ``first_nonzero`` gets the kernel time of the first non-zero one.
    """
    ignore_sigint()
    fifo_problem = set_fifo(priority)
    gc.disable()  # no collector pauses; nothing here makes reference cycles
    sock = multicast_listener(can_port)
    program = _only_from_port(sock, can_port) if filtered else None
    sock.setblocking(False)
    drops_before = _socket_drops(sock)
    commands: list[Command] = []
    ready.set()
    while not stop.is_set():
        if not select.select([sock], [], [], 0.05)[0]:
            continue
        with suppress(BlockingIOError):
            while True:
                data, sender_port, stamp = recv_stamped(sock)
                if sender_port != can_port:  # not the bridge's bus socket: a flood's junk
                    continue
                command = _command(protocol, data, stamp)
                if command is None:
                    continue
                commands.append(command)
                seen.value += 1
                if not command.zero and first_nonzero.value == 0.0:
                    first_nonzero.value = stamp
    drops_after = _socket_drops(sock)
    drops = None
    if not filtered and drops_before is not None and drops_after is not None:
        drops = drops_after - drops_before
    sock.close()
    del program
    out.put(ObserverReport(fifo_problem, filtered, commands, drops))


# -- the autopilot process ------------------------------------------------------------------


@dataclass
class PilotReport:
    fifo_problem: str | None
    sends: list[float]  # wall time of every SERVO_OUTPUT_RAW
    late_ticks: int  # ticks skipped after waking more than a period late


def pilot_worker(mavlink_port: int, priority: int, stop: Any, ready: Any, out: Any) -> None:
    """Armed HEARTBEAT at 1 Hz and SERVO_OUTPUT_RAW at 200 Hz (PWM 1500 on motors 1..4)
    until ``stop`` is set; whatever the bridge sends back is read and dropped."""
    ignore_sigint()
    fifo_problem = set_fifo(priority)
    gc.disable()
    dialect = load_dialect()
    mav = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    dest = ("127.0.0.1", mavlink_port)
    armed = dialect.MAV_MODE_FLAG_SAFETY_ARMED | dialect.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    pwm = [PWM_US] * MOTORS + [0] * (16 - MOTORS)
    sends: list[float] = []
    late_ticks = 0
    period = 1.0 / PILOT_HZ
    ready.set()
    start = time.monotonic()
    for k in itertools.count():
        if stop.is_set():
            break
        if k % HEARTBEAT_EVERY == 0:
            heartbeat = mav.heartbeat_encode(2, 3, armed, 0, 4)  # quadrotor, ArduPilot, active
            sock.sendto(heartbeat.pack(mav), dest)
        time_usec = int((time.monotonic() - start) * 1e6) & 0xFFFFFFFF
        sock.sendto(mav.servo_output_raw_encode(time_usec, 0, *pwm).pack(mav), dest)
        sends.append(time.time())
        with suppress(BlockingIOError):
            while sock.recv(MAX_DATAGRAM):
                pass
        deadline = start + (k + 1) * period
        delay = deadline - time.monotonic()
        if delay < -period:  # woke a whole period late: carry on from now, no burst
            skipped = int(-delay / period)
            late_ticks += skipped
            start += skipped * period
            delay += skipped * period
        if delay > 0:
            time.sleep(delay)
    sock.close()
    out.put(PilotReport(fifo_problem, sends, late_ticks))


# -- one run --------------------------------------------------------------------------------


@dataclass
class Run:
    """The measurements of one run of one load."""

    load: str
    protocol: str
    index: int
    frames: int = 0
    zero: int = 0
    spells: int = 0
    longest_spell_ms: float = 0.0
    lost_kernel: int | None = None  # the observer socket's kernel drop count
    lost_transfer_ids: int | None = None  # CKESC transfer-ID gaps (a lower bound)
    pilot_sends: int = 0
    pilot_max_gap_ms: float = float("nan")
    pilot_late_ticks: int = 0
    rate_hz: float = float("nan")  # frames per second per stream
    period_err_us: list[float] = field(default_factory=list)
    bridge_cpu_pct: float = float("nan")
    load_cpu_pct: float = float("nan")
    machine_pct: float = float("nan")
    pilot_fifo: str | None = None  # None: SCHED_FIFO as asked; else why not
    observer_fifo: str | None = None
    loads: list[LoadReport] = field(default_factory=list)
    daemon_exit: int | None = None
    bridge_log: list[str] = field(default_factory=list)  # its lines about the output loop
    problems: list[str] = field(default_factory=list)

    @property
    def lost(self) -> int | None:
        return self.lost_kernel if self.lost_kernel is not None else self.lost_transfer_ids


def _bridge_args(
    args: argparse.Namespace, protocol: str, mavlink_port: int, can_port: int
) -> list[str]:
    """``esc-bridge run`` with flags only (a --bridge-config file is the one extra)."""
    command = [
        *bridge_command(mavlink_port, can_port, "info"),
        "--bitrate",
        "1000000",
        "--protocol",
        protocol,
        "--rate",
        str(OUTPUT_RATE_HZ[protocol]),
        "--mixer",
        "passthrough-4",
    ]
    if args.no_zenoh:
        command.append("--no-zenoh")
    else:  # as on a vehicle, but on loopback only and without looking for peers
        command += ["--no-zenoh-scouting", "--zenoh-listen", "tcp/127.0.0.1:0"]
    if args.bridge_config:
        command += ["--config", args.bridge_config]
    return command


def run_once(
    load_name: str, protocol: str, index: int, args: argparse.Namespace, ctx: Any
) -> tuple[Run, list[Command], list[float], float, float]:
    """One run; the raw commands and autopilot sends come back beside the Run for analysis."""
    run = Run(load_name, protocol, index)
    mavlink_port, can_port = free_port(), free_port()
    loads = preset(load_name, can_port=can_port, group=GROUP)
    filtered = any(load.spec.kind == "can_flood" for load in loads)
    # Whatever the run started stops however it ends; the loads stop on their own (``with``).
    with tempfile.TemporaryDirectory() as tmp, processes(daemon_timeout_s=15) as procs:
        stop_observer, observer_ready = ctx.Event(), ctx.Event()
        seen = ctx.Value("q", 0, lock=False)
        first_nonzero = ctx.Value("d", 0.0, lock=False)
        observer_q = ctx.Queue()
        observer = ctx.Process(
            target=observer_worker,
            args=(
                can_port,
                protocol,
                args.observer_priority,
                filtered,
                stop_observer,
                observer_ready,
                seen,
                first_nonzero,
                observer_q,
            ),
            name="observer",
        )
        observer.start()
        procs.add_worker(observer, stop_observer)
        if not observer_ready.wait(START_TIMEOUT_S):
            raise RuntimeError("the observer process did not start")
        log_path = Path(tmp) / "bridge.log"
        with log_path.open("wb") as log_file:
            daemon = subprocess.Popen(
                _bridge_args(args, protocol, mavlink_port, can_port),
                stdout=log_file,
                stderr=subprocess.STDOUT,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
        procs.daemon = daemon
        # Up: it sends (safe) frames, or at least holds a socket on the bus (a bridge may
        # stay silent until it has input).
        wait_for(
            lambda: seen.value > 0 or holds_bus(daemon.pid, can_port),
            START_TIMEOUT_S,
            "before the bridge opened its CAN bus",
            daemon,
            log_path,
        )
        with loads:
            sleep_watching(args.settle, daemon, log_path)
            stop_pilot, pilot_ready = ctx.Event(), ctx.Event()
            pilot_q = ctx.Queue()
            pilot = ctx.Process(
                target=pilot_worker,
                args=(mavlink_port, args.pilot_priority, stop_pilot, pilot_ready, pilot_q),
                name="autopilot",
            )
            pilot.start()
            procs.add_worker(pilot, stop_pilot)
            wait_for(
                lambda: first_nonzero.value > 0.0,
                START_TIMEOUT_S,
                "before the bridge sent a non-zero command (armed, PWM 1500)",
                daemon,
                log_path,
            )
            t0 = float(first_nonzero.value)
            t1 = t0 + args.seconds
            bridge_pids = process_tree(daemon.pid)
            start = (
                time.monotonic(),
                cpu_seconds(bridge_pids),
                loads.cpu_seconds(),
                machine_busy_seconds(),
            )
            sleep_watching(max(0.0, t1 - time.time()), daemon, log_path)
            elapsed = time.monotonic() - start[0]
            run.bridge_cpu_pct = 100 * (cpu_seconds(bridge_pids) - start[1]) / elapsed
            run.load_cpu_pct = 100 * (loads.cpu_seconds() - start[2]) / elapsed
            run.machine_pct = 100 * (machine_busy_seconds() - start[3]) / elapsed
            time.sleep(0.05)  # frames sent at t1 reach the observer
            stop_pilot.set()
            pilot_report: PilotReport = pilot_q.get(timeout=30)
            pilot.join(5)
        run.loads = list(loads.stop())
        stop_observer.set()
        observed: ObserverReport = observer_q.get(timeout=60)
        observer.join(5)
        daemon.send_signal(signal.SIGTERM)
        try:
            run.daemon_exit = daemon.wait(15)
        except subprocess.TimeoutExpired:
            run.problems.append("the bridge did not stop within 15 s of SIGTERM")
        run.bridge_log = [
            line
            for line in log_path.read_text(errors="replace").splitlines()
            if "output loop" in line
        ]
        if run.daemon_exit not in (0, None):
            run.problems.append(
                f"the bridge exited with code {run.daemon_exit}:\n{log_tail(log_path)}"
            )
    run.pilot_fifo = pilot_report.fifo_problem
    run.observer_fifo = observed.fifo_problem
    run.pilot_late_ticks = pilot_report.late_ticks
    run.lost_kernel = observed.drops
    for report in run.loads:
        if report.error:
            run.problems.append(f"load {report.name}: {report.error}")
    return run, observed.commands, pilot_report.sends, t0, t1


def analyse(run: Run, commands: list[Command], sends: list[float], t0: float, t1: float) -> None:
    """Fill ``run``'s counts from the commands and autopilot sends in the window [t0, t1]."""
    period = 1.0 / OUTPUT_RATE_HZ[run.protocol]
    window = [c for c in commands if t0 <= c.stamp <= t1]
    if run.protocol == "ckesc":
        window = [c for c in window if c.stream == 1]  # the quad's one throttle group
    run.frames = len(window)
    run.zero = sum(c.zero for c in window)
    streams: dict[int, list[Command]] = {}
    for command in window:
        streams.setdefault(command.stream, []).append(command)
    spells: list[tuple[float, float]] = []  # (from a zero frame, to the next non-zero one)
    intervals = 0
    span = 0.0
    tid_gaps = 0
    for frames in streams.values():
        spell_start: float | None = None
        for frame in frames:
            if frame.zero and spell_start is None:
                spell_start = frame.stamp
            elif not frame.zero and spell_start is not None:
                spells.append((spell_start, frame.stamp))
                spell_start = None
        if spell_start is not None:  # still safe when the window closed
            spells.append((spell_start, frames[-1].stamp + period))
        for a, b in itertools.pairwise(frames):
            run.period_err_us.append(abs(b.stamp - a.stamp - period) * 1e6)
            if a.transfer_id >= 0 and b.transfer_id >= 0:
                tid_gaps += (b.transfer_id - a.transfer_id - 1) % (uavcan_v0.MAX_TRANSFER_ID + 1)
        intervals += len(frames) - 1
        span += frames[-1].stamp - frames[0].stamp
    run.rate_hz = intervals / span if span > 0 else float("nan")
    if run.protocol == "ckesc":
        run.lost_transfer_ids = tid_gaps
    # Spells of different ESCs that overlap in time are one spell of the vehicle.
    merged: list[list[float]] = []
    for begin, end in sorted(spells):
        if merged and begin <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], end)
        else:
            merged.append([begin, end])
    run.spells = len(merged)
    run.longest_spell_ms = max((end - begin for begin, end in spells), default=0.0) * 1e3
    in_window = [s for s in sends if t0 - 1.0 / PILOT_HZ <= s <= t1]
    run.pilot_sends = len(in_window)
    gaps = [b - a for a, b in itertools.pairwise(in_window)]
    run.pilot_max_gap_ms = max(gaps) * 1e3 if gaps else float("nan")


# -- the report -----------------------------------------------------------------------------


def _median_range(values: list[int | None], width: int) -> str:
    """One run: its value; several: 'median (min-max)'."""
    known = [v for v in values if v is not None]
    if not known:
        return f"{'-':>{width}}"
    if len(values) == 1:
        return f"{known[0]:>{width}d}"
    median = statistics.median(known)
    text = f"{median:g} ({min(known)}-{max(known)})"
    return f"{text:>{width}}"


@dataclass
class Row:
    """One load and protocol over all its runs: what the table and the JSON show."""

    load: str
    protocol: str
    runs: int
    frames: float
    zero: list[int]
    spells: list[int]
    longest_spell_ms: float
    lost: list[int | None]
    pilot_max_gap_ms: float
    rate_hz: float
    period_err_p50_us: float
    period_err_p99_us: float
    period_err_max_us: float
    bridge_cpu_pct: float
    load_cpu_pct: float
    machine_pct: float


def summarise(runs: list[Run]) -> Row:
    errors = [e for run in runs for e in run.period_err_us]
    return Row(
        load=runs[0].load,
        protocol=runs[0].protocol,
        runs=len(runs),
        frames=statistics.median(run.frames for run in runs),
        zero=[run.zero for run in runs],
        spells=[run.spells for run in runs],
        longest_spell_ms=max(run.longest_spell_ms for run in runs),
        lost=[run.lost for run in runs],
        pilot_max_gap_ms=max(run.pilot_max_gap_ms for run in runs),
        rate_hz=statistics.median(run.rate_hz for run in runs),
        period_err_p50_us=percentile(errors, 0.5),
        period_err_p99_us=percentile(errors, 0.99),
        period_err_max_us=max(errors) if errors else float("nan"),
        bridge_cpu_pct=statistics.median(run.bridge_cpu_pct for run in runs),
        load_cpu_pct=statistics.median(run.load_cpu_pct for run in runs),
        machine_pct=statistics.median(run.machine_pct for run in runs),
    )


HEADER = (
    f"{'load':<18} {'proto':<5} {'runs':>4} {'frames':>7} {'zero':>12} {'spells':>10} "
    f"{'longest ms':>10} {'lost':>8} {'pilot gap ms':>12} {'rate Hz':>7} {'err p50':>7} "
    f"{'err p99':>7} {'bridge %':>8} {'load %':>6} {'machine %':>9}"
)


def print_row(row: Row) -> None:
    print(
        f"{row.load:<18} {row.protocol:<5} {row.runs:>4d} {row.frames:>7.0f} "
        f"{_median_range(list(row.zero), 12)} {_median_range(list(row.spells), 10)} "
        f"{row.longest_spell_ms:>10.1f} {_median_range(row.lost, 8)} "
        f"{num(row.pilot_max_gap_ms, '.1f', 12)} {num(row.rate_hz, '.1f', 7)} "
        f"{num(row.period_err_p50_us, '.0f', 7)} {num(row.period_err_p99_us, '.0f', 7)} "
        f"{num(row.bridge_cpu_pct, '.1f', 8)} {num(row.load_cpu_pct, '.0f', 6)} "
        f"{num(row.machine_pct, '.0f', 9)}",
        flush=True,
    )


def print_notes(runs: list[Run], args: argparse.Namespace) -> None:
    print(
        "  frames, zero: command frames in the window (CKESC group 1 / every FT ESC) and the "
        "all-zero ones\n  (FT: per-ESC frames at 0 A); spells: runs of zero frames (several "
        "ESCs' at once count once);\n  longest: zero frame -> next non-zero frame of that "
        "stream; lost: frames the observer missed (kernel\n  drop count; under a flood, CKESC "
        "transfer-ID gaps, a lower bound; '-' unknown); pilot gap: the\n  autopilot's longest "
        f"time between two sends ({1e3 / PILOT_HZ:.0f} ms is on time); err: |interval - "
        "period| per stream, µs;\n  bridge %: the daemon and its processes, load %: the "
        f"load's processes, machine %: all {os.cpu_count()} CPUs busy,\n  each in % of one core"
    )
    pilot = {run.pilot_fifo for run in runs}
    observer = {run.observer_fifo for run in runs}
    print(
        f"autopilot: SCHED_FIFO {args.pilot_priority}"
        if pilot == {None}
        else f"autopilot: NOT at SCHED_FIFO: {'; '.join(sorted(p or 'FIFO' for p in pilot))}"
    )
    print(
        f"observer: SCHED_FIFO {args.observer_priority}"
        if observer == {None}
        else f"observer: NOT at SCHED_FIFO: {'; '.join(sorted(o or 'FIFO' for o in observer))}"
    )
    for run in runs:
        for report in run.loads:
            if report.achieved_per_s is not None and report.asked_per_s:
                reached = 100 * report.achieved_per_s / report.asked_per_s
                if report.kind == "can_flood" or reached < 90:
                    print(
                        f"  {run.load} #{run.index + 1}: {report.name} reached "
                        f"{report.achieved_per_s:.0f} {report.unit} ({reached:.0f} % of asked)"
                    )
        if run.pilot_late_ticks:
            print(
                f"  {run.load} #{run.index + 1}: the autopilot woke a period late "
                f"{run.pilot_late_ticks} times"
            )
        for problem in run.problems:
            print(f"!! {run.load} {run.protocol} #{run.index + 1}: {problem}")


def _json_safe(value: Any) -> Any:
    """``value`` with NaN (an empty measurement) as null: JSON has no NaN."""
    if isinstance(value, float) and value != value:
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="armed time measured per run")
    parser.add_argument(
        "--loads",
        nargs="+",
        choices=list(PRESETS),
        default=list(PRESETS),
        metavar="PRESET",
        help=f"load presets, in order (default all: {', '.join(PRESETS)})",
    )
    parser.add_argument(
        "--protocol",
        nargs="+",
        choices=list(OUTPUT_RATE_HZ),
        default=["ckesc"],
        help="ckesc: RawCommand_12b quad at 400 Hz; ft: current-mode quad at 100 Hz per ESC",
    )
    parser.add_argument("--repeat", type=int, default=1, help="runs per load and protocol")
    parser.add_argument(
        "--settle", type=float, default=2.0, help="seconds of load before the autopilot starts"
    )
    parser.add_argument("--pilot-priority", type=int, default=60, help="autopilot SCHED_FIFO")
    parser.add_argument("--observer-priority", type=int, default=10, help="observer SCHED_FIFO")
    parser.add_argument("--no-zenoh", action="store_true", help="run the bridge without Zenoh")
    parser.add_argument(
        "--bridge-config", metavar="FILE", help="a TOML config for the bridge (flags still win)"
    )
    parser.add_argument("--json", metavar="FILE", help="write every run and row as JSON")
    args = parser.parse_args()
    if args.seconds <= 0 or args.repeat < 1 or args.settle < 0:
        parser.error("--seconds must be > 0, --repeat >= 1 and --settle >= 0")
    signal.signal(signal.SIGTERM, raise_interrupt)
    ctx = multiprocessing.get_context("spawn")
    print(
        f"safety under load: {args.seconds:g} s armed per run after {args.settle:g} s of load; "
        f"SERVO_OUTPUT_RAW {PILOT_HZ} Hz (PWM {PWM_US} on {MOTORS} motors), HEARTBEAT armed "
        f"1 Hz; {os.cpu_count()} CPUs; Zenoh {'off' if args.no_zenoh else 'on (loopback)'}",
        flush=True,
    )
    runs: list[Run] = []
    rows: list[Row] = []
    failures: list[str] = []
    try:
        for protocol in args.protocol:
            what = "CKESC RawCommand_12b" if protocol == "ckesc" else "FT current mode"
            print(f"\n{what} quad at {OUTPUT_RATE_HZ[protocol]} Hz per stream", flush=True)
            print(HEADER)
            print("-" * len(HEADER), flush=True)
            for load_name in args.loads:
                mine = []
                for index in range(args.repeat):
                    try:
                        run, commands, sends, t0, t1 = run_once(
                            load_name, protocol, index, args, ctx
                        )
                    except (RuntimeError, BridgeError) as exc:  # the next load may still run
                        failures.append(f"{load_name} {protocol} #{index + 1}: {exc}")
                        print(f"{load_name:<18} {protocol:<5} failed: see below", flush=True)
                        continue
                    analyse(run, commands, sends, t0, t1)
                    mine.append(run)
                if mine:
                    runs.extend(mine)
                    rows.append(summarise(mine))
                    print_row(rows[-1])
    except KeyboardInterrupt:
        print("interrupted; every process this bench started has been stopped", file=sys.stderr)
        return 130
    print()
    print_notes(runs, args)
    if args.json:
        document = {
            "bench": "safety_load",
            "seconds": args.seconds,
            "settle_s": args.settle,
            "cpus": os.cpu_count(),
            "pilot_priority": args.pilot_priority,
            "observer_priority": args.observer_priority,
            "zenoh": not args.no_zenoh,
            "failures": failures,
            "rows": [asdict(row) for row in rows],
            "runs": [
                {
                    **{k: v for k, v in asdict(run).items() if k != "period_err_us"},
                    "lost": run.lost,
                    "period_err_p50_us": percentile(run.period_err_us, 0.5),
                    "period_err_p99_us": percentile(run.period_err_us, 0.99),
                    "period_err_max_us": max(run.period_err_us, default=float("nan")),
                }
                for run in runs
            ],
        }
        Path(args.json).write_text(json.dumps(_json_safe(document), indent=2) + "\n")
        print(f"wrote {args.json}")
    for failure in failures:
        print(f"!! failed: {failure}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
