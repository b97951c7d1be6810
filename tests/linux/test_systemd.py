"""The shipped unit under systemd itself: systemd 252 as PID 1 in User-Mode Linux, on an overlay of
the host's files (the host's files are never written), esc-bridge installed there as
docs/service.md says (:func:`linux.kernel.boot_systemd`): its system user, /etc/esc-bridge
(:func:`linux.service.vehicle_config`), the unit with its serial device deleted (the autopilot
is on UDP here) and enabled, ``can0`` made at boot by systemd-networkd from a ``.netdev``.

One boot holds every test here, in the order a vehicle lives it: the boot, a SIGKILL of the
bridge's main process, then ``systemctl stop``. Each step is a call into the guest that
collects what happened (``candump -L`` on can0, ``systemctl show``, the journal, /proc); the
host checks each behaviour in a test of its own.
"""

from __future__ import annotations

import itertools
import os
import pwd
import re
import statistics
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from linux import guest, service
from linux.kernel import Kernel, boot_systemd, systemd_refusal
from linux.service import ARMED, RATE_HZ, SAFE, START_TIMEOUT_S, throttles

WATCH_S = 2.0  # candump's look at the bus after the boot: the rate
AFTER_S = 2.0  # the bus watched after the new main process's loop runs, or after the stop


# -- in the guest ------------------------------------------------------------------------------


def after_boot() -> dict[str, Any]:
    """The service as the boot left it, its bus watched for WATCH_S."""
    main, loop = service.running()
    dump = guest.Candump("can0")
    time.sleep(WATCH_S)
    status = Path(f"/proc/{main}/status").read_text()
    uid = re.search(r"^Uid:\s+(\d+)", status, re.M)
    assert uid is not None, status
    cache = Path("/var/cache/esc-bridge/mavlink")
    return {
        "service": service.show(),
        "can0": guest.systemctl_show(
            "sys-subsystem-net-devices-can0.device", "ActiveEnterTimestampMonotonic"
        ),
        "user": pwd.getpwuid(int(uid[1])).pw_name,
        "policy": os.sched_getscheduler(loop),
        "priority": os.sched_getparam(loop).sched_priority,
        "cache": {p.name: pwd.getpwuid(p.stat().st_uid).pw_name for p in cache.glob("*.py")},
        "journal": service.journal(),
        "frames": dump.stop(),
    }


def kill_main() -> dict[str, Any]:
    """Armed, then ``systemctl kill --kill-whom=main -s KILL``: the bus until the service's
    new main process runs its loop, and AFTER_S more."""
    old_main, _ = service.running()
    pilot, dump = service.armed()
    try:
        killed = time.time()
        guest.run(["systemctl", "kill", "--kill-whom=main", "-s", "KILL", "esc-bridge"])
        new_main, _ = service.running(other_than=old_main)
        time.sleep(AFTER_S)
    finally:
        pilot.close()
    return {
        "old_main": old_main,
        "new_main": new_main,
        "killed": killed,
        "pilot_gaps": gaps(pilot.sent),
        "service": service.show(),
        "frames": dump.stop(),
    }


def gaps(sent: list[float]) -> list[tuple[float, float]]:
    """The autopilot's gaps over 0.2 s between outputs: (when, how long)."""
    return [(a, round(b - a, 3)) for a, b in itertools.pairwise(sent) if b - a > 0.2]


def stop() -> dict[str, Any]:
    """Armed, then ``systemctl stop``: the bus, the unit's result, the journal."""
    service.running()
    pilot, dump = service.armed()
    try:
        stopped = time.time()
        guest.run(["systemctl", "stop", "esc-bridge"], timeout_s=60)
        time.sleep(AFTER_S)
    finally:
        pilot.close()
    return {
        "stopped": stopped,
        "pilot_gaps": gaps(pilot.sent),
        "service": service.show(),
        "frames": dump.stop(),
        "journal": service.journal(),
    }


# -- on the host -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def systemd(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Kernel]:
    refusal = systemd_refusal()
    if refusal:
        pytest.skip(f"cannot boot systemd in User-Mode Linux: {refusal}")
    kernel = boot_systemd(tmp_path_factory.mktemp("systemd"), service.vehicle_config())
    yield kernel
    kernel.close()


@pytest.fixture(scope="module")
def booted(systemd: Kernel) -> dict[str, Any]:
    result: dict[str, Any] = systemd.call(after_boot, timeout_s=START_TIMEOUT_S + 60)
    return result


@pytest.fixture(scope="module")
def killed(systemd: Kernel, booted: dict[str, Any]) -> dict[str, Any]:
    result: dict[str, Any] = systemd.call(kill_main, timeout_s=3 * START_TIMEOUT_S)
    return result


@pytest.fixture(scope="module")
def stopped(systemd: Kernel, killed: dict[str, Any]) -> dict[str, Any]:
    result: dict[str, Any] = systemd.call(stop, timeout_s=2 * START_TIMEOUT_S)
    return result


