"""A real Linux kernel's SocketCAN for the tests: User-Mode Linux, or the host's own.

The tests in ``tests/linux/`` run the bridge, its peers and their observers on a vcan of a real
kernel, and assert on the host. :func:`boot` gives a :class:`Kernel`; ``kernel.call(function,
**kwargs)`` runs ``function`` (a module-level function of a module under ``tests/``, importable
as ``linux.<module>``, or of one in ``bench/``) where the kernel is, with the helpers of
:mod:`linux.guest`, and returns what it returned (plain JSON data). One kernel holds every call
of a test session: a call makes its own interfaces and processes and removes them at its end.

Where it runs, in this order (``ESC_BRIDGE_LINUX`` unset or ``auto``):

- ``host``: the host can make a vcan itself (root, the vcan module: a Linux machine with
  SocketCAN). The agent runs as a subprocess; the interfaces get names of their own and never
  touch the host's ``can0``.
- ``uml``: Debian's ``user-mode-linux`` (``linux``): Linux 6.1 as an ordinary process, booted
  in a few seconds with the host's files as its root (hostfs) and one CPU. ``uml_init.sh`` is
  its PID 1: it mounts what the bridge needs, loads the CAN modules (vcan with ``echo=1``,
  vxcan, netem) and starts the agent on the console channel ``con1``, a pair of pipes the host
  holds. The guest's own files (``/run``, ``/dev/shm``) are its memory; of the host's files it
  writes only Python's bytecode caches (the host user's, as a run on the host would).
- Neither: :func:`choose` says why and :data:`INSTALL` what to install; the tests skip.

:func:`boot_systemd` boots systemd itself in User-Mode Linux (``uml_systemd_init.sh``), on an
overlay whose lower layer is the host's files and whose upper layer is the guest's memory: the
host's files are never written. esc-bridge is installed there as docs/service.md says, and the
agent runs as a service of its own on the same channel.

``ESC_BRIDGE_LINUX=uml`` or ``host`` asks for one (the other is not tried), ``off`` skips.

The guest has one CPU and stalls while the host's files are read: test what happens there,
never how fast (timings belong in ``bench/``, on the host).
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

ROOT = Path(__file__).resolve().parent.parent.parent
TESTS = ROOT / "tests"
INIT = Path(__file__).resolve().parent / "uml_init.sh"
SYSTEMD_INIT = Path(__file__).resolve().parent / "uml_systemd_init.sh"
UNIT = ROOT / "config" / "esc-bridge.service"
INSTALLED_AT = "/opt/esc-bridge"  # the checkout in the systemd guest, as docs/service.md says
MODE_ENV = "ESC_BRIDGE_LINUX"
CACHE_ENV = "ESC_BRIDGE_CACHE"
INSTALL = "sudo apt-get install user-mode-linux can-utils kmod iproute2"
UML_MODULES = Path("/usr/lib/uml/modules")
# What the calls use, from which Debian package: the observers and injectors, the interfaces,
# the queueing disciplines.
TOOLS = {"candump": "can-utils", "cansend": "can-utils", "cangen": "can-utils"}
TOOLS |= {"ip": "iproute2", "tc": "iproute2"}
UML_TOOLS = {"linux": "user-mode-linux", "insmod": "kmod"}
BOOT_TIMEOUT_S = 120.0  # the agent's first line; about 5 s on an idle machine, 30 s at load 10
SYSTEMD_BOOT_TIMEOUT_S = 300.0  # systemd to start the agent; about 50 s on an idle machine
CALL_TIMEOUT_S = 300.0
HIDDEN_BY_UNIT = ("/home", "/root", "/tmp", "/var/tmp")  # ProtectHome=true, PrivateTmp=true
SYSTEMD_FILES = {"/lib/systemd/systemd": "systemd", "/lib/systemd/systemd-networkd": "systemd"}
UML_MEMORY = "1G"
LOG_IN_ERROR = 8000  # the tail of a failed call's log in its error (all of it is printed)


class GuestError(AssertionError):
    """A call failed where the kernel is: its traceback and the log of what it ran."""


class Kernel:
    """The agent on a kernel: :meth:`call` runs a function there; :meth:`close` ends it."""

    def __init__(
        self,
        mode: str,
        process: subprocess.Popen[bytes],
        requests: IO[bytes],
        answers: IO[bytes],
        workdir: Path,
        console: Path,
        boot_timeout_s: float = BOOT_TIMEOUT_S,
    ) -> None:
        self.mode = mode
        """``uml`` or ``host``."""
        self.workdir = workdir
        """The host's directory of this kernel's console log (and UML's pid file)."""
        self._process = process
        self._requests = requests
        self._answers = answers
        self._console = console
        self._next_id = 1
        self._broken = ""
        self.release = ""
        """The kernel's release (``uname -r``)."""
        ready = self._answer(boot_timeout_s, "the agent to start")
        self.release = ready["ready"]

    def console(self, last: int = 60) -> str:
        """The last lines the kernel (UML's console) or the agent printed."""
        try:
            lines = self._console.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(lines[-last:])

    def _answer(self, timeout_s: float, what: str) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        fd = self._answers.fileno()
        line = b""
        while not line.endswith(b"\n"):
            left = deadline - time.monotonic()
            ready, _, _ = select.select([fd], [], [], max(left, 0.0))
            if not ready:
                self._broken = f"no answer within {timeout_s} s waiting for {what}"
                raise GuestError(f"{self._broken}\n--- console:\n{self.console()}")
            chunk = os.read(fd, 4096)
            if not chunk:
                self._broken = f"the {self.mode} kernel's agent ended waiting for {what}"
                self._process.poll()
                raise GuestError(
                    f"{self._broken} (exit {self._process.returncode})\n--- console:\n"
                    f"{self.console()}"
                )
            line += chunk
        answer: dict[str, Any] = json.loads(line)
        return answer

    def call(
        self, function: Callable[..., Any], /, timeout_s: float = CALL_TIMEOUT_S, **kwargs: Any
    ) -> Any:
        """Run ``function(**kwargs)`` where the kernel is; what it returned.

        The guest's log of the call (commands, process outputs) is printed, so pytest shows it
        beside a failing test.

        Raises:
            GuestError: the function raised (its traceback and log), or the kernel did not
                answer within ``timeout_s`` (its console), or an earlier call broke it.
        """
        if self._broken:
            raise GuestError(f"the {self.mode} kernel broke in an earlier call: {self._broken}")
        module = function.__module__
        if module == "__main__" or "." in function.__qualname__:
            raise ValueError(
                f"{function.__qualname__} ({module}): the agent imports a module-level function "
                "of a module by its name (linux.<module> under tests/, or one of bench/)"
            )
        request_id = self._next_id
        self._next_id += 1
        request = {"id": request_id, "function": f"{module}:{function.__name__}", "kwargs": kwargs}
        self._requests.write((json.dumps(request) + "\n").encode())
        self._requests.flush()
        result = self._answer(timeout_s, f"{function.__name__}")
        assert result["id"] == request_id, (result["id"], request_id)
        print(
            f"--- {self.mode} kernel {self.release}, {function.__name__} ({result['seconds']} s):"
        )
        print(result["log"])
        if not result["ok"]:
            raise GuestError(
                f"{function.__name__} failed in the {self.mode} kernel:\n{result['error']}"
                f"--- its log:\n{result['log'][-LOG_IN_ERROR:]}"
            )
        return result["value"]

    def close(self, timeout_s: float = 60.0) -> None:
        """Close the channel: the agent ends and UML powers off."""
        with contextlib.suppress(OSError):
            self._requests.close()
        try:
            self._process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self._process.pid, signal.SIGKILL)
            self._process.wait()
        with contextlib.suppress(OSError):
            self._answers.close()


