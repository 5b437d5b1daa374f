"""Env core invariants: safety, determinism, batching, episode timing, auto-reset, input errors."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import marbler_jax
from marbler_jax import cbf, control_loop
from marbler_jax.rollout import make_rollout
from tests.helpers import run_with_two_devices, slow_unless

NAMES = marbler_jax.registered()


MARBLER = ["arctic_transport", "material_transport", "predator_capture_prey", "simple_navigation", "warehouse"]


@pytest.fixture(scope="module", params=NAMES)
def env(request):
    return marbler_jax.make(request.param)


@pytest.fixture(scope="module", params=slow_unless(NAMES, MARBLER))
def env_core(request):
    """MARBLER's scenarios in the default run; the others (the same core code path) under ``-m slow``."""
    return marbler_jax.make(request.param)


def test_registry_and_sizes():
    assert NAMES == sorted(["simple_navigation", "predator_capture_prey", "warehouse", "material_transport",
                            "arctic_transport", "discovery", "foraging", "rware"])
    sizes = {n: (marbler_jax.make(n).num_agents, marbler_jax.make(n).obs_dim, marbler_jax.make(n).num_actions)
             for n in NAMES}
    # MARBLER's layouts: Simple 2(N+1); PCP 4 x 4; Warehouse 3 x 6; MT 9 (N = 4); AT 30
    assert sizes == {"simple_navigation": (4, 10, 5), "predator_capture_prey": (4, 16, 5), "warehouse": (6, 18, 5),
                     "material_transport": (4, 9, 20), "arctic_transport": (4, 30, 5),
                     # JaxRobotarium's layouts: 3N + 3L + 2N; 3N + 3R + N; 3N + 1 + 3C + N
                     "discovery": (4, 38, 5), "foraging": (3, 18, 5), "rware": (3, 31, 5)}
    assert marbler_jax.make("PredatorCapturePrey").name == "predator_capture_prey"  # MARBLER alias


def test_zero_collisions_and_no_nan_over_random_episodes(env):
    """Default settings (safe CBF, control every tick): random policies never collide (256 envs, each
    running its episodes for one episode length)."""
    _random_episodes_are_safe(env, 256)


@pytest.mark.slow     # the same check over 16x the episodes
def test_zero_collisions_and_no_nan_over_thousands_of_random_episodes(env):
    _random_episodes_are_safe(env, 4096)


def _random_episodes_are_safe(env, num_envs):
    rollout = make_rollout(env, num_envs, env.max_steps)
    state, (rewards, done, info) = rollout(jax.random.PRNGKey(7))
    episodes = int(done.sum()) + int((~done[-1]).sum())  # finished + the ones still running
    assert episodes >= num_envs
    assert int(info["collisions"].sum()) == 0, f"{env.name}: {int(info['collisions'].sum())} collision steps"
    assert bool(jnp.all(jnp.isfinite(rewards))) and bool(jnp.all(jnp.isfinite(state.poses)))
    # boundary violations stay rare (no boundary barrier in MARBLER's certificate)
    assert float(info["out_of_bounds"].sum()) / num_envs < 0.05


def test_determinism_jit_and_vmap(env_core):
    env = env_core
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    obs, state = jax.jit(jax.vmap(env.reset))(keys)
    actions = jax.random.randint(jax.random.PRNGKey(4), (3, env.num_agents), 0, env.num_actions)
    step = jax.jit(jax.vmap(env.step))
    out_a = step(keys, state, actions)
    out_b = step(keys, state, actions)
    jax.tree_util.tree_map(np.testing.assert_array_equal, out_a, out_b)  # same key -> same result
    # vmap == loop; jit == eager on one scenario (op-by-op dispatch compiles every op of the step, and what
    # it checks -- XLA's fusion keeps the arithmetic -- does not depend on the scenario)
    one = env.step if env.name == "predator_capture_prey" else jax.jit(env.step)
    looped = [one(keys[i], jax.tree_util.tree_map(lambda x: x[i], state), actions[i]) for i in range(3)]
    for i in range(3):
        np.testing.assert_allclose(out_a[0][i], looped[i][0], atol=1e-5)
        np.testing.assert_allclose(out_a[1].poses[i], looped[i][1].poses, atol=1e-5)
        np.testing.assert_allclose(out_a[2][i], looped[i][2], atol=1e-5)
        assert bool(out_a[3][i]) == bool(looped[i][3])
    obs2, _ = jax.jit(jax.vmap(env.reset))(keys)
    np.testing.assert_array_equal(obs, obs2)
    assert obs.dtype == jnp.float32 and obs.shape == (3, env.num_agents, env.obs_dim)


