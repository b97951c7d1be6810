"""ESC telemetry through the whole daemon: frames on a real bus in, MAVLink and Zenoh out.

The daemon runs through its CLI; the test plays the ESCs (real encoded frames on the
cross-process udp_multicast bus), the autopilot and ground station (pymavlink on loopback UDP,
decoded with the project's dialect, which has ESC_INFO and ESC_STATUS), and a Zenoh subscriber
(multicast scouting off, loopback endpoints only).
"""

from __future__ import annotations

import itertools
import json
import os
import re
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest
import zenoh
from conftest import (
    ESC_BRIDGE,
    STARTUP_TIMEOUT_S,
    Autopilot,
    Daemon,
    MavlinkReceiver,
    Observer,
    free_port,
    holds_of,
    multicast_bus,
)

from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.dronecan import codec as dronecan_codec
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.mavlink import load_dialect
from bridge.telemetry.payload import (
    ActuatorsInputPayload,
    ActuatorsOutputPayload,
    EscInfoPayload,
    EscStatusPayload,
    EscTelemetryPayload,
    HealthPayload,
)

S = ckesc_records.Msg1Status
# The test's autopilot link stands in for a ground station here: it gets every family (the
# per-link default sets are tested in mavlink/test_link_sets.py).
EVERY_FAMILY = "autopilot_messages = { esc_status = 10, esc_info = 1, esc_telemetry = 10 }\n"
dialect = load_dialect()
INT16_MAX = 32767


class Escs:
    """Simulated ESCs in a thread: each sends its telemetry every 20 ms."""

    def __init__(self, port: int, frames: Callable[[int], list[can.Message]]) -> None:
        self.bus = multicast_bus(port)
        self.frames = frames
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="escs", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        tick = 0
        while not self._stop.is_set():
            for msg in self.frames(tick):
                self.bus.send(msg)
            tick += 1
            time.sleep(0.02)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.bus.shutdown()


def ck(node: int, message: ckesc_records.CkescMessage, tid: int) -> can.Message:
    frame = ckesc_codec.CkescFrame(
        ckesc_codec.default_priority(message), node, None, tid % 32, message
    )
    return ckesc_codec.encode(frame)


def ckesc_reports(nodes: list[int], silent: set[int]) -> Callable[[int], list[can.Message]]:
    """ESC node n reports rpm 1000 n, 20 + n / 100 V, n A, MOSFET 30 + n °C, ..."""

    def frames(tick: int) -> list[can.Message]:
        out = []
        for n in nodes:
            if n in silent:
                continue
            out.append(ck(n, ckesc_records.Msg1(1000 * n, 100 * n, S.RUNNING), tick))
            out.append(ck(n, ckesc_records.Msg2(20 + n / 100, float(n), 30 + n), tick))
            out.append(ck(n, ckesc_records.Msg3(30 + n, 20 + n, 40 + n, 25 + n), tick))
        return out

    return frames


def write_mixer(path: Path, n: int) -> Path:
    outputs = "".join(f'\n[[outputs]]\nname = "m{i}"\nsource = "ch{i}"\n' for i in range(1, n + 1))
    path.write_text(
        f'[info]\nkey = "passthrough-{n}"\ndescription = "test"\n\n[output_default]\n'
        f"input_range = [1000.0, 2000.0]\nmin = 0.0\nmax = 1.0\n{outputs}",
        encoding="utf-8",
    )
    return path


@pytest.fixture
def receiver(autopilot: Autopilot) -> Iterator[MavlinkReceiver]:
    rx = MavlinkReceiver(autopilot.conn)
    yield rx
    rx.close()


