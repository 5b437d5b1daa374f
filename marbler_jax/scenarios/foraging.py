"""Foraging (JaxRobotarium ``foraging``): level-based foraging with robots.

Agents have levels (``levels``, default 1, 2, 3); each resource has a level too. A resource is
collected when the levels of the agents strictly within ``forage_radius`` of it add up to at least
its level; no special action is needed. Collected resources keep their place and show level -1.
Resource levels come from the agents': take the ``R x N`` upper-triangular ones matrix (row r
selects agents r, r+1, ..., N-1), shuffle its rows, and give resource r the summed levels of the
agents its row selects -- with levels (1, 2, 3) and two resources, one needs all three robots and the
other the robots of level 2 and 3 together.

Team reward ``forage_reward * (levels collected this step) + time_penalty * [resources remain after
the step]``. Observation of agent i (``3N + 3R + N``, 18 for the defaults): its pose, the others'
poses in cyclic order (i+1, ..., i-1), every resource's (x, y, level or -1), then the levels of
itself and the others in cyclic order. Reset: agents and resources on distinct points of the
spacing-0.3 grid of the 2.5 x 1.5 m spawn area (agents first), random agent headings.

Bug fix (JaxRobotarium): the time penalty there can never fire (its condition looks for negative
entries in an array that has none); here it is charged on every step while some resource remains,
which is what a time penalty is for. Other choices: ``terminate_on_success`` (default False, as
JaxRobotarium) ends the episode once everything is collected; violations are penalized and end the
episode as in every marbler-jax scenario; actions use MARBLER's order (0 -x, 1 +x, 2 -y, 3 +y, 4 stay).
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
from flax import struct

from marbler_jax.xp import namespace
from marbler_jax.scenarios.base import (JaxRobotariumConfig, Scenario, check_grid_capacity, cyclic_blocks,
                                        sample_grid_points)


@dataclasses.dataclass(frozen=True)
class ForagingConfig(JaxRobotariumConfig):
    """Foraging settings (JaxRobotarium's, with MARBLER's env core).

    Attributes:
        levels: each robot's level (one entry per robot, so its length is the team size).
        num_resources: resources per episode.
        forage_radius: robots strictly closer than this to a resource add their levels to collect it [m].
        forage_reward: team reward per level collected.
        time_penalty: team reward every step while some resource remains.
        terminate_on_success: end the episode once every resource is collected.
        spawn_spacing: spacing of the spawn grid of robots and resources [m].
        spawn_area: (width, height) of the spawn area at the arena's centre [m].
    """

    levels: tuple[float, ...] = (1.0, 2.0, 3.0)
    num_resources: int = 2
    forage_radius: float = 0.3
    forage_reward: float = 1.0
    time_penalty: float = -0.01
    terminate_on_success: bool = False
    spawn_spacing: float = 0.3
    spawn_area: tuple[float, float] = (2.5, 1.5)

    def validate(self) -> None:
        super().validate()
        n = len(self.levels)
        if n < 1 or any(level <= 0 for level in self.levels):
            raise ValueError(f"levels must be one positive number per robot, got {self.levels}")
        if not 1 <= self.num_resources <= n:
            raise ValueError(f"num_resources must be in [1, {n}] (one per robot at most), got {self.num_resources}")
        check_grid_capacity("foraging", n + self.num_resources, self.spawn_spacing, self.spawn_area,
                            "robots and resources")


@struct.dataclass
class ForagingState:
    resources: jax.Array   # [R, 2]
    level: jax.Array       # [R] required level, -1 once collected


class Foraging(Scenario):
    name = "foraging"
    Config = ForagingConfig
    violation_reward = -5.0
    shared_reward = True

    @property
    def num_agents(self) -> int:
        return len(self.config.levels)

    @property
    def obs_dim(self) -> int:
        return 4 * self.num_agents + 3 * self.config.num_resources

    def reset(self, key):
        c = self.config
        n, r = self.num_agents, c.num_resources
        k_points, k_theta, k_rows = jax.random.split(key, 3)
        xy = sample_grid_points(k_points, n + r, c.spawn_spacing, *c.spawn_area)
        theta = jax.random.uniform(k_theta, (n, 1), jnp.float32, -math.pi, math.pi)
        select = jnp.triu(jnp.ones((r, n), jnp.float32))                # row r: agents r .. N-1
        select = jax.random.permutation(k_rows, select, axis=0)
        level = select @ jnp.asarray(c.levels, jnp.float32)
        poses = jnp.concatenate([xy[:n], theta], axis=-1)
        return poses, ForagingState(resources=xy[n:], level=level)

    def update(self, poses, state, actions):
        xp = namespace(poses, state.resources)
        c = self.config
        d = poses[:, None, :2] - state.resources[None, :, :]
        near = xp.sqrt(xp.sum(d * d, axis=-1)) < c.forage_radius                # [N, R]
        power = xp.sum(xp.where(near, xp.asarray(c.levels, dtype=poses.dtype)[:, None], 0), axis=0)
        open_ = state.level > 0
        collected = open_ & (power >= state.level)
        level = xp.where(collected, xp.asarray(-1, dtype=state.level.dtype), state.level)
        remain = xp.any(level > 0)
        team = c.forage_reward * xp.sum(xp.where(collected, state.level, 0)) + c.time_penalty * remain
        rewards = xp.full((self.num_agents,), team, dtype=poses.dtype)
        return state.replace(level=level), rewards, (~remain) & c.terminate_on_success

    def observe(self, poses, state):
        xp = namespace(poses, state.resources)
        n = self.num_agents
        res = xp.concatenate([state.resources, state.level[:, None]], axis=-1).reshape(1, -1)
        levels = xp.asarray(self.config.levels, dtype=poses.dtype)[:, None]
        return xp.concatenate([cyclic_blocks(poses), xp.broadcast_to(res, (n, res.shape[-1])).astype(poses.dtype),
                               cyclic_blocks(levels)], axis=-1)

    def metrics(self, state):
        xp = namespace(state.level)
        return {"resources_left": xp.sum(state.level > 0)}

    def render_layers(self, state):
        import numpy as np

        level = np.asarray(state.level)
        layers = []
        for (x, y), lv in zip(np.asarray(state.resources), level):
            layers.append({"kind": "circle", "xy": (x, y), "r": self.config.forage_radius,
                           "color": "lightgrey" if lv < 0 else "gold", "alpha": 0.3})
            layers.append({"kind": "text", "xy": (x, y), "text": "done" if lv < 0 else f"{lv:g}", "size": 9})
        return layers
