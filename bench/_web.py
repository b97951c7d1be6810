"""What the web monitor's benchmarks share: a fleet of bridges with ESCs on their buses, the
monitor serving them, browsers watching it, and the bench's own readers of each stage.

- :class:`Fleet`: per vehicle the real bridge (``esc-bridge run``: a passthrough mixer for
  :data:`ESCS` CKESCs at 400 Hz, Zenoh listening on loopback only, no autopilot: it sits in
  ``no_input`` and still publishes every ESC) on a udp_multicast bus of its own, where a thread
  of this process plays the ESCs' telemetry (MSG1, MSG2, MSG3 every :data:`ESC_PERIOD_S`, rpm
  moving); then ``esc-bridge monitor --web`` connected to every bridge.
- :class:`Browsers`: headless Chromium windows on the page, through the tests' WebDriver client
  (``tests/browser.py``, one copy of it).
- :class:`Events` reads the monitor's event stream as a browser does; :class:`ZenohWatch`
  subscribes to the bridges' ``esc/status``.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import can
import zenoh
from _common import ESC_BRIDGE, GROUP, bridge_command, free_port, log_tail

from bridge.escs.ckesc import codec, records

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
# The tests' WebDriver client: one copy of it.
from browser import INSTALL, Browser, find_browser

ESCS = 8
VEHICLES = ("bench-a", "bench-b")
ESC_PERIOD_S = 0.04  # each ESC's three telemetry frames, 25 times a second
BASE_RPM = 3000  # the played rpm swing around this, ±1000, so every snapshot changes
START_TIMEOUT_S = 90.0  # bridges, the monitor and browsers starting on a loaded machine

# The page's cards and the rpm of their rows, as shown.
PAGE_RPM = """
return Object.fromEntries(Array.from(document.querySelectorAll("section.vehicle")).map(
  card => [card.dataset.vehicle, Array.from(card.querySelectorAll("td[data-col=rpm]")).map(
    td => td.textContent)]));
"""


def loads() -> str:
    """The machine's load averages, for the report."""
    one, five, fifteen = os.getloadavg()
    return f"{one:.1f} / {five:.1f} / {fifteen:.1f} (1 / 5 / 15 min)"


class EscPlayer:
    """Plays :data:`ESCS` CKESCs' telemetry on one bus, in a thread. Motor 1's rpm can be set
    to a marker: :meth:`mark` returns when the first frame carrying it left."""

    def __init__(self, can_port: int) -> None:
        self.bus = can.Bus(interface="udp_multicast", channel=GROUP, port=can_port, hop_limit=0)
        self._marker: int | None = None
        self._sent: dict[int, float] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="escs", daemon=True)
        self._thread.start()

    def mark(self, rpm: int) -> None:
        """From the next frame on, motor 1 reports ``rpm``."""
        with self._lock:
            self._marker = rpm

    def sent(self) -> dict[int, float]:
        """Marker rpm -> wall-clock time its first frame left."""
        with self._lock:
            return dict(self._sent)

    def _run(self) -> None:
        transfer_id = 0
        next_s = time.monotonic()
        while not self._stop.is_set():
            now = time.time()
            with self._lock:
                marker = self._marker
            for node in range(1, ESCS + 1):
                rpm = round(BASE_RPM + 1000 * math.sin(now + node))
                if node == 1 and marker is not None:
                    rpm = marker
                for message in (
                    records.Msg1(rpm, 600, records.Msg1Status.RUNNING),
                    records.Msg2(16.4, 2.0 + node / 4, 40),
                    records.Msg3(40, 35, 45 + node, 38),
                ):
                    priority = codec.default_priority(message)
                    frame = codec.CkescFrame(priority, node, None, transfer_id, message)
                    self.bus.send(codec.encode(frame))
                    if node == 1 and marker is not None and isinstance(message, records.Msg1):
                        with self._lock:
                            self._sent.setdefault(marker, time.time())
            transfer_id = (transfer_id + 1) % 32
            next_s = max(next_s + ESC_PERIOD_S, time.monotonic())
            self._stop.wait(max(0.0, next_s - time.monotonic()))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.bus.shutdown()


