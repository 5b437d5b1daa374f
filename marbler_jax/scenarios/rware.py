"""RWARE (JaxRobotarium ``rware``): a robotic warehouse with shelves, requests and a delivery zone.

Layout (deterministic): robots start at ``x = linspace(-1.1, 1.1, N)``, ``y = -0.75``, facing +y.
``num_cells`` storage cells sit at ``x = linspace(-1.1, 0.6, C/2)`` in two rows (``y = +0.25`` for
cells ``0 .. C/2-1``, ``-0.25`` for the rest); shelf ``c`` starts in cell ``c``. The delivery zone is
``x > delivery_x``. ``N`` distinct shelves are requested at a time.

Action 4 (MARBLER's "stay") doubles as the pick-up / put-down toggle; 0-3 move as in MARBLER. A
robot that carries a shelf cannot drive through a cell that holds one: if any of 5 points evenly
spaced along its move (excluding its current position) lies within 0.125 m (per axis) of an
occupied cell, its waypoint is its current position. Per step, after the robots moved:

1. pick-up -- a robot not carrying at the start of the step that chose action 4 within
   ``pickup_radius`` of a cell that holds a shelf takes that shelf (the lowest-index robot per cell);
2. delivery -- a robot carrying a requested shelf at the start of the step with ``x > delivery_x``
   fulfils that request (``+deliver_reward``, team reward) and the request is replaced by a shelf
   drawn uniformly among those not requested; the robot keeps the shelf and must put it back;
3. put-down -- a robot carrying at the start of the step that chose action 4 within
   ``pickup_radius`` of a cell that was empty at the start of the step stores its shelf there.

Observation of agent i (``3N + 1 + 3C + N``, 31 for the defaults): its pose, the others' poses in
cyclic order, the id of the shelf it carries (-1 for none), every cell's (x, y, stored shelf id or
-1), the requested shelf ids.

Bug fixes (JaxRobotarium): a pick-up takes the id of the shelf *stored in* the cell (JaxRobotarium
stores the cell index, which is wrong once shelves have moved) and only from a cell that holds one
(JaxRobotarium lets robots "pick up" empty cells). Choices: the replacement request is drawn before
the fulfilled one is removed, so the shelf just delivered is not re-requested at once (JaxRobotarium
may re-draw it and let the robot deliver it again without putting it back); the blocking test skips
the robot's own position, so a robot pushed into an occupied cell can still leave it; the request
draws use uniforms sampled at reset (``update`` stays deterministic and runs unchanged in the numpy
Robotarium bundle); violations are penalized and end the episode as in every marbler-jax scenario.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from marbler_jax.xp import namespace
from marbler_jax.scenarios.base import JaxRobotariumConfig, Scenario, cyclic_blocks, distinct_indices

BLOCK_HALF = 0.125   # half side of a cell's blocking box [m]
MOVE_SAMPLES = (0.2, 0.4, 0.6, 0.8, 1.0)


@dataclasses.dataclass(frozen=True)
class RwareConfig(JaxRobotariumConfig):
    """RWARE settings (JaxRobotarium's, with MARBLER's env core).

    Attributes:
        n_agents: robots (also the number of shelves requested at a time).
        num_cells: storage cells, in two rows (even, >= 2); each starts with its own shelf.
        pickup_radius: a robot picks up or puts down a shelf within this distance of a cell [m].
        delivery_x: a requested shelf carried to ``x > delivery_x`` is delivered [m].
        deliver_reward: team reward per delivery.
    """

    n_agents: int = 3
    num_cells: int = 6
    pickup_radius: float = 0.2
    delivery_x: float = 1.1
    deliver_reward: float = 1.0
    update_frequency: int = 60

    def validate(self) -> None:
        super().validate()
        if self.num_cells < 2 or self.num_cells % 2:
            raise ValueError(f"num_cells must be an even number >= 2, got {self.num_cells}")
        if not 1 <= self.n_agents < self.num_cells:
            raise ValueError(f"n_agents must be in [1, num_cells - 1] = [1, {self.num_cells - 1}] (one request "
                             f"per robot, and a shelf left to request), got {self.n_agents}")
        if self.n_agents > 12:
            raise ValueError(f"rware: at most 12 robots fit on the start line (0.2 m apart), got {self.n_agents}")
        if self.num_cells > 16:
            raise ValueError(f"rware: at most 16 cells fit in the two storage rows, got {self.num_cells}")


@struct.dataclass
class RwareState:
    grid: jax.Array        # [C] int32 id of the shelf stored in each cell, -1 if empty
    payload: jax.Array     # [N] int32 id of the carried shelf, -1 if none
    requests: jax.Array    # [N] int32 requested shelf ids (distinct)
    draws: jax.Array       # [K] float32 uniforms for replacement requests
    drawn: jax.Array       # int32 draws used so far
    deliveries: jax.Array  # int32 requests fulfilled this episode


class Rware(Scenario):
    name = "rware"
    Config = RwareConfig
    violation_reward = -5.0
    shared_reward = True

    @property
    def num_agents(self) -> int:
        return self.config.n_agents

    @property
    def obs_dim(self) -> int:
        return 4 * self.num_agents + 1 + 3 * self.config.num_cells

    def cells(self) -> np.ndarray:
        """Cell centres ``[C, 2]``."""
        half = self.config.num_cells // 2
        xs = np.linspace(-1.1, 0.6, half)
        return np.stack([np.concatenate([xs, xs]), np.repeat([0.25, -0.25], half)], axis=-1).astype(np.float32)

    def reset(self, key):
        n, c = self.num_agents, self.config.num_cells
        k_req, k_draws = jax.random.split(key)
        x = jnp.linspace(-1.1, 1.1, n) if n > 1 else jnp.array([-1.1])
        poses = jnp.stack([x, jnp.full(n, -0.75), jnp.full(n, math.pi / 2)], axis=-1).astype(jnp.float32)
        draws = jax.random.uniform(k_draws, (n * (self.config.max_episode_steps + 1),))
        return poses, RwareState(grid=jnp.arange(c, dtype=jnp.int32), payload=jnp.full(n, -1, jnp.int32),
                                 requests=distinct_indices(k_req, n, c), draws=draws, drawn=jnp.int32(0),
                                 deliveries=jnp.int32(0))

    def goals(self, poses, state, actions):
        xp = namespace(poses)
        goals = super().goals(poses, state, actions)
        cells = xp.asarray(self.cells(), dtype=poses.dtype)
        t = xp.asarray(MOVE_SAMPLES, dtype=poses.dtype)[None, :, None]
        points = poses[:, None, :2] + t * (goals - poses[:, :2])[:, None, :]          # [N, 5, 2]
        gap = xp.abs(points[:, :, None, :] - cells[None, None, :, :])                 # [N, 5, C, 2]
        inside = (gap[..., 0] < BLOCK_HALF) & (gap[..., 1] < BLOCK_HALF) & (state.grid >= 0)
        blocked = (state.payload >= 0) & xp.any(inside, axis=(1, 2))
        return xp.where(blocked[:, None], poses[:, :2], goals)

    @staticmethod
    def _claims(xp, eligible):
        """``[N, C]`` bool: each agent its lowest eligible cell, each cell its lowest claiming agent."""
        n, c = eligible.shape
        first = xp.argmax(eligible, axis=1)
        choice = xp.any(eligible, axis=1)[:, None] & (xp.arange(c)[None, :] == first[:, None])
        winner = xp.argmax(choice, axis=0)
        return choice & (xp.arange(n)[:, None] == winner[None, :])

    def update(self, poses, state, actions):
        xp = namespace(poses, state.grid)
        c = self.config
        d = poses[:, None, :2] - xp.asarray(self.cells(), dtype=poses.dtype)[None, :, :]
        near = xp.sqrt(xp.sum(d * d, axis=-1)) < c.pickup_radius                      # [N, C]
        toggle = (actions == 4)[:, None]
        carrying = state.payload >= 0
        # 1. pick-up: the shelf stored in the cell, only from an occupied cell
        pick = self._claims(xp, (~carrying)[:, None] & toggle & near & (state.grid >= 0)[None, :])
        payload = xp.where(xp.any(pick, axis=1), xp.sum(xp.where(pick, state.grid[None, :], 0), axis=1), state.payload)
        grid = xp.where(xp.any(pick, axis=0), -1, state.grid)
        # 2. delivery: replacement drawn among the shelves not requested (before the swap)
        requests, drawn, fulfilled = state.requests, state.drawn, 0
        shelves = xp.arange(c.num_cells)
        for i in range(self.num_agents):
            match = carrying[i] & (poses[i, 0] > c.delivery_x) & (requests == state.payload[i])
            hit = xp.any(match)
            free = ~xp.any(shelves[:, None] == requests[None, :], axis=1)
            k = xp.floor(state.draws[drawn] * xp.sum(free)).astype(xp.int32)
            new = xp.argmax(xp.cumsum(free) > k)
            requests = xp.where(match, new, requests).astype(state.requests.dtype)
            drawn = drawn + hit.astype(xp.int32)
            fulfilled = fulfilled + hit.astype(xp.int32)
        # 3. put-down into a cell that was empty at the start of the step
        put = self._claims(xp, carrying[:, None] & toggle & near & (state.grid < 0)[None, :])
        grid = xp.where(xp.any(put, axis=0), xp.sum(xp.where(put, state.payload[:, None], 0), axis=0), grid)
        payload = xp.where(xp.any(put, axis=1), -1, payload)
        rewards = xp.full((self.num_agents,), c.deliver_reward * fulfilled, dtype=poses.dtype)
        new_state = state.replace(grid=grid.astype(state.grid.dtype), payload=payload.astype(state.payload.dtype),
                                  requests=requests, drawn=drawn.astype(state.drawn.dtype),
                                  deliveries=(state.deliveries + fulfilled).astype(state.deliveries.dtype))
        return new_state, rewards, xp.zeros((), dtype=bool)

    def observe(self, poses, state):
        xp = namespace(poses, state.grid)
        n, dtype = self.num_agents, poses.dtype
        cells = xp.concatenate([xp.asarray(self.cells(), dtype=dtype), state.grid[:, None].astype(dtype)], axis=-1)
        shared = xp.concatenate([cells.reshape(-1), state.requests.astype(dtype)])
        return xp.concatenate([cyclic_blocks(poses), state.payload[:, None].astype(dtype),
                               xp.broadcast_to(shared[None, :], (n, shared.shape[0]))], axis=-1)

    def metrics(self, state):
        return {"deliveries": state.deliveries}

    def render_layers(self, state):
        grid, requests, payload = np.asarray(state.grid), np.asarray(state.requests), np.asarray(state.payload)
        layers = [{"kind": "rect", "xywh": (self.config.delivery_x, -1.0, 1.6 - self.config.delivery_x, 2.0),
                   "color": "green", "alpha": 0.15}]
        for (x, y), shelf in zip(self.cells(), grid):
            layers.append({"kind": "rect", "xywh": (x - BLOCK_HALF, y - BLOCK_HALF, 2 * BLOCK_HALF, 2 * BLOCK_HALF),
                           "color": "tan" if shelf >= 0 else "lightgrey", "alpha": 0.6 if shelf >= 0 else 0.25})
            if shelf >= 0:
                layers.append({"kind": "text", "xy": (x, y), "text": str(shelf), "size": 8})
        carrying = " ".join(f"{i}:{p}" if p >= 0 else f"{i}:-" for i, p in enumerate(payload))
        layers.append({"kind": "text", "xy": (-0.4, 0.8), "size": 8,
                       "text": f"requested {','.join(map(str, requests))}   robot:shelf {carrying}"})
        return layers
