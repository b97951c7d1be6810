"""The output loop under load, against a plain pymavlink + python-can loop.

Run: ``python bench/loop.py [--seconds 30] [--warmup 2] [--modes fixed immediate baseline]
[--bridge-source DIR]``

For each case (rate 400/1000 Hz x 8/20 ESCs) the daemon runs through its CLI (`esc-bridge run`,
loop in its own process, CKESC 12b on a udp_multicast bus on this machine) in fixed-rate and in
immediate mode, with MAVLink SERVO_OUTPUT_RAW arriving at 400 Hz from an autopilot process and
CKESC telemetry (MSG1/2/3 at 50/10/2 Hz per ESC) from an ESC process. The same workload then runs
through the baseline: one loop that drains pymavlink, encodes and sends, then ``time.sleep``
(period).

Frames are timed by the kernel (SO_TIMESTAMPNS on the observer's socket; on loopback the
receive path runs inside the sender's send call, so this is the send time to within µs):
- rate: group-1 frames per second against the nominal rate;
- period error: |interval between consecutive group-1 frames - period|, µs;
- latency: from the autopilot's send of a SERVO_OUTPUT_RAW to the first frame carrying it;
- CPU: user + system time of the daemon's processes (main and loop) over the run, % of a core,
  and of the loop process alone.

``--bridge-source`` runs the daemon from another checkout (``git worktree add /tmp/before
<commit>``) with this bench, so a change is compared with the code before it on the same
machine in the same hour: alternate the two, a few runs each, and compare medians.
"""

from __future__ import annotations

import argparse
import itertools
import multiprocessing
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
from _common import GROUP, bridge_command, children, cpu_seconds, free_port
from _stats import percentile

from bridge.escs import uavcan_v0
from bridge.escs.ckesc import codec, records

INPUT_RATE_HZ = 400
TELEMETRY_HZ = (50, 10, 2)  # MSG1, MSG2, MSG3 per ESC


def _bus(port: int) -> can.BusABC:
    return can.Bus(interface="udp_multicast", channel=GROUP, port=port, hop_limit=0)


def _sleep_until(deadline: float) -> None:
    delay = deadline - time.monotonic()
    if delay > 0:
        time.sleep(delay)


