"""The service's start, restart and stop times under systemd itself, on the bus.

Run: ``python bench/service.py [--cycles 5]``

Boots systemd 252 in User-Mode Linux with esc-bridge installed as docs/service.md says
(``tests/linux/kernel.py``: ``boot_systemd``; the configuration is ``tests/linux/service.py``'s:
config/quad-ckesc.toml with the autopilot on UDP, 100 Hz), an autopilot streaming armed
outputs and ``candump`` on can0, then ``--cycles`` times: ``systemctl kill --kill-whom=main -s
KILL esc-bridge`` (to the first safe frame, and until the autopilot's outputs are back on the
bus), ``systemctl stop`` (to the first safe frame, and until the command returns), ``systemctl
start`` (to the first frame, and to the autopilot's outputs). Medians, with the least and the
most; and the boot's own start (the unit's ExecMainStart to its "output loop runs" line).

User-Mode Linux has one CPU, and each of its system calls is a trip through the host: every
time here is longer than on a vehicle's own kernel, the more the busier the host (the table
says the load). What it shows is the shape: RestartSec, the interpreter's start, the flush.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from _service import cycles
from linux.kernel import boot_systemd, systemd_refusal
from linux.service import RATE_HZ, unit_seconds, vehicle_config

ROWS = {
    "kill_to_safe": "SIGKILL of the main process -> first safe frame",
    "kill_to_back": "SIGKILL of the main process -> the autopilot's outputs again",
    "stop_to_safe": "systemctl stop -> first safe frame",
    "stop_returns": "systemctl stop -> it returns (the service stopped)",
    "start_to_frame": "systemctl start -> first frame",
    "start_to_outputs": "systemctl start -> the autopilot's outputs",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=5, help="kill, stop, start (default 5)")
    args = parser.parse_args()
    refusal = systemd_refusal()
    if refusal:
        sys.exit(f"bench/service.py: cannot boot systemd in User-Mode Linux: {refusal}")
    with tempfile.TemporaryDirectory(prefix="esc-bridge-service-") as work:
        kernel = boot_systemd(Path(work), vehicle_config())
        try:
            result = kernel.call(cycles, count=args.cycles, timeout_s=300 * args.cycles + 300)
        finally:
            kernel.close()
    boot, runs = result["boot"], result["runs"]
    print(
        f"esc-bridge under systemd in User-Mode Linux {kernel.release} (one CPU), CKESC quad at "
        f"{RATE_HZ} Hz, RestartSec={unit_seconds('RestartSec'):g}; {len(runs)} cycles; "
        f"load {os.getloadavg()[0]:.1f} at the end"
    )
    print(
        f"boot: the unit started {boot['started_s']:.1f} s after the kernel, its loop ran "
        f"{boot['loop_runs_s'] - boot['started_s']:.1f} s later"
    )
    print("| from -> to | median, s | least-most, s |")
    print("| --- | --- | --- |")
    for key, name in ROWS.items():
        values = [run[key] for run in runs]
        print(f"| {name} | {statistics.median(values):.2f} | {min(values):.2f}-{max(values):.2f} |")


if __name__ == "__main__":
    main()
