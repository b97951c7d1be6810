"""From a telemetry frame on the bus to the value on the web page, and each stage between.

Run: ``python bench/web_latency.py [--runs 3] [--changes 60] [--browsers 5]``

Each run starts the fleet of ``bench/_web.py`` (2 vehicles x 8 ESCs, real bridges, the web
monitor connected to both) with ``--browsers`` headless Chromium windows on the page. Then,
``--changes`` times, 0.4-0.8 s apart (so that no schedule on the way lines up with them), the
ESC player gives motor 1 of the first vehicle a new rpm no other frame carries, noting when the
first frame with it left (wall clock). The value is then looked for at each stage:

- Zenoh: the bridge's ``esc/status`` carrying it (a subscriber of this process);
- the event stream: the monitor's snapshot carrying it (a reader of ``/events`` of this process,
  as a browser's EventSource reads it);
- the page: the first browser's rpm cell showing it (a MutationObserver in the page, Date.now()
  when the cell's text changed; the browser paints it at its next frame, within 17 ms).

Every stage has a schedule in it: the bridge publishes ``esc/status`` at ``[zenoh]
status_hz`` (10 Hz), the monitor pushes ten snapshots a second. All clocks are this machine's
wall clock. The table pools every change of every run: median and p99 in ms, and the
median of each run.
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import time

from _common import num
from _stats import percentile
from _web import (
    ESCS,
    VEHICLES,
    Browsers,
    EscPlayer,
    Fleet,
    check_browser,
    loads,
    wait_until,
    watchers,
)

SETTLE_S = 5.0
FIRST_MARKER_RPM = 20_000  # the played rpm stay near 3000; markers count up from here
GAP_S = (0.4, 0.8)
LATE_S = 3.0  # after the last change, how long the stages have to show it

# Records every text motor 1's rpm cell of the first vehicle shows, with Date.now().
OBSERVE = """
const td = document.querySelector(
  `section.vehicle[data-vehicle="${arguments[0]}"] tr[data-motor="1"] td[data-col="rpm"]`);
window.benchSeen = [];
new MutationObserver(() => window.benchSeen.push([td.textContent, Date.now()])).observe(
  td, {childList: true, characterData: true, subtree: true});
return true;
"""
STAGES = ("bus -> Zenoh esc/status", "-> event stream", "-> page", "bus -> page")


def one_run(changes: int, count: int) -> dict[str, list[float]]:
    """Delays in ms by stage, one per change that reached the page."""
    with Fleet() as fleet, watchers(fleet.endpoints, fleet.url) as (watch, events):
        browsers = Browsers(fleet.url, count)
        try:
            page = browsers.all[0]
            page.run(OBSERVE, VEHICLES[0])
            time.sleep(SETTLE_S)
            player: EscPlayer = fleet.players[0]
            markers = [FIRST_MARKER_RPM + n for n in range(changes)]
            for marker in markers:
                player.mark(marker)
                time.sleep(random.uniform(*GAP_S))
            wait_until(lambda: str(markers[-1]) in events.seen(), LATE_S + 30, "last change")
            time.sleep(LATE_S)
            shown: dict[str, float] = {}
            for text, ms in page.run("return window.benchSeen"):
                shown.setdefault(text, ms / 1000)
            sent, zenoh, stream = player.sent(), watch.seen(), events.seen()
        finally:
            browsers.close()
    delays: dict[str, list[float]] = {stage: [] for stage in STAGES}
    for marker in markers:
        key = str(marker)
        if marker not in sent or marker not in zenoh or key not in stream or key not in shown:
            continue
        delays[STAGES[0]].append(1000 * (zenoh[marker] - sent[marker]))
        delays[STAGES[1]].append(1000 * (stream[key] - zenoh[marker]))
        delays[STAGES[2]].append(1000 * (shown[key] - stream[key]))
        delays[STAGES[3]].append(1000 * (shown[key] - sent[marker]))
    missed = changes - len(delays[STAGES[3]])
    if missed:
        print(f"  {missed} of {changes} changes not seen at every stage (left out)")
    return delays


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs (default 3)")
    parser.add_argument("--changes", type=int, default=60, help="rpm changes a run (default 60)")
    parser.add_argument("--browsers", type=int, default=5, help="browsers (default 5)")
    args = parser.parse_args()
    check_browser()
    print(f"load before: {loads()}; {os.cpu_count()} cores")
    runs = []
    for run in range(1, args.runs + 1):
        runs.append(one_run(args.changes, args.browsers))
        end_to_end = runs[-1][STAGES[3]]
        median = statistics.median(end_to_end) if end_to_end else float("nan")
        print(f"run {run}: bus -> page median {median:.0f} ms", flush=True)
    print(f"load after: {loads()}")
    print()
    print(
        f"telemetry frame on the bus -> value on the page, ms: {len(VEHICLES)} vehicles x "
        f"{ESCS} ESCs, {args.browsers} browsers, {args.changes} changes x {args.runs} runs"
    )
    header = f"{'stage':<26} {'n':>5} {'median':>8} {'p99':>8}   median of each run"
    print(header)
    print("-" * len(header))
    for stage in STAGES:
        pooled = [d for run in runs for d in run[stage]]
        medians = ", ".join(f"{statistics.median(run[stage]):.0f}" for run in runs if run[stage])
        print(
            f"{stage:<26} {len(pooled):>5} "
            f"{num(statistics.median(pooled) if pooled else None, '.0f', 8)} "
            f"{num(percentile(pooled, 0.99), '.0f', 8)}   {medians}"
        )


if __name__ == "__main__":
    main()
