"""esc-bridge as a systemd service in the guest that :func:`linux.kernel.boot_systemd` boots:
its configuration there, and what tests/linux/test_systemd.py and bench/service.py read of it
(``systemctl show``, the journal, its processes, the bus).

The configuration is config/quad-ckesc.toml edited as docs/service.md tells a user to edit it,
for the guest: the autopilot on loopback UDP (the guest has no serial port), the loop at 100 Hz
(every tick's system calls are dear in a one-CPU guest on a loaded host), the longest input
timeout (the guest stands still while the host runs others), no Zenoh (nothing listens).
"""

from __future__ import annotations

import re
import time
from pathlib import Path

from pymavlink import mavutil

from bridge._compat import tomllib
from bridge.config import build_config
from bridge.errors import CodecError
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from linux import guest

ROOT = Path(__file__).resolve().parent.parent.parent
UNIT = ROOT / "config" / "esc-bridge.service"
SHIPPED_CONFIG = ROOT / "config" / "quad-ckesc.toml"
AUTOPILOT_PORT = 14550  # the configuration's udpin
AUTOPILOT_HZ = 20
PWM = [1100, 1350, 1600, 1850]  # four outputs, four values
START_TIMEOUT_S = 240.0  # a start of the service in the guest, on a loaded host
STREAMING_S = 2 / AUTOPILOT_HZ  # the autopilot's newest output at most this old: streaming


def vehicle_config() -> str:
    text = SHIPPED_CONFIG.read_text()
    edits = {
        'url = "serial:/dev/ttyAMA0:921600"': f'url = "udpin:127.0.0.1:{AUTOPILOT_PORT}"',
        "rate_hz = 400": "rate_hz = 100\ninput_timeout_ms = 1000",
    }
    for old, new in edits.items():
        assert old in text, f"{SHIPPED_CONFIG} has no {old!r} any more"
        text = text.replace(old, new)
    return text + "\n[zenoh]\nenabled = false\n"


RATE_HZ = build_config(tomllib.loads(vehicle_config()), "guest").rate_hz
FULL_SCALE = ckesc_records.THROTTLE_MAX  # quad-ckesc.toml: RawCommand_12b


def unit_seconds(key: str) -> float:
    """A time of the shipped unit's, in seconds (``RestartSec=2``: 2.0)."""
    match = re.search(rf"^{key}=(\d+(?:\.\d+)?)s?$", UNIT.read_text(), re.M)
    assert match is not None, key
    return float(match[1])


def throttles(line: str) -> tuple[int, ...] | None:
    """The first four throttles of a ``candump -L`` line's RawCommand_12b, or None."""
    try:
        frame = ckesc_codec.decode(guest.candump_message(line)[1])
    except (ValueError, CodecError):
        return None
    if frame is None or not isinstance(frame.message, ckesc_records.RawCommand12b):
        return None
    return frame.message.throttles[:4]


ARMED = tuple(round((p - 1000) / 1000 * FULL_SCALE) for p in PWM)
SAFE = (0, 0, 0, 0)


# -- in the guest ------------------------------------------------------------------------------


def show() -> dict[str, str]:
    """The service's state, main process, result, restarts and start time."""
    return guest.systemctl_show(
        "esc-bridge.service",
        "MainPID",
        "ActiveState",
        "SubState",
        "Result",
        "NRestarts",
        "ExecMainStatus",
        "ExecMainStartTimestampMonotonic",
    )


def loop_of(main: int) -> int | None:
    """The output loop's process among ``main``'s children (the one multiprocessing spawned to
    run it; the other child is multiprocessing's resource tracker)."""
    for pid in guest.children(main):
        try:
            if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes():
                return pid
        except OSError:
            continue
    return None


def journal(pid: int | None = None) -> list[str]:
    """The bridge's journal since boot (or one process's), each line with its monotonic time."""
    which = ["-u", "esc-bridge"] if pid is None else [f"_PID={pid}"]
    command = ["journalctl", *which, "-b", "-o", "short-monotonic", "--no-pager"]
    return guest.run(command, check=False).splitlines()


def running(other_than: int = 0) -> tuple[int, int]:
    """(main, loop) once the service's main process (not ``other_than``) says its loop runs."""
    found: list[int] = []

    def loop_runs() -> bool:
        main = int(show()["MainPID"])
        loop = loop_of(main) if main not in (0, other_than) else None
        found[:] = [main, loop or 0]
        return loop is not None and any("output loop runs" in line for line in journal(main))

    guest.wait_until(loop_runs, START_TIMEOUT_S, "the service's output loop")
    return found[0], found[1]


def armed() -> tuple[guest.Autopilot, guest.Candump]:
    """The autopilot armed at PWM and candump on can0, once the bridge sends the outputs and
    the autopilot is streaming them: its newest output delivered under STREAMING_S ago and the
    newest command on can0 carrying it. What a test does next (a kill, a stop) then meets a
    bridge sending armed outputs, not one gone to its failsafe because the test's autopilot,
    a thread in a one-CPU guest, fell quiet for a while (seen once: 1.2 s).

    And first, once the bridge answers this autopilot: it takes one autopilot's address and
    ignores another's until the first has been silent a while, so a new autopilot (a socket of
    another port) after an earlier test's would find the bridge still sending the earlier one's
    last outputs, the same values, until its input went stale (seen in CI: a FAILSAFE 0.1 s
    before the stop test's stop)."""
    dump = guest.Candump("can0")
    pilot = guest.Autopilot(AUTOPILOT_PORT, stack=mavutil.mavlink.MAV_AUTOPILOT_PX4)
    pilot.pwm = list(PWM)
    pilot.armed = True
    pilot.start_stream(AUTOPILOT_HZ)
    # What the bridge sends its autopilot (its HEARTBEAT among them) goes to the address it took.
    guest.MavlinkWatch(pilot.conn).wait_for("HEARTBEAT", lambda _: True, START_TIMEOUT_S)

    def streaming() -> bool:
        delivered = pilot.delivered
        if not delivered or time.time() - delivered[-1] > STREAMING_S:
            return False
        newest = next((t for t in map(throttles, reversed(dump.lines())) if t is not None), None)
        return newest == ARMED

    guest.wait_until(streaming, START_TIMEOUT_S, "the autopilot's outputs on can0")
    return pilot, dump