def autopilot_worker(port: int, n_channels: int, seconds: float, out: Any) -> None:
    """Armed HEARTBEAT at 10 Hz and SERVO_OUTPUT_RAW at 400 Hz; channel 1 changes every send."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{port}", source_system=1, source_component=1
    )
    mav = conn.mav
    armed = mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    sends: list[tuple[int, float]] = []
    period = 1.0 / INPUT_RATE_HZ
    start = time.monotonic()
    k = 0
    while (now := time.monotonic()) - start < seconds:
        if k % (INPUT_RATE_HZ // 10) == 0:
            mav.heartbeat_send(2, 3, armed, 0, 4)
        pwm = [1000 + (k % 1000)] + [1500] * 31  # throttle on channel 1 = 2 x (k mod 1000)
        ext = {f"servo{i}_raw": pwm[i - 1] for i in range(9, 17)}
        time_us = time.monotonic_ns() // 1000 & 0xFFFFFFFF  # the autopilot's clock, as ArduPilot
        # Stamped before the send: a real-time bridge can run, and send the frame, between this
        # process's sendto and its next line.
        sends.append((2 * (k % 1000), time.time()))
        mav.servo_output_raw_send(time_us, 0, *pwm[:8], **ext)
        if n_channels > 16:
            ext = {f"servo{i}_raw": pwm[i + 15] for i in range(9, 17)}
            mav.servo_output_raw_send(time_us, 1, *pwm[16:24], **ext)
        k += 1
        _sleep_until(start + k * period)
        del now
    conn.close()
    out.put(sends)


def telemetry_worker(port: int, n_escs: int, seconds: float) -> None:
    """CKESC telemetry from every ESC at its factory rates, spread over time."""
    bus = _bus(port)
    frames: list[tuple[float, can.Message]] = []  # (period s, frame) for every periodic frame
    messages: tuple[records.CkescMessage, ...] = (
        records.Msg1(speed_rpm=5000, throttle=1000, status=records.Msg1Status.RUNNING),
        records.Msg2(voltage_v=24.0, current_a=5.0, mos_temp_c=40),
        records.Msg3(mos_temp_c=40, capacitor_temp_c=35, motor_temp_c=50, mcu_temp_c=45),
    )
    for node in range(1, n_escs + 1):
        for hz, message in zip(TELEMETRY_HZ, messages, strict=True):
            frame = codec.CkescFrame(uavcan_v0.PRIORITY_LOWEST, node, None, 0, message)
            frames.append((1.0 / hz, codec.encode(frame)))
    start = time.monotonic()
    due = [start + i * 0.0003 for i in range(len(frames))]
    while time.monotonic() - start < seconds:
        i = min(range(len(due)), key=due.__getitem__)
        _sleep_until(due[i])
        bus.send(frames[i][1])
        due[i] += frames[i][0]
    bus.shutdown()


def baseline_worker(
    mavlink_port: int, can_port: int, rate_hz: int, n_escs: int, seconds: float
) -> None:
    """The plain loop: drain MAVLink, encode the throttle groups, send, sleep one period."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{mavlink_port}")
    bus = _bus(can_port)
    throttles = [0] * 20
    groups = range(1, (n_escs + 3) // 4 + 1)
    period = 1.0 / rate_hz
    tid = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        while (msg := conn.recv_match(type="SERVO_OUTPUT_RAW", blocking=False)) is not None:
            first = 16 * msg.port
            for i in range(16):
                if first + i < n_escs:
                    pwm = getattr(msg, f"servo{i + 1}_raw")
                    throttles[first + i] = min(max(2 * (pwm - 1000), 0), 2000)
        for group in groups:
            bus.send(codec.encode_raw_12b(group, throttles[4 * group - 4 : 4 * group], tid))
            tid = (tid + 1) & 31
        time.sleep(period)
    bus.shutdown()
    conn.close()


@dataclass
class Result:
    name: str
    rate_hz: int
    achieved_hz: float
    period_err_us: list[float]
    latency_us: list[float]
    cpu_pct: float
    loop_cpu_pct: float  # the daemon's loop process alone (its children); the baseline: 0
    seen_pct: float  # inputs that reached the bus: a run that ignored its input is no result


def _daemon_config(path: Path, rate_hz: int, n_escs: int, latency: str) -> Path:
    mixer = path / f"passthrough-{n_escs}.toml"
    outputs = "".join(
        f'\n[[outputs]]\nname = "m{i}"\nsource = "ch{i}"\n' for i in range(1, n_escs + 1)
    )
    mixer.write_text(f'[info]\ndescription = "bench passthrough"\n{outputs}')
    config = path / f"bench-{rate_hz}-{n_escs}-{latency}.toml"
    config.write_text(
        f'[mavlink]\nstream_rate_hz = 0\n[mixer]\nname = "{mixer}"\n'
        f'[output]\nrate_hz = {rate_hz}\nlatency = "{latency}"\n'
        # A CPU and timing stress test: the virtual bus has no bit rate to saturate.
        "bus_load_ceiling = 1.0\n[can]\nbitrate = 1000000\n"
    )
    return config


def _daemon_command(source: Path | None) -> tuple[list[str], dict[str, str] | None]:
    """How to start ``esc-bridge``: installed, or from the source tree ``source`` (another
    commit's checkout, for a before/after comparison on the same machine and hour)."""
    if source is None:
        return [], None
    main = "import sys; from bridge.cli import main; sys.exit(main())"
    return [sys.executable, "-c", main], {**os.environ, "PYTHONPATH": str(source)}


def run_case(
    name: str,
    rate_hz: int,
    n_escs: int,
    seconds: float,
    warmup: float,
    latency: str | None,
    source: Path | None = None,
) -> Result | str:
    """The measurements of one case, or why the daemon refused to run it."""
    ctx = multiprocessing.get_context("spawn")
    mavlink_port, can_port = free_port(), free_port()
    observer = _bus(can_port)
    with tempfile.TemporaryDirectory() as tmp:
        if latency is None:
            target = ctx.Process(
                target=baseline_worker,
                args=(mavlink_port, can_port, rate_hz, n_escs, seconds + warmup + 1),
            )
            target.start()
            pid: int = target.pid or 0
        else:
            config = _daemon_config(Path(tmp), rate_hz, n_escs, latency)
            command = [*bridge_command(mavlink_port, can_port, "warning"), "--config", str(config)]
            prefix, env = _daemon_command(source)
            if prefix:
                command[:1] = prefix
            proc = subprocess.Popen(command, env=env)
            pid = proc.pid
        time.sleep(1.5)  # the daemon spawns its loop process
        if latency is not None and proc.poll() is not None:
            observer.shutdown()
            return "refused by the daemon's bus-load check (see its message above)"
        sends_q = ctx.Queue()
        pilot = ctx.Process(
            target=autopilot_worker, args=(mavlink_port, n_escs, seconds + warmup, sends_q)
        )
        esc = ctx.Process(target=telemetry_worker, args=(can_port, n_escs, seconds + warmup))
        pilot.start()
        esc.start()
        frames: list[tuple[float, int]] = []  # kernel time, channel-1 throttle of group-1 frames
        start = time.monotonic()
        cpu_start = loop_cpu_start = 0.0
        pids = kids = [pid]
        while (elapsed := time.monotonic() - start) < seconds + warmup:
            if cpu_start == 0.0 and elapsed >= warmup:
                kids = children(pid) if latency is not None else []
                pids = [pid, *kids]
                cpu_start, loop_cpu_start = cpu_seconds(pids), cpu_seconds(kids)
                cpu_t0 = time.monotonic()
            msg = observer.recv(0.1)
            # Every 12b group has the same CAN ID; the group number is byte 6.
            if msg is None or msg.arbitration_id != 0x004E8500 or msg.data[6] != 1:
                continue
            if elapsed < warmup:
                continue
            frames.append((msg.timestamp, (msg.data[0] | (msg.data[1] & 0x0F) << 8)))
        cpu_s = time.monotonic() - cpu_t0
        cpu_pct = 100 * (cpu_seconds(pids) - cpu_start) / cpu_s
        loop_cpu_pct = 100 * (cpu_seconds(kids) - loop_cpu_start) / cpu_s
        sends: list[tuple[int, float]] = sends_q.get(timeout=30)
        pilot.join()
        esc.join()
        if latency is None:
            target.join()
        else:
            proc.terminate()
            proc.wait(10)
    observer.shutdown()

    period = 1.0 / rate_hz
    intervals = [b[0] - a[0] for a, b in itertools.pairwise(frames)]
    achieved = (len(frames) - 1) / (frames[-1][0] - frames[0][0])
    errors = [abs(dt - period) * 1e6 for dt in intervals] if latency != "immediate" else []
    measured_sends = [s for s in sends if frames[0][0] <= s[1] <= frames[-1][0] - 0.01]
    latencies = _latencies(measured_sends, frames)
    seen_pct = 100 * len(latencies) / max(1, len(measured_sends))
    return Result(name, rate_hz, achieved, errors, latencies, cpu_pct, loop_cpu_pct, seen_pct)


def _latencies(sends: list[tuple[int, float]], frames: list[tuple[float, int]]) -> list[float]:
    """Send -> first frame carrying that value, for each send seen on the bus."""
    out = []
    i = 0
    for value, sent in sends:
        while i < len(frames) and frames[i][0] < sent:
            i += 1
        for ts, seen in frames[i : i + 200]:
            if seen == value:
                out.append((ts - sent) * 1e6)
                break
    return out


MODES = {"fixed": "fixed", "immediate": "immediate", "baseline": None}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="measured time per case")
    parser.add_argument("--warmup", type=float, default=2.0, help="time discarded at the start")
    parser.add_argument("--rates", type=int, nargs="+", default=[400, 1000], help="loop rates, Hz")
    parser.add_argument("--escs", type=int, nargs="+", default=[8, 20], help="ESC counts")
    parser.add_argument(
        "--modes", nargs="+", choices=list(MODES), default=list(MODES), help="what to run"
    )
    parser.add_argument(
        "--bridge-source",
        type=Path,
        metavar="DIR",
        help="run the daemon from this source tree (e.g. a `git worktree` of another commit) "
        "instead of the installed package",
    )
    args = parser.parse_args()
    header = (
        f"{'case':<34} {'rate Hz':>8} {'dev %':>7} {'err p50':>8} {'err p99':>8} {'err max':>8} "
        f"{'lat p50':>8} {'lat p99':>8} {'CPU %':>6} {'loop %':>6} {'seen %':>6}"
    )
    print(f"output loop, {args.seconds:.0f} s per case, input 400 Hz, CKESC telemetry arriving")
    print(
        "period error and latency in µs; CPU in % of one core (daemon: main + loop process; "
        "loop: the loop process alone)"
    )
    if args.bridge_source:
        print(f"daemon from {args.bridge_source}")
    print(header)
    print("-" * len(header))
    for rate_hz in args.rates:
        for n_escs in args.escs:
            rows: dict[str, Result] = {}
            for mode in args.modes:
                latency = MODES[mode]
                label = f"{'daemon ' + latency if latency else 'baseline sleep(period)'}"
                result = run_case(
                    label, rate_hz, n_escs, args.seconds, args.warmup, latency, args.bridge_source
                )
                if isinstance(result, str):
                    print(f"{f'{rate_hz} Hz x{n_escs} {label}':<34} {result}", flush=True)
                    continue
                rows[mode] = result
                err = result.period_err_us
                print(
                    f"{f'{rate_hz} Hz x{n_escs} {label}':<34} {result.achieved_hz:>8.1f} "
                    f"{100 * (result.achieved_hz / rate_hz - 1):>+7.2f} "
                    f"{percentile(err, 0.5):>8.0f} {percentile(err, 0.99):>8.0f} "
                    f"{max(err) if err else float('nan'):>8.0f} "
                    f"{statistics.median(result.latency_us):>8.0f} "
                    f"{percentile(result.latency_us, 0.99):>8.0f} {result.cpu_pct:>6.1f} "
                    f"{result.loop_cpu_pct:>6.1f} {result.seen_pct:>6.1f}",
                    flush=True,
                )
            fixed, immediate, base = (rows.get(mode) for mode in MODES)
            if fixed is None or base is None:
                continue

            def p99_ratio(ours: list[float], theirs: list[float]) -> str:
                return f"{percentile(ours, 0.99) / percentile(theirs, 0.99):>8.2f}"

            latency_ratio = (
                p99_ratio(immediate.latency_us, base.latency_us) if immediate else f"{'-':>8}"
            )
            print(
                f"{'  ratios daemon/baseline':<34} {'':>8} {'':>7} {'':>8} "
                f"{p99_ratio(fixed.period_err_us, base.period_err_us)} "
                f"{'':>8} {'':>8} {latency_ratio} {fixed.cpu_pct / base.cpu_pct:>6.2f}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
