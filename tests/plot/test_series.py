"""A capture as per-ESC series (bridge/plot/series.py), from real CKESC and FT frames decoded
through their families: telemetry, commands by channel and by node, failure runs, the
all-stopped changes, which ESC a channel drives, the family guess, and thinning."""

from __future__ import annotations

import can
import pytest

from bridge.capture import BadLine
from bridge.errors import ConfigError
from bridge.escs import registry
from bridge.escs.ckesc import codec as ckesc_codec
from bridge.escs.ckesc import records as ckesc_records
from bridge.escs.family import FAILURE_GENERIC, FAILURE_OVER_TEMPERATURE, CommandSeen
from bridge.escs.ft import codec as ft_codec
from bridge.escs.ft import records as ft_records
from bridge.plot.series import (
    EscSeries,
    Series,
    capture_series,
    failure_names,
    guess_family,
    is_stop,
    match_escs,
    thin,
)

S = ckesc_records.Msg1Status
T0 = 1_790_000_000.0  # wall-clock seconds, as a capture stamps its frames


def at(t_s: float, msg: can.Message) -> can.Message:
    msg.timestamp = T0 + t_s
    return msg


def ck(t_s: float, node: int, message: ckesc_records.CkescMessage) -> can.Message:
    frame = ckesc_codec.CkescFrame(ckesc_codec.default_priority(message), node, None, 0, message)
    return at(t_s, ckesc_codec.encode(frame))


def throttles(t_s: float, *values: int) -> can.Message:
    return at(t_s, ckesc_codec.encode_raw_14b(list(values), 0))


def ft_frame(t_s: float, esc_id: int, message: ft_records.FtMessage) -> can.Message:
    return at(t_s, ft_codec.encode(ft_records.FtFrame(esc_id, message)))


def ft_command(t_s: float, esc_id: int, command: ft_records.Command, value: float) -> can.Message:
    return at(t_s, ft_codec.encode_command(esc_id, command, value))


def ckesc_capture() -> list[can.Message | BadLine]:
    return [
        throttles(0.0, 0, 0),
        ck(0.05, 1, ckesc_records.Msg1(0, 0, S.RUNNING)),
        ck(0.06, 2, ckesc_records.Msg1(0, 0, S.RUNNING)),
        throttles(1.0, 400, 500),
        ck(1.05, 1, ckesc_records.Msg1(3000, 400, S.RUNNING)),
        ck(1.06, 1, ckesc_records.Msg2(16.4, 3.25, 41)),
        ck(1.07, 2, ckesc_records.Msg1(3500, 500, S.RUNNING | S.OVER_TEMPERATURE)),
        BadLine(9, "garbage", "ValueError: no"),
        ck(2.0, 2, ckesc_records.Msg1(3400, 500, S.RUNNING | S.OVER_TEMPERATURE | S.UNDER_VOLTAGE)),
        throttles(2.5, 0, 0),  # every channel stopped
        ck(3.0, 2, ckesc_records.Msg1(0, 0, S.RUNNING)),
        throttles(3.5, 300, 300),
        at(3.6, can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False)),
    ]


def test_a_ckesc_capture_as_series_per_node_with_commands_by_channel() -> None:
    captured = capture_series(ckesc_capture(), registry.family("ckesc"))
    assert sorted(captured.telemetry) == [1, 2]
    one, two = captured.telemetry[1], captured.telemetry[2]
    assert one.rpm == Series((T0 + 0.05, T0 + 1.05), (0.0, 3000.0))
    assert one.voltage_v.values == pytest.approx((16.4,))
    assert one.current_a.values == pytest.approx((3.25,))
    assert one.temps_c["MOSFET"] == Series((T0 + 1.06,), (41.0,))
    assert len(one.motor_current_a) == 0 and one.telemetry_frames == 3
    assert two.rpm.values == (0.0, 3500.0, 3400.0, 0.0)
    # OVER_TEMPERATURE from 1.07, joined by UNDER_VOLTAGE (GENERIC) at 2.0, gone at 3.0.
    runs = [(round(r.start_s - T0, 6), round(r.end_s - T0, 6), r.flags) for r in two.failures]
    assert runs == [
        (1.07, 2.0, FAILURE_OVER_TEMPERATURE),
        (2.0, 3.0, FAILURE_OVER_TEMPERATURE | FAILURE_GENERIC),
    ]
    assert two.failures[1].names == ("over temperature", "generic")
    # RawCommand_14b carries its channels as throttle; the bridge's four slots are all read.
    assert sorted(captured.by_channel) == [1, 2, 3, 4] and not captured.by_node
    assert captured.by_channel[2]["throttle"].values == (0.0, 500.0, 0.0, 300.0)
    changes = [(round(t - T0, 6), stopped) for t, stopped in captured.all_stopped]
    assert changes == [(0.0, True), (1.0, False), (2.5, True), (3.5, False)]
    summary = captured.summary
    assert (summary.family, summary.frames, summary.telemetry_frames) == ("CKESC", 12, 7)
    assert (summary.command_frames, summary.other, summary.bad_lines) == (4, 1, 1)
    assert (captured.first_s, captured.last_s) == (T0, T0 + 3.6)


