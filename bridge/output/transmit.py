"""The output loop's transmit side of the bus: each tick's frames out without blocking, and never
a tick written behind frames the kernel still holds.

A frame written to a socket belongs to the kernel: the bridge cannot take it back. On a bus that
holds frames (ESCs unpowered at boot so nothing acknowledges, an error-passive controller, a
loose connector) the controller retries the head frame while the rest wait in the queue, and
when the bus moves again they all go out at wire speed, the first one as old as the outage: a
command that reaches an ESC late. So on SocketCAN (:class:`SocketcanTransmitter`):

- **Frames in flight are counted by their echo.** The socket receives its own frames back
  (``CAN_RAW_RECV_OWN_MSGS``) once they have left: a controller with ``IFF_ECHO`` echoes a frame
  when its transmission completed, vcan with ``echo=1`` when it passed the queue, and the CAN
  core at once where the driver cannot. A kernel filter on the loop's own command IDs keeps
  every other frame out. A tick is written only when every frame of the ticks before it has
  left; otherwise it is held back (counted in :attr:`~SocketcanTransmitter.ticks_held`), and
  the next tick decides again with what is current then. So the kernel holds at most one
  tick's frames, at most one command per ESC, whatever the outage's length.
- **Why the echo, not the send buffer's fill.** ``getsockopt(SO_MEMINFO)``'s ``wmem_alloc``
  says the same with one call a tick and no read per frame, but only for frames in the queue:
  a driver with ``IFF_ECHO`` uncharges a frame when it takes it into its transmit buffers
  (can_put_echo_skb keeps a clone owned by ``sock_efree``), and netem uncharges every frame
  it delays, so neither a frame in a USB adapter's buffers nor a netem hold shows there.
  Reading the echoes costs one ``recv`` per frame, fewer system calls than python-can's
  ``send`` (a ``select`` and a ``send`` per frame), which this replaces.
- **The send buffer at its least.** ``SO_SNDBUF`` is set to hold one tick's frames and no more
  (:data:`CAN_FRAME_TRUESIZE` each; the kernel's floor is ``SOCK_MIN_SNDBUF``, 4608 bytes, six
  frames): where the echo cannot tell (a driver without ``IFF_ECHO``), the kernel itself
  refuses a seventh frame rather than queue it.
- **What the kernel drops, it says.** A restarted controller (``CAN_ERR_RESTARTED``, an
  error frame this socket also asks for) and an interface taken down (``ENETDOWN``) drop what
  they held, unsent: nothing is in flight afterwards. Where a frame is dropped without a word
  (a queueing discipline replaced by hand), its echo never comes: after
  :data:`PROBE_AFTER_S` without an echo, while the send buffer is empty (so no frame of ours
  waits in the queue), the count is taken for lost and one tick goes out; the wait doubles
  while nothing comes back.

On other interfaces (:class:`PlainTransmitter`: udp_multicast, virtual, serial adapters) a frame
leaves at once or fails, and python-can's ``send`` is used as it is.

Each tick the loop calls :meth:`~SocketcanTransmitter.send_tick`; :attr:`state` is a
:class:`TxState` the supervisor reports. An error that means the bus is gone (the interface was
deleted) is raised as :class:`BusGone`, and the loop reopens the bus with a backoff.
"""

from __future__ import annotations

import enum
import errno
import logging
import socket
import struct
import sys
from collections.abc import Sequence
from typing import Final, Protocol

import can

from bridge.can_io import is_transient

log = logging.getLogger(__name__)

__all__ = [
    "CAN_FRAME_TRUESIZE",
    "PROBE_AFTER_S",
    "BusGone",
    "PlainTransmitter",
    "SocketcanTransmitter",
    "Transmitter",
    "TxState",
    "transmitter_for",
]

