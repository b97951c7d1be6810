"""MAV_SEVERITY values of the bridge's STATUSTEXTs (the log level follows: WARNING and worse
log as warnings)."""

from __future__ import annotations

SEVERITY_CRITICAL, SEVERITY_WARNING, SEVERITY_NOTICE, SEVERITY_INFO = 2, 4, 5, 6
