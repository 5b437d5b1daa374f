"""Array-namespace helpers: one source of math for JAX (training) and numpy (deployment).

The physics, controller and barrier modules never import JAX themselves. They ask
:func:`namespace` for the module that matches their inputs (``jax.numpy`` when any input is
a JAX array or tracer, ``numpy`` otherwise) and loop with :func:`fori_loop`, which becomes
``jax.lax.fori_loop`` under JAX and a plain Python loop under numpy. The numpy-only
Robotarium submission bundle therefore runs the very same functions as training.
"""
from __future__ import annotations

import dataclasses
import sys
from typing import Any, Callable

import numpy as np


def _jax_array_type():
    jax = sys.modules.get("jax")
    return None if jax is None else jax.Array


def is_jax(*arrays: Any) -> bool:
    """True when any argument is a JAX array or tracer (never imports JAX)."""
    array_type = _jax_array_type()
    return array_type is not None and any(isinstance(a, array_type) for a in arrays)


def jax_module():
    """The already-imported ``jax`` module (callers only get here with JAX inputs)."""
    return sys.modules["jax"]


def namespace(*arrays: Any):
    """``jax.numpy`` if any input is a JAX array/tracer, else ``numpy``."""
    if is_jax(*arrays):
        return sys.modules["jax"].numpy
    return np


def fori_loop(xp, lower: int, upper: int, body: Callable[[int, Any], Any], init: Any) -> Any:
    """``lax.fori_loop`` under JAX, a Python ``for`` loop under numpy (static trip count; a single
    trip runs the body once, with ``i`` a Python int, outside any loop construct)."""
    if xp is np or upper - lower == 1:
        val = init
        for i in range(lower, upper):
            val = body(i, val)
        return val
    return sys.modules["jax"].lax.fori_loop(lower, upper, body, init)


def to_minor(a, batch_ndim: int, xp):
    """``[*batch, *rest] -> [*rest, B]``: the flattened batch becomes the minor (SIMD) axis."""
    rest = a.shape[batch_ndim:]
    flat = a.reshape((-1,) + rest)
    return xp.moveaxis(flat, 0, -1)


def from_minor(a, batch_shape, xp):
    """Inverse of :func:`to_minor`: ``[*rest, B] -> [*batch, *rest]``."""
    return xp.moveaxis(a, -1, 0).reshape(tuple(batch_shape) + a.shape[:-1])


def vmap_in_place(fn: Callable) -> Callable:
    """``fn`` (which already accepts any leading batch axes) with a vmap rule that calls it on the
    batched arrays instead of letting ``jax.vmap`` map it.

    Plain ``jax.vmap`` puts the mapped axis first, where XLA's CPU backend cannot vectorise over
    it; a function written for batch-minor arrays (see :func:`to_minor`) keeps every op unit-stride
    over the whole batch. Nested vmaps (seeds x envs) apply the rule once per level; unbatched
    arguments are broadcast. Arguments are arrays or pytrees of arrays (``None`` leaves allowed).
    Only for JAX inputs.
    """
    jax = jax_module()

    @jax.custom_batching.custom_vmap
    def wrapped(*args):
        return fn(*args)

    @wrapped.def_vmap
    def _rule(axis_size, in_batched, *args):
        def batched(a, is_batched):
            return a if is_batched else jax.numpy.broadcast_to(a, (axis_size,) + a.shape)

        args = jax.tree_util.tree_map(batched, args, tuple(in_batched))
        out = wrapped(*args)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return wrapped


def result_dtype(xp, *arrays: Any):
    """Floating dtype shared by ``arrays`` (float32 for integer inputs)."""
    dtype = xp.result_type(*arrays)
    if not xp.issubdtype(dtype, xp.floating):
        dtype = xp.float32
    return dtype


def frozen_state(cls):
    """Frozen dataclass with ``replace``: what the numpy bundle uses where training uses
    ``flax.struct.dataclass`` for scenario states (flax is not installed on the Robotarium)."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    cls.replace = lambda self, **changes: dataclasses.replace(self, **changes)
    return cls
