"""Zenoh sessions on this machine that a monitor cannot scout for, and where they listen.

``esc-bridge demo``'s bridge listens on a free port of 127.0.0.1 with multicast scouting off,
so that nothing of the demo leaves the machine; a monitor that scouts never finds it. While the
demo runs it writes that endpoint into a file of its own (:func:`announcing`), and a monitor
started without Zenoh settings connects to every endpoint announced by a process still running
(:func:`announced`): ``esc-bridge monitor`` (or ``--web 8080``) in a second terminal just works.

The files are ``<dir>/<pid>``, one endpoint each, in ``$XDG_RUNTIME_DIR/esc-bridge/listening``
(the user's own runtime directory), else ``esc-bridge-<uid>/listening`` in the temporary
directory; a directory that another user owns or may write is not read. Only loopback TCP
endpoints are announced and taken.
"""

from __future__ import annotations

import logging
import os
import re
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Final

log = logging.getLogger(__name__)

RUNTIME_ENV: Final = "XDG_RUNTIME_DIR"
_LOOPBACK_TCP: Final = re.compile(r"tcp/127\.0\.0\.1:[0-9]{1,5}")


def directory() -> Path:
    """Where the announcements are (it may not exist)."""
    runtime = os.environ.get(RUNTIME_ENV)
    if runtime:
        return Path(runtime) / "esc-bridge" / "listening"
    return Path(tempfile.gettempdir()) / f"esc-bridge-{os.getuid()}" / "listening"


@contextmanager
def announcing(endpoint: str) -> Iterator[None]:
    """Announce ``endpoint`` (``tcp/127.0.0.1:<port>``) while the block runs. A directory that
    cannot be written costs only the announcement: a monitor then needs ``--connect``.

    Raises:
        ValueError: ``endpoint`` is not a loopback TCP endpoint.
    """
    if not _LOOPBACK_TCP.fullmatch(endpoint):
        raise ValueError(f"expected tcp/127.0.0.1:<port>, got {endpoint!r}")
    path = directory() / str(os.getpid())
    try:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        path.write_text(endpoint + "\n", encoding="ascii")
    except OSError as exc:
        log.info("cannot announce %s in %s (%s): a monitor needs --connect", endpoint, path, exc)
        yield
        return
    try:
        yield
    finally:
        path.unlink(missing_ok=True)


def announced() -> list[str]:
    """The endpoints announced by processes still running, oldest process first."""
    folder = directory()
    try:
        info = folder.stat()
        entries = list(folder.iterdir())
    except OSError:
        return []
    if info.st_uid != os.getuid() or info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        log.warning("ignoring %s: another user owns it or may write to it", folder)
        return []
    endpoints = []
    for entry in sorted(entries, key=lambda e: int(e.name) if e.name.isdigit() else -1):
        if not entry.name.isdigit() or not _running(int(entry.name)):
            continue
        try:
            endpoint = entry.read_text(encoding="ascii").strip()
        except (OSError, UnicodeDecodeError):
            continue
        if _LOOPBACK_TCP.fullmatch(endpoint) and endpoint not in endpoints:
            endpoints.append(endpoint)
    return endpoints


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process has that number now
        return False
    return True
