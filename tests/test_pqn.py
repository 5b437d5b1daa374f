"""PQN (VDN form): its settings, its export, a run through the driver, and (``slow``) that it learns (its
TD(lambda) targets are ``q_learning.lambda_returns``, tested in test_value_based)."""
from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

import marbler_jax
from marbler_jax_rl import registry
from marbler_jax_rl.driver import train_run
from marbler_jax_rl.export import export_params
from marbler_jax_rl.pqn import PQNConfig, greedy_policy
from marbler_jax.numpy_policy import load_policy

TINY = dict(num_envs=8, num_steps=8, num_minibatches=2, hidden=16, eps_decay_steps=256)


@pytest.mark.parametrize("bad, message", [
    ({"num_minibatches": 3}, "num_minibatches=3 must divide num_envs \\* num_steps = 64"),
    ({"td_lambda": 1.5}, "td_lambda must be in \\[0, 1\\], got 1.5"),
    ({"lr": 0.0}, "lr must be in \\(0, 1\\], got 0.0"),
    ({"num_epochs": 0}, "num_epochs must be >= 1, got 0"),
])
def test_bad_settings_are_one_error_naming_them(bad, message):
    with pytest.raises(ValueError, match=message):
        PQNConfig(**dict(TINY, **bad)).validate()


def test_pqn_is_a_built_in_with_a_recipe_and_no_paper_preset():
    from marbler_jax_rl.recipes import recipe, settings

    assert "pqn" in registry.names() and registry.get("pqn").config is PQNConfig
    assert recipe("pqn").config == PQNConfig() and settings("recipe", "warehouse", "pqn")[2] == 10_000_000
    assert settings("paper", "warehouse", "pqn")[1] == settings("recipe", "warehouse", "pqn")[1]   # its defaults


def test_a_run_through_the_driver_exports_a_policy_that_acts_alike(tmp_path):
    """Four updates in chunks of two through ``train_run`` (greedy tests, best checkpoint, evaluation); the
    exported numpy policy's actions equal the JAX greedy policy's."""
    from marbler_jax_rl.run import Run

    env = marbler_jax.make("predator_capture_prey")
    result = train_run("pcp", "pqn", 4 * 64, 2, tmp_path / "run", hp=TINY, test_episodes=4, eval_episodes=8,
                       checkpoint_every=2, progress=False, log=lambda *a: None)
    assert result["trained"] is not None and np.isfinite(result["best_return"])
    metrics = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [m["update"] for m in metrics] == [1, 2, 3, 4] and "test_returns" in metrics[1]

    run = Run.open(tmp_path / "run")
    cfg, params = run.algorithm_config(), run.seed_params(1, "final")
    export_params("pqn", cfg, params, env, tmp_path / "policy")
    policy = load_policy(tmp_path / "policy")
    obs = np.random.default_rng(0).uniform(-1.5, 1.5, (64, env.num_agents, env.obs_dim)).astype(np.float32)
    actions, _, q = policy.act(obs, policy.initial_hidden()[None].repeat(64, 0))
    np.testing.assert_array_equal(actions, np.asarray(greedy_policy(env, cfg, params)(None, jnp.asarray(obs))))
    assert q.shape == (64, env.num_agents, env.num_actions)


@pytest.mark.slow
def test_pqn_learns_simple_navigation(tmp_path):
    """200k env steps (epsilon down over the first 100k): the greedy policy beats random actions clearly."""
    result = train_run("simple_navigation", "pqn", 200_000, 1, tmp_path / "run", hp={"eps_decay_steps": 100_000},
                       eval_episodes=256, progress=False, log=lambda *a: None)
    assert result["trained"]["return"] > result["random"]["return"] + 40, result
    assert result["trained"]["collision_rate"] == 0.0