CAN_FRAME_TRUESIZE: Final = 768
"""What one classic CAN frame costs a socket's send buffer (its sk_buff's truesize): measured on
Linux 6.1, x86-64 (a 512-byte data block and the 256-byte sk_buff; the same sizes on arm64),
by ``bench/late_frames.py --truesize``."""
PROBE_AFTER_S: Final = 2.0
"""How long frames may go without an echo, the send buffer empty, before their count is taken
for lost (see the module docstring); doubled while nothing comes back, up to
:data:`PROBE_AFTER_MAX_S`."""
PROBE_AFTER_MAX_S: Final = 16.0

# linux/can.h, linux/can/raw.h, linux/can/error.h; asm-generic/socket.h.
_CAN_EFF_FLAG: Final = 0x80000000
_CAN_RTR_FLAG: Final = 0x40000000
_CAN_EFF_MASK: Final = 0x1FFFFFFF
_CAN_SFF_MASK: Final = 0x000007FF
_CAN_ERR_RESTARTED: Final = 0x100
_SOL_CAN_RAW: Final = 101
_CAN_RAW_FILTER: Final = 1
_CAN_RAW_ERR_FILTER: Final = 2
_CAN_RAW_RECV_OWN_MSGS: Final = 4
_AF_CAN: Final = 29
_SO_MEMINFO: Final = 55
_WMEM_END: Final = 4 * 3  # SO_MEMINFO's u32 array up to SK_MEMINFO_WMEM_ALLOC, its third
_CAN_FRAME: Final = struct.Struct("=IB3x8s")  # struct can_frame: id, dlc, pad, data
_FILTER: Final = struct.Struct("=II")  # struct can_filter: id, mask
# The top byte of can_id, where CAN_ERR_FLAG (bit 29) is, in the host's byte order.
_ID_TOP_BYTE: Final = 3 if sys.byteorder == "little" else 0
_ERR_FLAG_IN_TOP_BYTE: Final = 0x20
# Send errors that mean the interface is down (the socket stays good and works again once it is
# up), and those that mean the socket's interface is gone (deleted: the socket is unbound).
_DOWN_ERRNOS: Final = frozenset({errno.ENETDOWN})
_GONE_ERRNOS: Final = frozenset({errno.ENODEV, errno.ENXIO, errno.EBADF})


class TxState(enum.IntEnum):
    """How the loop's frames are leaving, worst last."""

    MOVING = 0
    """Frames leave (or the interface cannot tell: it is not SocketCAN)."""
    STUCK = 1
    """No tick could be written for longer than the stuck time: frames written before have not
    left (nothing acknowledges them, or the controller is bus-off) or the queue is full."""
    DOWN = 2
    """The interface is down: every send fails until it is up again."""
    GONE = 3
    """The interface is gone (deleted, a USB adapter unplugged): the loop reopens the bus."""


class BusGone(Exception):
    """The bus handle cannot be used again (its interface was deleted, or an unknown error):
    the loop closes it and reopens the bus."""


class Transmitter(Protocol):
    """What the loop sends through."""

    state: TxState
    ticks_held: int
    send_errors: int
    probes: int

    def send_tick(self, frames: Sequence[can.Message], now_ns: int) -> int:
        """Write one tick's frames (or none); the number written.

        Raises:
            BusGone: the handle is unusable; reopen the bus.
        """
        ...


def transmitter_for(bus: can.BusABC, stuck_after_ns: int) -> Transmitter:
    """The transmitter for ``bus``: :class:`SocketcanTransmitter` on a SocketCAN socket
    (python-can's ``SocketcanBus.socket``), else :class:`PlainTransmitter`.

    ``stuck_after_ns``: how long ticks may be held back before :attr:`Transmitter.state` says
    :attr:`TxState.STUCK`.
    """
    sock = getattr(bus, "socket", None)
    if isinstance(sock, socket.socket) and sock.family == _AF_CAN:
        try:
            return SocketcanTransmitter(sock, stuck_after_ns)
        except OSError as exc:
            log.warning(
                "CAN frames in flight cannot be counted on %s (%s): frames are sent as they "
                "come, and a bus that holds them is not seen",
                bus.channel_info,
                exc,
            )
    return PlainTransmitter(bus, stuck_after_ns)


