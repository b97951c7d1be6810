"""docs/protocols.md, the protocol reference the code cites: every ``docs/protocols.md §N.M`` in
the repository (and every ``§N.M`` inside the page) names a section that exists, nothing cites
the workspace's PROTOCOLS.md any more, and the page's example frames (§3.9, §4.8, §5.5, §6.9)
are what the production codecs encode and decode.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.dronecan import codec as dronecan
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.escs.vesc import codec as vesc
from bridge.escs.vesc import records as vesc_records

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "protocols.md"

SKIPPED_DIRS = {".git", ".venv", "venv", "build", "dist", "node_modules", "__pycache__"}
"""Not the project's text: tool and build output."""
TEXT_SUFFIXES = {".py", ".md", ".toml", ".txt", ".lua", ".service", ".cfg", ".ini", ".yml"}
_SECTION = r"§(\d+(?:\.\d+)?)"
# "docs/protocols.md §2.1, §3.2 and §4.2" (the file name may be in ``backticks``).
CITATION = re.compile(
    r"docs/protocols\.md\W{0,3}" + _SECTION + r"((?:(?:,\s*|\s+and\s+|\s+or\s+)" + _SECTION + r")*)"
)
BARE = re.compile(_SECTION)
HEADING = re.compile(r"^(##|###) (\d+(?:\.\d+)?)\.? ", re.MULTILINE)


def sections(text: str) -> set[str]:
    """The numbers of the page's "## N." and "### N.M" headings."""
    return {number for _, number in HEADING.findall(text)}


def project_files() -> Iterator[Path]:
    for path in sorted(ROOT.rglob("*")):
        relative = path.relative_to(ROOT)
        if any(part in SKIPPED_DIRS or part.endswith(".egg-info") for part in relative.parts):
            continue
        if path.is_file() and path.suffix in TEXT_SUFFIXES:
            yield path


def citations() -> list[tuple[str, str]]:
    """(file:line, section) for every citation of the page outside it."""
    found = []
    for path in project_files():
        if path == DOC:
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        for match in CITATION.finditer(text):
            line = text.count("\n", 0, match.start()) + 1
            where = f"{path.relative_to(ROOT)}:{line}"
            found.append((where, match.group(1)))
            found += [(where, more) for more in BARE.findall(match.group(2))]
    return found


def test_the_page_numbers_its_sections_in_order() -> None:
    numbers = HEADING.findall(DOC.read_text(encoding="utf-8"))
    chapters = [int(number) for level, number in numbers if level == "##"]
    assert chapters == list(range(1, len(chapters) + 1)), chapters
    for level, number in numbers:
        if level == "###":
            chapter, _ = number.split(".")
            assert int(chapter) in chapters, f"§{number} outside any chapter"


def test_every_citation_names_a_section_that_exists() -> None:
    known = sections(DOC.read_text(encoding="utf-8"))
    found = citations()
    # The codecs, their tests and the bus-load check cite the page: an empty list means the
    # pattern no longer finds them, not that all is well.
    assert len(found) >= 40, found
    cited_files = {where.split(":")[0] for where, _ in found}
    assert {"bridge/escs/uavcan_v0.py", "bridge/escs/ft/sim.py"} <= cited_files
    missing = [f"{where}: §{number}" for where, number in found if number not in known]
    assert not missing, "citations of sections docs/protocols.md does not have:\n" + "\n".join(
        missing
    )


def test_every_section_reference_inside_the_page_exists() -> None:
    text = DOC.read_text(encoding="utf-8")
    known = sections(text)
    referenced = set(BARE.findall(text))
    assert {"1.3", "2.6", "3.9", "4.5", "5.2"} <= referenced
    assert referenced <= known, sorted(referenced - known)


def test_nothing_cites_the_workspace_protocols_file() -> None:
    stale = [
        f"{path.relative_to(ROOT)}:{text.count(chr(10), 0, match.start()) + 1}"
        for path in project_files()
        if path != Path(__file__).resolve()
        for text in [path.read_text(encoding="utf-8", errors="replace")]
        for match in re.finditer(r"PROTOCOLS\.md", text)
    ]
    assert not stale, "cite docs/protocols.md instead:\n" + "\n".join(stale)


