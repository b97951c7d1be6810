"""What the supervisor says about the autopilot's address on a UDP link, read from the control
loop's counters (the loop decides, :mod:`bridge.mavlink.autopilot_address`, and counts; it never
logs per frame).

- The address, once known: one INFO line.
- Frames claiming to be the autopilot from another address: a WARNING and a STATUSTEXT naming
  that address, once per address (the first :data:`ADDRESSES_REPORTED`; a sender that changes
  its source port for every datagram is not worth more lines). The count is in the health's
  ``input.other_address``.
- The autopilot back from a new address after its old one fell silent: a WARNING and a
  STATUSTEXT, each time.

docs/troubleshooting.md explains each message.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Final

from bridge.config import BridgeConfig
from bridge.daemon.severity import SEVERITY_WARNING
from bridge.mavlink.autopilot_address import address_text
from bridge.output.mailbox import LoopStats

__all__ = ["ADDRESSES_REPORTED", "AddressReports"]

log = logging.getLogger(__name__)

ADDRESSES_REPORTED: Final = 16
"""Other addresses named at most, each once."""


class AddressReports:
    """Reports the autopilot's address and the frames refused from other addresses; the
    supervisor calls :meth:`check` a few times a second with the loop's counters."""

    def __init__(self, config: BridgeConfig, statustext: Callable[[int, str], None]) -> None:
        mavlink = config.mavlink
        self._url = mavlink.url
        self._who = f"{mavlink.autopilot_system_id}/{mavlink.autopilot_component_id}"
        self._silent_ms = config.output.arming_timeout_ms
        self._statustext = statustext
        self._address = 0  # as last reported (address_code); 0: not known yet
        self._reported: set[int] = set()

    def check(self, stats: LoopStats) -> None:
        """Report what changed since the last call."""
        address = stats["link_autopilot_address"]
        if address != self._address:
            self._report_address(self._address, address)
            self._address = address
        other = stats["input_other_address_from"]
        if other and other not in self._reported and len(self._reported) < ADDRESSES_REPORTED:
            self._reported.add(other)
            who, there = self._who, address_text(other)
            log.warning(
                "MAVLink %s: frames claiming to be the autopilot %s came from %s, not from its "
                "address %s: ignored (%d so far). A second route to the autopilot, another "
                "sender using its IDs, or the autopilot back from a new address, which takes "
                "the old one's place after %d ms of silence from it (docs/troubleshooting.md)",
                self._url,
                who,
                there,
                address_text(address) if address else "(none yet)",
                stats["input_other_address"],
                self._silent_ms,
            )
            self._statustext(SEVERITY_WARNING, f"Ignoring {who} from {there}")

    def _report_address(self, old: int, new: int) -> None:
        who, there = self._who, address_text(new)
        if not old:
            log.info(
                "MAVLink %s: the autopilot %s is at %s; frames claiming to be %s from any other "
                "address are ignored",
                self._url,
                who,
                there,
                who,
            )
            return
        log.warning(
            "MAVLink %s: the autopilot %s now speaks from %s: nothing came from %s for over "
            "%d ms (arming_timeout_ms); disarmed until its HEARTBEAT says otherwise "
            "(docs/troubleshooting.md)",
            self._url,
            who,
            there,
            address_text(old),
            self._silent_ms,
        )
        self._statustext(SEVERITY_WARNING, f"Autopilot {who} now at {there}")
