"""Write a Robotarium submission bundle: a flat folder that runs a numpy policy with numpy + rps only.

Contents (every file has an extension the Robotarium accepts):

* ``main.py`` -- the entry point (mark it as the main file when uploading);
* ``robotarium_loop.py``, ``control_loop.py``, ``physics.py``, ``controllers.py``, ``cbf.py``, ``xp.py``,
  ``numpy_policy.py``, ``scenario_base.py`` and the scenario's module -- the package's own modules,
  flattened by :mod:`marbler_jax.deploy.flatten` (flat imports, no JAX);
* ``policy_spec.npy`` and one ``.npy`` per weight tensor (:mod:`marbler_jax.numpy_policy`);
* ``bundle_config.npy`` -- the scenario config the policy was trained with (same control period,
  barrier, update frequency, horizon) plus what ``main.py`` needs to rebuild the scenario;
* ``initial_poses.npy`` ``[E, N, 3]`` and ``initial_<field>.npy`` -- the start states of the ``E``
  episodes, sampled at export time with the env's own ``reset`` (JAX randomness stays in training;
  the deployed run is reproducible and can be replayed in the JAX env from the same states); only starts
  that the Robotarium's drive-in can reach (:func:`drive_in_reachable`).

The folder is written under a temporary name, checked with
:func:`marbler_jax.deploy.flatten.check_bundle_folder`, and renamed into place.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import tempfile
from pathlib import Path

import jax
import numpy as np

from marbler_jax.deploy.flatten import CORE_MODULES, check_bundle_folder, flatten_modules
from marbler_jax.deploy.main import BUNDLE_FORMAT, CONFIG_FILE


# rps v2 (the current Robotarium) drives the robots from the chargers to the initial poses under
# create_uni_barrier_certificate(): a 0.15 m safety radius between the points 0.05 m ahead of the robots, widened
# by twice that projection. Two initial poses whose points are closer than that are seldom reached together (the
# drive-in mostly loops forever, and the Robotarium rejects experiments that cannot reach their initial conditions).
DRIVE_IN_PROJECTION = 0.05                          # m
DRIVE_IN_SPACING = 0.15 + 2 * DRIVE_IN_PROJECTION   # m
MAX_DRAWS = 100                                     # rounds of ``episodes`` reset keys before giving up


def deployment_settings(control_period: int | None = 1) -> dict:
    """Env settings (on top of a policy's own, see :func:`marbler_jax.scenarios.base.merge_settings`) of the
    loop a bundle runs: with the default period 1 today's robots (``protocol="robots"``: controller and
    barrier every iteration, rps v2's motor limits, the real first observation), whatever protocol the
    policy trained in; another period keeps the policy's settings but that (a command held that long lets
    robots collide on the testbed); ``None`` keeps the policy's settings as they are."""
    if control_period is None:
        return {}
    return {"protocol": "robots"} if control_period == 1 else {"control_period": control_period}


def drive_in_reachable(poses) -> np.ndarray:
    """Whether the Robotarium's drive-in can reach ``poses`` ``[..., N, 3]`` (bool ``[...]``): the points
    :data:`DRIVE_IN_PROJECTION` ahead of every two robots at least :data:`DRIVE_IN_SPACING` apart."""
    poses = np.asarray(poses, np.float64)
    ahead = poses[..., :2] + DRIVE_IN_PROJECTION * np.stack([np.cos(poses[..., 2]), np.sin(poses[..., 2])], -1)
    distances = np.linalg.norm(ahead[..., :, None, :] - ahead[..., None, :, :], axis=-1)
    distances += np.where(np.eye(poses.shape[-2], dtype=bool), np.inf, 0.0)
    return np.all(distances >= DRIVE_IN_SPACING, axis=(-2, -1))