def test_done_exactly_after_max_episode_steps_plus_one(env):
    """With violations off and robots idle, the episode lasts max_episode_steps + 1 steps."""
    quiet = marbler_jax.make(env.name, penalize_violations=False)
    idle = jnp.full((quiet.num_agents,), 4 if quiet.num_actions == 5 else 16, jnp.int32)  # no_action
    step = jax.jit(quiet.step)
    obs, state = quiet.reset(jax.random.PRNGKey(0))
    for t in range(quiet.max_steps):
        key = jax.random.PRNGKey(t + 1)
        obs, state, rewards, done, info = step(key, state, idle)
        assert bool(done) == (t == quiet.max_steps - 1), f"{env.name}: done={bool(done)} at step {t + 1}"
    # auto-reset: the info describes the finished episode, the state is a new episode
    assert bool(info["returned_episode"]) and int(info["steps"]) == quiet.max_steps
    assert int(state.step) == 0 and float(state.episode_return) == 0.0
    new_obs, _ = quiet.reset(jax.random.split(jax.random.PRNGKey(quiet.max_steps))[1])
    np.testing.assert_allclose(obs, new_obs)


def test_violation_ends_episode_with_penalty():
    env = marbler_jax.make("simple_navigation", barrier_certificate="none")
    # two robots placed nose to nose: the first tick's check sees the collision
    obs, state = env.reset(jax.random.PRNGKey(0))
    poses = state.poses.at[1, :2].set(state.poses[0, :2] + jnp.array([0.1, 0.0]))
    state = state.replace(poses=poses)
    _, next_state, rewards, done, info = env.step_env(jax.random.PRNGKey(1), state, jnp.zeros(4, jnp.int32))
    assert bool(done) and bool(info["collisions"]) and bool(info["violation"])
    np.testing.assert_allclose(rewards, -5.0)
    assert int(info["steps"]) == 1


@pytest.mark.parametrize("bad", [np.nan, np.inf, 1e20, -1e6])
def test_a_non_finite_pose_is_a_violation_and_the_others_still_move_safely(bad):
    """A robot whose position is not finite, or finite but far outside the arena (1e20 m squared overflows
    float32), is out of bounds at the step's first tick: the episode ends with the violation reward, and the
    barrier certified the other robots without it."""
    env = marbler_jax.make("predator_capture_prey", control_period=1)
    _, state = env.reset(jax.random.PRNGKey(0))
    state = state.replace(poses=state.poses.at[2, 0].set(bad))
    _, _, rewards, done, info = jax.jit(env.step_env)(jax.random.PRNGKey(1), state, jnp.zeros(env.num_agents, jnp.int32))
    assert bool(done) and bool(info["out_of_bounds"]) and bool(info["violation"])
    np.testing.assert_allclose(rewards, env.scenario.violation_reward)
    goals = env.scenario.goals(state.poses, state.scenario, jnp.zeros(env.num_agents, jnp.int32))
    velocities = env.velocities(state.poses, goals)
    assert np.all(np.isfinite(velocities)) and not np.any(velocities[2])


def test_capture_reward_and_termination_pcp():
    env = marbler_jax.make("predator_capture_prey", num_prey=1, barrier_certificate="none")
    obs, state = env.reset(jax.random.PRNGKey(0))
    prey = jnp.array([[0.0, 0.0]])
    # predator 0 on the prey (senses it), capture robot 2 next to it choosing "no_action" (captures)
    poses = state.poses.at[0, :2].set(jnp.array([0.0, 0.3])).at[2, :2].set(jnp.array([0.1, -0.05]))
    state = state.replace(poses=poses, scenario=state.scenario.replace(prey=prey))
    actions = jnp.array([4, 1, 4, 1])
    _, nxt, rewards, done, info = env.step_env(jax.random.PRNGKey(1), state, actions)
    np.testing.assert_allclose(rewards, 1 + 5 - 0.05, atol=1e-6)  # sensed and captured in one step
    assert bool(done) and int(info["prey_left"]) == 0


