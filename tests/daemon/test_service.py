"""The shipped systemd unit (``config/esc-bridge.service``): systemd accepts it, and its
ExecStart runs, sends frames and stops cleanly inside the sandbox its own lines describe.

No systemd runs here, so the sandbox is built from the unit's lines, each as systemd builds it
(``SANDBOX`` below: a line the unit gains that this test does not know makes it fail, until it
is reproduced here or said to need nothing). Two things differ from an installed vehicle, and
only these: the unit's ``User=esc-bridge`` is an unused uid with no password entry (this
machine has no esc-bridge user, and creating one would outlast the test), and ExecStart's
``/opt/esc-bridge/.venv/bin/esc-bridge`` and ``--config /etc/esc-bridge/config.toml`` become
this checkout's venv and a test configuration on a udp_multicast bus of the test's own; every
other word of ExecStart is used as written. The checkout, venv included, is read-only in the
sandbox, as ``ProtectSystem=strict`` makes ``/opt/esc-bridge``. What the bridge runs from that
``ProtectHome=true`` and ``PrivateTmp=true`` hide (the venv's Python under a home directory, as
pyenv's ``/root/.pyenv``; a checkout cloned into ``/tmp``), the sandbox shows again, read-only,
where it is: on a vehicle the venv's Python is the system's, in ``/usr``, and the checkout is
``/opt/esc-bridge``.

Building the sandbox needs root (a mount namespace, another uid); elsewhere these tests skip,
saying so. ``systemd-analyze verify`` needs only the program.
"""

from __future__ import annotations

import grp
import os
import pwd
import re
import resource
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from conftest import MULTICAST_GROUP, ROOT, Observer, free_port

UNIT = ROOT / "config" / "esc-bridge.service"
PAGE = ROOT / "docs" / "service.md"
INSTALLED_VENV_BIN = "/opt/esc-bridge/.venv/bin/"
INSTALLED_CONFIG = "/etc/esc-bridge/config.toml"
VENV_BIN = Path(sys.executable).parent
SYSTEMD_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
HOME_OF_A_SYSTEM_USER = "/home/esc-bridge"  # what `useradd --system esc-bridge` records; not made

# How each [Service] line of the unit is reproduced, or why it needs nothing here.
SANDBOX = {
    "Type": "nothing: how systemd decides the start is done",
    "User": "setpriv --reuid (an unused uid)",
    "Group": "setpriv --regid (the same number)",
    "SupplementaryGroups": "setpriv --groups",
    "ExecStart": "the command line itself",
    "KillSignal": "sent to every process of the bridge, as KillMode=control-group does",
    "TimeoutStopSec": "the time the bridge gets to exit after it",
    "Restart": "nothing: systemd's reaction to an exit (systemd-analyze checks the line)",
    "RestartSec": "nothing: as Restart",
    "CacheDirectory": "a directory of the user's, writable, at /var/cache/NAME, $CACHE_DIRECTORY",
    "LogsDirectory": "a directory of the user's, writable, at /var/log/NAME, $LOGS_DIRECTORY",
    "AmbientCapabilities": "setpriv --inh-caps and --ambient-caps",
    "CapabilityBoundingSet": "setpriv --bounding-set",
    "LimitRTPRIO": "prlimit --rtprio, where this machine's hard limit allows it",
    "NoNewPrivileges": "setpriv --no-new-privs",
    "ProtectSystem": "strict: / remounted read-only; only the directories above writable",
    "ProtectHome": "true: an empty read-only tmpfs on /home and /root",
    "PrivateTmp": "true: a tmpfs of its own on /tmp and /var/tmp",
}

needs_root = pytest.mark.skipif(
    os.geteuid() != 0 or not all(shutil.which(tool) for tool in ("unshare", "setpriv", "mount")),
    reason="building the unit's sandbox needs root (a mount namespace, another uid) and "
    "util-linux's unshare, setpriv and mount",
)


