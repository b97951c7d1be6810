"""The bus's faults reported once each, from the loop's and the reader's counters: a state
entered and left between two looks is still told, the current state last; a spell of lost
frames once."""

from __future__ import annotations

from bridge.can_errors import ControllerState, decode_error_frame
from bridge.daemon.bus_reports import LOST_SPELL_NS, BusWatch
from bridge.output.mailbox import LoopStats
from bridge.output.transmit import TxState
from bridge.telemetry.reader import ReaderStats

SECOND_NS = 1_000_000_000


class Reports:
    def __init__(self) -> None:
        self.said: list[tuple[int, str, str]] = []

    def __call__(self, severity: int, text: str, detail: str) -> None:
        self.said.append((severity, text, detail))

    def texts(self) -> list[str]:
        texts = [text for _, text, _ in self.said]
        self.said.clear()
        return texts


def enter(stats: LoopStats, state: TxState) -> None:
    """As the loop does: the state and its entry count."""
    stats[f"entered_tx_{state.name.lower()}"] += 1
    stats["tx_state"] = state


def test_the_transmit_side_each_state_once_the_current_one_last() -> None:
    stats, reports = LoopStats(), Reports()
    watch = BusWatch(reports)
    watch.check(0, stats, None)
    assert reports.texts() == []  # moving from the start: nothing to say
    enter(stats, TxState.STUCK)
    stats["ticks_held"] = 40
    watch.check(1, stats, None)
    watch.check(2, stats, None)  # still stuck: said once
    assert reports.said[0][2] == "40 ticks held back in all, 0 frames refused, bus reopened 0 times"
    assert reports.texts() == ["CAN: FAULT bus stuck, frames not leaving"]
    # Gone and back, then down, all between two looks: each told, down (the current) last.
    enter(stats, TxState.GONE)
    enter(stats, TxState.MOVING)
    enter(stats, TxState.DOWN)
    watch.check(3, stats, None)
    assert reports.texts() == [
        "CAN: FAULT interface gone, reopening it",
        "CAN: frames leaving again",
        "CAN: FAULT interface down, frames not sent",
    ]
    enter(stats, TxState.MOVING)
    watch.check(4, stats, None)
    assert reports.texts() == ["CAN: frames leaving again"]


def test_the_controller_from_its_error_frames() -> None:
    stats, reader, reports = LoopStats(), ReaderStats(), Reports()
    watch = BusWatch(reports)
    controller = reader.controller
    controller.note(decode_error_frame(0x204, bytes.fromhex("0020000000008800")))
    watch.check(0, stats, reader)
    assert reports.said == [
        (
            4,
            "CAN: ERROR-PASSIVE, errors on the bus",
            "last error frame: controller: transmit error-passive (transmit errors 136, "
            "receive errors 0)",
        )
    ]
    reports.texts()
    controller.note(decode_error_frame(0x040, b""))  # bus-off
    controller.note(decode_error_frame(0x100, b""))  # restarted: error-active
    watch.check(1, stats, reader)
    assert controller.state == ControllerState.ERROR_ACTIVE
    assert reports.texts() == [
        "CAN: FAULT BUS-OFF, controller off the bus",
        "CAN: ERROR-ACTIVE again",
        "CAN: controller restarted",
    ]
    watch.check(2, stats, reader)
    assert reports.texts() == []


def test_lost_frames_once_a_spell() -> None:
    stats, reader, reports = LoopStats(), ReaderStats(), Reports()
    watch = BusWatch(reports)
    reader.kernel_drops = 0
    watch.check(0, stats, reader)
    reader.kernel_drops = 120
    watch.check(1 * SECOND_NS, stats, reader)
    assert reports.said[-1][2] == (
        "120 frames dropped by the kernel for the reader, 0 receive overflows of the controller"
    )
    assert reports.texts() == ["CAN: receive queue full, frames lost"]
    reader.kernel_drops = 300  # more, within the spell
    watch.check(5 * SECOND_NS, stats, reader)
    reader.controller.note(decode_error_frame(0x004, b"\x00\x01"))  # the controller's own
    watch.check(6 * SECOND_NS, stats, reader)
    watch.check(6 * SECOND_NS + LOST_SPELL_NS, stats, reader)
    assert reports.texts() == []
    watch.check(7 * SECOND_NS + LOST_SPELL_NS, stats, reader)  # the spell is over
    reader.kernel_drops = 301  # a new one
    watch.check(8 * SECOND_NS + LOST_SPELL_NS, stats, reader)
    assert reports.texts() == ["CAN: receive queue full, frames lost"]
