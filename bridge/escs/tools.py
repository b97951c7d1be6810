"""What the command line hands a family's set-up commands (its ``cli.py``, see
:mod:`bridge.escs.family`): the bus flags every ``esc-bridge esc`` command shares.

The commands sit in the family's folder, but the configuration and the CLI's flags are above
it: the CLI passes a :class:`BusFlags` to the family's ``add_commands``, so the family imports
nothing of them.
"""

from __future__ import annotations

import argparse
from typing import Protocol

import can


class BusFlags(Protocol):
    """The bus flags of ``esc-bridge esc`` (``--config`` and the CAN flags, as for ``run``)."""

    def add(self, group: argparse._ArgumentGroup, *, bitrate_help: str) -> None:
        """Add ``--config`` and the CAN flags to ``group``."""
        ...

    def open(self, args: argparse.Namespace) -> can.BusABC:
        """The bus the flags name (defaults < ``--config`` file < flags), opened.

        Raises:
            bridge.errors.ConfigError: a flag or the file is invalid, or the file is for
                another family.
            bridge.errors.LinkError: the bus cannot be opened.
        """
        ...

    def describe(self, args: argparse.Namespace) -> str:
        """The bus the flags name, for messages: ``socketcan can7 at 500000 bit/s (500 kbit/s)``.

        Raises:
            bridge.errors.ConfigError: a flag or the file is invalid.
        """
        ...
