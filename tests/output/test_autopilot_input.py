"""The loop's input side on real sockets: a UDP datagram is scanned on its own, the autopilot is
tied to one address, and frames claiming to be it from anywhere else are refused and counted.

Each test drives :class:`AutopilotInput` itself, one datagram at a time (sent on loopback, then
read), so what each datagram did is known; the daemon as a whole is in
tests/test_udp_link_e2e.py.
"""

from __future__ import annotations

import random
import select
import socket
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest
from conftest import free_port
from datagram_fuzz import ARMED, AUTOPILOT_PWM, DISARMED, fuzz_datagrams, heartbeat, packer, servo

from bridge.config import build_config
from bridge.daemon.preflight import plan
from bridge.mavlink.autopilot_address import address_code
from bridge.mavlink.relay import LoopEnd, relay_pair
from bridge.output.autopilot_input import AutopilotInput, InputSetup
from bridge.output.mailbox import InputSnapshot, LoopStats
from bridge.output.safety import ControlInputs

HOST = "127.0.0.1"


@dataclass
class Rig:
    """An :class:`AutopilotInput` opened on ``url``, its relay's main end, and the sockets that
    send to it (each bound to its own port: one address each)."""

    input: AutopilotInput
    inputs: ControlInputs
    stats: LoopStats
    snapshot: InputSnapshot
    main_end: socket.socket
    port: int
    senders: list[socket.socket] = field(default_factory=list)

    def sender(self) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind((HOST, 0))
        sock.settimeout(2.0)
        self.senders.append(sock)
        return sock

    def deliver(self, sock: socket.socket, data: bytes) -> None:
        """Send one datagram from ``sock`` and have the input side read it."""
        sock.sendto(data, (HOST, self.port))
        fd = self.input.fd
        assert fd is not None
        assert select.select([fd], [], [], 5.0)[0], "the datagram never arrived"
        self.input.on_readable(time.monotonic_ns())

    def relayed(self) -> bytes:
        """Everything relayed to the main process so far."""
        out = b""
        self.main_end.setblocking(False)
        try:
            while True:
                out += self.main_end.recv(1 << 17)
        except BlockingIOError:
            return out

    def close(self) -> None:
        self.input.close()
        self.main_end.close()
        for sock in self.senders:
            sock.close()


@pytest.fixture
def rig() -> Iterator[Callable[..., Rig]]:
    made: list[Rig] = []

    def make(kind: str = "udpin", peer: int = 0, arming_timeout_ms: int = 3000) -> Rig:
        port = peer or free_port()
        raw = {
            "mavlink": {"url": f"{kind}:{HOST}:{port}"},
            "can": {"interface": "virtual", "channel": "unused"},
            "output": {"arming_timeout_ms": arming_timeout_ms},
            "zenoh": {"enabled": False},
        }
        checked = plan(build_config(raw, "test"))
        stats, inputs = LoopStats(), ControlInputs()
        snapshot = InputSnapshot(len(checked.mixer.outputs))
        loop_end, main_end = relay_pair()
        setup = InputSetup(checked.mixer, checked.valid_range, None)
        side = AutopilotInput(checked.config, setup, inputs, stats, snapshot, LoopEnd(loop_end))
        side.open()
        made.append(Rig(side, inputs, stats, snapshot, main_end, port))
        return made[-1]

    yield make
    for made_rig in made:
        made_rig.close()


def autopilot_known(rig: Rig) -> tuple[socket.socket, Any]:
    """The autopilot, 1/1 on a socket of its own, heard once (disarmed): its address is known."""
    sock, mav = rig.sender(), packer()
    rig.deliver(sock, heartbeat(mav, DISARMED))
    assert rig.stats["link_autopilot_address"] == address_code(sock.getsockname())
    assert rig.stats["input_heartbeats"] == 1 and not rig.inputs.armed
    return sock, mav


# -- a datagram is whole frames ---------------------------------------------------------------


