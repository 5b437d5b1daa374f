"""marbler-jax inside JaxMARL: the adapter speaks JaxMARL's MultiAgentEnv API, and JaxMARL's own wrappers
(``LogWrapper``, ``CTRolloutManager``, code no one here wrote) run over it, jitted and vmapped."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import marbler_jax

pytest.importorskip("jaxmarl")
from jaxmarl.environments.multi_agent_env import MultiAgentEnv  # noqa: E402
from jaxmarl.wrappers.baselines import CTRolloutManager, LogWrapper  # noqa: E402

from marbler_jax.adapters import JaxMARLEnv  # noqa: E402

SCENARIO = "predator_capture_prey"


@pytest.fixture(scope="module")
def pair():
    env = marbler_jax.make(SCENARIO)
    return env, JaxMARLEnv(env)


def random_actions(adapted, key):
    keys = jax.random.split(key, adapted.num_agents)
    return {a: adapted.action_space(a).sample(k) for a, k in zip(adapted.agents, keys)}


def test_the_adapter_is_a_jaxmarl_env_that_steps_as_the_env_does(pair):
    env, adapted = pair
    assert isinstance(adapted, MultiAgentEnv) and adapted.agents == [f"agent_{i}" for i in range(env.num_agents)]
    assert adapted.observation_space("agent_0").shape == (env.obs_dim,)
    assert adapted.action_space("agent_0").n == env.num_actions
    obs, state = adapted.reset(jax.random.PRNGKey(0))
    raw_obs, raw_state = env.reset(jax.random.PRNGKey(0))
    np.testing.assert_array_equal(np.stack([obs[a] for a in adapted.agents]), raw_obs)
    np.testing.assert_array_equal(obs["world_state"], raw_obs.reshape(-1))
    np.testing.assert_array_equal(adapted.get_state(state), env.observe(state).reshape(-1))
    assert all(bool(v.all()) for v in adapted.get_avail_actions(state).values())
    key = jax.random.PRNGKey(1)
    step, raw_step = jax.jit(adapted.step), jax.jit(env.step)   # compiled, as a JaxMARL script runs them
    for t in range(env.max_steps + 2):                    # through an episode's end and the auto-reset
        key, k_act, k_step = jax.random.split(key, 3)
        actions = random_actions(adapted, k_act)
        obs, state, rewards, dones, info = step(k_step, state, actions)
        raw = raw_step(k_step, raw_state, jnp.stack([actions[a] for a in adapted.agents]))
        raw_obs, raw_state, raw_rewards, raw_done, raw_info = raw
        np.testing.assert_array_equal(np.stack([obs[a] for a in adapted.agents]), raw_obs)
        np.testing.assert_array_equal(np.stack([rewards[a] for a in adapted.agents]), raw_rewards)
        assert set(dones) == set(adapted.agents) | {"__all__"} and bool(dones["__all__"]) == bool(raw_done)
        assert float(info["episode_return"]) == float(raw_info["episode_return"])


def test_jaxmarls_log_wrapper_runs_jitted_and_vmapped_and_counts_the_episodes(pair):
    env, adapted = pair
    wrapped = LogWrapper(adapted)
    batch, steps = 8, env.max_steps

    def rollout(key):
        k_reset, k_run = jax.random.split(key)
        _, state = wrapped.reset(k_reset)

        def step(state, key):
            k_act, k_step = jax.random.split(key)
            _, state, rewards, dones, info = wrapped.step(k_step, state, random_actions(adapted, k_act))
            return state, (dones["__all__"], info["returned_episode_returns"], info["episode_return"])

        return jax.lax.scan(step, state, jax.random.split(k_run, steps))[1]

    done, logged, episode_return = jax.jit(jax.vmap(rollout))(jax.random.split(jax.random.PRNGKey(2), batch))
    assert done.shape == (batch, steps) and done.any(axis=1).all()       # every env finished an episode
    # where an episode ends, JaxMARL's per-agent return summed is the env's own episode return (team reward
    # = the sum of the robots' rewards in Predator Capture Prey's shared reward)
    ends = np.asarray(done)
    team = np.asarray(logged)[ends].sum(-1)
    np.testing.assert_allclose(team / env.num_agents, np.asarray(episode_return)[ends], rtol=1e-5, atol=1e-4)


def test_jaxmarls_centralised_rollout_manager_batches_the_adapter(pair):
    env, adapted = pair
    manager = CTRolloutManager(adapted, batch_size=6)
    obs, state = manager.batch_reset(jax.random.PRNGKey(3))
    assert obs["__all__"].shape == (6, env.num_agents * env.obs_dim)     # the global state
    assert obs["agent_0"].shape == (6, env.obs_dim + env.num_agents)    # padded, with the agent ID
    key = jax.random.PRNGKey(4)
    for _ in range(3):
        key, k_act, k_step = jax.random.split(key, 3)
        actions = {a: manager.batch_sample(k, a) for a, k in zip(adapted.agents, jax.random.split(k_act, env.num_agents))}
        obs, state, rewards, dones, _ = manager.batch_step(k_step, state, actions)
        assert rewards["__all__"].shape == (6,) and dones["__all__"].shape == (6,)
        assert np.isfinite(np.asarray(obs["__all__"])).all()


@pytest.mark.parametrize("updates", [pytest.param(150, marks=pytest.mark.slow), 3])
def test_an_ippo_script_written_for_jaxmarl_learns_on_predator_capture_prey(pair, updates):
    """``examples/jaxmarl_ippo.py`` uses JaxMARL's API alone (dict observations, its LogWrapper). 150 updates
    (307k env steps per seed) on the adapter lift both seeds' per-robot return from about -4.4 (random) to
    above 5; the default suite runs three updates of the same program."""
    from tests.helpers import load_example

    ippo = load_example("jaxmarl_ippo")
    keys = jax.random.split(jax.random.PRNGKey(0), 3)[1:]
    params, returns = jax.jit(jax.vmap(ippo.make_train(pair[1], updates=updates)))(keys)
    assert returns.shape == (2, updates)
    assert all(np.isfinite(np.asarray(leaf)).all() for leaf in jax.tree_util.tree_leaves(params))
    if updates >= 150:
        first, last = np.nanmean(np.asarray(returns[:, :10]), 1), np.nanmean(np.asarray(returns[:, -10:]), 1)
        print(f"JaxMARL IPPO on marbler-jax PCP: {first} -> {last}")
        assert (first < 0).all() and (last > 5).all(), (first, last)
