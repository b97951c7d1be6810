"""The MCAP writer (bridge/telemetry/mcap_out.py), fed from several threads as the bridge feeds
it: every item one message on its channel, in log-time order, with the log and publish times it
should have; what JSON cannot carry counted; a writer that falls behind drops and counts; a file
cut short before the summary still reads back; the log module's lines as foxglove.Log."""

from __future__ import annotations

import io
import json
import logging
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from bridge.errors import ConfigError
from bridge.mavlink import load_dialect
from bridge.mavlink.traffic import TrafficReader
from bridge.plot.mcap_flight import read_mcap
from bridge.telemetry import mcap_channels, mcap_out
from bridge.telemetry.mcap_channels import BridgeState, metadata
from bridge.telemetry.mcap_out import LogHandler, McapRecording
from bridge.telemetry.state import EscSnapshot, LastCommand

T0_S = 1_790_000_000.0


def snapshot(motor: int, rpm: int, voltage_v: float = 24.0) -> EscSnapshot:
    return EscSnapshot(
        motor=motor,
        node_id=motor + 10,
        online=True,
        age_ms=0.0,
        rpm=rpm,
        voltage_v=voltage_v,
        current_a=1.5,
        motor_current_a=None,
        throttle=0.5,
        mos_temp_c=40.0,
        capacitor_temp_c=None,
        motor_temp_c=None,
        mcu_temp_c=None,
        status=None,
        failure_flags=0,
        frames=1,
        errors=0,
        consumed_mah=0.5,
    )


def messages(data: bytes) -> list[tuple[str, int, int, Any]]:
    reader = make_reader(io.BytesIO(data))
    return [
        (channel.topic, message.log_time, message.publish_time, json.loads(message.data))
        for _, channel, message in reader.iter_messages(log_time_order=False)
    ]


class Sink(io.BytesIO):
    """A file whose bytes stay readable after close()."""

    def close(self) -> None:
        self.kept = self.getvalue()
        super().close()


def traffic() -> TrafficReader:
    return TrafficReader(load_dialect(), "servo_output_raw", (1, 1), (1, 191))