@pytest.mark.parametrize("cutter", ["another sender", "the autopilot"])
@pytest.mark.parametrize("completer", ["another sender", "the cutter"])
@pytest.mark.parametrize("cut", [1, 2, 7])
def test_a_frame_cut_short_is_never_completed_by_the_next_datagram(
    rig: Callable[..., Rig], cutter: str, completer: str, cut: int
) -> None:
    """An armed HEARTBEAT "from 1/1" cut ``cut`` bytes short; the next datagram starts with the
    missing bytes, then garbage. Neither, nor both together, is a frame."""
    r = rig()
    autopilot, _ = autopilot_known(r)
    cutting = autopilot if cutter == "the autopilot" else r.sender()
    completing = cutting if completer == "the cutter" else r.sender()
    armed = heartbeat(packer(), ARMED)
    junk_before = r.stats["input_junk_bytes"]
    for _ in range(5):
        r.deliver(cutting, armed[:-cut])
        r.deliver(completing, armed[-cut:] + b"\x00\x13garbage\xfe")
        assert not r.inputs.armed
    assert r.stats["input_heartbeats"] == 1
    assert r.stats["input_other_address"] == 0  # no frame at all: nothing claimed anything
    assert r.stats["input_junk_bytes"] - junk_before == 5 * (len(armed) + 10)
    # The same bytes whole, from the autopilot: a frame, obeyed.
    r.deliver(autopilot, armed)
    assert r.inputs.armed


