"""One MARBLER episode on the Robotarium API (the ``rps`` simulator or the real robots), numpy only.

This is the training env's control loop (:meth:`marbler_jax.env.MarblerEnv.step_env`) with the
robots in place of :func:`marbler_jax.physics.held_ticks`; the maths is shared, not copied:
waypoints, task events, rewards and observations come from the scenario, the command from
:func:`marbler_jax.control_loop.control`, the step's closing rules from
:func:`marbler_jax.control_loop.finish_step`, the violation tests from :mod:`marbler_jax.physics`.

Per env step: the policy acts on the observation, the scenario turns actions into waypoints from the
poses at the start of the step, then for each of ``update_frequency`` Robotarium iterations:
``get_poses()`` (exactly once) -> check that pose for collisions / boundary violations (as the env
checks every pre-tick pose) -> every ``control_period`` iterations recompute the command (held in
between) -> clip to the motors' limits (:func:`marbler_jax.physics.actuator_safe`, so rps reports no
actuator error) -> ``set_velocities`` -> ``step()``. As in MARBLER (and the env), the iteration whose
pose violates still runs; with ``penalize_violations`` the env step then ends and so does the
episode. The pose after the step's last iteration is read by the next ``get_poses()``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from marbler_jax import physics
from marbler_jax.control_loop import control, control_warm, finish_step


@dataclass
class EpisodeLog:
    """What one episode did (float64 numpy arrays, one row per env step unless said otherwise).

    Attributes:
        poses: ``[T + 1, N, 3]`` poses at each decision point (row 0: the episode's first pose).
        actions: ``[T, N]`` int actions.
        rewards: ``[T, N]`` rewards.
        team_return: MARBLER's episode reward (sum of the team reward).
        violation: the episode ended on a penalized collision / boundary violation.
        collisions, out_of_bounds: some checked iteration collided / was outside the arena.
        metrics: the scenario's paper metrics at the end (e.g. ``prey_left``).
        compute_s: ``[iterations]`` seconds from ``get_poses()`` to ``set_velocities`` per iteration
            (including the policy and task update at the first iteration of each env step).
    """

    poses: list = field(default_factory=list)
    actions: list = field(default_factory=list)
    rewards: list = field(default_factory=list)
    team_return: float = 0.0
    violation: bool = False
    collisions: bool = False
    out_of_bounds: bool = False
    metrics: dict = field(default_factory=dict)
    compute_s: list = field(default_factory=list)

    @property
    def steps(self) -> int:
        return len(self.actions)

    def arrays(self) -> dict[str, np.ndarray]:
        """The log as arrays (``poses``, ``actions``, ``rewards``, ``compute_s``)."""
        return dict(poses=np.asarray(self.poses), actions=np.asarray(self.actions),
                    rewards=np.asarray(self.rewards), compute_s=np.asarray(self.compute_s))


def _read_poses(robotarium) -> np.ndarray:
    """``get_poses()`` as a robot-major float64 copy ``[N, 3]`` (rps returns its live ``[3, N]`` array)."""
    return np.array(robotarium.get_poses(), dtype=np.float64).T


def run_episode(robotarium, scenario, policy, scenario_state, barrier=None, params=None,
                clip_actuators: bool = True) -> EpisodeLog:
    """Run one episode on ``robotarium`` (an ``rps`` ``Robotarium`` created at the initial poses).

    Args:
        robotarium: object with ``get_poses() -> [3, N]``, ``set_velocities(ids, [2, N])``, ``step()``.
        scenario: the scenario (its ``config`` gives update frequency, control period, horizon).
        policy: a :class:`marbler_jax.numpy_policy.NumpyPolicy` (greedy; hidden state carried).
        scenario_state: the scenario's state at the start of the episode.
        barrier: the SI barrier (:func:`marbler_jax.control_loop.barrier_for`), ``None`` for none.
        params: physics constants for the violation tests (default: ``config.physics``).
        clip_actuators: send :func:`marbler_jax.physics.actuator_safe` commands (default); False
            sends the controller's command as it is and leaves the clipping to the simulator.

    Returns:
        the :class:`EpisodeLog`.
    """
    config = scenario.config
    params = params if params is not None else physics.get_params(config.physics)
    n = scenario.num_agents
    ids = np.arange(n)
    log = EpisodeLog()
    poses = _read_poses(robotarium)
    started = time.perf_counter()
    state = scenario_state
    obs = np.asarray(scenario.observe(poses, state), dtype=np.float64)
    if config.zero_reset_obs:
        obs = np.zeros_like(obs)
    hidden = policy.initial_hidden()
    # The barrier is warm-started from the previous refresh, exactly as in the batched env.
    multipliers = None
    if barrier is not None and config.warm_start_barrier:
        multipliers = barrier.initial_multipliers(n, (), np.float64)
    step, done = 0, False
    log.poses.append(poses)
    while not done:
        actions, hidden, _ = policy.act(np.asarray(obs, np.float32), hidden)
        actions = np.asarray(actions, dtype=np.int32)
        goals = scenario.goals(poses, state, actions)
        collided = outside = False
        for tick in range(config.update_frequency):
            if tick > 0:
                poses = _read_poses(robotarium)
                started = time.perf_counter()
            hit = bool(np.any(physics.collisions(params, poses)))
            out = bool(np.any(physics.out_of_bounds(params, poses)))
            collided, outside = collided or hit, outside or out
            if tick % config.control_period == 0:
                if multipliers is None:
                    velocities = np.asarray(control(poses, goals, barrier), dtype=np.float64)
                else:
                    velocities, multipliers = control_warm(poses, goals, barrier, multipliers)
                    velocities = np.asarray(velocities, dtype=np.float64)
            command = physics.actuator_safe(velocities) if clip_actuators else velocities
            command = np.where(np.isfinite(command), command, 0.0)   # never send a non-finite velocity
            robotarium.set_velocities(ids, np.array(command.T))
            log.compute_s.append(time.perf_counter() - started)
            robotarium.step()
            if config.penalize_violations and (hit or out):
                break   # as MARBLER: the violating iteration still runs, then the env step ends
        poses = _read_poses(robotarium)
        started = time.perf_counter()   # the next iteration's compute starts here (policy, waypoints)
        state, rewards, done, _, obs, step = finish_step(scenario, poses, state, actions, collided, outside, step)
        done = bool(done)
        log.actions.append(actions)
        log.rewards.append(np.asarray(rewards, dtype=np.float64))
        log.poses.append(poses)
        log.team_return += float(scenario.team_reward(np.asarray(rewards)))
        log.collisions |= collided
        log.out_of_bounds |= outside
        log.violation = bool(config.penalize_violations and (collided or outside))
    log.metrics = {k: float(v) for k, v in scenario.metrics(state).items()}
    return log


__all__ = ["EpisodeLog", "run_episode"]
