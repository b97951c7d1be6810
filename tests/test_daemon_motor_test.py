"""MAV_CMD_DO_MOTOR_TEST end to end: `esc-bridge run` as a subprocess, a pymavlink autopilot, a
ground station on the bridge's `[mavlink] outputs`, and a python-can observer on the bus."""

from __future__ import annotations

import itertools
import json
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest
import zenoh
from conftest import Autopilot, Daemon, MavlinkReceiver, Observer, free_port
from pymavlink import mavutil

from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.escs.vesc import codec as vesc_codec
from bridge.escs.vesc import records as vesc_records
from bridge.mavlink import load_dialect
from bridge.telemetry.payload import HealthPayload

dialect = load_dialect()
START_TIMEOUT_S = 10.0  # a cold start spawns the loop's interpreter first
PERCENT, PWM = dialect.MOTOR_TEST_THROTTLE_PERCENT, dialect.MOTOR_TEST_THROTTLE_PWM
ACCEPTED, DENIED = dialect.MAV_RESULT_ACCEPTED, dialect.MAV_RESULT_DENIED
REJECTED, UNSUPPORTED = dialect.MAV_RESULT_TEMPORARILY_REJECTED, dialect.MAV_RESULT_UNSUPPORTED
SAFE = (0, 0, 0, 0)


class Gcs(MavlinkReceiver):
    """A ground station on one of the bridge's extra outputs: sends DO_MOTOR_TEST, records
    everything the bridge sends (decoded with the project's dialect)."""

    def __init__(self, system: int = 255) -> None:
        self.port = free_port()
        self.conn: Any = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{self.port}", source_system=system, source_component=190
        )
        super().__init__(self.conn)

    def wait_for(
        self,
        kind: str,
        predicate: Callable[[Any], bool],
        timeout_s: float = START_TIMEOUT_S,
        after: float = 0.0,
        first: bool = True,
    ) -> Any:
        return super().wait_for(kind, predicate, timeout_s, after, first)

    def motor_test(
        self,
        motor: float,
        throttle_type: float,
        throttle: float,
        timeout_s: float,
        count: float = 0,
        order: float = 0,
    ) -> int:
        """Send DO_MOTOR_TEST to the bridge; its COMMAND_ACK's result."""
        sent = time.monotonic()
        self.conn.mav.command_long_send(
            1,
            191,
            dialect.MAV_CMD_DO_MOTOR_TEST,
            0,
            motor,
            throttle_type,
            throttle,
            timeout_s,
            count,
            order,
            0,
        )
        ack = self.wait_for(
            "COMMAND_ACK", lambda m: m.command == dialect.MAV_CMD_DO_MOTOR_TEST, after=sent
        )
        return int(ack.result)

    def texts(self) -> list[str]:
        with self._lock:
            return [m.text for _, m in self.messages if m.get_type() == "STATUSTEXT"]

    def close(self) -> None:
        super().close()
        self.conn.close()


@pytest.fixture
def gcs() -> Iterator[Gcs]:
    station = Gcs()
    yield station
    station.close()


def write_config(path: Path, gcs: Gcs, extra: str = "", motor_test: bool = True) -> str:
    """A config with the GCS as an output and DO_MOTOR_TEST on (off by default in the bridge)."""
    switch = f"motor_test = {'true' if motor_test else 'false'}\n"
    extra = (
        extra.replace("[output]\n", "[output]\n" + switch)
        if "[output]" in extra
        else (extra + "[output]\n" + switch)
    )
    path.write_text(f'[mavlink]\noutputs = ["udpout:127.0.0.1:{gcs.port}"]\n{extra}')
    return str(path)


def throttles(msg: can.Message) -> tuple[int, ...] | None:
    frame = ckesc_codec.decode(msg)
    if frame is None or not isinstance(frame.message, ckesc_records.RawCommand12b):
        return None
    return frame.message.throttles


def ft_command(msg: can.Message) -> tuple[int, str, float] | None:
    """(ESC ID, "duty" or "current", value) of an FT duty or current command, else None."""
    frame = ft_codec.decode(msg)
    if frame is None:
        return None
    if isinstance(frame.message, ft_records.SetDuty):
        return frame.esc_id, "duty", round(frame.message.duty, 6)
    if isinstance(frame.message, ft_records.SetCurrent):
        return frame.esc_id, "current", frame.message.current_a
    return frame.esc_id, type(frame.message).__name__, 0.0


