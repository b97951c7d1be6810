"""ESC telemetry on a saturated bus, while the output loop runs: drops, timing, latency, CPU.

Run: ``python bench/telemetry.py [--seconds 20] [--escs 8]``

The daemon runs through its CLI (`esc-bridge run`: CKESC 12b at 400 Hz, a passthrough mixer, a
udp_multicast bus on this machine, Zenoh on loopback only), with an armed autopilot process
sending SERVO_OUTPUT_RAW at 200 Hz. Three runs:

- idle: no telemetry on the bus;
- saturated, twice (ESC_STATUS at the default 10 Hz, then at 50 Hz): an ESC process sends real
  CKESC telemetry (MSG1, MSG2, MSG3, MSG_EXP1 from nodes 1..N) at the frame rate of a saturated
  1 Mbit/s bus, in bursts every 2 ms, and counts every frame it sends.

Measured:
- frames: sent by the ESC process against the telemetry the daemon's CAN reader counted (its
  "CAN in:" line at exit); the kernel's drop counter of the reader's socket says whether a loss
  happened before the reader (socket buffer overflow) or after it;
- output period error: |interval between consecutive group-1 command frames - 2.5 ms|, frames
  timed by the kernel (SO_TIMESTAMPNS on the observer's socket; on loopback that is the send time
  to within µs), p99 of each saturated run against the idle run;
- telemetry -> ESC_STATUS: every 150-250 ms the ESC process gives node 1 a new, unique rpm and
  notes when the first frame carrying it left; the autopilot process timestamps (kernel) the
  first ESC_STATUS whose rpm[0] shows it;
- CPU: user + system time of the daemon's main process and of its output-loop process over the
  measured time, % of one core; beside them the bench's own processes and the rest of the machine
  (other work on a shared machine shows up there, and in the results).

Verdicts, for each saturated run: period error p99 within 10 % of the idle run's; no telemetry
frame dropped.
"""

from __future__ import annotations

import argparse
import itertools
import multiprocessing
import os
import random
import re
import select
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from _common import (
    GROUP,
    SO_TIMESTAMPNS,
    UdpSocket,
    bridge_command,
    children,
    cpu_seconds,
    free_port,
    ignore_sigint,
    log_tail,
    machine_busy_seconds,
    multicast_listener,
    num,
    process_sockets,
    processes,
    raise_interrupt,
    recv_stamped,
    udp_sockets,
)
from _stats import percentile
from can.interfaces.udp_multicast.utils import pack_message, unpack_message

from bridge.escs.ckesc import codec, records
from bridge.mavlink import load_dialect

OUTPUT_RATE_HZ = 400
INPUT_RATE_HZ = 200  # SERVO_OUTPUT_RAW; HEARTBEAT (armed) at 10 Hz
SATURATED_FPS = 6250  # 1 Mbit/s over ~160 bits per extended frame with 8 data bytes
BURST_PERIOD_S = 0.002
MAX_BURST_FACTOR = 2  # after a stall the ESC process sends at most 2 bursts' worth at once
MARKER_INTERVAL_S = (0.15, 0.25)
BASE_RPM = 5000
FIRST_MARKER_RPM = 20_000  # marker rpms count up from here (MSG1 speed is u16)
# Per node and cycle: MSG1 four times, MSG2 twice, MSG3 and MSG_EXP1 once each.
SLOT_KINDS = ("msg1", "msg2", "msg1", "msg3", "msg1", "msg2", "msg1", "exp1")
RX_SAMPLE_S = 0.05
DRAINED_BYTES = 16 << 10  # ~20 frames: the commands keep arriving, so never quite 0
STALL_S = 0.010  # a pause of the ESC process longer than this is noted
CAN_IN = re.compile(
    r"CAN in: (\d+) frames read, (\d+) telemetry, (\d+) malformed, \d+ error frames, (\d+) read "
    r"errors; (\d+) of (\d+) ESCs online"
)
LOOP_SUMMARY = re.compile(
    r"output loop: (\d+) ticks, (\d+) frames, (\d+) send errors, \d+ ticks held back, (\d+) "
    r"overruns, .*"
    r"lateness p50 (\d+) µs, p99 (\d+) µs, max (\d+) µs"
)


# -- sockets and /proc --------------------------------------------------------------------


