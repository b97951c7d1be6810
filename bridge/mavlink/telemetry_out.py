"""ESC telemetry sent over MAVLink: ESC_STATUS, ESC_INFO and ArduPilot's ESC_TELEMETRY_x_TO_y.

:class:`MavlinkTelemetry`, a named daemon thread that sends each of the three message families
at its own rate on each connection of the link (``send`` with ``to``) and lets a ground station
change a rate on the connection it speaks on (MAV_CMD_SET_MESSAGE_INTERVAL), ask for one
message now (MAV_CMD_REQUEST_MESSAGE) or read a rate (MAV_CMD_GET_MESSAGE_INTERVAL). It reads
only :class:`EscTable` snapshots and touches nothing of the output loop, so it can never slow a
motor command down.

Which messages go where: the autopilot's connection carries only what its flight stack forwards
to its ground stations, slowly (:data:`AUTOPILOT_SETS`, chosen from the ``autopilot`` field of
its HEARTBEAT: ArduPilot drops ESC_INFO/ESC_STATUS, which its MAVLink lacks; PX4 forwards those
but not ESC_TELEMETRY_x_TO_y), unless ``[mavlink] autopilot_messages`` says otherwise; each
output (a ground station) gets all three at ``esc_*_hz``, or its ``output_messages`` entry.

The messages themselves, the default sets and their byte counts are in
:mod:`bridge.mavlink.esc_messages`. The sender needs only what :class:`TelemetryLink` names of the
link it sends on (a :class:`~bridge.mavlink.link.MavlinkLink` in the daemon), never the link
class itself.

Commands: intervals shorter than :data:`MIN_INTERVAL_US` (faster than 100 Hz) are refused with
MAV_RESULT_DENIED; an interval of 0 restores the configured rate, -1 turns the family off, any
other negative value is DENIED. Setting the interval of any ESC_TELEMETRY_x_TO_y sets the rate
of all of them (one family). A rate is set on the connection the command came in on.
MAV_CMD_REQUEST_MESSAGE for an ESC_TELEMETRY_x_TO_y sends only that batch, and is DENIED when
no configured ESC falls into it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from types import ModuleType, TracebackType
from typing import Any, Final, Protocol

from bridge.config import MavlinkConfig
from bridge.mavlink.commands import COMMAND_ORIGIN, CommandHandler
from bridge.mavlink.esc_messages import (
    AUTOPILOT_SETS,
    ESC_TELEMETRY_MAX_ESCS,
    ESCS_PER_MESSAGE,
    FAMILIES,
    OTHER_AUTOPILOT_SET,
    TELEMETRY_GROUPS,
    Family,
    as_rates,
    esc_info_messages,
    esc_status_messages,
    esc_telemetry_messages,
    rates_text,
)
from bridge.telemetry.state import EscSnapshot, EscTable

__all__ = [
    "MIN_INTERVAL_US",
    "MavlinkTelemetry",
    "TelemetryLink",
    "TelemetryStats",
]

log = logging.getLogger(__name__)

MIN_INTERVAL_US: Final = 10_000
"""The shortest interval a ground station may ask for: 100 Hz, the configuration's ceiling."""
_INT32_MAX: Final = 2**31 - 1  # MESSAGE_INTERVAL.interval_us is int32
_IDLE_WAIT_S: Final = 0.25  # the sender re-checks this often (the autopilot's set may change)
# A round this late says the sender did not run (its process starved of CPU or of the GIL): the
# messages it missed are skipped, not caught up, so the rates dip; said in the log and counted.
_HELD_UP_NS: Final = 500_000_000
_JOIN_TIMEOUT_S: Final = 2.0


class TelemetryLink(Protocol):
    """What the sender uses of the link it sends on (:class:`bridge.mavlink.link.MavlinkLink`)."""

    @property
    def mav(self) -> Any:
        """The pymavlink MAVLink object the messages are built with."""

    @property
    def dialect(self) -> ModuleType:
        """The dialect module: message IDs, MAV_CMD_* and MAV_RESULT_* constants."""

    @property
    def autopilot_type(self) -> int | None:
        """MAV_AUTOPILOT from the autopilot's latest HEARTBEAT; None before the first."""

    def autopilot_boot_usec(self, now_ns: int) -> int | None:
        """The autopilot's µs since boot at the local monotonic ``now_ns``; None while unknown."""

    def send(self, msg: Any, to: Collection[str] | None = None) -> None:
        """Send ``msg`` to every connection, or only to those whose URL ``to`` holds."""

    def add_command_handler(self, handler: CommandHandler) -> None:
        """Pass COMMAND_LONGs addressed to the bridge to ``handler`` too."""

    def remove_command_handler(self, handler: CommandHandler) -> None:
        """Stop passing commands to ``handler``."""


