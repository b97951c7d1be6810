"""A SocketCAN interface as the system has it configured: does it exist, is it up, at which bit
rate, in which CAN state; and what that means for a bridge configured for a bit rate.

The bridge cannot set the bit rate itself (that needs CAP_NET_ADMIN, and belongs to the
network configuration: docs/hardware.md), so at start it reads the interface's and compares.
A different rate is refused, not warned about: nothing on the bus would understand the
bridge, the ESCs would look silent ("0 of 4 ESCs online") and the bus-load check would have
been made for the wrong rate. The message says which of the two to change.

The state is read from ``ip -details -json link show dev NAME`` (iproute2, present on every
Debian, Raspberry Pi OS and Ubuntu system; no privileges needed): :func:`parse_ip_link` is the
pure reading of its output, :func:`read_link` the I/O. Nothing is opened or changed.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import dataclass
from typing import Any, Final

from bridge.bitrate import bitrate_text

__all__ = ["Assessment", "LinkState", "assess", "bring_up_command", "parse_ip_link", "read_link"]

_IP_TIMEOUT_S: Final = 5.0
_MISSING: Final = "does not exist"  # iproute2: 'Device "can7" does not exist.'
_UNUSABLE_CAN_STATES: Final = frozenset({"BUS-OFF", "STOPPED"})
_VIRTUAL_KINDS: Final = frozenset({"vcan", "vxcan"})


@dataclass(frozen=True)
class LinkState:
    """One network interface as iproute2 reports it."""

    name: str
    exists: bool
    up: bool = False
    """Administratively up (``ip link set NAME up``)."""
    kind: str | None = None
    """``can`` (a CAN controller), ``vcan``, ``vxcan``, ...; None: no link kind (``lo``, ...)."""
    link_type: str | None = None
    """``can``, ``loopback``, ``ether``, ..."""
    bitrate: int | None = None
    """A CAN controller's configured bit rate; None when not set (or not a controller)."""
    can_state: str | None = None
    """A CAN controller's state: ERROR-ACTIVE, ERROR-WARNING, ERROR-PASSIVE, BUS-OFF, STOPPED."""


def bring_up_command(channel: str, bitrate: int) -> str:
    """The command that configures and starts a CAN controller at ``bitrate``."""
    return f"sudo ip link set {channel} up type can bitrate {bitrate}"


def parse_ip_link(text: str, name: str) -> LinkState:
    """The state of ``name`` from ``ip -details -json link show dev NAME``'s output.

    Raises:
        ValueError: the text is not iproute2's JSON for that interface.
    """
    try:
        links = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"`ip -json link` output is not JSON: {exc}") from None
    named = [
        item
        for item in (links if isinstance(links, list) else ())
        if isinstance(item, dict) and item.get("ifname") == name
    ]
    if not named:
        raise ValueError(f"`ip -json link` output has no interface {name!r}")
    link = named[0]
    info = _table(link.get("linkinfo"))
    data = _table(info.get("info_data"))
    bitrate = _table(data.get("bittiming")).get("bitrate")
    flags = link.get("flags")
    return LinkState(
        name,
        exists=True,
        up=isinstance(flags, list) and "UP" in flags,
        kind=_text(info.get("info_kind")),
        link_type=_text(link.get("link_type")),
        bitrate=bitrate if isinstance(bitrate, int) and bitrate > 0 else None,
        can_state=_text(data.get("state")),
    )


def _table(value: Any) -> dict[str, Any]:
    return value if isinstance(value, dict) else {}


def _text(value: Any) -> str | None:
    return value if isinstance(value, str) else None


