"""What a bus that holds frames costs in commands delivered late, measured on a real kernel: the
guest's side of ``bench/late_frames.py`` (and of ``test_late_frames.py``).

:func:`hold_through_a_disarm`: the bridge (CKESC x4, the passthrough mixer) runs on a vcan with
``echo=1``, a pymavlink autopilot armed at half throttle (PWM 1500) streaming to it. A netem
qdisc then delays every frame on the interface by the hold; halfway through the hold the
autopilot disarms and stops its outputs (the input goes stale); at the hold's end the delay is
set to 0 (what netem holds still leaves at its time). candump, the ESCs' view, times every
frame as the kernel delivered it. The figure: the command frames other than the safe values
(the live throttle) delivered after the disarm, and how long after it the last one came.

:func:`transmit_cost` and :func:`send_buffer_frames`: what the loop's transmit side costs a tick,
three ways, and how many frames a socket's send buffer holds (the skb truesize of a CAN frame).
"""

from __future__ import annotations

import contextlib
import os
import socket
import struct
import subprocess
import sys
import sysconfig
import time
from pathlib import Path
from typing import Any

import can
from conftest import free_port

from bridge.can_io import open_bus
from bridge.config import CanConfig
from bridge.output.transmit import CAN_FRAME_TRUESIZE, transmitter_for
from linux import guest

CKESC_COMMAND = "004E8500:00FFFF00"  # candump's filter: CKESC RawCommand_12b from any node
_COMMAND_TYPE = 20101
WAIT_S = 120.0


def _command_payloads(dump: guest.Candump) -> list[tuple[float, bytes]]:
    """(delivery time, data without the tail byte) of every command frame so far."""
    found = []
    for when, frame in dump.frames():
        can_id, data = frame.split("#")
        if (int(can_id, 16) >> 8) & 0xFFFF == _COMMAND_TYPE:
            found.append((when, bytes.fromhex(data)[:-1]))
    return found


def hold_through_a_disarm(
    hold_ms: int, rate_hz: int, code: str = "", loaded: bool = False
) -> dict[str, Any]:
    """One hold of ``hold_ms`` (0: none, the reference) with the bridge at ``rate_hz``, run from
    the checkout or from ``code`` (a directory holding another version's ``bridge`` package);
    ``loaded``: two busy processes and a flood of other frames on the interface throughout."""
    channel = guest.vcan()
    if loaded:
        for _ in range(2):
            guest.start([sys.executable, "-c", "while True: pass"], "busy")
        guest.cangen(channel, "-g", "1", "-I", "7FF", "-L", "8")
    port = free_port()
    argv = ["run", "--can-interface", "socketcan", "--can-channel", channel]
    argv += ["--mavlink", f"udpin:127.0.0.1:{port}", "--no-zenoh", "--rate", str(rate_hz)]
    if code:
        # Without site (-S), the venv's editable install of the checkout does not take the
        # import of `bridge` first; its dependencies come from its site-packages, on the path.
        # The loop's process is spawned with the same flags and environment.
        purelib = sysconfig.get_paths()["purelib"]
        main = "import sys; from bridge.cli import main; sys.exit(main())"
        bridge = guest.start(
            [sys.executable, "-S", "-P", "-c", main, *argv],
            "bridge",
            {"PYTHONPATH": f"{code}{os.pathsep}{purelib}"},
        )
    else:
        bridge = guest.start([guest.ESC_BRIDGE, *argv], "bridge")
    bridge.wait_for_output("output loop runs", WAIT_S)
    # The filter in the interface's argument: one socket (Candump adds its argument last, and
    # a second argument would be a second socket, every frame counted twice).
    dump = guest.Candump(f"{channel},{CKESC_COMMAND}", "-r", str(8 << 20))
    guest.wait_until(lambda: bool(guest.receivers(channel)), WAIT_S, "candump's socket")
    guest.wait_until(lambda: len(_command_payloads(dump)) > 10, WAIT_S, "safe values")
    safe = _command_payloads(dump)[-1][1]
    autopilot = guest.Autopilot(port)
    autopilot.armed = True
    autopilot.pwm = [1500] * 8
    autopilot.start_stream(50.0)
    hold_s = hold_ms / 1000
    try:
        bridge.wait_for_output("ESC out: armed, sending motor commands", WAIT_S)
        time.sleep(1.0)
        if hold_ms:
            _netem(channel, "add", hold_ms)
        held_at = time.monotonic()
        time.sleep(hold_s / 2)
        autopilot.armed = False
        autopilot.pause_outputs()
        disarmed_at = time.time()
        time.sleep(max(0.0, held_at + hold_s - time.monotonic()))
        if hold_ms:
            _netem(channel, "change", 0)
        # Everything held leaves by then: the hold, a probe's own hold, the 2 s before a probe.
        time.sleep(hold_s + (2.0 + hold_s if hold_s >= 2.0 else 0.0) + 1.5)
    finally:
        autopilot.close()
        bridge.stop()
        dump.stop()
    live_after = [when - disarmed_at for when, data in _command_payloads(dump) if data != safe]
    live_after = [late for late in live_after if late > 0]
    output = bridge.output()
    return {
        "hold_ms": hold_ms,
        "live_after": len(live_after),
        "latest_ms": round(1000 * max(live_after), 1) if live_after else 0.0,
        "stuck_reports": output.count("CAN: FAULT bus stuck"),
        "summary": [line for line in output.splitlines() if "output loop:" in line],
    }