def read_unit(path: Path) -> dict[str, dict[str, list[str]]]:
    """The unit's sections, each key with its values in order (a key may repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    for number, raw in enumerate(path.read_text().splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        assert not line.endswith("\\"), f"{path}:{number}: continued lines are not read here"
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        key, equals, value = line.partition("=")
        assert current is not None and equals, f"{path}:{number}: not key=value: {raw!r}"
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


SERVICE = read_unit(UNIT)["Service"]


def one(key: str) -> str:
    values = SERVICE[key]
    assert len(values) == 1, f"{UNIT}: {key}= given {len(values)} times"
    return values[0]


HIDDEN = ("/home", "/root", "/tmp", "/var/tmp")  # ProtectHome=true, PrivateTmp=true


def hidden(path: Path) -> bool:
    """Whether the unit's sandbox hides ``path``."""
    return any(path.is_relative_to(top) for top in HIDDEN)


def capabilities(line: str) -> str:
    """A unit's capability list as setpriv's: ``CAP_SYS_NICE`` -> ``+sys_nice``."""
    return ",".join(f"+{cap.lower().removeprefix('cap_')}" for cap in line.split())


def unused_uid() -> int:
    for uid in range(61_000, 62_000):
        try:
            pwd.getpwuid(uid)
        except KeyError:
            try:
                grp.getgrgid(uid)
            except KeyError:
                return uid
    raise AssertionError("no unused uid between 61000 and 61999")


def page_drop_in() -> str:
    """The ExecStart that docs/service.md's recording drop-in puts in place of the unit's."""
    block = re.search(r"```ini\n\[Service\]\nExecStart=\n(ExecStart=.*)\n```", PAGE.read_text())
    assert block is not None, f"{PAGE}: no [Service] drop-in that clears ExecStart"
    return block[1].removeprefix("ExecStart=")


def exec_start(line: str, config: Path) -> list[str]:
    """An ExecStart line with the venv and the configuration file put in place (only)."""
    argv = shlex.split(line)
    assert argv[0].startswith(INSTALLED_VENV_BIN), argv
    assert argv.count(INSTALLED_CONFIG) == 1, argv
    argv[0] = str(VENV_BIN / argv[0].removeprefix(INSTALLED_VENV_BIN))
    return [str(config) if word == INSTALLED_CONFIG else word for word in argv]


