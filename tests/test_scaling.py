"""Teams beyond MARBLER's sizes: 20 robots (the Robotarium's hardware limit) where a scenario makes
sense of it, 50 in simulation, and clear errors where the arena or the task cannot take them."""
from __future__ import annotations

import jax
import pytest

import marbler_jax
from marbler_jax.rollout import episode_stats, make_rollout
from tests.helpers import slow_unless

TWENTY = {
    "simple_navigation": dict(n_agents=20, robot_band_right=0.0),
    "predator_capture_prey": dict(predator=10, capture=10, robot_band_right=0.0),
    "warehouse": dict(n_agents=20, start_dist=0.4),
    "material_transport": dict(n_fast_agents=10, n_slow_agents=10, end_goal_width=1.0, start_dist=0.25),
    "discovery": dict(n_sensing=10, n_tagging=10, agent_area=(1.5, 1.5)),
    "foraging": dict(levels=(1.0, 2.0, 3.0, 4.0) * 5),
}


DEFAULT_RUN = {"material_transport", "discovery"}   # the others are marked slow (same code path, ~9 s each)


@pytest.mark.parametrize("name", slow_unless(sorted(TWENTY), DEFAULT_RUN))
def test_twenty_robots_run_without_collisions(name):
    env = marbler_jax.make(name, max_episode_steps=8, **TWENTY[name])
    assert env.num_agents == 20
    _, traj = make_rollout(env, 8, env.max_steps)(jax.random.PRNGKey(0))
    stats = episode_stats(traj)
    assert stats["episodes"] >= 8 and stats["collision_rate"] == 0.0


def test_observations_keep_their_size_as_the_team_grows():
    # Warehouse observes a fixed number of neighbours (3 x 6 entries), whatever the team's size
    assert {marbler_jax.make("warehouse", n_agents=n, start_dist=0.3).obs_dim for n in (6, 20, 50)} == {3 * 6}


@pytest.mark.slow     # the twenty-robot tests take the same path in the default suite
def test_fifty_robots_in_simulation():
    env = marbler_jax.make("warehouse", n_agents=50, start_dist=0.3, max_episode_steps=2, control_period=15)
    _, traj = make_rollout(env, 2, env.max_steps)(jax.random.PRNGKey(0))
    assert episode_stats(traj)["collision_rate"] == 0.0


@pytest.mark.parametrize("name, overrides, message", [
    ("simple_navigation", dict(n_agents=20), "holds at most 17"),
    ("warehouse", dict(n_agents=51, start_dist=0.2), "number of robots must be in \\[1, 50\\]"),
    ("material_transport", dict(n_fast_agents=10, n_slow_agents=10), "holds at most 5"),
    ("rware", dict(n_agents=13, num_cells=16), "at most 12 robots"),
])
def test_too_many_robots_is_a_clear_error(name, overrides, message):
    with pytest.raises(ValueError, match=message):
        marbler_jax.make(name, **overrides)
