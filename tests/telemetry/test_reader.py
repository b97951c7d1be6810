"""The CAN reader and error frames: an error frame (SocketCAN's word on the bus's faults) is read
into the controller's state and counts, never counted as a malformed frame; a frame received
after a bus-off says the controller is back. Its own filters, where the kernel has none, refuse
what python-can's would."""

from __future__ import annotations

import random
import threading
import time
from pathlib import Path

import can
import pytest

from bridge.can_errors import ControllerState
from bridge.escs import registry
from bridge.telemetry.reader import COALESCE_S, DECIDED_IDS, CanReader
from bridge.telemetry.state import EscTable


def _error(classes: int, data: str = "") -> can.Message:
    # As python-can's socketcan gives it: the class mask as the ID, CAN_ERR_FLAG as the flag.
    return can.Message(
        arbitration_id=classes, is_error_frame=True, is_extended_id=False,
        data=bytes.fromhex(data.ljust(16, "0")),
    )  # fmt: skip


def test_error_frames_fold_into_the_controller_not_into_malformed() -> None:
    recorded: list[can.Message] = []
    reader = CanReader(
        lambda: None, EscTable([1, 2]), registry.family("ckesc"), recorder=recorded.append
    )
    reader.handle(_error(0x204, "0020000000008800"), 1)
    reader.handle(_error(0x040), 2)
    stats = reader.stats
    assert (stats.frames, stats.malformed, stats.telemetry) == (2, 0, 0)
    controller = stats.controller
    assert (controller.state, controller.frames) == (ControllerState.BUS_OFF, 2)
    assert len(recorded) == 2  # the recording keeps them: candump logs error frames too
    # A frame of the bus again (an ESC's, garbage here: counted malformed as ever): not bus-off.
    reader.handle(can.Message(arbitration_id=0x1000, data=b"\x00"), 3)
    assert (controller.state, controller.entered) == (ControllerState.ERROR_ACTIVE, [1, 0, 1, 1])


def _voluntary_switches(native_id: int) -> int:
    for line in Path(f"/proc/self/task/{native_id}/status").read_text().splitlines():
        if line.startswith("voluntary_ctxt_switches:"):
            return int(line.split()[1])
    raise AssertionError("no voluntary_ctxt_switches")


def test_a_busy_bus_wakes_the_reader_at_a_coalesced_rate_and_its_filters_drop_the_rest() -> None:
    # On a bus without kernel filters (python-can's virtual here) the reader gets every frame
    # and filters them itself: what passes is counted, nothing else is.
    bus = can.Bus(interface="virtual", channel="test_reader_coalesced")
    sender = can.Bus(interface="virtual", channel="test_reader_coalesced")
    family = registry.family("ckesc")
    ours = family.reader_filters([1])
    assert ours
    reader = CanReader(bus, EscTable([1]), family, filters=ours)
    passed = can.Message(arbitration_id=ours[0]["can_id"], data=bytes(8), is_extended_id=True)
    refused = can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=True)
    reader.start()
    try:
        (thread,) = [t for t in threading.enumerate() if t.name == "can-reader"]
        native_id = thread.native_id
        assert native_id is not None
        seconds, per_ms = 1.0, 2  # 2 000 frames a second, each pair apart by a millisecond
        switches_before = _voluntary_switches(native_id)
        started = time.monotonic()
        sent = 0
        while (elapsed := time.monotonic() - started) < seconds:
            for _ in range(per_ms):
                sender.send(refused if sent % 2 else passed)
                sent += 1
            time.sleep(0.001)
        time.sleep(3 * COALESCE_S)
        wakes = _voluntary_switches(native_id) - switches_before
        stats = reader.stats
        assert stats.frames == (sent + 1) // 2  # the refused half never counted
        # About one wake-up per coalescing period (measured: 52 to 55 in 1.06 s, beside two
        # busy processes too); twice that for the GIL's hand-overs, against one per frame if
        # each woke it (921 for 1 704 frames, measured without the coalescing).
        assert wakes <= 2 * (elapsed + 3 * COALESCE_S) / COALESCE_S, (wakes, sent)
    finally:
        reader.close()
        sender.shutdown()
        bus.shutdown()


@pytest.mark.parametrize("name", ["ckesc", "ft", "dronecan", "vesc"])
def test_the_readers_filters_refuse_what_python_cans_own_refuse(name: str) -> None:
    """The reader's verdict on each ID (kept per ID, and started again past DECIDED_IDS) is
    python-can's: a virtual bus given the same filters lets through the same frames. IDs: each
    filter's own and its neighbours, and random standard and extended IDs, twice over."""
    family = registry.family(name)
    filters = family.reader_filters(range(1, 9))
    rng = random.Random(name)
    ids = [(f["can_id"] ^ flip, True) for f in filters for flip in (0, 1, 0x80, 0x100)]
    ids += [(rng.getrandbits(29), True) for _ in range(DECIDED_IDS + 200)]
    ids += [(rng.getrandbits(11), False) for _ in range(50)]
    messages = [can.Message(arbitration_id=i, is_extended_id=e, data=bytes(8)) for i, e in ids * 2]
    reader = CanReader(lambda: None, EscTable(list(range(1, 9))), family, filters=filters)
    ours = []
    for msg in messages:
        before = reader.stats.frames
        reader.handle(msg, 0)
        ours.append(reader.stats.frames > before)
    with (
        can.Bus(interface="virtual", channel=f"filters-{name}", can_filters=filters) as bus,
        can.Bus(interface="virtual", channel=f"filters-{name}") as sender,
    ):
        theirs = []
        for msg in messages:
            sender.send(msg)
            # One frame queued: recv gives it, or None where the filters refuse it.
            theirs.append(bus.recv(0) is not None)
    assert ours == theirs
    assert 0 < sum(theirs) < len(messages) / 2
