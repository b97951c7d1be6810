"""Warnings that name what is missing: the autopilot's HEARTBEAT, and the ESCs' telemetry.

A bridge that starts with nothing on the other side used to say only "waiting for motor
outputs". :class:`AbsenceWatch` looks, from the supervisor (never the output loop), at what the
main process already counts: the autopilot link's last HEARTBEAT and the ESC state. After
:data:`GRACE_S` from the start it warns once about each missing piece, naming where the bridge
listens and what to check, and again every :data:`REPEAT_S` while it lasts; when the piece
turns up after a warning it says so once. docs/troubleshooting.md explains each message.

A stream slower than ``input_timeout_ms`` needs is reported where the rate is measured
(:mod:`bridge.mavlink.heartbeat`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final

from bridge.bitrate import bitrate_text
from bridge.config import BridgeConfig
from bridge.escs import registry
from bridge.mavlink.stats import LinkStats
from bridge.telemetry.state import EscSnapshot

__all__ = ["GRACE_S", "HEARD_S", "REPEAT_S", "AbsenceWatch", "EscsHeard"]

GRACE_S: Final = 5.0
"""Seconds after the start before a missing HEARTBEAT or silent ESC is warned about: an
autopilot sends a HEARTBEAT a second, ESCs their telemetry many times a second."""
REPEAT_S: Final = 30.0
"""While a piece stays missing, the warning is repeated this often."""
HEARD_S: Final = 3.0
"""The autopilot is there while its last HEARTBEAT is at most this old (three missed)."""

_NS: Final = 1_000_000_000

Report = Callable[[int, str], None]
"""Where the watch's messages go: (logging level, text)."""


@dataclass(frozen=True)
class EscsHeard:
    """What the CAN reader heard, as of one moment."""

    escs: Sequence[EscSnapshot]
    """The ESC state, in motor order."""
    frames: int
    """Every frame read from the bus (our own commands too, where the bus echoes them)."""
    foreign: int
    """Telemetry frames from IDs that are none of our ESCs'."""


def _list(values: Sequence[int]) -> str:
    return ", ".join(str(v) for v in values)


class AbsenceWatch:
    """Warns about a missing autopilot HEARTBEAT and silent ESCs; :meth:`check` is called a few
    times a second with the monotonic time and what the link and the ESC state hold."""

    def __init__(self, config: BridgeConfig, started_ns: int, report: Report) -> None:
        self._config = config
        self._report = report
        self._started_ns = started_ns
        self._next_check_ns = started_ns + round(GRACE_S * _NS)
        self._heartbeat_warned_ns: int | None = None
        self._silent_warned: tuple[int, ...] = ()
        self._silent_warned_ns: int | None = None

    def check(
        self,
        now_ns: int,
        link: LinkStats,
        escs: Callable[[], EscsHeard] | None,
    ) -> None:
        """Report what is missing as of ``now_ns`` (looked at once a second from
        :data:`GRACE_S` after the start): ``link`` is the autopilot link's counters, ``escs``
        gives what the CAN reader heard (None: no reader runs)."""
        if now_ns < self._next_check_ns:
            return
        self._next_check_ns = now_ns + _NS
        self._check_heartbeat(now_ns, link)
        if escs is not None:
            self._check_escs(now_ns, escs())

    def _due(self, warned_ns: int | None, now_ns: int) -> bool:
        return warned_ns is None or now_ns - warned_ns >= REPEAT_S * _NS

    def _check_heartbeat(self, now_ns: int, link: LinkStats) -> None:
        mavlink = self._config.mavlink
        who = f"{mavlink.autopilot_system_id}/{mavlink.autopilot_component_id}"
        last = link.last_heartbeat_ns
        if last and now_ns - last <= HEARD_S * _NS:
            if self._heartbeat_warned_ns is not None:
                self._report(logging.INFO, f"HEARTBEAT from the autopilot {who} on {mavlink.url}")
                self._heartbeat_warned_ns = None
            return
        if not self._due(self._heartbeat_warned_ns, now_ns):
            return
        self._heartbeat_warned_ns = now_ns
        if last:
            since = f"for {(now_ns - last) / _NS:.0f} s"
        else:
            since = f"{(now_ns - self._started_ns) / _NS:.0f} s after start"
        if link.messages:
            heard = (
                f"; {link.messages} MAVLink messages arrived, none a HEARTBEAT from system "
                f"{who}: are [mavlink] autopilot_system_id and autopilot_component_id right?"
            )
        elif mavlink.url.startswith("serial:"):
            heard = (
                "; nothing arrived: is the flight controller's telemetry port wired to it (TX to "
                "RX, RX to TX, GND), at the URL's baud rate, with MAVLink 2 on that port "
                "(ArduPilot SERIALn_PROTOCOL 2, PX4 MAV_n_CONFIG)?"
            )
        else:
            heard = "; nothing arrived: is the autopilot (or SITL) sending to this address?"
        self._report(
            logging.WARNING,
            f"no HEARTBEAT from the autopilot {who} on {mavlink.url} {since}{heard} "
            "(docs/troubleshooting.md)",
        )

    def _check_escs(self, now_ns: int, heard: EscsHeard) -> None:
        escs = heard.escs
        silent = tuple(esc.node_id for esc in escs if not esc.online)
        if not silent:
            if self._silent_warned:
                self._report(logging.INFO, f"ESC telemetry: all {len(escs)} ESCs online")
                self._silent_warned, self._silent_warned_ns = (), None
            return
        if silent == self._silent_warned and not self._due(self._silent_warned_ns, now_ns):
            return
        self._silent_warned, self._silent_warned_ns = silent, now_ns
        config = self._config
        family = registry.family(config.output.protocol)
        motors = [esc.motor for esc in escs if not esc.online]
        never = [esc.node_id for esc in escs if not esc.online and esc.frames == 0]
        rate = config.bitrate
        bus = f"{config.can.interface} {config.can.channel} at {rate} bit/s ({bitrate_text(rate)})"
        if heard.foreign:
            hint = (
                f"{heard.foreign} telemetry frames came from IDs not in [escs] ids: are those "
                "the ESCs' IDs? (`esc-bridge run --record` then `esc-bridge decode` shows who "
                "sends)"
            )
        elif len(never) == len(escs):
            hint = (
                f"no ESC telemetry on the bus at all ({heard.frames} frames read): are the ESCs "
                "powered, the bus wired (CAN H to H, L to L, 120 ohm at both ends), the ESCs at "
                "that bit rate and their reports on?"
            )
        elif never:
            hint = (
                f"{_list(never)} never heard: is each such ESC powered and wired, its ID the "
                "one in [escs] ids, its reports on?"
            )
        else:
            hint = "heard before, silent now: power, wiring, or an ESC that reset"
        self._report(
            logging.WARNING,
            f"no telemetry from {family.title} ESC ID{'s' if len(silent) > 1 else ''} "
            f"{_list(silent)} (motor{'s' if len(motors) > 1 else ''} {_list(motors)}) of "
            f"{len(escs)} on {bus}: {hint} (docs/troubleshooting.md)",
        )
