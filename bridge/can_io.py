"""The CAN edge: opening python-can buses from the config, choosing what each handle receives,
counting what the kernel dropped for it, and telling passing send failures from a bus that is
gone. The only module besides the codecs (and :mod:`bridge.multicast_receive`, which reads a
``udp_multicast`` handle's socket for the CAN reader) that imports python-can's buses.

What a handle receives (``open_bus(receive=...)``) matters under load: every frame a socket
is subscribed to costs the kernel a copy and a queue slot, and costs the process a wake-up, a
read and a decode, whether anyone wants the frame or not. So the output process, which only
sends, opens a transmit-only handle (``"none"``), and the telemetry reader asks the kernel for
its ESCs' telemetry only (``"telemetry"`` with the family's
:meth:`~bridge.escs.family.EscFamily.reader_filters`).
"""

from __future__ import annotations

import contextlib
import errno
import ipaddress
import logging
import os
import socket
import struct
from collections.abc import Iterator, Sequence
from typing import Final, Literal

import can
from can.typechecking import CanFilter

from bridge.can_interface import assess, bring_up_command, read_link
from bridge.config import CanConfig
from bridge.errors import ConfigError, LinkError

log = logging.getLogger(__name__)

# Interfaces that several processes can open at once on one machine, so the output loop can
# have a process (and a bus handle) of its own.
SHAREABLE_INTERFACES = frozenset({"socketcan", "udp_multicast"})

# Send errors that mean "try again next tick" rather than "the bus is gone": the transmit
# queue is full (the ESCs are not acknowledging, or the bus is saturated).
TRANSIENT_ERRNOS = frozenset({errno.ENOBUFS, errno.EAGAIN})

# Interfaces whose handles filter in the kernel (CAN_RAW_FILTER): a frame no filter passes is
# never queued. Elsewhere python-can filters in ``recv``, one frame a call: ``recv(0)`` then
# returns None for a refused frame as for an empty queue.
KERNEL_FILTERING_INTERFACES = frozenset({"socketcan"})

Receive = Literal["all", "telemetry", "none"]
"""What a bus handle receives: every frame, the frames its filters pass, or nothing."""


class _QuietOpens(logging.Filter):
    """Drops python-can's lines about each SocketCAN open: "Created a socket" (INFO) and "Could
    not access SocketCAN device" (ERROR, a bind that failed). The output loop reopens a bus
    that is gone, every few seconds for as long as it stays gone, and the bridge says itself,
    once, what is wrong (:class:`~bridge.errors.LinkError`, the bus's state reports)."""

    _TEMPLATES: Final = frozenset({"Created a socket", "Could not access SocketCAN device %s (%s)"})

    def filter(self, record: logging.LogRecord) -> bool:
        return record.msg not in self._TEMPLATES


logging.getLogger("can.interfaces.socketcan.socketcan").addFilter(_QuietOpens())

# -- the socket options python-can does not set for us (Linux) --------------------------------

_SO_MEMINFO: Final = 55  # asm-generic/socket.h (x86, arm, arm64); Python has no constant
_SK_MEMINFO_DROPS: Final = 8  # index of sk_drops in SO_MEMINFO's u32 array (Linux >= 4.6)
_AF_CAN: Final = 29  # linux/socket.h; socket.AF_CAN is missing where Python was built without it
_SOL_CAN_RAW: Final = 101  # linux/can.h: SOL_CAN_BASE + CAN_RAW
_CAN_RAW_FILTER: Final = 1  # linux/can/raw.h
_CAN_RAW_ERR_FILTER: Final = 2
_IP_MULTICAST_ALL: Final = 49  # linux/in.h
_IPV6_MULTICAST_ALL: Final = 29  # linux/in6.h (Linux >= 4.20)
_PROC_NET_UDP: Final[dict[int, str]] = {
    socket.AF_INET: "/proc/net/udp",
    socket.AF_INET6: "/proc/net/udp6",
}
_UDP_INODE_COLUMN = 9
_UDP_DROPS_COLUMN = 12