def _netem(channel: str, action: str, delay_ms: int) -> None:
    guest.run(["tc", "qdisc", action, "dev", channel, "root", "netem", "delay", f"{delay_ms}ms",
               "limit", "100000"])  # fmt: skip


def transmit_cost(frames: int, ticks: int) -> dict[str, float]:
    """CPU per tick (µs, this process) of writing ``frames`` frames three ways: python-can's
    ``send`` (what the loop did before), :class:`~bridge.output.transmit.SocketcanTransmitter`
    (raw sends, then the echoes read back), and raw sends with one ``SO_MEMINFO`` read."""
    channel = guest.vcan()
    config = CanConfig("socketcan", channel)
    messages = [can.Message(arbitration_id=0x1000 + i, data=bytes(8)) for i in range(frames)]
    cost: dict[str, float] = {}

    def measure(name: str, tick: Any) -> None:
        tick()
        started = time.process_time_ns()
        for _ in range(ticks):
            tick()
        cost[name] = round((time.process_time_ns() - started) / ticks / 1000, 1)

    bus = open_bus(config, 500_000, receive="none")
    measure("python-can send", lambda: [bus.send(m, timeout=0) for m in messages])
    bus.shutdown()
    bus = open_bus(config, 500_000, receive="none")
    tx = transmitter_for(bus, 10**9)
    measure("raw send + echoes read", lambda: tx.send_tick(messages, time.monotonic_ns()))
    sock: socket.socket = bus.socket  # type: ignore[attr-defined]
    packed = [struct.pack("=IB3x8s", m.arbitration_id | 0x80000000, 8, bytes(8)) for m in messages]

    def meminfo_tick() -> None:
        for data in packed:
            sock.send(data, socket.MSG_DONTWAIT)
        sock.getsockopt(socket.SOL_SOCKET, 55, 12)  # SO_MEMINFO up to wmem_alloc

    sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_RECV_OWN_MSGS, 0)
    measure("raw send + SO_MEMINFO", meminfo_tick)
    bus.shutdown()
    return cost


def send_buffer_frames() -> dict[str, Any]:
    """CAN frames a socket's send buffer takes while the interface holds them all (a plug
    qdisc, which keeps them charged to the socket, unlike netem): with the default buffer, the
    least the kernel allows (SO_SNDBUF 1: SOCK_MIN_SNDBUF) and the transmitter's for 8 frames;
    the buffer's fill after each frame is the frame's skb truesize."""
    modules = Path("/usr/lib/uml/modules", os.uname().release, "kernel/net/sched/sch_plug.ko")
    with contextlib.suppress(subprocess.CalledProcessError):
        guest.run(["insmod", str(modules)] if modules.exists() else ["modprobe", "sch_plug"])
    found: dict[str, Any] = {}
    for name, size in (
        ("default", None),
        ("least", 1),
        ("transmitter, 8 frames", 8 * CAN_FRAME_TRUESIZE // 2),
    ):
        channel = guest.vcan()
        guest.run(["tc", "qdisc", "add", "dev", channel, "root", "plug", "limit", "10000000"])
        guest.run(["tc", "qdisc", "change", "dev", channel, "root", "plug", "block"])
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        sock.bind((channel,))
        if size is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, size)
        fills: list[int] = []
        while len(fills) < 10_000:
            try:
                sock.send(struct.pack("=IB3x8s", 0x80001000, 8, bytes(8)), socket.MSG_DONTWAIT)
            except BlockingIOError:
                break
            fills.append(struct.unpack("9I", sock.getsockopt(socket.SOL_SOCKET, 55, 36))[2])
        found[name] = {
            "sndbuf": sock.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF),
            "frames": len(fills),
            "truesize": fills[0],
        }
        sock.close()
        guest.run(["ip", "link", "delete", channel])
    return found
