"""``esc-bridge monitor --web`` in a real browser: headless Chromium (Debian's chromium and
chromium-driver) reads the page while real bridges publish.

Two bridges (``esc-bridge run``, vehicles alpha and beta) each drive four simulated ESCs
(``esc-bridge sim``) for an autopilot of this test at different throttles; motor 2 of alpha
reports over-temperature and motor 3 of beta is silent. The page must show both vehicles with
the rpm each bridge publishes (this test subscribes to them too), the failure and the offline
ESC standing out, the charts drawn, a phone's width without sideways scrolling, and beta's
card stale once its bridge stops. ``esc-bridge demo`` with a plain ``esc-bridge monitor --web``
beside it is the README's line.

``ESC_BRIDGE_SCREENSHOT=1`` makes the first test write docs/web-monitor.png (the picture in
docs/telemetry.md); without it the tree is left alone.
"""

from __future__ import annotations

import json
import os
import re
import select
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from browser import INSTALL, Browser, find_browser
from conftest import ESC_BRIDGE, ROOT, Autopilot, Daemon, can_args, free_port

SCREENSHOT_ENV = "ESC_BRIDGE_SCREENSHOT"
SCREENSHOT = ROOT / "docs" / "web-monitor.png"
PAGE_TIMEOUT_S = 60.0  # bridges, simulators, Zenoh and a browser starting on a loaded machine
# How far back a card's rpm is looked for among its bridge's esc/status samples: the page is
# live, but a load of 25 on two cores holds any of its processes for seconds.
RECENT_S = 10.0

# Every card as the page shows it: name, class, summary, alerts, health, rows by motor.
CARDS = """
return Array.from(document.querySelectorAll("section.vehicle")).map(function (card) {
  return {
    name: card.dataset.vehicle,
    level: card.className,
    summary: card.querySelector(".summary").textContent,
    alerts: Array.from(card.querySelectorAll(".alerts li")).map(li => li.textContent),
    health: Object.fromEntries(Array.from(card.querySelectorAll(".health div")).map(
      item => [item.dataset.item, item.lastChild.textContent])),
    rows: Object.fromEntries(Array.from(card.querySelectorAll("tbody tr")).map(row => [
      row.dataset.motor,
      Object.assign(
        {level: row.className, background: getComputedStyle(row.cells[0]).backgroundColor},
        Object.fromEntries(Array.from(row.cells).map(td => [td.dataset.col, td.textContent])))])),
  };
});
"""
# How many pixels each chart of a card has drawn in the motors' colours (not the grid's grey).
CHART_PIXELS = """
const card = document.querySelector(`section.vehicle[data-vehicle="${arguments[0]}"]`);
return Object.fromEntries(Array.from(card.querySelectorAll("figure")).map(function (figure) {
  const canvas = figure.querySelector("canvas");
  const data = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height).data;
  let coloured = 0;
  for (let i = 0; i < data.length; i += 4) {
    const [r, g, b, a] = [data[i], data[i + 1], data[i + 2], data[i + 3]];
    if (a > 128 && Math.max(r, g, b) - Math.min(r, g, b) > 60) coloured++;
  }
  return [figure.dataset.chart, coloured];
}));
"""


@pytest.fixture(scope="module")
def chromium() -> tuple[str, str]:
    found = find_browser()
    if found is None:
        pytest.skip(f"no chromium and chromedriver on PATH: {INSTALL}")
    return found


