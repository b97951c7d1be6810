"""A failsafe and a failing ESC in a real recording: ``esc-bridge run --record`` with simulated
CKESC ESCs (one reporting over-temperature part-way) and an autopilot that arms, stops sending
its outputs while armed (the bridge's stale-input failsafe), then disarms. The plot shows the
bridge's FAILSAFE report, every ESC stopped while armed, and the ESC's failure flags."""

from __future__ import annotations

import re
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import can
import pytest
from conftest import ESC_BRIDGE, Autopilot, Daemon, Observer, can_args

from bridge.errors import FrameError
from bridge.escs.ckesc import codec
from bridge.escs.family import FAILURE_GENERIC, FAILURE_OVER_TEMPERATURE
from bridge.plot.flight import load_flight
from bridge.plot.recording import find_recordings
from bridge.plot.series import EscSeries
from bridge.plot.spans import ARMED, FAILSAFE, STOPPED_ARMED

mpl_image = pytest.importorskip(
    "matplotlib.image", reason="matplotlib (the plot extra, in the test extra) is not installed"
)

START_TIMEOUT_S = 15.0
FAULT_AT_S = 3.0


def spinning(msg: can.Message) -> bool:
    """A CKESC throttle command with every channel above zero."""
    try:
        frame = codec.decode(msg)
    except FrameError:
        return False
    message = None if frame is None else frame.message
    throttles = getattr(message, "throttles", None)
    return throttles is not None and all(t > 0 for t in throttles)


def first_report_s(esc: EscSeries) -> float:
    """When the ESC's first telemetry in the recording arrived."""
    series = (esc.rpm, esc.voltage_v, esc.current_a, esc.motor_current_a, *esc.temps_c.values())
    return min(s.t_s[0] for s in series if len(s))


def test_a_failsafe_and_a_failing_esc_are_drawn(
    tmp_path: Path,
    can_port: int,
    autopilot: Autopilot,
    observer: Observer,
    start_daemon: Callable[..., Daemon],
) -> None:
    record = tmp_path / "flight"
    sim = subprocess.Popen(
        [
            ESC_BRIDGE,
            "sim",
            "--escs",
            "4",
            "--fault",
            f"2:over_temperature@{FAULT_AT_S}",
            *can_args(can_port),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        started = time.monotonic()
        daemon = start_daemon("--record", str(record))
        autopilot.pwm = [1300] * 4
        autopilot.armed = True
        autopilot.start_stream(50)
        observer.wait_for(spinning, START_TIMEOUT_S)
        time.sleep(max(0.0, FAULT_AT_S + 1.0 - (time.monotonic() - started)))
        autopilot.pause_outputs()  # armed, no outputs: stale input, the bridge stops the motors
        time.sleep(1.5)
        autopilot.armed = False
        time.sleep(1.0)
        assert daemon.stop() == 0, daemon.output[-2000:]
    finally:
        sim.terminate()
        sim.wait(10)

    (files,) = find_recordings(record)
    flight = load_flight(files)
    (armed,) = flight.spans_of(ARMED)
    # The pause's failsafe is the last; on a loaded machine this test's autopilot thread may
    # also have stalled past the input timeout earlier, which the bridge rightly reported too.
    failsafes = flight.spans_of(FAILSAFE)
    failsafe = failsafes[-1]
    assert all(armed.start_s < f.start_s <= f.end_s <= armed.end_s + 0.5 for f in failsafes)
    assert failsafe.label == "FAILSAFE input stale, motors stopped"
    assert armed.start_s < failsafe.start_s < armed.end_s
    assert failsafe.end_s == pytest.approx(armed.end_s, abs=0.5)  # until the disarm's report
    stops = flight.spans_of(STOPPED_ARMED)
    assert any(s.start_s < failsafe.start_s + 0.5 and s.end_s > failsafe.end_s - 0.5 for s in stops)
    # Besides ESC 2's over-temperature, an ESC may have said "no command received" (generic)
    # for a few ms in its first reports, before it read the bridge's first command (0.81-0.83 s
    # into a recording at load 8; in CI 0.40-0.42 s, after the arming, the bridge's commands on
    # the bus since its start): a generic run from the ESC's first report that ended while the
    # bridge still commanded (before the pause's failsafe) is that. One later, or one that never
    # ended, is a failure.
    failing = {
        esc.node_id: [
            r
            for r in esc.failures
            if not (
                r.flags == FAILURE_GENERIC
                and r.start_s <= first_report_s(esc)
                and r.end_s < failsafe.start_s
            )
        ]
        for esc in flight.escs
    }
    # What told the runs apart, for a failure's message.
    when = {
        "armed": armed.start_s,
        "failsafe": failsafe.start_s,
        **{f"ESC {esc.node_id}'s first report": first_report_s(esc) for esc in flight.escs},
    }
    told = f"{failing}; {when}"
    assert failing[2] and all(r.flags & FAILURE_OVER_TEMPERATURE for r in failing[2]), told
    assert not failing[1] and not failing[3] and not failing[4], told

    result = subprocess.run(
        [ESC_BRIDGE, "plot", str(record)], capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 0, result.stderr
    assert f"{len(failsafes)} failsafe" in result.stdout and "1 armed" in result.stdout
    picture = record / f"{files.name}-plot" / "esc-2.png"
    assert mpl_image.imread(picture).shape == (1100, 1400, 4)
    page = (record / f"{files.name}-plot" / "index.html").read_text()
    # The page names every flag an ESC raised, a "generic" before the first command included.
    failures = re.findall(r'<span class="bad">([^<]*) \(from [\d.]+ s\)</span>', page)
    assert any("over temperature" in names.split(", ") for names in failures), failures
