"""``esc-bridge monitor --web``: the monitor's vehicles as a live web page.

:mod:`.model` turns the vehicles into the page's JSON messages (pure), :mod:`.server` serves
the page (``page.html``, ``page.js``, ``page.css``, package data beside these modules) and
streams the messages to every browser.
"""

from __future__ import annotations

from bridge.monitor.web.server import (
    DEFAULT_HOST,
    PUSH_PERIOD_S,
    WebMonitor,
    WebStats,
    is_loopback,
    parse_address,
)

__all__ = [
    "DEFAULT_HOST",
    "PUSH_PERIOD_S",
    "WebMonitor",
    "WebStats",
    "is_loopback",
    "parse_address",
]
