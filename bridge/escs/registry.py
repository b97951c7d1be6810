"""The ESC families by name, each imported only when asked for, and their tools.

Adding a family is one line here (its name and where its :class:`~bridge.escs.family.EscFamily`
class is) plus its folder ``bridge/escs/<name>/`` (and the folder in ``pyproject.toml``'s
packages). Everything else (``[output] protocol``, every ``--protocol`` choice, the config keys,
``esc-bridge decode --protocol auto``, the help texts' lists of families) follows from this
table. A family's tools (its simulator, set-up client, set-up commands) are modules beside its
``family.py``, found by :func:`tool`.
"""

from __future__ import annotations

import importlib
from functools import cache
from types import ModuleType
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from bridge.escs.family import EscFamily

FAMILIES: Final[dict[str, str]] = {
    "ckesc": "bridge.escs.ckesc.family:CkescFamily",
    "ft": "bridge.escs.ft.family:FtFamily",
    "dronecan": "bridge.escs.dronecan.family:DronecanFamily",
    "vesc": "bridge.escs.vesc.family:VescFamily",
}
"""Family name -> "module:class" of its :class:`~bridge.escs.family.EscFamily`, in the order
the names are listed (the first is the default protocol) and IDs are claimed."""

DEFAULT: Final = next(iter(FAMILIES))


def names() -> tuple[str, ...]:
    """Every family's name, the default first."""
    return tuple(FAMILIES)


def _entry(name: str) -> tuple[str, str]:
    try:
        module_name, _, class_name = FAMILIES[name].partition(":")
    except KeyError:
        expected = ", ".join(repr(n) for n in FAMILIES)
        raise ValueError(f"unknown ESC protocol {name!r}; expected one of {expected}") from None
    return module_name, class_name


@cache
def family(name: str) -> EscFamily:
    """The family called ``name``, its module imported now if it was not yet.

    Raises:
        ValueError: no family has that name.
    """
    module_name, class_name = _entry(name)
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


def tool(name: str, module: str) -> ModuleType | None:
    """The family ``name``'s tool module ``module`` (``sim``, ``setup`` or ``cli``: see
    :mod:`bridge.escs.family`), imported now; None if the family has none.

    Raises:
        ValueError: no family has that name.
    """
    package = _entry(name)[0].rpartition(".")[0]
    full_name = f"{package}.{module}"
    try:
        return importlib.import_module(full_name)
    except ModuleNotFoundError as exc:
        if exc.name == full_name:
            return None
        raise


def titles(conjunction: str = "and") -> str:
    """Every family's title, for help texts: "CKESC, FT and DroneCAN"."""
    shown = [family(name).title for name in FAMILIES]
    return shown[0] if len(shown) == 1 else f"{', '.join(shown[:-1])} {conjunction} {shown[-1]}"