def test_a_stream_still_carries_a_partial_frame_to_the_next_read(
    rig: Callable[..., Rig],
) -> None:
    """TCP (and serial) reads cut a byte stream anywhere: a frame spans two reads."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as listener:
        listener.bind((HOST, 0))
        listener.listen(1)
        r = rig("tcp", peer=listener.getsockname()[1])
        deadline = time.monotonic() + 5
        listener.settimeout(0.05)
        conn = None
        while conn is None:
            assert time.monotonic() < deadline, "the input side never connected"
            r.input.service(time.monotonic_ns())
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
        with conn:
            armed = heartbeat(packer(), ARMED)
            fd = r.input.fd
            assert fd is not None
            for part in (armed[:-1], armed[-1:]):
                conn.sendall(part)
                assert select.select([fd], [], [], 5.0)[0]
                r.input.on_readable(time.monotonic_ns())
    assert r.inputs.armed
    assert r.stats["link_autopilot_address"] == 0  # a stream has no addresses to tie


# -- the autopilot's address ------------------------------------------------------------------


def test_frames_claiming_the_autopilot_from_another_address_are_refused_counted_and_not_relayed(
    rig: Callable[..., Rig],
) -> None:
    r = rig()
    autopilot, mav = autopilot_known(r)
    assert r.relayed() == heartbeat(mav, DISARMED)
    impostor, impostor_mav = r.sender(), packer()
    foreign_mav = packer(system=2)
    own_beat = heartbeat(foreign_mav, ARMED)  # 2/1 speaking for itself: foreign, relayed
    r.deliver(impostor, heartbeat(impostor_mav, ARMED) + servo(impostor_mav, 1900) + own_beat)
    assert not r.inputs.armed
    assert r.stats["input_other_address"] == 2
    assert r.stats["input_other_address_from"] == address_code(impostor.getsockname())
    assert r.stats["input_foreign"] == 1
    assert r.stats["link_autopilot_address"] == address_code(autopilot.getsockname())
    assert r.relayed() == own_beat  # the impostor's 1/1 frames go nowhere
    snapshot = r.snapshot.read()
    assert snapshot is not None and snapshot.inputs == ()  # no output acted on
    # The autopilot itself goes on as before.
    beat = heartbeat(mav, ARMED)
    r.deliver(autopilot, beat + servo(mav, 1500))
    assert r.inputs.armed and r.stats["input_outputs"] == 1
    assert r.relayed() == beat


def test_before_the_autopilot_is_known_other_frames_neither_take_its_place_nor_are_refused(
    rig: Callable[..., Rig],
) -> None:
    r = rig()
    early = r.sender()
    mav = packer()
    status = bytes(mav.system_time_encode(0, 1000).pack(mav))  # 1/1, but no control message
    r.deliver(early, status)
    assert r.stats["link_autopilot_address"] == 0 and r.stats["input_other_address"] == 0
    assert r.relayed() == status
    autopilot_known(r)  # its first control message makes it the autopilot
    r.relayed()
    r.deliver(early, status)
    assert r.stats["input_other_address"] == 1 and r.relayed() == b""


def test_replies_go_to_the_autopilot_once_known_whoever_sent_last(
    rig: Callable[..., Rig],
) -> None:
    r = rig()
    autopilot, _ = autopilot_known(r)
    other = r.sender()
    r.deliver(other, b"\x00junk")  # the latest sender, as pymavlink's udpin would reply to
    reply = heartbeat(packer(component=191), 0)
    r.main_end.setblocking(True)
    r.main_end.send(reply)
    fd = r.input.fd
    assert fd is not None
    r.input.on_relay()
    assert autopilot.recv(1000) == reply
    other.settimeout(0.1)
    with pytest.raises(TimeoutError):
        other.recv(1000)


def test_a_silent_autopilot_is_replaced_after_the_arming_timeout_and_forgotten(
    rig: Callable[..., Rig],
) -> None:
    """A SITL restarted on a new source port: its frames are refused while the old address
    speaks and until it has been silent for arming_timeout_ms; then the new one is the
    autopilot, disarmed until its own HEARTBEAT says otherwise."""
    r = rig(arming_timeout_ms=500)
    old, mav = autopilot_known(r)
    r.deliver(old, heartbeat(mav, ARMED) + servo(mav, 1500))
    assert r.inputs.armed
    silent_from = time.monotonic()
    new, new_mav = r.sender(), packer()
    r.deliver(new, heartbeat(new_mav, DISARMED))
    assert r.inputs.armed and r.stats["input_other_address"] == 1  # refused: the old one spoke
    time.sleep(max(0.0, silent_from + 0.6 - time.monotonic()))
    r.deliver(new, servo(new_mav, 1100, time_us=5_000_000))  # a new boot's clock
    assert r.stats["link_autopilot_address"] == address_code(new.getsockname())
    assert r.stats["link_autopilot_moves"] == 1
    assert not r.inputs.armed  # the old one's arming state is forgotten
    r.deliver(new, heartbeat(new_mav, ARMED))
    assert r.inputs.armed
    r.deliver(old, heartbeat(mav, DISARMED))  # the old address, back: refused now
    assert r.inputs.armed and r.stats["input_other_address"] == 2


def test_udpout_accepts_the_autopilot_only_from_its_configured_address(
    rig: Callable[..., Rig],
) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as autopilot:
        autopilot.bind((HOST, 0))
        autopilot.settimeout(2.0)
        r = rig("udpout", peer=autopilot.getsockname()[1])
        assert r.stats["link_autopilot_address"] == address_code(autopilot.getsockname())
        r.main_end.send(heartbeat(packer(component=191), 0))  # the bridge speaks first
        r.input.on_relay()
        bridge = autopilot.recvfrom(1000)[1]
        r.port = bridge[1]
        impostor, mav = r.sender(), packer()
        r.deliver(impostor, heartbeat(mav, ARMED))  # before the autopilot ever spoke
        assert not r.inputs.armed and r.stats["input_other_address"] == 1
        autopilot.sendto(heartbeat(mav, ARMED), bridge)
        fd = r.input.fd
        assert fd is not None and select.select([fd], [], [], 5.0)[0]
        r.input.on_readable(time.monotonic_ns())
        assert r.inputs.armed


# -- the fuzz that found it -------------------------------------------------------------------

FUZZ_SEED = 19
FUZZ_DATAGRAMS = 10_000


def test_a_seeded_fuzz_of_datagrams_from_several_senders_never_arms(
    rig: Callable[..., Rig],
) -> None:
    """10 000 datagrams from four sockets: the autopilot (disarmed, outputs at 1500) and three
    that send garbage, genuine frames claiming 1/1 (armed, other outputs), other systems'
    frames, and frames cut anywhere whose rest opens the next datagram, whoever sends it. Not
    one datagram arms the input side or brings it an output other than the autopilot's."""
    r = rig()
    socks = [r.sender() for _ in range(4)]
    r.deliver(socks[0], heartbeat(packer(), DISARMED))
    rng = random.Random(FUZZ_SEED)
    started = time.monotonic()
    for sender, datagram in fuzz_datagrams(rng, len(socks), FUZZ_DATAGRAMS):
        r.deliver(socks[sender], datagram)
        assert not r.inputs.armed, f"armed by {datagram.hex()} from sender {sender}"
        snapshot = r.snapshot.read()
        assert snapshot is None or set(snapshot.inputs[:8]) <= {float(AUTOPILOT_PWM)}
    elapsed_s = time.monotonic() - started
    stats = r.stats
    # The seeded run: 151 HEARTBEATs and 1 354 outputs from the autopilot, 1 115 frames
    # refused, 183 949 junk bytes.
    assert stats["input_heartbeats"] > 100 and stats["input_outputs"] > 1000
    assert stats["input_other_address"] > 1000 and stats["input_junk_bytes"] > 150_000
    assert stats["link_autopilot_address"] == address_code(socks[0].getsockname())
    assert elapsed_s < 60  # 3.6 s at load 12: a hang, not a timing bound
