"""The load generators (loadgen/load.py): each one really loads the machine, and nothing of
it is left running once its context exits, also after an exception or the caller's death.

Real processes, files and sockets; every test takes a second or two.
"""

from __future__ import annotations

import os
import select
import socket
import statistics
import struct
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest
from can.interfaces.udp_multicast.utils import unpack_message
from conftest import MULTICAST_GROUP, free_port

from bridge.errors import BridgeError, CodecError, ConfigError, NotExtendedIdError
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ft import codec as ft_codec
from loadgen.load import (
    PRESETS,
    Load,
    LoadSet,
    busy,
    can_flood,
    compiler_build,
    disk_writer,
    group_pids,
    memory_churn,
    preset,
    stall,
)


def stat(pid: int) -> list[str]:
    """/proc/<pid>/stat from the state on (index 0 is field 3)."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def comm(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return ""


def assert_gone(pgid: int, within_s: float = 0.0) -> None:
    deadline = time.monotonic() + within_s
    while (left := group_pids(pgid)) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert left == [], f"processes {left} of load group {pgid} still running"


def cpu_gained(load: Load | LoadSet, cpu_s: float, within_s: float = 10.0) -> float:
    """The CPU time ``load`` used from now until it has used ``cpu_s`` (or ``within_s`` has
    passed): a spinner's share of a loaded machine varies, spinning does not."""
    before = load.cpu_seconds()
    deadline = time.monotonic() + within_s
    while (gained := load.cpu_seconds() - before) < cpu_s and time.monotonic() < deadline:
        time.sleep(0.05)
    return gained


def test_busy_spins_at_its_nice_level_and_leaves_nothing() -> None:
    with busy(2, nice=7) as load:
        assert load.pgid is not None
        pgid = load.pgid
        pids = load.pids()
        assert len(pids) == 3  # the supervisor and two spinners
        # Two spinners at nice 7 on a 2-core machine that is busy with more (other tests, at
        # nice 0, take most of it: 0.42 s of CPU in 1 s seen at load 6): they spin, they do not
        # sleep, so their CPU time grows by a whole second within 10 s.
        assert cpu_gained(load, 1.0) >= 1.0
        assert {int(stat(pid)[16]) for pid in pids} == {7}  # field 19: nice, inherited
    assert_gone(pgid)
    assert load.report is not None
    assert load.report.details["spinners"] == 2
    assert load.report.cpu_s > 0.2


def test_an_exception_inside_the_context_stops_everything() -> None:
    with pytest.raises(RuntimeError, match="inside the load"), busy(1) as load:
        assert load.pgid is not None
        pgid = load.pgid
        assert len(group_pids(pgid)) == 2
        raise RuntimeError("inside the load")
    assert_gone(pgid)
    assert load.report is not None and load.report.error is None


def test_the_load_stops_when_its_caller_is_killed(tmp_path: Path) -> None:
    caller = tmp_path / "caller.py"
    caller.write_text(
        textwrap.dedent(
            """
            import time
            from loadgen.load import busy
            load = busy(2).start()
            print(load.pgid, flush=True)
            time.sleep(60)
            """
        )
    )
    # loadgen/ is not installed: the caller finds it at the repository's root, as pytest does.
    root = str(Path(__file__).resolve().parents[2])
    proc = subprocess.Popen(
        [sys.executable, str(caller)],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": root},
    )
    try:
        assert proc.stdout is not None
        assert select.select([proc.stdout], [], [], 10.0)[0], "the caller printed no pgid"
        pgid = int(proc.stdout.readline())
        assert len(group_pids(pgid)) == 3
    finally:
        proc.kill()  # SIGKILL: no __exit__, no __del__, nothing but the kernel closing its fds
        proc.wait()
    assert_gone(pgid, within_s=2.5)


def test_memory_churn_faults_in_and_frees_what_it_was_asked_for() -> None:
    with memory_churn(64, chunk_mb=4) as load:
        assert load.pgid is not None
        pid = load.pgid
        faults_before = int(stat(pid)[7])  # field 10: minor faults
        rss_kb = []
        for _ in range(10):
            time.sleep(0.1)
            rss_kb.append(int(stat(pid)[21]) * 4)  # field 24: resident pages
        faults = int(stat(pid)[7]) - faults_before
    # 64 MiB/s for 1 s is 16384 pages touched; at least half, whatever the machine's load.
    assert faults > 8192
    assert max(rss_kb) < 64 * 1024  # freed as it goes: pattern + one chunk, not everything
    report = load.report
    assert report is not None and report.achieved_per_s is not None
    assert report.unit == "MiB/s"
    assert 0.8 * 64 <= report.achieved_per_s <= 1.1 * 64
    assert_gone(pid)


