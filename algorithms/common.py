"""Pieces shared by the training loops: the per-rollout episode metrics, flat parameter names."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

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


def float32_tensors(params, sep: str = ".") -> dict[str, np.ndarray]:
    """:func:`flatten_params` of ``params`` as ``float32`` arrays (what a numpy policy folder holds)."""
    return {name: np.asarray(value, np.float32) for name, value in flatten_params(params, sep).items()}


def flatten_params(params, sep: str = "/") -> dict[str, np.ndarray]:
    """A parameter pytree of nested dicts as ``{"a<sep>b<sep>c": array}``."""
    return {sep.join(str(getattr(k, "key", k)) for k in key_path): np.asarray(v)
            for key_path, v in jax.tree_util.tree_flatten_with_path(params)[0]}


def global_state(obs):
    """The global state of MARBLER's learners: every agent's observation concatenated,
    ``[..., N, D] -> [..., N * D]``."""
    return obs.reshape(obs.shape[:-2] + (obs.shape[-2] * obs.shape[-1],))