@dataclass
class TelemetryStats:
    """Messages handed to the link, per family, and encoding faults; updated in place.

    A message sent to several connections at once counts once."""

    esc_status: int = 0
    esc_info: int = 0
    esc_telemetry: int = 0
    errors: int = 0
    """Rounds not sent because encoding or sending raised (a bug); logged."""
    held_up: int = 0
    """Rounds sent over half a second late (the sender did not run meanwhile); logged."""
    longest_hold_s: float = 0.0
    """The greatest lateness among them, in seconds."""


class MavlinkTelemetry:
    """Sends ESC telemetry from an :class:`EscTable` over a :class:`TelemetryLink`.

    Each connection has its own message set and rates. The autopilot's connection
    (``[mavlink] url``) carries ``autopilot_messages``, or when that is unset the set for the
    autopilot's flight stack (:data:`AUTOPILOT_SETS`, from the ``autopilot`` field of its
    latest HEARTBEAT). Each output carries its ``output_messages`` entry, else
    ``esc_status_hz``, ``esc_info_hz`` and ``esc_telemetry_hz`` (0 = off). A ground station's
    MAV_CMD_SET_MESSAGE_INTERVAL sets the rate on the connection it came in on, until the next
    start. Use :meth:`start` once, then :meth:`close` (or a ``with`` block). The link need not
    be started yet: until it is, what is sent is dropped and counted by the link.
    """

    def __init__(self, config: MavlinkConfig, link: TelemetryLink, table: EscTable) -> None:
        self._link = link
        self._table = table
        dialect = link.dialect
        self._dialect = dialect
        self._autopilot_url = config.url
        self._autopilot_set = (
            None if config.autopilot_messages is None else as_rates(config.autopilot_messages)
        )
        self._urls: tuple[str, ...] = (config.url, *config.outputs)
        self._output_sets: dict[str, dict[Family, float]] = {
            url: as_rates(config.output_rates(url)) for url in config.outputs
        }
        self._families: dict[int, Family] = {
            dialect.MAVLINK_MSG_ID_ESC_STATUS: "esc_status",
            dialect.MAVLINK_MSG_ID_ESC_INFO: "esc_info",
        }
        self._telemetry_batch: dict[int, int] = {}  # ESC_TELEMETRY_x_TO_y id -> batch number
        for batch_no, (first, last) in enumerate(TELEMETRY_GROUPS):
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
            log.info("MAVLink ESC telemetry to the autopilot: %s", rates_text(self._autopilot_set))
        else:
            log.info("MAVLink ESC telemetry to the autopilot: chosen from its HEARTBEAT")
        for url, rates in self._output_sets.items():
            log.info("MAVLink ESC telemetry to %s: %s", url, rates_text(rates))

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
            if due:
                self._note_lateness(now - min(next_due[s] for s in due))
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

    def _note_lateness(self, late_ns: int) -> None:
        if late_ns <= _HELD_UP_NS:
            return
        stats = self.stats
        stats.held_up += 1
        stats.longest_hold_s = max(stats.longest_hold_s, late_ns / 1e9)
        if stats.held_up & (stats.held_up - 1) == 0:  # the 1st, 2nd, 4th, ...
            log.warning(
                "ESC telemetry went out %.2f s late: this process did not run (%d times so "
                "far, the longest %.2f s); what was due meanwhile is skipped, not caught up",
                late_ns / 1e9,
                stats.held_up,
                stats.longest_hold_s,
            )

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
                rates_text(chosen),
            )

    def _send_round(
        self, due: list[tuple[str, Family]], requested: list[tuple[int, str]], now_ns: int
    ) -> None:
        """Send the due families and the requested messages from one snapshot; a family due
        on several connections is encoded and packed once for all of them."""
        snapshots = self._table.snapshot(now_ns)
        time_usec = self._time_usec(now_ns)
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

    def _time_usec(self, now_ns: int) -> int:
        """The stamp of what is sent at ``now_ns``: the autopilot's boot clock when known (as
        PX4 stamps ESC_STATUS/ESC_INFO and mavros reads them), else µs since the Unix epoch."""
        boot_usec = self._link.autopilot_boot_usec(now_ns)
        return time.time_ns() // 1000 if boot_usec is None else boot_usec

    def _encode(
        self, family: Family, snapshots: Sequence[EscSnapshot], time_usec: int
    ) -> list[Any]:
        mav = self._link.mav
        if family == "esc_status":
            return esc_status_messages(mav, snapshots, time_usec)
        if family == "esc_info":
            return esc_info_messages(mav, snapshots, time_usec)
        return esc_telemetry_messages(mav, snapshots)

    def _send(self, messages: list[Any], family: Family, urls: list[str]) -> None:
        for message in messages:
            self._link.send(message, urls)
        setattr(self.stats, family, getattr(self.stats, family) + len(messages))


def _sender(msg: Any) -> tuple[int, int]:
    return msg.get_srcSystem(), msg.get_srcComponent()