@pytest.mark.parametrize("bad, message", [
    (dict(unknown_key=1), "unknown config key"),
    (dict(max_episode_steps=0), "max_episode_steps must be a positive integer"),
    (dict(max_episode_steps=2.5), "max_episode_steps must be an integer"),
    (dict(barrier_certificate="strong"), "barrier_certificate='strong' is not one of"),
    (dict(physics="rps1999"), "unknown physics preset 'rps1999'"),
    (dict(predator=20), "cannot place 22 robots"),
    (dict(x_min=-2.0), "waypoint box"),
    (dict(UP=-0.5), r"unknown config key\(s\) \['UP'\] for PredatorCapturePreyConfig \(UP is y_min here\)"),
    (dict(penalize_violations="yes"), "penalize_violations must be true or false"),
    (dict(cbf_relaxation=2.0), r"cbf_relaxation=2.0 must lie in \(0, 2\)"),
    (dict(cbf_iterations=0), "cbf_iterations must be a positive integer"),
])
def test_bad_config_is_rejected_clearly(bad, message):
    with pytest.raises(ValueError, match=message):
        marbler_jax.make("predator_capture_prey", **bad)


def test_bad_scenario_and_actions_are_rejected_clearly():
    with pytest.raises(ValueError, match=r"unknown scenario 'pacman'; registered scenarios: \['arctic_transport'"):
        marbler_jax.make("pacman")
    env = marbler_jax.make("simple_navigation")
    obs, state = env.reset(jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match=r"actions must have shape \(4,\)"):
        env.step(jax.random.PRNGKey(0), state, jnp.zeros(3, jnp.int32))
    with pytest.raises(ValueError, match=r"actions must be in \[0, 5\), got \[0, 7, 0, 0\]"):
        env.step(jax.random.PRNGKey(0), state, jnp.array([0, 7, 0, 0]))
    with pytest.raises(ValueError, match="must be integers"):
        env.step(jax.random.PRNGKey(0), state, jnp.zeros(4))


def test_barrier_sweeps_and_relaxation_follow_the_config():
    """Defaults from control_loop (the env's 1.5 for every team size, not the golden cases' 1.7 that
    cbf uses above 10 robots); explicit cbf_iterations / cbf_relaxation reach the solver unchanged."""
    cases = [(dict(), 4, 6), (dict(control_period=15), 4, 12),
             (dict(n_agents=20, start_dist=0.3), 20, 10), (dict(n_agents=20, start_dist=0.3, control_period=15), 20, 20)]
    for overrides, n, sweeps in cases:
        env = marbler_jax.make("warehouse", **{"n_agents": 4, **overrides})
        assert env.num_agents == n and env.barrier.iterations == sweeps, (overrides, env.barrier.iterations)
        assert env.barrier.omega(n) == control_loop.ENV_RELAXATION == 1.5
    env = marbler_jax.make("warehouse", n_agents=20, start_dist=0.3, cbf_iterations=7, cbf_relaxation=1.2)
    assert (env.barrier.iterations, env.barrier.omega(20)) == (7, 1.2)
    assert cbf.make_barrier("si2").omega(20) == 1.7


def test_spawn_sampler_is_uniform_over_ordered_cells():
    from marbler_jax.scenarios.base import distinct_indices

    draws = np.asarray(jax.jit(jax.vmap(lambda k: distinct_indices(k, 3, 6)))(
        jax.random.split(jax.random.PRNGKey(0), 60000)))
    assert all(len(set(row)) == 3 for row in draws)
    # every ordered triple of distinct cells (120 of them) equally likely: chi-square, 119 dof
    codes = draws[:, 0] * 36 + draws[:, 1] * 6 + draws[:, 2]
    counts = np.bincount(codes, minlength=216)
    observed = counts[counts > 0]
    assert len(observed) == 120
    expected = len(draws) / 120
    chi2 = float(((observed - expected) ** 2 / expected).sum())
    assert chi2 < 180, chi2  # p ~ 3e-4 under uniformity


