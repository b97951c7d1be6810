"""A recording's files (bridge/plot/recording.py): found in a --record directory with clear
errors when they are not there, and the tlog read for the autopilot's HEARTBEATs and the
STATUSTEXTs, past damaged records, from frames pymavlink packs as the bridge's link does."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v10 import common as mavlink1

from bridge.errors import ConfigError
from bridge.mavlink import load_dialect
from bridge.plot.recording import (
    RecordingFiles,
    find_recordings,
    read_tlog,
    tlog_events,
    tlog_records,
)
from bridge.telemetry.recorder import Recording

T0_US = 1_790_000_000_000_000


def record(stamp_us: int, frame: bytes) -> bytes:
    return struct.pack(">Q", stamp_us) + frame


def frames() -> tuple[Any, Any, Any]:
    """The autopilot's, the bridge's and a ground station's MAVLink 2 encoders."""
    dialect: Any = load_dialect()
    return (
        dialect.MAVLink(None, srcSystem=1, srcComponent=1),
        dialect.MAVLink(None, srcSystem=1, srcComponent=191),
        dialect.MAVLink(None, srcSystem=255, srcComponent=190),
    )


def heartbeat(mav: Any, autopilot: int, armed: bool, kind: int = 2) -> bytes:
    base_mode = 0x80 if armed else 0
    return bytes(mav.heartbeat_encode(kind, autopilot, base_mode, 0, 4).pack(mav))


def test_recordings_are_found_oldest_first_and_checked(tmp_path: Path) -> None:
    with Recording.open(tmp_path) as first:
        pass
    later = tmp_path / f"{first.log_path.stem}-1.log"
    later.write_text("")
    (tmp_path / "notes.txt").write_text("not a recording")
    found = find_recordings(tmp_path)
    assert [r.name for r in found] == [first.log_path.stem, later.stem]
    found[0].check()
    assert found[0].log_path == first.log_path and found[0].tlog_path == first.tlog_path
    with pytest.raises(ConfigError, match=rf"its MAVLink tlog {later.stem}\.tlog is missing"):
        found[1].check()
    with pytest.raises(ConfigError, match=r"its CAN capture .*\.log is missing"):
        RecordingFiles(tmp_path, "esc-bridge-20000101-000000").check()


def test_a_directory_that_is_not_a_recording_says_what_was_expected(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such directory"):
        find_recordings(tmp_path / "absent")
    (tmp_path / "file").write_text("")
    with pytest.raises(ConfigError, match="not a directory; expected the directory given to"):
        find_recordings(tmp_path / "file")
    with pytest.raises(ConfigError, match=r"not a recording; expected esc-bridge-YYYYmmdd"):
        find_recordings(tmp_path)


def test_the_tlog_gives_the_autopilots_heartbeats_and_every_statustext(tmp_path: Path) -> None:
    autopilot, bridge, gcs = frames()
    dialect: Any = load_dialect()
    ardupilot, invalid = dialect.MAV_AUTOPILOT_ARDUPILOTMEGA, dialect.MAV_AUTOPILOT_INVALID
    v1 = mavlink1.MAVLink(None, srcSystem=1, srcComponent=1)
    servo = autopilot.servo_output_raw_encode(0, 0, 1100, 1100, 1100, 1100, 0, 0, 0, 0)
    text = bridge.statustext_encode(2, b"ESC out: FAILSAFE input stale, motors stopped")
    data = b"".join(
        [
            record(T0_US, heartbeat(autopilot, ardupilot, armed=False)),
            record(T0_US + 1, heartbeat(bridge, invalid, armed=False, kind=18)),  # the bridge's
            record(T0_US + 2, heartbeat(gcs, invalid, armed=True, kind=6)),  # a ground station
            record(T0_US + 100_000, bytes(servo.pack(autopilot))),
            b"\x00\x01junk",  # a damaged stretch: the reader finds the next record
            record(T0_US + 200_000, heartbeat(autopilot, ardupilot, armed=True)),
            record(T0_US + 300_000, bytes(text.pack(bridge))),
            record(T0_US + 400_000, bytes(v1.heartbeat_encode(2, ardupilot, 0x80, 0, 4).pack(v1))),
            record(T0_US + 500_000, heartbeat(autopilot, ardupilot, armed=True))[:-3],  # cut
        ]
    )
    events = tlog_events(data, dialect)
    assert [(round(b.t_s * 1e6) - T0_US, b.armed) for b in events.heartbeats] == [
        (0, False),
        (200_000, True),
        (400_000, True),
    ]
    (got,) = events.texts
    assert (got.text, got.severity, got.system, got.component) == (
        "ESC out: FAILSAFE input stale, motors stopped",
        2,
        1,
        191,
    )
    assert (events.records, events.bad_records) == (7, 2)
    assert events.first_s == T0_US / 1e6
    assert events.last_s == pytest.approx((T0_US + 400_000) / 1e6)
    path = tmp_path / "flight.tlog"
    path.write_bytes(data)
    assert read_tlog(path) == events
    with pytest.raises(ConfigError, match="cannot read it"):
        read_tlog(tmp_path)


def test_tlog_records_split_v1_and_v2_frames() -> None:
    autopilot, _, _ = frames()
    v2 = heartbeat(autopilot, 3, armed=True)
    v1 = bytes(mavlink1.MAVLink(None).heartbeat_encode(2, 3, 0, 0, 4).pack(mavlink1.MAVLink(None)))
    got = list(tlog_records(record(T0_US, v2) + record(T0_US + 1, v1)))
    assert got == [(T0_US / 1e6, v2), ((T0_US + 1) / 1e6, v1)]
    assert list(tlog_records(b"")) == []
