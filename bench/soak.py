"""The bridge's memory and file descriptors over a long run: do they stay flat?

Run: ``python bench/soak.py [--duration 3600] [--interval 60] [--bridge-source DIR]``

The bridge runs through its CLI (``esc-bridge run``: CKESC 12b x8 at 400 Hz, fixed latency, a
udp_multicast bus of this machine) as on a vehicle, with everything on:
- the autopilot of ``bench/cpu.py`` (SERVO_OUTPUT_RAW at 200 Hz, a new value each send, HEARTBEAT
  armed at 10 Hz), so the motors run the whole time;
- eight simulated ESCs (``esc-bridge sim``) answering with their telemetry;
- Zenoh on loopback, with a subscriber on every key;
- a ground-station output (``[mavlink] outputs``) that a socket here reads, and sends a
  HEARTBEAT a second to.

Every ``--interval`` seconds (and at 10, 30 s): the resident memory (VmRSS) and the open file
descriptors of the main process and of the loop process, and their CPU over the interval. At
the end: the growth of each from the first minute's sample to the last, and per hour after
that.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import suppress
from pathlib import Path
from typing import Any

from _common import (
    bridge_command,
    cpu_seconds,
    free_port,
    holds_bus,
    processes,
    raise_interrupt,
    sleep_watching,
    wait_for,
)
from cpu import CASES, Case, bridge_prefix, loop_processes, pilot_worker, simulated_escs

from bridge.mavlink import load_dialect

START_TIMEOUT_S = 120.0  # a loaded machine takes that long to spawn and import the loop
START_ATTEMPTS = 5  # the bridge gives up on a loop that does not start in 15 s: start again


def rss_kib(pid: int) -> int | None:
    """The resident memory of ``pid``, KiB (None once it is gone)."""
    with suppress(OSError):
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return None


def open_fds(pid: int) -> int | None:
    with suppress(OSError):
        return len(os.listdir(f"/proc/{pid}/fd"))
    return None


def ground_station(port: int, stop: threading.Event, counts: dict[str, int]) -> None:
    """Read what the bridge sends to its output; a GCS HEARTBEAT a second back to it."""
    dialect = load_dialect()
    mav = dialect.MAVLink(None, srcSystem=255, srcComponent=190)
    heartbeat = mav.heartbeat_encode(6, 8, 0, 0, 4).pack(mav)  # a GCS, no autopilot
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    sock.settimeout(0.2)
    peer = None
    next_beat = time.monotonic()
    while not stop.is_set():
        try:
            data, peer = sock.recvfrom(65536)
            counts["bytes"] += len(data)
        except TimeoutError:
            pass
        if peer is not None and time.monotonic() >= next_beat:
            sock.sendto(heartbeat, peer)
            next_beat += 1.0
    sock.close()


def zenoh_subscriber(port: int, counts: dict[str, int]) -> Any:
    """A Zenoh session on the bridge's listening port subscribing to everything it publishes
    (None when zenoh will not open one)."""
    try:
        import zenoh

        config = zenoh.Config()
        config.insert_json5("mode", '"peer"')
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
        session = zenoh.open(config)

        def on_sample(_sample: Any) -> None:
            counts["samples"] += 1

        session.declare_subscriber("esc-bridge/**", on_sample)
        return session
    except Exception as exc:  # noqa: BLE001 - the soak runs on without a subscriber
        print(f"!! no Zenoh subscriber: {exc}", flush=True)
        return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=3600.0, help="seconds (default 1 h)")
    parser.add_argument("--interval", type=float, default=60.0, help="seconds between samples")
    parser.add_argument("--bridge-source", type=Path, metavar="DIR", help="run that checkout")
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, raise_interrupt)
    ctx = multiprocessing.get_context("spawn")
    case = Case("ckesc", **CASES["ckesc"], telemetry=True, load="idle")
    can_port, mavlink_port, gcs_port, zenoh_port = (free_port() for _ in range(4))
    print(
        f"bench/soak.py: {args.duration:g} s, {case.label}; Zenoh subscriber, ground-station "
        f"output; load average {os.getloadavg()[0]:.1f}",
        flush=True,
    )
    counts = {"bytes": 0, "samples": 0}
    stop_gcs = threading.Event()
    gcs = threading.Thread(target=ground_station, args=(gcs_port, stop_gcs, counts))
    gcs.start()
    session = None
    try:
        with (
            tempfile.TemporaryDirectory() as tmp_name,
            processes(daemon_timeout_s=15) as procs,
            simulated_escs(case, can_port),
        ):
            tmp = Path(tmp_name)
            config = tmp / "soak.toml"
            config.write_text(
                f'[mavlink]\nstream_rate_hz = 0\nautopilot_heartbeat_hz = 0\noutputs = ["udpout:'
                f'127.0.0.1:{gcs_port}"]\n[mixer]\nname = "passthrough-8"\n'
                '[output]\nprotocol = "ckesc"\nrate_hz = 400\n[can]\nbitrate = 1000000\n'
                "[zenoh]\nmulticast_scouting = false\n"
                f'listen = ["tcp/127.0.0.1:{zenoh_port}"]\n'
            )
            prefix, env = bridge_prefix(args.bridge_source)
            command = bridge_command(mavlink_port, can_port, "info")
            # At nice -10 where allowed: on a machine loaded by others the loop process must
            # still start within the 15 s the bridge gives it (memory does not care).
            command[:1] = (["nice", "-n", "-10"] if os.geteuid() == 0 else []) + prefix
            command += ["--config", str(config)]
            log_path = tmp / "bridge.log"
            for attempt in range(1, START_ATTEMPTS + 1):
                with log_path.open("wb") as log_file:
                    daemon = subprocess.Popen(
                        command,
                        stdout=log_file,
                        stderr=subprocess.STDOUT,
                        env=env,
                        cwd=args.bridge_source,
                    )
                procs.daemon = daemon
                try:
                    wait_for(
                        lambda d=daemon: holds_bus(d.pid, can_port) and loop_processes(d.pid),
                        START_TIMEOUT_S,
                        "before the bridge opened its bus",
                        daemon,
                        log_path,
                    )
                    break
                except RuntimeError as exc:
                    if attempt == START_ATTEMPTS:
                        raise
                    print(f"!! start {attempt}: {str(exc).splitlines()[-1]}", flush=True)
                    procs.stop_all()
            loop = loop_processes(daemon.pid)[0]
            stop_pilot, pilot_ready = ctx.Event(), ctx.Event()
            pilot_q = ctx.Queue()
            pilot = ctx.Process(
                target=pilot_worker, args=(mavlink_port, stop_pilot, pilot_ready, pilot_q)
            )
            pilot.start()
            procs.add_worker(pilot, stop_pilot)
            session = zenoh_subscriber(zenoh_port, counts)
            header = (
                f"{'t s':>6} {'main RSS MiB':>12} {'fds':>4} {'CPU %':>6} "
                f"{'loop RSS MiB':>12} {'fds':>4} {'CPU %':>6} {'GCS kB':>7} {'Zenoh':>7}"
            )
            print(header + "\n" + "-" * len(header), flush=True)
            start = time.monotonic()
            due = [10.0, 30.0] + [args.interval * k for k in range(1, 10_000)]
            due = sorted({t for t in due if t <= args.duration} | {args.duration})
            series: list[tuple[float, int, int]] = []  # (t, main RSS, loop RSS)
            last = (start, cpu_seconds([daemon.pid]), cpu_seconds([loop]))
            for t in due:
                sleep_watching(max(0.0, start + t - time.monotonic()), daemon, log_path)
                now = (time.monotonic(), cpu_seconds([daemon.pid]), cpu_seconds([loop]))
                span = now[0] - last[0]
                main_cpu, loop_cpu = (100 * (now[i] - last[i]) / span for i in (1, 2))
                last = now
                main_rss, loop_rss = rss_kib(daemon.pid) or 0, rss_kib(loop) or 0
                series.append((t, main_rss, loop_rss))
                print(
                    f"{t:>6.0f} {main_rss / 1024:>12.2f} {open_fds(daemon.pid):>4} "
                    f"{main_cpu:>6.1f} {loop_rss / 1024:>12.2f} {open_fds(loop):>4} "
                    f"{loop_cpu:>6.1f} {counts['bytes'] / 1000:>7.0f} {counts['samples']:>7}",
                    flush=True,
                )
            stop_pilot.set()
            pilot_q.get(timeout=30)
            summarise(series)
    except KeyboardInterrupt:
        print("interrupted; every process this bench started has been stopped", file=sys.stderr)
        return 130
    finally:
        stop_gcs.set()
        gcs.join()
        if session is not None:
            session.close()
    return 0


def summarise(series: list[tuple[float, int, int]]) -> None:
    """Growth from the first sample at or after a minute to the last, and per hour."""
    after = [s for s in series if s[0] >= 60.0]
    if len(after) < 2:
        print("(too short to say: samples after the first minute are compared)")
        return
    (t0, main0, loop0), (t1, main1, loop1) = after[0], after[-1]
    hours = (t1 - t0) / 3600
    for name, first, final in (("main", main0, main1), ("loop", loop0, loop1)):
        growth = (final - first) / 1024
        peak = max(s[1 if name == "main" else 2] for s in after) / 1024
        print(
            f"{name}: {first / 1024:.2f} MiB at {t0:.0f} s, {final / 1024:.2f} MiB at {t1:.0f} s "
            f"(peak {peak:.2f}): {growth:+.2f} MiB, {growth / hours:+.2f} MiB/h",
            flush=True,
        )


if __name__ == "__main__":
    raise SystemExit(main())