def check_interface(config: CanConfig, source: str) -> None:
    """Refuse an interface name python-can does not know, and a channel the interface could
    never open, before anything is opened.

    The channels checked are those whose form is known without opening: a SocketCAN
    interface's name (what the kernel takes: 1 to 15 characters, no ``/``, no white space;
    python-can's empty name, every interface at once, cannot be sent on), and a udp_multicast
    group (a multicast IP address, which python-can joins; a host name would be looked up, and
    then refused). Whether the SocketCAN interface exists and is up is for
    :mod:`bridge.can_interface`.

    Raises:
        ConfigError: naming the interface and the ones python-can has, or the channel and what
            the interface expects.
    """
    if config.interface not in can.VALID_INTERFACES:
        known = ", ".join(sorted(can.VALID_INTERFACES))
        raise ConfigError(
            f"{source}: [can] interface {config.interface!r} is not available; "
            f"expected one of {known}"
        )
    expected = _channel_refusal(config.interface, config.channel)
    if expected:
        raise ConfigError(
            f"{source}: [can] channel {config.channel!r} cannot be a {config.interface} "
            f"channel; expected {expected}"
        )


_IFNAMSIZ: Final = 16  # linux/if.h: a name and its terminating zero


def _channel_refusal(interface: str, channel: str) -> str:
    """What ``interface`` expects of a channel that ``channel`` is not; '' when it may be."""
    if interface == "socketcan":
        if (
            not 0 < len(channel) < _IFNAMSIZ
            or channel in (".", "..")
            or any(c == "/" or c.isspace() for c in channel)
        ):
            return (
                "a network interface's name such as can0 (1 to 15 characters, no '/' or "
                "white space): `ip link show` lists them"
            )
    elif interface == "udp_multicast":
        try:
            multicast = ipaddress.ip_address(channel).is_multicast
        except ValueError:
            multicast = False
        if not multicast:
            return (
                "a multicast IP address: IPv4 in 224.0.0.0/4 such as 239.74.163.2, or IPv6 in "
                "ff00::/8"
            )
    return ""


def open_bus(
    config: CanConfig,
    bitrate: int,
    *,
    receive: Receive = "all",
    filters: Sequence[CanFilter] | None = None,
    explain: bool = True,
) -> can.BusABC:
    """Open the configured bus; ``receive`` says what the handle gets from it.

    - ``"all"``: every frame (the recorder, the monitor, ESC set-up, the simulator).
    - ``"telemetry"``: only frames that match one of ``filters`` (a family's ``reader_filters``).
      socketcan filters in the kernel (CAN_RAW_FILTER): other frames cost the process
      nothing. udp_multicast and virtual have no kernel filter: python-can drops the other
      frames in ``recv`` after reading each, so a flood still costs the reader its reads (but
      not its decoding). Other interfaces filter in hardware or in python-can, as each can.
      An empty ``filters`` passes nothing: the handle is opened as with ``"none"`` (so on an
      interface where that does nothing, it receives every frame).
    - ``"none"``: a transmit-only handle, for a process that never reads (the output loop),
      whose socket would otherwise fill and make the kernel copy and then discard every
      frame. socketcan: an empty CAN_RAW_FILTER and no error frames, set on the socket
      directly, since python-can takes an empty filter list for "every frame".
      udp_multicast: the socket leaves the multicast group and clears IP_MULTICAST_ALL
      (IPV6_MULTICAST_ALL), so no datagram is queued for it (measured under a flood:
      shutdown(SHUT_RD) fails with ENOTCONN and changes nothing, leaving the group alone
      changes nothing since IP_MULTICAST_ALL still delivers every group joined on the host,
      and a minimal SO_RCVBUF still queues one datagram and counts every other as dropped).
      Other interfaces: nothing is done; frames queue for the handle as before (a ``virtual``
      handle's queue grows without bound if it is never read).

    ``explain``: when a SocketCAN bus cannot be opened, read the interface's state (a run of
    ``ip``, :mod:`bridge.can_interface`) to say what is missing; False (the output loop, which
    must not start processes) gives only the command that brings the interface up.

    Raises:
        ConfigError: the interface is not one python-can knows.
        LinkError: the bus could not be opened (no such device, no permission, ...).
        ValueError: ``filters`` without ``receive="telemetry"``, or that without ``filters``.
    """
    if (receive == "telemetry") != (filters is not None):
        raise ValueError(
            f"open_bus(receive={receive!r}, filters={filters!r}): filters go with "
            "receive='telemetry', and only there"
        )
    kwargs = dict(config.options or {})
    if filters:
        kwargs["can_filters"] = list(filters)
    try:
        bus = can.Bus(interface=config.interface, channel=config.channel, bitrate=bitrate, **kwargs)
    except can.CanInterfaceNotImplementedError as exc:
        known = ", ".join(sorted(can.VALID_INTERFACES))
        raise ConfigError(
            f"[can] interface {config.interface!r} is not available: {exc}; expected one of {known}"
        ) from exc
    except (can.CanError, OSError, ValueError, TypeError) as exc:
        hint = ""
        if config.interface == "socketcan":
            found = assess(read_link(config.channel), config.channel, bitrate) if explain else None
            refusal = None if found is None else found.refusal
            hint = f" ({refusal or bring_up_command(config.channel, bitrate)})"
        raise LinkError(
            f"cannot open CAN bus {config.interface}:{config.channel}: {exc}{hint}"
        ) from exc
    silence = receive == "none" or (receive == "telemetry" and not filters)
    if silence and not _stop_receiving(bus, config.channel):
        log.debug("%s: this interface has no transmit-only handle", config.interface)
    return bus