class Rig:
    """One vehicle: a bridge, its simulated ESCs and an autopilot."""

    def __init__(self, vehicle: str, faults: list[str], pwm: list[int]) -> None:
        self.vehicle = vehicle
        can_port, mavlink_port = free_port(), free_port()
        self.zenoh = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
        self.sim = subprocess.Popen(
            [ESC_BRIDGE, "sim", "--escs", "4", *can_args(can_port), *faults],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        self.bridge = Daemon(
            [
                "run",
                "--mavlink",
                f"udpin:127.0.0.1:{mavlink_port}",
                *can_args(can_port),
                "--vehicle",
                vehicle,
                "--zenoh-listen",
                self.zenoh,
                "--no-zenoh-scouting",
            ]
        )
        self.autopilot = Autopilot(mavlink_port)
        self.autopilot.armed = True
        self.autopilot.pwm = pwm
        self.autopilot.start_stream(50)

    def stop_bridge(self) -> int:
        return self.bridge.stop()

    def close(self) -> None:
        self.autopilot.close()
        self.bridge.stop()
        self.sim.send_signal(signal.SIGTERM)
        try:
            self.sim.wait(10)
        except subprocess.TimeoutExpired:
            self.sim.kill()
            self.sim.wait()


class Published:
    """Every rpm each vehicle's bridge publishes on ``esc/status``, as a subscriber sees it."""

    def __init__(self, endpoints: list[str]) -> None:
        config = zenoh.Config()
        config.insert_json5("connect/endpoints", json.dumps(endpoints))
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        self.session = zenoh.open(config)
        self.rpm: list[tuple[float, str, list[int | None]]] = []
        self._lock = threading.Lock()
        self.session.declare_subscriber("esc-bridge/*/esc/status", self._on_status)

    def _on_status(self, sample: zenoh.Sample) -> None:
        vehicle = str(sample.key_expr).split("/")[1]
        escs = json.loads(sample.payload.to_bytes())["escs"]
        with self._lock:
            self.rpm.append((time.monotonic(), vehicle, [e["rpm"] for e in escs]))

    def since(self, vehicle: str, t: float) -> list[list[int | None]]:
        with self._lock:
            return [rpm for when, name, rpm in self.rpm if name == vehicle and when >= t]

    def of(self, vehicle: str) -> list[tuple[float, list[int | None]]]:
        """Every (monotonic time, rpm) of ``vehicle``."""
        with self._lock:
            return [(when, rpm) for when, name, rpm in self.rpm if name == vehicle]

    def close(self) -> None:
        self.session.close()  # type: ignore[no-untyped-call]


def start_web_monitor(
    *args: str, env: dict[str, str] | None = None
) -> tuple[subprocess.Popen[str], str]:
    """``esc-bridge monitor --web 127.0.0.1:0 ARGS``; the process and the page's URL."""
    proc = subprocess.Popen(
        [ESC_BRIDGE, "monitor", "--web", "127.0.0.1:0", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, **(env or {})},
    )
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], PAGE_TIMEOUT_S)
    line = proc.stdout.readline() if ready else ""
    found = re.search(r"http://127\.0\.0\.1:\d+/", line)
    if found is None:
        proc.kill()
        raise AssertionError(f"no URL from the monitor: {line!r} {proc.communicate()}")
    return proc, found.group(0)


def stop(proc: subprocess.Popen[str]) -> tuple[int, str]:
    proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    return proc.returncode, err


def cards(browser: Browser) -> dict[str, dict[str, Any]]:
    return {card["name"]: card for card in browser.run(CARDS)}


def wait_for(
    browser: Browser, check: Callable[[dict[str, dict[str, Any]]], bool], timeout_s: float
) -> dict[str, dict[str, Any]]:
    deadline = time.monotonic() + timeout_s
    seen: dict[str, dict[str, Any]] = {}
    while time.monotonic() < deadline:
        seen = cards(browser)
        try:
            if check(seen):
                return seen
        except (KeyError, ValueError):
            pass
        time.sleep(0.2)
    raise AssertionError(f"the page never showed it within {timeout_s} s; it showed {seen}")


def rpm(card: dict[str, Any]) -> list[int | None]:
    return [
        None if row["rpm"] == "-" else int(row["rpm"])
        for _, row in sorted(card["rows"].items(), key=lambda item: int(item[0]))
    ]


