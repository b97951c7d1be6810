"""`esc-bridge decode` through the real console script, on captures in every text format."""

from __future__ import annotations

import datetime
import json
import subprocess
from pathlib import Path

import can
import pytest
from conftest import ESC_BRIDGE, ROOT

from bridge.capture import BadLine, read_capture
from bridge.escs.dronecan import codec as dronecan_codec
from bridge.escs.dronecan.driver import DronecanDriver
from bridge.escs.family import EscSetup
from bridge.escs.vesc import codec as vesc_codec
from bridge.escs.vesc import records as vesc_records
from bridge.escs.vesc.family import VescFamily
from bridge.escs.vesc.keys import VescKeys

CKESC_LOG = ROOT / "tests" / "data" / "ckesc-quad.log"
FT_LOG = ROOT / "tests" / "data" / "ft-quad.log"


def decode(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [ESC_BRIDGE, "decode", *args], capture_output=True, text=True, timeout=60, check=False
    )


def test_ckesc_capture_text_summary() -> None:
    result = decode(str(CKESC_LOG))
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "node 3   Msg1  speed_rpm=3003 throttle=1110 status=RUNNING" in out
    assert "node 1   Msg2  voltage_v=24.79 current_a=4.5 mos_temp_c=41" in out
    assert "RawCommand12b  group=1 throttles=1100,1105,1110,1115" in out
    assert "line 61: not a frame" in out and "'(not a time) can0 garbage'" in out
    assert "TailByteError" in out
    # Line 44's 11-bit frame is no family's, not a malformed frame of one.
    assert (
        "00000123  de ad be ef              not understood: an 11-bit ID: every ESC family here "
        "uses 29-bit IDs (another device's frame)"
    ) in out
    assert "NotExtendedIdError" not in out
    summary = out[out.index("-- 73 frames") :]
    for line in (
        "20  ckesc Msg1",
        "4  ckesc Msg2",
        "4  ckesc Msg3",
        "40  ckesc RawCommand12b",
        # Node 42's NodeStatus is standard DroneCAN, no longer another protocol's traffic.
        "1  dronecan NodeStatus",
        "1  not understood (another protocol)",
        "2  DlcError",
        "1  TailByteError",
        "-- CRC errors: 0; malformed lines skipped: 1",
    ):
        assert line in summary


def test_nodes_keep_other_vendors_frames_out() -> None:
    # Node 42's 8-byte frame on MSG1's type ID is another vendor's message, not a bad MSG1.
    result = decode(str(CKESC_LOG), "--nodes", "1,2,3,4")
    assert result.returncode == 0
    assert "3  not understood (another protocol)" in result.stdout  # and the 11-bit frame
    assert "1  DlcError" in result.stdout  # only the truncated MSG1 from node 3 is left


def test_ft_capture_counts_crc_errors() -> None:
    result = decode(str(FT_LOG))
    assert result.returncode == 0
    assert "node 2   RealtimeData2  mosfet_temp_c=38.5 motor_temp_c=-2.25" in result.stdout
    assert "CrcError: FT REALTIME_DATA_1 (0x0C), ESC 3" in result.stdout
    assert "-- CRC errors: 1; malformed lines skipped: 0" in result.stdout


def test_json_lines() -> None:
    result = decode(str(FT_LOG), "--json")
    records = [json.loads(line) for line in result.stdout.splitlines()]
    first = records[0]
    assert first["protocol"] == "ft" and first["type"] == "SetCurrent"
    assert first["fields"] == {"current_a": 2.0, "gear": "NONE", "crc": True}
    assert first["can_id"] == "0x00000100" and first["node"] == 1
    errors = [r for r in records if r.get("error") == "CrcError"]
    assert len(errors) == 1 and "expected 0x" in errors[0]["detail"]
    summary = records[-1]["summary"]
    assert summary["frames"] == 201
    assert summary["by_type"]["ft RealtimeData1"] == 40
    assert summary["errors"] == {"CrcError": 1}