def _multicast_sender() -> socket.socket:
    """A socket that sends to the bus (TTL 0: never leaves this machine) and joins nothing."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("@I", 0))
    return sock


def _run_delay_seconds(pid: int) -> float:
    """Time the threads of ``pid`` (those alive now) spent runnable, waiting for a CPU."""
    total = 0
    with suppress(OSError):
        for task in os.listdir(f"/proc/{pid}/task"):
            with suppress(OSError, IndexError, ValueError):
                total += int(Path(f"/proc/{pid}/task/{task}/schedstat").read_text().split()[1])
    return total / 1e9


def _spawned_children(pid: int) -> list[int]:
    """The multiprocessing children of ``pid`` (the output loop; not the resource tracker)."""
    kids = []
    for kid in children(pid):
        with suppress(OSError):
            if b"spawn_main" in Path(f"/proc/{kid}/cmdline").read_bytes():
                kids.append(kid)
    return kids


# -- the ESC process ------------------------------------------------------------------------


def _telemetry_packet(node: int, message: records.CkescMessage, transfer_id: int) -> bytes:
    """A real CKESC frame, as python-can's udp_multicast puts it on the wire."""
    frame = codec.CkescFrame(codec.default_priority(message), node, None, transfer_id, message)
    packet: bytes = pack_message(codec.encode(frame))
    return packet


def _message(kind: str, rpm: int) -> records.CkescMessage:
    if kind == "msg1":
        return records.Msg1(speed_rpm=rpm, throttle=1000, status=records.Msg1Status.RUNNING)
    if kind == "msg2":
        return records.Msg2(voltage_v=24.0, current_a=5.0, mos_temp_c=40)
    if kind == "msg3":
        return records.Msg3(mos_temp_c=40, capacitor_temp_c=35, motor_temp_c=50, mcu_temp_c=45)
    return records.MsgExp1(speed_rpm=rpm, voltage_v=24.0, current_a=5.0)


@dataclass
class EscReport:
    """What the ESC process did."""

    sent: int = 0
    send_errors: int = 0
    skipped: int = 0  # frames not sent because the process fell behind by more than a burst
    longest_gap_s: float = 0.0  # the longest time between two of its bursts
    stalls: list[float] = field(default_factory=list)  # wall times of gaps over STALL_S
    cpu_s: float = 0.0  # its own CPU time, user + system
    active_s: float = 0.0
    markers: list[tuple[int, float]] = field(default_factory=list)  # (rpm, wall time sent)


def esc_worker(port: int, n_escs: int, fps: float, end_wall: float, seed: int, out: Any) -> None:
    """CKESC telemetry from nodes 1..n_escs at ``fps`` frames/s in total, until ``end_wall``.

    Frames go out in bursts every BURST_PERIOD_S, in a fixed round robin over the nodes, with
    their own transfer ID counters. Node 1's rpm jumps to a new marker value now and then: a
    MSG1 carrying it goes out at once (its send time is noted) and node 1's later MSG1 and
    MSG_EXP1 frames carry it until the next marker.
    """
    ignore_sigint()
    rng = random.Random(seed)
    sock = _multicast_sender()
    dest = (GROUP, port)
    # Every other node's frames never change but for the transfer ID: encode them up front.
    slots = [(node, kind) for kind in SLOT_KINDS for node in range(1, n_escs + 1)]
    fixed: dict[tuple[int, str], list[bytes]] = {}
    for node, kind in set(slots):
        if node != 1 or kind in ("msg2", "msg3"):
            fixed[node, kind] = [
                _telemetry_packet(node, _message(kind, BASE_RPM), t) for t in range(32)
            ]
    transfer_ids: dict[tuple[int, str], int] = dict.fromkeys(set(slots), 0)
    report = EscReport()
    rpm = BASE_RPM
    marker = FIRST_MARKER_RPM
    max_burst = MAX_BURST_FACTOR * max(1, round(fps * BURST_PERIOD_S))
    start = time.monotonic()
    end = start + (end_wall - time.time())
    next_marker = start + rng.uniform(*MARKER_INTERVAL_S)
    next_burst = last = start
    cursor = itertools.cycle(slots)

    def send(packet: bytes) -> None:
        try:
            sock.sendto(packet, dest)
        except OSError:
            report.send_errors += 1
        else:
            report.sent += 1

    while (now := time.monotonic()) < end:
        report.longest_gap_s = max(report.longest_gap_s, now - last)
        if now - last > STALL_S:
            report.stalls.append(time.time())
        last = now
        if now >= next_marker:
            rpm, marker = marker, marker + 1
            key = (1, "msg1")
            packet = _telemetry_packet(1, _message("msg1", rpm), transfer_ids[key])
            transfer_ids[key] = (transfer_ids[key] + 1) & 31
            report.markers.append((rpm, time.time()))
            send(packet)
            next_marker = now + rng.uniform(*MARKER_INTERVAL_S)
        due = int((now - start) * fps) - (report.sent + report.send_errors + report.skipped)
        if due > max_burst:  # fell behind: a real bus would not have carried the backlog either
            report.skipped += due - max_burst
            due = max_burst
        for _ in range(max(0, due)):
            node, kind = key = next(cursor)
            tid = transfer_ids[key]
            transfer_ids[key] = (tid + 1) & 31
            if key in fixed:
                send(fixed[key][tid])
            else:
                send(_telemetry_packet(node, _message(kind, rpm), tid))
        next_burst += BURST_PERIOD_S
        delay = next_burst - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -BURST_PERIOD_S:
            next_burst = time.monotonic()  # woke late: no run of back-to-back bursts
    report.active_s = time.monotonic() - start
    report.cpu_s = time.process_time()
    sock.close()
    out.put(report)


