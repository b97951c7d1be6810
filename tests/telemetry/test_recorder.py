"""Recording: CAN frames read by the real CanReader into a candump log that `esc-bridge decode`
and python-can read back, and a tlog that pymavlink reads back."""

from __future__ import annotations

import gc
import logging
import re
import struct
import subprocess
import threading
import time
import uuid
from pathlib import Path

import can
import pytest
from conftest import ESC_BRIDGE
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2

from bridge.config import CanConfig
from bridge.errors import ConfigError
from bridge.escs import registry
from bridge.escs.ckesc import codec, records
from bridge.telemetry.reader import CanReader
from bridge.telemetry.recorder import Recording, candump_line
from bridge.telemetry.state import EscTable

LINE = re.compile(r"^\((\d+\.\d{6})\) (\S+) ([0-9A-F]{3}|[0-9A-F]{8})#([0-9A-F]*)$")


def ckesc_telemetry(node: int, transfer_id: int) -> list[can.Message]:
    messages = (
        records.Msg1(3000 + node, 1100 + 5 * node, records.Msg1Status.RUNNING),
        records.Msg2(24.0 + node / 100, 4.5, 40 + node),
        records.Msg3(40 + node, 30, 50, 45),
    )
    return [
        codec.encode(codec.CkescFrame(codec.default_priority(m), node, None, transfer_id, m))
        for m in messages
    ]


def read_back(path: Path) -> list[can.Message]:
    with can.CanutilsLogReader(path) as reader:
        return list(reader)


