"""MARBLER's own code as an oracle: run numpy policies (or random actions) in MARBLER's scenarios.

Runs in a Python with MARBLER's stack and without JAX (see ``../shared/marbler/MARBLER-README-for-tests.md``):

    python3 -m venv .marbler-venv
    .marbler-venv/bin/pip install "numpy==1.24.4" cvxopt scipy "matplotlib<3.9" pyyaml imageio "gym==0.26.2" \\
        robotarium-python-simulator
    .marbler-venv/bin/pip install --no-deps -e ../shared/marbler
    .marbler-venv/bin/python scripts/marbler_oracle.py evaluate --scenario PredatorCapturePrey \\
        --policy results/paper-models/policies/predator_capture_prey-vdn --episodes 500 --out pcp-vdn.json

It is a check beside marbler-jax, not a part of it. Two things make MARBLER's code run here as it ran for the
paper (both in this interpreter only, nothing is changed on disk):

* ``torch`` and ``tensorflow``, which ``robotarium_gym.utilities.misc`` imports at module level and the env
  path never uses, are stand-in modules; the policy is a marbler-jax numpy policy
  (:mod:`marbler_jax.numpy_policy`, whose forward pass the test suite checks against MARBLER's torch agents).
* rps 6bb184e's violation bookkeeping: PyPI's ``robotarium-python-simulator`` has rps 6bb184e's dynamics but
  counts violations as integers, without the collision offset, where MARBLER's ``roboEnv`` reads per-robot
  dictionaries. ``_validate`` is replaced by 6bb184e's (``../shared/spec/robotarium.md`` section 5): a robot
  is out of bounds when its centre leaves [-1.6, 1.6] x [-1, 1], two robots collide when the points 0.025 m
  ahead of them are at most 0.135 m apart, counts per robot in one dictionary shared by every Robotarium
  instance (rps's mutable-default dictionary, cleared when an env is created).

``evaluate`` writes per-episode metrics as marbler-jax's evaluation counts them: ``reward`` (team return: the
shared reward once, or the sum of the robots' rewards), ``steps`` (episode length; the step limit + 1 when a
violation ended the episode, as the paper counts), ``collisions`` / ``out_of_bounds`` (100 for an episode
that a violation of that kind ended, else 0) and ``prey_left`` / ``material_left``.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import random
import sys
import time
import types
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MARBLER = REPO.parent / "shared" / "marbler"
SCENARIOS = {          # MARBLER class name -> (module, class, team-reward kind)
    "PredatorCapturePrey": ("PredatorCapturePrey.PredatorCapturePrey", "PredatorCapturePrey", "shared"),
    "Warehouse": ("Warehouse.warehouse", "Warehouse", "sum"),
    "MaterialTransport": ("MaterialTransport.MaterialTransport", "MaterialTransport", "shared"),
    "ArcticTransport": ("ArcticTransport.ArcticTransport", "ArcticTransport", "shared"),
    "Simple": ("Simple.simple", "simple", "sum"),
}
MARBLER_JAX_NAMES = {"predator_capture_prey": "PredatorCapturePrey", "warehouse": "Warehouse",
                     "material_transport": "MaterialTransport", "arctic_transport": "ArcticTransport",
                     "simple_navigation": "Simple"}

_ERRORS: dict = {}


def _validate_6bb184e(self, errors=_ERRORS):
    """rps 6bb184e's ``RobotariumABC._validate``: per-robot boundary and collision counts, one shared dict
    (vectorised: the counts are rps's, the loops are numpy's)."""
    p = self.poses
    outside = (p[0] < -1.6) | (p[0] > 1.6) | (p[1] < -1.0) | (p[1] > 1.0)
    for i in np.flatnonzero(outside):
        errors.setdefault("boundary", {})
        errors["boundary"][int(i)] = errors["boundary"].get(int(i), 0) + 1
        errors["boundary_string"] = "iteration(s) robots were outside the boundaries."
    centres = p[:2] + 0.025 * np.vstack((np.cos(p[2]), np.sin(p[2])))
    gaps = np.sqrt(((centres[:, :, None] - centres[:, None, :]) ** 2).sum(0))
    for j, k in zip(*np.nonzero(np.triu(gaps <= 0.135, 1))):
        errors.setdefault("collision", {})
        for robot in (int(j), int(k)):
            errors["collision"][robot] = errors["collision"].get(robot, 0) + 1
        errors["collision_string"] = "iteration(s) where robots collided."
    if np.any(np.abs(self._uni_to_diff(self.velocities)) > self.max_wheel_velocity):
        errors["actuator"] = errors.get("actuator", 0) + 1
        errors["actuator_string"] = "iteration(s) where the actuator limits were exceeded."
    return errors


TIGHT_QP = {"reltol": 1e-10, "abstol": 1e-10, "feastol": 1e-10, "maxiters": 200}
"""cvxopt options of a near-exact barrier QP (rps sets reltol = feastol = 1e-2 and 50 iterations at import)."""


def _import_marbler(tight_qp: bool = False):
    """MARBLER's scenario package with torch/tensorflow stand-ins and rps 6bb184e's bookkeeping; with
    ``tight_qp`` the barrier's cvxopt QP solved near-exactly (:data:`TIGHT_QP`) instead of rps's loose way."""
    for name in ("torch", "tensorflow"):
        sys.modules.setdefault(name, types.ModuleType(name))
    sys.path.insert(0, str(MARBLER))
    import rps.robotarium_abc as abc
    abc.RobotariumABC._validate = _validate_6bb184e
    if tight_qp:
        import rps.utilities.barrier_certificates as certificates
        certificates.options.update(TIGHT_QP)
    import importlib
    return importlib


def make_env(scenario: str, seed: int, robots_loop: bool = False, tight_qp: bool = False):
    """MARBLER's ``scenario`` (class name or marbler-jax name) from its ``config.yaml``: no figure, ``seed``
    for numpy's global generator (MARBLER draws its start states from it), and with ``robots_loop`` the
    per-iteration controller refresh (``robotarium: True``) instead of every 15 iterations."""
    import yaml

    scenario = MARBLER_JAX_NAMES.get(scenario, scenario)
    if scenario not in SCENARIOS:
        raise SystemExit(f"unknown scenario {scenario!r}; one of {sorted(SCENARIOS)}")
    importlib = _import_marbler(tight_qp)
    from robotarium_gym.utilities.misc import objectview

    module, cls, reward_kind = SCENARIOS[scenario]
    folder = MARBLER / "robotarium_gym" / "scenarios" / scenario
    config = yaml.safe_load((folder / "config.yaml").read_text())
    config.update(show_figure_frequency=-1, save_gif=False, enable_logging=False, real_time=False, seed=-1,
                  robotarium=bool(robots_loop))
    _ERRORS.clear()
    np.random.seed(seed)
    random.seed(seed)                 # ArcticTransport draws its goal column with Python's random
    env_class = getattr(importlib.import_module(f"robotarium_gym.scenarios.{module}"), cls)
    with contextlib.redirect_stdout(io.StringIO()):
        env = env_class(objectview(config))
    return env, config, reward_kind


def _left(env, scenario: str) -> dict:
    if scenario == "PredatorCapturePrey":
        return {"prey_left": float(env.num_prey - sum(env.prey_captured))}
    if scenario == "MaterialTransport":
        return {"material_left": float(env.zone1_load + env.zone2_load + sum(a.load for a in env.agents))}
    return {}


def run_episodes(scenario: str, episodes: int, seed: int, policy=None, robots_loop: bool = False,
                 record_steps: int = 0, tight_qp: bool = False):
    """``episodes`` episodes of MARBLER's ``scenario`` with a numpy ``policy`` (random actions when None);
    returns per-episode metrics and, with ``record_steps``, the first steps' observations."""
    scenario = MARBLER_JAX_NAMES.get(scenario, scenario)
    env, config, reward_kind = make_env(scenario, seed, robots_loop, tight_qp)
    rng = np.random.default_rng(seed)
    num_actions = int(config["n_actions"])
    limit = int(config["max_episode_steps"])
    metrics: dict[str, list] = {}
    recorded = []
    quiet = io.StringIO()
    for _ in range(episodes):
        with contextlib.redirect_stdout(quiet):
            obs = np.asarray(env.reset(), np.float32)
        hidden = None if policy is None else policy.initial_hidden()
        total, message, episode_obs = 0.0, "", []
        for step in range(limit + 1):
            if len(episode_obs) < record_steps:
                episode_obs.append(obs)
            if policy is None:
                actions = rng.integers(0, num_actions, size=len(obs))
            else:
                actions, hidden, _ = policy.act(obs, hidden)
            with contextlib.redirect_stdout(quiet):
                obs, reward, done, info = env.step(np.asarray(actions))
            obs = np.asarray(obs, np.float32)
            total += float(reward[0]) if reward_kind == "shared" else float(np.sum(reward))
            message = info.get("message") or ""
            if isinstance(info.get("remaining"), str):        # Simple reports its violation as "remaining"
                message = info["remaining"]
            if done[0]:
                break
        quiet.seek(0)
        quiet.truncate()
        violated = message != ""
        row = {"reward": total, "steps": float(limit + 1 if violated else step + 1),
               "collisions": 100.0 * ("collision" in message), "out_of_bounds": 100.0 * ("boundary" in message),
               **_left(env, scenario)}
        for key, value in row.items():
            metrics.setdefault(key, []).append(value)
        if record_steps:
            recorded.append(np.stack(episode_obs))
    return metrics, recorded


