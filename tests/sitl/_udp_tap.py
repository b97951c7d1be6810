"""The body of the PX4 harness's UDP tap (``_px4.UdpTap``), in a process of its own.

Standard library only, so that a spawned process starts it at once.
"""

from __future__ import annotations

import contextlib
import select
import socket
import time
from typing import Any


def run(listen_port: int, bridge_port: int, record: str, stop: Any, ready: Any) -> None:
    """Relay datagrams between the autopilot (who sends to ``listen_port``) and the bridge
    (listening on ``bridge_port``) until ``stop`` is set; append each datagram from the
    autopilot to ``record`` as: monotonic ns (8 bytes LE), length (4 bytes LE), data."""
    upstream = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    upstream.bind(("127.0.0.1", listen_port))
    downstream = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    downstream.bind(("127.0.0.1", 0))
    upstream.setblocking(False)
    downstream.setblocking(False)
    autopilot: tuple[str, int] | None = None
    poller = select.poll()
    poller.register(upstream.fileno(), select.POLLIN)
    poller.register(downstream.fileno(), select.POLLIN)
    ready.set()
    with open(record, "wb", buffering=0) as out:
        while not stop.is_set():
            for fd, _ in poller.poll(100):
                if fd == upstream.fileno():
                    with contextlib.suppress(BlockingIOError):
                        data, autopilot = upstream.recvfrom(65536)
                        # Stamped before forwarding: the bridge cannot have it any earlier.
                        stamp = time.monotonic_ns()
                        downstream.sendto(data, ("127.0.0.1", bridge_port))
                        out.write(stamp.to_bytes(8, "little") + len(data).to_bytes(4, "little"))
                        out.write(data)
                else:
                    with contextlib.suppress(BlockingIOError):
                        data = downstream.recv(65536)
                        if autopilot is not None:
                            upstream.sendto(data, autopilot)
    upstream.close()
    downstream.close()
