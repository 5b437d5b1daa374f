"""Discovery (JaxRobotarium ``discovery``): sensing robots find landmarks, tagging robots tag them.

JaxRobotarium's heterogeneous version of MARBLER's Predator Capture Prey, in our env core (MARBLER's
control loop, barrier certificate and violation handling; MARBLER's action order 0 -x, 1 +x, 2 -y,
3 +y, 4 stay). Agents ``0 .. n_sensing-1`` sense (radius ``sensing_radius``), agents
``n_sensing ..`` tag (radius ``tagging_radius``); capabilities are per-agent data.

Per step, after the robots moved: a landmark becomes *sensed* (sticky) when a sensing robot is
strictly closer than its sensing radius, and *tagged* (sticky) when a tagging robot is strictly
closer than its tagging radius -- tagging needs neither prior sensing nor a special action, and
tagged landmarks stay in the world. Team reward ``sense_reward * newly_sensed + tag_reward *
newly_tagged + time_penalty * [some landmark untagged after the step]``.

Observation of agent i (``3N + 3L + 2N``, 38 for the defaults): its pose (x, y, theta), the other
agents' poses in cyclic order (i+1, ..., i-1), every landmark's (x, y, 0) if any agent has sensed it
else (-5, -5, -5) (team knowledge), then the capability rows ``[sensing radius, tagging radius]`` of
itself and the others in cyclic order.

Reset: agents on distinct points of the spacing-0.3 grid of the 0.8333 x 1.5 m centre strip with
random headings; landmarks on distinct points of the spacing-0.5 grid of the 2.5 x 1.5 m spawn area
(independent of the agents, as in JaxRobotarium).

Choices (documented deviations): a landmark's third observation entry is 0 (JaxRobotarium shows the
random heading its sampler drew, which carries no information); ``terminate_on_success`` (default
False, as JaxRobotarium) ends the episode once every landmark is tagged; violations are penalized
and end the episode as in every marbler-jax scenario (JaxRobotarium only logs them).
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

UNSEEN = -5.0


@dataclasses.dataclass(frozen=True)
class DiscoveryConfig(JaxRobotariumConfig):
    """Discovery settings (JaxRobotarium's, with MARBLER's env core).

    Attributes:
        n_sensing: sensing robots (indices ``0 .. n_sensing-1``).
        n_tagging: tagging robots (the next indices).
        num_landmarks: landmarks per episode.
        sensing_radius: a sensing robot senses a landmark strictly closer than this [m].
        tagging_radius: a tagging robot tags a landmark strictly closer than this [m].
        sense_reward: team reward per landmark sensed for the first time.
        tag_reward: team reward per landmark tagged for the first time.
        time_penalty: team reward every step while some landmark is untagged.
        terminate_on_success: end the episode once every landmark is tagged.
        agent_spacing: spacing of the robots' spawn grid [m].
        agent_area: (width, height) of the robots' spawn area at the arena's centre [m].
        landmark_spacing: spacing of the landmarks' spawn grid [m].
        landmark_area: (width, height) of the landmarks' spawn area at the arena's centre [m].
    """

    n_sensing: int = 2
    n_tagging: int = 2
    num_landmarks: int = 6
    sensing_radius: float = 0.45
    tagging_radius: float = 0.25
    sense_reward: float = 1.0
    tag_reward: float = 5.0
    time_penalty: float = -0.05
    terminate_on_success: bool = False
    agent_spacing: float = 0.3
    agent_area: tuple[float, float] = (0.8333, 1.5)
    landmark_spacing: float = 0.5
    landmark_area: tuple[float, float] = (2.5, 1.5)

    def validate(self) -> None:
        super().validate()
        if self.n_sensing < 0 or self.n_tagging < 0 or self.n_sensing + self.n_tagging < 1:
            raise ValueError(f"need n_sensing, n_tagging >= 0 and at least one robot, got {self.n_sensing}, "
                             f"{self.n_tagging}")
        if self.num_landmarks < 1:
            raise ValueError(f"num_landmarks must be >= 1, got {self.num_landmarks}")
        check_grid_capacity("discovery", self.n_sensing + self.n_tagging, self.agent_spacing, self.agent_area)
        check_grid_capacity("discovery", self.num_landmarks, self.landmark_spacing, self.landmark_area, "landmarks")


@struct.dataclass
class DiscoveryState:
    landmarks: jax.Array   # [L, 2]
    sensed: jax.Array      # [L] bool, sticky
    tagged: jax.Array      # [L] bool, sticky


class Discovery(Scenario):
    name = "discovery"
    Config = DiscoveryConfig
    violation_reward = -5.0
    shared_reward = True

    @property
    def num_agents(self) -> int:
        return self.config.n_sensing + self.config.n_tagging

    @property
    def obs_dim(self) -> int:
        return 5 * self.num_agents + 3 * self.config.num_landmarks

    def capabilities(self, xp, dtype):
        """``[N, 2]`` rows ``[sensing radius, tagging radius]``."""
        c = self.config
        rows = [[c.sensing_radius, 0.0]] * c.n_sensing + [[0.0, c.tagging_radius]] * c.n_tagging
        return xp.asarray(rows, dtype=dtype)

    def reset(self, key):
        c = self.config
        k_agents, k_theta, k_marks = jax.random.split(key, 3)
        xy = sample_grid_points(k_agents, self.num_agents, c.agent_spacing, *c.agent_area)
        theta = jax.random.uniform(k_theta, (self.num_agents, 1), jnp.float32, -math.pi, math.pi)
        marks = sample_grid_points(k_marks, c.num_landmarks, c.landmark_spacing, *c.landmark_area)
        none = jnp.zeros(c.num_landmarks, bool)
        return jnp.concatenate([xy, theta], axis=-1), DiscoveryState(landmarks=marks, sensed=none, tagged=none)

    def update(self, poses, state, actions):
        xp = namespace(poses, state.landmarks)
        c = self.config
        caps = self.capabilities(xp, poses.dtype)
        d = poses[:, None, :2] - state.landmarks[None, :, :]
        dist = xp.sqrt(xp.sum(d * d, axis=-1))                                   # [N, L]
        sensed = state.sensed | xp.any(dist < caps[:, :1], axis=0)
        tagged = state.tagged | xp.any(dist < caps[:, 1:], axis=0)
        new_sensed = xp.sum(sensed & ~state.sensed)
        new_tagged = xp.sum(tagged & ~state.tagged)
        done = xp.all(tagged)
        team = c.sense_reward * new_sensed + c.tag_reward * new_tagged + c.time_penalty * (~done)
        rewards = xp.full((self.num_agents,), team, dtype=poses.dtype)
        new_state = state.replace(sensed=sensed, tagged=tagged)
        return new_state, rewards, done & c.terminate_on_success

    def observe(self, poses, state):
        xp = namespace(poses, state.landmarks)
        n = self.num_agents
        marks = xp.concatenate([state.landmarks, xp.zeros_like(state.landmarks[:, :1])], axis=-1)
        marks = xp.where(state.sensed[:, None], marks, xp.asarray(UNSEEN, dtype=marks.dtype)).reshape(1, -1)
        caps = self.capabilities(xp, poses.dtype)
        return xp.concatenate([cyclic_blocks(poses), xp.broadcast_to(marks, (n, marks.shape[-1])),
                               cyclic_blocks(caps)], axis=-1).astype(poses.dtype)

    def metrics(self, state):
        xp = namespace(state.tagged)
        return {"landmarks_left": xp.sum(~state.tagged), "landmarks_sensed": xp.sum(state.sensed)}

    def render_layers(self, state):
        import numpy as np

        sensed, tagged = np.asarray(state.sensed), np.asarray(state.tagged)
        colour = np.where(tagged, "lightgrey", np.where(sensed, "orange", "black"))
        return [{"kind": "points", "xy": np.asarray(state.landmarks), "marker": "D", "size": 45, "color": list(colour)}]
