"""``esc-bridge demo``: the whole system on one machine, no hardware, no configuration file.

Four parts, all on loopback:

- the bridge, ``esc-bridge run`` in a process of its own, with a configuration written to a
  temporary directory (:func:`bridge_settings`): MAVLink ``udpin`` on a free UDP port, a
  python-can ``udp_multicast`` bus (group :data:`MULTICAST_GROUP`, a free port, hop limit 0:
  nothing leaves the machine), Zenoh listening on ``tcp/127.0.0.1:<free port>`` without
  multicast scouting, vehicle ``demo``;
- the ESCs, ``esc-bridge sim`` in a process of its own on the same bus;
- the autopilot, :class:`bridge.sim.autopilot.SimAutopilot` in this process, flying its
  scripted flight once the bridge reports every ESC;
- the monitor, a :class:`bridge.monitor.ZenohSource` in this process connected to the bridge's
  endpoint, shown as the live table (or a plain-text table a second when not on a terminal).

The demo ends after the flight (or ``duration_s``) or on Ctrl-C / SIGTERM / SIGHUP, in order:
the autopilot disarms, the bridge gets SIGTERM (it sends safe values, then exits 0), then the
simulator. A child that exits on its own before that ends the demo with status 1 and its last
lines of output. The children run in sessions of their own so that the terminal's Ctrl-C
reaches only the demo, which stops them in that order.

The only output is to the ``out`` and ``err`` streams the caller passes (the CLI: stdout and
stderr). Beside this module: :mod:`bridge.demo.child` (a child process and its last lines) and
:mod:`bridge.demo.watch` (what the demo watches of the bridge, and the summary).
"""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any, Final, TextIO

from bridge.config import BridgeConfig, build_config
from bridge.demo.child import Child
from bridge.demo.watch import (
    LOOPBACK,
    PREFIX,
    VEHICLE,
    DemoSource,
    Record,
    all_online,
    summary_text,
)
from bridge.escs import registry
from bridge.monitor import (
    LIVE_PERIOD_S,
    PLAIN_PERIOD_S,
    VehicleState,
    plain_text,
    render_table,
    schedule,
    waiting_text,
)
from bridge.sim.autopilot import FLIGHT_S, WAITING, Airframe, SimAutopilot, motor_count

if TYPE_CHECKING:
    from rich.console import RenderableType

MULTICAST_GROUP: Final = "239.74.163.2"

START_TIMEOUT_S: Final = 30.0
"""The bridge must publish ESC telemetry within this long of the start, or the demo fails."""
ALL_ONLINE_WAIT_S: Final = 5.0
"""After the first telemetry, how long the flight waits for every ESC to be online."""
DISARM_WAIT_S: Final = 1.5
"""At the end, how long to wait for the bridge to report the autopilot disarmed."""
BRIDGE_STOP_TIMEOUT_S: Final = 10.0
SIM_STOP_TIMEOUT_S: Final = 5.0
EXIT_OK: Final = 0
EXIT_FAILED: Final = 1


@dataclass(frozen=True)
class DemoOptions:
    """What ``esc-bridge demo`` was asked for."""

    protocol: str = registry.DEFAULT
    airframe: Airframe = "quad"
    duration_s: float | None = None
    """Stop after this long from the start, repeating the flight as needed; None: one flight."""
    plain: bool = False
    """Plain-text tables even on a terminal."""
    time_scale: float = 1.0
    """Fly the profile this many times faster (for tests)."""
    record_dir: Path | None = None
    """The bridge records the flight here (``esc-bridge run --record``); None: no recording."""

    def __post_init__(self) -> None:
        if self.protocol not in registry.names():
            raise ValueError(f"protocol must be one of {registry.names()}, got {self.protocol!r}")
        motor_count(self.airframe)  # raises for an unknown airframe
        if self.duration_s is not None and not (0 < self.duration_s < math.inf):
            raise ValueError(f"duration must be a number of seconds > 0, got {self.duration_s!r}")
        if not (0 < self.time_scale < math.inf):
            raise ValueError(f"time scale must be a number > 0, got {self.time_scale!r}")

    @property
    def escs(self) -> int:
        return motor_count(self.airframe)


