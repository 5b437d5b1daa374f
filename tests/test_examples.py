"""The custom-scenario example (examples/coverage.py): rules, safety, training, CLI and bundle export."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import marbler_jax
from marbler_jax_rl import ippo
from marbler_jax_rl.run import load_run
from marbler_jax_rl.export import export_params
from marbler_jax_rl.cli import main
from marbler_jax.deploy.bundle import write_bundle
from marbler_jax.deploy.flatten import check_bundle_folder
from marbler_jax.rollout import episode_stats, make_rollout
from tests.helpers import initial_params

SPEC = f"{Path(__file__).resolve().parents[1] / 'examples' / 'coverage.py'}:Coverage"


def _state(env, robots_xy, landmarks):
    _, state = env.reset(jax.random.PRNGKey(0))
    poses = jnp.concatenate([jnp.asarray(robots_xy, jnp.float32), jnp.zeros((len(robots_xy), 1))], axis=-1)
    return state.replace(poses=poses, scenario=state.scenario.replace(landmarks=jnp.asarray(landmarks, jnp.float32)))


def test_coverage_rewards_and_termination_on_hand_built_states():
    env = marbler_jax.make(SPEC, update_frequency=1)
    marks = [[0.5, 0.0], [0.5, 0.5], [1.0, -0.5]]
    stay = jnp.full(3, 4, jnp.int32)
    def gaps(poses):
        return np.min(np.linalg.norm(np.asarray(marks)[None] - np.asarray(poses)[:, None, :2], axis=-1), axis=0)

    _, after, rewards, done, info = env.step_env(None, _state(env, marks, marks), stay)  # every landmark covered
    assert gaps(after.poses).max() < 0.01
    np.testing.assert_allclose(rewards, 5.0 - gaps(after.poses).mean(), atol=1e-5)
    assert bool(done) and int(info["uncovered"]) == 0
    robots = [[-1.0, 0.0], [-1.0, 0.5], [-1.0, -0.5]]                                # all far away
    _, after, rewards, done, info = env.step_env(None, _state(env, robots, marks), stay)
    np.testing.assert_allclose(rewards, -gaps(after.poses).mean(), atol=1e-5)
    assert not bool(done) and int(info["uncovered"]) == 3
    obs = env.observe(_state(env, robots, marks))
    np.testing.assert_allclose(obs[0, :4], [-1.0, 0.0, 1.5, 0.0], atol=1e-6)       # own xy, first landmark offset


def test_coverage_is_safe_under_the_certificate():
    env = marbler_jax.make(SPEC)
    _, traj = make_rollout(env, 32, 2 * env.max_steps)(jax.random.PRNGKey(0))
    stats = episode_stats(traj)
    assert stats["episodes"] >= 32 and stats["collision_rate"] == 0.0


@pytest.mark.slow     # a learning check; the CLI test below trains the example scenario in the default suite
def test_coverage_is_trainable():
    env = marbler_jax.make(SPEC)
    cfg = ippo.IPPOConfig(total_timesteps=40_000, num_envs=32, num_steps=64, lr=1e-3)
    params, metrics = jax.jit(ippo.make_train(env, cfg))(jax.random.PRNGKey(0))
    trained = episode_stats(make_rollout(env, 64, env.max_steps, ippo.greedy_policy(env, cfg, params))(
        jax.random.PRNGKey(1))[1])
    random = episode_stats(make_rollout(env, 64, env.max_steps)(jax.random.PRNGKey(1))[1])
    assert trained["return"] > random["return"] + 10, (trained, random)


def test_coverage_trains_from_the_cli_and_exports_a_jax_free_bundle(tmp_path):
    run = tmp_path / "run"
    assert main(["train", "--scenario", os.path.relpath(SPEC.rsplit(":", 1)[0]) + ":Coverage", "--total-steps",
                 "1024", "--out", str(run), "--no-progress", "--hp", "num_envs=8", "--hp", "num_steps=16",
                 "--test-episodes", "4", "--eval-episodes", "0"]) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["scenario"] == SPEC                      # stored with an absolute path: loads from anywhere
    env, _ = load_run(run)
    assert env.name == "coverage"
    cfg = ippo.IPPOConfig(hidden=16)
    export_params("ippo", cfg, initial_params(ippo, env, cfg), env, tmp_path / "p")
    write_bundle(env, tmp_path / "p", tmp_path / "bundle", "ippo", episodes=1)
    assert "coverage.py" in check_bundle_folder(tmp_path / "bundle")
    script = ("import sys; sys.modules.update(jax=None, flax=None); sys.path.insert(0, '.'); import main; "
              "s, policy, barrier, poses, states = main.build(main.load_config()); "
              "obs = s.observe(poses[0], states[0]); a, _, _ = policy.act(obs.astype('float32')); "
              "g = s.goals(poses[0], states[0], a); st, r, done = s.update(poses[0], states[0], a); "
              "print(obs.shape, a.shape, g.shape, float(r[0]), bool(done))")
    out = subprocess.run([sys.executable, "-c", script], cwd=tmp_path / "bundle", capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("(3, 12) (3,) (3, 2)")
