"""The autopilot link shared between the control loop, which owns it, and the main process.

The control loop reads the autopilot's bytes itself (the motor outputs and arming state must
not wait on anything), and the main process still needs the rest of the traffic: commands from
a ground station routed through the autopilot, HEARTBEAT and stream bookkeeping, the
recording. So the loop relays the whole frames it finds (all but the autopilot's outputs,
unless the link is recorded) to the main process, and writes to the autopilot link whatever
frames the main process hands it (its HEARTBEAT, STATUSTEXT, ESC telemetry, command answers,
stream requests).

A relay is a pair of connected ``AF_UNIX``/``SOCK_SEQPACKET`` sockets: message boundaries are
kept (one read's frames, or one frame, per message), the kernel buffers them, and the loop's end is
non-blocking: when the main process falls behind, the loop drops what it cannot hand over and
counts it, and never waits. A closed peer reads as end of file, which is how the loop learns at
once that the main process died (and the main process that the loop did).
"""

from __future__ import annotations

import socket
from dataclasses import dataclass

from bridge.errors import LinkError

_MAX_MESSAGE = 1 << 17  # a UDP datagram's frames (64 KiB at most) fit with room to spare
# The main side waits at most this long to hand a frame to the loop, which drains its end on
# every wake-up; longer means the loop is gone or stopped, and MAVLink is lossy anyway.
_MAIN_SEND_TIMEOUT_S = 0.05
_SOCKET_BUFFER_BYTES = 1 << 20  # ~1 s of a busy autopilot link either way


@dataclass
class LoopEnd:
    """The control loop's end: non-blocking, never waits."""

    sock: socket.socket

    def __post_init__(self) -> None:
        self.sock.setblocking(False)

    def fileno(self) -> int:
        return self.sock.fileno()

    def forward(self, frames: bytes) -> bool:
        """Hand frames read from the autopilot to the main process; False when dropped (the
        main process is behind or gone)."""
        try:
            self.sock.send(frames)
        except (BlockingIOError, ConnectionError, OSError):
            return False
        return True

    def take(self) -> bytes | None:
        """One frame the main process wants written to the autopilot; None when none is
        waiting.

        Raises:
            EOFError: the main process closed its end (it exited or died).
        """
        try:
            frame = self.sock.recv(_MAX_MESSAGE)
        except BlockingIOError:
            return None
        except ConnectionError as exc:
            raise EOFError("the main process's end of the relay is gone") from exc
        if not frame:
            raise EOFError("the main process's end of the relay is closed")
        return frame

    def close(self) -> None:
        self.sock.close()


class MainConnection:
    """The main process's end, shaped like the pymavlink transports :class:`MavlinkLink` reads
    and writes (``fd``, ``recv``, ``write``, ``close``), so the link handles the relayed
    autopilot traffic exactly as it would a socket of its own."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        sock.settimeout(_MAIN_SEND_TIMEOUT_S)
        self.fd = sock.fileno()

    def recv(self, _size: int = 0) -> bytes:
        """The next relayed frames; b'' when none came in time.

        Raises:
            EOFError: the loop closed its end (it stopped or died): the link has ended.
        """
        try:
            message = self._sock.recv(_MAX_MESSAGE)
        except TimeoutError:
            return b""
        except ConnectionError as exc:
            raise EOFError("the control loop closed the autopilot relay") from exc
        if not message:
            raise EOFError("the control loop closed the autopilot relay")
        return message

    def write(self, frame: bytes) -> int:
        """Hand ``frame`` to the loop for the autopilot link; returns its length, or -1 when it
        was dropped, counted by the link as a send failure (as pymavlink's serial write
        reports one)."""
        try:
            self._sock.send(frame)
        except (TimeoutError, OSError):
            return -1
        return len(frame)

    def close(self) -> None:
        self._sock.close()


def relay_pair() -> tuple[socket.socket, socket.socket]:
    """(loop's socket, main process's socket), connected, with room for bursts.

    Raises:
        LinkError: the sockets could not be made (out of descriptors or memory).
    """
    try:
        loop_sock, main_sock = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    except OSError as exc:
        raise LinkError(f"cannot create the autopilot relay: {exc}") from exc
    for sock in (loop_sock, main_sock):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _SOCKET_BUFFER_BYTES)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _SOCKET_BUFFER_BYTES)
    return loop_sock, main_sock
