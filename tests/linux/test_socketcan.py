"""Every ESC family on a real kernel's SocketCAN, and the kernel's filters in front of its reader.

`esc-bridge run --can-interface socketcan` with simulated ESCs (`esc-bridge sim`) and a pymavlink
autopilot on loopback, watched by `candump -L`: one flight per family, in the kernel
(:func:`fly`). The bridge starts; its sockets' receivers are read from /proc/net/can. Armed at
four different outputs until the ESCs' telemetry comes back in ESC_STATUS; `cangen` floods the
bus with foreign IDs; the outputs pause (stale input) and resume; SIGTERM.

The host decodes candump's lines with the project's codecs and checks each behaviour in a test
of its own: the rate, the values (under the flood too: no false failsafe), the telemetry in,
the failsafe, the stop flush, the receivers the bridge registered (exactly the reader's filters,
as the production code derives them for the configuration; none for the output loop), and
that the flood reached none of them.

First, the harness itself (one kernel holds this file, so the harness costs no boot of its
own): a call runs where the kernel is, on a vcan of its own, and a failure comes back with the
guest's log.
"""

from __future__ import annotations

import contextlib
import datetime
import itertools
import platform
import signal
import statistics
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import can
import pytest
from can.typechecking import CanFilter
from conftest import free_port
from pymavlink import mavutil

from bridge._compat import tomllib
from bridge.config import BridgeConfig, build_config, with_mixer_esc_count
from bridge.errors import CodecError
from bridge.escs import registry
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.dronecan.codec import Decoder as DronecanDecoder
from bridge.escs.dronecan.codec import RawCommand as DronecanRawCommand
from bridge.escs.dronecan.wire import COMMAND_MAX
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.escs.ft.keys import FtKeys
from bridge.telemetry.for_config import esc_table
from bridge.telemetry.reader import reader_filters
from linux import guest
from linux.kernel import GuestError, Kernel

PWM = [1100, 1350, 1600, 1850]  # four outputs, four values: a swapped channel cannot pass
FLOOD_FRAMES = 500  # armed, under cangen's flood of foreign IDs
FLOOD_GAP_MS = 1  # cangen's gap between frames: up to 1000 foreign frames a second
FLOOD_DATA = "F100DF100DF100DF"  # what tells the flood's frames on the bus (random IDs)
FLOOD_BYTES = bytes.fromhex(FLOOD_DATA)
ARMED_AFTER_FLOOD_S = 0.5
STALE_FOR_S = 2.0
RESUMED_FOR_S = 1.0
AUTOPILOT_HZ = 20  # SERVO_OUTPUT_RAW (the bridge arms on 2 Hz at its 1 s input timeout)
START_TIMEOUT_S = 120.0  # the bridge's start in a one-CPU guest beside a loaded host


# -- the harness itself ------------------------------------------------------------------------


def frames_through_vcan(count: int) -> dict[str, object]:
    channel = guest.vcan()
    dump = guest.Candump(channel)
    for i in range(count):
        guest.cansend(channel, f"1{i:02X}#{i:02X}")
    guest.wait_until(lambda: len(dump.frames()) == count, 10, f"{count} frames")
    return {
        "release": platform.release(),
        "channel": channel,
        "frames": [f for _, f in dump.frames()],
    }


def fails_with_a_log() -> None:
    guest.run(["ip", "link", "show", "no-such-interface"])


def test_a_call_sends_frames_through_a_vcan(linux: Kernel) -> None:
    result = linux.call(frames_through_vcan, count=3)
    assert result["frames"] == ["100#00", "101#01", "102#02"]
    if linux.mode == "uml":
        assert result["release"] == linux.release != platform.release()


def test_a_failing_call_says_what_it_ran(linux: Kernel) -> None:
    with pytest.raises(GuestError) as failure:
        linux.call(fails_with_a_log)
    assert "CalledProcessError" in str(failure.value)
    assert "ip link show no-such-interface" in str(failure.value)


# -- every family, one flight each -------------------------------------------------------------