def test_disk_writer_files_appear_and_vanish() -> None:
    with disk_writer(8) as load:
        directory = load.workdir
        assert directory is not None and directory.is_dir()
        time.sleep(1.0)
        files = list(directory.iterdir())
        written = sum(f.stat().st_size for f in files)
        assert files and all(f.name.startswith("load-") for f in files)
        assert written >= 4 << 20  # 8 MiB/s for 1 s, fsync'd; at least half on disk
        assert load.pgid is not None
        pgid = load.pgid
    assert not directory.exists()
    assert_gone(pgid)
    assert load.report is not None and load.report.details["files"] >= 1


def test_compiler_build_runs_real_compilers_again_and_again() -> None:
    with compiler_build(jobs=2, functions=3) as load:  # small files: many builds in a second
        seen: set[str] = set()
        before = load.cpu_seconds()
        # 1.5 s, or longer until it has had the CPU for a few builds: beside the whole suite it
        # got 0.3 s of CPU in 1.5 s (2 builds); alone it gets that in a fraction of a second.
        start = time.monotonic()
        cpu_s = 0.0
        while time.monotonic() - start < 1.5 or (cpu_s < 1.0 and time.monotonic() - start < 10):
            seen.update(comm(pid) for pid in load.pids())
            time.sleep(0.01)
            cpu_s = load.cpu_seconds() - before
        directory = load.workdir
        assert load.pgid is not None
        pgid = load.pgid
    assert seen & {"cc", "gcc", "cc1", "clang", "as"}, f"no compiler among {seen}"
    assert cpu_s > 0.3
    assert load.report is not None
    assert load.report.details["builds"] >= 4
    assert load.report.details["failures"] == 0
    assert directory is not None and not directory.exists()
    assert_gone(pgid)


@pytest.fixture
def spinner() -> Iterator[subprocess.Popen[bytes]]:
    proc = subprocess.Popen([sys.executable, "-I", "-S", "-c", "while True: pass"])
    yield proc
    proc.kill()
    proc.wait()


def test_stall_stops_and_resumes_its_target_and_leaves_it_running(
    spinner: subprocess.Popen[bytes],
) -> None:
    states = []
    with stall(spinner.pid, period_s=0.25, stopped_s=0.1) as load:
        end = time.monotonic() + 1.2
        while time.monotonic() < end:
            states.append(stat(spinner.pid)[0])
            time.sleep(0.005)
    stopped_share = states.count("T") / len(states)
    assert 0.15 < stopped_share < 0.75, states
    assert load.report is not None and load.report.details["stalls"] >= 3
    assert load.report.details["stopped_max_s"] >= 0.1
    time.sleep(0.05)
    assert stat(spinner.pid)[0] != "T"


def test_stall_of_no_process_fails_to_start() -> None:
    proc = subprocess.Popen([sys.executable, "-I", "-S", "-c", "pass"])
    proc.wait()  # reaped: its pid names no process now
    with pytest.raises(BridgeError, match="ProcessLookupError"):
        stall(proc.pid, 1.0, 0.1).start()


# Linux's SO_TIMESTAMPNS (asm-generic/socket.h), which Python's socket module does not name: the
# kernel stamps each datagram as it is queued, which on loopback is when the flood sent it.
SO_TIMESTAMPNS = 35


