"""CPU profiling of the bridge's processes for ``bench/cpu.py --profile``.

Python imports this module at start-up when its folder is on PYTHONPATH, as the bench puts it
for the bridge and so for the loop process the bridge spawns. With ``ESC_BRIDGE_PROFILE_DIR``
set it installs a SIGUSR1 handler: the first SIGUSR1 starts yappi on every thread with the CPU
clock (time in system calls counts, time asleep does not), the second stops it and writes the
process's functions and threads to ``<dir>/<pid>.json``. Without the variable it does nothing.
"""

from __future__ import annotations

import json
import os
import signal
import sys
from pathlib import Path
from types import FrameType

_DIR = os.environ.get("ESC_BRIDGE_PROFILE_DIR")


def _toggle(_signum: int, _frame: FrameType | None) -> None:
    import yappi

    if not yappi.is_running():
        yappi.clear_stats()
        yappi.set_clock_type("cpu")
        yappi.start(builtins=True, profile_threads=True)
        return
    yappi.stop()
    functions = [
        {
            "name": f"{stat.name} ({'/'.join(Path(stat.module).parts[-2:])}:{stat.lineno})",
            "own_s": stat.tsub,
            "under_s": stat.ttot,
            "calls": stat.ncall,
        }
        for stat in yappi.get_func_stats()
    ]
    import threading

    names = {t.ident: t.name for t in threading.enumerate()}
    threads = [
        {"name": names.get(t.tid, t.name), "cpu_s": t.ttot} for t in yappi.get_thread_stats()
    ]
    assert _DIR is not None
    out = Path(_DIR) / f"{os.getpid()}.json"
    out.write_text(json.dumps({"argv": sys.argv, "functions": functions, "threads": threads}))


if _DIR:
    signal.signal(signal.SIGUSR1, _toggle)
