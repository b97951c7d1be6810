"""CAN bit rates as people write them: ``500000``, ``500k``, ``1M`` (in ``[can] bitrate`` and
every ``--bitrate``), read into bit/s, and bit/s written back for messages. Pure: no I/O.

The rates are the classical CAN rates the ESC families here use between them; each family's
factory rate is its ``default_bitrate`` (bridge/escs/<family>/family.py).
"""

from __future__ import annotations

import re
from typing import Any, Final

__all__ = ["BITRATES", "FORMS", "bitrate_text", "parse_bitrate"]

BITRATES: Final = (1_000_000, 750_000, 500_000, 250_000, 200_000, 125_000, 100_000, 50_000)
"""The bit rates a bus may be configured with, bit/s."""

FORMS: Final = "a bit rate such as 500000, 500k or 1M, one of " + ", ".join(
    str(rate) for rate in BITRATES
)
"""What a bit rate may look like, for messages."""

_TEXT = re.compile(r"(\d+(?:\.\d+)?)\s*([km]?)(?:bit/s|bps)?", re.IGNORECASE)
_SCALE: Final = {"": 1, "k": 1_000, "m": 1_000_000}


def parse_bitrate(value: Any) -> int:
    """``value`` (an integer, or text such as ``"500k"``, ``"1M"``, ``"1000000"``) in bit/s.

    Raises:
        ValueError: not a bit rate, or not one of :data:`BITRATES`; the message names the value
            and the accepted forms.
    """
    rate: float | None = None
    if isinstance(value, int) and not isinstance(value, bool):
        rate = value
    elif isinstance(value, str):
        match = _TEXT.fullmatch(value.strip())
        if match is not None:
            rate = float(match[1]) * _SCALE[match[2].lower()]
    if rate is None or rate != round(rate) or round(rate) not in BITRATES:
        raise ValueError(f"expected {FORMS}, got {value!r}")
    return round(rate)


def bitrate_text(bps: int) -> str:
    """``500000`` -> ``"500 kbit/s"``, ``1000000`` -> ``"1 Mbit/s"``."""
    if bps % 1_000_000 == 0:
        return f"{bps // 1_000_000} Mbit/s"
    if bps % 1000 == 0:
        return f"{bps // 1000} kbit/s"
    return f"{bps} bit/s"