def test_channels_go_to_the_escs_in_order_or_as_given() -> None:
    captured = capture_series(ckesc_capture(), registry.family("ckesc"))
    one, two = match_escs(captured)
    assert (one.node_id, one.channel, one.motor, one.title) == (1, 1, None, "ESC 1, channel 1")
    assert two.commands["throttle"].values == (0.0, 500.0, 0.0, 300.0)
    # Swapped channels, motor numbers from the ID list; channels 3 and 4 only ever carried 0.
    two, one = match_escs(captured, ids=[2, 1], channels=[1, 2])
    assert (two.motor, two.title) == (1, "motor 1, ESC 2, channel 1")
    assert two.commands["throttle"].values == (0.0, 400.0, 0.0, 300.0)
    assert one.commands["throttle"].values == (0.0, 500.0, 0.0, 300.0)
    # One ESC listed: channel 2 is commanded but nobody answers on it, so it is shown.
    (listed, silent) = match_escs(captured, ids=[1])
    assert (silent.node_id, silent.channel, silent.slug) == (None, 2, "channel-2")
    assert silent.title == "throttle channel 2 (no ESC answered)"
    assert listed.rpm == captured.telemetry[1].rpm
    with pytest.raises(ConfigError, match=r"channels \[1\]: 1 for 2 ESCs \[1, 2\]"):
        match_escs(captured, channels=[1])


def test_an_ft_capture_reads_erpm_as_rpm_and_keeps_each_command_unit_apart() -> None:
    family = registry.family("ft")
    messages: list[can.Message | BadLine] = [
        ft_command(0.0, 3, ft_records.Command.SET_CURRENT_BRAKE_CRC16, 2.0),
        ft_frame(0.01, 3, ft_records.RealtimeData1(erpm=-7000, duty=-0.1)),
        ft_command(1.0, 3, ft_records.Command.SET_CURRENT_GEAR_CRC16, 4.5),
        ft_frame(1.01, 3, ft_records.RealtimeData1(erpm=21000, duty=0.3)),
        ft_frame(1.02, 3, ft_records.RealtimeData0(motor_current_a=9.5, battery_current_a=4.25)),
        ft_frame(
            1.03, 3, ft_records.RealtimeData2(45.0, 51.5, 15.2)
        ),  # MOSFET, motor °C; battery V
        ft_command(2.0, 3, ft_records.Command.SET_CURRENT_GEAR_CRC16, 0.0),
    ]
    captured = capture_series(messages, family, pole_pairs={3: 14})
    esc = captured.telemetry[3]
    assert esc.rpm.values == (-500.0, 1500.0)
    assert esc.motor_current_a.values == pytest.approx((9.5,))
    assert esc.current_a.values == pytest.approx((4.25,))
    assert set(esc.temps_c) == {"MOSFET", "motor"}
    assert esc.voltage_v.values == pytest.approx((15.2,))
    commands = captured.by_node[3]
    assert list(commands) == ["current_a", "brake_current_a"]  # the unit sent most first
    assert commands["current_a"].values == pytest.approx((4.5, 0.0))
    assert commands["brake_current_a"].values == pytest.approx((2.0,))
    # A brake command stops the motor whatever its value; so does a zero current.
    assert [stopped for _, stopped in captured.all_stopped] == [True, False, True]
    (matched,) = match_escs(captured)
    assert (matched.node_id, matched.channel, matched.title) == (3, None, "ESC 3")
    assert capture_series(messages, family, pole_pairs=7).telemetry[3].rpm.values == (
        -1000.0,
        3000.0,
    )


def test_the_family_is_the_one_that_reads_the_capture() -> None:
    assert guess_family(ckesc_capture()) is registry.family("ckesc")
    ft_messages = [ft_frame(0.0, 1, ft_records.RealtimeData1(erpm=700, duty=0.1))] * 3
    assert guess_family([*ft_messages, throttles(0.0, 1)]) is registry.family("ft")
    standard = can.Message(arbitration_id=0x7FF, data=b"", is_extended_id=False)
    assert guess_family([standard, BadLine(1, "x", "y")]) is None


def test_stops_and_failure_names() -> None:
    assert is_stop(CommandSeen(0.0, "throttle", channel=1))
    assert not is_stop(CommandSeen(0.1, "current_a", node_id=1))
    assert is_stop(CommandSeen(3.0, "brake_current_a", node_id=1))
    assert failure_names(FAILURE_OVER_TEMPERATURE | 1 << 9) == ("over temperature", "bit 9")
    assert failure_names(0) == ()


def test_thin_keeps_each_runs_extremes_in_time_order() -> None:
    values = [0.0] * 1000
    values[333], values[777] = 50.0, -20.0
    series = Series(tuple(float(i) for i in range(1000)), tuple(values))
    shown = thin(series, 100)
    assert len(shown) <= 100
    assert 50.0 in shown.values and -20.0 in shown.values
    assert list(shown.t_s) == sorted(shown.t_s)
    assert thin(series, 5000) is series
    with pytest.raises(ValueError, match="2 times but 1 values"):
        Series((1.0, 2.0), (1.0,))


def test_an_esc_series_shifts_every_time() -> None:
    esc = EscSeries(1, rpm=Series((T0 + 1,), (5.0,)), commands={"duty": Series((T0 + 2,), (0.5,))})
    shifted = esc.shifted(T0)
    assert shifted.rpm.t_s == (1.0,) and shifted.commands["duty"].t_s == (2.0,)