_TICKS: list = []


def episode_starts(scenario: str, episodes: int, seed: int) -> list[dict]:
    """The starts of the ``episodes`` episodes that ``evaluate --seed`` (or ``trace --seed``) plays with a policy,
    in :mod:`marbler_jax_rl.marbler_starts`' layout: ``reset_poses [3, N]``, ``reset_state`` and ``reset_agents``.
    MARBLER draws a start at each ``reset()`` from the generators :func:`make_env` seeds, and a policy's episode
    draws nothing from them, so resetting alone gives the same sequence (``tests/test_marbler_parity.py``)."""
    env, _, _ = make_env(scenario, seed)
    starts = []
    for _ in range(episodes):
        with contextlib.redirect_stdout(io.StringIO()):
            env.reset()
        start = current_start(env)
        starts.append(dict(start, reset_poses=start["reset_poses"].tolist()))
    return starts


def current_start(env) -> dict:
    """The start MARBLER's scenario ``env`` holds after ``reset()``: ``reset_poses [3, N]`` (a copy),
    ``reset_state`` and ``reset_agents`` (the scenario's and each agent's numeric attributes)."""
    return {"reset_poses": np.array(env.agent_poses, dtype=float, copy=True), "reset_state": _numeric_state(env),
            "reset_agents": [_numeric_state(a) for a in getattr(env, "agents", [])]}


