"""ArduPilot learns the ESCs' telemetry from the bridge: ``autopilot/ardupilot/esc-bridge.lua``
in a real ArduCopter SITL.

What runs (loopback only, see conftest.py): ArduCopter SITL (quad, real time) with
``SIM_ESC_TELEM 0`` (no ESC data of its own), ``SCR_ENABLE 1`` and the script in its
``scripts/`` directory, the harmonic notch on ESC rpm (``INS_HNTCH_ENABLE 1``,
``INS_HNTCH_MODE 3``, ``INS_HNTCH_REF 1``) and logging while disarmed (``LOG_DISARMED 1``: the
run is motor tests, which need no GPS lock); one CKESC bridge on SERIAL1 sending
ESC_TELEMETRY_1_TO_4 to the autopilot at the rate under test (``[mavlink]
autopilot_messages``: docs/telemetry.md's 10 Hz, and the 2 Hz the bridge picks for ArduPilot by
default), four simulated ESCs and an observer on its CAN bus; a ground station on SERIAL0
asking ArduCopter for its own ESC_TELEMETRY_1_TO_4 at 10 Hz. The module-scoped ``run``
fixture (about 15 s per rate) does:

1. waits for the script's "ESCB: ESC telemetry from 1/191" (it fed ArduPilot);
2. ArduCopter's motor test at :data:`LOW_PERCENT` for 3 s, then at :data:`HIGH_PERCENT` for
   3 s on the same motor: the rpm the ESCs report steps up, down and up again;
3. during the second test stops the simulated ESCs (all fall silent at once): the bridge goes
   on sending, their frame counters frozen;
4. stops ArduCopter and reads its dataflash log (``logs/*.BIN``, pymavlink).

Each test then checks one thing against what the CAN bus carried: ArduCopter's own
ESC_TELEMETRY_1_TO_4 (from 1/1), its log's ESC records, the notch's tracked frequency (log
FTNS), and the staleness after the silence. Times are compared on our monotonic clock: the
autopilot's boot time maps onto it by the least (receive time - ``time_boot_ms``) of its
SYSTEM_TIME messages, and its simulated clock's drift from ours over the run widens the log's
windows.
"""

from __future__ import annotations

import contextlib
import shutil
import statistics
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from conftest import ROOT, free_port
from pymavlink import mavutil

from bridge.errors import CodecError
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records

from .conftest import (
    ARDUPILOT_SERIAL_PORTS,
    ARDUPILOT_UDP_PORTS,
    ArduCopter,
    ArduCopterBuild,
    GroundStation,
    Process,
    from_autopilot,
    mavlink,
    measured,
    reserved_instance,
    start_bridge,
    start_sim,
    udp_drops,
    wide_observer,
)

SCRIPT = ROOT / "autopilot" / "ardupilot" / "esc-bridge.lua"
RATES_HZ = (10.0, 2.0)
"""ESC_TELEMETRY_1_TO_4 on the autopilot link: docs/telemetry.md's setting for the script, and the
bridge's default for ArduPilot."""
AP_TELEMETRY_HZ = 10.0
"""ArduCopter's own ESC_TELEMETRY_1_TO_4, asked on the ground station's link."""
NOTCH_REF = 1.0
LOW_PERCENT, HIGH_PERCENT = 20.0, 50.0
TEST_S = 3.0
# The simulated CKESC's report periods: Msg1 (rpm) at 50 Hz, Msg2 (volts, amps, °C) at 10 Hz.
MSG1_PERIOD_S, MSG2_PERIOD_S = 0.02, 0.1
# The bus's and the ground station's stamps are taken on one clock by two processes; a loaded
# 2-core machine may hold a packet a few ms before either sees it.
SLACK_S = 0.05
# ArduPilot judges an ESC's rpm stale 1 s after its last update (ESC_RPM_DATA_TIMEOUT_US).
AP_RPM_TIMEOUT_S = 1.0
FTNS_PERIOD_S = 0.1  # ArduCopter logs the notch at 10 Hz

