"""What the bridge's own commands would cost the CAN reader, passing its filters, on a real vcan.

Run: ``python bench/readback.py [--runs 5] [--seconds 10] [--rate 400] [--kernel auto]``

On SocketCAN the reader's kernel filters decide what wakes it. The bridge never reads its own
commands back: the output loop says what it sent through shared memory
(``bridge/daemon/commands_sent.py``), and the reader's filters pass only the ESCs' telemetry.
Only a recording (``--record``) opens the reader to every frame, the commands among them, since
its candump log wants the whole bus. This runs the production reader (``CanReader`` on a
kernel-filtered handle, in a process of its own: ``bench/_readback.py``) both ways against the
same bus, which carries the commands of a CKESC quad at ``--rate`` (``cangen`` repeating the
driver's frames; the ESCs' telemetry would cost both ways the same, and is left out): with the
family's telemetry filters (what the bridge runs), and with the command IDs passing beside them
(what reading them back cost before, and what a recording's reader pays for them). It prints the
reader's CPU (user + system, % of one core), the frames it read and the difference, medians over
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


def cpu_percent(run: dict[str, Any]) -> float:
    return 100 * float(run["cpu_s"]) / float(run["seconds"])


def row(name: str, runs: list[dict[str, Any]]) -> str:
    cpu = [cpu_percent(r) for r in runs]
    rate = [r["frames"] / r["seconds"] for r in runs]
    return (
        f"| {name} | {statistics.median(cpu):.2f} ({min(cpu):.2f}-{max(cpu):.2f}) "
        f"| {statistics.median(rate):.0f} |"
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
        f"CAN reader, CKESC quad's commands at {args.rate} Hz on the bus; {where}; "
        f"{args.runs} runs of {args.seconds:.0f} s each way; load {load:.1f} at the end"
    )
    without = [r for r in results if not r["read_back"]]
    with_read_back = [r for r in results if r["read_back"]]
    print("| reader's filters | CPU, % of a core: median (least-most) | frames read/s |")
    print("| --- | --- | --- |")
    print(row("the ESCs' telemetry (the bridge)", without))
    print(row("the ESCs' telemetry and the bridge's commands", with_read_back))
    # Each run of one way against the run of the other beside it.
    extra = [cpu_percent(a) - cpu_percent(b) for a, b in zip(with_read_back, without, strict=True)]
    frames = [a["frames"] / a["seconds"] for a in with_read_back]
    per_frame = [
        1e4 * e / f for e, f in zip(extra, frames, strict=True) if f
    ]  # % of a core per frame/s -> µs per frame
    print(
        f"the commands passing: +{statistics.median(extra):.2f} % of a core "
        f"(median of {len(extra)} pairs), "
        f"{statistics.median(per_frame):.0f} µs per command frame read"
    )


if __name__ == "__main__":
    main()
