"""MAVLink framing against pymavlink: its encoder makes the frames, its parser is the reference.

Random messages of the project's dialect are packed by pymavlink as MAVLink 1 (with the v1.0
dialect, which leaves out extension fields, as a MAVLink 1 sender does), MAVLink 2 (trailing
zeros truncated) and signed MAVLink 2, mixed with junk and fed in random pieces. The stream
properties run derandomized: a bad frame passes a 16-bit CRC by chance once in 65536, and a
fixed set of examples keeps that from ever making the suite flaky.
"""

from __future__ import annotations

import hashlib
import random
from collections.abc import Iterator, Sequence
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from pymavlink.generator.mavcrc import x25crc_slow

from bridge.errors import ConfigError
from bridge.mavlink import load_dialect
from bridge.mavlink.frames import (
    FRAME_MAX_LEN,
    MAGIC_V1,
    MAGIC_V2,
    Frame,
    FrameScanner,
    ReplayGuard,
    crc_x25,
    frame_crc,
    signature_ok,
    signing_timestamp,
)

DIALECT: Any = load_dialect()
KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
ONE_MINUTE = 6_000_000  # signing timestamp units (10 µs)

SEEDS = st.integers(0, 2**32 - 1)  # a seed per example: the stream is built from random.Random
STREAM = settings(
    max_examples=400,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)

_INT_RANGES = {
    "uint8_t": (0, 0xFF),
    "int8_t": (-0x80, 0x7F),
    "uint16_t": (0, 0xFFFF),
    "int16_t": (-0x8000, 0x7FFF),
    "uint32_t": (0, 0xFFFFFFFF),
    "int32_t": (-0x80000000, 0x7FFFFFFF),
    "uint64_t": (0, 0xFFFFFFFFFFFFFFFF),
    "int64_t": (-0x8000000000000000, 0x7FFFFFFFFFFFFFFF),
}
_FLOAT_CHOICES = (0.0, -0.0, 1.0, -1.5, 1e38, float("inf"), float("nan"))