def test_protocol_forced() -> None:
    # Read as FT, CKESC IDs are outside FT's space: nothing is understood, nothing crashes.
    result = decode(str(CKESC_LOG), "--protocol", "ft")
    assert result.returncode == 1
    assert "72  not understood (another protocol)" in result.stdout
    assert result.stderr == (
        f"esc-bridge: error: nothing in {CKESC_LOG} decoded as --protocol ft: 73 frames read, 1 "
        "line that is no frame\n"
    )


def dronecan_capture(path: Path) -> Path:
    """A candump log of DroneCAN traffic: the bridge's RawCommand for six ESCs (two frames) and
    NodeStatus, an ESC's esc.Status (three frames) and NodeStatus, then a Status with a bad CRC."""
    frames = DronecanDriver(range(6), clock=lambda: 0).tick_frames(0, [0.1 * i for i in range(6)])
    esc = dronecan_codec.Sender(21)
    status = dronecan_codec.EscStatus(1, 0, 16.5, 2.25, 300.25, -1234, 12)
    frames += esc.frames(status) + esc.frames(dronecan_codec.NodeStatus(7, 0, 0))
    bad = esc.frames(status)
    bad[0].data[0] ^= 1
    with can.Logger(path) as log:
        for i, msg in enumerate(frames + bad):
            msg.timestamp, msg.channel = 1795330000.0 + i / 1000, "can0"
            log.on_message_received(msg)
    return path


def test_dronecan_capture(tmp_path: Path) -> None:
    path = dronecan_capture(tmp_path / "dronecan.log")
    result = decode(str(path), "--protocol", "dronecan")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "dronecan node 10  TransferPart  message_type=RawCommand frame=1" in out
    assert "dronecan node 10  RawCommand  commands=0,819,1638,2457,3276,4096" in out
    assert "dronecan node 10  NodeStatus  uptime_s=0 health=0 mode=0" in out
    assert (
        "dronecan node 21  EscStatus  esc_index=1 error_count=0 voltage_v=16.5 current_a=2.25 "
        "temperature_k=300.25 rpm=-1234 power_rating_pct=12"
    ) in out
    assert "CrcError: DroneCAN transfer 0x10040A15 (transfer ID 1)" in out
    summary = out[out.index("-- 10 frames") :]
    for line in (
        "1  dronecan EscStatus",
        "2  dronecan NodeStatus",
        "1  dronecan RawCommand",
        "5  dronecan TransferPart",
        "1  CrcError",
        "-- CRC errors: 1; malformed lines skipped: 0",
    ):
        assert line in summary
    result = decode(str(path), "--protocol", "dronecan", "--json")
    records = [json.loads(line) for line in result.stdout.splitlines()]
    status = next(r for r in records if r.get("type") == "EscStatus")
    assert status["node"] == 21 and status["fields"]["rpm"] == -1234
    assert records[-1]["summary"]["by_type"]["dronecan TransferPart"] == 5


def test_dronecan_capture_auto(tmp_path: Path) -> None:
    """CKESC's ID space holds DroneCAN's; auto tries CKESC, then DroneCAN, which understands
    them. The bad CRC is DroneCAN's to report: CKESC does not know the type."""
    path = dronecan_capture(tmp_path / "dronecan.log")
    auto = decode(str(path)).stdout
    assert auto == decode(str(path), "--protocol", "dronecan").stdout
    assert "5  dronecan TransferPart" in auto and "1  CrcError" in auto