def fly(family: str, pwm: list[int]) -> dict[str, Any]:
    """In the kernel: the bridge and simulated ESCs on a vcan of their own, one flight of
    ``family`` (a key of :data:`FAMILIES`)."""
    channel = guest.vcan()
    path = guest.scratch() / "bridge.toml"
    path.write_text(FAMILIES[family].config)
    dump = guest.Candump(channel)
    before_bridge = guest.receivers(channel)
    port = free_port()
    bridge = guest.bridge(channel, port, "--config", str(path), "--no-zenoh")
    # One at a time: the guest's one CPU starts an interpreter faster without a second one.
    bridge.wait_for_output("output loop runs", START_TIMEOUT_S)
    # The reader opens its handle just after the loop reports; the loop's own socket holds
    # exact-ID receivers only (the echo of its frames), the reader's masked ones ("fil").
    old_owners = {row["owner"] for row in before_bridge}
    guest.wait_until(
        lambda: any(
            row["list"] == "fil" and row["owner"] not in old_owners
            for row in guest.receivers(channel)
        ),
        30,
        "the reader's receivers",
    )
    with_bridge = guest.receivers(channel)
    sim = guest.sim(channel, "--config", str(path))
    pilot = guest.Autopilot(port, stack=mavutil.mavlink.MAV_AUTOPILOT_PX4)  # ESC_STATUS back
    watch = guest.MavlinkWatch(pilot.conn)
    marks: dict[str, float] = {}
    try:
        pilot.pwm = list(pwm)
        pilot.armed = True
        pilot.start_stream(AUTOPILOT_HZ)
        # The telemetry is back once every ESC turns, faster for a larger output.
        status = watch.wait_for(
            "ESC_STATUS",
            lambda m: 0 < m.rpm[0] < m.rpm[1] < m.rpm[2] < m.rpm[3],
            timeout_s=START_TIMEOUT_S,
        )
        marks["live"] = time.time()
        # The reader's counts just before and after the flood, each read between two marks.
        marks["before_flood"] = time.time()
        before_flood = guest.receivers(channel)
        marks["flood"] = time.time()
        flood = guest.cangen(
            channel,
            *("-e", "-I", "r", "-L", "8", "-D", FLOOD_DATA),
            *("-g", str(FLOOD_GAP_MS), "-n", str(FLOOD_FRAMES)),
        )
        flood.wait(START_TIMEOUT_S)
        marks["flooded"] = time.time()
        after_flood = guest.receivers(channel)
        marks["after_flood"] = time.time()
        time.sleep(ARMED_AFTER_FLOOD_S)
        marks["paused"] = time.time()
        pilot.pause_outputs()
        time.sleep(STALE_FOR_S)
        marks["resumed"] = time.time()
        pilot.resume_outputs()
        # The flight goes on once the outputs are on the bus again: a guest that stood still
        # (the host running others) may take longer than RESUMED_FOR_S to get there.
        guest.wait_until(
            lambda: _commanded_since(dump, FAMILIES[family].read(), marks["resumed"], pwm),
            START_TIMEOUT_S,
            "the autopilot's outputs on the bus again after the stale spell",
        )
        marks["outputs_again"] = time.time()
        time.sleep(RESUMED_FOR_S)
        marks["terminated"] = time.time()
        code = bridge.stop(signal.SIGTERM)
        time.sleep(0.2)  # the last frames reach candump
    finally:
        pilot.close()
        sim.stop()
    frames = dump.stop()
    return {
        "frames": frames,
        "candump_drops": dump.drops(),
        "marks": marks,
        "exit": code,
        "output": bridge.output(),
        "sent": pilot.sent,
        "delivered": pilot.delivered,
        "status": {
            "rpm": list(status.rpm),
            "voltage": list(status.voltage),
            "current": list(status.current),
        },
        "receivers": {
            "before_bridge": before_bridge,
            "with_bridge": with_bridge,
            "before_flood": before_flood,
            "after_flood": after_flood,
        },
    }


def _commanded_since(dump: guest.Candump, read: Reader, since: float, pwm: list[int]) -> bool:
    """Whether candump saw a command of ``pwm``'s outputs after ``since``."""
    want = commanded(pwm)
    for line in dump.lines():
        if not guest.CANDUMP_LINE.match(line):
            continue  # candump's own notes (its drops)
        t, msg = guest.candump_message(line)
        commands = command_of(read, msg) if t >= since else None
        if commands is not None and same(commands, want):
            return True
    return False


# -- the host's side ---------------------------------------------------------------------------


Commands = dict[int, float]
"""The command fractions (0..1) a frame carries, by ESC (0-based, motor order)."""

Reader = Callable[[can.Message], Commands | None]


