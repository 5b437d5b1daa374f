"""Material Transport (MARBLER ``MaterialTransport``): empty two zones into a drop-off strip.

Agents ``0 .. n_fast_agents-1`` are fast (waypoint step ``fast_step``, capacity ``small_torque``);
the rest are slow (``slow_step``, capacity ``large_torque``). Zone 1 is the disk of radius
``zone1_radius`` at the origin, zone 2 the strip ``x > 1.5 - end_goal_width``, the drop-off the strip
``x < -1.5 + end_goal_width``. Zone loads are ``int(Normal(loc, scale))`` at reset (truncated toward
zero, as MARBLER's ``int(np.random.normal(...))``; clamped at 0).

Actions are ``Discrete(5 * 4)``: ``move = a // 4`` (MARBLER's waypoint table with the agent's own
step), ``message = a % 4`` broadcast to every agent. Team reward per step: ``time_penalty`` plus, for
each agent in index order (lower index has priority when a zone runs low, post-move positions):
drop-off of a load -> ``load * unload_multiplier`` and load := 0; else, empty-handed in zone 2 (checked
first) or zone 1 -> takes ``q = min(capacity, zone left)``, reward ``q * load_multiplier``. -6 to every
agent on a penalized violation. The episode ends after ``max_episode_steps + 1`` steps or when both
zones are empty and nobody carries anything.

Observation: ``[x, y, load, zone1 left, zone2 left, message of agent 0 .. N-1]``
(+ ``[capacity, step]`` with ``capability_aware``). Loads and zone counts are those before this
step's loading/unloading (MARBLER builds observations before applying them); messages are this step's,
also on a step that a violation ends (MARBLER sets them before it checks for one).

Deviations (bug fixes): the message block has one entry per agent (MARBLER hard-codes 4, which breaks
any other team size); ``reset`` returns the real first observation (``zero_reset_obs=True`` restores
MARBLER's zeros). Zone distributions are normal only (MARBLER accepts any numpy distribution name).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from marbler_jax.xp import namespace
from marbler_jax.scenarios.base import Scenario, ScenarioConfig, check_capacity, grid_positions

MESSAGES = 4


@dataclasses.dataclass(frozen=True)
class MaterialTransportConfig(ScenarioConfig):
    """Material Transport settings (MARBLER's names; zone loads are normal distributions).

    Attributes:
        n_fast_agents: fast robots (indices ``0 .. n_fast_agents-1``).
        n_slow_agents: slow robots (the next indices).
        fast_step: waypoint offset of a fast robot's move [m].
        slow_step: waypoint offset of a slow robot's move [m].
        large_torque: load capacity of a slow robot.
        small_torque: load capacity of a fast robot.
        unload_multiplier: team reward per unit unloaded in the drop-off strip.
        load_multiplier: team reward per unit loaded in a zone.
        end_goal_width: width of the drop-off strip (left), of zone 2 (right) and of the spawn band [m].
        time_penalty: team reward every step.
        capability_aware: append ``[capacity, step]`` to each observation.
        zone1_radius: radius of zone 1, the disk at the origin [m].
        zone1_loc: mean of zone 1's load at reset (``int(Normal(loc, scale))``, at least 0).
        zone1_scale: standard deviation of zone 1's load at reset.
        zone2_loc: mean of zone 2's load at reset.
        zone2_scale: standard deviation of zone 2's load at reset.
        start_dist: spacing of the spawn grid [m].
    """

    n_fast_agents: int = 2
    n_slow_agents: int = 2
    fast_step: float = 0.45
    slow_step: float = 0.15
    large_torque: int = 15
    small_torque: int = 5
    unload_multiplier: float = 0.075
    load_multiplier: float = 0.025
    end_goal_width: float = 0.5
    time_penalty: float = -0.1
    capability_aware: bool = False
    zone1_radius: float = 0.35
    zone1_loc: float = 100.0
    zone1_scale: float = 10.0
    zone2_loc: float = 20.0
    zone2_scale: float = 4.0
    start_dist: float = 0.3
    max_episode_steps: int = 70
    update_frequency: int = 74

    def validate(self) -> None:
        super().validate()
        if self.n_fast_agents < 0 or self.n_slow_agents < 0 or self.n_fast_agents + self.n_slow_agents < 1:
            raise ValueError(f"need n_fast_agents, n_slow_agents >= 0 and at least one robot, got "
                             f"{self.n_fast_agents} and {self.n_slow_agents}")
        if self.large_torque < 0 or self.small_torque < 0:
            raise ValueError("capacities large_torque and small_torque must be >= 0")
        if self.zone1_scale < 0 or self.zone2_scale < 0:
            raise ValueError("zone scales must be >= 0")
        check_capacity("material_transport", self.n_fast_agents + self.n_slow_agents, self.start_dist,
                       self.end_goal_width, self.y_max - self.y_min)


@struct.dataclass
class MaterialTransportState:
    load: jax.Array      # [N] int32 units carried
    zone1: jax.Array     # int32 units left in zone 1
    zone2: jax.Array     # int32 units left in zone 2
    messages: jax.Array  # [N] int32, this step's messages


class MaterialTransport(Scenario):
    name = "material_transport"
    Config = MaterialTransportConfig
    violation_reward = -6.0
    shared_reward = True

    @property
    def num_agents(self) -> int:
        return self.config.n_fast_agents + self.config.n_slow_agents

    @property
    def num_actions(self) -> int:
        return 5 * MESSAGES

    @property
    def obs_dim(self) -> int:
        return 5 + self.num_agents + (2 if self.config.capability_aware else 0)

    @property
    def obs_bound(self) -> float:
        c = self.config  # zone counts: int(Normal) beyond 10 sigma is practically impossible
        return float(max(10.0, c.zone1_loc + 10 * c.zone1_scale, c.zone2_loc + 10 * c.zone2_scale,
                         c.large_torque, c.small_torque))

    def capabilities(self, xp, dtype):
        """Per-agent (capacity ``[N]`` int, waypoint step ``[N]``)."""
        c = self.config
        capacity = [c.small_torque] * c.n_fast_agents + [c.large_torque] * c.n_slow_agents
        step = [c.fast_step] * c.n_fast_agents + [c.slow_step] * c.n_slow_agents
        return xp.asarray(capacity, dtype=xp.int32), xp.asarray(step, dtype=dtype)

    def step_sizes(self, poses, state):
        return self.capabilities(namespace(poses), poses.dtype)[1]

    def move_actions(self, actions):
        return actions // MESSAGES

    def reset(self, key):
        c = self.config
        k_pos, k1, k2 = jax.random.split(key, 3)
        width = c.end_goal_width
        thresh = c.x_min + c.end_goal_width
        xy = grid_positions(k_pos, self.num_agents, c.start_dist, width, c.y_max - c.y_min)
        xy = xy + jnp.array([-(width / 2 - thresh), 0.0], jnp.float32)
        poses = jnp.concatenate([xy, jnp.zeros((self.num_agents, 1), jnp.float32)], axis=-1)
        zone1 = jnp.maximum(jnp.trunc(c.zone1_loc + c.zone1_scale * jax.random.normal(k1)), 0).astype(jnp.int32)
        zone2 = jnp.maximum(jnp.trunc(c.zone2_loc + c.zone2_scale * jax.random.normal(k2)), 0).astype(jnp.int32)
        zeros = jnp.zeros(self.num_agents, jnp.int32)
        return poses, MaterialTransportState(load=zeros, zone1=zone1, zone2=zone2, messages=zeros)

    def update(self, poses, state, actions):
        xp = namespace(poses)
        c = self.config
        capacity, _ = self.capabilities(xp, poses.dtype)
        edge = 1.5 - c.end_goal_width
        x = poses[:, 0]
        near_origin = xp.sqrt(xp.sum(poses[:, :2] * poses[:, :2], axis=-1)) <= c.zone1_radius
        reward = xp.asarray(c.time_penalty, dtype=poses.dtype)
        zone1, zone2 = state.zone1, state.zone2
        loads = []
        for i in range(self.num_agents):  # sequential: lower index has priority
            load = state.load[i]
            drop = (load > 0) & (x[i] < -edge)
            empty = load == 0
            from2 = empty & ~drop & (x[i] > edge)
            from1 = empty & ~drop & ~from2 & near_origin[i]
            take2 = xp.where(from2, xp.minimum(capacity[i], zone2), 0)
            take1 = xp.where(from1, xp.minimum(capacity[i], zone1), 0)
            reward = reward + xp.where(drop, load * c.unload_multiplier, 0) + (take1 + take2) * c.load_multiplier
            zone1, zone2 = zone1 - take1, zone2 - take2
            loads.append(xp.where(drop, 0, xp.where(from2 | from1, take1 + take2, load)))
        load = xp.stack(loads).astype(xp.int32)
        rewards = xp.full((self.num_agents,), reward, dtype=poses.dtype)
        done = (zone1 == 0) & (zone2 == 0) & xp.all(load == 0)
        messages = (actions % MESSAGES).astype(xp.int32)
        return MaterialTransportState(load=load, zone1=zone1, zone2=zone2, messages=messages), rewards, done

    def observe(self, poses, state):
        xp = namespace(poses)
        n = self.num_agents
        dt = poses.dtype
        shared = xp.concatenate([xp.stack([state.zone1, state.zone2]).astype(dt), state.messages.astype(dt)])
        parts = [poses[:, :2], state.load[:, None].astype(dt), xp.broadcast_to(shared, (n, shared.shape[0]))]
        if self.config.capability_aware:
            capacity, step = self.capabilities(xp, dt)
            parts.append(xp.stack([capacity.astype(dt), step], axis=-1))
        return xp.concatenate(parts, axis=-1)

    def observation_state(self, before, after):
        # MARBLER observes before loading/unloading (loads and zone counts lag one step) but after
        # reading this step's messages.
        return before.replace(messages=after.messages)

    def render_layers(self, state):
        c = self.config
        edge = 1.5 - c.end_goal_width
        return [
            {"kind": "circle", "xy": (0.0, 0.0), "r": c.zone1_radius, "color": "tab:blue"},
            {"kind": "rect", "xywh": (edge, -1.0, 1.6 - edge, 2.0), "color": "tab:blue"},
            {"kind": "rect", "xywh": (-1.6, -1.0, 1.6 - edge, 2.0), "color": "tab:green"},
            {"kind": "text", "xy": (0.0, 0.0), "text": f"{int(state.zone1)}"},
            {"kind": "text", "xy": (edge + 0.3, 0.0), "text": f"{int(state.zone2)}"},
        ]

    def metrics(self, state):
        xp = namespace(state.load)
        return {"material_left": state.zone1 + state.zone2 + xp.sum(state.load)}