class Fleet:
    """The bridges of :data:`VEHICLES`, their ESCs, and the web monitor serving them."""

    def __init__(self) -> None:
        self.players: list[EscPlayer] = []
        self.bridges: list[subprocess.Popen[bytes]] = []
        self.logs: list[IO[str]] = []  # each bridge's output
        self._files = contextlib.ExitStack()
        self.endpoints: list[str] = []
        self.monitor: subprocess.Popen[str] | None = None
        self.url = ""
        try:
            self._start()
        except BaseException:
            self.close()
            raise

    def _start(self) -> None:
        # One bridge at a time, each running before its ESCs and the next bridge start (two
        # output loops spawning at once, or beside their ESCs' telemetry, took over their 15 s
        # to start beside other work), then the monitor: it connects to endpoints that
        # listen already.
        for vehicle in VEHICLES:
            can_port = free_port()
            with socket.socket() as sock:
                sock.bind(("127.0.0.1", 0))
                endpoint = f"tcp/127.0.0.1:{sock.getsockname()[1]}"
            command = bridge_command(free_port(), can_port, "info")
            command += ["--mixer", f"passthrough-{ESCS}", "--vehicle", vehicle]
            command += ["--zenoh-listen", endpoint, "--no-zenoh-scouting"]
            # The bridge's output, to know it runs and for its last lines if it stops.
            log = self._files.enter_context(tempfile.TemporaryFile("w+"))  # noqa: SIM115
            self.logs.append(log)
            self.bridges.append(subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT))
            self.endpoints.append(endpoint)
            self._wait_for_bridge(vehicle, self.bridges[-1], log)
            self.players.append(EscPlayer(can_port))
        connect = [arg for endpoint in self.endpoints for arg in ("--connect", endpoint)]
        errors = self._files.enter_context(tempfile.TemporaryFile("w+"))  # noqa: SIM115
        self.monitor = subprocess.Popen(
            [ESC_BRIDGE, "monitor", "--web", "127.0.0.1:0", *connect, "--no-multicast-scouting"],
            stdout=subprocess.PIPE,
            stderr=errors,
            text=True,
        )
        assert self.monitor.stdout is not None
        ready, _, _ = select.select([self.monitor.stdout], [], [], START_TIMEOUT_S)
        line = self.monitor.stdout.readline() if ready else ""
        found = re.search(r"http://127\.0\.0\.1:\d+/", line)
        if found is None:
            errors.seek(0)
            raise RuntimeError(
                f"the monitor gave no URL: {line!r}\n{log_tail(Path(), errors.read())}"
            )
        self.url = found.group(0)
        self._wait_for_vehicles(VEHICLES)

    @staticmethod
    def _wait_for_bridge(vehicle: str, bridge: subprocess.Popen[bytes], log: IO[str]) -> None:
        """Until the bridge's loop runs and its Zenoh session is open (its log says both)."""
        deadline = time.monotonic() + START_TIMEOUT_S
        text = ""
        while time.monotonic() < deadline:
            log.seek(0)
            text = log.read()
            if bridge.poll() is not None:
                raise RuntimeError(
                    f"the bridge of {vehicle} exited with status {bridge.returncode}:\n"
                    + log_tail(Path(), text)
                )
            if "ESC out: safe" in text and "Zenoh session open" in text:
                return
            time.sleep(0.2)
        raise RuntimeError(f"the bridge of {vehicle} did not start:\n{log_tail(Path(), text)}")

    def _wait_for_vehicles(self, vehicles: tuple[str, ...]) -> None:
        """Until the monitor shows ``vehicles`` with their ESCs; a bridge that exits first is
        an error with its last lines."""
        deadline = time.monotonic() + START_TIMEOUT_S
        state: dict[str, Any] = {"vehicles": []}
        while time.monotonic() < deadline:
            for vehicle, bridge, log in zip(vehicles, self.bridges, self.logs, strict=True):
                if bridge.poll() is not None:
                    log.seek(0)
                    raise RuntimeError(
                        f"the bridge of {vehicle} exited with status {bridge.returncode}:\n"
                        + log_tail(Path(), log.read())
                    )
            with urllib.request.urlopen(self.url + "state.json", timeout=10) as answer:
                state = json.loads(answer.read())
            shown = {v["name"] for v in state["vehicles"] if len(v["escs"]) == ESCS}
            if shown >= set(vehicles):
                return
            time.sleep(0.5)
        raise RuntimeError(
            f"the monitor did not show {vehicles} within {START_TIMEOUT_S:.0f} s: "
            f"{[(v['name'], v['summary']) for v in state['vehicles']]}"
        )

    @property
    def monitor_pid(self) -> int:
        assert self.monitor is not None
        return self.monitor.pid

    def close(self) -> None:
        procs: list[subprocess.Popen[Any]] = [*self.bridges]
        if self.monitor is not None:
            procs.append(self.monitor)
        for proc in procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in procs:
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for player in self.players:
            player.close()
        self._files.close()

    def __enter__(self) -> Fleet:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def check_browser() -> None:
    """Exit naming the install line where there is no browser."""
    if find_browser() is None:
        sys.exit(f"no chromium and chromedriver on PATH: {INSTALL}")