def test_barrier_warm_start_carries_multipliers_and_tracks_the_exact_qp():
    """At control period 1 the barrier is warm-started from the last refresh (state.cbf_multipliers:
    zero at reset, zeroed again by auto-reset); with its few default sweeps the closed loop follows the
    200-sweep solution to ~1 mm over 20 steps, where as many cold sweeps drift by centimetres."""
    env = marbler_jax.make("predator_capture_prey")
    assert env.config.warm_start_barrier and env.barrier.iterations == 6
    assert marbler_jax.make("predator_capture_prey", control_period=15).reset(jax.random.PRNGKey(0))[1].cbf_multipliers is None
    assert marbler_jax.make("predator_capture_prey", barrier_certificate="none").initial_multipliers() is None
    with pytest.raises(ValueError, match=r"cbf_warm_start must be true or false, got 'yes' \(or None for the default\)"):
        marbler_jax.make("predator_capture_prey", cbf_warm_start="yes")
    _, state = env.reset(jax.random.PRNGKey(0))
    assert state.cbf_multipliers.pairs.shape == (3, 2) and not np.any(state.cbf_multipliers.pairs)

    def rollout(env, batch=64, steps=20):
        def run(key):
            keys = jax.random.split(key, batch)
            _, state = jax.vmap(env.reset)(keys)

            def body(state, k):
                k_act, k_step = jax.random.split(k)
                actions = jax.random.randint(k_act, (batch, env.num_agents), 0, env.num_actions)
                _, state, _, done, _ = jax.vmap(env.step_env)(jax.random.split(k_step, batch), state, actions)
                return state, (state.poses, done, state.cbf_multipliers)
            return jax.lax.scan(body, state, jax.random.split(key, steps))[1]
        return jax.jit(run)(jax.random.PRNGKey(1))

    poses, done, multipliers = rollout(env)
    exact, exact_done, _ = rollout(marbler_jax.make("predator_capture_prey", cbf_iterations=200, cbf_warm_start=False))
    cold, _, _ = rollout(marbler_jax.make("predator_capture_prey", cbf_iterations=6, cbf_warm_start=False))
    assert float(jnp.max(multipliers.pairs)) > 0
    np.testing.assert_array_equal(done, exact_done)
    warm_drift = float(jnp.abs(poses - exact)[..., :2].max())
    cold_drift = float(jnp.abs(cold - exact)[..., :2].max())
    assert warm_drift < 5e-3 < cold_drift, (warm_drift, cold_drift)
    # auto-reset starts the next episode cold
    state = jax.tree_util.tree_map(lambda x: x[-1, 0], multipliers)
    _, s = env.reset(jax.random.PRNGKey(2))
    s = s.replace(cbf_multipliers=state, step=jnp.int32(env.config.max_episode_steps))
    _, after, _, done, _ = env.step(jax.random.PRNGKey(3), s, jnp.zeros(env.num_agents, jnp.int32))
    assert bool(done) and not np.any(after.cbf_multipliers.pairs)


@pytest.mark.parametrize("finished", [5, 40])
def test_batched_auto_reset_resets_exactly_the_finished_envs(finished):
    """A batch resets only its finished envs when few finished (<= 1/16) and resets all otherwise; both
    paths equal stepping without auto-reset, then ``reset(key_reset)`` where done."""
    env = marbler_jax.make("predator_capture_prey", control_period=15)
    batch = 128
    keys = jax.random.split(jax.random.PRNGKey(5), batch)
    _, state = jax.jit(jax.vmap(env.reset))(keys)
    ending = np.zeros(batch, bool)
    ending[np.random.default_rng(finished).choice(batch, finished, replace=False)] = True
    state = state.replace(step=jnp.where(ending, env.config.max_episode_steps, 3).astype(jnp.int32))
    actions = jax.random.randint(jax.random.PRNGKey(6), (batch, env.num_agents), 0, env.num_actions)
    step_keys = jax.random.split(jax.random.PRNGKey(7), batch)
    obs, new_state, rewards, done, info = jax.jit(jax.vmap(env.step))(step_keys, state, actions)

    def reference(key, state, actions):
        key_step, key_reset = jax.random.split(key)
        obs, state, rewards, done, info = env.step_env(key_step, state, actions)
        reset_obs, reset_state = env.reset(key_reset)
        state = jax.tree_util.tree_map(lambda r, s: jnp.where(done, r, s), reset_state, state)
        return jnp.where(done, reset_obs, obs), state, done

    ref_obs, ref_state, ref_done = jax.jit(jax.vmap(reference))(step_keys, state, actions)
    np.testing.assert_array_equal(done, ref_done)
    assert int(done.sum()) >= finished
    assert (int(done.sum()) <= batch // 16) == (finished == 5)   # each case takes the path it is meant to
    np.testing.assert_allclose(obs, ref_obs, atol=1e-6)
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, b, atol=1e-6), new_state, ref_state)
    np.testing.assert_array_equal(new_state.step, np.where(done, 0, state.step + 1))