# -- the autopilot process ------------------------------------------------------------------


@dataclass
class PilotReport:
    """What the autopilot process sent and received."""

    sent: int = 0
    received: dict[str, int] = field(default_factory=dict)  # message name -> count
    bad_data: int = 0
    esc_status: list[tuple[float, int]] = field(default_factory=list)  # (kernel time, rpm[0])


def autopilot_worker(mavlink_port: int, n_escs: int, stop: Any, out: Any) -> None:
    """Armed HEARTBEAT at 10 Hz and SERVO_OUTPUT_RAW at 200 Hz until ``stop`` is set; every
    MAVLink message the daemon sends back is parsed with the project's dialect, and ESC_STATUS
    for ESCs 0..3 is noted with its kernel receive time."""
    ignore_sigint()
    dialect = load_dialect()
    mav = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
    parser = dialect.MAVLink(None, srcSystem=255, srcComponent=190)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.bind(("127.0.0.1", 0))
    dest = ("127.0.0.1", mavlink_port)
    armed = dialect.MAV_MODE_FLAG_SAFETY_ARMED | dialect.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    report = PilotReport()
    period = 1.0 / INPUT_RATE_HZ
    start = time.monotonic()
    for k in itertools.count():
        if k % 8 == 0 and stop.is_set():
            break
        if k % (INPUT_RATE_HZ // 10) == 0:
            heartbeat = mav.heartbeat_encode(2, 3, armed, 0, 4)  # quadrotor, ArduPilot, active
            sock.sendto(heartbeat.pack(mav), dest)
        time_usec = int((time.monotonic() - start) * 1e6) & 0xFFFFFFFF
        pwm = [1400 + (k % 200)] * n_escs + [0] * (32 - n_escs)
        for port in range(2 if n_escs > 16 else 1):  # port 1 carries channels 17..32
            message = mav.servo_output_raw_encode(time_usec, port, *pwm[16 * port : 16 * port + 16])
            sock.sendto(message.pack(mav), dest)
            report.sent += 1
        deadline = start + (k + 1) * period
        while (left := deadline - time.monotonic()) > 0:
            if not select.select([sock], [], [], left)[0]:
                break
            data, _port, stamp = recv_stamped(sock)
            try:
                messages = parser.parse_buffer(data) or []
            except dialect.MAVError:
                report.bad_data += 1
                continue
            for msg in messages:
                name = msg.get_type()
                report.received[name] = report.received.get(name, 0) + 1
                if name == "ESC_STATUS" and msg.index == 0:
                    report.esc_status.append((stamp, int(msg.rpm[0])))
    sock.close()
    out.put(report)


# -- one run of the daemon ------------------------------------------------------------------


@dataclass
class Run:
    """The measurements of one daemon run."""

    name: str
    telemetry: bool
    esc_status_hz: float
    period_err_us: list[float] = field(default_factory=list)
    achieved_hz: float = float("nan")
    latency_ms: list[float] = field(default_factory=list)
    window_start: float = 0.0  # wall time the measured time began
    markers: int = 0
    esc_status_hz_seen: float = float("nan")  # index-0 ESC_STATUS received per second
    cpu_main_pct: float = float("nan")
    cpu_loop_pct: float = float("nan")
    cpu_bench_pct: float = float("nan")  # the ESC and autopilot processes and the observer
    cpu_machine_pct: float = float("nan")  # every CPU of the machine, busy time
    main_waiting_pct: float = float("nan")  # the main process's threads, waiting for a CPU
    esc: EscReport | None = None
    pilot: PilotReport | None = None
    observed_telemetry: int = 0
    observer_drops: int = 0
    reader_drops: int | None = None  # the kernel's drop count of the daemon's reader socket
    reader_peak_bytes: int = 0  # the most it held, sampled every RX_SAMPLE_S
    drop_times: list[float] = field(default_factory=list)  # samples (s into the window) with drops
    can_in: tuple[int, ...] | None = None  # frames, telemetry, malformed, read errors, online, n
    loop_summary: tuple[int, ...] | None = None  # ticks, frames, errors, overruns, p50, p99, max
    exit_code: int | None = None
    problems: list[str] = field(default_factory=list)

    @property
    def counted(self) -> int | None:
        return None if self.can_in is None else self.can_in[1]

    @property
    def dropped(self) -> int | None:
        if self.counted is None:
            return None
        return (self.esc.sent if self.esc else 0) - self.counted


def _daemon_config(path: Path, n_escs: int, esc_status_hz: float, zenoh: bool) -> Path:
    mixer = path / f"passthrough-{n_escs}.toml"
    outputs = "".join(
        f'\n[[outputs]]\nname = "m{i}"\nsource = "ch{i}"\n' for i in range(1, n_escs + 1)
    )
    mixer.write_text(f'[info]\ndescription = "bench passthrough"\n{outputs}')
    zenoh_section = (
        # Peer mode, no scouting, no peers, listening on loopback only: never leaves this host.
        '[zenoh]\nenabled = true\nmode = "peer"\nmulticast_scouting = false\n'
        'listen = ["tcp/127.0.0.1:0"]\nvehicle = "bench"\n'
        if zenoh
        else "[zenoh]\nenabled = false\n"
    )
    config = path / f"bench-{esc_status_hz:g}.toml"
    config.write_text(
        # The autopilot link carries every family, as a ground station's would.
        f"[mavlink]\nstream_rate_hz = 0\nautopilot_messages = {{ esc_status = {esc_status_hz}, "
        "esc_info = 1, esc_telemetry = 10 }\n"
        f'[mixer]\nname = "{mixer}"\n'
        f'[output]\nrate_hz = {OUTPUT_RATE_HZ}\nlatency = "fixed"\n'
        # The virtual bus has no bit rate; the telemetry here is far above CKESC's factory rates.
        "bus_load_ceiling = 1.0\n"
        '[can]\nbitrate = 1000000\n[escs]\nckesc_command = "12b"\n'
        f"{zenoh_section}"
    )
    return config


def _wait_for(
    predicate: Callable[[], bool], timeout_s: float, what: str, daemon: subprocess.Popen[bytes]
) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if daemon.poll() is not None:
            raise RuntimeError(f"the daemon exited (code {daemon.returncode}) {what}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out {what}")
        time.sleep(0.05)


def run_case(
    run: Run, n_escs: int, seconds: float, warmup: float, fps: float, zenoh: bool, seed: int
) -> Run:
    ctx = multiprocessing.get_context("spawn")
    mavlink_port, can_port = free_port(), free_port()
    with (
        multicast_listener(can_port) as observer,
        tempfile.TemporaryDirectory() as tmp,
        processes(daemon_timeout_s=10) as procs,
    ):
        observer.setblocking(False)
        observer_inode = os.fstat(observer.fileno()).st_ino
        config = _daemon_config(Path(tmp), n_escs, run.esc_status_hz, zenoh)
        log_path = Path(tmp) / "daemon.log"
        with log_path.open("wb") as log_file:
            daemon = subprocess.Popen(
                [*bridge_command(mavlink_port, can_port, "info"), "--config", str(config)],
                stdout=log_file,
                stderr=subprocess.STDOUT,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
        procs.daemon = daemon
        # The CAN reader's socket (the only one on the bus in the main process) exists once the
        # output loop is up: from then on the kernel queues every frame for it.
        _wait_for(
            lambda: bool(process_sockets(daemon.pid, can_port)),
            30.0,
            "before its CAN reader opened the bus",
            daemon,
        )
        loop_pids = _spawned_children(daemon.pid)
        reader_sockets = process_sockets(daemon.pid, can_port)
        if len(reader_sockets) != 1:
            run.problems.append(f"the daemon holds {len(reader_sockets)} sockets on the bus, not 1")
        reader_inode = reader_sockets[0].inode
        reader_drops = reader_sockets[0].drops
        stop_pilot = ctx.Event()
        pilot_q = ctx.Queue()
        pilot = ctx.Process(
            target=autopilot_worker, args=(mavlink_port, n_escs, stop_pilot, pilot_q)
        )
        pilot.start()
        procs.add_worker(pilot)
        time.sleep(1.0)  # the autopilot's interpreter starts; the daemon arms
        window_start = time.time() + warmup
        window_end = window_start + seconds
        run.window_start = window_start
        esc_q = ctx.Queue()
        esc_pid = 0
        if run.telemetry:
            esc = ctx.Process(
                target=esc_worker, args=(can_port, n_escs, fps, window_end, seed, esc_q)
            )
            esc.start()
            procs.add_worker(esc)
            esc_pid = esc.pid or 0

        group1: list[float] = []  # kernel times of group-1 command frames
        cpu_start: tuple[float, float, float, float, float, float] | None = None
        bench_pids = [pilot.pid or 0, os.getpid()]
        next_sample = 0.0
        while (now := time.time()) < window_end + 0.05:
            if cpu_start is None and now >= window_start:
                cpu_start = (
                    time.monotonic(),
                    cpu_seconds([daemon.pid]),
                    cpu_seconds(loop_pids),
                    cpu_seconds([*bench_pids, esc_pid]),
                    machine_busy_seconds(),
                    _run_delay_seconds(daemon.pid),
                )
            if now >= next_sample:  # the reader socket's backlog and drops, every 50 ms
                next_sample = now + RX_SAMPLE_S
                if daemon.poll() is not None:
                    raise RuntimeError(
                        f"the daemon exited during the run (code {daemon.returncode}):\n"
                        + log_tail(log_path)
                    )
                sample = udp_sockets(can_port).get(reader_inode)
                if sample is not None:
                    run.reader_peak_bytes = max(run.reader_peak_bytes, sample.rx_queue_bytes)
                    if sample.drops > reader_drops:
                        run.drop_times.append(now - window_start)
                    reader_drops = sample.drops
            if not select.select([observer], [], [], RX_SAMPLE_S)[0]:
                continue
            with suppress(BlockingIOError):
                while True:
                    data, sender_port, stamp = recv_stamped(observer)
                    if sender_port != can_port:  # the ESC process's sending socket
                        run.observed_telemetry += 1
                        continue
                    msg = unpack_message(data)
                    frame = codec.decode(msg)
                    if (
                        frame is not None
                        and isinstance(frame.message, records.RawCommand12b)
                        and frame.message.group == 1
                        and window_start <= stamp <= window_end
                    ):
                        group1.append(stamp)
        assert cpu_start is not None
        elapsed = time.monotonic() - cpu_start[0]
        run.cpu_main_pct = 100 * (cpu_seconds([daemon.pid]) - cpu_start[1]) / elapsed
        loop_cpu = cpu_seconds(loop_pids)
        run.cpu_loop_pct = 100 * (loop_cpu - cpu_start[2]) / elapsed
        run.cpu_machine_pct = 100 * (machine_busy_seconds() - cpu_start[4]) / elapsed
        run.main_waiting_pct = 100 * (_run_delay_seconds(daemon.pid) - cpu_start[5]) / elapsed
        bench_cpu = cpu_seconds(bench_pids) - cpu_start[3]
        if run.telemetry:
            run.esc = esc_q.get(timeout=30)
            bench_cpu += run.esc.cpu_s  # it has ended (with the window) by now
        run.cpu_bench_pct = 100 * bench_cpu / elapsed
        # Let the reader drain what the kernel still holds for it before asking for its count.
        drain_end = time.monotonic() + 5.0
        while time.monotonic() < drain_end:
            sample = udp_sockets(can_port).get(reader_inode)
            if sample is None or sample.rx_queue_bytes < DRAINED_BYTES:
                break
            time.sleep(0.05)
        time.sleep(0.3)
        reader = udp_sockets(can_port).get(reader_inode)
        if reader is not None:
            run.reader_drops = reader.drops
            if reader.drops > reader_drops:
                run.drop_times.append(time.time() - window_start)
            if reader.rx_queue_bytes >= DRAINED_BYTES:
                run.problems.append(f"the reader still held {reader.rx_queue_bytes} B at the end")
        run.observer_drops = udp_sockets(can_port).get(observer_inode, UdpSocket(0, 0, 0)).drops
        with suppress(BlockingIOError):  # what arrived after the window
            while True:
                _data, sender_port, _stamp = recv_stamped(observer)
                if sender_port != can_port:
                    run.observed_telemetry += 1

        daemon.send_signal(signal.SIGTERM)
        try:
            run.exit_code = daemon.wait(20)
        except subprocess.TimeoutExpired:
            run.problems.append("the daemon did not stop within 20 s of SIGTERM")
        stop_pilot.set()
        run.pilot = pilot_q.get(timeout=30)
        log_text = log_path.read_text(errors="replace")

    if (m := CAN_IN.search(log_text)) is not None:
        run.can_in = tuple(int(g) for g in m.groups())
    else:
        run.problems.append("no 'CAN in:' line in the daemon's log")
    if (m := LOOP_SUMMARY.search(log_text)) is not None:
        run.loop_summary = tuple(int(g) for g in m.groups())
    if run.observer_drops:
        run.problems.append(f"the bench's own socket dropped {run.observer_drops} frames")
    if run.pilot is not None and run.pilot.bad_data:
        run.problems.append(f"the autopilot got {run.pilot.bad_data} unparsable MAVLink datagrams")
    if run.exit_code not in (0, None):
        run.problems.append(f"the daemon exited with code {run.exit_code}")
    if run.problems:
        run.problems.append(f"daemon log (last lines):\n{log_tail(log_path, log_text)}")

    period = 1.0 / OUTPUT_RATE_HZ
    if len(group1) > 1:
        run.period_err_us = [abs(b - a - period) * 1e6 for a, b in itertools.pairwise(group1)]
        run.achieved_hz = (len(group1) - 1) / (group1[-1] - group1[0])
    if run.pilot is not None:
        in_window = [s for s in run.pilot.esc_status if window_start <= s[0] <= window_end]
        run.esc_status_hz_seen = len(in_window) / seconds
        if run.esc is not None:
            _latencies(run, run.esc.markers, run.pilot.esc_status, window_start)
    return run


def _latencies(
    run: Run, markers: list[tuple[int, float]], statuses: list[tuple[float, int]], since: float
) -> None:
    """Marker send -> the first ESC_STATUS showing that rpm, for markers sent after ``since``."""
    first_seen: dict[int, float] = {}
    for stamp, rpm in statuses:
        first_seen.setdefault(rpm, stamp)
    for rpm, sent in markers:
        if sent < since:
            continue
        run.markers += 1
        seen = first_seen.get(rpm)
        if seen is not None and seen >= sent:
            run.latency_ms.append((seen - sent) * 1e3)


# -- the report -----------------------------------------------------------------------------


def _print_runs(runs: list[Run], args: argparse.Namespace) -> None:
    idle = runs[0]
    print()
    print("telemetry frames: sent by the ESC process, counted by the daemon's CAN reader")
    header = (
        f"{'run':<30} {'sent':>8} {'sent/s':>7} {'observed':>8} {'counted':>8} {'dropped':>7} "
        f"{'malformed':>9} {'read errs':>9} {'all read':>8}"
    )
    print(header)
    print("-" * len(header))
    for run in runs:
        esc = run.esc
        can_in = run.can_in
        print(
            f"{run.name:<30} {esc.sent if esc else 0:>8d} "
            f"{num(esc.sent / esc.active_s if esc else None, '.0f', 7)} "
            f"{run.observed_telemetry:>8d} {num(run.counted, 'd', 8)} "
            f"{num(run.dropped, 'd', 7)} {num(can_in[2] if can_in else None, 'd', 9)} "
            f"{num(can_in[3] if can_in else None, 'd', 9)} "
            f"{num(can_in[0] if can_in else None, 'd', 8)}"
        )
    print(
        "  observed: seen by the bench's own socket; counted/malformed/read errs/all read: the "
        "daemon's 'CAN in:' line\n  at exit (all read includes the bridge's own commands, read "
        "back); dropped = sent - counted"
    )

    print()
    print(
        "where frames were lost: the daemon's reader socket (kernel counters, sampled every "
        f"{RX_SAMPLE_S * 1e3:.0f} ms) and the ESC process's pacing"
    )
    header = (
        f"{'run':<30} {'rx drops':>8} {'drop spells':>11} {'peak KiB':>8} {'ESC skipped':>11} "
        f"{'ESC gap ms':>10}  drops at (s into the run)"
    )
    print(header)
    print("-" * len(header))
    for run in runs:
        esc = run.esc
        spells = [round(t, 1) for t in run.drop_times]
        shown = " ".join(f"{t:g}" for t in spells[:8]) + (" ..." if len(spells) > 8 else "")
        if esc is not None and esc.stalls:
            stalls = [round(t - run.window_start, 1) for t in esc.stalls]
            shown += f"{'; ' if shown else ''}ESC stalls at " + " ".join(
                f"{t:g}" for t in stalls[:8]
            )
            shown += " ..." if len(stalls) > 8 else ""
        print(
            f"{run.name:<30} {num(run.reader_drops, 'd', 8)} {len(spells):>11d} "
            f"{run.reader_peak_bytes / 1024:>8.0f} {num(esc.skipped if esc else None, 'd', 11)} "
            f"{num(esc.longest_gap_s * 1e3 if esc else None, '.1f', 10)}  {shown}"
        )
    print(
        f"  rx drops: frames the kernel threw away because the reader's socket buffer was full "
        f"(the daemon asks for 4 MiB; the kernel caps it at rmem_max {_rmem_max()} B x 2),\n"
        "  commands included; drop spells: samples in "
        "which that count rose; peak: the most the socket held; ESC skipped/gap:\n  frames the "
        "ESC process left out after falling behind, and its longest pause between bursts"
    )

    print()
    print(
        f"output period error, µs: |interval between group-1 command frames - "
        f"{1e6 / OUTPUT_RATE_HZ:.0f} µs|, kernel timestamps"
    )
    header = (
        f"{'run':<30} {'frames':>7} {'rate Hz':>8} {'p50':>6} {'p90':>6} {'p99':>6} {'max':>7} "
        f"{'p99/idle':>8} {'overruns':>8} {'late p99':>8}"
    )
    print(header)
    print("-" * len(header))
    idle_p99 = percentile(idle.period_err_us, 0.99)
    for run in runs:
        err = run.period_err_us
        p99 = percentile(err, 0.99)
        summary = run.loop_summary
        print(
            f"{run.name:<30} {len(err) + 1 if err else 0:>7d} {num(run.achieved_hz, '.1f', 8)} "
            f"{num(percentile(err, 0.5), '.0f', 6)} {num(percentile(err, 0.9), '.0f', 6)} "
            f"{num(p99, '.0f', 6)} {num(max(err) if err else None, '.0f', 7)} "
            f"{num(p99 / idle_p99 if idle_p99 else None, '.2f', 8)} "
            f"{num(summary[3] if summary else None, 'd', 8)} "
            f"{num(summary[5] if summary else None, 'd', 8)}"
        )
    print(
        "  overruns and late p99 (wake-up lateness, µs): the daemon's own count at exit, over "
        "the whole run"
    )

    print()
    print("telemetry frame -> ESC_STATUS showing it (ESC 0), ms")
    header = (
        f"{'run':<30} {'markers':>7} {'seen':>5} {'p50':>6} {'p90':>6} {'p99':>6} {'max':>6} "
        f"{'ESC_STATUS/s':>12}"
    )
    print(header)
    print("-" * len(header))
    for run in runs:
        if not run.telemetry:
            continue
        lat = run.latency_ms
        print(
            f"{run.name:<30} {run.markers:>7d} {len(lat):>5d} "
            f"{num(percentile(lat, 0.5), '.1f', 6)} {num(percentile(lat, 0.9), '.1f', 6)} "
            f"{num(percentile(lat, 0.99), '.1f', 6)} {num(max(lat) if lat else None, '.1f', 6)} "
            f"{num(run.esc_status_hz_seen, '.1f', 12)}"
        )
    print("  ESC_STATUS/s: index-0 messages the autopilot received per second while measuring")

    print()
    print(f"CPU, % of one core ({os.cpu_count()} cores here)")
    header = (
        f"{'run':<30} {'main':>6} {'loop':>6} {'daemon':>6} {'bench':>6} {'others':>6} "
        f"{'machine':>7} {'main waited':>11}"
    )
    print(header)
    print("-" * len(header))
    for run in runs:
        daemon = run.cpu_main_pct + run.cpu_loop_pct
        others = run.cpu_machine_pct - daemon - run.cpu_bench_pct
        print(
            f"{run.name:<30} {num(run.cpu_main_pct, '.1f', 6)} {num(run.cpu_loop_pct, '.1f', 6)} "
            f"{num(daemon, '.1f', 6)} {num(run.cpu_bench_pct, '.1f', 6)} "
            f"{num(others, '.1f', 6)} {num(run.cpu_machine_pct, '.1f', 7)} "
            f"{num(run.main_waiting_pct, '.1f', 11)}"
        )
    print(
        "  main: the daemon's process (MAVLink, CAN reader, publishers); loop: its output-loop "
        "process;\n  bench: the ESC and autopilot processes and this one (the observer); "
        "others: the rest of the machine\n  (kernel work included); machine: all CPUs busy; main "
        "waited: time the daemon's main-process\n  threads spent runnable but waiting for a CPU "
        "(summed over threads)"
    )

    print()
    for run in runs:
        for problem in run.problems:
            print(f"!! {run.name}: {problem}")
    for run in runs[1:]:
        p99 = percentile(run.period_err_us, 0.99)
        within = p99 <= 1.10 * idle_p99
        change = 100 * (p99 / idle_p99 - 1) if idle_p99 else float("nan")
        print(
            f"verdict, {run.name}: period p99 within 10 % of idle: {'yes' if within else 'no'} "
            f"({p99:.0f} µs vs {idle_p99:.0f} µs idle, {change:+.0f} %)"
        )
        dropped = run.dropped
        print(
            f"verdict, {run.name}: dropped == 0: {'yes' if dropped == 0 else 'no'} "
            f"({'?' if dropped is None else dropped} of {run.esc.sent if run.esc else 0} sent)"
        )


def _rmem_max() -> str:
    try:
        return Path("/proc/sys/net/core/rmem_max").read_text().strip()
    except OSError:
        return "?"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="measured time per run")
    parser.add_argument("--warmup", type=float, default=2.0, help="time before measuring")
    parser.add_argument("--escs", type=int, default=8, help="ESCs (nodes 1..N, 12b channels)")
    parser.add_argument(
        "--fps", type=float, default=SATURATED_FPS, help="telemetry frames per second in all"
    )
    parser.add_argument("--no-zenoh", action="store_true", help="run the daemon without Zenoh")
    parser.add_argument("--seed", type=int, default=1, help="seed of the marker times")
    args = parser.parse_args()
    if not 1 <= args.escs <= 20:
        parser.error("--escs: 1..20 (CKESC 12b channels)")
    signal.signal(signal.SIGTERM, raise_interrupt)
    print(
        f"ESC telemetry under load: {args.escs} ESCs, CKESC 12b at {OUTPUT_RATE_HZ} Hz (fixed), "
        f"SERVO_OUTPUT_RAW at {INPUT_RATE_HZ} Hz, Zenoh {'off' if args.no_zenoh else 'on'}"
    )
    print(
        f"saturated: {args.fps:.0f} telemetry frames/s (MSG1/MSG2/MSG3/MSG_EXP1 from nodes "
        f"1..{args.escs}, bursts every {BURST_PERIOD_S * 1e3:.0f} ms); "
        f"{args.seconds:.0f} s measured per run after {args.warmup:.0f} s",
        flush=True,
    )
    cases = [
        Run("idle (no telemetry)", telemetry=False, esc_status_hz=10.0),
        Run("saturated, ESC_STATUS 10 Hz", telemetry=True, esc_status_hz=10.0),
        Run("saturated, ESC_STATUS 50 Hz", telemetry=True, esc_status_hz=50.0),
    ]
    try:
        for run in cases:
            print(f"  running: {run.name} ...", flush=True)
            run_case(
                run,
                args.escs,
                args.seconds,
                args.warmup,
                args.fps,
                not args.no_zenoh,
                args.seed,
            )
    except KeyboardInterrupt:
        print("interrupted; every process this bench started has been stopped", file=sys.stderr)
        return 130
    except RuntimeError as exc:
        print(f"bench/telemetry.py: {exc}", file=sys.stderr)
        return 1
    _print_runs(cases, args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