def command_of(read: Reader, msg: can.Message) -> Commands | None:
    """What ``msg`` commands, None for a frame of the flood: its random IDs take a family's
    command ID now and then (CKESC's RawCommand, an FT command of ESC 235), and its data then
    decodes as a command or fails to (8 bytes where FT's frame has 6)."""
    return None if msg.data == FLOOD_BYTES else read(msg)


@dataclass(frozen=True)
class Family:
    """A family's configuration and how to read its commands back from the bus."""

    config: str
    read: Callable[[], Reader]
    """A reader of one frame stream (DroneCAN's decoder keeps multi-frame transfers)."""

    @property
    def bridge_config(self) -> BridgeConfig:
        """The configuration as the bridge builds it (its ESC lists sized for the mixer)."""
        return with_mixer_esc_count(build_config(tomllib.loads(self.config), "family"))


def ckesc_reader(full_scale: int) -> Callable[[], Reader]:
    def read(msg: can.Message) -> Commands | None:
        try:
            frame = ckesc_codec.decode(msg)
        except CodecError:
            return None
        if frame is None or not isinstance(
            frame.message,
            ckesc_records.RawCommand12b | ckesc_records.RawCommand14b | ckesc_records.RawCommand10b,
        ):
            return None
        return {i: t / full_scale for i, t in enumerate(frame.message.throttles[:4])}

    return lambda: read


def ft_reader(record: type, value: Callable[[Any], float]) -> Callable[[], Reader]:
    """FT commands of kind ``record``, each ``value`` (a fraction) of one ESC (IDs 11..14); and
    the safe value, whatever the mode: zero current (SetCurrent 0 A, which the driver sends)."""

    def read(msg: can.Message) -> Commands | None:
        frame = ft_codec.decode(msg)
        if frame is None:
            return None
        if isinstance(frame.message, record):
            return {frame.esc_id - 11: value(frame.message)}
        if isinstance(frame.message, ft_records.SetCurrent) and frame.message.current_a == 0:
            return {frame.esc_id - 11: 0.0}
        return None

    return lambda: read


def dronecan_reader() -> Reader:
    decoder = DronecanDecoder()

    def read(msg: can.Message) -> Commands | None:
        try:
            frame = decoder.decode(msg)
        except CodecError:
            return None
        if frame is None or not isinstance(frame.message, DronecanRawCommand):
            return None
        return {i: c / COMMAND_MAX for i, c in enumerate(frame.message.commands[:4])}

    return read


# What every flight shares, for the guest's one CPU on a loaded host. The loop ticks at 50 Hz:
# every tick's system calls are dear there, and at 400 Hz beside a host at load 16 it could not
# keep up (the real-time loop took 95 % of the guest's CPU: the kernel's RT throttling). The
# input is stale after the longest timeout there is: the guest stands still while the host runs
# others (the autopilot's outputs arrived at 11..51 Hz, not 50, beside a host at load 11). These
# flights check what is sent, not when.
OUTPUT = "input_timeout_ms = 1000\n"
FT = f'[output]\nprotocol = "ft"\nrate_hz = 12\n{OUTPUT}[escs]\nids = [11, 12, 13, 14]\n'
CKESC = f"[output]\nrate_hz = 50\n{OUTPUT}[escs]\n"
FAMILIES = {
    "ckesc-12b": Family(
        f'{CKESC}ckesc_command = "12b"\n', ckesc_reader(ckesc_records.THROTTLE_MAX)
    ),
    "ckesc-14b": Family(
        f'{CKESC}ckesc_command = "14b"\n', ckesc_reader(ckesc_records.THROTTLE_MAX)
    ),
    "ckesc-10b": Family(
        f'{CKESC}ckesc_command = "10b"\n', ckesc_reader(ckesc_records.THROTTLE_10B_MAX)
    ),
    "ft-current": Family(
        f'{FT}ft_mode = "current"\n',
        ft_reader(ft_records.SetCurrent, lambda m: m.current_a / FtKeys().ft_max_current_a),
    ),
    "ft-duty": Family(
        f'{FT}ft_mode = "duty"\n',
        ft_reader(ft_records.SetDuty, lambda m: m.duty / FtKeys().ft_max_duty),
    ),
    "dronecan": Family(f'[output]\nprotocol = "dronecan"\nrate_hz = 50\n{OUTPUT}', dronecan_reader),
}


