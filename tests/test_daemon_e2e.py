"""The daemon end to end: a pymavlink autopilot on loopback UDP, `esc-bridge run` as a subprocess,
and a python-can observer on the cross-process bus decoding what the bridge sends."""

from __future__ import annotations

import itertools
import math
import os
import re
import signal
import time
from collections.abc import Callable
from pathlib import Path

import can
import pytest
from conftest import STARTUP_TIMEOUT_S, Autopilot, Daemon, Observer
from pymavlink import mavutil

from bridge.errors import CodecError
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.dronecan.codec import Decoder as DronecanDecoder
from bridge.escs.dronecan.codec import DronecanFrame, NodeStatus
from bridge.escs.dronecan.codec import RawCommand as DronecanRawCommand
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records


def ckesc_throttles(msg: can.Message) -> tuple[int, ...] | None:
    """The throttles of a CKESC throttle frame, or None for any other frame (junk included)."""
    try:
        frame = ckesc_codec.decode(msg)
    except CodecError:
        return None
    if frame is None or not isinstance(
        frame.message,
        ckesc_records.RawCommand12b | ckesc_records.RawCommand14b | ckesc_records.RawCommand10b,
    ):
        return None
    return frame.message.throttles


def expect_throttles(
    observer: Observer, want: tuple[int, ...], timeout_s: float = 3.0, after: float = 0.0
) -> float:
    """Wait for a throttle frame seen at or after ``after`` whose leading values are ``want``;
    returns its time."""
    ts, _ = observer.wait_for(
        lambda m: (t := ckesc_throttles(m)) is not None and t[: len(want)] == want,
        timeout_s,
        after,
    )
    return ts


def pwm_to_throttle(pwm: int, full_scale: int = 2000) -> int:
    fraction = min(max((pwm - 1000) / 1000, 0.0), 1.0)
    return int(fraction * full_scale + 0.5)


def arm_at(autopilot: Autopilot, pwm: list[int]) -> None:
    autopilot.pwm = pwm
    autopilot.armed = True
    autopilot.start_stream(50)


SWEEP = [1000, 1100, 1250, 1500, 1733, 2000, 950, 2100, 1501]