def _record_ticks() -> None:
    """Record every ``Robotarium.step`` call: the velocity it integrates and the pose after it."""
    import rps.robotarium as robotarium

    if getattr(robotarium.Robotarium.step, "recording", False):
        return
    original = robotarium.Robotarium.step

    def step(self):
        velocities = np.array(self.velocities, dtype=float, copy=True)
        result = original(self)
        _TICKS.append((np.array(self.poses, dtype=float, copy=True), velocities))
        return result

    step.recording = True
    robotarium.Robotarium.step = step


def _plain(value):
    """``value`` as JSON (numbers, bools, nested lists), or None when it is not plain data."""
    if isinstance(value, (bool, int, float, np.bool_, np.integer, np.floating)):
        return value.item() if isinstance(value, np.generic) else value
    if isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
        return value.tolist()
    if isinstance(value, (list, tuple)):
        items = [_plain(v) for v in value]
        return None if any(i is None for i in items) else items
    return None


def _numeric_state(obj) -> dict:
    return {k: v for k, v in ((k, _plain(v)) for k, v in vars(obj).items()) if v is not None}


def trace_episodes(scenario: str, episodes: int, seed: int, policy=None, tight_qp: bool = False) -> dict[str, np.ndarray]:
    """Whole MARBLER episodes in the layout of ``../shared/golden/rollouts`` (README section (d)): per episode
    ``e{i}_`` arrays ``actions``, ``reset_poses``, ``obs``, ``rewards``, ``dones``, ``poses``, ``iter_poses``,
    ``iter_vels``, ``iter_index``, and ``meta`` (JSON) with each episode's ``reset_state``, ``reset_agents``
    (numeric attributes after reset) and ``step_info`` (message / remaining per step)."""
    scenario = MARBLER_JAX_NAMES.get(scenario, scenario)
    _record_ticks()
    env, config, _ = make_env(scenario, seed, tight_qp=tight_qp)
    rng = np.random.default_rng(seed)
    arrays, meta = {}, {"config": {k: v for k, v in config.items() if _plain(v) is not None or isinstance(v, str)},
                        "episodes": []}
    quiet = io.StringIO()
    for e in range(episodes):
        _TICKS.clear()
        with contextlib.redirect_stdout(quiet):
            obs = np.asarray(env.reset(), np.float32)
        tag = f"e{e}"
        start = current_start(env)
        reset_poses = start.pop("reset_poses")
        episode = {"tag": tag, **start, "step_info": []}
        index, rows = [len(_TICKS)], {"actions": [], "obs": [], "rewards": [], "dones": [], "poses": []}
        hidden = None if policy is None else policy.initial_hidden()
        for _ in range(int(config["max_episode_steps"]) + 1):
            if policy is None:
                actions = rng.integers(0, int(config["n_actions"]), size=len(obs))
            else:
                actions, hidden, _ = policy.act(obs, hidden)
            with contextlib.redirect_stdout(quiet):
                obs, reward, done, info = env.step(np.asarray(actions))
            obs = np.asarray(obs, np.float32)
            index.append(len(_TICKS))
            for key, value in (("actions", actions), ("obs", obs), ("rewards", reward), ("dones", done),
                               ("poses", env.agent_poses)):
                rows[key].append(np.array(value, copy=True))
            episode["step_info"].append({k: _plain(v) if _plain(v) is not None else v for k, v in info.items()
                                         if k in ("message", "remaining")})
            if done[0]:
                break
        quiet.seek(0)
        quiet.truncate()
        for key, value in rows.items():
            arrays[f"{tag}_{key}"] = np.stack(value)
        arrays[f"{tag}_reset_poses"] = reset_poses
        arrays[f"{tag}_iter_poses"] = np.stack([p for p, _ in _TICKS])
        arrays[f"{tag}_iter_vels"] = np.stack([v for _, v in _TICKS])
        arrays[f"{tag}_iter_index"] = np.asarray(index)
        meta["episodes"].append(episode)
    arrays["meta"] = np.array(json.dumps(meta))
    return arrays


