"""What reading the bridge's own commands back costs the CAN reader, on a real kernel's vcan.

Run: ``python bench/readback.py [--runs 5] [--seconds 10] [--rate 400] [--kernel auto]``

On SocketCAN the reader's kernel filters decide what wakes it. With read-back they pass the
bridge's own command frames too (the ESC state's ``command`` for the actuators/output key
comes from them), without it only the ESCs' telemetry. This runs the production reader
(``CanReader`` on a kernel-filtered handle, in a process of its own: ``bench/_readback.py``)
both ways against the same traffic: the simulated ESCs' telemetry (``esc-bridge sim``, CKESC
quad) and the commands at ``--rate`` (``cangen`` repeating the driver's frames), and prints
the reader's CPU (user + system, % of one core) and the frames it read, medians over
``--runs`` runs of each (alternating, so a change of load beside it hits both).

Where: the host's own kernel where it can make a vcan (root and the vcan module: a Linux
machine with SocketCAN), else User-Mode Linux (``tests/linux/kernel.py``; ``--kernel uml``
asks for it). In User-Mode Linux every system call of the guest is a trip through the host, so
every CPU figure is inflated, the more the busier the host: there the table shows that it
works and the ratio between the two ways, not what a vehicle's CPU would spend. The table says
which kernel it ran on.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from _readback import measure
from linux.kernel import MODE_ENV, boot, choose


def row(name: str, runs: list[dict[str, Any]]) -> str:
    cpu = [100 * r["cpu_s"] / r["seconds"] for r in runs]
    rate = [r["frames"] / r["seconds"] for r in runs]
    per_frame = [1e6 * r["cpu_s"] / r["frames"] for r in runs if r["frames"]]
    return (
        f"| {name} | {statistics.median(cpu):.2f} ({min(cpu):.2f}-{max(cpu):.2f}) "
        f"| {statistics.median(rate):.0f} | {statistics.median(per_frame):.0f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="runs of each way (default 5)")
    parser.add_argument("--seconds", type=float, default=10.0, help="each run (default 10)")
    parser.add_argument("--rate", type=int, default=400, help="command rate, Hz (default 400)")
    parser.add_argument(
        "--kernel", choices=("auto", "host", "uml"), default="auto", help="where (default auto)"
    )
    args = parser.parse_args()
    os.environ[MODE_ENV] = args.kernel
    mode, reason = choose()
    if not mode:
        sys.exit(f"bench/readback.py: {reason}")
    config = f'[output]\nprotocol = "ckesc"\nrate_hz = {args.rate}\n'
    ways = ((True, False), (False, True))  # each run both ways, which first alternating
    order = [way for run in range(args.runs) for way in ways[run % 2]]
    with tempfile.TemporaryDirectory(prefix="esc-bridge-readback-") as work:
        kernel = boot(mode, Path(work))
        try:
            results = kernel.call(
                measure,
                config=config,
                seconds=args.seconds,
                order=order,
                timeout_s=len(order) * (args.seconds + 120) + 300,
            )
        finally:
            kernel.close()
    load = os.getloadavg()[0]
    where = "the host's kernel" if mode == "host" else f"User-Mode Linux {kernel.release}"
    print(
        f"CAN reader, CKESC quad at {args.rate} Hz with simulated telemetry; {where}; "
        f"{args.runs} runs of {args.seconds:.0f} s each way; load {load:.1f} at the end"
    )
    print("| reader | CPU, % of a core: median (min-max) | frames read/s | CPU per frame, µs |")
    print("| --- | --- | --- | --- |")
    print(row("telemetry only", [r for r in results if not r["read_back"]]))
    print(row("telemetry + own commands (read-back)", [r for r in results if r["read_back"]]))


if __name__ == "__main__":
    main()
