"""The bridge's CPU against the plain loop it replaces, side by side in one run.

Run: ``python bench/cpu.py [--seconds 20] [--runs 3] [--protocols ckesc ft]
[--telemetry off on] [--loads idle busy2] [--contenders plain fixed immediate]
[--profile] [--perf] [--perf-python] [--bridge-source DIR] [--json FILE]``

Contenders, each fed by the same autopilot and timed by the same observer:

- plain: the script a user would write instead of the bridge, pymavlink + python-can: drain
  SERVO_OUTPUT_RAW, encode, send, ``time.sleep(period)`` (no arming, staleness, telemetry,
  relay or Zenoh; no real-time priority);
- fixed, immediate: ``esc-bridge run`` through its CLI with ``[output] latency`` "fixed" or
  "immediate", as shipped (loop in its own SCHED_FIFO process, Zenoh on loopback without
  scouting).
- floor (not run unless named): the least a Python loop does for the same frames, run as the
  bridge's loop runs (SCHED_FIFO at its default priority, ticks on absolute deadlines of the
  monotonic clock): at each tick it takes the newest SERVO_OUTPUT_RAW's first channel off its
  socket (no CRC, arming, staleness or relay), encodes and sends through python-can as the
  others do. Not a design (no safety path): what this machine charges any Python process for
  these frames at this rate, on the day, to judge the others' CPU and period error against.

Every contender runs at nice -10 when the bench runs as root (a busy machine's other work
would otherwise keep the bridge's loop process from starting in time).

Cases: CKESC RawCommand_12b x8 at 400 Hz (two frames a tick) and FT current mode x4 at 100 Hz
per ESC (one frame a tick, 400 ticks/s); without and with ESC telemetry on the bus (``esc-bridge
sim``: simulated ESCs that answer the commands at their families' own telemetry rates); idle,
and beside two busy processes (``loadgen/load.py``'s ``busy2``). The contenders of a case
take turns, run after run, so that the machine's load falls on all of them alike.

Beside the contender, all on a udp_multicast CAN bus of this machine and loopback MAVLink:
- the autopilot: SERVO_OUTPUT_RAW at 200 Hz with every motor at PWM 1100 + (k mod 800), a new
  value each send, and HEARTBEAT armed at 10 Hz, from a SCHED_FIFO process; it notes the wall
  time of every send (before the send);
- the observer: a SCHED_FIFO process that timestamps every frame on the bus in the kernel
  (SO_TIMESTAMPNS; on loopback the send time to within µs) and decodes the command frames.

Measured over ``--seconds`` after ``--warmup`` seconds of armed input:
- CPU: user + system time over the window, % of one core: the main process, the loop process
  (the bridge's), and all of them (its total);
- rate: command frames per second per stream (CKESC group 1 and 2; each FT ESC);
- period error: |interval between a stream's consecutive frames - its period|, µs (not for
  immediate mode, whose frames follow the input);
- input -> frame: from the autopilot's send of a value to the first frame carrying it, µs;
  seen: the share of sends that reached the bus (FT at 100 Hz per ESC carries every other one);
- telemetry: the non-command frames per second on the bus.
- ctxsw: context switches per second of all the contender's processes (threads included),
  nearly all of them waits ending: on this machine a process's CPU follows its wake-ups more
  than its work (``bench/tick.py``).

Each cell is the median over the runs of each run's figure. Under each case: the bridge's
total CPU over the plain script's, and the same per frame sent (each run's CPU over its rate,
medians: the plain script runs slow, and sends fewer frames for its CPU); with and without
telemetry run, the main process's CPU per telemetry frame (the difference over the frame rate).
The load average is printed with each case: on a shared machine compare within one run only.

``--profile``: after the runs of each case, one more run of the bridge in fixed mode under
yappi (the ``bench`` extra; ``bench/profile_hook``) with the CPU clock, in both processes and
every thread, over the measured window only: each thread's CPU, and the top functions by their
own CPU and by the CPU under them (a deterministic profiler slows what it watches: the shares
tell where the time goes, the CPU column of the runs before tells how much).

``--perf``: in every run, Linux's ``perf record`` samples the contender's processes (999 Hz,
every thread) over the measured window; under each case, the share of each process's samples
(%) that fell in the Python interpreter (libpython), the kernel, the C library (and the vDSO's
clock reads), and the rest (C extensions: msgpack, _socket, select ...). It tells whether the
CPU is the Python a process runs or the system calls and wake-ups it makes (the sampling adds a
little to the CPU columns of those runs). Needs ``perf`` (Debian: ``sudo apt-get install
linux-perf``) and the right to sample those processes (``kernel.perf_event_paranoid`` at most 1,
or root).

``--perf-python``: ``--perf`` with each sample's call stack (perf's DWARF unwinding) and
Python's perf maps (``PYTHONPERFSUPPORT=1``, Python 3.12 or later: run the bench from a 3.12
environment, whose ``esc-bridge`` it starts), so that under each case every process's samples
are also shared out by the innermost Python function on their stack, C calls and the kernel
under it included (a ``sendto`` to the function that called it): the functions with
``--profile-top`` of the largest shares, averaged over the runs. Unwinding copies each sample's
stack, which adds more to the CPU columns than ``--perf`` alone.

``--bridge-source DIR`` runs the bridge from another checkout (``git worktree add /tmp/before
<commit>``, or ``git archive <commit> | tar -x -C /tmp/before``) with this bench; ``--before DIR``
with the contenders ``fixed-before`` and ``immediate-before`` runs that checkout beside this one,
taking turns in the same run, so that a change is compared with the code before it in the same
minutes.
"""