def sent(lines: list[str]) -> list[tuple[float, tuple[int, ...]]]:
    """Each command frame on the bus: (candump's time, the four throttles)."""
    found = ((guest.candump_message(line)[0], throttles(line)) for line in lines)
    return [(t, commands) for t, commands in found if commands is not None]


def monotonic_s(usec: str) -> float:
    return int(usec) / 1e6


def journal_time(line: str) -> float:
    """The monotonic time of a ``short-monotonic`` journal line."""
    match = re.match(r"\[\s*(\d+\.\d+)\]", line)
    assert match is not None, line
    return float(match[1])


def test_it_starts_at_boot_once_can0_exists(booted: dict[str, Any]) -> None:
    state = booted["service"]
    assert (state["ActiveState"], state["SubState"]) == ("active", "running"), state
    can0_s = monotonic_s(booted["can0"]["ActiveEnterTimestampMonotonic"])
    started_s = monotonic_s(state["ExecMainStartTimestampMonotonic"])
    assert 0 < can0_s <= started_s, (can0_s, started_s)
    assert state["NRestarts"] == "0", booted["journal"]


def test_it_sends_safe_values_at_the_configured_rate(booted: dict[str, Any]) -> None:
    """No autopilot yet: safe values, at the configured rate (the median interval: a one-CPU
    guest on a loaded host misses a tick now and then)."""
    frames = sent(booted["frames"])
    assert len(frames) > 10 and all(t == SAFE for _, t in frames), frames[:5]
    period_s = statistics.median(b - a for (a, _), (b, _) in itertools.pairwise(frames))
    assert period_s == pytest.approx(1 / RATE_HZ, rel=0.1)


def test_it_runs_as_its_user_with_real_time_priority(booted: dict[str, Any]) -> None:
    assert booted["user"] == "esc-bridge"
    assert (booted["policy"], booted["priority"]) == (os.SCHED_FIFO, 50)


def test_its_dialect_lands_in_its_cache_directory(booted: dict[str, Any]) -> None:
    assert len(booted["cache"]) == 1, booted["cache"]
    ((name, owner),) = booted["cache"].items()
    assert name.startswith("esc_bridge-") and owner == "esc-bridge"


def test_the_journal_shows_its_start_line(booted: dict[str, Any]) -> None:
    journal = "\n".join(booted["journal"])
    assert re.search(r"esc-bridge: ckesc x4 \(12b\), mixer passthrough-4, 100 Hz", journal)
    assert "output loop runs with SCHED_FIFO priority 50" in journal


def test_a_killed_main_process_leaves_safe_values_and_it_comes_back(
    booted: dict[str, Any], killed: dict[str, Any]
) -> None:
    """SIGKILL to the main process: the loop sends safe values (it sees the relay close) and
    nothing else until the unit, restarted after RestartSec, has a new loop that sends the
    autopilot's outputs again; within RestartSec plus the time the boot's start took (twice
    over, and 5 s: an interpreter starts slowly in a guest on a loaded host)."""
    assert killed["new_main"] != killed["old_main"]
    assert killed["service"]["NRestarts"] == "1", killed["service"]
    frames = sent(killed["frames"])
    before = [t for when, t in frames if when < killed["killed"]]
    after = [(when, t) for when, t in frames if when >= killed["killed"]]
    assert before and before[-1] == ARMED, (before[-5:], killed["pilot_gaps"])
    first_safe = next(i for i, (_, t) in enumerate(after) if t == SAFE)
    assert all(t == ARMED for _, t in after[:first_safe])
    back = next(when for when, t in after[first_safe:] if t == ARMED)
    assert all(t == SAFE for when, t in after[first_safe:] if when < back)
    state = booted["service"]
    loop_ran = next(line for line in booted["journal"] if "output loop runs" in line)
    start_s = journal_time(loop_ran) - monotonic_s(state["ExecMainStartTimestampMonotonic"])
    took_s = back - killed["killed"]
    assert took_s < service.unit_seconds("RestartSec") + 2 * start_s + 5, (took_s, start_s)


def test_systemctl_stop_flushes_safe_values_and_exits_zero(stopped: dict[str, Any]) -> None:
    state = stopped["service"]
    assert (state["ActiveState"], state["Result"], state["ExecMainStatus"]) == (
        "inactive",
        "success",
        "0",
    ), state
    frames = sent(stopped["frames"])
    before = [t for when, t in frames if when < stopped["stopped"]]
    after = [t for when, t in frames if when >= stopped["stopped"]]
    assert before and before[-1] == ARMED, (before[-5:], stopped["pilot_gaps"])
    first_safe = after.index(SAFE)
    assert all(t == ARMED for t in after[:first_safe])
    assert all(t == SAFE for t in after[first_safe:])
    assert "stopped after sending safe values" in "\n".join(stopped["journal"])
