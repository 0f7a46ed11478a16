"""Warming a process up for one trajectory per call: the device tree for small batches too.

``certify``'s LARC runs a batch of :data:`~larc_jax.engine.tree_pool.TREE_FROM_TRAJECTORIES` or more
on the device tree (:mod:`larc_jax.engine.tree`), a smaller one on the host frontier: the tree is one
large program per batch class, so for a one-off call of one or two trajectories its first call
(compiling, or loading it from the cache) costs more than the host frontier's whole run (README,
"Cold start"). A process that certifies trajectories one per call for a while (a planner checking
each path it plans) gets the tree's warm speed instead by asking for it once: :func:`warm_up_tree`
certifies the trajectories it is given with the tree (compiling it for batches shaped like them)
and from then on this process runs small batches on the tree as well
(:func:`~larc_jax.engine.tree_pool.small_batches_on_tree`). A batch of another shape (another
trajectory length class, box count class or enclosure) compiles its program when first met, as
the host frontier's kernels do. The certificate does not depend on it: the same intervals,
leaves, evaluations and decisions (tested); a clearance may differ in its last bits.
"""

from __future__ import annotations

from ..defaults import METHODS
from ..errors import LarcInputError
from ..run_spec import RunSpec
from .certify import certify
from .results import DatasetResult
from .tree_pool import small_batches_on_tree

__all__ = ["warm_up_tree"]


def warm_up_tree(trajectories, scenes, robot, capsules, *, spec: RunSpec | None = None, **options) -> DatasetResult:
    """Certify ``trajectories`` against ``scenes`` as :func:`~larc_jax.engine.certify.certify` does
    (same arguments; its result returned) with LARC on the device tree, and keep running
    ``certify``'s small LARC batches on the tree in this process (module docstring). Refused
    (:class:`~larc_jax.errors.LarcInputError`, nothing changed) for a run that is not LARC; a run
    the tree does not take (the swept stage, point-cloud pieces, several devices) runs as
    ``certify`` runs it."""
    method = spec.method if spec is not None else options.get("method", METHODS[0])
    method = getattr(method, "value", method)
    if method != "larc":
        raise LarcInputError(f"warm_up_tree: method {method!r}: the device tree runs LARC (method='larc')")
    was = small_batches_on_tree(True)
    try:
        return certify(trajectories, scenes, robot, capsules, spec=spec, **options)
    except BaseException:
        small_batches_on_tree(was)
        raise