@pytest.fixture
def rigs() -> Iterator[dict[str, Rig]]:
    started: dict[str, Rig] = {}
    try:
        started["alpha"] = Rig("alpha", ["--fault", "2:over_temperature"], [1250, 1300, 1350, 1400])
        started["beta"] = Rig("beta", ["--fault", "3:silent"], [1600] * 4)
        yield started
    finally:
        for rig in started.values():
            rig.close()


def test_two_vehicles_failures_phone_width_and_a_bridge_going_away(
    chromium: tuple[str, str], rigs: dict[str, Rig]
) -> None:
    endpoints = [rig.zenoh for rig in rigs.values()]
    published = Published(endpoints)
    connect = [arg for e in endpoints for arg in ("--connect", e)]
    monitor, url = start_web_monitor(*connect, "--no-multicast-scouting")
    try:
        with Browser(1400, 1000) as browser:
            browser.get(url)

            def both_spinning(seen: dict[str, dict[str, Any]]) -> bool:
                alpha, beta = rpm(seen["alpha"]), rpm(seen["beta"])
                return all(r for r in alpha) and sum(1 for r in beta if r) == 3

            wait_for(browser, both_spinning, PAGE_TIMEOUT_S)

            # The rpm of each card are ones its own bridge published in the last seconds, and
            # never the other's. The monitor and this test's subscriber get each sample
            # separately, and under load either may miss one (the bridge's publisher drops
            # rather than wait): a card's rpm must match, at three looks out of at most 30.
            matched = {"alpha": 0, "beta": 0}
            misses: list[tuple[str, list[int | None], list[float]]] = []
            for _ in range(30):
                asked = time.monotonic()
                seen = cards(browser)
                time.sleep(0.5)  # for a sample the monitor got first
                for name, other in (("alpha", "beta"), ("beta", "alpha")):
                    shown = rpm(seen[name])
                    if shown in published.since(name, asked - RECENT_S):
                        matched[name] += 1
                    else:
                        ages = [asked - t for t, rpms in published.of(name) if rpms == shown]
                        misses.append((name, shown, ages))
                    assert shown not in published.since(other, asked - RECENT_S), (name, shown)
                if min(matched.values()) >= 3:
                    break
            assert min(matched.values()) >= 3, (matched, "missed (vehicle, rpm, s ago):", misses)

            # What stands out, as soon as the page shows it (at a load of 22, a simulator's
            # stall left all of beta's ESCs offline for a moment).
            seen = wait_for(
                browser,
                lambda s: (
                    s["alpha"]["alerts"] == ["motor 2: overtemp"]
                    and s["beta"]["alerts"] == ["motor 3: offline"]
                ),
                PAGE_TIMEOUT_S,
            )
            alpha, beta = seen["alpha"], seen["beta"]
            assert list(seen) == ["alpha", "beta"]  # in name order
            # alpha's motor 2 reports over-temperature: said in the banner, red in the table.
            assert alpha["alerts"] == ["motor 2: overtemp"]
            assert "level-bad" in alpha["level"]
            assert alpha["summary"] == "4/4 ESCs online"
            assert alpha["rows"]["2"]["flags"] == "overtemp"
            assert alpha["rows"]["2"]["level"] == "esc-failure"
            assert int(alpha["rows"]["2"]["MOS°C"]) >= 150
            assert alpha["rows"]["1"]["level"] == "esc-ok"
            assert alpha["rows"]["2"]["background"] != alpha["rows"]["1"]["background"]
            # beta's motor 3 is silent: offline, and said so.
            assert beta["alerts"] == ["motor 3: offline"]
            assert beta["summary"] == "3/4 ESCs online"
            assert beta["rows"]["3"]["state"] == "offline"
            assert beta["rows"]["3"]["level"] == "esc-offline"
            assert beta["rows"]["3"]["background"] != beta["rows"]["1"]["background"]
            # The bridge's state and the autopilot's arming from bridge/health.
            assert alpha["health"]["bridge"].startswith("running, ")
            assert alpha["health"]["autopilot"].startswith("armed, ")
            assert set(alpha["health"]) == {"bridge", "autopilot", "link", "bus"}
            # The charts draw the last seconds in the motors' colours (the grid is grey).
            # alpha's throttles step meanwhile; for the screenshot, for longer.
            screenshot = bool(os.environ.get(SCREENSHOT_ENV))
            for step in range(12 if screenshot else 2):
                rigs["alpha"].autopilot.pwm = [1250 + 50 * m + 40 * (step % 3) for m in range(4)]
                time.sleep(2.0)
            pixels = browser.run(CHART_PIXELS, "alpha")
            assert set(pixels) == {"rpm", "current_a", "temp_c"}
            assert all(count > 20 for count in pixels.values()), pixels
            if screenshot:
                browser.screenshot(SCREENSHOT)

            # A phone's width: no sideways scrolling of the page, the minor columns gone.
            browser.set_window(400, 900)
            narrow = browser.wait_for(
                "return window.innerWidth <= 520 && "
                "document.documentElement.scrollWidth <= window.innerWidth && "
                "getComputedStyle(document.querySelector('td[data-col=node]')).display",
                PAGE_TIMEOUT_S,
            )
            assert narrow == "none"
            browser.set_window(1400, 1000)

            # beta's bridge stops: its card stays, stale, with its age counting up.
            assert rigs["beta"].stop_bridge() == 0
            stale = wait_for(
                browser, lambda s: s["beta"]["summary"].startswith("STALE"), PAGE_TIMEOUT_S
            )
            assert "level-stale" in stale["beta"]["level"]
            assert stale["beta"]["alerts"] == []
            assert {row["state"] for row in stale["beta"]["rows"].values()} == {"stale"}
            first = float(re.findall(r"[\d.]+", stale["beta"]["summary"])[0])
            # The age grows, and alpha's card stays live beside it.
            wait_for(
                browser,
                lambda s: (
                    float(re.findall(r"[\d.]+", s["beta"]["summary"])[0]) > first + 1.0
                    and s["alpha"]["summary"] == "4/4 ESCs online"
                ),
                PAGE_TIMEOUT_S,
            )
    finally:
        status, err = stop(monitor)
        published.close()
    assert status == 0, err