@dataclass
class Sandbox:
    """The unit's sandbox around a command: a mount namespace, then another uid."""

    work: Path  # on the host; /mnt inside, readable by the sandbox's user
    uid: int
    directories: dict[str, str] = field(default_factory=dict)  # env var -> path inside
    mounts: list[tuple[str, str]] = field(default_factory=list)  # (host path, path inside)

    @classmethod
    def of_unit(cls, work: Path, uid: int, *, state_directories: bool) -> Sandbox:
        sandbox = cls(work, uid)
        if state_directories:
            for key, env, parent in (
                ("CacheDirectory", "CACHE_DIRECTORY", "/var/cache"),
                ("LogsDirectory", "LOGS_DIRECTORY", "/var/log"),
            ):
                host = work / parent.strip("/").replace("/", "-")
                name = one(key)
                (host / name).mkdir(parents=True)
                os.chown(host / name, uid, uid)
                sandbox.mounts.append((str(host), parent))
                sandbox.directories[env] = f"{parent}/{name}"
        return sandbox

    def inside(self, host: Path) -> str:
        """Where a file under ``work`` is seen from inside."""
        return "/mnt/" + str(host.relative_to(self.work))

    def command(self, argv: list[str]) -> list[str]:
        assert one("ProtectSystem") == "strict" and one("ProtectHome") == "true"
        assert one("PrivateTmp") == "true" and one("NoNewPrivileges") == "true"
        caps = capabilities(one("AmbientCapabilities"))
        bounding = capabilities(one("CapabilityBoundingSet"))
        groups = ",".join(str(grp.getgrnam(g).gr_gid) for g in one("SupplementaryGroups").split())
        # What the bridge runs from that the sandbox hides (under /home, /root, /tmp or
        # /var/tmp: a checkout cloned into /tmp, pyenv's Python in /root), shown again
        # read-only where it is, as the system's Python and /opt/esc-bridge are on a vehicle.
        runs_from = (ROOT, Path(sys.prefix).resolve(), Path(sys.base_prefix).resolve())
        shown = [path for path in runs_from if hidden(path)]
        shown = [p for p in shown if not any(p != q and p.is_relative_to(q) for q in shown)]
        setup = [f"mount --bind {shlex.quote(str(self.work))} /mnt"]
        setup += [f"mount --bind {shlex.quote(host)} {inside}" for host, inside in self.mounts]
        for number, path in enumerate(shown):
            (self.work / f"shown-{number}").mkdir()
            setup.append(f"mount --bind {shlex.quote(str(path))} /mnt/shown-{number}")
        setup += [
            "mount -o remount,bind,ro /",  # ProtectSystem=strict
            "mount -t tmpfs -o mode=1777 tmpfs /tmp",  # PrivateTmp=true
            "mount -t tmpfs -o mode=1777 tmpfs /var/tmp",
            "mount -t tmpfs -o mode=755 tmpfs /home",  # ProtectHome=true
            "mount -t tmpfs -o mode=755 tmpfs /root",
        ]
        for number, path in enumerate(shown):
            quoted = shlex.quote(str(path))
            setup += [f"mkdir -p {quoted}", f"mount --bind -o ro /mnt/shown-{number} {quoted}"]
        setup += [
            "mount -o remount,ro /home",
            "mount -o remount,ro /root",
            "cd /",  # systemd's working directory for a system service
        ]
        limit = []
        rtprio = int(one("LimitRTPRIO"))
        if resource.getrlimit(resource.RLIMIT_RTPRIO)[1] >= rtprio:
            limit = ["prlimit", f"--rtprio={rtprio}"]
        drop = [
            "setpriv",
            f"--reuid={self.uid}",
            f"--regid={self.uid}",
            f"--groups={groups}",
            f"--inh-caps=-all,{caps}",
            f"--ambient-caps=-all,{caps}",
            f"--bounding-set=-all,{bounding}",
            "--no-new-privs",
            "--",
        ]
        script = " && ".join(setup) + ' && exec "$@"'
        return ["unshare", "--mount", "--", "sh", "-c", script, "sandbox", *limit, *drop, *argv]

    def environment(self, *, home: str | None) -> dict[str, str]:
        """What systemd gives a system service of a user without a home directory."""
        env = {"PATH": SYSTEMD_PATH, "USER": "esc-bridge", "LOGNAME": "esc-bridge"}
        env["SHELL"] = "/usr/sbin/nologin"
        if home is not None:
            env["HOME"] = home
        return {**env, **self.directories}


@pytest.fixture
def work() -> Iterator[Path]:
    """A directory the sandbox's user may read (pytest's tmp_path is root's alone)."""
    path = Path(tempfile.mkdtemp(prefix="esc-bridge-service-"))
    path.chmod(0o755)
    yield path
    shutil.rmtree(path)


def test_the_unit_says_what_the_sandbox_reproduces() -> None:
    assert set(SERVICE) <= set(SANDBOX), (
        f"{UNIT} gained {sorted(set(SERVICE) - set(SANDBOX))}: reproduce it in this test's "
        "sandbox, or say in SANDBOX why it needs nothing here"
    )
    unit = read_unit(UNIT)["Unit"]
    # Retrying for ever at boot, while can0 or the serial port is not there yet.
    assert unit["StartLimitIntervalSec"] == ["0"]
    assert one("Restart") == "always" and 0 < float(one("RestartSec")) <= 5
    for device in ("sys-subsystem-net-devices-can0.device", "dev-ttyAMA0.device"):
        assert device in " ".join(unit["Wants"]).split()
        assert device in " ".join(unit["After"]).split()


