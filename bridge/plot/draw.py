"""The pictures of a :class:`~bridge.plot.flight.Flight`, drawn with matplotlib.

Figures are made with :class:`matplotlib.figure.Figure` and saved through the Agg canvas, never
through ``pyplot``: no GUI backend, no global figure state, nothing for a headless machine to
lack. Only ``esc-bridge plot`` imports this module (matplotlib is the optional extra ``plot``).

Pictures, :data:`WIDTH_PX` wide:

- ``overview.png``: every ESC's rpm, then every ESC's command, over the whole recording;
- ``<esc>.png`` per ESC, four panels over time: rpm with the command on its own axis, supply
  and phase current, voltage, and each temperature sensor it reports.

Every panel shades the spans: the autopilot armed (green), the bridge in failsafe (red), every
ESC commanded to stop while armed (orange hatching), a motor test (purple); a span too narrow
to see at this scale also gets a marker above the top panel. An ESC's failure flags are red
bars along the top of its rpm panel, named at their start.
"""

from __future__ import annotations

import datetime
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.transforms import blended_transform_factory

from bridge.plot.flight import Flight
from bridge.plot.series import EscSeries, Series, thin
from bridge.plot.spans import ARMED, FAILSAFE, MOTOR_TEST, STOPPED_ARMED, Span

WIDTH_PX: Final = 1400
DPI: Final = 100
ESC_HEIGHT_PX: Final = 1100
OVERVIEW_HEIGHT_PX: Final = 800
MAX_POINTS: Final = 4000
"""Points drawn per line at most (:func:`~bridge.plot.series.thin` keeps the extremes)."""
NARROW: Final = 0.004
"""A span narrower than this fraction of the recording also gets a marker."""

SPAN_STYLES: Final[Mapping[str, tuple[str, float, str | None, str]]] = {
    ARMED: ("#2ca02c", 0.10, None, "autopilot armed"),
    FAILSAFE: ("#d62728", 0.30, None, "bridge failsafe"),
    STOPPED_ARMED: ("#ff7f0e", 0.9, "///", "every ESC commanded to stop while armed"),
    MOTOR_TEST: ("#9467bd", 0.25, None, "motor test"),
}
"""Span kind -> (colour, alpha, hatch, legend text)."""
FAILURE_COLOUR: Final = "#b00000"
RPM_COLOUR: Final = "#1f77b4"
COMMAND_COLOURS: Final = ("#333333", "#8c564b", "#e377c2")
ESC_COLOURS: Final = (
    "#1f77b4",
    "#ff7f0e",
    "#2ca02c",
    "#d62728",
    "#9467bd",
    "#8c564b",
    "#e377c2",
    "#7f7f7f",
    "#bcbd22",
    "#17becf",
)

OVERVIEW: Final = "overview.png"


def start_text(flight: Flight) -> str:
    """The recording's start, for axis labels: UTC date and time."""
    start = datetime.datetime.fromtimestamp(flight.start_wall_s, datetime.timezone.utc)
    return start.strftime("%Y-%m-%d %H:%M:%S UTC")


