"""Commands to the bridge (COMMAND_LONG): who is addressed, which handler answers, what to ACK.

Addressed to the bridge means ``target_system`` is the vehicle's system ID or 0 (broadcast) and
``target_component`` is the bridge's component ID or 0, from any sender on any connection. The
registered handlers (the daemon's MAV_CMD_DO_MOTOR_TEST, the telemetry sender's
MAV_CMD_SET_MESSAGE_INTERVAL and MAV_CMD_REQUEST_MESSAGE, ...) are asked in the order they were
added; each returns a MAV_RESULT, or ``None`` for "not mine", and the first answer wins. A
command nobody claims is answered MAV_RESULT_UNSUPPORTED only when it named the bridge exactly
(system and component); broadcasts nobody claims get no answer. Packing and sending the
COMMAND_ACK is the link's (:class:`bridge.mavlink.link.MavlinkLink`): this module touches no
connection.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any, Final

from bridge.mavlink.stats import Counters, log_sparsely

__all__ = ["COMMAND_ORIGIN", "CommandDispatcher", "CommandHandler"]

log = logging.getLogger(__name__)

CommandHandler = Callable[[Any], int | None]
"""Takes a COMMAND_LONG addressed to the bridge; returns a MAV_RESULT, or None: not mine."""

COMMAND_ORIGIN: Final = "bridge_connection"
"""The attribute a COMMAND_LONG carries while the handlers see it: the URL (as configured) of
the connection it came in on, for :meth:`~bridge.mavlink.link.MavlinkLink.send`'s ``to``."""


class CommandDispatcher:
    """The command handlers of one link, and the choice of answer.

    ``ours``: the bridge's (system, component). ``failed`` and ``unsupported``: the dialect's
    MAV_RESULT_FAILED and MAV_RESULT_UNSUPPORTED.
    """

    def __init__(self, ours: tuple[int, int], failed: int, unsupported: int) -> None:
        self._ours = ours
        self._failed = failed
        self._unsupported = unsupported
        # Replaced, never mutated: a reader walks the tuple it found without a lock.
        self._handlers: tuple[CommandHandler, ...] = ()
        self._lock = threading.Lock()  # serializes add/remove only

    def add(self, handler: CommandHandler) -> None:
        """Ask ``handler`` too, after the handlers added before it (adding one twice does
        nothing)."""
        with self._lock:  # two threads adding at once must not lose one
            if handler not in self._handlers:
                self._handlers = (*self._handlers, handler)

    def remove(self, handler: CommandHandler) -> None:
        """Stop asking ``handler``; removing one that is not there does nothing."""
        with self._lock:
            self._handlers = tuple(h for h in self._handlers if h != handler)

    def addressed(self, msg: Any) -> bool:
        """Whether the COMMAND_LONG ``msg`` is addressed to the bridge (exactly, or broadcast)."""
        system, component = msg.target_system, msg.target_component
        return system in (0, self._ours[0]) and component in (0, self._ours[1])

    def dispatch(self, msg: Any, origin: str, counters: Counters) -> int | None:
        """Ask the handlers about ``msg`` (addressed to the bridge), which came in on the
        connection ``origin`` (its URL, as configured; set on ``msg`` as
        :data:`COMMAND_ORIGIN`). A handler that raises is counted in ``counters`` and logged,
        and the next one is asked.

        Returns:
            The MAV_RESULT to answer with, or None: no answer (a broadcast nobody claimed).
        """
        named_us = (msg.target_system, msg.target_component) == self._ours
        setattr(msg, COMMAND_ORIGIN, origin)
        result: int | None = None
        failed = False
        for handler in self._handlers:
            try:
                result = handler(msg)
            # A handler's fault must not stop the reader; the sender learns it failed.
            except Exception:  # noqa: BLE001
                counters.handler_errors += 1
                log_sparsely(
                    log,
                    logging.ERROR,
                    counters.handler_errors,
                    "MAVLink command %d: a handler raised",
                    msg.command,
                    exc_info=True,
                )
                failed = True
                continue
            if result is not None:
                break
        if result is None and failed and named_us:
            result = self._failed
        if result is None:
            if not named_us:
                return None  # a broadcast nobody here handles is not ours to refuse
            result = self._unsupported
        return result
