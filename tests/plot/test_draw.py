"""The pictures (bridge/plot/draw.py), checked on the figures before saving (panels, labels,
spans, failure marks) and read back from the PNG files (size, not blank)."""

from __future__ import annotations

from pathlib import Path

import pytest

mpl_image = pytest.importorskip(
    "matplotlib.image", reason="matplotlib (the plot extra, in the test extra) is not installed"
)

from matplotlib.patches import Polygon, Rectangle  # noqa: E402 - after the skip
from test_flight import a_flight  # noqa: E402

from bridge.plot.draw import (  # noqa: E402
    DPI,
    ESC_HEIGHT_PX,
    OVERVIEW,
    OVERVIEW_HEIGHT_PX,
    WIDTH_PX,
    draw_esc,
    draw_overview,
    write_pictures,
)
from bridge.plot.series import EscSeries  # noqa: E402


def test_an_escs_figure_has_its_four_panels_spans_and_failures() -> None:
    flight = a_flight()
    figure = draw_esc(flight, flight.escs[0])
    rpm, current, voltage, temperature, command = figure.axes  # the command's twin comes last
    assert [ax.get_ylabel() for ax in (rpm, current, voltage, temperature)] == [
        "rpm",
        "current (A)",
        "voltage (V)",
        "temperature (°C)",
    ]
    assert command.get_ylabel() == "command (throttle)"
    assert temperature.get_xlabel().startswith("time (s) since 20")
    assert temperature.get_xlim() == pytest.approx((0, flight.duration_s))
    assert figure.get_suptitle().endswith("ESC 1, channel 1 (CKESC, 3 telemetry frames)")
    assert rpm.get_lines()[0].get_label() == "rpm"
    texts = [t.get_text() for t in rpm.texts]
    assert "failure: over current" in texts
    # Armed, failsafe and stopped-while-armed spans are shaded on every panel.
    shaded = [p for p in rpm.patches if isinstance(p, Polygon | Rectangle)]
    assert len(shaded) == len(flight.spans) == 3
    legend = figure.legends[0]
    assert [t.get_text() for t in legend.get_texts()] == [
        "autopilot armed",
        "bridge failsafe",
        "every ESC commanded to stop while armed",
    ]
    assert [t.get_text() for t in current.texts] == ["no current in the recording"]
    size = figure.get_size_inches() * figure.dpi
    assert list(size) == [WIDTH_PX, ESC_HEIGHT_PX]


def test_the_overview_has_every_escs_rpm_and_command() -> None:
    flight = a_flight()
    figure = draw_overview(flight)
    rpm, command = figure.axes
    assert rpm.get_ylabel() == "rpm" and command.get_ylabel() == "command (throttle)"
    assert [line.get_label() for line in rpm.get_lines() if line.get_label() == "ESC 1"]


def test_the_pictures_read_back_at_their_size(tmp_path: Path) -> None:
    flight = a_flight()
    silent = EscSeries(None, channel=3, commands=flight.escs[0].commands)
    flight = type(flight)(**{**flight.__dict__, "escs": (*flight.escs, silent)})
    written = write_pictures(flight, tmp_path / "out")
    assert [p.name for p in written] == [OVERVIEW, "esc-1.png", "channel-3.png"]
    heights = (OVERVIEW_HEIGHT_PX, ESC_HEIGHT_PX, ESC_HEIGHT_PX)
    for path, height in zip(written, heights, strict=True):
        pixels = mpl_image.imread(path)
        assert pixels.shape[:2] == (height, WIDTH_PX), path
        assert pixels.std() > 0.05, path  # something drawn, not a blank page
    assert DPI * 14 == WIDTH_PX
