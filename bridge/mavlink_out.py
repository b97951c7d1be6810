"""ESC telemetry over MAVLink: ESC_STATUS, ESC_INFO and ArduPilot's ESC_TELEMETRY_x_TO_y.

Pure encoders first: ESC snapshots in, pymavlink message objects out (no clock, socket or
lock), every value clamped to its field's range and NaN/None turned into the field's "unknown".
Then :class:`MavlinkTelemetry`, a named daemon thread that sends each of the three message
families at its own rate through :meth:`MavlinkLink.send` and lets a ground station change those
rates (MAV_CMD_SET_MESSAGE_INTERVAL), ask for one message now (MAV_CMD_REQUEST_MESSAGE) or read
a rate (MAV_CMD_GET_MESSAGE_INTERVAL). It reads only :class:`EscTable` snapshots and touches
nothing of the output loop, so it can never slow a motor command down.

Encoding choices the MAVLink definitions leave open (README, "ESC telemetry over MAVLink"):

* An offline ESC (no frame within the table's timeout) reports its measurements as unknown:
  rpm, voltage, current 0 and temperature INT16_MAX (ESC_INFO) or 0 (ESC_TELEMETRY), so a
  ground station never shows a dead ESC's last values as live. Its failure flags, error count,
  consumed charge and frame count are state, not measurements, and are still sent.
* Batches cover four ESCs in motor order; ``index`` is the first ESC's 0-based position. The
  last batch pads the missing ESCs with zeros (INT16_MAX temperature); ESC_INFO ``count`` says
  how many ESCs there are. ESC_STATUS and ESC_INFO cover up to 255 ESCs (``index`` and
  ``count`` are uint8), ESC_TELEMETRY_x_TO_y the first 32.
* ``time_usec`` is wall time, µs since the Unix epoch (published data uses wall time).
* ESC_INFO ``counter`` counts ESC_INFO rounds (all batches, once each) sent since start,
  modulo 65536, the first round carrying 1: every batch's counter goes up by one each time
  that batch is sent, periodically or on request.
* A real ESC_INFO temperature is clamped to -32768..32766 cdegC, so it never reads as the
  INT16_MAX "unknown".
* Intervals shorter than :data:`MIN_INTERVAL_US` (faster than 100 Hz) are refused with
  MAV_RESULT_DENIED; an interval of 0 restores the configured rate, -1 turns the family off,
  any other negative value is DENIED. Setting the interval of any ESC_TELEMETRY_x_TO_y sets the
  rate of all of them (one family). MAV_CMD_REQUEST_MESSAGE for an ESC_TELEMETRY_x_TO_y sends
  only that batch, and is DENIED when no configured ESC falls into it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Final, Literal

from bridge.config import MavlinkConfig
from bridge.mavlink_in import MavlinkLink
from bridge.telemetry.state import EscSnapshot, EscTable

__all__ = [
    "ESCS_PER_MESSAGE",
    "ESC_TELEMETRY_MAX_ESCS",
    "MAX_ESCS",
    "MIN_INTERVAL_US",
    "Family",
    "MavlinkTelemetry",
    "TelemetryStats",
    "esc_info_messages",
    "esc_status_messages",
    "esc_telemetry_messages",
]

log = logging.getLogger(__name__)

Family = Literal["esc_status", "esc_info", "esc_telemetry"]
FAMILIES: Final[tuple[Family, ...]] = ("esc_status", "esc_info", "esc_telemetry")

ESCS_PER_MESSAGE: Final = 4
ESC_TELEMETRY_MAX_ESCS: Final = 32
"""ArduPilot defines ESC_TELEMETRY_1_TO_4 .. ESC_TELEMETRY_29_TO_32 only."""
MAX_ESCS: Final = 255
"""ESC_STATUS/ESC_INFO ``index`` and ESC_INFO ``count`` are uint8."""
MIN_INTERVAL_US: Final = 10_000
"""The shortest interval a ground station may ask for: 100 Hz, the configuration's ceiling."""

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

_TELEMETRY_GROUPS: Final = tuple(
    (first, first + ESCS_PER_MESSAGE - 1)
    for first in range(1, ESC_TELEMETRY_MAX_ESCS + 1, ESCS_PER_MESSAGE)
)
"""(1, 4), (5, 8) .. (29, 32): the ESCs each ESC_TELEMETRY_x_TO_y message carries."""

_IDLE_WAIT_S: Final = 1.0  # the sender re-checks this often even with every family off
_JOIN_TIMEOUT_S: Final = 2.0


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
    snapshots were taken (wall µs). Per ESC: ``rpm`` signed mechanical rpm (int32), ``voltage``
    in V and ``current`` in A (float); 0 when unknown or the ESC is offline.
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


