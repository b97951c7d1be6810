"""Reading a python-can ``udp_multicast`` bus without unpacking the frames a reader refuses.

On ``udp_multicast`` every handle receives every datagram of the bus: there is no kernel filter
as on SocketCAN. The telemetry reader, which wants its ESCs' telemetry only, so reads the
bridge's own commands too (800 a second for 8 ESCs at 400 Hz), and python-can's ``recv``
turns each into a :class:`can.Message` (a msgpack map unpacked, the message checked, a log
call) for the reader to drop: most of the main process's CPU (``bench/cpu.py --profile``).

python-can sends a frame as a msgpack map whose first entries are, in this order, the
timestamp, the arbitration ID and the remote, extended and error flags.
:class:`MulticastReceiver` reads the ID and flags from those bytes and unpacks only the frames
its ``passes`` accepts. A datagram laid out any other way (another sender's packing, another
python-can) is unpacked whole, as python-can does, and judged on the message. The socket is
read directly (a duplicate of the bus's descriptor) with the kernel's receive stamp, as
python-can reads it.
"""

from __future__ import annotations

import os
import re
import select
import socket
import struct
import time
from collections.abc import Callable

import can
from can.interfaces.udp_multicast import UdpMulticastBus
from can.interfaces.udp_multicast.utils import unpack_message

# The head of a frame as python-can packs it: a map of 11 entries, "timestamp" (a float),
# "arbitration_id" (an unsigned int: positive fixint, uint8, 16 or 32: group 1),
# "is_extended_id" (false/true: group 2), "is_remote_frame", "is_error_frame" (false: an error
# frame is never refused, so it is unpacked whole).
_HEAD = re.compile(
    rb"\x8b\xa9timestamp\xcb.{8}"
    rb"\xaearbitration_id([\x00-\x7f]|\xcc.|\xcd..|\xce....)"
    rb"\xaeis_extended_id([\xc2\xc3])"
    rb"\xafis_remote_frame[\xc2\xc3]"
    rb"\xaeis_error_frame\xc2",
    re.DOTALL,
)
_TRUE = 0xC3
DATAGRAM_MAX_BYTES = 4096  # python-can's own receive size
MAX_DROPPED_PER_CALL = 1000
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("@ll")
_ANCILLARY_BYTES = socket.CMSG_SPACE(_TIMESPEC.size)

Passes = Callable[[int, bool], bool]
"""Whether the reader wants a frame of this arbitration ID (and extended flag)."""


def receives_multicast(bus: can.BusABC) -> bool:
    """Whether ``bus`` is a python-can ``udp_multicast`` handle (which this can read)."""
    return isinstance(bus, UdpMulticastBus)


class MulticastReceiver:
    """Receives from one ``udp_multicast`` handle the frames ``passes`` accepts; :meth:`close`
    when done (the handle itself stays open: its owner shuts it down)."""

    def __init__(self, bus: can.BusABC, passes: Passes) -> None:
        """Raises:
        OSError: the handle has no descriptor any more (it was shut down)."""
        self.bus = bus
        self._passes = passes
        self._fd_mode = bus.protocol is can.CanProtocol.CAN_FD
        self._socket = socket.socket(fileno=os.dup(bus.fileno()))
        self._socket.setblocking(False)
        self.dropped = 0
        """Frames read and dropped: refused (most without being unpacked), or CAN FD frames
        on a handle without CAN FD (python-can drops those too)."""
        self.drained = False
        """Whether the last :meth:`recv` that returned None ended on an empty queue (not on
        MAX_DROPPED_PER_CALL)."""

    def recv(self, timeout_s: float | None) -> can.Message | None:
        """The next frame ``passes`` accepts, reading and dropping the others (counted in
        :attr:`dropped`); None when there is none: the queue is empty (:attr:`drained`), or
        MAX_DROPPED_PER_CALL frames were dropped (a flood: the caller gets to look at its
        other duties). It waits up to ``timeout_s`` for a datagram only while it has read
        none: once it has dropped some, an empty queue ends the call, so that a reader may let
        frames gather before it reads again instead of waking for each.

        Raises:
            can.CanOperationError: the socket failed, or a datagram could not be unpacked.
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        sock, head, passes = self._socket, _HEAD.match, self._passes
        dropped_before = self.dropped
        self.drained = False
        while self.dropped - dropped_before < MAX_DROPPED_PER_CALL:
            try:
                data, ancillary, _flags, _sender = sock.recvmsg(
                    DATAGRAM_MAX_BYTES, _ANCILLARY_BYTES
                )
            except BlockingIOError:
                left_s = None if deadline is None else deadline - time.monotonic()
                if (
                    self.dropped != dropped_before
                    or (left_s is not None and left_s <= 0)
                    or not self._wait_readable(left_s)
                ):
                    self.drained = True
                    return None
                continue
            except OSError as exc:
                raise can.CanOperationError(f"cannot read the bus: {exc}") from exc
            found = head(data)
            if found is None:
                # Laid out otherwise: judged on the whole message (an error frame passes).
                msg = self._unpack(data, ancillary)
                if msg is not None and (
                    msg.is_error_frame or passes(msg.arbitration_id, msg.is_extended_id)
                ):
                    return msg
            else:
                encoded = found[1]
                can_id = encoded[0] if len(encoded) == 1 else int.from_bytes(encoded[1:], "big")
                if passes(can_id, found[2][0] == _TRUE):
                    msg = self._unpack(data, ancillary)
                    if msg is not None:
                        return msg
            self.dropped += 1
        return None

    def close(self) -> None:
        self._socket.close()

    def _wait_readable(self, timeout_s: float | None) -> bool:
        """Whether a datagram came within ``timeout_s``.

        Raises:
            can.CanOperationError: the wait failed.
        """
        try:
            return bool(select.select([self._socket], (), (), timeout_s)[0])
        except OSError as exc:
            raise can.CanOperationError(f"cannot wait for the bus: {exc}") from exc

    def _unpack(self, data: bytes, ancillary: list[tuple[int, int, bytes]]) -> can.Message | None:
        """The whole frame, stamped with the kernel's receive time; None for a CAN FD frame on
        a handle without CAN FD (python-can drops those too)."""
        stamp: dict[str, float] = {}
        for level, kind, value in ancillary:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
                seconds, nanoseconds = _TIMESPEC.unpack(value[: _TIMESPEC.size])
                stamp["timestamp"] = seconds + nanoseconds * 1e-9
        try:
            msg = unpack_message(data, replace=stamp, check=True)
        except Exception as exc:  # msgpack and can.Message raise many kinds
            raise can.CanOperationError(f"could not unpack received message: {exc}") from exc
        if msg.is_fd and not self._fd_mode:
            return None
        return msg
