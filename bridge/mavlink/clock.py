"""When did the autopilot produce a message, on our monotonic clock?

An input's age must be judged by when the autopilot produced it, not by when Python read it:
after the process was stopped for a few seconds (a swap storm, a debugger, a slow disk write),
the socket hands over a burst of old packets all at once, and judged by receive time they
would all look fresh. The control messages carry the autopilot's own time (``time_usec``, µs
since its boot: SERVO_OUTPUT_RAW's is a uint32 that wraps every 71.6 min, the others are
uint64). :class:`AutopilotClock` maps that time onto the local monotonic clock.

Design
------
Each sample gives an offset, ``local receive time - remote time``: the true offset between the
clocks plus that message's transport delay. The estimate follows the smallest offset at once
(the sample with the least delay is the best one) and may rise only at ``max_drift`` times the
remote time elapsed since the previous sample, which covers a remote clock running slower than
ours (crystals differ by well under 0.1 %; 2 % leaves room for a slow simulator) and a path
that got longer. A burst of old packets read late carries old remote times with a large
offset each; the estimate barely moves for them, so their produced time stays near when they
were really sent (within ``max_drift`` of how long they waited) and their age shows.

``produced = remote time + estimate``, never later than the receive time.

- Wrapping: a 32-bit remote time is unwrapped by the step from the previous sample taken
  modulo 2**32 (a step of more than half the range is a step back).
- Reboot: a remote time more than 1 s behind the newest one re-seeds the estimate from the new
  sample. A reboot of a 32-bit clock that was past half its range (35.8 min) looks like a step
  forward instead; the estimate follows a lower offset at once, so the result is right anyway.
- Gap: when the remote time moved on by more than ``reset_after_ns`` since the newest sample
  and at least as much local time passed (the autopilot sent nothing, or nothing reached us,
  for that long), the estimate is re-seeded from the new sample, taking up a new transport
  delay at once. A long local gap alone (this process stopped while the autopilot kept
  sending) is not a gap: the packets queued meanwhile have remote times that fill it, and
  re-seeding from the first of them would pass that stale burst as fresh.
- A remote time of 0 or None (a sender that leaves the field empty): the receive time is all
  there is.
- A remote time equal to the newest one: once, that is the same instant (SERVO_OUTPUT_RAW ports
  0 and 1 of one round can carry one time) and gets the same produced time; repeated again,
  it is a sender that fills a constant, and the receive time is returned.
- A remote time up to 1 s behind the newest one (a reordered packet) is placed by the estimate
  and does not move the newest time.

- Not a clock: a remote time that advances at under half our rate, measured over 0.5 s of
  samples that arrived close together (at most 100 ms apart, so neither a stall of ours nor a
  silence of the autopilot counts), is no µs clock (a message counter in ``time_usec``, a
  frozen simulator): the receive time is returned until a window shows a real rate again.
  Without this, such a sender's inputs would all look old and never move a motor.

Limits. The first sample, and the first after a re-seed, is taken as fresh: a backlog read at
start-up (or a silence longer than ``reset_after_ns`` followed at once by a stall of this
process) is misjudged until its newer packets arrive; drain the link before trusting it. A
remote clock that runs slow by more than ``max_drift``, or stands still while we run (a
paused simulator), makes inputs look older than they are: the safe direction.

Pure: no clock calls; the caller passes the times in (``time.monotonic_ns()`` at receipt).
"""

from __future__ import annotations

from typing import Final

__all__ = ["AutopilotClock"]

_REBOOT_STEP_US: Final = 1_000_000  # a step back of more than 1 s is a reboot
_SAME_TIME_REPEATS: Final = 1  # a repeated remote time is the same instant this many times
_NS_PER_US: Final = 1000
# The rate check: pairs of samples at most this far apart locally count, over windows of this
# much local time; a remote clock slower than this fraction of ours is no clock.
_RATE_PAIR_MAX_GAP_NS: Final = 100_000_000
_RATE_WINDOW_NS: Final = 500_000_000
_MIN_RATE: Final = 0.5


