"""The reopen backoff: doubling from the first wait to the longest, jittered both ways, back to
the first on reset."""

from __future__ import annotations

import pytest

from bridge.backoff import Backoff


def test_the_waits_double_up_to_the_longest_and_start_over_on_reset() -> None:
    backoff = Backoff(0.1, 2.0)
    assert not backoff.grown
    assert [round(backoff.wait_s(0.5), 3) for _ in range(7)] == [0.1, 0.2, 0.4, 0.8, 1.6, 2.0, 2.0]
    assert backoff.grown
    backoff.reset()
    assert not backoff.grown
    assert backoff.wait_s(0.5) == pytest.approx(0.1)


def test_jitter_scales_each_wait_both_ways() -> None:
    assert Backoff(1.0, 1.0).wait_s(0.0) == pytest.approx(0.5)
    assert Backoff(1.0, 1.0).wait_s(1.0) == pytest.approx(1.5)
    assert Backoff(1.0, 1.0, jitter=0.0).wait_s(0.9) == 1.0


def test_an_interface_gone_for_a_minute_is_tried_a_few_dozen_times_not_600() -> None:
    # The fixed 100 ms: 600 attempts a minute. Doubling to 2 s, at the shortest jitter:
    backoff, elapsed_s, attempts = Backoff(0.1, 2.0), 0.0, 0
    while elapsed_s < 60.0:
        elapsed_s += backoff.wait_s(0.0)
        attempts += 1
    assert attempts <= 65
    backoff = Backoff(0.1, 2.0)
    assert sum(backoff.wait_s(1.0) for _ in range(5)) > 4.0  # 5 failed attempts: over 4 s


@pytest.mark.parametrize(("first", "longest", "jitter"), [(0, 1, 0.5), (2, 1, 0.5), (1, 1, 1.0)])
def test_bad_settings_are_refused(first: float, longest: float, jitter: float) -> None:
    with pytest.raises(ValueError, match="expected 0 < first_s <= longest_s"):
        Backoff(first, longest, jitter)