@needs_root
@pytest.mark.parametrize("recording", [False, True], ids=["unit", "page-record-drop-in"])
def test_exec_start_runs_as_a_system_user_in_the_units_sandbox(work: Path, recording: bool) -> None:
    """The unit's ExecStart, and the one docs/service.md's drop-in makes it to record flights
    into LogsDirectory=."""
    can_port, mavlink_port = free_port(), free_port()
    config = work / "config.toml"
    config.write_text(
        f'[mavlink]\nurl = "udpin:127.0.0.1:{mavlink_port}"\n\n'
        f'[can]\ninterface = "udp_multicast"\nchannel = "{MULTICAST_GROUP}"\n'
        f"options = {{ port = {can_port}, hop_limit = 0 }}\n\n"
        "[zenoh]\nmulticast_scouting = false\n"
    )
    config.chmod(0o644)
    uid = unused_uid()
    sandbox = Sandbox.of_unit(work, uid, state_directories=True)
    line = page_drop_in() if recording else one("ExecStart")
    argv = exec_start(line, Path(sandbox.inside(config)))
    observer = Observer(can_port)
    proc = subprocess.Popen(
        sandbox.command(argv),
        env=sandbox.environment(home=HOME_OF_A_SYSTEM_USER),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # the unit's control group: the bridge and its loop process
    )
    try:
        # Started: the loop sends the safe values at its rate (no autopilot is there).
        observer.wait_for(lambda msg: True, timeout_s=60.0)
        os.killpg(proc.pid, signal.Signals[one("KillSignal")])
        out, _ = proc.communicate(timeout=float(one("TimeoutStopSec")))
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
        observer.close()
    assert proc.returncode == 0, out
    assert "Traceback" not in out and "Read-only file system" not in out, out
    assert "stopped after sending safe values" in out, out
    # AmbientCapabilities=CAP_SYS_NICE is what gives an unprivileged bridge its priority.
    assert "output loop runs with SCHED_FIFO priority" in out, out
    # The dialect went to CacheDirectory= (systemd's $CACHE_DIRECTORY), owned by the user.
    cached = list((work / "var-cache" / one("CacheDirectory") / "mavlink").glob("esc_bridge-*.py"))
    assert len(cached) == 1 and cached[0].stat().st_uid == uid, cached
    recorded = sorted(p.suffix for p in (work / "var-log" / one("LogsDirectory")).iterdir())
    assert recorded == ([".log", ".mcap", ".tlog"] if recording else []), recorded


def test_the_page_shows_the_units_lines() -> None:
    """docs/service.md: the device lines to edit are the unit's, the drop-in only adds
    --record into LogsDirectory=, and every key its table explains is in the unit."""
    page = PAGE.read_text()
    unit = read_unit(UNIT)
    for key in ("Wants", "After"):
        assert f"\n{key}={unit['Unit'][key][0]}\n" in page, key
    logs = f"/var/log/{one('LogsDirectory')}"
    assert page_drop_in() == f"{one('ExecStart')} --record {logs}"
    explained = set(re.findall(r"^\| `(\w+)=", page, re.M))
    explained |= set(re.findall(r"`, `(\w+)=", page))
    keys = {key for section in unit.values() for key in section}
    assert explained and explained <= keys, explained - keys
    assert keys - explained <= {"Description", "Documentation", "Type", "WantedBy"}, (
        keys - explained
    )


@needs_root
def test_the_demo_runs_for_a_user_without_a_home(work: Path) -> None:
    """`esc-bridge demo` as a user with no home and no cache, the checkout read-only."""
    sandbox = Sandbox.of_unit(work, unused_uid(), state_directories=False)
    argv = [str(VENV_BIN / "esc-bridge"), "demo", "--plain", "--duration", "10"]
    argv += ["--time-scale", "4"]
    done = subprocess.run(
        sandbox.command(argv),
        env=sandbox.environment(home=None),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr
    assert "bridge exit status 0, sim exit status 0" in done.stdout
    assert re.search(r"^\|\s+4 \|\s+4 \| online ", done.stdout, re.M), done.stdout[-3000:]


def test_systemd_accepts_the_unit(tmp_path: Path) -> None:
    """``systemd-analyze verify`` on a copy whose ExecStart names this checkout's venv (the
    installed path does not exist here, and verify checks that the program does)."""
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze not found (no systemd on this machine)")
    copy = tmp_path / UNIT.name
    copy.write_text(UNIT.read_text().replace(INSTALLED_VENV_BIN, f"{VENV_BIN}/"))
    done = subprocess.run(
        [analyze, "verify", str(copy)], capture_output=True, text=True, timeout=60
    )
    assert (done.returncode, done.stdout, done.stderr) == (0, "", "")
    # And it does check: a misspelt key is reported.
    copy.write_text(UNIT.read_text().replace("RestartSec=", "RestartSecs=", 1))
    done = subprocess.run(
        [analyze, "verify", str(copy)], capture_output=True, text=True, timeout=60
    )
    assert "Unknown key 'RestartSecs'" in done.stderr
