"""``esc-bridge plot`` end to end: a real demo flight recorded through the CLI (``demo
--record``), drawn by the CLI, the PNGs read back; the errors a user meets (not a recording, a
missing file, no matplotlib); and no other command loading matplotlib."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import phase_start

from bridge.plot.flight import load_flight
from bridge.plot.recording import find_recordings
from bridge.plot.spans import ARMED

mpl_image = pytest.importorskip(
    "matplotlib.image", reason="matplotlib (the plot extra, in the test extra) is not installed"
)

ESC_BRIDGE = str(Path(sys.executable).parent / "esc-bridge")
TIME_SCALE = 4


def esc_bridge(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [ESC_BRIDGE, *args], capture_output=True, text=True, timeout=timeout, check=False
    )


@pytest.fixture(scope="module", params=["ckesc", "ft", "vesc"])
def recorded(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory holding one recorded demo flight (quad, flown 4 times faster)."""
    directory = tmp_path_factory.mktemp(f"record-{request.param}")
    demo = esc_bridge(
        "demo",
        "--plain",
        "--protocol",
        request.param,
        "--time-scale",
        str(TIME_SCALE),
        "--record",
        str(directory),
        timeout=90,
    )
    assert demo.returncode == 0, demo.stdout[-3000:] + demo.stderr
    assert "flight complete" in demo.stdout
    return directory


# Which recording is drawn, and the refusals, do not depend on the ESC family: one is enough.
ONE_FAMILY = pytest.mark.parametrize("recorded", ["ckesc"], indirect=True)


def test_a_recorded_demo_flight_is_drawn(recorded: Path, tmp_path: Path) -> None:
    (files,) = find_recordings(recorded)
    result = esc_bridge("plot", str(recorded), "--out", str(tmp_path))
    assert result.returncode == 0, result.stdout + result.stderr
    out = tmp_path / f"{files.name}-plot"
    pictures = ["overview.png", "esc-1.png", "esc-2.png", "esc-3.png", "esc-4.png"]
    lines = result.stdout.splitlines()
    assert lines[0].startswith(f"{files.name}: 4 ESCs (") and "1 armed" in lines[0], lines
    assert lines[1:] == [f"  {out / name}" for name in ["index.html", *pictures]]
    for name in pictures:
        pixels = mpl_image.imread(out / name)
        height = 800 if name == "overview.png" else 1100
        assert pixels.shape == (height, 1400, 4), name
        assert pixels.std() > 0.05, name
    page = (out / "index.html").read_text()
    assert all(f'<img src="{name}"' in page for name in pictures)
    assert "ESC out: armed, sending motor commands" in page

    # What was drawn: the flight as the demo flew it.
    flight = load_flight(files)
    (armed,) = flight.spans_of(ARMED)
    flown = (phase_start("disarm") - phase_start("arm")) / TIME_SCALE
    assert armed.end_s - armed.start_s == pytest.approx(flown, abs=0.5)
    for esc in flight.escs:
        assert (esc.rpm.max_abs() or 0) > 1000, esc.title
        assert len(esc.voltage_v) and len(esc.current_a) and esc.temps_c, esc.title
        (unit, commands) = next(iter(esc.commands.items()))
        assert max(commands.values) > 0, (esc.title, unit)
        # None once commanded: a simulated ESC still waiting for its first command when the
        # capture starts says COMMS_FAULT (its 200 ms timeout), as a real one would.
        first_command_s = commands.t_s[0]
        assert [run for run in esc.failures if run.end_s > first_command_s + 0.05] == []


@ONE_FAMILY
def test_the_newest_recording_one_named_or_all(recorded: Path, tmp_path: Path) -> None:
    (files,) = find_recordings(recorded)
    names = ["esc-bridge-20260101-120000", "esc-bridge-20260101-120000-1"]
    for name in names:
        shutil.copy(files.log_path, tmp_path / f"{name}.log")
        shutil.copy(files.tlog_path, tmp_path / f"{name}.tlog")

    def drawn(*args: str) -> list[str]:
        result = esc_bridge("plot", str(tmp_path), *args)
        assert result.returncode == 0, result.stderr
        return [line.split(":")[0] for line in result.stdout.splitlines() if line[:1] != " "]

    assert drawn() == [names[1]]  # the newest: a second recording within the same second
    assert drawn("--recording", f"{names[0]}.log") == [names[0]]
    assert drawn("--all") == names
    assert {p.name for p in tmp_path.glob("*-plot")} == {f"{n}-plot" for n in names}
    result = esc_bridge("plot", str(tmp_path), "--recording", "esc-bridge-20250101-000000")
    assert result.returncode == 2
    assert f"no recording esc-bridge-20250101-000000; it holds {', '.join(names)}" in result.stderr