def test_robotarium_setting_picks_physics_and_barrier_together():
    v2 = marbler_jax.make("predator_capture_prey", robotarium="v2")
    assert (v2.config.physics, v2.config.barrier_certificate) == ("robotarium", "safe_v2")
    assert v2.barrier.kind == "si_v2" and v2.barrier.safety_radius == 0.2
    old = marbler_jax.make("predator_capture_prey", robotarium="2023")
    assert (old.config.physics, old.config.barrier_certificate, old.barrier.kind) == ("marbler", "safe", "si2")
    default = marbler_jax.make("predator_capture_prey")
    assert default.config.robotarium is None and default.barrier.kind == "si2"
    # the same value given twice is fine; a contradiction or an unknown simulator is one clear error
    marbler_jax.make("predator_capture_prey", robotarium="v2", physics="robotarium")
    with pytest.raises(ValueError, match="robotarium='v2' uses physics='robotarium', but physics='marbler'"):
        marbler_jax.make("predator_capture_prey", robotarium="v2", physics="marbler")
    with pytest.raises(ValueError, match="robotarium='2024' is not one of"):
        marbler_jax.make("predator_capture_prey", robotarium="2024")


def test_v2_env_stops_a_team_the_certificate_cannot_make_safe():
    # Two robots of a v2 env placed 5 mm apart: separating them as fast as the radius demands takes
    # 0.64 m/s, beyond the 0.2 m/s rows, so rps v2's QP has no solution and no robot of the team moves
    # this refresh; the same placement under MARBLER's certificate is pushed apart instead.
    poses = jnp.array([[0.0, 0.0, 0.0], [0.005, 0.0, 0.0], [1.0, 0.5, 0.0], [-1.0, -0.5, 0.0]])
    goals = jnp.array([[0.5, 0.0], [0.5, 0.0], [1.2, 0.5], [-1.2, -0.5]])
    v2 = marbler_jax.make("predator_capture_prey", robotarium="v2")
    np.testing.assert_array_equal(control_loop.control(poses, goals, v2.barrier), 0.0)
    old = marbler_jax.make("predator_capture_prey")
    assert float(jnp.abs(control_loop.control(poses, goals, old.barrier)).max()) > 0


def test_barrier_radius_is_a_config_field():
    assert marbler_jax.make("warehouse").barrier.safety_radius == control_loop.MARBLER_SAFETY_RADIUS
    assert marbler_jax.make("warehouse", cbf_safety_radius=0.25).barrier.safety_radius == 0.25
    assert marbler_jax.make("warehouse", barrier_certificate="si").barrier.safety_radius == 0.17   # rps default
    with pytest.raises(ValueError, match="cbf_safety_radius=-0.1 must lie in"):
        marbler_jax.make("warehouse", cbf_safety_radius=-0.1)


@pytest.mark.parametrize("barrier, period", [("safe", 1), ("safe", 15), ("none", 1), ("safe_v2", 1)])
def test_batch_minor_tick_loop_matches_the_per_refresh_reference(barrier, period):
    """``run_ticks`` (one batch-minor loop, the heading carried as a unit vector) against the loop
    spelled out from the public pieces: controller + barrier (``env.velocities``) at every refresh,
    then ``physics.held_ticks`` for the refresh's ticks, stopping at a violation."""
    from marbler_jax import physics

    env = marbler_jax.make("material_transport", barrier_certificate=barrier, control_period=period)
    keys = jax.random.split(jax.random.PRNGKey(4), 32)
    _, state = jax.jit(jax.vmap(env.reset))(keys)
    actions = jax.random.randint(jax.random.PRNGKey(5), (32, env.num_agents), 0, env.num_actions)
    goals = jax.vmap(env.scenario.goals)(state.poses, state.scenario, actions)
    poses, collided, outside, dist, _ = jax.jit(jax.vmap(env.run_ticks))(state.poses, goals)

    def reference(pose, goal):
        def refresh(carry, ticks):
            pose, stopped, hit_any, out_any, moved = carry
            new, hit, out, d = physics.held_ticks(env.params, pose, env.velocities(pose, goal), ticks)
            return (jnp.where(stopped, pose, new), stopped | hit | out, hit_any | (~stopped & hit),
                    out_any | (~stopped & out), moved + jnp.where(stopped, 0, d))

        full, rest = divmod(env.config.update_frequency, period)
        false = jnp.bool_(False)
        carry = jax.lax.scan(lambda c, _: (refresh(c, period), None), (pose, false, false, false,
                                                                        jnp.zeros(env.num_agents)), length=full)[0]
        pose, _, hit_any, out_any, moved = refresh(carry, rest) if rest else carry
        return pose, hit_any, out_any, moved

    ref_poses, ref_hit, ref_out, ref_dist = jax.jit(jax.vmap(reference))(state.poses, goals)
    np.testing.assert_allclose(poses[..., :2], ref_poses[..., :2], atol=2e-5)
    np.testing.assert_allclose(np.cos(poses[..., 2] - ref_poses[..., 2]), 1, atol=1e-8)
    np.testing.assert_array_equal(collided, ref_hit)
    np.testing.assert_array_equal(outside, ref_out)
    np.testing.assert_allclose(dist, ref_dist, atol=2e-5)
    assert float(jnp.abs(poses[..., :2] - state.poses[..., :2]).max()) > 0.05    # the robots moved


