"""Kernel CAN filters for a family's ID fields: the fewest (value, mask) blocks covering a set.

socketcan tries every filter on every frame, so a family's telemetry filters should be as few
as its ID layout allows: each ID field (a message type, a node ID, a command) is split into the
fewest aligned blocks that cover exactly its values, and one filter is made per combination of
blocks (see each family's ``reader_filters``).
"""

from __future__ import annotations

from collections.abc import Iterable

from bridge.errors import ValueRangeError

# Exact search for the fewest blocks gives up after this many steps and keeps the best cover
# found so far (still exact, maybe one block longer); no ID set of a real vehicle comes near.
_COVER_SEARCH_BUDGET = 20_000


def check_ids(ids: Iterable[int], allowed: range, what: str) -> None:
    bad = sorted(i for i in ids if i not in allowed)
    if bad:
        raise ValueRangeError(f"{what} IDs {bad} are not in {allowed.start}..{allowed.stop - 1}")


def fewest_blocks(values: frozenset[int], width: int) -> list[tuple[int, int]]:
    """The fewest (value, mask) blocks over ``width`` bits whose union is exactly ``values``.

    A block is the set of numbers that equal ``value`` on the bits set in ``mask``. The
    candidates are the largest blocks inside ``values`` (merged pairwise, Quine-McCluskey);
    a depth-first search with the greedy answer as its first bound picks the fewest.
    """
    full = (1 << width) - 1
    level = {(v, full) for v in values}
    largest: set[tuple[int, int]] = set()
    while level:
        merged: set[tuple[int, int]] = set()
        used: set[tuple[int, int]] = set()
        for value, mask in level:
            for bit in (1 << i for i in range(width)):
                partner = (value | bit, mask)
                if mask & bit and not value & bit and partner in level:
                    merged.add((value, mask & ~bit))
                    used.update(((value, mask), partner))
        largest |= level - used
        level = merged
    members = {block: _members(*block, width) for block in largest}
    covering = {v: [b for b in largest if v in members[b]] for v in values}

    best: list[tuple[int, int]] = []
    left = set(values)
    while left:  # greedy: the block that covers most of what is left
        block = max(sorted(largest), key=lambda b: len(members[b] & left))
        best.append(block)
        left -= members[block]
    steps = 0

    def search(left: frozenset[int], chosen: list[tuple[int, int]]) -> None:
        nonlocal best, steps
        steps += 1
        if not left:
            best = list(chosen)
            return
        if len(chosen) + 1 >= len(best) or steps > _COVER_SEARCH_BUDGET:
            return
        # Branch on the value the fewest blocks can cover: one of them must be chosen.
        value = min(left, key=lambda v: (len(covering[v]), v))
        for block in sorted(covering[value], key=lambda b: (-len(members[b] & left), b)):
            chosen.append(block)
            search(left - members[block], chosen)
            chosen.pop()

    search(frozenset(values), [])
    return sorted(best)


def _members(value: int, mask: int, width: int) -> frozenset[int]:
    free = [1 << i for i in range(width) if not mask >> i & 1]
    result = []
    for combination in range(1 << len(free)):
        member = value
        for i, bit in enumerate(free):
            if combination >> i & 1:
                member |= bit
        result.append(member)
    return frozenset(result)