pytestmark = pytest.mark.sitl


@dataclass(frozen=True)
class BusSample:
    """One ESC's telemetry as the bus carried it: rpm from CKESC Msg1, volts, amps and °C from
    Msg2."""

    t: float
    esc: int  # 0-based
    rpm: int | None = None
    voltage_v: float | None = None
    current_a: float | None = None
    temp_c: int | None = None


@dataclass
class Run:
    rate_hz: float
    ap: ArduCopter
    gcs: GroundStation
    bridge: Process
    bus: list[BusSample] = field(default_factory=list)
    events: dict[str, float] = field(default_factory=dict)
    log: list[Any] = field(default_factory=list)
    boot_offset_s: float = 0.0
    """Our monotonic time = the autopilot's boot time + this."""
    drift_s: float = 0.0
    """How far the autopilot's clock fell behind ours over the run."""
    observer_drops: int = 0
    test_motor: int = -1

    @property
    def period_s(self) -> float:
        return 1 / self.rate_hz

    def from_boot(self, time_us: int) -> float:
        return time_us / 1e6 + self.boot_offset_s

    def values(self, esc: int, kind: str, start: float, end: float) -> list[Any]:
        """The bus's ``kind`` values of ``esc`` in [start, end], and the last one before."""
        before: list[Any] = []
        inside = []
        for s in self.bus:
            value = getattr(s, kind)
            if s.esc != esc or value is None or s.t > end:
                continue
            if s.t < start:
                before = [value]
            else:
                inside.append(value)
        return before + inside

    def last_frame(self) -> float:
        return max(s.t for s in self.bus)

    def ap_telemetry(
        self, start: float = 0.0, end: float = float("inf")
    ) -> list[tuple[float, Any]]:
        """ArduCopter's own ESC_TELEMETRY_1_TO_4 (from 1/1) received in [start, end]."""
        return [
            (t, m)
            for t, m in self.gcs.received("ESC_TELEMETRY_1_TO_4", start)
            if from_autopilot(m) and t <= end
        ]

    def ap_telemetry_sent(self, after_boot_s: float) -> list[tuple[float, float, Any]]:
        """ArduCopter's own ESC_TELEMETRY_1_TO_4 sent after ``after_boot_s`` on its boot clock,
        each with the span of that clock it was sent in: from the SYSTEM_TIME the autopilot sent
        before it to the one after (both streamed at 10 Hz on the same link, so in the order
        sent). On the autopilot's own clock, not the ground station's receive times, which a
        loaded machine may hold up and bunch."""
        sent: list[tuple[float, float, Any]] = []
        before_s: float | None = None
        waiting: list[Any] = []
        for _, m in self.gcs.received():
            if not from_autopilot(m):
                continue
            if m.get_type() == "SYSTEM_TIME":
                now_s = m.time_boot_ms / 1000
                sent.extend((before_s, now_s, w) for w in waiting if before_s is not None)
                before_s, waiting = now_s, []
            elif m.get_type() == "ESC_TELEMETRY_1_TO_4" and (before_s or 0.0) >= after_boot_s:
                waiting.append(m)
        return sent

    def log_records(self, kind: str, start: float = 0.0, end: float = float("inf")) -> list[Any]:
        return [
            m for m in self.log if m.get_type() == kind and start <= self.from_boot(m.TimeUS) <= end
        ]


def decode_bus(frames: list[tuple[float, Any]]) -> list[BusSample]:
    out = []
    for t, msg in sorted(frames, key=lambda f: f[0]):
        with contextlib.suppress(CodecError):
            frame: Any = ckesc_codec.decode(msg)
            if frame is None:
                continue
            rec = frame.message
            if isinstance(rec, ckesc_records.Msg1):
                out.append(BusSample(t, frame.node_id - 1, rpm=rec.speed_rpm))
            elif isinstance(rec, ckesc_records.Msg2):
                out.append(
                    BusSample(
                        t,
                        frame.node_id - 1,
                        voltage_v=rec.voltage_v,
                        current_a=rec.current_a,
                        temp_c=rec.mos_temp_c,
                    )
                )
    return out