def read_link(name: str) -> LinkState | None:
    """The system's state of interface ``name``; None when it cannot be read (no ``ip``
    command, or output it does not understand)."""
    # A service's PATH may lack the sbin directories, where Debian keeps ip.
    ip = shutil.which("ip") or shutil.which("ip", path="/usr/sbin:/sbin")
    if ip is None:
        return None
    try:
        result = subprocess.run(
            [ip, "-details", "-json", "link", "show", "dev", name],
            capture_output=True,
            text=True,
            timeout=_IP_TIMEOUT_S,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    if result.returncode != 0:
        return LinkState(name, exists=False) if _MISSING in result.stderr else None
    try:
        return parse_ip_link(result.stdout, name)
    except ValueError:
        return None


@dataclass(frozen=True)
class Assessment:
    """What a link's state means for a bridge at a bit rate."""

    text: str
    """One line for ``run --check``."""
    refusal: str | None = None
    """Why ``run`` must not start (the interface is missing, down or unusable), with what to do;
    None: it may."""
    mismatch: bool = False
    """The interface runs at another bit rate than the configured one (a configuration error)."""


def assess(state: LinkState | None, channel: str, bitrate: int) -> Assessment:
    """What ``state`` (of SocketCAN interface ``channel``) means for a bridge configured for
    ``bitrate`` bit/s."""
    rate = f"{bitrate} ({bitrate_text(bitrate)})"
    up = bring_up_command(channel, bitrate)
    where = f"SocketCAN interface {channel}"
    if state is None:
        return Assessment(f"{where}: state not readable (no `ip` command); bit rate not checked")
    if not state.exists:
        refusal = (
            f"{where} does not exist; expected a CAN interface: is the CAN adapter's driver "
            "loaded (a Raspberry Pi CAN HAT's dtoverlay, a USB adapter plugged in)? `ip link "
            "show` lists the interfaces; or set [can] channel (docs/hardware.md)"
        )
        return Assessment(f"{where}: not found on this machine; run refuses to start", refusal)
    if state.kind != "can":
        what = state.kind or state.link_type or "unknown"
        if state.kind in _VIRTUAL_KINDS:  # virtual: no bit rate, nothing to compare
            text = f"{where}: virtual ({what}), no bit rate to compare with {rate}"
        else:
            return Assessment(
                f"{where}: not a CAN interface ({what}); run refuses to start",
                f"{where} is not a CAN interface (it is {what}); expected a CAN controller "
                "such as can0 ([can] channel)",
            )
    elif state.bitrate is None:
        return Assessment(
            f"{where}: no bit rate set; run refuses to start",
            f"{where} has no bit rate set; expected one: `{up}`",
        )
    elif state.bitrate != bitrate:
        return Assessment(
            f"{where}: configured for {state.bitrate} ({bitrate_text(state.bitrate)}), "
            f"not [can] bitrate {rate}",
            f"{where} runs at {state.bitrate} bit/s ({bitrate_text(state.bitrate)}) but [can] "
            f"bitrate is {rate}; expected the ESCs' rate on both: if the ESCs run at "
            f"{bitrate_text(state.bitrate)}, give the bridge that rate (bitrate = "
            f"{state.bitrate} in [can], or --bitrate {state.bitrate}); if at "
            f"{bitrate_text(bitrate)}, `sudo ip link set {channel} down` then `{up}` "
            "(docs/hardware.md: the network configuration)",
            mismatch=True,
        )
    else:
        text = f"{where}: configured for {rate}, as [can] bitrate"
    if not state.up:
        if state.kind in _VIRTUAL_KINDS:  # no bit rate to give it
            up = f"sudo ip link set {channel} up"
        return Assessment(
            f"{text}; down: run refuses to start",
            f"{where} is down; expected it up: `{up}`"
            + (" (or set it up in the network configuration: docs/hardware.md)"),
        )
    if state.can_state in _UNUSABLE_CAN_STATES:
        return Assessment(
            f"{text}; {state.can_state}: run refuses to start",
            f"{where} is {state.can_state} (the controller stopped sending after too many "
            "errors: wiring, termination or another node at another bit rate); expected "
            f"ERROR-ACTIVE: check the bus, then `sudo ip link set {channel} down` and `{up}` "
            f"(or set `restart-ms 100` on it)",
        )
    return Assessment(f"{text}; up" + (f", {state.can_state}" if state.can_state else ""))
