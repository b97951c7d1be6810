"""A failsafe and a failing ESC in a real recording: ``esc-bridge run --record`` with simulated
CKESC ESCs (one reporting over-temperature part-way) and an autopilot that arms, stops sending
its outputs while armed (the bridge's stale-input failsafe), then disarms. The plot shows the
bridge's FAILSAFE report, every ESC stopped while armed, and the ESC's failure flags."""

from __future__ import annotations

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
    # for a few ms at the start, before the bridge's first command reached it (0.81-0.83 s into
    # a recording at load 8): a generic run that began before the arming is that.
    failing = {
        esc.node_id: [
            r
            for r in esc.failures
            if not (r.flags == FAILURE_GENERIC and r.start_s < armed.start_s)
        ]
        for esc in flight.escs
    }
    assert failing[2] and all(r.flags & FAILURE_OVER_TEMPERATURE for r in failing[2]), failing
    assert not failing[1] and not failing[3] and not failing[4], failing

    result = subprocess.run(
        [ESC_BRIDGE, "plot", str(record)], capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 0, result.stderr
    assert f"{len(failsafes)} failsafe" in result.stdout and "1 armed" in result.stdout
    picture = record / f"{files.name}-plot" / "esc-2.png"
    assert mpl_image.imread(picture).shape == (1100, 1400, 4)
    page = (record / f"{files.name}-plot" / "index.html").read_text()
    assert "over temperature (from" in page
