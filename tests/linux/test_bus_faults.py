"""Every fault a bus has, on a real kernel's SocketCAN, through the daemon as it runs on the
vehicle: each reported once (log and STATUSTEXT), counted, and recovered from without a restart.

One bridge (CKESC x4 at 100 Hz, sending safe values: no autopilot and no ESCs, since what it
sends is what matters here) goes through, in turn: the controller's error frames (warning,
passive, bus-off, restarted, as a driver sends them; injected with cansend), the interface down
and up, the interface deleted and made again (a USB adapter unplugged), and the main process
stalled (SIGSTOP) while a flood overflows the reader's receive queue. Each time, the bridge's
frames reach the bus again afterwards, seen by candump."""

from __future__ import annotations

import itertools
import signal
import time
from typing import Any

from conftest import free_port

from bridge.can_errors import ControllerState
from bridge.daemon.bus_reports import CONTROLLER_REPORTS, RECEIVE_LOST, RESTARTED, TX_REPORTS
from bridge.output.transmit import TxState
from linux import guest
from linux.kernel import Kernel

WAIT_S = 60.0  # the one-CPU guest at load: generous, and met at once when all is well
# The reader asks for a 4 MiB receive buffer (the kernel doubles it: 8 MiB, which the guest's
# net.core.rmem_max allows); a CAN frame's skb takes at least 256 bytes of it (about 700 in
# Linux 6.1), so at most 32 768 frames fit and this many overflow it whatever the skb's size.
OVERFLOW_FRAMES = 40_000

STUCK = TX_REPORTS[TxState.STUCK][1]
DOWN = TX_REPORTS[TxState.DOWN][1]
GONE = TX_REPORTS[TxState.GONE][1]
MOVING = TX_REPORTS[TxState.MOVING][1]
WARNING = CONTROLLER_REPORTS[ControllerState.ERROR_WARNING][1]
PASSIVE = CONTROLLER_REPORTS[ControllerState.ERROR_PASSIVE][1]
BUS_OFF = CONTROLLER_REPORTS[ControllerState.BUS_OFF][1]
ACTIVE = CONTROLLER_REPORTS[ControllerState.ERROR_ACTIVE][1]


def _commands_flow(channel: str, what: str) -> int:
    """The bridge's commands (CKESC's 12-bit command, message type 20101) reach the bus: the
    next 40 of them, seen by candump; how long that took, ms."""
    started = time.monotonic()
    lines = guest.run(
        ["candump", "-n", "40", "-T", "30000", f"{channel},004E8500:00FFFF00"], timeout_s=60
    ).splitlines()
    assert len([line for line in lines if "004E85" in line]) == 40, f"no commands {what}"
    return round((time.monotonic() - started) * 1000)


def _bridge(channel: str, port: int) -> guest.Process:
    """``esc-bridge run`` on ``channel``: CKESC x4 at 100 Hz. The loop runs at real-time
    priority, and 400 Hz of UML's costly system calls leaves the guest's one CPU to little else
    on a loaded host."""
    return guest.bridge(channel, port, "--no-zenoh", "--rate", "100")