def vesc_capture(path: Path, malformed: bool) -> Path:
    """A candump log of a VESC bus: the bridge's duty commands to VESCs 1..4, each VESC's STATUS,
    STATUS_4 and STATUS_5, a PING and its PONG, a NOTIFY_BOOT; with ``malformed`` also a STATUS
    cut to 7 bytes and a 6-byte SET_CURRENT (the off-delay form the bridge does not read)."""
    v = vesc_records
    driver = VescFamily().driver(EscSetup((1, 2, 3, 4), VescKeys()))
    frames = [driver.tick_frames(tick, [0.1, 0.2, 0.3, 0.4])[0] for tick in range(4)]
    for n in (1, 2, 3, 4):
        for record in (
            v.Status(-7000 * n, 2.5 * n, -0.1 * n),
            v.Status4(30.0 + n, 40.0 + n, 1.5 * n, 0.0),
            v.Status5(100 * n, 24.8),
        ):
            frames.append(vesc_codec.encode(v.VescFrame(n, record)))
    frames.append(vesc_codec.encode(v.VescFrame(2, v.Ping(254))))
    frames.append(vesc_codec.encode(v.VescFrame(254, v.Pong(2, v.HwType.VESC))))
    frames.append(vesc_codec.encode(v.VescFrame(3, v.NotifyBoot("60_MK6"))))
    if malformed:
        frames.append(can.Message(arbitration_id=0x903, data=bytes(7), is_extended_id=True))
        frames.append(can.Message(arbitration_id=0x104, data=bytes(6), is_extended_id=True))
    with can.Logger(path) as log:
        for i, msg in enumerate(frames):
            msg.timestamp, msg.channel = 1795330000.0 + i / 1000, "can0"
            log.on_message_received(msg)
    return path


def test_vesc_capture(tmp_path: Path) -> None:
    path = vesc_capture(tmp_path / "vesc.log", malformed=True)
    result = decode(str(path), "--protocol", "vesc")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "vesc  node 2   SetDuty  duty=0.19" in out
    assert "vesc  node 3   Status  erpm=-21000 motor_current_a=7.5 duty=-0.3" in out
    assert (
        "vesc  node 4   Status4  fet_temp_c=34 motor_temp_c=44 input_current_a=6 pid_position_deg=0"
    ) in out
    assert "vesc  node 1   Status5  tachometer=100 input_voltage_v=24.8" in out
    assert "vesc  node 2   Ping  sender_id=254" in out
    assert "vesc  node 254 Pong  controller_id=2 hw_type=0" in out
    assert "vesc  node 3   NotifyBoot  hw_name=60_MK6" in out
    assert "DlcError: VESC STATUS (9), controller 3: 7 data bytes, expected 8" in out
    assert "DlcError: VESC SET_CURRENT (1), controller 4: 6 data bytes, expected 4 (the" in out
    summary = out[out.index("-- 21 frames") :]
    for line in ("4  vesc SetDuty", "4  vesc Status", "1  vesc Pong", "2  DlcError"):
        assert line in summary
    result = decode(str(path), "--protocol", "vesc", "--json")
    records = [json.loads(line) for line in result.stdout.splitlines()]
    status = next(r for r in records if r.get("type") == "Status4")
    assert status["node"] == 1 and status["fields"]["input_current_a"] == 1.5


def test_vesc_capture_auto(tmp_path: Path) -> None:
    """VESC's ID space is FT's: auto tries FT first and gives VESC what FT does not understand.
    Every frame of a well-formed VESC capture of IDs 1..4 decodes as VESC's that way."""
    path = vesc_capture(tmp_path / "vesc.log", malformed=False)
    auto = decode(str(path)).stdout
    assert auto == decode(str(path), "--protocol", "vesc").stdout
    assert " ft " not in auto and "Error" not in auto


@pytest.mark.parametrize(
    ("suffix", "writer"),
    [(".asc", can.ASCWriter), (".csv", can.CSVWriter), (".trc", can.TRCWriter)],
)
def test_other_formats_with_a_bad_line(
    tmp_path: Path, suffix: str, writer: type[can.io.generic.MessageWriter]
) -> None:
    frames = [m for m in read_capture(FT_LOG) if isinstance(m, can.Message)][:30]
    path = tmp_path / f"capture{suffix}"
    with writer(path) as out:
        for msg in frames:
            out.on_message_received(msg)
    lines = path.read_text().splitlines(keepends=True)
    # Corrupt a frame line near the end: a bad hex data byte, or a CSV row short of columns.
    # (A line python-can's ASC reader does not recognise as a frame at all is an "event" it
    # skips by design; a frame line it cannot parse is what we must report and step over.)
    target = len(lines) - 10 if suffix != ".asc" else len(lines) - 11
    bad_data = lines[target].rstrip("\n").rsplit(" ", 1)[0] + " ZZ\n"
    lines[target] = "1.0,zz,1\n" if suffix == ".csv" else bad_data
    path.write_text("".join(lines))
    items = list(read_capture(path))
    bad = [i for i in items if isinstance(i, BadLine)]
    good = [i for i in items if isinstance(i, can.Message)]
    assert len(bad) == 1 and bad[0].line_no == target + 1
    assert len(good) == len(frames) - 1
    assert [m.arbitration_id for m in good[-5:]] == [m.arbitration_id for m in frames[-5:]]
    result = decode(str(path))
    assert f"line {target + 1}: not a frame" in result.stdout
    assert "malformed lines skipped: 1" in result.stdout


