"""The endpoints a demo announces on this machine (bridge/monitor/local.py), and a monitor started
without Zenoh settings connecting to them. Each test has its own runtime directory."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ESC_BRIDGE

from bridge.monitor.local import RUNTIME_ENV, announced, announcing, directory


@pytest.fixture(autouse=True)
def runtime_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv(RUNTIME_ENV, str(tmp_path))
    return tmp_path


def dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", ""])
    child.wait()
    return child.pid


def test_an_endpoint_is_announced_while_the_block_runs(runtime_dir: Path) -> None:
    assert directory() == runtime_dir / "esc-bridge" / "listening"
    assert announced() == []
    with announcing("tcp/127.0.0.1:7447"):
        assert (directory() / str(os.getpid())).read_text() == "tcp/127.0.0.1:7447\n"
        assert announced() == ["tcp/127.0.0.1:7447"]
        assert directory().stat().st_mode & 0o777 == 0o700
    assert announced() == []
    assert list(directory().iterdir()) == []


def test_what_a_dead_process_or_another_address_left_is_ignored() -> None:
    with announcing("tcp/127.0.0.1:7447"):
        (directory() / str(dead_pid())).write_text("tcp/127.0.0.1:7448\n")
        (directory() / "1").write_text("tcp/10.0.0.1:7447\n")  # pid 1 runs: but not loopback
        (directory() / "notes").write_text("tcp/127.0.0.1:7449\n")
        assert announced() == ["tcp/127.0.0.1:7447"]


def test_only_loopback_tcp_is_announced() -> None:
    refused = r"expected tcp/127\.0\.0\.1:<port>, got 'tcp/0\.0\.0"
    with pytest.raises(ValueError, match=refused), announcing("tcp/0.0.0.0:7447"):
        pass


def test_a_directory_others_may_write_is_not_read() -> None:
    with announcing("tcp/127.0.0.1:7447"):
        directory().chmod(0o777)
        assert announced() == []


def test_a_directory_that_cannot_be_made_costs_only_the_announcement(runtime_dir: Path) -> None:
    (runtime_dir / "esc-bridge").write_text("a file where the directory would be")
    with announcing("tcp/127.0.0.1:7447"):
        assert announced() == []


def monitor(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [ESC_BRIDGE, "monitor", "--plain", "--duration", "0.5", *args],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
        env=os.environ.copy(),
    )


def test_a_monitor_without_zenoh_settings_connects_to_what_is_announced() -> None:
    # This test's own process announces: it runs, so its announcement counts.
    with announcing("tcp/127.0.0.1:1"):
        found = monitor()
        told = monitor("--connect", "tcp/127.0.0.1:2")
        scouting_off = monitor("--no-multicast-scouting")
    assert found.returncode == 0, found.stderr
    assert found.stderr == (
        "esc-bridge monitor: also connecting to tcp/127.0.0.1:1 (esc-bridge demo on this machine)\n"
    )
    # Told how to reach the bridges, it does only that.
    assert told.returncode == 0 and told.stderr == ""
    assert scouting_off.returncode == 0 and scouting_off.stderr == ""
