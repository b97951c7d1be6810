"""The shared-memory hand-over: whole records across processes, the last good one on a
collision, never "nothing" or "disarmed" because a write was in progress."""

from __future__ import annotations

import copy
import math
import multiprocessing
import struct
import time
from typing import Any

from bridge.output.mailbox import InputSnapshot, MotorTestBlock, SharedBlock


def _reader(block: SharedBlock, ready: Any, distinct: Any, out: Any) -> None:
    """In another process: read until the final record, checking every read is one whole
    write; ``distinct`` tells the writer how many different writes it has seen so far."""
    seen: list[tuple[int, float]] = []
    ready.set()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        record = block.read()
        if record is None:
            continue
        seq, stamp, *values = record
        assert len(set(values)) == 1, f"torn read: {values}"
        assert stamp == round(values[0] * 1e9), "stamp and values from different writes"
        if not seen or seen[-1][0] != seq:
            seen.append((seq, values[0]))
            distinct.value = len(seen)
        if values[0] == 1.0:
            break
    out.put([len(seen), seen[-1]])


def test_reads_are_whole_writes_across_processes() -> None:
    ctx = multiprocessing.get_context("spawn")
    block = SharedBlock("q16d", ctx)
    results: Any = ctx.Queue()
    ready = ctx.Event()
    distinct_seen = ctx.Value("q", 0, lock=False)
    reader = ctx.Process(target=_reader, args=(block, ready, distinct_seen, results))
    reader.start()
    assert ready.wait(30)
    # Write until the reader has overlapped many writes (a loaded machine may schedule it late
    # and seldom), or for 20 s at most.
    start = time.monotonic()
    writes = 0
    while writes < 200_000 or (distinct_seen.value <= 100 and time.monotonic() - start < 20):
        writes += 1
        block.write(writes, *([writes / 1e9] * 16))
    block.write(1_000_000_000, *([1.0] * 16))
    distinct, last = results.get(timeout=30)
    reader.join(10)
    assert reader.exitcode == 0
    assert last == (writes + 1, 1.0)
    assert distinct > 100, "the reader should have seen writes in progress, not just the last"


def _tear(block: SharedBlock) -> None:
    """Leave ``block`` as a writer preempted half-way leaves it: a new sequence number and part
    of a new body in memory, the checksum still the old record's."""
    raw = memoryview(block._raw).cast("B")
    struct.pack_into("<Q", raw, 0, 999)
    raw[8] ^= 0xFF


def test_a_collision_keeps_the_last_good_read_instead_of_nothing() -> None:
    snapshot = InputSnapshot(4)
    vector = [1500.0] * 4 + [math.nan] * 32
    snapshot.write(1_000, [0.5, 0.5, 0.5, 0.5], True, 2_000, vector)
    first = snapshot.read()
    assert first is not None and first.armed and first.fractions == (0.5, 0.5, 0.5, 0.5)
    assert first.inputs[:4] == (1500.0,) * 4 and len(first.inputs) == 36
    _tear(snapshot._block)
    again = snapshot.read()
    assert again == first  # not None, not disarmed: the last whole record
    snapshot.write(3_000, None, False, 4_000, vector)  # the writer finishes a later record
    latest = snapshot.read()
    assert latest is not None and not latest.armed and not latest.valid
    assert latest.produced_ns == 3_000 and latest.fractions == ()


def test_a_new_sequence_number_never_comes_with_an_old_body() -> None:
    block = SharedBlock("qq")
    block.write(1, 1)
    fresh_reader = copy.copy(block)  # another reader of the same memory
    assert block.read() == (1, 1, 1)
    _tear(block)
    assert block.read() == (1, 1, 1)  # the torn (new seq, old body) mix is refused whole
    assert fresh_reader.read() is None  # one that never read a whole record: none yet


def test_motor_tests_are_read_once_each_and_validated() -> None:
    tests = MotorTestBlock(4)
    assert tests.read_motor_test(0) is None
    tests.write_motor_test(1, 2, 0.25, 10, 5, 8)
    test = tests.read_motor_test(0)
    assert test is not None and (test.first, test.count, test.fraction) == (1, 2, 0.25)
    assert test.until_ns == 10 + 8 + 5
    assert [test.index_at(t) for t in (9, 10, 14, 15, 18, 22, 23)] == [-1, 1, 1, -1, 2, 2, -1]
    assert tests.read_motor_test(test.seq) is None  # nothing new
    tests.stop_motor_test()
    stopped = tests.read_motor_test(test.seq)
    assert stopped is not None and stopped.count == 0 and stopped.until_ns == 0
    for bad in [(3, 2, 0.5, 0, 1, 1), (0, 1, 1.5, 0, 1, 1), (0, 1, 0.5, 0, 2, 1)]:
        try:
            tests.write_motor_test(*bad)
        except ValueError:
            continue
        raise AssertionError(f"{bad} accepted")