def a_bridge_through_every_fault() -> dict[str, Any]:
    channel = guest.vcan()
    bridge = _bridge(channel, free_port())
    bridge.wait_for_output("ESC out: safe, waiting for motor outputs", WAIT_S)
    phases: dict[str, int] = {}  # where each phase begins in the bridge's output

    def phase(name: str) -> None:
        phases[name] = len(bridge.output())

    try:
        _commands_flow(channel, "at the start")
        # The controller's error frames, as can_change_state() and can_restart() send them.
        phase("error frames")
        for frame, report in [
            ("20000004#0008000000000000", WARNING),
            ("20000204#0020000000008800", PASSIVE),
            ("20000040#0000000000000000", BUS_OFF),
            ("20000100#0000000000000000", RESTARTED[1]),
        ]:
            guest.cansend(channel, frame)
            bridge.wait_for_output(report, WAIT_S)
        bridge.wait_for_output(ACTIVE, WAIT_S)
        _commands_flow(channel, "after the error frames")
        phase("down and up")
        guest.run(["ip", "link", "set", channel, "down"])
        guest.wait_until(lambda: DOWN in bridge.output()[phases["down and up"] :], WAIT_S, DOWN)
        time.sleep(1.0)
        guest.run(["ip", "link", "set", channel, "up"])
        _commands_flow(channel, "after down and up")
        phase("deleted and made again")
        guest.run(["ip", "link", "delete", channel])
        guest.wait_until(lambda: GONE in bridge.output()[phases["deleted and made again"] :],
                         WAIT_S, GONE)  # fmt: skip
        time.sleep(3.0)
        guest.run(["ip", "link", "add", "dev", channel, "type", "vcan"])
        guest.run(["ip", "link", "set", channel, "up"])
        _commands_flow(channel, "after the interface was made again")
        bridge.wait_for_output("CAN reader: bus open again", WAIT_S)
        # The main process stalled: the reader's queue overflows with frames its filters pass
        # (an ESC's status, from cangen), while the loop, a process of its own, sends on.
        phase("main process stopped")
        bridge.send(signal.SIGSTOP)
        flood = guest.cangen(
            channel, "-e", "-I", "004E5201", "-L", "8", *("-g", "0", "-p", "10"),
            "-n", str(OVERFLOW_FRAMES),
        )  # fmt: skip
        took_ms = _commands_flow(channel, "while the main process is stopped")
        guest.wait_until(lambda: not flood.running(), WAIT_S, f"cangen's {OVERFLOW_FRAMES} frames")
        bridge.send(signal.SIGCONT)
        guest.wait_until(
            lambda: RECEIVE_LOST[1] in bridge.output()[phases["main process stopped"] :],
            WAIT_S,
            RECEIVE_LOST[1],
        )
        phase("end")
    finally:
        code = bridge.stop()
    output = bridge.output()
    names = list(phases)
    windows = {
        name: output[phases[name] : phases[after]] for name, after in itertools.pairwise(names)
    }
    reports = [STUCK, DOWN, GONE, MOVING, WARNING, PASSIVE, BUS_OFF, ACTIVE]
    reports += [RESTARTED[1], RECEIVE_LOST[1]]
    return {
        "said": {
            name: {text: window.count(text) for text in reports if text in window}
            for name, window in windows.items()
        },
        "exit": code,
        "commands_while_stopped_ms": took_ms,
        "python_can_lines": output.count("Created a socket") + output.count("Could not access"),
        "summary": [line for line in output.splitlines() if "CAN in:" in line],
    }


def test_every_fault_is_reported_once_and_recovered_from(linux: Kernel) -> None:
    found = linux.call(a_bridge_through_every_fault)
    said = found["said"]
    # The controller's reports, once each. (Where the guest's one CPU stalls past the input
    # timeout, a STUCK spell and a full receive queue may come besides, and are told too.)
    controller = (WARNING, PASSIVE, BUS_OFF, RESTARTED[1], ACTIVE)
    assert {text: said["error frames"].get(text) for text in controller} == {
        WARNING: 1, PASSIVE: 1, BUS_OFF: 1, RESTARTED[1]: 1, ACTIVE: 1
    }  # fmt: skip
    assert said["down and up"][DOWN] == 1 and said["down and up"][MOVING] >= 1
    # Made again, the interface is down until set up: DOWN may come before the recovery.
    gone = said["deleted and made again"]
    assert gone[GONE] == 1 and gone[MOVING] >= 1
    assert said["main process stopped"][RECEIVE_LOST[1]] == 1
    assert found["exit"] == 0
    # The loop's process sent on while the main process was stopped: 40 commands at 100 Hz.
    assert found["commands_while_stopped_ms"] < 5000
    assert found["python_can_lines"] == 0
    # Error frames are counted as such (the flood's frames are the malformed ones).
    assert len(found["summary"]) == 1
    assert " malformed, 4 error frames" in found["summary"][0]
