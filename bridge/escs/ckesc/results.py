"""What the CKESC set-up client (:mod:`bridge.escs.ckesc.setup`) answers, and the names its
values go by in ``esc-bridge esc``: the result records, what a scan shows that needs fixing,
the services' and LED colours' names."""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection
from dataclasses import dataclass
from typing import Final

from bridge.escs.ckesc import records

COUNTER_MODULUS: Final = 1 << 32
"""The CANTest counter is a u32 that wraps."""

SERVICE_NAMES: Final[dict[int, str]] = {
    records.SERVICE_SET_ID: "Set ID",
    records.SERVICE_SET_BAUD: "Set Baud",
    records.SERVICE_SET_LED: "Set LED",
    records.SERVICE_SET_ROTATION: "Set Rotation",
    records.SERVICE_SET_FREQ: "Set/Get Freq",
    records.SERVICE_THROTTLE_SELECT: "Throttle Select",
    records.SERVICE_SELF_TEST: "Self Test",
    records.SERVICE_EXPAND_SET: "Expand Set",
    records.SERVICE_ESC_INFO: "ESC Information",
    records.SERVICE_MAINTENANCE: "Maintenance Information",
    records.SERVICE_MAJOR_CONFIG: "Get Major Configuration",
}
"""The seed's name of each service type the client uses, for messages."""

LED_COLOR_NAMES: Final[dict[int, str]] = {
    0: "off",
    int(records.LedColor.BLUE): "blue",
    int(records.LedColor.GREEN): "green",
    int(records.LedColor.GREEN | records.LedColor.BLUE): "cyan",
    int(records.LedColor.RED): "red",
    int(records.LedColor.RED | records.LedColor.BLUE): "magenta",
    int(records.LedColor.RED | records.LedColor.GREEN): "yellow",
    int(records.LedColor.RED | records.LedColor.GREEN | records.LedColor.BLUE): "white",
}
"""Set LED's colour bits by name."""

MaintenanceResponse = (
    records.Maintenance0Response | records.Maintenance1Response | records.Maintenance2Response
)


@dataclass(frozen=True, slots=True)
class ScannedEsc:
    """One GET_ESC_ID answer, with the ESC's information (240) and major configuration (242).

    ``problem`` says why ``info`` or ``config`` is missing (no answer, a shared node ID).
    """

    node_id: int
    throttle_channel: int
    info: records.EscInfoResponse | None = None
    config: records.MajorConfigResponse | None = None
    problem: str | None = None


@dataclass(frozen=True, slots=True)
class SetIdResult:
    """A Set ID the ESC took: its node ID and channel before and now (saved in its flash)."""

    old_node_id: int
    old_throttle_channel: int
    node_id: int
    throttle_channel: int


@dataclass(frozen=True, slots=True)
class SelfTestResult:
    """Self Test's answer; for a failed test, fault code 1 from Maintenance option 2 (None when
    the ESC did not give it)."""

    node_id: int
    passed: bool
    fault: records.SelfTestFault | int | None = None


@dataclass(frozen=True, slots=True)
class ExpandResult:
    """An Expand Set sent to ``node_id``.

    ``confirmed``: True when Get Major Configuration shows the new setting, None when nothing
    on the bus can show it (the motor's beep is the only sign). ``temp_records``: the MSG_EXP12
    records that answered READ_TEMP_RECORD.
    """

    node_id: int
    command: records.ExpandSetCommand
    part: int
    confirmed: bool | None
    temp_records: tuple[records.MsgExp12, ...] = ()


@dataclass(frozen=True, slots=True)
class ReportsResult:
    """A MSGControl command and the nodes that acknowledged it."""

    command: records.MsgControlCommand
    acked_by: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class CanTestResult:
    """CANTest reports of one ESC over ``duration_s``, counted against their counter."""

    node_id: int
    received: int
    first_count: int
    last_count: int
    duration_s: float

    @property
    def expected(self) -> int:
        """Reports the counter says were sent from the first received to the last."""
        return (self.last_count - self.first_count) % COUNTER_MODULUS + 1

    @property
    def lost(self) -> int:
        """Reports missing between the first and the last received."""
        return max(0, self.expected - self.received)


def scan_warnings(escs: Collection[ScannedEsc]) -> list[str]:
    """What a scan shows that needs fixing before flight: shared node IDs, shared throttle
    channels, ESCs still at the factory node ID (which send no telemetry)."""
    warnings = []
    by_node = Counter(esc.node_id for esc in escs)
    for node, count in sorted(by_node.items()):
        if count > 1:
            warnings.append(
                f"{count} ESCs answered as node {node}: connect them one at a time and give "
                "each its own node ID (set-id)"
            )
    channels: dict[int, set[int]] = {}
    for esc in escs:
        channels.setdefault(esc.throttle_channel, set()).add(esc.node_id)
    for channel, nodes in sorted(channels.items()):
        if len(nodes) > 1:
            listed = ", ".join(map(str, sorted(nodes)))
            warnings.append(
                f"nodes {listed} all follow throttle channel {channel}: they would spin "
                "together; give each its own channel (set-id)"
            )
    if records.FACTORY_NODE_ID in by_node:
        warnings.append(
            f"node {records.FACTORY_NODE_ID} is the factory node ID: such an ESC sends no "
            "telemetry; give it a node ID of its own (set-id)"
        )
    return warnings


def led_color_name(color: records.LedColor | int) -> str:
    """ "red", "cyan", "off", ...: the name of an RGB combination (a number if not 0..7)."""
    return LED_COLOR_NAMES.get(int(color), str(int(color)))


def value_name(value: object) -> str:
    """A value as ``esc-bridge esc`` spells it: "reversed", "pwm-can", "phase-a-high", "cyan",
    "yes"; anything else as it prints."""
    if isinstance(value, records.LedColor):
        return led_color_name(value)
    if isinstance(value, bool):
        return "yes" if value else "no"
    if value == records.ThrottleSource.PWM_AND_CAN and isinstance(value, records.ThrottleSource):
        return "pwm-can"
    name = getattr(value, "name", None)
    return name.lower().replace("_", "-") if isinstance(name, str) else str(value)
