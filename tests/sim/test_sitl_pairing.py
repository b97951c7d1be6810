"""The SITL recipe's files (docs/simulation.md), with an ArduCopter stand-in where no SITL build
is needed: config/sitl.toml, `esc-bridge run` and `esc-bridge sim` as separate processes on one
udp_multicast bus (tests/sitl flies the real autopilots).

The stand-in behaves as ArduCopter SITL does (../shared/sitl/README.md): MAVLink on a TCP
server (SITL's SERIAL1, 5762), no SERVO_OUTPUT_RAW until MAV_CMD_SET_MESSAGE_INTERVAL asks for
message 36, then at the asked rate up to 200 Hz; motors 1000 µs disarmed, ~1100 µs armed at
idle, ~1590 µs in hover.
"""

from __future__ import annotations

import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import ESC_BRIDGE, ROOT, Daemon, free_port

from bridge.mavlink import load_dialect

dialect = load_dialect()
MAX_STREAM_HZ = 200.0


class ArduCopterStandIn:
    """A TCP MAVLink server that streams SERVO_OUTPUT_RAW only once asked."""

    def __init__(self, port: int) -> None:
        self._server = socket.create_server(("127.0.0.1", port))
        self._server.settimeout(0.2)
        self._mav = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
        self._parser = dialect.MAVLink(None)
        self._parser.robust_parsing = True
        self.asked_interval_us: float | None = None
        self.pwm = 1000
        self.armed = False
        self.esc_telemetry: list[Any] = []
        self.unknown_to_ardupilot = 0  # ESC_STATUS/ESC_INFO: ArduPilot would drop them
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="arducopter", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        conn = None
        while conn is None and not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except TimeoutError:
                continue
        if conn is None:
            return
        conn.settimeout(0.002)
        with conn:
            try:
                self._serve(conn)
            except OSError:
                return  # the bridge hung up

    def _serve(self, conn: socket.socket) -> None:
        next_heartbeat = next_output = time.monotonic()
        while not self._stop.is_set():
            try:
                data = conn.recv(4096)
                for msg in self._parser.parse_buffer(data) or []:
                    self._handle(conn, msg)
            except TimeoutError:
                pass
            now = time.monotonic()
            if now >= next_heartbeat:
                mode = dialect.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                if self.armed:
                    mode |= dialect.MAV_MODE_FLAG_SAFETY_ARMED
                conn.sendall(
                    self._mav.heartbeat_encode(
                        dialect.MAV_TYPE_QUADROTOR,
                        dialect.MAV_AUTOPILOT_ARDUPILOTMEGA,
                        mode,
                        0,
                        dialect.MAV_STATE_ACTIVE,
                    ).pack(self._mav)
                )
                next_heartbeat = now + 1.0
            if self.asked_interval_us and now >= next_output:
                period = max(self.asked_interval_us / 1e6, 1 / MAX_STREAM_HZ)
                servos = [self.pwm] * 4 + [0] * 4
                conn.sendall(
                    self._mav.servo_output_raw_encode(int(now * 1e6) & 0xFFFFFFFF, 0, *servos).pack(
                        self._mav
                    )
                )
                next_output = max(next_output + period, now)

    def _handle(self, conn: socket.socket, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "ESC_TELEMETRY_1_TO_4":  # what ArduPilot forwards to its ground stations
            self.esc_telemetry.append(msg)
        elif kind in ("ESC_STATUS", "ESC_INFO"):
            self.unknown_to_ardupilot += 1
        elif (
            kind == "COMMAND_LONG"
            and msg.command == dialect.MAV_CMD_SET_MESSAGE_INTERVAL
            and int(msg.param1) == dialect.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
        ):
            self.asked_interval_us = msg.param2
            ack = self._mav.command_ack_encode(msg.command, dialect.MAV_RESULT_ACCEPTED)
            conn.sendall(ack.pack(self._mav))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._server.close()


@pytest.fixture
def arducopter() -> Iterator[tuple[ArduCopterStandIn, int]]:
    port = free_port(socket.SOCK_STREAM)
    stand_in = ArduCopterStandIn(port)
    yield stand_in, port
    stand_in.close()


def test_the_readme_sitl_recipe_flies(arducopter: tuple[ArduCopterStandIn, int]) -> None:
    autopilot, mavlink_port = arducopter
    can_port = free_port()
    config = str(ROOT / "config" / "sitl.toml")
    bus = ["--can-option", f"port={can_port}"]
    sim = subprocess.Popen(
        [ESC_BRIDGE, "sim", "--config", config, *bus],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    bridge = Daemon(
        [
            "run",
            "--config",
            config,
            "--mavlink",
            f"tcp:127.0.0.1:{mavlink_port}",
            *bus,
            "--no-zenoh-scouting",
        ]
    )
    try:
        deadline = time.monotonic() + 20
        while autopilot.asked_interval_us is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert autopilot.asked_interval_us == pytest.approx(5000)  # 200 Hz, as configured
        autopilot.armed, autopilot.pwm = True, 1100
        time.sleep(1.0)
        autopilot.pwm = 1590  # hover
        deadline = time.monotonic() + 10
        hovering: list[int] = []
        while time.monotonic() < deadline:
            latest = autopilot.esc_telemetry[-1] if autopilot.esc_telemetry else None
            if latest is not None and all(rpm > 5000 for rpm in latest.rpm):
                hovering = list(latest.rpm)
                break
            time.sleep(0.1)
        # 1590 µs is 59 % throttle: about 0.59 x 920 rpm/V x 16.7 V, behind the motors' lag.
        assert hovering and all(5000 < rpm < 11_000 for rpm in hovering), hovering
        autopilot.armed = False
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and any(autopilot.esc_telemetry[-1].rpm):
            time.sleep(0.1)
        assert not any(autopilot.esc_telemetry[-1].rpm)  # disarmed: safe values, motors stopped
    finally:
        assert bridge.stop() == 0, bridge.output
        sim.terminate()
        out, _ = sim.communicate(timeout=10)
    assert sim.returncode == 0, out
    assert "SERVO_OUTPUT_RAW from 1/1 arriving at" in bridge.output
    assert autopilot.unknown_to_ardupilot == 0  # the ArduPilot link's set: ESC_TELEMETRY only
