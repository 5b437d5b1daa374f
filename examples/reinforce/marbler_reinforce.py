"""REINFORCE on marbler-jax's envs: an algorithm written against marbler-jax's public interface only.

Each robot samples its action from a shared tanh MLP (its observation and a one-hot robot ID in) and
climbs the gradient of its own discounted return (returns-to-go, normalised per update). Each update
runs ``num_envs`` fresh episodes to their end. docs/algorithms.md walks through this file; installed
(``pip install examples/reinforce``) it is ``--algo reinforce``, without installing ``--algo
marbler_reinforce:REINFORCE`` with this folder on ``PYTHONPATH``.
"""
from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from marbler_jax_rl.common import episode_info, rollout_metrics
from marbler_jax_rl.algorithm import trainer
from marbler_jax_rl.registry import Algorithm


@dataclasses.dataclass(frozen=True)
class ReinforceConfig:
    """Settings (``marbler-jax train --hp key=value``); ``total_timesteps`` is every algorithm's."""

    total_timesteps: int = 200_000
    num_envs: int = 32
    lr: float = 3e-3
    gamma: float = 0.99
    hidden: int = 64

    def validate(self) -> None:
        for name in ("total_timesteps", "num_envs", "hidden"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {self.gamma}")


class Actor(nn.Module):
    """Logits ``[..., A]`` from a robot's input ``[..., D + N]``."""

    num_actions: int
    hidden: int

    @nn.compact
    def __call__(self, x):
        return nn.Dense(self.num_actions, name="Dense_1")(nn.tanh(nn.Dense(self.hidden, name="Dense_0")(x)))


def actor_inputs(obs):
    """Observation and robot-ID one-hot: ``[..., N, D] -> [..., N, D + N]``."""
    n = obs.shape[-2]
    return jnp.concatenate([obs, jnp.broadcast_to(jnp.eye(n, dtype=obs.dtype), obs.shape[:-2] + (n, n))], -1)


def make_train(env, cfg: ReinforceConfig):
    cfg.validate()
    actor = Actor(env.num_actions, cfg.hidden)
    steps_per_update = cfg.num_envs * env.max_steps
    num_updates = max(1, cfg.total_timesteps // steps_per_update)
    tx = optax.adam(cfg.lr)

    def init(key):
        key, k_actor = jax.random.split(key)
        params = actor.init(k_actor, jnp.zeros((env.num_agents, env.obs_dim + env.num_agents)))
        return dict(params=params, opt_state=tx.init(params), key=key)

    def rollout(params, key):
        """One episode per env (the env resets itself after it; later steps are masked out)."""
        k_reset, k_run = jax.random.split(key)
        obs, state = jax.vmap(env.reset)(jax.random.split(k_reset, cfg.num_envs))

        def step(carry, key):
            obs, state, live = carry
            k_act, k_env = jax.random.split(key)
            actions = jax.random.categorical(k_act, actor.apply(params, actor_inputs(obs)))
            next_obs, state, rewards, done, info = jax.vmap(env.step)(
                jax.random.split(k_env, cfg.num_envs), state, actions)
            out = dict(obs=obs, actions=actions, rewards=rewards, live=live, done=done, info=episode_info(info))
            return (next_obs, state, live & ~done), out

        live = jnp.ones((cfg.num_envs,), bool)
        return jax.lax.scan(step, (obs, state, live), jax.random.split(k_run, env.max_steps))[1]

    def loss_fn(params, traj):
        def back(future, t):                          # returns-to-go of each robot [E, N]
            ret = t["rewards"] + cfg.gamma * future * (1.0 - t["done"][:, None])
            return ret, ret

        _, returns = jax.lax.scan(back, jnp.zeros_like(traj["rewards"][0]), traj, reverse=True)
        mask = traj["live"][..., None].astype(jnp.float32)                     # [T, E, 1]
        mean = (returns * mask).sum() / (mask.sum() * returns.shape[-1])
        std = jnp.sqrt((((returns - mean) * mask) ** 2).sum() / (mask.sum() * returns.shape[-1]) + 1e-8)
        logp = jax.nn.log_softmax(actor.apply(params, actor_inputs(traj["obs"])))
        taken = jnp.take_along_axis(logp, traj["actions"][..., None], -1)[..., 0]
        return -(taken * (returns - mean) / std * mask).sum() / (mask.sum() * returns.shape[-1])

    def run(runner, n: int):
        def update(runner, _):
            key, k_roll = jax.random.split(runner["key"])
            traj = rollout(runner["params"], k_roll)
            grads = jax.grad(loss_fn)(runner["params"], traj)
            updates, opt_state = tx.update(grads, runner["opt_state"], runner["params"])
            runner = dict(params=optax.apply_updates(runner["params"], updates), opt_state=opt_state, key=key)
            return runner, rollout_metrics(traj["done"], traj["info"])

        return jax.lax.scan(update, runner, None, length=n)

    return trainer(init, run, num_updates, steps_per_update)


def greedy_policy(env, cfg: ReinforceConfig, params):
    actor = Actor(env.num_actions, cfg.hidden)
    return lambda key, obs: jnp.argmax(actor.apply(params, actor_inputs(obs)), -1).astype(jnp.int32)


def policy_tensors(cfg: ReinforceConfig, params):
    layers = ("Dense_0", "Dense_1")
    tensors = {f"actor.{layer}.{name}": np.asarray(params["params"][layer][name], np.float32)
               for layer in layers for name in ("kernel", "bias")}
    fields = dict(kind="actor", recurrent=False, cell="none", hidden=cfg.hidden, activation="tanh",
                  layers=[f"actor.{layer}" for layer in layers], shared=True, agent_ids=True)
    return fields, tensors


REINFORCE = Algorithm(
    name="reinforce", summary="REINFORCE: each robot follows the gradient of its own return (example package)",
    config=ReinforceConfig, make_train=make_train, greedy_policy=greedy_policy, policy_tensors=policy_tensors)
