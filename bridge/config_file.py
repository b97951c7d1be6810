"""Reading a configuration file into raw tables, and laying the command line's over them
(validated afterwards, once, by :func:`bridge.config.build_config`)."""

from __future__ import annotations

import codecs
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from bridge._compat import tomllib
from bridge.errors import ConfigError

# A config file is a few kB; anything much bigger is the wrong file (or /dev/zero), and is
# refused before it is read into memory.
MAX_CONFIG_BYTES = 1 << 20


def read_config_file(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file into raw tables (validated later by :func:`build_config`).

    The file must be UTF-8 text (a leading byte-order mark is allowed, as Windows editors write
    one) of at most :data:`MAX_CONFIG_BYTES`; an empty file is valid and means the defaults.

    Raises:
        ConfigError: the file is missing, a directory or a device, unreadable, too big, binary
            or not UTF-8 (naming the byte offset), or not valid TOML.
    """
    path = Path(path)
    try:
        # Not even opened: a serial port would wait for its carrier forever, /dev/zero never ends.
        if stat.S_ISCHR(path.stat().st_mode) or stat.S_ISBLK(path.stat().st_mode):
            raise ConfigError(f"{path}: a device, not a file; expected a TOML config file")
        with path.open("rb") as file:
            data = file.read(MAX_CONFIG_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory; expected a TOML config file") from None
    except OSError as exc:
        raise ConfigError(
            f"{path}: cannot read: {exc.strerror or exc}; expected a readable TOML config file"
        ) from exc
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(
            f"{path}: larger than {MAX_CONFIG_BYTES // 1024} KiB; expected a TOML config file"
        )
    text = _decode_text(data, path)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    except RecursionError:
        raise ConfigError(
            f"{path}: not valid TOML: arrays or inline tables nested too deeply"
        ) from None
    except ValueError as exc:
        # tomllib lets int()'s limit of 4300 digits through as a plain ValueError.
        reason = str(exc).split(";")[0]  # not its advice to change the interpreter's limit
        raise ConfigError(f"{path}: not valid TOML: {reason}; expected a 64-bit integer") from exc


def _decode_text(data: bytes, path: Path) -> str:
    """``data`` as text, or ConfigError naming the offset of the first byte that is not."""
    nul = data.find(b"\0")
    start = len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0
    try:
        text = data[start:].decode("utf-8")
    except UnicodeDecodeError as exc:
        offset = start + exc.start
        if 0 <= nul < offset:
            raise ConfigError(
                f"{path}: a binary file (NUL byte at offset {nul}); expected a TOML text file"
            ) from None
        raise ConfigError(
            f"{path}: not UTF-8 text: byte 0x{data[offset]:02X} at offset {offset} "
            f"({exc.reason}); expected a UTF-8 TOML file"
        ) from None
    if nul >= 0:
        raise ConfigError(
            f"{path}: a binary file (NUL byte at offset {nul}); expected a TOML text file"
        )
    return text


def merge(base: dict[str, Any], override: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Overlay ``override``'s keys on ``base``'s, section by section (override wins)."""
    merged = {
        name: dict(table) if isinstance(table, dict) else table for name, table in base.items()
    }
    for name, table in override.items():
        section = merged.setdefault(name, {})
        if isinstance(section, dict):
            section.update(table)
    return merged
