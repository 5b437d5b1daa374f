"""Pieces shared by the training loops: the per-rollout episode metrics."""
from __future__ import annotations

import jax.numpy as jnp

# The info entries a training rollout keeps (per step) to report finished episodes.
EPISODE_INFO = ("episode_return", "steps", "episode_collided", "episode_out_of_bounds")


def episode_info(info: dict) -> dict:
    return {k: info[k] for k in EPISODE_INFO}


def rollout_metrics(done, info) -> dict:
    """Means over the episodes that finished in a rollout (``done [T, E]``, ``info`` entries
    ``[T, E]``): ``return``, ``length``, ``collision_rate``, ``out_of_bounds_rate`` (NaN when no
    episode finished) and ``episodes`` (how many finished)."""
    count = done.sum()

    def at_done(x):
        return jnp.where(count > 0, jnp.sum(jnp.where(done, x, 0)) / jnp.maximum(count, 1), jnp.nan)

    return {"return": at_done(info["episode_return"]), "length": at_done(info["steps"]),
            "collision_rate": at_done(info["episode_collided"]),
            "out_of_bounds_rate": at_done(info["episode_out_of_bounds"]), "episodes": count}