def commanded(pwm: list[int]) -> Commands:
    """The command fractions the passthrough mixer makes of ``pwm`` (1000..2000 µs)."""
    return {i: (p - 1000) / 1000 for i, p in enumerate(pwm)}


WANT = commanded(PWM)
SAFE = dict.fromkeys(range(4), 0.0)

# linux/can.h, and how net/can/af_can.c's can_rcv_list_find files a filter.
CAN_EFF_FLAG, CAN_RTR_FLAG, CAN_ERR_FLAG = 0x80000000, 0x40000000, 0x20000000
CAN_SFF_MASK, CAN_EFF_MASK = 0x7FF, 0x1FFFFFFF


def kernel_receiver(python_can: CanFilter) -> tuple[str, int, int]:
    """A python-can filter as the kernel keeps it: (its receive list, can_id, can_mask).

    python-can's socketcan (``pack_filters``) adds CAN_EFF_FLAG to the mask of a filter that
    says ``extended``, and to its ID when true; the CAN core then files it by its mask.
    """
    can_id, mask = python_can["can_id"], python_can["can_mask"]
    if "extended" in python_can:
        mask |= CAN_EFF_FLAG
        if python_can["extended"]:
            can_id |= CAN_EFF_FLAG
    if mask & CAN_ERR_FLAG:
        return "err", can_id, mask & CAN_EFF_MASK
    if mask & CAN_EFF_FLAG and not can_id & CAN_EFF_FLAG:
        mask &= CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG
    can_id &= mask
    if not mask:
        return "all", can_id, mask
    exact = CAN_EFF_FLAG | CAN_RTR_FLAG
    if mask & exact == exact and not can_id & CAN_RTR_FLAG:
        if can_id & CAN_EFF_FLAG and mask == CAN_EFF_MASK | exact:
            return "eff", can_id, mask
        if not can_id & CAN_EFF_FLAG and mask == CAN_SFF_MASK | exact:
            return "sff", can_id, mask
    return "fil", can_id, mask


def passes(receiver: dict[str, Any], msg: can.Message) -> bool:
    """Whether a receiver of the kernel's passes ``msg`` (net/can/af_can.c, can_rcv_filter)."""
    can_id = msg.arbitration_id | (CAN_EFF_FLAG if msg.is_extended_id else 0)
    return bool((can_id & receiver["can_mask"]) == receiver["can_id"])


@dataclass
class Flight:
    name: str
    family: Family
    result: dict[str, Any]
    frames: list[tuple[float, can.Message]]
    """Every frame candump saw, with its receive time."""
    commands: list[tuple[float, Commands]]
    """Every command frame the bridge sent, decoded."""

    @property
    def marks(self) -> dict[str, float]:
        marks: dict[str, float] = self.result["marks"]
        return marks

    def between(self, start: str, end: str) -> list[tuple[float, Commands]]:
        return [(t, c) for t, c in self.commands if self.marks[start] <= t < self.marks[end]]

    def input_stale_at(self, t: float) -> bool:
        """Whether the newest output the bridge could have had at the tick that sent the frame
        candump saw at ``t`` was older than the input timeout (less 5 %: the bridge dates an
        input by the autopilot's clock, mapped onto its own). Had: delivered a loop period
        before ``t`` (the tick decides before its frame reaches candump)."""
        period_s = 1 / self.family.bridge_config.rate_hz
        had = [
            s
            for s, d in zip(self.result["sent"], self.result["delivered"], strict=True)
            if d < t - period_s
        ]
        timeout_s = self.family.bridge_config.output.input_timeout_ms / 1000
        return not had or t - had[-1] > 0.95 * timeout_s

    def sent_gaps(self) -> list[tuple[float, float]]:
        """The autopilot's gaps between outputs over 0.2 s: (when, how long)."""
        sent = self.result["sent"]
        return [(a, round(b - a, 3)) for a, b in itertools.pairwise(sent) if b - a > 0.2]

    def receivers(self, when: str) -> list[dict[str, Any]]:
        rows: list[dict[str, Any]] = self.result["receivers"][when]
        return rows

    def bridges_receivers(self) -> list[dict[str, Any]]:
        """The receivers the bridge's sockets held once it ran (before the simulated ESCs
        came): those of sockets that were not there before it."""
        before = {row["owner"] for row in self.receivers("before_bridge")}
        return [row for row in self.receivers("with_bridge") if row["owner"] not in before]

    def reader_owner(self) -> str:
        """The bridge's socket holding masked filters (the reader's): the output loop's holds
        exact IDs only, the echo of its own frames."""
        owners = {row["owner"] for row in self.bridges_receivers() if row["list"] == "fil"}
        assert len(owners) == 1, self.bridges_receivers()
        return str(owners.pop())

    def readers_filters(self, when: str) -> list[dict[str, Any]]:
        """The filters of the reader's socket, at ``when``."""
        owner = self.reader_owner()
        return [r for r in self.receivers(when) if r["owner"] == owner and r["list"] != "err"]