def crc_bitwise(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/MCRF4XX from its definition: reflected polynomial 0x8408, one bit at a time."""
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
    return crc


def random_value(rng: random.Random, ftype: str) -> Any:
    if ftype in ("float", "double"):
        return rng.choice(_FLOAT_CHOICES) if rng.random() < 0.3 else rng.uniform(-1e4, 1e4)
    low, high = _INT_RANGES[ftype]
    # Zeros often, so MAVLink 2 truncation gets exercised; the extremes and anything between.
    return rng.choice((0, 0, low, high, rng.randint(low, high)))


def random_message(rng: random.Random, dialect: Any, msg_id: int) -> Any:
    """A message of ``msg_id`` with random fields, built with the dialect's own class."""
    cls = dialect.mavlink_map[msg_id]
    # fieldtypes follow the definition's order, array_lengths the wire order.
    counts = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    args: list[Any] = []
    for name, ftype in zip(cls.fieldnames, cls.fieldtypes, strict=True):
        count = counts[name]
        if ftype == "char":
            size = rng.randint(0, max(count, 1))
            args.append(bytes(rng.randint(0x20, 0x7E) for _ in range(size)))
        elif count:
            args.append([random_value(rng, ftype) for _ in range(count)])
        else:
            args.append(random_value(rng, ftype))
    return cls(*args)


V1_IDS = sorted(mavlink1.mavlink_map)
TAIL = bytes(FRAME_MAX_LEN)  # no magic byte: resolves any partial frame before it
V2_IDS = sorted(DIALECT.mavlink_map)


class Sender:
    """One pymavlink sender: a system/component, its sequence numbers and its signing state."""

    def __init__(self, rng: random.Random, system: int, component: int) -> None:
        self.rng = rng
        self.v1: Any = mavlink1.MAVLink(None, srcSystem=system, srcComponent=component)
        self.v2: Any = DIALECT.MAVLink(None, srcSystem=system, srcComponent=component)
        self.signed: Any = DIALECT.MAVLink(None, srcSystem=system, srcComponent=component)
        self.signed.signing.secret_key = KEY
        self.signed.signing.sign_outgoing = True
        self.signed.signing.link_id = rng.randint(0, 255)
        self.signed.signing.timestamp = rng.randint(1, 1 << 40)

    def frame(self, kind: str) -> bytes:
        """One packed frame: kind is "v1", "v2" or "signed"."""
        if kind == "v1":
            mav, dialect, ids = self.v1, mavlink1, V1_IDS
        else:
            mav, dialect, ids = (self.v2 if kind == "v2" else self.signed), DIALECT, V2_IDS
        frame = bytes(random_message(self.rng, dialect, self.rng.choice(ids)).pack(mav))
        mav.seq = (mav.seq + 1) % 256
        return frame


def encoded_frames(rng: random.Random, count: int) -> list[bytes]:
    senders = [Sender(rng, rng.randint(1, 255), rng.randint(0, 255)) for _ in range(3)]
    return [rng.choice(senders).frame(rng.choice(("v1", "v2", "signed"))) for _ in range(count)]


def split(rng: random.Random, data: bytes) -> Iterator[bytes]:
    """``data`` in random pieces, empty ones included."""
    pos = 0
    while pos < len(data):
        size = rng.choice((0, 1, 2, 7, rng.randint(1, 64), rng.randint(1, 600)))
        yield data[pos : pos + size]
        pos += size


def scan(scanner: FrameScanner, pieces: Iterator[bytes]) -> list[Frame]:
    found: list[Frame] = []
    for piece in pieces:
        found += scanner.feed(piece)
        assert scanner.pending < FRAME_MAX_LEN
    return found


def pymavlink_parse(pieces: Iterator[bytes]) -> list[Any]:
    """The messages pymavlink's robust parser finds (BAD_DATA left out)."""
    parser: Any = DIALECT.MAVLink(None)
    parser.robust_parsing = True
    found: list[Any] = []
    for piece in pieces:
        found += [m for m in parser.parse_buffer(piece) or [] if m.get_type() != "BAD_DATA"]
    # parse_buffer returns at most one message per call for the bytes it already holds.
    while (m := parser.parse_char(b"")) is not None:
        if m.get_type() != "BAD_DATA":
            found.append(m)
    return found


def reference_scan(
    stream: bytes, known: Sequence[int] = V2_IDS, pass_unknown: bool = True
) -> list[bytes]:
    """The scanning rules of bridge.mavlink.frames over a whole stream at once, with
    pymavlink deciding whether each candidate of a known id is a frame (its header, length and
    CRC checks): a candidate that fails costs one byte, a frame is skipped whole. ``known``:
    the ids the scanner under test knows; the others pass unchecked or cost one byte."""
    decoder: Any = DIALECT.MAVLink(None)
    found: list[bytes] = []
    pos = 0
    while pos < len(stream):
        magic = stream[pos]
        if magic not in (MAGIC_V1, MAGIC_V2):
            pos += 1
            continue
        header = 10 if magic == MAGIC_V2 else 6
        if len(stream) - pos < 3:
            break
        flags = stream[pos + 2] if magic == MAGIC_V2 else 0
        if flags & ~1:
            pos += 1
            continue
        size = header + stream[pos + 1] + 2 + (13 if flags else 0)
        if pos + size > len(stream):
            break
        candidate = stream[pos : pos + size]
        if msg_id_of(candidate) in known:
            try:
                decoder.decode(bytearray(candidate))
            except DIALECT.MAVError:
                pos += 1
                continue
        elif not pass_unknown:
            pos += 1
            continue
        found.append(candidate)
        pos += size
    return found


def msg_id_of(frame: bytes) -> int:
    return int.from_bytes(frame[7:10], "little") if frame[0] == MAGIC_V2 else frame[5]


def junk_piece(rng: random.Random, frames: list[bytes], magic: bool) -> bytes:
    """Random bytes, or (with ``magic``) also a truncated or damaged copy of a real frame."""
    kind = rng.choice(("bytes", "truncated", "damaged") if magic else ("bytes",))
    if kind == "bytes":
        data = bytes(rng.randrange(256) for _ in range(rng.randint(0, 40)))
        return data if magic else data.replace(b"\xfd", b"\x00").replace(b"\xfe", b"\x01")
    frame = bytearray(rng.choice(frames))
    # Cut or damage the part the CRC covers. The CRC does not cover a signature block, so a
    # frame damaged there is still a frame (signature_ok refuses it), and one cut there takes
    # the next bytes as the rest of its signature: framing cannot tell either.
    framed = len(frame) - (13 if frame[0] == MAGIC_V2 and frame[2] & 1 else 0)
    if kind == "truncated":
        return bytes(frame[: rng.randint(1, framed - 1)])
    frame[rng.randrange(framed)] ^= rng.randint(1, 255)
    return bytes(frame)


def with_junk(rng: random.Random, frames: list[bytes], magic: bool) -> bytes:
    out = bytearray()
    for frame in frames:
        if rng.random() < 0.5:
            out += junk_piece(rng, frames, magic)
        out += frame
    return bytes(out)


def scanner_for(known: Sequence[int] | None = None, pass_unknown: bool = True) -> FrameScanner:
    if known is None:
        return FrameScanner.for_dialect(DIALECT, pass_unknown=pass_unknown)
    m = DIALECT.mavlink_map
    return FrameScanner(
        {i: m[i].crc_extra for i in known},
        {i: m[i].unpacker.size for i in known},
        pass_unknown=pass_unknown,
    )


def zero_extended(payload: bytes, msg_id: int) -> bytes:
    size = DIALECT.mavlink_map[msg_id].unpacker.size
    return payload + bytes(max(0, size - len(payload)))


# -- CRC ------------------------------------------------------------------------------------


def test_crc_matches_the_catalogue_check_value() -> None:
    # CRC-16/MCRF4XX in the CRC catalogue: check value of "123456789" is 0x6F91.
    assert crc_x25(b"123456789") == 0x6F91 == crc_bitwise(b"123456789")
    assert crc_x25(b"") == 0xFFFF


@given(st.binary(max_size=300), st.binary(max_size=50), st.integers(0, 255))
def test_crc_agrees_with_the_definition_and_pymavlink(
    data: bytes, more: bytes, crc_extra: int
) -> None:
    assert crc_x25(data) == crc_bitwise(data) == x25crc_slow(data).crc
    assert crc_x25(more, crc_x25(data)) == crc_bitwise(data + more)
    assert frame_crc(data, crc_extra) == crc_bitwise(data + bytes((crc_extra,)))


# -- frames found against pymavlink's parser ----------------------------------------------------


@STREAM
@given(SEEDS, st.integers(1, 12))
def test_finds_exactly_what_pymavlink_finds(seed: int, count: int) -> None:
    rng = random.Random(seed)
    frames = encoded_frames(rng, count)
    stream = with_junk(rng, frames, magic=False)
    # Some ids unknown to the scanner: they must come through unchecked, byte for byte.
    known = [i for i in V2_IDS if rng.random() < 0.8]
    scanner = scanner_for(known)

    ours = scan(scanner, split(rng, stream))
    theirs = pymavlink_parse(split(random.Random(rng.random()), stream))

    assert [f.raw for f in ours] == [bytes(m.get_msgbuf()) for m in theirs] == frames
    packer: Any = DIALECT.MAVLink(None)
    for frame, msg in zip(ours, theirs, strict=True):
        assert (frame.msg_id, frame.sys_id, frame.comp_id, frame.seq) == (
            msg.get_msgId(),
            msg.get_srcSystem(),
            msg.get_srcComponent(),
            msg.get_seq(),
        )
        raw = frame.raw
        # pymavlink reports neither the signature (get_signed() is False without a key) nor a
        # MAVLink 2 payload (get_payload() cuts at byte 6): read both from its frame.
        signed = raw[0] == MAGIC_V2 and bool(raw[2] & 1)
        assert (frame.version, frame.signed) == ((2, signed) if raw[0] == MAGIC_V2 else (1, False))
        assert frame.link_id == (raw[-13] if signed else None)
        assert frame.signature_timestamp == (
            int.from_bytes(raw[-12:-6], "little") if signed else None
        )
        if frame.msg_id in known:
            # The fields pymavlink decoded, packed again and zero-extended, are our payload.
            again = bytes(msg.pack(packer))
            assert frame.payload == zero_extended(again[10 : 10 + again[1]], frame.msg_id)
        else:
            header = 10 if raw[0] == MAGIC_V2 else 6
            assert frame.payload == raw[header : header + raw[1]]
    assert scanner.frames == len(frames)
    assert scanner.unknown == sum(f.msg_id not in known for f in ours)
    assert scanner.bad_crc == scanner.bad_flags == 0
    assert scanner.junk_bytes == len(stream) - sum(map(len, frames))


@STREAM
@given(SEEDS, st.integers(1, 10), st.booleans())
def test_any_junk_gives_what_the_rules_give_over_the_whole_stream(
    seed: int, count: int, pass_unknown: bool
) -> None:
    rng = random.Random(seed)
    frames = encoded_frames(rng, count)
    stream = with_junk(rng, frames, magic=True)
    known = [i for i in V2_IDS if rng.random() < 0.9]
    scanner = scanner_for(known, pass_unknown)

    ours = scan(scanner, split(rng, stream))

    assert [f.raw for f in ours] == reference_scan(stream, known, pass_unknown)


@STREAM
@given(SEEDS, st.integers(1, 10))
def test_junk_never_costs_a_known_frame_when_unknown_ids_are_junk_too(
    seed: int, count: int
) -> None:
    rng = random.Random(seed)
    frames = encoded_frames(rng, count)
    # The tail: more bytes arrive, so a junk header near the end that claims a long frame is
    # resolved (a partial frame waits for its bytes: a frame behind it waits with it).
    stream = with_junk(rng, frames, magic=True) + TAIL
    scanner = scanner_for(pass_unknown=False)

    ours = scan(scanner, split(rng, stream))

    # Truncated and damaged copies of real frames in the junk never pass; every real frame
    # is found, whatever junk came before it.
    assert [f.raw for f in ours] == frames


@STREAM
@given(SEEDS, st.integers(1, 8), st.data(), st.booleans())
def test_a_corrupted_byte_never_yields_a_wrong_frame(
    seed: int, count: int, data: st.DataObject, pass_unknown: bool
) -> None:
    rng = random.Random(seed)
    frames = encoded_frames(rng, count)
    stream = bytearray(b"".join(frames))
    at = data.draw(st.integers(0, len(stream) - 1), label="at")
    stream[at] ^= data.draw(st.integers(1, 255), label="xor")
    damaged = 0
    while at >= len(frames[damaged]):
        at -= len(frames[damaged])
        damaged += 1
    scanner = scanner_for(pass_unknown=pass_unknown)

    ours = [f.raw for f in scan(scanner, split(rng, bytes(stream) + TAIL))]

    intact = frames[:damaged] + frames[damaged + 1 :]
    frame = frames[damaged]
    if frame[0] == MAGIC_V2 and frame[2] & 1 and at >= len(frame) - 13:
        # In the signature block, which the CRC does not cover: still a frame, with a
        # signature that no longer matches.
        start = sum(map(len, frames[:damaged]))
        assert ours == [
            *frames[:damaged],
            bytes(stream[start : start + len(frame)]),
            *intact[damaged:],
        ]
        (found,) = scanner_for().feed(ours[damaged])
        assert not signature_ok(found, KEY)
    elif pass_unknown:
        # The damage can turn the frame into one of an unknown id (passed unchecked) whose
        # claimed length hides frames after it; every frame of a known id is a real one.
        known = [f for f in ours if msg_id_of(f) in DIALECT.mavlink_map]
        assert all(f in intact for f in known), "a frame that was never sent"
        assert ours[:damaged] == frames[:damaged]
    else:
        assert ours == intact


# -- what differs from pymavlink, and the details -------------------------------------------------


def test_a_truncated_frame_costs_pymavlink_the_next_frame_but_not_us() -> None:
    mav: Any = DIALECT.MAVLink(None, srcSystem=1, srcComponent=1)
    first = mav.servo_output_raw_encode(1000, 0, *range(1100, 1116)).pack(mav)
    second = mav.servo_output_raw_encode(2000, 0, *range(1200, 1216)).pack(mav)
    # A serial link dropped the end of the first frame: its header claims 49 bytes, which
    # reach into the second frame, and the CRC there is wrong.
    stream = first[:20] + second

    scanner = scanner_for()
    ours = scanner.feed(stream)
    theirs = pymavlink_parse(iter([stream]))

    assert [f.raw for f in ours] == [second]
    assert theirs == []
    assert scanner.bad_crc == 1
    assert scanner.junk_bytes == 20


def test_counters_and_resync_on_a_hand_made_stream() -> None:
    mav: Any = DIALECT.MAVLink(None, srcSystem=1, srcComponent=1)
    beat = mav.heartbeat_encode(2, 3, 128, 0, 4).pack(mav)
    bad_flags = bytearray(beat)
    bad_flags[2] = 0x02  # an incompatibility flag nobody defined: unusable
    bad_crc = bytearray(beat)
    bad_crc[-1] ^= 0x55
    scanner = scanner_for()

    found = scanner.feed(b"\x00\x01junk" + bytes(bad_flags) + bytes(bad_crc) + beat)

    assert [f.raw for f in found] == [beat]
    assert scanner.frames == 1
    assert scanner.bad_flags == 1
    assert scanner.bad_crc == 1
    assert scanner.junk_bytes == 6 + len(bad_flags) + len(bad_crc)
    assert scanner.pending == 0


def test_partial_frames_are_held_and_junk_never_grows_memory() -> None:
    mav: Any = DIALECT.MAVLink(None, srcSystem=1, srcComponent=1)
    beat = mav.heartbeat_encode(2, 3, 128, 0, 4).pack(mav)
    scanner = scanner_for()
    assert scanner.feed(beat[:7]) == []
    assert scanner.pending == 7
    assert [f.raw for f in scanner.feed(beat[7:])] == [beat]
    assert scanner.pending == 0

    rng = random.Random(1)
    for _ in range(2000):  # 1 MB of junk rich in magic bytes that announce long frames
        chunk = bytes(rng.choice((0xFD, 0xFE, 0xFF, rng.randrange(256))) for _ in range(500))
        scanner.feed(chunk)
        assert scanner.pending < FRAME_MAX_LEN
    scanner.reset()
    assert scanner.pending == 0
    assert [f.raw for f in scanner.feed(beat)] == [beat]


def test_a_whole_datagram_leaves_nothing_pending() -> None:
    mav: Any = DIALECT.MAVLink(None, srcSystem=1, srcComponent=1)
    beat = mav.heartbeat_encode(2, 3, 128, 0, 4).pack(mav)
    # A junk magic byte whose header claims a 255-byte payload, then a real frame.
    datagram = b"\xfd\xff\x00" + beat

    held = scanner_for()
    assert held.feed(datagram) == []  # the claimed frame could still complete
    assert held.pending == len(datagram)

    whole = scanner_for()
    assert [f.raw for f in whole.feed(datagram, whole=True)] == [beat]
    assert whole.pending == 0
    assert whole.junk_bytes == 3
    assert whole.feed(beat[:5], whole=True) == []  # a cut frame is junk, not kept
    assert (whole.pending, whole.junk_bytes) == (0, 8)


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("cut", [1, 2, 9])
def test_a_frame_cut_short_in_one_datagram_is_never_completed_by_the_next(
    version: int, cut: int
) -> None:
    """An armed HEARTBEAT cut ``cut`` bytes short, then a datagram that starts with the
    missing bytes (from anyone): as a stream that is the frame; as datagrams it is junk."""
    module: Any = mavlink1 if version == 1 else DIALECT
    mav: Any = module.MAVLink(None, srcSystem=1, srcComponent=1)
    armed = mav.heartbeat_encode(2, 3, 128 | 1, 0, 4).pack(mav)
    first, second = armed[:-cut], armed[-cut:] + b"\x00garbage\xfd\x01"

    stream = scanner_for()
    assert stream.feed(first) == []
    assert [f.raw for f in stream.feed(second)] == [armed]  # a byte stream's reads may cut

    datagrams = scanner_for()
    assert datagrams.feed(first, whole=True) == []
    assert datagrams.feed(second, whole=True) == []
    assert datagrams.pending == 0 and datagrams.frames == 0
    assert datagrams.junk_bytes == len(first) + len(second)


def test_unknown_ids_pass_unchecked_or_are_junk() -> None:
    mav: Any = DIALECT.MAVLink(None, srcSystem=1, srcComponent=1)
    status = mav.statustext_encode(4, b"hello").pack(mav)  # STATUSTEXT (253), unknown below
    beat = mav.heartbeat_encode(2, 3, 128, 0, 4).pack(mav)
    damaged = bytearray(status)
    damaged[12] ^= 0xFF  # nobody can tell: no CRC_EXTRA for an unknown id

    passing = scanner_for([0])
    found = passing.feed(bytes(damaged) + beat)
    assert [f.raw for f in found] == [bytes(damaged), beat]
    assert found[0].msg_id == 253
    assert found[0].payload == bytes(damaged[10:-2])  # as sent: the full length is unknown
    assert passing.unknown == 1

    skipping = scanner_for([0], pass_unknown=False)
    assert [f.raw for f in skipping.feed(bytes(damaged) + beat)] == [beat]
    assert skipping.junk_bytes == len(damaged)


def test_payloads_are_zero_extended_to_the_full_length() -> None:
    v2: Any = DIALECT.MAVLink(None, srcSystem=1, srcComponent=1)
    v1: Any = mavlink1.MAVLink(None, srcSystem=1, srcComponent=1)
    truncated = v2.servo_output_raw_encode(7, 0, 1500, *[0] * 15).pack(v2)
    old = v1.servo_output_raw_encode(7, 0, *range(1, 9)).pack(v1)
    assert truncated[1] == 6 and old[1] == 21  # what went on the wire

    a, b = scanner_for().feed(truncated + old)

    assert (a.version, len(a.payload)) == (2, 37)
    assert a.payload == (7).to_bytes(4, "little") + (1500).to_bytes(2, "little") + bytes(31)
    assert (b.version, len(b.payload)) == (1, 37)
    assert b.payload[4:20] == b"".join(i.to_bytes(2, "little") for i in range(1, 9))
    assert b.payload[21:] == bytes(16)


def test_signed_frames_carry_link_id_and_timestamp() -> None:
    mav: Any = DIALECT.MAVLink(None, srcSystem=5, srcComponent=6)
    mav.signing.secret_key = KEY
    mav.signing.sign_outgoing = True
    mav.signing.link_id = 9
    mav.signing.timestamp = 0x123456789A
    raw = mav.heartbeat_encode(2, 3, 128, 0, 4).pack(mav)

    (frame,) = scanner_for().feed(raw)

    assert frame.signed and frame.version == 2
    assert (frame.link_id, frame.signature_timestamp) == (9, 0x123456789A)
    assert frame.raw == raw
    assert len(frame.payload) == 9
    assert signature_ok(frame, KEY)
    assert not signature_ok(frame, OTHER_KEY)
    for at in range(len(raw) - 13, len(raw)):  # damage in the signature block: still a frame
        damaged = bytearray(raw)
        damaged[at] ^= 0x20
        (forged,) = scanner_for().feed(bytes(damaged))
        assert not signature_ok(forged, KEY)
    digest = hashlib.sha256(KEY + raw[:-6]).digest()  # the spec's formula, spelt out
    assert raw[-6:] == digest[:6]


def test_for_dialect_knows_every_message_of_the_dialect() -> None:
    scanner = FrameScanner.for_dialect(DIALECT)
    mav: Any = DIALECT.MAVLink(None, srcSystem=1, srcComponent=1)
    esc_status = mav.esc_status_encode(0, 1, [1, 2, 3, 4], [1.0] * 4, [2.0] * 4).pack(mav)
    (frame,) = scanner.feed(esc_status)
    assert frame.msg_id == 291  # the project's own message
    assert scanner.unknown == 0
    assert len(frame.payload) == 57


def test_mismatched_tables_are_refused() -> None:
    with pytest.raises(ConfigError, match=r"\[1\]"):
        FrameScanner({0: 50, 1: 124}, {0: 9})
    with pytest.raises(ConfigError, match=r"expected 0\.\.255 each"):
        FrameScanner({0: 300}, {0: 9})


# -- signing: replay protection ----------------------------------------------------------------


class SignedSender:
    def __init__(self, key: bytes = KEY, link_id: int = 0, system: int = 1) -> None:
        self.mav: Any = DIALECT.MAVLink(None, srcSystem=system, srcComponent=1)
        self.mav.signing.secret_key = key
        self.mav.signing.sign_outgoing = True
        self.mav.signing.link_id = link_id
        self.mav.signing.timestamp = 10 * ONE_MINUTE

    def frame(self, timestamp: int | None = None) -> Frame:
        if timestamp is not None:
            self.mav.signing.timestamp = timestamp
        raw = self.mav.heartbeat_encode(2, 3, 128, 0, 4).pack(self.mav)
        (frame,) = scanner_for().feed(raw)
        return frame


def test_replay_guard_accepts_newer_and_refuses_replays() -> None:
    guard = ReplayGuard(KEY)
    sender = SignedSender()
    first, second = sender.frame(), sender.frame()

    assert guard.accept(first)
    assert guard.accept(second)
    assert not guard.accept(second)  # the same frame again
    assert not guard.accept(first)  # an older one
    assert (guard.accepted, guard.replayed) == (2, 2)
    assert guard.timestamp == second.signature_timestamp


def test_a_forged_frame_never_touches_the_replay_state() -> None:
    guard = ReplayGuard(KEY)
    sender = SignedSender()
    assert guard.accept(sender.frame())
    forger = SignedSender(key=OTHER_KEY)
    forged = forger.frame(timestamp=(1 << 48) - 1)  # the latest possible timestamp

    assert not guard.accept(forged)
    assert guard.bad_signature == 1
    assert guard.timestamp < (1 << 48) - 1
    assert guard.accept(sender.frame())  # the genuine stream goes on


def test_streams_are_separate_per_link_system_and_component() -> None:
    guard = ReplayGuard(KEY)
    a, b = SignedSender(link_id=0), SignedSender(link_id=1)
    frame_b = b.frame(timestamp=10 * ONE_MINUTE)
    assert guard.accept(a.frame(timestamp=10 * ONE_MINUTE + 5))
    assert guard.accept(frame_b)  # older than a's, but its own stream's first
    c = SignedSender(system=2)
    assert guard.accept(c.frame(timestamp=10 * ONE_MINUTE + 1))


def test_a_new_stream_more_than_a_minute_behind_is_refused() -> None:
    now = 100 * ONE_MINUTE
    guard = ReplayGuard(KEY, timestamp=now)
    late, recent = SignedSender(link_id=1), SignedSender(link_id=2)

    assert not guard.accept(late.frame(timestamp=now - ONE_MINUTE - 1))
    assert guard.too_old == 1
    assert guard.accept(recent.frame(timestamp=now - ONE_MINUTE))
    # Once known, a stream is judged by its own last timestamp only.
    assert guard.accept(recent.frame(timestamp=now - ONE_MINUTE + 1))
    guard.advance(now + 5)
    guard.advance(now - 5)  # never lowers
    assert guard.timestamp == now + 5


def test_unsigned_frames_and_a_full_stream_table_are_refused() -> None:
    mav: Any = DIALECT.MAVLink(None, srcSystem=1, srcComponent=1)
    (unsigned,) = scanner_for().feed(mav.heartbeat_encode(2, 3, 128, 0, 4).pack(mav))
    guard = ReplayGuard(KEY, max_streams=2)
    assert not guard.accept(unsigned)
    assert not signature_ok(unsigned, KEY)
    assert guard.unsigned == 1

    for link in range(3):
        accepted = guard.accept(SignedSender(link_id=link).frame())
        assert accepted == (link < 2)
    assert guard.too_many_streams == 1
    with pytest.raises(ConfigError, match="31 bytes: expected 32"):
        ReplayGuard(bytes(31))


def test_signing_timestamp_counts_10_us_since_2015() -> None:
    assert signing_timestamp(1_420_070_400 * 10**9) == 0
    assert signing_timestamp(1_420_070_401 * 10**9 + 25_000) == 100_002
    assert signing_timestamp(0) == 0
