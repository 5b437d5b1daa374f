"""An episode replay buffer in pure JAX (a pytree; jit-, scan- and vmap-friendly).

The buffer holds ``capacity`` fixed-length sequences (for the value-based learners: one
``num_steps``-step rollout of one env, starting at an episode start) as a pytree of arrays with
leading axis ``capacity``. ``add`` writes a batch of sequences at the insertion point (circular:
the oldest are overwritten once full) and ``sample`` draws sequences uniformly from those written.
Everything has static shapes, so the buffer lives inside the jitted training loop.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class EpisodeBuffer:
    """``data``: pytree of ``[capacity, ...]`` arrays; ``insert``: next write slot; ``size``: slots filled."""

    data: dict
    insert: jax.Array
    size: jax.Array

    @property
    def capacity(self) -> int:
        return jax.tree_util.tree_leaves(self.data)[0].shape[0]


def init(example, capacity: int) -> EpisodeBuffer:
    """An empty buffer for sequences shaped like ``example`` (a pytree of one sequence's arrays)."""
    if capacity < 1:
        raise ValueError(f"buffer capacity must be >= 1, got {capacity}")
    data = jax.tree_util.tree_map(lambda x: jnp.zeros((capacity,) + jnp.shape(x), jnp.asarray(x).dtype), example)
    return EpisodeBuffer(data=data, insert=jnp.int32(0), size=jnp.int32(0))


def add(buffer: EpisodeBuffer, batch) -> EpisodeBuffer:
    """Write ``batch`` (pytree of ``[B, ...]``, ``B <= capacity``) at the insertion point."""
    cap = buffer.capacity
    count = jax.tree_util.tree_leaves(batch)[0].shape[0]
    if count > cap:
        raise ValueError(f"cannot add {count} sequences to a buffer of capacity {cap}")
    slots = (buffer.insert + jnp.arange(count)) % cap
    data = jax.tree_util.tree_map(lambda store, x: store.at[slots].set(x), buffer.data, batch)
    return EpisodeBuffer(data=data, insert=(buffer.insert + count) % cap,
                         size=jnp.minimum(buffer.size + count, cap))


def sample(buffer: EpisodeBuffer, key, batch_size: int):
    """``batch_size`` sequences drawn uniformly (with replacement) from the filled slots."""
    index = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buffer.size, 1))
    return jax.tree_util.tree_map(lambda store: store[index], buffer.data)


__all__ = ["EpisodeBuffer", "init", "add", "sample"]