# --------------------------------------------------------------------------------------------
# The example frames: each row of the page's tables, read from the page, against the record the
# row describes, through the production codec both ways.


def example_rows(section: str) -> dict[str, list[can.Message]]:
    """The rows of the table under "### <section> ": description -> the frames of its data
    column (one frame per backticked hex group, all with the row's CAN ID)."""
    text = DOC.read_text(encoding="utf-8")
    start = text.index(f"### {section} ")
    end = text.find("\n### ", start + 1)
    rows: dict[str, list[can.Message]] = {}
    for line in text[start : end if end > 0 else None].splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) != 3 or not cells[1].startswith("`0x"):
            continue
        what, can_id, data = cells
        arbitration_id = int(can_id.strip("`"), 16)
        rows[what] = [
            can.Message(
                arbitration_id=arbitration_id, data=bytes.fromhex(frame), is_extended_id=True
            )
            for frame in re.findall(r"`([0-9a-f ]+)`", data)
        ]
    return rows


CKESC_EXAMPLES = {
    "RawCommand_12b, group 1, throttles 1000, 1500, 0, 2000": ckesc_codec.CkescFrame(
        0, 0, None, 0, ckesc_records.RawCommand12b(1, (1000, 1500, 0, 2000))
    ),
    "RawCommand_14b, throttles 1000, 1000, 1000, 1000": ckesc_codec.CkescFrame(
        0, 0, None, 0, ckesc_records.RawCommand14b((1000, 1000, 1000, 1000))
    ),
    "RawCommand_10b, throttles 100, 200, 300, 400, 500, 1000": ckesc_codec.CkescFrame(
        0, 0, None, None, ckesc_records.RawCommand10b((100, 200, 300, 400, 500, 1000))
    ),
    "Set LED request to node 5: save, green, steady": ckesc_codec.CkescFrame(
        24, 0, 5, 0, ckesc_records.SetLedRequest(True, ckesc_records.LedColor.GREEN, 0)
    ),
    "MSG1 from node 3: 12000 rpm, throttle 1500, status 0x0100 (running), transfer ID 7": (
        ckesc_codec.CkescFrame(
            31, 3, None, 7, ckesc_records.Msg1(12000, 1500, ckesc_records.Msg1Status.RUNNING)
        )
    ),
    "MSG2 from node 3: 25.20 V, 12.34 A, 45 °C, transfer ID 2": ckesc_codec.CkescFrame(
        31, 3, None, 2, ckesc_records.Msg2(25.20, 12.34, 45)
    ),
}

FT_EXAMPLES = {
    "SET_CURRENT_GEAR_CRC16 to ESC 1: 50 A, gear none": ft_records.FtFrame(
        1, ft_records.SetCurrent(50.0, ft_records.Gear.NONE, crc=True)
    ),
    "SET_CURRENT_GEAR to ESC 2: 1.5 A, gear low": ft_records.FtFrame(
        2, ft_records.SetCurrent(1.5, ft_records.Gear.LOW, crc=False)
    ),
    "SET_CURRENT_BRAKE to ESC 3: 2 A": ft_records.FtFrame(
        3, ft_records.SetCurrentBrake(2.0, crc=False)
    ),
}

DRONECAN_EXAMPLES: dict[str, dronecan.RawCommand | dronecan.NodeStatus] = {
    "RawCommand, four values 1000": dronecan.RawCommand((1000, 1000, 1000, 1000)),
    "RawCommand, values 8191, 0, -8191, 100, 0 (multi-frame)": dronecan.RawCommand(
        (8191, 0, -8191, 100, 0)
    ),
    "NodeStatus from node 10, uptime 5 s, OK, OPERATIONAL (priority 31)": dronecan.NodeStatus(
        5, health=0, mode=0
    ),
}


