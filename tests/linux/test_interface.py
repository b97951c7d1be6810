"""The interface as the system has it: iproute2's own JSON for a real vcan and vxcan (no bit rate),
read by bridge/can_interface.py, and what `run --check` and `run` say about each, up, down and
missing: --check refuses what run refuses, in the same words, with the same exit status."""

from __future__ import annotations

import subprocess
from typing import Any

from bridge.can_interface import assess, parse_ip_link
from linux import guest
from linux.kernel import Kernel


def _check(channel: str) -> dict[str, Any]:
    """``run --check`` on ``channel``: exit status, last line of the plan, the error."""
    done = subprocess.run(
        [guest.ESC_BRIDGE, "run", "--check", "--no-zenoh", "--can-channel", channel],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    guest.LOG.add(f"run --check on {channel} -> {done.returncode}\n{done.stdout}{done.stderr}")
    return {"exit": done.returncode, "last": done.stdout.splitlines()[-1], "error": done.stderr}


def interfaces_as_the_system_has_them() -> dict[str, Any]:
    vcan = guest.vcan()
    vxcan, peer = f"{vcan}x", f"{vcan}y"
    guest.run(["ip", "link", "add", "dev", vxcan, "type", "vxcan", "peer", "name", peer])
    guest.run(["ip", "link", "set", vxcan, "up"])
    guest.run(["ip", "link", "set", peer, "up"])
    found: dict[str, Any] = {"names": (vcan, vxcan)}
    for name in (vcan, vxcan):
        text = guest.run(["ip", "-details", "-json", "link", "show", "dev", name])
        state = parse_ip_link(text, name)
        found[name] = {
            "kind": state.kind, "up": state.up, "bitrate": state.bitrate,
            "can_state": state.can_state, "assessed": assess(state, name, 500_000).text,
            "check": _check(name),
        }  # fmt: skip
    guest.run(["ip", "link", "set", vcan, "down"])
    found["down"] = _check(vcan)
    guest.run(["ip", "link", "delete", vxcan])
    found["missing"] = _check(vxcan)
    run = subprocess.run(
        [guest.ESC_BRIDGE, "run", "--no-zenoh", "--can-channel", vcan],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    found["run down"] = {"exit": run.returncode, "error": run.stderr}
    return found


def test_vcan_and_vxcan_as_ip_reports_them(linux: Kernel) -> None:
    found = linux.call(interfaces_as_the_system_has_them)
    vcan, vxcan = found["names"]
    for name, kind in ((vcan, "vcan"), (vxcan, "vxcan")):
        seen = found[name]
        assert (seen["kind"], seen["up"], seen["bitrate"], seen["can_state"]) == (
            kind, True, None, None
        )  # fmt: skip
        line = (
            f"SocketCAN interface {name}: virtual ({kind}), no bit rate to compare with 500000 "
            "(500 kbit/s); up"
        )
        assert seen["assessed"] == line
        assert seen["check"] == {"exit": 0, "last": f"  {line}", "error": ""}
    # Down: --check prints every check, then refuses as run does.
    down = found["down"]
    assert down["exit"] == 1 == found["run down"]["exit"]
    assert down["last"] == (
        f"  SocketCAN interface {vcan}: virtual (vcan), no bit rate to compare with 500000 "
        "(500 kbit/s); down: run refuses to start"
    )
    assert down["error"] == found["run down"]["error"]
    assert down["error"].startswith(
        f"esc-bridge: error: cannot start: SocketCAN interface {vcan} is down; expected it up: "
        f"`sudo ip link set {vcan} up`"
    )
    missing = found["missing"]
    assert missing["exit"] == 1
    assert missing["last"].endswith("not found on this machine; run refuses to start")
    assert f"SocketCAN interface {vxcan} does not exist" in missing["error"]
