"""The SocketCAN interface's state read from iproute2's JSON (samples in the format of
``ip -details -json link show dev NAME``, iproute2 6.x), and what the bridge makes of it."""

from __future__ import annotations

import pytest

from bridge.can_interface import LinkState, assess, parse_ip_link, read_link
from bridge.can_io import open_bus
from bridge.config import CanConfig
from bridge.errors import LinkError

# An MCP2515 HAT's controller, configured and up.
CAN_UP_500K = (
    '[{"ifindex":3,"ifname":"can0","flags":["NOARP","UP","LOWER_UP","ECHO"],"mtu":16,'
    '"qdisc":"pfifo_fast","operstate":"UP","linkmode":"DEFAULT","group":"default","txqlen":10,'
    '"link_type":"can","promiscuity":0,"allmulti":0,"min_mtu":0,"max_mtu":0,"linkinfo":{'
    '"info_kind":"can","info_data":{"ctrlmode":[],"state":"ERROR-ACTIVE","berr_counter":'
    '{"tx":0,"rx":0},"restart_ms":0,"bittiming":{"bitrate":500000,"sample_point":"0.875",'
    '"tq":125,"prop_seg":6,"phase_seg1":7,"phase_seg2":2,"sjw":1,"brp":1},"bittiming_const":'
    '{"name":"mcp251x","tseg1":{"min":3,"max":16},"tseg2":{"min":2,"max":8},"sjw":{"min":1,'
    '"max":4},"brp":{"min":1,"max":64},"brp_inc":1},"clock":8000000}},"num_tx_queues":1,'
    '"num_rx_queues":1,"gso_max_size":65536,"gso_max_segs":65535}]'
)
# The same controller before any `type can bitrate`: the kernel sends no bit timing, and down.
CAN_UNCONFIGURED = (
    '[{"ifindex":3,"ifname":"can7","flags":["NOARP","ECHO"],"mtu":16,"qdisc":"noop",'
    '"operstate":"DOWN","linkmode":"DEFAULT","group":"default","txqlen":10,"link_type":"can",'
    '"promiscuity":0,"linkinfo":{"info_kind":"can","info_data":{"ctrlmode":[],"state":"STOPPED",'
    '"restart_ms":0,"bittiming_const":{"name":"mttcan","tseg1":{"min":2,"max":256},"tseg2":'
    '{"min":2,"max":128},"sjw":{"min":1,"max":128},"brp":{"min":1,"max":512},"brp_inc":1},'
    '"clock":50000000}}}]'
)
# Configured at 1 Mbit/s, then bus-off after errors.
CAN_BUS_OFF_1M = CAN_UP_500K.replace('"bitrate":500000', '"bitrate":1000000').replace(
    "ERROR-ACTIVE", "BUS-OFF"
)
VCAN_UP = (
    '[{"ifindex":4,"ifname":"vcan0","flags":["NOARP","UP","LOWER_UP"],"mtu":72,'
    '"qdisc":"noqueue","operstate":"UNKNOWN","linkmode":"DEFAULT","group":"default",'
    '"txqlen":1000,"link_type":"can","promiscuity":0,"linkinfo":{"info_kind":"vcan"},'
    '"num_tx_queues":1,"num_rx_queues":1,"gso_max_size":65536,"gso_max_segs":65535}]'
)


def test_parse_a_configured_controller() -> None:
    assert parse_ip_link(CAN_UP_500K, "can0") == LinkState(
        "can0", True, up=True, kind="can", link_type="can", bitrate=500_000,
        can_state="ERROR-ACTIVE",
    )  # fmt: skip


def test_parse_an_unconfigured_controller_and_a_virtual_one() -> None:
    assert parse_ip_link(CAN_UNCONFIGURED, "can7") == LinkState(
        "can7", True, up=False, kind="can", link_type="can", bitrate=None, can_state="STOPPED"
    )
    assert parse_ip_link(VCAN_UP, "vcan0") == LinkState(
        "vcan0", True, up=True, kind="vcan", link_type="can"
    )


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("Device not found", "not JSON"),
        ('[{"ifname":"can1"}]', "no interface 'can0'"),
        ('{"ifname":"can0"}', "no interface 'can0'"),
    ],
)
def test_parse_refuses_other_output(text: str, expected: str) -> None:
    with pytest.raises(ValueError, match=expected):
        parse_ip_link(text, "can0")


def test_matching_rate_passes() -> None:
    found = assess(parse_ip_link(CAN_UP_500K, "can0"), "can0", 500_000)
    assert found.refusal is None and not found.mismatch
    assert found.text == (
        "SocketCAN interface can0: configured for 500000 (500 kbit/s), as [can] bitrate; up, "
        "ERROR-ACTIVE"
    )


def test_another_rate_is_a_mismatch_naming_both_fixes() -> None:
    found = assess(parse_ip_link(CAN_UP_500K, "can0"), "can0", 1_000_000)
    assert found.mismatch
    assert found.refusal is not None
    assert found.refusal.startswith(
        "SocketCAN interface can0 runs at 500000 bit/s (500 kbit/s) but [can] bitrate is "
        "1000000 (1 Mbit/s)"
    )
    assert "bitrate = 500000 in [can], or --bitrate 500000" in found.refusal
    assert "`sudo ip link set can0 up type can bitrate 1000000`" in found.refusal


