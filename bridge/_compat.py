"""The few names esc-bridge takes from Python 3.11's standard library, for Python 3.10.

Python 3.10 is what JetPack 6 (Jetson) and Ubuntu 22.04 ship. On 3.10 the names come from the
backports ``pyproject.toml`` installs there only (``tomli``, ``typing_extensions``); on 3.11 and
later from the standard library. When ``requires-python`` leaves 3.10 behind, ruff's UP036 flags
the branch below and this module goes.
"""

import sys

if sys.version_info >= (3, 11):
    from typing import Self, assert_never

    import tomllib
else:
    import tomli as tomllib
    from typing_extensions import Self, assert_never

__all__ = ["Self", "assert_never", "tomllib"]
