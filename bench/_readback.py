"""The guest's side of ``bench/readback.py``: runs where the kernel is (tests/linux's agent calls
:func:`measure`), and its ``__main__`` is the reader process being measured.

:func:`measure` puts the bridge's command frames on a vcan of its own at the configured rate
(``cangen`` repeating the driver's safe frames: the same IDs and length as every command).
Then it runs the reader, each way in turn, in a process of its own (``python
bench/_readback.py reader ...``): the production :class:`~bridge.telemetry.reader.CanReader`
on a handle that the kernel filters with the family's telemetry filters (what the bridge
runs), or with the family's command filters beside them. Each reader reports its own CPU time
over the measured seconds and the frames it read. The ESCs' telemetry would cost both ways
the same and is left out: in a guest on a busy machine the simulated ESCs' rate wandered (6
to 150 frames a second beside a load of 14) and drowned the difference.
"""

from __future__ import annotations

import json
import resource
import sys
import time
from pathlib import Path
from typing import Any

from can.typechecking import CanFilter

from bridge._compat import tomllib
from bridge.can_io import open_bus
from bridge.config import BridgeConfig, build_config, with_mixer_esc_count
from bridge.escs import registry
from bridge.telemetry.for_config import esc_table
from bridge.telemetry.reader import CanReader

WARM_UP_S = 1.0  # the reader's first second: its handle's queue drained, its caches warm


def _config(text: str, channel: str) -> BridgeConfig:
    raw = tomllib.loads(text)
    raw.setdefault("can", {}).update({"interface": "socketcan", "channel": channel})
    return with_mixer_esc_count(build_config(raw, "bench"))


def command_frames(config: BridgeConfig) -> list[tuple[int, bytes]]:
    """(ID, data) of one cycle of the bridge's commands (its safe values: same IDs and length)."""
    driver = config.family.driver(config.esc_setup)
    return [
        (msg.arbitration_id, bytes(msg.data))
        for tick in range(driver.ticks_per_cycle)
        for msg in driver.safe_frames(tick)
    ]


def filters(config: BridgeConfig, read_back: bool) -> list[CanFilter]:
    """The family's filters: its telemetry, and with ``read_back`` the bridge's command IDs too
    (one exact filter each, as a reader that read them back would ask)."""
    family = registry.family(config.output.protocol)
    telemetry = family.reader_filters(esc_table(config).node_ids)
    if not read_back:
        return telemetry
    commands: list[CanFilter] = [
        {"can_id": ident, "can_mask": 0x1FFFFFFF, "extended": True}
        for ident in sorted({ident for ident, _ in command_frames(config)})
    ]
    return [*telemetry, *commands]


def measure(config: str, seconds: float, order: list[bool]) -> list[dict[str, Any]]:
    """In the kernel: the commands on a vcan, and a reader run for each of ``order`` (True: the
    commands pass its filters)."""
    from linux import guest

    channel = guest.vcan()
    path = guest.scratch() / "bridge.toml"
    path.write_text(config)
    bridge_config = _config(config, channel)
    frames = command_frames(bridge_config)
    gap_ms = 1000 / (
        bridge_config.rate_hz * bridge_config.family.driver(bridge_config.esc_setup).ticks_per_cycle
    )
    for ident, data in frames:
        guest.cangen(
            channel,
            *("-e", "-I", f"{ident:08X}", "-L", str(len(data)), "-D", data.hex().upper()),
            *("-g", f"{gap_ms * len(frames):.3f}"),
        )
    results = []
    for read_back in order:
        out = guest.run(
            [sys.executable, __file__, "reader", str(path), channel, str(seconds), str(read_back)],
            timeout_s=seconds + 120,
        )
        results.append({"read_back": read_back, **json.loads(out.strip().splitlines()[-1])})
    return results


def reader(config_path: str, channel: str, seconds: float, read_back: bool) -> dict[str, Any]:
    """The measured process: the production reader on a filtered handle, for ``seconds``."""
    config = _config(Path(config_path).read_text(), channel)
    family = registry.family(config.output.protocol)
    table = esc_table(config)
    bus = open_bus(
        config.can, config.bitrate, receive="telemetry", filters=filters(config, read_back)
    )
    can_reader = CanReader(bus, table, family)
    can_reader.start()
    time.sleep(WARM_UP_S)
    before, frames_before = resource.getrusage(resource.RUSAGE_SELF), can_reader.stats.frames
    started = time.monotonic()
    time.sleep(seconds)
    after, frames_after = resource.getrusage(resource.RUSAGE_SELF), can_reader.stats.frames
    elapsed = time.monotonic() - started
    can_reader.close()
    bus.shutdown()
    cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {
        "cpu_s": cpu_s,
        "seconds": elapsed,
        "frames": frames_after - frames_before,
    }


if __name__ == "__main__" and sys.argv[1:2] == ["reader"]:
    _, _, path, interface, duration, with_read_back = sys.argv
    print(json.dumps(reader(path, interface, float(duration), with_read_back == "True")))
