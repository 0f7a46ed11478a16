"""Streaming certification: datasets of any size, certified chunk by chunk with bounded memory.

:func:`certify_stream` takes an *iterable* of ``(trajectory, scene)`` pairs (a generator that
reads files lazily is fine) and yields one :class:`~larc_jax.engine.results.DatasetResult` per chunk
of ``chunk_size`` pairs, in order. Only one chunk's trajectories, splines, frontier and leaves
are alive at a time, so peak memory depends on ``chunk_size`` (and the depth), not on the
dataset size. Each chunk is one :func:`~larc_jax.engine.certify.certify` call: the results are the
ones a single call on the whole dataset gives (certification of a trajectory never depends on
the others in its batch). Chunks have a fixed padded size, so a stream compiles the same few
shapes as one call.

File-based streaming with resumable Parquet output (``larc certify --manifest``) is in
:mod:`larc_jax.drivers.manifest`.
"""

from __future__ import annotations

import itertools
from typing import Iterable, Iterator

from ..engine.certify import SPEC_KEYWORDS, certify, run_spec
from ..defaults import DEFAULT_CHUNK_SIZE
from ..enclosure.capsule import CapsuleModel
from ..errors import LarcInputError
from ..engine.results import DatasetResult
from ..model.robot import Robot
from ..model.scene import Scene
from ..model.trajectory import Trajectory

__all__ = ["certify_stream", "chunked"]


def chunked(items: Iterable, size: int) -> Iterator[list]:
    """Consecutive lists of ``size`` items (the last may be shorter)."""
    it = iter(items)
    while chunk := list(itertools.islice(it, size)):
        yield chunk


def certify_stream(
    items: Iterable[tuple[Trajectory, Scene]],
    robot: Robot,
    capsules: CapsuleModel,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    **certify_kwargs,
) -> Iterator[DatasetResult]:
    """Certify ``(trajectory, scene)`` pairs chunk by chunk; yield one result per chunk.

    ``certify_kwargs`` are those of :func:`~larc_jax.engine.certify.certify`: ``spec`` (a
    :class:`~larc_jax.run_spec.RunSpec`, checked here once, before the first chunk is read) or its
    keyword arguments (``method``, ``margin``, ``max_depth``, ``dtype``...), ``progress``... Every
    chunk's result carries the spec. Memory is bounded by ``chunk_size``; the iterable is
    consumed lazily.
    """
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise LarcInputError(f"certify_stream: chunk_size must be an integer >= 1, got {chunk_size!r}")
    options = {k: certify_kwargs.pop(k) for k in list(certify_kwargs) if k in SPEC_KEYWORDS}
    spec = run_spec(certify_kwargs.pop("spec", None), **options)  # validated once, before any item is read
    seen = 0
    for chunk in chunked(items, chunk_size):
        for k, pair in enumerate(chunk):
            if not (isinstance(pair, tuple) and len(pair) == 2):
                raise LarcInputError(f"certify_stream: item {seen + k} is not a (trajectory, scene) pair")
        seen += len(chunk)
        trajectories, scenes = zip(*chunk)
        yield certify(list(trajectories), list(scenes), robot, capsules, spec=spec, **certify_kwargs)
