"""Load MARBLER golden rollouts (``shared/golden/rollouts``) into marbler-jax states and replay them."""
from __future__ import annotations

import json
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

import marbler_jax
from marbler_jax import physics
from marbler_jax_rl.marbler_starts import env_state
from tests.conftest import golden_path

TAGS = [f"s{s}_e{e}" for s in range(3) for e in range(2)]


@dataclass
class Episode:
    tag: str
    config: dict
    meta: dict
    data: dict  # arrays of this episode, keys without the tag prefix

    @property
    def steps(self) -> int:
        return len(self.data["actions"])


def load_episodes(scenario_file: str) -> list[Episode]:
    return episodes_from(np.load(golden_path(f"rollouts/{scenario_file}.npz")))


def episodes_from(raw) -> list[Episode]:
    """The episodes of a golden-rollout ``.npz`` (or a ``scripts/marbler_oracle.py trace`` file)."""
    meta = json.loads(str(raw["meta"]))
    episodes = []
    for ep in meta["episodes"]:
        tag = ep["tag"]
        data = {k[len(tag) + 1:]: raw[k] for k in raw.files if k.startswith(tag + "_")}
        episodes.append(Episode(tag, meta["config"], ep, data))
    return episodes


def replay(env, state, episode: Episode, build_velocity_check=True):
    """Step ``env`` (float64) through the episode's actions. Returns per-step arrays and the first
    step whose controller refresh disagrees with MARBLER's recorded (loose-QP) velocities."""
    step = jax.jit(env.step_env)
    vel_fn = jax.jit(lambda p, g: physics.threshold(env.params, env.velocities(p, g)))
    goals_fn = jax.jit(env.scenario.goals)
    d = episode.data
    iter_poses = np.swapaxes(d["iter_poses"], -1, -2)
    iter_vels = np.swapaxes(d["iter_vels"], -1, -2)
    index = d["iter_index"]
    out = {"poses": [], "rewards": [], "dones": [], "obs": [], "info": []}
    divergence = None
    for t in range(episode.steps):
        actions = jnp.asarray(d["actions"][t], jnp.int32)
        if divergence is None and build_velocity_check:
            start_pose = jnp.asarray(iter_poses[index[t] - 1])
            goals = goals_fn(start_pose, state.scenario, actions)
            for j in range(index[t], index[t + 1]):
                if (j - index[t]) % env.config.control_period == 0:
                    ours = np.asarray(vel_fn(jnp.asarray(iter_poses[j - 1]), goals))
                    if np.abs(ours - iter_vels[j]).max() > 1e-7:
                        divergence = t
                        break
        obs, state, rewards, done, info = step(jax.random.PRNGKey(0), state, actions)
        out["poses"].append(np.asarray(state.poses))
        out["rewards"].append(np.asarray(rewards))
        out["dones"].append(bool(done))
        out["obs"].append(np.asarray(obs))
        out["info"].append(jax.tree_util.tree_map(np.asarray, info))
    return {k: (np.stack(v) if k not in ("info",) else v) for k, v in out.items()}, divergence


def golden_env(name: str, episode: Episode, **overrides):
    """The scenario with MARBLER's settings: ``marbler`` physics, zero reset obs, its config keys."""
    return marbler_jax.make(name, physics="marbler", zero_reset_obs=True, **overrides)


def recorded_velocities(env, episode: Episode, t: int) -> np.ndarray:
    """MARBLER's command at each control refresh of step ``t``: ``[num_segments, N, 2]``.

    Segments that MARBLER never reached (the step ended early on a violation) are zero.
    """
    d = episode.data
    start, stop = d["iter_index"][t], d["iter_index"][t + 1]
    vels = np.swapaxes(d["iter_vels"], -1, -2)
    out = np.zeros((env.num_segments, env.num_agents, 2))
    for s in range(env.num_segments):
        j = start + s * env.config.control_period
        if j < stop:
            out[s] = vels[j]
    return out


def replay_recorded(env, state, episode: Episode):
    """Closed-loop replay with MARBLER's recorded commands; returns per-step arrays."""
    step = jax.jit(env.step_env)
    out = {"poses": [], "rewards": [], "dones": [], "obs": [], "info": []}
    for t in range(episode.steps):
        vel = recorded_velocities(env, episode, t)
        obs, state, rewards, done, info = step(jax.random.PRNGKey(0), state,
                                               jnp.asarray(episode.data["actions"][t], jnp.int32), vel)
        out["poses"].append(np.asarray(state.poses))
        out["rewards"].append(np.asarray(rewards))
        out["dones"].append(bool(done))
        out["obs"].append(np.asarray(obs))
        out["info"].append(jax.tree_util.tree_map(np.asarray, info))
        if bool(done):
            break
    return {k: (np.stack(v) if k != "info" else v) for k, v in out.items()}


def initial_state(env, name_file: str, episode: Episode):
    """``env``'s float64 state at the episode's recorded MARBLER start."""
    return env_state(env, name_file, episode.data["reset_poses"], episode.meta["reset_state"],
                     episode.meta["reset_agents"], jnp.float64)


def assert_matches_marbler(env, out: dict, ep: Episode) -> None:
    """A replay (:func:`replay_recorded`) equals MARBLER's episode at every step: poses, rewards, observations,
    dones (1e-9, float64), the violation that ended it, and the episode's prey / material left."""
    steps = len(out["poses"])
    assert steps == ep.steps, f"{ep.tag}: episode lasted {steps} steps, MARBLER {ep.steps}"
    np.testing.assert_allclose(out["poses"], np.swapaxes(ep.data["poses"], -1, -2), atol=1e-9, err_msg=ep.tag)
    np.testing.assert_allclose(out["rewards"], ep.data["rewards"], atol=1e-9, err_msg=ep.tag)
    np.testing.assert_allclose(out["obs"], ep.data["obs"], atol=1e-9, err_msg=ep.tag)
    np.testing.assert_array_equal(out["dones"], ep.data["dones"][:, 0], err_msg=ep.tag)
    for t, (ours, marbler) in enumerate(zip(out["info"], ep.meta["step_info"])):
        message = marbler.get("message") or ""
        if isinstance(marbler.get("remaining"), str):      # Simple reports its violation as "remaining"
            message = marbler["remaining"]
        assert bool(ours["violation"]) == (message != ""), f"{ep.tag} step {t}: MARBLER said {message!r}"
        assert bool(ours["collisions"]) == ("collision" in message), f"{ep.tag} step {t}: {message!r}"
        assert bool(ours["out_of_bounds"]) == ("boundary" in message), f"{ep.tag} step {t}: {message!r}"
    remaining = ep.meta["step_info"][-1].get("remaining")
    if isinstance(remaining, int):  # Prey Left / Material Left
        key = "prey_left" if "prey_left" in out["info"][-1] else "material_left"
        assert int(out["info"][-1][key]) == remaining, ep.tag
    assert np.isclose(float(out["info"][-1]["episode_return"]),
                      float(env.scenario.team_reward(np.asarray(ep.data["rewards"])).sum()), atol=1e-9)
