"""Fidelity against MARBLER's own episodes (golden rollouts, rps 6bb184e, MARBLER 59c4923).

MARBLER's cvxopt QP runs with loose tolerances: even where no constraint is active it returns
controls ~1e-4 m/s and ~1e-3 rad/s away from the exact QP, so a closed loop with an exact certificate
leaves MARBLER's trajectory at the first control refresh. The tests therefore check:

1. the full env (goals, control loop, tick-level violation checks, early stop, scenario events,
   observations, rewards, dones, episode end) by replaying MARBLER's *recorded* commands at each
   control refresh: everything must match to 1e-9 (float64);
2. the physics alone: every recorded command replays MARBLER's per-tick poses;
3. the controller + our certificate at MARBLER's poses: within the loose-QP gap, statistically.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import marbler_jax
from marbler_jax import physics
from marbler_jax_rl.marbler_starts import SCENARIOS as SCENARIO_FILES
from tests.golden_rollouts import (assert_matches_marbler, golden_env, initial_state, load_episodes, recorded_velocities,
                                   replay_recorded)

FILES = sorted(SCENARIO_FILES)


@pytest.mark.parametrize("fname", FILES)
def test_replay_of_recorded_commands_matches_marbler(fname):
    name = SCENARIO_FILES[fname][0]
    with jax.enable_x64(True):
        for ep in load_episodes(fname):
            env = golden_env(name, ep, control_period=15)
            out = replay_recorded(env, initial_state(env, fname, ep), ep)
            assert_matches_marbler(env, out, ep)


@pytest.mark.parametrize("fname", FILES)
def test_physics_replays_every_recorded_tick(fname):
    params = physics.PRESETS["marbler"]
    for ep in load_episodes(fname):
        poses = np.swapaxes(ep.data["iter_poses"], -1, -2)
        vels = np.swapaxes(ep.data["iter_vels"], -1, -2)
        start = np.swapaxes(ep.data["reset_poses"], 0, 1)
        # teacher-forced, one tick at a time (numpy path = the deployment bundle's code)
        prev = np.concatenate([start[None], poses[:-1]])
        stepped = physics.integrate(params, prev, vels)
        err = np.abs(stepped - poses)
        err[..., 2] = np.abs(np.arctan2(np.sin(stepped[..., 2] - poses[..., 2]), np.cos(stepped[..., 2] - poses[..., 2])))
        assert err.max() <= 1e-12, f"{ep.tag}: {err.max():.2e}"
        # free-running over the whole episode
        pose = start
        for j in range(len(vels)):
            pose = physics.integrate(params, pose, vels[j])
        assert np.abs(pose[:, :2] - poses[-1, :, :2]).max() <= 1e-9, ep.tag


@pytest.mark.parametrize("fname", ["PredatorCapturePrey", "Warehouse"])
def test_our_certificate_stays_within_marblers_loose_qp_gap(fname):
    name = SCENARIO_FILES[fname][0]
    gaps = []
    with jax.enable_x64(True):
        for ep in load_episodes(fname)[:3]:
            env = golden_env(name, ep, control_period=15)
            vel_fn = jax.jit(lambda p, g, env=env: physics.threshold(env.params, env.velocities(p, g)))
            goals_fn = jax.jit(env.scenario.goals)
            step = jax.jit(env.step_env)
            state = initial_state(env, fname, ep)
            d = ep.data
            iter_poses = np.swapaxes(d["iter_poses"], -1, -2)
            iter_vels = np.swapaxes(d["iter_vels"], -1, -2)
            index = d["iter_index"]
            for t in range(ep.steps):
                actions = jnp.asarray(d["actions"][t], jnp.int32)
                goals = goals_fn(jnp.asarray(iter_poses[index[t] - 1]), state.scenario, actions)
                for j in range(index[t], index[t + 1], 15):
                    gaps.append(np.abs(np.asarray(vel_fn(jnp.asarray(iter_poses[j - 1]), goals)) - iter_vels[j]).max(0))
                _, state, _, _, _ = step(jax.random.PRNGKey(0), state, actions, recorded_velocities(env, ep, t))
    gaps = np.array(gaps)
    v_med, w_med = np.median(gaps, axis=0)
    v_p99, w_p99 = np.percentile(gaps, 99, axis=0)
    print(f"{fname}: control gap to MARBLER v median {v_med:.1e} p99 {v_p99:.1e}, w median {w_med:.1e} p99 {w_p99:.1e}")
    assert v_med <= 1e-3 and w_med <= 1e-2
    assert v_p99 <= 3e-2 and w_p99 <= 0.5


SPAWN = {
    # scenario -> (robot x values, robot y values) MARBLER's grids can produce
    "simple_navigation": ({-1.45, -1.15, -0.85, -0.55}, {round(-0.9 + 0.3 * i, 6) for i in range(6)}),
    "predator_capture_prey": ({-1.4, -1.1, -0.8, -0.5}, {round(-0.9 + 0.3 * i, 6) for i in range(6)}),
    "warehouse": ({-1.4, -0.8, -0.2, 0.4, 1.0}, {-0.9, -0.3, 0.3}),
    "material_transport": ({-1.4, -1.1}, {round(-0.9 + 0.3 * i, 6) for i in range(6)}),
}


@pytest.mark.parametrize("fname", FILES)
def test_reset_distribution_covers_marblers(fname):
    name = SCENARIO_FILES[fname][0]
    env = marbler_jax.make(name)
    _, states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 2000))
    poses = np.asarray(states.poses, dtype=np.float64)
    # every MARBLER reset pose is one our sampler can produce, and ours stay on MARBLER's grid
    ours = {tuple(np.round(p[:2], 4)) for p in poses.reshape(-1, 3)}
    for ep in load_episodes(fname):
        for p in np.swapaxes(ep.data["reset_poses"], 0, 1):
            assert tuple(np.round(p[:2], 4)) in ours, f"{ep.tag}: MARBLER spawned at {p[:2]}"
    if name in SPAWN:
        xs, ys = SPAWN[name]
        assert {round(float(v), 4) for v in poses[..., 0].ravel()} <= {round(v, 4) for v in xs}
        assert {round(float(v), 4) for v in poses[..., 1].ravel()} <= {round(v, 4) for v in ys}
        # robots never share a cell
        flat = np.round(poses[..., :2], 4)
        assert all(len({tuple(p) for p in team}) == len(team) for team in flat)