from __future__ import annotations

import argparse
import bisect
import gc
import importlib.util
import itertools
import json
import multiprocessing
import os
import select
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from contextlib import AbstractContextManager, ExitStack, contextmanager, nullcontext, suppress
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from _common import (
    ESC_BRIDGE,
    GROUP,
    MAX_DATAGRAM,
    bridge_command,
    context_switches,
    cpu_seconds,
    free_port,
    holds_bus,
    ignore_sigint,
    log_tail,
    multicast_listener,
    num,
    process_tree,
    processes,
    raise_interrupt,
    recv_stamped,
    set_fifo,
    sleep_watching,
    wait_for,
)
from _stats import percentile
from can.interfaces.udp_multicast.utils import unpack_message

from bridge.errors import CodecError
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.mavlink import load_dialect
from loadgen.load import preset

PILOT_HZ = 200
HEARTBEAT_EVERY = PILOT_HZ // 10
PWM_LOW, PWM_SPAN = 1100, 800  # every send a new value, none of them zero or full
FT_MAX_CURRENT_A = 20.0  # the FT driver's default full scale (ft_max_current_a)
START_TIMEOUT_S = 60.0  # a first start generates the MAVLink dialect (seconds at load)
# Every contender at nice -10 where allowed, alike: on a machine busy with others' work the
# bridge's loop process must still start within the 15 s the bridge gives it.
NICE_LEVEL = -10
NICE = ["nice", "-n", str(NICE_LEVEL)] if os.geteuid() == 0 else []
FLOOR_FIFO_PRIORITY = 50  # the bridge loop's default [output] realtime_priority
LATENCY_HORIZON_S = 0.5  # a value not on the bus this long after its send was never sent


@dataclass(frozen=True)
class Case:
    protocol: str
    escs: int
    rate_hz: int  # per stream: CKESC group, FT ESC
    ticks_hz: int  # the loop's ticks per second
    telemetry: bool
    load: str

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def label(self) -> str:
        what = "CKESC 12b x8 400 Hz" if self.protocol == "ckesc" else "FT current x4 100 Hz"
        return f"{what}, telemetry {'on' if self.telemetry else 'off'}, {self.load}"


CASES = {
    "ckesc": dict(escs=8, rate_hz=400, ticks_hz=400),
    "ft": dict(escs=4, rate_hz=100, ticks_hz=400),
}


# -- what the frames carry ------------------------------------------------------------------


def frame_value(protocol: str, data: bytes) -> tuple[int, int] | None:
    """(stream, PWM the autopilot sent) of a command frame; (-1, 0) for any other frame of
    the family (telemetry); None for anything else."""
    try:
        msg = unpack_message(data)
        if protocol == "ckesc":
            frame = ckesc_codec.decode(msg)
            if frame is None:
                return None
            if not isinstance(frame.message, ckesc_records.RawCommand12b):
                return -1, 0
            return frame.message.group, 1000 + frame.message.throttles[0] // 2
        ft_frame = ft_codec.decode(msg)
    except (CodecError, ValueError, TypeError):
        return None
    if ft_frame is None:
        return None
    current = getattr(ft_frame.message, "current_a", None)
    if current is None:
        return -1, 0
    return ft_frame.esc_id, 1000 + round(current / FT_MAX_CURRENT_A * 1000)


# -- the processes beside the contender -----------------------------------------------------


def observer_worker(
    can_port: int, protocol: str, stop: Any, ready: Any, first_value: Any, out: Any
) -> None:
    """Every command frame on the bus as (kernel time, stream, PWM), and the telemetry frames'
    kernel times, until ``stop``; ``first_value`` gets the time of the first frame carrying an
    autopilot's value."""
    ignore_sigint()
    problem = set_fifo(10)
    gc.disable()  # nothing here makes reference cycles; no collector pauses
    sock = multicast_listener(can_port)
    sock.setblocking(False)
    commands: list[tuple[float, int, int]] = []
    telemetry: list[float] = []
    ready.set()
    while not stop.is_set():
        if not select.select([sock], [], [], 0.05)[0]:
            continue
        with suppress(BlockingIOError):
            while True:
                data, _port, stamp = recv_stamped(sock)
                found = frame_value(protocol, data)
                if found is None:
                    continue
                stream, pwm = found
                if stream < 0:
                    telemetry.append(stamp)
                    continue
                commands.append((stamp, stream, pwm))
                if pwm >= PWM_LOW and first_value.value == 0.0:
                    first_value.value = stamp
    sock.close()
    out.put((problem, commands, telemetry))


