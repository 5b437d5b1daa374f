"""The batched MARBLER env core: one pure ``reset`` / ``step`` shared by every scenario.

``env = marbler_jax.make(name, **overrides)``; then, for a single env (vmap/jit it for many)::

    obs, state = env.reset(key)                                   # obs [N, obs_dim] float32
    obs, state, rewards, done, info = env.step(key, state, actions)   # actions [N] int32

Actions outside ``[0, num_actions)`` raise outside ``jit`` and are clipped under it; :func:`checked`
runs a step with that check raising under ``jit`` too.

One env step runs MARBLER's control loop (``robotarium_gym/utilities/roboEnv.py``):

1. actions -> waypoints from the poses at the start of the step;
2. for ``update_frequency`` simulator ticks, every ``control_period`` ticks recompute
   SI position controller (projection point) -> barrier certificate -> SI -> unicycle map and hold
   the command in between; before each tick, check the pose for collisions / boundary violations
   (rps validates the pre-tick pose, so the last pose of a step is checked at the next step's first
   tick, exactly as in MARBLER);
3. with ``penalize_violations`` the step ends after the first violating tick: every agent gets the
   scenario's violation reward and the episode ends; otherwise the scenario's task update runs.

The ticks of one control period share one command; :func:`marbler_jax.physics.held_ticks` runs them
with a trig-free heading rotation and the per-tick checks on the i < j pairs.

The episode ends when the step counter exceeds ``max_episode_steps`` (``max_episode_steps + 1`` steps),
on task completion, or on a penalized violation. ``step`` then auto-resets: it returns the new
episode's first observation and state, while ``rewards``, ``done`` and ``info`` describe the finished
transition (``info["returned_episode"]`` is True and the episode metrics are the finished episode's).
"""
from __future__ import annotations

import contextvars
import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.experimental import checkify

from marbler_jax import controllers, physics
from marbler_jax.cbf import Multipliers
from marbler_jax.xp import from_minor, to_minor, vmap_in_place
from marbler_jax.control_loop import barrier_for, control, control_warm, finish_step
from marbler_jax.scenarios.base import Scenario


@struct.dataclass
class EnvState:
    """State of one env (a pytree; batch it with vmap).

    Attributes:
        poses: ``[N, 3]`` robot poses (x, y, theta).
        scenario: the scenario's own state pytree.
        step: env steps taken in this episode (int32).
        episode_return: team return so far (float32; MARBLER's reported reward).
        collided: the episode has seen a collision tick (bool).
        out_of_bounds: the episode has seen a boundary violation tick (bool).
        cbf_multipliers: the barrier's multipliers at the last control refresh
            (:class:`marbler_jax.cbf.Multipliers`, zeros at reset; ``None`` when the barrier is not
            warm-started, see ``cbf_warm_start``): the next refresh starts its sweeps from them.
    """

    poses: jax.Array
    scenario: Any
    step: jax.Array
    episode_return: jax.Array
    collided: jax.Array
    out_of_bounds: jax.Array
    cbf_multipliers: Any = None


