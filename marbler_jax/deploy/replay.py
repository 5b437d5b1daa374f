"""Replay a bundle's run (``MARBLER_JAX_TRACE`` output) in the JAX env and measure the differences.

``python -m marbler_jax.deploy.replay BUNDLE TRACE_DIR`` prints one JSON line per episode (see
:func:`replay_trace`): how far the poses the bundle logged (from rps or the robots) are from what
the JAX env produces from the same start state and actions, over the whole episode and per step,
and whether rewards and greedy actions agree. The env uses the ``"deployed"`` physics preset: the
bundle clips every command to the motors' limits at rps v2's base length
(:func:`marbler_jax.physics.actuator_safe`, the same wheel clip as that preset), after which the
PyPI rps's own v / omega clip changes nothing, so that preset moves the robots as either rps does. Set ``JAX_ENABLE_X64=1`` to replay in float64: the bundle computes in
float64, so any difference left is a logic difference. In float32 (training precision) each step
agrees to ~1e-7 m, but whole episodes in which robots crowd under an active barrier can drift
apart by centimetres: the closed loop amplifies float32 rounding.
"""
from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import marbler_jax
from marbler_jax.deploy.main import load_config
from marbler_jax.env import EnvState
from marbler_jax.numpy_policy import load_policy
from marbler_jax.scenarios.base import merge_settings


def replay_trace(bundle, trace, physics: str = "deployed") -> list[dict]:
    """Compare each episode the bundle logged in ``trace`` with the JAX env.

    Two replays from the episode's start state with the bundle's actions: a *free* run (the env
    integrates the whole episode itself: ``max_pose_deviation``, ``env_return``) and a *forced* run
    that restarts every step from the pose the bundle logged (``max_step_deviation``,
    ``max_reward_deviation``, ``actions_agree``: the numpy policy's greedy actions on the env's
    observations equal the bundle's). Deviations are position maxima over robots and steps [m].
    """
    bundle, trace = Path(bundle), Path(trace)
    config = load_config(str(bundle))
    env = marbler_jax.make(config["scenario"], **merge_settings(config["config"], {"physics": physics, "robotarium": None}))
    dtype = jnp.asarray(0.0).dtype
    poses0 = np.load(bundle / "initial_poses.npy", allow_pickle=False)
    fields = {name: np.load(bundle / f"initial_{name}.npy", allow_pickle=False) for name in config["state_fields"]}
    policy = load_policy(bundle)
    # one compiled program each (the many small ops of an eager reset would each compile their own)
    _, template = jax.jit(env.reset)(jax.random.PRNGKey(0))
    step, reset_obs = jax.jit(env.step_env), jax.jit(env.reset_obs)
    results = []
    for k in range(len(poses0)):
        path = trace / f"episode_{k}.npz"
        if not path.exists():
            break
        log = np.load(path, allow_pickle=False)
        scenario = dataclasses.replace(template.scenario, **{n: jnp.asarray(v[k]) for n, v in fields.items()})
        start = EnvState(poses=jnp.asarray(poses0[k], dtype), scenario=scenario, step=jnp.int32(0),
                         episode_return=jnp.zeros((), dtype), collided=jnp.bool_(False),
                         out_of_bounds=jnp.bool_(False), cbf_multipliers=env.initial_multipliers(dtype))
        free, forced = start, start
        obs = reset_obs(start)
        hidden = policy.initial_hidden()
        pose_dev = step_dev = reward_dev = 0.0
        agree, done = True, False
        for t, actions in enumerate(log["actions"]):
            actions = jnp.asarray(actions, jnp.int32)
            greedy, hidden, _ = policy.act(np.asarray(obs, np.float32), hidden)
            agree &= bool(np.array_equal(greedy, log["actions"][t]))
            _, free, _, done, _ = step(None, free, actions)
            forced = forced.replace(poses=jnp.asarray(log["poses"][t], dtype))
            obs, forced, rewards, _, _ = step(None, forced, actions)
            logged = log["poses"][t + 1][:, :2]
            pose_dev = max(pose_dev, float(np.abs(np.asarray(free.poses)[:, :2] - logged).max()))
            step_dev = max(step_dev, float(np.abs(np.asarray(forced.poses)[:, :2] - logged).max()))
            reward_dev = max(reward_dev, float(np.abs(np.asarray(rewards) - log["rewards"][t]).max()))
        results.append(dict(episode=k, steps=int(len(log["actions"])), max_pose_deviation=pose_dev,
                            max_step_deviation=step_dev, max_reward_deviation=reward_dev,
                            bundle_return=float(log["team_return"]), env_return=float(free.episode_return),
                            env_done=bool(done), actions_agree=agree))
    return results


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2 or len(argv) % 2:
        print("usage: python -m marbler_jax.deploy.replay BUNDLE TRACE_DIR [BUNDLE TRACE_DIR ...]", file=sys.stderr)
        return 2
    for bundle, trace in zip(argv[::2], argv[1::2]):
        for result in replay_trace(bundle, trace):
            print(json.dumps(dict(bundle=str(bundle), **result)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