def test_candump_default_output(tmp_path: Path) -> None:
    # What `candump can0` prints on a terminal (and with -t a, -t A, -x, -a), saved as .log.
    path = tmp_path / "plain.log"
    path.write_text(
        "  can0  1F4E5203   [7]  E0 2E DC 05 00 01 C7\n"
        " (1795330000.000100)  can0  00000100   [7]  00 03 0D 40 00 47 84\n"
        " (2026-11-24 23:59:59.500000)  can0  1F4E5203   [7]  E0 2E DC 05 00 01 C7\n"
        "  can0  RX - -  1E4   [3]  00 11 22   '..\"'\n"
        "  can0  123   [0]  remote request\n"
        "\n"
        "can0 1F4E5201 [8] 11 22\n"
    )
    result = decode(str(path))
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    msg1 = "1F4E5203  e0 2e dc 05 00 01 c7     ckesc node 3   Msg1  speed_rpm=12000 throttle=1500"
    assert lines[0] == f"      0.000000  {msg1} status=RUNNING"
    assert lines[1] == (
        "1795330000.000100  00000100  00 03 0d 40 00 47 84     ft    node 1   SetCurrent  "
        "current_a=2 gear=NONE crc=True"
    )
    stamp = datetime.datetime(2026, 11, 24, 23, 59, 59, 500000).timestamp()
    assert lines[2] == f"{stamp:14.6f}  {msg1} status=RUNNING"
    assert lines[3].endswith(
        "000001E4  00 11 22                 not understood: an 11-bit ID: "
        "every ESC family here uses 29-bit IDs (another device's frame)"
    )
    assert lines[4].endswith("not understood: a remote (RTR) frame: no ESC family here uses them")
    # The last line says [8] but carries 2 bytes: neither format.
    assert lines[5] == (
        "line 7: not a frame (expected a candump line: `candump -L` such as '(1712345678.123456) "
        "can0 1F4E5201#B90B4C04', or candump's default such as '  can0  1F4E5201   [4]  B9 0B 4C "
        "04'): 'can0 1F4E5201 [8] 11 22'"
    )
    assert "-- 5 frames" in result.stdout and "malformed lines skipped: 1" in result.stdout


def test_a_capture_of_no_frames_fails(tmp_path: Path) -> None:
    path = tmp_path / "notes.log"
    path.write_text("bus was quiet\nsee ticket 12\n")
    result = decode(str(path))
    assert result.returncode == 1
    assert [line[:33] for line in result.stdout.splitlines()[:2]] == [
        "line 1: not a frame (expected a c",
        "line 2: not a frame (expected a c",
    ]
    assert result.stderr == (
        f"esc-bridge: error: nothing in {path} decoded as any ESC protocol: 0 frames read, 2 "
        "lines that are no frame\n"
    )


def test_unknown_format_and_missing_file(tmp_path: Path) -> None:
    odd = tmp_path / "capture.pcap"
    odd.write_bytes(b"\x00")
    result = decode(str(odd))
    assert result.returncode == 2
    assert "unknown format '.pcap'; expected one of .asc, .blf" in result.stderr
    result = decode(str(tmp_path / "absent.log"))
    assert result.returncode == 2 and "no such file" in result.stderr


def test_bad_nodes_argument() -> None:
    result = decode(str(CKESC_LOG), "--nodes", "1,x")
    assert result.returncode == 2
    assert "not a comma-separated list of node IDs" in result.stderr
