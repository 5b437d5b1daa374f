"""Batched rollouts: ``jit(scan(vmap(step)))`` helpers for random or given policies."""
from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec as P


@dataclasses.dataclass(frozen=True)
class StatefulPolicy:
    """A policy with memory (e.g. a recurrent Q-network) for batched rollouts.

    ``initial_carry(batch_shape) -> carry`` and ``step(key, obs [..., N, D], carry, reset [...]) ->
    (actions [..., N], carry)``, where ``reset`` is True at the first step of an episode (the policy
    must clear its memory there). Plain policies are callables ``(key, obs) -> actions``.
    """

    initial_carry: Callable
    step: Callable


def as_stateful(policy) -> StatefulPolicy:
    """``policy`` as a :class:`StatefulPolicy`: plain ``(key, obs) -> actions`` callables get an empty memory."""
    if isinstance(policy, StatefulPolicy):
        return policy
    return StatefulPolicy(initial_carry=lambda batch_shape: (),
                          step=lambda key, obs, carry, reset: (policy(key, obs), carry))


def numpy_policy_greedy(policy) -> StatefulPolicy:
    """A :class:`marbler_jax.numpy_policy.NumpyPolicy` (an exported or imported policy folder) acting
    greedily in batched rollouts: its forward pass runs on JAX arrays, its memory is zeroed at each
    episode's first step."""
    def initial_carry(batch_shape):
        return jnp.zeros(tuple(batch_shape) + policy.initial_hidden().shape, jnp.float32)

    def step(key, obs, carry, reset):
        carry = jnp.where(reset[..., None, None], jnp.zeros_like(carry), carry)
        actions, carry, _ = policy.act(obs, carry)
        return actions, carry

    return StatefulPolicy(initial_carry=initial_carry, step=step)


def random_actions(env, key, batch_shape=()):
    """Uniform random actions ``[*batch_shape, N]`` int32."""
    return jax.random.randint(key, tuple(batch_shape) + (env.num_agents,), 0, env.num_actions, jnp.int32)


def batched_rollout(env, key, num_envs: int, num_steps: int, policy: Callable | None = None, start=None):
    """Run ``num_envs`` envs for ``num_steps`` steps (auto-reset) with ``policy(key, obs) -> actions``
    or a :class:`StatefulPolicy` (uniform random when None). Returns the final state and the per-step ``(rewards, done, info)``
    stacked as ``[num_steps, num_envs, ...]``. Jit it with ``env``, ``num_envs``, ``num_steps`` and
    ``policy`` static (see :func:`make_rollout`). ``start``: ``(obs [num_envs, N, D], state [num_envs, ...])``
    to begin from instead of fresh resets (e.g. MARBLER's own starts, :mod:`marbler_jax_rl.marbler_starts`)."""
    step = jax.vmap(env.step)
    key_reset, key_run = jax.random.split(key)
    if start is None:
        obs, state = jax.vmap(env.reset)(jax.random.split(key_reset, num_envs))
    else:
        obs, state = start
    if policy is not None:
        policy = as_stateful(policy)
    memory = policy.initial_carry((num_envs,)) if policy is not None else ()

    def body(carry, key_t):
        obs, state, memory, reset = carry
        key_act, key_step = jax.random.split(key_t)
        if policy is None:
            actions = random_actions(env, key_act, (num_envs,))
        else:
            actions, memory = policy.step(key_act, obs, memory, reset)
        obs, state, rewards, done, info = step(jax.random.split(key_step, num_envs), state, actions)
        return (obs, state, memory, done), (rewards, done, info)

    start = (obs, state, memory, jnp.ones((num_envs,), bool))
    (obs, state, _, _), traj = jax.lax.scan(body, start, jax.random.split(key_run, num_steps))
    return state, traj


