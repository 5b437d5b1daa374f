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


def test_recurrent_ippo_learns_simple_navigation():
    """GRU actors (``cell="gru"``), 49k env steps: the greedy recurrent policy beats random clearly."""
    env = marbler_jax.make("simple_navigation")
    cfg = IPPOConfig(total_timesteps=49_152, num_envs=64, num_steps=64, lr=1e-3, hidden=32, cell="gru")
    params, _ = jax.block_until_ready(jax.jit(make_train(env, cfg))(jax.random.PRNGKey(0)))
    from marbler_jax_rl.ippo import greedy_policy

    _, random_traj = make_rollout(env, 256, env.max_steps * 2)(jax.random.PRNGKey(9))
    _, greedy_traj = make_rollout(env, 256, env.max_steps * 2, greedy_policy(env, cfg, params))(jax.random.PRNGKey(9))
    random_return, trained = episode_stats(random_traj)["return"], episode_stats(greedy_traj)["return"]
    print(f"recurrent IPPO simple_navigation: random {random_return:.1f}, greedy {trained:.1f}")
    assert trained > random_return + 30


@pytest.mark.parametrize("cell,shared", [("gru", True), ("mingru", False)])
def test_recurrent_actors_unroll_the_rollouts_steps(cell, shared):
    """The learner's unroll of a recorded rollout (from the hidden state it started with, zeroed where an
    episode starts) gives the logits the rollout's steps had: across auto-resets and per-robot networks."""
    import jax.numpy as jnp

    from marbler_jax_rl.ippo import actor_sequence, make_network, recurrent_act

    env = marbler_jax.make("material_transport", max_episode_steps=6)      # episodes end inside the 20 steps
    cfg = IPPOConfig(num_envs=4, hidden=16, cell=cell, shared=shared)
    network = make_network(env, cfg)
    params = make_train(env, cfg).init(jax.random.PRNGKey(0))["params"]
    obs, state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(1), 4))
    start = jax.random.normal(jax.random.PRNGKey(2), (4, env.num_agents, 16))    # mid-episode memory
    hidden, reset = start, jnp.zeros(4, bool)
    steps = []
    for t in range(20):
        hidden, logits = recurrent_act(network, cfg, params, hidden, obs, reset)
        steps.append((obs, reset, logits))
        actions = jnp.argmax(logits, -1)
        obs, state, _, reset, _ = jax.vmap(env.step)(jax.random.split(jax.random.PRNGKey(t), 4), state, actions)
    obs_seq, reset_seq, logits_seq = (jnp.stack(x) for x in zip(*steps))
    assert reset_seq[1:].any() and not reset_seq[:, 0].all()
    unrolled = actor_sequence(network, cfg, params, start, obs_seq, reset_seq)
    np.testing.assert_allclose(unrolled, logits_seq, rtol=1e-5, atol=1e-5)
    # the memory matters: from a zero start the first episode's logits differ
    zero_start = actor_sequence(network, cfg, params, jnp.zeros_like(start), obs_seq, reset_seq)
    assert not np.allclose(zero_start[0], logits_seq[0], atol=1e-4)


def test_recurrent_settings_are_checked():
    with pytest.raises(ValueError, match=r"cell must be one of \['gru', 'mingru', 'none'\], got 'lstm'"):
        IPPOConfig(cell="lstm").validate()
    with pytest.raises(ValueError, match="num_envs = 6 must be divisible by num_minibatches = 4 with a recurrent cell"):
        IPPOConfig(num_envs=6, num_steps=8, num_minibatches=4, cell="gru").validate()
    IPPOConfig(num_envs=6, num_steps=8, num_minibatches=4).validate()      # feed-forward: samples, 48 / 4
    with pytest.raises(ValueError, match=r"the minibatch's envs \(num_envs / num_minibatches\) = 3 must be divisible"):
        IPPOConfig(num_envs=12, num_minibatches=4, cell="gru", learner_devices=2).validate()
