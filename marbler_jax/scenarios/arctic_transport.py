"""Arctic Transport (MARBLER ``ArcticTransport``): drones scout terrain, two robots cross it to a goal.

Four agents (as in MARBLER): 0 and 1 are drones (waypoint step ``fast_step`` everywhere), 2 is the
ice robot and 3 the water robot. The map is 8 rows x 12 columns of 0.25 m cells: 0 normal, 1 ice,
2 water, 3 goal. A robot's step depends on the tile it stood on at the end of the previous step
(normal or goal ``normal_step``, its own terrain ``fast_step``, the other liquid ``slow_step``).

Reset: every cell uniform in {0, 1, 2}; a goal column ``c`` uniform in 1..11 turns cells
(0, c-1), (0, c), (1, c-1), (1, c) into goal tiles; the bottom row's columns 1..10 are set to normal.
Robots start at x = (-0.3, 0.3, -0.9, 0.9), y = -0.8, facing +y. The goal point used by rewards and
observations is the reference point of cell (1, c): ``(0.25 c - 1.5, 0.5)``.

Team reward per step, summed over the two robots (drones do not count): ``not_reached_penalty`` while
the robot has never stood on a goal tile (sticky), plus ``dist_multiplier * |p - goal point|^2`` while
it is not on a goal tile now. -30 to every agent on a penalized violation. The episode ends after
``max_episode_steps + 1`` steps or once both robots have reached the goal.

Observation (30): own ``[x, y, tile]``, the three others' ``[x, y, tile]`` (agent 0 sees 1, 2, 3;
agent 1 sees 0, 2, 3; agent 2 sees 3, 0, 1; agent 3 sees 2, 0, 1), the goal point, and each drone's
8 neighbouring tiles (order (r-1,c-1), (r,c-1), (r+1,c-1), (r-1,c), (r+1,c), (r-1,c+1), (r,c+1),
(r+1,c+1); indices off the grid are replaced by the drone's own row/column).

Deviation (bug fix): ``reset`` returns the real first observation (``zero_reset_obs=True`` restores
MARBLER's zeros).
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from marbler_jax.xp import namespace
from marbler_jax.scenarios.base import Scenario, ScenarioConfig

ROWS, COLS, CELL = 8, 12, 0.25
NORMAL, ICE, WATER, GOAL = 0, 1, 2, 3
OTHERS = np.array([[1, 2, 3], [0, 2, 3], [3, 0, 1], [2, 0, 1]], dtype=np.int32)
NEIGHBOURS = ((-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1))
START = ((-0.3, -0.8), (0.3, -0.8), (-0.9, -0.8), (0.9, -0.8))


@dataclasses.dataclass(frozen=True)
class ArcticTransportConfig(ScenarioConfig):
    """Arctic Transport settings (MARBLER's names; robots 0, 1 are drones, 2 the ice and 3 the water robot).

    Attributes:
        normal_step: waypoint offset of a ground robot's move from a normal or goal tile [m].
        fast_step: waypoint offset of a drone's move, and of a ground robot's from its own terrain [m].
        slow_step: waypoint offset of a ground robot's move from the other liquid [m].
        not_reached_penalty: team reward per ground robot that has never reached the goal, every step.
        dist_multiplier: team reward per squared metre of a ground robot's distance to the goal point,
            every step it is off the goal.
    """

    normal_step: float = 0.2
    fast_step: float = 0.3
    slow_step: float = 0.1
    not_reached_penalty: float = -0.05
    dist_multiplier: float = -0.075
    max_episode_steps: int = 60
    update_frequency: int = 36


@struct.dataclass
class ArcticTransportState:
    grid: jax.Array          # [8, 12] int32 tile codes
    goal_col: jax.Array      # int32 c in 1..11
    tile: jax.Array          # [4] int32 tile under each agent at the end of the last step
    reached: jax.Array       # [4] bool, sticky


def cell_of(poses):
    """(row ``[N]``, col ``[N]``) of each position (MARBLER: int truncation, then clamped)."""
    xp = namespace(poses)
    row = xp.clip(xp.trunc((1 - poses[..., 1]) / CELL), 0, ROWS - 1).astype(xp.int32)
    col = xp.clip(xp.trunc((poses[..., 0] + 1.5) / CELL), 0, COLS - 1).astype(xp.int32)
    return row, col


class ArcticTransport(Scenario):
    name = "arctic_transport"
    Config = ArcticTransportConfig
    violation_reward = -30.0
    shared_reward = True

    @property
    def num_agents(self) -> int:
        return 4

    @property
    def obs_dim(self) -> int:
        return 3 * 4 + 2 + 2 * len(NEIGHBOURS)

    def reset(self, key):
        k_grid, k_goal = jax.random.split(key)
        grid = jax.random.randint(k_grid, (ROWS, COLS), 0, 3, jnp.int32)
        c = jax.random.randint(k_goal, (), 1, COLS, jnp.int32)
        rows = jnp.arange(ROWS)[:, None]
        cols = jnp.arange(COLS)[None, :]
        goal_block = (rows <= 1) & ((cols == c) | (cols == c - 1))
        grid = jnp.where(goal_block, GOAL, grid)
        grid = jnp.where((rows == ROWS - 1) & (cols >= 1) & (cols <= COLS - 2), NORMAL, grid)
        poses = jnp.array([[x, y, math.pi / 2] for x, y in START], jnp.float32)
        state = ArcticTransportState(grid=grid, goal_col=c, tile=jnp.zeros(4, jnp.int32), reached=jnp.zeros(4, bool))
        return poses, state

    def goal_point(self, state, dtype):
        xp = namespace(state.grid)
        return xp.stack([CELL * state.goal_col - 1.5, xp.asarray(0.5)]).astype(dtype)

    def tiles(self, poses, state):
        row, col = cell_of(poses)
        return state.grid[row, col]

    def step_sizes(self, poses, state):
        xp = namespace(poses)
        c = self.config
        tile = state.tile
        own = xp.asarray([-1, -1, ICE, WATER])
        other = xp.asarray([-1, -1, WATER, ICE])
        robot = xp.where(tile == own, c.fast_step, xp.where(tile == other, c.slow_step, c.normal_step))
        drone = xp.asarray([True, True, False, False])
        return xp.where(drone, c.fast_step, robot).astype(poses.dtype)

    def update(self, poses, state, actions):
        xp = namespace(poses)
        c = self.config
        tile = self.tiles(poses, state).astype(xp.int32)
        reached = state.reached | (tile == GOAL)
        goal = self.goal_point(state, poses.dtype)
        d = poses[2:, :2] - goal
        on_goal = tile[2:] == GOAL
        per_robot = xp.where(reached[2:], 0.0, c.not_reached_penalty) + xp.where(
            on_goal, 0.0, c.dist_multiplier * xp.sum(d * d, axis=-1))
        team = xp.sum(per_robot)
        rewards = xp.full((4,), team, dtype=poses.dtype)
        new_state = ArcticTransportState(grid=state.grid, goal_col=state.goal_col, tile=tile, reached=reached)
        return new_state, rewards, xp.all(reached[2:])

    def observe(self, poses, state):
        xp = namespace(poses)
        dt = poses.dtype
        tile = self.tiles(poses, state)
        local = xp.concatenate([poses[:, :2], tile[:, None].astype(dt)], axis=-1)  # [4, 3]
        others = local[xp.asarray(OTHERS)].reshape(4, 9)
        row, col = cell_of(poses)
        patches = []
        for drone in (0, 1):
            for dr, dc in NEIGHBOURS:
                r, cc = row[drone] + dr, col[drone] + dc
                r = xp.where((r < 0) | (r >= ROWS), row[drone], r)
                cc = xp.where((cc < 0) | (cc >= COLS), col[drone], cc)
                patches.append(state.grid[r, cc])
        shared = xp.concatenate([self.goal_point(state, dt), xp.stack(patches).astype(dt)])
        return xp.concatenate([local, others, xp.broadcast_to(shared, (4, shared.shape[0]))], axis=-1)

    def render_layers(self, state):
        palette = np.array([[0.85, 0.85, 0.8], [0.75, 0.9, 1.0], [0.3, 0.55, 0.9], [1.0, 0.85, 0.3]])
        rgb = palette[np.asarray(state.grid)]
        goal = np.asarray(self.goal_point(state, np.float32))
        return [{"kind": "image", "rgb": rgb, "extent": (-1.5, -1.5 + COLS * CELL, 1.0 - ROWS * CELL, 1.0), "alpha": 0.7},
                {"kind": "points", "xy": goal, "marker": "*", "size": 120, "color": "black"}]

    def metrics(self, state):
        xp = namespace(state.reached)
        return {"robots_at_goal": xp.sum(state.reached[2:])}
