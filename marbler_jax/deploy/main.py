"""Robotarium entry point of a marbler-jax submission bundle (numpy + rps only, no JAX).

Mark this file as the main file when uploading the bundle. It reads ``bundle_config.npy`` (the
scenario config the policy was trained with), the numpy policy (``policy_spec.npy`` + weights) and
the initial states sampled at export time (``initial_*.npy``), then runs ``episodes`` greedy
episodes: one ``robotarium.Robotarium(number_of_robots=N, show_figure=True, initial_conditions=...,
sim_in_real_time=True)`` per episode, as MARBLER's submissions do, with the control loop of
:mod:`marbler_jax.deploy.robotarium_loop`, and the end-of-script call of the installed rps
(``call_at_scripts_end()`` up to 2024, ``debug()`` in rps v2). One line of metrics per episode goes
to stdout.

Environment variables (for local tests, not needed on the Robotarium):

* ``MARBLER_JAX_HEADLESS=1``: no figure and not in real time.
* ``MARBLER_JAX_TRACE=DIR``: also save each episode's poses, actions and rewards to
  ``DIR/episode_<k>.npz``.
* ``MARBLER_JAX_EPISODES=K``: run only the first ``K`` episodes.
"""
from __future__ import annotations

import json
import os
import sys

import numpy as np

from marbler_jax import physics
from marbler_jax.deploy.robotarium_loop import run_episode
from marbler_jax.numpy_policy import load_policy
from marbler_jax.scenarios.base import build_config
from marbler_jax.control_loop import barrier_for

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG_FILE = "bundle_config.npy"
BUNDLE_FORMAT = "marbler-jax-bundle/1"


def load_config(folder: str = HERE) -> dict:
    """The bundle's config (JSON text stored in a numpy unicode array)."""
    config = json.loads(str(np.load(os.path.join(folder, CONFIG_FILE), allow_pickle=False)))
    if config.get("format") != BUNDLE_FORMAT:
        raise ValueError(f"{CONFIG_FILE}: format {config.get('format')!r} is not {BUNDLE_FORMAT!r}")
    return config


def check_initial_poses(poses, scenario) -> None:
    """``initial_poses.npy`` must be ``[E, N, 3]``, finite, inside the arena and free of collisions."""
    params = physics.get_params(scenario.config.physics)
    if poses.ndim != 3 or poses.shape[1:] != (scenario.num_agents, 3):
        raise ValueError(f"initial_poses.npy must be [episodes, {scenario.num_agents}, 3], got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise ValueError("initial_poses.npy holds non-finite values")
    if np.any(physics.out_of_bounds(params, poses)):
        raise ValueError(f"initial_poses.npy puts a robot outside the arena {params.arena}")
    if np.any(physics.collisions(params, poses)):
        raise ValueError("initial_poses.npy puts two robots in collision")


def build(config: dict, folder: str = HERE):
    """``(scenario, policy, barrier, initial poses [E, N, 3], initial states)`` of a bundle config."""
    import importlib

    module = importlib.import_module(config["module"])
    scenario_cls = getattr(module, config["scenario_class"])
    state_cls = getattr(module, config["state_class"])
    scenario = scenario_cls(build_config(scenario_cls.Config, config["config"]))
    policy = load_policy(folder)
    if policy.spec["num_agents"] != scenario.num_agents or policy.spec["obs_dim"] != scenario.obs_dim:
        raise ValueError(f"policy ({policy.spec['num_agents']} agents, obs {policy.spec['obs_dim']}) does not fit "
                         f"{config['scenario']} ({scenario.num_agents} agents, obs {scenario.obs_dim})")
    if policy.num_actions is not None and policy.num_actions != scenario.num_actions:
        raise ValueError(f"policy has {policy.num_actions} actions, {config['scenario']} {scenario.num_actions}")
    barrier = barrier_for(scenario.config, scenario.num_agents)
    poses = np.load(os.path.join(folder, "initial_poses.npy"), allow_pickle=False)
    check_initial_poses(poses, scenario)
    fields = {name: np.load(os.path.join(folder, f"initial_{name}.npy"), allow_pickle=False)
              for name in config["state_fields"]}
    states = [state_cls(**{name: value[k] for name, value in fields.items()}) for k in range(len(poses))]
    return scenario, policy, barrier, poses, states


def end_of_script(robotarium) -> None:
    """``call_at_scripts_end()`` (rps up to 2024) or ``debug()`` (rps v2)."""
    finish = getattr(robotarium, "call_at_scripts_end", None) or getattr(robotarium, "debug", None)
    if finish is None:
        raise AttributeError("this rps has neither call_at_scripts_end() nor debug()")
    finish()


def main() -> int:
    headless = os.environ.get("MARBLER_JAX_HEADLESS", "") == "1"
    if headless:
        os.environ.setdefault("MPLBACKEND", "Agg")
    from rps import robotarium

    config = load_config()
    scenario, policy, barrier, initial_poses, initial_states = build(config)
    episodes = len(initial_poses)
    if os.environ.get("MARBLER_JAX_EPISODES"):
        episodes = min(episodes, int(os.environ["MARBLER_JAX_EPISODES"]))
    trace = os.environ.get("MARBLER_JAX_TRACE")
    print(f"marbler-jax bundle: {config['scenario']} with {scenario.num_agents} robots, {config['algo']} policy, "
          f"{episodes} episode(s), control period {scenario.config.control_period}, "
          f"update frequency {scenario.config.update_frequency}, barrier {scenario.config.barrier_certificate}")
    for k in range(episodes):
        r = robotarium.Robotarium(number_of_robots=scenario.num_agents, show_figure=not headless,
                                  initial_conditions=np.array(initial_poses[k].T, dtype=np.float64),
                                  sim_in_real_time=not headless)
        log = run_episode(r, scenario, policy, initial_states[k], barrier)
        compute = np.asarray(log.compute_s)
        metrics = " ".join(f"{name}={value:g}" for name, value in log.metrics.items())
        print(f"episode {k + 1}/{episodes}: return={log.team_return:.3f} steps={log.steps} "
              f"violation={log.violation} collisions={log.collisions} out_of_bounds={log.out_of_bounds} {metrics} "
              f"compute_ms_mean={1e3 * compute.mean():.2f} compute_ms_max={1e3 * compute.max():.2f}", flush=True)
        if trace:
            os.makedirs(trace, exist_ok=True)
            np.savez(os.path.join(trace, f"episode_{k}.npz"), team_return=log.team_return, **log.arrays())
        end_of_script(r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
