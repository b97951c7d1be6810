"""The CKESC driver: fractions to throttle frames, never out of range."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridge.escs.ckesc import codec, records
from bridge.escs.ckesc.driver import CkescDriver

ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)


def _throttles(frames: list[codec.CkescFrame]) -> dict[int, int]:
    """Channel -> throttle from decoded 12b frames."""
    out = {}
    for frame in frames:
        message = frame.message
        assert isinstance(message, records.RawCommand12b)
        for i, value in enumerate(message.throttles):
            out[4 * message.group - 3 + i] = value
    return out


def test_ckesc_12b_groups_and_scaling() -> None:
    driver = CkescDriver("12b", [1, 2, 3, 4, 5, 6, 7, 8])
    msgs = driver.tick_frames(0, [0.0, 0.25, 0.5, 1.0, 0.0005, 0.9995, 0.3, 0.7])
    frames = [codec.decode(m) for m in msgs]
    assert all(f is not None for f in frames)
    throttles = _throttles([f for f in frames if f is not None])
    assert throttles == {1: 0, 2: 500, 3: 1000, 4: 2000, 5: 1, 6: 1999, 7: 600, 8: 1400}
    # Each frame of the type takes the next transfer ID.
    assert [f.transfer_id for f in frames if f is not None] == [0, 1]
    assert [f.transfer_id for f in map(codec.decode, driver.safe_frames(1)) if f] == [2, 3]


def test_ckesc_channel_map_leaves_unused_channels_at_zero() -> None:
    driver = CkescDriver("12b", [3, 9])
    frames = [codec.decode(m) for m in driver.tick_frames(0, [1.0, 0.5])]
    throttles = _throttles([f for f in frames if f is not None])
    assert throttles[3] == 2000 and throttles[9] == 1000
    assert {k: v for k, v in throttles.items() if k not in (3, 9)} == dict.fromkeys(
        [1, 2, 4, 10, 11, 12], 0
    )


def test_ckesc_10b_and_14b() -> None:
    msg = CkescDriver("10b", [1, 2, 3, 4, 5, 6]).tick_frames(0, [0.1, 0.2, 0.3, 0.4, 0.5, 1.0])[0]
    frame = codec.decode(msg)
    assert frame is not None and isinstance(frame.message, records.RawCommand10b)
    assert frame.message.throttles == (100, 200, 300, 400, 500, 1000)
    msg = CkescDriver("14b", [1, 2, 3, 4]).tick_frames(0, [0.5, 0.5, 0.5, 0.5])[0]
    assert msg.arbitration_id == 0x004E8400
    assert bytes(msg.data[:7]) == bytes.fromhex("e80fa03e80fa03")  # docs/protocols.md §3.9


@given(st.lists(ANY_FLOAT, min_size=8, max_size=8))
def test_ckesc_never_out_of_range(fractions: list[float]) -> None:
    for frame in map(codec.decode, CkescDriver("12b", range(1, 9)).tick_frames(0, fractions)):
        assert frame is not None and isinstance(frame.message, records.RawCommand12b)
        assert all(0 <= t <= records.THROTTLE_MAX for t in frame.message.throttles)


def test_ckesc_frames_made_for_an_input_are_the_ones_its_ticks_send(
    ckesc_12b_encodes: list[float],
) -> None:
    """``prepare`` makes an input's frames between ticks: the ticks that send them encode
    nothing, only stamp their transfer IDs, and send what a driver never prepared sends."""
    fractions = [0.0, 0.25, 0.5, 1.0, 0.0005, 0.9995, 0.3, 0.7]
    unprepared = CkescDriver("12b", range(1, 9))
    expected = [
        [(m.arbitration_id, bytes(m.data)) for m in unprepared.tick_frames(tick, fractions)]
        for tick in range(3)
    ]
    made = len(ckesc_12b_encodes)
    prepared = CkescDriver("12b", range(1, 9))
    prepared.prepare(fractions)
    assert len(ckesc_12b_encodes) == made + 2
    for tick in range(3):
        sent = prepared.tick_frames(tick, list(fractions))  # an equal list, not the same one
        assert [(m.arbitration_id, bytes(m.data)) for m in sent] == expected[tick]
    assert len(ckesc_12b_encodes) == made + 2
    assert [f.transfer_id for f in map(codec.decode, sent) if f] == [4, 5]


def test_ckesc_a_prepare_that_fails_leaves_no_frames_behind() -> None:
    """A vector that cannot be encoded raises, and the frames made before it are dropped: the
    tick makes its own again rather than send ones it did not ask for."""
    driver = CkescDriver("12b", range(1, 9))
    driver.prepare([0.5] * 8)
    with pytest.raises(ValueError):
        driver.prepare([0.25] * 7)
    frames = [codec.decode(m) for m in driver.tick_frames(0, [1.0] * 8)]
    assert _throttles([f for f in frames if f is not None]) == dict.fromkeys(range(1, 9), 2000)
