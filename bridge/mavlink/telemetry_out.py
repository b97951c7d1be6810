"""ESC telemetry over MAVLink: ESC_STATUS, ESC_INFO and ArduPilot's ESC_TELEMETRY_x_TO_y.

Pure encoders first: ESC snapshots in, pymavlink message objects out (no clock, socket or
lock), every value clamped to its field's range and NaN/None turned into the field's "unknown".
Then :class:`MavlinkTelemetry`, a named daemon thread that sends each of the three message
families at its own rate on each connection of the :class:`MavlinkLink` (``MavlinkLink.send``
with ``to``) and lets a ground station change a rate on the connection it speaks on
(MAV_CMD_SET_MESSAGE_INTERVAL), ask for one message now (MAV_CMD_REQUEST_MESSAGE) or read a rate
(MAV_CMD_GET_MESSAGE_INTERVAL). It reads only :class:`EscTable` snapshots and touches nothing of
the output loop, so it can never slow a motor command down.

Which messages go where: the autopilot's connection carries only what its flight stack forwards
to its ground stations, slowly (:data:`AUTOPILOT_SETS`, chosen from the ``autopilot`` field of
its HEARTBEAT: ArduPilot drops ESC_INFO/ESC_STATUS, which its MAVLink lacks; PX4 forwards those
but not ESC_TELEMETRY_x_TO_y), unless ``[mavlink] autopilot_messages`` says otherwise; each
output (a ground station) gets all three at ``esc_*_hz``, or its ``output_messages`` entry.

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
  rate of all of them (one family). A rate is set on the connection the command came in on.
  MAV_CMD_REQUEST_MESSAGE for an ESC_TELEMETRY_x_TO_y sends only that batch, and is DENIED when
  no configured ESC falls into it.
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
from bridge.mavlink.link import COMMAND_ORIGIN, MavlinkLink
from bridge.telemetry.state import EscSnapshot, EscTable

__all__ = [
    "AUTOPILOT_SETS",
    "ESCS_PER_MESSAGE",
    "ESC_TELEMETRY_MAX_ESCS",
    "MAX_ESCS",
    "MIN_INTERVAL_US",
    "OTHER_AUTOPILOT_SET",
    "Family",
    "MavlinkTelemetry",
    "TelemetryStats",
    "bytes_per_s",
    "describe_sets",
    "esc_info_messages",
    "esc_status_messages",
    "esc_telemetry_messages",
    "messages_per_round",
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

_IDLE_WAIT_S: Final = 0.25  # the sender re-checks this often (the autopilot's set may change)
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


@dataclass
class TelemetryStats:
    """Messages handed to the link, per family, and encoding faults; updated in place.

    A message sent to several connections at once counts once."""

    esc_status: int = 0
    esc_info: int = 0
    esc_telemetry: int = 0
    errors: int = 0
    """Rounds not sent because encoding or sending raised (a bug); logged."""


def _rates_text(rates: dict[Family, float]) -> str:
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
        return f"{_rates_text(rates)} ({load:.0f} B/s)" if load else _rates_text(rates)

    if config.autopilot_messages is not None:
        autopilot = text(_as_rates(config.autopilot_messages))
    else:
        autopilot = (
            f"by its HEARTBEAT: ArduPilot {text(AUTOPILOT_SETS[MAV_AUTOPILOT_ARDUPILOTMEGA])}; "
            f"PX4 {text(AUTOPILOT_SETS[MAV_AUTOPILOT_PX4])}; other {text(OTHER_AUTOPILOT_SET)}"
        )
    parts = [f"autopilot link {autopilot}"]
    for url in config.outputs:
        parts.append(f"{url} {text(_as_rates(config.output_rates(url)))}")
    return f"MAVLink ESC telemetry for {n_escs} ESCs: " + "; ".join(parts)


def _as_rates(table: Any) -> dict[Family, float]:
    """A configured message set (a family not listed is off) as a rate per family."""
    return {family: float(table.get(family, 0.0)) for family in FAMILIES}


class MavlinkTelemetry:
    """Sends ESC telemetry from an :class:`EscTable` over a :class:`MavlinkLink`.

    Each connection has its own message set and rates. The autopilot's connection
    (``[mavlink] url``) carries ``autopilot_messages``, or when that is unset the set for the
    autopilot's flight stack (:data:`AUTOPILOT_SETS`, from the ``autopilot`` field of its
    latest HEARTBEAT). Each output carries its ``output_messages`` entry, else
    ``esc_status_hz``, ``esc_info_hz`` and ``esc_telemetry_hz`` (0 = off). A ground station's
    MAV_CMD_SET_MESSAGE_INTERVAL sets the rate on the connection it came in on, until the next
    start. Use :meth:`start` once, then :meth:`close` (or a ``with`` block). The link need not
    be started yet: until it is, what is sent is dropped and counted by the link.
    """

    def __init__(self, config: MavlinkConfig, link: MavlinkLink, table: EscTable) -> None:
        self._link = link
        self._table = table
        dialect = link.dialect
        self._dialect = dialect
        self._autopilot_url = config.url
        self._autopilot_set = (
            None if config.autopilot_messages is None else _as_rates(config.autopilot_messages)
        )
        self._urls: tuple[str, ...] = (config.url, *config.outputs)
        self._output_sets: dict[str, dict[Family, float]] = {
            url: _as_rates(config.output_rates(url)) for url in config.outputs
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
        self._lock = threading.Lock()  # guards _set_hz and _requested
        # Rates a ground station set (SET_MESSAGE_INTERVAL), by (connection URL, family).
        self._set_hz: dict[tuple[str, Family], float] = {}
        self._requested: list[tuple[int, str]] = []  # (message ID, connection URL), send once
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        self._info_rounds = 0  # owned by the sender thread
        self._logged_autopilot_set: dict[Family, float] | None = None  # sender thread's

    def default_rates(self, url: str | None = None) -> dict[Family, float]:
        """The configured (or, for the autopilot, chosen) rates of the connection ``url``
        (None: the autopilot's), before any SET_MESSAGE_INTERVAL."""
        if url is None or url == self._autopilot_url:
            if self._autopilot_set is not None:
                return dict(self._autopilot_set)
            kind = self._link.autopilot_type
            return dict(AUTOPILOT_SETS.get(kind, OTHER_AUTOPILOT_SET))
        return dict(self._output_sets[url])

    def rate_hz(self, family: Family, url: str | None = None) -> float:
        """The family's current rate on the connection ``url`` (None: the autopilot's); 0 = off."""
        url = self._autopilot_url if url is None else url
        with self._lock:
            set_hz = self._set_hz.get((url, family))
        return self.default_rates(url)[family] if set_hz is None else set_hz

    def _rates(self) -> dict[tuple[str, Family], float]:
        """Every connection's current rate of every family."""
        with self._lock:
            set_hz = dict(self._set_hz)
        rates: dict[tuple[str, Family], float] = {}
        for url in self._urls:
            defaults = self.default_rates(url)
            for family in FAMILIES:
                rates[url, family] = set_hz.get((url, family), defaults[family])
        return rates

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
        if self._autopilot_set is not None:
            log.info("MAVLink ESC telemetry to the autopilot: %s", _rates_text(self._autopilot_set))
        else:
            log.info("MAVLink ESC telemetry to the autopilot: chosen from its HEARTBEAT")
        for url, rates in self._output_sets.items():
            log.info("MAVLink ESC telemetry to %s: %s", url, _rates_text(rates))

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
        about our messages, None for anything else (so it is not claimed). Each acts on the
        connection the command came in on."""
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
        url: str = getattr(msg, COMMAND_ORIGIN, self._autopilot_url)
        if url not in self._urls:
            url = self._autopilot_url
        if command == dialect.MAV_CMD_SET_MESSAGE_INTERVAL:
            interval_us: float = msg.param2
            if interval_us != 0 and self._rate_for_interval(interval_us) is None:
                return int(dialect.MAV_RESULT_DENIED)
            with self._lock:
                if interval_us == 0:  # back to the configured (or chosen) rate
                    self._set_hz.pop((url, family), None)
                else:
                    self._set_hz[url, family] = self._rate_for_interval(interval_us) or 0.0
            log.info(
                "%s rate on %s set to %g Hz by %d/%d",
                family,
                url,
                self.rate_hz(family, url),
                *_sender(msg),
            )
            self._wake.set()
            return int(dialect.MAV_RESULT_ACCEPTED)
        if command == dialect.MAV_CMD_REQUEST_MESSAGE:
            if not self._has_data(msg_id):
                return int(dialect.MAV_RESULT_DENIED)
            with self._lock:
                self._requested.append((msg_id, url))
            self._wake.set()
            return int(dialect.MAV_RESULT_ACCEPTED)
        rate_hz = self.rate_hz(family, url)
        interval_us_out = -1 if rate_hz <= 0 else min(_INT32_MAX, round(1e6 / rate_hz))
        self._link.send(self._link.mav.message_interval_encode(msg_id, interval_us_out), [url])
        return int(dialect.MAV_RESULT_ACCEPTED)

    @staticmethod
    def _rate_for_interval(interval_us: float) -> float | None:
        """SET_MESSAGE_INTERVAL's param2 (not 0) as a rate (0 = off), or None: refused."""
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
        next_due: dict[tuple[str, Family], int] = {}
        last_rates: dict[tuple[str, Family], float] = {}
        epoch = time.monotonic_ns()
        while not self._stop.is_set():
            self._wake.clear()  # before reading the state, so no later change is missed
            rates = self._rates()
            self._log_autopilot_set()
            with self._lock:
                requested, self._requested = self._requested, []
            now = time.monotonic_ns()
            for slot, rate in rates.items():
                if last_rates.get(slot) != rate:
                    next_due[slot] = now  # a new rate starts with a message now
            last_rates = rates
            due = [s for s, rate in rates.items() if rate > 0 and now >= next_due[s]]
            if due or requested:
                try:
                    self._send_round(due, requested, now)
                # A bug in an encoder must not end telemetry for the rest of the flight.
                except Exception:
                    self.stats.errors += 1
                    if self.stats.errors & (self.stats.errors - 1) == 0:
                        log.exception("ESC telemetry round failed (%d so far)", self.stats.errors)
            for slot in due:
                # The next tick of the slot's grid, counted from the sender's start: a family
                # at the same or a multiple rate on several connections is then due at the same
                # instants (one frame, one ESC_INFO round for all). A tick less than half a
                # period away (after a new rate's first message, or a stall) is skipped: no
                # burst.
                period_ns = round(1e9 / rates[slot])
                tick = epoch + ((now - epoch) // period_ns + 1) * period_ns
                next_due[slot] = tick if tick - now >= period_ns // 2 else tick + period_ns
            enabled = [next_due[s] for s, rate in rates.items() if rate > 0]
            wait_ns = min(enabled) - time.monotonic_ns() if enabled else _IDLE_WAIT_S * 1e9
            self._wake.wait(max(0.0, min(wait_ns / 1e9, _IDLE_WAIT_S)))

    def _log_autopilot_set(self) -> None:
        """Say once which set the autopilot's HEARTBEAT chose (and again if it changes)."""
        if self._autopilot_set is not None or self._link.autopilot_type is None:
            return
        chosen = self.default_rates()
        if chosen != self._logged_autopilot_set:
            self._logged_autopilot_set = chosen
            log.info(
                "MAVLink ESC telemetry to the autopilot (MAV_AUTOPILOT %d): %s",
                self._link.autopilot_type,
                _rates_text(chosen),
            )

    def _send_round(
        self, due: list[tuple[str, Family]], requested: list[tuple[int, str]], now_ns: int
    ) -> None:
        """Send the due families and the requested messages from one snapshot; a family due
        on several connections is encoded and packed once for all of them."""
        snapshots = self._table.snapshot(now_ns)
        time_usec = time.time_ns() // 1000
        for family in FAMILIES:
            urls = [url for url, f in due if f == family]
            if urls:
                self._send(self._encode(family, snapshots, time_usec), family, urls)
        for msg_id, url in dict.fromkeys(requested):  # the same request twice: once
            family = self._families[msg_id]
            messages = self._encode(family, snapshots, time_usec)
            if family == "esc_telemetry":
                messages = [m for m in messages if m.get_msgId() == msg_id]
            self._send(messages, family, [url])

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

    def _send(self, messages: list[Any], family: Family, urls: list[str]) -> None:
        for message in messages:
            self._link.send(message, urls)
        setattr(self.stats, family, getattr(self.stats, family) + len(messages))


def _sender(msg: Any) -> tuple[int, int]:
    return msg.get_srcSystem(), msg.get_srcComponent()