SPLIT_ROLLOUT = """
import jax
jax.config.update("jax_num_cpu_devices", 2)
import numpy as np
import marbler_jax
from marbler_jax.rollout import make_rollout

env = marbler_jax.make("simple_navigation", control_period=1)
key = jax.random.PRNGKey(3)
state, traj = make_rollout(env, 8, 5, devices=2)(key)
for i, k in enumerate(jax.random.split(key, 2)):      # each device's share is a one-device rollout from its key
    s, t = make_rollout(env, 4, 5)(k)
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_array_equal(a[4 * i:4 * i + 4], b), state, s)
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_array_equal(a[:, 4 * i:4 * i + 4], b), traj, t)
for bad, match in ((dict(num_envs=7, devices=2), "num_envs=7 must be divisible by devices=2"),
                   (dict(num_envs=8, devices=3), "devices=3 but JAX has 2 cpu device"),
                   (dict(num_envs=8, devices=0), "devices must be an integer >= 1, got 0"),
                   (dict(num_envs=8, devices=True), "devices must be an integer >= 1, got True")):
    try:
        make_rollout(env, num_steps=5, **bad)
    except ValueError as error:
        assert match in str(error), error
    else:
        raise AssertionError(bad)
print("ok")
"""


def test_a_rollout_split_over_devices_runs_each_share_like_one_device():
    """``make_rollout(..., devices=2)`` (two CPU devices, set before JAX first runs: a fresh interpreter)."""
    run_with_two_devices(SPLIT_ROLLOUT)


def test_a_protocol_replaces_the_settings_it_decides():
    """``merge_settings``: ``--protocol`` on top of a recipe's or a saved run's settings replaces what the
    protocol decides; another override on a protocol run changes only that setting."""
    import dataclasses

    from marbler_jax.scenarios.base import merge_settings

    def config(base, overrides):
        c = marbler_jax.make("predator_capture_prey", **merge_settings(base, overrides)).config
        return c.physics, c.control_period, c.zero_reset_obs, c.barrier_certificate

    marbler_run = dataclasses.asdict(marbler_jax.make("predator_capture_prey", protocol="marbler").config)
    robots_run = dataclasses.asdict(marbler_jax.make("predator_capture_prey").config)
    v2_run = dataclasses.asdict(marbler_jax.make("predator_capture_prey", robotarium="v2").config)
    assert config({"control_period": 1}, {"protocol": "marbler"}) == ("marbler", 15, True, "safe")
    assert config(robots_run, {"protocol": "marbler"}) == ("marbler", 15, True, "safe")
    assert config(marbler_run, {"protocol": "robots"}) == ("robotarium", 1, False, "safe")
    assert config(v2_run, {"protocol": "robots"}) == ("robotarium", 1, False, "safe_v2")
    assert config(marbler_run, {"control_period": 1}) == ("marbler", 1, True, "safe")     # the loop alone
    assert config({"protocol": "marbler"}, {"physics": "robotarium"}) == ("robotarium", 15, True, "safe")
    with pytest.raises(ValueError, match="protocol='robots' uses physics='robotarium', but physics='marbler'"):
        marbler_jax.make("predator_capture_prey", protocol="robots", physics="marbler")
