"""The CAN edge: opening python-can buses from the config, and telling passing send failures
from a bus that is gone. The only module besides the codecs that imports python-can's buses."""

from __future__ import annotations

import errno
import socket

import can

from bridge.config import CanConfig
from bridge.errors import ConfigError, LinkError

# Interfaces that several processes can open at once on one machine, so the output loop can
# have a process (and a bus handle) of its own.
SHAREABLE_INTERFACES = frozenset({"socketcan", "udp_multicast"})

# Send errors that mean "try again next tick" rather than "the bus is gone": the transmit
# queue is full (the ESCs are not acknowledging, or the bus is saturated).
TRANSIENT_ERRNOS = frozenset({errno.ENOBUFS, errno.EAGAIN})


def check_interface(config: CanConfig, source: str) -> None:
    """Refuse an interface name python-can does not know, before anything is opened.

    Raises:
        ConfigError: naming the interface and the ones python-can has.
    """
    if config.interface not in can.VALID_INTERFACES:
        known = ", ".join(sorted(can.VALID_INTERFACES))
        raise ConfigError(
            f"{source}: [can] interface {config.interface!r} is not available; "
            f"expected one of {known}"
        )


def open_bus(config: CanConfig, bitrate: int) -> can.BusABC:
    """Open the configured bus.

    Raises:
        ConfigError: the interface is not one python-can knows.
        LinkError: the bus could not be opened (no such device, no permission, ...).
    """
    kwargs = dict(config.options or {})
    try:
        return can.Bus(
            interface=config.interface, channel=config.channel, bitrate=bitrate, **kwargs
        )
    except can.CanInterfaceNotImplementedError as exc:
        known = ", ".join(sorted(can.VALID_INTERFACES))
        raise ConfigError(
            f"[can] interface {config.interface!r} is not available: {exc}; expected one of {known}"
        ) from exc
    except (can.CanError, OSError, ValueError, TypeError) as exc:
        raise LinkError(
            f"cannot open CAN bus {config.interface}:{config.channel}: {exc}"
            + (
                " (on Linux: `ip link set can0 up type can bitrate 1000000`, or vcan0 for tests)"
                if config.interface == "socketcan"
                else ""
            )
        ) from exc


def enlarge_receive_buffer(bus: can.BusABC, size_bytes: int) -> int | None:
    """Ask the kernel for a receive buffer of ``size_bytes`` on the bus's socket.

    A reader that the GIL or a busy CPU holds off for tens of ms must find the frames that
    arrived meanwhile still queued; the default buffer (about 200 kB) holds only ~250 frames,
    ~40 ms of a saturated 1 Mbit/s bus. The kernel caps the size at net.core.rmem_max.

    Returns:
        The buffer size the kernel granted, or None when the interface has no socket.
    """
    try:
        fd = bus.fileno()
    except (NotImplementedError, AttributeError, OSError, ValueError):
        return None
    if not isinstance(fd, int) or fd < 0:
        return None
    try:
        # fromfd duplicates the descriptor: the option applies to the bus's socket, and closing
        # the duplicate leaves the bus's own descriptor open.
        with socket.fromfd(fd, socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size_bytes)
            granted: int = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
            return granted
    except OSError:
        return None


def is_transient(exc: BaseException) -> bool:
    """True for a send failure worth retrying on the same bus handle."""
    code = getattr(exc, "error_code", None) or getattr(exc, "errno", None)
    return code in TRANSIENT_ERRNOS or (isinstance(exc, can.CanOperationError) and code is None)
