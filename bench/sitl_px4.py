"""The bridge against a real PX4 SITL: the measurements of tests/sitl/test_px4.py over several
flights, and what PX4 offers a companion for learning of arming early.

Run: ``python bench/sitl_px4.py [--flights 3] [--heartbeat] [--json FILE]``

- ``--flights N`` runs the test module's flight N times (``pytest tests/sitl/test_px4.py``, each
  a PX4 start, two bridges, simulated ESCs; ~50 s each) and prints each measurement's median and
  range over the flights;
- ``--stall-recovery S`` hovers with one bridge (actuator_output_status, CKESC), stops PX4
  for S seconds (SIGSTOP/SIGCONT) and prints how long after SIGCONT the bridge sends non-zero
  commands again (it waits ``--recovery-wait`` seconds, 90 by default);
- ``--heartbeat`` starts PX4 alone and, on its onboard link (where a companion listens), asks
  for HEARTBEAT (message 0) with MAV_CMD_SET_MESSAGE_INTERVAL at several rates, printing the
  COMMAND_ACK result and the rate that then arrives; then it arms and disarms PX4 from a
  ground station a few times and prints, per arming, how long after PX4's motor outputs armed
  (ACTUATOR_OUTPUT_STATUS at ~120 Hz on the same link) the first armed HEARTBEAT, and the first
  SYS_STATUS / EXTENDED_SYS_STATE, arrived.

Needs the PX4 build the tests use (``$ESC_BRIDGE_PX4`` or ``../shared/sitl/px4/...``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
# tests/ holds the top-level conftest and the sitl package (tests/sitl) the harness lives in.
sys.path[:0] = [str(ROOT / "tests")]

from _stats import percentile  # noqa: E402
from conftest import Observer, free_port  # noqa: E402
from sitl._px4 import (  # noqa: E402
    GroundStation,
    UdpTap,
    extract_build,
    find_build,
    px4_instance,
    start_bridge,
    start_sim_escs,
    wait_until,
    write_bridge_config,
)

from bridge.errors import CodecError  # noqa: E402
from bridge.escs import ckesc  # noqa: E402


def run_flights(count: int) -> list[dict[str, Any]]:
    reports: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        target = Path(tmp) / "report.jsonl"
        for i in range(count):
            started = time.monotonic()
            result = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "pytest",
                    "-q",
                    "-p",
                    "no:cacheprovider",
                    str(ROOT / "tests" / "sitl" / "test_px4.py"),
                ],
                cwd=ROOT,
                env={**os.environ, "ESC_BRIDGE_SITL_REPORT": str(target)},
                capture_output=True,
                text=True,
                check=False,
            )
            lines = result.stdout.strip().splitlines()
            summary = lines[-1] if lines else result.stderr.strip()[-300:]
            print(f"flight {i + 1}: {time.monotonic() - started:.0f} s, {summary}", flush=True)
            for line in lines:
                if line.startswith(("FAILED", "ERROR", "XPASS")):
                    print(f"  {line[:300]}", flush=True)
        if target.exists():
            reports = [json.loads(line) for line in target.read_text().splitlines()]
    return reports


def print_flights(reports: list[dict[str, Any]]) -> None:
    keys = [k for k in reports[0] if isinstance(reports[0][k], int | float)] if reports else []
    print(f"\n{'measurement':<72} {'median':>9} {'min':>9} {'max':>9}  (n={len(reports)})")
    for key in keys:
        values = [float(r[key]) for r in reports if isinstance(r.get(key), int | float)]
        print(
            f"{key:<72} {statistics.median(values):>9.1f} {min(values):>9.1f} {max(values):>9.1f}"
        )


def _msgs(tap: UdpTap, kind: str, sysid: int, after: float) -> list[tuple[float, Any]]:
    return [
        (t, m)
        for t, m in tap.poll()
        if t >= after
        and m.get_type() == kind
        and (m.get_srcSystem(), m.get_srcComponent()) == (sysid, 1)
    ]


def heartbeat_study(arms: int) -> None:
    build, why = find_build()
    if build is None:
        sys.exit(why)
    with tempfile.TemporaryDirectory() as tmp:
        root = extract_build(build, Path(tmp) / "build")
        with px4_instance(root, Path(tmp)) as (px4, claim):
            ports = claim.ports
            # The tap is the companion here: it answers nothing itself, so requests go through
            # a socket of ours that sends to PX4 via the tap's downstream side.
            companion_port = free_port()
            tap = UdpTap(ports.onboard_remote, companion_port, Path(tmp) / "tap.bin")
            companion = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            companion.bind(("127.0.0.1", companion_port))
            companion.settimeout(0.0)
            gcs: GroundStation | None = None
            try:
                px4.start()
                px4.wait_ready()
                gcs = GroundStation(f"udpout:127.0.0.1:{ports.gcs_local}")
                sysid = px4.system_id
                mav = gcs.mav  # the GCS's encoder packs our requests (its ids do not matter)
                tap_addr: tuple[str, int] | None = None
                wait_until(lambda: bool(_msgs(tap, "HEARTBEAT", sysid, 0)), 10, "HEARTBEAT")

                def request(msg_id: int, interval_us: float) -> int | None:
                    nonlocal tap_addr
                    # Learn the tap's downstream address from what it forwards to us.
                    deadline = time.monotonic() + 2
                    while tap_addr is None and time.monotonic() < deadline:
                        try:
                            _, tap_addr = companion.recvfrom(65536)
                        except BlockingIOError:
                            time.sleep(0.01)
                    assert tap_addr is not None
                    sent = time.monotonic()
                    frame = mav.command_long_encode(
                        sysid, 1, 511, 0, float(msg_id), interval_us, 0, 0, 0, 0, 0
                    ).pack(mav)
                    companion.sendto(frame, tap_addr)
                    while time.monotonic() < sent + 1.0:
                        for _, ack in _msgs(tap, "COMMAND_ACK", sysid, sent):
                            if ack.command == 511:
                                return int(ack.result)
                        time.sleep(0.01)
                    return None

                def drain() -> None:
                    while True:
                        try:
                            companion.recvfrom(65536)
                        except BlockingIOError:
                            return

                request(375, 5000)  # ACTUATOR_OUTPUT_STATUS at 200 Hz, to time arming by it
                print("\nHEARTBEAT (id 0) on PX4's onboard link, asked with SET_MESSAGE_INTERVAL")
                print(f"{'asked':>12} {'ACK result':>12} {'arriving Hz':>12}")
                for hz in (1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0):
                    result = request(0, 1e6 / hz)
                    time.sleep(1.0)
                    start = time.monotonic()
                    time.sleep(3.0)
                    drain()
                    beats = _msgs(tap, "HEARTBEAT", sysid, start)
                    got = len(beats) / 3.0
                    print(f"{hz:>10.0f}Hz {result!s:>12} {got:>12.1f}")
                request(0, 1e6)  # back to PX4's own 1 Hz
                print("\narming seen on the onboard link, ms after PX4's outputs armed")
                print(f"{'arming':>6} {'HEARTBEAT':>10}")
                heartbeat_lags: list[float] = []
                for n in range(arms):
                    drain()
                    t0 = time.monotonic()
                    gcs.command((sysid, 1), 400, [1], 20, "arm")
                    time.sleep(1.5)
                    gcs.command((sysid, 1), 400, [0], 10, "disarm")
                    time.sleep(0.5)
                    drain()
                    outputs = [
                        t
                        for t, m in _msgs(tap, "ACTUATOR_OUTPUT_STATUS", sysid, t0)
                        if max(m.actuator[:4]) >= 1000
                    ]
                    beat = next(
                        (t for t, m in _msgs(tap, "HEARTBEAT", sysid, t0) if m.base_mode & 128),
                        math.nan,
                    )
                    first = outputs[0] if outputs else math.nan
                    heartbeat_lags.append((beat - first) * 1000)
                    print(f"{n + 1:>6} {(beat - first) * 1000:>10.0f}")
                good = [x for x in heartbeat_lags if not math.isnan(x)]
                print(
                    f"HEARTBEAT after outputs armed: median {statistics.median(good):.0f} ms, "
                    f"max {percentile(good, 1.0):.0f} ms"
                    if good
                    else "no armed HEARTBEAT seen"
                )
            finally:
                if gcs is not None:
                    gcs.close()
                companion.close()
                tap.close()


def _spinning(msg: Any) -> bool:
    """A CKESC throttle frame with a motor not at 0."""
    try:
        frame = ckesc.decode(msg)
    except CodecError:
        return False
    return (
        frame is not None
        and isinstance(frame.message, ckesc.RawCommand12b)
        and any(frame.message.throttles)
    )


def stall_recovery(stall_s: float, wait_s: float) -> None:
    """One bridge (actuator_output_status, CKESC) in a hover: stop PX4 for ``stall_s``, then
    time how long after SIGCONT the bridge sends non-zero commands again (at most ``wait_s``)."""
    build, why = find_build()
    if build is None:
        sys.exit(why)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        root = extract_build(build, work / "build")
        with px4_instance(root, work) as (px4, claim):
            ports = claim.ports
            can_port, bridge_port = free_port(), free_port()
            observer = Observer(can_port)
            tap = UdpTap(ports.onboard_remote, bridge_port, work / "tap.bin")
            sim = start_sim_escs(can_port, work / "sim.log")
            config = write_bridge_config(
                work / "bridge.toml",
                source="actuator_output_status",
                autopilot_system_id=px4.system_id,
                component_id=191,
            )
            bridge = start_bridge(
                config,
                f"udpin:127.0.0.1:{bridge_port}",
                can_port,
                work / "bridge.log",
                "--no-zenoh",
            )
            gcs: GroundStation | None = None
            try:
                wait_until(lambda: "listening" in bridge.output(), 30, "the bridge listening")
                px4.start()
                px4.wait_ready()
                gcs = GroundStation(f"udpout:127.0.0.1:{ports.gcs_local}")
                target = (px4.system_id, 1)
                time.sleep(2.0)
                gcs.command(target, 400, [1], 20, "arm")
                nan_position = [0.0, 0.0, 0.0, math.nan, math.nan, math.nan, math.nan]
                gcs.command(target, 22, nan_position, 10, "takeoff")
                time.sleep(10.0)
                px4.pause()
                time.sleep(stall_s)
                px4.resume()
                resumed = time.monotonic()
                running, _ = observer.wait_for(_spinning, wait_s, after=resumed)
                print(
                    f"stall {stall_s:.1f} s: the bridge ran the motors again "
                    f"{running - resumed:.1f} s after SIGCONT",
                    flush=True,
                )
            except AssertionError as exc:
                print(f"stall {stall_s:.1f} s: not running again: {exc}", flush=True)
            finally:
                if gcs is not None:
                    gcs.close()
                px4.stop()
                bridge.stop()
                sim.stop()
                tap.close()
                observer.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--flights", type=int, default=0)
    parser.add_argument("--heartbeat", action="store_true")
    parser.add_argument("--arms", type=int, default=5)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--stall-recovery", type=float, metavar="SECONDS", default=0.0)
    parser.add_argument("--recovery-wait", type=float, default=90.0)
    args = parser.parse_args()
    if args.stall_recovery:
        stall_recovery(args.stall_recovery, args.recovery_wait)
    if args.heartbeat:
        heartbeat_study(args.arms)
    if args.flights:
        reports = run_flights(args.flights)
        print_flights(reports)
        if args.json:
            args.json.write_text(json.dumps(reports, indent=1))


if __name__ == "__main__":
    main()
