"""``esc-bridge esc spin``: one motor spun from this process, the bridge not running.

:func:`plan_spin` checks the request against the configuration (interface, mixer, ESC lists,
bus load, motor number); :func:`spin` opens the bus itself, ramps the motor up to the asked
throttle, holds it, ramps it down, and sends safe values to every ESC afterwards, whatever ends
the spin (the time limit, Ctrl-C, SIGTERM, an exception). Each tick's frames are the output
loop's for a motor test (:func:`bridge.output.motor_test.test_frames`), through the same
drivers and limits. Nothing here prints; the CLI does (``bridge/cli/spin.py``).

Sending proves nothing on CAN: a frame no ESC acknowledges just stays in the controller's
queue, and on a virtual bus nothing acknowledges at all. Every ESC family here reports
telemetry many times a second, so the spin reads the bus with the daemon's reader meanwhile,
and the result says how many telemetry frames the spun ESC sent: none means nothing answered.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Final, Literal

import can

from bridge.can_io import check_interface, is_transient, open_bus
from bridge.config import BridgeConfig, with_mixer_esc_count
from bridge.errors import ConfigError, LinkError
from bridge.escs.drivers import flush_safe_values
from bridge.mixing.definition import MixerDefinition
from bridge.mixing.loader import load_mixer
from bridge.output.busload import check_bus_load
from bridge.output.motor_test import SPIN_RAMP_S, SpinRequest, ramp_fraction, test_frames
from bridge.telemetry.for_config import esc_table
from bridge.telemetry.reader import CanReader

__all__ = [
    "SpinPlan",
    "SpinProgress",
    "SpinResult",
    "plan_spin",
    "spin",
]

SPIN_PROGRESS_S: Final = 0.5
"""A spin reports its progress this often, and at each change of phase."""
SPIN_MIN_FLUSH_MS: Final = 50
"""Safe values are sent at least this long after a spin, even with shutdown_flush_ms 0."""


@dataclass(frozen=True)
class SpinPlan:
    """A checked spin: nothing has been opened or sent yet."""

    config: BridgeConfig
    """With the ESC lists filled in."""
    mixer: MixerDefinition
    request: SpinRequest
    fraction: float
    """The held throttle, 0..1 of the full range (the request, capped at the output's max)."""
    ramp_s: float

    @property
    def index(self) -> int:
        """The motor's 0-based output index."""
        return self.request.motor - 1

    @property
    def esc_id(self) -> int:
        """The ID on the bus of the motor's ESC."""
        return self.config.escs.ids[self.index]

    @property
    def rate_hz(self) -> float:
        """Frames per second put on the bus: the daemon's command rate."""
        return float(
            self.config.rate_hz * self.config.family.driver(self.config.esc_setup).ticks_per_cycle
        )


def plan_spin(config: BridgeConfig, request: SpinRequest) -> SpinPlan:
    """Check ``request`` against ``config``: interface, mixer, ESC lists, bus load, motor number.

    Raises:
        ConfigError: the configuration is invalid, or the motor is not one of the mixer's.
    """
    check_interface(config.can, config.source)
    mixer = load_mixer(config.mixer.name)
    n_motors = len(mixer.outputs)
    if request.motor > n_motors:
        raise ConfigError(
            f"--motor {request.motor}: mixer {mixer.name!r} has motors 1..{n_motors}; "
            "expected one of those"
        )
    config = with_mixer_esc_count(config, mixer)
    check_bus_load(config)
    output = mixer.outputs[request.motor - 1]
    fraction = min(request.throttle_pct / 100.0, output.maximum)
    return SpinPlan(config, mixer, request, fraction, min(SPIN_RAMP_S, request.seconds / 4))


Phase = Literal["ramp up", "hold", "ramp down"]


@dataclass(frozen=True)
class SpinProgress:
    """Where a running spin is, for the caller's progress lines."""

    phase: Phase
    elapsed_s: float
    fraction: float
    """The throttle sent on this tick, 0..1 of the full range."""


@dataclass(frozen=True)
class SpinResult:
    """How a spin went. ``ended``: ``done`` (the time limit), ``interrupted`` (a signal or the
    stop event), ``bus error`` (the bus went away)."""

    ended: Literal["done", "interrupted", "bus error"]
    elapsed_s: float
    frames_sent: int
    """Frames sent while the motor was commanded (ramps and hold)."""
    safe_frames_sent: int
    """Safe-value frames sent afterwards."""
    send_errors: int
    peak_fraction: float
    telemetry_frames: int = 0
    """Telemetry frames the spun motor's ESC sent during the spin and the safe values after:
    0 means nothing answered (no such ESC on the bus, or not at this bit rate)."""
    rpm: int | None = None
    """The rpm that ESC last reported (None: it reported none)."""


def spin(
    plan: SpinPlan,
    *,
    stop: threading.Event | None = None,
    progress: Callable[[SpinProgress], None] | None = None,
    handle_signals: bool = True,
) -> SpinResult:
    """Spin ``plan``'s motor, then send safe values to every ESC, whatever happens.

    Frames go out at the daemon's rate on absolute deadlines of the monotonic clock. The spin
    ends at ``plan.request.seconds`` after the first frame (the hard limit), or at once when
    ``stop`` is set. With ``handle_signals`` (and on the main thread) SIGINT and SIGTERM end the
    spin the same way for the duration, so Ctrl-C ends the spin without interrupting the safe
    values.
    Afterwards safe values go to every ESC for ``shutdown_flush_ms`` (at least
    :data:`SPIN_MIN_FLUSH_MS` and one whole cycle, so every ESC gets one), also when an
    exception (from ``progress``, say) ends the spin; the exception then propagates.

    Raises:
        LinkError: the bus could not be opened (nothing was sent).
        ConfigError: the interface is not one python-can has.
    """
    stop = stop or threading.Event()
    config = plan.config
    driver = config.family.driver(config.esc_setup)
    period_ns = round(1e9 / (config.rate_hz * driver.ticks_per_cycle))
    bus = open_bus(config.can, config.bitrate)
    table = esc_table(config)
    reader = CanReader(bus, table, config.family)
    reader.start()
    sender = _Sender(bus)
    fractions = [0.0] * len(config.escs.ids)
    index, target, ramp_s = plan.index, plan.fraction, plan.ramp_s
    seconds = plan.request.seconds
    ended: Literal["done", "interrupted", "bus error"] = "interrupted"
    peak = 0.0
    tick = 0
    start_ns = time.monotonic_ns()
    elapsed_s = 0.0
    # One set of handlers from the first frame to the last safe value: between two, a signal
    # would get its default action (KeyboardInterrupt) in the middle of the stop.
    with _signals_noted(handle_signals) as signalled:
        try:
            end_ns = start_ns + round(seconds * 1e9)
            next_ns = start_ns
            next_report_s = 0.0
            last_phase: Phase | None = None
            while True:
                now = time.monotonic_ns()
                elapsed_s = (now - start_ns) / 1e9
                if now >= end_ns:
                    ended = "done"
                    break
                if stop.is_set() or signalled:
                    break
                fraction = ramp_fraction(elapsed_s, seconds, ramp_s, target)
                fractions[index] = fraction
                peak = max(peak, fraction)
                if not sender.send(test_frames(driver, tick, fractions, index)):
                    ended = "bus error"
                    break
                tick += 1
                phase: Phase = (
                    "ramp up"
                    if elapsed_s < ramp_s
                    else "ramp down"
                    if elapsed_s >= seconds - ramp_s
                    else "hold"
                )
                if progress is not None and (phase != last_phase or elapsed_s >= next_report_s):
                    progress(SpinProgress(phase, elapsed_s, fraction))
                    next_report_s = elapsed_s + SPIN_PROGRESS_S
                    last_phase = phase
                next_ns += period_ns
                if now - next_ns >= period_ns:  # woke a period late or more: skip, no burst
                    next_ns += (now - next_ns) // period_ns * period_ns
                # Never sleep past the limit: the last tick may be shorter than a period.
                delay_ns = min(next_ns, end_ns) - time.monotonic_ns()
                if delay_ns > 0:
                    stop.wait(delay_ns / 1e9)
        finally:
            frames_sent = sender.sent
            sender.sent = 0
            try:
                if sender.gone:  # one more try on a fresh handle: the safe values matter most
                    reader.close()
                    bus.shutdown()
                    with contextlib.suppress(LinkError):
                        bus = sender.reopen(open_bus(config.can, config.bitrate))
                flush_ms = max(config.output.shutdown_flush_ms, SPIN_MIN_FLUSH_MS)
                flush_safe_values(sender.send, driver, period_ns, flush_ms, tick)
            finally:
                reader.close()
                bus.shutdown()
    heard = table.snapshot(time.monotonic_ns())[index]
    return SpinResult(
        ended,
        elapsed_s,
        frames_sent,
        sender.sent,
        sender.errors,
        peak,
        heard.frames,
        heard.rpm,
    )


class _Sender:
    """Sends without blocking and counts; False once the bus is gone (not a passing error)."""

    def __init__(self, bus: can.BusABC) -> None:
        self._bus = bus
        self.sent = 0
        self.errors = 0
        self.gone = False

    def reopen(self, bus: can.BusABC) -> can.BusABC:
        """Send on ``bus`` from now on (the old handle is the caller's to shut down)."""
        self._bus = bus
        self.gone = False
        return bus

    def send(self, frames: list[can.Message]) -> bool:
        if self.gone:
            return False
        for frame in frames:
            try:
                self._bus.send(frame, timeout=0)
            except (can.CanError, OSError) as exc:
                self.errors += 1
                self.gone = not is_transient(exc)
                return not self.gone
            self.sent += 1
        return True


@contextlib.contextmanager
def _signals_noted(enabled: bool) -> Iterator[list[int]]:
    """While inside: SIGINT and SIGTERM are noted in the list given (the spin looks at it every
    tick) instead of raising or ending the process (main thread only; elsewhere signals are
    not ours to take). The handler only appends: a handler runs between two bytecodes of the
    main thread, which may hold the lock of the Event the spin waits on, and setting that
    Event from there would wait for it for good."""
    noted: list[int] = []
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield noted
        return
    previous = {
        sig: signal.signal(sig, lambda signum, _frame: noted.append(signum))
        for sig in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        yield noted
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
