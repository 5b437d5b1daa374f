"""Write ``tests/data/epymarl_forward.npz``: MARBLER's own torch agents on observations MARBLER recorded.

For each of the paper's 16 models, the observation sequence of one MARBLER episode of its scenario (random
actions, the first ``--steps`` steps, starting from MARBLER's all-zero reset observation), and what MARBLER's
``RNNAgent`` / ``RNNNSAgent`` (``robotarium_gym/utilities``) compute on it the way MARBLER's ``main.py`` runs
them: the agent-ID one-hot appended when ``obs_agent_id``, the hidden state carried from step to step, the
greedy action the argmax. ``tests/test_epymarl.py`` checks marbler-jax's import against it. Made once:

    .marbler-venv/bin/python scripts/marbler_oracle.py record --scenario PredatorCapturePrey --out obs-pcp.npz
    ... (the same for Warehouse, MaterialTransport, ArcticTransport)
    TORCH_PYTHON scripts/make_epymarl_fixture.py --obs PredatorCapturePrey=obs-pcp.npz ... \\
        --out tests/data/epymarl_forward.npz

``TORCH_PYTHON`` is a Python with torch and numpy (nothing else of MARBLER's stack: ``gym``, which
``robotarium_gym/__init__.py`` imports to register its envs, is a stand-in here).
"""
from __future__ import annotations

import argparse
import json
import sys
import types
from pathlib import Path

import numpy as np
import torch

MARBLER = Path(__file__).resolve().parents[2] / "shared" / "marbler"
ALGOS = ("mappo", "qmix", "qmix_ns", "vdn")
NUM_ACTIONS = {"MaterialTransport": 20}


def _marbler_agents():
    gym = types.ModuleType("gym")
    gym.envs = types.ModuleType("gym.envs")
    registration = types.ModuleType("gym.envs.registration")
    registration.register = lambda *args, **kwargs: None
    sys.modules.update({"gym": gym, "gym.envs": gym.envs, "gym.envs.registration": registration})
    sys.path.insert(0, str(MARBLER))
    from robotarium_gym.utilities.rnn_agent import RNNAgent
    from robotarium_gym.utilities.rnn_ns_agent import RNNNSAgent

    return RNNAgent, RNNNSAgent


def forward(scenario: str, algo: str, obs: np.ndarray) -> np.ndarray:
    """Outputs ``[T, N, A]`` of MARBLER's torch agent on ``obs [T, N, D]`` (hidden state carried)."""
    rnn_agent, rnn_ns_agent = _marbler_agents()
    folder = MARBLER / "robotarium_gym" / "scenarios" / scenario / "models"
    config = json.loads((folder / f"{algo}.json").read_text())
    n = obs.shape[1]
    config.update(n_actions=NUM_ACTIONS.get(scenario, 5), n_agents=n)
    args = types.SimpleNamespace(**config)
    weights = torch.load(folder / f"{algo}.th", map_location="cpu")
    input_dim = weights[next(iter(weights))].shape[1]
    ns = config["agent"] == "rnn_ns"
    model = (rnn_ns_agent if ns else rnn_agent)(input_dim, args)
    model.load_state_dict(weights)
    hidden = torch.zeros((n, config["hidden_dim"]))
    outputs = []
    with torch.no_grad():
        for step_obs in obs:
            x = np.concatenate([step_obs, np.eye(n)], axis=1) if config["obs_agent_id"] else step_obs
            if ns:           # main.py passes ``hs.T``: every axis reversed
                hidden = hidden.permute(*reversed(range(hidden.dim())))
            q, hidden = model(torch.tensor(x, dtype=torch.float32), hidden)
            outputs.append(q.numpy())
    return np.stack(outputs).astype(np.float32)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--obs", nargs="+", required=True, metavar="SCENARIO=FILE",
                        help="observations recorded by marbler_oracle.py record, per MARBLER scenario")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    arrays = {}
    for item in args.obs:
        scenario, file = item.split("=", 1)
        obs = np.load(file)["episode0"].astype(np.float32)
        arrays[f"{scenario}/obs"] = obs
        for algo in ALGOS:
            values = forward(scenario, algo, obs)
            arrays[f"{scenario}/{algo}/values"] = values
            arrays[f"{scenario}/{algo}/actions"] = values.argmax(-1).astype(np.int32)
    np.savez_compressed(args.out, **arrays)
    print(f"written {args.out}: {len(arrays)} arrays")


if __name__ == "__main__":
    main()