def test_the_demo_and_a_plain_web_monitor_beside_it(
    chromium: tuple[str, str], tmp_path: Path
) -> None:
    # The README's line: `esc-bridge demo` in one terminal, `esc-bridge monitor --web PORT` in
    # another, nothing else. Their own runtime directory: no other test's demo is found.
    env = {"XDG_RUNTIME_DIR": str(tmp_path)}
    demo = subprocess.Popen(
        # Flying until this test stops it (at a load of 25, one flight ended before the page
        # showed it).
        [ESC_BRIDGE, "demo", "--plain", "--duration", "600"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, **env},
    )
    monitor: subprocess.Popen[str] | None = None
    try:
        deadline = time.monotonic() + PAGE_TIMEOUT_S
        while not list((tmp_path / "esc-bridge" / "listening").glob("*")):
            assert time.monotonic() < deadline, "the demo announced no endpoint"
            time.sleep(0.1)
        monitor, url = start_web_monitor(env=env)
        with Browser() as browser:
            browser.get(url)
            # The demo's card, live (a stale one keeps its last rpm): every ESC online, spinning.
            wait_for(
                browser,
                lambda s: s["demo"]["summary"] == "4/4 ESCs online" and any(rpm(s["demo"])),
                PAGE_TIMEOUT_S * 1.5,
            )
    finally:
        if monitor is not None:
            status, err = stop(monitor)
            assert status == 0, err
            assert "also connecting to tcp/127.0.0.1:" in err
        demo.send_signal(signal.SIGINT)
        try:
            demo.wait(30)
        except subprocess.TimeoutExpired:
            demo.kill()
            demo.wait()
