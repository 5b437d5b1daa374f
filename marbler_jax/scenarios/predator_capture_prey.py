"""Predator Capture Prey (MARBLER ``PredatorCapturePrey``): sense static prey, then capture them.

Agents ``0 .. predator-1`` are sensing robots (sensing radius ``predator_radius``, cannot capture);
agents ``predator .. predator+capture-1`` are capture robots (blind, capture radius
``capture_radius``). Heterogeneity is data: per-agent radius arrays, not subclasses.

Per step, after the robots moved, for every prey not yet captured (index order): it becomes
*sensed* (sticky) if some agent is within that agent's sensing radius (``<=``); a sensed prey (also
one sensed this step) becomes *captured* if some agent chose action 4 (``no_action`` doubles as
"capture") and is within its capture radius. Team reward
``sense_reward * newly_sensed + capture_reward * newly_captured + time_penalty``; -5 to every agent
on a penalized violation. The episode ends after ``max_episode_steps + 1`` steps or when every prey
is captured.

Observation of agent i: its local vector ``[x, y, px, py]`` (+ ``[sensing radius, capture radius]``
with ``capability_aware``) where (px, py) is the closest uncaptured prey within *its own* sensing
radius, or (-5, -5) -- captured as of the end of the step: MARBLER applies the step's sensing and
captures before it builds the observation (``PredatorCapturePrey.step``); followed by the local vectors of ``num_neighbors`` other agents (all others in
index order when ``num_neighbors >= N - 1``, as MARBLER's configs use; otherwise the nearest ones,
nearest first -- MARBLER leaves their order unspecified).

Deviation (bug fix): ``reset`` returns the real first observation (``zero_reset_obs=True`` restores
MARBLER's zeros).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from marbler_jax.xp import namespace
from marbler_jax.scenarios.base import BandSpawnConfig, Scenario, nearest_others, spawn_band

NO_PREY = -5.0


@dataclasses.dataclass(frozen=True)
class PredatorCapturePreyConfig(BandSpawnConfig):
    """Predator Capture Prey settings (MARBLER's names; the prey spawn in the right band).

    Attributes:
        time_penalty: team reward every step.
        sense_reward: team reward per prey sensed for the first time.
        capture_reward: team reward per prey captured.
        predator: number of sensing robots (indices ``0 .. predator-1``).
        predator_radius: sensing radius of a sensing robot [m].
        capture: number of capture robots (the next ``capture`` indices).
        capture_radius: capture radius of a capture robot [m].
        capability_aware: append ``[sensing radius, capture radius]`` to each local observation vector.
        num_neighbors: other robots whose local vectors follow a robot's own in its observation.
        num_prey: prey per episode.
    """

    time_penalty: float = -0.05
    sense_reward: float = 1.0
    capture_reward: float = 5.0
    predator: int = 2
    predator_radius: float = 0.45
    capture: int = 2
    capture_radius: float = 0.25
    capability_aware: bool = False
    num_neighbors: int = 3
    num_prey: int = 6
    max_episode_steps: int = 80
    update_frequency: int = 29

    def validate(self) -> None:
        super().validate()
        for name in ("predator", "capture", "num_prey"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.predator + self.capture < 1:
            raise ValueError("predator + capture must be >= 1 robot")
        if self.num_prey < 1:
            raise ValueError(f"num_prey must be >= 1, got {self.num_prey}")
        if self.num_neighbors < 0:
            raise ValueError(f"num_neighbors must be >= 0, got {self.num_neighbors}")
        self.check_bands("predator_capture_prey", self.predator + self.capture, self.num_prey, "prey")


@struct.dataclass
class PredatorCapturePreyState:
    prey: jax.Array      # [P, 2] positions
    sensed: jax.Array    # [P] bool, sticky
    captured: jax.Array  # [P] bool, sticky


class PredatorCapturePrey(Scenario):
    name = "predator_capture_prey"
    Config = PredatorCapturePreyConfig
    violation_reward = -5.0
    shared_reward = True

    @property
    def num_agents(self) -> int:
        return self.config.predator + self.config.capture

    @property
    def neighbors(self) -> int:
        return min(self.config.num_neighbors, self.num_agents - 1)

    @property
    def local_dim(self) -> int:
        return 6 if self.config.capability_aware else 4

    @property
    def obs_dim(self) -> int:
        return self.local_dim * (self.neighbors + 1)

    def radii(self, xp, dtype):
        """Per-agent (sensing radius ``[N]``, capture radius ``[N]``)."""
        c = self.config
        sensing = [c.predator_radius] * c.predator + [0.0] * c.capture
        capture = [0.0] * c.predator + [c.capture_radius] * c.capture
        return xp.asarray(sensing, dtype=dtype), xp.asarray(capture, dtype=dtype)

    def reset(self, key):
        k_robots, k_prey = jax.random.split(key)
        xy = spawn_band(k_robots, self.num_agents, self.config, self.config.start_dist, left=True)
        poses = jnp.concatenate([xy, jnp.zeros((self.num_agents, 1), jnp.float32)], axis=-1)
        prey = spawn_band(k_prey, self.config.num_prey, self.config, self.config.step_dist, left=False)
        none = jnp.zeros(self.config.num_prey, bool)
        return poses, PredatorCapturePreyState(prey=prey, sensed=none, captured=none)

    def _distances(self, poses, state):
        xp = namespace(poses, state.prey)
        d = poses[..., :, None, :2] - state.prey[..., None, :, :]
        return xp.sqrt(xp.sum(d * d, axis=-1))  # [N, P]

    def update(self, poses, state, actions):
        xp = namespace(poses, state.prey)
        c = self.config
        sensing, capture = self.radii(xp, poses.dtype)
        dist = self._distances(poses, state)
        in_sense = xp.any(dist <= sensing[:, None], axis=-2)
        capturing = (actions == 4)[:, None]
        in_capture = xp.any((dist <= capture[:, None]) & capturing, axis=-2)
        open_prey = ~state.captured
        sensed = state.sensed | (open_prey & in_sense)
        captured = state.captured | (open_prey & sensed & in_capture)
        new_sensed = xp.sum(sensed & ~state.sensed)
        new_captured = xp.sum(captured & ~state.captured)
        team = c.sense_reward * new_sensed + c.capture_reward * new_captured + c.time_penalty
        rewards = xp.full((self.num_agents,), team, dtype=poses.dtype)
        new_state = PredatorCapturePreyState(prey=state.prey, sensed=sensed, captured=captured)
        return new_state, rewards, xp.all(captured)

    def local_vectors(self, poses, state):
        """``[N, local_dim]``: own position, closest visible uncaptured prey, capabilities."""
        xp = namespace(poses, state.prey)
        sensing, capture = self.radii(xp, poses.dtype)
        dist = self._distances(poses, state)
        visible = (dist <= sensing[:, None]) & ~state.captured[None, :]
        masked = xp.where(visible, dist, xp.inf)
        nearest = xp.argmin(masked, axis=-1)
        seen = xp.any(visible, axis=-1)
        prey_xy = xp.where(seen[:, None], state.prey[nearest], xp.asarray(NO_PREY, dtype=poses.dtype))
        parts = [poses[:, :2], prey_xy]
        if self.config.capability_aware:
            parts.append(xp.stack([sensing, capture], axis=-1))
        return xp.concatenate(parts, axis=-1)

    def observe(self, poses, state):
        xp = namespace(poses, state.prey)
        local = self.local_vectors(poses, state)
        others = nearest_others(poses, self.neighbors)  # [N, k]
        neighbor_vecs = local[others].reshape(self.num_agents, -1)
        return xp.concatenate([local, neighbor_vecs], axis=-1)

    def render_layers(self, state):
        import numpy as np

        prey, sensed, captured = (np.asarray(a) for a in (state.prey, state.sensed, state.captured))
        colour = np.where(captured, "lightgrey", np.where(sensed, "orange", "black"))
        return [{"kind": "points", "xy": prey, "marker": "P", "size": 70, "color": list(colour)}]

    def metrics(self, state):
        xp = namespace(state.captured)
        return {"prey_left": xp.sum(~state.captured)}
