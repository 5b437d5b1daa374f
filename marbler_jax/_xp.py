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
    """``lax.fori_loop`` under JAX, a Python ``for`` loop under numpy (static trip count)."""
    if xp is np:
        val = init
        for i in range(lower, upper):
            val = body(i, val)
        return val
    return sys.modules["jax"].lax.fori_loop(lower, upper, body, init)


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