@pytest.mark.parametrize("n", [4, 8, 20])
def test_esc_status_info_and_telemetry_for_every_esc(
    n: int,
    tmp_path: Path,
    can_port: int,
    autopilot: Autopilot,
    receiver: MavlinkReceiver,
    start_daemon: Callable[..., Daemon],
) -> None:
    mixer = write_mixer(tmp_path / "mixer.toml", n)
    silent = {n}  # the last ESC never reports: offline, unknown temperature
    escs = Escs(can_port, ckesc_reports(list(range(1, n + 1)), silent))
    try:
        # 20 ESCs' commands and telemetry fill a 500 kbit/s bus: a 1 Mbit/s bus, as on a big
        # vehicle (the bus-load check refuses the default).
        config = tmp_path / "bridge.toml"
        config.write_text(f"[mavlink]\n{EVERY_FAMILY}")
        daemon = start_daemon(
            "--mixer", str(mixer), "--bitrate", "1000000", "--config", str(config)
        )
        autopilot.start_stream(20)  # heartbeats: the daemon answers to this link
        batches = range(0, n, 4)
        # ESC_INFO ``info``: the vehicle's online bits in every batch, bit i = motor i (0..7).
        mask = sum(1 << motor for motor in range(min(n, 8)) if motor + 1 not in silent)
        for index in batches:
            reporting = [
                slot
                for slot in range(4)
                if index + slot + 1 <= n and index + slot + 1 not in silent
            ]

            # Each ESC's values come in three messages (CKESC's MSG1: rpm; MSG2: volts, amps and
            # the MOSFET's temperature; MSG3: the others), which on a loaded machine may reach the
            # bridge on either side of an ESC_STATUS or ESC_INFO: the first with every reporting
            # ESC's values is waited for, and its values checked.
            def all_reporting(msg: Any, first: int = index, slots: list[int] = reporting) -> bool:
                return bool(
                    msg.index == first
                    and all(msg.rpm[s] != 0 and msg.voltage[s] != 0 for s in slots)
                )

            def all_online(
                msg: Any, first: int = index, online: int = mask, slots: list[int] = reporting
            ) -> bool:
                return bool(
                    msg.index == first
                    and msg.info == online
                    and all(msg.temperature[s] != INT16_MAX for s in slots)
                )

            status = receiver.wait_for("ESC_STATUS", all_reporting, timeout_s=STARTUP_TIMEOUT_S)
            info = receiver.wait_for("ESC_INFO", all_online, timeout_s=10)
            for slot in range(4):
                esc = index + slot + 1  # node = motor number
                if esc > n or esc in silent:
                    assert status.rpm[slot] == 0 and status.voltage[slot] == 0
                    assert info.temperature[slot] == INT16_MAX
                    continue
                assert status.rpm[slot] == 1000 * esc
                assert status.voltage[slot] == pytest.approx(20 + esc / 100, abs=1e-4)
                assert status.current[slot] == pytest.approx(esc, abs=1e-4)
                assert info.temperature[slot] == (30 + esc) * 100
                assert info.failure_flags[slot] == 0
                assert info.error_count[slot] == 0
            assert info.count == n
            assert info.connection_type == dialect.ESC_CONNECTION_TYPE_CAN
        telemetry = receiver.wait_for(
            "ESC_TELEMETRY_1_TO_4", lambda m: all(m.rpm[s] != 0 for s in range(min(n - 1, 4)))
        )
        assert list(telemetry.rpm) == [1000, 2000, 3000, 4000 if n > 4 else 0]
        assert list(telemetry.voltage)[:3] == [2001, 2002, 2003]  # cV
        assert list(telemetry.current)[:3] == [100, 200, 300]  # cA
        assert list(telemetry.temperature)[:3] == [31, 32, 33]  # °C
        assert all(c > 0 for c in telemetry.count[:3])
    finally:
        escs.close()
    assert daemon.stop() == 0
    assert f"of {n} ESCs online" in daemon.output


def test_offline_after_the_timeout_and_back(
    tmp_path: Path,
    can_port: int,
    autopilot: Autopilot,
    receiver: MavlinkReceiver,
    start_daemon: Callable[..., Daemon],
) -> None:
    config = tmp_path / "bridge.toml"
    config.write_text(
        "[telemetry]\ntimeout_ms = 300\n[mavlink]\nautopilot_messages = { esc_info = 20 }\n"
    )
    silent: set[int] = set()
    escs = Escs(can_port, ckesc_reports([1, 2, 3, 4], silent))
    try:
        start_daemon("--config", str(config))
        autopilot.start_stream(20)
        receiver.wait_for("ESC_INFO", lambda m: m.info == 0b1111, timeout_s=STARTUP_TIMEOUT_S)
        silent.add(2)
        went = time.monotonic()
        receiver.wait_for("ESC_INFO", lambda m: m.info == 0b1101, after=went)
        silent.discard(2)
        back = time.monotonic()
        receiver.wait_for("ESC_INFO", lambda m: m.info == 0b1111, after=back)
        # Generous: offline within timeout + a few info periods, back at the next report.
        offline = [t for t, m in receiver.messages if t > went and m.get_type() == "ESC_INFO"]
        first_offline = next(
            t
            for t, m in receiver.messages
            if t > went and m.get_type() == "ESC_INFO" and m.info == 0b1101
        )
        assert offline and first_offline - went < 1.5
    finally:
        escs.close()


