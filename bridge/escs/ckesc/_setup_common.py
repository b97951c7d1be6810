"""What the CKESC set-up client (:mod:`bridge.escs.ckesc.setup`) shares with its callers: its
times, the services' names and conditions, the result records, and the names values go by."""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection, Iterable
from dataclasses import dataclass
from typing import Final, TypeVar

from bridge.errors import (
    ValueRangeError,
)
from bridge.escs import ckesc, uavcan_v0
from bridge.escs.ckesc import (
    EscInfoResponse,
    ExpandSetCommand,
    LedColor,
    Maintenance0Response,
    Maintenance1Response,
    Maintenance2Response,
    MajorConfigResponse,
    MsgControlCommand,
    MsgExp12,
    SelfTestFault,
    ThrottleSource,
)

DEFAULT_TIMEOUT_S: Final = 0.5
"""How long a request waits for its answer."""
ANSWER_WINDOW_S: Final = 0.064
"""GET_ESC_ID answers and MSGControl acks come (node_id % 32) x 2 ms late: within 64 ms."""
LEARN_WINDOW_S: Final = 0.1
"""How long :func:`learn_node_ids` listens for the answers (all of them by 62 ms)."""
SET_ID_WINDOW_S: Final = 120
"""An ESC takes Set ID and Set Baud only this long after power-up (seed 4.3.2)."""
COUNTER_MODULUS: Final = 1 << 32
"""The CANTest counter is a u32 that wraps."""
_DRAIN_LIMIT: Final = 100_000
"""At most this many queued frames are dropped before a request (a flooded bus never ends)."""

SERVICE_NAMES: Final[dict[int, str]] = {
    ckesc.SERVICE_SET_ID: "Set ID",
    ckesc.SERVICE_SET_BAUD: "Set Baud",
    ckesc.SERVICE_SET_LED: "Set LED",
    ckesc.SERVICE_SET_ROTATION: "Set Rotation",
    ckesc.SERVICE_SET_FREQ: "Set/Get Freq",
    ckesc.SERVICE_THROTTLE_SELECT: "Throttle Select",
    ckesc.SERVICE_SELF_TEST: "Self Test",
    ckesc.SERVICE_EXPAND_SET: "Expand Set",
    ckesc.SERVICE_ESC_INFO: "ESC Information",
    ckesc.SERVICE_MAINTENANCE: "Maintenance Information",
    ckesc.SERVICE_MAJOR_CONFIG: "Get Major Configuration",
}
"""The seed's name of each service type the client uses, for messages."""

_SET_ID_HELP: Final = (
    "an ESC takes Set ID only within 120 s of its power-up and only while no other ESC is "
    "on the bus: connect this ESC alone, switch its power off and on, and run set-id within "
    "2 minutes"
)
_CONDITIONS: Final[dict[int, str]] = {
    ckesc.SERVICE_SET_ID: _SET_ID_HELP,
    ckesc.SERVICE_SET_BAUD: "an ESC takes Set Baud only within 120 s of its power-up: switch "
    "its power off and on and set the bit rate within 2 minutes",
    ckesc.SERVICE_SET_LED: "an ESC takes Set LED only while its reports are on (MSGControl resume)",
    ckesc.SERVICE_SET_ROTATION: "an ESC takes Set Rotation only with the motor stopped and its "
    "reports on (MSGControl resume)",
    ckesc.SERVICE_SET_FREQ: "intervals must be 20..500 ms, even",
    ckesc.SERVICE_THROTTLE_SELECT: "an ESC takes Throttle Select only at zero throttle",
    ckesc.SERVICE_EXPAND_SET: "an ESC takes Expand Set only with the motor stopped, and may "
    "not support every part",
}
_NO_ANSWER_HELP: Final = (
    "is the ESC powered and wired (CAN H/L, 120 ohm at both ends), and does the bus run at the "
    "ESC's bit rate (500 kbit/s from the factory)?"
)

_R = TypeVar("_R")

LED_COLOR_NAMES: Final[dict[int, str]] = {
    0: "off",
    int(LedColor.BLUE): "blue",
    int(LedColor.GREEN): "green",
    int(LedColor.GREEN | LedColor.BLUE): "cyan",
    int(LedColor.RED): "red",
    int(LedColor.RED | LedColor.BLUE): "magenta",
    int(LedColor.RED | LedColor.GREEN): "yellow",
    int(LedColor.RED | LedColor.GREEN | LedColor.BLUE): "white",
}
"""Set LED's colour bits by name."""

