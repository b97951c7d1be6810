"""MAVLink datagrams for the UDP link's tests: frames packed by pymavlink, and the seeded fuzz
that once armed the bridge (a frame cut short in one datagram, completed by the next one's first
bytes from another sender).

Used by tests/output/test_autopilot_input.py (the input side, one datagram at a time) and
tests/test_udp_link_e2e.py (the daemon through its CLI).
"""

from __future__ import annotations

import random
import time
from collections.abc import Iterator
from typing import Any

from pymavlink.dialects.v10 import ardupilotmega as mavlink1

from bridge.mavlink import load_dialect

DIALECT: Any = load_dialect()
ARMED = 128 | 1  # MAV_MODE_FLAG_SAFETY_ARMED | CUSTOM_MODE_ENABLED
DISARMED = 1
AUTOPILOT_PWM = 1500  # the autopilot's outputs in the fuzz; every other sender's differ


def packer(system: int = 1, component: int = 1, version: int = 2) -> Any:
    """A pymavlink encoder speaking as ``system``/``component``, MAVLink 1 or 2."""
    module: Any = DIALECT if version == 2 else mavlink1
    return module.MAVLink(None, srcSystem=system, srcComponent=component)


def heartbeat(mav: Any, base_mode: int) -> bytes:
    """A quadrotor's HEARTBEAT from ArduPilot, armed when ``base_mode`` says so."""
    return bytes(mav.heartbeat_encode(2, 3, base_mode, 0, 4).pack(mav))


def servo(mav: Any, pwm: int, time_us: int | None = None) -> bytes:
    """SERVO_OUTPUT_RAW with every channel at ``pwm``, stamped now (or at ``time_us``)."""
    stamp = time.monotonic_ns() // 1000 if time_us is None else time_us
    return bytes(mav.servo_output_raw_encode(stamp & 0xFFFFFFFF, 0, *[pwm] * 8).pack(mav))


def garbage(rng: random.Random, most: int) -> bytes:
    """Up to ``most`` random bytes, one in four of them a magic byte."""
    data = bytearray(rng.randbytes(rng.randrange(most)))
    for at in range(0, len(data), 4):
        data[at] = rng.choice((0xFD, 0xFE))
    return bytes(data)


def fuzz_datagrams(rng: random.Random, senders: int, count: int) -> Iterator[tuple[int, bytes]]:
    """(sender index, datagram) for ``count`` datagrams, made as they are asked for (the
    autopilot's outputs are stamped when made).

    Sender 0 is the autopilot (1/1): disarmed, outputs at :data:`AUTOPILOT_PWM`, whole frames
    only. The others send garbage; genuine frames claiming to be 1/1 (armed HEARTBEATs, other
    outputs) or speaking for another system; and frames cut anywhere, whose rest opens the next
    datagram, whoever sends it (the autopilot included). MAVLink 1 and 2.
    """
    autopilot = packer()
    claims = [
        frame
        for mav in (packer(version=1), packer(version=2))
        for frame in (
            heartbeat(mav, ARMED),
            heartbeat(mav, ARMED | 4),
            *(servo(mav, pwm) for pwm in (1100, 1900, 2000)),
        )
    ]
    others = [heartbeat(packer(system=2, version=1), ARMED), heartbeat(packer(2, 3), DISARMED)]
    carry = b""
    own = 0  # the autopilot's own datagrams
    for _ in range(count):
        sender = rng.randrange(senders)
        if sender == 0:
            own += 1
            if carry:  # the rest of someone's cut frame opens the autopilot's datagram
                yield 0, carry + garbage(rng, 8)
            elif own % 10 == 0:
                yield 0, heartbeat(autopilot, DISARMED)
            else:
                yield 0, servo(autopilot, AUTOPILOT_PWM)
            carry = b""
            continue
        kind = rng.random()
        genuine = rng.choice(claims)
        if kind < 0.5:  # cut anywhere: the next datagram, from anyone, opens with the rest
            cut = rng.randrange(1, len(genuine))
            before = rng.choice(others) if rng.random() < 0.3 else b""
            yield sender, carry + before + genuine[:cut]
            carry = genuine[cut:]
            continue
        if kind < 0.7:
            body = garbage(rng, 120)
        elif kind < 0.85:
            body = genuine  # whole, claiming to be the autopilot, from another address
        else:
            body = rng.choice(others)
        yield sender, carry + body + garbage(rng, 4)
        carry = b""
