"""What the stream transports share (TCP and serial): a stalled peer never blocks a send, frames
stay whole, and pending bytes of a lost stream are counted.

Every call into a transport under test is timed (:class:`watched.Watched`): one that waited
or spun fails the test.
"""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path

import pytest
import watched
from watched import Open, Pty, frame, pump, read_fd, stalled_peer

from bridge.mavlink.transport.base import PENDING_LIMIT_BYTES

opened = watched.opened
pty = watched.pty


@pytest.mark.parametrize("kind", ["tcp", "serial"])
def test_a_stalled_peer_never_blocks_send_and_frames_stay_whole(
    opened: Open, tmp_path: Path, kind: str
) -> None:
    with ExitStack() as stack:
        link, peer_fd = stalled_peer(kind, opened, tmp_path, stack)
        stack.callback(link.close)  # before the pty goes
        accepted: list[bytes] = []
        refused = 0
        sizes = (100, 37, 280, 9)  # odd sizes, so frames straddle the kernel's free space
        for index in range(200_000):
            candidate = frame(index, sizes[index % len(sizes)])
            if link.send(candidate):
                accepted.append(candidate)
                continue
            refused += 1
            assert link.wants_write()  # refused because bytes are pending
            if refused == 50:
                break
        assert refused == 50, "the peer never stalled"
        assert link.stats.frames_dropped == refused
        assert link.stats.frames_sent == len(accepted)

        expected = b"".join(accepted)
        received = read_fd(peer_fd, len(expected), serve=link)
        # Every accepted frame whole and in order, nothing between them.
        assert received == expected
        pump(link, until=lambda: not link.wants_write(), what="the pending bytes")
        assert link.stats.bytes_out == len(expected)


def test_pending_bytes_of_a_lost_stream_are_counted_as_dropped(opened: Open, pty: Pty) -> None:
    serial = opened(f"serial:{pty.link}", pending_limit_bytes=PENDING_LIMIT_BYTES)
    sent = 0
    while serial.send(frame(sent)):
        sent += 1
    assert serial.wants_write()
    pending_frames = serial.stats.frames_sent
    pty.close()
    pump(serial, until=lambda: serial.recv() is None and not serial.stats.connected, what="loss")
    assert not serial.wants_write()
    dropped = serial.stats.frames_dropped - 1  # the refused one that ended the loop
    assert 1 <= dropped <= pending_frames
