"""Which address the autopilot speaks from on a datagram link, and what to make of frames that
claim to be it from anywhere else.

On UDP anyone who reaches the bridge's port can send a frame that says "system 1, component 1":
a second route to the same autopilot (a ground station forwarding its link, a router with two
paths), a stale sender, a fuzzer, someone on the network. MAVLink's system and component IDs
say who a frame claims to be, not who sent it; the address a datagram came from does say that.
So the control loop ties the autopilot to one address and obeys frames claiming its IDs only
from there:

- ``udpout``: the configured peer, for good (the bridge sends there; ``0.0.0.0``, which Linux
  takes as this host, answers from ``127.0.0.1``).
- ``udpin``: the address its first control message (HEARTBEAT or motor output) came from.
- A frame claiming its IDs from any other address is refused (neither acted on nor relayed)
  and counted, with the address it came from.
- An autopilot that comes back from a new address (a restarted SITL on a new source port, a
  new DHCP lease) takes the place once the old address has sent nothing for ``move_after_ns``
  (the loop gives ``arming_timeout_ms``: by then the HEARTBEAT-lost failsafe holds the motors
  stopped anyway); the loop then forgets the old one's arming state and clock. ArduPilot ties a
  UDP input to its first sender for good (it ``connect()``s the socket); mavros and
  mavlink-router follow every new sender at once; this sits between: nobody else takes the
  autopilot's place while it speaks.

Signing (``[mavlink] signing_key``) is what proves who sent a frame; this only stops frames
from a second address being taken for the autopilot's.

Pure: addresses and monotonic times in, decisions and counters out; no I/O, clock or logging.
"""

from __future__ import annotations

import socket
from typing import Final

__all__ = ["Address", "AutopilotAddress", "address_code", "address_text"]

Address = tuple[str, int]
"""An IPv4 socket address as Python's socket module gives it: (dotted quad, port)."""

_THIS_HOST: Final = "0.0.0.0"
_LOOPBACK: Final = "127.0.0.1"


class AutopilotAddress:
    """The autopilot's address on one datagram link: :attr:`address` (None until known), when
    a datagram last came from it (:attr:`heard_ns`, kept by the caller), and the counters.

    The caller compares each datagram's sender with :attr:`address` (one tuple comparison,
    the common case) and asks :meth:`may_take` only for a frame claiming the autopilot from
    another address.
    """

    def __init__(self, configured: Address | None, move_after_ns: int) -> None:
        """``configured``: the peer of a ``udpout`` link (the autopilot is there for good);
        None for ``udpin`` (the first sender of a control message). ``move_after_ns``: how long
        the address must have been silent before another may take its place (``udpin``).

        Raises:
            ValueError: ``move_after_ns`` is not positive.
        """
        if move_after_ns <= 0:
            raise ValueError(f"move_after_ns={move_after_ns}: expected a positive duration")
        if configured is not None and configured[0] == _THIS_HOST:
            configured = (_LOOPBACK, configured[1])
        self.address: Address | None = configured
        self.fixed = configured is not None
        """``udpout``: the address never moves."""
        self.heard_ns = 0
        """When the latest datagram from :attr:`address` arrived (the caller writes it)."""
        self._move_after_ns = move_after_ns
        self.moves = 0
        """Times another address took the place of a silent one."""
        self.refused = 0
        """Frames claiming the autopilot's IDs from another address, refused."""
        self.refused_from: Address | None = None
        """Where the latest refused frame came from."""

    def may_take(self, now_ns: int) -> bool:
        """Whether a control message claiming the autopilot from another address, arriving at
        ``now_ns``, makes that address the autopilot's: none is known yet, or (``udpin``) the
        known one has been silent for longer than ``move_after_ns``."""
        return self.address is None or (
            not self.fixed and now_ns - self.heard_ns > self._move_after_ns
        )

    def take(self, sender: Address, now_ns: int) -> bool:
        """``sender`` is the autopilot's address from ``now_ns`` on; True when it took the place
        of another (a move), False for the first."""
        moved = self.address is not None
        self.address = sender
        self.heard_ns = now_ns
        self.moves += moved
        return moved

    def refuse(self, sender: Address) -> None:
        """Count a frame claiming the autopilot from ``sender``, which is not its address."""
        self.refused += 1
        self.refused_from = sender


def address_code(address: Address) -> int:
    """An IPv4 address and port as one integer (address << 16 | port), for a counter slot
    shared between processes; 0 never names an address anyone sends from.

    Raises:
        OSError: ``address`` is no IPv4 dotted quad.
    """
    return int.from_bytes(socket.inet_aton(address[0]), "big") << 16 | address[1]


def address_text(code: int) -> str:
    """``HOST:PORT`` of an :func:`address_code`."""
    return f"{socket.inet_ntoa((code >> 16).to_bytes(4, 'big'))}:{code & 0xFFFF}"
