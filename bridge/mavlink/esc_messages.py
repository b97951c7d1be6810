"""ESC telemetry as MAVLink messages: ESC_STATUS, ESC_INFO and ArduPilot's ESC_TELEMETRY_x_TO_y.

Pure: ESC snapshots in, pymavlink message objects out (no clock, socket or lock), every value
clamped to its field's range and NaN/None turned into the field's "unknown". Then the message
sets each kind of connection carries by default, and what they cost in bytes per second (for
``run --check``). :mod:`bridge.mavlink.telemetry_out` sends them.

Encoding choices the MAVLink definitions leave open (docs/telemetry.md, "MAVLink out"):

* An offline ESC (no frame within the table's timeout) reports its measurements as unknown:
  rpm, voltage, current 0 and temperature INT16_MAX (ESC_INFO) or 0 (ESC_TELEMETRY), so a
  ground station never shows a dead ESC's last values as live. Its failure flags, error count,
  consumed charge and frame count are state, not measurements, and are still sent.
* Batches cover four ESCs in motor order; ``index`` is the first ESC's 0-based position. The
  last batch pads the missing ESCs with zeros (INT16_MAX temperature); ESC_INFO ``count`` says
  how many ESCs there are. ESC_STATUS and ESC_INFO cover the first 64 ESCs (``index`` 0..60, as
  the definition allows), ESC_TELEMETRY_x_TO_y the first 32.
* ESC_INFO ``info`` is the whole vehicle's online bits, the same in every batch: bit i set while
  motor i (0-based) is online, as PX4 fills it (``esc_online_flags``) and QGroundControl's ESC
  page reads it. It is a uint8, so ESCs from the ninth on have no bit there.
* ``time_usec`` is the autopilot's time since boot (µs) when the sender knows it (its
  SYSTEM_TIME or TIMESYNC), as PX4 stamps these messages and mavros expects; before that, µs
  since the Unix epoch (the definition allows both; a receiver tells them apart by size).
* ESC_INFO ``counter`` is "telemetry packets received": every frame received from the ESCs,
  all of them together, modulo 65536. It moves only while ESC telemetry arrives.
* A real ESC_INFO temperature is clamped to -32768..32766 cdegC, so it never reads as the
  INT16_MAX "unknown".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Final, Literal

from bridge.config import MavlinkConfig
from bridge.telemetry.state import EscSnapshot

__all__ = [
    "AUTOPILOT_SETS",
    "ESCS_PER_MESSAGE",
    "ESC_TELEMETRY_MAX_ESCS",
    "FAMILIES",
    "INFO_BITS",
    "MAX_ESCS",
    "OTHER_AUTOPILOT_SET",
    "TELEMETRY_GROUPS",
    "Family",
    "as_rates",
    "bytes_per_s",
    "describe_sets",
    "esc_info_messages",
    "esc_status_messages",
    "esc_telemetry_messages",
    "messages_per_round",
    "online_bits",
    "packets_received",
    "rates_text",
]


Family = Literal["esc_status", "esc_info", "esc_telemetry"]
FAMILIES: Final[tuple[Family, ...]] = ("esc_status", "esc_info", "esc_telemetry")

ESCS_PER_MESSAGE: Final = 4
ESC_TELEMETRY_MAX_ESCS: Final = 32
"""ArduPilot defines ESC_TELEMETRY_1_TO_4 .. ESC_TELEMETRY_29_TO_32 only."""
MAX_ESCS: Final = 64
"""ESC_STATUS/ESC_INFO ``index`` runs 0..60 by the definition: 16 batches of four."""
INFO_BITS: Final = 8
"""ESC_INFO ``info`` is a uint8: the online bits of motors 0..7."""

ESC_CONNECTION_TYPE_CAN: Final = 4
"""ESC_CONNECTION_TYPE_CAN: every ESC the bridge drives is on CAN."""
INT16_MAX: Final = 32_767
"""ESC_INFO temperature "unknown"."""
_INT16_MIN: Final = -32_768
_INT32_MIN: Final = -(2**31)
_INT32_MAX: Final = 2**31 - 1
_UINT8_MAX: Final = 0xFF
_UINT16_MAX: Final = 0xFFFF
_UINT32_MAX: Final = 0xFFFF_FFFF
_FLOAT32_MAX: Final = 3.4028234663852886e38  # a larger Python float cannot be packed as float

TELEMETRY_GROUPS: Final = tuple(
    (first, first + ESCS_PER_MESSAGE - 1)
    for first in range(1, ESC_TELEMETRY_MAX_ESCS + 1, ESCS_PER_MESSAGE)
)
"""(1, 4), (5, 8) .. (29, 32): the ESCs each ESC_TELEMETRY_x_TO_y message carries."""


# -- pure encoders --------------------------------------------------------------------------


def _known(value: float | None) -> float | None:
    """``value`` if it is a real number; NaN and infinities are as unknown as None."""
    return value if value is not None and math.isfinite(value) else None


def _clamp_int(value: float, low: int, high: int) -> int:
    """``value`` rounded to the nearest integer and held within ``low..high``."""
    return max(low, min(high, round(value)))


def _float32(value: float | None) -> float:
    """A float field's value: 0.0 when unknown, else within float32's range."""
    known = _known(value)
    return 0.0 if known is None else max(-_FLOAT32_MAX, min(_FLOAT32_MAX, known))


def _batches(snapshots: Sequence[EscSnapshot], limit: int) -> list[list[EscSnapshot | None]]:
    """The first ``limit`` ESCs in groups of four, the last group padded with None."""
    escs = list(snapshots[:limit])
    return [
        (escs[first : first + ESCS_PER_MESSAGE] + [None] * ESCS_PER_MESSAGE)[:ESCS_PER_MESSAGE]
        for first in range(0, len(escs), ESCS_PER_MESSAGE)
    ]


def _live(esc: EscSnapshot | None) -> EscSnapshot | None:
    """The ESC if its measurements are current (it is online), else None: unknown."""
    return esc if esc is not None and esc.online else None


def esc_status_messages(mav: Any, snapshots: Sequence[EscSnapshot], time_usec: int) -> list[Any]:
    """ESC_STATUS messages (id 291) for every batch of four ESCs, in motor order.

    ``mav`` is the dialect's MAVLink object (``MavlinkLink.mav``); ``time_usec`` is when the
    snapshots were taken (the autopilot's boot clock or the Unix epoch: the module docstring).
    Per ESC: ``rpm`` signed mechanical rpm (int32), ``voltage`` in V and ``current`` in A
    (float); 0 when unknown or the ESC is offline.
    """
    messages = []
    for batch_no, batch in enumerate(_batches(snapshots, MAX_ESCS)):
        live = [_live(esc) for esc in batch]
        rpm = [
            0 if esc is None or esc.rpm is None else _clamp_int(esc.rpm, _INT32_MIN, _INT32_MAX)
            for esc in live
        ]
        voltage_v = [_float32(esc.voltage_v if esc else None) for esc in live]
        current_a = [_float32(esc.current_a if esc else None) for esc in live]
        messages.append(
            mav.esc_status_encode(batch_no * ESCS_PER_MESSAGE, time_usec, rpm, voltage_v, current_a)
        )
    return messages


def _temperature_cdeg(esc: EscSnapshot | None) -> int:
    """ESC_INFO temperature: cdegC, INT16_MAX when unknown (a real value never reaches it)."""
    temp_c = _known(esc.esc_temp_c) if esc is not None else None
    if temp_c is None:
        return INT16_MAX
    return _clamp_int(temp_c * 100.0, _INT16_MIN, INT16_MAX - 1)


def online_bits(snapshots: Sequence[EscSnapshot]) -> int:
    """ESC_INFO ``info``: bit i set while motor i (0-based; the first :data:`INFO_BITS`) is
    online."""
    return sum(1 << i for i, esc in enumerate(snapshots[:INFO_BITS]) if esc.online)


def packets_received(snapshots: Sequence[EscSnapshot]) -> int:
    """ESC_INFO ``counter``: telemetry frames received from all ESCs together, modulo 65536."""
    return sum(esc.frames for esc in snapshots) & _UINT16_MAX


def esc_info_messages(mav: Any, snapshots: Sequence[EscSnapshot], time_usec: int) -> list[Any]:
    """ESC_INFO messages (id 290) for every batch of four ESCs, in motor order.

    Every batch carries the vehicle's ``count`` (number of ESCs), ``counter``
    (:func:`packets_received`), ``connection_type`` CAN and ``info`` (:func:`online_bits`, bit i
    = motor i). Per ESC: ``failure_flags`` (ESC_FAILURE_FLAGS), ``error_count`` (CRC/format
    errors) and ``temperature`` in cdegC (INT16_MAX when unknown or offline).
    """
    count = min(len(snapshots), MAX_ESCS)
    online = online_bits(snapshots)
    counter = packets_received(snapshots)
    messages = []
    for batch_no, batch in enumerate(_batches(snapshots, MAX_ESCS)):
        failure_flags = [
            0 if esc is None else _clamp_int(esc.failure_flags, 0, _UINT16_MAX) for esc in batch
        ]
        error_count = [
            0 if esc is None else _clamp_int(esc.errors, 0, _UINT32_MAX) for esc in batch
        ]
        temperature = [_temperature_cdeg(_live(esc)) for esc in batch]
        messages.append(
            mav.esc_info_encode(
                batch_no * ESCS_PER_MESSAGE,
                time_usec,
                counter,
                count,
                ESC_CONNECTION_TYPE_CAN,
                online,
                failure_flags,
                error_count,
                temperature,
            )
        )
    return messages


def _uint(value: float | None, scale: float, high: int) -> int:
    """An unsigned fixed-point field: ``value * scale`` rounded, 0 when unknown, ≤ ``high``."""
    known = _known(value)
    return 0 if known is None else _clamp_int(known * scale, 0, high)


def esc_telemetry_messages(mav: Any, snapshots: Sequence[EscSnapshot]) -> list[Any]:
    """ArduPilot's ESC_TELEMETRY_1_TO_4 .. ESC_TELEMETRY_29_TO_32 for the first 32 ESCs.

    Per ESC: ``temperature`` °C (uint8, 0 when unknown), ``voltage`` cV, ``current`` cA,
    ``totalcurrent`` mAh consumed, ``rpm`` |mechanical rpm| (uint16 each, clamped; the
    measurements 0 when unknown or offline), ``count`` = telemetry frames received mod 65536.
    """
    messages = []
    for batch_no, batch in enumerate(_batches(snapshots, ESC_TELEMETRY_MAX_ESCS)):
        live = [_live(esc) for esc in batch]
        temperature = [_uint(esc.esc_temp_c if esc else None, 1, _UINT8_MAX) for esc in live]
        voltage_cv = [_uint(esc.voltage_v if esc else None, 100, _UINT16_MAX) for esc in live]
        current_ca = [_uint(esc.current_a if esc else None, 100, _UINT16_MAX) for esc in live]
        rpm = [
            _uint(abs(esc.rpm) if esc and esc.rpm is not None else None, 1, _UINT16_MAX)
            for esc in live
        ]
        consumed_mah = [_uint(esc.consumed_mah if esc else None, 1, _UINT16_MAX) for esc in batch]
        frames = [0 if esc is None else esc.frames % (_UINT16_MAX + 1) for esc in batch]
        first, last = TELEMETRY_GROUPS[batch_no]
        encode = getattr(mav, f"esc_telemetry_{first}_to_{last}_encode")
        messages.append(encode(temperature, voltage_cv, current_ca, consumed_mah, rpm, frames))
    return messages


MAV_AUTOPILOT_ARDUPILOTMEGA: Final = 3
MAV_AUTOPILOT_PX4: Final = 12

AUTOPILOT_SETS: Final[dict[int | None, dict[Family, float]]] = {
    # ArduPilot's MAVLink lacks ESC_INFO (290) and ESC_STATUS (291) and drops them; it forwards
    # ESC_TELEMETRY_x_TO_y to its ground stations.
    MAV_AUTOPILOT_ARDUPILOTMEGA: {"esc_status": 0.0, "esc_info": 0.0, "esc_telemetry": 2.0},
    # PX4 forwards ESC_INFO and ESC_STATUS to its ground-station link, not ESC_TELEMETRY_x_TO_y.
    MAV_AUTOPILOT_PX4: {"esc_status": 2.0, "esc_info": 1.0, "esc_telemetry": 0.0},
    # Before the autopilot's first HEARTBEAT: nothing (it comes within a second).
    None: {"esc_status": 0.0, "esc_info": 0.0, "esc_telemetry": 0.0},
}
"""The autopilot link's default set by the autopilot's HEARTBEAT ``autopilot`` (MAV_AUTOPILOT),
in Hz: only what it forwards, slowly, since its radio to a ground station may be a 57600-baud
link (~5.7 kB/s). Any other flight stack gets :data:`OTHER_AUTOPILOT_SET`."""
OTHER_AUTOPILOT_SET: Final[dict[Family, float]] = {
    "esc_status": 2.0,
    "esc_info": 1.0,
    "esc_telemetry": 2.0,
}
"""A flight stack the bridge does not know (not ArduPilot, not PX4): every family, slowly."""


def rates_text(rates: dict[Family, float]) -> str:
    on = [f"{name} {rates[f]:g} Hz" for f, name in _NAMES.items() if rates[f] > 0]
    return ", ".join(on) or "nothing"


_NAMES: Final[dict[Family, str]] = {
    "esc_status": "ESC_STATUS",
    "esc_info": "ESC_INFO",
    "esc_telemetry": "ESC_TELEMETRY",
}


FRAME_OVERHEAD: Final = 12
"""A MAVLink 2 frame's bytes besides its payload: 10 of header, 2 of checksum."""
SIGNATURE_BYTES: Final = 13
"""What signing adds to each frame: link ID, 6-byte timestamp, 6-byte signature."""
PAYLOAD_BYTES: Final[dict[Family, int]] = {"esc_status": 57, "esc_info": 46, "esc_telemetry": 44}
"""Each family's full payload. MAVLink 2 drops trailing zero bytes, so a frame is at most
this plus :data:`FRAME_OVERHEAD`; with live ESCs it is that long."""


def messages_per_round(family: Family, n_escs: int) -> int:
    """How many messages one round of ``family`` is for ``n_escs`` ESCs (batches of four)."""
    limit = ESC_TELEMETRY_MAX_ESCS if family == "esc_telemetry" else MAX_ESCS
    return -(-min(n_escs, limit) // ESCS_PER_MESSAGE)


def bytes_per_s(rates: dict[Family, float], n_escs: int, signed: bool = False) -> float:
    """The most bytes per second a message set sends for ``n_escs`` ESCs (every frame full)."""
    extra = FRAME_OVERHEAD + (SIGNATURE_BYTES if signed else 0)
    return sum(
        rate * messages_per_round(family, n_escs) * (PAYLOAD_BYTES[family] + extra)
        for family, rate in rates.items()
    )


def describe_sets(config: MavlinkConfig, n_escs: int) -> str:
    """What each connection carries by default and its bytes per second for ``n_escs`` ESCs,
    one line (for ``run --check``)."""
    signed = config.signing_key is not None

    def text(rates: dict[Family, float]) -> str:
        load = bytes_per_s(rates, n_escs, signed)
        return f"{rates_text(rates)} ({load:.0f} B/s)" if load else rates_text(rates)

    if config.autopilot_messages is not None:
        autopilot = text(as_rates(config.autopilot_messages))
    else:
        autopilot = (
            f"by its HEARTBEAT: ArduPilot {text(AUTOPILOT_SETS[MAV_AUTOPILOT_ARDUPILOTMEGA])}; "
            f"PX4 {text(AUTOPILOT_SETS[MAV_AUTOPILOT_PX4])}; other {text(OTHER_AUTOPILOT_SET)}"
        )
    parts = [f"autopilot link {autopilot}"]
    for url in config.outputs:
        parts.append(f"{url} {text(as_rates(config.output_rates(url)))}")
    return f"MAVLink ESC telemetry for {n_escs} ESCs: " + "; ".join(parts)


def as_rates(table: Any) -> dict[Family, float]:
    """A configured message set (a family not listed is off) as a rate per family."""
    return {family: float(table.get(family, 0.0)) for family in FAMILIES}
