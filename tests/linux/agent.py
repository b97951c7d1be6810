"""The agent on the kernel under test: runs the functions the host's tests ask for, one at a time.

It reads one request per line on stdin (``{"id": 1, "function": "linux.test_x:name",
"kwargs": {...}}``), runs the function, and answers with one line of JSON on stdout: the id,
what the function returned (or the traceback it raised), the guest's log of that call
(:data:`linux.guest.LOG`) and how long it took. It reads until stdin closes. Before the first
request it says ``{"ready": ...}`` with the kernel's release.

Inside User-Mode Linux, stdin and stdout are the console channel the host holds (``uml_init.sh``
starts the agent on it, or systemd does, ``uml_systemd_init.sh``); on a host that makes its own
vcan they are the pipes of a subprocess (:mod:`linux.kernel`). Nothing but the answers may reach
the channel: the agent keeps it on descriptors of its own and gives stdin /dev/null and stdout
its stderr, which every process a test starts inherits.
"""

from __future__ import annotations

import importlib
import json
import os
import platform
import sys
import time
import traceback
import tty
from pathlib import Path
from typing import IO, Any


def _channel() -> tuple[IO[str], IO[str]]:
    """The request and answer streams, on descriptors no child inherits."""
    if os.isatty(0):
        # UML's console channel: no echo, no line editing, no newline translation.
        tty.setraw(0)
    requests = os.fdopen(os.dup(0), "r", encoding="utf-8")
    answers = os.fdopen(os.dup(1), "w", encoding="utf-8")
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    return requests, answers


def _answer(stream: IO[str], message: dict[str, Any]) -> None:
    stream.write(json.dumps(message) + "\n")
    stream.flush()


def main() -> None:
    # The functions asked for are in modules of tests/ (linux.*) and bench/.
    tests = Path(__file__).resolve().parent.parent
    for path in (tests.parent / "bench", tests):
        if str(path) not in sys.path:
            sys.path.insert(0, str(path))
    requests, answers = _channel()
    from linux import guest  # after the channel is safe: it imports the bridge

    _answer(answers, {"ready": platform.release(), "pid": os.getpid()})
    for line in requests:
        if not line.strip():
            continue
        request = json.loads(line)
        guest.begin_call(request["function"])
        started = time.monotonic()
        result: dict[str, Any]
        try:
            module_name, _, name = request["function"].partition(":")
            function = getattr(importlib.import_module(module_name), name)
            value = function(**request["kwargs"])
            result = {"ok": True, "value": value}
        except BaseException:  # noqa: BLE001 (the traceback goes to the host, whatever it was)
            result = {"ok": False, "error": traceback.format_exc()}
        finally:
            guest.end_call()
        result["id"] = request["id"]
        result["log"] = guest.LOG.text()
        result["seconds"] = round(time.monotonic() - started, 3)
        _answer(answers, result)


if __name__ == "__main__":
    main()
