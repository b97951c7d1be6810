"""Codec throughput: encode and decode rates of the ESC protocols, on one core.

Run: ``python bench/codec.py [--runs 9] [--frames 20000]``

Each workload codes a batch of frames; a run's rate is frames / elapsed. The table gives the
median over runs with the 10th and 90th percentile, the median cost per frame, and the share
of one core needed to keep up with a saturated 1 Mbit/s bus (about 6 250 frames/s).
Targets (issue 2): decode >= 200 000 telemetry frames/s, encode >= 200 000 throttle frames/s.
DroneCAN's RawCommand for 8 ESCs is a 3-frame transfer: the output loop's hand encoder and the
``dronecan`` package's (the reason the loop does not use the package) are both timed, per frame.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can
from _stats import percentile

from bridge.escs import uavcan_v0
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.dronecan import wire
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.escs.vesc import codec as vesc_codec
from bridge.escs.vesc import records as vesc_records

BUS_SATURATION_FRAMES_PER_S = 6_250
TARGET_FRAMES_PER_S = 200_000
ESC_NODES = frozenset(range(1, 21))


@dataclass(frozen=True)
class Workload:
    name: str
    target_per_s: int | None
    make_batch: Callable[[int], Callable[[], int]]  # frames -> a run that codes them


def _ckesc_encode_12b(frames: int) -> Callable[[], int]:
    groups = [(1 + i % 5, [(i * 7 + k * 131) % 2001 for k in range(4)]) for i in range(frames)]

    def run() -> int:
        tid = 0
        for group, throttles in groups:
            ckesc_codec.encode_raw_12b(group, throttles, tid)
            tid = (tid + 1) & 31
        return len(groups)

    return run


def _ckesc_encode_14b(frames: int) -> Callable[[], int]:
    commands = [[(i * 7 + k * 131) % 2001 for k in range(4)] for i in range(frames)]

    def run() -> int:
        for i, throttles in enumerate(commands):
            ckesc_codec.encode_raw_14b(throttles, i & 31)
        return len(commands)

    return run


def _ckesc_encode_10b(frames: int) -> Callable[[], int]:
    commands = [[(i * 7 + k * 131) % 1001 for k in range(6)] for i in range(frames)]

    def run() -> int:
        for throttles in commands:
            ckesc_codec.encode_raw_10b(throttles)
        return len(commands)

    return run


def _ft_encode(command: ft_records.Command, scale: float) -> Callable[[int], Callable[[], int]]:
    def make(frames: int) -> Callable[[], int]:
        values = [(i % 1000) / 1000 * scale for i in range(frames)]

        def run() -> int:
            for i, value in enumerate(values):
                ft_codec.encode_command(1 + i % 8, command, value)
            return len(values)

        return run

    return make


DRONECAN_ESCS = 8


def _dronecan_commands(i: int) -> list[int]:
    return [(i * 37 + 500 * k) % 8192 for k in range(DRONECAN_ESCS)]


def _dronecan_encode_by_hand(frames: int) -> Callable[[], int]:
    encoder = wire.RawCommandEncoder(DRONECAN_ESCS, source_node=10)
    values = [_dronecan_commands(i) for i in range(64)]

    def run() -> int:
        count = 0
        while count < frames:
            count += len(encoder.frames(values[count & 63]))
        return count

    return run


def _dronecan_encode_with_package(frames: int) -> Callable[[], int]:
    import dronecan  # only here: the bridge's loop never imports it
    from dronecan.transport import Transfer

    raw_command: Any = dronecan.uavcan.equipment.esc.RawCommand
    values = [_dronecan_commands(i) for i in range(64)]

    def run() -> int:
        count = 0
        while count < frames:
            transfer = Transfer(
                transfer_id=count & 31,
                source_node_id=10,
                payload=raw_command(cmd=values[count & 63]),
                transfer_priority=wire.PRIORITY_ESC_COMMAND,
            )
            count += len(transfer.to_frames())
        return count

    return run


def _ckesc_telemetry(frames: int) -> list[can.Message]:
    messages: list[ckesc_records.CkescMessage] = [
        ckesc_records.Msg1(
            speed_rpm=12_000, throttle=1_500, status=ckesc_records.Msg1Status.RUNNING
        ),
        ckesc_records.Msg2(voltage_v=25.2, current_a=12.34, mos_temp_c=45),
        ckesc_records.Msg3(mos_temp_c=45, capacitor_temp_c=40, motor_temp_c=60, mcu_temp_c=50),
    ]
    out = []
    for i in range(frames):
        frame = ckesc_codec.CkescFrame(
            priority=uavcan_v0.PRIORITY_LOWEST,
            source_node=1 + i % 20,
            destination_node=None,
            transfer_id=i & 31,
            message=messages[i % 3],
        )
        out.append(ckesc_codec.encode(frame))
    return out


def _vesc_encode_duty(frames: int) -> Callable[[], int]:
    values = [(i % 1000) / 1000 for i in range(frames)]

    def run() -> int:
        for i, value in enumerate(values):
            vesc_codec.encode_command(1 + i % 8, vesc_records.Packet.SET_DUTY, value)
        return len(values)

    return run


def _vesc_telemetry(frames: int) -> list[can.Message]:
    messages: list[vesc_records.VescMessage] = [
        vesc_records.Status(erpm=84_000, motor_current_a=12.5, duty=0.55),
        vesc_records.Status4(45.5, 60.2, 10.2, 0.0),
        vesc_records.Status5(tachometer=123_456, input_voltage_v=25.2),
    ]
    return [
        vesc_codec.encode(vesc_records.VescFrame(1 + i % 20, messages[i % 3]))
        for i in range(frames)
    ]


def _ft_telemetry(frames: int) -> list[can.Message]:
    messages: list[ft_records.FtMessage] = [
        ft_records.RealtimeData0(motor_current_a=12.5, battery_current_a=10.25),
        ft_records.RealtimeData1(erpm=84_000, duty=0.55),
        ft_records.RealtimeData2(mosfet_temp_c=45.5, motor_temp_c=60.25, battery_voltage_v=25.2),
    ]
    return [
        ft_codec.encode(ft_records.FtFrame(esc_id=1 + i % 20, message=messages[i % 3]))
        for i in range(frames)
    ]


def _decoder(
    make_frames: Callable[[int], list[can.Message]], decode: Callable[[can.Message], object]
) -> Callable[[int], Callable[[], int]]:
    def make(frames: int) -> Callable[[], int]:
        batch = make_frames(frames)

        def run() -> int:
            for msg in batch:
                if decode(msg) is None:
                    raise AssertionError(f"benchmark frame not decoded: {msg}")
            return len(batch)

        return run

    return make


WORKLOADS = [
    Workload("ckesc encode RawCommand_12b", TARGET_FRAMES_PER_S, _ckesc_encode_12b),
    Workload("ckesc encode RawCommand_14b", TARGET_FRAMES_PER_S, _ckesc_encode_14b),
    Workload("ckesc encode RawCommand_10b", TARGET_FRAMES_PER_S, _ckesc_encode_10b),
    Workload(
        "ft encode SET_CURRENT_GEAR_CRC16",
        TARGET_FRAMES_PER_S,
        _ft_encode(ft_records.Command.SET_CURRENT_GEAR_CRC16, 50.0),
    ),
    Workload(
        "ft encode SET_DUTY_GEAR",
        TARGET_FRAMES_PER_S,
        _ft_encode(ft_records.Command.SET_DUTY_GEAR, 1.0),
    ),
    Workload("vesc encode SET_DUTY", TARGET_FRAMES_PER_S, _vesc_encode_duty),
    Workload(
        f"dronecan encode RawCommand x{DRONECAN_ESCS}",
        TARGET_FRAMES_PER_S,
        _dronecan_encode_by_hand,
    ),
    Workload(f"dronecan pkg RawCommand x{DRONECAN_ESCS}", None, _dronecan_encode_with_package),
    Workload(
        "ckesc decode MSG1/2/3",
        TARGET_FRAMES_PER_S,
        _decoder(_ckesc_telemetry, lambda m: ckesc_codec.decode(m, ESC_NODES)),
    ),
    Workload(
        "ft decode REALTIME_DATA_0/1/2",
        TARGET_FRAMES_PER_S,
        _decoder(_ft_telemetry, ft_codec.decode),
    ),
    Workload(
        "vesc decode STATUS/4/5",
        TARGET_FRAMES_PER_S,
        _decoder(_vesc_telemetry, vesc_codec.decode),
    ),
]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=9, help="runs per workload (default 9)")
    parser.add_argument("--frames", type=int, default=20_000, help="frames per run")
    args = parser.parse_args()

    header = (
        f"{'workload':<34} {'median/s':>10} {'p10/s':>10} {'p90/s':>10} "
        f"{'µs/frame':>9} {'%core@bus':>9} {'target':>8}"
    )
    print(f"codec throughput, {args.runs} runs x {args.frames} frames, one core")
    print(header)
    print("-" * len(header))
    failed = 0
    for workload in WORKLOADS:
        run = workload.make_batch(args.frames)
        run()  # warm-up: first-call costs are not what a running bridge pays
        rates = []
        for _ in range(args.runs):
            start = time.perf_counter()
            count = run()
            rates.append(count / (time.perf_counter() - start))
        median = statistics.median(rates)
        verdict = "-"
        if workload.target_per_s is not None:
            verdict = "ok" if median >= workload.target_per_s else "MISSED"
            failed += verdict == "MISSED"
        print(
            f"{workload.name:<34} {median:>10,.0f} {percentile(rates, 0.1):>10,.0f} "
            f"{percentile(rates, 0.9):>10,.0f} {1e6 / median:>9.2f} "
            f"{100 * BUS_SATURATION_FRAMES_PER_S / median:>8.1f}% {verdict:>8}"
        )
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
