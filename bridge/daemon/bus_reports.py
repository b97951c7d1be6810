"""What the daemon says about the CAN bus: each fault once, when it begins, and its end.

Two sides tell: the output loop, of its frames (:class:`~bridge.output.transmit.TxState`: stuck,
the interface down or gone, moving again), and the CAN reader, of what the controller reports
in its error frames (:class:`~bridge.can_errors.ControllerState`: error-warning, error-passive,
bus-off and back, a restart) and of frames lost because a receive queue was full (the kernel's,
or the controller's own). :class:`BusWatch` compares their counters at every look of the
supervisor's and reports each state entered since the last look (also one already left again)
and each new spell of lost frames, by STATUSTEXT and in the log, with the details for the log.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Final

from bridge.can_errors import ControllerState
from bridge.daemon.severity import (
    SEVERITY_CRITICAL,
    SEVERITY_INFO,
    SEVERITY_NOTICE,
    SEVERITY_WARNING,
)
from bridge.output.mailbox import LoopStats
from bridge.output.transmit import TxState
from bridge.telemetry.reader import ReaderStats

Report = Callable[[int, str, str], None]
"""``report(severity, text, detail)``: ``text`` is the STATUSTEXT (50 characters), ``text:
detail`` the log line."""

TX_REPORTS: Final[dict[TxState, tuple[int, str]]] = {
    TxState.STUCK: (SEVERITY_CRITICAL, "CAN: FAULT bus stuck, frames not leaving"),
    TxState.DOWN: (SEVERITY_CRITICAL, "CAN: FAULT interface down, frames not sent"),
    TxState.GONE: (SEVERITY_CRITICAL, "CAN: FAULT interface gone, reopening it"),
    TxState.MOVING: (SEVERITY_INFO, "CAN: frames leaving again"),
}
"""What each state of the loop's transmit side is reported as, when the loop enters it."""

CONTROLLER_REPORTS: Final[dict[ControllerState, tuple[int, str]]] = {
    ControllerState.ERROR_WARNING: (SEVERITY_WARNING, "CAN: ERROR-WARNING, errors on the bus"),
    ControllerState.ERROR_PASSIVE: (SEVERITY_WARNING, "CAN: ERROR-PASSIVE, errors on the bus"),
    ControllerState.BUS_OFF: (SEVERITY_CRITICAL, "CAN: FAULT BUS-OFF, controller off the bus"),
    ControllerState.ERROR_ACTIVE: (SEVERITY_INFO, "CAN: ERROR-ACTIVE again"),
}
"""What each controller state is reported as, when an error frame announces it."""

RESTARTED: Final = (SEVERITY_NOTICE, "CAN: controller restarted")
RECEIVE_LOST: Final = (SEVERITY_WARNING, "CAN: receive queue full, frames lost")
LOST_SPELL_NS: Final = 10_000_000_000
"""Frames lost again within this long of the last loss belong to the same spell: reported
once."""


class BusWatch:
    """Reports the bus's faults from the loop's and the reader's counters (the supervisor's
    thread calls :meth:`check` at each look)."""

    def __init__(self, report: Report) -> None:
        self._report = report
        self._tx_entered = [0] * len(TxState)
        self._controller_entered = [0] * len(ControllerState)
        self._restarts = 0
        self._lost = 0
        self._lost_at_ns = 0  # when frames were last seen lost; 0: not in a spell

    def check(self, now_ns: int, stats: LoopStats, reader: ReaderStats | None) -> None:
        """Report what changed since the last call."""
        self._check_tx(stats)
        if reader is not None:
            self._check_controller(reader)
            self._check_lost(now_ns, reader)

    def _check_tx(self, stats: LoopStats) -> None:
        entered = stats.tx_state_entries()
        if entered == self._tx_entered:
            return
        now = TxState(stats["tx_state"])
        detail = (
            f"{stats['ticks_held']} ticks held back in all, {stats['send_errors']} frames "
            f"refused, bus reopened {stats['bus_reopens']} times"
        )
        # The faults passed through first, then a recovery passed through, the current one last.
        for state in sorted(TxState, key=lambda s: (s == now, s == TxState.MOVING)):
            if entered[state] != self._tx_entered[state]:
                severity, text = TX_REPORTS[state]
                self._report(severity, text, detail)
        self._tx_entered = entered

    def _check_controller(self, reader: ReaderStats) -> None:
        controller = reader.controller
        entered = list(controller.entered)
        last = controller.last
        detail = "" if last is None else f"last error frame: {last.describe()}"
        if entered != self._controller_entered:
            current, recovered = controller.state, ControllerState.ERROR_ACTIVE
            for state in sorted(ControllerState, key=lambda s: (s == current, s == recovered)):
                if entered[state] != self._controller_entered[state]:
                    severity, text = CONTROLLER_REPORTS[state]
                    self._report(severity, text, detail)
            self._controller_entered = entered
        if controller.restarts != self._restarts:
            self._restarts = controller.restarts
            self._report(*RESTARTED, f"{controller.restarts} restarts in all; {detail}")

    def _check_lost(self, now_ns: int, reader: ReaderStats) -> None:
        lost = (reader.kernel_drops or 0) + reader.controller.receive_overflows
        if lost == self._lost:
            if self._lost_at_ns and now_ns - self._lost_at_ns > LOST_SPELL_NS:
                self._lost_at_ns = 0
            return
        if not self._lost_at_ns:
            self._report(
                *RECEIVE_LOST,
                f"{reader.kernel_drops or 0} frames dropped by the kernel for the reader, "
                f"{reader.controller.receive_overflows} receive overflows of the controller",
            )
        self._lost, self._lost_at_ns = lost, now_ns
