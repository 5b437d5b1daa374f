"""Simple Navigation (MARBLER ``Simple``): every robot drives to one shared goal; dense reward.

Faithful to MARBLER: robots spawn on the rps grid (spacing ``start_dist``) in the left band
``[x_min, robot_band_right]`` facing +x; the goal spawns on a ``step_dist`` grid in the right
band ``[goal_band_left, x_max]``. Observation ``[own x, own y, (x, y) of every other robot in
index order, goal x, goal y]`` (``2 (N + 1)``). Reward per robot ``-reward_scaler * |p_i - goal|^2``
(individual); a penalized violation gives every robot -5 and ends the episode. Reaching the goal does
not end the episode (``max_episode_steps + 1`` = 51 steps).

Deviation (bug fix): ``reset`` returns the real first observation (MARBLER returns zeros; set
``zero_reset_obs=True`` to reproduce that).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from marbler_jax.xp import namespace
from marbler_jax.scenarios.base import BandSpawnConfig, Scenario, nearest_others, spawn_band


@dataclasses.dataclass(frozen=True)
class SimpleConfig(BandSpawnConfig):
    """Simple Navigation settings (MARBLER's names; the goal spawns in the right band).

    Attributes:
        n_agents: robots.
        reward_scaler: each robot's reward is ``-reward_scaler`` times its squared distance to the goal.
    """

    n_agents: int = 4
    x_min: float = -1.45
    x_max: float = 1.45
    reward_scaler: float = 0.1
    max_episode_steps: int = 50
    update_frequency: int = 29

    def validate(self) -> None:
        super().validate()
        if self.n_agents < 1:
            raise ValueError(f"n_agents must be >= 1, got {self.n_agents}")
        self.check_bands("simple_navigation", self.n_agents, 1, "goals")


@struct.dataclass
class SimpleState:
    goal: jax.Array  # [2]


class SimpleNavigation(Scenario):
    name = "simple_navigation"
    Config = SimpleConfig
    violation_reward = -5.0
    shared_reward = False

    @property
    def num_agents(self) -> int:
        return self.config.n_agents

    @property
    def obs_dim(self) -> int:
        return 2 * (self.num_agents + 1)

    def reset(self, key):
        k_robots, k_goal = jax.random.split(key)
        xy = spawn_band(k_robots, self.num_agents, self.config, self.config.start_dist, left=True)
        poses = jnp.concatenate([xy, jnp.zeros((self.num_agents, 1), jnp.float32)], axis=-1)
        goal = spawn_band(k_goal, 1, self.config, self.config.step_dist, left=False)[0]
        return poses, SimpleState(goal=goal)

    def update(self, poses, state, actions):
        xp = namespace(poses)
        d = poses[..., :2] - state.goal[..., None, :]
        rewards = -self.config.reward_scaler * xp.sum(d * d, axis=-1)
        return state, rewards, xp.zeros(rewards.shape[:-1], dtype=bool)

    def render_layers(self, state):
        return [{"kind": "points", "xy": state.goal, "marker": "*", "size": 160, "color": "gold"}]

    def observe(self, poses, state):
        xp = namespace(poses)
        n = self.num_agents
        xy = poses[..., :2]
        others = xy[..., nearest_others(poses, n - 1), :].reshape(xy.shape[:-2] + (n, 2 * (n - 1)))
        goal = xp.broadcast_to(state.goal[..., None, :], xy.shape[:-2] + (n, 2))
        return xp.concatenate([xy, others, goal], axis=-1)