def ready(autopilot: Autopilot, observer: Observer, gcs: Gcs, pwm: int = 1000) -> None:
    """The autopilot streams, disarmed; the bridge sends safe values and talks to the GCS."""
    autopilot.pwm = [pwm] * 4
    autopilot.start_stream(50)
    observer.wait_for(lambda m: throttles(m) == SAFE, START_TIMEOUT_S)
    heard_disarmed(gcs)


def heard_disarmed(gcs: Gcs) -> None:
    """The bridge has heard the autopilot say disarmed (it reports that to the GCS)."""
    gcs.wait_for("STATUSTEXT", lambda m: m.text == "ESC out: disarmed, motors stopped")


def throttle_run(observer: Observer, want: tuple[int, ...], timeout_s: float) -> list[float]:
    """Kernel times of the frames carrying ``want``, from the first until a frame that does not
    (which must be safe); asserts nothing else came in between."""
    start, _ = observer.wait_for(lambda m: throttles(m) == want, timeout_s)
    observer.wait_for(lambda m: throttles(m) not in (None, want), timeout_s, after=start)
    run = [(m.timestamp, throttles(m)) for m in observer.since(start) if throttles(m)]
    first_other = next(i for i, (_, t) in enumerate(run) if t != want)
    assert run[first_other][1] == SAFE
    return [ts for ts, _ in run[:first_other]]