MaintenanceResponse = Maintenance0Response | Maintenance1Response | Maintenance2Response
_MAINTENANCE_RESPONSES: Final[dict[int, type[MaintenanceResponse]]] = {
    0: Maintenance0Response,
    1: Maintenance1Response,
    2: Maintenance2Response,
}

# What Get Major Configuration shows of an Expand Set: command -> part -> (field, value).
_EXPAND_EFFECTS: Final[dict[int, dict[int, tuple[str, object]]]] = {
    ExpandSetCommand.DIRECTION: {1: ("direction_reversed", False), 2: ("direction_reversed", True)},
    ExpandSetCommand.LED: {
        0: ("led_color", LedColor(0)),
        1: ("led_color", LedColor.RED),
        2: ("led_color", LedColor.GREEN),
        3: ("led_color", LedColor.BLUE),
    },
    ExpandSetCommand.THROTTLE_INTERFACE: {
        2: ("throttle_source", ThrottleSource.PWM_AND_CAN),
        3: ("throttle_source", ThrottleSource.CAN),
    },
}
_TEMP_RECORDS: Final = 4
"""READ_TEMP_RECORD: the ESC sends MCU, MOS, capacitor and motor records."""


# --------------------------------------------------------------------------------------------
# Results


@dataclass(frozen=True, slots=True)
class ScannedEsc:
    """One GET_ESC_ID answer, with the ESC's information (240) and major configuration (242).

    ``problem`` says why ``info`` or ``config`` is missing (no answer, a shared node ID).
    """

    node_id: int
    throttle_channel: int
    info: EscInfoResponse | None = None
    config: MajorConfigResponse | None = None
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
    fault: SelfTestFault | int | None = None


@dataclass(frozen=True, slots=True)
class ExpandResult:
    """An Expand Set sent to ``node_id``.

    ``confirmed``: True when Get Major Configuration shows the new setting, None when nothing
    on the bus can show it (the motor's beep is the only sign). ``temp_records``: the MSG_EXP12
    records that answered READ_TEMP_RECORD.
    """

    node_id: int
    command: ExpandSetCommand
    part: int
    confirmed: bool | None
    temp_records: tuple[MsgExp12, ...] = ()


@dataclass(frozen=True, slots=True)
class ReportsResult:
    """A MSGControl command and the nodes that acknowledged it."""

    command: MsgControlCommand
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
    if ckesc.FACTORY_NODE_ID in by_node:
        warnings.append(
            f"node {ckesc.FACTORY_NODE_ID} is the factory node ID: such an ESC sends no "
            "telemetry; give it a node ID of its own (set-id)"
        )
    return warnings


# --------------------------------------------------------------------------------------------
# The client


def _check_node(node_id: object) -> int:
    if isinstance(node_id, int) and 1 <= node_id <= uavcan_v0.MAX_NODE_ID:
        return node_id
    raise ValueRangeError(
        f"node = {node_id!r} is not in 1..{uavcan_v0.MAX_NODE_ID} (0 is the host, "
        f"{uavcan_v0.MAX_NODE_ID + 1} and {uavcan_v0.MAX_NODE_ID + 2} are reserved)"
    )


def _service_label(service_type: int) -> str:
    return f"{SERVICE_NAMES.get(service_type, 'service')} ({service_type})"


def _nodes(nodes: Iterable[int]) -> str:
    return ", ".join(map(str, sorted(nodes)))


def led_color_name(color: LedColor | int) -> str:
    """ "red", "cyan", "off", ...: the name of an RGB combination (a number if not 0..7)."""
    return LED_COLOR_NAMES.get(int(color), str(int(color)))


def value_name(value: object) -> str:
    """A value as ``esc-bridge esc`` spells it: "reversed", "pwm-can", "phase-a-high", "cyan",
    "yes"; anything else as it prints."""
    if isinstance(value, LedColor):
        return led_color_name(value)
    if isinstance(value, bool):
        return "yes" if value else "no"
    if value == ThrottleSource.PWM_AND_CAN and isinstance(value, ThrottleSource):
        return "pwm-can"
    name = getattr(value, "name", None)
    return name.lower().replace("_", "-") if isinstance(name, str) else str(value)