class MarblerEnv:
    """A scenario wrapped in MARBLER's control loop; pure ``reset``/``step`` (jit/vmap-able)."""

    def __init__(self, scenario: Scenario):
        self.scenario = scenario
        self.config = scenario.config
        self.params = physics.get_params(self.config.physics)
        physics.check_num_robots(self.params, scenario.num_agents)
        self.barrier = barrier_for(self.config, scenario.num_agents)

    # --- sizes -------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.scenario.name

    @property
    def num_agents(self) -> int:
        return self.scenario.num_agents

    @property
    def obs_dim(self) -> int:
        return self.scenario.obs_dim

    @property
    def num_actions(self) -> int:
        return self.scenario.num_actions

    @property
    def max_steps(self) -> int:
        """Steps of a full-length episode (``max_episode_steps + 1``)."""
        return self.config.max_episode_steps + 1

    @functools.cached_property
    def metric_names(self) -> tuple[str, ...]:
        """The scenario's paper metrics in ``info`` (``prey_left``, ``deliveries``, ...); found by shape
        evaluation, without computing a reset."""
        metrics = jax.eval_shape(lambda key: self.scenario.metrics(self.reset(key)[1].scenario), jax.random.PRNGKey(0))
        return tuple(metrics)

    def __repr__(self) -> str:
        return f"MarblerEnv({self.name!r}, agents={self.num_agents}, obs_dim={self.obs_dim}, actions={self.num_actions})"

    # --- API ---------------------------------------------------------------------------------
    def reset(self, key: jax.Array) -> tuple[jax.Array, EnvState]:
        """Start an episode: ``(obs [N, obs_dim], state)``."""
        poses, scenario_state = self.scenario.reset(key)
        state = EnvState(
            poses=jnp.asarray(poses, jnp.float32), scenario=scenario_state, step=jnp.int32(0),
            episode_return=jnp.float32(0), collided=jnp.bool_(False), out_of_bounds=jnp.bool_(False),
            cbf_multipliers=self.initial_multipliers(),
        )
        return self.reset_obs(state), state

    def initial_multipliers(self, dtype=jnp.float32):
        """Cold-start barrier multipliers of one env (``None`` when nothing is warm-started)."""
        if self.barrier is None or not self.config.warm_start_barrier:
            return None
        return self.barrier.initial_multipliers(self.num_agents, (), dtype, jnp)

    def reset_obs(self, state: EnvState) -> jax.Array:
        obs = self.observe(state)
        return jnp.zeros_like(obs) if self.config.zero_reset_obs else obs

    def observe(self, state: EnvState) -> jax.Array:
        return jnp.asarray(self.scenario.observe(state.poses, state.scenario), state.poses.dtype)

    def step(self, key: jax.Array, state: EnvState, actions: jax.Array):
        """One env step with auto-reset: ``(obs, state, rewards [N], done, info)``."""
        key_step, key_reset = jax.random.split(key)
        obs, next_state, rewards, done, info = self.step_env(key_step, state, actions)
        obs, next_state = self._auto_reset(done, key_reset, obs, next_state)
        return obs, next_state, rewards, done, info

    @functools.cached_property
    def _auto_reset(self):
        """``(done, key, obs, state) -> (obs, state)`` with the finished envs replaced by
        ``reset(key)``; batched over any leading axes, also under ``jax.vmap`` (see
        :func:`marbler_jax.xp.vmap_in_place`)."""
        return vmap_in_place(self._reset_where)

    def _reset_where(self, done, key, obs, state):
        """Replace the envs where ``done [...]`` by a fresh ``reset(key)``.

        A batch of ``B >= 64`` envs resets only the finished ones when at most ``B // 16`` finished
        this step (the usual case: episodes end at different steps): their keys are gathered, reset,
        and scattered back. More finished envs (e.g. a whole batch truncated at the same step) take
        the plain path that resets every env and selects. Both give the same result (to float
        rounding): each env's reset depends only on its own key.
        """
        batch = done.shape
        size = math.prod(batch)
        flat = jax.tree_util.tree_map(lambda a: a.reshape((size,) + a.shape[len(batch):]), (done, key, obs, state))
        done, key, obs, state = flat
        capacity = size // 16

        def reset_all(_):
            reset_obs, reset_state = jax.vmap(self.reset)(key)
            select = lambda r, s: jnp.where(done.reshape((size,) + (1,) * (s.ndim - 1)), r, s)
            return select(reset_obs, obs), jax.tree_util.tree_map(select, reset_state, state)

        def reset_finished(_):
            (slots,) = jnp.nonzero(done, size=capacity, fill_value=size)   # size = "no env": dropped
            reset_obs, reset_state = jax.vmap(self.reset)(jnp.take(key, slots, axis=0, mode="clip"))
            put = lambda s, r: s.at[slots].set(r, mode="drop")
            return put(obs, reset_obs), jax.tree_util.tree_map(put, state, reset_state)

        if size < 64:
            obs, state = reset_all(None)
        else:
            obs, state = jax.lax.cond(jnp.sum(done) <= capacity, reset_finished, reset_all, None)
        return jax.tree_util.tree_map(lambda a: a.reshape(batch + a.shape[1:]), (obs, state))

    @property
    def num_segments(self) -> int:
        """Control refreshes per env step: ``ceil(update_frequency / control_period)``."""
        return -(-self.config.update_frequency // self.config.control_period)

    def step_env(self, key: jax.Array, state: EnvState, actions: jax.Array, velocities=None):
        """One env step without auto-reset (``key`` is unused: the dynamics are deterministic).

        ``velocities [num_segments, N, 2]`` optionally replaces the controller's output at each
        control refresh (replaying a recorded command sequence, e.g. from MARBLER or the robots).
        """
        del key
        actions = self._check_actions(actions)
        goals = self.scenario.goals(state.poses, state.scenario, actions)
        poses, collided, outside, dist, multipliers = self.run_ticks(
            state.poses, goals, velocities, state.cbf_multipliers)
        scenario_state, rewards, done, violated, obs, step = finish_step(
            self.scenario, poses, state.scenario, actions, collided, outside, state.step)
        episode_return = state.episode_return + self.scenario.team_reward(rewards)
        next_state = EnvState(
            poses=poses, scenario=scenario_state, step=step, episode_return=episode_return,
            collided=state.collided | collided, out_of_bounds=state.out_of_bounds | outside,
            cbf_multipliers=multipliers,
        )
        info = {
            "collisions": collided,
            "out_of_bounds": outside,
            "violation": violated,
            "steps": step,
            "returned_episode": done,
            "episode_return": episode_return,
            "episode_collided": next_state.collided,
            "episode_out_of_bounds": next_state.out_of_bounds,
            "dist_travelled": dist,
            **{k: jnp.asarray(v) for k, v in self.scenario.metrics(scenario_state).items()},
        }
        return obs, next_state, rewards, done, info

    # --- the control loop --------------------------------------------------------------------
    def velocities(self, poses, goals, multipliers=None):
        """MARBLER's controller: SI position control of the projection point -> CBF -> (v, omega).

        With ``multipliers`` (the last refresh's, see :class:`EnvState`) the barrier is warm-started
        and ``(velocities, multipliers)`` is returned; without, the velocities only.
        """
        if multipliers is None:
            return control(poses, goals, self.barrier)
        return control_warm(poses, goals, self.barrier, multipliers)

    def run_ticks(self, poses, goals, velocities=None, multipliers=None):
        """``update_frequency`` ticks with control refresh every ``control_period`` ticks.

        Returns ``(poses, collided, out_of_bounds, dist_travelled [N], multipliers)``. With
        ``penalize_violations`` the motion stops after the first violating tick. ``multipliers``
        warm-start the barrier at each refresh and come back updated (``None`` stays ``None``).
        Batched over any leading axes of ``poses [..., N, 3]`` and ``goals [..., N, 2]``, also under
        ``jax.vmap``: the loop runs on batch-minor arrays (see :meth:`_ticks`).
        """
        if velocities is not None:
            velocities = jnp.asarray(velocities, poses.dtype)
            expected = tuple(poses.shape[:-2]) + (self.num_segments, self.num_agents, 2)
            if velocities.shape != expected:
                raise ValueError(f"velocities must have shape {expected}, got {tuple(velocities.shape)}")
        return self._tick_loop(poses, goals, velocities, multipliers)

    @functools.cached_property
    def _tick_loop(self):
        return vmap_in_place(self._ticks)

    def _ticks(self, poses, goals, velocities, multipliers):
        """:meth:`run_ticks` on leading batch axes ``[*batch]``, folded into the minor axis ``B``.

        Every per-tick op (controller, barrier sweeps, integration, checks) is then a unit-stride vector
        op over the whole batch, and the heading is carried as its unit vector ``(cos, sin)``, advanced by
        a rotation each tick by the turn ``dt * omega`` (:func:`marbler_jax.physics.turn`: no trig call).
        """
        batch = poses.shape[:-2]
        nb = len(batch)
        fold = lambda a: None if a is None else to_minor(a, nb, jnp)   # noqa: E731
        unfold = lambda a: None if a is None else from_minor(a, batch, jnp)   # noqa: E731
        x, y, theta = (fold(poses[..., k]) for k in range(3))
        goal_x, goal_y = fold(goals[..., 0]), fold(goals[..., 1])
        commands = fold(velocities)                                           # [S, N, 2, B] or None
        warm = None if multipliers is None else Multipliers(*(fold(v) for v in multipliers))
        total, period = self.config.update_frequency, self.config.control_period
        stop = self.config.penalize_violations
        full, rest = divmod(total, period)
        flag = jnp.zeros(x.shape[1:], bool)
        carry = (x, y, jnp.cos(theta), jnp.sin(theta), flag, flag, flag, jnp.zeros_like(x), warm)

        def segment(carry, length, index):
            x, y, c, s, stopped, hit_any, out_any, dist, warm = carry
            if commands is not None:
                v, w = commands[index, :, 0], commands[index, :, 1]
            else:
                v, w, updated = controllers.marbler_velocities_minor(x, y, c, s, goal_x, goal_y, self.barrier, warm)
                if warm is not None:   # the multipliers keep their dtype (a float32 state stays float32 under x64)
                    warm = jax.tree_util.tree_map(lambda new, old: new.astype(old.dtype), updated, warm)
            v, w = physics.threshold_vw(self.params, v, w, jnp)
            nx, ny, nc, ns, hit, out, moved = physics.held_ticks_minor(self.params, x, y, c, s, v, w, length, stop)
            live = ~stopped
            x, y, c, s = (jnp.where(live, new, old) for new, old in ((nx, x), (ny, y), (nc, c), (ns, s)))
            dist = dist + jnp.where(live, moved, 0)
            hit_any = hit_any | (live & hit)
            out_any = out_any | (live & out)
            if stop:
                stopped = stopped | hit | out
            return (x, y, c, s, stopped, hit_any, out_any, dist, warm), None

        if full:
            carry, _ = jax.lax.scan(lambda c, i: segment(c, period, i), carry, jnp.arange(full))
        if rest:
            carry, _ = segment(carry, rest, full)
        x, y, c, s, _, hit_any, out_any, dist, warm = carry
        new_poses = unfold(jnp.stack([x, y, jnp.arctan2(s, c)], axis=1))
        warm = None if warm is None else Multipliers(*(unfold(v) for v in warm))
        return new_poses, unfold(hit_any), unfold(out_any), unfold(dist), warm

    def _check_actions(self, actions):
        """Shape/dtype errors always raise; out-of-range values raise when concrete (outside jit).

        Under ``jit`` values cannot be inspected, so out-of-range actions are clipped there, unless the
        caller runs under :func:`checked` (``jax.experimental.checkify``), which raises instead.
        """
        if not isinstance(actions, jax.core.Tracer):
            values = np.asarray(jax.device_get(actions))
            if values.size and np.issubdtype(values.dtype, np.integer) and (
                    values.min() < 0 or values.max() >= self.num_actions):
                raise ValueError(
                    f"{self.name}: actions must be in [0, {self.num_actions}), got {values.tolist()}")
        actions = jnp.asarray(actions)
        if actions.shape != (self.num_agents,):
            raise ValueError(
                f"{self.name}: actions must have shape ({self.num_agents},) (one int per agent), "
                f"got {tuple(actions.shape)}"
            )
        if not jnp.issubdtype(actions.dtype, jnp.integer):
            raise ValueError(f"{self.name}: actions must be integers in [0, {self.num_actions}), got dtype {actions.dtype}")
        if _TRACING_CHECKED.get():
            checkify.check(jnp.all((actions >= 0) & (actions < self.num_actions)),
                           f"{self.name}: actions must be in [0, {self.num_actions}), got {{actions}}", actions=actions)
        return jnp.clip(actions.astype(jnp.int32), 0, self.num_actions - 1)


# Whether the program being traced runs under :func:`checked`. The check on traced actions is traced only
# then: checkify numbers every check it traces from a global counter, and that number is part of the
# program, so an unconditional check would make every retrace a new program that JAX's persistent
# compilation cache cannot serve (and, under vmap, adds work that only checkify reads).
_TRACING_CHECKED = contextvars.ContextVar("marbler_jax_tracing_checked", default=False)


def checked(fn):
    """``fn`` jitted with the env's checks on traced values raising: an out-of-range action, which a
    jitted ``step`` otherwise clips, raises ``checkify.JaxRuntimeError`` naming the actions. For
    debugging (it adds a host round trip per call)::

        step = marbler_jax.env.checked(jax.vmap(env.step))
        obs, state, rewards, done, info = step(keys, state, actions)
    """
    def traced_checked(*args, **kwargs):
        token = _TRACING_CHECKED.set(True)
        try:
            return fn(*args, **kwargs)
        finally:
            _TRACING_CHECKED.reset(token)

    program = jax.jit(checkify.checkify(traced_checked, errors=checkify.user_checks))

    def run(*args, **kwargs):
        error, out = program(*args, **kwargs)
        error.throw()
        return out

    return run