V = vesc_records
VESC_EXAMPLES = {
    "SET_CURRENT to VESC 23: 51 A": V.VescFrame(23, V.SetCurrent(51.0)),
    "SET_DUTY to VESC 2: -0.25": V.VescFrame(2, V.SetDuty(-0.25)),
    "SET_RPM to every VESC: -7000 erpm": V.VescFrame(255, V.SetRpm(-7000)),
    "PING to VESC 23 from host 254": V.VescFrame(23, V.Ping(254)),
    "PONG to host 254 from VESC 23, a VESC": V.VescFrame(254, V.Pong(23, V.HwType.VESC)),
    "STATUS from VESC 23: 35 000 erpm, 12.3 A, duty 0.456": V.VescFrame(
        23, V.Status(35000, 12.3, 0.456)
    ),
    "STATUS_4 from VESC 23: 35.5 °C, 48.2 °C, 7.5 A, 180°": V.VescFrame(
        23, V.Status4(35.5, 48.2, 7.5, 180.0)
    ),
    "STATUS_5 from VESC 23: tachometer 123 456, 25.2 V": V.VescFrame(23, V.Status5(123456, 25.2)),
}


def same_frame(a: can.Message, b: can.Message) -> bool:
    return (a.arbitration_id, bytes(a.data)) == (b.arbitration_id, bytes(b.data))


def test_the_pages_example_tables_are_the_ones_checked_here() -> None:
    # A row added to the page (or one renamed) must be added here too, or it goes unchecked.
    assert set(example_rows("3.9")) == set(CKESC_EXAMPLES)
    assert set(example_rows("4.8")) == set(FT_EXAMPLES)
    assert set(example_rows("5.5")) == set(DRONECAN_EXAMPLES)
    assert set(example_rows("6.9")) == set(VESC_EXAMPLES)


@pytest.mark.parametrize("what", sorted(CKESC_EXAMPLES))
def test_ckesc_example_frame(what: str) -> None:
    (frame,) = example_rows("3.9")[what]
    expected = CKESC_EXAMPLES[what]
    assert ckesc_codec.decode(frame) == expected
    assert same_frame(ckesc_codec.encode(expected), frame)


@pytest.mark.parametrize("what", sorted(FT_EXAMPLES))
def test_ft_example_frame(what: str) -> None:
    (frame,) = example_rows("4.8")[what]
    expected = FT_EXAMPLES[what]
    assert ft_codec.decode(frame) == expected
    assert same_frame(ft_codec.encode(expected), frame)


@pytest.mark.parametrize("what", sorted(VESC_EXAMPLES))
def test_vesc_example_frame(what: str) -> None:
    (frame,) = example_rows("6.9")[what]
    expected = VESC_EXAMPLES[what]
    assert vesc.decode(frame) == expected
    assert same_frame(vesc.encode(expected), frame)


def test_the_vesc_example_of_the_issue_is_the_pages() -> None:
    # 51 A to VESC 23: EID 0x117, data 00 00 C7 38 (issue 21).
    (frame,) = example_rows("6.9")["SET_CURRENT to VESC 23: 51 A"]
    assert (frame.arbitration_id, bytes(frame.data)) == (0x117, bytes.fromhex("0000C738"))


def test_ft_crc_check_value_is_the_pages() -> None:
    text = DOC.read_text(encoding="utf-8")
    stated = re.search(r"CRC-16/MODBUS of the ASCII bytes `123456789` is `0x([0-9A-F]{4})`", text)
    assert stated is not None
    assert ft_records.crc16_modbus(b"123456789") == int(stated.group(1), 16) == 0x4B37


@pytest.mark.parametrize("what", sorted(DRONECAN_EXAMPLES))
def test_dronecan_example_frames(what: str) -> None:
    frames = example_rows("5.5")[what]
    expected = DRONECAN_EXAMPLES[what]
    decoder = dronecan.Decoder()
    *parts, last = [decoder.decode(frame) for frame in frames]
    assert all(
        isinstance(part, dronecan.DronecanFrame) and isinstance(part.message, dronecan.TransferPart)
        for part in parts
    )
    assert isinstance(last, dronecan.DronecanFrame)
    assert (last.message, last.source_node, last.transfer_id) == (expected, 10, 0)
    assert last.frames == len(frames)
    encoded = dronecan.encode(expected, source_node=10, transfer_id=0, priority=last.priority)
    assert len(encoded) == len(frames)
    assert all(same_frame(a, b) for a, b in zip(encoded, frames, strict=True))
