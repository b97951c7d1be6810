"""The autopilot's UDP link end to end through `esc-bridge run`: a datagram is whole frames, and
only the autopilot's address speaks for it (docs/running.md, "Who the bridge listens to on UDP").

The daemon as a subprocess on a udpin link, a pymavlink autopilot on its own socket saying
disarmed, other sockets sending what once armed the bridge, and a udp_multicast observer that
decodes every command frame on the bus. The safety claims run idle and beside two busy
processes on both cores.
"""

from __future__ import annotations

import contextlib
import random
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from conftest import STARTUP_TIMEOUT_S, Autopilot, Daemon, Observer
from datagram_fuzz import ARMED as ARMED_MODE
from datagram_fuzz import DISARMED, fuzz_datagrams, heartbeat, packer
from test_daemon_e2e import ckesc_throttles, expect_throttles

from loadgen.load import preset

HOST = "127.0.0.1"
SAFE = (0, 0, 0, 0)
HOVER = (1000, 1000, 1000, 1000)  # PWM 1500 on a passthrough quad
LOADS = ["idle", "busy2"]
# From the command to the loop's first frame: a hang guard, not a bound. Beside other test
# sessions at load 15 the daemon's interpreter and then the loop's took 15 s in all.
START_TIMEOUT_S = 40.0


def throttles_since(observer: Observer, t: float) -> list[tuple[int, ...]]:
    return [th for m in observer.since(t) if (th := ckesc_throttles(m)) is not None]


def load(name: str) -> contextlib.AbstractContextManager[object]:
    return contextlib.nullcontext() if name == "idle" else preset(name)


@pytest.fixture
def sockets() -> Iterator[Callable[[], socket.socket]]:
    """Plain UDP sockets, each bound to a port of its own (one address each)."""
    made: list[socket.socket] = []

    def make() -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind((HOST, 0))
        made.append(sock)
        return sock

    yield make
    for sock in made:
        sock.close()


def heard(sock: socket.socket, port: int, datagram: bytes) -> None:
    """Send ``datagram`` from ``sock`` until the bridge answers it (its own HEARTBEAT, a second):
    then the bridge's link is open and has read what came from ``sock``."""
    sock.settimeout(0.2)
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while True:
        assert time.monotonic() < deadline, "the bridge never answered"
        sock.sendto(datagram, (HOST, port))
        try:
            sock.recv(4096)
        except TimeoutError:
            continue
        return


def wait_for_frames(observer: Observer) -> None:
    expect_throttles(observer, SAFE, START_TIMEOUT_S)


@pytest.mark.parametrize("loaded", LOADS)
def test_a_heartbeat_cut_short_and_completed_by_another_sender_never_arms_the_bridge(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    mavlink_port: int,
    sockets: Callable[[], socket.socket],
    loaded: str,
) -> None:
    """The targeted repeat of what a fuzz found: fifty times in 2 s, an armed HEARTBEAT "from
    1/1" cut one byte short from one socket, then the missing byte and garbage from another,
    while the autopilot on a third says disarmed. Before each datagram was scanned on its own,
    this sent 805 command frames at the autopilot's last output."""
    daemon = start_daemon()
    wait_for_frames(observer)
    autopilot.pwm = [1500] * 4
    autopilot.start_stream(50)  # disarmed: HEARTBEAT at 10 Hz, outputs at 50 Hz
    cutter, completer = sockets(), sockets()
    mav = packer()
    with load(loaded):
        time.sleep(0.5)
        start = time.monotonic()
        for pair in range(50):
            armed = heartbeat(mav, ARMED_MODE)
            cutter.sendto(armed[:-1], (HOST, mavlink_port))
            completer.sendto(armed[-1:] + bytes([0x13, pair]) + b"garbage", (HOST, mavlink_port))
            time.sleep(0.04)
        time.sleep(0.3)
        seen = throttles_since(observer, start)
    assert len(seen) > 100  # 2.3 s at 400 Hz is 920; the observer keeps enough of them
    assert [t for t in seen if t != SAFE] == []
    assert daemon.stop() == 0
    assert "ESC out: armed" not in daemon.output, daemon.output[-3000:]
    assert "ESC out: disarmed, motors stopped" in daemon.output


