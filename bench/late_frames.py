"""Commands delivered late after a bus held frames, on a real kernel's SocketCAN.

Run: ``python bench/late_frames.py [--holds 0 100 1000 5000] [--runs 3] [--rate 400]
[--code REV] [--cost] [--truesize]``

It boots the kernel the tests in ``tests/linux`` use (User-Mode Linux, or the host's own vcan:
``tests/linux/kernel.py``) and, there, for each hold and run
(``tests/linux/late_frames.py:hold_through_a_disarm``): the bridge (``esc-bridge run``, CKESC x4
on a vcan with echo, the passthrough mixer, ``--rate`` Hz), a pymavlink autopilot armed at half
throttle, and candump as the ESCs. A netem qdisc delays every frame by the hold; halfway
through it the autopilot disarms and stops its outputs; at its end the delay goes back to 0.

Per hold, the median over the runs (and the range) of:

- live after disarm: command frames other than the safe values that candump received after
  the disarm (an ESC told to spin by a vehicle already disarmed);
- latest: how long after the disarm the last of them came, ms. Hold 0 is the reference: the
  bridge's own reaction (the next HEARTBEAT, or the input timeout).
- stuck: the bridge's ``CAN: FAULT bus stuck`` reports.

``--code REV`` runs the bridge of another commit (``git archive REV``, put first on PYTHONPATH)
for the figures before a change. ``--cost`` adds the CPU per tick of three ways to send eight
frames and know whether they left, in the guest (compare them with each other; UML's system
calls cost several times a host's); ``--truesize`` the frames a socket's send buffer takes.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from linux import late_frames  # noqa: E402 (tests/ on the path first)
from linux.kernel import Kernel, boot, choose  # noqa: E402


def _archive(rev: str, into: Path) -> str:
    """``rev``'s tree unpacked into ``into``; the directory to put on PYTHONPATH."""
    tar = into / "code.tar"
    subprocess.run(["git", "-C", str(ROOT), "archive", "-o", str(tar), rev], check=True)
    with tarfile.open(tar) as archive:
        archive.extractall(into / "code", filter="data")
    # Where the installed package has it (pyproject.toml's package-dir).
    shutil.copytree(into / "code" / "mixers", into / "code" / "bridge" / "mixers")
    return str(into / "code")


def _row(hold_ms: int, runs: list[dict[str, object]]) -> str:
    def spread(key: str) -> str:
        values = [float(str(run[key])) for run in runs]
        median = statistics.median(values)
        return f"{median:g} ({min(values):g}..{max(values):g})"

    return f"| {hold_ms} | {len(runs)} | {spread('live_after')} | {spread('latest_ms')} | " + (
        f"{spread('stuck_reports')} |"
    )


def _holds(kernel: Kernel, args: argparse.Namespace, code: str) -> None:
    print("| hold, ms | runs | live after disarm | latest, ms after disarm | stuck reports |")
    print("| --- | --- | --- | --- | --- |")
    for hold_ms in args.holds:
        runs = []
        for _ in range(args.runs):
            with contextlib.redirect_stdout(io.StringIO()):  # the guest's log of the call
                runs.append(
                    kernel.call(
                        late_frames.hold_through_a_disarm,
                        timeout_s=600,
                        hold_ms=hold_ms,
                        rate_hz=args.rate,
                        code=code,
                    )
                )
        print(_row(hold_ms, runs), flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--holds", type=int, nargs="+", default=[0, 100, 1000, 5000])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--rate", type=int, default=400, help="the bridge's rate, Hz")
    parser.add_argument("--code", metavar="REV", help="run the bridge of this commit")
    parser.add_argument("--cost", action="store_true", help="also the transmit side's CPU")
    parser.add_argument("--truesize", action="store_true", help="also the send buffer's frames")
    args = parser.parse_args()
    mode, reason = choose()
    if not mode:
        print(f"no kernel to measure on: {reason}", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory(prefix="late-frames-") as tmp:
        code = _archive(args.code, Path(tmp)) if args.code else ""
        kernel = boot(mode, Path(tmp) / "kernel")
        try:
            load = os.getloadavg()[0]
            print(
                f"{mode} kernel {kernel.release}, bridge at {args.rate} Hz from "
                f"{args.code or 'the checkout'}; load {load:.1f} at the start, "
                f"{time.strftime('%Y-%m-%d %H:%M')}"
            )
            if args.truesize:
                print(kernel.call(late_frames.send_buffer_frames))
            if args.cost:
                print(kernel.call(late_frames.transmit_cost, frames=8, ticks=2000))
            _holds(kernel, args, code)
            print(f"load {os.getloadavg()[0]:.1f} at the end")
        finally:
            kernel.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