def log_lines(output: str) -> list[tuple[float, str]]:
    """The bridge's log lines with their time (the guest's clock, as time.time())."""
    lines = []
    for line in output.splitlines():
        with contextlib.suppress(ValueError):
            when = datetime.datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f")
            lines.append((when.timestamp(), line))
    return lines


def same(got: Commands, want: Commands) -> bool:
    """Equal to the resolution of the coarsest command (10-bit CKESC: 1/1000)."""
    return all(abs(value - want[esc]) < 1.5e-3 for esc, value in got.items())


@pytest.fixture(scope="module", params=sorted(FAMILIES))
def flight(request: pytest.FixtureRequest, linux: Kernel) -> Iterator[Flight]:
    family = FAMILIES[request.param]
    result = linux.call(fly, family=request.param, pwm=PWM)
    read = family.read()
    frames = [guest.candump_message(line) for line in result["frames"]]
    commands = [(t, decoded) for t, msg in frames if (decoded := command_of(read, msg)) is not None]
    yield Flight(request.param, family, result, frames, commands)


def test_commands_go_out_at_the_configured_rate(flight: Flight) -> None:
    """The median interval between two commands to one ESC is the configured period (the
    median: a one-CPU guest on a loaded host may miss a tick now and then)."""
    armed = flight.between("live", "paused")
    for esc in range(4):
        times = [t for t, commands in armed if esc in commands]
        assert len(times) > 10, (esc, len(times))
        period_s = statistics.median(b - a for a, b in itertools.pairwise(times))
        rate_hz = flight.family.bridge_config.rate_hz
        assert period_s == pytest.approx(1 / rate_hz, rel=0.1), (esc, period_s)


def test_the_commands_are_the_autopilots_outputs_flood_or_not(flight: Flight) -> None:
    """Every command while armed, the cangen flood included, is the autopilot's output, or safe
    where the input was stale by the bridge's rules: its last output sent longer than the input
    timeout before (the guest stood still while the host ran others). No false failsafe."""
    armed = flight.between("live", "paused")
    assert any(same(c, WANT) for _, c in flight.between("flood", "flooded")), "none in the flood"
    wrong = [(t, c) for t, c in armed if not same(c, WANT)]
    assert all(same(c, SAFE) for _, c in wrong), wrong[:5]
    false_failsafes = [t for t, _ in wrong if not flight.input_stale_at(t)]
    assert not false_failsafes, (false_failsafes, flight.sent_gaps())
    # And the outputs again once they resumed after the stale spell.
    assert any(same(c, WANT) for _, c in flight.between("resumed", "terminated"))


def test_the_escs_telemetry_comes_back_in_esc_status(flight: Flight) -> None:
    status = flight.result["status"]
    assert 0 < status["rpm"][0] < status["rpm"][1] < status["rpm"][2] < status["rpm"][3]
    # The simulated battery: 4 cells (13.2..16.8 V), seen by every ESC.
    assert all(13.0 < volts < 17.0 for volts in status["voltage"]), status
    assert all(amps >= 0 for amps in status["current"]), status


def test_stale_input_gives_safe_values_until_it_resumes(flight: Flight) -> None:
    stale = flight.between("paused", "resumed")
    first_safe = next(i for i, (_, commands) in enumerate(stale) if same(commands, SAFE))
    # input_timeout_ms (1000) after the last output, within the time it was stale.
    assert stale[first_safe][0] - flight.marks["paused"] < STALE_FOR_S
    assert all(same(commands, WANT) for _, commands in stale[:first_safe])
    assert all(same(commands, SAFE) for _, commands in stale[first_safe:])


