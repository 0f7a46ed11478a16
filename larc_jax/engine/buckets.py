"""The shapes a process compiles: the bucket sizes interval calls are padded to, and the size
classes batch dimensions round up to (issue 20: few shapes, compiled once, whatever the data).

Each bucket size and each size class is a separate compiled program per kernel, so the lists are
short; a call's padding is at most its bucket's ratio to the one below.
"""

from __future__ import annotations

__all__ = ["BUCKETS", "MAX_BATCH_TRAJECTORIES", "CASCADE_BUCKETS", "PAIR_BUCKETS", "CULLED_BUCKETS", "PAIR_BYTES",
           "CALL_BYTES", "size_class"]

BUCKETS = tuple(2**k for k in range(2, 13))
"""Frontier arrays are padded to the next of these sizes, 4 .. 4096 (at most 2x waste, 11 shapes;
larger frontiers run in 4096-chunks): small ones matter one trajectory per call, where a call
costs ~0.1 ms plus ~10 us per padded interval on a CPU core. (Cutting a level into whole buckets
instead of padding it saved ~5 % of a warm whole-set call, but a fresh process then traces and
loads more shapes: a 1,000-trajectory call took 29.5 s instead of 15.9 s; measured, not kept.)"""


MAX_BATCH_TRAJECTORIES = 1024
"""Trajectories :func:`~larc_jax.engine.certify.certify` prepares into one :class:`Batch` (larger
datasets run batch after batch): bounds the padded spline and bound arrays, so memory does not
grow with the dataset."""


CASCADE_BUCKETS = (64, 256, 1024)
"""Sizes of the cascade's later calls (larc_jax.leaf.cascade, the screen, steps 4 and the swept
stage): few, as those kernels take seconds to compile; a small call padded to 64 costs a few ms,
and a GJK pair 7-11 us on this 2-core CPU (1024 pairs a call), so larger counts run in 1024-chunks
rather than 4096."""


PAIR_BUCKETS = (16, 32, 64, 128, 256, 512, 1024)
"""Sizes of the cascade's step-2 calls (:func:`~larc_jax.leaf.cascade.interval_pairs`, ~1.2 s to
compile each): a ladder of 2, as one trajectory's open frontier is a few dozen to a few hundred
intervals (on Stage B one at a time, the median call held 119: 4.1 ms at 256, 2.6 ms at 128)."""


CULLED_BUCKETS = (32, 128, 1024)
"""Sizes of capsule-stage calls on culled item lists (:mod:`larc_jax.engine.cull`): each width compiles
its own kernels, so a short ladder (a 32-call of a few items costs well under a millisecond)."""


PAIR_BYTES = 512
"""Device memory per capsule-obstacle pair per interval that the all-pairs kernel may hold (XLA
keeps each pair's candidate points; measured ~380 bytes on the CPU), rounded up."""
CALL_BYTES = 2**30
"""Device memory one interval call may take for its pairs (:attr:`Batch.max_chunk`)."""


def size_class(n: int, minimum: int) -> int:
    """Next power of two >= max(n, minimum): sizes that vary between calls (waypoints, trajectories,
    scenes) round up to these, so a process compiles a few shapes (each ~100 memory mappings)."""
    return 1 << (max(int(n), int(minimum)) - 1).bit_length()
