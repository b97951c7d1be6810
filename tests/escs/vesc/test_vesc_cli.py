"""``esc-bridge esc vesc-scan`` against simulated VESCs: in this process (``main``) on a
``virtual`` channel of its own, then the console script against ``esc-bridge sim`` on
udp_multicast."""

from __future__ import annotations

import itertools
import json
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from conftest import ESC_BRIDGE, Daemon, can_args, free_port

from bridge.cli import main
from bridge.escs.vesc.records import Packet
from bridge.escs.vesc.sim import STATUS_1_TO_5, SimVesc
from bridge.sim.runner import Simulator

_channels = itertools.count()


@pytest.fixture
def channel() -> Iterator[str]:
    name = f"vesc-cli-{next(_channels)}"
    keep = can.Bus(interface="virtual", channel=name)  # the channel lives while a handle does
    yield name
    keep.shutdown()


def simulate(channel: str, *escs: SimVesc) -> Simulator:
    bus = can.Bus(interface="virtual", channel=channel)
    return Simulator(bus, escs, own_bus=True, name=f"sim-{channel}").start()


def scan(channel: str, *extra: str) -> list[str]:
    return ["esc", "vesc-scan", "--can-interface", "virtual", "--can-channel", channel, *extra]


def test_every_vesc_and_its_status_frames(channel: str, capsys: pytest.CaptureFixture[str]) -> None:
    with simulate(channel, SimVesc(3, status=STATUS_1_TO_5), SimVesc(17, status=STATUS_1_TO_5)):
        code = main(scan(channel, "--listen", "0.3"))
    out, err = capsys.readouterr()
    assert (code, err) == (0, "")
    assert out == (
        "  id  type        status frames\n"
        "   3  VESC        STATUS, STATUS_2, STATUS_3, STATUS_4, STATUS_5\n"
        "  17  VESC        STATUS, STATUS_2, STATUS_3, STATUS_4, STATUS_5\n"
        "2 VESCs answered.\n"
    )


def test_a_vesc_with_its_status_frames_off_is_named_with_the_setting(
    channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with simulate(channel, SimVesc(3, status=STATUS_1_TO_5), SimVesc(4)):
        code = main(scan(channel, "--listen", "0.3", "--host-id", "200", "--json"))
    out, _ = capsys.readouterr()
    assert code == 1
    result = json.loads(out)
    assert result["vescs"] == [
        {
            "controller_id": 3,
            "hw_type": "VESC",
            "answers": 1,
            "status": [Packet(p).name for p in sorted(STATUS_1_TO_5)],
        },
        {"controller_id": 4, "hw_type": "VESC", "answers": 1, "status": []},
    ]
    (warning,) = result["warnings"]
    assert warning.startswith("VESC 4: sends no status frames: turn them on in VESC Tool: ")
    assert "Can Messages Rate 1: Status 1 to 5" in warning


def test_no_answer_is_exit_1_naming_what_to_check(
    channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(scan(channel, "--listen", "0.05")) == 1
    _, err = capsys.readouterr()
    assert err.startswith("esc-bridge: error: no VESC answered a PING to IDs 0..254: are the")


@pytest.mark.parametrize(
    ("flags", "match"),
    [
        (["--host-id", "255"], "--host-id: expected a VESC ID 0..254, got '255'"),
        (["--listen", "0"], "--listen: expected seconds, above 0 and at most 60, got '0'"),
    ],
)
def test_bad_arguments_are_exit_2(
    channel: str, flags: list[str], match: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(scan(channel, *flags))
    assert exit_info.value.code == 2
    assert match in capsys.readouterr().err


def run_scan(port: int, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [ESC_BRIDGE, "esc", "vesc-scan", *can_args(port), "--json", *extra],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )


def scanned(port: int, count: int, *extra: str) -> tuple[int, Any]:
    """The scan once ``count`` VESCs answer it (the simulator process needs a moment)."""
    deadline = time.monotonic() + 15.0
    while True:
        result = run_scan(port, *extra)
        if result.returncode in (0, 1) and result.stdout:
            found = json.loads(result.stdout)
            if len(found["vescs"]) == count or time.monotonic() > deadline:
                return result.returncode, found
        assert time.monotonic() < deadline, result.stderr


def test_console_script_scans_simulated_vescs(tmp_path: Path) -> None:
    port = free_port()
    sim = Daemon(["sim", *can_args(port), "--protocol", "vesc", "--ids", "1,2,3,4"])
    try:
        code, found = scanned(port, 4)
        assert code == 0 and found["warnings"] == []
        assert [v["controller_id"] for v in found["vescs"]] == [1, 2, 3, 4]
        assert all(len(v["status"]) == 5 for v in found["vescs"])
    finally:
        assert sim.stop() == 0, sim.output
    # VESCs as from the factory: no status frames.
    config = tmp_path / "factory.toml"
    config.write_text('[output]\nprotocol = "vesc"\n[escs]\nids = [7]\nvesc_status_hz = 0\n')
    port = free_port()
    sim = Daemon(["sim", *can_args(port), "--config", str(config)])
    try:
        code, found = scanned(port, 1)
        assert code == 1 and found["vescs"][0]["status"] == []
        assert found["warnings"][0].startswith("VESC 7: sends no status frames")
    finally:
        assert sim.stop() == 0, sim.output