def _missing_tools(tools: dict[str, str]) -> str:
    missing = sorted(
        f"{tool} ({package})" for tool, package in tools.items() if not shutil.which(tool)
    )
    return ", ".join(missing)


def host_vcan_refusal() -> str:
    """Why this host cannot make a vcan of its own ('' when it can)."""
    if sys.platform != "linux":
        return f"the host is {sys.platform}, not Linux"
    missing = _missing_tools(TOOLS)
    if missing:
        return f"missing {missing}"
    name = f"ebtprobe{os.getpid() % 100000}"
    done = subprocess.run(
        ["ip", "link", "add", "dev", name, "type", "vcan"],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        return f"the host cannot make a vcan ({done.stderr.strip() or done.returncode})"
    subprocess.run(["ip", "link", "delete", name], capture_output=True, check=False)
    return ""


def uml_refusal() -> str:
    """Why User-Mode Linux cannot run the tests here ('' when it can)."""
    missing = _missing_tools(TOOLS | UML_TOOLS)
    if missing:
        return f"missing {missing}"
    if not list(UML_MODULES.glob("*/kernel/drivers/net/can/vcan.ko")):
        return f"no vcan module under {UML_MODULES} (user-mode-linux)"
    for path in (ROOT, Path(sys.executable)):
        if any(c.isspace() for c in str(path)):
            return f"{path} has white space, which the kernel's command line cannot carry"
    return ""


def choose() -> tuple[str, str]:
    """(mode, '') for the kernel to use, or ('', why none can be: the reason to skip)."""
    asked = os.environ.get(MODE_ENV, "auto")
    reasons = [f"{MODE_ENV}=off"] if asked == "off" else []
    if asked in ("auto", "host"):
        refusal = host_vcan_refusal()
        if not refusal:
            return "host", ""
        reasons.append(f"host: {refusal}")
    if asked in ("auto", "uml"):
        refusal = uml_refusal()
        if not refusal:
            return "uml", ""
        reasons.append(f"User-Mode Linux: {refusal}")
    if asked not in ("auto", "host", "uml", "off"):
        reasons.append(f"{MODE_ENV}={asked!r}: expected auto, host, uml or off")
    return "", "no kernel with SocketCAN to test on (" + "; ".join(reasons) + f"); {INSTALL}"


def _environment(mode: str) -> dict[str, str]:
    """What the agent (and the guest's PID 1) needs to know."""
    env = {
        "ESC_BRIDGE_ROOT": str(ROOT),
        "ESC_BRIDGE_PYTHON": sys.executable,
        "ESC_BRIDGE_KERNEL": mode,
        "MAVLINK20": "1",
        # The host user's home: the guest finds the MAVLink dialect in its cache. And bytecode
        # written (beside the sources, as Python does): without it each start in the guest
        # compiles the 2 MB dialect again (5 s on the host, 40 000 page faults, each far
        # dearer in User-Mode Linux).
        "HOME": os.environ.get("HOME", "/root"),
    }
    if CACHE_ENV in os.environ:
        env[CACHE_ENV] = os.environ[CACHE_ENV]
    return env


def boot(mode: str, workdir: Path) -> Kernel:
    """Start the agent on a kernel (``mode`` from :func:`choose`); its console log and UML's
    files go to ``workdir``.

    Raises:
        GuestError: the agent did not start (the console says why).
    """
    workdir.mkdir(parents=True, exist_ok=True)
    env = _environment(mode)
    if mode != "host":
        return _boot_uml(mode, INIT, env, workdir)
    console = workdir / "console.log"
    with console.open("wb") as log:
        process = subprocess.Popen(
            [sys.executable, "-m", "linux.agent"],
            cwd=TESTS,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=log,
            env={**os.environ, **env},
            start_new_session=True,
        )
    assert process.stdin is not None and process.stdout is not None
    return Kernel(mode, process, process.stdin, process.stdout, workdir, console)


def systemd_refusal() -> str:
    """Why systemd cannot be booted in User-Mode Linux here ('' when it can), with the install
    line."""
    asked = os.environ.get(MODE_ENV, "auto")
    if asked not in ("auto", "uml"):
        return f"{MODE_ENV}={asked} (systemd runs in User-Mode Linux only); {INSTALL}"
    refusal = _systemd_refusal()
    return f"{refusal}; {INSTALL}" if refusal else ""


def _systemd_refusal() -> str:
    refusal = uml_refusal()
    if refusal:
        return refusal
    missing = _missing_tools({"useradd": "passwd", "pivot_root": "util-linux"})
    if missing:
        return f"missing {missing}"
    for path, package in SYSTEMD_FILES.items():
        if not Path(path).exists():
            return f"no {path} ({package})"
    if not list(UML_MODULES.glob("*/kernel/fs/overlayfs/overlay.ko")):
        return f"no overlay module under {UML_MODULES} (user-mode-linux)"
    return ""


def boot_systemd(workdir: Path, config: str) -> Kernel:
    """Boot systemd in User-Mode Linux on an overlay of the host's files, with esc-bridge
    installed as docs/service.md says (``uml_systemd_init.sh``) and ``config`` as its
    /etc/esc-bridge/config.toml; the agent runs as a service of its own, and powers the guest
    off when :meth:`Kernel.close` closes its channel.

    Raises:
        GuestError: the agent did not start (the console says why).
    """
    setup = workdir / "setup"
    setup.mkdir(parents=True, exist_ok=True)
    (setup / "config.toml").write_text(config)
    drop_ins = {"shown-again.conf": _shown_again(), "venv-under-test.conf": _venv_under_test()}
    for name, drop_in in drop_ins.items():
        if drop_in:
            (setup / "esc-bridge.service.d").mkdir(exist_ok=True)
            (setup / "esc-bridge.service.d" / name).write_text(drop_in)
    env = {**_environment("uml-systemd"), "ESC_BRIDGE_SETUP": str(setup)}
    return _boot_uml("uml-systemd", SYSTEMD_INIT, env, workdir, timeout_s=SYSTEMD_BOOT_TIMEOUT_S)


def _venv_under_test() -> str:
    """A drop-in for the unit: its ExecStart run from the venv these tests run in, where that
    is not the checkout's ``.venv`` the unit names as ``/opt/esc-bridge/.venv`` ('' when it is).
    CI's Python 3.10 half runs from ``.venv310``: the service must run the Python under test,
    not whatever ``.venv`` holds (or nothing, where there is none)."""
    venv = Path(sys.prefix).resolve()
    if venv == (ROOT / ".venv").resolve():
        return ""
    exec_start = next(
        line for line in UNIT.read_text().splitlines() if line.startswith("ExecStart=")
    )
    # Inside the checkout, by the path the guest installs it at (/opt/esc-bridge).
    installed = f"{INSTALLED_AT}/{venv.relative_to(ROOT)}" if venv.is_relative_to(ROOT) else venv
    return f"[Service]\nExecStart=\n{exec_start.replace(f'{INSTALLED_AT}/.venv', str(installed))}\n"


def _shown_again() -> str:
    """A drop-in for the unit: what the bridge runs from that its ProtectHome= or PrivateTmp=
    hides, shown again read-only where it is ('' when nothing is hidden). On a vehicle the
    venv's Python is /usr's and the checkout /opt/esc-bridge; here pyenv's Python may be in
    /root, or a clone in /tmp. ``ProtectHome=tmpfs`` (an empty /root and /home, as ``true``
    but passable) lets the service reach a path shown again under them."""
    runs_from = (ROOT, Path(sys.prefix).resolve(), Path(sys.base_prefix).resolve())
    hidden = [p for p in runs_from if any(p.is_relative_to(top) for top in HIDDEN_BY_UNIT)]
    hidden = [p for p in hidden if not any(p != q and p.is_relative_to(q) for q in hidden)]
    if not hidden:
        return ""
    lines = ["[Service]"]
    if any(p.is_relative_to("/root") or p.is_relative_to("/home") for p in hidden):
        lines.append("ProtectHome=tmpfs")
    lines += [f"BindReadOnlyPaths={p}" for p in dict.fromkeys(hidden)]
    return "\n".join(lines) + "\n"


def _boot_uml(
    mode: str, init: Path, env: dict[str, str], workdir: Path, timeout_s: float = BOOT_TIMEOUT_S
) -> Kernel:
    console = workdir / "console.log"
    to_guest_r, to_guest_w = os.pipe()
    from_guest_r, from_guest_w = os.pipe()
    argv = [
        "linux",
        f"mem={UML_MEMORY}",
        "rootfstype=hostfs",
        "rootflags=/",
        "rw",
        f"init={init}",
        "con=null",
        "ssl=null",
        # Its pid file and management socket: in the work directory, not ~/.uml.
        f"uml_dir={workdir}",
        "con0=fd:0,fd:1",
        f"con1=fd:{to_guest_r},fd:{from_guest_w}",
        *(f"{key}={value}" for key, value in env.items()),
    ]
    # UML backs the guest's memory with a file in TMPDIR: a tmpfs keeps it off the disk.
    tmp = "/dev/shm" if os.path.isdir("/dev/shm") else os.environ.get("TMPDIR", "/tmp")
    with console.open("wb") as log:
        process = subprocess.Popen(
            argv,
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            pass_fds=(to_guest_r, from_guest_w),
            env={"PATH": os.environ.get("PATH", ""), "HOME": str(workdir), "TMPDIR": tmp},
            start_new_session=True,
        )
    os.close(to_guest_r)
    os.close(from_guest_w)
    requests = os.fdopen(to_guest_w, "wb")
    answers = os.fdopen(from_guest_r, "rb")
    try:
        return Kernel(mode, process, requests, answers, workdir, console, timeout_s)
    except BaseException:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        raise
