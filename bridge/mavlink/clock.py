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
- Pause: the autopilot fell silent and its clock stood still meanwhile (a stopped process
  whose clock is simulated, as a SITL's is: after SIGSTOP/SIGCONT it goes on from where it
  stopped), so every later sample has an offset larger by the pause and the estimate, which
  rises slowly, would judge every input old for a minute. A sample after a silence of more than
  ``_PAUSE_SILENCE_NS`` whose remote time moved on by less than half of it opens a check: when
  the next ``_PAUSE_CONFIRM_SAMPLES`` samples arrive in the rhythm the remote clock gives them
  (over at least ``_PAUSE_MIN_SPAN_NS``, the remote time elapsed never more than a quarter
  ahead of the local, and at least half of it), the autopilot runs again, and the estimate is
  re-seeded from their least offset (when that is larger than the estimate by half the
  silence: else no clock stood still). A backlog released by a frozen link or read late by a
  stalled process fails the check: it arrives faster than its remote times advance. A sample
  read late (local time ahead) is not held against the rhythm: on a loaded machine a reader
  busy for a few ms is common, and a backlog never looks like that. For ``_PAUSE_RETRY_NS``
  after the first sample a failed check starts again from the failing sample, since a SITL
  resumes unevenly (a burst, a late first interval); a backlog keeps failing, and the rhythm
  after it carries the offset already held. Cost: the first few inputs after a pause are
  judged old (safe values), ~20 ms at 200 Hz.
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
remote clock that runs slow by more than ``max_drift`` makes inputs look older than they are:
the safe direction. A link that froze and then delivers its backlog exactly as fast as the
autopilot sends (a saturated link whose queue never drains) looks like a pause and is taken as
fresh; a link with room drains faster than that and is caught.

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
# The pause check (see "Pause" above).
_PAUSE_SILENCE_NS: Final = 100_000_000
_PAUSE_CONFIRM_SAMPLES: Final = 4
_PAUSE_MIN_SPAN_NS: Final = 15_000_000
_PAUSE_RATE_TOLERANCE: Final = 0.25
_PAUSE_SLACK_NS: Final = 2_000_000  # transport jitter between the first and last sample
# For this long after the first sample after a pause, a sample that breaks the rhythm starts
# the check again from itself rather than ending it: a SITL resumes unevenly (ArduCopter sends
# ~20 outputs within 5 ms first, PX4's first interval after SIGCONT was 15 ms for 8 ms of its
# clock), and a check ended on that judged every input ~1 s old until the landing.
_PAUSE_RETRY_NS: Final = 250_000_000


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
        # An open pause check: samples, remote and local time elapsed, their least offset.
        self._pause: list[int] | None = None
        self.not_a_clock = False
        """The remote time runs at under half our rate: it is no µs clock (a counter, a
        frozen simulator), and the receive time is all there is."""
        self.reseeds = 0
        """Times the estimate was re-seeded by a reboot, a gap or a pause (not the first)."""
        self.reboots = 0
        """Times the remote clock stepped back by more than 1 s: the autopilot restarted."""

    @property
    def offset_ns(self) -> int | None:
        """The current estimate, local minus remote time in ns; None before the first sample."""
        return self._offset_ns

    def reset(self) -> None:
        """Forget everything (a new link, another autopilot); the next sample seeds."""
        self._offset_ns = None
        self._repeats = 0
        self._pause = None

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
            remote_ns = (self._newest_us + step_us) * _NS_PER_US
            sample = received_ns - remote_ns
            resumed_offset = self._follow_pause(step_ns, local_gap_ns, sample, offset)
            if resumed_offset is not None:
                self.reseeds += 1
                self._offset_ns = offset = resumed_offset
            if 0 <= local_gap_ns <= _RATE_PAIR_MAX_GAP_NS:
                self._rate_remote_ns += step_ns
                self._rate_local_ns += local_gap_ns
                if self._rate_local_ns >= _RATE_WINDOW_NS:
                    self.not_a_clock = self._rate_remote_ns < self._rate_local_ns * _MIN_RATE
                    self._rate_remote_ns = self._rate_local_ns = 0
            allowed = offset + int(step_ns * self._max_drift)
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
            self.reboots += 1
            return self._seed(remote_us, received_ns)
        # A reordered packet: older than the newest one. Its offset still bounds the estimate.
        remote_ns = (self._newest_us + step_us) * _NS_PER_US
        sample = received_ns - remote_ns
        if sample < offset:
            self._offset_ns = offset = sample
        return remote_ns + offset

    def _follow_pause(
        self, step_ns: int, local_gap_ns: int, sample_ns: int, current_ns: int
    ) -> int | None:
        """Open, advance or close the pause check with a sample ``step_ns`` of remote and
        ``local_gap_ns`` of local time after the newest, of offset ``sample_ns`` (the estimate
        is ``current_ns``); the offset to re-seed from when the autopilot was paused and runs
        again, else None."""
        if local_gap_ns > _PAUSE_SILENCE_NS and 2 * step_ns < local_gap_ns:
            # Silent, and its clock stood still meanwhile. The check: samples, remote span,
            # local span, least offset; and the local time since this first sample.
            self._pause = [0, 0, 0, sample_ns, 0]
            return None
        check = self._pause
        if check is None:
            return None
        if local_gap_ns > _RATE_PAIR_MAX_GAP_NS:
            self._pause = None  # another silence: no rhythm to judge
            return None
        check[0] += 1
        check[1] += step_ns
        check[2] += local_gap_ns
        check[3] = min(check[3], sample_ns)
        check[4] += local_gap_ns
        remote_span, local_span = check[1], check[2]
        if remote_span - local_span > _PAUSE_RATE_TOLERANCE * local_span + _PAUSE_SLACK_NS:
            # Its times ran ahead of its arrival: a backlog, or a SITL catching up as it
            # resumes. Early on, judge again from this sample: a backlog keeps failing, and the
            # rhythm that follows it carries its true offset anyway.
            since_open = check[4]
            self._pause = [0, 0, 0, sample_ns, since_open] if since_open < _PAUSE_RETRY_NS else None
            return None
        # Arrival running ahead of the times is no backlog, only a sample read late (this
        # process, or the link, busy for a few ms) or a slow clock: never held against the
        # rhythm, or one late read on a loaded machine would cost a whole check again. A clock
        # at under half our rate does not run yet (a late read, diluted by more samples, does).
        if (
            check[0] < _PAUSE_CONFIRM_SAMPLES
            or local_span < _PAUSE_MIN_SPAN_NS
            or remote_span < _MIN_RATE * local_span
        ):
            return None
        self._pause = None
        if check[3] - current_ns < _PAUSE_SILENCE_NS // 2:
            # The rhythm carries the offset already held: no clock stood still (this process
            # stalled and read a queue), nothing to re-seed.
            return None
        return check[3]

    def _seed(self, remote_us: int, received_ns: int) -> int:
        self._offset_ns = received_ns - remote_us * _NS_PER_US
        self._newest_raw_us = remote_us
        self._newest_us = remote_us
        self._newest_received_ns = received_ns
        self._repeats = 0
        self._pause = None
        return received_ns