def initial_states(env, episodes: int, seed: int = 0):
    """``(poses [E, N, 3] float64, {field: [E, ...]}, state class)``: ``env.reset`` with keys split from
    ``seed``, keeping the starts the Robotarium's drive-in can reach (:func:`drive_in_reachable`) in key order;
    where fewer than ``episodes`` are left, the next keys come from ``fold_in(seed key, round)``."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    reset = jax.jit(jax.vmap(env.reset))      # one program, not one dispatch per op
    root = jax.random.PRNGKey(seed)
    kept, count = [], 0
    for draw in range(MAX_DRAWS):
        keys = jax.random.split(root if draw == 0 else jax.random.fold_in(root, draw), episodes)
        _, states = reset(keys)
        reachable = drive_in_reachable(np.asarray(states.poses))
        kept.append(jax.tree_util.tree_map(lambda x: np.asarray(x)[reachable], states))
        count += int(reachable.sum())
        if count >= episodes:
            break
    else:
        raise ValueError(f"{env.name}: fewer than {episodes} of {MAX_DRAWS * episodes} start states put every two "
                         f"robots' points {DRIVE_IN_PROJECTION} m ahead at least {DRIVE_IN_SPACING} m apart, "
                         "which the Robotarium's drive-in needs to reach them")
    states = jax.tree_util.tree_map(lambda *x: np.concatenate(x)[:episodes], *kept)
    fields = {f.name: np.asarray(getattr(states.scenario, f.name)) for f in dataclasses.fields(states.scenario)}
    return np.asarray(states.poses, np.float64), fields, type(states.scenario)


def write_bundle(env, policy_dir, out, algo: str, episodes: int = 2, seed: int = 0, force: bool = False) -> dict:
    """Write the bundle for ``env`` (a :class:`marbler_jax.env.MarblerEnv`) and the numpy policy in
    ``policy_dir`` to the folder ``out``; returns the bundle config. ``out`` is replaced only if it is
    empty or an earlier bundle (or ``force``; see :func:`check_target`)."""
    check_target(out, CONFIG_FILE, "bundle", force)
    scenario = env.scenario
    module = type(scenario).__module__
    stem = module.rsplit(".", 1)[-1]
    if stem in CORE_MODULES.values():
        raise ValueError(f"scenario module name {stem!r} clashes with a bundled module; rename it")
    names = dict(CORE_MODULES, **{module: stem})
    poses, fields, state_cls = initial_states(env, episodes, seed)
    config = dict(
        format=BUNDLE_FORMAT, scenario=env.name, algo=algo, module=stem, scenario_class=type(scenario).__name__,
        state_class=state_cls.__name__, state_fields=sorted(fields), config=dataclasses.asdict(env.config),
        episodes=episodes, seed=seed, num_agents=env.num_agents,
    )
    with building(out) as tmp:
        for flat, source in flatten_modules(names).items():
            (tmp / f"{flat}.py").write_text(source)
        for entry in Path(policy_dir).iterdir():
            if entry.is_dir() or (tmp / entry.name).exists():
                raise ValueError(f"policy folder entry {entry.name} cannot go into a flat bundle")
            shutil.copyfile(entry, tmp / entry.name)
        np.save(tmp / "initial_poses.npy", poses, allow_pickle=False)
        for name, value in fields.items():
            np.save(tmp / f"initial_{name}.npy", value, allow_pickle=False)
        np.save(tmp / CONFIG_FILE, np.array(json.dumps(config, indent=1)), allow_pickle=False)
        check_bundle_folder(tmp)
    return config


def check_target(out, marker: str, what: str, force: bool = False) -> None:
    """Refuse to replace ``out`` unless it is absent, empty, or an earlier output of ours (holds
    ``marker``); ``force`` replaces any folder. A file is never replaced."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out} is a file, not a folder; give a folder for the {what}")
    if out.is_dir() and not force and any(out.iterdir()) and not (out / marker).exists():
        raise ValueError(f"{out} holds files marbler-jax did not write (no {marker}); choose a new or empty folder "
                         f"for the {what}, or pass --force to replace that folder")


def staging_folder(out) -> Path:
    """A new, empty folder beside ``out`` to build ``out`` in, named as no user names a folder
    (``.<name>.new-<random>``): nothing of the user's is ever in the way or removed with it."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.new-", dir=out.parent))


@contextlib.contextmanager
def building(out):
    """``with building(out) as tmp:`` fill ``tmp`` (:func:`staging_folder`); at the end it replaces ``out``
    (:func:`replace_folder`), or, if the block fails, it is removed and ``out`` is left as it was."""
    tmp = staging_folder(out)
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    replace_folder(tmp, out)


def replace_folder(tmp, out) -> None:
    """Move the finished folder ``tmp`` to ``out``, replacing any old ``out`` (never half-written); the old one
    is moved aside under a name of its own (``.<name>.old-<random>``) and removed."""
    tmp, out = Path(tmp), Path(out)
    if out.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
        os.replace(out, old)            # onto the empty folder just made
        os.replace(tmp, out)
        shutil.rmtree(old)
    else:
        os.replace(tmp, out)


def folder_size(folder) -> int:
    """Total bytes of the files in a flat folder (a bundle or a policy export)."""
    return sum(p.stat().st_size for p in Path(folder).iterdir())


__all__ = ["write_bundle", "initial_states", "folder_size", "replace_folder", "check_target", "staging_folder",
           "building", "deployment_settings"]