def test_can_reader_frames_are_recorded_and_decode_back(tmp_path: Path) -> None:
    channel = f"record-{uuid.uuid4().hex}"
    sender = can.Bus(interface="virtual", channel=channel)
    receiver = can.Bus(interface="virtual", channel=channel)
    directory = tmp_path / "flights" / "today"  # created, parents too
    recording = Recording.open(directory, CanConfig(channel="vcan7"))
    reader = CanReader(
        receiver, EscTable([1, 2, 3, 4]), registry.family("ckesc"), recorder=recording.can
    )
    sent = [m for tid in range(5) for node in (1, 2, 3, 4) for m in ckesc_telemetry(node, tid)]
    sent.append(codec.encode_raw_12b(1, [1100, 1105, 1110, 1115], 7))  # the bridge's command
    sent.append(can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False))
    try:
        reader.start()
        for msg in sent:
            sender.send(msg)
        deadline = time.monotonic() + 5
        while reader.stats.frames < len(sent) and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        reader.close()
        recording.close()
        sender.shutdown()
        receiver.shutdown()
    assert reader.stats.frames == len(sent)

    assert recording.log_path.parent == directory
    assert re.fullmatch(r"esc-bridge-\d{8}-\d{6}\.log", recording.log_path.name)
    assert recording.tlog_path == recording.log_path.with_suffix(".tlog")
    lines = recording.log_path.read_text().splitlines()
    assert len(lines) == len(sent) == recording.frames
    assert all(LINE.match(line) for line in lines), lines[:3]
    assert {match[2] for match in map(LINE.match, lines) if match} == {"vcan7"}

    back = read_back(recording.log_path)
    assert [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in back] == [
        (m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in sent
    ]
    stamps = [m.timestamp for m in back]
    assert stamps == sorted(stamps) and abs(stamps[-1] - time.time()) < 30

    result = subprocess.run(
        [ESC_BRIDGE, "decode", str(recording.log_path)],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert f"-- {len(sent)} frames" in out
    for line in (
        "20  ckesc Msg1",
        "20  ckesc Msg2",
        "20  ckesc Msg3",
        "1  ckesc RawCommand12b",
        "1  not understood (another protocol)",  # the 11-bit frame: no family's
        "-- CRC errors: 0; malformed lines skipped: 0",
    ):
        assert line in out
    assert "node 3   Msg1  speed_rpm=3003 throttle=1115 status=RUNNING" in out
    assert "node 2   Msg2  voltage_v=24.02 current_a=4.5 mos_temp_c=42" in out


def test_candump_line_format() -> None:
    msg = can.Message(
        timestamp=1712345678.123456,
        arbitration_id=0x1F4E5201,
        data=bytes.fromhex("B90B4C040001C0"),
    )
    line = candump_line(msg, "can0", msg.timestamp)
    assert line == "(1712345678.123456) can0 1F4E5201#B90B4C040001C0\n"


def test_other_frame_kinds_read_back(tmp_path: Path) -> None:
    frames = [
        can.Message(timestamp=1.000001, arbitration_id=0x7FF, data=b"", is_extended_id=False),
        can.Message(
            timestamp=2.000002, arbitration_id=0x42, is_extended_id=False, is_remote_frame=True
        ),
        can.Message(
            timestamp=2.250003, arbitration_id=0x1ABCDE, is_remote_frame=True, dlc=4, data=None
        ),
        can.Message(
            timestamp=3.999999,
            arbitration_id=0x10,
            data=bytes(range(12)),
            is_fd=True,
            bitrate_switch=True,
        ),
        can.Message(timestamp=4.000004, is_error_frame=True),
    ]
    with Recording.open(tmp_path) as recording:
        for msg in frames:
            recording.can(msg)
    back = read_back(recording.log_path)
    assert len(back) == len(frames)
    for got, want in zip(back, frames, strict=True):
        assert got.timestamp == pytest.approx(want.timestamp, abs=1e-7)
        assert got.is_error_frame == want.is_error_frame
        if not want.is_error_frame:
            assert (got.arbitration_id, got.is_extended_id) == (
                want.arbitration_id,
                want.is_extended_id,
            )
            assert (got.is_remote_frame, got.dlc, got.is_fd, got.bitrate_switch) == (
                want.is_remote_frame,
                want.dlc,
                want.is_fd,
                want.bitrate_switch,
            )
            assert bytes(got.data or b"") == bytes(want.data or b"")


def test_a_frame_without_timestamp_is_stamped_now(tmp_path: Path) -> None:
    with Recording.open(tmp_path) as recording:
        before = time.time()
        recording.can(can.Message(arbitration_id=0x1, data=b"\x00"))
        after = time.time()
    stamp = read_back(recording.log_path)[0].timestamp
    assert before - 1e-6 <= stamp <= after + 1e-6


def test_lines_reach_the_disk_within_a_second(tmp_path: Path) -> None:
    recording = Recording.open(tmp_path)
    try:
        recording.can(can.Message(timestamp=10.0, arbitration_id=0x1F4E5201, data=b"\x01"))
        deadline = time.monotonic() + 1.2
        text = ""
        while not text and time.monotonic() < deadline:
            time.sleep(0.05)
            text = recording.log_path.read_text()  # another reader, before close()
        assert text == "(10.000000) can0 1F4E5201#01\n"
    finally:
        recording.close()


def test_writers_on_several_threads_lose_and_mix_nothing(tmp_path: Path) -> None:
    per_thread = 3000
    recording = Recording.open(tmp_path)

    def write(thread: int) -> None:
        for i in range(per_thread):
            data = struct.pack(">HH", thread, i)
            recording.can(can.Message(timestamp=1.0, arbitration_id=0x100 + thread, data=data))

    threads = [threading.Thread(target=write, args=(n,)) for n in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    recording.close()
    recording.close()  # a second close does nothing
    back = read_back(recording.log_path)
    assert recording.frames == len(back) == 4 * per_thread
    for n in range(4):
        mine = [struct.unpack(">HH", m.data) for m in back if m.arbitration_id == 0x100 + n]
        assert mine == [(n, i) for i in range(per_thread)]  # each thread's frames, in order
    recording.can(can.Message(arbitration_id=0x1))  # after close: dropped, no error
    assert len(read_back(recording.log_path)) == 4 * per_thread


def test_tlog_reads_back_with_pymavlink(tmp_path: Path) -> None:
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    heartbeat = mav.heartbeat_encode(
        mavlink2.MAV_TYPE_QUADROTOR,
        mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
        mavlink2.MAV_MODE_FLAG_SAFETY_ARMED,
        4,
        mavlink2.MAV_STATE_ACTIVE,
    )
    servo = mav.servo_output_raw_encode(123456, 0, 1100, 1200, 1300, 1400, 0, 0, 0, 0)
    stamps_us = [1_712_345_678_123_456, 1_712_345_678_223_456]
    with Recording.open(tmp_path) as recording:
        for stamp, msg in zip(stamps_us, (heartbeat, servo), strict=True):
            recording.tlog.write(struct.pack(">Q", stamp) + msg.pack(mav))
    log = mavutil.mavlink_connection(str(recording.tlog_path))
    try:
        got_heartbeat = log.recv_match(blocking=False)
        got_servo = log.recv_match(blocking=False)
        assert log.recv_match(blocking=False) is None
    finally:
        log.close()
    assert got_heartbeat.get_type() == "HEARTBEAT"
    assert (got_heartbeat.type, got_heartbeat.custom_mode, got_heartbeat.base_mode) == (
        mavlink2.MAV_TYPE_QUADROTOR,
        4,
        mavlink2.MAV_MODE_FLAG_SAFETY_ARMED,
    )
    assert got_servo.get_type() == "SERVO_OUTPUT_RAW"
    assert (got_servo.servo1_raw, got_servo.servo4_raw) == (1100, 1400)
    assert [got_heartbeat._timestamp, got_servo._timestamp] == pytest.approx(
        [s / 1e6 for s in stamps_us], abs=1e-6
    )


def test_recordings_started_together_get_their_own_files(tmp_path: Path) -> None:
    recordings = [Recording.open(tmp_path) for _ in range(3)]
    for recording in recordings:
        recording.close()
    logs = {r.log_path for r in recordings}
    assert len(logs) == 3 and len({r.tlog_path for r in recordings}) == 3
    assert all(p.exists() for r in recordings for p in (r.log_path, r.tlog_path))


@pytest.mark.parametrize("below", ["", "sub"])
def test_a_directory_that_cannot_be_made_names_itself(tmp_path: Path, below: str) -> None:
    in_the_way = tmp_path / "a-file"
    in_the_way.write_text("not a directory")
    target = in_the_way / below if below else in_the_way
    with pytest.raises(ConfigError, match=f"recording directory {re.escape(str(target))}: "):
        Recording.open(target)


def test_a_forgotten_recording_warns_and_still_writes(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    recording = Recording.open(tmp_path)
    path = recording.log_path
    recording.can(can.Message(timestamp=5.0, arbitration_id=0x1F4E5201, data=b"\x02"))
    with caplog.at_level(logging.WARNING, logger="bridge.telemetry.recorder"):
        del recording
        gc.collect()
    assert "was not closed" in caplog.text
    assert path.read_text() == "(5.000000) can0 1F4E5201#02\n"