def test_sigterm_flushes_safe_values_last_and_exits_zero(flight: Flight) -> None:
    assert flight.result["exit"] == 0, flight.result["output"]
    assert "stopped after sending safe values" in flight.result["output"]
    after = [(t, c) for t, c in flight.commands if t >= flight.marks["terminated"]]
    first_safe = next(i for i, (_, commands) in enumerate(after) if same(commands, SAFE))
    assert all(same(commands, SAFE) for _, commands in after[first_safe:])
    # Every ESC had its safe value, last.
    for esc in range(4):
        last = [c[esc] for _, c in after[first_safe:] if esc in c]
        assert last and last[-1] == 0.0, esc


def test_the_kernel_holds_exactly_the_readers_filters(flight: Flight) -> None:
    """/proc/net/can: the reader's socket holds the filters the production code derives for
    this configuration (its ESCs' telemetry), plus the error-frame receiver python-can gives
    every handle it opens. The output loop's socket holds exact IDs only: the echo of the
    frames it sent (docs/running.md, "A bus that holds frames"). None of the reader's filters
    passes a frame the bridge sent: its own commands are never read back (the loop says what
    it sent, through shared memory)."""
    config = flight.family.bridge_config
    family = registry.family(config.output.protocol)
    filters = reader_filters(family, esc_table(config).node_ids, recording=False)
    assert filters is not None  # None is "every frame", for a recording
    want = sorted(kernel_receiver(f) for f in filters)
    held = flight.bridges_receivers()
    reader = flight.reader_owner()
    got = sorted(
        (row["list"], row["can_id"], row["can_mask"]) for row in held if row["owner"] == reader
    )
    assert [r for r in got if r[0] != "err"] == want
    assert [r[0] for r in got if r[0] == "err"] == ["err"]
    loop_rows = [row for row in held if row["owner"] != reader]
    assert len({row["owner"] for row in loop_rows}) <= 1, held
    assert all(row["list"] in ("eff", "sff", "err") for row in loop_rows), loop_rows
    read = flight.family.read()
    sent = [msg for _, msg in flight.frames if command_of(read, msg) is not None]
    assert sent, "no command on the bus"
    fil = flight.readers_filters("with_bridge")
    assert not [msg for msg in sent if any(passes(r, msg) for r in fil)]


def test_a_flood_of_foreign_ids_reaches_none_of_the_readers_filters(flight: Flight) -> None:
    """cangen's random extended IDs: each of the reader's filters passed what it passes without
    them (the ESCs' telemetry), and of the flood only the frames whose random ID happened to be
    one of those (rarely one: DroneCAN's filters take a data type from any node, 2**-17 of the
    29-bit IDs each, so one of the 500 passes in about one flight of 130)."""
    assert flight.result["candump_drops"] == 0, "candump lost frames: the counts cannot be told"
    fil = flight.readers_filters("before_flood")
    flood = [msg for _, msg in flight.frames if msg.data == FLOOD_BYTES]
    assert len(flood) == FLOOD_FRAMES, len(flood)  # every one of them on the bus
    # The filters are narrow: a random extended ID passes one with a chance of 2**-(ID bits
    # its mask holds), under 1 % for the whole flood; two passing would be a 1-in-10 000 run.
    extended = [r for r in fil if r["can_id"] & CAN_EFF_FLAG or not r["can_mask"] & CAN_EFF_FLAG]
    chance = sum(2.0 ** -bin(r["can_mask"] & 0x1FFFFFFF).count("1") for r in extended)
    assert chance * len(flood) < 0.01, [hex(r["can_mask"]) for r in extended]
    flood_passed = [msg for msg in flood if any(passes(r, msg) for r in fil)]
    assert len(flood_passed) <= 1, flood_passed
    after = {(r["owner"], r["can_id"], r["can_mask"]): r for r in flight.receivers("after_flood")}
    marks = flight.marks

    def on_bus(receiver: dict[str, Any], start: float, end: float) -> int:
        return sum(1 for t, msg in flight.frames if start <= t <= end and passes(receiver, msg))

    for r in fil:
        # The kernel counts each filter's matches (a frame two of them pass counts for both).
        # They were read while frames arrived: between what surely came after the first reading
        # and before the second, and what may have.
        passed = after[(r["owner"], r["can_id"], r["can_mask"])]["matches"] - r["matches"]
        least = on_bus(r, marks["flood"], marks["flooded"])
        most = on_bus(r, marks["before_flood"], marks["after_flood"])
        assert least <= passed <= most, (hex(r["can_id"]), hex(r["can_mask"]), least, passed, most)
