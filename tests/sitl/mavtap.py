"""A recording TCP tap between a bridge and the autopilot, run as a process of its own.

``python mavtap.py LOG LISTEN_PORT UPSTREAM_PORT [LISTEN_PORT UPSTREAM_PORT ...]``

Each pair is one link: the tap listens on 127.0.0.1:LISTEN_PORT; when the bridge connects, it
connects to the autopilot on 127.0.0.1:UPSTREAM_PORT (retrying while the autopilot is not up)
and copies bytes both ways unchanged. When either side closes, it closes the other, as a dead
autopilot's link would, and waits for the bridge to connect again.

Why a tap: the tests must know which motor output the bridge had when each CAN frame went out,
from something that is not the bridge. The tap writes, with the monotonic clock read *before*
it forwards the bytes (so the bridge cannot have seen a message before its stamp), every
SERVO_OUTPUT_RAW (also stamped after the forward: the bridge has it by then) and the
autopilot's HEARTBEAT (armed or not) to LOG, one line each:

    S <link> <t> <t_sent> <time_usec> <servo1> .. <servo8>
    H <link> <t> <armed 0|1>
    E <link> <t> <event>            (connected, upstream, closed)

It runs in its own process so that the test process's threads (observers, the ground station)
never hold a forward up, and it flushes every line so a failed test can read what happened.
"""

from __future__ import annotations

import os
import select
import socket
import sys
import time
from typing import Any, TextIO

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink

SERVO_OUTPUT_RAW = 36
HEARTBEAT = 0
ARMED_FLAG = 128  # MAV_MODE_FLAG_SAFETY_ARMED


class Link:
    def __init__(self, index: int, listen_port: int, upstream_port: int, log: TextIO) -> None:
        self.index = index
        self.upstream_port = upstream_port
        self.server = socket.create_server(("127.0.0.1", listen_port))
        self.server.setblocking(False)
        self.client: socket.socket | None = None
        self.upstream: socket.socket | None = None
        self.parser: Any = None
        self.log = log

    def event(self, what: str) -> None:
        self.log.write(f"E {self.index} {time.monotonic():.6f} {what}\n")
        self.log.flush()

    def close_pair(self) -> None:
        for sock in (self.client, self.upstream):
            if sock is not None:
                sock.close()
        self.client = self.upstream = None
        self.event("closed")

    def accept(self) -> None:
        client, _ = self.server.accept()
        if self.client is not None:  # one bridge per link: a new connection replaces the old
            self.close_pair()
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.client = client
        self.event("connected")

    def try_upstream(self) -> None:
        """Connect to the autopilot; while it is not listening, try again on the next pass."""
        try:
            sock = socket.create_connection(("127.0.0.1", self.upstream_port), timeout=0.2)
        except OSError:
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(True)
        self.upstream = sock
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.event("upstream")

    def from_upstream(self) -> None:
        assert self.upstream is not None and self.client is not None
        try:
            data = self.upstream.recv(65536)
        except OSError:
            data = b""
        if not data:
            self.close_pair()
            return
        # Stamps right before and right after the forward, and the parsing after both: the
        # bridge cannot have the bytes before the first, and has them by the second (however
        # long this process waited for a CPU in between).
        stamp = time.monotonic()
        try:
            self.client.sendall(data)
        except OSError:
            self.close_pair()
            return
        sent = time.monotonic()
        lines = []
        for msg in self.parser.parse_buffer(data) or []:
            msg_id = msg.get_msgId()
            if msg_id == SERVO_OUTPUT_RAW:
                servos = " ".join(str(getattr(msg, f"servo{i}_raw")) for i in range(1, 9))
                lines.append(f"S {self.index} {stamp:.6f} {sent:.6f} {msg.time_usec} {servos}\n")
            elif msg_id == HEARTBEAT and msg.get_srcSystem() == 1 and msg.get_srcComponent() == 1:
                armed = int(bool(msg.base_mode & ARMED_FLAG))
                lines.append(f"H {self.index} {stamp:.6f} {armed}\n")
        if lines:
            self.log.write("".join(lines))
            self.log.flush()

    def from_client(self) -> None:
        assert self.upstream is not None and self.client is not None
        try:
            data = self.client.recv(65536)
            if data:
                self.upstream.sendall(data)
        except OSError:
            data = b""
        if not data:
            self.close_pair()


def main(argv: list[str]) -> None:
    log = open(argv[0], "a", buffering=1)  # noqa: SIM115 - open for the process's life
    ports = [int(p) for p in argv[1:]]
    links = [Link(i, ports[2 * i], ports[2 * i + 1], log) for i in range(len(ports) // 2)]
    log.write(f"E -1 {time.monotonic():.6f} listening\n")
    log.flush()
    while True:
        readable: list[Any] = []
        waiting = False
        for link in links:
            readable.append(link.server)
            if link.client is not None and link.upstream is None:
                waiting = True
            if link.client is not None and link.upstream is not None:
                readable += [link.client, link.upstream]
        ready, _, _ = select.select(readable, [], [], 0.05 if waiting else 0.5)
        for link in links:
            if link.server in ready:
                link.accept()
            if link.client is not None and link.upstream is None:
                link.try_upstream()
            if link.upstream is not None and link.upstream in ready:
                link.from_upstream()
            if link.client is not None and link.upstream is not None and link.client in ready:
                link.from_client()


if __name__ == "__main__":
    main(sys.argv[1:])