class PlainTransmitter:
    """python-can's ``send`` on an interface whose frames leave at once or fail."""

    def __init__(self, bus: can.BusABC, stuck_after_ns: int) -> None:
        self._send = bus.send
        self._stuck_after_ns = stuck_after_ns
        self._failing_since_ns = 0
        self.state = TxState.MOVING
        self.ticks_held = 0
        self.send_errors = 0
        self.probes = 0

    def send_tick(self, frames: Sequence[can.Message], now_ns: int) -> int:
        sent = 0
        send = self._send
        for frame in frames:
            try:
                send(frame, timeout=0)
            except (can.CanError, OSError) as exc:
                self.send_errors += 1
                if not is_transient(exc):
                    raise BusGone(str(exc)) from exc
                break  # the rest of this tick would fail the same way
            sent += 1
        if sent == len(frames):
            self._failing_since_ns = 0
            self.state = TxState.MOVING
        else:
            if not self._failing_since_ns:
                self._failing_since_ns = now_ns
            if now_ns - self._failing_since_ns >= self._stuck_after_ns:
                self.state = TxState.STUCK
        return sent


class SocketcanTransmitter:
    """A raw CAN socket, its frames counted in flight by their echo (the module docstring)."""

    def __init__(self, sock: socket.socket, stuck_after_ns: int) -> None:
        self._sock = sock
        self._stuck_after_ns = stuck_after_ns
        self._send = sock.send
        self._recv_into = sock.recv_into
        self._buf = bytearray(_CAN_FRAME.size)
        self._ids: set[int] = set()  # the can_ids (with their flags) this socket has sent
        self._sized_for = 0  # the most frames of one tick the send buffer was sized for
        self.in_flight = 0
        """Frames written whose echo has not come back."""
        self.state = TxState.MOVING
        self.ticks_held = 0
        """Ticks not written because frames of an earlier one were still in the kernel."""
        self.send_errors = 0
        """Frames the kernel refused (queue full, interface down or gone)."""
        self.probes = 0
        """Ticks written after their predecessors' echoes were taken for lost."""
        self._held_since_ns = 0  # when this spell of held ticks began; 0: frames are leaving
        self._echo_ns = 0  # when frames last left (or the spell began)
        self._probe_after_ns = int(PROBE_AFTER_S * 1e9)
        # Our echoes (each ID joins the filter with its first frame) and the error class that
        # says the controller dropped what it held; nothing else.
        sock.setsockopt(_SOL_CAN_RAW, _CAN_RAW_FILTER, b"")
        sock.setsockopt(_SOL_CAN_RAW, _CAN_RAW_RECV_OWN_MSGS, 1)
        sock.setsockopt(_SOL_CAN_RAW, _CAN_RAW_ERR_FILTER, _CAN_ERR_RESTARTED)
        self._size_send_buffer(1)

    def send_tick(self, frames: Sequence[can.Message], now_ns: int) -> int:
        try:
            self._take_echoes(now_ns)
            if self.in_flight:
                self._not_leaving(now_ns)
                if not self._probe(now_ns):
                    self.ticks_held += 1
                    return 0
            sent = self._write(frames)
        except OSError as exc:
            return self._failed(exc, now_ns)
        if sent < len(frames):  # the queue is full (ENOBUFS, EAGAIN): the rest waits
            self._not_leaving(now_ns)
        elif self._held_since_ns == 0 or self.state == TxState.DOWN:
            self.state = TxState.MOVING
        return sent

    def _write(self, frames: Sequence[can.Message]) -> int:
        if len(frames) > self._sized_for:
            self._size_send_buffer(len(frames))
        send, ids, pack = self._send, self._ids, _CAN_FRAME.pack
        sent = 0
        for frame in frames:
            can_id = frame.arbitration_id | (_CAN_EFF_FLAG if frame.is_extended_id else 0)
            if frame.is_remote_frame:
                can_id |= _CAN_RTR_FLAG
            if can_id not in ids:
                self._learn(can_id)
            try:
                send(pack(can_id, frame.dlc, bytes(frame.data)), socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                self.send_errors += 1
                break
            except OSError as exc:
                if exc.errno != errno.ENOBUFS:
                    raise
                self.send_errors += 1
                break
            sent += 1
        self.in_flight += sent
        return sent

    def _take_echoes(self, now_ns: int) -> None:
        """Read what came back since the last tick: our echoes, and the error frames that say
        the controller dropped what it held."""
        recv_into, buf = self._recv_into, self._buf
        echoes = 0
        while True:
            try:
                recv_into(buf, _CAN_FRAME.size, socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                break
            if buf[_ID_TOP_BYTE] & _ERR_FLAG_IN_TOP_BYTE:
                if _CAN_FRAME.unpack(buf)[0] & _CAN_ERR_RESTARTED:
                    self.in_flight = echoes = 0  # dropped by the restart, never to echo
                    self._echoed(now_ns)
                continue
            echoes += 1
        if echoes:
            # A frame with one of our IDs from another sender counts too: never below zero.
            self.in_flight = max(0, self.in_flight - echoes)
            self._echoed(now_ns)

    def _echoed(self, now_ns: int) -> None:
        self._echo_ns = now_ns
        self._probe_after_ns = int(PROBE_AFTER_S * 1e9)
        if not self.in_flight:
            self._held_since_ns = 0

    def _probe(self, now_ns: int) -> bool:
        """Whether to take the frames in flight for lost and write this tick anyway: no echo
        for the probe time, and none of ours in the send queue (where they would still be
        waiting, not lost)."""
        if now_ns - max(self._echo_ns, self._held_since_ns) < self._probe_after_ns:
            return False
        self._echo_ns = now_ns
        self._probe_after_ns = min(2 * self._probe_after_ns, int(PROBE_AFTER_MAX_S * 1e9))
        meminfo = self._sock.getsockopt(socket.SOL_SOCKET, _SO_MEMINFO, _WMEM_END)
        if struct.unpack_from("=I", meminfo, _WMEM_END - 4)[0]:
            return False
        self.in_flight = 0
        self.probes += 1
        return True

    def _not_leaving(self, now_ns: int) -> None:
        if not self._held_since_ns:
            self._held_since_ns = now_ns
        elif now_ns - self._held_since_ns >= self._stuck_after_ns and self.state == TxState.MOVING:
            self.state = TxState.STUCK

    def _failed(self, exc: OSError, now_ns: int) -> int:
        self.send_errors += 1
        if exc.errno in _DOWN_ERRNOS:
            # Taking the interface down dropped everything it held: nothing is in flight.
            self.in_flight = 0
            self._held_since_ns = 0
            self.state = TxState.DOWN
            return 0
        raise BusGone(f"{exc.strerror or exc}") from exc

    def _learn(self, can_id: int) -> None:
        """Add ``can_id`` (with its flags) to the kernel filter, so that its echo comes back."""
        self._ids.add(can_id)
        filters = [
            _FILTER.pack(known, _CAN_EFF_FLAG | _CAN_RTR_FLAG | _CAN_EFF_MASK)
            if known & _CAN_EFF_FLAG
            else _FILTER.pack(known, _CAN_EFF_FLAG | _CAN_RTR_FLAG | _CAN_SFF_MASK)
            for known in sorted(self._ids)
        ]
        self._sock.setsockopt(_SOL_CAN_RAW, _CAN_RAW_FILTER, b"".join(filters))

    def _size_send_buffer(self, frames: int) -> None:
        """Make the send buffer hold ``frames`` frames and no more (the kernel doubles what it is
        given, and keeps at least SOCK_MIN_SNDBUF)."""
        self._sized_for = frames
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, frames * CAN_FRAME_TRUESIZE // 2)
