"""docs/troubleshooting.md quotes the bridge's messages: each one it explains must still be one
the code can say (each literal part, between the page's "…", found in bridge/), and each
warning the start-up checks and the absence watch give must have its entry."""

from __future__ import annotations

import re

from conftest import ROOT

PAGE = ROOT / "docs" / "troubleshooting.md"
# Adjacent string literals, as the code splits long messages over lines: joined up again.
_JOIN = re.compile(r"\"\s*\n\s*(?:rf|fr|f|r)?\"")


def _source() -> str:
    return "\n".join(
        _JOIN.sub("", path.read_text(encoding="utf-8")) for path in (ROOT / "bridge").rglob("*.py")
    )


def _quoted_messages() -> list[str]:
    page = PAGE.read_text(encoding="utf-8")
    headings = [
        quoted
        for heading in re.findall(r"^###.*$", page, flags=re.MULTILINE)
        for quoted in re.findall(r"`([^`]+)`", heading)
    ]
    rows = re.findall(r"^\| `([^`]+)` \|", page, flags=re.MULTILINE)
    return headings + rows


def test_every_quoted_message_is_one_the_bridge_says() -> None:
    source = _source()
    quoted = _quoted_messages()
    assert len(quoted) >= 25
    missing = []
    for message in quoted:
        parts = [part.strip(" .,:;()[]") for part in message.split("…")]
        missing += [
            f"{message!r}: {part!r}" for part in parts if len(part) > 2 and part not in source
        ]
    assert missing == []


def test_the_new_warnings_are_explained() -> None:
    quoted = " ".join(_quoted_messages())
    for start in (
        "no HEARTBEAT from the autopilot",
        "no telemetry from",
        "too slow for input_timeout_ms",
        "but [can] bitrate is",
        "does not exist",
        "is down",
        "has no bit rate set",
        "the controller stopped sending",
        "nothing answered",
        "not a frame",
        "output loop runs WITHOUT real-time priority",
        "CAN: FAULT bus stuck",
        "CAN: FAULT interface down",
        "CAN: FAULT interface gone",
        "CAN: FAULT BUS-OFF",
        "CAN: ERROR-PASSIVE",
        "CAN: receive queue full",
        "frames claiming to be the autopilot",
        "now speaks from",
    ):
        assert start in quoted, start
