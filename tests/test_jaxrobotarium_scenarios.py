"""Discovery, Foraging and RWARE: reward / termination rules on hand-built states, and the bug fixes."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import marbler_jax

STAY = 4


def _place(env, key, xy, **scenario):
    """A reset state with robots at ``xy`` (headings kept) and scenario fields replaced."""
    _, state = env.reset(jax.random.PRNGKey(key))
    poses = state.poses.at[:, :2].set(jnp.asarray(xy, jnp.float32))
    return state.replace(poses=poses, scenario=state.scenario.replace(
        **{k: jnp.asarray(v) for k, v in scenario.items()}))


def _quiet(name, **overrides):
    """One tick per step, no barrier: robots barely move, so rules are tested at known positions."""
    return marbler_jax.make(name, update_frequency=1, barrier_certificate="none", **overrides)


def test_discovery_sensing_tagging_and_time_penalty():
    env = _quiet("discovery", num_landmarks=2)
    marks = [[0.0, 0.0], [1.0, 0.5]]
    # sensing robot 0 at 0.3 of landmark 0 (< 0.45), tagging robot 2 at 0.1 of landmark 1 (< 0.25)
    state = _place(env, 0, [[0.3, 0.0], [-1.0, -0.6], [1.1, 0.5], [-1.0, 0.6]], landmarks=marks,
                   sensed=[False, False], tagged=[False, False])
    obs, nxt, rewards, done, info = env.step_env(None, state, jnp.full(4, STAY, jnp.int32))
    np.testing.assert_allclose(rewards, 1 + 5 - 0.05, atol=1e-6)        # tagging needs no prior sensing
    assert list(np.asarray(nxt.scenario.sensed)) == [True, False] and list(np.asarray(nxt.scenario.tagged)) == [False, True]
    assert not bool(done) and int(info["landmarks_left"]) == 1
    # every agent sees the sensed landmark (team knowledge); the unsensed one stays hidden
    np.testing.assert_allclose(obs[:, 12:15], np.tile([0.0, 0.0, 0.0], (4, 1)), atol=1e-6)
    np.testing.assert_allclose(obs[:, 15:18], -5.0)
    # capability block: own row first, then the others in cyclic order
    np.testing.assert_allclose(obs[2, 18:], [0, 0.25, 0, 0.25, 0.45, 0, 0.45, 0], atol=1e-6)
    # tagging the last landmark: no time penalty, and with terminate_on_success the episode ends
    ender = _quiet("discovery", num_landmarks=2, terminate_on_success=True)
    last = nxt.replace(poses=nxt.poses.at[3, :2].set(jnp.array([0.1, 0.0])))
    _, _, rewards, done, info = ender.step_env(None, last, jnp.full(4, STAY, jnp.int32))
    np.testing.assert_allclose(rewards, 5.0, atol=1e-6)
    assert bool(done) and int(info["landmarks_left"]) == 0


def test_discovery_radii_are_strict():
    env = marbler_jax.make("discovery", num_landmarks=1)
    _, state = env.reset(jax.random.PRNGKey(1))
    scenario = state.scenario.replace(landmarks=np.zeros((1, 2), np.float32), sensed=np.zeros(1, bool),
                                      tagged=np.zeros(1, bool))
    for gap, sensed in ((0.45, False), (0.4499, True)):   # numpy inputs: the same code the bundle runs
        poses = np.array([[gap, 0, 0], [-1, -0.6, 0], [-1, 0, 0], [-1, 0.6, 0]], np.float64)
        new, _, _ = env.scenario.update(poses, scenario, np.full(4, STAY))
        assert bool(new.sensed[0]) == sensed, gap


def test_foraging_levels_collection_and_fixed_time_penalty():
    env = _quiet("foraging")
    for seed in range(6):                       # resource levels: {6, 5} in random order
        _, state = env.reset(jax.random.PRNGKey(seed))
        assert sorted(np.asarray(state.scenario.level).tolist()) == [5.0, 6.0]
    res = [[0.0, 0.0], [1.0, 0.5]]
    # level-1 robot alone at the level-5 resource: nothing; the time penalty fires (the JaxRobotarium bug)
    state = _place(env, 0, [[0.1, 0.0], [-1.0, -0.6], [-1.0, 0.6]], resources=res, level=[5.0, 6.0])
    _, nxt, rewards, done, info = env.step_env(None, state, jnp.full(3, STAY, jnp.int32))
    np.testing.assert_allclose(rewards, -0.01, atol=1e-6)
    assert int(info["resources_left"]) == 2
    # levels 2 + 3 at the level-5 resource: collected (+5), one resource left (-0.01)
    state = _place(env, 0, [[-1.0, -0.6], [0.1, 0.0], [0.0, 0.15]], resources=res, level=[5.0, 6.0])
    obs, nxt, rewards, done, info = env.step_env(None, state, jnp.full(3, STAY, jnp.int32))
    np.testing.assert_allclose(rewards, 5 - 0.01, atol=1e-6)
    assert np.asarray(nxt.scenario.level).tolist() == [-1.0, 6.0] and int(info["resources_left"]) == 1
    np.testing.assert_allclose(obs[0, 9:15], [0.0, 0.0, -1.0, 1.0, 0.5, 6.0], atol=1e-6)   # resources in obs
    np.testing.assert_allclose(obs[1, 15:], [2.0, 3.0, 1.0])                                # levels, cyclic
    # all three at the level-6 resource: +6 and no time penalty once everything is collected
    last = nxt.replace(poses=nxt.poses.at[:, :2].set(jnp.array([[1.0, 0.6], [1.1, 0.5], [0.9, 0.45]])))
    _, _, rewards, done, info = env.step_env(None, last, jnp.full(3, STAY, jnp.int32))
    np.testing.assert_allclose(rewards, 6.0, atol=1e-6)
    assert int(info["resources_left"]) == 0 and not bool(done)           # no early end by default


def test_foraging_scripted_team_collects_everything_under_the_certificate():
    """The whole env (controller, barrier, episode end on violations) lets a team forage: three robots
    that all drive to the open resource of the highest level collect both in every episode, so a policy
    that learns less is a learning problem, not an impossible task."""
    env = marbler_jax.make("foraging")

    def scripted(state):
        target = state.scenario.resources[jnp.argmax(state.scenario.level)]
        d = target[None, :] - state.poses[:, :2]
        along_x = jnp.abs(d[:, 0]) >= jnp.abs(d[:, 1])
        move = jnp.where(along_x, jnp.where(d[:, 0] > 0, 1, 0), jnp.where(d[:, 1] > 0, 3, 2))  # MARBLER order
        return jnp.where(jnp.hypot(d[:, 0], d[:, 1]) < 0.12, STAY, move)

    def episode(key):
        _, state = env.reset(key)

        def step(state, _):
            _, state, _, _, info = env.step_env(None, state, scripted(state))
            return state, info["collisions"] | info["out_of_bounds"]

        state, violations = jax.lax.scan(step, state, None, env.config.max_episode_steps)
        return state.scenario.level, violations

    level, violations = jax.jit(jax.vmap(episode))(jax.random.split(jax.random.PRNGKey(0), 32))
    assert not np.asarray(violations).any()
    assert (np.asarray(level) == -1).all()


def test_rware_pickup_takes_the_stored_shelf_and_never_an_empty_cell():
    env = _quiet("rware")
    cells = env.scenario.cells()
    # cell 0 holds shelf 3 (shelves have moved), cell 1 is empty
    grid = [3, -1, 2, 0, 4, 5]
    state = _place(env, 0, [cells[0] + [0.05, 0.0], cells[1] + [0.05, 0.0], [1.0, -0.75]], grid=grid,
                   payload=[-1, -1, -1])
    _, nxt, rewards, _, info = env.step_env(None, state, jnp.array([STAY, STAY, STAY]))
    assert np.asarray(nxt.scenario.payload).tolist() == [3, -1, -1]          # the shelf id, not the cell index
    assert np.asarray(nxt.scenario.grid).tolist() == [-1, -1, 2, 0, 4, 5]    # nothing from the empty cell
    np.testing.assert_allclose(rewards, 0.0)
    # without the toggle action nothing is picked up
    _, nxt2, _, _, _ = env.step_env(None, state, jnp.array([1, 1, 1]))
    assert np.asarray(nxt2.scenario.payload).tolist() == [-1, -1, -1]


def test_rware_delivery_replaces_the_request_and_put_down_needs_an_empty_cell():
    env = _quiet("rware")
    cells = env.scenario.cells()
    state = _place(env, 0, [[1.3, 0.0], cells[1] + [0.05, 0.0], cells[2] + [0.05, 0.0]],
                   grid=[0, -1, 2, 3, 4, 5], payload=[1, 0, 5], requests=[1, 4, 2])
    _, nxt, rewards, _, info = env.step_env(None, state, jnp.array([STAY, STAY, STAY]))
    np.testing.assert_allclose(rewards, 1.0)                                 # robot 0 delivered shelf 1
    requests = np.asarray(nxt.scenario.requests).tolist()
    assert requests[1:] == [4, 2] and requests[0] not in (1, 4, 2)           # replaced, not the delivered one
    payload = np.asarray(nxt.scenario.payload).tolist()
    assert payload[0] == 1                                                   # keeps the shelf to put back
    assert payload[1] == -1 and np.asarray(nxt.scenario.grid)[1] == 0        # put down into the empty cell 1
    assert payload[2] == 5 and np.asarray(nxt.scenario.grid)[2] == 2         # cell 2 is occupied: kept
    assert int(info["deliveries"]) == 1


def test_rware_carrying_robot_cannot_drive_through_a_shelf():
    env = _quiet("rware")
    cells = env.scenario.cells()
    below = cells[3] + [0.0, -0.2]                                           # just below an occupied cell
    state = _place(env, 0, [below, [1.0, -0.75], [-0.5, -0.75]], payload=[2, -1, -1])
    up = jnp.array([3, 3, 3])                                                # MARBLER action 3: +y
    goals = env.scenario.goals(state.poses, state.scenario, up)
    np.testing.assert_allclose(goals[0], state.poses[0, :2])                 # blocked: stays
    np.testing.assert_allclose(goals[1], state.poses[1, :2] + jnp.array([0.0, 0.2]), atol=1e-6)
    free = state.replace(scenario=state.scenario.replace(payload=jnp.array([-1, -1, -1])))
    goals = env.scenario.goals(free.poses, free.scenario, up)                # not carrying: moves
    np.testing.assert_allclose(goals[0], free.poses[0, :2] + jnp.array([0.0, 0.2]), atol=1e-6)


@pytest.mark.parametrize("name, bad, message", [
    ("discovery", dict(n_sensing=10, n_tagging=10), "cannot place 20 robots"),
    ("foraging", dict(num_resources=4), "num_resources must be in"),
    ("foraging", dict(levels=(1.0, -2.0)), "levels must be"),
    ("rware", dict(num_cells=5), "even number"),
    ("rware", dict(n_agents=6), "n_agents must be in"),
])
def test_bad_configs_name_the_value(name, bad, message):
    with pytest.raises(ValueError, match=message):
        marbler_jax.make(name, **bad)