def read_log(workdir: Path) -> list[Any]:
    """Every message of the newest dataflash log ArduCopter wrote in ``workdir``."""
    logs = sorted((workdir / "logs").glob("*.BIN"), key=lambda p: p.stat().st_mtime)
    assert logs, f"no dataflash log in {workdir / 'logs'}"
    reader: Any = mavutil.mavlink_connection(str(logs[-1]))
    out: list[Any] = []
    while True:
        msg = reader.recv_msg()
        if msg is None:
            return out
        out.append(msg)


def motor_test(gcs: GroundStation, percent: float, seconds: float) -> float:
    sent = gcs.send_command(
        mavlink.MAV_CMD_DO_MOTOR_TEST,
        1,
        mavlink.MOTOR_TEST_THROTTLE_PERCENT,
        percent,
        seconds,
        0,
        mavlink.MOTOR_TEST_ORDER_BOARD,
    )
    result = gcs.ack(mavlink.MAV_CMD_DO_MOTOR_TEST, sent)
    assert result == mavlink.MAV_RESULT_ACCEPTED, f"motor test at {percent} % refused: {result}"
    return sent


def fly(run: Run, sim: Process) -> None:
    gcs, e = run.gcs, run.events
    gcs.wait_for(
        "STATUSTEXT",
        lambda m: "ESCB: ESC telemetry from" in m.text,
        40,
        what="the script's first fresh ESC telemetry",
    )
    e["fed"] = time.monotonic()
    for msg_id, hz in ((mavlink.MAVLINK_MSG_ID_ESC_TELEMETRY_1_TO_4, AP_TELEMETRY_HZ), (2, 10)):
        sent = gcs.send_command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
        assert gcs.ack(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, sent) == mavlink.MAV_RESULT_ACCEPTED
    time.sleep(1.5)  # at rest: every ESC at 0 rpm
    e["low"] = motor_test(gcs, LOW_PERCENT, TEST_S)
    time.sleep(TEST_S + 1.0)
    e["high"] = motor_test(gcs, HIGH_PERCENT, TEST_S)
    time.sleep(TEST_S - 0.8)
    e["silence"] = time.monotonic()
    sim.stop()
    time.sleep(AP_RPM_TIMEOUT_S + 2 * run.period_s + 0.8)
    e["end"] = time.monotonic()


