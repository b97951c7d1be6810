"""The CAN edge: opening python-can buses from the config, and telling passing send failures
from a bus that is gone. The only module besides the codecs that imports python-can's buses."""

from __future__ import annotations

import errno

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


def is_transient(exc: BaseException) -> bool:
    """True for a send failure worth retrying on the same bus handle."""
    code = getattr(exc, "error_code", None) or getattr(exc, "errno", None)
    return code in TRANSIENT_ERRNOS or (isinstance(exc, can.CanOperationError) and code is None)