def test_a_directory_that_is_not_a_recording_is_refused(tmp_path: Path) -> None:
    result = esc_bridge("plot", str(tmp_path))
    assert result.returncode == 2
    assert "not a recording; expected esc-bridge-YYYYmmdd-HHMMSS.log and .tlog" in result.stderr
    result = esc_bridge("plot", str(tmp_path / "absent"))
    assert (result.returncode, result.stderr.strip()) == (
        2,
        f"esc-bridge: recording directory {tmp_path / 'absent'}: no such directory",
    )


@ONE_FAMILY
def test_a_recording_without_its_tlog_is_refused(recorded: Path, tmp_path: Path) -> None:
    (files,) = find_recordings(recorded)
    shutil.copy(files.log_path, tmp_path)
    result = esc_bridge("plot", str(tmp_path))
    assert result.returncode == 2
    assert f"its MAVLink tlog {files.name}.tlog is missing" in result.stderr


@ONE_FAMILY
def test_without_matplotlib_it_says_what_to_install(recorded: Path, tmp_path: Path) -> None:
    # The interpreter refuses to import matplotlib, as one without it installed does.
    code = (
        "import sys; sys.modules['matplotlib'] = None; from bridge.cli import main; "
        f"sys.exit(main(['plot', {str(recorded)!r}, '--out', {str(tmp_path)!r}]))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 1, result.stderr
    assert "pip install 'esc-bridge[plot]'" in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_nothing_but_the_plot_command_imports_matplotlib() -> None:
    code = (
        "import sys; from bridge.cli import build_parser; build_parser(); "
        "import bridge.plot.flight, bridge.plot.page, bridge.daemon.supervisor; "
        "import bridge.demo.system; "
        "print(sorted(m for m in sys.modules if m.startswith('matplotlib')))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert result.stdout.strip() == "[]"


def test_a_recording_is_drawn_from_its_mcap_alone(recorded: Path, tmp_path: Path) -> None:
    (files,) = find_recordings(recorded)
    shutil.copy(files.mcap_path, tmp_path)
    result = esc_bridge("plot", str(tmp_path))
    assert result.returncode == 0, result.stdout + result.stderr
    lines = result.stdout.splitlines()
    assert lines[0].startswith(f"{files.name}: 4 ESCs (") and "1 armed" in lines[0], lines
    assert len(lines) == 7 and (tmp_path / f"{files.name}-plot" / "esc-1.png").is_file()

    # The same flight as its candump log and tlog show it.
    (mcap_files,) = find_recordings(tmp_path)
    from_mcap, from_capture = load_flight(mcap_files), load_flight(files, source="capture")
    assert from_mcap.can.family == from_capture.can.family
    (armed,), (armed_capture,) = from_mcap.spans_of(ARMED), from_capture.spans_of(ARMED)
    assert armed.end_s - armed.start_s == pytest.approx(armed_capture.end_s - armed_capture.start_s)
    for esc, capture in zip(from_mcap.escs, from_capture.escs, strict=True):
        assert esc.motor == esc.node_id == capture.node_id  # the MCAP names motor and ESC
        assert esc.telemetry_frames == capture.telemetry_frames
        # ±1: from erpm the ESC state truncates (int), the capture's series round.
        assert esc.rpm.max_abs() == pytest.approx(capture.rpm.max_abs(), abs=1)
        assert list(esc.commands) == list(capture.commands)
        unit = next(iter(esc.commands))
        assert max(esc.commands[unit].values) == max(capture.commands[unit].values)
    assert [t.text for t in from_mcap.texts] == [t.text for t in from_capture.texts]
    # Asked for a source that is not there: it says which file is missing.
    result = esc_bridge("plot", str(tmp_path), "--source", "capture")
    assert result.returncode == 2 and "its CAN capture" in result.stderr