def pilot_worker(mavlink_port: int, stop: Any, ready: Any, out: Any) -> None:
    """SERVO_OUTPUT_RAW at 200 Hz, every motor at PWM 1100 + (k mod 800), and HEARTBEAT armed
    at 10 Hz, until ``stop``; reports (PWM, wall time just before the send) of every send."""
    ignore_sigint()
    problem = set_fifo(60)
    gc.disable()
    dialect = load_dialect()
    mav = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    dest = ("127.0.0.1", mavlink_port)
    armed = dialect.MAV_MODE_FLAG_SAFETY_ARMED | dialect.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    sends: list[tuple[int, float]] = []
    period = 1.0 / PILOT_HZ
    ready.set()
    start = time.monotonic()
    for k in itertools.count():
        if stop.is_set():
            break
        if k % HEARTBEAT_EVERY == 0:
            sock.sendto(mav.heartbeat_encode(2, 3, armed, 0, 4).pack(mav), dest)
        pwm = PWM_LOW + k % PWM_SPAN
        time_usec = int((time.monotonic() - start) * 1e6) & 0xFFFFFFFF
        frame = mav.servo_output_raw_encode(time_usec, 0, *([pwm] * 16)).pack(mav)
        sends.append((pwm, time.time()))
        sock.sendto(frame, dest)
        with suppress(BlockingIOError):
            while sock.recv(MAX_DATAGRAM):
                pass
        delay = start + (k + 1) * period - time.monotonic()
        if delay < -period:  # a whole period late: carry on from now, no burst
            start -= delay
        elif delay > 0:
            time.sleep(delay)
    sock.close()
    out.put((problem, sends))