def _load_policy(folder):
    sys.path.insert(0, str(REPO))
    from marbler_jax.numpy_policy import load_policy

    return load_policy(folder)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    ev = sub.add_parser("evaluate", help="per-episode metrics of a numpy policy (or random actions) in MARBLER")
    ev.add_argument("--scenario", required=True)
    ev.add_argument("--policy", default=None, help="numpy policy folder (default: uniform random actions)")
    ev.add_argument("--episodes", type=int, default=100)
    ev.add_argument("--seed", type=int, default=0)
    ev.add_argument("--robots-loop", action="store_true", help="refresh controller and barrier every iteration")
    ev.add_argument("--tight-qp", action="store_true",
                    help="solve the barrier's QP near-exactly (rps solves it loosely: reltol/feastol 1e-2, 50 "
                         "iterations), to tell the solver's share of a difference from the rest")
    ev.add_argument("--out", required=True, help="JSON file to write")
    rec = sub.add_parser("record", help="observations of random-action episodes (an .npz of [T, N, D] arrays)")
    rec.add_argument("--scenario", required=True)
    rec.add_argument("--episodes", type=int, default=2)
    rec.add_argument("--steps", type=int, default=20)
    rec.add_argument("--seed", type=int, default=0)
    rec.add_argument("--out", required=True)
    tr = sub.add_parser("trace", help="whole episodes with every simulator tick (golden-rollout layout, .npz)")
    tr.add_argument("--scenario", required=True)
    tr.add_argument("--policy", default=None, help="numpy policy folder (default: uniform random actions)")
    tr.add_argument("--episodes", type=int, default=10)
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--tight-qp", action="store_true", help="as evaluate --tight-qp")
    tr.add_argument("--out", required=True)
    st = sub.add_parser("starts", help="the start states of the episodes evaluate/trace --seed play with a policy "
                                       "(JSON)")
    st.add_argument("--scenario", required=True)
    st.add_argument("--episodes", type=int, default=100)
    st.add_argument("--seed", type=int, default=0)
    st.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    if args.command == "starts":
        starts = episode_starts(args.scenario, args.episodes, args.seed)
        Path(args.out).write_text(json.dumps(dict(scenario=MARBLER_JAX_NAMES.get(args.scenario, args.scenario),
                                                  seed=args.seed, starts=starts)))
        return
    if args.command == "trace":
        policy = None if args.policy is None else _load_policy(args.policy)
        np.savez_compressed(args.out, **trace_episodes(args.scenario, args.episodes, args.seed, policy, args.tight_qp))
        return
    if args.command == "record":
        _, recorded = run_episodes(args.scenario, args.episodes, args.seed, record_steps=args.steps)
        np.savez_compressed(args.out, **{f"episode{i}": obs for i, obs in enumerate(recorded)})
        return
    policy = None if args.policy is None else _load_policy(args.policy)
    start = time.perf_counter()
    metrics, _ = run_episodes(args.scenario, args.episodes, args.seed, policy, args.robots_loop,
                              tight_qp=args.tight_qp)
    seconds = time.perf_counter() - start
    result = dict(scenario=MARBLER_JAX_NAMES.get(args.scenario, args.scenario), policy=args.policy,
                  episodes=args.episodes, seed=args.seed, loop="robots" if args.robots_loop else "marbler",
                  qp="tight" if args.tight_qp else "rps",
                  seconds=round(seconds, 1), episodes_metrics=metrics)
    Path(args.out).write_text(json.dumps(result))
    print(f"{args.scenario}: {args.episodes} episodes in {seconds:.0f} s, reward {np.mean(metrics['reward']):.2f}")


if __name__ == "__main__":
    main()
