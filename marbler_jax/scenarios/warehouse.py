"""Warehouse (MARBLER ``Warehouse``): repeated colour-coded pickup and delivery under congestion.

Robots with an even index are "green", odd ones "red". Load zones are at the right (``x > 1.5 -
goal_width``): green loads at ``y <= 0``, red at ``y > 0``. Unload zones are at the left
(``x < -1.5 + goal_width``): green unloads at ``y > 0``, red at ``y <= 0``. Per step (post-move
positions, every agent on its own): a loaded agent in its unload zone gets ``unload_reward`` and
becomes unloaded; otherwise an unloaded agent in its load zone gets ``load_reward`` and becomes
loaded. Rewards are individual; -5 to every agent on a penalized violation. Episodes last
``max_episode_steps + 1`` steps (no success termination).

Robots spawn on the rps grid with spacing ``start_dist`` over the waypoint box (random headings).
Observation: local ``[x, y, loaded]`` (``loaded`` as it was before this step's events: MARBLER
builds observations before it applies them) followed by ``num_neighbors`` other agents' local vectors
(all others in index order by default). The agent's colour is not observed (MARBLER relies on
agent-ID one-hots in the learner).

Deviation (bug fix): ``reset`` returns the real first observation (``zero_reset_obs=True`` restores
MARBLER's zeros).
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
from flax import struct

from marbler_jax.xp import namespace
from marbler_jax.scenarios.base import Scenario, ScenarioConfig, check_capacity, grid_positions, nearest_others


@dataclasses.dataclass(frozen=True)
class WarehouseConfig(ScenarioConfig):
    """Warehouse settings (MARBLER's names).

    Attributes:
        n_agents: robots (even indices green, odd red).
        num_neighbors: other robots whose local vectors follow a robot's own in its observation.
        step_dist: waypoint offset of a move action [m].
        start_dist: spacing of the spawn grid [m].
        load_reward: reward of a robot that loads in its load zone.
        unload_reward: reward of a loaded robot that unloads in its unload zone.
        goal_width: depth of the load (right) and unload (left) zones [m].
    """

    n_agents: int = 6
    num_neighbors: int = 5
    step_dist: float = 0.2
    start_dist: float = 0.6
    load_reward: float = 1.0
    unload_reward: float = 3.0
    goal_width: float = 0.5
    max_episode_steps: int = 100
    update_frequency: int = 29

    def validate(self) -> None:
        super().validate()
        if self.n_agents < 1:
            raise ValueError(f"n_agents must be >= 1, got {self.n_agents}")
        if self.num_neighbors < 0:
            raise ValueError(f"num_neighbors must be >= 0, got {self.num_neighbors}")
        if not 0 < self.goal_width < 1.5:
            raise ValueError(f"goal_width must be in (0, 1.5), got {self.goal_width}")
        check_capacity("warehouse", self.n_agents, self.start_dist, self.x_max - self.x_min, self.y_max - self.y_min)


@struct.dataclass
class WarehouseState:
    loaded: jax.Array  # [N] bool


class Warehouse(Scenario):
    name = "warehouse"
    Config = WarehouseConfig
    violation_reward = -5.0
    shared_reward = False

    @property
    def num_agents(self) -> int:
        return self.config.n_agents

    @property
    def neighbors(self) -> int:
        return min(self.config.num_neighbors, self.num_agents - 1)

    @property
    def obs_dim(self) -> int:
        return 3 * (self.neighbors + 1)

    def reset(self, key):
        c = self.config
        k_pos, k_theta = jax.random.split(key)
        xy = grid_positions(k_pos, self.num_agents, c.start_dist, c.x_max - c.x_min, c.y_max - c.y_min)
        shift = jnp.array([(1.5 + c.x_min) / 2 - (1.5 - c.x_max) / 2, -(1 + c.y_min) / 2 + (1 - c.y_max) / 2], jnp.float32)
        theta = jax.random.uniform(k_theta, (self.num_agents, 1), jnp.float32) * 2 * math.pi - math.pi
        poses = jnp.concatenate([xy + shift, theta], axis=-1)
        return poses, WarehouseState(loaded=jnp.zeros(self.num_agents, bool))

    def zones(self, poses):
        """Per-agent booleans (in own load zone, in own unload zone)."""
        xp = namespace(poses)
        x, y = poses[..., 0], poses[..., 1]
        edge = 1.5 - self.config.goal_width
        green = xp.asarray([i % 2 == 0 for i in range(self.num_agents)])
        low = y <= 0
        in_load = (x > edge) & xp.where(green, low, ~low)
        in_unload = (x < -edge) & xp.where(green, ~low, low)
        return in_load, in_unload

    def update(self, poses, state, actions):
        xp = namespace(poses)
        c = self.config
        in_load, in_unload = self.zones(poses)
        unload = state.loaded & in_unload
        load = ~state.loaded & in_load
        rewards = xp.where(unload, c.unload_reward, xp.where(load, c.load_reward, 0.0)).astype(poses.dtype)
        loaded = xp.where(unload, False, xp.where(load, True, state.loaded))
        return WarehouseState(loaded=loaded), rewards, xp.zeros((), dtype=bool)

    def observe(self, poses, state):
        xp = namespace(poses)
        local = xp.concatenate([poses[:, :2], state.loaded[:, None].astype(poses.dtype)], axis=-1)
        others = nearest_others(poses, self.neighbors)
        return xp.concatenate([local, local[others].reshape(self.num_agents, -1)], axis=-1)

    def observation_state(self, before, after):
        return before  # MARBLER observes before loading/unloading: the flag shows up one step later

    def render_layers(self, state):
        edge, w = 1.5 - self.config.goal_width, self.config.goal_width
        return [  # green loads right-low / unloads left-high; red the other way round
            {"kind": "rect", "xywh": (edge, -1.0, w + 0.1, 1.0), "color": "green"},
            {"kind": "rect", "xywh": (edge, 0.0, w + 0.1, 1.0), "color": "red"},
            {"kind": "rect", "xywh": (-1.6, 0.0, w + 0.1, 1.0), "color": "green", "alpha": 0.12},
            {"kind": "rect", "xywh": (-1.6, -1.0, w + 0.1, 1.0), "color": "red", "alpha": 0.12},
        ]

    def metrics(self, state):
        xp = namespace(state.loaded)
        return {"loaded": xp.sum(state.loaded)}
