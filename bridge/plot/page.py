"""The HTML page of a plotted recording: the flight in numbers, then its pictures.

One self-contained file (``index.html``) beside the pictures, which it shows by relative name:
what was recorded, the spans (armed, failsafe, ...), one row per ESC (frames, highest rpm and
current, voltage range, hottest sensor, failure flags), the STATUSTEXTs in the tlog, and the
pictures. Pure: a :class:`~bridge.plot.flight.Flight` and picture names in, text out.
"""

from __future__ import annotations

import datetime
from collections.abc import Sequence
from html import escape
from typing import Final

from bridge.plot.flight import Flight
from bridge.plot.series import EscSeries, Series, failure_names

PAGE: Final = "index.html"

_STYLE: Final = """
body { font-family: sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: right; }
th { background: #f3f3f3; }
td.text { text-align: left; }
.bad { color: #b00000; font-weight: bold; }
img { max-width: 100%; display: block; margin: 1em 0 2em; border: 1px solid #ddd; }
"""


def _number(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _range(series: Series) -> str:
    if not len(series):
        return "-"
    return f"{min(series.values):.2f} .. {max(series.values):.2f}"


def _hottest(esc: EscSeries) -> str:
    best: tuple[float, str] | None = None
    for sensor, series in esc.temps_c.items():
        if len(series):
            top = max(series.values)
            if best is None or top > best[0]:
                best = (top, sensor)
    return "-" if best is None else f"{best[0]:.1f} ({escape(best[1])})"


def _failures(esc: EscSeries) -> str:
    if not esc.failures:
        return "none"
    flags = 0
    for run in esc.failures:
        flags |= run.flags
    first = esc.failures[0].start_s
    return (
        f'<span class="bad">{escape(", ".join(failure_names(flags)))} (from {first:.1f} s)</span>'
    )


def page_html(flight: Flight, pictures: Sequence[str]) -> str:
    """The page for ``flight``, showing ``pictures`` (file names beside the page) in order."""
    start = datetime.datetime.fromtimestamp(flight.start_wall_s, datetime.timezone.utc)
    can = flight.can
    title = escape(flight.name)
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{title}</title><style>{_STYLE}</style></head><body>",
        f"<h1>{title}</h1>",
        f"<p>Recorded {start:%Y-%m-%d %H:%M:%S} UTC, {flight.duration_s:.1f} s. "
        f"CAN: {can.frames} frames read as {escape(can.family)} ({can.telemetry_frames} "
        f"telemetry, {can.command_frames} commands, {can.other} other, {can.malformed} "
        f"malformed, {can.bad_lines} unreadable lines). MAVLink: {flight.tlog_records} "
        f"messages, {flight.tlog_bad_records} unreadable.</p>",
        "<h2>Spans</h2>",
    ]
    if flight.spans:
        parts.append("<table><tr><th>what</th><th>from (s)</th><th>to (s)</th><th>for (s)</th>")
        parts.append("<th>as reported</th></tr>")
        for span in flight.spans:
            parts.append(
                f'<tr><td class="text">{escape(span.kind)}</td><td>{span.start_s:.3f}</td>'
                f"<td>{span.end_s:.3f}</td><td>{span.end_s - span.start_s:.3f}</td>"
                f'<td class="text">{escape(span.label)}</td></tr>'
            )
        parts.append("</table>")
    else:
        parts.append("<p>The autopilot was never armed; no failsafe, no motor test.</p>")
    parts += [
        "<h2>ESCs</h2>",
        "<table><tr><th>ESC</th><th>telemetry frames</th><th>max |rpm|</th>",
        "<th>max supply current (A)</th><th>voltage (V)</th><th>hottest (°C)</th>",
        "<th>failure flags</th></tr>",
    ]
    for esc in flight.escs:
        parts.append(
            f'<tr><td class="text">{escape(esc.title)}</td><td>{esc.telemetry_frames}</td>'
            f"<td>{_number(esc.rpm.max_abs(), 0)}</td>"
            f"<td>{_number(esc.current_a.max_abs())}</td><td>{_range(esc.voltage_v)}</td>"
            f'<td>{_hottest(esc)}</td><td class="text">{_failures(esc)}</td></tr>'
        )
    parts.append("</table>")
    if flight.texts:
        parts.append("<h2>Messages (STATUSTEXT)</h2><table>")
        parts.append("<tr><th>time (s)</th><th>from</th><th>severity</th><th>text</th></tr>")
        for text in flight.texts:
            parts.append(
                f"<tr><td>{text.t_s:.3f}</td><td>{text.system}/{text.component}</td>"
                f'<td>{text.severity}</td><td class="text">{escape(text.text)}</td></tr>'
            )
        parts.append("</table>")
    parts.append("<h2>Pictures</h2>")
    for picture in pictures:
        name = escape(picture)
        parts.append(f'<a href="{name}"><img src="{name}" alt="{name}"></a>')
    parts.append("</body></html>\n")
    return "\n".join(parts)
