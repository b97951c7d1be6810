"""Non-blocking byte transports to the autopilot, for a real-time loop that owns its MAVLink link.

The real-time control loop is one thread that polls the autopilot's link itself, decodes the
motor outputs, mixes and sends CAN frames at a fixed rate. It must never block: not on a read,
a write, a TCP connect, a serial port that vanished, or a reconnect. pymavlink's transports
(which :mod:`bridge.mavlink.link` uses from its own threads) block in several of those places,
so this package opens the same five kinds of connection with plain non-blocking file
descriptors and leaves framing to the caller: bytes in, bytes out, nothing about MAVLink.

One :class:`AutopilotTransport` per link, made by :func:`open_transport`, used by one thread::

    transport = open_transport(parse_url("tcp:127.0.0.1:5760"))
    while running:
        now_ns = time.monotonic_ns()
        transport.service(now_ns)            # connect, accept, reopen, flush: never waits
        fd = transport.fileno()              # None while not connected
        # poll fd for POLLIN (and POLLOUT while transport.wants_write()), up to the next tick;
        # on any event (POLLIN, POLLHUP, POLLERR) call recv(), which notices a lost link.
        # Ask for fileno() again every tick: a reconnect brings a new descriptor, which may
        # even reuse the old number.
        while (got := transport.recv()) is not None:
            data, received_ns = got
        transport.send(frame)                # False: dropped, never blocked
    transport.close()

Kinds (the URL forms of :data:`~bridge.mavlink.endpoints.ACCEPTED_URL_FORMS`, parsed by
:func:`~bridge.mavlink.endpoints.parse_url`):

* ``udpin:HOST:PORT`` binds there and replies to whoever sent the latest datagram, as
  pymavlink does, or to the peer its reader names with
  :meth:`~AutopilotTransport.reply_to` (the autopilot, once known); until a datagram arrives
  there is nobody to send to.
* ``udpout:HOST:PORT`` sends there and receives the replies on the same socket.
* ``tcp:HOST:PORT`` connects there, without blocking: the connect is started, and completed
  (or given up after 2 s without an answer) by :meth:`~AutopilotTransport.service`.
* ``tcpin:HOST:PORT`` listens there and serves one client at a time: a new client replaces the
  old one (an autopilot that restarted reconnects before its old connection times out).
* ``serial:DEVICE[:BAUD]`` opens a terminal device raw, 8N1, no flow control; a helper thread
  does the reopening, since a USB adapter's driver sleeps in open() (:class:`SerialTransport`).

A datagram transport (``datagrams``) returns one whole datagram per read, and says who sent it
(``sender``): its reader scans each datagram on its own and may judge frames by their sender.
A stream's reads cut frames anywhere, and its reader carries a partial frame to the next read.

Clocks: every input is stamped with ``time.monotonic_ns()``. A UDP datagram carries the kernel's
receive time (``SO_TIMESTAMPNS``), so its stamp says when it arrived even when the loop reads it
a tick later; the kernel stamps with the wall clock, converted here to the monotonic clock at
read time. A stream read is stamped with the read time: a byte stream has no arrival times.

Link trouble never raises once open: a TCP or serial stream that ends or fails is closed and
reopened with jittered, capped exponential backoff (0.1 s, doubling, 5 s cap, as
:mod:`bridge.mavlink.connection`), and counted in :class:`TransportStats`. Each change of state
(lost, connected, a different reason for failing) is logged once through the package's loggers; the
retries themselves are not. The logging happens on the calling thread, so the real-time
process should give its loggers a handler that never blocks (``logging.handlers.QueueHandler``
with a ``QueueListener``), not one that writes to a pipe or journald from the loop.
:func:`open_transport` raises :class:`~bridge.errors.LinkError` only for what is wrong at start
and will not get better (see its docstring).

Sends never block either. A stream that cannot take a whole frame now keeps the rest in a
bounded pending buffer, written out by later :meth:`~AutopilotTransport.send` and
:meth:`~AutopilotTransport.service` calls ahead of any later frame, so the peer never sees half
a frame followed by another frame; once the buffer is full, new frames are dropped whole.

Linux only (``SO_TIMESTAMPNS``, ``termios``), IPv4 only like pymavlink (the URL forms have no
room for an IPv6 literal). Not thread-safe: one thread owns a transport.

The modules: ``base`` (:class:`AutopilotTransport`, :class:`TransportStats`, shared helpers),
``udp`` (``udpin``, ``udpout``), ``stream`` (what TCP and serial share: the pending buffer, loss
and reopening), ``tcp`` (``tcp``, ``tcpin``), ``serial``; this one only picks the kind
(:func:`open_transport`).
"""

from __future__ import annotations

from bridge.mavlink.endpoints import Endpoint
from bridge.mavlink.transport.base import PENDING_LIMIT_BYTES, AutopilotTransport
from bridge.mavlink.transport.serial import SerialTransport
from bridge.mavlink.transport.tcp import TcpClientTransport, TcpServerTransport
from bridge.mavlink.transport.udp import UdpInTransport, UdpOutTransport

__all__ = ["open_transport"]


def open_transport(
    endpoint: Endpoint,
    wait_for_link: bool = True,
    pending_limit_bytes: int = PENDING_LIMIT_BYTES,
) -> AutopilotTransport:
    """Open the transport for ``endpoint`` (from :func:`~bridge.mavlink.endpoints.parse_url`).
    Call it before the loop starts: it is the one call that may wait, to resolve a host name
    (once; the loop never does), to open a serial device the first time and start its helper
    thread, and, without ``wait_for_link``, for a TCP connect. No method of the transport waits
    after it.

    ``wait_for_link`` True (the default, for the real-time loop): a TCP server that is not up
    yet, or a serial device that does not exist yet (a USB adapter not enumerated at boot, a
    device node udev has not opened to us yet), is no error: the transport starts
    disconnected and :meth:`~AutopilotTransport.service` keeps retrying with backoff, logging
    once that it waits. False: the old daemon's behaviour, which refuses to start without its
    autopilot: such a link raises LinkError here (a TCP connect is waited for, up to 2 s). UDP
    and tcpin need no peer to open and behave the same either way.

    ``pending_limit_bytes``: the bound of a stream's pending buffer (see
    :data:`PENDING_LIMIT_BYTES`); frames larger than it are always dropped.

    Raises:
        LinkError: naming the URL, for what is wrong at start and will not get better: an
            address that cannot be bound (in use, not local), an unknown host, a serial path
            that is no terminal or a non-standard baud rate; and, with ``wait_for_link``
            False, a TCP server or serial device that cannot be reached now.
        ValueError: ``pending_limit_bytes`` is not positive.
    """
    if endpoint.kind == "udpin":
        return UdpInTransport(endpoint)
    if endpoint.kind == "udpout":
        return UdpOutTransport(endpoint)
    if endpoint.kind == "tcp":
        return TcpClientTransport(endpoint, wait_for_link, pending_limit_bytes)
    if endpoint.kind == "tcpin":
        return TcpServerTransport(endpoint, pending_limit_bytes)
    return SerialTransport(endpoint, wait_for_link, pending_limit_bytes)