class AutopilotClock:
    """Maps one autopilot message stream's ``time_usec`` onto the local monotonic clock (see
    the module docstring for the design). Feed it the messages of one stream, in the order
    they were read: one clock per decoder, and only the messages the decoder accepted."""

    def __init__(
        self,
        time_bits: int = 64,
        max_drift: float = 0.02,
        reset_after_ns: int = 2_000_000_000,
    ) -> None:
        """``time_bits``: 32 or 64, the width of the remote time (wrapping at 2**time_bits µs).
        ``max_drift``: how fast the estimate may rise, as a fraction of remote time elapsed.
        ``reset_after_ns``: a silence this long re-seeds the estimate.

        Raises:
            ValueError: an argument outside its range (named in the message).
        """
        if time_bits not in (32, 64):
            raise ValueError(f"time_bits={time_bits!r}: expected 32 or 64")
        if not 0.0 <= max_drift < 1.0:
            raise ValueError(f"max_drift={max_drift!r}: expected 0 <= max_drift < 1")
        if reset_after_ns <= 0:
            raise ValueError(f"reset_after_ns={reset_after_ns!r}: expected > 0")
        self._modulus = 1 << time_bits
        self._half = 1 << (time_bits - 1)
        self._max_drift = max_drift
        self._reset_after_ns = reset_after_ns
        self._offset_ns: int | None = None  # the estimate: local - remote, ns
        self._newest_raw_us = 0  # the newest remote time as sent
        self._newest_us = 0  # ... unwrapped
        self._newest_received_ns = 0
        self._repeats = 0
        # The remote clock's rate against ours, over pairs of samples that arrived close
        # together (a stall of ours or a silence of the autopilot in between says nothing).
        self._rate_remote_ns = 0
        self._rate_local_ns = 0
        self.not_a_clock = False
        """The remote time runs at under half our rate: it is no µs clock (a counter, a
        frozen simulator), and the receive time is all there is."""
        self.reseeds = 0
        """Times the estimate was re-seeded by a reboot or a gap (not counting the first)."""

    @property
    def offset_ns(self) -> int | None:
        """The current estimate, local minus remote time in ns; None before the first sample."""
        return self._offset_ns

    def reset(self) -> None:
        """Forget everything (a new link, another autopilot); the next sample seeds."""
        self._offset_ns = None
        self._repeats = 0

    def produced_ns(self, remote_us: int | None, received_ns: int) -> int:
        """The local monotonic time (ns) at which the autopilot produced a message that carries
        ``remote_us`` (its ``time_usec``) and was read at ``received_ns``; never later than
        ``received_ns``."""
        if not remote_us:
            return received_ns
        offset = self._offset_ns
        if offset is None:
            return self._seed(remote_us, received_ns)
        step_us = (remote_us - self._newest_raw_us) % self._modulus
        if step_us >= self._half:
            step_us -= self._modulus
        if step_us > 0:
            step_ns = step_us * _NS_PER_US
            reset_after = self._reset_after_ns
            if step_ns > reset_after and received_ns - self._newest_received_ns > reset_after:
                self.reseeds += 1
                return self._seed(remote_us, received_ns)
            local_gap_ns = received_ns - self._newest_received_ns
            if 0 <= local_gap_ns <= _RATE_PAIR_MAX_GAP_NS:
                self._rate_remote_ns += step_ns
                self._rate_local_ns += local_gap_ns
                if self._rate_local_ns >= _RATE_WINDOW_NS:
                    self.not_a_clock = self._rate_remote_ns < self._rate_local_ns * _MIN_RATE
                    self._rate_remote_ns = self._rate_local_ns = 0
            remote_ns = (self._newest_us + step_us) * _NS_PER_US
            allowed = offset + int(step_ns * self._max_drift)
            sample = received_ns - remote_ns
            self._offset_ns = sample if sample < allowed else allowed
            self._newest_raw_us = remote_us
            self._newest_us += step_us
            self._newest_received_ns = received_ns
            self._repeats = 0
            if self.not_a_clock:
                return received_ns
            return remote_ns + self._offset_ns
        if step_us == 0:
            self._repeats += 1
            if self._repeats > _SAME_TIME_REPEATS:
                return received_ns  # a sender that fills a constant
            return min(received_ns, self._newest_us * _NS_PER_US + offset)
        if step_us < -_REBOOT_STEP_US:
            self.reseeds += 1
            return self._seed(remote_us, received_ns)
        # A reordered packet: older than the newest one. Its offset still bounds the estimate.
        remote_ns = (self._newest_us + step_us) * _NS_PER_US
        sample = received_ns - remote_ns
        if sample < offset:
            self._offset_ns = offset = sample
        return remote_ns + offset

    def _seed(self, remote_us: int, received_ns: int) -> int:
        self._offset_ns = received_ns - remote_us * _NS_PER_US
        self._newest_raw_us = remote_us
        self._newest_us = remote_us
        self._newest_received_ns = received_ns
        self._repeats = 0
        return received_ns
