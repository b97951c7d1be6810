"""Connection strings to the autopilot and the extra outputs, checked once at start.

The five kinds of connection (udpin, udpout, tcp, tcpin, serial) are opened by
:mod:`bridge.mavlink.transport` in the control loop and by pymavlink in
:mod:`bridge.mavlink.link`; both read the same :class:`Endpoint`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Final, Literal, cast

from bridge.config import MavlinkConfig
from bridge.errors import ConfigError

__all__ = [
    "ACCEPTED_URL_FORMS",
    "DEFAULT_BAUD",
    "Endpoint",
    "Transport",
    "check_endpoints",
    "parse_url",
]

Transport = Literal["udpin", "udpout", "tcp", "tcpin", "serial"]

ACCEPTED_URL_FORMS: Final = (
    "udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT, "
    "serial:DEVICE[:BAUD] or a device path DEVICE[:BAUD] (e.g. serial:/dev/ttyAMA0:921600)"
)
DEFAULT_BAUD: Final = 115_200  # pymavlink's default; USB CDC links ignore it
_NETWORK_URL: Final = re.compile(r"(udpin|udpout|tcp|tcpin):([^:\s]+):([0-9]{1,5})")
# The device ends at the last ":digits", if any: /dev/serial/by-path names contain colons.
_SERIAL_URL: Final = re.compile(r"(?:serial:)?(/\S*?)(?::([0-9]+))?")


@dataclass(frozen=True)
class Endpoint:
    """A validated connection string."""

    url: str
    """As configured, for messages."""
    kind: Transport
    address: str
    """``HOST:PORT``, or the serial device path."""
    baud: int = DEFAULT_BAUD
    """Serial only, in bit/s."""

    @property
    def is_stream(self) -> bool:
        """A byte stream that can end (TCP, serial) rather than datagrams."""
        return self.kind in ("tcp", "tcpin", "serial")


def parse_url(url: str, key: str = "url") -> Endpoint:
    """Check a connection string and split it into what a transport opens.

    Only the forms in :data:`ACCEPTED_URL_FORMS` are accepted: pymavlink would also take a file
    name (and replay it as a log, or run it if it looks like a program), which must never
    happen by accident on a vehicle. ``key`` is the ``[mavlink]`` key the URL came from, for
    the message (``url`` or ``outputs``).

    Raises:
        ConfigError: naming the key, the URL and the accepted forms.
    """
    where = f"[mavlink] {key} {url!r}"
    network = _NETWORK_URL.fullmatch(url)
    if network is not None:
        kind, host, port = network.groups()
        if not 1 <= int(port) <= 65535:
            raise ConfigError(
                f"{where}: port {port} is not 1..65535; expected one of {ACCEPTED_URL_FORMS}"
            )
        return Endpoint(url, cast(Transport, kind), f"{host}:{int(port)}")
    serial = _SERIAL_URL.fullmatch(url)
    if serial is not None:
        device, baud = serial.groups()
        if baud is not None and int(baud) == 0:
            raise ConfigError(f"{where}: baud rate 0; expected one of {ACCEPTED_URL_FORMS}")
        return Endpoint(url, "serial", device, int(baud) if baud else DEFAULT_BAUD)
    raise ConfigError(
        f"{where} is not a connection string esc-bridge accepts; "
        f"expected one of {ACCEPTED_URL_FORMS}"
    )


def check_endpoints(config: MavlinkConfig) -> tuple[Endpoint, list[Endpoint]]:
    """Parse ``url`` and every ``outputs`` entry, and refuse a connection listed twice.

    Two entries are the same connection when they have the same transport and address (a port
    written with leading zeros is the same port): opening both would fail, or send everything
    twice. Called by :meth:`MavlinkLink.start` and by the start-up check before it.

    Returns:
        The autopilot's endpoint and the outputs' endpoints, in ``outputs`` order.

    Raises:
        ConfigError: a URL is malformed (see :func:`parse_url`), or an output repeats the
            autopilot's URL or another output.
    """
    endpoint = parse_url(config.url)
    outputs = [parse_url(url, "outputs") for url in config.outputs]
    seen = {(endpoint.kind, endpoint.address): f"[mavlink] url {endpoint.url!r}"}
    for output in outputs:
        where = (output.kind, output.address)
        if where in seen:
            raise ConfigError(
                f"[mavlink] outputs {output.url!r} is the same connection as {seen[where]}; "
                "list each connection once"
            )
        seen[where] = repr(output.url)
    return endpoint, outputs