@pytest.mark.parametrize("loaded", LOADS)
def test_a_seeded_fuzz_of_datagrams_never_moves_a_motor(
    start_daemon: Callable[..., Daemon],
    observer: Observer,
    mavlink_port: int,
    sockets: Callable[[], socket.socket],
    loaded: str,
) -> None:
    """The fuzz that found it, kept: 10 000 datagrams in about 2.5 s from four sockets, the
    first of them the autopilot (disarmed, outputs at 1500 µs), the others garbage, genuine
    frames claiming to be 1/1 (armed, other outputs), other systems' frames, and frames cut
    anywhere whose rest opens the next datagram. Only safe values reach the bus."""
    daemon = start_daemon()
    wait_for_frames(observer)
    socks = [sockets() for _ in range(4)]
    heard(socks[0], mavlink_port, heartbeat(packer(), DISARMED))
    rng = random.Random(19)
    with load(loaded):
        start = time.monotonic()
        for index, (sender, datagram) in enumerate(fuzz_datagrams(rng, len(socks), 10_000)):
            socks[sender].sendto(datagram, (HOST, mavlink_port))
            if index % 40 == 39:
                time.sleep(0.01)
        time.sleep(0.3)
        seen = throttles_since(observer, start)
    assert len(seen) > 100
    assert [t for t in seen if t != SAFE] == []
    assert daemon.stop() == 0
    output = daemon.output
    assert "ESC out: armed" not in output, output[-3000:]
    assert f"the autopilot 1/1 is at {HOST}:{socks[0].getsockname()[1]}" in output
    named = [f"came from {HOST}:{sock.getsockname()[1]}, not from its address" for sock in socks]
    assert named[0] not in output and all(name in output for name in named[1:]), output[-3000:]


def test_an_autopilot_restarted_on_a_new_port_is_followed_once_the_old_one_is_silent(
    start_daemon: Callable[..., Daemon],
    observer: Observer,
    mavlink_port: int,
    tmp_path: Path,
) -> None:
    """A SITL restarted on a new source port: armed again at once, but its frames are refused
    until its old address has been silent for arming_timeout_ms (1 s here); then the bridge
    follows it, without a restart."""
    config = tmp_path / "bridge.toml"
    config.write_text("[output]\narming_timeout_ms = 1000\n")
    daemon = start_daemon("--config", str(config))
    wait_for_frames(observer)
    first = Autopilot(mavlink_port)
    try:
        first.pwm = [1500] * 4
        first.armed = True
        first.start_stream(50)
        expect_throttles(observer, HOVER, STARTUP_TIMEOUT_S)
    finally:
        first.close()  # its thread has sent its last datagram when this returns
    silent_from = time.monotonic()
    restarted = Autopilot(mavlink_port)
    try:
        restarted.pwm = [1500] * 4
        restarted.armed = True
        restarted.start_stream(50)
        back_at = expect_throttles(observer, HOVER, STARTUP_TIMEOUT_S, after=silent_from + 0.2)
        new_port = restarted.conn.port.getsockname()[1]
    finally:
        restarted.close()
    # Not before the old address had been silent for the timeout (the stamps are the kernel's,
    # the clocks the same monotonic one): a load can only make it later.
    assert back_at - silent_from >= 0.95
    assert set(throttles_since(observer, silent_from + 0.2)) - {SAFE, HOVER} == set()
    daemon.stop()
    assert f"the autopilot 1/1 now speaks from {HOST}:{new_port}" in daemon.output
    assert f"came from {HOST}:{new_port}, not from its address" in daemon.output
