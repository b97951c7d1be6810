"""The guest's side of ``bench/service.py``: in the systemd that tests/linux boots, the service's
start, restart and stop, timed from the command to what ``candump`` sees on can0.

An autopilot streams armed outputs all along, so "back" and "started" mean the bridge sends
the autopilot's outputs again, not merely that a process exists.
"""

from __future__ import annotations

import time
from typing import Any

from linux import guest, service
from linux.service import ARMED, SAFE, throttles


def _first(lines: list[str], after: float, want: tuple[int, ...] | None) -> float:
    """candump's time of the first command frame at or after ``after`` (equal to ``want``,
    when given)."""
    for line in lines:
        stamp = guest.candump_message(line)[0]
        found = throttles(line)
        if stamp >= after and found is not None and (want is None or found == want):
            return stamp
    raise AssertionError(f"no frame {want} after {after}")


def cycles(count: int) -> dict[str, Any]:
    """``count`` times: kill the main process, stop, start; each timed. And the boot's start."""
    main, _ = service.running()
    state = service.show()
    boot = {
        "started_s": int(state["ExecMainStartTimestampMonotonic"]) / 1e6,
        "loop_runs_s": next(
            float(line[1 : line.index("]")])
            for line in service.journal(main)
            if "output loop runs" in line
        ),
    }
    pilot, dump = service.armed()
    dump.stop()
    runs = []
    try:
        for _ in range(count):
            runs.append(_cycle())
    finally:
        pilot.close()
    return {"boot": boot, "runs": runs}


def _cycle() -> dict[str, float]:
    """Kill the main process, stop, start (the autopilot streaming), on a candump of its own."""
    main, _ = service.running()
    dump = guest.Candump("can0")
    try:
        guest.wait_until(lambda: _has(dump.lines(), 0, ARMED), 60, "the outputs on the bus")
        killed = time.time()
        guest.run(["systemctl", "kill", "--kill-whom=main", "-s", "KILL", "esc-bridge"])
        service.running(other_than=main)
        guest.wait_until(lambda: _has(dump.lines(), killed, ARMED, after_safe=True), 120, "back")
        stopping = time.time()
        guest.run(["systemctl", "stop", "esc-bridge"], timeout_s=60)
        stopped = time.time()
        starting = time.time()
        guest.run(["systemctl", "start", "esc-bridge"], timeout_s=60)
        guest.wait_until(lambda: _has(dump.lines(), starting, ARMED), 120, "started")
    finally:
        lines = dump.stop()
    safe_after_kill = _first(lines, killed, SAFE)
    return {
        "kill_to_safe": safe_after_kill - killed,
        "kill_to_back": _first(lines, safe_after_kill, ARMED) - killed,
        "stop_to_safe": _first(lines, stopping, SAFE) - stopping,
        "stop_returns": stopped - stopping,
        "start_to_frame": _first(lines, starting, None) - starting,
        "start_to_outputs": _first(lines, starting, ARMED) - starting,
    }


def _has(lines: list[str], after: float, want: tuple[int, ...], after_safe: bool = False) -> bool:
    """Whether candump saw ``want`` after ``after`` (and, with ``after_safe``, after a safe
    frame that came after it)."""
    try:
        start = _first(lines, after, SAFE) if after_safe else after
        _first(lines, start, want)
    except AssertionError:
        return False
    return True