@dataclass(frozen=True)
class DemoPorts:
    """The loopback ports of one demo."""

    mavlink: int
    """UDP: the bridge's ``udpin``, where the autopilot sends."""
    can: int
    """UDP: the ``udp_multicast`` CAN bus."""
    zenoh: int
    """TCP: where the bridge's Zenoh session listens."""

    @property
    def zenoh_endpoint(self) -> str:
        return f"tcp/{LOOPBACK}:{self.zenoh}"

    @classmethod
    def pick(cls) -> DemoPorts:
        """Ports the OS reports free now (another program may still take one before us)."""
        return cls(_free_port(socket.SOCK_DGRAM), _free_port(socket.SOCK_DGRAM), _free_port())


def _free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind((LOOPBACK, 0))
        port: int = sock.getsockname()[1]
        return port


# -- the children's command lines -------------------------------------------------------------


def bridge_settings(options: DemoOptions, ports: DemoPorts) -> dict[str, dict[str, Any]]:
    """The bridge's configuration tables (written as its TOML file)."""
    n = options.escs
    settings: dict[str, dict[str, Any]] = {
        "mavlink": {"url": f"udpin:{LOOPBACK}:{ports.mavlink}"},
        "mixer": {"name": f"passthrough-{n}"},
        # A demo on a desktop needs no real-time priority.
        "output": {"protocol": options.protocol, "realtime_priority": 0},
        "can": {
            "interface": "udp_multicast",
            "channel": MULTICAST_GROUP,
            "options": {"port": ports.can, "hop_limit": 0},
        },
        "escs": {"ids": list(range(1, n + 1))},
        "zenoh": {
            "mode": "peer",
            "listen": [ports.zenoh_endpoint],
            "multicast_scouting": False,
            "vehicle": VEHICLE,
        },
    }
    # The family's own demo settings, if its simulator has any.
    family_settings = getattr(registry.tool(options.protocol, "sim"), "DEMO_SETTINGS", {})
    for section, values in family_settings.items():
        settings[section].update(values)
    return settings


def bridge_config(options: DemoOptions, ports: DemoPorts) -> BridgeConfig:
    """:func:`bridge_settings` validated, as the bridge will read them.

    Raises:
        ConfigError: the settings are invalid (a bug in the demo).
    """
    return build_config(bridge_settings(options, ports), "demo")


def toml_text(tables: Mapping[str, Mapping[str, Any]]) -> str:
    """``tables`` as TOML: one ``[section]`` per table; values are strings, numbers, booleans,
    lists of those, or one level of inline table.

    Raises:
        TypeError: a value of another type.
    """
    lines: list[str] = []
    for section, table in tables.items():
        lines.append(f"[{section}]")
        lines += [f"{key} = {_toml_value(value)}" for key, value in table.items()]
        lines.append("")
    return "\n".join(lines)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string for anything JSON escapes the same way
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"no TOML form for {value!r}")


def esc_bridge_command() -> list[str]:
    """How to start ``esc-bridge``: the console script beside this Python, else the module."""
    script = Path(sys.executable).parent / "esc-bridge"
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [sys.executable, "-c", "import sys; from bridge.cli import main; sys.exit(main())"]


def bridge_args(config_path: Path, record_dir: Path | None = None) -> list[str]:
    record = [] if record_dir is None else ["--record", str(record_dir)]
    return ["run", "--config", str(config_path), *record]


def sim_args(options: DemoOptions, ports: DemoPorts) -> list[str]:
    return [
        "sim",
        "--protocol",
        options.protocol,
        "--escs",
        str(options.escs),
        "--can-interface",
        "udp_multicast",
        "--can-channel",
        MULTICAST_GROUP,
        "--can-option",
        f"port={ports.can}",
        "--can-option",
        "hop_limit=0",
    ]


# -- children -----------------------------------------------------------------------------------


# -- the demo ---------------------------------------------------------------------------------


class _Failed(Exception):
    """The demo cannot go on: a child died, or the bridge never reported."""