def test_ft_crc_errors_count_into_error_count_and_raise_generic(
    tmp_path: Path,
    can_port: int,
    autopilot: Autopilot,
    receiver: MavlinkReceiver,
    start_daemon: Callable[..., Daemon],
) -> None:
    config = tmp_path / "bridge.toml"
    config.write_text(f"[telemetry]\npole_pairs = 7\nerror_burst = 5\n[mavlink]\n{EVERY_FAMILY}")

    def frames(tick: int) -> list[can.Message]:
        out = []
        for esc in (1, 2, 3, 4):
            out.append(
                ft_codec.encode(
                    ft_records.FtFrame(esc, ft_records.RealtimeData1(erpm=-7000 * esc, duty=-0.1))
                )
            )
            out.append(
                ft_codec.encode(
                    ft_records.FtFrame(esc, ft_records.RealtimeData2(40.0 + esc, 50.0, 24.0))
                )
            )
        bad = ft_codec.encode(ft_records.FtFrame(3, ft_records.RealtimeData0(1.0, 2.0)))
        bad.data[6] ^= 0x5A  # ESC 3 sends a bad CRC every 20 ms
        out.append(bad)
        return out

    escs = Escs(can_port, frames)
    try:
        start_daemon("--protocol", "ft", "--config", str(config))
        autopilot.start_stream(20)
        status = receiver.wait_for(
            "ESC_STATUS", lambda m: m.rpm[3] != 0, timeout_s=STARTUP_TIMEOUT_S
        )
        assert list(status.rpm) == [-1000, -2000, -3000, -4000]  # erpm / 7, signed
        info = receiver.wait_for("ESC_INFO", lambda m: m.error_count[2] >= 10)
        assert info.error_count[0] == info.error_count[1] == info.error_count[3] == 0
        assert info.failure_flags[2] == dialect.ESC_FAILURE_GENERIC
        assert info.failure_flags[0] == 0
        assert info.temperature[0] == 4100
        telemetry = receiver.wait_for("ESC_TELEMETRY_1_TO_4", lambda m: m.rpm[3] != 0)
        assert list(telemetry.rpm) == [1000, 2000, 3000, 4000]  # ArduPilot's is unsigned
    finally:
        escs.close()


