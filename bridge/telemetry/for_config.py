"""The ESC state of a configuration: the one place that reads ``[telemetry]`` and the ESC lists
into an :class:`~bridge.telemetry.state.EscTable`, so the state itself stays free of the
configuration (and runs, and is tested, without it)."""

from __future__ import annotations

from bridge.config import BridgeConfig
from bridge.telemetry.state import EscTable, TelemetryLimits


def esc_table(config: BridgeConfig, *, commanded: bool = True) -> EscTable:
    """The ESCs of ``config`` (its ESC lists already sized by ``with_esc_count``), with its
    ``[telemetry]`` timeout, pole pairs and limits; ``commanded``: as :class:`EscTable`."""
    telemetry = config.telemetry
    return EscTable(
        config.escs.ids,
        pole_pairs=telemetry.pole_pairs,
        channels=config.esc_setup.channels,
        timeout_ms=telemetry.timeout_ms,
        limits=TelemetryLimits(
            max_temp_c=telemetry.max_temp_c,
            max_current_a=telemetry.max_current_a,
            max_rpm=telemetry.max_rpm,
            error_burst=telemetry.error_burst,
        ),
        commanded=commanded,
    )