def _figure(height_px: int) -> Figure:
    figure = Figure(figsize=(WIDTH_PX / DPI, height_px / DPI), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _line(ax: Axes, series: Series, label: str, **style: object) -> bool:
    """Draw ``series`` (thinned); False when it is empty."""
    if not len(series):
        return False
    shown = thin(series, MAX_POINTS)
    ax.plot(shown.t_s, shown.values, label=label, linewidth=1.0, **style)  # type: ignore[arg-type]
    return True


def _span_style(kind: str) -> dict[str, Any]:
    """A span's patch style: a fill, or (hatched spans) only the hatch, so that a fill under
    it still shows."""
    colour, alpha, hatch, _ = SPAN_STYLES[kind]
    if hatch is None:
        return {"facecolor": colour, "alpha": alpha, "edgecolor": "none"}
    return {"facecolor": "none", "hatch": hatch, "edgecolor": colour, "alpha": alpha}


def _narrow(span: Span, flight: Flight) -> bool:
    return span.end_s - span.start_s <= NARROW * flight.duration_s


def _shade(ax: Axes, flight: Flight) -> None:
    """Every span, as a band, or a dotted line where a band would be too narrow to see."""
    for span in flight.spans:
        if _narrow(span, flight):
            middle = (span.start_s + span.end_s) / 2
            colour = SPAN_STYLES[span.kind][0]
            ax.axvline(middle, color=colour, linewidth=1.5, linestyle=":", zorder=0)
        else:
            ax.axvspan(span.start_s, span.end_s, linewidth=0, zorder=0, **_span_style(span.kind))


def _mark_narrow(ax: Axes, flight: Flight) -> None:
    """A marker and the length above the panel for each span too narrow to see."""
    top = blended_transform_factory(ax.transData, ax.transAxes)
    for span in flight.spans:
        if span.kind == ARMED or not _narrow(span, flight):
            continue
        colour = SPAN_STYLES[span.kind][0]
        middle = (span.start_s + span.end_s) / 2
        ax.plot([middle], [1.0], marker="v", markersize=9, color=colour, transform=top)
        length = f"{(span.end_s - span.start_s) * 1000:.0f} ms"
        ax.text(middle, 0.985, f" {length}", color=colour, fontsize=9, va="top", transform=top)


def _empty(ax: Axes, what: str) -> None:
    ax.text(
        0.5, 0.5, f"no {what} in the recording", ha="center", va="center", transform=ax.transAxes
    )


def _span_legend(figure: Figure, flight: Flight) -> None:
    kinds = [kind for kind in SPAN_STYLES if flight.spans_of(kind)]
    handles = [Patch(label=SPAN_STYLES[k][3], **_span_style(k)) for k in kinds]
    if handles:
        figure.legend(handles=handles, loc="outside lower center", ncols=len(handles))


def _failures(ax: Axes, esc: EscSeries) -> None:
    top = blended_transform_factory(ax.transData, ax.transAxes)
    for run in esc.failures:
        ax.plot(
            [run.start_s, max(run.end_s, run.start_s)],
            [0.97, 0.97],
            color=FAILURE_COLOUR,
            linewidth=6,
            solid_capstyle="butt",
            transform=top,
        )
        ax.plot([run.start_s], [0.97], marker="o", color=FAILURE_COLOUR, transform=top)
        ax.text(
            run.start_s,
            0.90,
            "failure: " + ", ".join(run.names),
            color=FAILURE_COLOUR,
            fontsize=9,
            va="top",
            transform=top,
        )


def draw_esc(flight: Flight, esc: EscSeries) -> Figure:
    """One ESC's figure: rpm and command, current, voltage, temperatures over time."""
    figure = _figure(ESC_HEIGHT_PX)
    axes = figure.subplots(4, 1, sharex=True, height_ratios=(3, 2, 1.5, 2))
    rpm_ax, current_ax, voltage_ax, temp_ax = axes
    figure.suptitle(
        f"{flight.name}: {esc.title} ({flight.can.family}, {esc.telemetry_frames} telemetry "
        "frames)",
        fontsize=13,
    )
    for ax in axes:
        _shade(ax, flight)
        ax.grid(True, alpha=0.3)
        ax.margins(x=0)
    _mark_narrow(rpm_ax, flight)

    if not _line(rpm_ax, esc.rpm, "rpm", color=RPM_COLOUR):
        _empty(rpm_ax, "rpm")
    rpm_ax.set_ylabel("rpm", color=RPM_COLOUR)
    command_ax = rpm_ax.twinx()
    units = list(esc.commands)
    for i, unit in enumerate(units):
        _line(
            command_ax,
            esc.commands[unit],
            f"command ({unit})",
            color=COMMAND_COLOURS[i % len(COMMAND_COLOURS)],
            alpha=0.8,
            linestyle="-" if i == 0 else ":",
            drawstyle="steps-post",  # a command holds until the next
        )
    command_ax.set_ylabel("command (" + ", ".join(units or ["none read back"]) + ")")
    handles = [*rpm_ax.get_legend_handles_labels()[0], *command_ax.get_legend_handles_labels()[0]]
    if handles:
        rpm_ax.legend(handles=handles, loc="best", fontsize=9)  # clear of the failure bars
    _failures(rpm_ax, esc)

    drew = _line(current_ax, esc.current_a, "supply", color="#d62728")
    drew |= _line(current_ax, esc.motor_current_a, "phase", color="#9467bd", alpha=0.7)
    if drew:
        current_ax.legend(loc="upper right", fontsize=9)
    else:
        _empty(current_ax, "current")
    current_ax.set_ylabel("current (A)")

    if not _line(voltage_ax, esc.voltage_v, "voltage", color="#2ca02c"):
        _empty(voltage_ax, "voltage")
    voltage_ax.set_ylabel("voltage (V)")

    for sensor, series in esc.temps_c.items():
        _line(temp_ax, series, sensor)
    if esc.temps_c:
        temp_ax.legend(loc="upper left", fontsize=9)
    else:
        _empty(temp_ax, "temperature")
    temp_ax.set_ylabel("temperature (°C)")
    temp_ax.set_xlabel(f"time (s) since {start_text(flight)}")
    temp_ax.set_xlim(0, max(flight.duration_s, 1e-3))
    _span_legend(figure, flight)
    return figure


def draw_overview(flight: Flight) -> Figure:
    """Every ESC's rpm, and every ESC's command (in the unit sent most), over time."""
    figure = _figure(OVERVIEW_HEIGHT_PX)
    rpm_ax, command_ax = figure.subplots(2, 1, sharex=True)
    figure.suptitle(
        f"{flight.name}: {len(flight.escs)} ESCs ({flight.can.family}), {flight.duration_s:.1f} s",
        fontsize=13,
    )
    for ax in (rpm_ax, command_ax):
        _shade(ax, flight)
        ax.grid(True, alpha=0.3)
        ax.margins(x=0)
    _mark_narrow(rpm_ax, flight)
    units: list[str] = []
    for i, esc in enumerate(flight.escs):
        colour = ESC_COLOURS[i % len(ESC_COLOURS)]
        name = esc.title.split(",")[0] if esc.node_id is not None else esc.title
        _line(rpm_ax, esc.rpm, name, color=colour)
        if esc.commands:
            unit, series = next(iter(esc.commands.items()))
            units += [unit] if unit not in units else []
            _line(command_ax, series, name, color=colour, alpha=0.8, drawstyle="steps-post")
    rpm_ax.set_ylabel("rpm")
    command_ax.set_ylabel("command (" + ", ".join(units or ["none read back"]) + ")")
    if flight.escs:
        rpm_ax.legend(loc="upper right", fontsize=9, ncols=min(4, len(flight.escs)))
    command_ax.set_xlabel(f"time (s) since {start_text(flight)}")
    command_ax.set_xlim(0, max(flight.duration_s, 1e-3))
    _span_legend(figure, flight)
    return figure


def write_pictures(flight: Flight, directory: Path) -> list[Path]:
    """Save the overview and one picture per ESC into ``directory`` (created if needed); their
    paths, the overview first.

    Raises:
        OSError: the directory or a file cannot be written.
    """
    directory.mkdir(parents=True, exist_ok=True)
    written = [directory / OVERVIEW]
    draw_overview(flight).savefig(written[0])
    for esc in flight.escs:  # one figure at a time: each holds its thinned lines
        written.append(directory / f"{esc.slug}.png")
        draw_esc(flight, esc).savefig(written[-1])
    return written
