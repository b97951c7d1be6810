"""The validators of configuration keys, shared by :mod:`bridge.config`'s sections and each ESC
family's ``keys.py``: each returns None for a good value, else what was expected ("an integer
1..125"), which :func:`bridge.config.build_config` puts in its message with the file, the
``[section] key`` and the value found. :func:`key` declares a key with its default, validator
and documentation. Pure: no I/O.
"""

from __future__ import annotations

import math
import reprlib
from collections.abc import Callable
from dataclasses import field
from typing import Any

from bridge.bitrate import FORMS, parse_bitrate

# Values quoted in messages are shortened: a 4000-digit number or a 10 000-entry list must not
# bury what was wrong.
_SHOWN = reprlib.Repr()
_SHOWN.maxstring = _SHOWN.maxother = 60
_SHOWN.maxlong = 40


def shown(value: Any) -> str:
    """``repr(value)``, shortened for a message."""
    return _SHOWN.repr(value)


def is_number(v: Any) -> bool:
    """A finite int or float (not a bool) that a float can hold: TOML integers have no bound,
    and ``float(10**400)`` raises."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:  # an int beyond the float range
        return False


def check(predicate: Callable[[Any], bool], expected: str) -> Callable[[Any], str | None]:
    def check(value: Any) -> str | None:
        return None if predicate(value) else expected

    return check


def int_range(lo: int, hi: int) -> Callable[[Any], str | None]:
    return check(
        lambda v: isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi,
        f"an integer {lo}..{hi}",
    )


def float_range(lo: float, hi: float) -> Callable[[Any], str | None]:
    return check(lambda v: is_number(v) and lo <= v <= hi, f"a number {lo:g}..{hi:g}")


def choice(*choices: str) -> Callable[[Any], str | None]:
    return check(lambda v: v in choices, "one of " + ", ".join(repr(c) for c in choices))


def string(v: Any) -> str | None:
    return None if isinstance(v, str) and v else "a non-empty string"


def boolean(v: Any) -> str | None:
    return None if isinstance(v, bool) else "true or false"


def int_list(lo: int, hi: int, *, non_empty: bool = False) -> Callable[[Any], str | None]:
    what = "a non-empty list" if non_empty else "a list"

    def check(v: Any) -> str | None:
        ok = isinstance(v, list) and all(
            isinstance(x, int) and not isinstance(x, bool) and lo <= x <= hi for x in v
        )
        if not ok or (non_empty and not v):
            return f"{what} of integers {lo}..{hi}"
        return None if len(set(v)) == len(v) else f"{what} of distinct integers {lo}..{hi}"

    return check


def optional(check: Callable[[Any], str | None]) -> Callable[[Any], str | None]:
    def optional(v: Any) -> str | None:
        return None if v is None else check(v)

    return optional


def range_pair(v: Any) -> str | None:
    ok = isinstance(v, list) and len(v) == 2 and all(is_number(x) for x in v) and v[0] != v[1]
    return None if ok else "two different numbers [low, high]"


def ordered_pair(v: Any) -> str | None:
    ok = isinstance(v, list) and len(v) == 2 and all(is_number(x) for x in v) and v[0] < v[1]
    return None if ok else "two numbers [low, high] with low < high"


def string_list(v: Any) -> str | None:
    ok = isinstance(v, list) and all(isinstance(x, str) and x for x in v)
    return None if ok else "a list of non-empty strings"


def bitrate_value(v: Any) -> str | None:
    """A CAN bit rate as :func:`bridge.bitrate.parse_bitrate` reads it (``500000``, ``"500k"``,
    ``"1M"``)."""
    try:
        parse_bitrate(v)
    except ValueError:
        return FORMS
    return None


def key(
    default: Any,
    check: Callable[[Any], str | None],
    doc: str,
    convert: Callable[[Any], Any] | None = None,
    *,
    per_esc: bool = False,
) -> Any:
    """A config key: its default, its validator (returns what was expected, or None), its doc,
    and what turns a checked value into the stored one (``convert``; None: kept as written).
    ``per_esc``: a list with one entry per ESC, default 1..N (an ESC family's key; checked
    against ``[escs] ids`` and the mixer's size, and filled, by :mod:`bridge.config`)."""
    metadata = {"check": check, "doc": doc, "convert": convert, "per_esc": per_esc}
    return field(default=default, metadata=metadata)
