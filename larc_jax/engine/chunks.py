"""How a batch of intervals is cut into kernel calls of a few compiled sizes.

Every call pads its intervals to one of a few bucket sizes (``larc_jax.engine.batch.BUCKETS``), so
a process compiles few shapes; padding costs the kernel's time per padded interval, a further call
costs its fixed host and dispatch time. A level of the frontier of a whole dataset is rarely a
bucket size (Stage B's 160 trajectories: 160, 320, 640, ... intervals), and padding it to the next
bucket wasted 12-20 % of LARC's capsule-stage work; cutting the rest into whole buckets wastes at
most :data:`SPLIT_WASTE` intervals a level for a few more calls. A leaf's test does not depend on
the call it runs in beyond its last bits (each bucket size is its own compiled program), and never
on its decision's soundness: every program's rounding is within the guard (larc_jax.leaf.interval).
"""

from __future__ import annotations

from typing import Sequence

__all__ = ["chunk_plan", "SPLIT_MIN", "SPLIT_WASTE"]

SPLIT_MIN = 256
"""A remainder is split into whole buckets of at least this many intervals rather than padded, when
padding would waste more than :data:`SPLIT_WASTE` (a call costs ~0.1-0.2 ms on the host and in
dispatch, about as much as 64 padded intervals of the capsule kernel on 2 CPU cores)."""
SPLIT_WASTE = 64


def chunk_plan(n: int, buckets: Sequence[int]) -> list[tuple[int, int, int]]:
    """``(start, stop, padded size)`` of the calls for ``n`` items: chunks of the largest bucket,
    then the rest in whole buckets of at least :data:`SPLIT_MIN` while padding it to one bucket
    would waste more than :data:`SPLIT_WASTE` items, the last part padded to the next bucket."""
    plan, start = [], 0
    while start < n:
        rest = n - start
        size = next((b for b in buckets if b >= rest), buckets[-1])
        if size - rest > SPLIT_WASTE:
            whole = [b for b in buckets if SPLIT_MIN <= b < rest]
            size = whole[-1] if whole else size
        stop = min(n, start + size)
        plan.append((start, stop, size))
        start = stop
    return plan
