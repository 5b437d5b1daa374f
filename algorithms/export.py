"""Export a run's trained agents to a numpy policy folder (see :mod:`marbler_jax.numpy_policy`).

``export_policy(run, out)`` takes the run's best checkpoint (or ``params.npz`` with
``checkpoint="final"``), keeps only what acting needs (the algorithm's ``policy_tensors``: the actor of
IPPO/MAPPO, the agent network of VDN/QMIX/QMIX_NS; critics and mixers are training-only), and writes one ``float32`` ``.npy`` per
tensor plus ``policy_spec.npy``. The folder is written under a temporary name and renamed into
place, so an interrupted export never leaves a half-written policy.
"""
from __future__ import annotations

import json

import numpy as np

from . import registry
from .run import DEFAULT_CHECKPOINT, Run
from marbler_jax.control_loop import ROBOTS_CONTROL_PERIOD
from marbler_jax.deploy.bundle import building, check_target, deployment_settings, write_bundle
from marbler_jax.numpy_policy import FORMAT, SPEC_FILE, NumpyPolicy, file_sha256


def export_params(algo: str, cfg, params, env, out, extra: dict | None = None, force: bool = False) -> NumpyPolicy:
    """Write the policy folder ``out`` for one seed's ``params`` (``extra``: more spec fields);
    returns the numpy policy. ``out`` is replaced only if it is empty or an earlier policy export (or
    ``force``)."""
    check_target(out, SPEC_FILE, "policy", force)
    fields, tensors = registry.get(algo).policy_tensors(cfg, params)
    spec = dict(format=FORMAT, algo=algo, scenario=env.name, num_agents=env.num_agents, obs_dim=env.obs_dim,
                num_actions=env.num_actions, **fields, **(extra or {}))
    return write_policy(spec, tensors, out, force)


def write_policy(spec: dict, tensors: dict, out, force: bool = False) -> NumpyPolicy:
    """Write ``spec`` (without ``tensors`` / ``sha256``, which this adds) and ``tensors`` as the policy
    folder ``out``, checked by loading before anything is replaced; returns the numpy policy. The folder is
    written under a temporary name and renamed into place."""
    check_target(out, SPEC_FILE, "policy", force)
    spec = dict(spec, tensors={name: f"{name.replace('.', '_')}.npy" for name in tensors})
    policy = NumpyPolicy(spec, tensors)
    with building(out) as tmp:
        for name, array in tensors.items():
            np.save(tmp / spec["tensors"][name], array, allow_pickle=False)
        spec["sha256"] = {file: file_sha256(tmp / file) for file in spec["tensors"].values()}
        np.save(tmp / SPEC_FILE, np.array(json.dumps(spec, indent=1)), allow_pickle=False)
    return policy


def export_policy(run, out, seed_index: int = 0, checkpoint: str = DEFAULT_CHECKPOINT, bundle=None, episodes: int = 2,
                  bundle_seed: int = 0, control_period: int | None = ROBOTS_CONTROL_PERIOD, force: bool = False) -> dict:
    """Export seed ``seed_index`` of run folder ``run`` to the policy folder ``out``; returns the spec.

    With ``bundle`` (a folder), also write the Robotarium submission bundle there
    (:func:`marbler_jax.deploy.bundle.write_bundle`) with ``episodes`` start states drawn from
    ``bundle_seed``, in the loop :func:`~marbler_jax.deploy.bundle.deployment_settings` gives for
    ``control_period``: 1 (default) today's robots, whatever protocol the policy trained in (a command
    held for 15 iterations is what lets robots collide on the real testbed); ``None`` deploys the
    training settings as they are. ``out`` and ``bundle`` are replaced only when empty or
    earlier outputs of ``export`` (``force`` replaces any folder; a file never)."""
    opened = Run.open(run)
    check_target(out, SPEC_FILE, "policy", force)
    if bundle is not None:
        from marbler_jax.deploy.main import CONFIG_FILE

        check_target(bundle, CONFIG_FILE, "bundle", force)
    config = opened.config
    if control_period is not None and (isinstance(control_period, bool) or not isinstance(control_period, int)
                                       or control_period < 1):
        raise ValueError(f"control_period must be an integer >= 1 (or None for the training period), "
                         f"got {control_period!r}")
    env = opened.env()
    one = opened.seed_params(seed_index, checkpoint)
    extra = dict(env=config["env"], checkpoint=checkpoint, seed_index=seed_index)
    spec = export_params(opened.algo, opened.algorithm_config(), one, env, out, extra, force=force).spec
    if bundle is not None:
        deployed = opened.env(**deployment_settings(control_period))
        write_bundle(deployed, out, bundle, opened.algo, episodes=episodes, seed=bundle_seed, force=force)
    return spec


__all__ = ["export_policy", "export_params", "write_policy"]
