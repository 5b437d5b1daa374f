"""Agent networks shared by the algorithms (flax.linen).

* :class:`MLP` -- a plain ReLU/tanh MLP.
* :class:`ActorCritic` -- separate policy and value MLPs on one observation (IPPO; MAPPO uses its
  own critic input).

Per-agent parameters (no sharing) are obtained by ``jax.vmap``-ing ``init``/``apply`` over agents
(:func:`init_agents`, :func:`apply_agents`); with sharing one parameter set serves every agent and
an agent-ID one-hot (:func:`with_agent_ids`) tells the agents apart.
"""
from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np


class MLP(nn.Module):
    """``features[-1]`` outputs after hidden layers ``features[:-1]`` (orthogonal init)."""

    features: Sequence[int]
    activation: str = "tanh"
    final_scale: float = 1.0

    @nn.compact
    def __call__(self, x):
        act = {"tanh": nn.tanh, "relu": nn.relu}[self.activation]
        for width in self.features[:-1]:
            x = act(nn.Dense(width, kernel_init=nn.initializers.orthogonal(np.sqrt(2)))(x))
        return nn.Dense(self.features[-1], kernel_init=nn.initializers.orthogonal(self.final_scale))(x)


class ActorCritic(nn.Module):
    """Policy logits ``[..., num_actions]`` and state value ``[...]`` from one observation."""

    num_actions: int
    hidden: int = 128
    layers: int = 2
    activation: str = "tanh"

    @nn.compact
    def __call__(self, obs):
        widths = [self.hidden] * self.layers
        logits = MLP(widths + [self.num_actions], self.activation, final_scale=0.01, name="actor")(obs)
        value = MLP(widths + [1], self.activation, final_scale=1.0, name="critic")(obs)[..., 0]
        return logits, value


def with_agent_ids(obs):
    """Append a one-hot agent ID: ``[..., N, D] -> [..., N, D + N]``."""
    n = obs.shape[-2]
    ids = jnp.broadcast_to(jnp.eye(n, dtype=obs.dtype), obs.shape[:-2] + (n, n))
    return jnp.concatenate([obs, ids], axis=-1)


def init_agents(module: nn.Module, key, sample_obs, num_agents: int, shared: bool):
    """Parameters for ``num_agents`` agents: one set if ``shared`` else a stack (leading axis N)."""
    if shared:
        return module.init(key, sample_obs)
    return jax.vmap(lambda k: module.init(k, sample_obs))(jax.random.split(key, num_agents))


def apply_agents(module: nn.Module, params, obs, shared: bool):
    """Apply to ``obs [..., N, D]``: the same parameters for all agents, or agent i's to agent i."""
    if shared:
        return module.apply(params, obs)
    agent_axis = obs.ndim - 2
    return jax.vmap(module.apply, in_axes=(0, agent_axis), out_axes=agent_axis)(params, obs)
