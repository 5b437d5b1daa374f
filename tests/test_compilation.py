"""Hot paths compile once and stay on the device: the env step, reset and a training chunk are traced
once for any number of calls with new keys, states and actions, and their programs contain no host
callback (no Python runs inside the compiled loop)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest

import marbler_jax
from marbler_jax_rl import ippo, vdn


def host_callbacks(lowered) -> int:
    """Number of host-callback custom calls in a lowered program (``jax.debug.callback``,
    ``jax.pure_callback``, ``io_callback`` and ``jax.debug.print`` all lower to one)."""
    return lowered.as_text().count("callback")


def test_the_detector_sees_a_host_callback():
    def noisy(x):
        jax.debug.callback(lambda v: None, x)
        return x + 1

    assert host_callbacks(jax.jit(noisy).lower(jnp.ones(3))) >= 1
    assert host_callbacks(jax.jit(lambda x: x + 1).lower(jnp.ones(3))) == 0


@pytest.mark.parametrize("name, period", [("predator_capture_prey", 15), ("warehouse", 1)])
def test_env_step_and_reset_compile_once_without_host_callbacks(name, period):
    env = marbler_jax.make(name, control_period=period)   # period 1: warm-started barrier state too
    batch = 8
    reset = jax.jit(jax.vmap(env.reset))
    step = jax.jit(jax.vmap(env.step))
    key = jax.random.PRNGKey(0)
    _, state = reset(jax.random.split(key, batch))
    for _ in range(4):   # new keys, states and actions every call: still one program
        key, k_act, k_step, k_reset = jax.random.split(key, 4)
        actions = jax.random.randint(k_act, (batch, env.num_agents), 0, env.num_actions)
        _, state, *_ = step(jax.random.split(k_step, batch), state, actions)
        reset(jax.random.split(k_reset, batch))
    assert step._cache_size() == 1 and reset._cache_size() == 1
    assert host_callbacks(step.lower(jax.random.split(key, batch), state, actions)) == 0
    assert host_callbacks(reset.lower(jax.random.split(key, batch))) == 0


@pytest.mark.parametrize("algo", ["vdn", "ippo", "ippo-gru"])
def test_a_training_chunk_compiles_once_without_host_callbacks(algo):
    """What the driver's Python loop calls once per chunk (``trainer.run`` under jit); recurrent PPO carries its
    hidden state in the runner."""
    env = marbler_jax.make("simple_navigation", control_period=15)
    if algo == "vdn":
        trainer = vdn.make_train(env, vdn.VDNConfig(hidden=8, num_envs=2, batch_size=2, buffer_size=8,
                                                    train_steps=1, learning_starts=0, total_timesteps=10**6))
    else:
        trainer = ippo.make_train(env, ippo.IPPOConfig(hidden=8, num_envs=2, num_steps=8, update_epochs=1,
                                                       num_minibatches=1, total_timesteps=10**6,
                                                       cell="gru" if algo == "ippo-gru" else "none"))
    run = jax.jit(trainer.run, static_argnums=1)
    runner = jax.jit(trainer.init)(jax.random.PRNGKey(0))
    for _ in range(3):
        runner, _ = run(runner, 2)
    assert run._cache_size() == 1
    assert host_callbacks(run.lower(runner, 2)) == 0


def test_a_retraced_program_is_the_same_program():
    """Tracing the same step again gives the same StableHLO, so JAX's persistent compilation cache serves
    a second run in one process (a training run after another, the benchmark's cells, the test suite)
    instead of compiling it again. A check that bakes a per-trace counter into the program breaks this."""
    env = marbler_jax.make("predator_capture_prey", control_period=15)
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    _, state = jax.jit(jax.vmap(env.reset))(keys)
    actions = jnp.zeros((4, env.num_agents), jnp.int32)

    def program():   # a fresh jit of a fresh function: traced anew, as a new training run's step is
        return jax.jit(lambda k, s, a: jax.vmap(env.step)(k, s, a)).lower(keys, state, actions).as_text(
            debug_info=False)

    assert program() == program()