def floor_worker(
    protocol: str, mavlink_port: int, can_port: int, escs: int, stop: Any, ready: Any
) -> None:
    """The floor contender (the module docstring), until ``stop``."""
    ignore_sigint()
    with suppress(PermissionError):
        os.nice(NICE_LEVEL)
    if (problem := set_fifo(FLOOR_FIFO_PRIORITY)) is not None:
        print(f"!! floor: not at SCHED_FIFO: {problem}", file=sys.stderr, flush=True)
    gc.disable()
    import can

    link = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    link.bind(("127.0.0.1", mavlink_port))
    link.setblocking(False)
    bus = can.Bus(interface="udp_multicast", channel=GROUP, port=can_port, hop_limit=0)
    period_ns = 1_000_000_000 // CASES[protocol]["ticks_hz"]
    groups = range(1, (escs + 3) // 4 + 1)
    pwm = 1000
    tid = tick = 0
    ready.set()
    next_ns = time.monotonic_ns()
    while not stop.is_set():
        with suppress(BlockingIOError):
            while True:
                data = link.recv(MAX_DATAGRAM)
                # MAVLink 2 SERVO_OUTPUT_RAW (id 36): servo1_raw after the 4-byte time_usec.
                if len(data) >= 16 and data[0] == 0xFD and data[7:10] == b"\x24\x00\x00":
                    pwm = data[14] | data[15] << 8
        fraction = min(max((pwm - 1000) / 1000, 0.0), 1.0)
        if protocol == "ckesc":
            throttles = [int(fraction * ckesc_records.THROTTLE_MAX + 0.5)] * 4
            for group in groups:
                bus.send(ckesc_codec.encode_raw_12b(group, throttles, tid))
                tid = (tid + 1) & 31
        else:
            bus.send(
                ft_codec.encode_command(
                    tick % escs + 1,
                    ft_records.Command.SET_CURRENT_GEAR_CRC16,
                    fraction * FT_MAX_CURRENT_A,
                )
            )
        tick += 1
        next_ns += period_ns
        delay_ns = next_ns - time.monotonic_ns()
        if delay_ns > 0:
            time.sleep(delay_ns / 1e9)
        elif delay_ns < -period_ns:
            next_ns = time.monotonic_ns()  # a period late: on from now, no burst
    bus.shutdown()
    link.close()


def plain_worker(
    protocol: str, mavlink_port: int, can_port: int, escs: int, stop: Any, ready: Any
) -> None:
    """The plain script: drain the autopilot's SERVO_OUTPUT_RAW, encode, send, sleep a period
    (CKESC: every group each tick; FT: one ESC a tick), until ``stop``."""
    ignore_sigint()
    with suppress(PermissionError):
        os.nice(NICE_LEVEL)
    os.environ["MAVLINK20"] = "1"
    import can
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{mavlink_port}")
    bus = can.Bus(interface="udp_multicast", channel=GROUP, port=can_port, hop_limit=0)
    pwm = [1000] * escs
    period = 1.0 / CASES[protocol]["ticks_hz"]
    groups = range(1, (escs + 3) // 4 + 1)
    tid = tick = 0
    ready.set()
    while not stop.is_set():
        while (msg := conn.recv_match(type="SERVO_OUTPUT_RAW", blocking=False)) is not None:
            pwm = [getattr(msg, f"servo{i + 1}_raw") for i in range(escs)]
        fractions = [min(max((p - 1000) / 1000, 0.0), 1.0) for p in pwm]
        if protocol == "ckesc":
            throttles = [int(f * ckesc_records.THROTTLE_MAX + 0.5) for f in fractions]
            for group in groups:
                bus.send(
                    ckesc_codec.encode_raw_12b(group, throttles[4 * group - 4 : 4 * group], tid)
                )
                tid = (tid + 1) & 31
        else:
            esc = tick % escs
            current = fractions[esc] * FT_MAX_CURRENT_A
            bus.send(
                ft_codec.encode_command(esc + 1, ft_records.Command.SET_CURRENT_GEAR_CRC16, current)
            )
        tick += 1
        time.sleep(period)
    bus.shutdown()
    conn.close()


# -- the bridge -----------------------------------------------------------------------------


def bridge_config(directory: Path, case: Case, latency: str) -> Path:
    """The bridge's configuration for ``case``: the passthrough mixer, no stream requests (the
    autopilot here sends at its own rates and answers none)."""
    path = directory / f"bridge-{case.protocol}-{latency}.toml"
    path.write_text(
        "[mavlink]\nstream_rate_hz = 0\nautopilot_heartbeat_hz = 0\n"
        f'[mixer]\nname = "passthrough-{case.escs}"\n'
        f'[output]\nprotocol = "{case.protocol}"\nrate_hz = {case.rate_hz}\n'
        f'latency = "{latency}"\n[can]\nbitrate = 1000000\n'
        '[zenoh]\nmulticast_scouting = false\nlisten = ["tcp/127.0.0.1:0"]\n'
    )
    return path


def bridge_prefix(source: Path | None) -> tuple[list[str], dict[str, str]]:
    """How to start ``esc-bridge``: installed, or from the source tree ``source`` (started in
    that folder: ``python -c`` puts the working folder first on the path)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if source is None:
        return [ESC_BRIDGE], env
    main = "import sys; from bridge.cli import main; sys.exit(main())"
    return [sys.executable, "-c", main], {**env, "PYTHONPATH": str(source)}


def loop_processes(pid: int) -> list[int]:
    """The bridge's loop process (the spawned child; not multiprocessing's resource tracker)."""
    found = []
    for child in process_tree(pid)[1:]:
        with suppress(OSError):
            if b"spawn_main" in Path(f"/proc/{child}/cmdline").read_bytes():
                found.append(child)
    return found


@contextmanager
def simulated_escs(case: Case, can_port: int) -> Iterator[None]:
    """``esc-bridge sim`` on the bus for a case with telemetry; nothing without."""
    if not case.telemetry:
        yield
        return
    command = [
        ESC_BRIDGE,
        "sim",
        "--protocol",
        case.protocol,
        "--escs",
        str(case.escs),
        "--can-interface",
        "udp_multicast",
        "--can-channel",
        GROUP,
        "--can-option",
        f"port={can_port}",
        "--can-option",
        "hop_limit=0",
        "--bitrate",
        "1000000",
        "--log-level",
        "warning",
    ]
    sim = subprocess.Popen(command)
    try:
        time.sleep(1.0)
        if sim.poll() is not None:
            raise RuntimeError(f"esc-bridge sim exited with code {sim.returncode}")
        yield
    finally:
        if sim.poll() is None:
            sim.send_signal(signal.SIGTERM)
            try:
                sim.wait(10)
            except subprocess.TimeoutExpired:
                sim.kill()
                sim.wait()


# -- one run --------------------------------------------------------------------------------


@dataclass
class Run:
    contender: str
    cpu_main_pct: float = float("nan")
    cpu_loop_pct: float = float("nan")  # the bridge's loop process; NaN for the plain script
    cpu_total_pct: float = float("nan")
    rate_hz: float = float("nan")
    err_p50_us: float = float("nan")
    err_p99_us: float = float("nan")
    lat_p50_us: float = float("nan")
    lat_p99_us: float = float("nan")
    seen_pct: float = float("nan")
    telemetry_per_s: float = 0.0
    switches_per_s: float = float("nan")  # context switches, all the contender's processes
    problems: list[str] = field(default_factory=list)
    profile: dict[str, list[str]] = field(default_factory=dict)
    perf: dict[str, dict[str, float]] = field(default_factory=dict)  # process -> where -> %
    # process -> innermost Python function -> % of the samples (--perf-python)
    perf_functions: dict[str, dict[str, float]] = field(default_factory=dict)


def run_once(
    case: Case, contender: str, can_port: int, args: argparse.Namespace, ctx: Any, tmp: Path
) -> Run:
    run = Run(contender)
    mavlink_port = free_port()
    log_path = tmp / f"{contender}.log"
    with processes(daemon_timeout_s=15) as procs:
        stop_observer, observer_ready = ctx.Event(), ctx.Event()
        first_value = ctx.Value("d", 0.0, lock=False)
        observer_q = ctx.Queue()
        observer = ctx.Process(
            target=observer_worker,
            args=(can_port, case.protocol, stop_observer, observer_ready, first_value, observer_q),
        )
        observer.start()
        procs.add_worker(observer, stop_observer)
        if not observer_ready.wait(START_TIMEOUT_S):
            raise RuntimeError("the observer did not start")
        daemon: subprocess.Popen[bytes] | None = None
        if contender in ("plain", "floor"):
            stop_plain, plain_ready = ctx.Event(), ctx.Event()
            plain = ctx.Process(
                target=plain_worker if contender == "plain" else floor_worker,
                args=(case.protocol, mavlink_port, can_port, case.escs, stop_plain, plain_ready),
            )
            with python_perf_maps(args.perf_python):
                plain.start()
            procs.add_worker(plain, stop_plain)
            if not plain_ready.wait(START_TIMEOUT_S):
                raise RuntimeError(f"the {contender} contender did not start")
            main_pid = plain.pid or 0
        else:
            latency, _, before = contender.partition("-")
            source = args.before if before else args.bridge_source
            prefix, env = bridge_prefix(source)
            if args.perf_python:
                env[PERF_MAPS_ENV] = "1"
            if args.profiling:
                (tmp / "profiles").mkdir(exist_ok=True)
                path = [str(PROFILE_HOOK), env.get("PYTHONPATH", "")]
                env["PYTHONPATH"] = os.pathsep.join(p for p in path if p)
                env["ESC_BRIDGE_PROFILE_DIR"] = str(tmp / "profiles")
            command = bridge_command(mavlink_port, can_port, "info")
            command[:1] = NICE + prefix
            command += ["--config", str(bridge_config(tmp, case, latency))]
            with log_path.open("wb") as log_file:
                daemon = subprocess.Popen(
                    command,
                    stdout=log_file,
                    stderr=subprocess.STDOUT,
                    env=env,
                    cwd=source,
                )
            procs.daemon = daemon
            main_pid = daemon.pid
            wait_for(
                lambda: holds_bus(main_pid, can_port) and loop_processes(main_pid),
                START_TIMEOUT_S,
                "before the bridge opened its bus",
                daemon,
                log_path,
            )
        stop_pilot, pilot_ready = ctx.Event(), ctx.Event()
        pilot_q = ctx.Queue()
        pilot = ctx.Process(
            target=pilot_worker, args=(mavlink_port, stop_pilot, pilot_ready, pilot_q)
        )
        pilot.start()
        procs.add_worker(pilot, stop_pilot)
        deadline = time.monotonic() + START_TIMEOUT_S
        while first_value.value == 0.0:
            if time.monotonic() > deadline or (daemon is not None and daemon.poll() is not None):
                raise RuntimeError(
                    f"{contender}: no command carrying the autopilot's values:\n"
                    + (log_tail(log_path) if daemon is not None else "")
                )
            time.sleep(0.02)
        time.sleep(args.warmup)
        loops = loop_processes(main_pid) if daemon is not None else []
        everything = process_tree(main_pid)
        if args.profiling:
            profile_toggle([main_pid, *loops])
        t0_wall, t0 = time.time(), time.monotonic()
        cpu0 = (cpu_seconds([main_pid]), cpu_seconds(loops), cpu_seconds(everything))
        switches0 = context_switches(everything)
        sampled = {"main": [main_pid], "loop": loops} if loops else {"main": [main_pid]}
        recording: AbstractContextManager[dict[str, Path]] = (
            perf_record(sampled, tmp / "perf", args.perf_python) if args.perf else nullcontext({})
        )
        with recording as samples:
            if daemon is not None:
                sleep_watching(args.seconds, daemon, log_path)
            else:
                time.sleep(args.seconds)
        elapsed = time.monotonic() - t0
        cpu1 = (cpu_seconds([main_pid]), cpu_seconds(loops), cpu_seconds(everything))
        switches1 = context_switches(everything)
        if args.perf_python:  # before perf_shares, which removes the data files
            run.perf_functions = {
                process: perf_functions(path) for process, path in samples.items()
            }
            for pid in everything:
                Path(f"/tmp/perf-{pid}.map").unlink(missing_ok=True)  # Python's perf maps
        run.perf = {process: perf_shares(path) for process, path in samples.items()}
        t1_wall = time.time()
        run.cpu_main_pct = 100 * (cpu1[0] - cpu0[0]) / elapsed
        run.cpu_loop_pct = 100 * (cpu1[1] - cpu0[1]) / elapsed if loops else float("nan")
        run.cpu_total_pct = 100 * (cpu1[2] - cpu0[2]) / elapsed
        run.switches_per_s = (switches1 - switches0) / elapsed
        if args.profiling:
            profile_toggle([main_pid, *loops])
            run.profile = profile_report(tmp / "profiles", main_pid, args.profile_top)
        stop_pilot.set()
        pilot_problem, sends = pilot_q.get(timeout=30)
        stop_observer.set()
        observer_problem, commands, telemetry = observer_q.get(timeout=60)
        for who, problem in (("autopilot", pilot_problem), ("observer", observer_problem)):
            if problem:
                run.problems.append(f"{who} not at SCHED_FIFO: {problem}")
    if daemon is not None and daemon.returncode not in (0, None):
        run.problems.append(f"the bridge exited {daemon.returncode}:\n{log_tail(log_path)}")
    analyse(run, case, commands, telemetry, sends, t0_wall, t1_wall)
    return run


START_ATTEMPTS = 4


def run_with_retry(
    case: Case, contender: str, can_port: int, args: argparse.Namespace, ctx: Any, tmp: Path
) -> Run | None:
    """:func:`run_once`, tried again when the contender did not start (a loop process slower
    to start than the bridge waits for, beside a busy machine's other work); None when it
    never did (said, and the bench goes on)."""
    for attempt in range(1, START_ATTEMPTS + 1):
        try:
            return run_once(case, contender, can_port, args, ctx, tmp)
        except RuntimeError as exc:
            print(f"!! {contender}, start {attempt}: {str(exc).splitlines()[-1]}", flush=True)
    return None


def analyse(
    run: Run,
    case: Case,
    commands: list[tuple[float, int, int]],
    telemetry: list[float],
    sends: list[tuple[int, float]],
    t0: float,
    t1: float,
) -> None:
    window = [c for c in commands if t0 <= c[0] <= t1]
    streams: dict[int, list[float]] = {}
    for stamp, stream, _pwm in window:
        streams.setdefault(stream, []).append(stamp)
    errors: list[float] = []
    rates = []
    for stamps in streams.values():
        if len(stamps) > 1:
            rates.append((len(stamps) - 1) / (stamps[-1] - stamps[0]))
            errors += [abs(b - a - case.period_s) * 1e6 for a, b in itertools.pairwise(stamps)]
    run.rate_hz = statistics.mean(rates) if rates else float("nan")
    if not run.contender.startswith("immediate"):
        run.err_p50_us, run.err_p99_us = percentile(errors, 0.5), percentile(errors, 0.99)
    stamps = [c[0] for c in commands]
    latencies = []
    measured = [s for s in sends if t0 <= s[1] <= t1 - LATENCY_HORIZON_S]
    for pwm, sent in measured:
        i = bisect.bisect_left(stamps, sent)
        while i < len(commands) and commands[i][0] - sent < LATENCY_HORIZON_S:
            if commands[i][2] == pwm:
                latencies.append((commands[i][0] - sent) * 1e6)
                break
            i += 1
    run.lat_p50_us, run.lat_p99_us = percentile(latencies, 0.5), percentile(latencies, 0.99)
    run.seen_pct = 100 * len(latencies) / max(1, len(measured))
    run.telemetry_per_s = sum(1 for s in telemetry if t0 <= s <= t1) / (t1 - t0)


# -- profiling ------------------------------------------------------------------------------

PROFILE_HOOK = Path(__file__).resolve().parent / "profile_hook"


def profile_toggle(pids: list[int]) -> None:
    """Start (first call) or stop and write (second) the profiles of ``pids``."""
    for pid in pids:
        with suppress(ProcessLookupError):
            os.kill(pid, signal.SIGUSR1)


def profile_report(directory: Path, main_pid: int, top: int) -> dict[str, list[str]]:
    """The top functions by own CPU and by CPU under them, and the CPU of each thread, of each
    profiled process (the main process and the loop)."""
    report: dict[str, list[str]] = {}
    deadline = time.monotonic() + 10
    while len(list(directory.glob("*.json"))) < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    for path in sorted(directory.glob("*.json")):
        profile = json.loads(path.read_text())
        name = "main" if int(path.stem) == main_pid else "loop"
        threads = sorted(profile["threads"], key=lambda t: -t["cpu_s"])
        total = sum(t["cpu_s"] for t in threads) or 1.0
        functions = profile["functions"]
        lines = [
            f"{total:.2f} s of CPU profiled; by thread: "
            + ", ".join(f"{t['name']} {100 * t['cpu_s'] / total:.0f} %" for t in threads)
        ]
        for key, label in (("own_s", "own"), ("under_s", "under")):
            ranked = sorted(functions, key=lambda f: -f[key])[:top]
            lines += [
                f"  {label:<5} {100 * f[key] / total:5.1f} % {f['calls']:>8} calls  {f['name']}"
                for f in ranked
            ]
        report[name] = lines
        path.unlink()
    return report


# -- perf ---------------------------------------------------------------------------------

PERF_WHERE = ("interpreter", "kernel", "libc", "other")
"""Where perf's samples fell, in the order printed (:func:`perf_where`)."""


@contextmanager
def perf_record(
    processes: dict[str, list[int]], directory: Path, stacks: bool = False
) -> Iterator[dict[str, Path]]:
    """``perf record`` of each named group of processes while the block runs (``stacks``: with
    each sample's call stack); yields the data file of each name (written once the block
    ends)."""
    directory.mkdir(exist_ok=True)
    paths = {name: directory / f"{name}.data" for name in processes}
    recorders = [
        subprocess.Popen(
            [
                "perf",
                "record",
                "-q",
                "-F",
                "999",
                *(["--call-graph", "dwarf,16384"] if stacks else []),
                "-o",
                str(paths[name]),
                "-p",
                ",".join(str(pid) for pid in pids),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for name, pids in processes.items()
    ]
    try:
        yield paths
    finally:
        for recorder in recorders:
            recorder.send_signal(signal.SIGINT)  # perf writes its file and exits
        for recorder in recorders:
            recorder.wait(30)


def perf_where(dso: str) -> str:
    """Where a sample in the shared object ``dso`` fell, one of :data:`PERF_WHERE`."""
    if dso.startswith("[kernel"):
        return "kernel"
    if "libpython" in dso or dso.startswith("python"):
        return "interpreter"
    if dso == "[vdso]" or dso.startswith(("libc.so", "libc-", "libm.so", "ld-linux")):
        return "libc"
    return "other"


def perf_shares(path: Path) -> dict[str, float]:
    """The share (%) of the samples in ``path`` that fell in each of :data:`PERF_WHERE`."""
    report = subprocess.run(
        [
            "perf",
            "report",
            "-i",
            str(path),
            "--stdio",
            "--sort",
            "dso",
            "--no-children",
            "-g",
            "none",
            "--percent-limit",
            "0",
        ],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    shares = dict.fromkeys(PERF_WHERE, 0.0)
    for line in report.splitlines():
        share, _, dso = line.strip().partition("%")
        with suppress(ValueError):
            shares[perf_where(dso.strip())] += float(share)
    path.unlink()
    return shares


PERF_MAPS_ENV = "PYTHONPERFSUPPORT"
"""Set to 1, Python 3.12 and later name each Python function in a perf map for perf."""


@contextmanager
def python_perf_maps(on: bool) -> Iterator[None]:
    """Python processes started in the block write perf maps (when ``on``)."""
    if on:
        os.environ[PERF_MAPS_ENV] = "1"
    try:
        yield
    finally:
        os.environ.pop(PERF_MAPS_ENV, None)


def perf_functions(path: Path) -> dict[str, float]:
    """The share (%) of the samples in ``path`` whose innermost Python function is each one
    (``<no Python>``: none on the stack, or its unwinding stopped short of one)."""
    script = subprocess.run(
        ["perf", "script", "-i", str(path), "-F", "tid,ip,sym"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    counts: Counter[str] = Counter()
    for sample in script.split("\n\n"):
        # A sample: its thread's line, then a line a frame, innermost first; Python's frames
        # are named "py::<qualified name>:<file>".
        frames = [line.split("py::", 1)[1] for line in sample.splitlines() if "py::" in line]
        if sample.strip():
            counts[frames[0].rsplit(":", 1)[0] if frames else "<no Python>"] += 1
    total = sum(counts.values())
    return {name: 100 * n / total for name, n in counts.items()} if total else {}


# -- the table ------------------------------------------------------------------------------


@dataclass
class Row:
    case: Case
    contender: str
    runs: list[Run]

    def median(self, name: str) -> float:
        return _median(getattr(run, name) for run in self.runs)

    def median_per_frame_sent(self) -> float:
        """The median over the runs of each run's CPU (all processes) per frame a second of a
        stream: % of a core per Hz."""
        return _median(run.cpu_total_pct / run.rate_hz for run in self.runs if run.rate_hz > 0)


def _median(values: Iterable[float]) -> float:
    """The median of ``values`` but NaN (a figure a run could not give); NaN if none."""
    known = [v for v in values if v == v]
    return statistics.median(known) if known else float("nan")


HEADER = (
    f"{'contender':<10} {'runs':>4} {'CPU %':>6} {'main %':>6} {'loop %':>6} {'rate Hz':>7} "
    f"{'err p50':>7} {'err p99':>7} {'lat p50':>7} {'lat p99':>7} {'seen %':>6} {'telem/s':>7} "
    f"{'ctxsw/s':>7}"
)


def print_row(row: Row) -> None:
    m = row.median
    print(
        f"{row.contender:<10} {len(row.runs):>4} {num(m('cpu_total_pct'), '.1f', 6)} "
        f"{num(m('cpu_main_pct'), '.1f', 6)} {num(m('cpu_loop_pct'), '.1f', 6)} "
        f"{num(m('rate_hz'), '.1f', 7)} {num(m('err_p50_us'), '.0f', 7)} "
        f"{num(m('err_p99_us'), '.0f', 7)} {num(m('lat_p50_us'), '.0f', 7)} "
        f"{num(m('lat_p99_us'), '.0f', 7)} {num(m('seen_pct'), '.0f', 6)} "
        f"{num(m('telemetry_per_s'), '.0f', 7)} {num(m('switches_per_s'), '.0f', 7)}",
        flush=True,
    )


def print_perf(row: Row, top_n: int) -> None:
    """Where each of the contender's processes spent its CPU (perf), medians over the runs."""
    for process in ("main", "loop"):
        shares = [run.perf[process] for run in row.runs if process in run.perf]
        if shares:
            where = ", ".join(
                f"{name} {statistics.median(s[name] for s in shares):.0f} %" for name in PERF_WHERE
            )
            print(f"  perf, {row.contender} {process} process: {where}", flush=True)
        functions = [
            run.perf_functions[process] for run in row.runs if process in run.perf_functions
        ]
        if functions:
            mean = {
                name: statistics.fmean(f.get(name, 0.0) for f in functions)
                for name in set().union(*functions)
            }
            top = sorted(mean.items(), key=lambda item: -item[1])[:top_n]
            listed = ", ".join(f"{name} {share:.1f} %" for name, share in top)
            print(f"  perf, {row.contender} {process} process, Python: {listed}", flush=True)


def print_ratios(rows: dict[str, Row]) -> None:
    plain = rows.get("plain")
    if plain is None:
        return
    base, base_per_frame = plain.median("cpu_total_pct"), plain.median_per_frame_sent()
    parts, per_frame = [], []
    for contender in ("floor", "fixed", "immediate", "fixed-before", "immediate-before"):
        if (row := rows.get(contender)) is not None:
            part = f"{contender} {row.median('cpu_total_pct') / base:.2f}x"
            if contender != "floor":  # one process: no loop of its own to compare
                part += f" (loop alone {row.median('cpu_loop_pct') / base:.2f}x)"
            parts.append(part)
            per_frame.append(f"{contender} {row.median_per_frame_sent() / base_per_frame:.2f}x")
    if parts:
        print(f"  CPU / plain script's: {', '.join(parts)}", flush=True)
        # The plain script's sleep(period) drifts (it sends 8-18 % fewer frames), and its CPU
        # follows its frames: per frame, the contenders are compared at the same work.
        print(f"  per frame sent (CPU / rate): {', '.join(per_frame)}", flush=True)


def print_per_frame(rows: dict[tuple[str, str, bool, str], Row]) -> None:
    """The main process's CPU per telemetry frame, from the cases run with and without."""
    lines = []
    for (protocol, load, telemetry, contender), on in rows.items():
        off = rows.get((protocol, load, False, contender))
        if not telemetry or contender in ("plain", "floor") or off is None:
            continue
        frames = on.median("telemetry_per_s")
        extra = on.median("cpu_main_pct") - off.median("cpu_main_pct")
        if frames > 0:
            lines.append(
                f"  {protocol} {load} {contender}: {frames:.0f} telemetry frames/s cost the main "
                f"process {extra:.1f} % of a core: {extra / 100 / frames * 1e6:.1f} µs a frame"
            )
    if lines:
        print("\nmain process CPU per telemetry frame (with telemetry - without, / frames):")
        print("\n".join(lines))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="measured time per run")
    parser.add_argument("--warmup", type=float, default=2.0, help="armed time before measuring")
    parser.add_argument("--runs", type=int, default=3, help="runs per contender and case")
    parser.add_argument("--protocols", nargs="+", choices=list(CASES), default=list(CASES))
    parser.add_argument("--telemetry", nargs="+", choices=["off", "on"], default=["off", "on"])
    parser.add_argument("--loads", nargs="+", choices=["idle", "busy2"], default=["idle", "busy2"])
    parser.add_argument(
        "--contenders",
        nargs="+",
        choices=["plain", "floor", "fixed", "immediate", "fixed-before", "immediate-before"],
        default=["plain", "fixed", "immediate"],
    )
    parser.add_argument(
        "--profile", action="store_true", help="one more fixed-mode run per case under yappi"
    )
    parser.add_argument(
        "--perf", action="store_true", help="where each process's CPU went, from perf's samples"
    )
    parser.add_argument(
        "--perf-python",
        action="store_true",
        help="--perf, and the Python functions the samples fell in (Python 3.12 or later)",
    )
    parser.add_argument("--profile-top", type=int, default=15, help="functions listed")
    parser.add_argument("--bridge-source", type=Path, metavar="DIR", help="run that checkout")
    parser.add_argument(
        "--before",
        type=Path,
        metavar="DIR",
        help="the checkout the fixed-before and immediate-before contenders run from",
    )
    parser.add_argument("--json", metavar="FILE", help="write every run as JSON")
    args = parser.parse_args()
    args.profiling = False
    if any(c.endswith("-before") for c in args.contenders) and args.before is None:
        parser.error("the -before contenders need --before DIR")
    if args.perf_python:
        if sys.version_info < (3, 12):
            parser.error(
                "--perf-python needs Python 3.12 or later (perf maps): run the bench from a 3.12 "
                "environment (docs/running.md, 'Measured: CPU against the plain loop', says how)"
            )
        args.perf = True
    if args.perf and shutil.which("perf") is None:
        parser.error("--perf needs perf: sudo apt-get install linux-perf")
    if args.profile and importlib.util.find_spec("yappi") is None:
        parser.error("--profile needs yappi: .venv/bin/pip install -e '.[bench]'")
    signal.signal(signal.SIGTERM, raise_interrupt)
    ctx = multiprocessing.get_context("spawn")
    print(
        f"bench/cpu.py: {args.seconds:g} s per run after {args.warmup:g} s armed, {args.runs} runs "
        f"per contender; autopilot SERVO_OUTPUT_RAW {PILOT_HZ} Hz; {os.cpu_count()} CPUs"
        + (f"; bridge from {args.bridge_source}" if args.bridge_source else ""),
        flush=True,
    )
    print(
        "CPU in % of one core (CPU: all the contender's processes; main, loop: the bridge's "
        "two); rate: frames/s per stream;\nerr: period error, lat: autopilot send -> first frame "
        "carrying it, µs; medians over the runs",
        flush=True,
    )
    all_rows: dict[tuple[str, str, bool, str], Row] = {}
    document: list[dict[str, Any]] = []
    try:
        for protocol, load, telemetry in itertools.product(
            args.protocols, args.loads, args.telemetry
        ):
            case = Case(protocol, **CASES[protocol], telemetry=telemetry == "on", load=load)
            print(
                f"\n{case.label} (load average {os.getloadavg()[0]:.1f})\n{HEADER}\n"
                + "-" * len(HEADER),
                flush=True,
            )
            can_port = free_port()
            runs: dict[str, list[Run]] = {c: [] for c in args.contenders}
            with (
                tempfile.TemporaryDirectory() as tmp_name,
                ExitStack() as stack,
            ):
                stack.enter_context(preset(load))
                stack.enter_context(simulated_escs(case, can_port))
                for index in range(args.runs):
                    turn = args.contenders[index % len(args.contenders) :]
                    for contender in turn + args.contenders[: len(args.contenders) - len(turn)]:
                        run = run_with_retry(case, contender, can_port, args, ctx, Path(tmp_name))
                        if run is None:
                            continue
                        runs[contender].append(run)
                        for problem in run.problems:
                            print(f"!! {contender}: {problem}", flush=True)
                rows = {c: Row(case, c, r) for c, r in runs.items() if r}
                for row in rows.values():
                    print_row(row)
                    all_rows[(protocol, load, case.telemetry, row.contender)] = row
                print_ratios(rows)
                if args.perf:
                    for row in rows.values():
                        print_perf(row, args.profile_top)
                if args.profile and "fixed" in args.contenders:
                    args.profiling = True
                    try:
                        profiled = run_with_retry(
                            case, "fixed", can_port, args, ctx, Path(tmp_name)
                        )
                    finally:
                        args.profiling = False
                    for process, lines in profiled.profile.items() if profiled else ():
                        print(f"  profile, bridge fixed, {process} process: " + lines[0])
                        print("\n".join(lines[1:]))
            document += [
                {"case": asdict(case), "runs": [asdict(run) for run in r]} for r in runs.values()
            ]
    except KeyboardInterrupt:
        print("interrupted; every process this bench started has been stopped", file=sys.stderr)
        return 130
    print_per_frame(all_rows)
    if args.json:
        Path(args.json).write_text(json.dumps(document, indent=1, default=str) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
