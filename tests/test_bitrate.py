"""Bit rates as written in [can] bitrate and every --bitrate."""

from __future__ import annotations

from typing import Any

import pytest

from bridge.bitrate import bitrate_text, parse_bitrate


@pytest.mark.parametrize(
    ("written", "bps"),
    [
        (1_000_000, 1_000_000),
        ("1000000", 1_000_000),
        ("1M", 1_000_000),
        ("1m", 1_000_000),
        ("500k", 500_000),
        ("500K", 500_000),
        (" 250k ", 250_000),
        ("0.5M", 500_000),
        ("750kbit/s", 750_000),
        ("125kbps", 125_000),
        (50_000, 50_000),
    ],
)
def test_accepted_forms(written: Any, bps: int) -> None:
    assert parse_bitrate(written) == bps


@pytest.mark.parametrize("written", [123, "300k", "1G", "", "fast", "1.0000001M", True, 5e5, None])
def test_refused_forms_name_the_value_and_the_forms(written: Any) -> None:
    with pytest.raises(ValueError) as caught:
        parse_bitrate(written)
    assert str(caught.value) == (
        "expected a bit rate such as 500000, 500k or 1M, one of 1000000, 750000, 500000, "
        f"250000, 200000, 125000, 100000, 50000, got {written!r}"
    )


def test_text() -> None:
    assert [bitrate_text(b) for b in (1_000_000, 500_000, 83_333)] == [
        "1 Mbit/s",
        "500 kbit/s",
        "83333 bit/s",
    ]