def test_dronecan_status_and_node_status_to_mavlink(
    tmp_path: Path,
    can_port: int,
    autopilot: Autopilot,
    receiver: MavlinkReceiver,
    start_daemon: Callable[..., Daemon],
) -> None:
    """DroneCAN ESCs at nodes 30..33 (esc_index 0..3): multi-frame esc.Status transfers,
    interleaved, and NodeStatus; ESC 2's node reports health ERROR, ESC 3 sends a Status with a
    bad transfer CRC beside its good ones."""
    config = tmp_path / "bridge.toml"
    config.write_text(f'[output]\nprotocol = "dronecan"\n[mavlink]\n{EVERY_FAMILY}')
    senders = [dronecan_codec.Sender(30 + index) for index in range(4)]

    def frames(tick: int) -> list[can.Message]:
        per_esc = []  # each ESC's transfers one after another
        for index, sender in enumerate(senders):
            esc = index + 1
            status = dronecan_codec.EscStatus(
                index, 0, 20 + esc / 4, float(esc), 273.15 + 30 + esc, -1000 * esc, 10 * esc
            )
            own = sender.frames(status)
            if index == 2:
                bad = sender.frames(status)
                bad[0].data[0] ^= 0x5A  # the transfer CRC's low byte
                own += bad
            if tick % 10 == 0:
                health = 2 if esc == 2 else 0
                own += sender.frames(dronecan_codec.NodeStatus(tick // 50, health, 0))
            per_esc.append(own)
        # The ESCs' frames interleaved, as several ESCs on one bus send them.
        return [f for group in itertools.zip_longest(*per_esc) for f in group if f is not None]

    escs = Escs(can_port, frames)
    try:
        start_daemon("--config", str(config))
        autopilot.start_stream(20)
        status = receiver.wait_for(
            "ESC_STATUS", lambda m: m.rpm[3] != 0, timeout_s=STARTUP_TIMEOUT_S
        )
        assert list(status.rpm) == [-1000, -2000, -3000, -4000]  # signed, as the ESCs sent
        assert list(status.voltage) == pytest.approx([20.25, 20.5, 20.75, 21.0], abs=1e-3)
        assert list(status.current) == pytest.approx([1.0, 2.0, 3.0, 4.0], abs=1e-3)
        info = receiver.wait_for(
            "ESC_INFO", lambda m: m.error_count[2] >= 5 and m.failure_flags[1] != 0
        )
        assert info.info == 0b1111
        assert [t / 100 for t in info.temperature] == pytest.approx([31, 32, 33, 34], abs=0.3)
        assert info.failure_flags[1] == dialect.ESC_FAILURE_GENERIC  # health ERROR
        assert info.failure_flags[0] == info.failure_flags[3] == 0
        assert info.error_count[0] == info.error_count[1] == info.error_count[3] == 0
        telemetry = receiver.wait_for("ESC_TELEMETRY_1_TO_4", lambda m: m.rpm[3] != 0)
        assert list(telemetry.rpm) == [1000, 2000, 3000, 4000]  # ArduPilot's is unsigned
    finally:
        escs.close()


def test_gcs_on_an_extra_output_sets_the_rate(
    tmp_path: Path,
    can_port: int,
    autopilot: Autopilot,
    start_daemon: Callable[..., Daemon],
) -> None:
    from pymavlink import mavutil

    gcs_port = free_port()
    gcs = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{gcs_port}", source_system=255, source_component=190
    )
    receiver = MavlinkReceiver(gcs)
    config = tmp_path / "bridge.toml"
    config.write_text(f'[mavlink]\noutputs = ["udpout:127.0.0.1:{gcs_port}"]\nesc_status_hz = 2\n')
    escs = Escs(can_port, ckesc_reports([1, 2, 3, 4], set()))
    try:
        start_daemon("--config", str(config))
        autopilot.start_stream(20)
        receiver.wait_for(
            "HEARTBEAT", lambda m: m.get_srcComponent() == 191, timeout_s=STARTUP_TIMEOUT_S
        )
        receiver.wait_for("ESC_STATUS", lambda m: m.rpm[0] == 1000)
        gcs.mav.srcSystem, gcs.mav.srcComponent = 255, 190
        gcs.mav.command_long_send(
            1, 191, dialect.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 291, 20_000, 0, 0, 0, 0, 0
        )
        ack = receiver.wait_for(
            "COMMAND_ACK", lambda m: m.command == dialect.MAV_CMD_SET_MESSAGE_INTERVAL
        )
        assert ack.result == dialect.MAV_RESULT_ACCEPTED
        time.sleep(0.5)
        start = time.monotonic()
        time.sleep(2.0)
        with receiver._lock:
            count = sum(
                1
                for t, m in receiver.messages
                if t >= start and m.get_type() == "ESC_STATUS" and m.index == 0
            )
        assert 70 <= count <= 110  # 50 Hz for 2 s, asked of a 2 Hz default
    finally:
        escs.close()
        receiver.close()
        gcs.close()


def test_a_held_up_sender_says_so_and_skips_what_it_missed(
    tmp_path: Path,
    can_port: int,
    autopilot: Autopilot,
    start_daemon: Callable[..., Daemon],
) -> None:
    """The main process stopped for 1 s (SIGSTOP; on a vehicle: starved of CPU): its first
    round after is logged as late by as much, counted in the exit summary, and the messages
    due meanwhile are skipped, not sent in a burst."""
    receiver = MavlinkReceiver(autopilot.conn)
    config = tmp_path / "bridge.toml"
    config.write_text(f"[mavlink]\n{EVERY_FAMILY}", encoding="utf-8")
    escs = Escs(can_port, ckesc_reports([1, 2, 3, 4], set()))
    try:
        daemon = start_daemon("--config", str(config))
        autopilot.start_stream(20)
        receiver.wait_for("ESC_STATUS", lambda m: m.rpm[0] == 1000, timeout_s=STARTUP_TIMEOUT_S)
        os.kill(daemon.proc.pid, signal.SIGSTOP)
        time.sleep(1.0)
        os.kill(daemon.proc.pid, signal.SIGCONT)
        resumed = time.monotonic()
        time.sleep(1.0)
        holds = holds_of(daemon)
    finally:
        escs.close()
        receiver.close()
    with receiver._lock:
        status = [t for t, m in receiver.messages if m.get_type() == "ESC_STATUS" and m.index == 0]
    gap, after = max((b - a, b) for a, b in itertools.pairwise(status))
    assert gap >= 0.95, f"no stop in the ESC_STATUS stream (longest gap {gap:.2f} s)"
    # 10 Hz resumed on its grid: within 0.25 s of the first message after the stop, three at
    # most (a catch-up would have sent the ten that were due meanwhile at once).
    assert sum(1 for t in status if after <= t < after + 0.25) <= 3
    assert after - resumed < 0.5, "ESC_STATUS did not come back within 0.5 s of SIGCONT"
    late = [
        float(s) for s in re.findall(r"ESC telemetry went out (\d+\.\d+) s late", daemon.output)
    ]
    assert late and max(late) >= 0.9, daemon.output
    assert holds.count >= 1 and holds.longest_s >= max(late)


def _zenoh_session(endpoint: str) -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def test_zenoh_subscriber_and_queryable(
    can_port: int,
    autopilot: Autopilot,
    start_daemon: Callable[..., Daemon],
) -> None:
    port = free_port(socket.SOCK_STREAM)
    endpoint = f"tcp/127.0.0.1:{port}"
    escs = Escs(can_port, ckesc_reports([1, 2, 3, 4], set()))
    received: dict[str, dict[str, Any]] = {}
    encodings: set[str] = set()
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        with lock:
            received[str(sample.key_expr)] = json.loads(sample.payload.to_bytes())
            encodings.add(str(sample.encoding))

    try:
        daemon = start_daemon("--zenoh-listen", endpoint, "--vehicle", "testcopter")
        autopilot.armed = True
        autopilot.pwm = [1500] * 4
        autopilot.start_stream(50)
        with _zenoh_session(endpoint) as session:
            session.declare_subscriber("esc-bridge/testcopter/**", on_sample)
            deadline = time.monotonic() + 15
            wanted = {
                "esc-bridge/testcopter/esc/3/telemetry",
                "esc-bridge/testcopter/esc/status",
                "esc-bridge/testcopter/esc/3/info",
                "esc-bridge/testcopter/bridge/health",
                "esc-bridge/testcopter/actuators/input",
                "esc-bridge/testcopter/actuators/output",
            }
            while time.monotonic() < deadline:
                with lock:
                    ready = (
                        wanted <= received.keys()
                        and received["esc-bridge/testcopter/bridge/health"].get("state")
                        == "running"
                    )
                if ready:
                    break
                time.sleep(0.05)
            with lock:
                got = dict(received)
            assert wanted <= got.keys(), sorted(got)
            esc3 = got["esc-bridge/testcopter/esc/3/telemetry"]
            assert (esc3["motor"], esc3["node_id"], esc3["online"]) == (3, 3, True)
            assert esc3["rpm"] == 3000
            assert esc3["voltage_v"] == pytest.approx(20.03)
            assert esc3["temperature_c"]["mos"] == 33
            status = got["esc-bridge/testcopter/esc/status"]
            assert [e["rpm"] for e in status["escs"]] == [1000, 2000, 3000, 4000]
            health = got["esc-bridge/testcopter/bridge/health"]
            assert health["state"] == "running" and health["failsafe"] is False
            inputs = got["esc-bridge/testcopter/actuators/input"]
            assert inputs["channels"]["ch1"] == 1500
            outputs = got["esc-bridge/testcopter/actuators/output"]
            assert [c["value"] for c in outputs["commands"]] == [1000.0] * 4  # 1500 µs
            assert all("json" in e for e in encodings)
            # Every key decodes with its record, as a reader on the network decodes it.
            for suffix, record in (
                ("esc/3/telemetry", EscTelemetryPayload),
                ("esc/3/info", EscInfoPayload),
                ("esc/status", EscStatusPayload),
                ("bridge/health", HealthPayload),
                ("actuators/input", ActuatorsInputPayload),
                ("actuators/output", ActuatorsOutputPayload),
            ):
                value = got[f"esc-bridge/testcopter/{suffix}"]
                assert json.loads(record.decode(json.dumps(value).encode()).encode()) == value
            assert HealthPayload.decode(json.dumps(health).encode()).can_rx.frames > 0
            replies = list(session.get("esc-bridge/testcopter/esc/*/telemetry", timeout=5.0))
            samples = [r.ok for r in replies if r.ok is not None]
            answered = {str(s.key_expr): json.loads(s.payload.to_bytes()) for s in samples}
            assert sorted(answered) == [
                f"esc-bridge/testcopter/esc/{n}/telemetry" for n in (1, 2, 3, 4)
            ]
            assert answered["esc-bridge/testcopter/esc/2/telemetry"]["rpm"] == 2000
            alive = list(session.liveliness().get("esc-bridge/testcopter/**", timeout=5.0))
            tokens = [str(r.ok.key_expr) for r in alive if r.ok is not None]
            assert tokens == ["esc-bridge/testcopter/alive"]
    finally:
        escs.close()
    assert daemon.stop() == 0


def test_output_rate_holds_with_zenoh_unreachable(
    tmp_path: Path,
    observer: Observer,
    autopilot: Autopilot,
    start_daemon: Callable[..., Daemon],
) -> None:
    closed = free_port(socket.SOCK_STREAM)  # nothing listens there
    config = tmp_path / "bridge.toml"
    config.write_text(f'[zenoh]\nmode = "client"\nconnect = ["tcp/127.0.0.1:{closed}"]\n')
    daemon = start_daemon("--config", str(config))
    autopilot.armed = True
    autopilot.pwm = [1600] * 4
    autopilot.start_stream(50)
    observer.wait_for(lambda m: m.arbitration_id >> 8 & 0xFFFF == 20101, timeout_s=15)
    time.sleep(0.5)
    start = time.monotonic()
    time.sleep(3.0)
    frames = [m for m in observer.since(start) if m.arbitration_id >> 8 & 0xFFFF == 20101]
    assert len(frames) >= 0.9 * 400 * 3, len(frames)  # one 12b frame per cycle at 400 Hz
    assert all(ckesc_codec.decode(m).message.throttles == (1200,) * 4 for m in frames[-10:])  # type: ignore[union-attr]
    assert daemon.stop() == 0
    assert "Zenoh" in daemon.output


def recorded_types(directory: Path) -> set[int]:
    """The CKESC data types in a recording's candump log so far (a line still being written, with
    no ``#`` yet, is skipped)."""
    found = set()
    for path in directory.glob("*.log"):
        for line in path.read_text(encoding="ascii", errors="replace").splitlines():
            fields = line.split()
            if len(fields) == 3 and "#" in fields[2]:
                found.add(int(fields[2].partition("#")[0], 16) >> 8 & 0xFFFF)
    return found


def test_record_writes_a_decodable_capture_and_tlog(
    tmp_path: Path,
    can_port: int,
    observer: Observer,
    autopilot: Autopilot,
    start_daemon: Callable[..., Daemon],
) -> None:
    from pymavlink import mavutil

    record = tmp_path / "flight"
    escs = Escs(can_port, ckesc_reports([1, 2, 3, 4], set()))
    try:
        daemon = start_daemon("--record", str(record))
        autopilot.armed = True
        autopilot.pwm = [1250] * 4
        autopilot.start_stream(50)

        def commands_1250_us(msg: can.Message) -> bool:
            frame = ckesc_codec.decode(msg)
            return (
                frame is not None
                and isinstance(frame.message, ckesc_records.RawCommand12b)
                and frame.message.throttles == (500,) * 4
            )

        # Until the recording holds the commands and every report (the recorder flushes at
        # least once a second), however long the daemon's start-up takes on a loaded machine.
        observer.wait_for(commands_1250_us, timeout_s=30)
        wanted = {
            ckesc_records.TYPE_RAW_COMMAND_12B,
            ckesc_records.TYPE_MSG1,
            ckesc_records.TYPE_MSG2,
            ckesc_records.TYPE_MSG3,
        }
        deadline = time.monotonic() + 30
        while not wanted <= recorded_types(record) and time.monotonic() < deadline:
            time.sleep(0.2)
        on_bus = {m.arbitration_id >> 8 & 0xFFFF for m in observer.since(0.0)}
        assert wanted <= on_bus, f"not even on the bus: {wanted - on_bus}"
    finally:
        escs.close()
    assert daemon.stop() == 0
    (log,) = record.glob("*.log")
    (tlog,) = record.glob("*.tlog")
    decoded = subprocess.run(
        [ESC_BRIDGE, "decode", "--json", str(log)],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    lines = [json.loads(line) for line in decoded.stdout.splitlines()]
    types = {line.get("type") for line in lines if "type" in line}
    assert {"RawCommand12b", "Msg1", "Msg2", "Msg3"} <= types, types
    commands = [line for line in lines if line.get("type") == "RawCommand12b"]
    assert any(c["fields"]["throttles"] == [500] * 4 for c in commands)
    reader = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    seen: set[str] = set()
    while (msg := reader.recv_match()) is not None:
        seen.add(msg.get_type())
    assert {"HEARTBEAT", "SERVO_OUTPUT_RAW"} <= seen, seen
