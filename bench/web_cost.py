"""What ``esc-bridge monitor --web`` costs the machine that serves it: 2 vehicles x 8 ESCs, with
no browser and then with 5 watching.

Run: ``python bench/web_cost.py [--runs 3] [--seconds 20] [--browsers 5]``

Each run starts the fleet of ``bench/_web.py`` (two real bridges, each with eight CKESCs whose
telemetry this process plays, rpm always moving) and the web monitor connected to both, then
measures the monitor's process over ``--seconds``: first with no browser, then with
``--browsers`` headless Chromium windows on the page (each showing both cards), after a few
seconds for them to settle. Measured:

- the monitor's CPU: user + system time of its process (Zenoh's threads, the publisher, one
  thread per browser) over the window, % of one core;
- its memory: resident set (VmRSS) at the window's end, MB;
- the stream one browser receives, kB/s (an event-stream reader of this process, beside the
  browsers);
- beside them, the browsers' own CPU (every Chromium process of all of them, % of one core):
  what the page costs where it is watched, on a phone or a laptop normally, here on this
  machine too.

The table gives the median of the runs (min-max beside it).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from dataclasses import dataclass

from _common import cpu_seconds, num
from _web import ESCS, VEHICLES, Browsers, Events, Fleet, check_browser, loads, rss_mb, wait_until

SETTLE_S = 5.0  # after the fleet or the browsers start, before measuring


@dataclass(frozen=True)
class Window:
    """One measured window."""

    monitor_cpu_pct: float
    monitor_rss_mb: float
    stream_kb_s: float
    browsers_cpu_pct: float | None


def measure(fleet: Fleet, seconds: float, browsers: Browsers | None) -> Window:
    events = Events(fleet.url)
    try:
        wait_until(lambda: events.received() > 0, 30, "event stream")
        time.sleep(1.0)
        pid = fleet.monitor_pid
        browser_pids = [] if browsers is None else browsers.pids()
        start = time.monotonic()
        cpu0, bytes0 = cpu_seconds([pid]), events.received()
        browsers0 = cpu_seconds(browser_pids)
        time.sleep(seconds)
        elapsed = time.monotonic() - start
        cpu = cpu_seconds([pid]) - cpu0
        received = events.received() - bytes0
        browsers_cpu = None if browsers is None else cpu_seconds(browser_pids) - browsers0
        return Window(
            monitor_cpu_pct=100 * cpu / elapsed,
            monitor_rss_mb=rss_mb(pid),
            stream_kb_s=received / elapsed / 1000,
            browsers_cpu_pct=None if browsers_cpu is None else 100 * browsers_cpu / elapsed,
        )
    finally:
        events.close()


def one_run(seconds: float, count: int) -> tuple[Window, Window]:
    with Fleet() as fleet:
        time.sleep(SETTLE_S)
        alone = measure(fleet, seconds, None)
        browsers = Browsers(fleet.url, count)
        try:
            time.sleep(SETTLE_S)
            watched = measure(fleet, seconds, browsers)
        finally:
            browsers.close()
    return alone, watched


def median_cell(values: list[float | None], spec: str, width: int) -> str:
    present = [v for v in values if v is not None]
    if not present:
        return num(None, spec, width)
    middle = num(statistics.median(present), spec, 0)
    spread = f"{min(present):{spec}}-{max(present):{spec}}"
    return f"{middle + ' (' + spread + ')':>{width}}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs (default 3)")
    parser.add_argument("--seconds", type=float, default=20.0, help="window (default 20 s)")
    parser.add_argument("--browsers", type=int, default=5, help="browsers (default 5)")
    args = parser.parse_args()
    check_browser()
    print(f"load before: {loads()}; {os.cpu_count()} cores")
    runs = []
    for run in range(1, args.runs + 1):
        runs.append(one_run(args.seconds, args.browsers))
        alone, watched = runs[-1]
        print(
            f"run {run}: monitor {alone.monitor_cpu_pct:.1f} % alone, "
            f"{watched.monitor_cpu_pct:.1f} % with {args.browsers} browsers",
            flush=True,
        )
    print(f"load after: {loads()}")
    print()
    print(
        f"esc-bridge monitor --web, {len(VEHICLES)} vehicles x {ESCS} ESCs, "
        f"{args.seconds:g} s windows, median of {args.runs} runs (min-max)"
    )
    header = (
        f"{'watching':<12} {'monitor CPU, % core':>22} {'monitor RSS, MB':>20} "
        f"{'stream per browser, kB/s':>26} {'browsers CPU, % core':>22}"
    )
    print(header)
    print("-" * len(header))
    for label, index in (("no browser", 0), (f"{args.browsers} browsers", 1)):
        windows = [run[index] for run in runs]
        print(
            f"{label:<12} "
            f"{median_cell([w.monitor_cpu_pct for w in windows], '.1f', 22)} "
            f"{median_cell([w.monitor_rss_mb for w in windows], '.0f', 20)} "
            f"{median_cell([w.stream_kb_s for w in windows], '.1f', 26)} "
            f"{median_cell([w.browsers_cpu_pct for w in windows], '.0f', 22)}"
        )


if __name__ == "__main__":
    main()