def apply_filters(bus: can.BusABC, filters: Sequence[CanFilter]) -> None:
    """Let only frames matching one of ``filters`` through ``bus.recv`` from now on (in the
    kernel on socketcan; see :func:`open_bus`). Frames already queued are still read.

    Raises:
        ValueError: ``filters`` is empty (python-can would pass every frame; open a handle
            with ``receive="none"`` for none).
    """
    if not filters:
        raise ValueError("apply_filters: no filters; python-can would take that as every frame")
    bus.set_filters(list(filters))


@contextlib.contextmanager
def _bus_socket(bus: can.BusABC) -> Iterator[socket.socket | None]:
    """A duplicate of the bus's socket (options set on it apply to the bus's own), or None
    when the interface has no descriptor."""
    try:
        fd = bus.fileno()
    except (NotImplementedError, AttributeError, OSError, ValueError):
        fd = -1
    if not isinstance(fd, int) or fd < 0:
        yield None
        return
    try:
        # fromfd duplicates the descriptor: closing the duplicate leaves the bus's own open.
        # The family given here does not matter for socket-level options.
        sock = socket.fromfd(fd, socket.AF_INET, socket.SOCK_DGRAM)
    except OSError:
        yield None
        return
    with sock:
        yield sock


def _kind(sock: socket.socket) -> tuple[int, int] | None:
    """The socket's real (family, type), or None: not a socket (a serial adapter's tty), or
    not Linux (SO_DOMAIN)."""
    so_domain = getattr(socket, "SO_DOMAIN", None)
    if so_domain is None:
        return None
    try:
        family = sock.getsockopt(socket.SOL_SOCKET, so_domain)
        kind = sock.getsockopt(socket.SOL_SOCKET, socket.SO_TYPE)
    except OSError:
        return None
    return family, kind


def _stop_receiving(bus: can.BusABC, channel: str) -> bool:
    """Make the kernel queue nothing for ``bus`` (see :func:`open_bus`, "none"); False when
    the interface has no socket this knows how to silence."""
    with _bus_socket(bus) as sock:
        kind = None if sock is None else _kind(sock)
        if sock is None or kind is None:
            return False
        try:
            if kind[0] == _AF_CAN:
                # No filter registers no receiver: the CAN core never even clones a frame for
                # this socket. Error frames have a receiver of their own: switch it off too.
                sock.setsockopt(_SOL_CAN_RAW, _CAN_RAW_FILTER, b"")
                sock.setsockopt(_SOL_CAN_RAW, _CAN_RAW_ERR_FILTER, 0)
                return True
            if kind[0] in _PROC_NET_UDP and kind[1] == socket.SOCK_DGRAM:
                _leave_group(sock, kind[0], channel)
                return True
        except OSError as exc:
            log.warning("cannot make the %s handle transmit-only: %s", channel, exc)
        return False


