"""IPPO learns, trains several seeds in one program, and supports per-agent parameters."""
from __future__ import annotations

import jax
import numpy as np
import pytest

import marbler_jax
from marbler_jax_rl.ippo import IPPOConfig, make_train
from marbler_jax.rollout import episode_stats, make_rollout


def test_ippo_learns_simple_navigation(ippo_simple_nav_run):
    """150k steps through the training driver (the session's shared run): greedy beats random clearly."""
    import json

    result = json.loads((ippo_simple_nav_run / "evaluation.json").read_text())
    trained, random_return = result["trained"], result["random"]["return"]
    rows = [json.loads(line) for line in (ippo_simple_nav_run / "metrics.jsonl").read_text().splitlines()]
    curve = [r["return_mean"] for r in rows if r["return_mean"] is not None]
    print(f"IPPO simple_navigation: random {random_return:.1f}, trained greedy {trained['return']:.1f}, "
          f"training curve {curve[0]:.1f} -> {curve[-1]:.1f}")
    assert trained["episodes"] >= 256 and len(curve) >= len(rows) - 2 and np.all(np.isfinite(curve))
    assert trained["return"] > random_return + 30, (random_return, trained["return"])
    assert trained["collision_rate"] == 0.0


def test_ippo_seeds_in_one_program_and_unshared_parameters():
    env = marbler_jax.make("material_transport")
    cfg = IPPOConfig(total_timesteps=2 * 16 * 8, num_envs=16, num_steps=8, num_minibatches=2, update_epochs=1,
                     hidden=32, shared=False)
    # seeds vmapped in one program, as the driver does
    params, metrics = jax.block_until_ready(
        jax.jit(jax.vmap(make_train(env, cfg)))(jax.random.split(jax.random.PRNGKey(1), 3)))
    kernel = params["params"]["actor"]["Dense_0"]["kernel"]
    assert np.all(np.isfinite(np.asarray(kernel)))
    assert kernel.shape == (3, env.num_agents, env.obs_dim, 32)   # [seeds, agents, in, out]
    assert metrics["loss"].shape == (3, cfg.num_updates)
    shared_cfg = IPPOConfig(total_timesteps=16 * 8, num_envs=16, num_steps=8, num_minibatches=2, update_epochs=1,
                            hidden=32)
    shared_params = jax.eval_shape(make_train(env, shared_cfg).init, jax.random.PRNGKey(2))["params"]   # shapes only
    # one set for all agents, input = obs + agent-ID one-hot
    assert shared_params["params"]["actor"]["Dense_0"]["kernel"].shape == (env.obs_dim + env.num_agents, 32)


def test_mappo_critic_sees_the_global_state():
    from marbler_jax_rl import mappo

    env = marbler_jax.make("simple_navigation")
    cfg = mappo.MAPPOConfig(total_timesteps=16 * 8, num_envs=16, num_steps=8)
    params = jax.eval_shape(mappo.make_train(env, cfg).init, jax.random.PRNGKey(0))["params"]   # shapes only
    n, d = env.num_agents, env.obs_dim
    assert params["params"]["critic"]["Dense_0"]["kernel"].shape[0] == n * d + n   # all obs + agent ID
    assert params["params"]["actor"]["Dense_0"]["kernel"].shape[0] == d + n        # own obs + agent ID


@pytest.mark.slow     # a learning check; IPPO's (the same PPO learner) stays in the default suite
def test_mappo_learns_simple_navigation():
    from marbler_jax_rl import mappo

    env = marbler_jax.make("simple_navigation")
    cfg = mappo.MAPPOConfig(total_timesteps=150_000, num_envs=64, num_steps=64, lr=1e-3)
    params, _ = jax.block_until_ready(jax.jit(mappo.make_train(env, cfg))(jax.random.PRNGKey(0)))
    _, random_traj = make_rollout(env, 256, env.max_steps * 2)(jax.random.PRNGKey(9))
    _, greedy_traj = make_rollout(env, 256, env.max_steps * 2, mappo.greedy_policy(env, cfg, params))(jax.random.PRNGKey(9))
    random_return, trained = episode_stats(random_traj)["return"], episode_stats(greedy_traj)
    print(f"MAPPO simple_navigation: random {random_return:.1f}, greedy {trained['return']:.1f}")
    assert trained["return"] > random_return + 30
