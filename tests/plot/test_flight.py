"""A recording ready to draw (bridge/plot/flight.py) and its HTML page (bridge/plot/page.py):
one time axis from the first record of either file, the spans from both, and the page's
summary, escaped."""

from __future__ import annotations

import can
import pytest
from test_series import T0, ck, throttles

from bridge.capture import BadLine
from bridge.errors import ConfigError
from bridge.escs import registry
from bridge.escs.ckesc import records
from bridge.plot.flight import Flight, flight
from bridge.plot.page import page_html
from bridge.plot.recording import Heartbeat, StatusText, TlogEvents
from bridge.plot.series import capture_series
from bridge.plot.spans import ARMED, FAILSAFE, STOPPED_ARMED

S = records.Msg1Status


def a_flight() -> Flight:
    messages: list[can.Message | BadLine] = [
        throttles(1.0, 0),
        ck(1.1, 1, records.Msg1(0, 0, S.RUNNING)),
        throttles(2.0, 600),
        ck(2.1, 1, records.Msg1(4000, 600, S.RUNNING | S.OVER_CURRENT)),
        throttles(5.0, 0),  # failsafe: stopped while armed
        ck(5.1, 1, records.Msg1(0, 0, S.RUNNING)),
        throttles(6.0, 600),
        BadLine(3, "x", "y"),
    ]
    captured = capture_series(messages, registry.family("ckesc"))
    tlog = TlogEvents(
        heartbeats=(
            Heartbeat(T0 + 0.5, False),
            *(Heartbeat(T0 + 2.0 + i / 2, True) for i in range(11)),  # armed 2.0 .. 7.0
        ),
        texts=(
            StatusText(T0 + 5.0, 2, "ESC out: FAILSAFE input stale, motors stopped", 1, 191),
            StatusText(T0 + 6.0, 6, "ESC out: armed, sending motor commands", 1, 191),
            StatusText(T0 + 6.5, 4, "<b>Low battery</b> & more", 1, 1),
        ),
        first_s=T0 + 0.5,
        last_s=T0 + 7.0,
        records=40,
        bad_records=1,
    )
    return flight("esc-bridge-20260101-000000", captured, tlog)


def test_both_files_on_one_time_axis_with_every_span() -> None:
    got = a_flight()
    assert got.start_wall_s == T0 + 0.5 and got.duration_s == pytest.approx(6.5)
    (esc,) = got.escs
    assert esc.rpm.t_s == pytest.approx((0.6, 1.6, 4.6))
    assert esc.commands["throttle"].t_s == pytest.approx((0.5, 1.5, 4.5, 5.5))
    assert [(round(f.start_s, 6), round(f.end_s, 6)) for f in esc.failures] == [(1.6, 4.6)]
    spans = [(s.kind, round(s.start_s, 6), round(s.end_s, 6)) for s in got.spans]
    assert spans == [(ARMED, 1.5, 6.5), (FAILSAFE, 4.5, 5.5), (STOPPED_ARMED, 4.5, 5.5)]
    assert got.spans_of(FAILSAFE)[0].label == "FAILSAFE input stale, motors stopped"
    assert got.texts[0].t_s == pytest.approx(4.5)
    assert (got.can.frames, got.can.bad_lines, got.tlog_records) == (7, 1, 40)


def test_an_empty_recording_is_refused() -> None:
    captured = capture_series([], registry.family("ft"))
    with pytest.raises(ConfigError, match="both its files are empty"):
        flight("empty", captured, TlogEvents())


def test_the_page_sums_the_flight_up_and_shows_the_pictures() -> None:
    html = page_html(a_flight(), ["overview.png", "esc-1.png"])
    assert "<h1>esc-bridge-20260101-000000</h1>" in html
    assert "CAN: 7 frames read as CKESC" in html and "MAVLink: 40 messages, 1 unreadable" in html
    assert "FAILSAFE input stale, motors stopped" in html
    assert "over current (from 1.6 s)" in html
    assert "&lt;b&gt;Low battery&lt;/b&gt; &amp; more" in html and "<b>Low" not in html
    assert html.index('src="overview.png"') < html.index('src="esc-1.png"')