class Browsers:
    """``count`` headless browsers on ``url``, each showing every vehicle's card."""

    def __init__(self, url: str, count: int) -> None:
        self.all: list[Browser] = []
        try:
            for _ in range(count):
                browser = Browser(1200, 900)
                self.all.append(browser)
                browser.get(url)
            for browser in self.all:
                browser.wait_for(
                    "return arguments[0].every(name => document.querySelector("
                    "`section.vehicle[data-vehicle='${name}'] td[data-col=rpm]`))",
                    START_TIMEOUT_S,
                    list(VEHICLES),
                )
        except BaseException:
            self.close()
            raise

    def pids(self) -> list[int]:
        """Every process of every browser (its chromedriver and all of Chromium's)."""
        found: list[int] = []
        for browser in self.all:
            found += _tree(browser.driver.pid)
        return found

    def close(self) -> None:
        for browser in self.all:
            browser.close()


def _tree(pid: int) -> list[int]:
    pids = [pid]
    try:
        tasks = Path(f"/proc/{pid}/task").iterdir()
        kids = [int(k) for task in tasks for k in (task / "children").read_text().split()]
    except OSError:
        return pids
    for kid in kids:
        pids += _tree(kid)
    return pids


def rss_mb(pid: int) -> float:
    """The process's resident memory, MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return math.nan


class Events:
    """The monitor's event stream read in a thread, as a browser's EventSource does: the bytes
    received, and when each vehicle's motor-1 rpm cell first showed each value."""

    def __init__(self, url: str) -> None:
        host, port = re.findall(r"//([^:/]+):(\d+)", url)[0]
        self.sock = socket.create_connection((host, int(port)), timeout=START_TIMEOUT_S)
        self.sock.sendall(b"GET /events HTTP/1.1\r\nHost: bench\r\n\r\n")
        self.bytes = 0
        self.first_seen: dict[str, float] = {}  # rpm text of bench-a's motor 1 -> wall time
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="events", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        with self.sock.makefile("rb") as stream:
            try:
                for line in stream:
                    now = time.time()
                    with self._lock:
                        self.bytes += len(line)
                    if line.startswith(b"data: ") and b'"vehicles"' in line:
                        self._snapshot(json.loads(line[6:]), now)
            except (OSError, ValueError):
                return

    def _snapshot(self, data: dict[str, Any], now: float) -> None:
        for vehicle in data["vehicles"]:
            if vehicle["name"] == VEHICLES[0] and vehicle["escs"]:
                rpm = vehicle["escs"][0]["cells"][3]
                with self._lock:
                    self.first_seen.setdefault(rpm, now)

    def received(self) -> int:
        with self._lock:
            return self.bytes

    def seen(self) -> dict[str, float]:
        with self._lock:
            return dict(self.first_seen)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        self._thread.join(2.0)


class ZenohWatch:
    """When the first vehicle's ``esc/status`` first carried each motor-1 rpm (wall time)."""

    def __init__(self, endpoints: list[str]) -> None:
        config = zenoh.Config()
        config.insert_json5("connect/endpoints", json.dumps(endpoints))
        config.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        config.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(config)
        self.first_seen: dict[int, float] = {}
        self._lock = threading.Lock()
        self.session.declare_subscriber(f"esc-bridge/{VEHICLES[0]}/esc/status", self._on_status)

    def _on_status(self, sample: zenoh.Sample) -> None:
        now = time.time()
        rpm = json.loads(sample.payload.to_bytes())["escs"][0]["rpm"]
        with self._lock:
            self.first_seen.setdefault(rpm, now)

    def seen(self) -> dict[int, float]:
        with self._lock:
            return dict(self.first_seen)

    def close(self) -> None:
        self.session.close()  # type: ignore[no-untyped-call]


@contextlib.contextmanager
def watchers(endpoints: list[str], url: str) -> Iterator[tuple[ZenohWatch, Events]]:
    """The Zenoh subscriber and the event-stream reader, both closed however the block ends (a
    Zenoh session left open holds the interpreter at exit)."""
    watch = ZenohWatch(endpoints)
    try:
        events = Events(url)
        try:
            yield watch, events
        finally:
            events.close()
    finally:
        watch.close()


def wait_until(check: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise RuntimeError(f"no {what} within {timeout_s:.0f} s")
        time.sleep(0.1)