def make_rollout(env, num_envs: int, num_steps: int, policy: Callable | None = None, devices: int = 1):
    """A jitted ``key -> (state, (rewards, done, info))`` for :func:`batched_rollout`.

    ``devices > 1`` splits the envs over this process's first ``devices`` devices (``num_envs`` divisible
    by it): device ``i`` runs ``num_envs / devices`` envs from ``jax.random.split(key, devices)[i]``, so
    the episodes are those of one-device rollouts from those keys, concatenated along the env axis. On a
    CPU, JAX shows one device unless ``jax.config.update("jax_num_cpu_devices", n)`` runs before it first
    computes; the env's per-tick kernels are small, and XLA's CPU backend runs them faster as one device
    per core than as one device spread over every core (BENCHMARKS.md).
    """
    if isinstance(devices, bool) or not isinstance(devices, int) or devices < 1:
        raise ValueError(f"devices must be an integer >= 1, got {devices!r}")
    if devices == 1:
        return jax.jit(lambda key: batched_rollout(env, key, num_envs, num_steps, policy))
    available = jax.local_devices()
    if len(available) < devices:
        raise ValueError(f"devices={devices} but JAX has {len(available)} {available[0].platform} device(s); on a CPU "
                         f"run jax.config.update('jax_num_cpu_devices', {devices}) before JAX first computes")
    if num_envs % devices:
        raise ValueError(f"num_envs={num_envs} must be divisible by devices={devices}")
    mesh = Mesh(np.array(available[:devices]), ("envs",))

    def share(keys):            # keys [1, 2]: this device's key
        return batched_rollout(env, keys[0], num_envs // devices, num_steps, policy)

    split = jax.shard_map(share, mesh=mesh, in_specs=P("envs"), out_specs=(P("envs"), P(None, "envs")),
                          check_vma=False)
    return jax.jit(lambda key: split(jax.random.split(key, devices)))


def at_first_done(done, x):
    """``x [T, E, ...]`` at the step where each env's first episode ended (``done [T, E]``), ``[E, ...]``;
    numpy or JAX arrays (jittable). An env that never finished reads step 0: check ``done.any(0)``."""
    first = done.argmax(axis=0)
    return x[first, jnp.arange(done.shape[1])]


EPISODE_METRICS = ("reward", "steps", "collisions", "out_of_bounds")
"""The metrics of every episode (MARBLER's Table II); scenarios add theirs (``env.metric_names``)."""


def first_episode_metrics(env, done, info) -> dict:
    """MARBLER's Table II metrics of the first episode each env finished, ``{name: [E]}`` float32, from
    ``done [T, E]`` and ``info`` entries ``[T, E]`` (jittable; numpy inputs work too): ``reward`` (team
    return), ``steps`` (episode length, the step limit where a violation ended it, as the paper counts),
    ``collisions`` / ``out_of_bounds`` (100 where the episode had one, else 0: their mean is a
    percentage of episodes) and the scenario's own metrics (``prey_left``, ``material_left``, ...)."""
    def at(key):
        return jnp.asarray(at_first_done(done, info[key]), jnp.float32)

    out = {"reward": at("episode_return"),
           "steps": jnp.where(at("violation") > 0, jnp.float32(env.max_steps), at("steps")),
           "collisions": 100.0 * at("episode_collided"), "out_of_bounds": 100.0 * at("episode_out_of_bounds")}
    for key in env.metric_names:
        out[key] = at(key)
    return out


def episode_stats(traj) -> dict[str, float]:
    """Mean metrics over the episodes that finished in a rollout trajectory."""
    rewards, done, info = traj
    finished = done
    count = jnp.maximum(jnp.sum(finished), 1)

    def mean_at_done(x):
        return float(jnp.sum(jnp.where(finished, x, 0)) / count)

    stats = {
        "episodes": int(jnp.sum(finished)),
        "return": mean_at_done(info["episode_return"]),
        "length": mean_at_done(info["steps"]),
        "collision_rate": mean_at_done(info["episode_collided"]),
        "out_of_bounds_rate": mean_at_done(info["episode_out_of_bounds"]),
    }
    for key in ("prey_left", "material_left"):
        if key in info:
            stats[key] = mean_at_done(info[key])
    return stats
