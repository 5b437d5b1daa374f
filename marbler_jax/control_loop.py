"""MARBLER's control loop -- one env step's controller, barrier and closing rules -- shared by the JAX env
and the numpy Robotarium bundle.

Everything here works on numpy *or* JAX arrays (see :mod:`marbler_jax.xp`): the batched env
(:mod:`marbler_jax.env`) calls it inside ``jit``/``vmap``, and the submission bundle's ``main.py``
calls the very same functions on the poses the Robotarium returns. What differs between the two is
only who moves the robots: :func:`marbler_jax.physics.held_ticks` in training, ``rps`` (or the real
robots) in deployment.
"""
from __future__ import annotations

import dataclasses

from marbler_jax import cbf, controllers
from marbler_jax.xp import namespace


ROBOTS_CONTROL_PERIOD = 1
"""The robots' loop: controller and barrier every Robotarium iteration (what ``marbler-jax export``
deploys unless told otherwise, and the loop ``evaluate`` compares a policy's training loop with)."""

MARBLER_SAFETY_RADIUS = 0.2
"""MARBLER's barrier radius between projection points [m] (its ``safe`` setting), also used for ``safe_v2``."""

ENV_RELAXATION = 1.5
"""Over-relaxation of the env's barrier sweeps when ``cbf_relaxation`` is not set.

The robots an env certificate keeps apart pose well-conditioned problems, on which 1.5 converges in
fewer sweeps than the 1.7 that :func:`marbler_jax.cbf.default_relaxation` uses above 10 robots (that
value suits the stiff, overlapping golden cases). On random-policy Warehouse trajectories with
12-32 robots, 1.5 matches the 400-sweep reference at least as often as 1.7 at budgets of 8-40 sweeps,
and far more often at small budgets (``scripts/bench_cbf_env.py --relaxation``, BENCHMARKS.md). Up to 10 robots both defaults are 1.5.
"""


def default_cbf_iterations(num_agents: int, warm_start: bool) -> int:
    """Barrier sweeps per control refresh when ``cbf_iterations`` is not set.

    Chosen with ``scripts/bench_cbf_env.py`` (BENCHMARKS.md) on random-policy Warehouse
    trajectories with 4-32 robots and relaxation :data:`ENV_RELAXATION`, so that >= 99.9 % of
    refreshes match a 400-sweep solve within the golden tolerance. Cold (refreshes
    ``control_period = 15`` ticks apart, where warm starts do not help: the robots move too far in
    between): ``8 + N`` up to 12 robots, 20 from 12 to 20 robots, ``N`` beyond. Warm-started (the
    default at ``control_period = 1``, where consecutive refreshes solve nearly the same problem):
    ``3 + 3N/4`` up to 9 robots, 10 from 10 to 32 robots (measured), ``N / 3`` beyond (extrapolated).
    """
    n = num_agents
    if warm_start:
        return max(min(3 + (3 * n) // 4, 10), n // 3)
    return max(min(8 + n, 20), n)


def barrier_for(config, num_agents: int):
    """The SI barrier for ``config.barrier_certificate`` (``None`` when ``"none"``).

    ``"safe"`` is MARBLER's default (certificate2 with safety radius 0.2), ``"default"`` MARBLER's
    ``barrier_certificate: default`` (certificate, radius 0.17), ``"safe_v2"`` the Robotarium's rps v2
    certificate (``si_v2``) at MARBLER's radius 0.2; other names are :func:`marbler_jax.cbf.make_barrier`
    kinds. Iterations: ``config.cbf_iterations`` or :func:`default_cbf_iterations` (the v2 kinds:
    :func:`marbler_jax.cbf.default_iterations`, since they stop a team whose last iterate is not
    feasible, a decision that needs a converged solve); relaxation: ``config.cbf_relaxation`` or
    :data:`ENV_RELAXATION`.
    """
    kind = config.barrier_certificate
    if kind == "none":
        return None
    cbf_kind = {"safe": "si2", "default": "si", "safe_v2": "si_v2"}.get(kind, kind)
    iterations = config.cbf_iterations
    if iterations is None and cbf_kind not in cbf.V2_KINDS:     # v2: make_barrier's own default
        iterations = default_cbf_iterations(num_agents, config.warm_start_barrier)
    relaxation = ENV_RELAXATION if config.cbf_relaxation is None else config.cbf_relaxation
    solver = dict(iterations=iterations, relaxation=relaxation)
    radius = config.cbf_safety_radius
    if radius is None and kind in ("safe", "safe_v2"):
        radius = MARBLER_SAFETY_RADIUS
    if radius is not None:
        solver["safety_radius"] = radius
    return cbf.make_barrier(cbf_kind, **solver)


def control(poses, goals, barrier):
    """One control refresh: SI position control of the projection point -> barrier -> (v, omega) ``[N, 2]``."""
    return controllers.marbler_velocities(poses, goals, barrier)


def control_warm(poses, goals, barrier, multipliers):
    """:func:`control` with the barrier warm-started from ``multipliers`` (those of the previous
    refresh); returns ``(velocities [N, 2], multipliers)``."""
    return controllers.marbler_velocities_warm(poses, goals, barrier, multipliers)


def select_state(cond, old, new):
    """Field-wise ``where(cond, old, new)`` of two scenario states (dataclasses of arrays)."""
    xp = namespace(*(getattr(new, f.name) for f in dataclasses.fields(new)))
    return dataclasses.replace(new, **{
        f.name: xp.where(cond, getattr(old, f.name), getattr(new, f.name)) for f in dataclasses.fields(new)})


def finish_step(scenario, poses, scenario_state, actions, collided, outside, step):
    """Close one env step after its ticks ran (MARBLER's ``roboEnv.step`` tail).

    With ``penalize_violations`` a collision or boundary violation voids the step's task events,
    gives every agent ``scenario.violation_reward`` and ends the episode. Otherwise the scenario's
    task events apply; the episode ends when the step counter exceeds ``max_episode_steps`` or the
    task is complete. The observation shows the step's events even on a violation step (MARBLER
    applies them, then checks for the violation; only the reward and the next state void them).

    Args:
        scenario: a :class:`marbler_jax.scenarios.base.Scenario`.
        poses: ``[N, 3]`` poses after the step's ticks.
        scenario_state: the scenario state at the start of the step.
        actions: ``[N]`` int actions of the step.
        collided, outside: whether a checked tick of the step violated (bool scalars).
        step: steps taken before this one (int).

    Returns:
        ``(scenario_state, rewards [N], done, violated, obs [N, obs_dim], step + 1)``.
    """
    xp = namespace(poses)
    config = scenario.config
    dtype = poses.dtype
    violated = (collided | outside) & config.penalize_violations
    applied, task_rewards, completed = scenario.update(poses, scenario_state, actions)
    new_state = select_state(violated, scenario_state, applied)
    rewards = xp.where(violated, xp.asarray(scenario.violation_reward, dtype=dtype), xp.asarray(task_rewards, dtype=dtype))
    step = step + 1
    done = violated | (step > config.max_episode_steps) | (completed & ~violated)
    seen = scenario.observation_state(scenario_state, applied)
    obs = xp.asarray(scenario.observe(poses, seen), dtype=dtype)
    return new_state, rewards, done, violated, obs, step


__all__ = ["ROBOTS_CONTROL_PERIOD", "MARBLER_SAFETY_RADIUS", "ENV_RELAXATION", "default_cbf_iterations", "barrier_for", "control", "control_warm", "select_state", "finish_step"]
