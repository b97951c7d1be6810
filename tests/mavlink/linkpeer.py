"""Shared by the link's tests: real pymavlink endpoints on 127.0.0.1 (one set of free ports per
test), and the fixtures that start links on them.

A :class:`Peer` plays the autopilot, or an intruder: a pymavlink connection whose codec is
pinned to a MAVLink 1 or MAVLink 2 dialect module, so what goes on the wire does not depend
on the ``MAVLINK20`` environment variable that ``mavutil`` reads. The test modules take the
fixtures with ``make_link = linkpeer.make_link`` (an import would shadow the argument).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from conftest import free_port
from pymavlink import mavutil
from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from bridge.config import MavlinkConfig
from bridge.mavlink.link import MavlinkLink

KEY = bytes(range(32))


ARMED = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED


TIMEOUT_S = 3.0


def wait_until(predicate: Callable[[], bool], what: str, timeout_s: float = TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


def wait_messages(link: MavlinkLink, n: int, what: str = "") -> None:
    """Wait until the link has read ``n`` messages from the autopilot's connection."""
    wait_until(lambda: link.stats.messages >= n, what or f"{n} messages read by the link")


class Peer:
    """A pymavlink endpoint on loopback with a MAVLink 1 or 2 codec, optionally signing."""

    def __init__(
        self,
        url: str,
        system: int = 1,
        component: int = 1,
        codec: Any = mavlink2,
        key: bytes | None = None,
        **opts: Any,
    ) -> None:
        self.conn: Any = mavutil.mavlink_connection(
            url, source_system=system, source_component=component, **opts
        )
        self.mav: Any = codec.MAVLink(self.conn, srcSystem=system, srcComponent=component)
        self.mav.robust_parsing = True
        self.conn.mav = self.mav  # so that setup_signing configures this codec
        if key is not None:
            self.conn.setup_signing(
                key, sign_outgoing=True, allow_unsigned_callback=lambda *_: False, link_id=0
            )

    def send(self, msg: Any) -> None:
        self.mav.send(msg)

    def write(self, data: bytes) -> None:
        self.conn.write(data)

    def receive(self, duration_s: float) -> list[tuple[float, Any]]:
        """Everything decoded within ``duration_s``, with monotonic receive times."""
        got: list[tuple[float, Any]] = []
        deadline = time.monotonic() + duration_s
        while time.monotonic() < deadline:
            self.conn.select(0.01)
            data = self.conn.recv(4096)
            if data:
                now = time.monotonic()
                got.extend((now, m) for m in self.mav.parse_buffer(data) or [])
        return got

    def drain(self) -> list[tuple[float, Any]]:
        """Everything decoded that is waiting now, without waiting."""
        got: list[tuple[float, Any]] = []
        while data := self.conn.recv(4096):
            now = time.monotonic()
            got.extend((now, m) for m in self.mav.parse_buffer(data) or [])
        return got

    def wait_for(self, kind: str) -> Any:
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline:
            for _, msg in self.receive(0.02):
                if msg.get_type() == kind:
                    return msg
        raise AssertionError(f"no {kind} within {TIMEOUT_S} s")

    def close(self) -> None:
        self.conn.close()


def servo(mav: Any, port: int, pwm: list[int]) -> Any:
    """SERVO_OUTPUT_RAW of ``pwm`` (padded with 0 = no output) for this codec's channel count."""
    n = 8 if isinstance(mav, mavlink1.MAVLink) else 16
    return mav.servo_output_raw_encode(0, port, *(pwm + [0] * n)[:n])


def heartbeat(mav: Any, armed: bool) -> Any:
    base_mode = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (ARMED if armed else 0)
    return mav.heartbeat_encode(
        mavlink2.MAV_TYPE_QUADROTOR,
        mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
        base_mode,
        0,
        mavlink2.MAV_STATE_ACTIVE,
    )


MakeLink = Callable[..., MavlinkLink]


MakePeer = Callable[..., Peer]


@pytest.fixture
def make_peer() -> Iterator[MakePeer]:
    peers: list[Peer] = []

    def make(url: str, **kwargs: Any) -> Peer:
        peer = Peer(url, **kwargs)
        peers.append(peer)
        return peer

    yield make
    for peer in peers:
        peer.close()


@pytest.fixture
def make_link(make_peer: MakePeer) -> Iterator[MakeLink]:
    """Start a link on a URL with config overrides; closed at the end of the test, before the
    peers (requested here for that order), so that closing does not look like a lost link."""
    links: list[MavlinkLink] = []

    def make(url: str, **config: Any) -> MavlinkLink:
        link = MavlinkLink(MavlinkConfig(url=url, **config))
        links.append(link)
        link.start()
        return link

    yield make
    for link in links:
        link.close()


@pytest.fixture
def udp_address() -> str:
    """The bridge listens here (udpin); peers send to it (udpout)."""
    return f"127.0.0.1:{free_port()}"


USER_1 = mavlink2.MAV_CMD_USER_1


USER_2 = mavlink2.MAV_CMD_USER_2


USER_3 = mavlink2.MAV_CMD_USER_3


ACCEPTED = mavlink2.MAV_RESULT_ACCEPTED


def command(peer: Peer, cmd: int, target: tuple[int, int], param1: float = 0) -> None:
    peer.send(peer.mav.command_long_encode(*target, cmd, 0, param1, 0, 0, 0, 0, 0, 0))


def receive_until(peer: Peer, predicate: Callable[[Any], bool]) -> list[Any]:
    """Everything ``peer`` receives up to and including the first message matching."""
    got: list[Any] = []
    deadline = time.monotonic() + TIMEOUT_S
    while time.monotonic() < deadline:
        for _, msg in peer.receive(0.02):
            got.append(msg)
            if predicate(msg):
                return got
    raise AssertionError(f"nothing matching within {TIMEOUT_S} s; got {len(got)} messages")


def receive_acks(peer: Peer, n: int) -> list[Any]:
    """The first ``n`` COMMAND_ACKs ``peer`` receives, and any that follow within 0.2 s."""
    acks: list[Any] = []
    deadline = time.monotonic() + TIMEOUT_S
    while len(acks) < n:
        assert time.monotonic() < deadline, f"{len(acks)} of {n} COMMAND_ACKs"
        acks += [m for _, m in peer.receive(0.02) if m.get_type() == "COMMAND_ACK"]
    return acks + [m for _, m in peer.receive(0.2) if m.get_type() == "COMMAND_ACK"]