def test_percent_spins_one_motor_for_the_capped_timeout_and_shows_in_health(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    gcs: Gcs,
    tmp_path: Path,
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    config = write_config(tmp_path / "b.toml", gcs, "[output]\nmotor_test_max_s = 1.0\n")
    daemon = start_daemon("--config", config, "--zenoh-listen", endpoint, "--vehicle", "mt")
    ready(autopilot, observer, gcs)
    health: list[HealthPayload] = []
    zconfig = zenoh.Config()
    zconfig.insert_json5("connect/endpoints", json.dumps([endpoint]))
    zconfig.insert_json5("listen/endpoints", "[]")
    zconfig.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(zconfig) as session:
        session.declare_subscriber(
            "esc-bridge/mt/bridge/health",
            lambda sample: health.append(HealthPayload.decode(sample.payload.to_bytes())),
        )
        assert gcs.motor_test(2, PERCENT, 30, timeout_s=20) == ACCEPTED  # cut to 1 s
        times = throttle_run(observer, (0, 600, 0, 0), 3.0)
    assert 0.85 <= times[-1] - times[0] <= 1.3  # the cap, not the 20 s asked
    assert len(times) >= 0.85 * 400 * 0.5  # at the loop's rate (400 Hz; generous)
    testing = [h.motor_test for h in health if h.state == "motor_test"]
    assert testing, [h.state for h in health]
    assert testing[0] is not None and testing[0].motor == 2
    assert testing[0].throttle == pytest.approx(0.3)
    time.sleep(0.3)  # the supervisor reports the end within 0.1 s
    texts = gcs.texts()
    assert "Motor test: motor 2 30% 1s (cut to 1 s)" in texts
    assert "ESC out: MOTOR TEST, one motor may spin" in texts
    assert "Motor test: done, motors safe" in texts
    assert daemon.stop() == 0


def test_pwm_on_ft_in_duty_mode_sends_duty_to_one_esc_and_safe_current_to_the_rest(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    gcs: Gcs,
    tmp_path: Path,
) -> None:
    extra = '[output]\nprotocol = "ft"\n[escs]\nids = [11, 12, 13, 14]\nft_mode = "duty"\n'
    start_daemon("--config", write_config(tmp_path / "b.toml", gcs, extra))
    autopilot.start_stream(50)
    observer.wait_for(lambda m: ft_codec.decode(m) is not None, START_TIMEOUT_S)
    heard_disarmed(gcs)
    sent = time.monotonic()
    assert gcs.motor_test(2, PWM, 1500, timeout_s=0.6) == ACCEPTED  # PWM 1500: half throttle
    first, _ = observer.wait_for(lambda m: (c := ft_command(m)) is not None and c[1] == "duty", 2.0)
    time.sleep(1.0)
    commands = [(m.timestamp, c) for m in observer.since(sent) if (c := ft_command(m))]
    duties = [(ts, c) for ts, c in commands if c[1] == "duty"]
    assert {c for _, c in duties} == {(12, "duty", 0.475)}  # 0.5 of ft_max_duty 0.95
    assert 0.5 <= duties[-1][0] - duties[0][0] <= 0.8
    others = {c for _, c in commands if c[0] != 12}
    assert others == {(11, "current", 0.0), (13, "current", 0.0), (14, "current", 0.0)}
    after = {c for m in observer.since(first + 0.8) if (c := ft_command(m)) is not None}
    assert after == {(esc, "current", 0.0) for esc in (11, 12, 13, 14)}


def vesc_command(msg: can.Message) -> tuple[int, str, float] | None:
    """(VESC ID, "duty" or "current", value) of a VESC duty or current command, else None."""
    frame = vesc_codec.decode(msg)
    if frame is None:
        return None
    if isinstance(frame.message, vesc_records.SetDuty):
        return frame.controller_id, "duty", round(frame.message.duty, 5)
    if isinstance(frame.message, vesc_records.SetCurrent):
        return frame.controller_id, "current", frame.message.current_a
    return frame.controller_id, type(frame.message).__name__, 0.0


def test_pwm_on_vesc_sends_duty_to_one_vesc_and_releases_the_rest(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    gcs: Gcs,
    tmp_path: Path,
) -> None:
    extra = '[output]\nprotocol = "vesc"\n[escs]\nids = [11, 12, 13, 14]\n'
    start_daemon("--config", write_config(tmp_path / "b.toml", gcs, extra))
    autopilot.start_stream(50)
    observer.wait_for(lambda m: vesc_codec.decode(m) is not None, START_TIMEOUT_S)
    heard_disarmed(gcs)
    sent = time.monotonic()
    assert gcs.motor_test(2, PWM, 1500, timeout_s=0.6) == ACCEPTED  # PWM 1500: half throttle
    first, _ = observer.wait_for(
        lambda m: (c := vesc_command(m)) is not None and c[1] == "duty", 2.0
    )
    time.sleep(1.0)
    commands = [(m.timestamp, c) for m in observer.since(sent) if (c := vesc_command(m))]
    duties = [(ts, c) for ts, c in commands if c[1] == "duty"]
    assert {c for _, c in duties} == {(12, "duty", 0.475)}  # 0.5 of vesc_max_duty 0.95
    assert 0.5 <= duties[-1][0] - duties[0][0] <= 0.8
    others = {c for _, c in commands if c[0] != 12}
    assert others == {(11, "current", 0.0), (13, "current", 0.0), (14, "current", 0.0)}
    after = {c for m in observer.since(first + 0.8) if (c := vesc_command(m)) is not None}
    assert after == {(esc, "current", 0.0) for esc in (11, 12, 13, 14)}


def test_arming_stops_a_test_at_once_and_an_armed_vehicle_refuses_one(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    gcs: Gcs,
    tmp_path: Path,
) -> None:
    start_daemon("--config", write_config(tmp_path / "b.toml", gcs))
    ready(autopilot, observer, gcs)
    assert gcs.motor_test(3, PERCENT, 25, timeout_s=5) == ACCEPTED
    observer.wait_for(lambda m: throttles(m) == (0, 0, 500, 0), 2.0)
    autopilot.armed = True
    autopilot.heartbeat()
    armed_at = time.monotonic()
    stopped_at, _ = observer.wait_for(lambda m: throttles(m) == SAFE, 2.0, after=armed_at)
    assert stopped_at - armed_at < 0.1  # the loop reads the arming state every tick
    time.sleep(0.1)

    # Armed: refused for now, and nothing spins.
    refused_at = time.monotonic()
    assert gcs.motor_test(1, PERCENT, 25, timeout_s=5) == REJECTED
    time.sleep(0.5)
    assert {throttles(m) for m in observer.since(refused_at)} <= {SAFE, None}
    # Disarmed again: the stopped test does not come back.
    autopilot.armed = False
    autopilot.heartbeat()
    time.sleep(0.5)
    assert {throttles(m) for m in observer.since(stopped_at + 0.05)} <= {SAFE, None}
    texts = gcs.texts()
    assert "Motor test: stopped, armed or autopilot lost" in texts
    assert "Motor test refused: vehicle armed" in texts


def test_a_count_tests_the_motors_in_turn_and_throttle_zero_stops(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    gcs: Gcs,
    tmp_path: Path,
) -> None:
    start_daemon("--config", write_config(tmp_path / "b.toml", gcs))
    ready(autopilot, observer, gcs)
    sent = time.monotonic()
    order = dialect.MOTOR_TEST_ORDER_BOARD
    assert gcs.motor_test(2, PERCENT, 20, timeout_s=0.4, count=3, order=order) == ACCEPTED
    runs = [throttle_run(observer, want, 3.0) for want in ((0, 400, 0, 0), (0, 0, 400, 0))]
    runs.append(throttle_run(observer, (0, 0, 0, 400), 3.0))
    seen = [t for m in observer.since(sent) if (t := throttles(m)) not in (None, SAFE)]
    assert seen[0] == (0, 400, 0, 0) and seen[-1] == (0, 0, 0, 400)
    assert {(0, 400, 0, 0), (0, 0, 400, 0), (0, 0, 0, 400)} == set(seen)  # never motor 1
    for run in runs:
        assert 0.3 <= run[-1] - run[0] <= 0.55
    for earlier, later in itertools.pairwise(runs):
        assert 0.12 <= later[0] - earlier[-1] <= 0.35  # safe for half the time in between

    # A new command with throttle 0 stops a running test at once.
    assert gcs.motor_test(1, PERCENT, 20, timeout_s=5) == ACCEPTED
    observer.wait_for(lambda m: throttles(m) == (400, 0, 0, 0), 2.0)
    stop_at = time.monotonic()
    assert gcs.motor_test(1, PERCENT, 0, timeout_s=0) == ACCEPTED
    safe_at, _ = observer.wait_for(lambda m: throttles(m) == SAFE, 2.0, after=stop_at)
    assert safe_at - stop_at < 0.1
    time.sleep(0.3)
    assert {throttles(m) for m in observer.since(safe_at)} <= {SAFE, None}
    assert "Motor test: motor 3" in gcs.texts()  # each motor of a sequence is announced


def test_bad_commands_are_refused_and_nothing_spins(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    gcs: Gcs,
    tmp_path: Path,
) -> None:
    start_daemon("--config", write_config(tmp_path / "b.toml", gcs))
    gcs.wait_for("HEARTBEAT", lambda m: m.get_srcComponent() == 191)
    observer.wait_for(lambda m: throttles(m) == SAFE, START_TIMEOUT_S)
    since = time.monotonic()
    # Before the autopilot is heard its arming state is unknown: not now.
    assert gcs.motor_test(1, PERCENT, 20, timeout_s=1) == REJECTED
    ready(autopilot, observer, gcs)
    cases = [
        ((0, PERCENT, 20, 1), DENIED),  # motors are 1..4
        ((5, PERCENT, 20, 1), DENIED),
        ((1.5, PERCENT, 20, 1), DENIED),
        ((1, PERCENT, 101, 1), DENIED),
        ((1, PERCENT, -1, 1), DENIED),
        ((1, PWM, 2100, 1), DENIED),  # outside the mixer's input range
        ((1, PWM, 900, 1), DENIED),
        ((1, PERCENT, 20, 0), DENIED),  # a test needs a time
        ((1, PERCENT, 20, float("nan")), DENIED),
        ((3, PERCENT, 20, 1, 3), DENIED),  # motors 3..5: there is no 5
        ((1, PERCENT, 20, 1, 0, 7), DENIED),  # no such test order
        ((1, dialect.MOTOR_TEST_THROTTLE_PILOT, 20, 1), UNSUPPORTED),
        ((1, dialect.MOTOR_TEST_COMPASS_CAL, 20, 1), UNSUPPORTED),
        ((1, 9, 20, 1), DENIED),
    ]
    results = [gcs.motor_test(*params) for params, _ in cases]
    assert results == [want for _, want in cases]
    time.sleep(0.3)
    assert {throttles(m) for m in observer.since(since)} <= {SAFE, None}
    texts = gcs.texts()
    assert "Motor test refused: autopilot not heard" in texts
    assert "Motor test: motor 5 not 1..4" in texts


@pytest.mark.parametrize(
    ("system", "switched_on", "text"),
    [
        (99, True, None),  # a stranger: refused without a word to the ground station
        (255, False, "Motor test refused: off in the bridge's config"),
    ],
    ids=["stranger", "switched-off"],
)
def test_a_motor_test_from_a_stranger_or_with_the_switch_off_is_denied_and_nothing_spins(
    start_daemon: Callable[..., Daemon],
    autopilot: Autopilot,
    observer: Observer,
    tmp_path: Path,
    system: int,
    switched_on: bool,
    text: str | None,
) -> None:
    station = Gcs(system)
    try:
        config = write_config(tmp_path / "b.toml", station, motor_test=switched_on)
        daemon = start_daemon("--config", config)
        ready(autopilot, observer, station)
        sent = time.monotonic()
        assert station.motor_test(1, PERCENT, 50, timeout_s=2) == DENIED
        time.sleep(1.0)
        assert {t for m in observer.since(sent) if (t := throttles(m))} == {SAFE}
        if text is not None:
            assert text in station.texts()
        else:
            assert not [t for t in station.texts() if "Motor test" in t]
        daemon.stop()
        if text is None:
            assert "refused a motor test from system 99" in daemon.output
    finally:
        station.close()
