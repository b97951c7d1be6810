"""The DroneCAN family's ``[escs]`` keys (documented in config/README.md)."""

from __future__ import annotations

from dataclasses import dataclass

from bridge.config_checks import float_range, int_list, int_range, key
from bridge.escs.dronecan.wire import DEFAULT_NODE_ID


@dataclass(frozen=True)
class DronecanKeys:
    dronecan_node_id: int = key(
        DEFAULT_NODE_ID,
        int_range(1, 125),
        "the bridge's own DroneCAN node ID, the source of its RawCommand and NodeStatus "
        "(default 10, as ArduPilot's CAN_D1_UC_NODE)",
    )
    dronecan_reversible: tuple[int, ...] = key(
        (),
        int_list(1, 20),
        "DroneCAN ESCs (by ESC number in ids) that run both ways: -1..1 becomes -8191..8191 "
        "(as ArduPilot's CAN_D1_UC_ESC_RV); the others get 0..8191",
    )
    dronecan_status_hz: float = key(
        50.0,
        float_range(0, 1000),
        "esc.Status transfers each DroneCAN ESC sends per second (for the bus-load check)",
    )