@pytest.fixture(scope="module", params=RATES_HZ, ids=lambda hz: f"{hz:g}Hz")
def run(
    request: pytest.FixtureRequest,
    arducopter_build: ArduCopterBuild,
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[Run]:
    rate_hz: float = request.param
    workdir: Path = tmp_path_factory.mktemp(f"arducopter-lua-{rate_hz:g}hz")
    (workdir / "scripts").mkdir()
    shutil.copy(SCRIPT, workdir / "scripts" / SCRIPT.name)
    with contextlib.ExitStack() as stack:
        instance = stack.enter_context(
            reserved_instance(ARDUPILOT_SERIAL_PORTS, ARDUPILOT_UDP_PORTS)
        )
        params = {
            "SIM_ESC_TELEM": 0,
            "SCR_ENABLE": 1,
            "INS_HNTCH_ENABLE": 1,
            "INS_HNTCH_MODE": 3,
            "INS_HNTCH_REF": NOTCH_REF,
            "LOG_DISARMED": 1,
        }
        ap = ArduCopter(arducopter_build, workdir, instance, params)
        stack.callback(ap.stop)
        can_port = free_port()
        observer = wide_observer(can_port)
        stack.callback(observer.close)
        sim = start_sim(can_port, workdir / "sim.log", "ckesc")
        stack.callback(sim.stop)
        config = workdir / "bridge.toml"
        config.write_text(
            "[mavlink]\n"
            f"autopilot_messages = {{ esc_telemetry = {rate_hz:g} }}\n"
            '[output]\nprotocol = "ckesc"\n'
            '[mixer]\nname = "passthrough-4"\n[escs]\nids = [1, 2, 3, 4]\n'
        )
        bridge = start_bridge(
            config, f"tcp:127.0.0.1:{ap.port(1)}", can_port, workdir / "bridge.log"
        )
        stack.callback(bridge.stop)
        ap.start()
        gcs = GroundStation(f"tcp:127.0.0.1:{ap.port(0)}")
        stack.callback(gcs.close)
        result = Run(rate_hz, ap, gcs, bridge)
        result.events["start"] = time.monotonic()
        try:
            fly(result, sim)
        except Exception as exc:
            logs = "\n".join(
                f"--- {p.log_path.name} ---\n{p.tail(15)}"
                for p in (bridge, sim, ap.process)
                if p is not None
            )
            raise AssertionError(f"the run failed: {exc}\n{logs}") from exc
        finally:
            ap.stop()
            bridge.stop()
            result.observer_drops = udp_drops(observer.bus)
            with observer._lock:
                frames = list(observer.frames)
        result.bus = decode_bus(frames)
        result.log = read_log(workdir)
        offsets = [
            t - m.time_boot_ms / 1000 for t, m in gcs.received("SYSTEM_TIME") if from_autopilot(m)
        ]
        assert offsets, "no SYSTEM_TIME from the autopilot"
        result.boot_offset_s = min(offsets)
        result.drift_s = max(offsets) - min(offsets)
        spun = {s.esc for s in result.bus if s.rpm and s.t > result.events["low"]}
        assert len(spun) == 1, f"the motor tests spun ESCs {sorted(spun)}"
        result.test_motor = spun.pop()
        measured(
            f"ArduCopter + esc-bridge.lua at {rate_hz:g} Hz: run",
            f"{result.events['end'] - result.events['start']:.1f} s, the autopilot's clock "
            f"{result.drift_s * 1000:.0f} ms behind at most",
        )
        yield result


# --------------------------------------------------------------------------------------------
# The checks


def ms(seconds: float) -> str:
    return f"{seconds * 1000:.0f} ms"


def between(value: float, seen: list[Any], tolerance: float) -> bool:
    """``value`` lies within [min, max] of ``seen``, give or take ``tolerance``."""
    return bool(seen) and min(seen) - tolerance <= value <= max(seen) + tolerance


def near_any(value: float, seen: list[Any], tolerance: float) -> bool:
    return any(abs(value - v) <= tolerance for v in seen)


def test_bus_observed_whole(run: Run) -> None:
    """The observer lost no frame: the bus record the other tests judge by is complete."""
    assert run.observer_drops == 0, f"the observer's socket dropped {run.observer_drops} frames"
    assert run.bus, "no ESC telemetry on the bus"


def test_autopilot_reports_the_escs(run: Run) -> None:
    """ArduCopter's own ESC_TELEMETRY_1_TO_4 (from 1/1, SIM_ESC_TELEM 0) carries every
    simulated ESC's rpm, volts, amps and temperature as the bus had them within one of the
    bridge's update periods: volts, amps and °C a value of the last period (plus the ESC's
    own 100 ms report period), the rpm between the values of the last two periods (ArduPilot
    slews the rpm from the previous update to the newest over one update period)."""
    e, period = run.events, run.period_s
    received = run.ap_telemetry(e["fed"] + 2 * period + 0.2, e["silence"])
    expected = (e["silence"] - e["fed"] - 2 * period - 0.2) * AP_TELEMETRY_HZ
    assert len(received) >= 0.8 * expected, (
        f"{len(received)} ESC_TELEMETRY_1_TO_4 from ArduCopter, ~{expected:.0f} expected"
    )
    wrong = []
    spinning = 0
    for t, msg in received:
        for m in range(4):
            # A SITL that fell behind sends what it knew that much later.
            early = run.drift_s + SLACK_S
            rpms = run.values(m, "rpm", t - 2 * period - MSG1_PERIOD_S - early, t + SLACK_S)
            start = t - period - MSG2_PERIOD_S - early
            volts = [round(v * 100) for v in run.values(m, "voltage_v", start, t + SLACK_S)]
            amps = [round(a * 100) for a in run.values(m, "current_a", start, t + SLACK_S)]
            temps = run.values(m, "temp_c", start, t + SLACK_S)
            spinning += msg.rpm[m] > 1000
            checks = (
                ("rpm", msg.rpm[m], between(msg.rpm[m], rpms, 1), rpms),
                ("cV", msg.voltage[m], near_any(msg.voltage[m], volts, 1), volts),
                ("cA", msg.current[m], near_any(msg.current[m], amps, 1), amps),
                ("°C", msg.temperature[m], msg.temperature[m] in temps, temps),
            )
            for unit, got, ok, bus in checks:
                if not ok:
                    wrong.append(
                        f"t={t - e['start']:.2f} s ESC {m + 1}: {got} {unit}, "
                        f"the bus {sorted(set(bus))}"
                    )
    assert spinning >= 2 * TEST_S * AP_TELEMETRY_HZ * 0.6, "the motor tests hardly showed"
    assert not wrong, f"{len(wrong)} values off the bus:\n" + "\n".join(wrong[:10])
    measured(
        f"ArduCopter + esc-bridge.lua at {run.rate_hz:g} Hz: ESC_TELEMETRY from 1/1",
        f"{len(received)} messages, every rpm/cV/cA/°C as on the bus within one update",
    )


def test_dataflash_log_holds_the_esc_records(run: Run) -> None:
    """ArduCopter's log has an ESC record per update of each ESC (at the bridge's rate), whose
    raw rpm, volts, amps and °C are the bus's within the bridge's update period."""
    e, period = run.events, run.period_s
    late = run.drift_s + SLACK_S
    for m in range(4):
        records = [
            r for r in run.log_records("ESC", e["fed"] + 0.2, e["silence"]) if r.Instance == m
        ]
        expected = (e["silence"] - e["fed"] - 0.2) * run.rate_hz
        # One record per update, or two when ArduPilot logs between the script's rpm and its
        # other values.
        assert 0.8 * expected <= len(records) <= 2 * expected + 2, (
            f"ESC {m + 1}: {len(records)} ESC records in the log, ~{expected:.0f} expected"
        )
        wrong = []
        for r in records:
            t = run.from_boot(r.TimeUS)
            rpms = run.values(m, "rpm", t - period - MSG1_PERIOD_S - SLACK_S, t + late)
            start = t - period - MSG2_PERIOD_S - SLACK_S
            volts = run.values(m, "voltage_v", start, t + late)
            amps = run.values(m, "current_a", start, t + late)
            temps = run.values(m, "temp_c", start, t + late)
            if not (
                near_any(r.RawRPM, rpms, 0.5)
                and near_any(r.Volt, volts, 0.006)
                and near_any(r.Curr, amps, 0.006)
                and near_any(r.Temp, temps, 0.01)
            ):
                wrong.append(
                    f"t={t - e['start']:.2f} s: RawRPM {r.RawRPM:g} Volt {r.Volt:.2f} Curr "
                    f"{r.Curr:.2f} Temp {r.Temp:g}; the bus: rpm {sorted(set(rpms))}, V "
                    f"{sorted(set(volts))}, A {sorted(set(amps))}, °C {sorted(set(temps))}"
                )
        assert not wrong, f"ESC {m + 1}: {len(wrong)} records off the bus:\n" + "\n".join(wrong[:8])
    mine = [r for r in run.log_records("ESC") if r.Instance == run.test_motor]
    assert max(r.RawRPM for r in mine) > 5000, "the log never saw the tested motor spin"


def steady(run: Run, start: float, end: float) -> tuple[float, list[Any]]:
    """The mean rpm of the four ESCs on the bus in [start, end] (each steady there: the motor
    tests' steady state) and the log's FTNS records of the first notch in it."""
    means = []
    for m in range(4):
        rpms = run.values(m, "rpm", start, end)[1:]
        assert rpms and max(rpms) - min(rpms) <= 0.01 * max(rpms) + 1, (
            f"ESC {m + 1} not steady in the window: "
            f"{min(rpms, default=None)}..{max(rpms, default=None)} rpm"
        )
        means.append(statistics.fmean(rpms))
    notch = [r for r in run.log_records("FTNS", start, end) if r.I == 0]
    assert len(notch) >= (end - start) / FTNS_PERIOD_S * 0.7, f"{len(notch)} FTNS records"
    return statistics.fmean(means), notch


def test_notch_follows_the_rpm(run: Run) -> None:
    """With INS_HNTCH_MODE 3 the notch's tracked (fundamental) frequency in the log is the
    ESCs' mean rpm / 60 x INS_HNTCH_REF in each steady phase of the motor tests, and steps with
    the rpm: up to the first test's, down at its end, up to the second's, within the bridge's
    update period, the slew over the next and the log's 10 Hz."""
    e, period = run.events, run.period_s
    phases = {
        "low": (e["low"] + 1.2, e["low"] + TEST_S - 0.2),
        "high": (e["high"] + 1.2, e["silence"] - 0.05),
    }
    tracked = {}
    for name, (start, end) in phases.items():
        rpm_mean, notch = steady(run, start, end)
        want = rpm_mean / 60 * NOTCH_REF
        off = [r.NF for r in notch if abs(r.NF - want) > 0.01 * want + 0.05]
        assert not off, f"{name}: notch {off[:5]} Hz, mean rpm {rpm_mean:.0f} gives {want:.2f} Hz"
        tracked[name] = (rpm_mean, want)
    # The steps: from when the bus's mean rpm passed half-way to the new steady value to when
    # the logged notch did.
    bound = 2 * period + MSG1_PERIOD_S + FTNS_PERIOD_S + run.drift_s + SLACK_S
    low, high = tracked["low"][1], tracked["high"][1]
    lags = []
    for name, since, until, f0, f1 in (
        ("up", e["low"], e["low"] + TEST_S - 0.2, 0.0, low),
        ("down", e["low"] + TEST_S - 0.2, e["high"], low, 0.0),
        ("up again", e["high"], e["silence"], 0.0, high),
    ):
        halfway = (f0 + f1) / 2

        def crossed(f: float, halfway: float = halfway, rising: bool = f1 > f0) -> bool:
            return f >= halfway if rising else f <= halfway

        bus_t = next(t for t, rpm in mean_rpm(run, since, until) if crossed(rpm / 60 * NOTCH_REF))
        notch = [r for r in run.log_records("FTNS", since, until + bound) if r.I == 0]
        log_t = next((run.from_boot(r.TimeUS) for r in notch if crossed(r.NF)), float("inf"))
        lags.append((name, log_t - bus_t))
    measured(
        f"ArduCopter + esc-bridge.lua at {run.rate_hz:g} Hz: notch",
        f"{tracked['low'][1]:.2f} Hz at {tracked['low'][0]:.0f} rpm mean, "
        f"{tracked['high'][1]:.2f} Hz at {tracked['high'][0]:.0f}; half-way "
        + ", ".join(f"{name} {ms(lag)}" for name, lag in lags)
        + " after the bus",
    )
    assert tracked["high"][1] > 2 * tracked["low"][1]
    late = [f"{name} {ms(lag)}" for name, lag in lags if lag > bound]
    assert not late, f"the notch followed the rpm late: {late} (bound {ms(bound)})"


def mean_rpm(run: Run, start: float, end: float) -> list[tuple[float, float]]:
    """(time, the mean of the four ESCs' latest rpm on the bus) at each Msg1 in [start, end]."""
    latest = [0, 0, 0, 0]
    out = []
    for s in run.bus:
        if s.rpm is None or s.t > end:
            continue
        latest[s.esc] = s.rpm
        if s.t >= start:
            out.append((s.t, statistics.fmean(latest)))
    return out


def test_silent_escs_go_stale(run: Run) -> None:
    """The simulated ESCs stopped: the bridge goes on sending ESC_TELEMETRY_1_TO_4 with the
    frame counters frozen, so the script feeds ArduPilot nothing more. ArduPilot's counters
    stop, its log gets no more ESC records, and the spinning ESC's rpm stays at its last value
    until ArduPilot's own 1 s timeout makes it stale (0 in ESC_TELEMETRY), as with its own
    drivers; the script says so once."""
    e, period = run.events, run.period_s
    last = run.last_frame()
    assert e["silence"] <= last + 0.5, "the bus went on after the ESCs were stopped"
    bridge = [
        m
        for t, m in run.gcs.received("ESC_TELEMETRY_1_TO_4", last + period + SLACK_S)
        if m.get_srcComponent() == 191
    ]
    assert len(bridge) >= 2, "the bridge stopped sending when its ESCs fell silent"
    assert len({tuple(m.count) for m in bridge}) == 1, "the bridge's counters moved"
    fed_until = last + period + SLACK_S
    after = run.ap_telemetry(fed_until + 1 / AP_TELEMETRY_HZ)
    assert after, "no ESC_TELEMETRY from ArduCopter after the silence"
    # The script's last update may reach ArduCopter's ESC_TELEMETRY a quarter second later on a
    # loaded machine (one more count came in a CI run beside two busy processes).
    settled = [m for t, m in after if t >= fed_until + 0.25 + 1 / AP_TELEMETRY_HZ]
    assert len({tuple(m.count) for m in settled}) == 1, "ArduCopter's ESC counters moved on"
    # The rpm's hold and timeout on ArduPilot's clock: from its last ESC record of the motor
    # (logged as an update arrives), to what it sent before and after a second had passed.
    motor = run.test_motor
    updated_s = max(r.TimeUS / 1e6 for r in run.log_records("ESC") if r.Instance == motor)
    sent = run.ap_telemetry_sent(updated_s)
    held = [m.rpm[motor] for _, end_s, m in sent if end_s <= updated_s + AP_RPM_TIMEOUT_S - 0.1]
    assert held and min(held) > 5000, f"the rpm was not held until the timeout: {held}"
    stale = [
        m.rpm[motor] for start_s, _, m in sent if start_s >= updated_s + AP_RPM_TIMEOUT_S + SLACK_S
    ]
    assert stale and all(rpm == 0 for rpm in stale), (
        f"ESC {motor + 1}'s rpm after ArduPilot's timeout: {stale[:10]}"
    )
    went = next(t for t, m in after if m.rpm[motor] == 0)
    records = run.log_records("ESC", fed_until + run.drift_s + SLACK_S)
    assert not records, f"{len(records)} ESC records logged after the silence"
    texts = [m.text for _, m in run.gcs.received("STATUSTEXT", e["silence"])]
    assert "ESCB: no fresh ESC telemetry for 1 s" in texts, texts
    measured(
        f"ArduCopter + esc-bridge.lua at {run.rate_hz:g} Hz: stale",
        f"rpm 0 in ArduCopter's ESC_TELEMETRY {ms(went - last)} after the last ESC frame",
    )