class Demo:
    """One run of the demo; :meth:`run` does everything and returns the exit status."""

    def __init__(self, options: DemoOptions, out: TextIO, err: TextIO) -> None:
        self.options = options
        self.out = out
        self.err = err
        self.ports = DemoPorts.pick()
        self.record = Record()
        self.bridge: Child | None = None
        self.sim: Child | None = None
        self.autopilot: SimAutopilot | None = None
        self.source: DemoSource | None = None
        self.started = time.monotonic()
        self.flying_since: float | None = None
        self.first_status: float | None = None
        self.plain = options.plain or not out.isatty()

    @property
    def header(self) -> str:
        o = self.options
        autopilot = self.autopilot
        phase = WAITING if autopilot is None else autopilot.phase
        state = None if self.source is None else self.source.state
        return (
            f"esc-bridge demo: {o.protocol} {o.airframe} ({o.escs} ESCs) | "
            f"phase {phase} | {time.monotonic() - self.started:5.1f} s | bridge {state or '-'}"
        )

    @property
    def watch_hint(self) -> str:
        return (
            "watch from another terminal: esc-bridge monitor --connect "
            f"{self.ports.zenoh_endpoint} --no-multicast-scouting"
        )

    def run(self) -> int:
        """Start everything, show the table until the end, stop everything; the exit status."""
        reason = "flight complete"
        failure: str | None = None
        with tempfile.TemporaryDirectory(prefix="esc-bridge-demo-") as tmp, _stop_signals():
            try:
                self._start(Path(tmp))
                reason = self._show()
            except KeyboardInterrupt:
                reason = "interrupted"
            except _Failed as exc:
                failure = str(exc)
            finally:
                with _ignoring_interrupts():
                    statuses = self._stop()
        self._write_summary(reason if failure is None else "failed", statuses)
        if failure is not None:
            self.err.write(f"esc-bridge demo: {failure}\n")
            self.err.flush()
            return EXIT_FAILED
        bad = {name: status for name, status in statuses.items() if status != 0}
        if bad:
            self.err.write(
                "esc-bridge demo: "
                + ", ".join(f"{name} exited with status {s}" for name, s in bad.items())
                + "\n"
            )
            return EXIT_FAILED
        return EXIT_OK

    # -- start ----------------------------------------------------------------------------------

    def _start(self, tmp: Path) -> None:
        o, ports = self.options, self.ports
        bridge_config(o, ports)  # a bad configuration is the demo's bug: fail before starting
        config_path = tmp / "bridge.toml"
        config_path.write_text(toml_text(bridge_settings(o, ports)), encoding="utf-8")
        command = esc_bridge_command()
        try:
            self.bridge = Child("bridge", [*command, *bridge_args(config_path, o.record_dir)])
            self.sim = Child("sim", [*command, *sim_args(o, ports)])
        except OSError as exc:
            raise _Failed(f"cannot start {command[0]}: {exc}") from exc
        if self.plain:
            flight = (
                f"a {FLIGHT_S / o.time_scale:.0f} s flight"
                if o.duration_s is None
                else f"flying for {o.duration_s:g} s"
            )
            self._write(
                f"esc-bridge demo: {o.protocol} {o.airframe} ({o.escs} ESCs), {flight}; "
                f"bridge pid {self.bridge.pid}, sim pid {self.sim.pid}\n{self.watch_hint}\n\n"
            )
        self.autopilot = SimAutopilot(
            ports.mavlink, o.airframe, time_scale=o.time_scale, loop=o.duration_s is not None
        )
        self.autopilot.start()
        try:
            self.source = DemoSource.connect(ports.zenoh_endpoint)
        except Exception as exc:  # ConfigError, LinkError: nothing to show without it
            raise _Failed(f"cannot watch the bridge over Zenoh: {exc}") from exc

    # -- run ------------------------------------------------------------------------------------

    def _step(self) -> tuple[list[VehicleState], str | None]:
        """One look: check the children, start the flight when ready; (vehicles, end reason)."""
        for child in (self.bridge, self.sim):
            if child is not None and child.poll() is not None:
                raise _Failed(self._died(child))
        assert self.source is not None and self.autopilot is not None
        vehicles = self.source.vehicles()
        self.record.update(vehicles)
        now = time.monotonic()
        if self.flying_since is None:
            if vehicles and self.first_status is None:
                self.first_status = now
            ready = all_online(vehicles, self.options.escs)
            waited = self.first_status is not None and now - self.first_status > ALL_ONLINE_WAIT_S
            if ready or waited:
                self.autopilot.fly()
                self.flying_since = now
            elif self.first_status is None and now - self.started > START_TIMEOUT_S:
                bridge = self.bridge
                lines = "" if bridge is None else _indent(bridge.last_lines())
                raise _Failed(
                    f"the bridge published no ESC telemetry within {START_TIMEOUT_S:.0f} s; "
                    f"its last output:\n{lines}"
                )
        elif self.autopilot.finished:
            return vehicles, "flight complete"
        return vehicles, None

    def _show(self) -> str:
        if self.plain:
            return self._show_plain()
        return self._show_live()

    def _show_plain(self) -> str:
        next_print = time.monotonic()
        for last in schedule(LIVE_PERIOD_S, self.options.duration_s):
            vehicles, reason = self._step()
            now = time.monotonic()
            if reason is not None or last or now >= next_print:
                table = plain_text(vehicles) if vehicles else waiting_text(PREFIX)
                self._write(f"{self.header}\n{table}\n\n")
                next_print = max(next_print + PLAIN_PERIOD_S, now)
            if reason is not None:
                return reason
        return "duration reached"

    def _show_live(self) -> str:
        from rich.console import Console, Group
        from rich.live import Live
        from rich.text import Text

        def view(vehicles: list[VehicleState]) -> RenderableType:
            header = Text(self.header, style="bold")
            hint = Text(self.watch_hint, style="dim")
            body: RenderableType = (
                render_table(vehicles) if vehicles else Text(waiting_text(PREFIX))
            )
            return Group(header, hint, body)

        with Live(Text(self.header), console=Console(file=self.out), auto_refresh=False) as live:
            for _ in schedule(LIVE_PERIOD_S, self.options.duration_s):
                vehicles, reason = self._step()
                live.update(view(vehicles), refresh=True)
                if reason is not None:
                    return reason
        return "duration reached"

    def _died(self, child: Child) -> str:
        return (
            f"the {child.name} (esc-bridge {child.argv[len(esc_bridge_command())]}) exited early "
            f"with status {child.returncode}; its last output:\n" + _indent(child.last_lines())
        )

    # -- stop -----------------------------------------------------------------------------------

    def _stop(self) -> dict[str, int]:
        """Disarm, then stop the bridge, then the simulator; their exit statuses."""
        statuses: dict[str, int] = {}
        autopilot, source = self.autopilot, self.source
        if autopilot is not None:
            autopilot.disarm()
            deadline = time.monotonic() + DISARM_WAIT_S
            while source is not None and source.state == "running":
                if time.monotonic() > deadline or self.bridge is None:
                    break
                if self.bridge.poll() is not None:
                    break
                time.sleep(0.05)
        if source is not None:
            self.record.update(source.vehicles())
        for child, timeout in (
            (self.bridge, BRIDGE_STOP_TIMEOUT_S),
            (self.sim, SIM_STOP_TIMEOUT_S),
        ):
            if child is None:
                continue
            status, killed = child.stop(timeout)
            statuses[child.name] = status
            if killed:
                self.err.write(
                    f"esc-bridge demo: the {child.name} did not stop within {timeout:.0f} s of "
                    "SIGTERM and was killed; its last output:\n"
                    + _indent(child.last_lines())
                    + "\n"
                )
        if autopilot is not None:
            autopilot.close()
        if source is not None:
            source.close()
        return statuses

    def _write_summary(self, reason: str, statuses: Mapping[str, int]) -> None:
        elapsed = time.monotonic() - self.started
        exits = ", ".join(f"{name} exit status {status}" for name, status in statuses.items())
        self._write(
            f"esc-bridge demo: {reason} after {elapsed:.1f} s; {exits or 'nothing started'}\n"
            f"{summary_text(self.record, self.options.escs)}\n"
        )

    def _write(self, text: str) -> None:
        self.out.write(text)
        self.out.flush()


def _indent(lines: Sequence[str]) -> str:
    return "\n".join(f"  | {line}" for line in lines) if lines else "  (no output)"


@contextmanager
def _stop_signals() -> Iterator[None]:
    """SIGTERM and SIGHUP end the demo as Ctrl-C does (in the main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, _frame: FrameType | None) -> None:
        raise KeyboardInterrupt(signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextmanager
def _ignoring_interrupts() -> Iterator[None]:
    """While the children are being stopped, a second Ctrl-C (or SIGTERM) must not cut that
    short and leave them running; it takes a few seconds at most."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    signals = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in signals}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def run_demo(options: DemoOptions, out: TextIO, err: TextIO) -> int:
    """Run the demo to its end; the exit status (0: a clean run, 1: a part failed)."""
    return Demo(options, out, err).run()
