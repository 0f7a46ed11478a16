"""Deferred JAX import, so that the NumPy float64 references run in a process without JAX.

The independent checker (:mod:`larc_jax.products.verify`, ``larc verify``) re-checks a certificate with
the NumPy references that live beside the JAX kernels (:func:`~larc_jax.leaf.interval.evaluate_interval_np`,
:func:`~larc_jax.model.robot.forward_kinematics_np`, ...), and must not load JAX at all: its verdict
then depends on NumPy alone. The modules holding those references therefore reach JAX only
through the proxies :data:`jax` and :data:`jnp` (the real module is imported on the first
attribute access, i.e. when a kernel runs) and register their dataclasses as pytrees with
:func:`pytree_dataclass`.

By default :func:`pytree_dataclass` registers at once (importing JAX, as a plain
``@jax.tree_util.register_dataclass`` would). After :func:`defer_jax` (called by the checker
before it imports anything else of the library) classes are queued instead, and registered when
JAX is first reached through a proxy (importing :mod:`larc_jax.engine.batch`, or any attribute of the
``larc_jax`` package, does); a class defined after JAX is loaded is registered at once. A process
that deferred JAX and then hands these classes to JAX itself calls :func:`register_pytrees` first.
"""

from __future__ import annotations

import functools
import importlib
import sys

__all__ = ["jax", "jnp", "pytree_dataclass", "defer_jax", "register_pytrees", "lazy_jit"]

_pending: list[type] = []
_deferred = False


def register_pytrees() -> None:
    """Import JAX and register every class :func:`pytree_dataclass` has queued."""
    import jax as real_jax

    while _pending:
        real_jax.tree_util.register_dataclass(_pending.pop(0))


class _LazyModule:
    """Stands for a module that is imported on first attribute access (then cached per name)."""

    def __init__(self, name: str):
        object.__setattr__(self, "_name", name)

    def __getattr__(self, attr: str):
        module = importlib.import_module(self._name)
        register_pytrees()
        value = getattr(module, attr)
        object.__setattr__(self, attr, value)
        return value

    def __repr__(self) -> str:
        return f"<lazy module {self._name}>"


jax = _LazyModule("jax")
"""``jax``, imported when first used."""
jnp = _LazyModule("jax.numpy")
"""``jax.numpy``, imported when first used."""


def defer_jax() -> None:
    """From now on, :func:`pytree_dataclass` queues classes instead of importing JAX."""
    global _deferred
    _deferred = True


def pytree_dataclass(cls):
    """``jax.tree_util.register_dataclass`` for a frozen dataclass, deferred after :func:`defer_jax`."""
    _pending.append(cls)
    if not _deferred or "jax" in sys.modules:
        register_pytrees()
    return cls


def lazy_jit(fn):
    """``jax.jit(fn)``, built on the first call."""

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if call.jitted is None:
            call.jitted = jax.jit(fn)
        return call.jitted(*args, **kwargs)

    call.jitted = None
    return call