def _leave_group(sock: socket.socket, family: int, group: str) -> None:
    """Leave the multicast group python-can's udp_multicast joined (on any interface), and
    stop receiving the groups other sockets on this host joined."""
    address = socket.inet_pton(family, group)
    if family == socket.AF_INET:
        mreq = address + struct.pack("=I", socket.INADDR_ANY)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_DROP_MEMBERSHIP, mreq)
        sock.setsockopt(socket.IPPROTO_IP, _IP_MULTICAST_ALL, 0)
    else:
        mreq = address + struct.pack("@I", 0)
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_LEAVE_GROUP, mreq)
        sock.setsockopt(socket.IPPROTO_IPV6, _IPV6_MULTICAST_ALL, 0)


def receive_drops(bus: can.BusABC) -> int | None:
    """Frames the kernel dropped for this handle since it was opened, because its receive
    queue was full (a reader held off for longer than its socket buffer lasts); None when the
    interface does not tell.

    A system call and, for udp_multicast, a read of a /proc table: call it now and then (the
    CAN reader does once a second), never per frame.

    - udp_multicast: the ``drops`` column of the socket's row in /proc/net/udp or
      /proc/net/udp6, found by the socket's inode.
    - socketcan: the socket's ``sk_drops`` counter through getsockopt(SO_MEMINFO) (Linux
      >= 4.6). It is the counter SO_RXQ_OVFL reports, but SO_RXQ_OVFL delivers it as
      ancillary data on each recvmsg, and python-can's socketcan ``capture_message`` asks
      for room for exactly one control message (the timestamp): reading it would mean
      replacing python-can's receive path. SO_MEMINFO reads the same count at any time.
      Untested here (this machine's kernel has no CAN); the same call on a UDP socket is
      tested against /proc/net/udp.
    - Other interfaces: None.
    """
    with _bus_socket(bus) as sock:
        kind = None if sock is None else _kind(sock)
        if sock is None or kind is None:
            return None
        if kind[0] in _PROC_NET_UDP:
            return _udp_drops(os.fstat(sock.fileno()).st_ino, _PROC_NET_UDP[kind[0]])
        if kind[0] == _AF_CAN:
            return socket_drops(sock)
        return None


def socket_drops(sock: socket.socket) -> int | None:
    """The kernel's drop count of any socket (getsockopt SO_MEMINFO), or None if the kernel
    does not give it."""
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, _SO_MEMINFO, 4 * (_SK_MEMINFO_DROPS + 1))
    except OSError:
        return None
    if len(raw) < 4 * (_SK_MEMINFO_DROPS + 1):
        return None
    drops: int = struct.unpack_from("=I", raw, 4 * _SK_MEMINFO_DROPS)[0]
    return drops


def _udp_drops(inode: int, path: str) -> int | None:
    try:
        with open(path, encoding="ascii") as table:
            next(table, None)  # the header
            for line in table:
                fields = line.split()
                if len(fields) > _UDP_DROPS_COLUMN and int(fields[_UDP_INODE_COLUMN]) == inode:
                    return int(fields[_UDP_DROPS_COLUMN])
    except (OSError, ValueError):
        return None
    return None


def enlarge_receive_buffer(bus: can.BusABC, size_bytes: int) -> int | None:
    """Ask the kernel for a receive buffer of ``size_bytes`` on the bus's socket.

    A reader that the GIL or a busy CPU holds off for tens of ms must find the frames that
    arrived meanwhile still queued; the default buffer (about 200 kB) holds only ~250 frames,
    ~40 ms of a saturated 1 Mbit/s bus. The kernel caps the size at net.core.rmem_max.

    Returns:
        The buffer size the kernel granted, or None when the interface has no socket.
    """
    with _bus_socket(bus) as sock:
        if sock is None:
            return None
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size_bytes)
            granted: int = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
            return granted
        except OSError:
            return None


def is_transient(exc: BaseException) -> bool:
    """True for a send failure worth retrying on the same bus handle."""
    code = getattr(exc, "error_code", None) or getattr(exc, "errno", None)
    return code in TRANSIENT_ERRNOS or (isinstance(exc, can.CanOperationError) and code is None)