def esc_info_messages(
    mav: Any, snapshots: Sequence[EscSnapshot], time_usec: int, counter: int
) -> list[Any]:
    """ESC_INFO messages (id 290) for every batch of four ESCs, in motor order.

    ``counter`` goes into every batch (kept to uint16). Per batch: ``count`` = number of ESCs,
    ``connection_type`` CAN, ``info`` bit i set while ESC ``index + i`` is online. Per ESC:
    ``failure_flags`` (ESC_FAILURE_FLAGS), ``error_count`` (CRC/format errors) and
    ``temperature`` in cdegC (INT16_MAX when unknown or offline).
    """
    count = min(len(snapshots), MAX_ESCS)
    messages = []
    for batch_no, batch in enumerate(_batches(snapshots, MAX_ESCS)):
        online = sum(1 << i for i, esc in enumerate(batch) if esc is not None and esc.online)
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
                counter & _UINT16_MAX,
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
        first, last = _TELEMETRY_GROUPS[batch_no]
        encode = getattr(mav, f"esc_telemetry_{first}_to_{last}_encode")
        messages.append(encode(temperature, voltage_cv, current_ca, consumed_mah, rpm, frames))
    return messages


# -- the sender -----------------------------------------------------------------------------


@dataclass
class TelemetryStats:
    """Messages handed to the link, per family, and encoding faults; updated in place."""

    esc_status: int = 0
    esc_info: int = 0
    esc_telemetry: int = 0
    errors: int = 0
    """Rounds not sent because encoding or sending raised (a bug); logged."""


