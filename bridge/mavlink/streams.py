"""Asking the autopilot for a message stream, and making sure the ask worked.

An autopilot streams SERVO_OUTPUT_RAW (or ACTUATOR_OUTPUT_STATUS, ...) and HEARTBEAT at rates
of its own choosing until someone asks otherwise with MAV_CMD_SET_MESSAGE_INTERVAL, and each
asker learns only from the COMMAND_ACK and from what then arrives whether it worked. Seen on
the real autopilots (docs/simulation.md, "Against the real autopilots, measured"):

* ArduCopter DENIES a rate faster than its main loop allows (400 Hz on a 400 Hz loop) and
  says why in a STATUSTEXT; it accepts 200 Hz.
* PX4 keeps its default (SERVO_OUTPUT_RAW at 10 Hz on the onboard link) until a request is
  ACCEPTED, and a request sent on a ``udpin`` link before the autopilot's first packet goes
  nowhere: nobody answers.
* PX4 ACCEPTS 200 Hz and delivers what its loop allows (~124 Hz for the SIH quad).

So a :class:`StreamRequest` asks again every check (a second) until the stream arrives at the
rate asked, or the autopilot ACCEPTED that rate and sends what it can. It steps down to the
next lower rate (:data:`FALLBACK_RATES_HZ`) on a refusal, or when the autopilot is there but
no stream comes of three requests; refused at the lowest, it stops asking until the stream
stops and starts again (a restarted autopilot). It says each of these once, at a level that
matches: never waiting silently. It does no I/O: the link sends the request it
returns and feeds it the ACKs and the arriving rate.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

log = logging.getLogger(__name__)

# MAV_RESULT values (common.xml).
MAV_RESULT_ACCEPTED: Final = 0
MAV_RESULT_TEMPORARILY_REJECTED: Final = 1
MAV_RESULT_DENIED: Final = 2
MAV_RESULT_UNSUPPORTED: Final = 3
MAV_RESULT_FAILED: Final = 4
MAV_RESULT_IN_PROGRESS: Final = 5
_RESULT_NAMES: Final = {
    MAV_RESULT_ACCEPTED: "ACCEPTED",
    MAV_RESULT_TEMPORARILY_REJECTED: "TEMPORARILY_REJECTED",
    MAV_RESULT_DENIED: "DENIED",
    MAV_RESULT_UNSUPPORTED: "UNSUPPORTED",
    MAV_RESULT_FAILED: "FAILED",
    MAV_RESULT_IN_PROGRESS: "IN_PROGRESS",
}
# Refusals that asking again at the same rate will not change.
_REFUSALS: Final = frozenset({MAV_RESULT_DENIED, MAV_RESULT_UNSUPPORTED, MAV_RESULT_FAILED})

FALLBACK_RATES_HZ: Final = (200.0, 100.0, 50.0, 25.0, 10.0)
"""The lower rates asked for, in turn, below the configured one, when a rate is refused."""
NEAR: Final = 0.8
"""A stream arriving at this fraction of the asked rate or more is what was asked for."""
FORGOTTEN: Final = 0.4
"""A stream that met the rate it was ACCEPTED at and now arrives under this fraction of it was
forgotten (an autopilot that restarted), not limited: it is asked again. Well under NEAR, so
that a rate measured a little low over one second on a busy machine asks nothing."""
UNANSWERED_BEFORE_STEP: Final = 3
"""Requests the autopilot (heard, so present) neither answered nor followed before the next
lower rate is tried."""


def result_name(result: int) -> str:
    """``MAV_RESULT_DENIED`` for 2, ... (the number for a value the definitions lack)."""
    return f"MAV_RESULT_{_RESULT_NAMES.get(result, str(result))}"


def rate_ladder(wanted_hz: float) -> tuple[float, ...]:
    """The rates to ask for, best first: ``wanted_hz``, then each fallback below it."""
    return (wanted_hz, *(rate for rate in FALLBACK_RATES_HZ if rate < wanted_hz))


@dataclass
class StreamRequest:
    """The negotiation of one message's rate with one autopilot.

    Call :meth:`observe` every check period (a second) and :meth:`due` when it is this
    request's turn, each with the rate arriving now; send the request :meth:`due` returns (a
    rate in Hz), if any, and pass the autopilot's COMMAND_ACK for it to :meth:`on_ack`.
    """

    name: str
    """The message's name, for the log (``SERVO_OUTPUT_RAW``)."""
    source: str
    """Who is asked, for the log (``autopilot 1/1``)."""
    wanted_hz: float
    """The configured rate; 0 = ask for nothing."""
    gave_up_level: int = logging.ERROR
    """How loudly to say that every rate was refused (the motor outputs: an error)."""

    def __post_init__(self) -> None:
        self._ladder: Sequence[float] = rate_ladder(self.wanted_hz) if self.wanted_hz > 0 else ()
        self._was_arriving = False
        self._asked_again = False  # asked again once after a rate far under the ACCEPTED one
        self._reset()

    def _reset(self) -> None:
        self._rung = 0
        self._accepted = False
        self._gave_up = False  # refused down to the lowest rate: asking no more
        self._unanswered = 0  # requests sent while the autopilot was there, not answered
        self._limit_logged = False
        self._silence_logged = False
        self._was_near = False  # arrived at the asked rate since the last reset

    @property
    def asked_hz(self) -> float:
        """The rate asked for now (0: none)."""
        return self._ladder[self._rung] if self._ladder else 0.0

    @property
    def accepted(self) -> bool:
        """The autopilot ACCEPTED :attr:`asked_hz` (and the stream has not stopped since)."""
        return self._accepted

    def observe(self, arriving_hz: float) -> None:
        """The rate arriving now, every check: also in checks where another request took the
        turn (one request a check) and :meth:`due` was not called, so that a stream that met
        the asked rate is known to have done so."""
        if self._ladder and arriving_hz >= NEAR * self.asked_hz:
            self._was_near = True

    def due(self, arriving_hz: float, autopilot_heard: bool) -> float | None:
        """The rate to ask for now, or None when nothing needs asking. ``arriving_hz``: the
        message's arriving rate over about the last second (0: none); ``autopilot_heard``:
        the autopilot's HEARTBEAT is current (it is there to answer)."""
        if not self._ladder:
            return None
        if arriving_hz <= 0:
            if self._was_arriving:
                # The stream stopped: an autopilot that restarted forgot every interval set.
                self._was_arriving = False
                self._reset()
            if autopilot_heard and self._unanswered >= UNANSWERED_BEFORE_STEP:
                self._step_down(f"did not come of {self._unanswered} unanswered requests")
            if self._gave_up:
                return None
        else:
            self._was_arriving = True
            if arriving_hz >= NEAR * self.asked_hz:
                self._was_near = True
                self._asked_again = False
                return None
            if self._accepted and self._was_near and arriving_hz >= FORGOTTEN * self.asked_hz:
                # It came at the rate it ACCEPTED, so that rate is not beyond it: a second a
                # little under it is the measurement's (a busy machine).
                return None
            # Far under what it ACCEPTED (under FORGOTTEN of a rate it met, a tenth of one it
            # never met): an autopilot that restarted forgot the interval, and one that
            # restarts within a check (ArduCopter SITL, ~1 s) never stops the stream for a
            # whole one. Ask once more, still taking the old ACCEPTED as the answer should this
            # one go unanswered (before: HEARTBEAT stayed at 2 Hz of 20, a motor test 0.4 s late).
            forgotten = FORGOTTEN if self._was_near else FORGOTTEN / 4
            if self._accepted and arriving_hz < forgotten * self.asked_hz and not self._asked_again:
                log.info(
                    "%s sends %s at %.0f Hz, far below the %.0f Hz it ACCEPTED: asking again",
                    self.source,
                    self.name,
                    arriving_hz,
                    self.asked_hz,
                )
                self._asked_again = True
                return self.asked_hz
            if self._accepted:
                if not self._limit_logged:
                    self._limit_logged = True
                    log.warning(
                        "%s ACCEPTED %s at %.0f Hz but sends %.0f Hz: taking that as its limit",
                        self.source,
                        self.name,
                        self.asked_hz,
                        arriving_hz,
                    )
                return None
            if self._gave_up:
                return None
            if self._unanswered >= UNANSWERED_BEFORE_STEP and not self._silence_logged:
                self._silence_logged = True
                log.warning(
                    "%s does not answer MAV_CMD_SET_MESSAGE_INTERVAL for %s at %.0f Hz; it "
                    "arrives at %.0f Hz; asking on",
                    self.source,
                    self.name,
                    self.asked_hz,
                    arriving_hz,
                )
        if autopilot_heard:
            self._unanswered += 1
        return self.asked_hz

    def on_ack(self, result: int) -> None:
        """The autopilot's COMMAND_ACK to the newest request."""
        self._unanswered = 0
        asked = self.asked_hz
        if result == MAV_RESULT_ACCEPTED:
            if not self._accepted:
                log.info("%s ACCEPTED %s at %.0f Hz", self.source, self.name, asked)
            self._accepted = True
            return
        self._accepted = False
        if result in _REFUSALS:
            self._step_down(f"at {asked:.0f} Hz: {result_name(result)}")
            return
        log.info(
            "%s answered %s for %s at %.0f Hz", self.source, result_name(result), self.name, asked
        )

    def _step_down(self, why: str) -> None:
        self._unanswered = 0
        if self._rung + 1 < len(self._ladder):
            self._rung += 1
            log.warning(
                "%s: %s %s; asking for %.0f Hz instead",
                self.source,
                self.name,
                why,
                self.asked_hz,
            )
        elif not self._gave_up:
            self._gave_up = True
            log.log(
                self.gave_up_level,
                "%s: %s %s, the lowest rate tried; asking no more and taking what it sends",
                self.source,
                self.name,
                why,
            )