def test_can_flood_reaches_its_rate_with_frames_no_esc_protocol_claims() -> None:
    port = free_port()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.bind(("", port))
    membership = socket.inet_aton(MULTICAST_GROUP) + struct.pack("@I", socket.INADDR_ANY)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
    sock.setblocking(False)
    packets: list[bytes] = []
    sent_s: list[float] = []

    def take() -> None:
        while True:
            try:
                packet, ancillary, _, _ = sock.recvmsg(4096, 64)
            except BlockingIOError:
                return
            packets.append(packet)
            ((level, kind, stamp),) = ancillary
            assert (level, kind) == (socket.SOL_SOCKET, SO_TIMESTAMPNS)
            seconds, nanoseconds = struct.unpack("@qq", stamp)
            sent_s.append(seconds + nanoseconds * 1e-9)

    with can_flood(port, 4000, MULTICAST_GROUP) as load:
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            if select.select([sock], [], [], 0.05)[0]:
                take()
    time.sleep(0.05)
    take()
    sock.close()
    report = load.report
    assert report is not None and report.achieved_per_s is not None
    assert report.unit == "frames/s"
    sent = report.details["sent"]
    assert report.achieved_per_s == pytest.approx(sent / report.active_s)
    assert len(packets) >= 0.95 * sent
    # Its rate while it runs, from when the kernel took each frame: the median of 10 ms bins.
    # A flood starved by the rest of the suite skips what it could not send (and says so in
    # its report) for a few bins; the median is of the bins it ran in.
    bins = [0] * int((sent_s[-1] - sent_s[0]) / 0.01)
    for t in sent_s:
        i = int((t - sent_s[0]) / 0.01)
        if i < len(bins):
            bins[i] += 1
    assert len(bins) >= 50
    assert abs(statistics.median(bins[1:-1]) * 100 - 4000) <= 400
    frames: list[can.Message] = [unpack_message(p) for p in packets]
    assert {f.is_extended_id for f in frames} == {True, False}
    for frame in frames:
        if frame.is_extended_id:
            assert ckesc_codec.decode(frame) is None and ft_codec.decode(frame) is None
        else:
            with pytest.raises(NotExtendedIdError):
                ft_codec.decode(frame)
            with pytest.raises(CodecError):
                ckesc_codec.decode(frame)


def test_load_set_starts_and_stops_its_loads_together() -> None:
    loads = LoadSet([busy(1), disk_writer(4)], "pair")
    with loads:
        pgids = [load.pgid for load in loads]
        assert len(loads.pids()) == 3  # busy: supervisor + spinner; disk: supervisor
        assert cpu_gained(loads, 1.0) >= 1.0  # 0.15 s in 0.5 s at load ~8: they spin
    reports = loads.stop()  # a second stop: the same reports
    assert [r.name for r in reports] == ["busy1", "disk 4 MiB/s"]
    for pgid in pgids:
        assert pgid is not None
        assert_gone(pgid)


def test_presets() -> None:
    assert set(PRESETS) == {
        "idle",
        "busy2",
        "busy8",
        "busy+mem+disk",
        "busy+build",
        "busy+build-nice10",
        "can-flood-60k",
    }
    assert len(preset("idle")) == 0
    assert [(load.spec.kind, load.nice) for load in preset("busy+build-nice10")] == [
        ("busy", 10),
        ("compiler_build", 0),
    ]
    assert [load.spec.kind for load in preset("busy+mem+disk")] == [
        "busy",
        "memory_churn",
        "disk_writer",
    ]
    flood = preset("can-flood-60k", can_port=43210)
    assert [load.spec.params["frames_per_s"] for load in flood] == [60_000]
    with pytest.raises(ConfigError, match="can_port"):
        preset("can-flood-60k")
    with pytest.raises(ConfigError, match="expected one of idle, busy2"):
        preset("busy3")


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: busy(0), "n=0, expected 1..256"),
        (lambda: busy(1, nice=20), "nice=20, expected -20..19"),
        (lambda: memory_churn(-5), "mb_per_s=-5, expected a number > 0"),
        (lambda: stall(os.getpid(), 0.1, 0.1), "stopped_s=0.1 must be shorter"),
        (lambda: can_flood(0, 100), "port=0, expected 1..65535"),
        (lambda: compiler_build(jobs=0), "jobs=0, expected 1..64"),
    ],
)
def test_bad_parameters_are_refused(make: Callable[[], object], message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        make()


def test_a_load_never_started_or_stopped_twice_is_harmless() -> None:
    load = busy(1)
    report = load.stop()
    assert report.active_s == 0.0 and load.pgid is None
    running = busy(1).start()
    with pytest.raises(BridgeError, match="already started"):
        running.start()
    assert running.stop() is running.stop()
