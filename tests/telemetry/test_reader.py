"""The CAN reader and error frames: an error frame (SocketCAN's word on the bus's faults) is read
into the controller's state and counts, never counted as a malformed frame; a frame received
after a bus-off says the controller is back."""

from __future__ import annotations

import can

from bridge.can_errors import ControllerState
from bridge.escs import registry
from bridge.telemetry.reader import CanReader
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