def test_what_is_missing_is_named_with_the_channel_and_rate() -> None:
    unset = assess(parse_ip_link(CAN_UNCONFIGURED, "can7"), "can7", 500_000)
    assert unset.refusal == (
        "SocketCAN interface can7 has no bit rate set; expected one: "
        "`sudo ip link set can7 up type can bitrate 500000`"
    )
    configured_down = CAN_UP_500K.replace('"NOARP","UP","LOWER_UP"', '"NOARP"').replace(
        '"operstate":"UP"', '"operstate":"DOWN"'
    )
    down = assess(parse_ip_link(configured_down, "can0"), "can0", 500_000)
    assert down.refusal is not None
    assert down.refusal.startswith(
        "SocketCAN interface can0 is down; expected it up: "
        "`sudo ip link set can0 up type can bitrate 500000`"
    )
    bus_off = assess(parse_ip_link(CAN_BUS_OFF_1M, "can0"), "can0", 1_000_000)
    assert bus_off.refusal is not None and "is BUS-OFF" in bus_off.refusal
    gone = assess(LinkState("can7", False), "can7", 500_000)
    assert gone.refusal is not None
    assert gone.refusal.startswith("SocketCAN interface can7 does not exist")
    assert gone.text == "SocketCAN interface can7: not found on this machine; run refuses to start"


# As `ip -details -json link show` printed them for Linux 6.1 (User-Mode Linux): a vxcan of a
# pair, up, and a vcan down; tests/linux/test_interface.py reads them from the real `ip`.
VXCAN_UP = (
    '[{"ifindex":4,"link":"vx1","ifname":"vx0","flags":["NOARP","UP","LOWER_UP"],"mtu":72,'
    '"qdisc":"noqueue","operstate":"UP","linkmode":"DEFAULT","group":"default","txqlen":10,'
    '"link_type":"can","promiscuity":0,"allmulti":0,"min_mtu":0,"max_mtu":0,"linkinfo":'
    '{"info_kind":"vxcan"},"num_tx_queues":1,"gso_max_size":65536,"gso_max_segs":65535,'
    '"tso_max_size":65536,"tso_max_segs":65535,"gro_max_size":65536}]'
)
VCAN_DOWN = (
    '[{"ifindex":5,"ifname":"can5","flags":["NOARP","ECHO"],"mtu":72,"qdisc":"noqueue",'
    '"operstate":"DOWN","linkmode":"DEFAULT","group":"default","txqlen":1000,"link_type":"can",'
    '"promiscuity":0,"allmulti":0,"min_mtu":0,"max_mtu":0,"linkinfo":{"info_kind":"vcan"},'
    '"num_tx_queues":1,"gso_max_size":65536,"gso_max_segs":65535,"tso_max_size":65536,'
    '"tso_max_segs":65535,"gro_max_size":65536}]'
)


def test_virtual_interfaces_up_and_down() -> None:
    vxcan = assess(parse_ip_link(VXCAN_UP, "vx0"), "vx0", 500_000)
    assert vxcan.refusal is None
    assert vxcan.text == (
        "SocketCAN interface vx0: virtual (vxcan), no bit rate to compare with 500000 "
        "(500 kbit/s); up"
    )
    down = assess(parse_ip_link(VCAN_DOWN, "can5"), "can5", 500_000)
    assert down.text.endswith("; down: run refuses to start")
    # A virtual interface takes no bit rate: the command that brings it up has none.
    assert down.refusal == (
        "SocketCAN interface can5 is down; expected it up: `sudo ip link set can5 up` (or set "
        "it up in the network configuration: docs/hardware.md)"
    )


def test_a_virtual_interface_has_no_rate_to_compare() -> None:
    found = assess(parse_ip_link(VCAN_UP, "vcan0"), "vcan0", 1_000_000)
    assert found.refusal is None
    assert found.text == (
        "SocketCAN interface vcan0: virtual (vcan), no bit rate to compare with 1000000 "
        "(1 Mbit/s); up"
    )


def test_read_link_asks_the_system() -> None:
    # This machine's kernel has no CAN: the loopback interface and a name that is not there.
    loopback = read_link("lo")
    assert loopback is not None
    assert (loopback.exists, loopback.up, loopback.kind, loopback.link_type) == (
        True, True, None, "loopback",
    )  # fmt: skip
    assert read_link("can-not-here") == LinkState("can-not-here", False)
    refused = assess(loopback, "lo", 500_000).refusal
    assert refused == (
        "SocketCAN interface lo is not a CAN interface (it is loopback); expected a CAN "
        "controller such as can0 ([can] channel)"
    )


def test_a_bus_that_cannot_be_opened_says_what_is_missing() -> None:
    # This machine has no SocketCAN; the output loop's reopening (explain=False) starts no `ip`.
    for explain, hint in (
        (True, "(SocketCAN interface nocan8 does not exist; expected a CAN interface: "),
        (False, "(sudo ip link set nocan8 up type can bitrate 250000)"),
    ):
        with pytest.raises(LinkError) as caught:
            open_bus(CanConfig(channel="nocan8"), 250_000, explain=explain)
        assert str(caught.value).startswith("cannot open CAN bus socketcan:nocan8: ")
        assert hint in str(caught.value)