def test_items_from_many_threads_become_messages_in_log_time_order(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # One batch, written at close: the feeders' items interleave out of time order in it.
    monkeypatch.setattr(mcap_out, "WRITE_INTERVAL_S", 60.0)
    sink = Sink()
    recording = McapRecording(sink, traffic(), metadata("fam", [11, 12], pole_pairs="7"))
    autopilot: Any = load_dialect().MAVLink(None, srcSystem=1, srcComponent=1)
    recording.autopilot_clock = lambda now_ns: 50_000_000  # the autopilot's boot clock now
    servo = bytes(
        autopilot.servo_output_raw_encode(49_000_000, 0, 1500, 1600, 0, 0, 0, 0, 0, 0).pack(
            autopilot
        )
    )

    def feed_escs(motor: int) -> None:
        for i in range(200):
            recording.esc(snapshot(motor, 1000 + i), T0_S + i / 100 + motor / 1000)

    threads = [threading.Thread(target=feed_escs, args=(m,)) for m in (1, 2)]
    for thread in threads:
        thread.start()
    recording.commands([LastCommand(1, 11, 0.5, "throttle"), LastCommand(2, 12, None, "")], T0_S)
    recording.mavlink(round(T0_S * 1e6) + 500, servo)
    recording.state(BridgeState(state="running", failsafe=False, severity=6, text="armed"))
    for thread in threads:
        thread.join()
    recording.close()
    recording.close()  # a second close does nothing
    got = messages(sink.kept)
    assert len(got) == recording.messages == 403 and recording.errors == recording.dropped == 0
    log_times = [m[1] for m in got]
    assert log_times == sorted(log_times)
    by_topic: dict[str, list[tuple[str, int, int, Any]]] = {}
    for message in got:
        by_topic.setdefault(message[0], []).append(message)
    assert sorted(by_topic) == sorted(
        [
            "/esc/1/telemetry",
            "/esc/2/telemetry",
            "/bridge/commands",
            "/autopilot/outputs",
            "/bridge/state",
        ]
    )
    first = by_topic["/esc/1/telemetry"][0]
    assert first[1] == first[2] == round((T0_S + 0.001) * 1e9)
    assert first[3]["rpm"] == 1000 and first[3]["node_id"] == 11
    assert [m[3]["rpm"] for m in by_topic["/esc/2/telemetry"]] == list(range(1000, 1200))
    assert by_topic["/bridge/commands"][0][3] == {
        "commands": [
            {"motor": 1, "node_id": 11, "value": 0.5, "unit": "throttle"},
            {"motor": 2, "node_id": 12, "value": None, "unit": ""},
        ]
    }
    ((_, log_ns, publish_ns, outputs),) = by_topic["/autopilot/outputs"]
    assert outputs["channels"] == {"ch1": 1500.0, "ch2": 1600.0}
    assert log_ns == round(T0_S * 1e6) * 1000 + 500_000
    # Stamped 1 s before the autopilot's clock read 50 s: 1 s before the writer looked (now,
    # give or take the test's run), whatever the log time says (made up here).
    assert abs(publish_ns - (time.time_ns() - 1_000_000_000)) < 30e9
    reader = make_reader(io.BytesIO(sink.kept))
    (meta,) = list(reader.iter_metadata())
    assert (meta.name, meta.metadata) == (
        "esc-bridge",
        {"protocol": "fam", "esc_ids": "11,12", "pole_pairs": "7"},
    )


def test_what_json_cannot_carry_is_counted_and_the_rest_written() -> None:
    sink = Sink()
    recording = McapRecording(sink)
    recording.esc(snapshot(1, 100, voltage_v=float("nan")), T0_S)
    recording.esc(snapshot(1, 200), T0_S + 1)
    recording.mavlink(1, b"not kept: no traffic reader")
    recording.close()
    assert [m[3]["rpm"] for m in messages(sink.kept)] == [200]
    assert (recording.messages, recording.errors) == (1, 1)


def test_a_writer_that_falls_behind_drops_and_counts(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(mcap_out, "MAX_PENDING", 10)
    monkeypatch.setattr(mcap_out, "WRITE_INTERVAL_S", 60.0)  # the writer never looks
    sink = Sink()
    recording = McapRecording(sink)
    for i in range(25):
        recording.esc(snapshot(1, i), T0_S + i)
    recording.close()
    assert (recording.messages, recording.dropped) == (10, 15)
    recording.esc(snapshot(1, 99), T0_S + 99)  # after close: nowhere to go, not a drop
    assert recording.dropped == 15


def test_a_file_cut_short_reads_back_to_its_last_chunk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(mcap_out, "WRITE_INTERVAL_S", 0.02)
    monkeypatch.setattr(mcap_out, "CHUNK_INTERVAL_S", 0.05)
    path, cut = tmp_path / "flight.mcap", tmp_path / "cut.mcap"
    with path.open("wb") as file:
        recording = McapRecording(file, metadata=metadata("fam", [11]))
        recording.esc(snapshot(1, 1234), T0_S)
        recording.commands([LastCommand(1, 11, 0.25, "throttle")], T0_S + 0.1)
        deadline = time.monotonic() + 10
        captured = None
        while captured is None and time.monotonic() < deadline:
            time.sleep(0.02)
            cut.write_bytes(path.read_bytes())  # as a bridge that died now would leave it
            try:
                captured, _, ids = read_mcap(cut)
            except ConfigError:  # no chunk written yet
                continue
        recording.close()
    assert captured is not None, "no chunk reached the file within 10 s"
    assert ids == (11,)
    assert captured.telemetry[11].rpm.values == (1234.0,)
    assert captured.by_node[11]["throttle"].values == (0.25,)


def test_log_lines_are_foxglove_logs() -> None:
    sink = Sink()
    recording = McapRecording(sink)
    logger = logging.getLogger("bridge.test_mcap_out")
    logger.setLevel(logging.DEBUG)
    handler = LogHandler(recording)
    logger.addHandler(handler)
    try:
        logger.warning("%d ESCs offline", 2)
        try:
            raise RuntimeError("boom")
        except RuntimeError:
            logger.exception("it failed")
    finally:
        logger.removeHandler(handler)
    recording.close()
    got = [m[3] for m in messages(sink.kept)]
    assert [(m["level"], m["name"], m["file"]) for m in got] == [
        (mcap_channels.LOG_WARNING, "bridge.test_mcap_out", "test_mcap_out.py"),
        (mcap_channels.LOG_ERROR, "bridge.test_mcap_out", "test_mcap_out.py"),
    ]
    assert got[0]["message"] == "2 ESCs offline" and got[0]["line"] > 0
    assert (
        got[1]["message"].startswith("it failed\nTraceback")
        and "RuntimeError: boom" in got[1]["message"]
    )
    assert got[0]["timestamp"]["sec"] > 1_700_000_000