class MavlinkTelemetry:
    """Sends ESC telemetry from an :class:`EscTable` over a :class:`MavlinkLink`.

    Rates start at ``esc_status_hz``, ``esc_info_hz`` and ``esc_telemetry_hz`` (0 = off) and
    follow a ground station's MAV_CMD_SET_MESSAGE_INTERVAL until the next start. Use
    :meth:`start` once, then :meth:`close` (or a ``with`` block). The link need not be started
    yet: until it is, what is sent is dropped and counted by the link.
    """

    def __init__(self, config: MavlinkConfig, link: MavlinkLink, table: EscTable) -> None:
        self._link = link
        self._table = table
        dialect = link.dialect
        self._dialect = dialect
        self._default_hz: dict[Family, float] = {
            "esc_status": config.esc_status_hz,
            "esc_info": config.esc_info_hz,
            "esc_telemetry": config.esc_telemetry_hz,
        }
        self._families: dict[int, Family] = {
            dialect.MAVLINK_MSG_ID_ESC_STATUS: "esc_status",
            dialect.MAVLINK_MSG_ID_ESC_INFO: "esc_info",
        }
        self._telemetry_batch: dict[int, int] = {}  # ESC_TELEMETRY_x_TO_y id -> batch number
        for batch_no, (first, last) in enumerate(_TELEMETRY_GROUPS):
            msg_id: int = getattr(dialect, f"MAVLINK_MSG_ID_ESC_TELEMETRY_{first}_TO_{last}")
            self._families[msg_id] = "esc_telemetry"
            self._telemetry_batch[msg_id] = batch_no
        self.stats = TelemetryStats()
        self._lock = threading.Lock()  # guards _rate_hz, _requested and _rescheduled
        self._rate_hz = dict(self._default_hz)
        self._requested: list[int] = []  # message IDs to send once, soon
        self._rescheduled: set[Family] = set()  # families whose rate changed
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        self._info_rounds = 0  # owned by the sender thread

    def rate_hz(self, family: Family) -> float:
        """The family's current rate; 0 = off."""
        with self._lock:
            return self._rate_hz[family]

    def start(self) -> None:
        """Register the command handler and start the sender thread.

        Raises:
            RuntimeError: started before, or closed.
        """
        if self._thread is not None or self._closed:
            raise RuntimeError("a MavlinkTelemetry can be started once, and not after close()")
        self._link.add_command_handler(self.handle_command)
        self._thread = threading.Thread(target=self._run, name="mavlink-telemetry", daemon=True)
        self._thread.start()
        log.info(
            "MAVLink ESC telemetry: ESC_STATUS %g Hz, ESC_INFO %g Hz, ESC_TELEMETRY %g Hz",
            *self._default_hz.values(),
        )

    def close(self) -> None:
        """Stop sending and unregister the command handler; a second call does nothing."""
        if self._closed:
            return
        self._closed = True
        if self._thread is None:
            return
        self._link.remove_command_handler(self.handle_command)
        self._stop.set()
        self._wake.set()
        self._thread.join(_JOIN_TIMEOUT_S)
        if self._thread.is_alive():
            log.warning("%s did not stop within %.0f s", self._thread.name, _JOIN_TIMEOUT_S)

    def __enter__(self) -> MavlinkTelemetry:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- commands (on the link's reader thread: no waiting here) ----------------------------

    def handle_command(self, msg: Any) -> int | None:
        """The link's command handler: a MAV_RESULT for the interval and request commands
        about our messages, None for anything else (so it is not claimed)."""
        dialect = self._dialect
        command: int = msg.command
        if command not in (
            dialect.MAV_CMD_SET_MESSAGE_INTERVAL,
            dialect.MAV_CMD_REQUEST_MESSAGE,
            dialect.MAV_CMD_GET_MESSAGE_INTERVAL,
        ):
            return None
        param1: float = msg.param1
        msg_id = int(param1) if math.isfinite(param1) and param1 == int(param1) else -1
        family = self._families.get(msg_id)
        if family is None:
            return None  # not one of ours: another component may own it
        if command == dialect.MAV_CMD_SET_MESSAGE_INTERVAL:
            rate_hz = self._rate_for_interval(family, msg.param2)
            if rate_hz is None:
                return int(dialect.MAV_RESULT_DENIED)
            with self._lock:
                self._rate_hz[family] = rate_hz
                self._rescheduled.add(family)
            log.info("%s rate set to %g Hz by %d/%d", family, rate_hz, *_sender(msg))
            self._wake.set()
            return int(dialect.MAV_RESULT_ACCEPTED)
        if command == dialect.MAV_CMD_REQUEST_MESSAGE:
            if not self._has_data(msg_id):
                return int(dialect.MAV_RESULT_DENIED)
            with self._lock:
                self._requested.append(msg_id)
            self._wake.set()
            return int(dialect.MAV_RESULT_ACCEPTED)
        rate_hz = self.rate_hz(family)
        interval_us = -1 if rate_hz <= 0 else min(_INT32_MAX, round(1e6 / rate_hz))
        self._link.send(self._link.mav.message_interval_encode(msg_id, interval_us))
        return int(dialect.MAV_RESULT_ACCEPTED)

    def _rate_for_interval(self, family: Family, interval_us: float) -> float | None:
        """SET_MESSAGE_INTERVAL's param2 as a rate (0 = off), or None: refused."""
        if interval_us == 0:
            return self._default_hz[family]
        if interval_us == -1:
            return 0.0
        if not math.isfinite(interval_us) or interval_us < MIN_INTERVAL_US:
            return None
        return 1e6 / interval_us

    def _has_data(self, msg_id: int) -> bool:
        """Whether some configured ESC falls into the message ``msg_id`` would carry."""
        n = len(self._table)
        batch_no = self._telemetry_batch.get(msg_id)
        if batch_no is None:
            return n > 0
        return batch_no * ESCS_PER_MESSAGE < min(n, ESC_TELEMETRY_MAX_ESCS)

    # -- the sender thread ------------------------------------------------------------------

    def _run(self) -> None:
        now = time.monotonic_ns()
        next_due: dict[Family, int] = dict.fromkeys(FAMILIES, now)
        while not self._stop.is_set():
            self._wake.clear()  # before reading the state, so no later change is missed
            with self._lock:
                rates = dict(self._rate_hz)
                requested, self._requested = self._requested, []
                rescheduled, self._rescheduled = self._rescheduled, set()
            now = time.monotonic_ns()
            for family in rescheduled:
                next_due[family] = now  # a new rate starts with a message now
            due = [f for f in FAMILIES if rates[f] > 0 and now >= next_due[f]]
            if due or requested:
                try:
                    self._send_round(due, requested, now)
                # A bug in an encoder must not end telemetry for the rest of the flight.
                except Exception:
                    self.stats.errors += 1
                    if self.stats.errors & (self.stats.errors - 1) == 0:
                        log.exception("ESC telemetry round failed (%d so far)", self.stats.errors)
            for family in due:
                period_ns = round(1e9 / rates[family])
                next_due[family] += period_ns
                if next_due[family] <= now:  # fell behind (a stall): skip, do not burst
                    next_due[family] = now + period_ns
            enabled = [next_due[f] for f in FAMILIES if rates[f] > 0]
            wait_ns = min(enabled) - time.monotonic_ns() if enabled else _IDLE_WAIT_S * 1e9
            self._wake.wait(max(0.0, min(wait_ns / 1e9, _IDLE_WAIT_S)))

    def _send_round(self, due: list[Family], requested: list[int], now_ns: int) -> None:
        """Send the due families and the requested messages from one snapshot."""
        snapshots = self._table.snapshot(now_ns)
        time_usec = time.time_ns() // 1000
        for family in due:
            self._send(self._encode(family, snapshots, time_usec), family)
        for msg_id in dict.fromkeys(requested):  # the same request twice: once
            family = self._families[msg_id]
            messages = self._encode(family, snapshots, time_usec)
            if family == "esc_telemetry":
                messages = [m for m in messages if m.get_msgId() == msg_id]
            self._send(messages, family)

    def _encode(
        self, family: Family, snapshots: Sequence[EscSnapshot], time_usec: int
    ) -> list[Any]:
        mav = self._link.mav
        if family == "esc_status":
            return esc_status_messages(mav, snapshots, time_usec)
        if family == "esc_info":
            self._info_rounds += 1
            return esc_info_messages(mav, snapshots, time_usec, self._info_rounds)
        return esc_telemetry_messages(mav, snapshots)

    def _send(self, messages: list[Any], family: Family) -> None:
        for message in messages:
            self._link.send(message)
        setattr(self.stats, family, getattr(self.stats, family) + len(messages))


def _sender(msg: Any) -> tuple[int, int]:
    return msg.get_srcSystem(), msg.get_srcComponent()