@pytest.mark.parametrize(
    ("command", "extra"),
    [("12b", []), ("14b", []), ("10b", []), ("12b", ["--latency", "immediate"])],
    ids=["12b", "14b", "10b", "12b-immediate"],
)
def test_ckesc_throttle_sweep(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    tmp_path: Path,
    command: str,
    extra: list[str],
) -> None:
    config = tmp_path / "bridge.toml"
    config.write_text(f'[escs]\nckesc_command = "{command}"\n')
    daemon = start_daemon("--config", str(config), *extra)
    full_scale = 1000 if command == "10b" else 2000
    arm_at(autopilot, [1000, 1000, 1000, 1000])
    expect_throttles(observer, (0, 0, 0, 0), STARTUP_TIMEOUT_S)
    for pwm in SWEEP:
        # Four different values per step, so a swapped channel cannot pass.
        pwms = [pwm, 3000 - pwm, (pwm + 1000) // 2 + 250, 1000 + (pwm % 1000)]
        autopilot.pwm = pwms
        expect_throttles(observer, tuple(pwm_to_throttle(p, full_scale) for p in pwms))
    assert daemon.stop() == 0


def test_immediate_mode_follows_a_fast_input_at_twice_the_rate_at_most(
    start_daemon: Callable[..., Daemon], autopilot: Autopilot, observer: Observer, tmp_path: Path
) -> None:
    # An input flood (SERVO_OUTPUT_RAW as fast as a Python thread sends, some 1 000 a second)
    # into a 100 Hz bridge in immediate mode: its frames go out on input, at most twice the
    # rate, never closer than half a period (5 ms) to the last input's frame.
    config = tmp_path / "bridge.toml"
    config.write_text('[output]\nrate_hz = 100\nlatency = "immediate"\n')
    daemon = start_daemon("--config", str(config))
    autopilot.pwm = [1500] * 4
    autopilot.armed = True
    autopilot.start_stream(2000)
    expect_throttles(observer, (1000,) * 4, STARTUP_TIMEOUT_S)
    window_s = 2.0
    start = time.monotonic()
    time.sleep(window_s)
    stamps = observer.stamps(start, start + window_s)
    rate_hz = len(stamps) / window_s
    assert 150 <= rate_hz <= 2 * 100 * 1.02, rate_hz  # on input, above the rate; capped at 2x
    gaps = sorted(b - a for a, b in itertools.pairwise(stamps))
    assert gaps[len(gaps) // 10] > 0.0045, gaps[:10]  # 5 ms apart, bar a late send's catch-up
    print(f"input flood: {rate_hz:.0f} frames/s, gap p10 {gaps[len(gaps) // 10] * 1e3:.2f} ms")
    assert daemon.stop() == 0


@pytest.mark.parametrize(
    ("mode", "record", "value_of"),
    [
        ("current", ft_records.SetCurrent, lambda m: m.current_a / 20.0),
        ("current_percent", ft_records.SetCurrentPercent, lambda m: m.fraction),
        ("duty", ft_records.SetDuty, lambda m: m.duty / 0.95),
        ("erpm", ft_records.SetErpm, lambda m: m.erpm / 50_000),
    ],
)
def test_ft_modes(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    mode: str,
    record: type,
    value_of: Callable[[ft_records.FtMessage], float],
    tmp_path: Path,
) -> None:
    config = tmp_path / "bridge.toml"
    config.write_text(
        f'[output]\nprotocol = "ft"\n[escs]\nids = [11, 12, 13, 14]\nft_mode = "{mode}"\n'
    )
    start_daemon("--config", str(config))
    arm_at(autopilot, [1000, 1250, 1500, 2000])
    want = {11: 0.0, 12: 0.25, 13: 0.5, 14: 1.0}
    got: dict[int, float] = {}

    def matches(msg: can.Message) -> bool:
        frame = ft_codec.decode(msg)
        if frame is None or not isinstance(frame.message, record):
            return False
        got[frame.esc_id] = value_of(frame.message)
        return all(abs(got.get(esc, -9) - v) < 1e-4 for esc, v in want.items())

    observer.wait_for(matches, STARTUP_TIMEOUT_S)
    # Spread, not burst: consecutive commands go to consecutive ESCs, ~2.5 ms apart at 100 Hz.
    # Kernel receive times (udp_multicast stamps each datagram), not when the observer's
    # thread got to them: on a loaded machine it reads in batches.
    recent = [
        (m.timestamp, f.esc_id)
        for _, m in observer.frames[-40:]
        if (f := ft_codec.decode(m)) is not None and isinstance(f.message, record)
    ]
    ids = [esc for _, esc in recent]
    assert all(b == (a - 10) % 4 + 11 for a, b in itertools.pairwise(ids))
    gaps = sorted(b[0] - a[0] for a, b in itertools.pairwise(recent))
    assert 0.001 < gaps[len(gaps) // 2] < 0.006  # the median gap is about 10 ms / 4


class DronecanReader:
    """The observer's frames as DroneCAN transfers: each frame decoded once, in order (a
    multi-frame RawCommand is put back together across them)."""

    def __init__(self, observer: Observer) -> None:
        self.observer = observer
        self.decoder = DronecanDecoder()
        self._seen: dict[int, DronecanFrame | None] = {}

    def frame(self, msg: can.Message) -> DronecanFrame | None:
        key = id(msg)
        if key not in self._seen:
            try:
                self._seen[key] = self.decoder.decode(msg)
            except CodecError:
                self._seen[key] = None
        return self._seen[key]

    def wait_for(
        self, predicate: Callable[[DronecanFrame], bool], timeout_s: float, after: float = 0.0
    ) -> tuple[float, DronecanFrame]:
        ts, msg = self.observer.wait_for(
            lambda m: (f := self.frame(m)) is not None and predicate(f), timeout_s, after
        )
        frame = self.frame(msg)
        assert frame is not None
        return ts, frame


def raw_commands(frame: DronecanFrame) -> tuple[int, ...] | None:
    message = frame.message
    return message.commands if isinstance(message, DronecanRawCommand) else None


def test_dronecan_commands_multi_frame_and_node_status(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    tmp_path: Path,
) -> None:
    """Eight ESCs: each tick one RawCommand of three frames from node 10 at priority 7 (as
    ArduPilot sends it), read back with dronecan; our NodeStatus once a second."""
    config = tmp_path / "bridge.toml"
    config.write_text(
        '[output]\nprotocol = "dronecan"\n[mixer]\nname = "passthrough-8"\n'
        "[escs]\ndronecan_reversible = [8]\n"
    )
    daemon = start_daemon("--config", str(config))
    reader = DronecanReader(observer)
    pwm = [1000, 1250, 1500, 2000, 1100, 1900, 1750, 1000]
    arm_at(autopilot, pwm)
    reader.wait_for(lambda f: raw_commands(f) == (0,) * 8, STARTUP_TIMEOUT_S)
    # 1000..2000 µs is 0..1; ESC 8 is reversible, so 1000 µs is still 0 (the mixer's range).
    want = tuple(round(min(max((p - 1000) / 1000, 0.0), 1.0) * 8191) for p in pwm)
    _, frame = reader.wait_for(lambda f: raw_commands(f) == want, STARTUP_TIMEOUT_S)
    assert (frame.priority, frame.source_node, frame.frames) == (7, 10, 3)
    start = time.monotonic()
    _, status = reader.wait_for(lambda f: isinstance(f.message, NodeStatus), 3.0, after=start)
    assert status.source_node == 10 and status.priority == 31
    assert isinstance(status.message, NodeStatus) and status.message.health == 0
    # Consecutive transfers take consecutive transfer IDs (mod 32): judged on the pairs that
    # reached the observer one 2.5 ms tick apart by the kernel's stamps, since on a loaded
    # machine the observer's socket may overflow and lose a transfer between two it kept.
    recent = [
        (t, f.transfer_id)
        for t, m in observer.frames[-120:]
        if (f := reader.frame(m)) is not None and raw_commands(f) is not None
    ]
    steps = [(b - a) % 32 for (ta, a), (tb, b) in itertools.pairwise(recent) if tb - ta < 0.00375]
    assert len(steps) > 10 and set(steps) == {1}, f"transfer ID steps a tick apart: {steps}"
    autopilot.armed = False
    autopilot.heartbeat()
    disarmed_at = time.monotonic()
    reader.wait_for(lambda f: raw_commands(f) == (0,) * 8, 2.0, after=disarmed_at)
    assert daemon.stop() == 0


def test_stale_input_goes_safe_within_timeout(
    start_daemon: Callable[..., Daemon], autopilot: Autopilot, observer: Observer
) -> None:
    start_daemon("--rate", "400")
    arm_at(autopilot, [1600, 1600, 1600, 1600])
    expect_throttles(observer, (1200, 1200, 1200, 1200), STARTUP_TIMEOUT_S)
    autopilot.pause_outputs()  # heartbeats go on: armed, but the output stream is stale
    stopped_at = time.monotonic()
    safe_at = expect_throttles(observer, (0, 0, 0, 0), 2.0, after=stopped_at)
    # input_timeout_ms 100 + 2 periods of 2.5 ms, plus up to one 20 ms input period and a
    # generous allowance for loopback and scheduling on a busy test machine.
    assert 0.07 <= safe_at - stopped_at <= 0.105 + 0.02 + 0.15
    # and it stays safe
    time.sleep(0.2)
    assert all(ckesc_throttles(m) in (None, (0, 0, 0, 0)) for m in observer.since(safe_at))


def test_disarm_goes_safe_at_once(
    start_daemon: Callable[..., Daemon], autopilot: Autopilot, observer: Observer
) -> None:
    start_daemon()
    arm_at(autopilot, [1500, 1500, 1500, 1500])
    expect_throttles(observer, (1000, 1000, 1000, 1000), STARTUP_TIMEOUT_S)
    autopilot.armed = False
    autopilot.heartbeat()
    disarmed_at = time.monotonic()
    safe_at = expect_throttles(observer, (0, 0, 0, 0), 2.0, after=disarmed_at)
    assert safe_at - disarmed_at < 0.1  # the next frame after the HEARTBEAT is read
    time.sleep(0.3)  # outputs keep streaming at 1500 µs: still safe while disarmed
    assert all(ckesc_throttles(m) in (None, (0, 0, 0, 0)) for m in observer.since(safe_at))


def test_sigterm_sends_safe_values_then_exits_zero(
    start_daemon: Callable[..., Daemon], autopilot: Autopilot, observer: Observer
) -> None:
    daemon = start_daemon()
    arm_at(autopilot, [1500, 1500, 1500, 1500])
    expect_throttles(observer, (1000, 1000, 1000, 1000), STARTUP_TIMEOUT_S)
    sent_at = time.monotonic()
    daemon.proc.send_signal(signal.SIGTERM)
    assert daemon.stop() == 0
    time.sleep(0.2)  # anything still in flight
    after = [(ts, t) for ts, m in observer.frames if ts >= sent_at and (t := ckesc_throttles(m))]
    first_safe = next(i for i, (_, t) in enumerate(after) if t == (0, 0, 0, 0))
    # Safe values follow the signal as soon as the main process (not real-time) runs its
    # handler: a few ticks, at most a few hundred ms on a loaded machine...
    assert after[first_safe][0] - sent_at < 0.3
    safe = [t for _, t in after[first_safe:]]
    # ...and only safe values follow, for shutdown_flush_ms 200 at 400 Hz: about 80 frames.
    assert all(t == (0, 0, 0, 0) for t in safe)
    assert 40 <= len(safe) <= 120
    assert "stopped after sending safe values for 200 ms" in daemon.output
    assert re.search(r"output loop: \d+ ticks, \d+ frames, 0 send errors", daemon.output)


def test_sigint_is_handled_like_sigterm(
    start_daemon: Callable[..., Daemon], autopilot: Autopilot, observer: Observer
) -> None:
    daemon = start_daemon()
    expect_throttles(observer, (0, 0, 0, 0), STARTUP_TIMEOUT_S)
    assert daemon.stop(signal.SIGINT) == 0
    assert "SIGINT: stopping" in daemon.output


def test_a_storm_of_stop_signals_still_ends_in_the_safe_flush(
    start_daemon: Callable[..., Daemon], autopilot: Autopilot, observer: Observer, tmp_path: Path
) -> None:
    """Stop signals one after another for 0.3 s, every kind, as fast as this process can send
    them (a demo's SIGINT beside its parent-death SIGTERM, a user's repeated Ctrl-C): the
    daemon still stops once, with its safe values, and exits 0. A handler that took a lock (an
    Event's) while a second signal's handler ran nested in it never came back: a demo's bridge
    was found hung so. The flush lasts 1 s, so the storm is over before the interpreter ends
    (where a signal gets its default action back)."""
    config = tmp_path / "bridge.toml"
    config.write_text("[output]\nshutdown_flush_ms = 1000\n", encoding="utf-8")
    daemon = start_daemon("--config", str(config))
    arm_at(autopilot, [1500, 1500, 1500, 1500])
    expect_throttles(observer, (1000, 1000, 1000, 1000), STARTUP_TIMEOUT_S)
    sent_at = time.monotonic()
    signals = itertools.cycle([signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGQUIT])
    sent = 0
    while time.monotonic() - sent_at < 0.3:
        try:
            os.kill(daemon.proc.pid, next(signals))
        except ProcessLookupError:  # it ended within the storm
            break
        sent += 1
    assert daemon.stop() == 0, f"after {sent} signals:\n{daemon.output}"
    assert "stopped after sending safe values for 1000 ms" in daemon.output
    time.sleep(0.2)  # anything still in flight
    after = [t for ts, m in observer.frames if ts >= sent_at and (t := ckesc_throttles(m))]
    assert after and after[-1] == (0, 0, 0, 0)


def test_other_senders_are_ignored(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    mavlink_port: int,
    tmp_path: Path,
) -> None:
    # A long input timeout: a loaded machine that delays the autopilot's stream must not make
    # the bridge go safe in the middle of what this test watches.
    config = tmp_path / "bridge.toml"
    config.write_text("[output]\ninput_timeout_ms = 1000\n")
    start_daemon("--config", str(config))
    arm_at(autopilot, [1500, 1500, 1500, 1500])
    expect_throttles(observer, (1000, 1000, 1000, 1000), STARTUP_TIMEOUT_S)
    intruder = Autopilot(mavlink_port, system=7, component=1)
    try:
        intruder.pwm = [2000, 2000, 2000, 2000]
        intruder.armed = True
        intruder.start_stream(100)
        since = time.monotonic()
        time.sleep(1.0)
        seen = {t for m in observer.since(since) if (t := ckesc_throttles(m)) is not None}
        assert seen == {(1000, 1000, 1000, 1000)}
        # When the autopilot disarms, the intruder's "armed" heartbeats do not keep it armed.
        autopilot.armed = False
        expect_throttles(observer, (0, 0, 0, 0), 2.0, after=time.monotonic())
    finally:
        intruder.close()


@pytest.mark.parametrize(
    ("toml", "args", "message"),
    [
        ("[output]\nrate = 400\n", [], "[output] unknown key 'rate'; expected one of protocol"),
        ('[mixer]\nname = "quad-y"\n', [], "quad-y"),
        ("[escs]\nids = [1, 2]\n", [], "ids has 2 entries but mixer 'passthrough-4' has 4"),
        (
            '[output]\nprotocol = "ft"\nrate_hz = 400\n[mixer]\nname = "passthrough-16"\n'
            "[can]\nbitrate = 250000\n",
            [],
            "exceeds the ceiling of 70%",
        ),
        ("", ["--mavlink", "carrier-pigeon:/dev/coop"], "carrier-pigeon:/dev/coop"),
        ("", ["--rate", "0"], "command line: --rate: expected an integer 1..1000, got 0"),
        ("", ["--can-interface", "no_such_bus"], "'no_such_bus' is not available"),
        ("[output\n", [], "not valid TOML"),
    ],
    ids=[
        "unknown-key",
        "mixer",
        "esc-count",
        "bus-load",
        "mavlink-url",
        "flag",
        "interface",
        "toml",
    ],
)
def test_bad_config_stops_before_sending(
    start_daemon: Callable[..., Daemon],
    observer: Observer,
    tmp_path: Path,
    toml: str,
    args: list[str],
    message: str,
) -> None:
    config = tmp_path / "bridge.toml"
    config.write_text(toml)
    daemon = start_daemon("--config", str(config), *args)
    assert daemon.proc.wait(30) == 2
    daemon.stop()
    assert message in daemon.output
    assert "Traceback" not in daemon.output
    time.sleep(0.3)
    assert observer.frames == []


def test_loop_goes_safe_and_exits_when_the_main_process_dies(
    start_daemon: Callable[..., Daemon], autopilot: Autopilot, observer: Observer
) -> None:
    daemon = start_daemon()
    arm_at(autopilot, [1500, 1500, 1500, 1500])
    expect_throttles(observer, (1000, 1000, 1000, 1000), STARTUP_TIMEOUT_S)
    killed_at = time.monotonic()
    daemon.proc.kill()  # no signal handler, no flush: the loop process is on its own
    daemon.proc.wait(5)
    safe_at = expect_throttles(observer, (0, 0, 0, 0), 2.0, after=killed_at)
    assert safe_at - killed_at < 0.5  # stale input (100 ms) or its parent gone, whichever first
    time.sleep(1.5)  # the orphaned loop flushes safe values for 200 ms, then exits
    quiet_since = time.monotonic()
    time.sleep(0.5)
    assert [m for m in observer.since(quiet_since) if ckesc_throttles(m)] == []
    assert all(ckesc_throttles(m) in (None, (0, 0, 0, 0)) for m in observer.since(safe_at))


def feed_until(
    send: Callable[[], None], observer: Observer, want: tuple[int, ...], timeout_s: float
) -> float:
    """Call ``send`` every 20 ms until a frame with throttles ``want`` is seen; its time."""
    start = time.monotonic()
    while time.monotonic() - start < timeout_s:
        send()
        time.sleep(0.02)
        for ts, msg in observer.frames[-20:]:
            if ts >= start and ckesc_throttles(msg) == want:
                return ts
    raise AssertionError(f"no frame with throttles {want} within {timeout_s} s")


def test_px4_hil_actuator_controls(
    start_daemon: Callable[..., Daemon], autopilot: Autopilot, observer: Observer
) -> None:
    """PX4 SITL: normalized 0..1 controls, armed by the message's own mode flag."""
    start_daemon("--source", "hil_actuator_controls")
    armed = mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED

    def send(controls: list[float], mode: int) -> Callable[[], None]:
        def once() -> None:
            autopilot.heartbeat()  # disarmed HEARTBEAT: the HIL mode flag arms
            autopilot.mav.hil_actuator_controls_send(
                int(time.monotonic() * 1e6), controls + [0.0] * 12, mode, 0
            )

        return once

    feed_until(
        send([0.0, 0.25, 0.5, 1.0], armed), observer, (0, 500, 1000, 2000), STARTUP_TIMEOUT_S
    )
    feed_until(send([0.0, 0.25, 0.5, 1.0], 0), observer, (0, 0, 0, 0), 2.0)


def test_nan_input_goes_safe(
    start_daemon: Callable[..., Daemon], autopilot: Autopilot, observer: Observer
) -> None:
    """PX4 ACTUATOR_OUTPUT_STATUS (PWM µs); a NaN among the used outputs means safe values."""
    start_daemon("--source", "actuator_output_status")
    autopilot.armed = True

    def send(outputs: list[float]) -> Callable[[], None]:
        def once() -> None:
            autopilot.heartbeat()
            autopilot.mav.actuator_output_status_send(
                int(time.monotonic() * 1e6), 0xF, outputs + [0.0] * 28
            )

        return once

    feed_until(
        send([1500.0, 1250.0, 1750.0, 2000.0]), observer, (1000, 500, 1500, 2000), STARTUP_TIMEOUT_S
    )
    nan_at = time.monotonic()
    safe_at = feed_until(send([1500.0, math.nan, 1500.0, 1500.0]), observer, (0, 0, 0, 0), 2.0)
    assert safe_at - nan_at < 0.2  # the next tick after the NaN input is read
    feed_until(send([1500.0, 1500.0, 1500.0, 1500.0]), observer, (1000, 1000, 1000, 1000), 2.0)


def test_geometry_mixer_from_configured_channels(
    start_daemon: Callable[..., Daemon], autopilot: Autopilot, observer: Observer, tmp_path: Path
) -> None:
    """quad-x with roll, pitch, thrust, yaw on channels 1..4 (PWM, 1500 = centre)."""
    config = tmp_path / "bridge.toml"
    config.write_text(
        '[mixer]\nname = "quad-x"\naxis_channels = { roll = 1, pitch = 2, thrust = 3, yaw = 4 }\n'
    )
    start_daemon("--config", str(config))
    arm_at(autopilot, [1500, 1500, 1500, 1500])  # level, half thrust
    _, hover = observer.wait_for(
        lambda m: (t := ckesc_throttles(m)) is not None and len(set(t)) == 1 and t[0] > 500,
        STARTUP_TIMEOUT_S,
    )
    level = ckesc_throttles(hover)
    assert level is not None
    autopilot.pwm = [1700, 1500, 1500, 1500]  # roll right: left motors up, right motors down
    # quad-x: 1 front right, 2 rear left, 3 front left, 4 rear right
    _, rolled = observer.wait_for(
        lambda m: (t := ckesc_throttles(m)) is not None and t[1] > level[1], 3.0
    )
    t = ckesc_throttles(rolled)
    assert t is not None
    assert t[1] == t[2] > level[0] > t[0] == t[3]
    assert abs((t[1] - level[0]) - (level[0] - t[0])) <= 2  # symmetric about hover
