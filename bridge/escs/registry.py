"""The ESC families by name, each imported only when asked for.

Adding a family is one line here (its name and where its :class:`~bridge.escs.family.EscFamily`
class is) plus its folder ``bridge/escs/<name>/`` (and the folder in ``pyproject.toml``'s
packages). Everything else (``[output] protocol``, every ``--protocol`` choice, the config keys,
``esc-bridge decode --protocol auto``) follows from this table.
"""

from __future__ import annotations

import importlib
from functools import cache
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from bridge.escs.family import EscFamily

FAMILIES: Final[dict[str, str]] = {
    "ckesc": "bridge.escs.ckesc.family:CkescFamily",
    "ft": "bridge.escs.ft.family:FtFamily",
    "dronecan": "bridge.escs.dronecan.family:DronecanFamily",
}
"""Family name -> "module:class" of its :class:`~bridge.escs.family.EscFamily`, in the order
the names are listed (the first is the default protocol) and IDs are claimed."""

DEFAULT: Final = next(iter(FAMILIES))


def names() -> tuple[str, ...]:
    """Every family's name, the default first."""
    return tuple(FAMILIES)


@cache
def family(name: str) -> EscFamily:
    """The family called ``name``, its module imported now if it was not yet.

    Raises:
        ValueError: no family has that name.
    """
    try:
        module_name, _, class_name = FAMILIES[name].partition(":")
    except KeyError:
        expected = ", ".join(repr(n) for n in FAMILIES)
        raise ValueError(f"unknown ESC protocol {name!r}; expected one of {expected}") from None
    family_class = getattr(importlib.import_module(module_name), class_name)
    found: EscFamily = family_class()
    return found


def families() -> tuple[EscFamily, ...]:
    """Every family (each imported)."""
    return tuple(family(name) for name in FAMILIES)


def families_of(arbitration_id: int) -> tuple[EscFamily, ...]:
    """The families whose ID space holds ``arbitration_id``, in :data:`FAMILIES` order (ID
    spaces may overlap: UAVCAN v0 vendors share theirs)."""
    return tuple(candidate for candidate in families() if candidate.owns(arbitration_id))


def family_of(arbitration_id: int) -> EscFamily | None:
    """The first family (in :data:`FAMILIES` order) whose ID space holds ``arbitration_id``."""
    candidates = families_of(arbitration_id)
    return candidates[0] if candidates else None
