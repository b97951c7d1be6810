"""The CKESC family's ``[escs]`` keys (documented in config/README.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Final, Literal

from bridge.config_checks import check, choice, int_list, is_number, key

CkescCommand = Literal["12b", "14b", "10b"]
COMMAND_CHANNELS: Final = {"12b": 20, "14b": 4, "10b": 6}
"""The highest throttle channel each command frame carries."""


def _is_report_rates(v: Any) -> bool:
    return (
        isinstance(v, list | tuple)
        and len(v) == 3
        and all(is_number(x) and 2 <= x <= 50 for x in v)
    )


@dataclass(frozen=True)
class CkescKeys:
    ckesc_command: CkescCommand = key(
        "12b", choice("12b", "14b", "10b"), "CKESC throttle frame (14b: <= 4 ESCs; 10b: <= 6)"
    )
    ckesc_channels: tuple[int, ...] = key(
        (),
        int_list(1, 20),
        "CKESC throttle channel of each output (set in the ESC with Set ID); default 1..N",
        per_esc=True,
    )
    ckesc_msg_hz: tuple[float, float, float] = key(
        (50.0, 10.0, 2.0),
        check(_is_report_rates, "three rates [MSG1, MSG2, MSG3] in Hz, each 2..50"),
        "CKESC telemetry rates the ESCs are set to (for the bus-load check)",
    )
