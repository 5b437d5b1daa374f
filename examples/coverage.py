"""Coverage: a complete custom scenario (see docs/custom_scenarios.md).

N robots start on the left, N landmarks lie on the right; the team must cover every landmark
(some robot within ``cover_radius``). Shared reward per step: minus the mean distance from each
landmark to its nearest robot, plus ``cover_bonus`` when every landmark is covered, which also ends
the episode. Observation of robot i: its position, the offsets to every landmark, the offsets to
the other robots (index order). ``marbler-jax train --scenario examples/coverage.py:Coverage``.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from marbler_jax.xp import namespace
from marbler_jax.scenarios.base import Scenario, ScenarioConfig, check_capacity, nearest_others, spawn_band


@dataclasses.dataclass(frozen=True)
class CoverageConfig(ScenarioConfig):
    n_agents: int = 3
    cover_radius: float = 0.2
    cover_bonus: float = 5.0
    step_dist: float = 0.2
    start_dist: float = 0.3
    robot_band_right: float = -0.5   # robots spawn left of this x
    goal_band_left: float = 0.0      # landmarks spawn right of this x
    max_episode_steps: int = 40

    def validate(self) -> None:
        super().validate()
        if self.n_agents < 1 or self.cover_radius <= 0:
            raise ValueError(f"need n_agents >= 1 and cover_radius > 0, got {self.n_agents}, {self.cover_radius}")
        height = self.y_max - self.y_min
        check_capacity("coverage", self.n_agents, self.start_dist, self.robot_band_right - self.x_min, height)
        check_capacity("coverage", self.n_agents, self.step_dist, self.x_max - self.goal_band_left, height,
                       what="landmarks")


@struct.dataclass
class CoverageState:
    landmarks: jax.Array   # [N, 2]
    covered: jax.Array     # [N] bool, as of the last step


class Coverage(Scenario):
    name = "coverage"
    Config = CoverageConfig
    violation_reward = -5.0
    shared_reward = True

    @property
    def num_agents(self) -> int:
        return self.config.n_agents

    @property
    def obs_dim(self) -> int:
        return 2 + 2 * self.num_agents + 2 * (self.num_agents - 1)

    def reset(self, key):                                  # JAX only: sampling
        k_robots, k_marks = jax.random.split(key)
        n = self.num_agents
        xy = spawn_band(k_robots, n, self.config, self.config.start_dist, left=True)
        poses = jnp.concatenate([xy, jnp.zeros((n, 1), jnp.float32)], axis=-1)
        marks = spawn_band(k_marks, n, self.config, self.config.step_dist, left=False)
        return poses, CoverageState(landmarks=marks, covered=jnp.zeros(n, bool))

    def gaps(self, poses, landmarks):
        """Distance from each landmark to its nearest robot ``[N]``."""
        xp = namespace(poses, landmarks)
        d = landmarks[None, :, :] - poses[:, None, :2]
        return xp.min(xp.sqrt(xp.sum(d * d, axis=-1)), axis=0)

    def update(self, poses, state, actions):              # numpy or JAX: runs in the bundle too
        xp = namespace(poses, state.landmarks)
        gaps = self.gaps(poses, state.landmarks)
        covered = gaps <= self.config.cover_radius
        done = xp.all(covered)
        team = -xp.mean(gaps) + self.config.cover_bonus * done
        rewards = xp.full((self.num_agents,), team, dtype=poses.dtype)
        return state.replace(covered=covered), rewards, done

    def observe(self, poses, state):
        xp = namespace(poses, state.landmarks)
        n, xy = self.num_agents, poses[:, :2]
        marks = (state.landmarks[None, :, :] - xy[:, None, :]).reshape(n, 2 * n)
        others = (xy[nearest_others(poses, n - 1)] - xy[:, None, :]).reshape(n, 2 * (n - 1))
        return xp.concatenate([xy, marks, others], axis=-1)

    def metrics(self, state):
        return {"uncovered": namespace(state.covered).sum(~state.covered)}

    def render_layers(self, state):                       # numpy, for marbler_jax.render
        covered = np.asarray(state.covered)
        layers = [{"kind": "circle", "xy": tuple(xy), "r": self.config.cover_radius,
                   "color": "green" if c else "orange", "alpha": 0.3} for xy, c in zip(np.asarray(state.landmarks), covered)]
        return layers + [{"kind": "points", "xy": state.landmarks, "marker": "x", "size": 50, "color": "black"}]
